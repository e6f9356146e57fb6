//! Criterion benchmarks of the motion kernel (results in `docs/performance.md`).
//!
//! - `plan/1mm_lines`: G-code lines parsed, interpreted and planned per second, for a program
//!   of 1 mm segments (the planner dry run behind the job estimate: parse, interpret, plan,
//!   time each block's profile).
//! - `pipeline/steps`: the whole kernel — lines in, step events prepared (thread side) and
//!   executed (interrupt side, no-op pins) — in step events per second.
//! - `isr/on_alarm`: one interrupt-side call, with the queue filled beforehand (untimed).
#![allow(missing_docs)]

use std::time::{Duration, Instant as WallInstant};

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use forja_hal_abstraction::stepper::StepTiming;
use forja_hal_abstraction::time::Instant;
use forja_motion::{Estimate, Kernel, Reply, StepGenerator, StepQueue, split};
use forja_protocol::gcode::Line;

mod common;
use common::{Pin, Switch, config, program, thread_turn};

fn plan(c: &mut Criterion) {
    let lines = program(2000);
    let mut q = StepQueue::<3, 256>::new();
    let (kernel, _isr): (Kernel<'_, 3>, _) =
        split(&mut q, config(), 1_000_000, StepTiming::CONSERVATIVE).expect("valid");
    let mut g = c.benchmark_group("plan");
    g.throughput(Throughput::Elements(lines.len() as u64));
    g.bench_function("1mm_lines", |b| {
        b.iter(|| {
            let mut estimate = Estimate::new(&kernel);
            for text in &lines {
                let line = Line::parse(text.as_bytes()).expect("valid G-code");
                estimate.line(&line);
            }
            estimate.seconds()
        })
    });
    g.finish();
}

/// Feed `lines` through the kernel and run the interrupt side as fast as it asks; returns
/// the step events (rising edges) executed and the interrupt calls made.
fn run_pipeline(
    kernel: &mut Kernel<'_, 3>,
    isr: &mut StepGenerator<'_, 3, 256>,
    lines: &[String],
    now: &mut u32,
) -> (u64, u64) {
    let mut pins = [Pin(0), Pin(0), Pin(0)];
    let mut switches = [Switch];
    let mut calls = 0u64;
    let mut steps = 0u64;
    let mut alarm: Option<Instant> = None;
    let mut next = 0;
    loop {
        while next < lines.len() && kernel.can_accept() {
            let line = Line::parse(lines[next].as_bytes()).expect("parses");
            match kernel.execute(&line).expect("ok") {
                Reply::Busy => break,
                _ => next += 1,
            }
        }
        if let Some(at) = thread_turn(kernel, Instant::from_ticks(*now), |k, t| k.poll(t)) {
            alarm = Some(at);
        }
        // Run the interrupt for up to 1 ms of machine time, then poll again.
        let until = now.wrapping_add(1000);
        while let Some(at) = alarm {
            if at.signed_ticks_since(Instant::from_ticks(until)) > 0 {
                break;
            }
            *now = (*now).max(at.ticks());
            alarm = isr.on_alarm(at, &mut pins, &mut switches);
            calls += 1;
        }
        *now = until;
        if next == lines.len() && kernel.is_idle() {
            break;
        }
    }
    steps += pins.iter().map(|p| p.0).sum::<u64>();
    (steps, calls)
}

fn pipeline(c: &mut Criterion) {
    let lines = program(300);
    let mut q = StepQueue::<3, 256>::new();
    let (mut kernel, mut isr): (Kernel<'_, 3>, _) =
        split(&mut q, config(), 1_000_000, StepTiming::CONSERVATIVE).expect("valid");
    let mut now = 0u32;
    let back: Vec<String> = {
        let mut b = lines.clone();
        b.reverse();
        b.push("G1 X500 Y500".into());
        b
    };
    // Go to the start, and back; then count the step events of one pass from the start.
    let _ = run_pipeline(&mut kernel, &mut isr, &lines, &mut now);
    let _ = run_pipeline(&mut kernel, &mut isr, &back, &mut now);
    let (steps, _) = run_pipeline(&mut kernel, &mut isr, &lines, &mut now);
    let _ = run_pipeline(&mut kernel, &mut isr, &back, &mut now);
    let mut g = c.benchmark_group("pipeline");
    g.throughput(Throughput::Elements(steps));
    g.sample_size(10);
    g.measurement_time(Duration::from_secs(8));
    g.bench_function("steps", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                // Back to the start (untimed), then the timed pass.
                let _ = run_pipeline(&mut kernel, &mut isr, &back, &mut now);
                let t = WallInstant::now();
                let _ = run_pipeline(&mut kernel, &mut isr, &lines, &mut now);
                total += t.elapsed();
            }
            total
        })
    });
    g.finish();
}

fn isr(c: &mut Criterion) {
    let mut q = StepQueue::<3, 256>::new();
    let (mut kernel, mut isr): (Kernel<'_, 3>, _) =
        split(&mut q, config(), 1_000_000, StepTiming::CONSERVATIVE).expect("valid");
    let mut pins = [Pin(0), Pin(0), Pin(0)];
    let mut switches = [Switch];
    let mut now = 0u32;
    let mut dir = 1;
    let mut alarm: Option<Instant> = None;
    let mut g = c.benchmark_group("isr");
    g.throughput(Throughput::Elements(1));
    g.bench_function("on_alarm", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            let mut done = 0u64;
            while done < iters {
                // Untimed: keep a long diagonal move queued and the step queue full.
                if kernel.is_idle() {
                    dir = -dir;
                    let text = format!("G1 X{} Y{} F6000", 500 + dir * 400, 500 + dir * 300);
                    let line = Line::parse(text.as_bytes()).expect("parses");
                    let _ = kernel.execute(&line).expect("ok");
                }
                if let Some(at) =
                    thread_turn(&mut kernel, Instant::from_ticks(now), |k, t| k.poll(t))
                {
                    alarm = Some(at);
                }
                // Timed: the events of the next millisecond (the thread side keeps 20 ms queued).
                let until = Instant::from_ticks(now.wrapping_add(1000));
                let t = WallInstant::now();
                let mut n = 0;
                while let Some(at) = alarm {
                    if at.signed_ticks_since(until) > 0 || done + n >= iters {
                        break;
                    }
                    alarm = isr.on_alarm(at, &mut pins, &mut switches);
                    n += 1;
                }
                total += t.elapsed();
                now = until.ticks();
                done += n;
            }
            total
        })
    });
    g.finish();
}

criterion_group!(benches, plan, pipeline, isr);
criterion_main!(benches);
