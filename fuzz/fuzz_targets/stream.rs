//! The mixed-link decoder: never panics; gives the same events whatever the chunking; every
//! input byte is accounted for; lines and frames are well formed and decode without panicking.
#![no_main]

use forja_protocol::frame::{ClientMessage, ControllerMessage, FRAME_LEN, is_frame};
use forja_protocol::gcode::{Line, MAX_LINE_LEN};
use forja_protocol::reply::Reply;
use forja_protocol::stream::{Decoder, Event};
use libfuzzer_sys::fuzz_target;

#[derive(Debug, PartialEq, Eq)]
enum Owned {
    Line(Vec<u8>),
    Frame(Vec<u8>),
    Garbage(usize),
    TooLong(usize),
}

fn owned(event: Event<'_>) -> Owned {
    match event {
        Event::Line(bytes) => {
            assert!(!bytes.is_empty() && bytes.len() <= MAX_LINE_LEN);
            assert!(!bytes.iter().any(|&b| b == b'\n' || b == b'\r'));
            let _ = Line::parse(bytes);
            let _ = Reply::parse(bytes);
            Owned::Line(bytes.to_vec())
        }
        Event::Frame(frame) => {
            assert!(is_frame(frame.as_bytes()));
            let _ = ClientMessage::parse(&frame);
            let _ = ControllerMessage::parse(&frame);
            Owned::Frame(frame.as_bytes().to_vec())
        }
        Event::Garbage { skipped, .. } => {
            assert!(skipped > 0);
            Owned::Garbage(skipped)
        }
        Event::TooLong { len } => {
            assert!(len > MAX_LINE_LEN);
            Owned::TooLong(len)
        }
        _ => unreachable!("no other events"),
    }
}

fn run(input: &[u8], sizes: &[u8]) -> Vec<Owned> {
    let mut decoder = Decoder::new();
    let mut events = Vec::new();
    let mut rest = input;
    let mut k = 0;
    while !rest.is_empty() {
        let size = sizes.get(k % sizes.len().max(1)).copied().unwrap_or(255);
        let n = usize::from(size).clamp(1, rest.len());
        k += 1;
        let (chunk, after) = rest.split_at(n);
        rest = after;
        decoder.feed_all(chunk, |e| events.push(owned(e)));
    }
    while let Some(e) = decoder.flush() {
        events.push(owned(e));
    }
    let stats = decoder.stats();
    let count = |f: fn(&Owned) -> bool| events.iter().filter(|e| f(e)).count() as u32;
    assert_eq!(stats.lines, count(|e| matches!(e, Owned::Line(_))));
    assert_eq!(stats.frames, count(|e| matches!(e, Owned::Frame(_))));
    assert_eq!(
        stats.garbage_runs,
        count(|e| matches!(e, Owned::Garbage(_)))
    );
    assert_eq!(stats.too_long, count(|e| matches!(e, Owned::TooLong(_))));
    events
}

fuzz_target!(|data: &[u8]| {
    // The first bytes choose chunk sizes; the rest is the link.
    let split = usize::from(data.first().copied().unwrap_or(0) % 8).min(data.len());
    let (sizes, input) = data.split_at(split);
    let sizes = sizes.get(1..).unwrap_or(&[]);

    let whole = run(input, &[]);
    assert_eq!(run(input, sizes), whole);
    assert_eq!(run(input, &[1]), whole);

    // Every byte is a terminator or in exactly one event.
    let terminators = input.iter().filter(|&&b| b == b'\n' || b == b'\r').count();
    let accounted: usize = whole
        .iter()
        .map(|e| match e {
            Owned::Line(b) => b.len(),
            Owned::Frame(_) => FRAME_LEN,
            Owned::Garbage(n) | Owned::TooLong(n) => *n,
        })
        .sum();
    assert_eq!(accounted + terminators, input.len());
});
