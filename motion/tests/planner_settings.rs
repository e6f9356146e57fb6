//! The planner settings that printer slicers send (`M201`, `M203`, `M204`, `M205`) and the feed
//! and flow overrides (`M220`, `M221`), on the simulated machine: each line is taken without
//! waiting for the motion before it, acts on the moves planned after it, and a bad value is
//! refused, naming its letter and changing nothing.

mod common;

use common::{KernelSim, StepRecord, check_axis, machine, sim};
use forja_motion::{
    AxisConfig, AxisKind, CommandError, MachineConfig, PathLimits, Reply, StepQueue,
};
use forja_protocol::gcode::Line;

const HZ: u32 = 1_000_000;

/// X and Y (80 steps/mm, 200 mm/s, 2000 mm/s²), Z (400 steps/mm), and an extruder E of 100
/// steps/mm (50 mm/s, 3000 mm/s²). Not homed.
fn printer() -> MachineConfig<4> {
    let mut e = AxisConfig::linear(b'E', 100.0, 3000.0, 3000.0, 0.0);
    e.kind = AxisKind::Extruder;
    e.min_mm = -100_000.0;
    e.max_mm = 100_000.0;
    MachineConfig::new([
        AxisConfig::linear(b'X', 80.0, 12_000.0, 2000.0, 220.0),
        AxisConfig::linear(b'Y', 80.0, 12_000.0, 2000.0, 220.0),
        AxisConfig::linear(b'Z', 400.0, 600.0, 100.0, 250.0),
        e,
    ])
}

fn exec<'l, const N: usize>(
    s: &mut KernelSim<'_, N, 32, 256>,
    text: &'l str,
) -> Result<Reply<'l, N>, CommandError> {
    let line = Line::parse(text.as_bytes()).expect("parses");
    s.kernel.execute(&line)
}

/// Run `line` to rest and return the steps each axis made for it, with the position each
/// axis started from.
fn run_alone<const N: usize>(
    s: &mut KernelSim<'_, N, 32, 256>,
    line: &str,
) -> Vec<(i32, Vec<StepRecord>)> {
    let before = s.record();
    s.send(line).expect("taken");
    assert!(s.run_until_idle(60 * u64::from(HZ)));
    let after = s.record();
    assert!(after.violations.is_empty(), "{:?}", after.violations);
    (0..N)
        .map(|i| {
            let start = before.position[i];
            (start, after.steps[i][before.steps[i].len()..].to_vec())
        })
        .collect()
}

/// The largest rate and acceleration of axis `axis` over `steps`, as ratios to `rate_mm_s` and
/// `accel_mm_s2`.
fn peaks<const N: usize>(
    config: &MachineConfig<N>,
    axis: usize,
    (start, steps): &(i32, Vec<StepRecord>),
    rate_mm_s: f64,
    accel_mm_s2: f64,
) -> (f64, f64) {
    let spm = f64::from(config.axes[axis].steps_per_mm);
    let d = check_axis(
        steps,
        *start,
        spm,
        rate_mm_s,
        accel_mm_s2,
        f64::from(HZ),
        None,
    );
    (d.rate, d.accel)
}

#[test]
fn flow_scales_the_extruder_motor_and_not_the_reported_position() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, printer(), HZ);
    s.send("M221 S50").expect("ok");
    s.send("G1 E10 F600").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    // Half of 10 mm at 100 steps/mm.
    assert_eq!(s.positions()[3], 500);
    let p = s.kernel.position();
    assert!((p.work_mm[3] - 10.0).abs() < 1e-9, "{p:?}");
    assert!((p.machine_mm[3] - 5.0).abs() < 1e-9, "{p:?}");
    // `G92 E0` sets the reported position; the motor goes on: E2 is 1 mm more.
    s.send("G92 E0").expect("ok");
    s.send("G1 E2").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions()[3], 600);
    assert!((s.kernel.position().work_mm[3] - 2.0).abs() < 1e-9);
    // Relative extrusion alike; back at 100 % the commanded distance again.
    s.send("M83").expect("ok");
    s.send("G1 E-1").expect("ok");
    s.send("M221 S100").expect("ok");
    s.send("G1 E1").expect("ok");
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(s.positions()[3], 600 - 50 + 100);
    assert!((s.kernel.position().work_mm[3] - 2.0).abs() < 1e-9);
    assert_eq!(s.kernel.machine_steps()[3], 650);
}

#[test]
fn settings_are_taken_while_moving_and_apply_to_the_moves_after_them() {
    let config = machine();
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, config, HZ);
    s.send("G1 X100 F6000").expect("ok");
    // Taken at once, the move before them still running.
    for line in [
        "M201 X200",
        "M220 S50",
        "M204 T400",
        "M205 J0.05",
        "M203 Y50",
    ] {
        assert_eq!(exec(&mut s, line), Ok(Reply::Ok), "{line}");
    }
    assert!(!s.kernel.is_idle());
    s.send("G1 X0").expect("ok");
    assert!(s.run_until_idle(30 * u64::from(HZ)));
    let r = s.record();
    assert!(r.violations.is_empty(), "{:?}", r.violations);
    assert_eq!(r.position[0], 0);
    let turn = r.steps[0]
        .iter()
        .position(|st| st.position == 8000)
        .expect("reached X100");
    let out = (0, r.steps[0][..=turn].to_vec());
    let back = (8000, r.steps[0][turn + 1..].to_vec());
    // Out: X's own 100 mm/s and 800 mm/s².
    let (rate, accel) = peaks(&config, 0, &out, 100.0, 800.0);
    assert!((0.98..1.02).contains(&rate), "{rate}");
    assert!((0.9..1.02).contains(&accel), "{accel}");
    // Back: half the feed (M220 S50), and 200 mm/s² (M201 X200 under M204 T400).
    let (rate, accel) = peaks(&config, 0, &back, 50.0, 200.0);
    assert!((0.98..1.02).contains(&rate), "{rate}");
    assert!((0.9..1.02).contains(&accel), "{accel}");
}

#[test]
fn m203_is_in_mm_per_s_rapids_move_at_it_and_the_override_scales_them() {
    let config = printer();
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, config, HZ);
    s.send("M203 X20").expect("ok");
    assert_eq!(s.kernel.config().axes[0].max_rate_mm_min, 1200.0);
    assert_eq!(s.kernel.planner_settings().max_rate_mm_s[0], 20.0);
    let steps = run_alone(&mut s, "G0 X50");
    let (rate, _) = peaks(&config, 0, &steps[0], 20.0, 2000.0);
    assert!((0.98..1.02).contains(&rate), "{rate}");
    s.send("M220 S50").expect("ok");
    let steps = run_alone(&mut s, "G0 X0");
    let (rate, _) = peaks(&config, 0, &steps[0], 10.0, 2000.0);
    assert!((0.98..1.02).contains(&rate), "{rate}");
    // Above 100 %, the maximum rate still caps the move.
    s.send("M220 S200").expect("ok");
    let steps = run_alone(&mut s, "G1 X50 F1000");
    let (rate, _) = peaks(&config, 0, &steps[0], 20.0, 2000.0);
    assert!((0.98..1.02).contains(&rate), "{rate}");
}

#[test]
fn m204_caps_printing_retracting_and_travel_moves() {
    let config = printer();
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, config, HZ);
    s.send("M204 P500 R250 T1000").expect("ok");
    assert_eq!(
        s.kernel.planner_settings().path,
        PathLimits {
            print_accel_mm_s2: Some(500.0),
            retract_accel_mm_s2: Some(250.0),
            travel_accel_mm_s2: Some(1000.0),
            ..PathLimits::NONE
        }
    );
    // Travel: X alone at 1000 mm/s².
    let steps = run_alone(&mut s, "G1 X100 F12000");
    let (_, accel) = peaks(&config, 0, &steps[0], 200.0, 1000.0);
    assert!((0.9..1.02).contains(&accel), "{accel}");
    // Printing: 500 mm/s² along the path, X carrying 100/√(100² + 5²) of it.
    let steps = run_alone(&mut s, "G1 X0 E5");
    let share = 100.0 / (100.0f64 * 100.0 + 25.0).sqrt();
    let (_, accel) = peaks(&config, 0, &steps[0], 200.0, 500.0 * share);
    assert!((0.9..1.02).contains(&accel), "{accel}");
    // Retracting: the extruder alone at 250 mm/s².
    let steps = run_alone(&mut s, "G1 E2 F2400");
    let (_, accel) = peaks(&config, 3, &steps[3], 40.0, 250.0);
    assert!((0.9..1.02).contains(&accel), "{accel}");
}

#[test]
fn m205_sets_the_junction_deviation_and_the_slowest_feeds() {
    let config = printer();
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, config, HZ);
    // PrusaSlicer's start: jerks (left out) and the slowest feeds.
    assert_eq!(exec(&mut s, "M205 X8.00 Y8.00 Z0.40 E4.50"), Ok(Reply::Ok));
    assert_eq!(exec(&mut s, "M205 S0 T0"), Ok(Reply::Ok));
    assert_eq!(exec(&mut s, "M205 J0.05 T20"), Ok(Reply::Ok));
    assert_eq!(s.kernel.config().junction_deviation_mm, 0.05);
    let settings = s.kernel.planner_settings();
    assert_eq!(settings.junction_deviation_mm, 0.05);
    assert_eq!(settings.path.min_travel_feed_mm_s, 20.0);
    assert_eq!(settings.path.min_extruding_feed_mm_s, 0.0);
    // A travel asked at 5 mm/s runs at 20.
    let steps = run_alone(&mut s, "G1 X20 F300");
    let (rate, _) = peaks(&config, 0, &steps[0], 20.0, 2000.0);
    assert!((0.98..1.02).contains(&rate), "{rate}");
}

#[test]
fn a_bad_setting_is_refused_by_its_letter_and_changes_nothing() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, printer(), HZ);
    let before = s.kernel.planner_settings();
    let config = *s.kernel.config();
    for (line, error) in [
        ("M201 X500 Y0", CommandError::BadValue { letter: b'Y' }),
        ("M201 A500", CommandError::UnknownAxis { letter: b'A' }),
        ("M203 Z-1", CommandError::BadValue { letter: b'Z' }),
        // 3000 mm/s at 80 steps/mm is 240 kHz; the 2 µs drivers need 6 µs between steps.
        ("M203 X3000", CommandError::BadValue { letter: b'X' }),
        ("M204 P0", CommandError::BadValue { letter: b'P' }),
        ("M204 T-5", CommandError::BadValue { letter: b'T' }),
        ("M205 J-0.01", CommandError::BadValue { letter: b'J' }),
        ("M205 E-1", CommandError::BadValue { letter: b'E' }),
        ("M220 S0", CommandError::BadValue { letter: b'S' }),
        ("M220 S", CommandError::MissingValue { letter: b'S' }),
        ("M221 S-10", CommandError::BadValue { letter: b'S' }),
        ("M221 T1 S95", CommandError::BadValue { letter: b'T' }),
    ] {
        assert_eq!(exec(&mut s, line), Err(error), "{line}");
    }
    assert_eq!(s.kernel.planner_settings(), before);
    assert_eq!(s.kernel.config(), &config);
    // The rate the drivers can step is taken.
    assert_eq!(exec(&mut s, "M203 X1000"), Ok(Reply::Ok));
}

#[test]
fn a_rate_below_the_homing_speeds_lowers_them() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    // X seeks at 1500 mm/min and locates at 120: 10 mm/s is 600.
    s.send("M203 X10 Y1").expect("ok");
    let axes = &s.kernel.config().axes;
    let x = axes[0].homing.expect("homing");
    let y = axes[1].homing.expect("homing");
    assert_eq!((x.seek_mm_min, x.locate_mm_min), (600.0, 120.0));
    assert_eq!((y.seek_mm_min, y.locate_mm_min), (60.0, 60.0));
    assert_eq!(s.kernel.config().validate(), Ok(()));
}

#[test]
fn the_settings_report_has_every_value_in_marlins_units() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, printer(), HZ);
    let start = s.kernel.planner_settings();
    assert_eq!(start.letters, *b"XYZE");
    assert_eq!(start.steps_per_mm, [80.0, 80.0, 400.0, 100.0]);
    assert_eq!(start.max_accel_mm_s2, [2000.0, 2000.0, 100.0, 3000.0]);
    assert_eq!(start.max_rate_mm_s, [200.0, 200.0, 10.0, 50.0]);
    assert_eq!(start.path, PathLimits::NONE);
    assert_eq!(start.junction_deviation_mm, 0.01);
    assert_eq!(start.feed_percent, 100);
    assert_eq!(start.flow_percent, [None, None, None, Some(100)]);
    // PrusaSlicer's machine limits, then the overrides.
    for line in [
        "M201 X1000 Y1000 Z200 E5000",
        "M203 X200 Y200 Z12 E120",
        "M204 P1250 R1250 T1250",
        "M205 X8.00 Y8.00 Z0.40 E4.50",
        "M205 S0 T0 J0.02",
        "M92 E93",
        "M220 S90",
        "M221 S95",
    ] {
        s.send(line).expect(line);
    }
    let now = s.kernel.planner_settings();
    assert_eq!(now.steps_per_mm, [80.0, 80.0, 400.0, 93.0]);
    assert_eq!(now.max_accel_mm_s2, [1000.0, 1000.0, 200.0, 5000.0]);
    assert_eq!(now.max_rate_mm_s, [200.0, 200.0, 12.0, 120.0]);
    assert_eq!(
        now.path,
        PathLimits {
            print_accel_mm_s2: Some(1250.0),
            retract_accel_mm_s2: Some(1250.0),
            travel_accel_mm_s2: Some(1250.0),
            ..PathLimits::NONE
        }
    );
    assert_eq!(now.junction_deviation_mm, 0.02);
    assert_eq!(now.feed_percent, 90);
    assert_eq!(now.flow_percent, [None, None, None, Some(95)]);
    // A soft reset puts the overrides back to 100 % and keeps the settings.
    s.kernel.reset();
    let reset = s.kernel.planner_settings();
    assert_eq!(
        (reset.feed_percent, reset.flow_percent[3]),
        (100, Some(100))
    );
    assert_eq!(reset.path, now.path);
    assert_eq!(reset.max_rate_mm_s, now.max_rate_mm_s);
}

/// The reference printer of the slicer corpus (`boards/sim-hal/machines/printer.toml`), soft
/// limits off (it is not homed here).
fn reference_printer() -> MachineConfig<4> {
    let mut e = AxisConfig::linear(b'E', 93.0, 3000.0, 3000.0, 0.0);
    e.kind = AxisKind::Extruder;
    e.min_mm = -100_000.0;
    e.max_mm = 100_000.0;
    let mut c = MachineConfig::new([
        AxisConfig::linear(b'X', 80.0, 12_000.0, 1000.0, 235.0),
        AxisConfig::linear(b'Y', 80.0, 12_000.0, 1000.0, 235.0),
        AxisConfig::linear(b'Z', 400.0, 600.0, 100.0, 250.0),
        e,
    ]);
    c.soft_limits = forja_motion::SoftLimits::Off;
    c
}

#[test]
fn the_slicer_corpus_runs_with_no_line_refused() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/corpus/slicers");
    for name in ["prusaslicer", "cura", "orcaslicer", "superslicer"] {
        let text = std::fs::read_to_string(format!("{dir}/{name}.gcode")).expect("corpus file");
        let mut q = StepQueue::<4, 256>::new();
        let mut s = sim(&mut q, reference_printer(), HZ);
        s.wiring.machine.set_tracing(false);
        for (n, text) in text.lines().enumerate() {
            // The controller drops comments before a line reaches the kernel.
            let code = text.split(';').next().unwrap_or("").trim();
            let line = Line::parse(code.as_bytes()).expect("parses");
            loop {
                match s.kernel.execute(&line) {
                    Ok(Reply::Busy) => s.advance(s.poll_period()),
                    Ok(_) => break s.poll(),
                    Err(e) => panic!("{name}.gcode:{}: {text}: {e:?}", n + 1),
                }
            }
        }
        assert!(s.run_until_idle(3600 * u64::from(HZ)), "{name}");
        assert!(s.record().violations.is_empty(), "{name}");
        // Every file leaves the reference printer's own limits and the overrides at 100 %.
        let settings = s.kernel.planner_settings();
        assert_eq!(settings.max_accel_mm_s2, [1000.0, 1000.0, 100.0, 3000.0]);
        assert_eq!(settings.max_rate_mm_s, [200.0, 200.0, 10.0, 50.0]);
        assert_eq!(settings.feed_percent, 100, "{name}");
        assert_eq!(settings.flow_percent[3], Some(100), "{name}");
        assert!(settings.path.print_accel_mm_s2.is_some(), "{name}");
    }
}

/// A whole set of settings at once (`M501`, `M502`): it waits for the machine to be idle, a
/// bad one changes nothing, and the machine keeps its millimetres.
#[test]
fn a_whole_set_of_settings_waits_for_idle_and_keeps_the_millimetres() {
    let mut q = StepQueue::<4, 256>::new();
    let mut s = sim(&mut q, printer(), HZ);
    assert_eq!(exec(&mut s, "G1 X10 F3000"), Ok(Reply::Ok));
    let mut machine = printer();
    machine.axes[0].steps_per_mm = 160.0;
    machine.axes[1].accel_mm_s2 = 500.0;
    let path = PathLimits {
        print_accel_mm_s2: Some(800.0),
        ..PathLimits::NONE
    };
    assert_eq!(
        s.kernel.set_planner_settings(&machine, path),
        Ok(Reply::Busy)
    );
    assert_eq!(s.kernel.planner_settings().steps_per_mm[0], 80.0);
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    let bad = PathLimits {
        travel_accel_mm_s2: Some(f32::NAN),
        ..path
    };
    assert!(s.kernel.set_planner_settings(&machine, bad).is_err());
    assert_eq!(s.kernel.planner_settings().path, PathLimits::NONE);
    assert_eq!(s.kernel.set_planner_settings(&machine, path), Ok(Reply::Ok));
    let now = s.kernel.planner_settings();
    assert_eq!(
        (now.steps_per_mm[0], now.max_accel_mm_s2[1], now.path),
        (160.0, 500.0, path)
    );
    assert_eq!(s.kernel.machine_steps()[0], 1600, "X10 at 160 steps/mm");
    assert!((s.kernel.position().work_mm[0] - 10.0).abs() < 1e-9);
}
