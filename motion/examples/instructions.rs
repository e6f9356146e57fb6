//! Workload for instruction counting under `valgrind --tool=callgrind` (see
//! `docs/performance.md`): plans a program of 1 mm segments, then runs it through the whole
//! kernel with no-op pins. The three measured parts are separate, never-inlined functions so
//! that `--toggle-collect` can count each one:
//!
//! ```text
//! cargo build --release -p forja-motion --example instructions
//! valgrind --tool=callgrind --toggle-collect='*count_plan*' target/release/examples/instructions
//! valgrind --tool=callgrind --toggle-collect='*count_isr*' target/release/examples/instructions
//! valgrind --tool=callgrind --toggle-collect='*count_thread*' target/release/examples/instructions
//! ```
//!
//! It prints the number of lines, step events and interrupt calls to divide by.

use forja_hal_abstraction::stepper::StepTiming;
use forja_hal_abstraction::time::Instant;
use forja_motion::{Estimate, Kernel, Reply, StepGenerator, StepQueue, split};
use forja_protocol::gcode::Line;

#[path = "../benches/common/mod.rs"]
mod common;
use common::{Pin, Switch, config, program, thread_turn};

#[inline(never)]
fn count_plan(kernel: &Kernel<'_, 3>, lines: &[String]) -> f32 {
    let mut estimate = Estimate::new(kernel);
    for text in lines {
        if let Ok(line) = Line::parse(text.as_bytes()) {
            estimate.line(&line);
        }
    }
    estimate.seconds()
}

#[inline(never)]
fn count_isr(
    isr: &mut StepGenerator<'_, 3, 256>,
    at: Instant,
    pins: &mut [Pin; 3],
    sw: &mut [Switch; 1],
) -> Option<Instant> {
    isr.on_alarm(at, pins, sw)
}

#[inline(never)]
fn count_thread(kernel: &mut Kernel<'_, 3>, now: Instant) -> Option<Instant> {
    kernel.poll(now)
}

#[inline(never)]
fn count_execute(kernel: &mut Kernel<'_, 3>, text: &str) -> bool {
    match Line::parse(text.as_bytes()) {
        Ok(line) => !matches!(kernel.execute(&line), Ok(Reply::Busy)),
        Err(_) => true,
    }
}

fn main() {
    let lines = program(1000);
    let mut q = StepQueue::<3, 256>::new();
    let Ok((mut kernel, mut isr)) =
        split::<3, 32, 256>(&mut q, config(), 1_000_000, StepTiming::CONSERVATIVE)
    else {
        return;
    };
    let t = count_plan(&kernel, &lines);
    println!("plan: {} lines, estimate {t:.2} s", lines.len());

    let mut pins = [Pin(0), Pin(0), Pin(0)];
    let mut sw = [Switch];
    let mut now = 0u32;
    let mut alarm = None;
    let mut calls = 0u64;
    let mut next = 0;
    loop {
        while next < lines.len() && kernel.can_accept() && count_execute(&mut kernel, &lines[next])
        {
            next += 1;
        }
        if let Some(at) = thread_turn(&mut kernel, Instant::from_ticks(now), count_thread) {
            alarm = Some(at);
        }
        let until = now.wrapping_add(1000);
        while let Some(at) = alarm {
            if at.signed_ticks_since(Instant::from_ticks(until)) > 0 {
                break;
            }
            now = now.max(at.ticks());
            alarm = count_isr(&mut isr, at, &mut pins, &mut sw);
            calls += 1;
        }
        now = until;
        if next == lines.len() && kernel.is_idle() {
            break;
        }
    }
    let steps: u64 = pins.iter().map(|p| p.0).sum();
    println!(
        "pipeline: {} lines, {steps} step events, {calls} interrupt calls",
        lines.len()
    );
}
