//! Safety under real use (issue 11): a stop during a hold or during motion keeps the position
//! true, lines taken during a hold run once after it, and values the machine cannot take are
//! refused with a named error, changing nothing.

mod common;

use common::{KernelSim, sim};
use forja_motion::{
    AxisConfig, AxisKind, CommandError, HomeDirection, HomingConfig, MachineConfig, MachineState,
    Reply, StepQueue,
};
use forja_protocol::gcode::{Decimal, Line};

const HZ: u32 = 1_000_000;

/// The simulator's router: X/Y 0..300 mm and Z 0..100 mm with homing switches, a rotary A
/// that turns without limit (±100 000°, as the simulator board maps it), 80 steps/mm on X, Y
/// and A, 400 on Z. Not homed.
fn router() -> MachineConfig<4> {
    let homing = |switch, direction| HomingConfig {
        direction,
        seek_mm_min: 600.0,
        locate_mm_min: 50.0,
        pull_off_mm: 2.0,
        switch,
        order: 1,
    };
    let mut a = AxisConfig::linear(b'A', 80.0, 3600.0, 720.0, 0.0);
    a.kind = AxisKind::Rotary;
    a.min_mm = -100_000.0;
    a.max_mm = 100_000.0;
    MachineConfig::new([
        AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 300.0)
            .with_homing(homing(0, HomeDirection::Min)),
        AxisConfig::linear(b'Y', 80.0, 6000.0, 500.0, 300.0)
            .with_homing(homing(1, HomeDirection::Min)),
        AxisConfig::linear(b'Z', 400.0, 1200.0, 200.0, 100.0)
            .with_homing(homing(2, HomeDirection::Max)),
        a,
    ])
}

type Sim<'q> = KernelSim<'q, 4, 32, 256>;

/// The steps the motors really made.
fn motor(s: &Sim<'_>) -> [i32; 4] {
    s.positions()
}

/// Advance until the hold has come to rest (at most 5 s of virtual time).
/// Send `line`, let it run half a second, then hold and wait until the machine is at rest.
fn held_half_a_second_into(s: &mut Sim<'_>, line: &str) {
    s.send(line).expect("ok");
    s.advance(u64::from(HZ) / 2);
    s.kernel.hold();
    until_held(s);
}

fn until_held(s: &mut Sim<'_>) {
    for _ in 0..5000 {
        s.advance(u64::from(HZ) / 1000);
        if s.kernel.state() == (MachineState::Hold { stopped: true }) {
            return;
        }
    }
    panic!("the hold did not come to rest: {:?}", s.kernel.state());
}

/// `M114` (work) and frame 51 (machine) agree with the motors, to the step.
fn assert_reports_match_motors(s: &Sim<'_>) {
    let m = motor(s);
    assert_eq!(s.kernel.machine_steps(), m, "machine steps");
    let p = s.kernel.position();
    for (i, (steps, axis)) in m.iter().zip(&s.kernel.config().axes).enumerate() {
        let want = f64::from(*steps) / f64::from(axis.steps_per_mm);
        assert!((p.machine_mm[i] - want).abs() < 1e-9, "machine {i}: {p:?}");
        assert!((p.work_mm[i] - want).abs() < 1e-6, "work {i}: {p:?}");
    }
}

fn mm(steps: f64) -> i32 {
    (steps * 80.0).round() as i32
}

#[test]
fn stop_during_a_hold_resyncs_to_the_steps_and_drops_the_plan() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    held_half_a_second_into(&mut s, "G1 X50 F600");
    let held = motor(&s);
    assert!(held[0] > 0 && held[0] < mm(50.0), "{held:?}");
    s.kernel.stop();
    assert!(s.run_until_idle(u64::from(HZ)), "{:?}", s.kernel.state());
    assert_eq!(s.kernel.state(), MachineState::Idle);
    assert_eq!(motor(&s), held, "a stop at rest moves nothing");
    assert_reports_match_motors(&s);
    // The next move runs, from the true position, to its end.
    s.send("G1 X100 F6000").expect("ok");
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(100.0), 0, 0, 0]);
    assert_reports_match_motors(&s);
    // A Start (resume) afterwards revives nothing.
    s.kernel.resume();
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(100.0), 0, 0, 0]);
    s.send("G1 X10 Y10").expect("ok");
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(10.0), mm(10.0), 0, 0]);
    assert_reports_match_motors(&s);
    let r = s.record();
    assert!(r.violations.is_empty(), "{:?}", r.violations);
}

#[test]
fn stop_during_a_hold_that_is_still_decelerating_ends_at_rest_and_resynced() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    s.send("G1 X200 F6000").expect("ok");
    s.send("G1 Y100").expect("ok");
    s.advance(u64::from(HZ));
    s.kernel.hold();
    s.advance(u64::from(HZ) / 100);
    assert_eq!(s.kernel.state(), MachineState::Hold { stopped: false });
    s.kernel.stop();
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.kernel.state(), MachineState::Idle);
    let here = motor(&s);
    assert!(
        here[0] > 0 && here[0] < mm(200.0) && here[1] == 0,
        "{here:?}"
    );
    assert_reports_match_motors(&s);
    s.kernel.resume();
    s.advance(u64::from(HZ));
    assert_eq!(motor(&s), here, "the dropped moves stay dropped");
    s.send("G91 G1 X-1").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(motor(&s), [here[0] - 80, 0, 0, 0]);
    assert_reports_match_motors(&s);
}

#[test]
fn stop_during_motion_resyncs_and_later_moves_start_there() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    s.send("G1 X50 F600").expect("ok");
    s.send("G1 X100").expect("ok");
    s.advance(u64::from(HZ) / 2);
    s.kernel.stop();
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    let here = motor(&s);
    assert!(here[0] > 0 && here[0] < mm(50.0), "{here:?}");
    assert_reports_match_motors(&s);
    s.send("G1 X10 Y10 F6000").expect("ok");
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(10.0), mm(10.0), 0, 0]);
    assert_reports_match_motors(&s);
}

#[test]
fn lines_taken_during_a_hold_run_once_after_resume() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    s.send("G91").expect("ok");
    held_half_a_second_into(&mut s, "G1 X20 F1200");
    let held = motor(&s);
    // Relative moves: running one twice (or dropping it) shows in the end position.
    s.send("G1 X5").expect("taken during the hold");
    s.send("G1 Y3").expect("taken during the hold");
    s.advance(u64::from(HZ));
    assert_eq!(motor(&s), held, "nothing moves while held");
    assert_eq!(s.kernel.state(), MachineState::Hold { stopped: true });
    assert!(!s.kernel.is_idle(), "motion is pending behind the hold");
    s.kernel.resume();
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(25.0), mm(3.0), 0, 0]);
    assert_reports_match_motors(&s);
}

#[test]
fn a_line_that_waits_for_motion_waits_through_a_hold() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    held_half_a_second_into(&mut s, "G1 X20 F1200");
    // `M92` and `M5` wait for the motion before them; a hold does not end that motion.
    let m92 = Line::parse(b"M92 X100").expect("parses");
    assert_eq!(s.kernel.execute(&m92), Ok(Reply::Busy));
    let m5 = Line::parse(b"M5").expect("parses");
    assert_eq!(s.kernel.execute(&m5), Ok(Reply::Busy));
    assert_eq!(s.kernel.config().axes[0].steps_per_mm, 80.0);
}

#[test]
fn a_jog_while_holding_is_refused_not_dropped() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    held_half_a_second_into(&mut s, "G1 X50 F600");
    assert_eq!(
        s.kernel.jog(b'Y', Decimal::new(1, 0), 5),
        Err(CommandError::NotIdle)
    );
    s.kernel.resume();
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(50.0), 0, 0, 0]);
    // At rest, the same jog runs.
    assert_eq!(s.kernel.jog(b'Y', Decimal::new(1, 0), 5), Ok(Reply::Ok));
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(50.0), mm(5.0), 0, 0]);
    assert_reports_match_motors(&s);
}

#[test]
fn a_line_sent_while_a_stop_completes_waits_and_then_runs() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    s.send("G1 X50 F600").expect("ok");
    s.advance(u64::from(HZ) / 2);
    s.kernel.stop();
    let line = Line::parse(b"G1 X10 Y10").expect("parses");
    assert_eq!(
        s.kernel.execute(&line),
        Ok(Reply::Busy),
        "not taken mid-stop"
    );
    assert!(!s.kernel.can_accept());
    // Offered again until taken: it runs after the stop, from where the machine stopped.
    s.send("G1 X10 Y10").expect("taken after the stop");
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(10.0), mm(10.0), 0, 0]);
    assert_reports_match_motors(&s);
}

/// Execute one line on the kernel directly (no retry), as a controller does.
fn exec<'l>(s: &mut Sim<'_>, text: &'l str) -> Result<Reply<'l, 4>, CommandError> {
    let line = Line::parse(text.as_bytes()).expect("parses");
    s.kernel.execute(&line)
}

/// The work position (`M114`), mm.
fn work(s: &Sim<'_>) -> [f64; 4] {
    s.kernel.position().work_mm
}

#[test]
fn g92_with_only_axes_the_machine_lacks_is_refused() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    s.send("G0 X5 Y6 Z7 A8").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(
        exec(&mut s, "G92 E0"),
        Err(CommandError::UnknownAxis { letter: b'E' })
    );
    assert_eq!(
        exec(&mut s, "G92 X0 E0"),
        Err(CommandError::UnknownAxis { letter: b'E' })
    );
    assert_eq!(
        exec(&mut s, "G28 E0"),
        Err(CommandError::UnknownAxis { letter: b'E' })
    );
    assert_eq!(work(&s), [5.0, 6.0, 7.0, 8.0], "no offset changed");
    // A bare G92 still zeroes every axis.
    assert_eq!(exec(&mut s, "G92"), Ok(Reply::Ok));
    assert_eq!(work(&s), [0.0; 4]);
}

#[test]
fn a_repeated_word_is_refused_and_changes_nothing() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    assert_eq!(
        exec(&mut s, "G91 G1 X5 X50 F600"),
        Err(CommandError::RepeatedWord { letter: b'X' })
    );
    // `X0x10` reads as the words X0 and X10.
    assert_eq!(
        exec(&mut s, "G1 X0x10"),
        Err(CommandError::RepeatedWord { letter: b'X' })
    );
    assert_eq!(
        exec(&mut s, "G1 X1 F100 F6000"),
        Err(CommandError::RepeatedWord { letter: b'F' })
    );
    s.advance(u64::from(HZ));
    assert_eq!(motor(&s), [0; 4], "nothing moved");
    // G91 of the refused line did not take: X2 is absolute.
    s.send("G1 X2 F3000").expect("ok");
    s.send("G1 X2").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(2.0), 0, 0, 0]);
    // Modal words of different groups still share a line.
    assert_eq!(exec(&mut s, "G90 G21 G1 X3"), Ok(Reply::Ok));
}

#[test]
fn a_negative_spindle_speed_is_refused() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    for text in ["M3 S-1", "M4 S-0.5", "M3 S99999999999"] {
        assert_eq!(
            exec(&mut s, text),
            Err(CommandError::BadValue { letter: b'S' }),
            "{text}"
        );
    }
    assert!(matches!(exec(&mut s, "M3 S12000"), Ok(Reply::Effect(_))));
    assert!(matches!(exec(&mut s, "M4 S0"), Ok(Reply::Effect(_))));
}

#[test]
fn a_feed_below_the_floor_is_refused_and_one_above_the_maximum_is_capped() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    for text in ["G1 X10 F0.0000001", "G1 F0.5", "G20 G1 X1 F0.03"] {
        assert_eq!(
            exec(&mut s, text),
            Err(CommandError::BadValue { letter: b'F' }),
            "{text}"
        );
    }
    s.advance(u64::from(HZ));
    assert_eq!(motor(&s), [0; 4], "nothing moved");
    // The refused G20 did not switch to inches; the floor itself is taken.
    s.send("G1 X0.05 F1").expect("1 mm/min is the floor");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(motor(&s), [4, 0, 0, 0]);
    // Far above the axis maximum (6000 mm/min): capped, as grbl does.
    let t0 = s.now();
    s.send("G1 X100.05 F1000000").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(motor(&s), [mm(100.05), 0, 0, 0]);
    let took = (s.now() - t0) as f64 / f64::from(HZ);
    assert!(
        took >= 1.0,
        "100 mm at 100 mm/s takes at least 1 s, took {took}"
    );
}

#[test]
fn a_jog_longer_than_the_travel_is_refused_unhomed() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    // Frame 01 `S1000X+9000000`.
    assert_eq!(
        s.kernel.jog(b'X', Decimal::new(1000, 0), 9_000_000),
        Err(CommandError::OutOfReach { axis: 0 })
    );
    // 301 mm on a 300 mm axis.
    assert_eq!(
        s.kernel.jog(b'Y', Decimal::new(1, 0), -301),
        Err(CommandError::OutOfReach { axis: 1 })
    );
    assert_eq!(
        exec(&mut s, "G91 G0 Z-100.5"),
        Err(CommandError::OutOfReach { axis: 2 })
    );
    assert_eq!(work(&s), [0.0; 4], "M114 unchanged");
    s.advance(u64::from(HZ));
    assert_eq!(motor(&s), [0; 4]);
    // The whole travel is possible (the machine does not know where it is yet).
    assert_eq!(s.kernel.jog(b'Z', Decimal::new(1, 0), -100), Ok(Reply::Ok));
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    assert_eq!(motor(&s), [0, 0, -40_000, 0]);
    assert_reports_match_motors(&s);
}

#[test]
fn a_position_that_cannot_be_reported_or_counted_is_refused() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, router(), HZ);
    // Frame 51 holds ±99999.9999.
    assert_eq!(
        exec(&mut s, "G0 A100000"),
        Err(CommandError::OutOfReach { axis: 3 })
    );
    assert_eq!(
        exec(&mut s, "G0 A-100000"),
        Err(CommandError::OutOfReach { axis: 3 })
    );
    assert_eq!(work(&s), [0.0; 4]);
    // At 40000 steps/°, i32 steps end at 53687.09°.
    assert_eq!(exec(&mut s, "M92 A40000"), Ok(Reply::Ok));
    assert_eq!(
        exec(&mut s, "G0 A53688"),
        Err(CommandError::OutOfReach { axis: 3 })
    );
    assert_eq!(exec(&mut s, "M92 A80"), Ok(Reply::Ok));
    // The largest reportable position is taken.
    assert_eq!(exec(&mut s, "G0 A99999.9999"), Ok(Reply::Ok));
    s.kernel.stop();
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_reports_match_motors(&s);
}

#[test]
fn an_extruder_feeds_past_the_reportable_range_within_its_steps() {
    let mut e = AxisConfig::linear(b'E', 93.0, 3000.0, 3000.0, 0.0);
    e.kind = AxisKind::Extruder;
    e.min_mm = -100_000.0;
    e.max_mm = 100_000.0;
    let config = MachineConfig::new([
        AxisConfig::linear(b'X', 80.0, 12000.0, 1000.0, 220.0),
        AxisConfig::linear(b'Y', 80.0, 12000.0, 1000.0, 220.0),
        AxisConfig::linear(b'Z', 400.0, 600.0, 100.0, 250.0),
        e,
    ]);
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, config, HZ);
    // A long print feeds more than 100 m of filament in relative mode.
    s.send("M83").expect("ok");
    for _ in 0..3 {
        assert_eq!(exec(&mut s, "G1 E60000 F3000"), Ok(Reply::Ok));
    }
    s.kernel.stop();
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_reports_match_motors(&s);
    // Its i32 step count still bounds it: at 100 000 steps/mm, 21 474.8 mm.
    s.send("M92 E100000").expect("ok");
    assert_eq!(
        exec(&mut s, "G1 E30000"),
        Err(CommandError::OutOfReach { axis: 3 })
    );
}
