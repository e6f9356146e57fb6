//! The replies and commands of printer hosts, in Marlin's forms (OctoPrint, Printrun, CNCjs).

use super::*;

#[test]
fn a_command_the_firmware_lacks_is_unknown_not_an_error() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M123 S1"), ["echo:Unknown command: \"M123\"", "ok"]);
    assert_eq!(b.ask("G38.6 X1"), ["echo:Unknown command: \"G38.6\"", "ok"]);
    assert_eq!(b.ask("G38.2 X1"), ["echo:E132 no-probe", "ok"]);
    assert_eq!(b.ctl.stats().executed, 0);
}

#[test]
fn m115_names_the_firmware_then_its_capabilities_then_ok() {
    let mut b = Bench::new();
    b.take();
    let out = b.ask("M115");
    assert!(
        out[0].starts_with("FIRMWARE_NAME:Forja FIRMWARE_VERSION:"),
        "{out:?}"
    );
    assert_eq!(out.last().map(String::as_str), Some("ok"));
    let caps: Vec<&str> = out[1..out.len() - 1].iter().map(String::as_str).collect();
    assert!(
        caps.iter()
            .all(|c| c.starts_with("Cap:") && c.ends_with(":1")),
        "{caps:?}"
    );
    for cap in [
        "Cap:EMERGENCY_PARSER:1",
        "Cap:AUTOREPORT_TEMP:1",
        "Cap:THERMAL_PROTECTION:1",
    ] {
        assert!(caps.contains(&cap), "{cap} in {caps:?}");
    }
}

#[test]
fn temperatures_carry_targets_and_power_and_waits_report_without_ok() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M140 S60"), ["ok"]);
    b.run_ms(100);
    let out = b.ask("M105");
    assert_eq!(out.len(), 1, "{out:?}");
    assert!(out[0].starts_with("ok T:20.0 /0.0 B:2"), "{out:?}");
    assert!(out[0].contains(" /60.0 @:0 B@:127"), "{out:?}");
    // M190 waits for the bed alone: reports every second, no `ok` until it is there.
    b.send("M104 S200");
    b.send("M190 S60");
    b.run_ms(1500);
    let out = b.take();
    assert_eq!(out[0], "ok", "{out:?}");
    let reports: Vec<&String> = out.iter().filter(|l| l.starts_with(" T:")).collect();
    assert!(
        !reports.is_empty() && out.len() == 1 + reports.len(),
        "{out:?}"
    );
    assert!(reports[0].contains(" /200.0 B:") && reports[0].contains(" /60.0 @:"));
    b.run_until(10_000, |b| b.ctl.stats().oks == 4);
    // The hot end is far from 200: M190 did not wait for it.
    let hot = b.ctl.peripherals().hot.current_mc;
    assert!(hot < 150_000, "{hot}");
}

#[test]
fn m109_s_waits_only_while_heating_and_r_waits_to_cool() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M109 S25"), Vec::<String>::new());
    b.run_until(5_000, |b| b.ctl.stats().oks == 1);
    // At 25 °C and above the new target: `S` does not wait to cool down.
    assert_eq!(b.ask("M109 S21").last().map(String::as_str), Some("ok"));
    // `R` does.
    assert!(b.ask("M109 R0").is_empty() || b.ctl.stats().oks == 3);
    assert!(b.ask("M109 R21").iter().all(|l| !l.starts_with("ok")));
    b.run_until(5_000, |b| b.ctl.stats().oks >= 4);
    assert!(b.ctl.peripherals().hot.current_mc <= 22_000);
}

#[test]
fn m108_ends_a_heating_wait_as_it_arrives() {
    let mut b = Bench::new();
    b.take();
    b.send("M109 S250");
    b.send("G1 X1 F600");
    b.run_ms(50);
    assert!(b.take().is_empty());
    b.send("M108");
    b.run_ms(20);
    let out = b.take();
    assert_eq!(out.iter().filter(|l| *l == "ok").count(), 3, "{out:?}");
}

#[test]
fn m400_answers_when_the_motion_is_done_with_busy_meanwhile() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("G1 X30 F600"), ["ok"]);
    b.send("M400");
    b.run_ms(2_500);
    assert_eq!(b.take(), ["echo:busy: processing"]);
    assert!(!b.ctl.kernel().is_idle());
    b.run_until(10_000, |b| b.ctl.stats().oks == 2);
    assert_eq!(b.take(), ["ok"]);
    assert!(b.ctl.kernel().is_idle());
    assert_eq!(b.position_mm()[0], 30.0);
    // `M113 S0` silences it; `M113` tells the period.
    assert_eq!(b.ask("M113"), ["echo:M113 S2", "ok"]);
    assert_eq!(b.ask("M113 S0"), ["ok"]);
    assert_eq!(b.ask("G1 X0"), ["ok"]);
    b.send("M400");
    b.run_until(10_000, |b| b.ctl.stats().oks == 6);
    assert_eq!(b.take(), ["ok"]);
}

#[test]
fn m410_stops_the_motion_at_once_and_keeps_the_homing() {
    let mut b = Bench::new();
    b.take();
    b.send("G28 X");
    b.idle();
    b.take();
    assert_eq!(b.ask("G1 X100 F3000"), ["ok"]);
    b.send("G1 X150");
    b.send("G1 X200");
    b.run_ms(300);
    b.take();
    b.send("M410");
    b.run_ms(5);
    b.idle();
    let out = b.take();
    assert!(
        out.iter().all(|l| l == "ok" || l.starts_with("echo:E")),
        "{out:?}"
    );
    let x = b.position_mm()[0];
    assert!(x > 1.0 && x < 100.0, "stopped on the way: {x}");
    assert_eq!(b.ctl.kernel().homed_axes() & 1, 1);
    assert_eq!(b.ask("G1 X10"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 10.0);
}

#[test]
fn progress_messages_and_host_lines() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M73 P12 R40"), ["ok"]);
    assert_eq!(b.ask("M73 L3"), ["ok"]);
    let p = b.ctl.host_progress();
    assert_eq!(
        (p.percent, p.remaining_min, p.layer),
        (Some(12), Some(40), Some(3))
    );
    assert_eq!(b.ask("M117 Printing part 1"), ["ok"]);
    assert_eq!(b.ctl.message(), "Printing part 1");
    assert_eq!(b.ask("M118 E1 Hello"), ["echo:Hello", "ok"]);
    assert_eq!(b.ask("M118 A1 action:pause"), ["// action:pause", "ok"]);
    assert_eq!(b.ask("M118 plain"), ["plain", "ok"]);
}

#[test]
fn m155_reports_temperatures_until_stopped() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M155 S1"), ["ok"]);
    b.run_ms(3_050);
    let out = b.take();
    assert_eq!(out.len(), 3, "{out:?}");
    assert!(
        out.iter()
            .all(|l| l.starts_with(" T:20.0 /0.0 B:20.0 /0.0"))
    );
    assert_eq!(b.ask("M155 S0"), ["ok"]);
    b.run_ms(3_000);
    assert!(b.take().is_empty());
}

#[test]
fn a_halted_machine_says_so_at_connection_and_refuses_moves() {
    let mut b = Bench::new();
    b.take();
    b.send("M112");
    b.run_ms(5);
    assert_eq!(b.take(), ["Error:E153 emergency-stop", "ok"]);
    let out = b.ask("M110 N0");
    assert_eq!(
        out,
        [
            "// action:notification Machine halted: E153 emergency-stop. Send M999 to clear.",
            "ok"
        ]
    );
    assert_eq!(b.ask("G1 X1"), ["echo:E125 alarm-locked", "ok"]);
    assert_eq!(b.ask("M999"), ["ok"]);
    assert_eq!(b.ask("M110 N0"), ["ok"]);
}

#[test]
fn releasing_some_axes_keeps_the_drivers_energised_until_all_are_released() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("G1 X1 F3000"), ["ok"]);
    b.idle();
    assert!(b.ctl.peripherals().motors);
    assert_eq!(b.ask("M84 X Y"), ["ok"]);
    assert!(b.ctl.peripherals().motors, "Z still held");
    assert_eq!(b.ask("M18 Z"), ["ok"]);
    assert!(!b.ctl.peripherals().motors);
}

#[test]
fn planner_settings_are_stored_loaded_reset_and_reported() {
    let mut b = Bench::new();
    b.take();
    let report = b.ask("M503");
    assert_eq!(report.last().map(String::as_str), Some("ok"));
    assert!(
        report.contains(&"echo:  M92 X80.00 Y80.00 Z400.00".to_string()),
        "{report:?}"
    );
    assert!(report.contains(&"echo:  M204".to_string()), "{report:?}");
    assert_eq!(b.ask("M92 X100"), ["ok"]);
    assert_eq!(b.ask("M204 P500 T900"), ["ok"]);
    assert_eq!(b.ask("M500"), ["echo:Settings stored", "ok"]);
    assert_eq!(
        b.ask("M502"),
        ["echo:Hardcoded default settings loaded", "ok"]
    );
    let report = b.ask("M503");
    assert!(
        report.contains(&"echo:  M92 X80.00 Y80.00 Z400.00".to_string()),
        "{report:?}"
    );
    assert!(report.contains(&"echo:  M204".to_string()), "{report:?}");
    assert_eq!(b.ask("M501"), ["echo:Stored settings retrieved", "ok"]);
    let report = b.ask("M503");
    assert!(
        report.contains(&"echo:  M92 X100.00 Y80.00 Z400.00".to_string()),
        "{report:?}"
    );
    assert!(
        report.contains(&"echo:  M204 P500.00 T900.00".to_string()),
        "{report:?}"
    );
    assert_eq!(b.ask("M500 X1"), ["echo:E127 unknown-axis X", "ok"]);
    // Switched off and on: the stored path limits are the kernel's at once.
    let (program, storage, physical) = b.power_off();
    let mut b = Bench::boot(machine(), program, storage, physical);
    b.take();
    let report = b.ask("M503");
    assert!(
        report.contains(&"echo:  M204 P500.00 T900.00".to_string()),
        "{report:?}"
    );
}

#[test]
fn m501_waits_for_the_motion_before_it() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M92 X160"), ["ok"]);
    assert_eq!(b.ask("M500"), ["echo:Settings stored", "ok"]);
    assert_eq!(
        b.ask("M502"),
        ["echo:Hardcoded default settings loaded", "ok"]
    );
    assert_eq!(b.ask("G1 X10 F600"), ["ok"]);
    b.send("M501");
    b.run_ms(5);
    assert!(b.take().is_empty(), "held while X moves");
    b.run_until(5_000, |b| b.ctl.stats().oks == 5);
    assert_eq!(b.take(), ["echo:Stored settings retrieved", "ok"]);
    assert_eq!(b.position_mm()[0], 10.0);
    assert_eq!(b.ctl.kernel().machine_steps()[0], 1600);
}

#[test]
fn g4_answers_after_the_motion_before_it_and_its_dwell() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("G1 X20 F1200"), ["ok"]);
    b.send("G4 P500");
    b.send("M105");
    b.run_ms(50);
    assert!(b.take().is_empty(), "held while X moves");
    b.run_until(10_000, |b| b.ctl.stats().oks == 3);
    assert!(b.ctl.kernel().is_idle());
    assert_eq!(b.position_mm()[0], 20.0);
    let out = b.take();
    assert_eq!(out[0], "ok", "{out:?}");
    assert!(out[1].starts_with("ok T:"), "{out:?}");
}

#[test]
fn outputs_the_power_supply_and_a_device_the_board_lacks() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M42 P1 S255"), ["ok"]);
    assert!(b.ctl.peripherals().outputs[1].0 && !b.ctl.peripherals().outputs[0].0);
    assert_eq!(b.ask("M42 P1 S0"), ["ok"]);
    assert!(!b.ctl.peripherals().outputs[1].0);
    assert_eq!(b.ask("M42 P7 S1"), ["echo:E194 no-device output 7", "ok"]);
    assert_eq!(b.ask("M42 S1"), ["echo:E122 missing-value P", "ok"]);
    assert_eq!(b.ask("M80"), ["ok"]);
    assert!(b.ctl.peripherals().psu.0);
    // `M81` waits for the motion before it.
    assert_eq!(b.ask("G1 X20 F1200"), ["ok"]);
    b.send("M81");
    b.run_ms(50);
    assert!(b.take().is_empty() && b.ctl.peripherals().psu.0);
    b.run_until(10_000, |b| b.ctl.stats().oks == 7);
    assert_eq!(b.take(), ["ok"]);
    assert!(!b.ctl.peripherals().psu.0);
    assert_eq!(b.position_mm()[0], 20.0);
    assert_eq!(b.ask("M141 S40"), ["echo:E194 no-device chamber", "ok"]);
    assert_eq!(
        b.ask("M104 T1 S200"),
        ["echo:E194 no-device hot end 1", "ok"]
    );
}

#[test]
fn m300_hands_its_tone_to_the_beeper_as_marlin_queues_it() {
    let mut b = Bench::new();
    b.take();
    let tones = |b: &Bench| b.ctl.peripherals().beeper.as_ref().unwrap().0.clone();
    assert_eq!(b.ask("M300 S440 P200"), ["ok"]);
    assert_eq!(b.ask("M300"), ["ok"], "Marlin's 260 Hz for 1 s");
    assert_eq!(b.ask("M300 S0 P150"), ["ok"], "a pause");
    assert_eq!(tones(&b), [(440, 200), (260, 1000), (0, 150)]);
    assert_eq!(b.ask("M300 S30000"), ["echo:E121 bad-value S", "ok"]);
    assert_eq!(tones(&b).len(), 3);
    // The tone is handed over as its line is read, while the move before it runs; after
    // `M400`, once the move is done.
    assert_eq!(b.ask("G1 X20 F1200"), ["ok"]);
    assert_eq!(b.ask("M300 S880 P100"), ["ok"]);
    assert_eq!(tones(&b).last(), Some(&(880, 100)));
    assert!(b.position_mm()[0] < 20.0);
    b.send("M400");
    b.send("M300 S660 P100");
    b.run_ms(50);
    assert_eq!(tones(&b).len(), 4);
    b.run_until(10_000, |b| {
        b.ctl.peripherals().beeper.as_ref().unwrap().0.len() == 5
    });
    assert_eq!(b.position_mm()[0], 20.0);
    assert_eq!(tones(&b).last(), Some(&(660, 100)));
    assert_eq!(b.take(), ["ok", "ok"]);
}

#[test]
fn m300_without_a_beeper_names_the_device() {
    let mut b = Bench::new();
    b.ctl.peripherals_mut().beeper = None;
    b.take();
    assert_eq!(
        b.ask("M300 S440 P200"),
        ["echo:E194 no-device beeper", "ok"]
    );
    // Checked before the device: a bad value is a bad value.
    assert_eq!(b.ask("M300 P-5"), ["echo:E121 bad-value P", "ok"]);
    assert_eq!(b.ask("M114").last().map(String::as_str), Some("ok"));
}
