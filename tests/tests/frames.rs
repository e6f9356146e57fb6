//! The operator's client over TCP, as the ESP32's WiFi link carries it: the greeting and the
//! keep-alives, settings, homing on the switches, a jog, a program uploaded with frames and run
//! (every stored line exactly once), pause, resume and stop, progress and positions, and a
//! restart that keeps the settings and the program.

use std::time::Duration;

use forja_app::job::JobState;
use forja_motion::MachineState;
use forja_protocol::frame::{Action, ClientMessage, ControllerMessage};
use forja_protocol::gcode::Decimal;
use forja_sim::board::BoardConfig;
use forja_sim_hal::link::{PtyLink, TcpLink};
use forja_tests::{HostEnd, Replies, Rig, TcpHost, frame, same_mm};

/// Send `msg` and let the firmware answer.
fn ask(rig: &mut Rig, host: &mut TcpHost, replies: &mut Replies, msg: &ClientMessage<'_>) {
    host.send(&frame(msg));
    rig.exchange(host, replies, 20);
}

/// The last 51 among the replies, as (letter, mm).
fn last_positions(replies: &Replies) -> Vec<(char, f64)> {
    replies
        .frames()
        .iter()
        .rev()
        .find_map(|m| match m {
            ControllerMessage::Positions(p) => Some(
                p.axes()
                    .iter()
                    .map(|a| (char::from(a.axis), a.mm().to_f64()))
                    .collect(),
            ),
            _ => None,
        })
        .expect("a 51 frame")
}

/// The last 52 among the replies.
fn last_progress(replies: &Replies) -> forja_protocol::frame::Progress {
    replies
        .frames()
        .iter()
        .rev()
        .find_map(|m| match m {
            ControllerMessage::Progress(p) => Some(*p),
            _ => None,
        })
        .expect("a 52 frame")
}

/// A program of relative moves whose every line changes where it ends: a line run twice or
/// not at all moves the end point by at least 0.05 mm. Returns the lines and the X and Y they
/// add up to.
fn program(n: usize) -> (Vec<String>, f64, f64) {
    let mut lines = vec!["G91".to_string(), "G1 F4000".to_string()];
    let (mut dx, mut dy) = (0.0, 0.0);
    for i in 0..n {
        let x = ((i % 7) as f64 + 1.0) * 0.25 * if i % 2 == 0 { 1.0 } else { -1.0 };
        let y = ((i % 5) as f64 + 1.0) * 0.05 * if i % 3 == 0 { -1.0 } else { 1.0 };
        lines.push(format!("G1 X{x:.2} Y{y:.2}"));
        dx += x;
        dy += y;
    }
    lines.push("G90".to_string());
    (lines, dx, dy)
}

fn connect(rig: &mut Rig, addr: std::net::SocketAddr, replies: &mut Replies) -> TcpHost {
    let mut host = TcpHost::connect(addr);
    rig.exchange(&mut host, replies, 50);
    host
}

#[test]
fn the_operators_client_over_tcp() {
    let mut rig = Rig::new("default", BoardConfig::default());
    let tcp = TcpLink::bind("127.0.0.1:0".parse().unwrap(), b"busy\n".to_vec()).unwrap();
    let addr = tcp.local_addr().unwrap();
    rig.board.add_port(tcp, true);
    rig.board.add_port(PtyLink::open(None).unwrap(), false);
    let mut replies = Replies::default();
    let mut host = connect(&mut rig, addr, &mut replies);
    assert_eq!(
        replies.lines.first().map(String::as_str),
        Some("N54Conected*****************************************F")
    );

    // Settings: set, read back, refuse.
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::SetSetting {
            key: "jog_feed",
            value: "2400",
        },
    );
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::ReadSetting {
            key: "x.steps_per_mm",
        },
    );
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::SetSetting {
            key: "x.accel",
            value: "0",
        },
    );
    let settings: Vec<(String, String)> = replies
        .frames()
        .iter()
        .filter_map(|m| match m {
            ControllerMessage::Setting { key, value } => Some((key.to_string(), value.to_string())),
            _ => None,
        })
        .collect();
    assert_eq!(
        settings,
        [
            ("jog_feed".to_string(), "2400".to_string()),
            ("x.steps_per_mm".to_string(), "80".to_string())
        ]
    );
    assert_eq!(replies.error_codes(), [104], "x.accel=0 is refused");

    // Homing on the switches (Z up first, then X and Y), then the positions.
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::HomeAll),
    );
    rig.settle(&mut host, &mut replies);
    assert_eq!(rig.board.status().controller.homed, 0b0111);
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Request { message_type: 51 },
    );
    assert_eq!(
        last_positions(&replies),
        [('X', 2.0), ('Y', 2.0), ('Z', 99.0), ('A', 0.0)]
    );
    for (axis, mm) in [(0, 2.0), (1, 2.0), (2, 99.0)] {
        assert!(same_mm(rig.machine.position_mm(axis).unwrap(), mm));
    }

    // A jog: 1000 steps of 0.01 mm, no reply when done.
    replies.clear();
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Jog {
            step: Decimal::new(1, 2),
            axis: b'X',
            count: 1000,
        },
    );
    rig.settle(&mut host, &mut replies);
    assert!(
        replies
            .frames()
            .iter()
            .all(|m| matches!(m, ControllerMessage::KeepAlive { .. })),
        "{:?}",
        replies.lines
    );
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Request { message_type: 51 },
    );
    assert_eq!(last_positions(&replies)[0], ('X', 12.0));

    // Upload a program: 53 after the last line, each line stored as sent.
    let (lines, dx, dy) = program(240);
    let total = lines.len() as u16;
    replies.clear();
    for (i, text) in lines.iter().enumerate() {
        host.send(&frame(&ClientMessage::LoadLine {
            index: i as u16 + 1,
            text,
            total,
        }));
    }
    rig.exchange(&mut host, &mut replies, 200);
    let confirms = replies
        .frames()
        .iter()
        .filter(|m| matches!(m, ControllerMessage::Confirm { what: "Gcode-load" }))
        .count();
    assert_eq!(confirms, 1, "{:?}", replies.lines);
    assert!(replies.error_codes().is_empty());
    assert_eq!(rig.board.status().controller.program_lines, total);
    for (i, text) in lines.iter().enumerate() {
        assert_eq!(
            rig.board.program_line(i as u16 + 1).as_deref(),
            Some(text.as_str())
        );
    }

    // Run it through: every stored line runs exactly once.
    let start = rig.board.status();
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::Start),
    );
    let finished = rig.run_until(Duration::from_secs(40), |board, _| {
        board.status().controller.job == JobState::Finished
    });
    assert!(finished, "{:?}", rig.board.status());
    let end = rig.board.status();
    assert_eq!(
        end.controller.stats.program_lines - start.controller.stats.program_lines,
        u32::from(total)
    );
    assert!(same_mm(end.machine_mm[0], 12.0 + dx));
    assert!(same_mm(end.machine_mm[1], 2.0 + dy));
    assert!(same_mm(rig.machine.position_mm(0).unwrap(), 12.0 + dx));
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Request { message_type: 52 },
    );
    let p = last_progress(&replies);
    assert_eq!(
        (p.total_lines, p.current_line),
        (u32::from(total), u32::from(total))
    );
    assert!(p.estimated_s > 0);

    // Again, with a pause, a resume and a stop; while it runs, moves from the link are refused
    // and reports still answered.
    replies.clear();
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::Rewind),
    );
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::Start),
    );
    rig.exchange(&mut host, &mut replies, 3_000);
    host.send(b"G1 X100\nM114\n");
    rig.exchange(&mut host, &mut replies, 20);
    assert!(replies.lines.contains(&"echo:E182 job-busy".to_string()));
    assert!(replies.lines.iter().any(|l| l.starts_with("X:")));
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::Pause),
    );
    rig.exchange(&mut host, &mut replies, 500);
    let held = rig.machine.positions_mm();
    rig.exchange(&mut host, &mut replies, 1_000);
    assert_eq!(rig.machine.positions_mm(), held, "paused");
    assert_eq!(rig.board.status().controller.job, JobState::Paused);
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Request { message_type: 52 },
    );
    let paused_at = last_progress(&replies).current_line;
    assert!(paused_at > 1 && paused_at < u32::from(total), "{paused_at}");
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::Start),
    );
    rig.exchange(&mut host, &mut replies, 1_000);
    assert_ne!(rig.machine.positions_mm(), held, "resumed");
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::Stop),
    );
    rig.settle(&mut host, &mut replies);
    let status = rig.board.status();
    assert_eq!(status.controller.job, JobState::Idle);
    assert_eq!(status.controller.state, MachineState::Idle);
    let second_run = status.controller.stats.program_lines - end.controller.stats.program_lines;
    assert!(
        second_run < u32::from(total),
        "{second_run} lines fed before the stop"
    );
    assert!(replies.error_codes().is_empty(), "{:?}", replies.lines);

    // Keep-alives came all along, counting up.
    let counters: Vec<u32> = replies
        .frames()
        .iter()
        .filter_map(|m| match m {
            ControllerMessage::KeepAlive { counter } => Some(*counter),
            _ => None,
        })
        .collect();
    assert!(counters.len() >= 3, "{counters:?}");
    assert!(
        counters.windows(2).all(|w| w[1] == w[0] + 1),
        "{counters:?}"
    );
    assert_eq!(rig.machine.violation_count(), 0);

    // A restart keeps the settings and the program.
    let machine = rig.machine.clone();
    let flash = rig.board.into_flash();
    let mut rig = Rig::on(
        machine,
        BoardConfig {
            flash,
            ..BoardConfig::default()
        },
    );
    assert_eq!(rig.board.status().controller.program_lines, total);
    assert_eq!(
        rig.board.program_line(3).as_deref(),
        Some(lines[2].as_str())
    );
    let tcp = TcpLink::bind("127.0.0.1:0".parse().unwrap(), b"busy\n".to_vec()).unwrap();
    let addr = tcp.local_addr().unwrap();
    rig.board.add_port(tcp, true);
    let mut replies = Replies::default();
    let mut host = connect(&mut rig, addr, &mut replies);
    ask(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::ReadSetting { key: "jog_feed" },
    );
    assert!(
        replies.frames().contains(&ControllerMessage::Setting {
            key: "jog_feed",
            value: "2400"
        }),
        "{:?}",
        replies.lines
    );
}
