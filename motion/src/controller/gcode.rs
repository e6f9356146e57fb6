//! G-code lines of the link, and the effects of lines (from the link or the stored program).

use core::fmt::Write as _;

use embedded_io::Write;
use forja_hal_abstraction::storage::RecordStorage;
use forja_protocol::gcode::{Decimal, Line, LineError, Recovery};
use forja_protocol::reply::{Axes, FORJA_CAPABILITIES, KeyValues, Reply, Word};

use super::peripherals::{Peripherals, Reading};
use super::text::{self, Refusal, Text};
use super::{Core, Held, JobState, LineBuf, wire};
use crate::config::HomeDirection;
use crate::effect::{Effect, Heater, Spindle, StopKind, Storage};
use crate::error::{Alarm, CommandError, JobError};
use crate::job::ProgramStore;
use crate::kernel::{MachineState, PositionReport, Reply as KernelReply};

/// An effect, owned (the stored program's effects borrow the job's line buffer).
#[derive(Debug, Clone, Copy)]
enum Cmd {
    Temperature { heater: Heater, mc: i32, wait: bool },
    BadTemperature,
    WaitHeaters,
    ReportTemperatures,
    Fan { index: u8, duty: u8 },
    Spindle(Spindle),
    Nothing,
    Firmware,
    Endstops,
    Unsupported(u32),
    Tool(u8),
    Motors(bool),
    Stop(StopKind),
    Paused,
    ProgramEnd,
}

impl Cmd {
    fn of(e: &Effect<'_>) -> Cmd {
        match *e {
            Effect::SetTemperature {
                heater,
                celsius,
                wait,
            } => match celsius
                .round_to_scale(3)
                .and_then(|v| i32::try_from(v).ok())
                .filter(|v| *v >= 0)
            {
                Some(mc) => Cmd::Temperature { heater, mc, wait },
                None => Cmd::BadTemperature,
            },
            Effect::WaitForTemperatures => Cmd::WaitHeaters,
            Effect::ReportTemperatures => Cmd::ReportTemperatures,
            Effect::Fan { index, duty } => Cmd::Fan { index, duty },
            Effect::Spindle(s) => Cmd::Spindle(s),
            Effect::SetLineNumber(_) => Cmd::Nothing,
            Effect::ReportFirmware => Cmd::Firmware,
            Effect::ReportEndstops => Cmd::Endstops,
            Effect::Storage(s) => Cmd::Unsupported(match s {
                Storage::List => 20,
                Storage::Init => 21,
                Storage::Release => 22,
                Storage::Select(_) => 23,
                Storage::Start => 24,
                Storage::Pause => 25,
                Storage::SetPosition(_) => 26,
                Storage::Report => 27,
                Storage::BeginWrite(_) => 28,
                Storage::EndWrite(_) => 29,
            }),
            Effect::SelectTool(t) => Cmd::Tool(t),
            Effect::Motors { enabled } => Cmd::Motors(enabled),
            Effect::Stopped(kind) => Cmd::Stop(kind),
            Effect::Paused => Cmd::Paused,
            Effect::ProgramEnd => Cmd::ProgramEnd,
        }
    }
}

/// What carrying out a [`Cmd`] came to.
enum Done {
    Ok,
    Refused(Refusal),
    Temperatures,
    Firmware,
    Endstops,
    Wait,
    Fault(Refusal),
}

/// What a link line may be while a stored program runs: nothing that moves or changes the
/// program's modal state; reports, temperature targets, line numbering and `M112`.
fn allowed_during_job(line: &Line<'_>) -> bool {
    if line.is_empty() {
        return true;
    }
    match line.command() {
        Some(w) if w.letter == b'M' => matches!(
            w.value.as_integer(),
            Some(104 | 105 | 110 | 112 | 114 | 115 | 119 | 140)
        ),
        _ => false,
    }
}

/// A temperature in tenths of a degree, for replies.
fn celsius(mc: i32) -> Decimal {
    let mc = i64::from(mc);
    Decimal::new((mc + 50 * mc.signum()) / 100, 1)
}

/// What `M105` says of a heater the board does not have: below absolute zero (the seed).
const ABSENT_C: Decimal = Decimal::from_integer(-300);

/// A position in mm with three decimals.
fn millimetres(v: f64) -> Decimal {
    Decimal::new(libm::round(v * 1000.0) as i64, 3)
}

impl<const N: usize, const B: usize, const Q: usize, P, X, S> Core<'_, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    pub(super) fn ok<W: Write>(&mut self, out: &mut W) {
        self.stats.oks = self.stats.oks.wrapping_add(1);
        wire::ok(out);
    }

    /// `!! E<code> <text>` then `ok`: the line had no effect, the host goes on.
    pub(super) fn refuse<W: Write>(&mut self, r: &Refusal, out: &mut W) {
        self.stats.refused = self.stats.refused.wrapping_add(1);
        wire::fault(out, r);
        self.ok(out);
    }

    pub(super) fn on_line<W: Write>(&mut self, bytes: &[u8], out: &mut W) {
        self.link.gcode_seen = true;
        if self.link.lines_held() {
            if !self.emergency(bytes, out) {
                self.link.queued = Some(LineBuf::new(bytes));
            }
            return;
        }
        self.process_line(bytes, out);
    }

    /// `M112` is carried out as soon as it is read, even while lines are held.
    fn emergency<W: Write>(&mut self, bytes: &[u8], out: &mut W) -> bool {
        let Ok(line) = Line::parse(bytes) else {
            return false;
        };
        if !line.is_command(b'M', 112) || self.link.numbering.accept(&line).is_err() {
            return false;
        }
        self.execute_line(&line, bytes, out);
        true
    }

    fn process_line<W: Write>(&mut self, bytes: &[u8], out: &mut W) {
        let line = match Line::parse(bytes) {
            Ok(line) => line,
            Err(e) => return self.on_line_error(&e, out),
        };
        if let Err(e) = self.link.numbering.accept(&line) {
            return self.on_line_error(&e, out);
        }
        self.execute_line(&line, bytes, out);
    }

    /// A line that failed its transport checks (`rs <expected>` alone) or that cannot be run
    /// (`!!` then `ok`), as [`forja_protocol::gcode::LineNumbering::recover`] decides — except
    /// that a numbered line that passed its checksum but is not G-code is asked for once more
    /// first: the XOR checksum misses some double faults (two equal bytes dropped), which a
    /// resend repairs; a line that comes back the same is refused and its number used up.
    pub(super) fn on_line_error<W: Write>(&mut self, e: &LineError, out: &mut W) {
        let expected = self.link.numbering.expected();
        if e.line() == Some(expected) && self.link.asked_again != Some(expected) {
            self.link.asked_again = Some(expected);
            self.stats.resends = self.stats.resends.wrapping_add(1);
            return wire::resend(out, expected);
        }
        match self.link.numbering.recover(e) {
            Recovery::Resend(n) => {
                self.stats.resends = self.stats.resends.wrapping_add(1);
                wire::resend(out, n);
            }
            _ => self.refuse(&Refusal::new(e), out),
        }
    }

    fn executed(&mut self) {
        self.stats.executed = self.stats.executed.wrapping_add(1);
        self.taken = true;
    }

    /// Run a line that passed its checks; `bytes` is kept aside if the kernel is busy.
    fn execute_line<W: Write>(&mut self, line: &Line<'_>, bytes: &[u8], out: &mut W) {
        if line.is_command(b'M', 999) {
            self.reset(out);
            self.executed();
            return self.ok(out);
        }
        if line.is_command(b'M', 110) {
            // The numbering took it already (`N-1 M110 N-1` included).
            self.executed();
            return self.ok(out);
        }
        if self.job_active() && !allowed_during_job(line) {
            return self.refuse(&Refusal::new(&JobError::Busy), out);
        }
        match self.kernel.execute(line) {
            Ok(KernelReply::Ok) => {
                self.executed();
                if self.kernel.state() == MachineState::Homing {
                    self.link.held = Some(Held::Homing);
                } else {
                    self.ok(out);
                }
            }
            Ok(KernelReply::Busy) => {
                self.link.held_line = LineBuf::new(bytes);
                self.link.held = Some(Held::Line);
            }
            Ok(KernelReply::Position(p)) => {
                self.executed();
                self.position_reply(&p, out);
            }
            Ok(KernelReply::Effect(e)) => {
                self.executed();
                let done = self.apply(Cmd::of(&e));
                self.answer(done, out);
            }
            Err(e) => {
                let r = text::command_refusal(&e, &self.letters());
                self.refuse(&r, out);
            }
        }
    }

    /// Offer the held line again, then the line kept behind it, as long as they are taken.
    pub(super) fn release_held<W: Write>(&mut self, out: &mut W) {
        loop {
            match self.link.held {
                Some(Held::Line) => {
                    let lb = self.link.held_line;
                    self.link.held = None;
                    match Line::parse(lb.bytes()) {
                        Ok(line) => self.execute_line(&line, lb.bytes(), out),
                        Err(e) => self.refuse(&Refusal::new(&e), out),
                    }
                    if self.link.held.is_some() {
                        return;
                    }
                }
                Some(Held::Heat { .. } | Held::Homing) => return,
                None => {}
            }
            let Some(queued) = self.link.queued.take() else {
                return;
            };
            self.process_line(queued.bytes(), out);
        }
    }

    /// Carry out an effect, from the link or the stored program.
    fn apply(&mut self, cmd: Cmd) -> Done {
        let peripheral = |e: super::PeripheralError| Done::Refused(Refusal::new(&e));
        match cmd {
            Cmd::Temperature { heater, mc, wait } => {
                if mc > 0 && self.kernel.state() == MachineState::Alarm(Alarm::EmergencyStop) {
                    return Done::Refused(Refusal::new(&CommandError::Locked));
                }
                match self.peripherals.set_temperature(heater, mc) {
                    Ok(()) if wait => Done::Wait,
                    Ok(()) => Done::Ok,
                    Err(e) => peripheral(e),
                }
            }
            Cmd::BadTemperature => Done::Refused(Refusal::with(
                &CommandError::BadValue { letter: b'S' },
                format_args!("S"),
            )),
            Cmd::WaitHeaters => Done::Wait,
            Cmd::ReportTemperatures => Done::Temperatures,
            Cmd::Fan { index, duty } => match self.peripherals.set_fan(index, duty) {
                Ok(()) => Done::Ok,
                Err(e) => Done::Refused(Refusal::with(&e, format_args!("fan {index}"))),
            },
            Cmd::Spindle(s) => match self.peripherals.set_spindle(s) {
                Ok(()) => Done::Ok,
                Err(e) => Done::Refused(Refusal::with(&e, format_args!("spindle"))),
            },
            Cmd::Nothing | Cmd::Paused => Done::Ok,
            // A board without a spindle has none to stop.
            Cmd::ProgramEnd => match self.peripherals.set_spindle(Spindle::Off) {
                Ok(()) | Err(super::PeripheralError::NoDevice) => Done::Ok,
                Err(e) => Done::Refused(Refusal::with(&e, format_args!("spindle"))),
            },
            Cmd::Firmware => Done::Firmware,
            Cmd::Endstops => Done::Endstops,
            Cmd::Unsupported(n) => Done::Refused(text::command_refusal(
                &CommandError::Unsupported {
                    letter: b'M',
                    number: Some(n),
                },
                &[],
            )),
            Cmd::Tool(t) if t < self.config.extruders.max(1) => Done::Ok,
            Cmd::Tool(t) => Done::Refused(Refusal::with(
                &CommandError::BadValue { letter: b'T' },
                format_args!("T{t}"),
            )),
            Cmd::Motors(enabled) => match self.peripherals.set_motors(enabled) {
                Ok(()) => {
                    self.motors_on = enabled;
                    Done::Ok
                }
                Err(e) => peripheral(e),
            },
            Cmd::Stop(kind) => {
                if kind == StopKind::Emergency {
                    self.job.stop(&mut self.kernel);
                    self.reported_alarm = Some(Alarm::EmergencyStop);
                    self.job_heat = false;
                }
                self.peripherals.shutdown();
                if self.peripherals.set_motors(false).is_ok() {
                    self.motors_on = false;
                }
                match kind {
                    StopKind::Emergency => Done::Fault(Refusal::new(&Alarm::EmergencyStop)),
                    StopKind::Program => Done::Ok,
                }
            }
        }
    }

    /// The link's answer to an effect.
    fn answer<W: Write>(&mut self, done: Done, out: &mut W) {
        match done {
            Done::Ok => self.ok(out),
            Done::Refused(r) => self.refuse(&r, out),
            Done::Temperatures => {
                let t = self.peripherals.temperatures();
                let current = |r: Option<Reading>| r.map_or(ABSENT_C, |r| celsius(r.current_mc));
                self.stats.oks = self.stats.oks.wrapping_add(1);
                let _ = wire::reply(
                    out,
                    &Reply::Temperatures {
                        extruder: current(t.hot_end),
                        bed: current(t.bed),
                    },
                );
            }
            Done::Firmware => self.firmware_reply(out),
            Done::Endstops => self.endstops_reply(out),
            Done::Wait => {
                if self.peripherals.heaters_at_target() {
                    self.ok(out);
                } else {
                    self.link.held = Some(Held::Heat {
                        next_report_ms: self
                            .clock
                            .ms
                            .wrapping_add(self.config.report_period_ms.max(1)),
                    });
                }
            }
            Done::Fault(r) => {
                self.end_heat_wait(out);
                self.report_fault(&r, out);
                self.ok(out);
            }
        }
    }

    fn position_reply<W: Write>(&mut self, p: &PositionReport<N>, out: &mut W) {
        let mut axes = Axes::new();
        for (letter, mm) in p.letters.iter().zip(p.work_mm.iter()) {
            let _ = axes.push(Word::new(*letter, millimetres(*mm)));
        }
        self.stats.oks = self.stats.oks.wrapping_add(1);
        let _ = wire::reply(out, &Reply::Position(axes));
    }

    fn firmware_reply<W: Write>(&mut self, out: &mut W) {
        let mut count = Text::<4>::new();
        let _ = write!(count, "{}", self.config.extruders);
        let [a, b, c, d] = FORJA_CAPABILITIES;
        let full = [
            a,
            b,
            c,
            d,
            ("MACHINE_TYPE", self.config.machine_type),
            ("EXTRUDER_COUNT", count.as_str()),
        ];
        let base = [a, b, c, d, ("EXTRUDER_COUNT", count.as_str())];
        self.stats.oks = self.stats.oks.wrapping_add(1);
        if !wire::reply(out, &Reply::Capabilities(KeyValues::Pairs(&full))) {
            let _ = wire::reply(out, &Reply::Capabilities(KeyValues::Pairs(&base)));
        }
    }

    fn endstops_reply<W: Write>(&mut self, out: &mut W) {
        let states = self.peripherals.endstops();
        let mut t = Text::<120>::new();
        for (i, state) in states.iter().enumerate() {
            let Some(triggered) = state else { continue };
            let axis = &self.kernel.config().axes[i];
            let side = match axis.homing.map(|h| h.direction) {
                Some(HomeDirection::Max) => "max",
                _ => "min",
            };
            if !t.as_bytes().is_empty() {
                let _ = t.write_str(" ");
            }
            let _ = write!(
                t,
                "{}_{side}:{}",
                char::from(axis.letter.to_ascii_lowercase()),
                if *triggered { "TRIGGERED" } else { "open" }
            );
        }
        if t.as_bytes().is_empty() {
            return self.ok(out);
        }
        self.stats.oks = self.stats.oks.wrapping_add(1);
        if !wire::reply(out, &Reply::OkWith(t.as_str())) {
            wire::ok(out);
        }
    }

    /// `// T:<hot end> /<target> B:<bed> /<target>`, during a wait.
    pub(super) fn report_temperatures<W: Write>(&mut self, out: &mut W) {
        let t = self.peripherals.temperatures();
        let mut line = Text::<64>::new();
        for (name, r) in [("T", t.hot_end), ("B", t.bed)] {
            if let Some(r) = r {
                if !line.as_bytes().is_empty() {
                    let _ = line.write_str(" ");
                }
                let _ = write!(
                    line,
                    "{name}:{} /{}",
                    celsius(r.current_mc),
                    celsius(r.target_mc)
                );
            }
        }
        if !line.as_bytes().is_empty() {
            let _ = wire::reply(out, &Reply::Debug(line.as_str()));
        }
    }

    /// Soft reset (`M999`, frame `Reset`): the kernel's alarms and modal state, the job (its
    /// program and line kept), latched heater faults, waits.
    pub(super) fn reset<W: Write>(&mut self, out: &mut W) {
        self.job.reset(&mut self.kernel);
        self.peripherals.reset();
        self.thermal = None;
        self.reported_alarm = None;
        self.job_heat = false;
        self.end_heat_wait(out);
    }

    /// Feed the stored program to the kernel, carrying out its effects.
    pub(super) fn feed_job<W: Write>(&mut self, out: &mut W) {
        for _ in 0..64 {
            if !self.job_active() || self.job_heat {
                return;
            }
            let before = self.job.next_line();
            let cmd = match self.job.poll(&mut self.kernel, &mut self.program, self.now) {
                Ok(e) => e.as_ref().map(Cmd::of),
                Err(e) => {
                    let r = text::job_refusal(&e);
                    self.error_frame(&r, out);
                    return;
                }
            };
            let fed = self.job.next_line().wrapping_sub(before);
            if fed > 0 {
                self.stats.program_lines = self.stats.program_lines.wrapping_add(u32::from(fed));
                self.taken = true;
            }
            let Some(cmd) = cmd else { return };
            match self.apply(cmd) {
                Done::Refused(r) => {
                    self.job.stop(&mut self.kernel);
                    self.error_frame(&r, out);
                    return;
                }
                Done::Wait => self.job_heat = !self.peripherals.heaters_at_target(),
                Done::Fault(r) => {
                    self.end_heat_wait(out);
                    self.report_fault(&r, out);
                    return;
                }
                Done::Ok | Done::Temperatures | Done::Firmware | Done::Endstops => {}
            }
            if self.job.state() != JobState::Running {
                return;
            }
        }
    }
}
