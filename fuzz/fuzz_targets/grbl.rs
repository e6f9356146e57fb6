//! The grbl dialect: a `$` line never panics the parser, and what parses as a setting
//! re-encodes to the `$<n>=<value>` line that parses to the same; a status report built from
//! any numbers encodes to a `<…>` line whose fields read back.
#![no_main]

use forja_protocol::grbl::{Command, Message, State, Status, StatusText};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(Command::Set { number, value }) = Command::parse(data) {
        let mut out = [0u8; 64];
        let len = Message::Setting { number, value }
            .encode(&mut out)
            .expect("a setting encodes");
        let line = &out[..len - 1];
        assert_eq!(
            Command::parse(line),
            Ok(Command::Set { number, value }),
            "{line:?}"
        );
    }
    let word = |i: usize| {
        let bytes = data.get(i * 8..i * 8 + 8).unwrap_or(&[0; 8]);
        i64::from_le_bytes(bytes.try_into().unwrap_or([0; 8]))
    };
    let machine = [word(0), word(1), word(2)];
    let offset = [word(3), word(4), word(5)];
    let report = Status {
        state: State::Hold(data.first().copied().unwrap_or(0)),
        machine: &machine,
        offset: &offset,
        work_position: data.get(1).is_some_and(|b| b & 1 != 0),
        send_offset: data.get(1).is_some_and(|b| b & 2 != 0),
        buffer: Some((word(6) as u16, word(7) as u16)),
        line: Some(word(6) as u32),
        feed_mm_min: word(7) as u32,
        spindle_rpm: None,
        overrides: Some([100, 100, 100]),
        pins: b"XP",
        accessories: b"",
    };
    let mut out = [0u8; 256];
    let len = report.encode(&mut out).expect("a report encodes");
    let text = StatusText::parse(&out[..len - 1]).expect("a report reads back");
    assert!(text.field(b"Bf").is_some());
});
