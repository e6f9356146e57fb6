//! Jobs from the program store: the frame actions, progress, and the time estimate against
//! the simulated execution.

mod common;

use common::{machine, sim};
use forja_hal_abstraction::time::Instant;
use forja_motion::job::{Job, JobState, ProgramStore, RamStore};
use forja_motion::sim::Simulation;
use forja_motion::{Effect, StepQueue, StoreError};

const HZ: u32 = 1_000_000;

fn load<const L: usize>(store: &mut RamStore<L>, lines: &[String]) {
    store.begin(lines.len() as u16).expect("begin");
    for (i, l) in lines.iter().enumerate() {
        store.store(i as u16 + 1, l.as_bytes()).expect("store");
    }
}

/// Run the job to its end; returns the virtual ticks it took and the effects it produced.
fn run_job<const L: usize>(
    s: &mut Simulation<'_, 3, 32, 256>,
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
        s.advance(s.poll_period);
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
        s.rec.borrow_mut().record = false;
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
        s.advance(s.poll_period);
    }
    assert_eq!(effects, [false, true], "fan, then the pause");
    assert_eq!(job.state(), JobState::Paused);
    assert_eq!(s.rec.borrow().position[..2], [4000, 4000]);
    let p = job.progress(&s.kernel, &store);
    assert_eq!((p.total_lines, p.current_line), (6, 3));
    // Resume with Start, then pause (feed hold) during the next move.
    let t = Instant::from_ticks(s.now() as u32);
    job.start(&mut s.kernel, &mut store, t).expect("resume");
    for _ in 0..500 {
        let t = Instant::from_ticks(s.now() as u32);
        job.poll(&mut s.kernel, &mut store, t).expect("ok");
        s.advance(s.poll_period);
    }
    job.pause(&mut s.kernel).expect("pause");
    assert!(s.run_until_idle(10 * u64::from(HZ)) || job.state() == JobState::Paused);
    let held = s.rec.borrow().position;
    assert!(held[0] > 0 && held[0] < 4000, "{held:?}");
    let t = Instant::from_ticks(s.now() as u32);
    job.start(&mut s.kernel, &mut store, t).expect("resume");
    for _ in 0..200 {
        let t = Instant::from_ticks(s.now() as u32);
        job.poll(&mut s.kernel, &mut store, t).expect("ok");
        s.advance(s.poll_period);
    }
    // Stop: motion ends, position kept, job idle; rewind goes back to line 1.
    job.stop(&mut s.kernel);
    assert!(s.run_until_idle(10 * u64::from(HZ)));
    assert_eq!(job.state(), JobState::Idle);
    assert_eq!(s.kernel.machine_steps(), s.rec.borrow().position);
    job.rewind().expect("rewind");
    assert_eq!(job.next_line(), 1);
    assert!(s.rec.borrow().violations.is_empty());
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

// ---------------------------------------------------------------------------------------
// Through the controller: programs whose upload was interrupted never run (issue 11, item
// 7), and a job interrupted by a power cut resumes after its last finished line (`M1000`).
// ---------------------------------------------------------------------------------------

mod controller_level {
    use std::cell::RefCell;
    use std::collections::VecDeque;
    use std::rc::Rc;

    use super::common::machine;
    use forja_hal_abstraction::stepper::StepTiming;
    use forja_hal_abstraction::storage::RecordStorage;
    use forja_hal_abstraction::time::Instant;
    use forja_motion::controller::store::{RESUME_RECORD, ResumeRecord};
    use forja_motion::controller::{
        Controller, ControllerConfig, NoPeripherals, RecordProgramStore, Settings,
    };
    use forja_motion::job::{JobState, ProgramStore, RamStore};
    use forja_motion::sim::{EdgeWatch, Recorder, SimStepper, SimSwitch, Simulation};
    use forja_motion::{StepGenerator, StepQueue, split};
    use forja_protocol::frame::{Action, ClientMessage, ControllerMessage, FRAME_LEN};

    const TICK_HZ: u32 = 1_000_000;

    /// Keyed records in memory (the last write of a key wins), as a flash record store.
    #[derive(Default, Clone)]
    struct MemStorage {
        records: Vec<(u16, Vec<u8>)>,
    }

    impl forja_hal_abstraction::ErrorType for MemStorage {
        type Error = core::convert::Infallible;
    }

    impl RecordStorage for MemStorage {
        fn read(&mut self, key: u16, buf: &mut [u8]) -> Result<Option<usize>, Self::Error> {
            Ok(self
                .records
                .iter()
                .rev()
                .find(|(k, _)| *k == key)
                .map(|(_, v)| {
                    buf[..v.len()].copy_from_slice(v);
                    v.len()
                }))
        }
        fn write(&mut self, key: u16, value: &[u8]) -> Result<(), Self::Error> {
            self.records.push((key, value.to_vec()));
            Ok(())
        }
        fn remove(&mut self, key: u16) -> Result<(), Self::Error> {
            self.records.retain(|(k, _)| *k != key);
            Ok(())
        }
    }

    impl MemStorage {
        fn resume_record(&mut self) -> Option<ResumeRecord> {
            let mut buf = [0u8; 16];
            let n = self.read(RESUME_RECORD, &mut buf).unwrap()?;
            ResumeRecord::decode(&buf[..n])
        }
    }

    #[derive(Default)]
    struct MemLink {
        rx: VecDeque<u8>,
        tx: Vec<u8>,
    }

    impl embedded_io::ErrorType for MemLink {
        type Error = core::convert::Infallible;
    }

    impl embedded_io::Read for MemLink {
        fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
            let n = buf.len().min(self.rx.len());
            for (d, s) in buf.iter_mut().zip(self.rx.drain(..n)) {
                *d = s;
            }
            Ok(n)
        }
    }

    impl embedded_io::ReadReady for MemLink {
        fn read_ready(&mut self) -> Result<bool, Self::Error> {
            Ok(!self.rx.is_empty())
        }
    }

    impl embedded_io::Write for MemLink {
        fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
            self.tx.extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> Result<(), Self::Error> {
            Ok(())
        }
    }

    type Ctl<P> = Controller<'static, 3, 32, 256, P, NoPeripherals, MemStorage>;

    /// A controller on a simulated machine, polled every millisecond of virtual time. The
    /// machine's switches sit 10 mm below where it is first switched on.
    struct Rig<P: ProgramStore> {
        ctl: Ctl<P>,
        isr: StepGenerator<'static, 3, 256>,
        steppers: [SimStepper<3>; 3],
        switches: Vec<SimSwitch<3>>,
        edges: EdgeWatch<'static>,
        rec: Rc<RefCell<Recorder<3>>>,
        alarm: Option<u64>,
        next_poll: u64,
        link: MemLink,
        out: String,
    }

    impl<P: ProgramStore> Rig<P> {
        /// Switch on (again): a new kernel over `program` and `storage`, the motors where
        /// `physical` (steps from where the machine was first switched on) says.
        fn boot(program: P, storage: MemStorage, physical: [i32; 3]) -> Self {
            let queue: &'static mut StepQueue<3, 256> = Box::leak(Box::new(StepQueue::new()));
            let timing = StepTiming::CONSERVATIVE;
            let (kernel, isr) = split::<3, 32, 256>(queue, machine(), TICK_HZ, timing).unwrap();
            let mut sim = Simulation::new(kernel, isr, timing);
            sim.add_switch(0, -800, true);
            sim.add_switch(1, -800, true);
            sim.rec.borrow_mut().position = physical;
            sim.rec.borrow_mut().record = false;
            let cfg = ControllerConfig::new("test-rig", timing);
            let ctl = Controller::new(sim.kernel, program, NoPeripherals, cfg)
                .with_settings(Settings::new(machine()), storage);
            let mut rig = Self {
                ctl,
                isr: sim.isr,
                steppers: sim.steppers,
                switches: sim.switches,
                edges: sim.edges,
                rec: sim.rec,
                alarm: None,
                next_poll: 0,
                link: MemLink::default(),
                out: String::new(),
            };
            rig.ctl.boot(&mut rig.link);
            rig.take();
            rig
        }

        /// Power off: the program store, the settings storage, and where the motors are.
        fn power_off(self) -> (P, MemStorage, [i32; 3]) {
            let physical = self.rec.borrow().position;
            let (_, program, _, storage) = self.ctl.release();
            (program, storage, physical)
        }

        fn now(&self) -> u64 {
            self.rec.borrow().now
        }

        fn abs(&self, at: Instant) -> u64 {
            let now = self.now();
            now + at
                .signed_ticks_since(Instant::from_ticks(now as u32))
                .max(0) as u64
        }

        fn run_ms(&mut self, ms: u64) {
            let until = self.now() + ms * 1000;
            loop {
                let t_alarm = self.alarm.unwrap_or(u64::MAX);
                let t = t_alarm.min(self.next_poll);
                if t > until {
                    let mut r = self.rec.borrow_mut();
                    r.now = r.now.max(until);
                    break;
                }
                {
                    let mut r = self.rec.borrow_mut();
                    r.now = r.now.max(t);
                }
                let now = Instant::from_ticks(self.now() as u32);
                if t_alarm <= self.next_poll {
                    self.alarm = None;
                    let at = self
                        .isr
                        .on_alarm(now, &mut self.steppers, &mut self.switches);
                    self.edges.look(&mut self.switches);
                    self.alarm = at.map(|i| self.abs(i));
                } else {
                    self.next_poll = t + 1000;
                    let out = self.ctl.poll(now, &mut self.link);
                    if let Some(at) = out.arm_alarm {
                        let a = self.abs(at);
                        self.alarm = Some(self.alarm.map_or(a, |x| x.min(a)));
                    }
                }
            }
            let bytes = core::mem::take(&mut self.link.tx);
            self.out.push_str(&String::from_utf8(bytes).unwrap());
        }

        fn take(&mut self) -> Vec<String> {
            let bytes = core::mem::take(&mut self.link.tx);
            self.out.push_str(&String::from_utf8(bytes).unwrap());
            let text = core::mem::take(&mut self.out);
            text.lines().map(str::to_string).collect()
        }

        fn ask(&mut self, text: &str) -> Vec<String> {
            self.link.rx.extend(text.as_bytes());
            self.link.rx.push_back(b'\n');
            self.run_ms(5);
            self.take()
        }

        fn frame(&mut self, msg: &ClientMessage<'_>) -> Vec<String> {
            let mut f = [0u8; FRAME_LEN];
            msg.encode(&mut f).unwrap();
            self.link.rx.extend(f);
            self.link.rx.push_back(b'\n');
            self.run_ms(3);
            self.take()
        }

        fn load(&mut self, index: u16, text: &str, total: u16) -> Vec<String> {
            self.frame(&ClientMessage::LoadLine { index, text, total })
        }

        /// The `NL` and `LA` of a 52.
        fn progress(&mut self) -> (u32, u32) {
            let out = self.frame(&ClientMessage::Request { message_type: 52 });
            match frames_of(&out).first() {
                Some(ControllerMessage::Progress(p)) => (p.total_lines, p.current_line),
                _ => panic!("{out:?}"),
            }
        }

        fn run_until(&mut self, max_ms: u64, mut done: impl FnMut(&mut Self) -> bool) {
            for _ in 0..max_ms {
                if done(self) {
                    return;
                }
                self.run_ms(1);
            }
            panic!("not done after {max_ms} ms; output: {:?}", self.out);
        }

        fn home(&mut self) {
            assert_eq!(self.frame(&ClientMessage::Action(Action::HomeAll)), [""; 0]);
            self.run_ms(2);
            self.run_until(60_000, |r| {
                r.ctl.kernel().is_idle() && r.ctl.kernel().homed_axes() == 3
            });
        }

        fn physical(&self) -> [i32; 3] {
            self.rec.borrow().position
        }
    }

    fn frames_of(lines: &[String]) -> Vec<ControllerMessage<'_>> {
        lines
            .iter()
            .filter(|l| l.len() == FRAME_LEN && l.starts_with('N'))
            .map(|l| ControllerMessage::decode(l.as_bytes()).unwrap())
            .collect()
    }

    fn error_codes(lines: &[String]) -> Vec<u16> {
        frames_of(lines)
            .iter()
            .filter_map(|m| match m {
                ControllerMessage::Error { code, .. } => Some(*code),
                _ => None,
            })
            .collect()
    }

    fn lines(tag: u32, n: u16) -> Vec<String> {
        (1..=n)
            .map(|k| format!("G1 X{}.{tag} F3000", k + 10))
            .collect()
    }

    /// Item 7: after 4 of 10 lines, 52 says `NL0004LA0000`, Start is refused with
    /// `E185 program-incomplete` and nothing moves; `M20` lists the program as incomplete.
    /// Lines 5–10 of another program with the same total, from a new host, are refused
    /// (`E175 no-upload`); after a restart the program is still incomplete and still refused;
    /// a fresh line 1 starts a new upload, which runs once complete.
    #[test]
    fn a_half_uploaded_program_never_runs() {
        let store = RecordProgramStore::open(MemStorage::default(), 64).unwrap();
        let mut rig = Rig::boot(store, MemStorage::default(), [0; 3]);
        let a = lines(1, 10);
        for (k, l) in a.iter().enumerate().take(4) {
            assert_eq!(rig.load(k as u16 + 1, l, 10), [""; 0]);
        }
        assert_eq!(rig.progress(), (4, 0));
        let out = rig.frame(&ClientMessage::Action(Action::Start));
        assert_eq!(error_codes(&out), [185], "{out:?}");
        assert!(out[0].contains("program-incomplete"), "{out:?}");
        rig.run_ms(200);
        assert_eq!(rig.ctl.job().state(), JobState::Idle);
        assert_eq!(rig.ctl.stats().program_lines, 0);
        assert_eq!(rig.physical(), [0; 3], "no motor step");
        assert_eq!(
            rig.ask("M20"),
            [
                "Begin file list",
                "program 4/10 incomplete",
                "End file list",
                "ok"
            ]
        );

        // Another host on the link sends lines 5–10 of its own program of 10 lines.
        rig.ctl.reset_link();
        let b = lines(2, 10);
        for (k, l) in b.iter().enumerate().skip(4) {
            let out = rig.load(k as u16 + 1, l, 10);
            // Line 5 would continue the program: no upload is open for it; the others are
            // out of order.
            let code = if k == 4 { 175 } else { 170 };
            assert_eq!(error_codes(&out), [code], "line {}: {out:?}", k + 1);
        }
        assert_eq!(rig.progress(), (4, 0));
        assert!(!rig.ctl.program().is_complete());

        // A restart: still incomplete, still refused, and the upload cannot go on.
        let (program, storage, physical) = rig.power_off();
        let store = RecordProgramStore::open(program.into_inner(), 64).unwrap();
        let mut rig = Rig::boot(store, storage, physical);
        assert_eq!(rig.progress(), (4, 0));
        let out = rig.frame(&ClientMessage::Action(Action::Start));
        assert_eq!(error_codes(&out), [185], "{out:?}");
        assert_eq!(error_codes(&rig.load(5, &a[4], 10)), [175]);

        // Line 1 starts over; the complete program runs, each line once.
        for (k, l) in b.iter().enumerate() {
            let out = rig.load(k as u16 + 1, l, 10);
            assert!(error_codes(&out).is_empty(), "{out:?}");
        }
        assert_eq!(rig.progress(), (10, 1));
        assert_eq!(
            rig.ask("M20"),
            [
                "Begin file list",
                "program 10/10 complete",
                "End file list",
                "ok"
            ]
        );
        rig.frame(&ClientMessage::Action(Action::Start));
        rig.run_until(20_000, |r| r.ctl.job().state() == JobState::Finished);
        assert_eq!(rig.ctl.stats().program_lines, 10);
    }

    /// A program of `n` relative 1 mm moves along X at 300 mm/min: line `k + 2` ends
    /// `k + 1` mm from where the program started.
    fn slow_program(n: u16) -> Vec<String> {
        let mut p = vec!["G91".to_string(), "G1 F300".to_string()];
        p.extend((0..n).map(|_| "G1 X1".to_string()));
        p
    }

    fn upload<P: ProgramStore>(rig: &mut Rig<P>, program: &[String]) {
        let total = program.len() as u16;
        for (k, l) in program.iter().enumerate() {
            let out = rig.load(k as u16 + 1, l, total);
            assert!(error_codes(&out).is_empty(), "{out:?}");
        }
    }

    /// Resume after a power cut: the record names only lines whose motion had finished (never
    /// one not done), `M1000` is refused before homing and runs the rest after it, replaying
    /// the program's relative mode; the job ends where an uninterrupted run ends.
    #[test]
    fn a_job_cut_by_power_loss_resumes_after_its_last_finished_line() {
        let program = slow_program(100);
        let mut rig = Rig::boot(RamStore::<128>::new(), MemStorage::default(), [0; 3]);
        assert_eq!(rig.ask("M413"), ["// power-loss recovery on", "ok"]);
        assert_eq!(rig.ask("M1000"), ["!! E186 no-resume", "ok"]);
        rig.home();
        let home = rig.physical();
        upload(&mut rig, &program);
        rig.frame(&ClientMessage::Action(Action::Start));
        rig.run_ms(15_000);
        assert_eq!(rig.ctl.job().state(), JobState::Running);
        // The power goes.
        let (store, mut storage, physical) = rig.power_off();
        let record = storage.resume_record().expect("a record");
        let x_done_mm = f64::from(physical[0] - home[0]) / 80.0;
        assert!(record.done >= 20, "progress was recorded: {record:?}");
        // Line k + 2 ends k + 1 mm along: every recorded line had finished.
        assert!(
            f64::from(record.done) - 2.0 <= x_done_mm + 1e-9,
            "{record:?} but the machine was at {x_done_mm} mm"
        );

        let mut rig = Rig::boot(store, storage, physical);
        assert_eq!(rig.ask("M1000"), ["!! E187 not-homed", "ok"]);
        rig.home();
        assert_eq!(rig.physical(), home);
        assert_eq!(rig.ask("M1000"), ["ok"]);
        rig.run_until(60_000, |r| r.ctl.job().state() == JobState::Finished);
        rig.run_ms(100);
        assert_eq!(
            rig.physical()[0] - home[0],
            100 * 80,
            "ends where the program ends"
        );
        assert_eq!(
            u32::from(program.len() as u16 - record.done),
            rig.ctl.stats().program_lines,
            "runs the lines after the record, each once"
        );
        // Finished: nothing left to resume.
        let (_, mut storage, _) = rig.power_off();
        assert_eq!(storage.resume_record(), None);
    }

    /// `M1000` refuses a changed program, `M1000 C1` forgets the record, `M413 S0` stops
    /// recording.
    #[test]
    fn resume_refuses_a_changed_program_and_can_be_cancelled_or_switched_off() {
        let program = slow_program(40);
        let mut rig = Rig::boot(RamStore::<128>::new(), MemStorage::default(), [0; 3]);
        rig.home();
        upload(&mut rig, &program);
        rig.frame(&ClientMessage::Action(Action::Start));
        rig.run_ms(3_000);
        let (mut store, storage, physical) = rig.power_off();
        // Another program of the same length replaces it.
        store.begin(program.len() as u16).unwrap();
        for (k, l) in program.iter().enumerate() {
            let l = if k == 5 { "G1 X2" } else { l.as_str() };
            store.store(k as u16 + 1, l.as_bytes()).unwrap();
        }
        let mut rig = Rig::boot(store, storage, physical);
        rig.home();
        assert_eq!(rig.ask("M1000"), ["!! E188 program-changed", "ok"]);
        assert_eq!(rig.ask("M1000 C1"), ["ok"]);
        assert_eq!(rig.ask("M1000"), ["!! E186 no-resume", "ok"]);
        assert_eq!(rig.ask("M413 S0"), ["ok"]);
        assert_eq!(rig.ask("M413"), ["// power-loss recovery off", "ok"]);
        assert_eq!(rig.ask("M413 S2"), ["!! E121 bad-value S", "ok"]);
        rig.frame(&ClientMessage::Action(Action::Start));
        rig.run_ms(3_000);
        let (_, mut storage, _) = rig.power_off();
        assert_eq!(storage.resume_record(), None, "recovery off: no record");
    }
}
