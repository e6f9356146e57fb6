//! Jobs from the program store: the frame actions, progress, and the time estimate against
//! the simulated execution.

#[path = "../../motion/tests/common/mod.rs"]
mod common;

use common::{KernelSim, machine, sim};
use forja_app::job::{Job, JobState};
use forja_hal_abstraction::program::{ProgramStore, RamStore, StoreError};
use forja_hal_abstraction::time::Instant;
use forja_motion::{Effect, StepQueue};

const HZ: u32 = 1_000_000;

fn load<const L: usize>(store: &mut RamStore<L>, lines: &[String]) {
    store.begin(lines.len() as u16).expect("begin");
    for (i, l) in lines.iter().enumerate() {
        store.store(i as u16 + 1, l.as_bytes()).expect("store");
    }
}

/// Run the job to its end; returns the virtual ticks it took and the effects it produced.
fn run_job<const L: usize>(
    s: &mut KernelSim<'_, 3, 32, 256>,
    job: &mut Job,
    store: &mut RamStore<L>,
    max_ticks: u64,
) -> (u64, Vec<String>) {
    let t0 = s.now();
    let mut effects = Vec::new();
    job.start(&mut s.kernel, store, Instant::from_ticks(t0 as u32))
        .expect("start");
    while job.state() == JobState::Running && s.now() - t0 < max_ticks {
        let now = Instant::from_ticks(s.now() as u32);
        if let Some(e) = job.poll(&mut s.kernel, store, now).expect("line ok") {
            effects.push(format!("{e:?}"));
            continue;
        }
        s.poll();
        s.advance(s.poll_period());
    }
    (s.now() - t0, effects)
}

/// A program of short segments: a spiral of 1 mm chords, with corners and feed changes.
fn segments(count: usize) -> Vec<String> {
    let mut lines = vec!["G21 G90".to_string(), "G1 F2400".to_string()];
    let (mut x, mut y) = (100.0f64, 100.0f64);
    for k in 0..count {
        let a = k as f64 * 0.09;
        x += a.cos();
        y += a.sin();
        let mut l = format!("G1 X{x:.3} Y{y:.3}");
        if k % 97 == 50 {
            l += " F4800";
        }
        if k % 97 == 0 {
            l += " F2400";
        }
        lines.push(l);
    }
    lines
}

#[test]
fn estimated_time_agrees_with_execution_within_two_percent() {
    for program in [segments(600), {
        let mut p = segments(150);
        p.push("G0 X10 Y10".into());
        p.push("G4 P250".into());
        p.push("G2 X30 Y10 I10 J0 F1500".into());
        p.push("G1 X30 Y60 Z5 F600".into());
        p
    }] {
        let mut q = StepQueue::<3, 256>::new();
        let mut s = sim(&mut q, machine(), HZ);
        s.wiring.machine.set_tracing(false);
        let mut store = RamStore::<1000>::new();
        load(&mut store, &program);
        let mut job = Job::new();
        let (ticks, _) = run_job(&mut s, &mut job, &mut store, 600 * u64::from(HZ));
        assert_eq!(job.state(), JobState::Finished);
        let actual = ticks as f64 / f64::from(HZ);
        let p = job.progress(&s.kernel, &store);
        let estimate = f64::from(p.estimated_s);
        // The frame shows whole seconds; compare the unrounded estimate.
        let exact = f64::from(job.estimate_s());
        println!("actual {actual:.3} s, estimate {exact:.3} s ({estimate} s)");
        assert!(
            (exact - actual).abs() <= 0.02 * actual,
            "{exact} vs {actual}"
        );
        assert_eq!(p.total_lines, program.len() as u16);
        assert_eq!(p.current_line, program.len() as u16);
    }
}

#[test]
fn start_pause_resume_stop_rewind() {
    let mut q = StepQueue::<3, 256>::new();
    let mut s = sim(&mut q, machine(), HZ);
    let mut store = RamStore::<16>::new();
    let program: Vec<String> = [
        "G1 X50 F3000",
        "M106 S200",
        "G1 Y50",
        "M226",
        "G1 X0",
        "G1 Y0",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    load(&mut store, &program);
    let mut job = Job::new();
    // Nothing stored: start refused.
    let mut empty = RamStore::<4>::new();
    let t = Instant::from_ticks(s.now() as u32);
    assert!(job.start(&mut s.kernel, &mut empty, t).is_err());
    let t = Instant::from_ticks(s.now() as u32);
    job.start(&mut s.kernel, &mut store, t).expect("start");
    // Run to the M226 pause, collecting effects.
    let mut effects = Vec::new();
    for _ in 0..20_000 {
        let t = Instant::from_ticks(s.now() as u32);
        if let Some(e) = job.poll(&mut s.kernel, &mut store, t).expect("ok") {
            effects.push(e == Effect::Paused);
        }
        if job.state() == JobState::Paused {
            break;
        }
        s.advance(s.poll_period());
    }
    assert_eq!(effects, [false, true], "fan, then the pause");
    assert_eq!(job.state(), JobState::Paused);
    assert_eq!(s.positions()[..2], [4000, 4000]);
    let p = job.progress(&s.kernel, &store);
    assert_eq!((p.total_lines, p.current_line), (6, 3));
    // Resume with Start, then pause (feed hold) during the next move.
    let t = Instant::from_ticks(s.now() as u32);
    job.start(&mut s.kernel, &mut store, t).expect("resume");
    for _ in 0..500 {
        let t = Instant::from_ticks(s.now() as u32);
        job.poll(&mut s.kernel, &mut store, t).expect("ok");
        s.advance(s.poll_period());
    }
    job.pause(&mut s.kernel).expect("pause");
    assert!(s.run_until_idle(10 * u64::from(HZ)) || job.state() == JobState::Paused);
    let held = s.positions();
    assert!(held[0] > 0 && held[0] < 4000, "{held:?}");
    let t = Instant::from_ticks(s.now() as u32);
    job.start(&mut s.kernel, &mut store, t).expect("resume");
    for _ in 0..200 {
        let t = Instant::from_ticks(s.now() as u32);
        job.poll(&mut s.kernel, &mut store, t).expect("ok");
        s.advance(s.poll_period());
    }
    // Stop: motion ends, position kept, job idle; rewind goes back to line 1.
    job.stop(&mut s.kernel);
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(job.state(), JobState::Idle);
    assert_eq!(s.kernel.machine_steps(), s.positions());
    job.rewind().expect("rewind");
    assert_eq!(job.next_line(), 1);
    assert!(s.record().violations.is_empty());
}

#[test]
fn the_store_refuses_lines_out_of_order_and_when_full() {
    let mut store = RamStore::<2>::new();
    assert_eq!(store.store(1, b"G1 X1"), Err(StoreError::NoUpload));
    assert_eq!(store.begin(3), Err(StoreError::Full));
    store.begin(2).expect("begin");
    assert_eq!(
        store.store(3, b"G1 X1"),
        Err(StoreError::OutOfOrder {
            expected: 1,
            got: 3
        })
    );
    store.store(1, b"G1 X1").expect("1");
    store.store(2, b"G1 X2").expect("2");
    assert_eq!(store.store(3, b"G1 X3"), Err(StoreError::NoUpload));
    assert_eq!(store.len(), 2);
}
