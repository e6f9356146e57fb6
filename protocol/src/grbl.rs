//! grbl 1.1: the dialect every CNC sender speaks (CNCjs, bCNC, Universal G-code Sender,
//! Candle), as grbl 1.1's interface document and grblHAL's core define it.
//!
//! Three kinds of input share the link with the G-code lines:
//!
//! - **Realtime bytes** ([`Realtime`]): `?`, `!`, `~`, `0x18` and the extended set from `0x84`,
//!   taken out of the stream as they arrive, wherever they fall, never part of a line.
//! - **System commands** ([`Command`]): lines that start with `$` (`$$`, `$X`, `$H`, `$J=…`,
//!   `$110=5000`).
//! - **G-code lines**, answered `ok` or `error:N` ([`Error`]), exactly one answer a line.
//!
//! What the controller says back is a [`Message`]: `ok`, `error:N`, `ALARM:N`, the welcome
//! banner, the bracketed feedback lines (`[MSG:…]`, `[GC:…]`, `[PRB:…]`, …), settings lines
//! (`$110=5000.000`) and the status report (`<Idle|MPos:…|FS:…>`, [`Status`]).
//!
//! The numbers of [`Error`] and [`Alarm`] are grbl's: senders show the text of their own
//! tables for them. Where grblHAL added numbers (`error:39` and up, `ALARM:10` and up), they
//! are grblHAL's.

use crate::decimal::{Decimal, parse_prefix};
use crate::error::EncodeError;
use crate::write::{Cursor, Sink};

/// The version the banner and `$I` give: grbl 1.1's interface, as senders test it
/// (`Grbl 1.1h`: CNCjs and bCNC match `Grbl 1.1`, UGS any `Grbl 1.1x`).
pub const VERSION: &str = "1.1h";

/// A realtime command: one byte, acted on as it arrives.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Realtime {
    /// `0x18` (ctrl-x): stop at once, keep the position if the machine was at rest, greet again.
    SoftReset,
    /// `?`: send a status report.
    StatusReport,
    /// `~`: start or resume (after a feed hold, a door closed, a tool change).
    CycleStart,
    /// `!`: decelerate to a stop and hold.
    FeedHold,
    /// `0x84`: the safety door opened.
    SafetyDoor,
    /// `0x85`: cancel the jog in progress (and the jog lines queued).
    JogCancel,
    /// `0x90`–`0x94`: the feed override.
    FeedOverride(Step),
    /// `0x95`–`0x97`: the rapid override, percent (100, 50, 25).
    RapidOverride(u8),
    /// `0x99`–`0x9D`: the spindle speed override.
    SpindleOverride(Step),
    /// `0x9E`: stop the spindle during a hold (again: start it).
    SpindleStop,
    /// `0xA0`: flood coolant on or off.
    FloodToggle,
    /// `0xA1`: mist coolant on or off.
    MistToggle,
}

/// A change of a feed or spindle override.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Step {
    /// Back to 100 %.
    Reset,
    /// By this many percent (±10, ±1).
    By(i8),
}

impl Step {
    /// `percent` after this step, within `min..=max` (grbl: feed 10–200 %, spindle 10–200 %).
    pub fn apply(self, percent: u8, min: u8, max: u8) -> u8 {
        match self {
            Self::Reset => 100,
            Self::By(d) => {
                let changed = i16::from(percent) + i16::from(d);
                changed.clamp(i16::from(min), i16::from(max)) as u8
            }
        }
    }
}

impl Realtime {
    /// The command of `byte`, if it is one.
    pub const fn from_byte(byte: u8) -> Option<Self> {
        Some(match byte {
            0x18 => Self::SoftReset,
            b'?' => Self::StatusReport,
            b'~' => Self::CycleStart,
            b'!' => Self::FeedHold,
            0x84 => Self::SafetyDoor,
            0x85 => Self::JogCancel,
            0x90 => Self::FeedOverride(Step::Reset),
            0x91 => Self::FeedOverride(Step::By(10)),
            0x92 => Self::FeedOverride(Step::By(-10)),
            0x93 => Self::FeedOverride(Step::By(1)),
            0x94 => Self::FeedOverride(Step::By(-1)),
            0x95 => Self::RapidOverride(100),
            0x96 => Self::RapidOverride(50),
            0x97 => Self::RapidOverride(25),
            0x99 => Self::SpindleOverride(Step::Reset),
            0x9A => Self::SpindleOverride(Step::By(10)),
            0x9B => Self::SpindleOverride(Step::By(-10)),
            0x9C => Self::SpindleOverride(Step::By(1)),
            0x9D => Self::SpindleOverride(Step::By(-1)),
            0x9E => Self::SpindleStop,
            0xA0 => Self::FloodToggle,
            0xA1 => Self::MistToggle,
            _ => return None,
        })
    }

    /// The byte of this command (the inverse of [`Realtime::from_byte`]; a rapid override other
    /// than 100, 50 or 25 % is sent as 25 %).
    pub const fn byte(self) -> u8 {
        match self {
            Self::SoftReset => 0x18,
            Self::StatusReport => b'?',
            Self::CycleStart => b'~',
            Self::FeedHold => b'!',
            Self::SafetyDoor => 0x84,
            Self::JogCancel => 0x85,
            Self::FeedOverride(step) => 0x90 + step_offset(step),
            Self::RapidOverride(100) => 0x95,
            Self::RapidOverride(50) => 0x96,
            Self::RapidOverride(_) => 0x97,
            Self::SpindleOverride(step) => 0x99 + step_offset(step),
            Self::SpindleStop => 0x9E,
            Self::FloodToggle => 0xA0,
            Self::MistToggle => 0xA1,
        }
    }
}

/// The offset of `step` in its block of five override bytes.
const fn step_offset(step: Step) -> u8 {
    match step {
        Step::Reset => 0,
        Step::By(10) => 1,
        Step::By(-10) => 2,
        Step::By(d) if d > 0 => 3,
        Step::By(_) => 4,
    }
}

/// What `$RST=` restores.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Restore {
    /// `$RST=$`: the `$` settings, to their defaults.
    Settings,
    /// `$RST=#`: the work offsets and stored positions, to zero.
    Parameters,
    /// `$RST=*`: both, and the startup lines.
    All,
}

/// A system command: a line that starts with `$`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Command<'a> {
    /// `$`: the help line.
    Help,
    /// `$$`: every setting.
    Settings,
    /// `$#`: the work offsets, stored positions, tool length offset and last probe.
    Parameters,
    /// `$G`: the parser state (`[GC:…]`).
    ParserState,
    /// `$I`: the build information (`[VER:…]`, `[OPT:…]`).
    BuildInfo,
    /// `$N`: the startup lines.
    StartupLines,
    /// `$C`: check mode on or off (lines are parsed and answered, nothing moves).
    CheckMode,
    /// `$X`: leave an alarm without homing.
    Unlock,
    /// `$H`: home every axis; `$HX`, `$HY` …: that axis alone (grblHAL).
    Home(Option<u8>),
    /// `$J=<G-code>`: a jog, its text after `=`.
    Jog(&'a [u8]),
    /// `$RST=…`.
    Restore(Restore),
    /// `$SLP`: sleep (motors off, alarm-locked until reset).
    Sleep,
    /// `$<n>=<value>`: set a setting.
    Set {
        /// The setting's number.
        number: u16,
        /// Its value, as written.
        value: Decimal,
    },
    /// `$N<n>=<line>`: set a startup line (0 or 1).
    SetStartupLine {
        /// Which.
        index: u8,
        /// The G-code line.
        line: &'a [u8],
    },
}

impl<'a> Command<'a> {
    /// Parse a `$` line (its terminator already stripped). Spaces are ignored as grbl ignores
    /// them, except inside a jog's or startup line's text, which is passed on as written.
    ///
    /// Errors: [`Error::InvalidStatement`] for what is no system command (`$Q`, `$H5`),
    /// [`Error::BadNumberFormat`] for a setting value that is no number,
    /// [`Error::ExpectedCommandLetter`] for a line that does not start with `$`.
    pub fn parse(line: &'a [u8]) -> Result<Self, Error> {
        let rest = match line.split_first() {
            Some((b'$', rest)) => rest,
            _ => return Err(Error::ExpectedCommandLetter),
        };
        // The text of `$J=` and `$N0=` is a G-code line: kept whole.
        if let Some(text) = strip_prefix_ci(rest, b"J=") {
            return Ok(Self::Jog(text));
        }
        // Room for the longest setting `$$` writes: a 5-digit number, `=`, and an `i64`
        // mantissa with its sign, point and leading `0.` (`$42412=0.424241291` is 17).
        let mut compact = [0u8; 32];
        let mut len = 0;
        for &b in rest.iter().filter(|b| **b != b' ') {
            if b == b'=' && matches!(compact.first(), Some(b'N' | b'n')) {
                break;
            }
            let slot = compact.get_mut(len).ok_or(Error::InvalidStatement)?;
            *slot = b.to_ascii_uppercase();
            len += 1;
        }
        let word = compact.get(..len).unwrap_or(&[]);
        Ok(match word {
            b"" => Self::Help,
            b"$" => Self::Settings,
            b"#" => Self::Parameters,
            b"G" => Self::ParserState,
            b"I" => Self::BuildInfo,
            b"N" => Self::StartupLines,
            b"C" => Self::CheckMode,
            b"X" => Self::Unlock,
            b"H" => Self::Home(None),
            b"SLP" => Self::Sleep,
            b"RST=$" => Self::Restore(Restore::Settings),
            b"RST=#" => Self::Restore(Restore::Parameters),
            b"RST=*" => Self::Restore(Restore::All),
            [b'H', axis] if axis.is_ascii_uppercase() => Self::Home(Some(*axis)),
            [b'N', digit] if matches!(digit, b'0' | b'1') => {
                let text = rest
                    .iter()
                    .position(|b| *b == b'=')
                    .and_then(|at| rest.get(at + 1..))
                    .ok_or(Error::InvalidStatement)?;
                Self::SetStartupLine {
                    index: digit - b'0',
                    line: text,
                }
            }
            [first, ..] if first.is_ascii_digit() => {
                let at = word
                    .iter()
                    .position(|b| *b == b'=')
                    .ok_or(Error::InvalidStatement)?;
                let (number, value) = (word.get(..at).unwrap_or(&[]), word.get(at + 1..));
                let number = parse_u16(number).ok_or(Error::InvalidStatement)?;
                let value = value.unwrap_or(&[]);
                let (value, used) = parse_prefix(value).map_err(|_| Error::BadNumberFormat)?;
                if used != word.len() - at - 1 {
                    return Err(Error::BadNumberFormat);
                }
                Self::Set { number, value }
            }
            _ => return Err(Error::InvalidStatement),
        })
    }
}

/// `text` without `prefix` (compared without regard to case), if it starts with it.
fn strip_prefix_ci<'t>(text: &'t [u8], prefix: &[u8]) -> Option<&'t [u8]> {
    let head = text.get(..prefix.len())?;
    head.eq_ignore_ascii_case(prefix)
        .then(|| text.get(prefix.len()..))
        .flatten()
}

/// `digits` as a `u16`: one to five ASCII digits.
fn parse_u16(digits: &[u8]) -> Option<u16> {
    if digits.is_empty() || digits.len() > 5 {
        return None;
    }
    let mut value: u32 = 0;
    for d in digits {
        if !d.is_ascii_digit() {
            return None;
        }
        value = value * 10 + u32::from(d - b'0');
    }
    u16::try_from(value).ok()
}

/// An `error:N` of grbl 1.1 (1–38) and grblHAL (39 and up): why a line was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Error {
    /// 1: a word without its letter.
    ExpectedCommandLetter,
    /// 2: a number that does not read, or a value missing.
    BadNumberFormat,
    /// 3: a `$` command grbl does not have.
    InvalidStatement,
    /// 4: a negative value where it cannot be.
    NegativeValue,
    /// 5: homing is not enabled (`$22`).
    SettingDisabled,
    /// 6: a step pulse shorter than 3 µs.
    SettingStepPulseMin,
    /// 7: the settings could not be read: defaults restored.
    SettingReadFail,
    /// 8: a `$` command that needs the machine at rest.
    IdleError,
    /// 9: G-code is locked out during an alarm or a jog.
    SystemGcLock,
    /// 10: soft limits need homing.
    SoftLimitError,
    /// 11: a line longer than the receive buffer.
    Overflow,
    /// 12: a setting that would step faster than the step generator can.
    MaxStepRateExceeded,
    /// 13: the safety door is open.
    CheckDoor,
    /// 14: a startup line longer than it may be.
    LineLengthExceeded,
    /// 15: a jog beyond the machine's travel.
    TravelExceeded,
    /// 16: a jog that is not a `G0`/`G1`-like target with a feed.
    InvalidJogCommand,
    /// 17: laser mode needs a PWM spindle.
    SettingDisabledLaser,
    /// 20: a G or M command this firmware does not have.
    UnsupportedCommand,
    /// 21: two commands of one modal group.
    ModalGroupViolation,
    /// 22: a feed move without a feed rate.
    UndefinedFeedRate,
    /// 23: a value that must be an integer.
    CommandValueNotInteger,
    /// 24: two commands that both use the axis words.
    AxisCommandConflict,
    /// 25: a word given twice.
    WordRepeated,
    /// 26: a motion without an axis word.
    NoAxisWords,
    /// 27: a line number out of range.
    InvalidLineNumber,
    /// 28: a word the command needs is missing.
    ValueWordMissing,
    /// 29: work coordinate systems G59.1–G59.3.
    UnsupportedCoordSys,
    /// 30: `G53` without `G0` or `G1`.
    G53InvalidMotionMode,
    /// 31: axis words no command uses.
    AxisWordsExist,
    /// 32: an arc without an axis word in its plane.
    NoAxisWordsInPlane,
    /// 33: a motion target that cannot be reached (an arc's end off its circle).
    InvalidTarget,
    /// 34: an arc radius that does not fit.
    ArcRadiusError,
    /// 35: an arc without an offset in its plane.
    NoOffsetsInPlane,
    /// 36: value words no command uses.
    UnusedWords,
    /// 37: a dynamic tool length offset on an axis other than Z.
    G43DynamicAxisError,
    /// 38: a tool number beyond the largest.
    MaxValueExceeded,
    /// 39 (grblHAL): a value out of its range.
    ValueOutOfRange,
    /// 60 (grblHAL): the SD card failed to mount.
    SdMountError,
    /// 62 (grblHAL): the file was not found or could not be read.
    SdFailedOpen,
    /// 64 (grblHAL): a file is already running.
    SdFileBusy,
    /// 79 (grblHAL): a command not allowed in this state.
    InvalidInState,
}

impl Error {
    /// The number after `error:`.
    pub const fn code(self) -> u8 {
        match self {
            Self::ExpectedCommandLetter => 1,
            Self::BadNumberFormat => 2,
            Self::InvalidStatement => 3,
            Self::NegativeValue => 4,
            Self::SettingDisabled => 5,
            Self::SettingStepPulseMin => 6,
            Self::SettingReadFail => 7,
            Self::IdleError => 8,
            Self::SystemGcLock => 9,
            Self::SoftLimitError => 10,
            Self::Overflow => 11,
            Self::MaxStepRateExceeded => 12,
            Self::CheckDoor => 13,
            Self::LineLengthExceeded => 14,
            Self::TravelExceeded => 15,
            Self::InvalidJogCommand => 16,
            Self::SettingDisabledLaser => 17,
            Self::UnsupportedCommand => 20,
            Self::ModalGroupViolation => 21,
            Self::UndefinedFeedRate => 22,
            Self::CommandValueNotInteger => 23,
            Self::AxisCommandConflict => 24,
            Self::WordRepeated => 25,
            Self::NoAxisWords => 26,
            Self::InvalidLineNumber => 27,
            Self::ValueWordMissing => 28,
            Self::UnsupportedCoordSys => 29,
            Self::G53InvalidMotionMode => 30,
            Self::AxisWordsExist => 31,
            Self::NoAxisWordsInPlane => 32,
            Self::InvalidTarget => 33,
            Self::ArcRadiusError => 34,
            Self::NoOffsetsInPlane => 35,
            Self::UnusedWords => 36,
            Self::G43DynamicAxisError => 37,
            Self::MaxValueExceeded => 38,
            Self::ValueOutOfRange => 39,
            Self::SdMountError => 60,
            Self::SdFailedOpen => 62,
            Self::SdFileBusy => 64,
            Self::InvalidInState => 79,
        }
    }
}

/// An `ALARM:N`: why the machine stopped and locked (grbl 1.1's 1–9, grblHAL's 10 and up).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Alarm {
    /// 1: a limit switch tripped while moving; the position may be lost.
    HardLimit,
    /// 2: a target beyond the machine's travel (soft limits).
    SoftLimit,
    /// 3: reset while moving; the position may be lost.
    AbortCycle,
    /// 4: the probe was already triggered before the probing move.
    ProbeFailInitial,
    /// 5: the probing move ended without contact.
    ProbeFailContact,
    /// 6: homing was reset.
    HomingFailReset,
    /// 7: the safety door opened during homing.
    HomingFailDoor,
    /// 8: the pull-off did not clear the switch.
    HomingFailPulloff,
    /// 9: the switch was not found within the search distance.
    HomingFailApproach,
    /// 10 (grblHAL): the emergency stop.
    EStop,
    /// 11 (grblHAL): homing is required before moving.
    HomingRequired,
    /// 13 (grblHAL): a motor driver reported a fault.
    MotorFault,
}

impl Alarm {
    /// The number after `ALARM:`.
    pub const fn code(self) -> u8 {
        match self {
            Self::HardLimit => 1,
            Self::SoftLimit => 2,
            Self::AbortCycle => 3,
            Self::ProbeFailInitial => 4,
            Self::ProbeFailContact => 5,
            Self::HomingFailReset => 6,
            Self::HomingFailDoor => 7,
            Self::HomingFailPulloff => 8,
            Self::HomingFailApproach => 9,
            Self::EStop => 10,
            Self::HomingRequired => 11,
            Self::MotorFault => 13,
        }
    }
}

/// The machine state at the head of a status report.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum State {
    /// At rest, ready.
    Idle,
    /// Running motion.
    Run,
    /// Held: `Hold:0` complete (at rest), `Hold:1` still decelerating.
    Hold(u8),
    /// Jogging.
    Jog,
    /// Alarm-locked.
    Alarm,
    /// The safety door: `Door:0` closed and ready to resume, `1` stopping, `2` open, `3`
    /// closed and restoring.
    Door(u8),
    /// Check mode (`$C`).
    Check,
    /// Homing.
    Home,
    /// Asleep (`$SLP`).
    Sleep,
    /// Waiting for a tool change (grblHAL).
    Tool,
}

impl State {
    fn write<S: Sink>(self, out: &mut S) -> Result<(), EncodeError> {
        let (name, sub): (&[u8], Option<u8>) = match self {
            Self::Idle => (b"Idle", None),
            Self::Run => (b"Run", None),
            Self::Hold(s) => (b"Hold", Some(s)),
            Self::Jog => (b"Jog", None),
            Self::Alarm => (b"Alarm", None),
            Self::Door(s) => (b"Door", Some(s)),
            Self::Check => (b"Check", None),
            Self::Home => (b"Home", None),
            Self::Sleep => (b"Sleep", None),
            Self::Tool => (b"Tool", None),
        };
        out.put_all(name)?;
        if let Some(s) = sub {
            out.put(b':')?;
            out.put_u64(u64::from(s))?;
        }
        Ok(())
    }
}

/// Micrometres: the unit of every position in grbl's messages (written in mm with three
/// decimals).
pub type Micrometres = i64;

/// Write `values` as `x.xxx,y.yyy,…`.
fn put_positions<S: Sink>(out: &mut S, values: &[Micrometres]) -> Result<(), EncodeError> {
    for (i, v) in values.iter().enumerate() {
        if i > 0 {
            out.put(b',')?;
        }
        Decimal::new(*v, 3).write(out)?;
    }
    Ok(())
}

/// A status report, `<State|MPos:…|Bf:…|Ln:…|FS:…|WCO:…|Ov:…|Pn:…|A:…>`: what a sender shows
/// of the machine. Which optional fields go out is the controller's choice (`$10`, and grbl's
/// rule of sending `WCO` and `Ov` only every so many reports).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Status<'a> {
    /// The state.
    pub state: State,
    /// The machine position, µm, one per axis.
    pub machine: &'a [Micrometres],
    /// The work coordinate offset, µm, one per axis: with `work_position` it is subtracted
    /// from `machine` to give `WPos`; sent as `WCO` when `send_offset`.
    pub offset: &'a [Micrometres],
    /// `WPos` (the work position) instead of `MPos`.
    pub work_position: bool,
    /// Send `WCO`.
    pub send_offset: bool,
    /// `Bf:<blocks free>,<bytes free>`, if sent.
    pub buffer: Option<(u16, u16)>,
    /// `Ln:<line number>` of the block running, if sent.
    pub line: Option<u32>,
    /// The feed rate now, mm/min.
    pub feed_mm_min: u32,
    /// The spindle speed, rpm: `FS:<feed>,<speed>` when `Some`, `F:<feed>` when `None`.
    pub spindle_rpm: Option<u32>,
    /// `Ov:<feed>,<rapid>,<spindle>` percent, if sent.
    pub overrides: Option<[u8; 3]>,
    /// `Pn:<letters>`: the inputs active (`X`, `Y`, `Z`, `P` probe, `D` door, `H` hold, `R`
    /// reset, `S` start); nothing sent when empty.
    pub pins: &'a [u8],
    /// `A:<letters>`: the accessories on (`S` spindle clockwise, `C` counter-clockwise, `F`
    /// flood, `M` mist); sent with the overrides, as grbl does.
    pub accessories: &'a [u8],
}

impl Status<'_> {
    /// Write the report, `\n` included, into `out`; its length.
    ///
    /// Errors: [`EncodeError::BufferTooSmall`]; [`EncodeError::InvalidText`] for a pin or
    /// accessory that is not an upper-case letter.
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, EncodeError> {
        let mut w = Cursor::new(out);
        let letters = |t: &[u8]| t.iter().all(u8::is_ascii_uppercase);
        if !letters(self.pins) || !letters(self.accessories) {
            return Err(EncodeError::InvalidText);
        }
        w.put(b'<')?;
        self.state.write(&mut w)?;
        if self.work_position {
            w.put_all(b"|WPos:")?;
            for (i, m) in self.machine.iter().enumerate() {
                if i > 0 {
                    w.put(b',')?;
                }
                let o = self.offset.get(i).copied().unwrap_or(0);
                Decimal::new(m.saturating_sub(o), 3).write(&mut w)?;
            }
        } else {
            w.put_all(b"|MPos:")?;
            put_positions(&mut w, self.machine)?;
        }
        if let Some((blocks, bytes)) = self.buffer {
            w.put_all(b"|Bf:")?;
            w.put_u64(u64::from(blocks))?;
            w.put(b',')?;
            w.put_u64(u64::from(bytes))?;
        }
        if let Some(line) = self.line {
            w.put_all(b"|Ln:")?;
            w.put_u64(u64::from(line))?;
        }
        match self.spindle_rpm {
            Some(rpm) => {
                w.put_all(b"|FS:")?;
                w.put_u64(u64::from(self.feed_mm_min))?;
                w.put(b',')?;
                w.put_u64(u64::from(rpm))?;
            }
            None => {
                w.put_all(b"|F:")?;
                w.put_u64(u64::from(self.feed_mm_min))?;
            }
        }
        if !self.pins.is_empty() {
            w.put_all(b"|Pn:")?;
            w.put_all(self.pins)?;
        }
        if self.send_offset {
            w.put_all(b"|WCO:")?;
            put_positions(&mut w, self.offset)?;
        }
        if let Some([feed, rapid, spindle]) = self.overrides {
            w.put_all(b"|Ov:")?;
            for (i, v) in [feed, rapid, spindle].into_iter().enumerate() {
                if i > 0 {
                    w.put(b',')?;
                }
                w.put_u64(u64::from(v))?;
            }
            if !self.accessories.is_empty() {
                w.put_all(b"|A:")?;
                w.put_all(self.accessories)?;
            }
        }
        w.put_all(b">\n")?;
        Ok(w.len())
    }
}

/// A status report read back as text (a sender's view, and the tests'): its state and its
/// `name:value` fields.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StatusText<'a> {
    inner: &'a [u8],
}

impl<'a> StatusText<'a> {
    /// The report of `line` (terminator stripped), if it is `<…>`.
    pub fn parse(line: &'a [u8]) -> Option<Self> {
        let inner = line.strip_prefix(b"<")?.strip_suffix(b">")?;
        Some(Self { inner })
    }

    /// The state, as written (`Idle`, `Hold:0`).
    pub fn state(&self) -> &'a [u8] {
        self.inner.split(|b| *b == b'|').next().unwrap_or(&[])
    }

    /// Each field after the state, as `(name, value)`, in order.
    pub fn fields(&self) -> impl Iterator<Item = (&'a [u8], &'a [u8])> + 'a {
        self.inner.split(|b| *b == b'|').skip(1).map(|field| {
            match field.iter().position(|b| *b == b':') {
                Some(at) => (
                    field.get(..at).unwrap_or(&[]),
                    field.get(at + 1..).unwrap_or(&[]),
                ),
                None => (field, &[][..]),
            }
        })
    }

    /// The value of the field `name`, if the report has it.
    pub fn field(&self, name: &[u8]) -> Option<&'a [u8]> {
        self.fields().find(|(n, _)| *n == name).map(|(_, v)| v)
    }
}

/// A line the controller sends in the grbl dialect, other than a [`Status`] report.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Message<'a> {
    /// `ok`.
    Ok,
    /// `error:N`.
    Error(Error),
    /// `ALARM:N`.
    Alarm(Alarm),
    /// The banner after a reset: `Grbl 1.1h ['$' for help]`.
    Welcome,
    /// `[MSG:<text>]`: a message for the operator.
    Feedback(&'a str),
    /// `[HLP:…]`, the answer to `$`.
    Help,
    /// `[GC:<modal words>]`, the answer to `$G`.
    ParserState(&'a str),
    /// `[VER:1.1h.<build>:<text>]`, the first line of `$I`.
    Version {
        /// The build's name (a date in grbl).
        build: &'a str,
        /// The build info string set with `$I=`.
        info: &'a str,
    },
    /// `[OPT:<codes>,<blocks>,<bytes>]`, the second line of `$I`.
    Options {
        /// The option letters (`V` variable spindle, `N` line numbers, `M` mist, …).
        codes: &'a str,
        /// Planner blocks.
        blocks: u16,
        /// Receive buffer bytes.
        bytes: u16,
    },
    /// `[echo:<line>]`.
    Echo(&'a str),
    /// `$<n>=<value>`: one setting, from `$$`.
    Setting {
        /// Its number.
        number: u16,
        /// Its value.
        value: Decimal,
    },
    /// `$N<n>=<line>`: one startup line, from `$N`.
    StartupLine {
        /// Which.
        index: u8,
        /// The line.
        line: &'a str,
    },
    /// `[<name>:x,y,z]`: a work offset (`G54`…`G59`), a stored position (`G28`, `G30`) or
    /// `G92`, from `$#`.
    Offset {
        /// `G54`, `G28`, `G92` …
        name: &'a str,
        /// The position, µm, one per axis.
        position: &'a [Micrometres],
    },
    /// `[TLO:<z>]`: the tool length offset, µm.
    ToolLengthOffset(Micrometres),
    /// `[PRB:x,y,z:<0|1>]`: the last probe's position (machine, µm) and whether it touched.
    Probe {
        /// Where the probe stopped.
        position: &'a [Micrometres],
        /// Whether it made contact.
        touched: bool,
    },
}

/// `t` as bytes if it can go in a message: printable ASCII without `]` (it would end a
/// bracketed line early).
fn text(t: &str) -> Result<&[u8], EncodeError> {
    if t.bytes().all(|b| (b' '..=b'~').contains(&b) && b != b']') {
        Ok(t.as_bytes())
    } else {
        Err(EncodeError::InvalidText)
    }
}

/// The text of `$`'s help line, grbl 1.1's commands.
const HELP: &[u8] = b"[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]";

impl Message<'_> {
    /// Write the line, `\n` included, into `out`; its length.
    ///
    /// Errors: [`EncodeError::BufferTooSmall`]; [`EncodeError::InvalidText`] for a text that is
    /// not printable ASCII or holds `]` (it would end the bracket early).
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, EncodeError> {
        let mut w = Cursor::new(out);
        match *self {
            Self::Ok => w.put_all(b"ok")?,
            Self::Error(e) => {
                w.put_all(b"error:")?;
                w.put_u64(u64::from(e.code()))?;
            }
            Self::Alarm(a) => {
                w.put_all(b"ALARM:")?;
                w.put_u64(u64::from(a.code()))?;
            }
            Self::Welcome => {
                w.put_all(b"Grbl ")?;
                w.put_all(VERSION.as_bytes())?;
                w.put_all(b" ['$' for help]")?;
            }
            Self::Feedback(t) => {
                w.put_all(b"[MSG:")?;
                w.put_all(text(t)?)?;
                w.put(b']')?;
            }
            Self::Help => w.put_all(HELP)?,
            Self::ParserState(t) => {
                w.put_all(b"[GC:")?;
                w.put_all(text(t)?)?;
                w.put(b']')?;
            }
            Self::Version { build, info } => {
                w.put_all(b"[VER:")?;
                w.put_all(VERSION.as_bytes())?;
                w.put(b'.')?;
                w.put_all(text(build)?)?;
                w.put(b':')?;
                w.put_all(text(info)?)?;
                w.put(b']')?;
            }
            Self::Options {
                codes,
                blocks,
                bytes,
            } => {
                w.put_all(b"[OPT:")?;
                w.put_all(text(codes)?)?;
                w.put(b',')?;
                w.put_u64(u64::from(blocks))?;
                w.put(b',')?;
                w.put_u64(u64::from(bytes))?;
                w.put(b']')?;
            }
            Self::Echo(t) => {
                w.put_all(b"[echo:")?;
                w.put_all(text(t)?)?;
                w.put(b']')?;
            }
            Self::Setting { number, value } => {
                w.put(b'$')?;
                w.put_u64(u64::from(number))?;
                w.put(b'=')?;
                value.write(&mut w)?;
            }
            Self::StartupLine { index, line } => {
                w.put_all(b"$N")?;
                w.put_u64(u64::from(index))?;
                w.put(b'=')?;
                w.put_all(text(line)?)?;
            }
            Self::Offset { name, position } => {
                w.put(b'[')?;
                w.put_all(text(name)?)?;
                w.put(b':')?;
                put_positions(&mut w, position)?;
                w.put(b']')?;
            }
            Self::ToolLengthOffset(z) => {
                w.put_all(b"[TLO:")?;
                Decimal::new(z, 3).write(&mut w)?;
                w.put(b']')?;
            }
            Self::Probe { position, touched } => {
                w.put_all(b"[PRB:")?;
                put_positions(&mut w, position)?;
                w.put_all(if touched { b":1]" } else { b":0]" })?;
            }
        }
        w.put(b'\n')?;
        Ok(w.len())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic, clippy::indexing_slicing)]
mod tests {
    extern crate std;
    use std::string::String;

    use super::*;

    #[test]
    fn a_setting_as_dollar_dollar_writes_it_parses_back_even_when_longer_than_typed() {
        // Found by the `grbl` fuzz target: `.424241291` is written `0.424241291`.
        let typed = Command::parse(b"$42412=.424241291").unwrap();
        let Command::Set { number, value } = typed else {
            panic!("{typed:?}");
        };
        let mut out = [0u8; 64];
        let n = Message::Setting { number, value }.encode(&mut out).unwrap();
        assert_eq!(Command::parse(&out[..n - 1]), Ok(typed));
        let widest = Command::parse(b"$65535=-0.000000000000000001").unwrap();
        assert!(matches!(widest, Command::Set { number: 65535, .. }));
    }

    fn text(encoded: Result<usize, EncodeError>, buf: &[u8]) -> String {
        let n = encoded.expect("encodes");
        String::from_utf8(buf[..n].to_vec()).expect("ASCII")
    }

    #[test]
    fn every_realtime_byte_round_trips() {
        let mut seen = 0;
        for b in 0..=255u8 {
            if let Some(r) = Realtime::from_byte(b) {
                assert_eq!(r.byte(), b, "{r:?}");
                seen += 1;
            }
        }
        assert_eq!(seen, 22);
        assert_eq!(Realtime::from_byte(b'G'), None);
        assert_eq!(Realtime::from_byte(b'\n'), None);
    }

    #[test]
    fn overrides_step_within_their_bounds() {
        assert_eq!(Step::By(10).apply(100, 10, 200), 110);
        assert_eq!(Step::By(10).apply(195, 10, 200), 200);
        assert_eq!(Step::By(-10).apply(15, 10, 200), 10);
        assert_eq!(Step::By(-1).apply(100, 10, 200), 99);
        assert_eq!(Step::Reset.apply(37, 10, 200), 100);
    }

    #[test]
    fn system_commands_parse_as_grbl_reads_them() {
        fn ok(t: &str) -> Command<'_> {
            Command::parse(t.as_bytes()).unwrap()
        }
        assert_eq!(ok("$"), Command::Help);
        assert_eq!(ok("$$"), Command::Settings);
        assert_eq!(ok("$#"), Command::Parameters);
        assert_eq!(ok("$g"), Command::ParserState);
        assert_eq!(ok("$I"), Command::BuildInfo);
        assert_eq!(ok("$N"), Command::StartupLines);
        assert_eq!(ok("$C"), Command::CheckMode);
        assert_eq!(ok("$X"), Command::Unlock);
        assert_eq!(ok("$H"), Command::Home(None));
        assert_eq!(ok("$HZ"), Command::Home(Some(b'Z')));
        assert_eq!(ok("$SLP"), Command::Sleep);
        assert_eq!(ok("$RST=#"), Command::Restore(Restore::Parameters));
        assert_eq!(ok("$RST=*"), Command::Restore(Restore::All));
        assert_eq!(ok("$J=G91 G21 X10 F500"), Command::Jog(b"G91 G21 X10 F500"));
        assert_eq!(
            ok("$110 = 5000.5"),
            Command::Set {
                number: 110,
                value: Decimal::new(50005, 1)
            }
        );
        assert_eq!(
            ok("$N0=G21 G90"),
            Command::SetStartupLine {
                index: 0,
                line: b"G21 G90"
            }
        );
        for bad in ["$Q", "$H5", "$RST=", "$N2=G0", "$100", "$99999999999=1"] {
            assert_eq!(
                Command::parse(bad.as_bytes()),
                Err(Error::InvalidStatement),
                "{bad}"
            );
        }
        assert_eq!(Command::parse(b"$100=x"), Err(Error::BadNumberFormat));
        assert_eq!(Command::parse(b"$100=1.5.5"), Err(Error::BadNumberFormat));
        assert_eq!(Command::parse(b"G0"), Err(Error::ExpectedCommandLetter));
    }

    #[test]
    fn a_status_report_has_the_fields_senders_read() {
        let mut buf = [0u8; 160];
        let report = Status {
            state: State::Hold(1),
            machine: &[10_000, -2_500, 0],
            offset: &[1_000, 0, -500],
            work_position: false,
            send_offset: true,
            buffer: Some((15, 128)),
            line: Some(42),
            feed_mm_min: 500,
            spindle_rpm: Some(12_000),
            overrides: Some([110, 100, 90]),
            pins: b"XP",
            accessories: b"SF",
        };
        let t = text(report.encode(&mut buf), &buf);
        assert_eq!(
            t,
            "<Hold:1|MPos:10.000,-2.500,0.000|Bf:15,128|Ln:42|FS:500,12000|Pn:XP|WCO:1.000,0.000,-0.500|Ov:110,100,90|A:SF>\n"
        );
        let read = StatusText::parse(t.trim_end().as_bytes()).unwrap();
        assert_eq!(read.state(), b"Hold:1");
        assert_eq!(read.fields().count(), 8);
        assert_eq!(read.field(b"Bf"), Some(&b"15,128"[..]));
        assert_eq!(read.field(b"WPos"), None);
        let work = Status {
            work_position: true,
            send_offset: false,
            buffer: None,
            line: None,
            spindle_rpm: None,
            overrides: None,
            pins: b"",
            ..report
        };
        let t = text(work.encode(&mut buf), &buf);
        assert_eq!(t, "<Hold:1|WPos:9.000,-2.500,0.500|F:500>\n");
        let bad = Status {
            pins: b"x",
            ..report
        };
        assert_eq!(bad.encode(&mut buf), Err(EncodeError::InvalidText));
        assert_eq!(
            report.encode(&mut [0u8; 20]),
            Err(EncodeError::BufferTooSmall)
        );
    }

    #[test]
    fn messages_are_written_as_grbl_writes_them() {
        let mut buf = [0u8; 128];
        let mut say = |m: Message<'_>| text(m.encode(&mut buf), &buf);
        assert_eq!(say(Message::Ok), "ok\n");
        assert_eq!(say(Message::Error(Error::UnsupportedCommand)), "error:20\n");
        assert_eq!(say(Message::Alarm(Alarm::ProbeFailContact)), "ALARM:5\n");
        assert_eq!(say(Message::Welcome), "Grbl 1.1h ['$' for help]\n");
        assert_eq!(
            say(Message::Feedback("Caution: Unlocked")),
            "[MSG:Caution: Unlocked]\n"
        );
        assert_eq!(
            say(Message::ParserState(
                "G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0"
            )),
            "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\n"
        );
        assert_eq!(
            say(Message::Version {
                build: "forja",
                info: ""
            }),
            "[VER:1.1h.forja:]\n"
        );
        assert_eq!(
            say(Message::Options {
                codes: "VNM",
                blocks: 15,
                bytes: 128
            }),
            "[OPT:VNM,15,128]\n"
        );
        assert_eq!(
            say(Message::Setting {
                number: 110,
                value: Decimal::new(5_000_000, 3)
            }),
            "$110=5000.000\n"
        );
        assert_eq!(
            say(Message::Offset {
                name: "G54",
                position: &[-1_000, 0, 12_345]
            }),
            "[G54:-1.000,0.000,12.345]\n"
        );
        assert_eq!(
            say(Message::Probe {
                position: &[0, 0, -4_321],
                touched: true
            }),
            "[PRB:0.000,0.000,-4.321:1]\n"
        );
        assert_eq!(say(Message::ToolLengthOffset(1_500)), "[TLO:1.500]\n");
        assert_eq!(
            Message::Feedback("a]b").encode(&mut [0u8; 32]),
            Err(EncodeError::InvalidText)
        );
    }

    #[test]
    fn error_and_alarm_numbers_are_grbls() {
        assert_eq!(Error::ExpectedCommandLetter.code(), 1);
        assert_eq!(Error::IdleError.code(), 8);
        assert_eq!(Error::SystemGcLock.code(), 9);
        assert_eq!(Error::InvalidJogCommand.code(), 16);
        assert_eq!(Error::ModalGroupViolation.code(), 21);
        assert_eq!(Error::MaxValueExceeded.code(), 38);
        assert_eq!(Alarm::HardLimit.code(), 1);
        assert_eq!(Alarm::HomingFailApproach.code(), 9);
    }
}
