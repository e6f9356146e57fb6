//! Frames: decoding never panics; a decoded message re-encodes to a frame that decodes to the
//! same message; messages built from arbitrary fields either refuse to encode or round-trip.
#![no_main]

use forja_protocol::frame::{
    Action, AxisPosition, ClientMessage, ControllerMessage, Decimal, FRAME_LEN, Frame, Positions,
    Progress, is_frame,
};
use libfuzzer_sys::arbitrary::{Result, Unstructured};
use libfuzzer_sys::fuzz_target;

fn check_client(msg: &ClientMessage<'_>) {
    let mut out = [0u8; FRAME_LEN];
    if msg.encode(&mut out).is_ok() {
        assert!(is_frame(&out));
        let back = ClientMessage::decode(&out).expect("an encoded frame decodes");
        assert_eq!(&back, msg);
        let mut again = [0u8; FRAME_LEN];
        back.encode(&mut again).expect("encodes again");
        assert_eq!(again, out);
    }
}

fn check_controller(msg: &ControllerMessage<'_>) {
    let mut out = [0u8; FRAME_LEN];
    if msg.encode(&mut out).is_ok() {
        assert!(is_frame(&out));
        let back = ControllerMessage::decode(&out).expect("an encoded frame decodes");
        assert_eq!(&back, msg);
        let mut again = [0u8; FRAME_LEN];
        back.encode(&mut again).expect("encodes again");
        assert_eq!(again, out);
    }
}

fn text<'a>(u: &mut Unstructured<'a>) -> Result<&'a str> {
    let len = u.int_in_range(0..=60)?;
    let bytes = u.bytes(len)?;
    Ok(core::str::from_utf8(bytes).unwrap_or("x"))
}

fn client<'a>(u: &mut Unstructured<'a>) -> Result<ClientMessage<'a>> {
    Ok(match u.int_in_range(0..=5)? {
        0 => ClientMessage::SetSetting {
            key: text(u)?,
            value: text(u)?,
        },
        1 => ClientMessage::ReadSetting { key: text(u)? },
        2 => ClientMessage::Jog {
            step: Decimal::new(u.arbitrary()?, u.arbitrary()?),
            axis: u.arbitrary()?,
            count: u.arbitrary()?,
        },
        3 => ClientMessage::Action(match u.int_in_range(0..=6)? {
            0 => Action::HomeAll,
            1 => Action::Home(u.arbitrary()?),
            2 => Action::Reset,
            3 => Action::Stop,
            4 => Action::Rewind,
            5 => Action::Start,
            _ => Action::Pause,
        }),
        4 => ClientMessage::LoadLine {
            index: u.arbitrary()?,
            text: text(u)?,
            total: u.arbitrary()?,
        },
        _ => ClientMessage::Request {
            message_type: u.arbitrary()?,
        },
    })
}

fn controller<'a>(u: &mut Unstructured<'a>) -> Result<ControllerMessage<'a>> {
    Ok(match u.int_in_range(0..=6)? {
        0 => ControllerMessage::Setting {
            key: text(u)?,
            value: text(u)?,
        },
        1 => {
            let mut p = Positions::new();
            for _ in 0..u.int_in_range(0..=4)? {
                let _ = p.push(AxisPosition {
                    axis: u.arbitrary()?,
                    value_tenth_um: u.arbitrary()?,
                });
            }
            ControllerMessage::Positions(p)
        }
        2 => ControllerMessage::Progress(Progress {
            elapsed_s: u.int_in_range(0..=5999)?,
            estimated_s: u.int_in_range(0..=5999)?,
            total_lines: u.int_in_range(0..=9999)?,
            current_line: u.int_in_range(0..=9999)?,
        }),
        3 => ControllerMessage::Confirm { what: text(u)? },
        4 => ControllerMessage::Connected,
        5 => ControllerMessage::KeepAlive {
            counter: u.int_in_range(0..=9_999_999)?,
        },
        _ => ControllerMessage::Error {
            code: u.arbitrary()?,
            detail: text(u)?,
        },
    })
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    match mode % 3 {
        0 => {
            // Raw bytes, and the same bytes forced into frame structure.
            let _ = Frame::new_checked(rest);
            let mut framed = [b'*'; FRAME_LEN];
            for (slot, &b) in framed.iter_mut().zip(rest) {
                *slot = b;
            }
            framed[0] = b'N';
            framed[FRAME_LEN - 1] = b'F';
            for bytes in [rest, &framed[..]] {
                if let Ok(msg) = ClientMessage::decode(bytes) {
                    check_client(&msg);
                }
                if let Ok(msg) = ControllerMessage::decode(bytes) {
                    check_controller(&msg);
                }
            }
        }
        1 => {
            if let Ok(msg) = client(&mut Unstructured::new(rest)) {
                check_client(&msg);
            }
        }
        _ => {
            if let Ok(msg) = controller(&mut Unstructured::new(rest)) {
                check_controller(&msg);
            }
        }
    }
});
