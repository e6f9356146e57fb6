//! Stored programs through the controller: a program whose upload was interrupted never runs,
//! and a job interrupted by a power cut resumes after its last finished line (`M1000`).

use super::*;
use crate::controller::store::{RESUME_RECORD, ResumeRecord};
use forja_hal_abstraction::storage::RecordStorage as _;

/// Switch the bench on over `program` and the settings `storage`, the motors at `physical`;
/// its `start` is read.
fn switch_on<P: ProgramStore>(program: P, storage: VecStorage, physical: [i32; 3]) -> Bench<P> {
    let mut b = Bench::boot(machine(), program, storage, physical);
    b.take();
    b
}

/// The resume record kept in `storage`, if any.
fn resume_record(storage: &mut VecStorage) -> Option<ResumeRecord> {
    let mut buf = [0u8; 16];
    let n = storage.read(RESUME_RECORD, &mut buf).unwrap()?;
    ResumeRecord::decode(&buf[..n])
}

impl<P: ProgramStore> Bench<P> {
    /// Send `msg`, run 3 ms, and return what came back.
    fn ask_frame(&mut self, msg: &ClientMessage<'_>) -> Vec<String> {
        self.send_frame(msg);
        self.run_ms(3);
        self.take()
    }

    /// Frame 03: line `index` of a program of `total`.
    fn load(&mut self, index: u16, text: &str, total: u16) -> Vec<String> {
        self.ask_frame(&ClientMessage::LoadLine { index, text, total })
    }

    /// The `NL` and `LA` of a 52.
    fn progress(&mut self) -> (u32, u32) {
        let out = self.ask_frame(&ClientMessage::Request { message_type: 52 });
        match frames_of(&out).first() {
            Some(ControllerMessage::Progress(p)) => (p.total_lines, p.current_line),
            _ => panic!("{out:?}"),
        }
    }

    /// Home every axis and wait for the end of the cycle.
    fn home(&mut self) {
        assert_eq!(
            self.ask_frame(&ClientMessage::Action(Action::HomeAll)),
            [""; 0]
        );
        self.run_ms(2);
        self.run_until(60_000, |b| {
            b.ctl.kernel().is_idle() && b.ctl.kernel().homed_axes() == 3
        });
    }

    /// Where the motors are, steps from where the machine was first switched on.
    fn physical(&self) -> [i32; 3] {
        self.wiring.positions()
    }
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
    let store = RecordProgramStore::open(VecStorage::default(), 64).unwrap();
    let mut rig = switch_on(store, VecStorage::default(), [0; 3]);
    let a = lines(1, 10);
    for (k, l) in a.iter().enumerate().take(4) {
        assert_eq!(rig.load(k as u16 + 1, l, 10), [""; 0]);
    }
    assert_eq!(rig.progress(), (4, 0));
    let out = rig.ask_frame(&ClientMessage::Action(Action::Start));
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
    let mut rig = switch_on(store, storage, physical);
    assert_eq!(rig.progress(), (4, 0));
    let out = rig.ask_frame(&ClientMessage::Action(Action::Start));
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
    rig.ask_frame(&ClientMessage::Action(Action::Start));
    rig.run_until(20_000, |r| r.ctl.job().state() == JobState::Finished);
    assert_eq!(rig.ctl.stats().program_lines, 10);
}

/// A program of `n` relative 1 mm moves along X at 300 mm/min: line `k + 2` ends
/// `k + 1` mm from where the program started.
fn slow_program(n: u16) -> Vec<String> {
    let mut p = std::vec!["G91".to_string(), "G1 F300".to_string()];
    p.extend((0..n).map(|_| "G1 X1".to_string()));
    p
}

fn upload<P: ProgramStore>(rig: &mut Bench<P>, program: &[String]) {
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
    let mut rig = switch_on(RamStore::<128>::new(), VecStorage::default(), [0; 3]);
    assert_eq!(rig.ask("M413"), ["// power-loss recovery on", "ok"]);
    assert_eq!(rig.ask("M1000"), ["echo:E186 no-resume", "ok"]);
    rig.home();
    let home = rig.physical();
    upload(&mut rig, &program);
    rig.ask_frame(&ClientMessage::Action(Action::Start));
    rig.run_ms(15_000);
    assert_eq!(rig.ctl.job().state(), JobState::Running);
    // The power goes.
    let (store, mut storage, physical) = rig.power_off();
    let record = resume_record(&mut storage).expect("a record");
    let x_done_mm = f64::from(physical[0] - home[0]) / 80.0;
    assert!(record.done >= 20, "progress was recorded: {record:?}");
    // Line k + 2 ends k + 1 mm along: every recorded line had finished.
    assert!(
        f64::from(record.done) - 2.0 <= x_done_mm + 1e-9,
        "{record:?} but the machine was at {x_done_mm} mm"
    );

    let mut rig = switch_on(store, storage, physical);
    assert_eq!(rig.ask("M1000"), ["echo:E187 not-homed", "ok"]);
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
    assert_eq!(resume_record(&mut storage), None);
}

/// `M1000` refuses a changed program, `M1000 C` forgets the record, `M413 S0` stops
/// recording.
#[test]
fn resume_refuses_a_changed_program_and_can_be_cancelled_or_switched_off() {
    let program = slow_program(40);
    let mut rig = switch_on(RamStore::<128>::new(), VecStorage::default(), [0; 3]);
    rig.home();
    upload(&mut rig, &program);
    rig.ask_frame(&ClientMessage::Action(Action::Start));
    rig.run_ms(3_000);
    let (mut store, storage, physical) = rig.power_off();
    // Another program of the same length replaces it.
    store.begin(program.len() as u16).unwrap();
    for (k, l) in program.iter().enumerate() {
        let l = if k == 5 { "G1 X2" } else { l.as_str() };
        store.store(k as u16 + 1, l.as_bytes()).unwrap();
    }
    let mut rig = switch_on(store, storage, physical);
    rig.home();
    assert_eq!(rig.ask("M1000"), ["echo:E188 program-changed", "ok"]);
    // Marlin's form: `C` alone.
    assert_eq!(rig.ask("M1000 C"), ["ok"]);
    assert_eq!(rig.ask("M1000"), ["echo:E186 no-resume", "ok"]);
    assert_eq!(rig.ask("M413 S0"), ["ok"]);
    assert_eq!(rig.ask("M413"), ["// power-loss recovery off", "ok"]);
    assert_eq!(rig.ask("M413 S2"), ["echo:E121 bad-value S", "ok"]);
    assert_eq!(rig.ask("M413 S"), ["echo:E122 missing-value S", "ok"]);
    rig.ask_frame(&ClientMessage::Action(Action::Start));
    rig.run_ms(3_000);
    let (store, mut storage, physical) = rig.power_off();
    assert_eq!(resume_record(&mut storage), None, "recovery off: no record");
    // The switch is a setting, kept across a power cycle and read by frame 00.
    let mut rig = switch_on(store, storage, physical);
    assert_eq!(rig.ask("M413"), ["// power-loss recovery off", "ok"]);
    let out = rig.ask_frame(&ClientMessage::ReadSetting {
        key: "power_loss_recovery",
    });
    assert_eq!(
        frames_of(&out),
        [ControllerMessage::Setting {
            key: "power_loss_recovery",
            value: "0"
        }]
    );
}
