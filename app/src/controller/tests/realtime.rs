//! The realtime path is never blocked: `M112`, frames and status requests act within 10 ms of
//! virtual time while G-code lines wait (held for the planner, homing, heating, a dwell,
//! `M226`), and the lines queued behind still get exactly one answer each, in order.

use super::*;
use crate::controller::gcode::{Realtime, realtime};

/// How soon a realtime record must act, ms of virtual time.
const REALTIME_MS: u64 = 10;

/// Frame 04 asks 51 and 52; both answers come within [`REALTIME_MS`].
fn requests_are_answered(b: &mut Bench) {
    b.take();
    b.send_frame(&ClientMessage::Request { message_type: 51 });
    b.send_frame(&ClientMessage::Request { message_type: 52 });
    b.run_ms(REALTIME_MS);
    let out = b.take();
    let frames = frames_of(&out);
    assert!(
        frames
            .iter()
            .any(|m| matches!(m, ControllerMessage::Positions(_))),
        "no 51 within {REALTIME_MS} ms: {out:?}"
    );
    assert!(
        frames
            .iter()
            .any(|m| matches!(m, ControllerMessage::Progress(_))),
        "no 52 within {REALTIME_MS} ms: {out:?}"
    );
}

/// `M112` stops the machine within [`REALTIME_MS`]; by then each of the `sent` lines before it
/// and the `M112` itself has had exactly one `ok`, and nothing moves afterwards.
fn m112_acts_at_once(b: &mut Bench, sent: u32) {
    b.take();
    let oks = b.ctl.stats().oks;
    b.send("M112");
    b.run_ms(REALTIME_MS);
    let out = b.take();
    assert_eq!(
        b.ctl.kernel().state(),
        MachineState::Alarm(forja_motion::Alarm::EmergencyStop),
        "{out:?}"
    );
    assert_eq!(
        out.first().map(String::as_str),
        Some("Error:E153 emergency-stop")
    );
    assert!(!b.ctl.peripherals().motors);
    assert_eq!(b.ctl.peripherals().hot.target_mc, 0);
    assert_eq!(b.ctl.stats().oks, sent + 1, "{out:?}");
    assert_eq!(
        out.iter().filter(|l| l.starts_with("ok")).count() as u32,
        b.ctl.stats().oks - oks
    );
    assert!(!b.ctl.is_holding());
    assert!(b.link.rx.is_empty());
    let stopped = b.position_mm();
    b.run_ms(500);
    assert_eq!(b.position_mm(), stopped);
    assert!(b.take().is_empty());
}

/// What the controller sent since the last look, without the temperature reports.
/// The answers to lines, one per line: reports (`//`, a heating wait's ` T:…`) left out, and
/// an `M114` position folded into the `ok` that follows it (`ok X:1.000 … Count …`).
fn replies(b: &mut Bench) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    let mut position: Option<String> = None;
    for l in b.take() {
        if l.starts_with("//") || l.starts_with(" T:") {
            continue;
        }
        if l.starts_with("X:") {
            position = Some(l);
            continue;
        }
        match position.take() {
            Some(p) if l == "ok" => out.push(format!("ok {p}")),
            Some(p) => out.extend([p, l]),
            None => out.push(l),
        }
    }
    out
}

/// Send `lines` at once, as a host that sends ahead does.
fn send_ahead(b: &mut Bench, lines: &[&str]) -> u32 {
    for l in lines {
        b.send(l);
    }
    lines.len() as u32
}

#[test]
fn realtime_acts_behind_lines_held_for_a_full_planner() {
    let mut b = Bench::new();
    let sent = b.fill_planner() + send_ahead(&mut b, &["G1 X10", "G1 X20", "M114"]);
    b.run_ms(2);
    assert!(b.ctl.is_holding());
    requests_are_answered(&mut b);
    b.send_frame(&ClientMessage::Action(Action::Pause));
    b.run_ms(REALTIME_MS);
    assert!(
        matches!(b.ctl.kernel().state(), MachineState::Hold { .. }),
        "{:?}",
        b.ctl.kernel().state()
    );
    b.run_ms(500);
    let held_at = b.position_mm();
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(REALTIME_MS);
    assert_eq!(b.ctl.kernel().state(), MachineState::Running);
    assert_ne!(b.position_mm(), held_at);
    m112_acts_at_once(&mut b, sent);
}

#[test]
fn stop_acts_behind_lines_held_for_a_full_planner() {
    let mut b = Bench::new();
    b.fill_planner();
    send_ahead(&mut b, &["G1 X10", "G1 X20"]);
    b.run_ms(2);
    b.send_frame(&ClientMessage::Action(Action::Stop));
    b.run_ms(REALTIME_MS);
    assert!(
        matches!(b.ctl.kernel().state(), MachineState::Hold { .. }),
        "{:?}",
        b.ctl.kernel().state()
    );
}

#[test]
fn realtime_acts_during_homing() {
    let mut b = Bench::new();
    b.take();
    let sent = send_ahead(&mut b, &["G28", "G1 X5", "M114"]);
    b.run_ms(5);
    assert_eq!(b.ctl.kernel().state(), MachineState::Homing);
    assert!(b.take().is_empty());
    requests_are_answered(&mut b);
    // Nothing to pause: the refusal comes at once too.
    b.send_frame(&ClientMessage::Action(Action::Pause));
    b.run_ms(REALTIME_MS);
    assert_eq!(error_codes(&b.take()), [181]);
    m112_acts_at_once(&mut b, sent);
}

#[test]
fn realtime_acts_during_an_m109_wait() {
    let mut b = Bench::new();
    b.take();
    let sent = send_ahead(&mut b, &["M109 S200", "G1 X5", "M105"]);
    b.run_ms(5);
    assert!(b.ctl.is_holding());
    requests_are_answered(&mut b);
    m112_acts_at_once(&mut b, sent);
}

#[test]
fn realtime_acts_during_an_m116_wait() {
    let mut b = Bench::new();
    b.take();
    let sent = send_ahead(&mut b, &["M140 S60", "M116", "G1 X5", "G1 X6"]);
    b.run_ms(5);
    assert!(b.ctl.is_holding());
    requests_are_answered(&mut b);
    m112_acts_at_once(&mut b, sent);
}

#[test]
fn realtime_acts_during_a_dwell_behind_a_full_planner() {
    let mut b = Bench::new();
    b.take();
    let lines: Vec<String> = core::iter::once("G4 P20000".to_string())
        .chain((0..40).map(|i| format!("G1 X{} F3000", i % 2)))
        .collect();
    let refs: Vec<&str> = lines.iter().map(String::as_str).collect();
    let sent = send_ahead(&mut b, &refs);
    b.run_ms(5);
    assert!(b.ctl.is_holding());
    requests_are_answered(&mut b);
    b.send_frame(&ClientMessage::Action(Action::Pause));
    b.run_ms(REALTIME_MS);
    assert!(
        matches!(b.ctl.kernel().state(), MachineState::Hold { .. }),
        "{:?}",
        b.ctl.kernel().state()
    );
    m112_acts_at_once(&mut b, sent);
}

#[test]
fn start_requests_and_lines_are_answered_while_m226_pauses() {
    let mut b = Bench::new();
    b.take();
    send_ahead(&mut b, &["M226", "G1 X5 F3000", "G1 X6"]);
    b.run_ms(5);
    assert_eq!(b.take(), ["ok"], "M226");
    assert_eq!(b.ctl.kernel().state(), MachineState::Paused);
    assert!(b.ctl.is_holding());
    requests_are_answered(&mut b);
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(REALTIME_MS);
    assert_ne!(b.ctl.kernel().state(), MachineState::Paused);
    assert_eq!(b.take(), ["ok", "ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 6.0);
}

#[test]
fn m112_acts_while_m226_pauses() {
    let mut b = Bench::new();
    b.take();
    let sent = send_ahead(&mut b, &["M226", "G1 X5 F3000", "G1 X6"]);
    b.run_ms(5);
    assert_eq!(b.ctl.kernel().state(), MachineState::Paused);
    requests_are_answered(&mut b);
    m112_acts_at_once(&mut b, sent);
    assert_eq!(b.position_mm()[0], 0.0);
}

#[test]
fn queued_lines_get_one_ok_each_in_order_and_run_once() {
    let mut b = Bench::new();
    b.take();
    let bodies = [
        "M109 S30",
        "G1 X1 F3000",
        "M114",
        "G1 X2",
        "M105",
        "M114",
        "G91",
        "G1 X1",
        "G90",
        "M114",
    ];
    for (i, body) in bodies.iter().enumerate() {
        b.send_numbered(i as u32 + 1, body);
    }
    b.run_ms(5);
    // Everything was read at once: the host is within the read-ahead window.
    assert!(b.link.rx.is_empty());
    assert!(b.take().is_empty(), "nothing answered before M109 is done");
    b.run_until(10_000, |b| !b.ctl.is_holding());
    b.run_ms(5);
    let out = replies(&mut b);
    assert_eq!(out.len(), bodies.len(), "{out:?}");
    assert_eq!(out[0], "ok");
    assert!(
        out[2].starts_with("ok X:1.000 Y:0.000 Z:0.000 Count "),
        "{out:?}"
    );
    assert!(out[4].starts_with("ok T:"), "{out:?}");
    assert!(
        out[5].starts_with("ok X:2.000 Y:0.000 Z:0.000 Count "),
        "{out:?}"
    );
    assert!(
        out[9].starts_with("ok X:3.000 Y:0.000 Z:0.000 Count "),
        "{out:?}"
    );
    assert_eq!(b.ctl.stats().executed, bodies.len() as u32);
    assert_eq!(b.ctl.stats().oks, bodies.len() as u32);
    b.idle();
    assert_eq!(b.position_mm()[0], 3.0);
}

#[test]
fn a_checksum_error_behind_queued_lines_asks_for_the_right_line() {
    let mut b = Bench::new();
    b.take();
    b.send_numbered(1, "M109 S30");
    b.send_numbered(2, "G1 X1 F3000");
    let good = numbered(3, "G1 X2");
    b.send(&good.replace("X2", "X7"));
    b.send_numbered(4, "G1 X3");
    b.send_numbered(5, "G1 X4");
    b.run_ms(5);
    assert!(b.link.rx.is_empty());
    b.run_until(10_000, |b| !b.ctl.is_holding());
    b.run_ms(5);
    let out = replies(&mut b);
    assert_eq!(&out[..2], ["ok", "ok"], "{out:?}");
    // Line 3 and each line after it is answered `rs 3`, none runs.
    assert_eq!(
        out[2..],
        ["rs 3", "ok", "rs 3", "ok", "rs 3", "ok"],
        "{out:?}"
    );
    assert_eq!(b.ctl.stats().executed, 2);
    b.send(&good);
    b.send_numbered(4, "G1 X3");
    b.send_numbered(5, "G1 X4");
    b.run_ms(5);
    assert_eq!(b.take(), ["ok", "ok", "ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 4.0);
    assert_eq!(b.ctl.stats().executed, 5);
}

#[test]
fn garbage_behind_queued_lines_asks_for_the_line_expected_then() {
    let mut b = Bench::new();
    b.take();
    b.send_numbered(1, "M109 S30");
    b.send_numbered(2, "G1 X1 F3000");
    // Line 3 is lost in garbage.
    b.send_raw(b"N3 G1\x01X2*1\n");
    b.send_numbered(4, "G1 X3");
    b.run_ms(5);
    assert!(b.take().is_empty());
    b.run_until(10_000, |b| !b.ctl.is_holding());
    b.run_ms(5);
    let out = replies(&mut b);
    let replies: Vec<&String> = out.iter().filter(|l| !l.starts_with('N')).collect();
    assert_eq!(replies, ["ok", "ok", "rs 3", "ok", "rs 3", "ok"], "{out:?}");
}

#[test]
fn m112_behind_queued_lines_answers_them_in_order_without_running_them() {
    let mut b = Bench::new();
    b.take();
    b.send_numbered(1, "M109 S200");
    b.send_numbered(2, "G1 X5 F3000");
    b.send_numbered(3, "M999");
    b.send_numbered(4, "M114");
    b.run_ms(5);
    assert!(b.take().is_empty());
    b.send_numbered(5, "M112");
    b.run_ms(REALTIME_MS);
    assert_eq!(
        b.take(),
        [
            "Error:E153 emergency-stop",
            "ok",
            "echo:E125 alarm-locked",
            "ok",
            "echo:E125 alarm-locked",
            "ok",
            "echo:E125 alarm-locked",
            "ok",
            "ok",
        ],
        "M109 ran (its wait ends), lines 2 to 4 are refused, then M112's ok"
    );
    assert_eq!(
        b.ctl.kernel().state(),
        MachineState::Alarm(forja_motion::Alarm::EmergencyStop)
    );
    // The numbering went on through the refused lines: line 6 is next.
    b.send_numbered(6, "M999");
    b.send_numbered(7, "G1 X1 F3000");
    b.run_ms(5);
    assert_eq!(b.take(), ["ok", "ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 1.0);
}

#[test]
fn a_damaged_m112_behind_queued_lines_still_stops_and_is_asked_again() {
    let mut b = Bench::new();
    b.take();
    b.send_numbered(1, "M109 S200");
    b.send_numbered(2, "G1 X5 F3000");
    b.run_ms(5);
    let good = numbered(3, "M112");
    let (head, sum) = good.split_once('*').unwrap();
    let wrong = (sum.parse::<u8>().unwrap()).wrapping_add(1);
    b.send(&format!("{head}*{wrong}"));
    b.run_ms(REALTIME_MS);
    assert_eq!(
        b.take(),
        [
            "Error:E153 emergency-stop",
            "ok",
            "echo:E125 alarm-locked",
            "ok",
            "rs 3",
            "ok"
        ]
    );
    assert_eq!(
        b.ctl.kernel().state(),
        MachineState::Alarm(forja_motion::Alarm::EmergencyStop)
    );
    b.send(&good);
    b.run_ms(5);
    assert_eq!(b.take(), ["Error:E153 emergency-stop", "ok"]);
}

#[test]
fn m108_ends_a_heater_wait_at_once_and_is_answered_in_turn() {
    let mut b = Bench::new();
    b.take();
    send_ahead(&mut b, &["M109 S200", "G1 X1 F3000"]);
    b.run_ms(5);
    assert!(b.take().is_empty());
    assert!(b.ctl.is_holding());
    b.send("M108");
    b.run_ms(REALTIME_MS);
    // M109's ok (its wait ended), then the line after it, then M108's own in turn.
    assert_eq!(b.take(), ["ok", "ok", "ok"]);
    assert!(!b.ctl.is_holding());
    assert_eq!(
        b.ctl.peripherals().hot.target_mc,
        200_000,
        "the target stays"
    );
    // Without a wait, M108 is just answered.
    assert_eq!(b.ask("M108"), ["ok"]);
}

#[test]
fn the_receive_queue_keeps_entries_in_order_across_its_end() {
    let mut q = LineQueue::new();
    let line = [b'G'; 100];
    // Fill and drain repeatedly so that entries wrap around the end of the ring.
    for round in 0..20u8 {
        assert!(q.push_line(&line[..usize::from(round) + 1]));
        assert!(q.push_dropped(Dropped::TooLong));
        assert!(q.push_line(b"M105"));
        assert!(q.push_dropped(Dropped::Garbage { text: false }));
        assert!(q.push_dropped(Dropped::Garbage { text: true }));
        let mut l = LineBuf::EMPTY;
        assert_eq!(q.pop(&mut l), Some(Queued::Line));
        assert_eq!(l.bytes(), &line[..usize::from(round) + 1]);
        assert_eq!(q.pop(&mut l), Some(Queued::Dropped(Dropped::TooLong)));
        assert_eq!(q.pop(&mut l), Some(Queued::Line));
        assert_eq!(l.bytes(), b"M105");
        assert_eq!(
            q.pop(&mut l),
            Some(Queued::Dropped(Dropped::Garbage { text: false }))
        );
        assert_eq!(
            q.pop(&mut l),
            Some(Queued::Dropped(Dropped::Garbage { text: true }))
        );
        assert!(q.is_empty());
        // Leave some bytes behind to move the head along.
        assert!(q.push_line(&line[..37]));
        assert_eq!(q.pop(&mut l), Some(Queued::Line));
        assert_eq!(l.bytes(), &line[..37]);
    }
    // Reading stops only once more than the read-ahead window is queued: a host within the
    // window is always read.
    let long = [b'X'; MAX_LINE_LEN];
    while q.has_room() {
        assert!(q.push_line(&long));
    }
    assert!(q.len > READ_AHEAD_BYTES);
    // Full to the last byte; a refused push changes nothing.
    while q.push_line(b"G1") {}
    let before = q.len;
    assert!(!q.push_line(b"G1"));
    assert!(!q.push_line(&long));
    assert_eq!(q.len, before);
    assert!(LINE_QUEUE_LEN - q.len < 3);
    // Not lines the decoder gives: refused.
    let mut e = LineQueue::new();
    assert!(!e.push_line(b""));
    assert!(!e.push_line(b"G1\nX1"));
    assert!(!e.push_line(b"\x01G1"));
    assert!(!e.push_line(&[b'G'; MAX_LINE_LEN + 1]));
    assert!(e.is_empty());
}

#[test]
fn realtime_commands_are_found_as_marlin_finds_them() {
    for (text, found) in [
        ("M112", Some(Realtime::EmergencyStop)),
        ("m112", Some(Realtime::EmergencyStop)),
        ("  N12 M112*0", Some(Realtime::EmergencyStop)),
        ("N-1 M112 ; stop", Some(Realtime::EmergencyStop)),
        ("M108", Some(Realtime::CancelWait)),
        ("N7 M108*99", Some(Realtime::CancelWait)),
        ("M1120", None),
        ("M112.5", None),
        ("M11", None),
        ("; M112", None),
        ("(M112)", None),
        ("G1 X112", None),
        ("M104 S112", None),
        ("N5", None),
        ("M", None),
    ] {
        assert_eq!(realtime(text.as_bytes()), found, "{text}");
    }
}

#[test]
fn stop_answers_the_lines_received_before_it_without_running_them() {
    let mut b = Bench::new();
    b.take();
    b.send_numbered(1, "M109 S200");
    b.send_numbered(2, "G1 X5 F3000");
    b.send_numbered(3, "M114");
    b.send_numbered(4, "G1 X7");
    b.run_ms(5);
    assert!(b.take().is_empty());
    b.send_frame(&ClientMessage::Action(Action::Stop));
    // Sent after the stop: runs as usual.
    b.send_numbered(5, "G1 X1 F3000");
    b.run_ms(REALTIME_MS);
    assert_eq!(
        replies(&mut b),
        [
            "ok",
            "echo:E198 stopped",
            "ok",
            "echo:E198 stopped",
            "ok",
            "echo:E198 stopped",
            "ok",
            "ok",
        ],
        "M109's wait ends, lines 2 to 4 are refused, line 5 runs"
    );
    assert!(!b.ctl.is_holding());
    b.idle();
    assert_eq!(b.position_mm()[0], 1.0);
    assert_eq!(b.ctl.stats().executed, 2);
    b.run_ms(500);
    assert_eq!(b.position_mm()[0], 1.0);
    assert!(b.take().is_empty());
}

/// A line damaged on the link and still waiting when the stop comes is not asked again: the
/// host's resend would run after the stop. It is refused like the intact ones, and its number
/// used up, so that the host's next line is taken.
#[test]
fn stop_refuses_a_damaged_waiting_line_instead_of_asking_it_again() {
    let mut b = Bench::new();
    b.take();
    b.send_numbered(1, "M109 S200");
    b.send_numbered(2, "G1 X5 F3000");
    // Line 3, its checksum wrong (damaged on the link).
    b.send_raw(b"N3 G1 X9*0\n");
    b.run_ms(5);
    assert!(b.take().is_empty());
    b.send_frame(&ClientMessage::Action(Action::Stop));
    b.send_numbered(4, "G1 X1 F3000");
    b.run_ms(REALTIME_MS);
    assert_eq!(
        replies(&mut b),
        [
            "ok",
            "echo:E198 stopped",
            "ok",
            "echo:E198 stopped",
            "ok",
            "ok",
        ],
        "M109's wait ends, line 2 and the damaged line 3 are refused, line 4 runs"
    );
    b.idle();
    assert_eq!(b.position_mm()[0], 1.0);
}

#[test]
fn stop_behind_a_full_planner_drops_the_held_and_queued_lines() {
    let mut b = Bench::new();
    b.fill_planner();
    send_ahead(&mut b, &["G1 X10", "G1 X20"]);
    b.run_ms(2);
    assert!(b.take().is_empty());
    b.send_frame(&ClientMessage::Action(Action::Stop));
    b.run_ms(REALTIME_MS);
    assert_eq!(
        b.take(),
        [
            "echo:E198 stopped",
            "ok",
            "echo:E198 stopped",
            "ok",
            "echo:E198 stopped",
            "ok"
        ],
        "the held line and the two queued behind it"
    );
    assert!(!b.ctl.is_holding());
    b.idle();
    let stopped = b.position_mm();
    assert!(stopped[0] < 10.0, "{stopped:?}");
    b.run_ms(500);
    assert_eq!(b.position_mm(), stopped);
    // The machine takes lines again once stopped.
    assert_eq!(b.ask("G1 X3 F3000"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 3.0);
}

#[test]
fn reset_answers_the_lines_received_before_it_without_running_them() {
    let mut b = Bench::new();
    b.take();
    b.send_numbered(1, "M109 S200");
    b.send_numbered(2, "G1 X5 F3000");
    b.send_numbered(3, "M110 N9");
    b.send_numbered(10, "G1 X7");
    b.run_ms(5);
    assert!(b.take().is_empty());
    b.send_frame(&ClientMessage::Action(Action::Reset));
    b.send_numbered(11, "G1 X2 F3000");
    b.run_ms(REALTIME_MS);
    assert_eq!(
        replies(&mut b),
        [
            "ok",
            "echo:E198 stopped",
            "ok",
            "ok",
            "echo:E198 stopped",
            "ok",
            "ok",
        ],
        "M109's wait ends, M110 renumbers, the moves before the reset do not run"
    );
    b.idle();
    assert_eq!(b.position_mm()[0], 2.0);
}
