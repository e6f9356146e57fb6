//! A printer job of several hundred numbered, checksummed lines streamed over the
//! pseudo-terminal by the `forja` client's streamer, one line at a time as Printrun streams:
//! homing on the switches, heating, moves with extrusion, the fan, and every report (`M105`,
//! `M114`, `M119`).

use std::time::{Duration, Instant};

use forja_host::streamer::{Config, Window};
use forja_protocol::reply::Reply;
use forja_sim::board::BoardConfig;
use forja_sim_hal::link::{PtyLink, TcpLink};
use forja_simulator::host::StreamHost;
use forja_tests::{HostEnd, PtyHost, Rig, same_mm, wall_ms};

/// The job: home, heat, a zig-zag of `moves` extruding moves, reports, cool down.
fn job(moves: usize) -> (Vec<String>, (f64, f64, f64)) {
    let mut lines: Vec<String> = [
        "G28",
        "M104 S200",
        "M140 S60",
        "M116 ; wait for both",
        "M105",
        "G92 E0",
        "M83 ; relative extrusion",
        "G1 Z0.3 F600",
        "M106 S200",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let (mut x, mut y) = (0.0, 0.0);
    for i in 0..moves {
        x = 20.0 + (i % 40) as f64 * 4.0;
        y = 20.0 + (i / 40) as f64 * 10.0;
        lines.push(format!("G1 X{x:.1} Y{y:.1} E0.25 F3000"));
    }
    lines.extend(
        [
            "M107",
            "M114",
            "M104 S0",
            "M140 S0",
            "G1 Z10 F600",
            "M119",
            "M114",
        ]
        .iter()
        .map(|s| s.to_string()),
    );
    (lines, (x, y, moves as f64 * 0.25))
}

#[test]
fn a_printer_job_over_the_pseudo_terminal() {
    let mut rig = Rig::new("printer", BoardConfig::default());
    let tcp = TcpLink::bind("127.0.0.1:0".parse().unwrap(), b"busy\n".to_vec()).unwrap();
    rig.board.add_port(tcp, true);
    let pty = PtyLink::open(None).unwrap();
    let path = pty.slave_path().to_path_buf();
    rig.board.add_port(pty, false);
    let mut host = PtyHost::open(&path);

    let (lines, (x, y, e)) = job(420);
    let config = Config {
        window: Window::PING_PONG,
        ..Config::default()
    };
    let mut sender = StreamHost::new(config, lines.iter().map(String::as_str)).unwrap();
    let start = Instant::now();
    let done = rig.run_until(Duration::from_secs(50), |board, _| {
        let out = sender.exchange(&host.receive(), wall_ms(start));
        if !out.is_empty() {
            host.send(&out);
        }
        let s = board.status();
        sender.is_over() && s.controller.idle && !s.controller.holding
    });
    assert!(
        done && sender.is_done(),
        "the job did not finish: {:?}, {:?}",
        sender.events(),
        rig.board.status()
    );

    // Every line sent once and taken, none refused, none resent on a clean link.
    let stats = sender.stats();
    let pushed = sender.streamer().pushed();
    assert_eq!(pushed as usize, lines.len());
    assert_eq!(sender.streamer().accepted(), pushed);
    // The job's lines and the closing line.
    assert_eq!(stats.lines_sent, u64::from(pushed) + 1);
    assert_eq!(
        (stats.lines_resent, stats.stalls, stats.refused),
        (0, 0, 0),
        "{stats:?}"
    );
    let faults: Vec<&str> = sender.faults().collect();
    assert!(faults.is_empty(), "{faults:?}");
    let status = rig.board.status();
    // The job's lines, the handshake's `M110` and the closing line.
    assert_eq!(status.controller.stats.executed, pushed + 2);
    assert_eq!(
        (
            status.controller.stats.resends,
            status.controller.stats.refused
        ),
        (0, 0)
    );
    assert_eq!(sender.replies().first().map(String::as_str), Some("start"));

    // Where the machine is: the kernel's position and the physical one agree.
    let want = [x, y, 10.0, e];
    for (axis, want) in want.iter().enumerate() {
        let got = rig.machine.position_mm(axis).unwrap();
        assert!(same_mm(got, *want), "axis {axis}: {got} instead of {want}");
        assert!(same_mm(status.machine_mm[axis], *want));
        assert_eq!(rig.machine.lost_steps(axis), Some(0));
    }
    assert_eq!(rig.machine.violation_count(), 0);

    // The reports.
    let replies = sender.replies();
    let oks: Vec<Reply<'_>> = replies
        .iter()
        .filter_map(|l| Reply::parse(l.as_bytes()).ok())
        .collect();
    let Some((Some(hot_end), Some(bed))) = oks.iter().find_map(|r| match r {
        Reply::Temperatures {
            hot_end,
            bed,
            ok: true,
        } => Some((*hot_end, *bed)),
        _ => None,
    }) else {
        panic!("no M105 answer: {replies:?}");
    };
    let (extruder, bed) = (hot_end.current, bed.current);
    assert!((extruder.to_f64() - 200.0).abs() <= 2.0, "{extruder}");
    assert!((bed.to_f64() - 60.0).abs() <= 2.0, "{bed}");
    assert_eq!((hot_end.target.to_f64(), 60.0), (200.0, 60.0));
    let positions: Vec<&Reply<'_>> = oks
        .iter()
        .filter(|r| matches!(r, Reply::Position { .. }))
        .collect();
    assert_eq!(positions.len(), 2);
    let Reply::Position { axes: last, .. } = positions[1] else {
        unreachable!()
    };
    let letters: String = last.iter().map(|w| char::from(w.letter)).collect();
    assert_eq!(letters, "XYZE");
    assert_eq!(last[0].value.to_f64(), x);
    assert_eq!(last[2].value.to_f64(), 10.0);
    assert!(
        replies.contains(&"ok x_min:open y_min:open z_min:open".to_string()),
        "{replies:?}"
    );

    // The fan ran at 200/255 between M106 and M107, the heaters are off again.
    let fan = rig.machine.output_index("part_fan").unwrap();
    let duties: Vec<u16> = rig
        .machine
        .pwm_history(fan)
        .unwrap()
        .iter()
        .map(|c| c.duty)
        .collect();
    assert_eq!(duties, [200, 0]);
    let hot = rig.machine.heater_index("hotend").unwrap();
    assert!(rig.machine.temperature_c(hot).unwrap() < 200.0);
    assert_eq!(rig.board.status().controller.stats.faults, 0);
}

/// Lines damaged on the link, one controller on an in-memory link (issue 11, items 3, 4, 9).
mod damaged {
    use forja_protocol::gcode::{Check, checksum, write_checked};
    use forja_sim::board::BoardConfig;
    use forja_sim_hal::link::{MemoryHost, MemoryLink};
    use forja_tests::{Replies, Rig};

    /// A numbered line with its XOR checksum, without terminator.
    fn numbered(n: i64, body: &str) -> String {
        let head = format!("N{n} {body}");
        format!("{head}*{}", checksum(head.as_bytes()))
    }

    /// A numbered line with its CRC-16, without terminator.
    fn strong(n: u32, body: &str) -> String {
        let mut buf = [0u8; 300];
        let len = write_checked(n, body.as_bytes(), Check::Crc16, &mut buf).unwrap();
        String::from_utf8(buf[..len].to_vec()).unwrap()
    }

    /// A rig on the default machine, its link, the host numbering from line 0.
    fn numbered_rig() -> (Rig, MemoryHost, Replies) {
        let mut rig = Rig::new("default", BoardConfig::default());
        let (link, mut host) = MemoryLink::pair();
        rig.board.add_port(link, false);
        let mut replies = Replies::default();
        host.send(format!("{}\n", numbered(-1, "M110 N-1")).as_bytes());
        rig.exchange(&mut host, &mut replies, 20);
        assert_eq!(replies.lines, ["start", "ok"]);
        replies.clear();
        (rig, host, replies)
    }

    fn send(rig: &mut Rig, host: &mut MemoryHost, replies: &mut Replies, bytes: &str) {
        host.send(bytes.as_bytes());
        rig.exchange(host, replies, 50);
    }

    #[test]
    fn an_interpreter_refusal_of_a_numbered_line_is_asked_again_once() {
        let (mut rig, mut host, mut replies) = numbered_rig();
        // `X` damaged into `Q`, the checksum still matching: asked again, not refused.
        let damaged = numbered(0, "G1 Q5 F600");
        send(&mut rig, &mut host, &mut replies, &format!("{damaged}\n"));
        assert_eq!(replies.lines, ["rs 0", "ok"]);
        // The same line again: refused, its number used up.
        send(&mut rig, &mut host, &mut replies, &format!("{damaged}\n"));
        assert_eq!(
            replies.lines,
            ["rs 0", "ok", "echo:E127 unknown-axis Q", "ok"]
        );
        replies.clear();
        // The resent line is taken in order the first time it is intact.
        let line = numbered(2, "G1 Z1 F600");
        send(
            &mut rig,
            &mut host,
            &mut replies,
            &format!("{}\n", numbered(1, "G91")),
        );
        send(
            &mut rig,
            &mut host,
            &mut replies,
            &format!("{}\n", numbered(2, "G1 M3 Q")),
        );
        assert_eq!(replies.lines, ["ok", "rs 2", "ok"]);
        let z = rig.machine.positions_mm()[2];
        send(&mut rig, &mut host, &mut replies, &format!("{line}\n"));
        rig.settle(&mut host, &mut replies);
        assert_eq!(replies.lines, ["ok", "rs 2", "ok", "ok"]);
        assert!((rig.machine.positions_mm()[2] - z - 1.0).abs() < 1e-3);
    }

    #[test]
    fn a_line_cut_in_two_by_a_damaged_star_gets_one_reply_and_does_not_run() {
        let (mut rig, mut host, mut replies) = numbered_rig();
        let before = rig.machine.positions_mm();
        for line in [numbered(0, "G1 X5 F600"), strong(0, "G1 X5 F600")] {
            let cut = line.replacen('*', "\n", 1);
            send(&mut rig, &mut host, &mut replies, &format!("{cut}\r\n"));
            assert_eq!(replies.lines, ["rs 0", "ok"], "{cut:?}");
            replies.clear();
        }
        assert_eq!(rig.machine.positions_mm(), before);
        // On a link that does not number its lines, a checksum alone is bad input.
        let mut rig = Rig::new("default", BoardConfig::default());
        let (link, mut host) = MemoryLink::pair();
        rig.board.add_port(link, false);
        let mut replies = Replies::default();
        send(&mut rig, &mut host, &mut replies, "71\n");
        assert_eq!(replies.lines, ["start", "echo:E15 line-fragment", "ok"]);
    }

    #[test]
    fn an_unnumbered_line_cut_by_a_pause_waits_for_its_end() {
        let (mut rig, mut host, mut replies) = numbered_rig();
        send(
            &mut rig,
            &mut host,
            &mut replies,
            &format!("{}\n", numbered(0, "G91")),
        );
        replies.clear();
        host.send(b"G1 X1");
        rig.exchange(&mut host, &mut replies, 200);
        assert!(replies.lines.is_empty(), "{:?}", replies.lines);
        let x = rig.machine.positions_mm()[0];
        send(&mut rig, &mut host, &mut replies, "0 F3000\n");
        rig.settle(&mut host, &mut replies);
        assert_eq!(replies.lines, ["ok"]);
        assert!((rig.machine.positions_mm()[0] - x - 10.0).abs() < 1e-3);
        replies.clear();
        for b in b"M114\n" {
            host.send(&[*b]);
            rig.exchange(&mut host, &mut replies, 60);
        }
        assert_eq!(replies.lines.len(), 2, "{:?}", replies.lines);
        assert!(replies.lines[0].starts_with("X:"), "{:?}", replies.lines);
        assert_eq!(replies.lines[1], "ok");
        // A numbered line whose terminator was lost is still taken once the link is quiet.
        replies.clear();
        host.send(numbered(1, "G1 X-10").as_bytes());
        rig.exchange(&mut host, &mut replies, 200);
        rig.settle(&mut host, &mut replies);
        assert_eq!(replies.lines, ["ok"]);
        assert!((rig.machine.positions_mm()[0] - x).abs() < 1e-3);
    }

    #[test]
    fn a_numbered_line_shaped_like_a_frame_is_a_line() {
        let (mut rig, mut host, mut replies) = numbered_rig();
        // Frames have two digits after `N`: number the lines from 10.
        send(
            &mut rig,
            &mut host,
            &mut replies,
            &format!("{}\n", numbered(9, "M110")),
        );
        replies.clear();
        let mut line = numbered(10, "G91");
        line.push_str(" ;");
        while line.len() < 52 {
            line.push('x');
        }
        line.push('F');
        assert!(forja_protocol::frame::is_frame(line.as_bytes()));
        send(&mut rig, &mut host, &mut replies, &format!("{line}\n"));
        assert_eq!(replies.lines, ["ok"]);
        // The next line is in order: the frame-shaped line was taken as line 10.
        send(
            &mut rig,
            &mut host,
            &mut replies,
            &format!("{}\n", numbered(11, "G90")),
        );
        assert_eq!(replies.lines, ["ok", "ok"]);
    }

    #[test]
    fn garbage_in_a_gcode_line_gets_a_reply_a_gcode_host_reads() {
        let mut rig = Rig::new("default", BoardConfig::default());
        let (link, mut host) = MemoryLink::pair();
        rig.board.add_port(link, false);
        let mut replies = Replies::default();
        send(&mut rig, &mut host, &mut replies, "M105\n");
        replies.clear();
        send(&mut rig, &mut host, &mut replies, "M114\x00\n");
        assert_eq!(replies.lines, ["echo:E8 bad-character", "ok"]);
        assert!(replies.frames().is_empty());
        // Control bytes alone between lines cost no line: no reply.
        replies.clear();
        send(&mut rig, &mut host, &mut replies, "\x00\x01\n");
        assert!(replies.lines.is_empty(), "{:?}", replies.lines);
        // A host that numbers its lines is asked to resend.
        let (mut rig, mut host, mut replies) = numbered_rig();
        send(&mut rig, &mut host, &mut replies, "N0 M1\x0014*99\n");
        assert_eq!(replies.lines, ["rs 0", "ok"]);
    }

    #[test]
    fn the_crc_is_announced_and_a_line_that_fails_it_is_asked_again() {
        let (mut rig, mut host, mut replies) = numbered_rig();
        send(&mut rig, &mut host, &mut replies, "M115\n");
        assert!(
            replies.lines[0].contains("LINE_CHECK:CRC16"),
            "{:?}",
            replies.lines
        );
        replies.clear();
        let line = strong(0, "G91");
        // Two digits swapped in the body: the XOR could not see it.
        let damaged = line.replacen("G91", "G19", 1);
        send(&mut rig, &mut host, &mut replies, &format!("{damaged}\n"));
        assert_eq!(replies.lines, ["rs 0", "ok"]);
        send(&mut rig, &mut host, &mut replies, &format!("{line}\n"));
        assert_eq!(replies.lines, ["rs 0", "ok", "ok"]);
        // Once the CRC is used, a numbered line with the XOR alone is asked again.
        send(
            &mut rig,
            &mut host,
            &mut replies,
            &format!("{}\n", numbered(1, "G90")),
        );
        assert_eq!(replies.lines, ["rs 0", "ok", "ok", "rs 1", "ok"]);
    }
}
