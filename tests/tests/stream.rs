//! A printer job of several hundred numbered, checksummed lines streamed over the
//! pseudo-terminal, as Printrun streams it: homing on the switches, heating, moves with
//! extrusion, the fan, and every report (`M105`, `M114`, `M119`).

use std::time::{Duration, Instant};

use forja_protocol::reply::Reply;
use forja_sim::board::BoardConfig;
use forja_sim::host::GcodeSender;
use forja_sim::link::{PtyLink, TcpLink};
use forja_tests::{HostEnd, PtyHost, Replies, Rig, same_mm, wall_ms};

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
    let mut sender = GcodeSender::new(lines.iter().map(String::as_str)).unwrap();
    sender.timeout_ms = 1_000;
    let start = Instant::now();
    let mut replies = Replies::default();
    let done = rig.run_until(Duration::from_secs(50), |board, _| {
        let received = host.receive();
        replies.feed(&received);
        let out = sender.poll(&received, wall_ms(start));
        if !out.is_empty() {
            host.send(&out);
        }
        let s = board.status();
        sender.is_done() && s.idle && !s.holding
    });
    assert!(done, "the job did not finish: {:?}", rig.board.status());

    // Every line taken once, none refused, none resent on a clean link.
    let stats = sender.stats();
    assert_eq!(stats.acked, sender.len() as u64);
    assert!(stats.faults.is_empty(), "{:?}", stats.faults);
    let status = rig.board.status();
    assert_eq!(status.stats.executed, sender.len() as u32);
    assert_eq!((status.stats.resends, status.stats.refused), (0, 0));
    assert_eq!(replies.lines.first().map(String::as_str), Some("start"));

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
    let oks: Vec<Reply<'_>> = stats
        .other
        .iter()
        .filter_map(|l| Reply::parse(l.as_bytes()).ok())
        .collect();
    let Some((extruder, bed)) = oks.iter().find_map(|r| match r {
        Reply::Temperatures { extruder, bed } => Some((extruder, bed)),
        _ => None,
    }) else {
        panic!("no M105 answer: {:?}", stats.other);
    };
    assert!((extruder.to_f64() - 200.0).abs() <= 2.0, "{extruder}");
    assert!((bed.to_f64() - 60.0).abs() <= 2.0, "{bed}");
    let positions: Vec<&Reply<'_>> = oks
        .iter()
        .filter(|r| matches!(r, Reply::Position(_)))
        .collect();
    assert_eq!(positions.len(), 2);
    let Reply::Position(last) = positions[1] else {
        unreachable!()
    };
    let letters: String = last.iter().map(|w| char::from(w.letter)).collect();
    assert_eq!(letters, "XYZE");
    assert_eq!(last[0].value.to_f64(), x);
    assert_eq!(last[2].value.to_f64(), 10.0);
    assert!(
        stats
            .other
            .contains(&"ok x_min:open y_min:open z_min:open".to_string()),
        "{:?}",
        stats.other
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
    assert_eq!(rig.board.status().stats.faults, 0);
}
