//! G-code lines of the link, and the effects of lines (from the link or the stored program).

use embedded_io::Write;
use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::thermal::FULL_POWER;
use forja_protocol::gcode::{Decimal, Line, LineError, MAX_LINE_LEN, Recovery};
use forja_protocol::reply::{
    Axes, Counts, FORJA_CAPABILITIES, Heat, KeyValues, LINE_CHECK, Reply, Word,
};

use super::files::FileCommand;
use super::grbl;
use super::host::{HostProgress, MESSAGE_LEN};
use super::peripherals::{Devices, HeatWait, HeatZones, PeripheralError, Peripherals, Reading};
use super::text::{self, Refusal, Text};
use super::{
    ControllerConfig, ControllerError, Core, Dropped, Held, JobState, LineBuf, Queued, wire,
};
use crate::error::JobError;
use forja_hal_abstraction::program::ProgramStore;
use forja_motion::config::{AxisKind, HomeDirection};
use forja_motion::effect::{Coolant, Effect, Heater, StopKind, TemperatureWait};
use forja_motion::error::{Alarm, CommandError};
use forja_motion::{MachineState, PositionReport, Reply as KernelReply};

/// What carrying out an effect came to.
#[derive(Clone, Copy)]
enum Done {
    Ok,
    Refused(Refusal),
    Temperatures,
    Firmware,
    Endstops,
    /// `M109`, `M190`, `M116`: hold the lines until the heaters are there.
    Wait(HeatWait),
    /// `M0`, `M112`: the controller stops ([`Core::stop`]) once the effect is done with.
    Stop(StopKind),
    /// `M410`: motion stops, the waiting lines are answered without running.
    QuickStop,
    /// `M73`.
    Progress(HostProgress),
    /// `M117`: the message, as far as it is kept.
    Message(Text<MESSAGE_LEN>),
    /// `M118`: the text after the command.
    HostMessage(Text<MAX_LINE_LEN>),
    /// `M155`.
    AutoReport(u8),
    /// `M113`.
    BusyInterval(Option<u8>),
    /// `M20`–`M32`: the SD-card commands, served by the board's file store (`files.rs`).
    Files(FileCommand),
    /// `M6`: the machine waits for a manual tool change; the operator is told which tool.
    ToolChange(Option<u8>),
    /// `M2`, `M30`: the program ended (grbl says so, and its overrides go back to 100 %).
    ProgramEnd,
}

/// `bytes` as far as they fit `C` bytes of printable ASCII.
fn copied<const C: usize>(bytes: &[u8]) -> Text<C> {
    let mut t = Text::new();
    t.push(core::str::from_utf8(bytes).unwrap_or("?"));
    t
}

/// What a link line may be while a stored program runs: nothing that moves or changes the
/// program's modal state; reports, temperature targets, line numbering and `M112`; and the
/// SD-card commands, which decide for themselves (`files.rs`: `M25` pauses the file, `M27`
/// reports it, `M23` is refused…). `M30` is one only with a file name: alone, it ends a
/// program.
fn allowed_during_job(line: &Line<'_>) -> bool {
    if line.is_empty() {
        return true;
    }
    match line.command() {
        Some(w) if w.letter == b'M' => match w.value.as_integer() {
            Some(104 | 105 | 110 | 112 | 114 | 115 | 119 | 140) => true,
            Some(20..=29 | 32) => true,
            Some(30) => line.text_arg().is_some(),
            _ => false,
        },
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
    /// `M410`: stop the motion, answer the waiting lines without running them.
    QuickStop,
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
        410 => Some(Realtime::QuickStop),
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

/// What a capability needs the board to have.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Needs {
    /// Nothing: every board has it.
    Nothing,
    /// A heater.
    Heaters,
    /// A file store.
    Files,
    /// A file store: enabled when it writes long names.
    LongNames,
}

/// The `Cap:` lines of `M115`, each with what it needs: what this firmware does, under the
/// names Marlin gives it and OctoPrint and CNCjs look for.
///
/// | name | what |
/// |---|---|
/// | `EMERGENCY_PARSER` | `M112`, `M108` and `M410` act as they arrive, ahead of waiting lines |
/// | `ARCS` | `G2`/`G3` |
/// | `BUILD_PERCENT` | `M73` |
/// | `HOST_ACTION_COMMANDS` | `// action:notification …` when a halted machine is connected to |
/// | `AUTOREPORT_TEMP` | `M155` |
/// | `THERMAL_PROTECTION` | heater runaway and sensor faults stop the machine |
/// | `SDCARD` | `M20`–`M32`: files uploaded, listed and printed |
/// | `AUTOREPORT_SD_STATUS` | `M27 S<seconds>` |
/// | `LFN_WRITE` | `M28` takes long names (up to 63 bytes), not only 8.3 ones (`:0` on a card that takes 8.3 names only) |
const CAPABILITIES: &[(&str, Needs)] = &[
    ("EMERGENCY_PARSER", Needs::Nothing),
    ("ARCS", Needs::Nothing),
    ("BUILD_PERCENT", Needs::Nothing),
    ("HOST_ACTION_COMMANDS", Needs::Nothing),
    ("AUTOREPORT_TEMP", Needs::Heaters),
    ("THERMAL_PROTECTION", Needs::Heaters),
    ("SDCARD", Needs::Files),
    ("AUTOREPORT_SD_STATUS", Needs::Files),
    ("LFN_WRITE", Needs::LongNames),
];

/// A temperature in tenths of a degree, for replies.
fn celsius(mc: i32) -> Decimal {
    let mc = i64::from(mc);
    Decimal::new((mc + 50 * mc.signum()) / 100, 1)
}

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

    /// `echo:E<code> <text>` then `ok`: the line had no effect, the host goes on
    /// (`error:N` in the grbl dialect).
    pub(super) fn refuse<W: Write>(&mut self, r: &Refusal, out: &mut W) {
        if self.speaks_grbl() {
            return self.grbl_refuse(r, out);
        }
        self.stats.refused = self.stats.refused.wrapping_add(1);
        wire::refused(out, r);
        self.ok(out);
    }

    /// A command this firmware does not have: Marlin's `echo:Unknown command: "<command>"`
    /// then `ok`. Nothing changed; hosts pass over it.
    fn unknown<W: Write>(&mut self, line: &Line<'_>, letter: u8, out: &mut W) {
        if self.speaks_grbl() {
            let number = line.command().and_then(|w| w.value.as_u32());
            let r = Refusal::new(&CommandError::Unsupported { letter, number });
            return self.grbl_refuse(&r, out);
        }
        self.stats.refused = self.stats.refused.wrapping_add(1);
        let mut command = Text::<24>::new();
        match line.words().iter().find(|w| w.letter == letter && !w.bare) {
            Some(w) => {
                command
                    .push_byte(text::letter(w.letter))
                    .push_decimal(w.value);
            }
            None => {
                command.push_byte(text::letter(letter));
            }
        }
        let _ = wire::reply(out, &Reply::Unknown(command.as_str()));
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
                Some(Realtime::QuickStop) => self.quick_stop(out),
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
            Some(Held::Homing | Held::Dwell | Held::Probe | Held::Heat { .. }) => self.ok(out),
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
        // `M108` and `M410` acted when they arrived.
        let acted = line.is_command(b'M', 108) || line.is_command(b'M', 410);
        if line.is_empty() || line.is_command(b'M', 110) || acted {
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
        self.job_heat = None;
        self.end_heat_wait(out);
    }

    fn process_line<W: Write>(&mut self, bytes: &[u8], out: &mut W) {
        // No RepRap line starts with `$`: a grbl system command, in either dialect (no single
        // damaged bit makes a line's first letter a `$`).
        if bytes.first() == Some(&b'$') {
            return self.grbl_command(bytes, out);
        }
        if !self.speaks_grbl() {
            self.link.reprap_lines = true;
        }
        let (bytes, number) = if self.speaks_grbl() {
            grbl::strip_line_number(bytes)
        } else {
            (bytes, None)
        };
        if let Some(n) = number {
            self.kernel.set_line_tag(n);
        }
        // Parsed in place: every line of a program comes this way.
        let mut line = Line::empty();
        match line.parse_in(bytes) {
            Ok(()) => {}
            Err(e) if self.speaks_grbl() => return self.refuse(&Refusal::new(&e), out),
            Err(e) => return self.on_line_error(&e, out),
        }
        // A grbl sender numbers no line: `N` is the line's number for `Ln:`, never checked.
        if self.speaks_grbl() {
            if self.grbl_check(&line, out) {
                return;
            }
        } else if let Err(e) = self.accept_number(&line) {
            return self.on_line_error(&e, out);
        }
        self.execute_line(&line, bytes, out);
    }

    /// A line that failed its transport checks (`rs <expected>` alone) or that cannot be run
    /// (`echo:E<code>` then `ok`), as [`forja_protocol::gcode::LineNumbering::recover`] decides — except
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
            // The numbering took it already (`N-1 M110 N-1` included). A host connecting
            // sends it first: a halted machine says so.
            self.halted_notice(out);
            self.executed();
            return self.ok(out);
        }
        if line.is_command(b'M', 108) {
            self.cancel_waits(out);
            self.executed();
            return self.ok(out);
        }
        // A file being written (`M28`) takes the line; `M20`, `M413`, `M1000`: the stored
        // program and power-loss recovery (frames.rs).
        if self.program_command(line, out) {
            return;
        }
        // `M500`–`M503`: the planner settings kept (planner_settings.rs).
        if self.settings_command(line, bytes, out) {
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
                } else if line.is_command(b'G', 4) && !self.kernel.is_idle() {
                    self.link.held = Some(Held::Dwell);
                } else if self.kernel.is_probing() {
                    self.link.held = Some(Held::Probe);
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
                if let CommandError::Unsupported { letter, .. } = e {
                    return self.unknown(line, letter, out);
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
                    let mut line = Line::empty();
                    match line.parse_in(lb.bytes()) {
                        Ok(()) => self.execute_line(&line, lb.bytes(), out),
                        Err(e) => self.refuse(&Refusal::new(&e), out),
                    }
                    if self.link.held.is_some() {
                        return;
                    }
                }
                Some(Held::Heat { .. } | Held::Homing | Held::Dwell | Held::Probe) => return,
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
        // The refusal of a device, named by `what` and its number if it has one.
        let device = |e: PeripheralError, what: &str, number: Option<u8>| {
            let mut r = Refusal::with(&e, what);
            if let Some(n) = number {
                r.detail().push_number(n);
            }
            Done::Refused(r)
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
                        "S",
                    ));
                };
                if mc > 0 && state == MachineState::Alarm(Alarm::EmergencyStop) {
                    return Done::Refused(Refusal::new(&CommandError::Locked));
                }
                let zones = match heater {
                    Heater::Bed => HeatZones::Bed,
                    Heater::Chamber => HeatZones::Chamber,
                    Heater::Extruder(_) => HeatZones::HotEnd,
                };
                match (devices.set_temperature(heater, mc), wait) {
                    (Err(e @ PeripheralError::NoDevice), _) => match heater {
                        Heater::Extruder(Some(t)) => device(e, "hot end", Some(t)),
                        Heater::Extruder(None) => device(e, "hot end", None),
                        Heater::Bed => device(e, "bed", None),
                        Heater::Chamber => device(e, "chamber", None),
                    },
                    (Err(e), _) => Done::Refused(Refusal::new(&e)),
                    (Ok(()), TemperatureWait::No) => Done::Ok,
                    (Ok(()), TemperatureWait::Heating) => Done::Wait(HeatWait {
                        zones,
                        heating_only: true,
                    }),
                    (Ok(()), TemperatureWait::Reach) => Done::Wait(HeatWait {
                        zones,
                        heating_only: false,
                    }),
                }
            }
            Effect::WaitForTemperatures => Done::Wait(HeatWait::ALL),
            Effect::ReportTemperatures => Done::Temperatures,
            Effect::Fan { index, duty } => match devices.set_fan(index, duty) {
                Ok(()) => Done::Ok,
                Err(e) => device(e, "fan", Some(index)),
            },
            Effect::Spindle(s) => match devices.set_spindle(s) {
                Ok(()) => Done::Ok,
                Err(e) => device(e, "spindle", None),
            },
            Effect::Coolant(c) => match devices.set_coolant(c) {
                Ok(()) => Done::Ok,
                // `M9` on a board without coolant: nothing is on, nothing to turn off (CAM
                // posts end every program with it).
                Err(PeripheralError::NoDevice) if c == Coolant::Off => Done::Ok,
                Err(e) => device(e, "coolant", None),
            },
            Effect::SetLineNumber(_) | Effect::Paused => Done::Ok,
            Effect::ToolChange(tool) => Done::ToolChange(tool),
            Effect::ProgramEnd => match devices.end_program() {
                Ok(()) => Done::ProgramEnd,
                Err((e, what)) => device(e, what, None),
            },
            Effect::ReportFirmware => Done::Firmware,
            Effect::ReportEndstops => Done::Endstops,
            Effect::Storage(s) => Done::Files(FileCommand::new(&s)),
            // A machine without extruders selects a cutting tool, which only `M6` changes
            // (grbl's and LinuxCNC's `T`); a printer selects one of its extruders.
            Effect::SelectTool(_) if config.extruders == 0 => Done::Ok,
            Effect::SelectTool(t) if t < config.extruders.max(1) => Done::Ok,
            Effect::SelectTool(t) => {
                let mut r = Refusal::new(&CommandError::BadValue { letter: b'T' });
                r.detail().push("T").push_number(t);
                Done::Refused(r)
            }
            Effect::Motors { enabled, axes } => match devices.set_axis_motors(enabled, axes) {
                Ok(()) => Done::Ok,
                Err(e) => Done::Refused(Refusal::new(&e)),
            },
            Effect::Stopped(kind) => Done::Stop(kind),
            Effect::MotionDone => Done::Ok,
            Effect::Output { index, on, .. } => match devices.set_output(index, on) {
                Ok(()) => Done::Ok,
                Err(e) => device(e, "output", Some(index)),
            },
            Effect::PowerSupply { on } => match devices.set_power_supply(on) {
                Ok(()) => Done::Ok,
                Err(e) => device(e, "power-supply", None),
            },
            Effect::Tone {
                frequency_hz,
                duration_ms,
            } => match devices.tone(frequency_hz, duration_ms) {
                Ok(()) => Done::Ok,
                Err(e) => device(e, "beeper", None),
            },
            Effect::QuickStop => Done::QuickStop,
            Effect::Progress {
                percent,
                remaining_min,
                layer,
            } => Done::Progress(HostProgress {
                percent,
                remaining_min,
                layer,
            }),
            Effect::Message(text) => Done::Message(copied(text)),
            Effect::HostMessage(text) => Done::HostMessage(copied(text)),
            Effect::AutoReport { seconds } => Done::AutoReport(seconds),
            Effect::BusyInterval(seconds) => Done::BusyInterval(seconds),
        }
    }

    /// Stop on `M0` (program stop) or `M112` (emergency): the devices shut down and the
    /// motors released; an emergency stop also ends the job and the heater waits, and is a
    /// fault to report (returned).
    fn stop(&mut self, kind: StopKind) -> Option<Refusal> {
        if kind == StopKind::Emergency {
            self.job.stop(&mut self.kernel);
            self.reported_alarm = Some(Alarm::EmergencyStop);
            self.job_heat = None;
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
                self.stats.oks = self.stats.oks.wrapping_add(1);
                if !self.write_temperatures(true, out) {
                    wire::ok(out);
                }
            }
            Done::Firmware => self.firmware_reply(out),
            Done::Endstops => self.endstops_reply(out),
            Done::ToolChange(tool) => {
                self.tool_change_notice(tool, out);
                self.ok(out);
            }
            Done::ProgramEnd => {
                self.program_end_notice(out);
                self.ok(out);
            }
            Done::Wait(wait) => {
                if self.heat_done(wait) {
                    self.ok(out);
                } else {
                    self.hold_for_heat(wait);
                }
            }
            Done::Stop(kind) => {
                if let Some(fault) = self.stop(kind) {
                    self.end_heat_wait(out);
                    self.report_fault(&fault, out);
                }
                self.ok(out);
            }
            other => {
                self.carry_out(other, out);
                self.ok(out);
            }
        }
    }

    /// When the machine is locked by an alarm or halted: `// action:notification Machine
    /// halted: E<code> <name>. Send M999 to clear.` (OctoPrint shows it to its user; other
    /// hosts show or pass over a `//` line). Written at a host's connection (`M110`, `M115`);
    /// every line refused meanwhile says `E125 alarm-locked` or `E126 halted`.
    fn halted_notice<W: Write>(&mut self, out: &mut W) {
        let mut line = Text::<96>::new();
        match self.kernel.state() {
            MachineState::Alarm(a) => {
                let r = text::alarm_refusal(&a, &self.letters());
                line.push("action:notification Machine halted: E")
                    .push_number(r.code)
                    .push(" ")
                    .push(r.text());
            }
            MachineState::Halted => {
                line.push("action:notification Machine halted by M0");
            }
            _ => return,
        }
        line.push(". Send M999 to clear.");
        let _ = wire::reply(out, &Reply::Debug(line.as_str()));
    }

    /// Carry out what an effect left to the controller (from the link or the stored program);
    /// whether it was one of those. The answer is the caller's.
    fn carry_out<W: Write>(&mut self, done: Done, out: &mut W) -> bool {
        match done {
            Done::QuickStop => self.quick_stop(out),
            Done::Progress(p) => self.set_host_progress(p),
            Done::Message(t) => self.set_message(t),
            Done::HostMessage(t) => self.host_message(t.as_bytes(), out),
            Done::AutoReport(s) => self.set_auto_report(s),
            Done::BusyInterval(s) => self.busy_interval(s, out),
            Done::Files(command) => self.file_command(command, out),
            _ => return false,
        }
        true
    }

    /// `M410` and the stop frame: the motion stops (the stored program with it) and the heater
    /// waits end; the lines received before it and not yet answered are answered without
    /// running. The machine keeps its position and homing.
    pub(super) fn quick_stop<W: Write>(&mut self, out: &mut W) {
        if self.job_active() {
            self.job.stop(&mut self.kernel);
        } else {
            self.kernel.stop();
        }
        self.job_heat = None;
        self.end_heat_wait(out);
        self.drop_waiting(&Refusal::new(&ControllerError::Stopped), out);
    }

    /// Whether every heater with a target is within the tolerance of it.
    pub(super) fn heat_done(&mut self, wait: HeatWait) -> bool {
        self.devices
            .heat_done(wait, self.config.heater_tolerance_mc)
    }

    /// `X:… Y:… Z:… E:… Count X:… Y:… Z:…` then `ok`: the work positions, then the step counts
    /// of the axes that are not extruders, as Marlin reports them.
    fn position_reply<W: Write>(&mut self, p: &PositionReport<N>, out: &mut W) {
        let mut axes = Axes::new();
        for (letter, mm) in p.letters.iter().zip(p.work_mm.iter()) {
            let _ = axes.push(Word::new(*letter, millimetres(*mm)));
        }
        let steps = self.kernel.machine_steps();
        let mut counts = Counts::new();
        for (axis, steps) in self.kernel.config().axes.iter().zip(steps) {
            if axis.kind != AxisKind::Extruder {
                let _ = counts.push((axis.letter, steps));
            }
        }
        let _ = wire::reply(out, &Reply::Position { axes, counts });
        self.ok(out);
    }

    fn firmware_reply<W: Write>(&mut self, out: &mut W) {
        let mut count = Text::<4>::new();
        count.push_number(self.config.extruders);
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
        if !wire::reply(out, &Reply::Firmware(KeyValues::Pairs(&full))) {
            let _ = wire::reply(out, &Reply::Firmware(KeyValues::Pairs(&base)));
        }
        self.halted_notice(out);
        let heaters = self.devices.temperatures();
        let has_heaters = heaters.hot_end.is_some() || heaters.bed.is_some();
        let files = self.devices.parts.files().map(|f| f.writes_long_names());
        for &(name, needs) in CAPABILITIES {
            let (present, enabled) = match needs {
                Needs::Nothing => (true, true),
                Needs::Heaters => (has_heaters, true),
                Needs::Files => (files.is_some(), true),
                Needs::LongNames => (files.is_some(), files == Some(true)),
            };
            if present {
                let _ = wire::reply(out, &Reply::Capability { name, enabled });
            }
        }
        self.ok(out);
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
                t.push(" ");
            }
            t.push_byte(axis.letter.to_ascii_lowercase())
                .push("_")
                .push(side)
                .push(":")
                .push(if *triggered { "TRIGGERED" } else { "open" });
        }
        if t.as_bytes().is_empty() {
            return self.ok(out);
        }
        self.stats.oks = self.stats.oks.wrapping_add(1);
        if !wire::reply(out, &Reply::OkWith(t.as_str())) {
            wire::ok(out);
        }
    }

    /// ` T:<hot end> /<target> B:<bed> /<target> @:<power> B@:<power>`, during a wait and for
    /// `M155`.
    pub(super) fn report_temperatures<W: Write>(&mut self, out: &mut W) {
        self.write_temperatures(false, out);
    }

    /// The temperature report, `M105`'s answer (`ok` first) or a report; `false` (nothing
    /// written) on a board without heaters.
    fn write_temperatures<W: Write>(&mut self, ok: bool, out: &mut W) -> bool {
        let t = self.devices.temperatures();
        let heat = |r: Reading| Heat {
            current: celsius(r.current_mc),
            target: celsius(r.target_mc),
            // Marlin's scale: 0 to 127.
            power: ((u32::from(r.power) * 127 + u32::from(FULL_POWER) / 2) / u32::from(FULL_POWER))
                as u8,
        };
        wire::reply(
            out,
            &Reply::Temperatures {
                hot_end: t.hot_end.map(heat),
                bed: t.bed.map(heat),
                ok,
            },
        )
    }

    /// Soft reset (`M999`, frame `Reset`): the kernel's alarms and modal state, the job (its
    /// program and line kept), latched heater faults, waits.
    pub(super) fn reset<W: Write>(&mut self, out: &mut W) {
        self.job.reset(&mut self.kernel);
        self.devices.reset();
        self.thermal = None;
        self.reported_alarm = None;
        self.job_heat = None;
        self.end_heat_wait(out);
    }

    /// Feed the stored program to the kernel, carrying out its effects.
    pub(super) fn feed_job<W: Write>(&mut self, out: &mut W) {
        for _ in 0..64 {
            if !self.job_active() || self.job_heat.is_some() {
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
                self.stats.program_lines = self.stats.program_lines.wrapping_add(fed);
                self.taken = true;
            }
            let Some(done) = done else { return };
            match done {
                Done::Refused(r) => {
                    self.job.stop(&mut self.kernel);
                    self.error_frame(&r, out);
                    return;
                }
                Done::Wait(wait) => {
                    self.job_heat = (!self.heat_done(wait)).then_some(wait);
                }
                Done::Stop(kind) => {
                    if let Some(fault) = self.stop(kind) {
                        self.end_heat_wait(out);
                        self.report_fault(&fault, out);
                        return;
                    }
                }
                Done::QuickStop => {
                    self.quick_stop(out);
                    return;
                }
                other => {
                    self.carry_out(other, out);
                }
            }
            if self.job.state() != JobState::Running {
                return;
            }
        }
    }
}
