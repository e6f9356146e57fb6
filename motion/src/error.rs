//! Errors of the motion kernel and their stable wire codes.
//!
//! Every error has a numeric code in `100..=199` that never changes meaning: it goes on the
//! wire as `echo:E<code> <text>` (a refusal) or `Error:E<code> <text>` (a fault) on a G-code link and as `Error:<text>` in a frame (message 56).
//! Senders may match on the code; the text is for people.
//!
//! | code | error | meaning |
//! |---|---|---|
//! | 100 | [`ConfigError::AxisCount`] | the machine has no axes, or more than 8 |
//! | 101 | [`ConfigError::Letter`] | an axis letter is not `A`–`Z`, is a parameter letter (`F`, `G`, `I`, `J`, `K`, `M`, `N`, `P`, `R`, `S`, `T`) or is used twice |
//! | 102 | [`ConfigError::StepsPerMm`] | steps/mm not finite and positive |
//! | 103 | [`ConfigError::MaxRate`] | maximum rate not finite and positive |
//! | 104 | [`ConfigError::Acceleration`] | acceleration not finite and positive |
//! | 105 | [`ConfigError::Travel`] | travel limits not finite, or `min_mm >= max_mm` |
//! | 106 | [`ConfigError::SeekRate`] | homing seek rate not positive, or above the maximum rate |
//! | 107 | [`ConfigError::LocateRate`] | homing locate rate not positive, or above the seek rate |
//! | 108 | [`ConfigError::PullOff`] | pull-off negative, or not shorter than the travel |
//! | 109 | [`ConfigError::LimitSwitch`] | a homed axis without a limit switch, or a switch index above 31 |
//! | 110 | [`ConfigError::StepRate`] | maximum rate × steps/mm needs step pulses closer than three pulse widths, or more than half the clock |
//! | 111 | [`ConfigError::JunctionDeviation`] | junction deviation negative or not finite |
//! | 112 | [`ConfigError::ArcTolerance`] | arc tolerance not finite and positive |
//! | 113 | [`ConfigError::JogFeed`] | jog or default feed not finite, or below 1 mm/min |
//! | 114 | [`ConfigError::QueueLead`] | segment queue lead outside 2..=1000 ms |
//! | 115 | [`ConfigError::TickRate`] | the clock's tick rate is zero |
//! | 116 | [`ConfigError::Encoding`] | a stored configuration does not decode |
//! | 120 | [`CommandError::Unsupported`] | a G, M or T command this firmware does not implement |
//! | 121 | [`CommandError::BadValue`] | a word's value is out of range for its command |
//! | 122 | [`CommandError::MissingValue`] | a required word is absent (arc centre or radius, M92 value) |
//! | 123 | [`CommandError::ArcGeometry`] | the arc's end point is not on its circle, or the radius is zero |
//! | 124 | [`CommandError::SoftLimit`] | the move ends outside the axis travel |
//! | 125 | [`CommandError::Locked`] | the machine is in alarm: reset or home first |
//! | 126 | [`CommandError::Halted`] | the machine stopped on `M0`: reset first |
//! | 127 | [`CommandError::UnknownAxis`] | a letter that names no axis of this machine |
//! | 128 | [`CommandError::NotIdle`] | the command needs the machine at rest (jog, homing during a job) |
//! | 129 | [`CommandError::ModalConflict`] | two commands of the same modal group on one line |
//! | 130 | [`CommandError::RepeatedWord`] | a word (other than `G`/`M`) given twice on one line |
//! | 131 | [`CommandError::OutOfReach`] | a move longer than the axis travel, or ending where a position cannot be counted in steps or reported (beyond ±99999.9999 mm) |
//! | 132 | [`CommandError::NoProbe`] | a probing move (`G38.2`–`G38.5`) on a machine without a probe |
//! | 133 | [`CommandError::NoMotionMode`] | axis words after `G80`, with no motion mode for them |
//! | 150 | [`Alarm::HardLimit`] | a limit switch tripped during motion; motion stopped at once |
//! | 151 | [`Alarm::HomingSwitchNotFound`] | homing travelled the whole axis without finding the switch |
//! | 152 | [`Alarm::HomingSwitchStuck`] | the switch stayed triggered after the back-off |
//! | 153 | [`Alarm::EmergencyStop`] | `M112` |
//! | 154 | [`Alarm::StepUnderrun`] | the step queue ran dry during motion (segment preparation too slow) |
//! | 155 | [`Alarm::DriverFault`] | a stepper driver or limit switch reported an error |
//! | 156 | [`Alarm::ResetDuringMotion`] | a soft reset cut the motion (grbl's `ALARM:3`): steps may be lost |
//! | 157 | [`Alarm::ProbeFailInitial`] | a probing move found the probe already in the state it waits for (grbl's `ALARM:4`); nothing moved |
//! | 158 | [`Alarm::ProbeFailContact`] | a `G38.2`/`G38.4` probing move reached its target without the probe changing (grbl's `ALARM:5`) |
//!
//! Codes not listed are reserved. A code is never reused for a different meaning. Codes
//! `170..=199` belong to the application layer (`forja-app`: the program store and jobs).
//!
//! Every error also implements `forja_protocol::error::WireError` (the code and a short
//! kebab-case name), so that the controller writes it with `Reply::fault`/`Reply::notice` or
//! into frame 56 like the protocol's own errors.

use core::fmt;

use forja_protocol::error::WireError;

/// The axis index in an error: `0` is the first configured axis.
pub type AxisIndex = u8;

/// A machine configuration that cannot be used.
///
/// Each variant names the offending field (and the axis, by index, where it is per axis).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum ConfigError {
    /// The machine has no axes, or more than 8.
    AxisCount,
    /// The letter of this axis is not usable.
    Letter(AxisIndex),
    /// `steps_per_mm` of this axis.
    StepsPerMm(AxisIndex),
    /// `max_rate_mm_min` of this axis.
    MaxRate(AxisIndex),
    /// `accel_mm_s2` of this axis.
    Acceleration(AxisIndex),
    /// `min_mm` / `max_mm` of this axis.
    Travel(AxisIndex),
    /// `homing.seek_mm_min` of this axis.
    SeekRate(AxisIndex),
    /// `homing.locate_mm_min` of this axis.
    LocateRate(AxisIndex),
    /// `homing.pull_off_mm` of this axis.
    PullOff(AxisIndex),
    /// `homing.switch` of this axis.
    LimitSwitch(AxisIndex),
    /// The step rate of this axis at its maximum rate is beyond the driver or the clock.
    StepRate(AxisIndex),
    /// `junction_deviation_mm`.
    JunctionDeviation,
    /// `arc_tolerance_mm`.
    ArcTolerance,
    /// `jog_feed_mm_min` or `default_feed_mm_min` (at least 1 mm/min, the slowest `F`).
    JogFeed,
    /// `queue_lead_ms`.
    QueueLead,
    /// The tick rate given to the kernel.
    TickRate,
    /// A stored configuration that does not decode.
    Encoding,
}

impl ConfigError {
    /// The stable wire code (see the module table).
    pub const fn code(&self) -> u16 {
        match self {
            Self::AxisCount => 100,
            Self::Letter(_) => 101,
            Self::StepsPerMm(_) => 102,
            Self::MaxRate(_) => 103,
            Self::Acceleration(_) => 104,
            Self::Travel(_) => 105,
            Self::SeekRate(_) => 106,
            Self::LocateRate(_) => 107,
            Self::PullOff(_) => 108,
            Self::LimitSwitch(_) => 109,
            Self::StepRate(_) => 110,
            Self::JunctionDeviation => 111,
            Self::ArcTolerance => 112,
            Self::JogFeed => 113,
            Self::QueueLead => 114,
            Self::TickRate => 115,
            Self::Encoding => 116,
        }
    }

    /// The axis this error is about, if any.
    pub const fn axis(&self) -> Option<AxisIndex> {
        match *self {
            Self::Letter(a)
            | Self::StepsPerMm(a)
            | Self::MaxRate(a)
            | Self::Acceleration(a)
            | Self::Travel(a)
            | Self::SeekRate(a)
            | Self::LocateRate(a)
            | Self::PullOff(a)
            | Self::LimitSwitch(a)
            | Self::StepRate(a) => Some(a),
            _ => None,
        }
    }
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let field = match self {
            Self::AxisCount => return f.write_str("config: the machine needs 1 to 8 axes"),
            Self::Letter(_) => "letter (A-Z, not a parameter letter, unique)",
            Self::StepsPerMm(_) => "steps_per_mm (> 0)",
            Self::MaxRate(_) => "max_rate_mm_min (> 0)",
            Self::Acceleration(_) => "accel_mm_s2 (> 0)",
            Self::Travel(_) => "min_mm/max_mm (min < max)",
            Self::SeekRate(_) => "homing seek_mm_min (> 0, <= max rate)",
            Self::LocateRate(_) => "homing locate_mm_min (> 0, <= seek rate)",
            Self::PullOff(_) => "homing pull_off_mm (>= 0, < travel)",
            Self::LimitSwitch(_) => "homing switch (present, index <= 31)",
            Self::StepRate(_) => "max step rate (beyond driver pulse timing or clock)",
            Self::JunctionDeviation => {
                return f.write_str("config: junction_deviation_mm (>= 0)");
            }
            Self::ArcTolerance => return f.write_str("config: arc_tolerance_mm (> 0)"),
            Self::JogFeed => return f.write_str("config: jog/default feed (>= 1 mm/min)"),
            Self::QueueLead => return f.write_str("config: queue_lead_ms (2..=1000)"),
            Self::TickRate => return f.write_str("config: tick rate (> 0)"),
            Self::Encoding => return f.write_str("config: stored configuration does not decode"),
        };
        match self.axis() {
            Some(a) => write!(f, "config: axis {a}: {field}"),
            None => write!(f, "config: {field}"),
        }
    }
}

/// A G-code line the interpreter refused. The machine state is unchanged by a refused line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum CommandError {
    /// A command this firmware does not implement: `letter` (`G`, `M` or `T`) and its number
    /// (`None` when the number is not an integer, e.g. `G1.5`).
    Unsupported {
        /// `b'G'`, `b'M'` or `b'T'`.
        letter: u8,
        /// The command number.
        number: Option<u32>,
    },
    /// The value of this word is out of range for the command.
    BadValue {
        /// The word's letter.
        letter: u8,
    },
    /// A required word is missing.
    MissingValue {
        /// The missing word's letter.
        letter: u8,
    },
    /// The arc cannot be drawn: the end is not on the circle or the radius is zero.
    ArcGeometry,
    /// The move would leave the travel of this axis.
    SoftLimit {
        /// The axis index.
        axis: AxisIndex,
    },
    /// The machine is in alarm; only reset and homing are accepted.
    Locked,
    /// The machine stopped on `M0`; only reset is accepted.
    Halted,
    /// A letter that names no axis of this machine.
    UnknownAxis {
        /// The letter.
        letter: u8,
    },
    /// The command needs the machine at rest and out of a job.
    NotIdle,
    /// Two commands of one modal group on one line (two motion commands, or `G20 G21`).
    ModalConflict,
    /// A word other than `G` or `M` given twice on one line (`G1 X5 X50`; `X0x10` reads as
    /// `X0 X10`).
    RepeatedWord {
        /// The repeated word's letter.
        letter: u8,
    },
    /// The move cannot be right on this machine: it travels further than the axis's whole
    /// travel, or it ends beyond the positions the kernel counts (steps in `i32`) and reports
    /// (±99999.9999 mm, the width of frame 51).
    OutOfReach {
        /// The axis index.
        axis: AxisIndex,
    },
    /// A probing move (`G38.2`–`G38.5`) on a machine without a probe.
    NoProbe,
    /// Axis words after `G80`: no motion mode for them to follow.
    NoMotionMode,
}

impl CommandError {
    /// The stable wire code (see the module table).
    pub const fn code(&self) -> u16 {
        match self {
            Self::Unsupported { .. } => 120,
            Self::BadValue { .. } => 121,
            Self::MissingValue { .. } => 122,
            Self::ArcGeometry => 123,
            Self::SoftLimit { .. } => 124,
            Self::Locked => 125,
            Self::Halted => 126,
            Self::UnknownAxis { .. } => 127,
            Self::NotIdle => 128,
            Self::ModalConflict => 129,
            Self::RepeatedWord { .. } => 130,
            Self::OutOfReach { .. } => 131,
            Self::NoProbe => 132,
            Self::NoMotionMode => 133,
        }
    }
}

/// Writes an ASCII letter, or `?` for a byte that is not printable.
struct Letter(u8);

impl fmt::Display for Letter {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let c = if self.0.is_ascii_graphic() {
            self.0 as char
        } else {
            '?'
        };
        write!(f, "{c}")
    }
}

impl fmt::Display for CommandError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::Unsupported {
                letter,
                number: Some(n),
            } => write!(f, "unsupported command {}{n}", Letter(letter)),
            Self::Unsupported {
                letter,
                number: None,
            } => write!(f, "unsupported command {} (not an integer)", Letter(letter)),
            Self::BadValue { letter } => write!(f, "bad value for {}", Letter(letter)),
            Self::MissingValue { letter } => write!(f, "missing {}", Letter(letter)),
            Self::ArcGeometry => f.write_str("arc: end point not on the circle"),
            Self::SoftLimit { axis } => write!(f, "soft limit: axis {axis} would leave its travel"),
            Self::Locked => f.write_str("alarm: reset or home first"),
            Self::Halted => f.write_str("halted by M0: reset first"),
            Self::UnknownAxis { letter } => write!(f, "no axis {}", Letter(letter)),
            Self::NotIdle => f.write_str("machine busy: command needs it at rest"),
            Self::ModalConflict => f.write_str("two commands of one modal group"),
            Self::RepeatedWord { letter } => write!(f, "word {} given twice", Letter(letter)),
            Self::OutOfReach { axis } => write!(f, "axis {axis}: move beyond the machine's reach"),
            Self::NoProbe => f.write_str("no probe on this machine"),
            Self::NoMotionMode => f.write_str("axis words without a motion mode (after G80)"),
        }
    }
}

/// Why motion stopped on its own. An alarm locks the machine: G-code is refused with
/// [`CommandError::Locked`] until a reset or a successful homing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Alarm {
    /// The limit switch of this axis tripped during motion.
    HardLimit {
        /// The axis index.
        axis: AxisIndex,
    },
    /// Homing travelled the axis without finding its switch.
    HomingSwitchNotFound {
        /// The axis index.
        axis: AxisIndex,
    },
    /// The switch stayed triggered after the homing back-off.
    HomingSwitchStuck {
        /// The axis index.
        axis: AxisIndex,
    },
    /// `M112`.
    EmergencyStop,
    /// The step queue ran dry while the machine moved.
    StepUnderrun,
    /// A driver or switch of this axis reported an error.
    DriverFault {
        /// The axis index.
        axis: AxisIndex,
    },
    /// A soft reset of the grbl dialect cut the motion at once: steps may be lost.
    ResetDuringMotion,
    /// A probing move started with the probe already in the state it waits for (touching for
    /// `G38.2`/`G38.3`, open for `G38.4`/`G38.5`): nothing moved.
    ProbeFailInitial,
    /// A `G38.2`/`G38.4` probing move reached its target without the probe changing.
    ProbeFailContact,
}

impl Alarm {
    /// The stable wire code (see the module table).
    pub const fn code(&self) -> u16 {
        match self {
            Self::HardLimit { .. } => 150,
            Self::HomingSwitchNotFound { .. } => 151,
            Self::HomingSwitchStuck { .. } => 152,
            Self::EmergencyStop => 153,
            Self::StepUnderrun => 154,
            Self::DriverFault { .. } => 155,
            Self::ResetDuringMotion => 156,
            Self::ProbeFailInitial => 157,
            Self::ProbeFailContact => 158,
        }
    }

    /// Whether the machine position is still known after this alarm. When it is not, soft
    /// limits and jobs need a new homing.
    pub const fn position_kept(&self) -> bool {
        matches!(
            self,
            Self::HomingSwitchNotFound { .. } | Self::ProbeFailInitial | Self::ProbeFailContact
        )
    }
}

impl fmt::Display for Alarm {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::HardLimit { axis } => write!(f, "alarm: hard limit on axis {axis}"),
            Self::HomingSwitchNotFound { axis } => {
                write!(f, "alarm: homing switch of axis {axis} not found")
            }
            Self::HomingSwitchStuck { axis } => {
                write!(f, "alarm: homing switch of axis {axis} did not release")
            }
            Self::EmergencyStop => f.write_str("alarm: emergency stop"),
            Self::StepUnderrun => f.write_str("alarm: step queue underrun"),
            Self::DriverFault { axis } => write!(f, "alarm: driver fault on axis {axis}"),
            Self::ResetDuringMotion => f.write_str("alarm: reset during motion"),
            Self::ProbeFailInitial => f.write_str("alarm: probe already tripped before probing"),
            Self::ProbeFailContact => f.write_str("alarm: probing ended without contact"),
        }
    }
}

impl WireError for ConfigError {
    fn code(&self) -> u16 {
        ConfigError::code(self)
    }
    fn name(&self) -> &'static str {
        match self {
            Self::AxisCount => "axis-count",
            Self::Letter(_) => "axis-letter",
            Self::StepsPerMm(_) => "steps-per-mm",
            Self::MaxRate(_) => "max-rate",
            Self::Acceleration(_) => "acceleration",
            Self::Travel(_) => "travel",
            Self::SeekRate(_) => "seek-rate",
            Self::LocateRate(_) => "locate-rate",
            Self::PullOff(_) => "pull-off",
            Self::LimitSwitch(_) => "limit-switch",
            Self::StepRate(_) => "step-rate",
            Self::JunctionDeviation => "junction-deviation",
            Self::ArcTolerance => "arc-tolerance",
            Self::JogFeed => "jog-feed",
            Self::QueueLead => "queue-lead",
            Self::TickRate => "tick-rate",
            Self::Encoding => "config-encoding",
        }
    }
}

impl WireError for CommandError {
    fn code(&self) -> u16 {
        CommandError::code(self)
    }
    fn name(&self) -> &'static str {
        match self {
            Self::Unsupported { .. } => "unsupported-command",
            Self::BadValue { .. } => "bad-value",
            Self::MissingValue { .. } => "missing-value",
            Self::ArcGeometry => "arc-geometry",
            Self::SoftLimit { .. } => "soft-limit",
            Self::Locked => "alarm-locked",
            Self::Halted => "halted",
            Self::UnknownAxis { .. } => "unknown-axis",
            Self::NotIdle => "not-idle",
            Self::ModalConflict => "modal-conflict",
            Self::RepeatedWord { .. } => "repeated-word",
            Self::OutOfReach { .. } => "out-of-reach",
            Self::NoProbe => "no-probe",
            Self::NoMotionMode => "no-motion-mode",
        }
    }
}

impl WireError for Alarm {
    fn code(&self) -> u16 {
        Alarm::code(self)
    }
    fn name(&self) -> &'static str {
        match self {
            Self::HardLimit { .. } => "hard-limit",
            Self::HomingSwitchNotFound { .. } => "homing-not-found",
            Self::HomingSwitchStuck { .. } => "homing-stuck",
            Self::EmergencyStop => "emergency-stop",
            Self::StepUnderrun => "step-underrun",
            Self::DriverFault { .. } => "driver-fault",
            Self::ResetDuringMotion => "reset-in-motion",
            Self::ProbeFailInitial => "probe-initial",
            Self::ProbeFailContact => "probe-no-contact",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_in_range_and_distinct() {
        let codes = [
            ConfigError::AxisCount.code(),
            ConfigError::Letter(0).code(),
            ConfigError::StepsPerMm(0).code(),
            ConfigError::MaxRate(0).code(),
            ConfigError::Acceleration(0).code(),
            ConfigError::Travel(0).code(),
            ConfigError::SeekRate(0).code(),
            ConfigError::LocateRate(0).code(),
            ConfigError::PullOff(0).code(),
            ConfigError::LimitSwitch(0).code(),
            ConfigError::StepRate(0).code(),
            ConfigError::JunctionDeviation.code(),
            ConfigError::ArcTolerance.code(),
            ConfigError::JogFeed.code(),
            ConfigError::QueueLead.code(),
            ConfigError::TickRate.code(),
            ConfigError::Encoding.code(),
            CommandError::Unsupported {
                letter: b'G',
                number: Some(38),
            }
            .code(),
            CommandError::BadValue { letter: b'S' }.code(),
            CommandError::MissingValue { letter: b'R' }.code(),
            CommandError::ArcGeometry.code(),
            CommandError::SoftLimit { axis: 0 }.code(),
            CommandError::Locked.code(),
            CommandError::Halted.code(),
            CommandError::UnknownAxis { letter: b'Q' }.code(),
            CommandError::NotIdle.code(),
            CommandError::ModalConflict.code(),
            CommandError::RepeatedWord { letter: b'X' }.code(),
            CommandError::OutOfReach { axis: 0 }.code(),
            CommandError::NoProbe.code(),
            CommandError::NoMotionMode.code(),
            Alarm::HardLimit { axis: 0 }.code(),
            Alarm::HomingSwitchNotFound { axis: 0 }.code(),
            Alarm::HomingSwitchStuck { axis: 0 }.code(),
            Alarm::EmergencyStop.code(),
            Alarm::StepUnderrun.code(),
            Alarm::DriverFault { axis: 0 }.code(),
            Alarm::ResetDuringMotion.code(),
            Alarm::ProbeFailInitial.code(),
            Alarm::ProbeFailContact.code(),
        ];
        for (i, c) in codes.iter().enumerate() {
            assert!((100..=199).contains(c), "{c}");
            assert!(!codes[..i].contains(c), "duplicate {c}");
        }
    }

    #[test]
    fn unsupported_names_the_command() {
        extern crate std;
        use std::string::ToString;
        let e = CommandError::Unsupported {
            letter: b'G',
            number: Some(38),
        };
        assert_eq!(e.to_string(), "unsupported command G38");
    }
}
