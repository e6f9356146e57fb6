//! The grbl 1.1 dialect of a link: what CNC senders (CNCjs, bCNC, Universal G-code Sender)
//! speak, on the same link as the RepRap lines and the frames.
//!
//! # Entering the dialect
//!
//! A link starts in the RepRap dialect (printer hosts, `forja send`, the frames) and enters the
//! grbl dialect at the first of:
//!
//! - `0x18` (ctrl-x, grbl's soft reset), anywhere: the machine resets as grbl's does and the
//!   banner `Grbl 1.1h ['$' for help]` goes out;
//! - `?` between records (not inside a line): a status report goes out (a sender that saw no
//!   banner polls with `?`);
//! - a line that starts with `$` (`$$`, `$X`, `$I`): no RepRap line does.
//!
//! `0x18` and `?` enter it only before the link's first RepRap line: once a printer host
//! streams, a bit flip that makes a `8` a ctrl-x is a damaged byte of its line, not a reset.
//! It stays there until the link is reset (a new session, another host).
//!
//! # In the dialect
//!
//! - **Realtime bytes** ([`Realtime`]) are taken out of the stream as they arrive, wherever
//!   they fall, before any line is decoded: `?` reports, `!` holds, `~` resumes, `0x18` resets,
//!   `0x85` cancels a jog, `0x90`–`0x9D` change the feed, rapid and spindle overrides (the
//!   kernel's realtime overrides, the devices' spindle override), `0x9E` stops the spindle
//!   during a hold, `0xA0`/`0xA1` toggle coolant.
//! - **Every line gets exactly one answer**: `ok`, or `error:N` with grbl's number (the
//!   table in `docs/protocol.md`); blank and comment-only lines get `ok`, and so does a line
//!   that is only `%` (a program's start or end marker). Lines are not numbered: `N10 G0 X5`
//!   runs and `N` is the line number `Ln:` reports.
//! - **Faults** that stop the machine are `ALARM:N`, followed by `[MSG:…]`.
//! - **`$` commands** ([`Command`]) as grbl 1.1 and grblHAL define them; `$$` and `$<n>=` are
//!   the controller's settings under grbl's numbers, `$N0=`/`$N1=` its startup lines.
//! - **Soft reset** (`0x18`) stops at once, the spindle and the coolant too, and the overrides
//!   go back to 100 %. Lines received and not yet answered are dropped without an answer, as
//!   grbl flushes its receive buffer (a sender clears its own count at reset). Motion cut
//!   mid-move leaves the machine in `ALARM:3` (steps may be lost: `$H` or `$X`). Out of an
//!   alarm, the startup lines run after the banner, each echoed `>LINE:ok` (or
//!   `>LINE:error:N`); they run at power-on too.

use embedded_io::Write;
use forja_hal_abstraction::device::Rotation;
use forja_hal_abstraction::program::ProgramStore;
use forja_hal_abstraction::storage::RecordStorage;
use forja_motion::config::SoftLimits;
use forja_motion::coords::{Coordinates, Nm, Slot};
use forja_motion::error::{Alarm as KernelAlarm, CommandError};
use forja_motion::preview::Preview;
use forja_motion::{MachineState, ProbeReport, Reply as KernelReply};
use forja_protocol::gcode::{Decimal, Line};
use forja_protocol::grbl::{
    Alarm, Command, Error, Message, Micrometres, Realtime, Restore, State, Status,
};

use super::peripherals::{Peripherals, SpindleMotion};
use super::settings::{AxisField, Key, MAX_STARTUP_LINE_LEN};
use super::text::{Refusal, Text};
use super::{Core, Held, LineBuf, READ_AHEAD_BYTES, wire};

/// Which dialect a link speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Dialect {
    /// RepRap G-code lines with Marlin's replies, and the frames.
    RepRap,
    /// grbl 1.1.
    Grbl,
}

/// The grbl state of a link.
#[derive(Debug, Clone, Copy)]
pub(super) struct GrblLink {
    /// A `$J=` jog runs.
    pub(super) jogging: bool,
    /// Status reports sent since `WCO` was last sent (grbl sends it every 10 reports, or at
    /// once after it changed).
    reports_since_offset: u8,
    /// Status reports sent since `Ov` was last sent.
    reports_since_overrides: u8,
    /// The safety door (`0x84`) was opened: the machine holds until cycle start.
    door: Option<Door>,
}

/// A safety door opening (grbl's `0x84`): the motion holds; once at rest the spindle and the
/// coolant stop, and cycle start brings them back before the motion goes on.
#[derive(Debug, Clone, Copy)]
struct Door {
    /// The machine has come to rest and the spindle and the coolant are stopped.
    stopped: bool,
    /// The coolant lines that were on (mist, flood), to turn on again.
    coolant: (bool, bool),
}

impl GrblLink {
    pub(super) const fn new() -> Self {
        Self {
            door: None,
            jogging: false,
            reports_since_offset: u8::MAX,
            reports_since_overrides: u8::MAX,
        }
    }
}

/// Realtime bytes taken out of the input, waiting for the controller, in arrival order.
#[derive(Debug, Clone, Copy)]
pub(super) struct RealtimeQueue {
    items: [Option<Realtime>; 16],
    head: usize,
    len: usize,
}

impl RealtimeQueue {
    pub(super) const fn new() -> Self {
        Self {
            items: [None; 16],
            head: 0,
            len: 0,
        }
    }

    /// Queue `r`. A full queue keeps the commands already there, except that a stop
    /// (`0x18`) always gets in, in place of the newest.
    pub(super) fn push(&mut self, r: Realtime) {
        let cap = self.items.len();
        if self.len == cap {
            if r != Realtime::SoftReset {
                return;
            }
            self.len -= 1;
        }
        if let Some(slot) = self.items.get_mut((self.head + self.len) % cap) {
            *slot = Some(r);
            self.len += 1;
        }
    }

    pub(super) fn pop(&mut self) -> Option<Realtime> {
        if self.len == 0 {
            return None;
        }
        let r = self.items.get_mut(self.head).and_then(Option::take);
        self.head = (self.head + 1) % self.items.len();
        self.len -= 1;
        r
    }
}

/// What a byte of the input is, before it is decoded: a realtime command taken out of the
/// stream, or a byte of a record. `grbl`: the link speaks the grbl dialect; `line_open`:
/// bytes of a record came since the last terminator.
pub(super) fn realtime_byte(byte: u8, grbl: bool, line_open: bool) -> Option<Realtime> {
    match Realtime::from_byte(byte)? {
        Realtime::SoftReset => Some(Realtime::SoftReset),
        Realtime::StatusReport if !line_open => Some(Realtime::StatusReport),
        r if grbl => Some(r),
        _ => None,
    }
}

/// grbl's number for a refusal of the controller (its Forja wire code).
pub(super) fn error_of(code: u16) -> Error {
    match code {
        1 | 11 => Error::Overflow,
        2..=7 | 13 => Error::InvalidLineNumber,
        8 | 12 => Error::ExpectedCommandLetter,
        9 | 10 => Error::BadNumberFormat,
        120 | 127 | 194 => Error::UnsupportedCommand,
        121 | 195 => Error::ValueOutOfRange,
        122 => Error::ValueWordMissing,
        123 => Error::InvalidTarget,
        124 | 131 => Error::TravelExceeded,
        125 | 126 => Error::SystemGcLock,
        128 => Error::IdleError,
        129 => Error::ModalGroupViolation,
        130 => Error::WordRepeated,
        132 => Error::UnsupportedCommand,
        133 => Error::AxisWordsExist,
        190 => Error::InvalidStatement,
        191 => Error::ValueOutOfRange,
        _ => Error::InvalidInState,
    }
}

/// grbl's alarm for a fault of the controller (its Forja wire code: the kernel's alarms
/// 150–156, a heater's faults).
fn alarm_of(code: u16) -> Alarm {
    match code {
        150 => Alarm::HardLimit,
        151 => Alarm::HomingFailApproach,
        152 => Alarm::HomingFailPulloff,
        153 => Alarm::EStop,
        155 => Alarm::MotorFault,
        157 => Alarm::ProbeFailInitial,
        158 => Alarm::ProbeFailContact,
        _ => Alarm::AbortCycle,
    }
}

/// Write one grbl message; nothing when it does not encode.
pub(super) fn say<W: Write>(out: &mut W, message: &Message<'_>) {
    let mut buf = [0u8; 160];
    if let Ok(n) = message.encode(&mut buf) {
        let _ = out.write_all(buf.get(..n).unwrap_or(&[]));
    }
}

/// `mm` as micrometres, rounded.
fn micrometres(mm: f64) -> Micrometres {
    libm::round(mm * 1000.0) as Micrometres
}

/// Millimetres in an inch.
const MM_PER_INCH: f64 = 25.4;

/// A position of µm as grbl reports it: unchanged, or with `$13=1` in thousandths of an inch
/// (written with three decimals: inches).
fn reported(um: Micrometres, inches: bool) -> Micrometres {
    if inches {
        libm::round(um as f64 / MM_PER_INCH) as Micrometres
    } else {
        um
    }
}

/// A rate of mm/min as grbl reports it, whole: mm/min, or with `$13=1` inches/min.
fn reported_rate(mm_min: f32, inches: bool) -> u32 {
    let rate = f64::from(mm_min) / if inches { MM_PER_INCH } else { 1.0 };
    libm::round(rate).clamp(0.0, f64::from(u32::MAX)) as u32
}

/// Up to eight letters of a status report field (`Pn:`, `A:`).
struct Letters {
    buf: [u8; 8],
    len: usize,
}

impl Letters {
    const fn new() -> Self {
        Self {
            buf: [0; 8],
            len: 0,
        }
    }

    fn push(&mut self, letter: u8) {
        if let Some(slot) = self.buf.get_mut(self.len) {
            *slot = letter;
            self.len += 1;
        }
    }

    fn as_bytes(&self) -> &[u8] {
        self.buf.get(..self.len).unwrap_or(&[])
    }
}

/// When a `$` command is answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Answer {
    /// Now: `ok`.
    Now,
    /// When what it started is done (`$H`: at the end of homing).
    Later,
}

/// The work offset, µm (grbl's `WCO` and `G92`: the machine position less the work position),
/// from the commanded position in work mm and in machine nm.
fn work_offset<const N: usize>(work_mm: &[f64; N], machine_nm: &[i64; N]) -> [Micrometres; N] {
    core::array::from_fn(|i| machine_nm[i].div_euclid(1000) - micrometres(work_mm[i]))
}

/// `nm` in whole micrometres, to the nearest (halves up), as grbl rounds what it prints.
fn nm_to_um(nm: Nm) -> Micrometres {
    nm.saturating_add(500).div_euclid(1000)
}

/// A line of a grbl sender without its `N` number (grbl's senders number lines without a
/// checksum, which the RepRap syntax refuses), and the number. A line that is only `%` (the
/// start or end marker of a program, as Fusion 360's posts write it, which grblHAL ignores)
/// comes back empty: it is answered `ok` and does nothing.
pub(super) fn strip_line_number(bytes: &[u8]) -> (&[u8], Option<u32>) {
    let blank = |b: &&u8| matches!(b, b' ' | b'\t');
    let start = bytes.iter().take_while(blank).count();
    let rest = bytes.get(start..).unwrap_or(&[]);
    let end = rest.len() - rest.iter().rev().take_while(blank).count();
    if rest.get(..end) == Some(b"%") {
        return (&[], None);
    }
    let Some((b'N' | b'n', tail)) = rest.split_first() else {
        return (bytes, None);
    };
    let digits = tail.iter().take_while(|b| b.is_ascii_digit()).count();
    if digits == 0 {
        return (bytes, None);
    }
    let number = tail
        .get(..digits)
        .and_then(|d| core::str::from_utf8(d).ok())
        .and_then(|d| d.parse().ok());
    (tail.get(digits..).unwrap_or(&[]), number)
}

/// The work coordinate systems by their G codes, `G54` first.
const SYSTEM_NAMES: [&str; 9] = [
    "G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3",
];

/// The first record key of the coordinate table: slot `k` ([`Slot::index`]) is kept at
/// `COORDINATE_RECORDS + k`, its axes as little-endian `i64` nanometres.
pub const COORDINATE_RECORDS: u16 = 0x0400;

/// The table kept in `storage`, over `defaults` for what is not there or does not read.
///
/// Context: thread, at start-up. Blocks for the storage reads.
pub(super) fn load_coordinates<S: RecordStorage, const N: usize>(
    storage: &mut S,
    defaults: &Coordinates<N>,
) -> Coordinates<N> {
    let mut coords = *defaults;
    for slot in Slot::all() {
        let mut buf = [0u8; 64];
        let key = COORDINATE_RECORDS + u16::from(slot.index());
        let Ok(Some(len)) = storage.read(key, &mut buf) else {
            continue;
        };
        if len != 8 * N {
            continue;
        }
        let values: [Nm; N] = core::array::from_fn(|i| {
            let mut word = [0u8; 8];
            if let Some(src) = buf.get(8 * i..8 * i + 8) {
                word.copy_from_slice(src);
            }
            i64::from_le_bytes(word)
        });
        coords.set(slot, values);
    }
    coords
}

/// A grbl setting: its number and what it is in the controller's settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum GrblSetting {
    /// A setting of the controller, by key.
    Stored(Key),
    /// `$130`+: an axis's travel, `max - min` (setting it moves `max`).
    Travel(usize),
    /// `$22`, homing enable: 1 when an axis homes (the machine configuration's; read-only).
    HomingEnable,
    /// `$24`, `$25`, `$27`: a homing setting of every axis that homes (`$$` reports the
    /// first's, setting it sets every one).
    Homing(AxisField),
}

impl<const N: usize, const B: usize, const Q: usize, P, X, S> Core<'_, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// Store the slots of the coordinate table that lines changed, once the machine is at rest
    /// (a flash write may hold the chip up). A slot that cannot be written stays to store.
    pub(super) fn store_coordinates(&mut self) {
        self.coords_unsaved |= self.kernel.take_changed_coordinates();
        if self.coords_unsaved == 0 || !self.kernel.is_idle() {
            return;
        }
        let coords = *self.kernel.coordinates();
        for slot in Slot::all() {
            let bit = 1u16 << slot.index();
            if self.coords_unsaved & bit == 0 {
                continue;
            }
            let mut buf = [0u8; 64];
            for (i, v) in coords.get(slot).iter().enumerate() {
                if let Some(dst) = buf.get_mut(8 * i..8 * i + 8) {
                    dst.copy_from_slice(&v.to_le_bytes());
                }
            }
            let bytes = buf.get(..8 * N).unwrap_or(&[]);
            let key = COORDINATE_RECORDS + u16::from(slot.index());
            if self.storage.write(key, bytes).is_ok() {
                self.coords_unsaved &= !bit;
            }
        }
    }

    /// `M2`/`M30` of the link, in the grbl dialect: `[MSG:Pgm End]`, and the feed, rapid and
    /// spindle overrides back to 100 % (grbl's default build). Nothing in the RepRap dialect.
    pub(super) fn program_end_notice<W: Write>(&mut self, out: &mut W) {
        if self.speaks_grbl() {
            self.reset_overrides();
            say(out, &Message::Feedback("Pgm End"));
        }
    }

    /// grbl's feed, rapid and spindle overrides back to 100 %.
    fn reset_overrides(&mut self) {
        self.kernel.set_realtime_overrides(100, 100);
        let _ = self.devices.set_spindle_override(100);
        self.link.grbl.reports_since_overrides = u8::MAX;
    }

    /// Let the spindle follow the motion now (each poll; cheap): the `S` of the move under way,
    /// and in laser mode (`$32`) a laser's power, off in rapids, homing and jogs, and at rest
    /// outside `G1`/`G2`/`G3`.
    pub(super) fn follow_spindle(&mut self) {
        self.door_stop();
        let laser = self.settings.laser_mode();
        let now = self.kernel.motion_now();
        let state = self.kernel.state();
        let cutting = laser
            && match state {
                MachineState::Homing => false,
                _ if self.link.grbl.jogging => false,
                _ if now.speed_mm_min > 0.0 => !now.rapid,
                _ => matches!(self.kernel.modal_report().motion, "G1" | "G2" | "G3"),
            };
        let motion = SpindleMotion {
            rpm: now.spindle_rpm,
            laser,
            fraction: now.fraction,
            cutting,
            held: matches!(
                state,
                MachineState::Hold { stopped: true } | MachineState::Paused
            ),
            running: matches!(state, MachineState::Running | MachineState::Homing),
        };
        let _ = self.devices.follow(motion);
    }

    /// Once the motion a safety door held is at rest: stop the spindle and the coolant, as
    /// grbl does (cycle start brings them back).
    fn door_stop(&mut self) {
        let Some(door) = self.link.grbl.door.as_mut() else {
            return;
        };
        if door.stopped || self.kernel.state() != (MachineState::Hold { stopped: true }) {
            return;
        }
        door.stopped = true;
        door.coolant = self.devices.coolant_state();
        let (mist, flood) = door.coolant;
        if mist {
            let _ = self.devices.set_coolant_line(false, false);
        }
        if flood {
            let _ = self.devices.set_coolant_line(true, false);
        }
        let _ = self.devices.stop_spindle_in_hold();
    }

    /// `M6`: tell the operator which tool to put in and how to go on: `[MSG:…]` in the grbl
    /// dialect (cycle start, `~`), `echo:` otherwise (resume: frame `Start`).
    pub(super) fn tool_change_notice<W: Write>(&mut self, tool: Option<u8>, out: &mut W) {
        let mut text = Text::<48>::new();
        match tool {
            Some(t) => text.push("Change to tool T").push_number(t),
            None => text.push("Change the tool"),
        };
        if self.speaks_grbl() {
            text.push(", then cycle start");
            say(out, &Message::Feedback(text.as_str()));
        } else {
            text.push(", then resume");
            let _ = wire::reply(out, &forja_protocol::reply::Reply::Echo(text.as_str()));
        }
    }

    /// The link speaks the grbl dialect from now on.
    pub(super) fn enter_grbl(&mut self) {
        self.link.dialect = Dialect::Grbl;
        self.kernel.set_grbl_dialect(true);
    }

    pub(super) fn speaks_grbl(&self) -> bool {
        self.link.dialect == Dialect::Grbl
    }

    /// Act on a realtime command, now.
    pub(super) fn on_realtime<W: Write>(&mut self, r: Realtime, out: &mut W) {
        self.enter_grbl();
        match r {
            Realtime::SoftReset => self.grbl_reset(out),
            Realtime::StatusReport => self.grbl_status(out),
            Realtime::FeedHold => self.kernel.hold(),
            Realtime::CycleStart => {
                // The coolant a door stopped, then the spindle stopped during the hold (the
                // door's, `0x9E`, a laser's), run again first.
                if let Some(door) = self.link.grbl.door.take() {
                    let (mist, flood) = door.coolant;
                    if mist {
                        let _ = self.devices.set_coolant_line(false, true);
                    }
                    if flood {
                        let _ = self.devices.set_coolant_line(true, true);
                    }
                }
                let _ = self.devices.restore_spindle();
                self.kernel.resume();
            }
            Realtime::SafetyDoor => {
                self.kernel.hold();
                if self.link.grbl.door.is_none() {
                    self.link.grbl.door = Some(Door {
                        stopped: false,
                        coolant: (false, false),
                    });
                }
            }
            Realtime::JogCancel => {
                if self.link.grbl.jogging {
                    self.kernel.stop();
                    self.link.grbl.jogging = false;
                }
            }
            Realtime::FeedOverride(step) => {
                let (feed, rapid) = self.kernel.realtime_overrides();
                let next = step.apply(feed.min(255) as u8, 10, 200);
                self.kernel.set_realtime_overrides(u16::from(next), rapid);
                self.link.grbl.reports_since_overrides = u8::MAX;
            }
            Realtime::RapidOverride(percent) => {
                let (feed, _) = self.kernel.realtime_overrides();
                self.kernel.set_realtime_overrides(feed, u16::from(percent));
                self.link.grbl.reports_since_overrides = u8::MAX;
            }
            Realtime::SpindleOverride(step) => {
                let next = step.apply(self.devices.spindle_override(), 10, 200);
                let _ = self.devices.set_spindle_override(next);
                self.link.grbl.reports_since_overrides = u8::MAX;
            }
            // grbl's rule: only in a hold, once at rest.
            Realtime::SpindleStop => {
                if self.kernel.state() == (MachineState::Hold { stopped: true }) {
                    let _ = self.devices.toggle_spindle_stop();
                }
            }
            Realtime::FloodToggle | Realtime::MistToggle => self.toggle_coolant(r),
        }
    }

    /// `0x18`: stop at once, drop what waits, greet again.
    fn grbl_reset<W: Write>(&mut self, out: &mut W) {
        let moving = !matches!(
            self.kernel.state(),
            MachineState::Idle
                | MachineState::Alarm(_)
                | MachineState::Hold { stopped: true }
                | MachineState::Paused
                | MachineState::Halted
        );
        if self.job_active() {
            self.job.stop(&mut self.kernel);
        }
        self.reset(out);
        self.kernel.reset();
        // grbl's reset stops the spindle and the coolant, and the overrides go back to 100 %.
        let _ = self.devices.end_program();
        self.reset_overrides();
        if moving {
            // grbl's order: the alarm, then the banner and how to unlock.
            self.kernel.lock_after_reset();
            self.reported_alarm = Some(KernelAlarm::ResetDuringMotion);
            say(out, &Message::Alarm(Alarm::AbortCycle));
        }
        // grbl flushes its receive buffer: what waited is dropped unanswered.
        self.link.held = None;
        self.link.queue.clear();
        self.link.grbl.jogging = false;
        self.link.grbl.door = None;
        self.check = None;
        let _ = out.write_all(b"\r\n");
        say(out, &Message::Welcome);
        if matches!(self.kernel.state(), MachineState::Alarm(_)) {
            say(out, &Message::Feedback("'$H'|'$X' to unlock"));
        } else {
            self.run_startup_lines(out);
        }
    }

    /// At power-on: the startup lines, run as in the grbl dialect whatever the link speaks
    /// (the link stays in its dialect), unless the machine starts in an alarm.
    pub(super) fn power_on_startup_lines<W: Write>(&mut self, out: &mut W) {
        let none = (0..2).all(|i| self.settings.startup_line(i).is_empty());
        if none || matches!(self.kernel.state(), MachineState::Alarm(_)) {
            return;
        }
        let (dialect, gcode_seen) = (self.link.dialect, self.link.gcode_seen);
        self.enter_grbl();
        self.run_startup_lines(out);
        self.link.gcode_seen = gcode_seen;
        if dialect == Dialect::RepRap {
            self.link.dialect = Dialect::RepRap;
            self.kernel.set_grbl_dialect(false);
        }
    }

    /// grbl's startup lines (`$N0`, `$N1`), in order: each runs as a line of the link would,
    /// and is echoed `>LINE:ok` or `>LINE:error:N` (an error does not stop the next). A line
    /// that waits for its motion or dwell is not waited for (`ok` at once); one that cannot be
    /// taken before the motion of the line before it ends is refused (`error:8`).
    fn run_startup_lines<W: Write>(&mut self, out: &mut W) {
        for index in 0..2 {
            let line = LineBuf::new(self.settings.startup_line(index).as_bytes());
            if line.bytes().is_empty() {
                continue;
            }
            // The echo's head, then the line's own answer (`ok`, `error:N`) completes it: the
            // line runs through the link's own path, to the link's own writer.
            let _ = out.write_all(b">");
            let _ = out.write_all(line.bytes());
            let _ = out.write_all(b":");
            self.on_line(line.bytes(), out);
            // A line that waits (its motion, a dwell, heaters) is not waited for: `ok` now. One
            // the kernel could not take yet is dropped.
            match self.link.held.take() {
                Some(Held::Line) => say(out, &Message::Error(Error::IdleError)),
                Some(_) => self.ok(out),
                None => {}
            }
        }
    }

    /// `?`: the status report.
    pub(super) fn grbl_status<W: Write>(&mut self, out: &mut W) {
        let state = match self.kernel.state() {
            _ if self.check.is_some() => State::Check,
            MachineState::Idle if self.link.lines_held() => State::Run,
            MachineState::Idle => State::Idle,
            MachineState::Running if self.link.grbl.jogging => State::Jog,
            MachineState::Running => State::Run,
            // Opened by `0x84` (there is no door switch, so it reads closed again at once):
            // `Door:1` while the motion stops, `Door:0` at rest, ready for cycle start.
            MachineState::Hold { stopped } if self.link.grbl.door.is_some() => {
                State::Door(u8::from(!stopped))
            }
            MachineState::Hold { stopped } => State::Hold(u8::from(!stopped)),
            MachineState::Paused | MachineState::Halted => State::Hold(0),
            MachineState::Homing => State::Home,
            MachineState::Alarm(_) => State::Alarm,
        };
        if matches!(state, State::Idle) {
            self.link.grbl.jogging = false;
        }
        let inches = self.settings.report_inches();
        let p = self.kernel.position();
        let commanded = self.kernel.commanded_position_nm();
        let machine: [Micrometres; N] =
            core::array::from_fn(|i| reported(micrometres(p.machine_mm[i]), inches));
        let offset = work_offset(&p.work_mm, &commanded).map(|um| reported(um, inches));
        let mask = self.settings.status_mask();
        let free_blocks = B.saturating_sub(self.kernel.planned_blocks()) as u16;
        let free_bytes = self.link.queue.free_bytes().min(READ_AHEAD_BYTES) as u16;
        let g = &mut self.link.grbl;
        let send_offset = g.reports_since_offset >= 10;
        g.reports_since_offset = if send_offset {
            0
        } else {
            g.reports_since_offset + 1
        };
        let send_overrides = !send_offset && g.reports_since_overrides >= 10;
        g.reports_since_overrides = if send_overrides {
            0
        } else {
            g.reports_since_overrides.saturating_add(1)
        };
        let (feed, rapid) = self.kernel.realtime_overrides();
        let overrides = [
            feed.min(255) as u8,
            rapid.min(255) as u8,
            self.devices.spindle_override(),
        ];
        let spindle = self.devices.spindle_output();
        let mut pins = Letters::new();
        for i in 0..N {
            if self.devices.parts.endstop(i) == Some(true) {
                pins.push(self.kernel.config().axes[i].letter);
            }
        }
        let mut accessories = Letters::new();
        match spindle {
            Some((Rotation::Clockwise, _)) => accessories.push(b'S'),
            Some((Rotation::CounterClockwise, _)) => accessories.push(b'C'),
            None => {}
        }
        let (mist, flood) = self.devices.coolant_state();
        if flood {
            accessories.push(b'F');
        }
        if mist {
            accessories.push(b'M');
        }
        let report = Status {
            state,
            machine: &machine,
            offset: &offset,
            work_position: mask & 1 == 0,
            send_offset,
            buffer: (mask & 2 != 0).then_some((free_blocks, free_bytes)),
            line: Some(self.kernel.current_line()),
            feed_mm_min: reported_rate(self.kernel.motion_now().speed_mm_min, inches),
            spindle_rpm: Some(spindle.map_or(0, |(_, rpm)| rpm)),
            overrides: send_overrides.then_some(overrides),
            pins: pins.as_bytes(),
            accessories: accessories.as_bytes(),
        };
        let mut buf = [0u8; 256];
        if let Ok(n) = report.encode(&mut buf) {
            let _ = out.write_all(buf.get(..n).unwrap_or(&[]));
        }
    }

    /// A refused line, in the grbl dialect: `error:N`.
    pub(super) fn grbl_refuse<W: Write>(&mut self, r: &Refusal, out: &mut W) {
        self.stats.refused = self.stats.refused.wrapping_add(1);
        say(out, &Message::Error(error_of(r.code)));
    }

    /// A fault that stopped the machine, in the grbl dialect: `ALARM:N` and the text.
    pub(super) fn grbl_fault<W: Write>(&mut self, r: &Refusal, out: &mut W) {
        say(out, &Message::Alarm(alarm_of(r.code)));
        say(out, &Message::Feedback(r.text()));
    }

    /// In check mode (`$C`), check `line` as the kernel would take it and answer it (`ok` or
    /// `error:N`) without running it: `true`. Out of check mode: `false`, the line runs.
    pub(super) fn grbl_check<W: Write>(&mut self, line: &Line<'_>, out: &mut W) -> bool {
        let Some(check) = self.check.as_mut() else {
            return false;
        };
        match check.line(line, |_| {}) {
            Ok(_) => self.ok(out),
            Err(e) => self.grbl_refuse(&Refusal::new(&e), out),
        }
        true
    }

    /// A `$` line: carried out and answered (`ok` or `error:N`, after what it reports).
    pub(super) fn grbl_command<W: Write>(&mut self, bytes: &[u8], out: &mut W) {
        self.enter_grbl();
        let answer = match Command::parse(bytes) {
            Ok(command) => self.run_command(command, out),
            Err(e) => Err(e),
        };
        match answer {
            Ok(Answer::Now) => say(out, &Message::Ok),
            Ok(Answer::Later) => {}
            Err(e) => {
                self.stats.refused = self.stats.refused.wrapping_add(1);
                say(out, &Message::Error(e));
            }
        }
    }

    fn run_command<W: Write>(
        &mut self,
        command: Command<'_>,
        out: &mut W,
    ) -> Result<Answer, Error> {
        let idle = self.kernel.is_idle() && !self.link.lines_held();
        match command {
            Command::Help => say(out, &Message::Help),
            Command::Settings => self.report_settings(out),
            Command::Parameters => self.report_parameters(out),
            Command::ParserState => self.report_parser_state(out),
            Command::BuildInfo => {
                say(
                    out,
                    &Message::Version {
                        build: "forja",
                        info: self.config.machine_type,
                    },
                );
                let options = Message::Options {
                    codes: "VN",
                    blocks: B as u16,
                    bytes: READ_AHEAD_BYTES as u16,
                };
                say(out, &options);
            }
            Command::StartupLines => {
                for index in 0..2 {
                    let line = self.settings.startup_line(index);
                    say(out, &Message::StartupLine { index, line });
                }
            }
            Command::CheckMode => {
                if !idle {
                    return Err(Error::IdleError);
                }
                let text = if self.check.take().is_some() {
                    "Disabled"
                } else {
                    let config = self.kernel.config();
                    self.check = Some(Preview::new(config, self.kernel.commanded_position_nm()));
                    "Enabled"
                };
                say(out, &Message::Feedback(text));
            }
            Command::Unlock => {
                if let MachineState::Alarm(KernelAlarm::EmergencyStop) = self.kernel.state() {
                    return Err(Error::InvalidInState);
                }
                if matches!(self.kernel.state(), MachineState::Alarm(_)) {
                    self.kernel.unlock();
                    say(out, &Message::Feedback("Caution: Unlocked"));
                }
            }
            Command::Home(axis) => {
                let mask = match axis {
                    None => self.homing_mask(),
                    Some(letter) => {
                        let i = self
                            .kernel
                            .config()
                            .axis_index(letter)
                            .ok_or(Error::InvalidStatement)?;
                        1u8 << i
                    }
                };
                if mask == 0 {
                    return Err(Error::SettingDisabled);
                }
                if !idle {
                    return Err(Error::IdleError);
                }
                self.kernel.home(mask).map_err(|e| error_of(e.code()))?;
                self.taken = true;
                // grbl answers `$H` when homing is done.
                self.link.held = Some(super::Held::Homing);
                return Ok(Answer::Later);
            }
            Command::Jog(text) => self.grbl_jog(text)?,
            Command::Restore(what) => {
                if !idle {
                    return Err(Error::IdleError);
                }
                if matches!(what, Restore::Settings | Restore::All) {
                    self.restore_settings()?;
                }
                if what == Restore::All {
                    self.store_grbl(Key::StartupLine(0), "")?;
                    self.store_grbl(Key::StartupLine(1), "")?;
                }
                if matches!(what, Restore::Parameters | Restore::All) {
                    self.kernel.reset_modal_state();
                    self.kernel.set_coordinates(Coordinates::ZERO);
                    self.coords_unsaved = Slot::all().fold(0, |m, s| m | 1 << s.index());
                }
                say(out, &Message::Feedback("Restoring defaults"));
            }
            Command::Sleep => {
                if !idle {
                    return Err(Error::IdleError);
                }
                let _ = self.devices.set_motors(false);
                self.kernel.emergency_stop();
                say(out, &Message::Feedback("Sleeping"));
            }
            Command::Set { number, value } => {
                if !idle {
                    return Err(Error::IdleError);
                }
                self.set_grbl_setting(number, value, out)?;
            }
            Command::SetStartupLine { index, line } => {
                if !idle {
                    return Err(Error::IdleError);
                }
                self.set_startup_line(index, line)?;
            }
        }
        Ok(Answer::Now)
    }

    /// `$N0=…`, `$N1=…`: store a startup line once it checks (run through a preview of the
    /// interpreter, as `$C` checks lines: nothing runs); empty, the line is cleared.
    fn set_startup_line(&mut self, index: u8, line: &[u8]) -> Result<(), Error> {
        if line.len() > MAX_STARTUP_LINE_LEN {
            return Err(Error::LineLengthExceeded);
        }
        let text = core::str::from_utf8(line).map_err(|_| Error::InvalidStatement)?;
        if !text.is_empty() {
            let (body, _) = strip_line_number(line);
            let parsed = Line::parse(body).map_err(|e| error_of(Refusal::new(&e).code))?;
            let mut check = Preview::new(self.kernel.config(), self.kernel.commanded_position_nm());
            check
                .line(&parsed, |_| {})
                .map_err(|e| error_of(e.code()))?;
        }
        self.store_grbl(Key::StartupLine(index), text)
    }

    /// The axes that home with `$H`.
    fn homing_mask(&self) -> u8 {
        let axes = &self.kernel.config().axes;
        axes.iter()
            .enumerate()
            .filter(|(_, a)| a.homing.is_some())
            .fold(0u8, |m, (i, _)| m | (1 << i))
    }

    /// `$J=…`: a jog, refused with grbl's errors when it is not one.
    fn grbl_jog(&mut self, text: &[u8]) -> Result<(), Error> {
        let line = Line::parse(text).map_err(|_| Error::InvalidJogCommand)?;
        if line.words().iter().any(|w| w.letter == b'M') || line.get(b'F').is_none() {
            return Err(Error::InvalidJogCommand);
        }
        if matches!(self.kernel.state(), MachineState::Alarm(_)) {
            return Err(Error::SystemGcLock);
        }
        match self.kernel.jog_line(&line) {
            Ok(KernelReply::Busy) => Err(Error::Overflow),
            Ok(_) => {
                self.link.grbl.jogging = true;
                self.taken = true;
                Ok(())
            }
            Err(CommandError::SoftLimit { .. } | CommandError::OutOfReach { .. }) => {
                Err(Error::TravelExceeded)
            }
            Err(e) => Err(error_of(e.code())),
        }
    }

    /// The settings under grbl's numbers, in grbl's order (`$24`, `$25`, `$27` only when an
    /// axis homes).
    fn grbl_settings(&self) -> impl Iterator<Item = (u16, GrblSetting)> + '_ {
        (0..).map_while(|index| self.grbl_setting(index))
    }

    /// The `index`-th of [`Self::grbl_settings`], `None` past the last. (One function that
    /// both `$$` and `$<n>=` call: an iterator of chained ranges would be inlined into each.)
    #[inline(never)]
    fn grbl_setting(&self, index: usize) -> Option<(u16, GrblSetting)> {
        const GLOBALS: [(u16, GrblSetting); 11] = [
            (10, GrblSetting::Stored(Key::StatusMask)),
            (11, GrblSetting::Stored(Key::JunctionDeviation)),
            (12, GrblSetting::Stored(Key::ArcTolerance)),
            (13, GrblSetting::Stored(Key::ReportInches)),
            (20, GrblSetting::Stored(Key::SoftLimits)),
            (21, GrblSetting::Stored(Key::HardLimits)),
            (22, GrblSetting::HomingEnable),
            (24, GrblSetting::Homing(AxisField::HomingLocate)),
            (25, GrblSetting::Homing(AxisField::HomingSeek)),
            (27, GrblSetting::Homing(AxisField::HomingPullOff)),
            (32, GrblSetting::Stored(Key::LaserMode)),
        ];
        let homes = self.homing_mask() != 0;
        let mut left = index;
        for &(number, setting) in &GLOBALS {
            if !homes && matches!(setting, GrblSetting::Homing(_)) {
                continue;
            }
            if left == 0 {
                return Some((number, setting));
            }
            left -= 1;
        }
        // Then `$100`+, `$110`+, `$120`+ and `$130`+, one per axis (ten at most).
        let axes = N.min(10);
        let (group, axis) = (left.checked_div(axes)?, left.checked_rem(axes)?);
        const AXES: [(u16, Option<AxisField>); 4] = [
            (100, Some(AxisField::StepsPerMm)),
            (110, Some(AxisField::MaxRate)),
            (120, Some(AxisField::Accel)),
            (130, None),
        ];
        let &(base, field) = AXES.get(group)?;
        let setting = match field {
            Some(field) => GrblSetting::Stored(Key::Axis { axis, field }),
            None => GrblSetting::Travel(axis),
        };
        Some((base + axis as u16, setting))
    }

    /// The keys of `field` of every axis that homes.
    fn homing_keys(&self, field: AxisField) -> impl Iterator<Item = Key> + '_ {
        let mask = self.homing_mask();
        (0..N)
            .filter(move |axis| mask & (1 << axis) != 0)
            .map(move |axis| Key::Axis { axis, field })
    }

    /// The value of a setting, as `$$` writes it.
    fn grbl_setting_value(&self, setting: GrblSetting) -> Decimal {
        let key = match setting {
            GrblSetting::Stored(key) => key,
            GrblSetting::Travel(axis) => {
                let m = self.settings.machine();
                return m.axes.get(axis).map_or(Decimal::ZERO, |a| {
                    Decimal::from_f32(a.max_mm - a.min_mm, 3).unwrap_or(Decimal::ZERO)
                });
            }
            GrblSetting::HomingEnable => {
                return Decimal::from_integer(i64::from(self.homing_mask() != 0));
            }
            GrblSetting::Homing(field) => match self.homing_keys(field).next() {
                Some(key) => key,
                None => return Decimal::ZERO,
            },
        };
        let m = self.settings.machine();
        let number = |v: f32| Decimal::from_f32(v, 3).unwrap_or(Decimal::ZERO);
        let flag = |on: bool| Decimal::from_integer(i64::from(on));
        match key {
            Key::StatusMask => Decimal::from_integer(i64::from(self.settings.status_mask())),
            Key::JunctionDeviation => number(m.junction_deviation_mm),
            Key::ArcTolerance => number(m.arc_tolerance_mm),
            Key::ReportInches => flag(self.settings.report_inches()),
            Key::SoftLimits => flag(m.soft_limits != SoftLimits::Off),
            Key::HardLimits => flag(m.hard_limits),
            Key::LaserMode => flag(self.settings.laser_mode()),
            Key::Axis { axis, field } => {
                let Some(a) = m.axes.get(axis) else {
                    return Decimal::ZERO;
                };
                number(field.value_of(a))
            }
            _ => Decimal::ZERO,
        }
    }

    /// `$$`.
    fn report_settings<W: Write>(&mut self, out: &mut W) {
        for (number, setting) in self.grbl_settings() {
            let value = self.grbl_setting_value(setting);
            say(out, &Message::Setting { number, value });
        }
    }

    /// `$<n>=<value>`.
    fn set_grbl_setting<W: Write>(
        &mut self,
        number: u16,
        value: Decimal,
        out: &mut W,
    ) -> Result<(), Error> {
        let (_, setting) = self
            .grbl_settings()
            .find(|(n, _)| *n == number)
            .ok_or(Error::InvalidStatement)?;
        if value.mantissa() < 0 {
            return Err(Error::NegativeValue);
        }
        // The value as written (a decimal, never through a float's formatting).
        let mut text = Text::<32>::new();
        let (key, text_value) = match setting {
            GrblSetting::Stored(
                key @ (Key::SoftLimits | Key::HardLimits | Key::ReportInches | Key::LaserMode),
            ) => {
                let on = value.as_integer().ok_or(Error::ValueOutOfRange)? != 0;
                let text = match (key, on) {
                    (Key::SoftLimits, false) => "off",
                    (Key::SoftLimits, true) => "homed",
                    (_, false) => "0",
                    (_, true) => "1",
                };
                return self.store_grbl(key, text);
            }
            GrblSetting::Stored(Key::StatusMask) => {
                let mask = value
                    .as_integer()
                    .and_then(|v| u8::try_from(v).ok())
                    .ok_or(Error::ValueOutOfRange)?;
                text.push_number(mask);
                return self.store_grbl(Key::StatusMask, text.as_str());
            }
            GrblSetting::HomingEnable => {
                let on = value.as_integer().ok_or(Error::ValueOutOfRange)? != 0;
                if on == (self.homing_mask() != 0) {
                    return Ok(());
                }
                say(
                    out,
                    &Message::Feedback("$22 follows the axes' homing in the machine configuration"),
                );
                return Err(Error::ValueOutOfRange);
            }
            GrblSetting::Homing(field) => {
                text.push_decimal(value);
                let mut keys = [Key::StatusMask; 8];
                let mut count = 0;
                for (slot, key) in keys.iter_mut().zip(self.homing_keys(field)) {
                    *slot = key;
                    count += 1;
                }
                let tick_hz = self.kernel.tick_hz();
                let timing = self.config.timing;
                self.settings
                    .set_all(
                        keys.get(..count).unwrap_or(&[]),
                        text.as_str(),
                        &mut self.storage,
                        &|m| {
                            m.validate()?;
                            m.validate_timing(tick_hz, timing)
                        },
                    )
                    .map_err(|_| Error::ValueOutOfRange)?;
                return self.give_kernel_settings();
            }
            GrblSetting::Stored(key) => (key, value),
            GrblSetting::Travel(axis) => {
                let min = self
                    .settings
                    .machine()
                    .axes
                    .get(axis)
                    .map_or(0.0, |a| a.min_mm);
                let key = Key::Axis {
                    axis,
                    field: AxisField::Max,
                };
                // In micrometres: the travel as written, the minimum as stored.
                let travel_um = value.round_to_scale(3).ok_or(Error::ValueOutOfRange)?;
                let min_um = libm::roundf(min * 1000.0) as i64;
                (key, Decimal::new(min_um.saturating_add(travel_um), 3))
            }
        };
        text.push_decimal(text_value);
        self.store_grbl(key, text.as_str())
    }

    /// Store `key` as frame 00 does, then give the kernel the planner settings it changed
    /// (steps, rates, accelerations, junction deviation take effect at once, as in grbl, and so
    /// do grbl's own `$10`, `$13`, `$32` and the startup lines; the travel, the limits, the arc
    /// tolerance and the homing settings at the next start).
    fn store_grbl(&mut self, key: Key, value: &str) -> Result<(), Error> {
        let mut name = Text::<24>::new();
        let _ = key.write_name(self.settings.machine(), &mut name);
        self.store_setting(name.as_str(), value)
            .map_err(|_| Error::ValueOutOfRange)?;
        self.give_kernel_settings()
    }

    /// The stored machine's planner settings to the kernel (at rest).
    fn give_kernel_settings(&mut self) -> Result<(), Error> {
        let machine = *self.settings.machine();
        let path = self.settings.path_limits();
        match self.kernel.set_planner_settings(&machine, path) {
            Ok(_) => Ok(()),
            Err(e) => Err(error_of(e.code())),
        }
    }

    /// `$RST=$`: every setting of the machine back to the board's defaults.
    fn restore_settings(&mut self) -> Result<(), Error> {
        self.settings
            .restore_defaults(&mut self.storage)
            .map_err(|_| Error::SettingReadFail)?;
        self.give_kernel_settings()
    }

    /// `0xA0`/`0xA1`: flood or mist on if off, off if on.
    fn toggle_coolant(&mut self, r: Realtime) {
        let flood = r == Realtime::FloodToggle;
        let (mist_on, flood_on) = self.devices.coolant_state();
        let on = if flood { !flood_on } else { !mist_on };
        let _ = self.devices.set_coolant_line(flood, on);
        // The next report carries the accessories (grbl sends `Ov:` and `A:` after a change).
        self.link.grbl.reports_since_overrides = u8::MAX;
    }

    /// `$#`.
    fn report_parameters<W: Write>(&mut self, out: &mut W) {
        let coords = *self.kernel.coordinates();
        let modal = self.kernel.modal_report();
        let inches = self.settings.report_inches();
        let um = |v: [Nm; N]| -> [Micrometres; N] {
            core::array::from_fn(|i| reported(nm_to_um(v[i]), inches))
        };
        let slots = SYSTEM_NAMES
            .iter()
            .zip(0u8..)
            .map(|(name, i)| (*name, Slot::System(i)))
            .chain([("G28", Slot::G28), ("G30", Slot::G30)]);
        for (name, slot) in slots {
            let position = um(coords.get(slot));
            say(
                out,
                &Message::Offset {
                    name,
                    position: &position,
                },
            );
        }
        let g92 = um(modal.g92_nm);
        say(
            out,
            &Message::Offset {
                name: "G92",
                position: &g92,
            },
        );
        say(
            out,
            &Message::ToolLengthOffset(reported(nm_to_um(modal.tool_length_nm), inches)),
        );
        let probe = self.kernel.probe_report();
        say(
            out,
            &Message::Probe {
                position: &um(probe.map_or([0; N], |p| p.machine_nm)),
                touched: probe.is_some_and(|p| p.tripped),
            },
        );
    }

    /// The outcome of a probing move that just ended: grbl's `[PRB:x,y,z:0|1]` (machine
    /// position); in the RepRap dialect an `echo:` line with the same.
    pub(super) fn report_probe<W: Write>(&mut self, probe: &ProbeReport<N>, out: &mut W) {
        let position: [Micrometres; N] = core::array::from_fn(|i| nm_to_um(probe.machine_nm[i]));
        if self.speaks_grbl() {
            let inches = self.settings.report_inches();
            say(
                out,
                &Message::Probe {
                    position: &position.map(|um| reported(um, inches)),
                    touched: probe.tripped,
                },
            );
            return;
        }
        let mut text = Text::<120>::new();
        text.push(if probe.tripped {
            "Probe: contact at"
        } else {
            "Probe: no contact, stopped at"
        });
        for (&letter, um) in self.letters().iter().zip(position) {
            text.push(" ").push_byte(letter).push(":");
            // Millimetres with three decimals, as the position in µm is exactly.
            text.push_decimal(Decimal::new(um, 3));
        }
        let _ = wire::reply(out, &forja_protocol::reply::Reply::Echo(text.as_str()));
    }

    /// `$G`.
    fn report_parser_state<W: Write>(&mut self, out: &mut W) {
        let mut text = Text::<96>::new();
        let m = self.kernel.modal_report();
        let spindle = self.devices.spindle_state();
        let spindle_mode = match spindle {
            Some((Rotation::Clockwise, _)) => 3,
            Some((Rotation::CounterClockwise, _)) => 4,
            None => 5,
        };
        text.push(m.motion).push(" ");
        text.push(
            SYSTEM_NAMES
                .get(usize::from(m.coordinate_system))
                .copied()
                .unwrap_or("G54"),
        );
        text.push(" G").push_number(m.plane);
        text.push(" G").push_number(if m.inches { 20 } else { 21 });
        text.push(" G")
            .push_number(if m.absolute { 90 } else { 91 });
        text.push(" G94 M").push_number(spindle_mode);
        text.push(" M9 T0 F").push_number(m.feed_mm_min as u32);
        text.push(" S")
            .push_number(spindle.map_or(0, |(_, rpm)| rpm));
        say(out, &Message::ParserState(text.as_str()));
    }
}
