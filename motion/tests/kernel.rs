//! Behaviour of the whole kernel on the simulated machine: arcs, feed hold, homing, limits,
//! effects, program stops, jogs, dwells.

mod common;

use common::{check_axis, machine, sim};
use forja_motion::effect::{Effect, StopKind, TemperatureWait};
use forja_motion::{Alarm, CommandError, MachineState, Reply, StepQueue};
use forja_protocol::gcode::{Decimal, Line};

const HZ: u32 = 1_000_000;

fn steps(mm: f64) -> i32 {
    (mm * 80.0).round() as i32
}

#[test]
fn arcs_end_exactly_at_their_end_point() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G1 X50 Y50 F3000").expect("ok");
    s.send("G2 X65.006 Y40.829 I10 J-0.5").expect("ij arc");
    s.send("G3 X80 Y40.456 R10.0005").expect("r arc");
    s.send("G2 X80 Y40.456 I-5 J5 Z3.21").expect("full helix");
    s.send("G3 X70.001 Y52 R-9").expect("long way round");
    assert!(s.run_until_idle(60 * u64::from(HZ)));
    let r = s.record();
    assert_eq!(
        r.position,
        [steps(70.001), steps(52.0), (3.21f64 * 400.0).round() as i32]
    );
    assert!(r.violations.is_empty(), "{:?}", r.violations);
}

#[test]
fn feed_hold_stops_on_the_path_and_resume_loses_no_step() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G1 X150 Y75 F6000").expect("ok");
    s.advance(u64::from(HZ) / 2);
    let before = s.positions();
    assert!(before[0] > 0 && before[0] < steps(150.0));
    s.kernel.hold();
    let mut stopped_at = None;
    for _ in 0..2000 {
        s.advance(u64::from(HZ) / 1000);
        if s.kernel.state() == (MachineState::Hold { stopped: true }) {
            stopped_at = Some(s.now());
            break;
        }
    }
    assert!(stopped_at.is_some(), "hold came to rest");
    let held = s.positions();
    // Still on the path: X:Y = 2:1 within a step.
    assert!((held[0] - 2 * held[1]).abs() <= 2, "{held:?}");
    assert!(held[0] < steps(150.0));
    s.advance(u64::from(HZ));
    assert_eq!(s.positions(), held, "no motion while held");
    s.kernel.resume();
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    let r = s.record();
    assert_eq!(r.position, [steps(150.0), steps(75.0), 0]);
    assert!(r.violations.is_empty(), "{:?}", r.violations);
    // The deceleration and the restart respect the axis limits.
    let c = machine();
    for i in 0..2 {
        let a = &c.axes[i];
        let d = check_axis(
            &r.steps[i],
            0,
            f64::from(a.steps_per_mm),
            f64::from(a.max_rate_mm_s()),
            f64::from(a.accel_mm_s2),
            f64::from(HZ),
            None,
        );
        assert!(d.rate <= 1.01 && d.accel <= 1.01, "{d:?}");
    }
}

#[test]
fn homing_finds_the_switch_backs_off_and_sets_the_position() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    // The X switch sits 1234 steps below the power-on position, the Y switch 3000 below.
    s.add_switch(0, -1234, true);
    s.add_switch(1, -3000, true);
    s.send("G28").expect("ok");
    assert!(s.run_until_idle(120 * u64::from(HZ)));
    assert_eq!(s.kernel.state(), MachineState::Idle);
    assert_eq!(s.kernel.homed_axes(), 0b011);
    // Home is min_mm = 0 at the switch; the pull-off leaves the axis 1 mm (80 steps) above it.
    assert_eq!(s.kernel.machine_steps()[..2], [80, 80]);
    let r = s.record();
    assert_eq!(r.position[..2], [-1234 + 80, -3000 + 80]);
    assert!(r.violations.is_empty(), "{:?}", r.violations);
    // The X sequence: seek down, back off up, locate down slowly, pull off up.
    let xs = &r.steps[0];
    let mut runs = Vec::new();
    let mut prev = 0;
    for st in xs {
        let d = st.position - prev;
        prev = st.position;
        if runs.last().map(|(dir, _)| *dir) != Some(d) {
            runs.push((d, 0));
        }
        if let Some(last) = runs.last_mut() {
            last.1 += 1;
        }
    }
    let dirs: Vec<i32> = runs.iter().map(|(d, _)| *d).collect();
    assert_eq!(dirs, [-1, 1, -1, 1], "{runs:?}");
    // After homing, positions are machine positions.
    s.send("G1 X10 F3000").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.kernel.machine_steps()[0], 800);
}

#[test]
fn homing_without_a_switch_in_reach_raises_an_alarm() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.add_switch(0, -100_000, true);
    s.add_switch(1, -100, true);
    s.send("G28 X0").expect("ok");
    assert!(s.run_until_idle(120 * u64::from(HZ)));
    assert_eq!(
        s.kernel.state(),
        MachineState::Alarm(Alarm::HomingSwitchNotFound { axis: 0 })
    );
    // Travel 200 mm plus twice the pull-off was searched.
    assert_eq!(s.positions()[0], -steps(202.0));
    assert_eq!(s.send("G1 X1"), Err(CommandError::Locked));
    s.kernel.reset();
    s.poll();
    assert_eq!(s.kernel.state(), MachineState::Idle);
    // The machine is 202 mm below its start: back to it would be longer than the travel.
    s.send("G91 G1 X1 F1000").expect("after reset");
}

#[test]
fn a_tripped_hard_limit_stops_motion_within_one_step_period() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.add_switch(0, -500, true);
    s.add_switch(1, -100_000, true);
    s.send("G1 X-20 Y-5 F3000").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(
        s.kernel.state(),
        MachineState::Alarm(Alarm::HardLimit { axis: 0 })
    );
    let r = s.record();
    // The switch closed on the step to -500; the next step was refused.
    assert_eq!(r.position[0], -500);
    let xs = &r.steps[0];
    let last = xs[xs.len() - 1].tick;
    let period = last - xs[xs.len() - 2].tick;
    // No axis stepped later than one X step period after the trip.
    for axis in &r.steps {
        if let Some(st) = axis.last() {
            assert!(
                st.tick <= last + period,
                "{} > {} + {}",
                st.tick,
                last,
                period
            );
        }
    }
    assert!(r.violations.is_empty(), "{:?}", r.violations);
    assert_eq!(s.send("G1 X0"), Err(CommandError::Locked));
    s.kernel.reset();
    assert_eq!(s.kernel.homed_axes(), 0);
}

#[test]
fn homing_samples_the_switch_at_every_step_without_reported_edges() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    // A board that never reports an edge: the simulation's watch goes to another queue.
    let other = Box::leak(Box::new(StepQueue::<3, 8>::new()));
    let (_, other_isr) = forja_motion::split::<3, 4, 8>(
        other,
        machine(),
        HZ,
        forja_hal_abstraction::stepper::StepTiming::CONSERVATIVE,
    )
    .unwrap();
    s.wiring.alert = other_isr.switch_alert();
    s.add_switch(0, -1234, true);
    s.send("G28 X0").expect("ok");
    assert!(s.run_until_idle(120 * u64::from(HZ)));
    assert_eq!(s.kernel.state(), MachineState::Idle);
    assert_eq!(s.kernel.homed_axes(), 0b001);
    assert_eq!(s.positions()[0], -1234 + 80);
}

#[test]
fn a_move_towards_a_switch_already_triggered_is_stopped_before_its_first_step() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    // Triggered from the start, before anything sampled or reported it.
    s.add_switch(0, 0, true);
    s.add_switch(1, -100_000, true);
    s.send("G1 X-5 F3000").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(
        s.kernel.state(),
        MachineState::Alarm(Alarm::HardLimit { axis: 0 })
    );
    assert_eq!(s.positions()[0], 0);
    assert!(s.record().steps[0].is_empty());
    // Away from it is allowed after a reset (hard limits stop motion towards a switch only).
    s.kernel.reset();
    s.send("G1 X5 F3000").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.kernel.state(), MachineState::Idle);
    assert_eq!(s.positions()[0], 400);
}

#[test]
fn soft_limits_reject_moves_before_they_are_planned() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.add_switch(0, 0, true);
    s.add_switch(1, 0, true);
    // Not homed yet: no soft limits (WhenHomed).
    s.send("G1 X-0.5 F3000").expect("not homed: allowed");
    s.send("G28").expect("ok");
    assert!(s.run_until_idle(120 * u64::from(HZ)));
    assert_eq!(s.send("G1 X-0.1"), Err(CommandError::SoftLimit { axis: 0 }));
    assert_eq!(
        s.send("G1 Y200.5"),
        Err(CommandError::SoftLimit { axis: 1 })
    );
    // An arc whose ends are inside but whose bulge is not.
    s.send("G1 X3 Y100").expect("inside");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(
        s.send("G2 X3 Y110 I0 J5"),
        Err(CommandError::SoftLimit { axis: 0 })
    );
    assert_eq!(s.kernel.planned_blocks(), 0);
    s.send("G1 X199.9 Y199.9").expect("inside");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
}

#[test]
fn a_tone_comes_back_at_once_while_the_moves_before_it_run() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G1 X20 F3000").expect("ok");
    // Marlin queues `M300` to its beeper as the line is read, not after the planner's moves.
    let line = Line::parse(b"M300 S440 P200").expect("parse");
    assert_eq!(
        s.kernel.execute(&line),
        Ok(Reply::Effect(Effect::Tone {
            frequency_hz: 440,
            duration_ms: 200
        }))
    );
    assert!(!s.kernel.is_idle());
    assert!(s.positions()[0] < steps(20.0));
    // After `M400`, it sounds once the move is done.
    let line = Line::parse(b"M400").expect("parse");
    while s.kernel.execute(&line) == Ok(Reply::Busy) {
        s.advance(1000);
    }
    assert_eq!(s.positions()[0], steps(20.0));
}

#[test]
fn effects_come_back_in_stream_order() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G1 X20 F3000").expect("ok");
    // A temperature target is for now: returned while the move runs.
    let line = Line::parse(b"M104 S210").expect("parse");
    assert!(matches!(
        s.kernel.execute(&line),
        Ok(Reply::Effect(Effect::SetTemperature {
            wait: TemperatureWait::No,
            ..
        }))
    ));
    assert!(!s.kernel.is_idle());
    // A fan change waits for the move before it.
    let line = Line::parse(b"M106 S128").expect("parse");
    let mut waited = 0;
    loop {
        match s.kernel.execute(&line) {
            Ok(Reply::Busy) => {
                waited += 1;
                s.advance(1000);
            }
            Ok(Reply::Effect(Effect::Fan {
                index: 0,
                duty: 128,
            })) => break,
            other => panic!("{other:?}"),
        }
    }
    assert!(waited > 100);
    assert!(s.kernel.is_idle());
    assert_eq!(s.positions()[0], steps(20.0));
    let line = Line::parse(b"M114").expect("parse");
    match s.kernel.execute(&line) {
        Ok(Reply::Position(p)) => {
            assert_eq!(p.letters, *b"XYZ");
            assert!((p.work_mm[0] - 20.0).abs() < 1e-9);
            assert!((p.machine_mm[0] - 20.0).abs() < 1e-9);
        }
        other => panic!("{other:?}"),
    }
    let line = Line::parse(b"M999").expect("parse");
    assert_eq!(
        s.kernel.execute(&line),
        Err(CommandError::Unsupported {
            letter: b'M',
            number: Some(999)
        })
    );
}

#[test]
fn program_stop_emergency_stop_and_pause() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G1 X10 F3000").expect("ok");
    s.send("M0").expect("after the move");
    assert_eq!(s.positions()[0], steps(10.0));
    assert_eq!(s.kernel.state(), MachineState::Halted);
    assert_eq!(s.send("G1 X0"), Err(CommandError::Halted));
    s.kernel.reset();
    s.send("G1 X0 F3000").expect("after reset");
    s.send("M226").expect("pause");
    assert_eq!(s.kernel.state(), MachineState::Paused);
    let line = Line::parse(b"G1 X5").expect("parse");
    assert_eq!(s.kernel.execute(&line), Ok(Reply::Busy));
    s.kernel.resume();
    s.send("G1 X50").expect("resumed");
    s.advance(u64::from(HZ) / 4);
    let line = Line::parse(b"M112").expect("parse");
    assert_eq!(
        s.kernel.execute(&line),
        Ok(Reply::Effect(Effect::Stopped(StopKind::Emergency)))
    );
    let at = s.positions()[0];
    s.advance(u64::from(HZ) / 10);
    assert_eq!(s.positions()[0], at, "motion cut at once");
    assert!(at < steps(50.0));
    assert_eq!(s.kernel.state(), MachineState::Alarm(Alarm::EmergencyStop));
    assert_eq!(s.send("G28"), Err(CommandError::Locked));
    s.kernel.reset();
    s.poll();
    assert_eq!(s.kernel.state(), MachineState::Idle);
    assert!(s.record().violations.is_empty());
}

#[test]
fn stop_keeps_the_position_and_flushes_the_plan() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G1 X100 F3000").expect("ok");
    s.send("G1 Y100").expect("ok");
    s.advance(u64::from(HZ));
    s.kernel.stop();
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    let here = s.positions();
    assert!(
        here[0] > 0 && here[0] < steps(100.0) && here[1] == 0,
        "{here:?}"
    );
    assert_eq!(s.kernel.machine_steps(), here);
    // The next move starts from where the machine stopped.
    s.send("G91").expect("ok");
    s.send("G1 X1").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions()[0], here[0] + 80);
}

#[test]
fn jog_moves_step_size_times_count() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    // Frame 01 `S0.0125X+1000`: +12.5 mm.
    let r = s.kernel.jog(b'X', Decimal::new(125, 4), 1000).expect("jog");
    assert_eq!(r, Reply::Ok);
    let r = s.kernel.jog(b'Z', Decimal::new(1, 2), -50).expect("jog");
    assert_eq!(r, Reply::Ok);
    assert_eq!(
        s.kernel.jog(b'Q', Decimal::new(1, 0), 1),
        Err(CommandError::UnknownAxis { letter: b'Q' })
    );
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions(), [1000, 0, -200]);
}

#[test]
fn dwell_waits_between_moves() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G1 X1 F3000").expect("ok");
    s.send("G4 P500").expect("ok");
    s.send("G1 X2").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    let r = s.record();
    let xs = &r.steps[0];
    let gap = xs[80].tick - xs[79].tick;
    assert!((500_000..520_000).contains(&gap), "{gap}");
}

#[test]
fn dwell_at_rest_takes_its_time_then_the_move_runs() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    let start = s.now();
    s.send("G4 P5000").expect("ok");
    s.send("G1 X10 F3000").expect("ok");
    assert!(s.run_until_idle(20 * u64::from(HZ)));
    assert_eq!(s.kernel.state(), MachineState::Idle, "no alarm");
    let r = s.record();
    assert_eq!(r.position, [steps(10.0), 0, 0]);
    let first = r.steps[0][0].tick - start;
    // The first step comes after the whole dwell, then the usual ramp of the first half step.
    assert!((5_000_000..5_020_000).contains(&first), "{first}");
    assert!(r.violations.is_empty(), "{:?}", r.violations);
}

#[test]
fn a_dwell_alone_at_rest_ends_idle_after_its_time() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G4 P300").expect("ok");
    s.advance(u64::from(HZ) / 5);
    assert_eq!(s.kernel.state(), MachineState::Running, "still dwelling");
    assert!(s.run_until_idle(u64::from(HZ)));
    assert!((300_000..320_000).contains(&s.now()), "{}", s.now());
    assert_eq!(s.kernel.state(), MachineState::Idle);
}

#[test]
fn long_moves_survive_clock_wrap_at_168_mhz() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), 168_000_000);
    s.wiring.machine.set_tracing(false);
    // 180 mm at 6 mm/s: 30 s, more than the 25.6 s wrap of a 32-bit 168 MHz counter.
    s.send("G1 X180 Y90 F360").expect("ok");
    assert!(s.run_until_idle(60 * 168_000_000));
    assert!(s.now() > 1u64 << 32);
    let r = s.record();
    assert_eq!(r.position, [steps(180.0), steps(90.0), 0]);
    assert!(r.violations.is_empty(), "{:?}", r.violations);
}

#[test]
fn steps_per_unit_change_keeps_the_millimetres_and_rescales_the_steps() {
    // Marlin's `M92`: the machine stays at X10, now 1600 steps; the motors do not move.
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G1 X10 F3000").expect("ok");
    s.send("M92 X160").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions()[0], 800, "no step for the change itself");
    assert_eq!(s.kernel.machine_steps()[0], 1600);
    assert!((s.kernel.position().work_mm[0] - 10.0).abs() < 1e-9);
    // A job goes on from where it was: X20 is 10 mm further (1600 steps), X15 5 mm back.
    s.send("G1 X20").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions()[0], 800 + 1600);
    s.send("G1 X15").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions()[0], 800 + 800);
    assert!((s.kernel.position().work_mm[0] - 15.0).abs() < 1e-9);
    assert!((s.kernel.position().machine_mm[0] - 15.0).abs() < 1e-9);
}

#[test]
fn late_interrupts_keep_pulse_widths_and_positions() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    // Up to 3 µs late at 1 MHz, with 2 µs pulses.
    s.wiring.config_mut().max_latency_ticks = 3;
    s.send("G1 X30 Y20 Z1 F6000").expect("ok");
    s.send("G1 X0 Y25 Z0").expect("ok");
    s.send("G2 X10 Y35 I10 J0").expect("ok");
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    let r = s.record();
    assert_eq!(r.position, [steps(10.0), steps(35.0), 0]);
    assert!(r.violations.is_empty(), "{:?}", r.violations);
}

#[test]
fn reversals_at_corners_honour_the_direction_set_up_time() {
    use common::KernelSim;
    use forja_hal_abstraction::stepper::StepTiming;
    // A slow driver behind opto-couplers: 5 µs pulses, 400 µs direction set-up (longer than
    // the gap between the last step before a corner and the first after it).
    let timing = StepTiming {
        min_pulse_ns: 5_000,
        dir_setup_ns: 400_000,
    };
    let mut config = machine();
    config.junction_deviation_mm = 0.2;
    let mut q = StepQueue::<3, 256>::new();
    let (kernel, isr) =
        forja_motion::split::<3, 32, 256>(&mut q, config, HZ, timing).expect("valid");
    let mut s = KernelSim::new(kernel, isr, timing);
    // A zig-zag: X reverses at every 90° corner, at the corner speed.
    s.send("G1 F6000").expect("ok");
    for k in 1..=20 {
        let x = if k % 2 == 1 { 5 } else { 0 };
        s.send(&format!("G1 X{x} Y{}", 5 * k)).expect("ok");
    }
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    let r = s.record();
    assert_eq!(r.position, [0, steps(100.0), 0]);
    assert!(r.violations.is_empty(), "{:?}", r.violations);
}

#[test]
fn realtime_overrides_change_the_move_under_way_and_those_queued() {
    let run = |change: Option<(u16, u16)>| {
        let mut q = StepQueue::<3, 256>::new();
        let mut s = sim(&mut q, machine(), HZ);
        s.send("G1 X20 F600").expect("ok");
        s.send("G1 X40").expect("ok");
        s.send("G0 X100").expect("ok");
        s.advance(u64::from(HZ));
        let before = s.kernel.speed_mm_min();
        if let Some((feed, rapid)) = change {
            s.kernel.set_realtime_overrides(feed, rapid);
        }
        s.advance(u64::from(HZ) / 2);
        let after = s.kernel.speed_mm_min();
        assert!(s.run_until_idle(60 * u64::from(HZ)));
        let r = s.record();
        assert_eq!(r.position[0], steps(100.0));
        assert!(r.violations.is_empty(), "{:?}", r.violations);
        (s.now(), before, after)
    };
    let (plain, before, after) = run(None);
    assert!(
        (before - 600.0).abs() < 1.0 && (after - 600.0).abs() < 1.0,
        "{before} {after}"
    );
    // Twice the feed from the second second on: the 30 mm of feed left at 1200 mm/min.
    let (faster, _, after) = run(Some((200, 100)));
    assert!((after - 1200.0).abs() < 1.0, "{after}");
    let saved = plain - faster;
    // About 1.5 s saved (30 mm in half the time), the rapid unchanged.
    assert!((1_350_000..1_650_000).contains(&saved), "{plain} {faster}");
    // A quarter of the rapid: the 60 mm of rapid at 1500 mm/min instead of 6000.
    let (slow_rapid, _, _) = run(Some((100, 25)));
    let lost = slow_rapid - plain;
    assert!(
        (1_700_000..2_100_000).contains(&lost),
        "{plain} {slow_rapid}"
    );
}

#[test]
fn a_spindle_command_on_a_motion_line_acts_first_at_rest_and_s_rides_on_the_moves() {
    use forja_motion::effect::Spindle;
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    s.send("G1 X10 F3000").expect("ok");
    // The command waits for the motion before it (the line is offered again).
    let line = Line::parse(b"G0 X20 Y5 S16000 M3").unwrap();
    assert_eq!(s.kernel.execute(&line), Ok(Reply::Busy));
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    match s.kernel.execute(&line) {
        Ok(Reply::Effect(Effect::Spindle(Spindle::Clockwise { rpm: Some(rpm) }))) => {
            assert_eq!(rpm.as_integer(), Some(16000));
        }
        other => panic!("{other:?}"),
    }
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions()[..2], [steps(20.0), steps(5.0)]);
    // A line refused in its motion changes nothing, its command included.
    let far = Line::parse(b"G1 X10000 M5").unwrap();
    assert_eq!(
        s.kernel.execute(&far),
        Err(CommandError::OutOfReach { axis: 0 })
    );
    // `S` on motion lines: carried by the moves; alone: an effect.
    s.send("G1 X30 S8000").expect("ok");
    s.advance(u64::from(HZ) / 10);
    let now = s.kernel.motion_now();
    assert_eq!(now.spindle_rpm, 8000);
    assert!(
        now.speed_mm_min > 0.0 && now.fraction > 0.0 && !now.rapid,
        "{now:?}"
    );
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    let alone = Line::parse(b"S9000").unwrap();
    match s.kernel.execute(&alone) {
        Ok(Reply::Effect(Effect::Spindle(Spindle::Speed { rpm }))) => {
            assert_eq!(rpm.as_integer(), Some(9000));
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(s.kernel.motion_now().spindle_rpm, 9000);
    assert_eq!(s.send("S-1"), Err(CommandError::BadValue { letter: b'S' }));
}

/// One `poll` prepares a bounded share of a move and asks to be called again; the motion
/// starts only once its lead is prepared, and runs to its end.
#[test]
fn a_poll_prepares_a_bounded_share_and_the_motion_starts_with_its_lead() {
    use forja_hal_abstraction::clock::Alarm as _;
    use forja_hal_abstraction::time::Instant;
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    let line = Line::parse(b"G1 X100 Y50 F6000").expect("parse");
    assert_eq!(s.kernel.execute(&line), Ok(Reply::Ok));
    let now = Instant::from_ticks(s.now() as u32);
    let mut calls = 1;
    let mut arm = s.kernel.poll(now);
    while s.kernel.needs_poll() {
        assert_eq!(arm, None, "no start before the lead is prepared");
        arm = s.kernel.poll(now);
        calls += 1;
    }
    assert!(calls > 2, "the lead took {calls} calls");
    assert_eq!(arm, Some(now), "the motion starts with its lead");
    let _ = s.wiring.machine.alarm().set_alarm(now);
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions(), [steps(100.0), steps(50.0), 0]);
    assert!(s.record().violations.is_empty());
}

/// A ramp too long for the step clocks' fixed point (a slow axis with a small acceleration on
/// a 168 MHz clock: the ramp lasts 20 s, over 2^31 ticks) is timed step by step in double
/// precision: every step still within one tick of its exact time, the rates and the
/// acceleration within the axis's limits, the position exact.
#[test]
fn a_ramp_beyond_the_step_clocks_range_is_timed_exactly() {
    use forja_motion::AxisConfig;
    let mut config = machine();
    config.axes[2] = AxisConfig::linear(b'Z', 400.0, 120.0, 0.1, 100.0);
    let mut q = StepQueue::<3, 256>::new();
    let hz = 168_000_000;
    let mut s = sim(&mut q, config, hz);
    s.wiring.machine.set_tracing(true);
    s.send("G1 Z50 F120").expect("ok");
    assert!(s.run_until_idle(700 * u64::from(hz)));
    let r = s.record();
    assert_eq!(r.position, [0, 0, 20_000]);
    assert!(r.violations.is_empty(), "{:?}", r.violations);
    #[cfg(debug_assertions)]
    {
        let e = s.kernel.worst_step_error_ticks();
        assert!(e <= 1.0, "a step {e} ticks from its exact time");
    }
    let z = &config.axes[2];
    let d = check_axis(
        &r.steps[2],
        0,
        f64::from(z.steps_per_mm),
        f64::from(z.max_rate_mm_s()),
        f64::from(z.accel_mm_s2),
        f64::from(hz),
        None,
    );
    assert!(d.rate <= 1.01 && d.accel <= 1.01, "{d:?}");
}

/// The thread side may wait as long as `Kernel::poll_within_ms` says: half of the motion the
/// step queue holds, less than half of the lead when fast steps fill the queue first. Polled
/// that late every time, a fast move on two axes with a long lead never runs the queue dry.
#[test]
fn polled_as_late_as_the_kernel_allows_the_queue_never_runs_dry() {
    let mut config = machine();
    config.queue_lead_ms = 200;
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, config, HZ);
    s.send("G1 X150 Y75 F6000").expect("ok");
    let mut longest = 0;
    let mut shortest = u32::MAX;
    while !s.kernel.is_idle() {
        let wait_ms = s.kernel.poll_within_ms();
        longest = longest.max(wait_ms);
        if s.positions()[0] > steps(10.0) && s.positions()[0] < steps(140.0) {
            shortest = shortest.min(wait_ms);
        }
        let wait = u64::from(wait_ms) * u64::from(HZ) / 1000;
        s.wiring.config_mut().poll_period_ticks = wait;
        s.advance(wait);
        assert!(
            !matches!(s.kernel.state(), MachineState::Alarm(_)),
            "{:?} after waiting {wait_ms} ms",
            s.kernel.state()
        );
    }
    // The 256 events of the queue hold a fraction of the 200 ms lead at full speed.
    assert!(shortest < 50, "{shortest} ms");
    assert!(longest <= 100, "{longest} ms");
    assert_eq!(s.positions()[..2], [steps(150.0), steps(75.0)]);
}

/// Preparation tops the queue up to the lead, then lets it run down to half of the lead
/// before the next top-up: polled every millisecond through a long cruise, the motion the
/// queue holds after a poll goes down from (just under) the lead to half of it and back, never
/// below half and never above the lead (it would stay at the lead if every poll topped it up).
#[test]
fn the_queue_runs_down_to_half_its_lead_between_top_ups() {
    let config = machine();
    let lead_ms = u32::from(config.queue_lead_ms);
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, config, HZ);
    s.wiring.config_mut().poll_period_ticks = u64::from(HZ) / 1000;
    // 1,000 mm/min on X: 1,333 steps a second, so the 256 events never fill before the lead.
    s.send("G1 X150 F1000").expect("ok");
    let mut waits = Vec::new();
    while !s.kernel.is_idle() {
        s.advance(u64::from(HZ) / 1000);
        assert!(
            !matches!(s.kernel.state(), MachineState::Alarm(_)),
            "{:?}",
            s.kernel.state()
        );
        // The cruise: past the first and before the last 10 mm.
        if s.positions()[0] > steps(10.0) && s.positions()[0] < steps(140.0) {
            waits.push(s.kernel.poll_within_ms());
        }
    }
    assert_eq!(s.positions()[0], steps(150.0));
    // `poll_within_ms` is half of what the queue holds, in whole ms. A top-up ends at the
    // lead's horizon, the step past it left for the next (0.75 ms away here): the queue holds
    // just under the lead at the most.
    let (least, most) = (waits.iter().min().copied(), waits.iter().max().copied());
    assert_eq!(
        (least, most),
        (Some(lead_ms / 4), Some(lead_ms / 2 - 1)),
        "{} polls",
        waits.len()
    );
}

/// On a diagonal both axes step at the same ticks through the cruise: each pair of edges is
/// one event, every pulse keeps its width and spacing, every step is within a tick of its
/// exact time, and the positions end exact.
#[test]
fn a_diagonal_steps_both_axes_together() {
    let config = machine();
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, config, HZ);
    s.wiring.machine.set_tracing(true);
    s.send("G1 X60 Y60 F3000").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    let r = s.record();
    assert_eq!(r.position, [steps(60.0), steps(60.0), 0]);
    assert!(r.violations.is_empty(), "{:?}", r.violations);
    let together = r.steps[0]
        .iter()
        .zip(r.steps[1].iter())
        .filter(|(x, y)| x.tick == y.tick)
        .count();
    assert!(
        together > r.steps[0].len() * 9 / 10,
        "{together} of {}",
        r.steps[0].len()
    );
    #[cfg(debug_assertions)]
    {
        let e = s.kernel.worst_step_error_ticks();
        assert!(e <= 1.0, "a step {e} ticks from its exact time");
    }
}

/// A top-up of the step queue may end with a block, the next block loaded by the next top-up
/// (blocks about half the lead long, as in a chain of short moves): between the two, the
/// speed reported is the last block's exit speed, never 0 while the machine moves (grbl's
/// `FS:` shows it, and a laser's power follows it).
#[test]
fn the_speed_reported_along_a_chain_of_short_moves_stays_at_the_feed_between_blocks() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    // 0.5 mm segments at 3,000 mm/min: 10 ms each, half the default lead of 20 ms.
    let mut sent = 0u32;
    let send_more = |s: &mut common::KernelSim<'_, 3, 32, 256>, sent: &mut u32| {
        while *sent < 400 && s.kernel.can_accept() {
            *sent += 1;
            let x = f64::from(*sent) * 0.5;
            s.send(&format!("G1 X{x:.1} F3000")).expect("ok");
        }
    };
    send_more(&mut s, &mut sent);
    // Up to speed (3,000 mm/min at 800 mm/s²: 0.03 s), then sampled every millisecond for
    // a second, the planner kept fed.
    s.advance(u64::from(HZ) / 5);
    let mut samples = 0;
    for _ in 0..1000 {
        send_more(&mut s, &mut sent);
        s.advance(u64::from(HZ) / 1000);
        let speed = s.kernel.speed_mm_min();
        assert!(
            (speed - 3000.0).abs() < 30.0,
            "{speed} mm/min at {} µs",
            s.now()
        );
        samples += 1;
    }
    assert_eq!(samples, 1000);
    while sent < 400 {
        sent += 1;
        s.send(&format!("G1 X{:.1} F3000", f64::from(sent) * 0.5))
            .expect("ok");
    }
    assert!(s.run_until_idle(60 * u64::from(HZ)));
    assert_eq!(s.positions()[0], steps(200.0));
}
