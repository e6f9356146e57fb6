//! Property tests of the whole kernel on the simulated machine: exact step counts, step times
//! within one tick of their exact times on the planned profiles (measured by the kernel in
//! debug builds), and step times that respect every axis's rate and acceleration limits.
//!
//! The 100,000-move drift test runs only in release builds:
//! `cargo test -p forja-motion --release --test properties`.

mod common;

use common::{check_axis, machine, mm_text, sim, steps_for_thou};
use forja_motion::StepQueue;
use proptest::prelude::*;

/// One random move: targets in thousandths of a mm, a feed, rapid or not.
#[derive(Debug, Clone)]
struct Move {
    thou: [i64; 3],
    feed: u32,
    rapid: bool,
    feed_on_line: bool,
}

fn moves(len: std::ops::Range<usize>) -> impl Strategy<Value = Vec<Move>> {
    prop::collection::vec(
        (
            0i64..60_000,
            0i64..60_000,
            0i64..5_000,
            200u32..8_000,
            prop::bool::weighted(0.2),
            prop::bool::ANY,
        )
            .prop_map(|(x, y, z, feed, rapid, feed_on_line)| Move {
                thou: [x, y, z],
                feed,
                rapid,
                feed_on_line,
            }),
        len,
    )
}

/// Run `moves` at `tick_hz` with junction deviation `jd`; check exact end positions and the
/// measured dynamics of every axis. Returns the worst ratios.
fn run(moves: &[Move], tick_hz: u32, jd: f32) -> (f64, f64) {
    let mut config = machine();
    config.junction_deviation_mm = jd;
    let spm: Vec<f32> = config.axes.iter().map(|a| a.steps_per_mm).collect();
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, config, tick_hz);
    // Per-axis step deltas of every move that steps, to find block boundaries.
    let mut deltas: Vec<[i32; 3]> = Vec::new();
    let mut at = [0i32; 3];
    for m in moves {
        let mut text = String::from(if m.rapid { "G0" } else { "G1" });
        for (i, l) in ["X", "Y", "Z"].iter().enumerate() {
            text += &format!(" {l}{}", mm_text(m.thou[i]));
        }
        if m.feed_on_line || !m.rapid {
            text += &format!(" F{}", m.feed);
        }
        s.send(&text).expect("move accepted");
        let target: [i32; 3] = core::array::from_fn(|i| steps_for_thou(m.thou[i], spm[i]));
        let d: [i32; 3] = core::array::from_fn(|i| target[i] - at[i]);
        if d != [0; 3] {
            deltas.push(d);
        }
        at = target;
    }
    assert!(s.run_until_idle(u64::from(tick_hz) * 3600));
    // Every step on its exact time on the planned profile, rounded: within one tick.
    #[cfg(debug_assertions)]
    {
        let e = s.kernel.worst_step_error_ticks();
        assert!(e <= 1.0, "a step {e} ticks from its exact time");
    }
    let r = s.record();
    assert_eq!(r.position, at, "end position in steps");
    assert!(r.violations.is_empty(), "{:?}", r.violations);
    let (mut worst_rate, mut worst_accel) = (0f64, 0f64);
    for (i, a) in config.axes.iter().enumerate() {
        let mut blocks = Vec::new();
        for (b, d) in deltas.iter().enumerate() {
            blocks.extend(std::iter::repeat_n(b, d[i].unsigned_abs() as usize));
        }
        assert_eq!(blocks.len(), r.steps[i].len());
        let within = if jd > 0.0 { Some(&blocks[..]) } else { None };
        let d = check_axis(
            &r.steps[i],
            0,
            f64::from(a.steps_per_mm),
            f64::from(a.max_rate_mm_s()),
            f64::from(a.accel_mm_s2),
            f64::from(tick_hz),
            within,
        );
        worst_rate = worst_rate.max(d.rate);
        worst_accel = worst_accel.max(d.accel);
    }
    (worst_rate, worst_accel)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// Stops at every corner (junction deviation 0): the limits hold over the whole run,
    /// corners included.
    #[test]
    fn exact_stops_respect_limits_everywhere(ms in moves(1..25)) {
        let (rate, accel) = run(&ms, 10_000_000, 0.0);
        prop_assert!(rate <= 1.01, "rate {rate}");
        prop_assert!(accel <= 1.01, "accel {accel}");
    }

    /// Junction-deviation cornering: the limits hold inside every block.
    #[test]
    fn cornering_respects_limits_inside_blocks(ms in moves(1..25)) {
        let (rate, accel) = run(&ms, 10_000_000, 0.05);
        prop_assert!(rate <= 1.01, "rate {rate}");
        prop_assert!(accel <= 1.01, "accel {accel}");
    }

    /// A 1 MHz clock (the simulator's and many boards'): same limits.
    #[test]
    fn one_megahertz_clock(ms in moves(1..15)) {
        let (rate, accel) = run(&ms, 1_000_000, 0.02);
        prop_assert!(rate <= 1.01, "rate {rate}");
        prop_assert!(accel <= 1.01, "accel {accel}");
    }
}

/// A small deterministic generator (the drift test must not depend on a seed file).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 33
    }
    fn range(&mut self, lo: i64, hi: i64) -> i64 {
        lo + (self.next() % (hi - lo) as u64) as i64
    }
}

/// `n` random moves — absolute with three decimals, relative with four (fractions of a step
/// that must add up exactly), full circles that must close — and the step count of every axis
/// compared with its rounded target every 500 moves and at the end.
fn drift(n: usize) {
    let config = machine();
    let spm: Vec<f64> = config
        .axes
        .iter()
        .map(|a| f64::from(a.steps_per_mm))
        .collect();
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, config, 1_000_000);
    s.wiring.machine.set_tracing(false);
    s.send("G1 F6000").expect("ok");
    let mut rng = Lcg(0x5eed);
    let mut nm = [0i64; 3];
    let letters = ["X", "Y", "Z"];
    for k in 0..n {
        let kind = rng.range(0, 10);
        let mut text;
        if kind < 4 {
            text = String::from("G90 G1");
            for (i, l) in letters.iter().enumerate() {
                if rng.range(0, 3) > 0 {
                    let thou = rng.range(0, if i == 2 { 5_000 } else { 20_000 });
                    nm[i] = thou * 1000;
                    text += &format!(" {l}{}", mm_text(thou));
                }
            }
        } else if kind < 9 {
            text = String::from("G91 G1");
            for (i, l) in letters.iter().enumerate() {
                let tenth_um = rng.range(-10_000, 10_000);
                nm[i] += tenth_um * 100;
                let sign = if tenth_um < 0 { "-" } else { "" };
                let a = tenth_um.abs();
                text += &format!(" {l}{sign}{}.{:04}", a / 10_000, a % 10_000);
            }
        } else {
            let r = rng.range(200, 2_000);
            text = format!("G90 G{} I{} J0", if k % 2 == 0 { 2 } else { 3 }, mm_text(r));
        }
        s.send(&text).expect("accepted");
        if k % 500 == 499 || k + 1 == n {
            assert!(s.run_until_idle(3600 * 1_000_000));
            let want: [i32; 3] =
                core::array::from_fn(|i| (nm[i] as f64 * spm[i] / 1e6).round() as i32);
            assert_eq!(s.positions(), want, "after {} moves", k + 1);
        }
    }
    assert!(s.record().violations.is_empty());
    #[cfg(debug_assertions)]
    {
        let e = s.kernel.worst_step_error_ticks();
        assert!(e <= 1.0, "a step {e} ticks from its exact time");
    }
}

/// No drift over 500 moves (every build).
#[test]
fn no_drift_short() {
    drift(500);
}

/// No drift over 100,000 moves. Release only: `cargo test -p forja-motion --release`.
#[test]
#[cfg_attr(debug_assertions, ignore = "100,000 moves: run with --release")]
fn no_drift_after_100_000_moves() {
    drift(100_000);
}

/// The measure of `check_axis` catches what it is meant to catch: the one-period jitter of a
/// Bresenham grid near the maximum rate, and a velocity step that no acceleration allows.
#[test]
fn the_measure_catches_grid_jitter_and_velocity_steps() {
    use common::StepRecord;
    let hz = 1_000_000.0;
    // 95 % of 100 mm/s at 80 steps/mm on a 30 µs grid: intervals of 120 and 150 µs.
    let mut steps = Vec::new();
    let mut t = 0u64;
    for k in 0..400 {
        t += if k % 4 == 0 { 150 } else { 120 };
        steps.push(StepRecord {
            tick: t,
            position: k + 1,
        });
    }
    let d = check_axis(&steps, 0, 80.0, 100.0, 800.0, hz, None);
    assert!(d.rate > 1.01, "{d:?}");
    // 10 mm/s, then 50 mm/s at once.
    let mut steps = Vec::new();
    let mut t = 0u64;
    for k in 0..2000 {
        t += if k < 300 { 1250 } else { 250 };
        steps.push(StepRecord {
            tick: t,
            position: k + 1,
        });
    }
    let d = check_axis(&steps, 0, 80.0, 100.0, 800.0, hz, None);
    assert!(d.rate <= 1.0 && d.accel > 1.5, "{d:?}");
}

/// The rate measurement itself: a tick of rounding at 100 ticks a step is not a violation, a
/// step rate 10 % over the limit is.
#[test]
fn the_rate_check_tells_rounding_from_overspeed() {
    use common::StepRecord;
    // 1 mm/s at 10,000 steps/mm on a 1 MHz clock: a step every 100 ticks at the limit.
    let steps = |intervals: &[u64]| -> Vec<StepRecord> {
        let mut tick = 0;
        intervals
            .iter()
            .enumerate()
            .map(|(i, d)| {
                tick += d;
                StepRecord {
                    tick,
                    position: i as i32 + 1,
                }
            })
            .collect()
    };
    let rounded: Vec<u64> = (0..50).map(|i| if i % 2 == 0 { 99 } else { 101 }).collect();
    let d = check_axis(&steps(&rounded), 0, 10_000.0, 1.0, 1.0e9, 1_000_000.0, None);
    assert!(d.rate <= 1.01, "rounding read as overspeed: {}", d.rate);
    let fast = vec![90; 50];
    let d = check_axis(&steps(&fast), 0, 10_000.0, 1.0, 1.0e9, 1_000_000.0, None);
    assert!(d.rate > 1.1, "overspeed missed: {}", d.rate);
}
