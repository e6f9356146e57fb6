//! Bad input of every kind always gets an error reply, and leaves the machine where it was and
//! the stored program as it was: garbage bytes, over-long lines, wrong line numbers and
//! checksums, frames with broken mirrors or unknown contents, program lines out of order or
//! not G-code, and a full program store.

use forja_protocol::frame::{Action, ClientMessage, ControllerMessage, FRAME_LEN};
use forja_protocol::gcode::checksum;
use forja_sim::board::BoardConfig;
use forja_sim_hal::link::MemoryLink;
use forja_tests::{Replies, Rig, frame};

/// A numbered line as a host writes it, with its `\n`.
fn numbered(n: i64, body: &str) -> Vec<u8> {
    let head = format!("N{n} {body}");
    format!("{head}*{}\n", checksum(head.as_bytes())).into_bytes()
}

/// A frame with its two mirrored keywords given.
fn mirrored(ty: &str, head: &str, tail: &str) -> Vec<u8> {
    let mut f = format!("N{ty}{head}");
    f.push_str(&"*".repeat(FRAME_LEN - 1 - f.len() - tail.len()));
    f.push_str(tail);
    f.push_str("F\n");
    f.into_bytes()
}

#[test]
fn bad_input_gets_an_error_reply_and_changes_nothing() {
    // A store of three lines, to fill it.
    let mut rig = Rig::new(
        "default",
        BoardConfig {
            program_lines: 3,
            ..BoardConfig::default()
        },
    );
    let (link, mut host) = MemoryLink::pair();
    rig.board.add_port(link, false);
    let mut replies = Replies::default();
    let program = ["G91", "G1 X1 F600", "G90"];
    for (i, text) in program.iter().enumerate() {
        host.send(&frame(&ClientMessage::LoadLine {
            index: i as u16 + 1,
            text,
            total: 3,
        }));
    }
    host.send(&numbered(-1, "M110 N-1"));
    rig.exchange(&mut host, &mut replies, 20);
    assert_eq!(
        replies.lines,
        [
            "start",
            "N53Confirm:Gcode-load*******************************F",
            "ok"
        ]
    );
    let position = rig.machine.positions_mm();
    let stored = |rig: &mut Rig| -> Vec<Option<String>> {
        (1..=4).map(|i| rig.board.program_line(i)).collect()
    };
    let program_before = stored(&mut rig);

    // Each case: the bytes, and the replies they must get.
    let cases: Vec<(&str, Vec<u8>, Vec<&str>)> = vec![
        (
            "garbage",
            b"\x00\x01\xfe junk \x07\x1b[2J\n".to_vec(),
            vec![
                "N56Error:E21 frame**********************************F",
                "rs 0",
                "ok",
            ],
        ),
        (
            "over-long numbered line",
            numbered(0, &format!("G1 X5 ({})", "x".repeat(300))),
            vec!["rs 0", "ok"],
        ),
        (
            "wrong line number",
            numbered(7, "G1 X5"),
            vec!["rs 0", "ok"],
        ),
        (
            "wrong checksum",
            b"N0 G1 X5*99\n".to_vec(),
            vec!["rs 0", "ok"],
        ),
        (
            "number without checksum",
            b"N0 G1 X5\n".to_vec(),
            vec!["rs 0", "ok"],
        ),
        (
            // The host numbers its lines: a lost line end is the likely cause.
            "over-long unnumbered line",
            format!("G1 X5 ({})\n", "y".repeat(400)).into_bytes(),
            vec!["rs 0", "ok"],
        ),
        (
            "unnumbered line that is not G-code",
            b"G1 X=5\n".to_vec(),
            vec!["echo:E9 no-value", "ok"],
        ),
        (
            "broken action mirror",
            mirrored("02", "Start", "Stopp"),
            vec!["N56Error:E23 frame-mirror***************************F"],
        ),
        (
            "broken request mirror",
            mirrored("04", "51", "52"),
            vec!["N56Error:E23 frame-mirror***************************F"],
        ),
        (
            "unknown action",
            mirrored("02", "Jump", "Jump"),
            vec!["N56Error:E25 frame-action***************************F"],
        ),
        (
            "unknown frame type",
            mirrored("09", "x", "x"),
            vec!["N56Error:E22 frame-type*****************************F"],
        ),
        (
            "jog on an axis the machine lacks",
            frame(&ClientMessage::Jog {
                step: forja_protocol::gcode::Decimal::new(1, 0),
                axis: b'Q',
                count: 5,
            }),
            vec!["N56Error:E127 unknown-axis Q************************F"],
        ),
        (
            "program line out of order",
            frame(&ClientMessage::LoadLine {
                index: 3,
                text: "G1 X9",
                total: 3,
            }),
            vec!["N56Error:E170 line-order 0003 expected 0004*********F"],
        ),
        (
            "program line of another program",
            frame(&ClientMessage::LoadLine {
                index: 4,
                text: "G1 X9",
                total: 4,
            }),
            vec!["N56Error:E193 load-total 0004***********************F"],
        ),
        (
            "unknown setting",
            frame(&ClientMessage::SetSetting {
                key: "q.max",
                value: "1",
            }),
            vec!["N56Error:E190 unknown-setting q.max*****************F"],
        ),
    ];
    for (what, bytes, expected) in cases {
        replies.clear();
        host.send(&bytes);
        rig.exchange(&mut host, &mut replies, 30);
        assert_eq!(replies.lines, expected, "{what}");
        assert_eq!(
            rig.machine.positions_mm(),
            position,
            "{what} moved the machine"
        );
        assert_eq!(
            stored(&mut rig),
            program_before,
            "{what} changed the program"
        );
    }

    // A full store: a new program of four lines is refused at its line 1 (no room), the old
    // program kept whole; its later lines are another program's (issue 11, item 7).
    replies.clear();
    let longer = ["G91", "G1 Y2 F600", "G90", "G1 Y3"];
    for (i, text) in longer.iter().enumerate() {
        host.send(&frame(&ClientMessage::LoadLine {
            index: i as u16 + 1,
            text,
            total: 4,
        }));
    }
    rig.exchange(&mut host, &mut replies, 30);
    assert_eq!(
        replies.error_codes(),
        [171, 193, 193, 193],
        "{:?}",
        replies.lines
    );
    assert!(
        !replies
            .frames()
            .iter()
            .any(|m| matches!(m, ControllerMessage::Confirm { .. }))
    );
    let stored_now = stored(&mut rig);
    assert_eq!(stored_now, program_before);
    // A program line that is not G-code is refused before anything is cleared.
    replies.clear();
    host.send(&frame(&ClientMessage::LoadLine {
        index: 1,
        text: "G1 X#",
        total: 1,
    }));
    rig.exchange(&mut host, &mut replies, 30);
    assert_eq!(replies.error_codes(), [9]);
    assert_eq!(stored(&mut rig), stored_now);

    // Nothing moved through all this; the link still works, and the stored lines run.
    assert_eq!(rig.machine.positions_mm(), position);
    replies.clear();
    host.send(&numbered(0, "G1 X10 F3000"));
    rig.exchange(&mut host, &mut replies, 10);
    rig.settle(&mut host, &mut replies);
    host.send(&frame(&ClientMessage::Action(Action::Start)));
    rig.exchange(&mut host, &mut replies, 50);
    rig.settle(&mut host, &mut replies);
    assert_eq!(replies.lines, ["ok"]);
    assert_eq!(
        rig.machine.positions_mm(),
        [position[0] + 11.0, position[1], position[2], position[3]]
    );
}
