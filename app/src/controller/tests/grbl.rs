//! The grbl 1.1 dialect on the link: how a link enters it, the realtime bytes, the answers,
//! the status report and the `$` commands, as grbl senders use them.

use forja_protocol::grbl::StatusText;

use super::*;

/// The status report among `lines`, as text.
fn report(lines: &[String]) -> String {
    lines
        .iter()
        .find(|l| l.starts_with('<'))
        .cloned()
        .unwrap_or_else(|| panic!("no status report in {lines:?}"))
}

/// The field `name` of the report `line`.
fn field(line: &str, name: &str) -> String {
    let text = StatusText::parse(line.as_bytes()).expect("a report");
    String::from_utf8(text.field(name.as_bytes()).expect(name).to_vec()).unwrap()
}

fn state(line: &str) -> String {
    let text = StatusText::parse(line.as_bytes()).expect("a report");
    String::from_utf8(text.state().to_vec()).unwrap()
}

/// The answer to `?` now.
fn status(b: &mut Bench) -> String {
    b.send_raw(b"?");
    b.run_ms(2);
    report(&b.take())
}

/// The `Ov:` field of the next report that has one (grbl sends it every tenth report, between
/// the `WCO` ones, and in the report after an override changed unless `WCO` is due).
fn overrides(b: &mut Bench) -> String {
    for _ in 0..12 {
        let r = status(b);
        if StatusText::parse(r.as_bytes())
            .unwrap()
            .field(b"Ov")
            .is_some()
        {
            return field(&r, "Ov");
        }
    }
    panic!("no Ov in twelve reports");
}

/// What the test board's spindle was last told.
fn spindle(b: &Bench) -> Option<Turning> {
    b.ctl.peripherals().spindle.last
}

/// A bench whose link has entered the grbl dialect with a soft reset.
fn grbl() -> Bench {
    let mut b = Bench::new();
    b.take();
    b.send_raw(&[0x18]);
    b.run_ms(5);
    let out = b.take();
    assert!(
        out.contains(&"Grbl 1.1h ['$' for help]".to_string()),
        "{out:?}"
    );
    b
}

#[test]
fn a_link_enters_the_dialect_at_a_reset_a_status_poll_or_a_dollar_line() {
    let _ = grbl();
    // CNCjs, when it saw no banner: `?` alone.
    let mut b = Bench::new();
    b.take();
    b.send_raw(b"?");
    b.run_ms(5);
    let out = b.take();
    assert_eq!(state(&report(&out)), "Idle");
    assert_eq!(field(&report(&out), "MPos"), "0.000,0.000,0.000");
    assert_eq!(b.ask("G1 X1 F600"), ["ok"]);
    // `$$` from a RepRap link.
    let mut b = Bench::new();
    b.take();
    let out = b.ask("$$");
    assert!(out.contains(&"$100=80.000".to_string()), "{out:?}");
    assert_eq!(out.last().map(String::as_str), Some("ok"));
    // A `?` inside a RepRap line is part of the line, and no report goes out.
    let mut b = Bench::new();
    b.take();
    let out = b.ask("M117 Ready?");
    assert!(!out.iter().any(|l| l.starts_with('<')), "{out:?}");
}

#[test]
fn every_line_gets_ok_or_a_grbl_error_and_line_numbers_are_not_checked() {
    let mut b = grbl();
    assert_eq!(b.ask("N10 G21 G90"), ["ok"]);
    assert_eq!(b.ask("N20 G0 X5"), ["ok"]);
    assert_eq!(b.ask("G5"), ["error:20"]);
    assert_eq!(b.ask("G0 X1 X2"), ["error:25"]);
    assert_eq!(b.ask("G0 G1 X1"), ["error:21"]);
    assert_eq!(b.ask("G0 X9999"), ["error:15"]);
    assert_eq!(b.ask("M123"), ["error:20"]);
    assert_eq!(b.ask("(a comment)"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 5.0);
}

#[test]
fn realtime_bytes_act_inside_a_line_and_never_damage_it() {
    let mut b = grbl();
    b.send_raw(b"G1 X2?0 F6");
    b.send_raw(b"00\n");
    b.run_ms(5);
    let out = b.take();
    assert!(out.iter().any(|l| l.starts_with('<')), "{out:?}");
    assert!(out.contains(&"ok".to_string()), "{out:?}");
    b.idle();
    assert_eq!(b.position_mm()[0], 20.0, "the line was G1 X20 F600");
}

#[test]
fn feed_hold_and_cycle_start() {
    let mut b = grbl();
    assert_eq!(b.ask("G1 X30 F600"), ["ok"]);
    b.run_ms(500);
    b.send_raw(b"!");
    b.run_ms(400);
    let held = status(&mut b);
    assert!(state(&held).starts_with("Hold"), "{held}");
    let x = b.position_mm()[0];
    b.run_ms(500);
    assert_eq!(b.position_mm()[0], x, "nothing moves during a hold");
    b.send_raw(b"~");
    b.idle();
    assert_eq!(b.position_mm()[0], 30.0, "the move goes on to its end");
    assert_eq!(b.violations(), 0);
}

#[test]
fn a_soft_reset_stops_drops_what_waits_and_locks_a_machine_it_stopped_moving() {
    let mut b = grbl();
    for x in 1..=20 {
        b.send(&format!("G1 X{x} F300"));
    }
    b.run_ms(300);
    b.take();
    b.send_raw(&[0x18]);
    b.run_ms(5);
    let out = b.take();
    // grbl's order: the alarm, the banner, how to unlock; the alarm said once.
    let banner = out.iter().position(|l| l == "Grbl 1.1h ['$' for help]");
    let alarm = out.iter().position(|l| l == "ALARM:3");
    assert!(alarm.is_some() && alarm < banner, "{out:?}");
    assert_eq!(
        out.iter().filter(|l| l.starts_with("ALARM")).count(),
        1,
        "{out:?}"
    );
    assert!(
        !out.contains(&"ok".to_string()),
        "no answer for dropped lines: {out:?}"
    );
    b.idle();
    let stopped = b.position_mm()[0];
    assert!(stopped < 20.0, "the lines after the reset did not run");
    assert_eq!(state(&status(&mut b)), "Alarm");
    assert_eq!(b.ask("G0 X0"), ["error:9"]);
    assert_eq!(b.ask("$X"), ["[MSG:Caution: Unlocked]", "ok"]);
    assert_eq!(b.ask("G0 X0"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 0.0);
}

#[test]
fn a_reset_at_rest_keeps_the_machine_unlocked() {
    let mut b = grbl();
    assert_eq!(b.ask("G0 X3"), ["ok"]);
    b.idle();
    b.send_raw(&[0x18]);
    b.run_ms(5);
    b.take();
    let r = status(&mut b);
    assert_eq!(state(&r), "Idle");
    assert_eq!(field(&r, "MPos"), "3.000,0.000,0.000");
}

#[test]
fn the_status_report_has_the_buffer_line_feed_and_offsets() {
    let mut b = grbl();
    assert_eq!(b.ask("$10=3"), ["ok"]);
    assert_eq!(b.ask("G92 X-10"), ["ok"]);
    let r = status(&mut b);
    assert_eq!(field(&r, "MPos"), "0.000,0.000,0.000");
    assert_eq!(field(&r, "WCO"), "10.000,0.000,0.000");
    let bf = field(&r, "Bf");
    let (blocks, bytes) = bf.split_once(',').unwrap();
    assert!(blocks.parse::<u32>().unwrap() > 0);
    assert!(bytes.parse::<u32>().unwrap() >= 128, "{r}");
    assert_eq!(b.ask("$10=2"), ["ok"]);
    let r = status(&mut b);
    assert_eq!(field(&r, "WPos"), "-10.000,0.000,0.000");
    assert_eq!(b.ask("N7 G1 X20 F600"), ["ok"]);
    b.run_ms(300);
    let r = status(&mut b);
    assert_eq!(state(&r), "Run");
    assert_eq!(field(&r, "FS"), "600,0");
}

#[test]
fn the_feed_and_rapid_overrides_are_the_kernels_realtime_ones_and_m220_is_apart() {
    let mut b = grbl();
    b.send_raw(&[0x91, 0x91, 0x93]);
    b.run_ms(2);
    assert_eq!(b.ctl.kernel().realtime_overrides(), (121, 100));
    b.send_raw(&[0x90]);
    b.run_ms(2);
    assert_eq!(b.ctl.kernel().realtime_overrides(), (100, 100));
    for _ in 0..30 {
        b.send_raw(&[0x92]);
    }
    b.run_ms(2);
    assert_eq!(b.ctl.kernel().realtime_overrides(), (10, 100));
    // At most 16 realtime bytes wait at once: send them in two reads.
    for _ in 0..2 {
        b.send_raw(&[0x91; 10]);
        b.run_ms(2);
    }
    b.send_raw(&[0x96]);
    b.run_ms(2);
    assert_eq!(b.ctl.kernel().realtime_overrides(), (200, 50));
    b.send_raw(&[0x97]);
    b.run_ms(2);
    assert_eq!(b.ctl.kernel().realtime_overrides(), (200, 25));
    b.send_raw(&[0x95, 0x90]);
    b.run_ms(2);
    assert_eq!(b.ctl.kernel().realtime_overrides(), (100, 100));
    // Marlin's `M220` stays the planner's own override.
    assert_eq!(b.ctl.kernel().feed_override_percent(), 100);
    assert_eq!(b.ask("M220 S50"), ["ok"]);
    assert_eq!(b.ctl.kernel().feed_override_percent(), 50);
    assert_eq!(b.ctl.kernel().realtime_overrides(), (100, 100));
}

#[test]
fn the_feed_override_acts_on_the_move_under_way_and_fs_reports_the_speed_now() {
    let mut b = grbl();
    assert_eq!(b.ask("G1 X40 F600"), ["ok"]);
    b.run_ms(300);
    assert_eq!(field(&status(&mut b), "FS"), "600,0");
    // +100 %: the move under way speeds up, and `FS:` reports the speed now.
    for _ in 0..10 {
        b.send_raw(&[0x91]);
    }
    b.run_ms(300);
    let r = status(&mut b);
    assert_eq!(field(&r, "FS"), "1200,0");
    let start = b.position_mm()[0];
    b.run_ms(500);
    let mm = b.position_mm()[0] - start;
    assert!((mm - 10.0).abs() < 0.2, "1200 mm/min for 0.5 s: {mm}");
    b.idle();
    assert_eq!(field(&status(&mut b), "FS"), "0,0");
    // The rapid override slows `G0`: 6000 mm/min at 25 %.
    b.send_raw(&[0x97]);
    b.run_ms(2);
    assert_eq!(b.ask("G0 X0"), ["ok"]);
    b.run_ms(400);
    assert_eq!(field(&status(&mut b), "FS"), "1500,0");
    b.idle();
    assert_eq!(b.violations(), 0);
}

#[test]
fn ov_reports_feed_rapid_and_spindle_overrides_and_a_reset_or_program_end_clears_them() {
    let mut b = grbl();
    b.send_raw(&[0x91, 0x96, 0x9A, 0x9A, 0x9C]);
    b.run_ms(2);
    assert_eq!(overrides(&mut b), "110,50,121");
    // Sent again in the next report once they change.
    b.send_raw(&[0x9B]);
    b.run_ms(2);
    assert_eq!(field(&status(&mut b), "Ov"), "110,50,111");
    assert_eq!(b.ask("M30"), ["[MSG:Pgm End]", "ok"]);
    assert_eq!(field(&status(&mut b), "Ov"), "100,100,100");
    b.send_raw(&[0x92, 0x97, 0x9B]);
    b.run_ms(2);
    assert_eq!(field(&status(&mut b), "Ov"), "90,25,90");
    b.send_raw(&[0x18]);
    b.run_ms(5);
    b.take();
    assert_eq!(overrides(&mut b), "100,100,100");
    assert_eq!(b.ctl.kernel().realtime_overrides(), (100, 100));
}

#[test]
fn dollar_commands_answer_as_grbl() {
    let mut b = grbl();
    let out = b.ask("$");
    assert!(out[0].starts_with("[HLP:"), "{out:?}");
    let out = b.ask("$I");
    assert!(out[0].starts_with("[VER:1.1h."), "{out:?}");
    assert!(out[1].starts_with("[OPT:"), "{out:?}");
    let out = b.ask("$G");
    assert_eq!(out[0], "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F1000 S0]");
    let out = b.ask("$#");
    assert!(
        out.contains(&"[G92:0.000,0.000,0.000]".to_string()),
        "{out:?}"
    );
    assert!(out.iter().any(|l| l.starts_with("[PRB:")), "{out:?}");
    assert_eq!(b.ask("$Q"), ["error:3"]);
    assert_eq!(b.ask("$100=abc"), ["error:2"]);
    assert_eq!(b.ask("$999=1"), ["error:3"]);
}

#[test]
fn settings_are_set_under_grbls_numbers_and_stored() {
    let mut b = grbl();
    let before = b.ask("$$");
    assert!(before.contains(&"$110=6000.000".to_string()), "{before:?}");
    assert_eq!(b.ask("$110=3000"), ["ok"]);
    let after = b.ask("$$");
    assert!(after.contains(&"$110=3000.000".to_string()), "{after:?}");
    assert_eq!(b.ask("$100=-5"), ["error:4"]);
    assert_eq!(b.ask("$RST=$"), ["[MSG:Restoring defaults]", "ok"]);
    let restored = b.ask("$$");
    assert!(
        restored.contains(&"$110=6000.000".to_string()),
        "{restored:?}"
    );
}

#[test]
fn jogs_move_relative_without_changing_the_modal_state_and_0x85_cancels() {
    let mut b = grbl();
    assert_eq!(b.ask("$J=G91 X5 F1200"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 5.0);
    let out = b.ask("$G");
    assert!(out[0].contains("G90"), "the jog's G91 was its own: {out:?}");
    assert_eq!(b.ask("$J=X5"), ["error:16"], "a jog needs a feed");
    assert_eq!(b.ask("$J=G91 X9999 F600"), ["error:15"]);
    assert_eq!(b.ask("$J=G91 X50 F300"), ["ok"]);
    b.run_ms(300);
    assert_eq!(state(&status(&mut b)), "Jog");
    b.send_raw(&[0x85]);
    b.idle();
    let x = b.position_mm()[0];
    assert!(x > 5.0 && x < 55.0, "the jog stopped short: {x}");
}

#[test]
fn homing_answers_when_it_ends_and_check_mode_runs_nothing() {
    let mut b = grbl();
    b.send("$H");
    b.run_ms(5);
    assert!(!b.take().contains(&"ok".to_string()), "no ok while homing");
    b.idle();
    b.run_ms(5);
    assert_eq!(b.take(), ["ok"]);
    let homed = b.position_mm();
    assert_eq!(b.ask("$C"), ["[MSG:Enabled]", "ok"]);
    assert_eq!(b.ask("G0 X7"), ["ok"]);
    assert_eq!(b.ask("G2 X1"), ["error:28"]);
    b.run_ms(100);
    assert_eq!(b.position_mm(), homed, "check mode moves nothing");
    assert_eq!(b.ask("$C"), ["[MSG:Disabled]", "ok"]);
}

#[test]
fn work_offsets_are_reported_used_and_survive_a_restart() {
    let mut b = grbl();
    assert_eq!(b.ask("G0 X10 Y5"), ["ok"]);
    b.idle();
    // A sender's "zero here".
    assert_eq!(b.ask("G10 L20 P0 X0 Y0"), ["ok"]);
    let r = status(&mut b);
    assert_eq!(field(&r, "WCO"), "10.000,5.000,0.000");
    let out = b.ask("$#");
    assert!(
        out.contains(&"[G54:10.000,5.000,0.000]".to_string()),
        "{out:?}"
    );
    assert_eq!(b.ask("G0 X1"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 11.0, "work X1 is machine X11");
    // G55, G53, G43.1 as CAM posts use them.
    assert_eq!(b.ask("G10 L2 P2 X-5"), ["ok"]);
    assert_eq!(b.ask("G55 G0 X0"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], -5.0);
    let out = b.ask("$G");
    assert!(out[0].contains(" G55 "), "{out:?}");
    assert_eq!(b.ask("G53 G0 X2"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 2.0);
    assert_eq!(b.ask("G43.1 Z1.5"), ["ok"]);
    let out = b.ask("$#");
    assert!(out.contains(&"[TLO:1.500]".to_string()), "{out:?}");
    // The table is stored once the machine rests, and read back at start-up.
    b.run_ms(20);
    let (program, storage, physical) = b.power_off();
    let mut again = Bench::boot(machine(), program, storage, physical);
    again.take();
    let out = again.ask("$#");
    assert!(
        out.contains(&"[G54:10.000,5.000,0.000]".to_string()),
        "{out:?}"
    );
    assert!(
        out.contains(&"[G55:-5.000,0.000,0.000]".to_string()),
        "{out:?}"
    );
    assert!(
        out.contains(&"[TLO:0.000]".to_string()),
        "the tool length offset is not kept"
    );
    // `$RST=#` clears them, stored too.
    assert_eq!(again.ask("$RST=#"), ["[MSG:Restoring defaults]", "ok"]);
    let out = again.ask("$#");
    assert!(
        out.contains(&"[G54:0.000,0.000,0.000]".to_string()),
        "{out:?}"
    );
}

#[test]
fn grbl_meanings_g28_to_the_stored_position_g4_in_seconds_m0_and_m6_until_cycle_start() {
    let mut b = grbl();
    assert_eq!(b.ask("G0 X20 Z5"), ["ok"]);
    b.idle();
    assert_eq!(b.ask("G28.1"), ["ok"]);
    assert_eq!(b.ask("G0 X40 Y10 Z10"), ["ok"]);
    b.idle();
    // Fusion 360's retract: `G28 G91 Z0` goes up through here to the stored Z.
    assert_eq!(b.ask("G28 G91 Z0"), ["ok"]);
    assert_eq!(b.ask("G90"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm(), [40.0, 10.0, 5.0]);
    assert_eq!(b.ask("G28"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm(), [20.0, 0.0, 5.0]);
    // `G4 P0.2`: 0.2 s.
    b.send("G4 P0.2");
    b.run_ms(100);
    assert!(b.take().is_empty(), "still dwelling");
    b.run_ms(200);
    assert_eq!(b.take(), ["ok"]);
    // `T2 M6`: the machine holds, tells the tool, and goes on at cycle start.
    b.send("T2 M6");
    b.send("G0 X0");
    b.run_ms(50);
    let out = b.take();
    assert!(
        out.contains(&"[MSG:Change to tool T2, then cycle start]".to_string()),
        "{out:?}"
    );
    assert!(state(&status(&mut b)).starts_with("Hold"));
    b.run_ms(200);
    assert_eq!(b.position_mm()[0], 20.0, "nothing moves before cycle start");
    b.send_raw(b"~");
    b.idle();
    assert_eq!(b.position_mm()[0], 0.0);
    assert_eq!(b.take(), ["ok"], "the line after M6 ran once resumed");
    // `M0` holds the same way.
    assert_eq!(b.ask("M0"), ["ok"]);
    assert!(b.ask("G0 X3").is_empty(), "the line waits for the pause");
    b.send_raw(b"~");
    b.idle();
    assert_eq!(b.position_mm()[0], 3.0);
}

#[test]
fn m62_to_m65_switch_outputs_with_the_motion_or_at_once() {
    let mut b = grbl();
    assert_eq!(b.ask("M64 P0"), ["ok"]);
    assert!(b.ctl.peripherals().outputs[0].0, "M64: on at once");
    assert_eq!(b.ask("G1 X20 F1200"), ["ok"]);
    b.send("M63 P0");
    b.run_ms(50);
    assert!(b.take().is_empty(), "M63 waits for the move before it");
    assert!(b.ctl.peripherals().outputs[0].0);
    b.idle();
    b.run_ms(5);
    assert_eq!(b.take(), ["ok"]);
    assert!(!b.ctl.peripherals().outputs[0].0);
    assert_eq!(b.position_mm()[0], 20.0);
    assert_eq!(b.ask("M62 P1"), ["ok"]);
    assert!(b.ctl.peripherals().outputs[1].0);
    assert_eq!(b.ask("M65 P1"), ["ok"]);
    assert!(!b.ctl.peripherals().outputs[1].0);
    assert_eq!(b.ask("M64 P9"), ["error:20"], "no output 9 on this board");
    assert_eq!(b.ask("M64"), ["error:28"]);
}

#[test]
fn extended_ascii_bytes_are_dropped_and_no_busy_line_goes_out() {
    let mut b = grbl();
    // A sender that writes the override 0x91 as UTF-8 (`C2 91`).
    b.send_raw(&[0xC2, 0x91]);
    b.send_raw(b"G1 X40. F600.\n");
    b.run_ms(5);
    assert_eq!(b.take(), ["ok"]);
    assert_eq!(b.ctl.kernel().realtime_overrides(), (110, 100));
    // A line waiting behind a full planner gets no `busy: processing`.
    for x in 0..40 {
        b.send(&format!("G1 X{} F300", x % 2));
    }
    b.run_ms(5_000);
    assert!(
        !b.take().iter().any(|l| l.contains("busy")),
        "no RepRap keep-alive in the grbl dialect"
    );
}

#[test]
fn program_end_and_coolant_off_answer_as_grbl() {
    let mut b = grbl();
    b.send_raw(&[0x91]);
    b.run_ms(2);
    b.ctl.peripherals_mut().coolant = None;
    assert_eq!(b.ask("M9"), ["ok"], "nothing to turn off without coolant");
    assert_eq!(b.ask("M8"), ["error:20"]);
    assert_eq!(b.ask("M30"), ["[MSG:Pgm End]", "ok"]);
    assert_eq!(b.ctl.kernel().realtime_overrides(), (100, 100));
}

#[test]
fn a_probe_answers_after_its_report_and_sets_what_a_probe_macro_expects() {
    let mut config = machine();
    config.probe_switch = Some(2);
    let mut b = Bench::with_machine(config);
    // The probe: a touch plate the tool meets 2.5 mm below where Z starts (400 steps/mm).
    b.wiring.add_switch(2, -1000, true);
    b.take();
    b.send_raw(&[0x18]);
    b.run_ms(5);
    b.take();
    // CNCjs's "probe Z" macro: relative probe down, then the plate's thickness as work Z.
    assert_eq!(b.ask("G91"), ["ok"]);
    b.send("G38.2 Z-10 F100");
    b.run_ms(20);
    assert_eq!(
        b.take(),
        Vec::<String>::new(),
        "no ok while the probe moves"
    );
    b.idle();
    b.run_ms(5);
    assert_eq!(b.take(), ["[PRB:0.000,0.000,-2.500:1]", "ok"]);
    assert_eq!(b.position_mm()[2], -2.5);
    assert_eq!(b.ask("G90"), ["ok"]);
    assert_eq!(b.ask("G10 L20 P1 Z0.5"), ["ok"]);
    let params = b.ask("$#");
    assert!(
        params.contains(&"[G54:0.000,0.000,-3.000]".to_string()),
        "{params:?}"
    );
    assert!(
        params.contains(&"[PRB:0.000,0.000,-2.500:1]".to_string()),
        "{params:?}"
    );
    // Probing again while touching the plate: grbl's ALARM:4, and nothing moves.
    b.send("G38.2 Z-12 F100");
    b.idle();
    b.run_ms(5);
    let out = b.take();
    assert!(out.contains(&"ALARM:4".to_string()), "{out:?}");
    assert_eq!(b.position_mm()[2], -2.5);
    assert_eq!(b.ask("$X"), ["[MSG:Caution: Unlocked]", "ok"]);
    // Up and away from the plate (work Z 3 is machine Z 0): G38.4 stops where the contact
    // opens, one step above it.
    b.send("G38.4 Z3 F50");
    b.idle();
    b.run_ms(5);
    assert_eq!(b.take(), ["[PRB:0.000,0.000,-2.497:1]", "ok"]);
}

#[test]
fn drilling_cycles_run_in_the_grbl_dialect_and_the_parser_state_names_them() {
    let mut b = grbl();
    assert_eq!(b.ask("G0 X10 Y10 Z5"), ["ok"]);
    assert_eq!(b.ask("G99 G83 X20 Y20 Z-3 R1 Q1 F300"), ["ok"]);
    assert_eq!(b.ask("X30"), ["ok"]);
    let state = b.ask("$G");
    assert!(state[0].starts_with("[GC:G83 G54 G17 G21 G90"), "{state:?}");
    assert_eq!(b.ask("G80"), ["ok"]);
    assert_eq!(b.ask("X40"), ["error:31"]);
    b.idle();
    assert_eq!(b.position_mm(), [30.0, 20.0, 1.0]);
}

#[test]
fn the_spindle_override_scales_the_commanded_speed_and_later_m3_keeps_it() {
    let mut b = grbl();
    assert_eq!(b.ask("M3 S1000"), ["ok"]);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 1000)));
    b.send_raw(&[0x9A, 0x9A]);
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 1200)));
    let r = status(&mut b);
    assert_eq!(field(&r, "FS"), "0,1200", "the speed in force");
    // `$G` reports the programmed speed.
    assert!(b.ask("$G")[0].ends_with(" S1000]"));
    assert_eq!(b.ask("M4 S2000"), ["ok"]);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::CounterClockwise, 2400)),
        "a later M4 keeps the override"
    );
    assert_eq!(b.ask("S500"), ["ok"]);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::CounterClockwise, 600))
    );
    b.send_raw(&[0x99]);
    b.run_ms(2);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::CounterClockwise, 500))
    );
    for _ in 0..30 {
        b.send_raw(&[0x9B]);
    }
    b.run_ms(2);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::CounterClockwise, 50)),
        "10 % at least"
    );
    assert_eq!(b.ask("M5"), ["ok"]);
    assert_eq!(spindle(&b), Some(Turning::Stopped));
    assert_eq!(field(&status(&mut b), "FS"), "0,0");
}

#[test]
fn spindle_stop_toggles_the_spindle_only_in_a_hold_at_rest_and_cycle_start_restores_it() {
    let mut b = grbl();
    assert_eq!(b.ask("M3 S1000"), ["ok"]);
    assert_eq!(b.ask("G1 X30 F600"), ["ok"]);
    b.run_ms(200);
    b.send_raw(&[0x9E]);
    b.run_ms(2);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::Clockwise, 1000)),
        "not while moving"
    );
    b.send_raw(b"!");
    b.run_ms(400);
    assert_eq!(state(&status(&mut b)), "Hold:0");
    b.send_raw(&[0x9E]);
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::Stopped));
    let r = overrides(&mut b);
    assert_eq!(r, "100,100,100");
    b.send_raw(&[0x9E]);
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 1000)));
    b.send_raw(&[0x9E]);
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::Stopped));
    // Cycle start: the spindle first, then the motion.
    b.send_raw(b"~");
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 1000)));
    b.idle();
    assert_eq!(b.position_mm()[0], 30.0);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 1000)));
}

#[test]
fn the_spindle_follows_s_on_motion_lines() {
    let mut b = grbl();
    assert_eq!(b.ask("M3 S1000"), ["ok"]);
    assert_eq!(b.ask("G1 X10 S3000 F600"), ["ok"]);
    b.run_ms(100);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 3000)));
    assert_eq!(field(&status(&mut b), "FS"), "600,3000");
    assert_eq!(b.ask("G1 X20 S500"), ["ok"]);
    b.idle();
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 500)));
    assert!(b.ask("$G")[0].ends_with(" S500]"));
    // Stopped, the spindle stays stopped; the next `M3` runs at the `S` in force.
    assert_eq!(b.ask("M5"), ["ok"]);
    assert_eq!(b.ask("G1 X0 S8000"), ["ok"]);
    b.idle();
    assert_eq!(spindle(&b), Some(Turning::Stopped));
    assert_eq!(b.ask("M3"), ["ok"]);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 8000)));
    // The override applies to the speed the moves carry.
    b.send_raw(&[0x9B]);
    b.run_ms(2);
    assert_eq!(b.ask("G1 X5 S2000"), ["ok"]);
    b.idle();
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 1800)));
}

#[test]
fn laser_mode_m4_power_follows_the_speed_and_rapids_never_burn() {
    let mut b = grbl();
    assert_eq!(b.ask("$32=1"), ["ok"]);
    assert!(b.ask("$$").contains(&"$32=1".to_string()));
    assert_eq!(b.ask("M4 S1000"), ["ok"]);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::CounterClockwise, 0)),
        "off at rest"
    );
    // Z accelerates at 200 mm/s² to 15 mm/s: 75 ms of ramp at each end.
    b.send("G1 Z10 F900");
    let mut powers = Vec::new();
    for _ in 0..1000 {
        b.run_ms(1);
        if let Some(Turning::At(Rotation::CounterClockwise, p)) = spindle(&b) {
            powers.push(p);
        }
        if b.ctl.kernel().is_idle() && b.position_mm()[2] == 10.0 {
            break;
        }
    }
    b.run_ms(5);
    assert!(powers.contains(&1000), "full power at speed");
    assert!(
        powers.iter().any(|&p| p > 100 && p < 900),
        "part power while accelerating: {powers:?}"
    );
    assert!(powers.iter().all(|&p| p <= 1000));
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::CounterClockwise, 0)),
        "off at rest again"
    );
    b.take();
    // A rapid with the laser on does not burn.
    b.send("G0 X30");
    b.run_ms(50);
    assert!(b.ctl.kernel().speed_mm_min() > 0.0);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::CounterClockwise, 0))
    );
    b.idle();
    // The override scales the power too.
    b.send_raw(&[0x9B, 0x9B]);
    b.send("G1 X0 F600");
    b.run_ms(300);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::CounterClockwise, 800))
    );
    b.idle();
    b.take();
    // Out of laser mode an `M4` runs as a spindle, at rest too.
    b.send_raw(&[0x99]);
    assert_eq!(b.ask("$32=0"), ["ok"]);
    b.run_ms(2);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::CounterClockwise, 1000))
    );
    assert_eq!(b.violations(), 0);
}

#[test]
fn laser_mode_m3_is_constant_power_in_a_feed_mode_and_off_in_a_hold() {
    let mut b = grbl();
    assert_eq!(b.ask("$32=1"), ["ok"]);
    assert_eq!(b.ask("M3 S800"), ["ok"]);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::Clockwise, 0)),
        "G0 is the motion mode after a reset: off"
    );
    // grbl's focusing: `M3` in `G1` mode is on at rest.
    assert_eq!(b.ask("G1"), ["ok"]);
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 800)));
    b.send("G1 Z10 F900");
    b.run_ms(20);
    assert_eq!(
        spindle(&b),
        Some(Turning::At(Rotation::Clockwise, 800)),
        "constant while accelerating"
    );
    // A hold at rest turns the laser off; 0x9E turns it on again, cycle start restores it.
    b.send_raw(b"!");
    b.run_ms(300);
    assert_eq!(state(&status(&mut b)), "Hold:0");
    assert_eq!(spindle(&b), Some(Turning::Stopped));
    b.send_raw(&[0x9E]);
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 800)));
    b.send_raw(&[0x9E]);
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::Stopped));
    b.send_raw(b"~");
    b.run_ms(30);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 800)));
    // A hold resumed otherwise (a frame client's pause and start) turns it on again too.
    b.ctl.kernel_mut().hold();
    b.run_ms(300);
    assert_eq!(spindle(&b), Some(Turning::Stopped));
    b.ctl.kernel_mut().resume();
    b.run_ms(30);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 800)));
    b.idle();
    assert_eq!(b.position_mm()[2], 10.0);
    // `M0` pauses as a hold does: the laser is off until cycle start.
    assert_eq!(b.ask("M0"), ["ok"]);
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::Stopped));
    b.send_raw(b"~");
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 800)));
    assert_eq!(b.ask("G0"), ["ok"]);
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 0)));
    // `$32` is refused while the machine moves.
    assert_eq!(b.ask("G0 X50"), ["ok"]);
    assert_eq!(b.ask("$32=0"), ["error:8"]);
    b.idle();
    assert!(b.ask("$$").contains(&"$32=1".to_string()));
}

#[test]
fn more_settings_are_mapped_persisted_and_refused_with_grbls_numbers() {
    let mut b = grbl();
    let all = b.ask("$$");
    for line in [
        "$10=1",
        "$11=0.010",
        "$12=0.002",
        "$13=0",
        "$22=1",
        "$24=300.000",
        "$25=3000.000",
        "$27=1.000",
        "$32=0",
    ] {
        assert!(all.contains(&line.to_string()), "{line} in {all:?}");
    }
    assert_eq!(b.ask("$12=0.01"), ["ok"]);
    assert_eq!(b.ask("$25=2000"), ["ok"]);
    assert_eq!(b.ask("$24=150.5"), ["ok"]);
    assert_eq!(b.ask("$27=2"), ["ok"]);
    assert_eq!(b.ask("$10=0"), ["ok"]);
    assert_eq!(b.ask("$32=1"), ["ok"]);
    // Every homing axis takes it; the others have none.
    let m = b.ctl.settings().machine();
    for axis in 0..2 {
        let h = m.axes[axis].homing.unwrap();
        assert_eq!(
            (h.seek_mm_min, h.locate_mm_min, h.pull_off_mm),
            (2000.0, 150.5, 2.0)
        );
    }
    assert!(m.axes[2].homing.is_none());
    // Refused: beyond the rate, locate above seek, negative, not a flag's number.
    assert_eq!(b.ask("$25=9000"), ["error:39"]);
    assert_eq!(b.ask("$24=2500"), ["error:39"]);
    assert_eq!(b.ask("$27=-1"), ["error:4"]);
    assert_eq!(b.ask("$12=0"), ["error:39"]);
    assert_eq!(b.ask("$10=300"), ["error:39"]);
    assert_eq!(b.ask("$25=abc"), ["error:2"]);
    // `$22` follows the machine configuration: the same value is accepted, another refused.
    assert_eq!(b.ask("$22=1"), ["ok"]);
    let out = b.ask("$22=0");
    assert_eq!(out.len(), 2, "{out:?}");
    assert!(out[0].starts_with("[MSG:$22 "), "{out:?}");
    assert_eq!(out[1], "error:39");
    // All stored: read back after a restart.
    b.run_ms(20);
    let (program, storage, physical) = b.power_off();
    let mut again = Bench::boot(machine(), program, storage, physical);
    again.take();
    let all = again.ask("$$");
    for line in [
        "$10=0",
        "$12=0.010",
        "$24=150.500",
        "$25=2000.000",
        "$27=2.000",
        "$32=1",
    ] {
        assert!(all.contains(&line.to_string()), "{line} in {all:?}");
    }
    assert!(
        StatusText::parse(status(&mut again).as_bytes())
            .unwrap()
            .field(b"WPos")
            .is_some(),
        "$10=0 reports WPos"
    );
    // `$RST=$` brings them back.
    assert_eq!(again.ask("$RST=$"), ["[MSG:Restoring defaults]", "ok"]);
    let all = again.ask("$$");
    assert!(all.contains(&"$32=0".to_string()), "{all:?}");
    assert!(all.contains(&"$25=3000.000".to_string()), "{all:?}");
    assert!(all.contains(&"$10=1".to_string()), "{all:?}");
}

#[test]
fn dollar_dollar_lists_every_setting_once_in_grbl_order() {
    let numbers = |out: &[String]| -> Vec<u16> {
        out.iter()
            .filter_map(|l| l.strip_prefix('$')?.split_once('=')?.0.parse().ok())
            .collect()
    };
    let mut b = Bench::new();
    b.take();
    let out = b.ask("$$");
    assert_eq!(out.last().map(String::as_str), Some("ok"));
    let axes = |base: u16| (0..3).map(move |a| base + a);
    let mut expected = std::vec![10, 11, 12, 13, 20, 21, 22, 24, 25, 27, 32];
    expected.extend(axes(100).chain(axes(110)).chain(axes(120)).chain(axes(130)));
    assert_eq!(numbers(&out), expected, "{out:?}");
    // Every one of them can be set to the value it reports (`$22` and the travel included).
    for line in out.iter().filter(|l| l.starts_with('$')) {
        assert_eq!(b.ask(line), ["ok"], "{line}");
    }
    assert_eq!(b.ask("$$"), out);
    assert_eq!(b.ask("$133=1"), ["error:3"]);
    assert_eq!(b.ask("$23=1"), ["error:3"]);
}

#[test]
fn a_machine_without_homing_reports_22_as_0_and_has_no_homing_settings() {
    let mut config = machine();
    for a in &mut config.axes {
        a.homing = None;
    }
    let mut b = Bench::with_machine(config);
    b.take();
    let all = b.ask("$$");
    assert!(all.contains(&"$22=0".to_string()), "{all:?}");
    assert!(!all.iter().any(|l| l.starts_with("$25=")), "{all:?}");
    assert_eq!(b.ask("$25=100"), ["error:3"]);
    assert_eq!(b.ask("$22=0"), ["ok"]);
}

#[test]
fn report_inches_gives_positions_and_rates_in_inches() {
    let mut b = grbl();
    assert_eq!(b.ask("G0 X25.4 Y12.7"), ["ok"]);
    b.idle();
    assert_eq!(b.ask("G10 L20 P1 X0"), ["ok"]);
    assert_eq!(b.ask("$13=1"), ["ok"]);
    let r = status(&mut b);
    assert_eq!(field(&r, "MPos"), "1.000,0.500,0.000");
    assert_eq!(field(&r, "WCO"), "1.000,0.000,0.000");
    let out = b.ask("$#");
    assert!(
        out.contains(&"[G54:1.000,0.000,0.000]".to_string()),
        "{out:?}"
    );
    // 1270 mm/min is 50 in/min.
    assert_eq!(b.ask("G1 X127 F1270"), ["ok"]);
    b.run_ms(500);
    assert_eq!(field(&status(&mut b), "FS"), "50,0");
    b.idle();
    assert_eq!(b.ask("$13=0"), ["ok"]);
    // Work X127 is machine X152.4.
    assert_eq!(field(&status(&mut b), "MPos"), "152.400,12.700,0.000");
}

#[test]
fn startup_lines_are_stored_listed_and_run_after_each_reset_and_at_power_on() {
    let mut b = grbl();
    assert_eq!(b.ask("$N"), ["$N0=", "$N1=", "ok"]);
    assert_eq!(b.ask("$N0=G55 G91"), ["ok"]);
    assert_eq!(b.ask("$N1=G5"), ["error:20"], "checked before it is kept");
    assert_eq!(b.ask("$N"), ["$N0=G55 G91", "$N1=", "ok"]);
    assert_eq!(
        b.ask("$G")[0],
        "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F1000 S0]"
    );
    // Beyond the machine: checks (the travel is not checked ahead), fails when it runs.
    assert_eq!(b.ask("$N1=G0 X900"), ["ok"]);
    b.send_raw(&[0x18]);
    b.run_ms(5);
    let out = b.take();
    let banner = out
        .iter()
        .position(|l| l == "Grbl 1.1h ['$' for help]")
        .unwrap();
    assert_eq!(
        out[banner + 1..],
        [">G55 G91:ok", ">G0 X900:error:15"],
        "{out:?}"
    );
    assert!(b.ask("$G")[0].starts_with("[GC:G0 G55 G17 G21 G91"));
    // At power-on too, after `start`.
    b.run_ms(20);
    let (program, storage, physical) = b.power_off();
    let mut again = Bench::boot(machine(), program, storage, physical);
    assert_eq!(again.take(), ["start", ">G55 G91:ok", ">G0 X900:error:15"]);
    // The link stays in its dialect: a RepRap line gets a RepRap answer.
    assert_eq!(again.ask("G5"), ["echo:Unknown command: \"G5\"", "ok"]);
    // Cleared with an empty line, and all with `$RST=*`.
    assert_eq!(again.ask("$N1="), ["ok"]);
    assert_eq!(again.ask("$N"), ["$N0=G55 G91", "$N1=", "ok"]);
    assert_eq!(again.ask("$RST=*"), ["[MSG:Restoring defaults]", "ok"]);
    assert_eq!(again.ask("$N"), ["$N0=", "$N1=", "ok"]);
}

#[test]
fn startup_lines_do_not_run_after_a_reset_that_leaves_an_alarm() {
    let mut b = grbl();
    assert_eq!(b.ask("$N0=G55"), ["ok"]);
    assert_eq!(b.ask("G1 X30 F600"), ["ok"]);
    b.run_ms(200);
    b.send_raw(&[0x18]);
    b.run_ms(5);
    let out = b.take();
    assert!(out.contains(&"ALARM:3".to_string()), "{out:?}");
    assert!(!out.iter().any(|l| l.starts_with('>')), "{out:?}");
}

#[test]
fn a_percent_line_is_answered_ok_and_does_nothing() {
    let mut b = grbl();
    assert_eq!(b.ask("%"), ["ok"]);
    assert_eq!(b.ask(" % "), ["ok"]);
    assert_eq!(b.ask("G0 X1"), ["ok"]);
    assert_eq!(b.ask("%"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 1.0);
    assert_eq!(b.ask("G0 X2 %"), ["error:1"]);
}

#[test]
fn a_blank_line_is_answered_ok_as_grbl_answers_it() {
    let mut b = grbl();
    assert_eq!(b.ask(""), ["ok"]);
    assert_eq!(b.ask("   "), ["ok"]);
    assert_eq!(b.ask("; only a comment"), ["ok"]);
}

#[test]
fn the_safety_door_holds_stops_spindle_and_coolant_and_cycle_start_brings_them_back() {
    let mut b = grbl();
    assert_eq!(b.ask("M3 S1000"), ["ok"]);
    assert_eq!(b.ask("M8"), ["ok"]);
    assert_eq!(b.ask("G1 X30 F600"), ["ok"]);
    b.run_ms(300);
    b.send_raw(&[0x84]);
    b.run_ms(2);
    assert_eq!(state(&status(&mut b)), "Door:1", "stopping");
    b.run_ms(400);
    assert_eq!(state(&status(&mut b)), "Door:0", "at rest, ready to resume");
    let x = b.position_mm()[0];
    assert!(x < 30.0);
    assert_eq!(spindle(&b), Some(Turning::Stopped));
    assert_eq!(super::coolant(&b), (false, false));
    b.run_ms(300);
    assert_eq!(
        b.position_mm()[0],
        x,
        "nothing moves while the door is open"
    );
    b.send_raw(b"~");
    b.run_ms(2);
    assert_eq!(spindle(&b), Some(Turning::At(Rotation::Clockwise, 1000)));
    assert_eq!(super::coolant(&b), (false, true));
    b.idle();
    assert_eq!(b.position_mm()[0], 30.0, "the move goes on to its end");
    assert_eq!(state(&status(&mut b)), "Idle");
}

#[test]
fn a_link_that_runs_reprap_lines_stays_in_that_dialect_whatever_a_damaged_byte_reads() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("G0 X1"), ["ok"]);
    // A bit flip that makes `8` (0x38) a ctrl-x (0x18), inside a line and between lines.
    b.send_raw(b"G0 X\x18\n");
    b.run_ms(5);
    let out = b.take();
    assert!(!out.iter().any(|l| l.starts_with("Grbl")), "{out:?}");
    assert!(!out.iter().any(|l| l.starts_with("ALARM")), "{out:?}");
    b.send_raw(&[0x18]);
    b.send_raw(b"?");
    b.run_ms(5);
    let out = b.take();
    assert!(
        !out.iter()
            .any(|l| l.starts_with("Grbl") || l.starts_with('<')),
        "{out:?}"
    );
    assert_eq!(b.ask("M114").last().map(String::as_str), Some("ok"));
}
