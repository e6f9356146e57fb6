//! Probing (`G38.2`–`G38.5`) and the drilling cycles (`G81`–`G83`, `G98`/`G99`) on the
//! simulated machine: where the steps stop, what is reported, and the moves of each cycle.

mod common;

use common::{machine, sim};
use forja_motion::{Alarm, CommandError, MachineConfig, MachineState, StepQueue};

const HZ: u32 = 1_000_000;
/// Z steps per mm on the test machine.
const Z_STEPS: f64 = 400.0;

fn z_steps(mm: f64) -> i32 {
    (mm * Z_STEPS).round() as i32
}

fn xy_steps(mm: f64) -> i32 {
    (mm * 80.0).round() as i32
}

/// The test machine with a probe wired as switch 0.
fn with_probe() -> MachineConfig<3> {
    let mut c = machine();
    c.probe_switch = Some(0);
    // No homing switches are placed: the probe is the only switch.
    for a in &mut c.axes {
        a.homing = None;
    }
    c
}

#[test]
fn g38_2_stops_on_contact_reports_where_and_goes_on_from_there() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, with_probe(), HZ);
    // The stock's surface: the probe closes at Z = -2.5 mm and below.
    s.add_switch(2, z_steps(-2.5), true);
    s.send("G38.2 Z-10 F100").expect("probe taken");
    // Nothing else is taken while the probe moves: the line after waits.
    assert!(!s.kernel.can_accept());
    assert!(s.run_until_idle(20 * u64::from(HZ)));
    assert_eq!(s.kernel.state(), MachineState::Idle);
    assert_eq!(
        s.positions()[2],
        z_steps(-2.5),
        "stopped at the contact step"
    );
    let report = s.kernel.take_probe_report().expect("a report");
    assert!(report.tripped);
    assert_eq!(report.machine_nm[2], -2_500_000);
    assert_eq!(s.kernel.take_probe_report(), None, "reported once");
    assert_eq!(s.kernel.probe_report(), Some(report), "kept for $#");
    // The position goes on from the contact: a relative move up is 2 mm from there.
    s.send("G91 G0 Z2").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions()[2], z_steps(-0.5));
    let r = s.record();
    assert!(r.violations.is_empty(), "{:?}", r.violations);
}

#[test]
fn g38_2_without_contact_is_an_alarm_and_g38_3_is_not() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, with_probe(), HZ);
    s.add_switch(2, z_steps(-50.0), true);
    s.send("G38.3 Z-3 F200").expect("ok");
    assert!(s.run_until_idle(20 * u64::from(HZ)));
    assert_eq!(s.kernel.state(), MachineState::Idle);
    let report = s.kernel.take_probe_report().expect("a report");
    assert!(!report.tripped);
    assert_eq!(s.positions()[2], z_steps(-3.0), "the whole move ran");
    s.send("G38.2 Z-6 F200").expect("ok");
    assert!(s.run_until_idle(20 * u64::from(HZ)));
    assert_eq!(
        s.kernel.state(),
        MachineState::Alarm(Alarm::ProbeFailContact)
    );
    assert!(!s.kernel.take_probe_report().expect("a report").tripped);
    assert_eq!(s.send("G0 Z0"), Err(CommandError::Locked));
}

#[test]
fn a_probe_already_touching_is_an_alarm_and_nothing_moves() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, with_probe(), HZ);
    s.add_switch(2, z_steps(1.0), true);
    s.send("G38.2 Z-5 F100").expect("taken");
    assert!(s.run_until_idle(20 * u64::from(HZ)));
    assert_eq!(
        s.kernel.state(),
        MachineState::Alarm(Alarm::ProbeFailInitial)
    );
    assert_eq!(s.positions(), [0, 0, 0]);
}

#[test]
fn g38_4_moves_away_until_the_contact_opens() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, with_probe(), HZ);
    // Touching at Z 0.75 mm and below, so touching at the start.
    s.add_switch(2, z_steps(0.75), true);
    s.send("G38.4 Z5 F100").expect("ok");
    assert!(s.run_until_idle(20 * u64::from(HZ)));
    assert_eq!(s.kernel.state(), MachineState::Idle);
    // The contact opens on the first step above 0.75 mm: the move stops before the next.
    assert_eq!(s.positions()[2], z_steps(0.75) + 1);
    assert!(s.kernel.take_probe_report().expect("a report").tripped);
}

#[test]
fn probing_is_refused_without_a_probe_and_without_a_target() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    assert_eq!(s.send("G38.2 Z-5 F100"), Err(CommandError::NoProbe));
    let mut q2 = StepQueue::<3, 256>::new();
    let mut p = sim(&mut q2, with_probe(), HZ);
    assert_eq!(
        p.send("G38.2 F100"),
        Err(CommandError::MissingValue { letter: b'Z' })
    );
}

/// Every turn of Z's direction in the step record, as (direction, steps) runs.
fn z_runs(s: &common::KernelSim<'_, 3, 32, 256>) -> Vec<(i32, i32)> {
    let r = s.record();
    let mut runs: Vec<(i32, i32)> = Vec::new();
    let mut prev = 0;
    for st in &r.steps[2] {
        let d = st.position - prev;
        prev = st.position;
        match runs.last_mut() {
            Some((dir, n)) if *dir == d => *n += 1,
            _ => runs.push((d, 1)),
        }
    }
    runs
}

#[test]
fn g81_drills_each_hole_and_g98_g99_choose_the_retract_height() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G0 X10 Y10 Z5").expect("ok");
    // G98: back to the initial Z (5) after each hole; R is 1, the bottom -2.
    s.send("G98 G81 X20 Y20 Z-2 R1 F300").expect("first hole");
    s.send("X30").expect("second hole, same cycle");
    s.send("G99 X40").expect("third hole, to R");
    s.send("G80").expect("cancel");
    assert_eq!(
        s.send("X50"),
        Err(CommandError::NoMotionMode),
        "no motion mode after G80"
    );
    assert!(s.run_until_idle(60 * u64::from(HZ)));
    assert_eq!(
        s.positions(),
        [xy_steps(40.0), xy_steps(20.0), z_steps(1.0)]
    );
    let runs = z_runs(&s);
    // Z: up to 5, then per hole down to -2 and back up (to 5, 5, then 1).
    let turns: Vec<i32> = runs.iter().map(|(d, _)| *d).collect();
    assert_eq!(turns, [1, -1, 1, -1, 1, -1, 1], "{runs:?}");
    assert_eq!(runs[1].1, z_steps(7.0));
    assert_eq!(runs[6].1, z_steps(3.0));
    assert!(s.record().violations.is_empty());
}

#[test]
fn g83_pecks_and_g82_dwells() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G0 X10 Y10 Z2").expect("ok");
    s.send("G99 G83 X10 Y10 Z-5 R1 Q2 F200").expect("pecks");
    assert!(s.run_until_idle(60 * u64::from(HZ)));
    // From 2 down to R (1) and on to -1, then out to R and in again (a rapid to just above
    // the depth reached, then the feed) to -3, and to -5: three runs down, each followed by a
    // rapid out to R.
    let runs = z_runs(&s);
    let downs: Vec<i32> = runs.iter().filter(|(d, _)| *d < 0).map(|r| r.1).collect();
    assert_eq!(
        downs,
        [z_steps(3.0), z_steps(4.0), z_steps(6.0)],
        "{runs:?}"
    );
    let ups: Vec<i32> = runs.iter().filter(|(d, _)| *d > 0).map(|r| r.1).collect();
    assert_eq!(
        ups[1..],
        [z_steps(2.0), z_steps(4.0), z_steps(6.0)],
        "{runs:?}"
    );
    assert_eq!(s.positions()[2], z_steps(1.0));
    let start = s.now();
    s.send("G82 X20 Z-1 R1 P0.5").expect("dwell cycle");
    assert!(s.run_until_idle(60 * u64::from(HZ)));
    assert!(s.now() - start >= 500_000, "the dwell at the bottom");
    assert_eq!(
        s.send("G83 X30 Z-1 R1 Q0"),
        Err(CommandError::BadValue { letter: b'Q' })
    );
    assert_eq!(
        s.send("G81 X30 Z2 R1"),
        Err(CommandError::BadValue { letter: b'R' }),
        "the bottom above R"
    );
}

#[test]
fn a_cycle_asked_for_while_the_machine_moves_is_served_from_the_next_poll() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    // A slow move: its steps fill the queue's lead, and the polls between top-ups find
    // nothing to do.
    s.send("G1 X40 F600").expect("ok");
    s.advance(u64::from(HZ) / 2);
    // 42 pecks (from R at 1 mm to -20 mm, 0.5 mm each), more moves than the planner holds:
    // the cycle waits on the thread side, which every poll from the next serves (debug builds
    // check that no poll passes it by).
    s.send("G99 G83 X40 Y0 Z-20 R1 Q0.5 F300").expect("pecks");
    assert!(s.run_until_idle(600 * u64::from(HZ)));
    assert_eq!(s.positions(), [xy_steps(40.0), 0, z_steps(1.0)]);
    let downs = z_runs(&s).iter().filter(|(d, _)| *d < 0).count();
    assert_eq!(downs, 42, "{:?}", z_runs(&s));
    assert!(s.record().violations.is_empty());
}
