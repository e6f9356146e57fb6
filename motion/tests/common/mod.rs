//! Shared set-up of the integration tests: the kernel on the simulated machine ([`bench`]), a
//! test machine, and the measures of its motion.
#![allow(dead_code)]

pub mod bench;

use forja_hal_abstraction::stepper::StepTiming;
use forja_motion::{AxisConfig, HomeDirection, HomingConfig, MachineConfig, StepQueue, split};

pub use bench::{KernelSim, StepRecord};

/// Three axes with homing on X and Y (switches 0 and 1), travel 0..200 mm.
pub fn machine() -> MachineConfig<3> {
    let homing = |switch| HomingConfig {
        direction: HomeDirection::Min,
        seek_mm_min: 1500.0,
        locate_mm_min: 120.0,
        pull_off_mm: 1.0,
        switch,
        order: switch,
    };
    let mut c = MachineConfig::new([
        AxisConfig::linear(b'X', 80.0, 6000.0, 800.0, 200.0).with_homing(homing(0)),
        AxisConfig::linear(b'Y', 80.0, 4800.0, 600.0, 200.0).with_homing(homing(1)),
        AxisConfig::linear(b'Z', 400.0, 900.0, 200.0, 100.0),
    ]);
    c.junction_deviation_mm = 0.02;
    c
}

/// The kernel of `config` on the simulated machine, split on `queue`.
pub fn sim<'q, const N: usize>(
    queue: &'q mut StepQueue<N, 256>,
    config: MachineConfig<N>,
    tick_hz: u32,
) -> KernelSim<'q, N, 32, 256> {
    let timing = StepTiming::CONSERVATIVE;
    let (kernel, isr) = split::<N, 32, 256>(queue, config, tick_hz, timing).expect("valid config");
    KernelSim::new(kernel, isr, timing)
}

/// The shortest span over which [`check_axis`] measures a rate, ticks.
pub const RATE_SPAN_TICKS: f64 = 200.0;

/// The worst figures found by [`check_axis`], as ratios to the axis limits.
#[derive(Debug, Clone, Copy, Default)]
pub struct Dynamics {
    /// Largest rate between two steps at least [`RATE_SPAN_TICKS`] apart, / max rate.
    pub rate: f64,
    /// Largest acceleration from three samples, / max acceleration.
    pub accel: f64,
    /// Acceleration samples checked.
    pub samples: usize,
}

/// Rate and acceleration of one axis, measured from its recorded step times alone.
///
/// * Each step is placed at its crossing point: a step that ends at position `p` moving in
///   direction `d` (±1) is the axis crossing `p − d/2` (the half-step it was scheduled at).
/// * **Rate**: every step and the first one at least [`RATE_SPAN_TICKS`] after it, the steps
///   between them all in one direction, give `v = k / (steps_per_mm · Δt)` for the `k` steps
///   between. Step times are whole ticks, each within half a tick of its ideal time, so one
///   interval can be a tick short of the ideal; over a span of at least 200 ticks that rounding
///   is at most 0.5 % of the rate (consecutive steps alone would show 1 % at 100 ticks apart,
///   the fastest axis of a 1 MHz clock).
/// * **Acceleration**: the step sequence is sampled at intervals of at least `tau` ticks (each
///   sample is the first step at or after the previous sample + `tau`), and every three
///   consecutive samples give the second divided difference of position over time,
///   `a = 2·[(x2 − x1)/(t2 − t1) − (x1 − x0)/(t1 − t0)] / (t2 − t0)`. For any motion whose
///   acceleration is bounded by `A`, this is at most `A` (mean value theorem for divided
///   differences), so it bounds the machine; sampling over `tau` keeps the clock's ±½-tick
///   rounding below 0.5 % of `A` (`tau = sqrt(2·v_max·tick / (0.005·A))`).
/// * With `blocks = Some(ids)` (the planner block of each step), only triples inside one
///   block count: the velocity change at a junction is the junction-deviation model's, bounded
///   by the planner (see the planner's junction tests); with `None`, every triple counts.
pub fn check_axis(
    steps: &[StepRecord],
    start: i32,
    steps_per_mm: f64,
    max_rate_mm_s: f64,
    max_accel_mm_s2: f64,
    tick_hz: f64,
    blocks: Option<&[usize]>,
) -> Dynamics {
    let mut out = Dynamics::default();
    let mut xs: Vec<(f64, f64, i32)> = Vec::with_capacity(steps.len());
    let mut prev = start;
    for s in steps {
        let d = s.position - prev;
        prev = s.position;
        xs.push((s.tick as f64, f64::from(s.position) - 0.5 * f64::from(d), d));
    }
    for (i, first) in xs.iter().enumerate() {
        let rest = xs.iter().skip(i + 1);
        let mut same = rest.take_while(|x| x.2 == first.2).enumerate();
        if let Some((k, last)) = same.find(|(_, x)| x.0 - first.0 >= RATE_SPAN_TICKS) {
            let v = tick_hz * (k + 1) as f64 / (last.0 - first.0) / steps_per_mm;
            out.rate = out.rate.max(v / max_rate_mm_s);
        }
    }
    let tau = (2.0 * max_rate_mm_s / tick_hz / (0.005 * max_accel_mm_s2)).sqrt() * tick_hz;
    let mut samples: Vec<usize> = Vec::new();
    for (k, x) in xs.iter().enumerate() {
        match samples.last() {
            Some(&j) if x.0 < xs[j].0 + tau => {}
            _ => samples.push(k),
        }
    }
    for w in samples.windows(3) {
        if let Some(b) = blocks
            && b[w[0]] != b[w[2]]
        {
            continue;
        }
        let (t0, x0, _) = xs[w[0]];
        let (t1, x1, _) = xs[w[1]];
        let (t2, x2, _) = xs[w[2]];
        let a = 2.0 * ((x2 - x1) / (t2 - t1) - (x1 - x0) / (t1 - t0)) / (t2 - t0);
        let a_mm = a.abs() * tick_hz * tick_hz / steps_per_mm;
        out.accel = out.accel.max(a_mm / max_accel_mm_s2);
        out.samples += 1;
    }
    out
}

/// Steps of an axis for a machine position written with three decimals (`thou` thousandths of
/// a millimetre), rounded as the kernel does.
pub fn steps_for_thou(thou: i64, steps_per_mm: f32) -> i32 {
    (thou as f64 * 1000.0 * f64::from(steps_per_mm) / 1e6).round() as i32
}

/// `thou` thousandths of a millimetre as G-code text.
pub fn mm_text(thou: i64) -> String {
    let sign = if thou < 0 { "-" } else { "" };
    let a = thou.abs();
    format!("{sign}{}.{:03}", a / 1000, a % 1000)
}
