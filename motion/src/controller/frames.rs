//! The 53-byte frames of the operator's client, and garbage on the link.

use embedded_io::Write;
use forja_hal_abstraction::storage::RecordStorage;
use forja_protocol::error::FrameError;
use forja_protocol::frame::{
    Action, AxisPosition, CONFIRM_GCODE_LOAD, ClientMessage, ControllerMessage, Frame, Positions,
};
use forja_protocol::gcode::{Decimal, Line, Recovery};

use super::peripherals::Peripherals;
use super::settings::Key;
use super::text::{self, Refusal, Text};
use super::{ControllerError, Core, JobState, wire};
use crate::error::{CommandError, JobError};
use crate::job::ProgramStore;
use crate::kernel::{MachineState, Reply as KernelReply};

impl<const N: usize, const B: usize, const Q: usize, P, X, S> Core<'_, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// Garbage: one 56 per run; a host that numbers its lines is also asked to resend the
    /// expected line, which the garbage may have held.
    pub(super) fn on_garbage<W: Write>(&mut self, out: &mut W) {
        self.stats.garbage_runs = self.stats.garbage_runs.wrapping_add(1);
        self.error_frame(&Refusal::new(&FrameError::Structure), out);
        if let Recovery::Resend(n) = self.link.numbering.recover_garbage() {
            self.stats.resends = self.stats.resends.wrapping_add(1);
            wire::resend(out, n);
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
                None => self.error_frame(
                    &Refusal::with(&super::SettingError::UnknownKey, format_args!("{key}")),
                    out,
                ),
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
            return self.error_frame(
                &Refusal::with(&CommandError::NotIdle, format_args!("{key}")),
                out,
            );
        }
        let tick_hz = self.kernel.tick_hz();
        let timing = self.config.timing;
        let result = self.settings.set(key, value, &mut self.storage, |m| {
            m.validate()?;
            m.validate_timing(tick_hz, timing)
        });
        match result {
            Ok(k) => self.send_setting(k, out),
            Err(e) => self.error_frame(&Refusal::with(&e, format_args!("{key}")), out),
        }
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
            Ok(KernelReply::Busy) => self.error_frame(
                &Refusal::with(&CommandError::NotIdle, format_args!("queue-full")),
                out,
            ),
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
            Action::Reset => {
                self.reset(out);
                Ok(())
            }
            Action::Stop => {
                if self.job_active() {
                    self.job.stop(&mut self.kernel);
                } else {
                    self.kernel.stop();
                }
                self.job_heat = false;
                self.end_heat_wait(out);
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

    fn try_load(&mut self, index: u16, line: &str, total: u16) -> Result<(), Refusal> {
        if self.job_active() {
            return Err(Refusal::new(&JobError::Busy));
        }
        if !self.kernel.is_idle() {
            return Err(Refusal::new(&CommandError::NotIdle));
        }
        if index != 1 && self.load_total != Some(total) {
            return Err(Refusal::with(
                &ControllerError::LoadTotal,
                format_args!("{index:04}"),
            ));
        }
        if let Err(e) = Line::parse(line.as_bytes()) {
            return Err(Refusal::with(&e, format_args!("{index:04}")));
        }
        if index == 1 {
            self.program.clear().map_err(|e| text::store_refusal(&e))?;
            self.load_total = Some(total);
            let _ = self.job.rewind();
        }
        self.program
            .store(index, line.as_bytes())
            .map_err(|e| text::store_refusal(&e))
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
                &Refusal::with(&ControllerError::BadRequest, format_args!("{t:02}")),
                out,
            ),
        }
    }
}
