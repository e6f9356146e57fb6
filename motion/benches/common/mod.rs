//! The machine, program and no-op hardware shared by the kernel's criterion benchmarks
//! (`benches/kernel.rs`) and its instruction-count workload (`examples/instructions.rs`), so
//! that the figures in `docs/performance.md` measure the same thing.
#![allow(dead_code)]

use std::convert::Infallible;
use std::hint::black_box;

use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::stepper::{Direction, StepTiming, Stepper};
use forja_hal_abstraction::time::Instant;
use forja_motion::{AxisConfig, Kernel, MachineConfig};

/// A step/direction output that counts its steps; `black_box` keeps every call.
pub struct Pin(pub u64);
impl ErrorType for Pin {
    type Error = Infallible;
}
impl Stepper for Pin {
    fn set_direction(&mut self, d: Direction) -> Result<(), Infallible> {
        black_box(d);
        Ok(())
    }
    fn step_begin(&mut self) -> Result<(), Infallible> {
        self.0 += 1;
        Ok(())
    }
    fn step_end(&mut self) -> Result<(), Infallible> {
        black_box(());
        Ok(())
    }
    fn timing(&self) -> StepTiming {
        StepTiming::CONSERVATIVE
    }
}
/// A limit switch that is never triggered.
pub struct Switch;
impl ErrorType for Switch {
    type Error = Infallible;
}
impl LimitSwitch for Switch {
    fn is_triggered(&mut self) -> Result<bool, Infallible> {
        Ok(black_box(false))
    }
}

/// X and Y 80 steps/mm, 12,000 mm/min, 3,000 mm/s²; Z 400 steps/mm, 900 mm/min, 200 mm/s².
pub fn config() -> MachineConfig<3> {
    MachineConfig::new([
        AxisConfig::linear(b'X', 80.0, 12_000.0, 3000.0, 1000.0),
        AxisConfig::linear(b'Y', 80.0, 12_000.0, 3000.0, 1000.0),
        AxisConfig::linear(b'Z', 400.0, 900.0, 200.0, 200.0),
    ])
}

/// `n` lines of 1 mm segments along a slowly turning path.
pub fn program(n: usize) -> Vec<String> {
    let (mut x, mut y) = (500.0f64, 500.0f64);
    (0..n)
        .map(|k| {
            let a = k as f64 * 0.05;
            x += a.cos();
            y += a.sin();
            format!("G1 X{x:.3} Y{y:.3} F6000")
        })
        .collect()
}

/// The thread loop's turn at `now`: `poll` (the kernel's, or a counted call of it), again at
/// once while the kernel has steps left to prepare, as a board's loop does. Returns where to
/// arm the step alarm, if anywhere.
pub fn thread_turn<'q>(
    kernel: &mut Kernel<'q, 3>,
    now: Instant,
    poll: impl Fn(&mut Kernel<'q, 3>, Instant) -> Option<Instant>,
) -> Option<Instant> {
    let mut arm = None;
    loop {
        arm = poll(kernel, now).or(arm);
        if !kernel.needs_poll() {
            return arm;
        }
    }
}
