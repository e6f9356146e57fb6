//! Property tests: round trips of every message type, single-byte corruption of checksummed
//! lines, and chunking invariance of the stream decoder.

use forja_protocol::frame::{
    Action, AxisPosition, ClientMessage, ControllerMessage, FRAME_LEN, MAX_LOAD_LINES,
    MAX_POSITION_TENTH_UM, MAX_PROGRESS_LINES, MAX_PROGRESS_S, Positions, Progress, is_frame,
};
use forja_protocol::gcode::{Decimal, EncodeError, Line, MAX_LINE_LEN, Word};
use forja_protocol::reply::{Axes, Counts, Heat, KeyValues, Reply};
use forja_protocol::stream::{Decoder, Event};
use proptest::prelude::*;

/// Printable ASCII without `*`: what a frame's text fields carry.
const TEXT: &str = "[ -)+-~]";
/// A setting key.
const KEY: &str = "[A-Za-z0-9_.:/-]{1,12}";

fn decimal() -> impl Strategy<Value = Decimal> {
    prop_oneof![
        (-100_000i64..100_000, 0u8..5).prop_map(|(m, s)| Decimal::new(m, s)),
        ((-i64::MAX)..=i64::MAX, 0u8..=18).prop_map(|(m, s)| Decimal::new(m, s)),
    ]
}

fn letter() -> impl Strategy<Value = u8> {
    b'A'..=b'Z'
}

fn command() -> impl Strategy<Value = Word> {
    (prop::sample::select(&b"GMT"[..]), 0i64..1000)
        .prop_map(|(l, n)| Word::new(l, Decimal::from_integer(n)))
}

/// The parts of a line: number, words, text.
fn line_parts() -> impl Strategy<Value = (Option<u32>, Vec<Word>, Option<String>)> {
    let words = (
        command(),
        prop::collection::vec(
            (letter(), decimal()).prop_map(|(l, v)| Word::new(l, v)),
            0..8,
        ),
    )
        .prop_map(|(first, rest)| {
            let mut words = vec![first];
            words.extend(rest);
            words
        });
    let text_line = (
        prop::sample::select(&[23i64, 28, 29, 30, 117][..]),
        "[!-)+-:<-~]([ -)+-:<-~]{0,30}[!-)+-:<-~])?",
    )
        .prop_map(|(m, t)| (vec![Word::new(b'M', Decimal::from_integer(m))], Some(t)));
    (
        prop::option::of(any::<u32>()),
        prop_oneof![
            4 => words.prop_map(|w| (w, None)),
            1 => text_line,
            1 => Just((vec![], None)),
        ],
    )
        .prop_map(|(n, (w, t))| (n, w, t))
}

fn encode_line(line: &Line<'_>) -> Result<Vec<u8>, EncodeError> {
    let mut out = [0u8; 2 * MAX_LINE_LEN];
    let n = line.encode(&mut out)?;
    Ok(out[..n].to_vec())
}

fn text(max: usize) -> impl Strategy<Value = String> {
    proptest::string::string_regex(&format!("{TEXT}{{0,{max}}}")).expect("regex")
}

fn key() -> impl Strategy<Value = String> {
    proptest::string::string_regex(KEY).expect("regex")
}

fn action() -> impl Strategy<Value = Action> {
    prop_oneof![
        Just(Action::HomeAll),
        letter().prop_map(Action::Home),
        Just(Action::Reset),
        Just(Action::Stop),
        Just(Action::Rewind),
        Just(Action::Start),
        Just(Action::Pause),
    ]
}

/// The owned fields of a client message.
#[derive(Clone, Debug)]
enum ClientSpec {
    Set(String, String),
    Read(String),
    Jog(Decimal, u8, i32),
    Action(Action),
    Load(u16, String, u16),
    Request(u8),
}

fn client_spec() -> impl Strategy<Value = ClientSpec> {
    prop_oneof![
        (key(), text(30)).prop_map(|(k, v)| ClientSpec::Set(k, v)),
        key().prop_map(ClientSpec::Read),
        (
            (0i64..10_000_000_000, 0u8..10).prop_map(|(m, s)| Decimal::new(m, s)),
            letter(),
            any::<i32>()
        )
            .prop_map(|(s, a, c)| ClientSpec::Jog(s, a, c)),
        action().prop_map(ClientSpec::Action),
        (1..=MAX_LOAD_LINES)
            .prop_flat_map(|total| (1..=total, text(39), Just(total)))
            .prop_map(|(i, t, n)| ClientSpec::Load(i, t, n)),
        (0u8..=99).prop_map(ClientSpec::Request),
    ]
}

fn client_message(spec: &ClientSpec) -> ClientMessage<'_> {
    match spec {
        ClientSpec::Set(key, value) => ClientMessage::SetSetting { key, value },
        ClientSpec::Read(key) => ClientMessage::ReadSetting { key },
        ClientSpec::Jog(step, axis, count) => ClientMessage::Jog {
            step: *step,
            axis: *axis,
            count: *count,
        },
        ClientSpec::Action(a) => ClientMessage::Action(*a),
        ClientSpec::Load(index, text, total) => ClientMessage::LoadLine {
            index: *index,
            text,
            total: *total,
        },
        ClientSpec::Request(t) => ClientMessage::Request { message_type: *t },
    }
}

/// The owned fields of a controller message.
#[derive(Clone, Debug)]
enum ControllerSpec {
    Setting(String, String),
    Positions(Vec<(u8, i32)>),
    Progress(Progress),
    Confirm(String),
    Connected,
    KeepAlive(u32),
    Error(u16, String),
}

fn controller_spec() -> impl Strategy<Value = ControllerSpec> {
    let position = (letter(), -MAX_POSITION_TENTH_UM..=MAX_POSITION_TENTH_UM);
    prop_oneof![
        (key(), text(30)).prop_map(|(k, v)| ControllerSpec::Setting(k, v)),
        prop::collection::vec(position, 0..=4).prop_map(ControllerSpec::Positions),
        (
            0..=MAX_PROGRESS_S,
            0..=MAX_PROGRESS_S,
            0..=MAX_PROGRESS_LINES,
            0..=MAX_PROGRESS_LINES
        )
            .prop_map(|(e, s, t, c)| ControllerSpec::Progress(Progress {
                elapsed_s: e,
                estimated_s: s,
                total_lines: t,
                current_line: c,
            })),
        text(41).prop_map(ControllerSpec::Confirm),
        Just(ControllerSpec::Connected),
        (0u32..10_000_000).prop_map(ControllerSpec::KeepAlive),
        (any::<u16>(), text(36)).prop_map(|(c, d)| ControllerSpec::Error(c, d)),
    ]
}

fn controller_message(spec: &ControllerSpec) -> ControllerMessage<'_> {
    match spec {
        ControllerSpec::Setting(key, value) => ControllerMessage::Setting { key, value },
        ControllerSpec::Positions(axes) => {
            let mut p = Positions::new();
            for &(axis, value_tenth_um) in axes {
                p.push(AxisPosition {
                    axis,
                    value_tenth_um,
                })
                .expect("at most four");
            }
            ControllerMessage::Positions(p)
        }
        ControllerSpec::Progress(p) => ControllerMessage::Progress(*p),
        ControllerSpec::Confirm(what) => ControllerMessage::Confirm { what },
        ControllerSpec::Connected => ControllerMessage::Connected,
        ControllerSpec::KeepAlive(counter) => ControllerMessage::KeepAlive { counter: *counter },
        ControllerSpec::Error(code, detail) => ControllerMessage::Error {
            code: *code,
            detail,
        },
    }
}

/// The owned fields of a reply.
#[derive(Clone, Debug)]
enum ReplySpec {
    Start,
    Ok,
    OkWith(String),
    Resend(u32),
    Fault(u16, String),
    Refused(u16, String),
    Unknown(String),
    Busy,
    Echo(String),
    Notice(u16, String),
    Debug(String),
    Temperatures(Option<Heat>, Option<Heat>, bool),
    Position(Vec<(u8, Decimal)>, Vec<(u8, i32)>),
    Firmware(Vec<(String, String)>),
    Capability(String, bool),
}

fn reply_spec() -> impl Strategy<Value = ReplySpec> {
    let printable = || proptest::string::string_regex("[ -~]{0,40}").expect("regex");
    let pair = (
        "[A-Z0-9_]{1,10}",
        proptest::string::string_regex("[!-~]{0,10}").expect("regex"),
    );
    prop_oneof![
        Just(ReplySpec::Start),
        Just(ReplySpec::Ok),
        printable().prop_map(ReplySpec::OkWith),
        any::<u32>().prop_map(ReplySpec::Resend),
        (any::<u16>(), printable()).prop_map(|(c, t)| ReplySpec::Fault(c, t)),
        (1..=u16::MAX, printable()).prop_map(|(c, t)| ReplySpec::Refused(c, t)),
        printable().prop_map(ReplySpec::Unknown),
        Just(ReplySpec::Busy),
        printable().prop_map(ReplySpec::Echo),
        (1..=u16::MAX, printable()).prop_map(|(c, t)| ReplySpec::Notice(c, t)),
        printable().prop_map(ReplySpec::Debug),
        (heat(), heat(), any::<bool>())
            .prop_filter("a heater", |(t, b, _)| t.is_some() || b.is_some())
            .prop_map(|(t, b, ok)| ReplySpec::Temperatures(t, b, ok)),
        (
            prop::collection::vec((letter(), decimal()), 1..=8),
            prop::collection::vec((letter(), any::<i32>()), 0..=8)
        )
            .prop_map(|(axes, counts)| ReplySpec::Position(axes, counts)),
        prop::collection::vec(pair, 0..5).prop_map(|mut pairs| {
            pairs.insert(0, ("FIRMWARE_NAME".into(), "Forja".into()));
            ReplySpec::Firmware(pairs)
        }),
        ("[A-Z0-9_]{1,20}", any::<bool>()).prop_map(|(n, e)| ReplySpec::Capability(n, e)),
    ]
}

fn heat() -> impl Strategy<Value = Option<Heat>> {
    prop::option::of(
        (decimal(), decimal(), 0u8..=127).prop_map(|(current, target, power)| Heat {
            current,
            target,
            power,
        }),
    )
}

fn with_reply<R>(spec: &ReplySpec, f: impl FnOnce(Reply<'_>) -> R) -> R {
    match spec {
        ReplySpec::Start => f(Reply::Start),
        ReplySpec::Ok => f(Reply::Ok),
        ReplySpec::OkWith(t) => f(Reply::OkWith(t)),
        ReplySpec::Resend(n) => f(Reply::Resend(*n)),
        ReplySpec::Fault(code, text) => f(Reply::Fault { code: *code, text }),
        ReplySpec::Refused(code, text) => f(Reply::Refused { code: *code, text }),
        ReplySpec::Unknown(t) => f(Reply::Unknown(t)),
        ReplySpec::Busy => f(Reply::Busy),
        ReplySpec::Echo(t) => f(Reply::Echo(t)),
        ReplySpec::Notice(code, text) => f(Reply::Notice { code: *code, text }),
        ReplySpec::Debug(t) => f(Reply::Debug(t)),
        ReplySpec::Temperatures(hot_end, bed, ok) => f(Reply::Temperatures {
            hot_end: *hot_end,
            bed: *bed,
            ok: *ok,
        }),
        ReplySpec::Position(axes, counts) => f(Reply::Position {
            axes: axes.iter().map(|&(l, v)| Word::new(l, v)).collect::<Axes>(),
            counts: counts.iter().copied().collect::<Counts>(),
        }),
        ReplySpec::Firmware(pairs) => {
            let pairs: Vec<(&str, &str)> = pairs
                .iter()
                .map(|(k, v)| (k.as_str(), v.as_str()))
                .collect();
            f(Reply::Firmware(KeyValues::Pairs(&pairs)))
        }
        ReplySpec::Capability(name, enabled) => f(Reply::Capability {
            name,
            enabled: *enabled,
        }),
    }
}

/// An owned copy of an event.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Owned {
    Line(Vec<u8>),
    Frame(Vec<u8>),
    Garbage(usize),
    TooLong(usize),
}

fn run(input: &[u8], sizes: &[usize]) -> Vec<Owned> {
    let mut decoder = Decoder::new();
    let mut events = Vec::new();
    let mut push = |e: Event<'_>| {
        events.push(match e {
            Event::Line(b) => Owned::Line(b.to_vec()),
            Event::Frame(f) => Owned::Frame(f.as_bytes().to_vec()),
            Event::Garbage { skipped, .. } => Owned::Garbage(skipped),
            Event::TooLong { len } => Owned::TooLong(len),
            _ => unreachable!(),
        })
    };
    let mut rest = input;
    let mut k = 0;
    while !rest.is_empty() {
        let n = sizes[k % sizes.len()].clamp(1, rest.len());
        k += 1;
        let (chunk, after) = rest.split_at(n);
        rest = after;
        decoder.feed_all(chunk, &mut push);
    }
    while let Some(e) = decoder.flush() {
        push(e);
    }
    events
}

/// One piece of a mixed link.
#[derive(Clone, Debug)]
enum Piece {
    Line(Vec<u8>),
    Frame(Vec<u8>),
    Noise(Vec<u8>),
}

fn piece() -> impl Strategy<Value = Piece> {
    prop_oneof![
        3 => line_parts().prop_filter_map("encodable", |(n, w, t)| {
            let line = Line::from_parts(n, &w, t.as_deref().map(str::as_bytes)).ok()?;
            encode_line(&line).ok().filter(|b| !b.is_empty()).map(Piece::Line)
        }),
        3 => client_spec().prop_filter_map("encodable", |spec| {
            let mut out = [0u8; FRAME_LEN];
            client_message(&spec).encode(&mut out).ok()?;
            Some(Piece::Frame(out.to_vec()))
        }),
        1 => prop::collection::vec(any::<u8>(), 0..300).prop_map(Piece::Noise),
    ]
}

const TERMINATORS: [&[u8]; 4] = [b"\n", b"\r", b"\r\n", b""];

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 2000,
        failure_persistence: Some(Box::new(
            proptest::test_runner::FileFailurePersistence::WithSource("regressions"),
        )),
        ..ProptestConfig::default()
    })]

    #[test]
    fn lines_round_trip((number, words, text) in line_parts()) {
        let line = Line::from_parts(number, &words, text.as_deref().map(str::as_bytes));
        let Ok(line) = line else {
            // Only a text command followed by more words is refused.
            prop_assume!(false);
            unreachable!()
        };
        match encode_line(&line) {
            Ok(bytes) => {
                let parsed = Line::parse(&bytes).expect("what is written reads back");
                prop_assert_eq!(&parsed, &line);
                prop_assert_eq!(parsed.checksum(), line.checksum());
                prop_assert_eq!(encode_line(&parsed).expect("again"), bytes);
            }
            Err(e) => prop_assert_eq!(e, EncodeError::TooLong),
        }
    }

    #[test]
    fn any_single_byte_corruption_of_a_checksummed_line_is_caught(
        number in any::<u32>(),
        (_, words, text) in line_parts(),
        at in any::<prop::sample::Index>(),
        byte in any::<u8>(),
    ) {
        let line = Line::from_parts(Some(number), &words, text.as_deref().map(str::as_bytes));
        prop_assume!(line.is_ok());
        let Ok(bytes) = encode_line(&line.expect("checked")) else {
            prop_assume!(false);
            unreachable!()
        };
        let mut damaged = bytes.clone();
        let i = at.index(damaged.len());
        prop_assume!(damaged[i] != byte);
        damaged[i] = byte;
        prop_assert!(Line::parse(&damaged).is_err(), "{:?}", String::from_utf8_lossy(&damaged));
    }

    #[test]
    fn client_frames_round_trip(spec in client_spec()) {
        let msg = client_message(&spec);
        let mut out = [0u8; FRAME_LEN];
        match msg.encode(&mut out) {
            Ok(()) => {
                prop_assert!(is_frame(&out));
                prop_assert_eq!(ClientMessage::decode(&out), Ok(msg));
            }
            // Only a setting too long for one payload is refused.
            Err(e) => prop_assert_eq!(e, EncodeError::TooLong),
        }
    }

    #[test]
    fn controller_frames_round_trip(spec in controller_spec()) {
        let msg = controller_message(&spec);
        let mut out = [0u8; FRAME_LEN];
        match msg.encode(&mut out) {
            Ok(()) => {
                prop_assert!(is_frame(&out));
                prop_assert_eq!(ControllerMessage::decode(&out), Ok(msg));
            }
            Err(e) => {
                // A setting too long, or an uncoded error detail that reads as coded.
                let coded_looking = matches!(&spec, ControllerSpec::Error(0, d) if d.starts_with('E'));
                prop_assert!(e == EncodeError::TooLong || (coded_looking && e == EncodeError::InvalidText), "{:?}", e);
            }
        }
    }

    #[test]
    fn replies_round_trip(spec in reply_spec()) {
        with_reply(&spec, |reply| {
            let mut out = [0u8; 512];
            match reply.encode(&mut out) {
                Ok(n) => {
                    prop_assert_eq!(out[n - 1], b'\n');
                    prop_assert_eq!(Reply::parse(&out[..n]), Ok(reply));
                }
                Err(e) => prop_assert!(
                    matches!(e, EncodeError::InvalidText),
                    "{:?} refused with {:?}", reply, e
                ),
            }
            Ok(())
        })?;
    }

    #[test]
    fn the_stream_gives_the_same_events_for_any_chunking(
        pieces in prop::collection::vec((piece(), prop::sample::select(&TERMINATORS[..])), 0..12),
        sizes in prop::collection::vec(1usize..80, 1..8),
    ) {
        let input: Vec<u8> = pieces
            .iter()
            .flat_map(|(p, t)| {
                let body = match p {
                    Piece::Line(b) | Piece::Frame(b) | Piece::Noise(b) => b.clone(),
                };
                body.into_iter().chain(t.iter().copied())
            })
            .collect();
        let whole = run(&input, &[input.len().max(1)]);
        prop_assert_eq!(&run(&input, &sizes), &whole);
        prop_assert_eq!(&run(&input, &[1]), &whole);
    }

    #[test]
    fn the_stream_gives_back_what_was_sent(
        pieces in prop::collection::vec(
            (piece().prop_filter("no noise", |p| !matches!(p, Piece::Noise(_))),
             prop::sample::select(&TERMINATORS[..3])),
            0..12,
        ),
        sizes in prop::collection::vec(1usize..80, 1..8),
    ) {
        let mut input = Vec::new();
        let mut expected = Vec::new();
        for (p, t) in &pieces {
            match p {
                Piece::Line(b) => expected.push(Owned::Line(b.clone())),
                Piece::Frame(b) => expected.push(Owned::Frame(b.clone())),
                Piece::Noise(_) => unreachable!(),
            }
            let (Piece::Line(b) | Piece::Frame(b) | Piece::Noise(b)) = p;
            input.extend_from_slice(b);
            input.extend_from_slice(t);
        }
        prop_assert_eq!(run(&input, &sizes), expected);
    }

    #[test]
    fn frames_back_to_back_need_no_terminator(
        specs in prop::collection::vec(client_spec(), 1..6),
        sizes in prop::collection::vec(1usize..80, 1..8),
    ) {
        let mut input = Vec::new();
        let mut expected = Vec::new();
        for spec in &specs {
            let mut out = [0u8; FRAME_LEN];
            if client_message(spec).encode(&mut out).is_ok() {
                input.extend_from_slice(&out);
                expected.push(Owned::Frame(out.to_vec()));
            }
        }
        prop_assert_eq!(run(&input, &sizes), expected);
    }

    /// A line parsed in place, over whatever it held, is the line `parse` returns; on an error
    /// it is the same error and the line is left empty.
    #[test]
    fn parsing_in_place_is_parsing(
        before in prop::collection::vec(any::<u8>(), 0..100),
        bytes in prop::collection::vec(any::<u8>(), 0..120),
        (number, words, text) in line_parts(),
    ) {
        // A line with words, text and a number in it first, when these parts make one.
        let mut held = Vec::new();
        if let Ok(line) = Line::from_parts(number, &words, text.as_deref().map(str::as_bytes))
            && let Ok(encoded) = encode_line(&line)
        {
            held = encoded;
        }
        for input in [&bytes, &held] {
            let mut line = Line::parse(&held).unwrap_or_else(|_| Line::empty());
            let _ = line.parse_in(&before);
            match (Line::parse(input), line.parse_in(input)) {
                (Ok(expected), Ok(())) => prop_assert_eq!(&line, &expected),
                (Err(expected), Err(e)) => {
                    prop_assert_eq!(e, expected);
                    prop_assert_eq!(&line, &Line::empty());
                }
                (a, b) => prop_assert!(false, "parse {:?}, parse_in {:?}", a, b),
            }
        }
    }

    #[test]
    fn decoders_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..400)) {
        let _ = Line::parse(&bytes);
        let _ = ClientMessage::decode(&bytes);
        let _ = ControllerMessage::decode(&bytes);
        let _ = Reply::parse(&bytes);
        let _ = run(&bytes, &[7]);
    }
}
