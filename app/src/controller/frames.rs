//! The 53-byte frames of the operator's client, and garbage on the link.

use embedded_io::Write;
use forja_hal_abstraction::storage::RecordStorage;
use forja_protocol::error::{FrameError, WireError};
use forja_protocol::frame::{
    Action, AxisPosition, CONFIRM_GCODE_LOAD, ClientMessage, ControllerMessage, Frame, Positions,
};
use forja_protocol::gcode::{Decimal, Line, Recovery};

use super::peripherals::Peripherals;
use super::settings::{Key, SettingError};
use super::store::{RESUME_RECORD, ResumeRecord};
use super::text::{self, Refusal, Text};
use super::{ControllerError, Core, JobState, wire};
use crate::error::{JobError, StoreRefusal};
use crate::job::Checkpoint;
use forja_hal_abstraction::program::StoreError;
use forja_hal_abstraction::program::{MAX_LINE_LEN, ProgramStore};
use forja_motion::config::AxisKind;
use forja_motion::error::CommandError;
use forja_motion::{MachineState, Replay, Reply as KernelReply};
use forja_protocol::reply::Reply;

impl<const N: usize, const B: usize, const Q: usize, P, X, S> Core<'_, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// A run of garbage, `text` when printable bytes were among it. Each side is answered in
    /// its own protocol (both when the link has shown neither yet):
    ///
    /// - a frame client (frames seen, or a link with sessions) gets one 56 per run;
    /// - a G-code host that numbers its lines is asked to resend the expected line, which the
    ///   garbage may have held;
    /// - a G-code host that does not number its lines gets, when text was lost (its line was
    ///   dropped, not run), `echo:E8 bad-character` then `ok`, so that it is not left waiting;
    ///   control bytes alone between its lines cost no line and get no reply (an `ok` it did
    ///   not ask for would be taken for the answer to its next line).
    pub(super) fn on_garbage_run<W: Write>(&mut self, text: bool, out: &mut W) {
        self.stats.garbage_runs = self.stats.garbage_runs.wrapping_add(1);
        let frames = self.link.frames_seen || self.link.session;
        let unknown = !frames && !self.link.gcode_seen;
        if frames || unknown {
            self.error_frame(&Refusal::new(&FrameError::Structure), out);
        }
        match self.link.numbering.recover_garbage() {
            Recovery::Resend(n) => {
                self.stats.resends = self.stats.resends.wrapping_add(1);
                wire::resend(out, n);
            }
            _ if text && (self.link.gcode_seen || unknown) => {
                let lost = forja_protocol::gcode::LineError::UnexpectedCharacter { line: None };
                self.refuse(&Refusal::new(&lost), out);
            }
            _ => {}
        }
    }

    pub(super) fn on_frame<W: Write>(&mut self, frame: &Frame<'_>, out: &mut W) {
        self.link.frames_seen = true;
        self.stats.frames = self.stats.frames.wrapping_add(1);
        let msg = match ClientMessage::parse(frame) {
            Ok(msg) => msg,
            Err(e) => return self.error_frame(&Refusal::new(&e), out),
        };
        match msg {
            ClientMessage::SetSetting { key, value } => self.set_setting(key, value, out),
            ClientMessage::ReadSetting { key } => match Key::parse(key, self.settings.machine()) {
                Some(k) => self.send_setting(k, out),
                None => self.error_frame(&Refusal::with(&SettingError::UnknownKey, key), out),
            },
            ClientMessage::Jog { step, axis, count } => self.jog(step, axis, count, out),
            ClientMessage::Action(action) => self.action(action, out),
            ClientMessage::LoadLine { index, text, total } => {
                self.load_line(index, text, total, out)
            }
            ClientMessage::Request { message_type } => self.request(message_type, out),
            _ => self.error_frame(
                &Refusal::new(&FrameError::UnknownType {
                    message_type: frame.message_type(),
                }),
                out,
            ),
        }
    }

    fn set_setting<W: Write>(&mut self, key: &str, value: &str, out: &mut W) {
        if !self.kernel.is_idle() {
            return self.error_frame(&Refusal::with(&CommandError::NotIdle, key), out);
        }
        match self.store_setting(key, value) {
            Ok(k) => self.send_setting(k, out),
            Err(e) => self.error_frame(&Refusal::with(&e, key), out),
        }
    }

    /// Set and store the setting `key` (frame 00, `M413`), refused when the configuration it
    /// makes is invalid or needs faster steps than the drivers allow.
    pub(super) fn store_setting(&mut self, key: &str, value: &str) -> Result<Key, SettingError> {
        let tick_hz = self.kernel.tick_hz();
        let timing = self.config.timing;
        self.settings.set(key, value, &mut self.storage, &|m| {
            m.validate()?;
            m.validate_timing(tick_hz, timing)
        })
    }

    fn send_setting<W: Write>(&mut self, key: Key, out: &mut W) {
        let mut name = Text::<24>::new();
        let mut value = Text::<48>::new();
        let _ = key.write_name(self.settings.machine(), &mut name);
        let _ = self.settings.write_value(key, &mut value);
        wire::frame(
            out,
            &ControllerMessage::Setting {
                key: name.as_str(),
                value: value.as_str(),
            },
        );
    }

    fn jog<W: Write>(&mut self, step: Decimal, axis: u8, count: i32, out: &mut W) {
        if self.job_active() {
            return self.error_frame(&Refusal::new(&JobError::Busy), out);
        }
        match self.kernel.jog(axis, step, count) {
            Ok(KernelReply::Busy) => {
                self.error_frame(&Refusal::with(&CommandError::NotIdle, "queue-full"), out)
            }
            Ok(_) => self.taken = true,
            Err(e) => {
                let r = text::command_refusal(&e, &self.letters());
                self.error_frame(&r, out);
            }
        }
    }

    fn action<W: Write>(&mut self, action: Action, out: &mut W) {
        let result: Result<(), Refusal> = match action {
            Action::HomeAll | Action::Home(_) => self.home(action),
            // The lines received before the frame and not yet answered are answered without
            // running: nothing sent before a stop moves the machine after it.
            Action::Reset => {
                self.reset(out);
                self.drop_waiting(&Refusal::new(&ControllerError::Stopped), out);
                Ok(())
            }
            Action::Stop => {
                self.quick_stop(out);
                Ok(())
            }
            Action::Rewind => self.job.rewind().map_err(|e| Refusal::new(&e)),
            Action::Start => self.start(),
            Action::Pause => {
                if self.job.state() == JobState::Running {
                    self.job
                        .pause(&mut self.kernel)
                        .map_err(|e| Refusal::new(&e))
                } else if self.kernel.state() == MachineState::Running {
                    self.kernel.hold();
                    Ok(())
                } else {
                    Err(Refusal::new(&JobError::NotRunning))
                }
            }
        };
        if let Err(r) = result {
            self.error_frame(&r, out);
        }
    }

    fn home(&mut self, action: Action) -> Result<(), Refusal> {
        if self.job_active() {
            return Err(Refusal::new(&JobError::Busy));
        }
        let config = self.kernel.config();
        let mask = match action {
            Action::Home(letter) => {
                let axis = config.axis_index(letter).ok_or_else(|| {
                    text::command_refusal(&CommandError::UnknownAxis { letter }, &[])
                })?;
                1u8 << axis
            }
            _ => config
                .axes
                .iter()
                .enumerate()
                .filter(|(_, a)| a.homing.is_some())
                .fold(0u8, |m, (i, _)| m | (1 << i)),
        };
        self.kernel
            .home(mask)
            .map_err(|e| text::command_refusal(&e, &self.letters()))?;
        self.taken = true;
        Ok(())
    }

    fn start(&mut self) -> Result<(), Refusal> {
        match self.kernel.state() {
            MachineState::Alarm(_) => return Err(Refusal::new(&CommandError::Locked)),
            MachineState::Halted => return Err(Refusal::new(&CommandError::Halted)),
            MachineState::Hold { .. } | MachineState::Paused if !self.job_active() => {
                self.kernel.resume();
                return Ok(());
            }
            _ => {}
        }
        self.job
            .start(&mut self.kernel, &mut self.program, self.now)
            .map_err(|e| text::job_refusal(&e))?;
        self.taken = true;
        Ok(())
    }

    fn load_line<W: Write>(&mut self, index: u16, line: &str, total: u16, out: &mut W) {
        if let Err(r) = self.try_load(index, line, total) {
            return self.error_frame(&r, out);
        }
        if index == total {
            wire::frame(
                out,
                &ControllerMessage::Confirm {
                    what: CONFIRM_GCODE_LOAD,
                },
            );
        }
    }

    /// Store one line of an upload. An upload is open from its line 1 until its last line is
    /// stored, on the link that sent line 1 and while the controller runs: a restart or a new
    /// host on the link (`reset_link`) closes it, and only a line 1 opens one. So a line of
    /// another upload — another host's, or one sent before a restart — is refused
    /// (`load-total` when its total differs, `line-order` when it is not the next line,
    /// `no-upload` when it is), never spliced in; and a program
    /// whose upload was interrupted stays incomplete, and never runs, until it is uploaded
    /// again from line 1.
    fn try_load(&mut self, index: u16, line: &str, total: u16) -> Result<(), Refusal> {
        if self.job_active() {
            return Err(Refusal::new(&JobError::Busy));
        }
        if !self.kernel.is_idle() {
            return Err(Refusal::new(&CommandError::NotIdle));
        }
        if index != 1 {
            // Another program's total, then the order, then whether an upload is open.
            let current = self.load_total.unwrap_or(self.program.total());
            if current != 0 && total != current {
                return Err(Refusal::numbered(&ControllerError::LoadTotal, index, 4));
            }
            let expected = self.program.len().saturating_add(1);
            if index != expected {
                return Err(text::store_refusal(&StoreError::OutOfOrder {
                    expected,
                    got: index,
                }));
            }
            if self.load_total.is_none() {
                return Err(Refusal::numbered(
                    &StoreRefusal(StoreError::NoUpload),
                    index,
                    4,
                ));
            }
        }
        if let Err(e) = Line::parse(line.as_bytes()) {
            return Err(Refusal::numbered(&e, index, 4));
        }
        if index == 1 {
            // A refused line 1 (a total the store has no room for) keeps the old program.
            self.program
                .begin(total)
                .map_err(|e| Refusal::numbered(&StoreRefusal(e), total, 4))?;
            self.load_total = Some(total);
            // What is uploaded now is what `Start` runs, rather than a selected file.
            let _ = self.job.select_program();
            let _ = self.job.rewind();
        }
        self.program
            .store(index, line.as_bytes())
            .map_err(|e| text::store_refusal(&e))?;
        if self.program.is_complete() {
            self.load_total = None;
        }
        Ok(())
    }

    fn request<W: Write>(&mut self, message_type: u8, out: &mut W) {
        match message_type {
            51 => {
                let p = self.kernel.position();
                let mut positions = Positions::new();
                for (letter, mm) in p.letters.iter().zip(p.machine_mm.iter()) {
                    let value = Decimal::new(libm::round(mm * 10_000.0) as i64, 4);
                    if let Some(a) = AxisPosition::from_mm(*letter, value) {
                        let _ = positions.push(a);
                    }
                }
                wire::frame(out, &ControllerMessage::Positions(positions));
            }
            52 => {
                let progress = self.job.progress(&self.kernel, &self.program);
                wire::frame(out, &ControllerMessage::Progress(progress.into()));
            }
            t => self.error_frame(
                &Refusal::numbered(&ControllerError::BadRequest, t.into(), 2),
                out,
            ),
        }
    }
}

/// At most one resume record is written per this many ms while a job runs (flash wear); a
/// pause, a stop and the end of the program are recorded at once.
pub const CHECKPOINT_PERIOD_MS: u32 = 10_000;

// Program commands of G-code hosts (`M20`, `M413`, `M1000`) and the resume record.
impl<const N: usize, const B: usize, const Q: usize, P, X, S> Core<'_, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// A line of an upload in progress (`M28` to `M29`, `files.rs`), `M20` (list the stored
    /// program and the files), `M413` (power-loss recovery), `M1000` (resume the interrupted
    /// job, `M1000 C` forget it): answered here, `true`; any other line, `false`.
    pub(super) fn program_command<W: Write>(&mut self, line: &Line<'_>, out: &mut W) -> bool {
        if self.upload_line(line, out) {
            return true;
        }
        let Some(w) = line.command() else {
            return false;
        };
        if w.letter != b'M' {
            return false;
        }
        let number = w.value.as_integer();
        if !matches!(number, Some(20 | 413 | 1000)) {
            return false;
        }
        // A letter alone is a flag only to `M1000 C` (Marlin's cancel).
        if let Some(letter) = line.bare_letter()
            && !(number == Some(1000) && letter == b'C')
        {
            let r = text::command_refusal(&CommandError::MissingValue { letter }, &[]);
            self.refuse(&r, out);
            return true;
        }
        let result = match number {
            Some(20) => {
                self.list_files(out);
                Ok(())
            }
            Some(413) => self.recovery_command(line, out),
            Some(1000) if line.mentions(b'C') => self.forget_resume(),
            Some(1000) => self.resume(),
            _ => return false,
        };
        match result {
            Ok(()) => {
                self.stats.executed = self.stats.executed.wrapping_add(1);
                self.ok(out);
            }
            Err(r) => self.refuse(&r, out),
        }
        true
    }

    /// `M413`: report; `M413 S0|S1`: switch power-loss recovery off (forgetting the record)
    /// or on: the setting `power_loss_recovery`, stored as frame 00 stores it.
    fn recovery_command<W: Write>(&mut self, line: &Line<'_>, out: &mut W) -> Result<(), Refusal> {
        let Some(s) = line.get(b'S') else {
            let _ = wire::reply(
                out,
                &Reply::Debug(if self.settings.power_loss_recovery() {
                    "power-loss recovery on"
                } else {
                    "power-loss recovery off"
                }),
            );
            return Ok(());
        };
        let value = match s.as_integer() {
            Some(0) => "0",
            Some(1) => "1",
            _ => {
                return Err(Refusal::with(&CommandError::BadValue { letter: b'S' }, "S"));
            }
        };
        self.store_setting("power_loss_recovery", value)
            .map_err(|e| Refusal::new(&e))?;
        if !self.settings.power_loss_recovery() {
            self.storage
                .remove(RESUME_RECORD)
                .map_err(|_| text::store_refusal(&StoreError::Device))?;
        }
        Ok(())
    }

    /// `M1000 C`: forget the interrupted job.
    fn forget_resume(&mut self) -> Result<(), Refusal> {
        if self.job_active() {
            return Err(Refusal::new(&JobError::Busy));
        }
        self.storage
            .remove(RESUME_RECORD)
            .map_err(|_| text::store_refusal(&StoreError::Device))
    }

    /// The resume record, if one is kept.
    fn resume_record(&mut self) -> Result<Option<ResumeRecord>, Refusal> {
        let mut buf = [0u8; 16];
        match self.storage.read(RESUME_RECORD, &mut buf) {
            Ok(Some(n)) => Ok(buf.get(..n).and_then(ResumeRecord::decode)),
            Ok(None) => Ok(None),
            Err(_) => Err(text::store_refusal(&StoreError::Device)),
        }
    }

    /// `M1000`: resume the recorded job after its last finished line. The machine must be at
    /// rest and homed, and the stored program the one that ran. The program's modal state
    /// (units, distance modes, feed, offsets, plane, motion mode) and the position where the
    /// next line starts are replayed from line 1 through the last finished line without
    /// moving; the machine then goes there at rapid — Z first up to the higher of where it is
    /// and where it goes, then the other axes, then Z down — extruder axes not moved but
    /// taken as being where the program left them (as `G92` would); and the job runs from the
    /// next line.
    fn resume(&mut self) -> Result<(), Refusal> {
        if self.job_active() {
            return Err(Refusal::new(&JobError::Busy));
        }
        match self.kernel.state() {
            MachineState::Alarm(_) => return Err(Refusal::new(&CommandError::Locked)),
            MachineState::Halted => return Err(Refusal::new(&CommandError::Halted)),
            _ if !self.kernel.is_idle() => return Err(Refusal::new(&CommandError::NotIdle)),
            _ => {}
        }
        let record = self
            .resume_record()?
            .ok_or_else(|| Refusal::new(&JobError::NothingToResume))?;
        if !self.program.is_complete()
            || self.program.digest() != record.digest
            || self.program.total() != record.total
        {
            return Err(Refusal::new(&JobError::ProgramChanged));
        }
        if record.done >= record.total {
            return Err(Refusal::new(&JobError::NothingToResume));
        }
        let config = self.kernel.config();
        let homing = config
            .axes
            .iter()
            .enumerate()
            .filter(|(_, a)| a.homing.is_some())
            .fold(0u8, |m, (i, _)| m | (1 << i));
        if self.kernel.homed_axes() & homing != homing {
            return Err(Refusal::new(&JobError::NotHomed));
        }
        let here = self.kernel.commanded_position_nm();
        let replayed = self.replay(record.done)?;
        let resumed_at = replayed.position();

        // Go to the resumed line's start in machine coordinates (a fresh modal state: mm,
        // absolute, no offsets), then take the program's modal state.
        let config = *self.kernel.config();
        self.kernel.reset_modal_state();
        self.kernel.set_line_tag(u32::from(record.done + 1));
        let z = config.axis_index(b'Z');
        let moves = |i: usize| {
            config
                .axes
                .get(i)
                .is_some_and(|a| a.kind != AxisKind::Extruder)
                && resumed_at[i] != here[i]
        };
        let mut target = here;
        if let Some(z) = z.filter(|&z| moves(z)) {
            target[z] = here[z].max(resumed_at[z]);
            self.rapid_to(&target, &here)?;
        }
        let before = target;
        for (i, t) in target.iter_mut().enumerate() {
            if Some(i) != z && moves(i) {
                *t = resumed_at[i];
            }
        }
        self.rapid_to(&target, &before)?;
        let before = target;
        if let Some(z) = z.filter(|&z| moves(z)) {
            target[z] = resumed_at[z];
        }
        self.rapid_to(&target, &before)?;
        self.kernel.take_modal_state(&replayed, target);
        self.job
            .start_resumed(
                &mut self.kernel,
                &mut self.program,
                record.done + 1,
                self.now,
            )
            .map_err(|e| text::job_refusal(&e))?;
        self.taken = true;
        Ok(())
    }

    /// The program's modal state after lines `1..=done`, from the power-on state at the
    /// position the machine has now ([`Replay`]), without moving.
    fn replay(&mut self, done: u16) -> Result<Replay<N>, Refusal> {
        let config = *self.kernel.config();
        let mut replay = Replay::new(&self.kernel);
        let mut buf = [0u8; MAX_LINE_LEN];
        for index in 1..=done {
            let len = self
                .program
                .read(index, &mut buf)
                .map_err(|e| text::store_refusal(&e))?;
            if let Ok(line) = Line::parse(buf.get(..len).unwrap_or(&[])) {
                replay.line(&line, &config);
            }
        }
        Ok(replay)
    }

    /// Queue a rapid move from `from` to `target` (machine nm), when they differ.
    fn rapid_to(&mut self, target: &[i64; N], from: &[i64; N]) -> Result<(), Refusal> {
        if target == from {
            return Ok(());
        }
        match self.kernel.rapid_to(*target) {
            Ok(KernelReply::Ok) => Ok(()),
            Ok(_) => Err(Refusal::new(&CommandError::NotIdle)),
            Err(e) => Err(text::command_refusal(&e, &self.letters())),
        }
    }

    /// Write the job's progress to the resume record as [`crate::job::Job::checkpoint`]
    /// decides (while power-loss recovery is on); remove the record when the program has
    /// finished. A write that fails is reported (`// E174 store-device resume`), the job goes
    /// on.
    pub(super) fn record_checkpoint<W: Write>(&mut self, out: &mut W) {
        if !self.settings.power_loss_recovery() {
            return;
        }
        let settle_ms = 2 * u32::from(self.kernel.config().queue_lead_ms) + 50;
        let Some(c) =
            self.job
                .checkpoint(&self.kernel, self.clock.ms, settle_ms, CHECKPOINT_PERIOD_MS)
        else {
            return;
        };
        let result = match c {
            Checkpoint::Done(done) => {
                let record = ResumeRecord {
                    digest: self.program.digest(),
                    total: self.program.total(),
                    done,
                };
                self.storage.write(RESUME_RECORD, &record.encode())
            }
            Checkpoint::Finished => self.storage.remove(RESUME_RECORD),
        };
        if result.is_err() {
            let _ = wire::reply(
                out,
                &Reply::Notice {
                    code: StoreRefusal(StoreError::Device).code(),
                    text: "store-device resume",
                },
            );
        }
    }
}
