//! G-code lines of the link, and the effects of lines (from the link or the stored program).

use core::fmt::Write as _;

use embedded_io::Write;
use forja_hal_abstraction::storage::RecordStorage;
use forja_protocol::gcode::{Decimal, Line, LineError, Recovery};
use forja_protocol::reply::{Axes, FORJA_CAPABILITIES, KeyValues, LINE_CHECK, Reply, Word};

use super::peripherals::{Devices, PeripheralError, Peripherals, Reading};
use super::text::{self, Refusal, Text};
use super::{
    ControllerConfig, ControllerError, Core, Dropped, Held, JobState, LineBuf, Queued, wire,
};
use crate::error::JobError;
use forja_hal_abstraction::program::ProgramStore;
use forja_motion::config::HomeDirection;
use forja_motion::effect::{Effect, StopKind, Storage};
use forja_motion::error::{Alarm, CommandError};
use forja_motion::{MachineState, PositionReport, Reply as KernelReply};

/// What carrying out an effect came to.
enum Done {
    Ok,
    Refused(Refusal),
    Temperatures,
    Firmware,
    Endstops,
    Wait,
    /// `M0`, `M112`: the controller stops ([`Core::stop`]) once the effect is done with.
    Stop(StopKind),
}

/// The `M` number of a storage command (`M20`–`M29`).
fn storage_number(s: &Storage<'_>) -> u32 {
    match s {
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
    }
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

/// A command that acts as soon as its line is read, even behind waiting lines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Realtime {
    /// `M112`.
    EmergencyStop,
    /// `M108`: end a heater wait.
    CancelWait,
}

/// The realtime command of a line (its bytes without the terminator), as Marlin's emergency
/// parser finds it: the first word after an optional `N` number, whatever follows it (a
/// damaged checksum included: a stop must not wait for a resend behind the queue), or the
/// command of a line that parses. The controller looks at every line of its link with it; a
/// board looks with it at the input it refuses from a host that is not in control (see
/// [`super::Controller::emergency_stop`]).
pub fn realtime(bytes: &[u8]) -> Option<Realtime> {
    let of = |n: i64| match n {
        112 => Some(Realtime::EmergencyStop),
        108 => Some(Realtime::CancelWait),
        _ => None,
    };
    if let Ok(line) = Line::parse(bytes)
        && let Some(w) = line.command()
        && w.letter == b'M'
    {
        return w.value.as_integer().and_then(of);
    }
    let blank = |b: &u8| matches!(b, b' ' | b'\t');
    let digit = |b: &u8| b.is_ascii_digit();
    let skip =
        |s: &[u8], f: &dyn Fn(&u8) -> bool| -> usize { s.iter().take_while(|b| f(b)).count() };
    let mut rest = bytes.get(skip(bytes, &blank)..)?;
    if let Some((b'N' | b'n', tail)) = rest.split_first() {
        let tail = tail.strip_prefix(b"-").unwrap_or(tail);
        let tail = tail.get(skip(tail, &digit)..)?;
        rest = tail.get(skip(tail, &blank)..)?;
    }
    let (b'M' | b'm', tail) = rest.split_first()? else {
        return None;
    };
    let len = skip(tail, &digit);
    if len == 0 || len > 6 || matches!(tail.get(len), Some(b) if *b == b'.' || digit(b)) {
        return None;
    }
    let n = tail
        .get(..len)?
        .iter()
        .fold(0i64, |n, d| n * 10 + i64::from(d - b'0'));
    of(n)
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

    /// A G-code line from the link: handled now, or, behind waiting lines, queued for its turn
    /// (`M112` and `M108` act first; see "Flow control" in the module documentation).
    pub(super) fn on_line<W: Write>(&mut self, bytes: &[u8], out: &mut W) {
        self.link.gcode_seen = true;
        if self.link.lines_held() {
            match realtime(bytes) {
                Some(Realtime::EmergencyStop) => return self.emergency(bytes, out),
                Some(Realtime::CancelWait) => self.cancel_waits(out),
                None => {}
            }
        }
        if !self.link.lines_held() {
            return self.process_line(bytes, out);
        }
        if !self.link.queue.push_line(bytes) {
            self.refuse(&Refusal::new(&ControllerError::QueueFull), out);
        }
    }

    /// A record the decoder dropped (an over-long line, a garbage run): answered now, or,
    /// behind waiting lines, queued for its turn, so that the resend it may ask for names the
    /// line expected then.
    pub(super) fn on_dropped<W: Write>(&mut self, dropped: Dropped, out: &mut W) {
        if !self.link.lines_held() {
            return self.answer_dropped(dropped, out);
        }
        if !self.link.queue.push_dropped(dropped) {
            self.refuse(&Refusal::new(&ControllerError::QueueFull), out);
        }
    }

    /// The answer to a dropped record, in its turn.
    fn answer_dropped<W: Write>(&mut self, dropped: Dropped, out: &mut W) {
        match dropped {
            Dropped::TooLong => self.on_line_error(&LineError::TooLong, out),
            Dropped::Garbage { text } => self.on_garbage_run(text, out),
        }
    }

    /// `M112` behind waiting lines: the machine stops now and the fault goes out; the lines
    /// received before it are answered in order without running; then the `M112` line's own
    /// answer, its number checked like any line's.
    fn emergency<W: Write>(&mut self, bytes: &[u8], out: &mut W) {
        self.emergency_stop(out);
        let line = match Line::parse(bytes) {
            Ok(line) => line,
            Err(e) => return self.on_line_error(&e, out),
        };
        if let Err(e) = self.accept_number(&line) {
            return self.on_line_error(&e, out);
        }
        self.executed();
        self.ok(out);
    }

    /// The emergency stop itself: the machine stops now and the fault goes out; the lines
    /// waiting are answered in order without running.
    pub(super) fn emergency_stop<W: Write>(&mut self, out: &mut W) {
        self.kernel.emergency_stop();
        if let Some(fault) = self.stop(StopKind::Emergency) {
            self.report_fault(&fault, out);
        }
        let locked = text::command_refusal(&CommandError::Locked, &self.letters());
        self.drop_waiting(&locked, out);
    }

    /// After an emergency stop (`M112`) or a stop or reset frame, answer every waiting line in
    /// order without running it: the held line is refused with `why` (the machine is locked,
    /// or stopped); a `G28`, `M109` or `M116` that was waiting ran, and gets its `ok`; queued
    /// lines are checked as when taken, then refused with `why`.
    pub(super) fn drop_waiting<W: Write>(&mut self, why: &Refusal, out: &mut W) {
        match self.link.held.take() {
            Some(Held::Line) => self.refuse(why, out),
            Some(Held::Homing | Held::Heat { .. }) => self.ok(out),
            None => {}
        }
        let mut lb = LineBuf::EMPTY;
        while let Some(entry) = self.link.queue.pop(&mut lb) {
            match entry {
                Queued::Line => self.drop_line(lb.bytes(), why, out),
                Queued::Dropped(dropped) => self.answer_dropped(dropped, out),
            }
        }
    }

    /// A queued line received before a stop: its transport checks as always, then `ok` if it
    /// does nothing to the machine (a comment, `M110`, an `M108` that acted when it arrived),
    /// else refused with `why`. A line that fails its transport checks is not asked again: its
    /// resend would run after the stop ([`Core::drop_damaged`]).
    fn drop_line<W: Write>(&mut self, bytes: &[u8], why: &Refusal, out: &mut W) {
        let line = match Line::parse(bytes) {
            Ok(line) => line,
            Err(e) => return self.drop_damaged(&e, why, out),
        };
        if let Err(e) = self.accept_number(&line) {
            return self.drop_damaged(&e, why, out);
        }
        if line.is_empty() || line.is_command(b'M', 110) || line.is_command(b'M', 108) {
            self.executed();
            return self.ok(out);
        }
        self.refuse(why, out);
    }

    /// A queued record received before a stop that failed its transport checks (damaged, or
    /// out of order after a lost line). Outside a stop it would be asked again (`rs`), but the
    /// host would then send again a line it sent before the stop, to run after it. So the line
    /// the host is at is refused with `why` and its number used up, as if it had arrived
    /// intact (for a line that arrived after lost ones, theirs too); the rest of a line answered
    /// already gets nothing, and a copy of a line taken before is asked as always.
    fn drop_damaged<W: Write>(&mut self, e: &LineError, why: &Refusal, out: &mut W) {
        let numbering = &mut self.link.numbering;
        if !numbering.is_numbered() {
            return self.on_line_error(e, out);
        }
        let expected = numbering.expected();
        match *e {
            LineError::Fragment => {}
            LineError::OutOfOrder { got, .. } if got.wrapping_sub(expected) < u32::MAX / 2 => {
                numbering.set_expected(got.wrapping_add(1));
                self.refuse(why, out);
            }
            LineError::OutOfOrder { .. } => self.on_line_error(e, out),
            _ => {
                numbering.set_expected(expected.wrapping_add(1));
                self.refuse(why, out);
            }
        }
    }

    /// Check a line's number and checksum against the link's numbering. An `M110` restarts the
    /// numbering, and with it the one resend each number is owed: a number asked again in the
    /// numbering before is owed it anew.
    fn accept_number(&mut self, line: &Line<'_>) -> Result<(), LineError> {
        self.link.numbering.accept(line)?;
        if line.is_command(b'M', 110) {
            self.link.asked_again = None;
        }
        Ok(())
    }

    /// `M108`: end the heater waits, of the link's `M109`/`M116` (its `ok` goes out) and of the
    /// stored program. The targets stay.
    fn cancel_waits<W: Write>(&mut self, out: &mut W) {
        self.job_heat = false;
        self.end_heat_wait(out);
    }

    fn process_line<W: Write>(&mut self, bytes: &[u8], out: &mut W) {
        let line = match Line::parse(bytes) {
            Ok(line) => line,
            Err(e) => return self.on_line_error(&e, out),
        };
        if let Err(e) = self.accept_number(&line) {
            return self.on_line_error(&e, out);
        }
        self.execute_line(&line, bytes, out);
    }

    /// A line that failed its transport checks (`rs <expected>` alone) or that cannot be run
    /// (`!!` then `ok`), as [`forja_protocol::gcode::LineNumbering::recover`] decides — except
    /// that a numbered line that passed its checksum but is not G-code is asked for once more
    /// first: the XOR checksum misses some double faults (two equal bytes dropped), which a
    /// resend repairs; a line that comes back the same is refused and its number used up. The
    /// rest of a line cut in two by a damaged `*` (a checksum alone) gets no reply: the first
    /// part was asked again already.
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
            Recovery::Drop => {}
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
        if line.is_command(b'M', 108) {
            self.cancel_waits(out);
            self.executed();
            return self.ok(out);
        }
        // `M20`, `M413`, `M1000`: the stored program and power-loss recovery (frames.rs).
        if self.program_command(line, out) {
            return;
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
                let state = self.kernel.state();
                let done = Self::apply(&mut self.devices, state, &self.config, &e);
                self.answer(done, out);
            }
            Err(e) => {
                // A refusal that damage on the link can cause (an unknown letter or command, a
                // malformed, repeated or out-of-range value), of the numbered line just
                // accepted: refusing changed nothing, so it is asked for once more before it
                // is refused; a line that comes back the same is refused and its number used
                // up. Refusals for the machine's state are not damage.
                let damage = !matches!(
                    e,
                    CommandError::Locked | CommandError::Halted | CommandError::NotIdle
                );
                if let Some(n) = line.number()
                    && damage
                    && self.link.asked_again != Some(n)
                    && self.link.numbering.give_back(n)
                {
                    self.link.asked_again = Some(n);
                    self.stats.resends = self.stats.resends.wrapping_add(1);
                    return wire::resend(out, n);
                }
                let r = text::command_refusal(&e, &self.letters());
                self.refuse(&r, out);
            }
        }
    }

    /// Offer the held line again, then the queued lines in order, as long as they are taken.
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
            let mut lb = LineBuf::EMPTY;
            let Some(entry) = self.link.queue.pop(&mut lb) else {
                return;
            };
            match entry {
                Queued::Line => self.process_line(lb.bytes(), out),
                Queued::Dropped(dropped) => self.answer_dropped(dropped, out),
            }
        }
    }

    /// Carry out an effect, from the link or the stored program, on the board's devices.
    ///
    /// An associated function over the devices alone, not a method: a stored program's effect
    /// borrows the job's line buffer, so it is carried out before the job is used again.
    fn apply(
        devices: &mut Devices<X, N>,
        state: MachineState,
        config: &ControllerConfig,
        effect: &Effect<'_>,
    ) -> Done {
        let device = |e: PeripheralError, what: core::fmt::Arguments<'_>| {
            Done::Refused(Refusal::with(&e, what))
        };
        match *effect {
            Effect::SetTemperature {
                heater,
                celsius,
                wait,
            } => {
                let Some(mc) = celsius
                    .round_to_scale(3)
                    .and_then(|v| i32::try_from(v).ok())
                    .filter(|v| *v >= 0)
                else {
                    return Done::Refused(Refusal::with(
                        &CommandError::BadValue { letter: b'S' },
                        format_args!("S"),
                    ));
                };
                if mc > 0 && state == MachineState::Alarm(Alarm::EmergencyStop) {
                    return Done::Refused(Refusal::new(&CommandError::Locked));
                }
                match devices.set_temperature(heater, mc) {
                    Ok(()) if wait => Done::Wait,
                    Ok(()) => Done::Ok,
                    Err(e) => Done::Refused(Refusal::new(&e)),
                }
            }
            Effect::WaitForTemperatures => Done::Wait,
            Effect::ReportTemperatures => Done::Temperatures,
            Effect::Fan { index, duty } => match devices.set_fan(index, duty) {
                Ok(()) => Done::Ok,
                Err(e) => device(e, format_args!("fan {index}")),
            },
            Effect::Spindle(s) => match devices.set_spindle(s) {
                Ok(()) => Done::Ok,
                Err(e) => device(e, format_args!("spindle")),
            },
            Effect::Coolant(c) => match devices.set_coolant(c) {
                Ok(()) => Done::Ok,
                Err(e) => device(e, format_args!("coolant")),
            },
            Effect::SetLineNumber(_) | Effect::Paused => Done::Ok,
            Effect::ProgramEnd => match devices.end_program() {
                Ok(()) => Done::Ok,
                Err((e, what)) => device(e, format_args!("{what}")),
            },
            Effect::ReportFirmware => Done::Firmware,
            Effect::ReportEndstops => Done::Endstops,
            Effect::Storage(s) => Done::Refused(text::command_refusal(
                &CommandError::Unsupported {
                    letter: b'M',
                    number: Some(storage_number(&s)),
                },
                &[],
            )),
            Effect::SelectTool(t) if t < config.extruders.max(1) => Done::Ok,
            Effect::SelectTool(t) => Done::Refused(Refusal::with(
                &CommandError::BadValue { letter: b'T' },
                format_args!("T{t}"),
            )),
            Effect::Motors { enabled } => match devices.set_motors(enabled) {
                Ok(()) => Done::Ok,
                Err(e) => Done::Refused(Refusal::new(&e)),
            },
            Effect::Stopped(kind) => Done::Stop(kind),
        }
    }

    /// Stop on `M0` (program stop) or `M112` (emergency): the devices shut down and the
    /// motors released; an emergency stop also ends the job and the heater waits, and is a
    /// fault to report (returned).
    fn stop(&mut self, kind: StopKind) -> Option<Refusal> {
        if kind == StopKind::Emergency {
            self.job.stop(&mut self.kernel);
            self.reported_alarm = Some(Alarm::EmergencyStop);
            self.job_heat = false;
        }
        self.devices.shutdown();
        let _ = self.devices.set_motors(false);
        (kind == StopKind::Emergency).then(|| Refusal::new(&Alarm::EmergencyStop))
    }

    /// The link's answer to an effect.
    fn answer<W: Write>(&mut self, done: Done, out: &mut W) {
        match done {
            Done::Ok => self.ok(out),
            Done::Refused(r) => self.refuse(&r, out),
            Done::Temperatures => {
                let t = self.devices.temperatures();
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
                if self.heaters_at_target() {
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
            Done::Stop(kind) => {
                if let Some(fault) = self.stop(kind) {
                    self.end_heat_wait(out);
                    self.report_fault(&fault, out);
                }
                self.ok(out);
            }
        }
    }

    /// Whether every heater with a target is within the tolerance of it.
    pub(super) fn heaters_at_target(&mut self) -> bool {
        self.devices
            .heaters_at_target(self.config.heater_tolerance_mc)
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
            LINE_CHECK,
        ];
        let base = [a, b, c, d, ("EXTRUDER_COUNT", count.as_str()), LINE_CHECK];
        self.stats.oks = self.stats.oks.wrapping_add(1);
        if !wire::reply(out, &Reply::Capabilities(KeyValues::Pairs(&full))) {
            let _ = wire::reply(out, &Reply::Capabilities(KeyValues::Pairs(&base)));
        }
    }

    fn endstops_reply<W: Write>(&mut self, out: &mut W) {
        let states = self.devices.endstops();
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
        let t = self.devices.temperatures();
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
        self.devices.reset();
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
            // The effect borrows the job's line buffer: it is carried out on the devices now,
            // and what it comes to settled once the job is free again.
            let done = match self.job.poll(&mut self.kernel, &mut self.program, self.now) {
                Ok(e) => {
                    e.map(|e| Self::apply(&mut self.devices, self.kernel.state(), &self.config, &e))
                }
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
            let Some(done) = done else { return };
            match done {
                Done::Refused(r) => {
                    self.job.stop(&mut self.kernel);
                    self.error_frame(&r, out);
                    return;
                }
                Done::Wait => self.job_heat = !self.heaters_at_target(),
                Done::Stop(kind) => {
                    if let Some(fault) = self.stop(kind) {
                        self.end_heat_wait(out);
                        self.report_fault(&fault, out);
                        return;
                    }
                }
                Done::Ok | Done::Temperatures | Done::Firmware | Done::Endstops => {}
            }
            if self.job.state() != JobState::Running {
                return;
            }
        }
    }
}
