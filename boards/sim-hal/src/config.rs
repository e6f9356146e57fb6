//! The machine file: what the simulated machine is.
//!
//! A machine file is TOML. It names the axes with their scale, rates, travel, homing and
//! switches, the touch probe, the simulated heaters with their thermal constants, the PWM
//! outputs, the switched (on/off) outputs, the beeper, the virtual clock rate and the link
//! settings. [`MachineConfig::from_toml_str`] parses and validates one; every error names the
//! line, the section and the field ([`MachineFileError`]).
//!
//! Two machine files are bundled ([`BUNDLED`]): `default` (`machines/default.toml`, a 4-axis
//! X/Y/Z/A CNC router with flood and mist coolant, the simulator's default) and `printer`
//! (`machines/printer.toml`, an X/Y/Z/E 3D printer with a hot end, a bed and a beeper). The
//! bundled files are the reference of the format: every field is there with a comment.
//!
//! # Format
//!
//! ```toml
//! name = "Example"            # optional, free text
//! tick_hz = 1_000_000         # optional, virtual clock rate; 10 kHz ..= 250 MHz
//!
//! [[axis]]
//! letter = "X"                # X Y Z A B C U V W or E, each at most once
//! kind = "linear"             # optional: "linear" (default), "rotary" ("mm" means degrees)
//!                             # or "extruder" (filament feed, no travel limits)
//! steps_per_mm = 80.0         # > 0
//! max_rate_mm_min = 6000.0    # > 0, and reachable by the driver's pulse timing
//! accel_mm_s2 = 500.0         # > 0
//! travel_min_mm = 0.0         # required for linear axes, optional for rotary and extruder ones
//! travel_max_mm = 300.0       # > travel_min_mm
//! start_mm = 150.0            # optional: physical position at power-up (default: mid-travel, or 0)
//! min_pulse_ns = 2000         # optional: simulated driver's STEP high/low minimum
//! dir_setup_ns = 1000         # optional: simulated driver's DIR set-up before a STEP edge
//!
//! [axis.homing]               # optional
//! direction = "negative"      # "negative" or "positive": needs a switch on that side
//! seek_mm_min = 2000.0        # > 0
//! locate_mm_min = 100.0       # > 0 and <= seek_mm_min
//! pull_off_mm = 2.0           # >= 0
//!
//! [[axis.switch]]             # zero or more, at most one per side
//! side = "min"                # "min": triggered at or below position_mm; "max": at or above
//! position_mm = 0.0
//! polarity = "normally_closed" # optional: "normally_open" (default) or "normally_closed"
//!
//! [probe]                     # optional: a touch probe, closed on the stock's surface
//! axis = "Z"                  # optional: the axis it closes along (default "Z")
//! position_mm = 20.0          # closed while that axis is at or below this machine position
//! polarity = "normally_open"  # optional: "normally_open" (default, a touch plate) or
//!                             # "normally_closed"
//!
//! [[heater]]                  # zero or more
//! name = "hotend"
//! power_w = 40.0              # > 0: power at full duty
//! heat_capacity_j_per_k = 10.0 # > 0
//! loss_w_per_k = 0.1          # > 0: loss to ambient per kelvin above it
//! ambient_c = 25.0            # optional, default 25
//! start_c = 25.0              # optional, default ambient_c
//!
//! [[output]]                  # PWM outputs (fans, spindles); zero or more
//! name = "spindle"
//! max_duty = 1000             # 1 ..= 65535
//!
//! [[digital_output]]          # on/off outputs (coolant valves, relays); zero or more
//! name = "flood"              # "flood" and "mist" are the coolant lines (M8, M7); unique
//! active = "high"             # optional: the line level that switches the device on, "high"
//!                             # (default) or "low"
//!
//! [beeper]                    # optional: a buzzer or speaker for M300
//! waiting_tones = 4           # optional: tones kept waiting behind the one sounding; 4 ..= 64
//!                             # (default 4, Marlin's queue)
//!
//! [link]                      # optional
//! tcp_bind = "127.0.0.1"      # default 127.0.0.1
//! tcp_port = 2323             # default 2323; 0 = any free port
//! http_port = 8080            # the operator's web page (and its WebSocket), on tcp_bind;
//!                             # default 8080; 0 = any free port
//! ```
//!
//! Unknown fields are errors, so that a misspelt field is not silently ignored. Integers are
//! accepted where a decimal number is expected.
//!
//! # What the parts are
//!
//! Names give heaters and outputs their part: the heater named `bed` is the bed
//! ([`MachineConfig::bed_heater`]), the first other heater the hot end
//! ([`MachineConfig::hot_end_heater`]); the output named `spindle` is the spindle
//! ([`MachineConfig::spindle_output`]), the others are fans 0, 1, … in file order
//! ([`MachineConfig::fan_outputs`]). The digital output named `flood` is the flood coolant
//! ([`MachineConfig::flood_output`]), the one named `mist` the mist coolant
//! ([`MachineConfig::mist_output`]); others are general outputs. An axis's homing switch is the
//! one on the side it homes towards ([`AxisConfig::homing_switch`]); other switches (a hard
//! limit at the far end) are modelled but are not the homing switch. The probe
//! ([`MachineConfig::probe`]) is a switch of its own beside them, never one of an axis's
//! min/max switches. Every axis's steps are scheduled for the slowest driver of the machine
//! ([`MachineConfig::slowest_step_timing`]).

use core::fmt;
use std::net::IpAddr;

use embedded_hal::digital::PinState;
use forja_hal_abstraction::stepper::{Direction, StepTiming};
use serde::Deserialize;
use toml::Spanned;

/// The bundled machine files, by name: `default` (the 4-axis router) and `printer`.
pub const BUNDLED: &[(&str, &str)] = &[
    ("default", include_str!("../machines/default.toml")),
    ("printer", include_str!("../machines/printer.toml")),
];

/// The default TCP port of the simulator's link: telnet's port 23, unprivileged.
///
/// The ESP32 board serves its WiFi link on port 23 like other WiFi CNC controllers; a host
/// process may not bind ports below 1024, hence 2323.
pub const DEFAULT_TCP_PORT: u16 = 2323;

/// The default port of the simulator's web link (the operator's page and its WebSocket): HTTP's
/// port 80 is privileged on a host, hence 8080. The ESP32 board serves it on port 80.
pub const DEFAULT_HTTP_PORT: u16 = 8080;

/// The default virtual clock rate: 1 MHz, one tick per microsecond.
pub const DEFAULT_TICK_HZ: u32 = 1_000_000;

/// Lowest accepted [`MachineConfig::tick_hz`].
pub const MIN_TICK_HZ: u32 = 10_000;

/// Highest accepted [`MachineConfig::tick_hz`] (above every supported board's timer).
pub const MAX_TICK_HZ: u32 = 250_000_000;

/// The name of the heater that is the bed.
pub const BED: &str = "bed";

/// The name of the output that is the spindle.
pub const SPINDLE: &str = "spindle";

/// The name of the digital output that is the flood coolant (`M8`).
pub const FLOOD: &str = "flood";

/// The name of the digital output that is the mist coolant (`M7`).
pub const MIST: &str = "mist";

/// The fewest and most tones a beeper keeps waiting behind the one it sounds
/// ([`BeeperConfig::waiting_tones`]): at least what the beeper contract asks for
/// ([`forja_hal_abstraction::device::MIN_WAITING_TONES`]).
pub const WAITING_TONES: core::ops::RangeInclusive<usize> =
    forja_hal_abstraction::device::MIN_WAITING_TONES..=64;

/// Axis letters a machine file may use.
pub const AXIS_LETTERS: &str = "XYZABCUVWE";

/// A validated machine description.
#[derive(Debug, Clone, PartialEq)]
pub struct MachineConfig {
    /// Free-text name of the machine.
    pub name: String,
    /// Rate of the virtual clock, in ticks per second.
    pub tick_hz: u32,
    /// The axes, in file order; an axis's index here is its index everywhere in the simulator.
    pub axes: Vec<AxisConfig>,
    /// Simulated heaters, in file order.
    pub heaters: Vec<HeaterConfig>,
    /// PWM outputs, in file order.
    pub outputs: Vec<OutputConfig>,
    /// Switched (on/off) outputs, in file order.
    pub digital_outputs: Vec<DigitalOutputConfig>,
    /// The beeper, if the machine has one.
    pub beeper: Option<BeeperConfig>,
    /// The touch probe, if the machine has one.
    pub probe: Option<ProbeConfig>,
    /// Link settings.
    pub link: LinkConfig,
}

/// Whether an axis moves in a line or turns.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum AxisKind {
    /// A linear axis: positions in millimetres.
    Linear,
    /// A rotary axis: every `_mm` quantity of the axis is in degrees, as G-code treats A/B/C.
    Rotary,
    /// A 3D printer's filament feed (`E`): millimetres of filament, no travel limits needed.
    Extruder,
}

/// The end of travel a limit switch sits at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SwitchSide {
    /// Triggered at or below its position.
    Min,
    /// Triggered at or above its position.
    Max,
}

/// The electrical behaviour of a limit switch, wired between the input and ground with a
/// pull-up (the same naming as the `forja-drivers` limit input).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SwitchPolarity {
    /// Closes at the limit: the input reads **low** when triggered.
    NormallyOpen,
    /// Opens at the limit: the input reads **high** when triggered.
    NormallyClosed,
}

/// Travel limits of an axis, in millimetres (degrees for rotary axes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Travel {
    /// Lowest machine position.
    pub min_mm: f64,
    /// Highest machine position.
    pub max_mm: f64,
}

/// How an axis homes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HomingConfig {
    /// Direction of travel towards the homing switch.
    pub direction: Direction,
    /// Rate of the fast search for the switch.
    pub seek_mm_min: f64,
    /// Rate of the slow, precise approach.
    pub locate_mm_min: f64,
    /// Distance to back off the switch after homing.
    pub pull_off_mm: f64,
}

/// One simulated limit switch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SwitchConfig {
    /// Which end it sits at.
    pub side: SwitchSide,
    /// Machine position at which it trips, in millimetres (degrees for rotary axes).
    pub position_mm: f64,
    /// How its input pin reads when triggered.
    pub polarity: SwitchPolarity,
}

/// The touch probe (machine file `[probe]`): a switch that closes when the tool touches the
/// stock's surface, at or below a machine position of one axis, as a `min` switch does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeConfig {
    /// The index of the axis it closes along (in [`MachineConfig::axes`]).
    pub axis: usize,
    /// Machine position at or below which it is closed (touching), in millimetres (degrees
    /// for a rotary axis).
    pub position_mm: f64,
    /// How its input pin reads when touching.
    pub polarity: SwitchPolarity,
}

/// One axis.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisConfig {
    /// Axis letter, upper case.
    pub letter: char,
    /// Linear or rotary.
    pub kind: AxisKind,
    /// Motor steps per millimetre (per degree for rotary axes).
    pub steps_per_mm: f64,
    /// Highest rate.
    pub max_rate_mm_min: f64,
    /// Acceleration.
    pub accel_mm_s2: f64,
    /// Travel limits; `None` only for a rotary axis that turns without limit or an extruder.
    pub travel: Option<Travel>,
    /// Physical position at power-up.
    pub start_mm: f64,
    /// Homing, when the axis homes.
    pub homing: Option<HomingConfig>,
    /// Limit switches, at most one per side.
    pub switches: Vec<SwitchConfig>,
    /// Timing that the simulated driver chip enforces.
    pub step_timing: StepTiming,
}

/// One simulated heater with its first-order thermal model (see [`crate::thermal`]).
#[derive(Debug, Clone, PartialEq)]
pub struct HeaterConfig {
    /// Name, unique among heaters (`hotend`, `bed`).
    pub name: String,
    /// Electrical power at full duty, in watts.
    pub power_w: f64,
    /// Heat capacity of the heated mass, in joules per kelvin.
    pub heat_capacity_j_per_k: f64,
    /// Heat lost to ambient, in watts per kelvin above ambient.
    pub loss_w_per_k: f64,
    /// Ambient temperature, in degrees Celsius.
    pub ambient_c: f64,
    /// Temperature at power-up, in degrees Celsius.
    pub start_c: f64,
}

/// One PWM output (fan, spindle).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutputConfig {
    /// Name, unique among outputs.
    pub name: String,
    /// Duty value meaning 100 %.
    pub max_duty: u16,
}

/// One switched (on/off) output (machine file `[[digital_output]]`): a coolant valve, a relay
/// (see [`crate::digital`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DigitalOutputConfig {
    /// Name, unique among digital outputs ([`FLOOD`], [`MIST`], or any other).
    pub name: String,
    /// The line level that switches the device on.
    pub active: PinState,
}

/// The beeper: a buzzer or a speaker that plays the tones of `M300` one after another (see
/// [`crate::beeper`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BeeperConfig {
    /// How many tones it keeps waiting behind the one it sounds; a tone beyond them is not
    /// played. In [`WAITING_TONES`].
    pub waiting_tones: usize,
}

impl Default for BeeperConfig {
    fn default() -> Self {
        Self {
            waiting_tones: *WAITING_TONES.start(),
        }
    }
}

/// Link settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkConfig {
    /// Address the TCP listener binds to.
    pub tcp_bind: IpAddr,
    /// TCP port; 0 picks any free port.
    pub tcp_port: u16,
    /// The web link's port, on `tcp_bind`; 0 picks any free port.
    pub http_port: u16,
}

impl Default for LinkConfig {
    fn default() -> Self {
        Self {
            tcp_bind: IpAddr::from([127, 0, 0, 1]),
            tcp_port: DEFAULT_TCP_PORT,
            http_port: DEFAULT_HTTP_PORT,
        }
    }
}

impl MachineConfig {
    /// Parse and validate a machine file.
    ///
    /// Errors: [`MachineFileError::Syntax`] for TOML that does not parse or a field of the wrong
    /// type, missing or unknown; [`MachineFileError::Invalid`] for a value out of range or
    /// inconsistent with another. Both carry the line of the offending text.
    pub fn from_toml_str(text: &str) -> Result<Self, MachineFileError> {
        let raw: RawMachine = toml::from_str(text).map_err(|e| MachineFileError::Syntax {
            line: e.span().map(|s| line_of(text, s.start)),
            message: e.message().trim().to_string(),
        })?;
        Validator { text }.machine(raw)
    }

    /// The text of a bundled machine file by name (see [`BUNDLED`]).
    pub fn bundled_toml(name: &str) -> Option<&'static str> {
        BUNDLED.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
    }

    /// The bundled default machine: the 4-axis router of `machines/default.toml`.
    ///
    /// Cannot fail: the bundled file is validated by this crate's tests.
    pub fn default_router() -> Self {
        Self::from_toml_str(include_str!("../machines/default.toml"))
            .expect("the bundled default machine file is valid")
    }

    /// The index of the axis named `letter` (either case).
    pub fn axis_index(&self, letter: char) -> Option<usize> {
        let letter = letter.to_ascii_uppercase();
        self.axes.iter().position(|a| a.letter == letter)
    }

    /// The slowest driver timing of the machine: the longest pulse and direction set-up that
    /// any of its drivers needs, what a firmware schedules every axis's steps for.
    pub fn slowest_step_timing(&self) -> StepTiming {
        self.axes.iter().fold(
            StepTiming {
                min_pulse_ns: 0,
                dir_setup_ns: 0,
            },
            |t, a| StepTiming {
                min_pulse_ns: t.min_pulse_ns.max(a.step_timing.min_pulse_ns),
                dir_setup_ns: t.dir_setup_ns.max(a.step_timing.dir_setup_ns),
            },
        )
    }

    /// The bed: the heater named `bed`.
    pub fn bed_heater(&self) -> Option<usize> {
        self.heaters.iter().position(|h| h.name == BED)
    }

    /// The hot end: the first heater not named `bed`.
    pub fn hot_end_heater(&self) -> Option<usize> {
        self.heaters.iter().position(|h| h.name != BED)
    }

    /// The spindle: the output named `spindle`.
    pub fn spindle_output(&self) -> Option<usize> {
        self.outputs.iter().position(|o| o.name == SPINDLE)
    }

    /// The flood coolant: the digital output named `flood`.
    pub fn flood_output(&self) -> Option<usize> {
        self.digital_output_index(FLOOD)
    }

    /// The mist coolant: the digital output named `mist`.
    pub fn mist_output(&self) -> Option<usize> {
        self.digital_output_index(MIST)
    }

    /// The index of the digital output called `name`.
    pub fn digital_output_index(&self, name: &str) -> Option<usize> {
        self.digital_outputs.iter().position(|o| o.name == name)
    }

    /// The fans 0, 1, …: the outputs not named `spindle`, in file order.
    pub fn fan_outputs(&self) -> impl Iterator<Item = usize> + '_ {
        self.outputs
            .iter()
            .enumerate()
            .filter(|(_, o)| o.name != SPINDLE)
            .map(|(i, _)| i)
    }
}

impl AxisConfig {
    /// `mm` millimetres (degrees) in whole steps, rounded to the nearest step.
    pub fn mm_to_steps(&self, mm: f64) -> i64 {
        (mm * self.steps_per_mm).round() as i64
    }

    /// `steps` in millimetres (degrees).
    pub fn steps_to_mm(&self, steps: i64) -> f64 {
        steps as f64 / self.steps_per_mm
    }

    /// The switch on `side`, if any.
    pub fn switch(&self, side: SwitchSide) -> Option<&SwitchConfig> {
        self.switches.iter().find(|s| s.side == side)
    }

    /// The homing switch: the switch on the side the axis homes towards, if it homes.
    pub fn homing_switch(&self) -> Option<&SwitchConfig> {
        self.switch(match self.homing?.direction {
            Direction::Negative => SwitchSide::Min,
            Direction::Positive => SwitchSide::Max,
        })
    }
}

impl From<SwitchPolarity> for forja_drivers::limit::Polarity {
    fn from(p: SwitchPolarity) -> Self {
        match p {
            SwitchPolarity::NormallyOpen => Self::NormallyOpen,
            SwitchPolarity::NormallyClosed => Self::NormallyClosed,
        }
    }
}

/// A machine file that cannot be used, with the line it was found at.
///
/// Its `Display` is one line: `machine file line 12: axis Y: steps_per_mm must be > 0`.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum MachineFileError {
    /// Not TOML, or a field of the wrong type, missing, duplicated or unknown.
    Syntax {
        /// 1-based line of the offending text, when known.
        line: Option<usize>,
        /// The parser's description.
        message: String,
    },
    /// A value out of range, or inconsistent with another.
    Invalid {
        /// 1-based line of the offending value (or of its section, for a missing one).
        line: Option<usize>,
        /// The section: `axis Y`, `heater bed`, `output fan`, `digital_output flood`, `probe`,
        /// `link`, or empty at top level.
        section: String,
        /// The field name, as written in the file (`steps_per_mm`, `homing.direction`).
        field: String,
        /// What is wrong with it.
        reason: String,
    },
}

impl MachineFileError {
    /// The 1-based line the error was found at, when known.
    pub fn line(&self) -> Option<usize> {
        match self {
            Self::Syntax { line, .. } | Self::Invalid { line, .. } => *line,
        }
    }

    /// The offending field, for a validation error.
    pub fn field(&self) -> Option<&str> {
        match self {
            Self::Syntax { .. } => None,
            Self::Invalid { field, .. } => Some(field),
        }
    }
}

impl fmt::Display for MachineFileError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("machine file")?;
        if let Some(line) = self.line() {
            write!(f, " line {line}")?;
        }
        match self {
            Self::Syntax { message, .. } => {
                write!(f, ": {}", message.lines().next().unwrap_or_default())
            }
            Self::Invalid {
                section,
                field,
                reason,
                ..
            } => {
                if !section.is_empty() {
                    write!(f, ": {section}")?;
                }
                write!(f, ": {field} {reason}")
            }
        }
    }
}

impl std::error::Error for MachineFileError {}

/// The 1-based line of byte offset `at` in `text`.
fn line_of(text: &str, at: usize) -> usize {
    let at = at.min(text.len());
    text.as_bytes()[..at]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
        + 1
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMachine {
    name: Option<String>,
    tick_hz: Option<Spanned<i64>>,
    #[serde(default, rename = "axis")]
    axes: Vec<Spanned<RawAxis>>,
    #[serde(default, rename = "heater")]
    heaters: Vec<Spanned<RawHeater>>,
    #[serde(default, rename = "output")]
    outputs: Vec<Spanned<RawOutput>>,
    #[serde(default, rename = "digital_output")]
    digital_outputs: Vec<Spanned<RawDigitalOutput>>,
    beeper: Option<Spanned<RawBeeper>>,
    probe: Option<Spanned<RawProbe>>,
    link: Option<Spanned<RawLink>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawAxis {
    letter: Spanned<String>,
    kind: Option<Spanned<String>>,
    steps_per_mm: Spanned<f64>,
    max_rate_mm_min: Spanned<f64>,
    accel_mm_s2: Spanned<f64>,
    travel_min_mm: Option<Spanned<f64>>,
    travel_max_mm: Option<Spanned<f64>>,
    start_mm: Option<Spanned<f64>>,
    min_pulse_ns: Option<Spanned<i64>>,
    dir_setup_ns: Option<Spanned<i64>>,
    homing: Option<Spanned<RawHoming>>,
    #[serde(default, rename = "switch")]
    switches: Vec<Spanned<RawSwitch>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHoming {
    direction: Spanned<String>,
    seek_mm_min: Spanned<f64>,
    locate_mm_min: Spanned<f64>,
    pull_off_mm: Spanned<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSwitch {
    side: Spanned<String>,
    position_mm: Spanned<f64>,
    polarity: Option<Spanned<String>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHeater {
    name: Spanned<String>,
    power_w: Spanned<f64>,
    heat_capacity_j_per_k: Spanned<f64>,
    loss_w_per_k: Spanned<f64>,
    ambient_c: Option<Spanned<f64>>,
    start_c: Option<Spanned<f64>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawOutput {
    name: Spanned<String>,
    max_duty: Spanned<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDigitalOutput {
    name: Spanned<String>,
    active: Option<Spanned<String>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBeeper {
    waiting_tones: Option<Spanned<i64>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawProbe {
    axis: Option<Spanned<String>>,
    position_mm: Spanned<f64>,
    polarity: Option<Spanned<String>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLink {
    tcp_bind: Option<Spanned<String>>,
    tcp_port: Option<Spanned<i64>>,
    http_port: Option<Spanned<i64>>,
}

/// Turns raw, spanned values into a [`MachineConfig`], naming the line of each error.
struct Validator<'a> {
    text: &'a str,
}

type Res<T> = Result<T, MachineFileError>;

impl Validator<'_> {
    /// Push `item` onto `list` unless an entry there has the same `key`: a second `kind` with
    /// the same `field` is an error at byte `at` of the file.
    fn push_unique<T, K: PartialEq + std::fmt::Display>(
        &self,
        list: &mut Vec<T>,
        item: T,
        key: impl Fn(&T) -> K,
        at: usize,
        kind: &str,
        field: &str,
    ) -> Res<()> {
        let k = key(&item);
        if list.iter().any(|other| key(other) == k) {
            return self.err(
                Some(at),
                &format!("{kind} {k}"),
                field,
                format!("is used by another {kind}"),
            );
        }
        list.push(item);
        Ok(())
    }

    fn err<T>(
        &self,
        at: Option<usize>,
        section: &str,
        field: &str,
        reason: impl Into<String>,
    ) -> Res<T> {
        Err(MachineFileError::Invalid {
            line: at.map(|a| line_of(self.text, a)),
            section: section.to_string(),
            field: field.to_string(),
            reason: reason.into(),
        })
    }

    /// A finite number, `> 0` when `positive`, `>= 0` otherwise.
    fn number(&self, v: &Spanned<f64>, section: &str, field: &str, positive: bool) -> Res<f64> {
        let x = *v.get_ref();
        if !x.is_finite() {
            return self.err(
                Some(v.span().start),
                section,
                field,
                "must be a finite number",
            );
        }
        if positive && x <= 0.0 {
            return self.err(Some(v.span().start), section, field, "must be > 0");
        }
        if !positive && x < 0.0 {
            return self.err(Some(v.span().start), section, field, "must be >= 0");
        }
        Ok(x)
    }

    fn finite(&self, v: &Spanned<f64>, section: &str, field: &str) -> Res<f64> {
        let x = *v.get_ref();
        if x.is_finite() {
            Ok(x)
        } else {
            self.err(
                Some(v.span().start),
                section,
                field,
                "must be a finite number",
            )
        }
    }

    fn integer(
        &self,
        v: &Spanned<i64>,
        section: &str,
        field: &str,
        range: core::ops::RangeInclusive<i64>,
    ) -> Res<i64> {
        let x = *v.get_ref();
        if range.contains(&x) {
            Ok(x)
        } else {
            self.err(
                Some(v.span().start),
                section,
                field,
                format!("must be in {}..={} (is {x})", range.start(), range.end()),
            )
        }
    }

    fn choice<T: Copy>(
        &self,
        v: &Spanned<String>,
        section: &str,
        field: &str,
        options: &[(&str, T)],
    ) -> Res<T> {
        match options
            .iter()
            .find(|(name, _)| *name == v.get_ref().as_str())
        {
            Some((_, value)) => Ok(*value),
            None => {
                let names: Vec<String> = options.iter().map(|(n, _)| format!("\"{n}\"")).collect();
                self.err(
                    Some(v.span().start),
                    section,
                    field,
                    format!(
                        "must be one of {} (is \"{}\")",
                        names.join(", "),
                        v.get_ref()
                    ),
                )
            }
        }
    }

    fn machine(&self, raw: RawMachine) -> Res<MachineConfig> {
        let tick_hz = match &raw.tick_hz {
            Some(v) => {
                self.integer(v, "", "tick_hz", MIN_TICK_HZ as i64..=MAX_TICK_HZ as i64)? as u32
            }
            None => DEFAULT_TICK_HZ,
        };
        if raw.axes.is_empty() {
            return self.err(None, "", "axis", "must list at least one axis ([[axis]])");
        }
        let mut axes: Vec<AxisConfig> = Vec::with_capacity(raw.axes.len());
        for a in &raw.axes {
            let axis = self.axis(a, tick_hz)?;
            let at = a.get_ref().letter.span().start;
            self.push_unique(&mut axes, axis, |x| x.letter, at, "axis", "letter")?;
        }
        let mut heaters: Vec<HeaterConfig> = Vec::new();
        for h in &raw.heaters {
            let heater = self.heater(h.get_ref())?;
            let at = h.get_ref().name.span().start;
            self.push_unique(
                &mut heaters,
                heater,
                |x| x.name.clone(),
                at,
                "heater",
                "name",
            )?;
        }
        let mut outputs: Vec<OutputConfig> = Vec::new();
        for o in &raw.outputs {
            let output = self.output(o.get_ref())?;
            let at = o.get_ref().name.span().start;
            self.push_unique(
                &mut outputs,
                output,
                |x| x.name.clone(),
                at,
                "output",
                "name",
            )?;
        }
        let mut digital_outputs: Vec<DigitalOutputConfig> = Vec::new();
        for o in &raw.digital_outputs {
            let output = self.digital_output(o.get_ref())?;
            let at = o.get_ref().name.span().start;
            self.push_unique(
                &mut digital_outputs,
                output,
                |x| x.name.clone(),
                at,
                "digital_output",
                "name",
            )?;
        }
        let beeper = match &raw.beeper {
            Some(b) => Some(self.beeper(b.get_ref())?),
            None => None,
        };
        let probe = match &raw.probe {
            Some(p) => Some(self.probe(p, &axes)?),
            None => None,
        };
        let link = match &raw.link {
            Some(l) => self.link(l.get_ref())?,
            None => LinkConfig::default(),
        };
        Ok(MachineConfig {
            name: raw.name.unwrap_or_else(|| "unnamed machine".to_string()),
            tick_hz,
            axes,
            heaters,
            outputs,
            digital_outputs,
            beeper,
            probe,
            link,
        })
    }

    fn axis(&self, spanned: &Spanned<RawAxis>, tick_hz: u32) -> Res<AxisConfig> {
        let a = spanned.get_ref();
        let letter_text = a.letter.get_ref();
        let mut chars = letter_text.chars();
        let letter = match (chars.next(), chars.next()) {
            (Some(c), None) if AXIS_LETTERS.contains(c) => c,
            _ => {
                return self.err(
                    Some(a.letter.span().start),
                    "axis",
                    "letter",
                    format!(
                        "must be one upper-case letter of {AXIS_LETTERS} (is \"{letter_text}\")"
                    ),
                );
            }
        };
        let s = format!("axis {letter}");
        let s = s.as_str();
        let kind = match &a.kind {
            Some(k) => self.choice(
                k,
                s,
                "kind",
                &[
                    ("linear", AxisKind::Linear),
                    ("rotary", AxisKind::Rotary),
                    ("extruder", AxisKind::Extruder),
                ],
            )?,
            None => AxisKind::Linear,
        };
        let steps_per_mm = self.number(&a.steps_per_mm, s, "steps_per_mm", true)?;
        let max_rate_mm_min = self.number(&a.max_rate_mm_min, s, "max_rate_mm_min", true)?;
        let accel_mm_s2 = self.number(&a.accel_mm_s2, s, "accel_mm_s2", true)?;

        let travel = match (&a.travel_min_mm, &a.travel_max_mm) {
            (Some(lo), Some(hi)) => {
                let min_mm = self.finite(lo, s, "travel_min_mm")?;
                let max_mm = self.finite(hi, s, "travel_max_mm")?;
                if max_mm <= min_mm {
                    return self.err(
                        Some(hi.span().start),
                        s,
                        "travel_max_mm",
                        format!("must be > travel_min_mm ({min_mm})"),
                    );
                }
                Some(Travel { min_mm, max_mm })
            }
            (None, None) if kind != AxisKind::Linear => None,
            (None, None) => {
                return self.err(
                    Some(spanned.span().start),
                    s,
                    "travel_min_mm",
                    "is required for a linear axis (with travel_max_mm)",
                );
            }
            (Some(lo), None) => {
                return self.err(
                    Some(lo.span().start),
                    s,
                    "travel_max_mm",
                    "is required when travel_min_mm is given",
                );
            }
            (None, Some(hi)) => {
                return self.err(
                    Some(hi.span().start),
                    s,
                    "travel_min_mm",
                    "is required when travel_max_mm is given",
                );
            }
        };

        let start_mm = match &a.start_mm {
            Some(v) => {
                let x = self.finite(v, s, "start_mm")?;
                if let Some(t) = travel
                    && !(t.min_mm..=t.max_mm).contains(&x)
                {
                    return self.err(
                        Some(v.span().start),
                        s,
                        "start_mm",
                        format!("must be within travel ({} ..= {})", t.min_mm, t.max_mm),
                    );
                }
                x
            }
            None => travel.map_or(0.0, |t| (t.min_mm + t.max_mm) / 2.0),
        };

        let ns = |v: &Option<Spanned<i64>>, field: &str, default: u32| -> Res<u32> {
            match v {
                Some(v) => Ok(self.integer(v, s, field, 1..=1_000_000)? as u32),
                None => Ok(default),
            }
        };
        let step_timing = StepTiming {
            min_pulse_ns: ns(
                &a.min_pulse_ns,
                "min_pulse_ns",
                StepTiming::CONSERVATIVE.min_pulse_ns,
            )?,
            dir_setup_ns: ns(
                &a.dir_setup_ns,
                "dir_setup_ns",
                StepTiming::CONSERVATIVE.dir_setup_ns,
            )?,
        };

        // The fastest step rate must fit the driver's pulse timing (a high and a low time per
        // step) and the virtual clock (two ticks per step, one per edge).
        let max_steps_s = max_rate_mm_min / 60.0 * steps_per_mm;
        let pulse_limit = 1e9 / (2.0 * f64::from(step_timing.min_pulse_ns));
        let clock_limit = f64::from(tick_hz) / 2.0;
        let limit = pulse_limit.min(clock_limit);
        if max_steps_s > limit {
            return self.err(
                Some(a.max_rate_mm_min.span().start),
                s,
                "max_rate_mm_min",
                format!(
                    "needs {max_steps_s:.0} steps/s, more than the {limit:.0} steps/s that \
                     min_pulse_ns and tick_hz allow"
                ),
            );
        }

        let mut switches: Vec<SwitchConfig> = Vec::new();
        for sw in &a.switches {
            let r = sw.get_ref();
            let side = self.choice(
                &r.side,
                s,
                "switch.side",
                &[("min", SwitchSide::Min), ("max", SwitchSide::Max)],
            )?;
            if switches.iter().any(|o| o.side == side) {
                return self.err(
                    Some(r.side.span().start),
                    s,
                    "switch.side",
                    "is used by another switch of this axis",
                );
            }
            let position_mm = self.finite(&r.position_mm, s, "switch.position_mm")?;
            let polarity = self.polarity(r.polarity.as_ref(), s, "switch.polarity")?;
            switches.push(SwitchConfig {
                side,
                position_mm,
                polarity,
            });
        }

        let homing = match &a.homing {
            Some(h) => {
                let h = h.get_ref();
                let direction = self.choice(
                    &h.direction,
                    s,
                    "homing.direction",
                    &[
                        ("negative", Direction::Negative),
                        ("positive", Direction::Positive),
                    ],
                )?;
                let needed = match direction {
                    Direction::Negative => SwitchSide::Min,
                    Direction::Positive => SwitchSide::Max,
                };
                if !switches.iter().any(|sw| sw.side == needed) {
                    let side = if needed == SwitchSide::Min {
                        "min"
                    } else {
                        "max"
                    };
                    return self.err(
                        Some(h.direction.span().start),
                        s,
                        "homing.direction",
                        format!("needs a switch with side = \"{side}\" on this axis"),
                    );
                }
                let seek_mm_min = self.number(&h.seek_mm_min, s, "homing.seek_mm_min", true)?;
                let locate_mm_min =
                    self.number(&h.locate_mm_min, s, "homing.locate_mm_min", true)?;
                if locate_mm_min > seek_mm_min {
                    return self.err(
                        Some(h.locate_mm_min.span().start),
                        s,
                        "homing.locate_mm_min",
                        format!("must be <= homing.seek_mm_min ({seek_mm_min})"),
                    );
                }
                if seek_mm_min > max_rate_mm_min {
                    return self.err(
                        Some(h.seek_mm_min.span().start),
                        s,
                        "homing.seek_mm_min",
                        format!("must be <= max_rate_mm_min ({max_rate_mm_min})"),
                    );
                }
                let pull_off_mm = self.number(&h.pull_off_mm, s, "homing.pull_off_mm", false)?;
                Some(HomingConfig {
                    direction,
                    seek_mm_min,
                    locate_mm_min,
                    pull_off_mm,
                })
            }
            None => None,
        };

        Ok(AxisConfig {
            letter,
            kind,
            steps_per_mm,
            max_rate_mm_min,
            accel_mm_s2,
            travel,
            start_mm,
            homing,
            switches,
            step_timing,
        })
    }

    fn name(&self, v: &Spanned<String>, what: &str) -> Res<String> {
        let n = v.get_ref().trim();
        if n.is_empty()
            || !n
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            return self.err(
                Some(v.span().start),
                what,
                "name",
                format!(
                    "must be letters, digits, '_' or '-' (is \"{}\")",
                    v.get_ref()
                ),
            );
        }
        Ok(n.to_string())
    }

    fn heater(&self, h: &RawHeater) -> Res<HeaterConfig> {
        let name = self.name(&h.name, "heater")?;
        let s = format!("heater {name}");
        let s = s.as_str();
        let power_w = self.number(&h.power_w, s, "power_w", true)?;
        let heat_capacity_j_per_k =
            self.number(&h.heat_capacity_j_per_k, s, "heat_capacity_j_per_k", true)?;
        let loss_w_per_k = self.number(&h.loss_w_per_k, s, "loss_w_per_k", true)?;
        let ambient_c = match &h.ambient_c {
            Some(v) => self.finite(v, s, "ambient_c")?,
            None => 25.0,
        };
        let start_c = match &h.start_c {
            Some(v) => self.finite(v, s, "start_c")?,
            None => ambient_c,
        };
        Ok(HeaterConfig {
            name,
            power_w,
            heat_capacity_j_per_k,
            loss_w_per_k,
            ambient_c,
            start_c,
        })
    }

    fn output(&self, o: &RawOutput) -> Res<OutputConfig> {
        let name = self.name(&o.name, "output")?;
        let s = format!("output {name}");
        let max_duty = self.integer(&o.max_duty, &s, "max_duty", 1..=i64::from(u16::MAX))? as u16;
        Ok(OutputConfig { name, max_duty })
    }

    fn digital_output(&self, o: &RawDigitalOutput) -> Res<DigitalOutputConfig> {
        let name = self.name(&o.name, "digital_output")?;
        let active = match &o.active {
            Some(a) => self.choice(
                a,
                &format!("digital_output {name}"),
                "active",
                &[("high", PinState::High), ("low", PinState::Low)],
            )?,
            None => PinState::High,
        };
        Ok(DigitalOutputConfig { name, active })
    }

    fn beeper(&self, b: &RawBeeper) -> Res<BeeperConfig> {
        let mut beeper = BeeperConfig::default();
        if let Some(n) = &b.waiting_tones {
            let range = *WAITING_TONES.start() as i64..=*WAITING_TONES.end() as i64;
            beeper.waiting_tones = self.integer(n, "beeper", "waiting_tones", range)? as usize;
        }
        Ok(beeper)
    }

    /// A switch's polarity: normally open unless the file says otherwise.
    fn polarity(
        &self,
        v: Option<&Spanned<String>>,
        section: &str,
        field: &str,
    ) -> Res<SwitchPolarity> {
        match v {
            Some(p) => self.choice(
                p,
                section,
                field,
                &[
                    ("normally_open", SwitchPolarity::NormallyOpen),
                    ("normally_closed", SwitchPolarity::NormallyClosed),
                ],
            ),
            None => Ok(SwitchPolarity::NormallyOpen),
        }
    }

    fn probe(&self, spanned: &Spanned<RawProbe>, axes: &[AxisConfig]) -> Res<ProbeConfig> {
        let p = spanned.get_ref();
        let (letter, at) = match &p.axis {
            Some(a) => (a.get_ref().as_str(), a.span().start),
            None => ("Z", spanned.span().start),
        };
        let mut chars = letter.chars();
        let axis = match (chars.next(), chars.next()) {
            (Some(c), None) => axes.iter().position(|a| a.letter == c),
            _ => None,
        };
        let Some(axis) = axis else {
            let names: Vec<String> = axes.iter().map(|a| format!("\"{}\"", a.letter)).collect();
            return self.err(
                Some(at),
                "probe",
                "axis",
                format!(
                    "must be an axis of the machine: one of {} (is \"{letter}\")",
                    names.join(", ")
                ),
            );
        };
        if axes[axis].kind == AxisKind::Extruder {
            return self.err(
                Some(at),
                "probe",
                "axis",
                format!("must not be the extruder (is \"{letter}\")"),
            );
        }
        Ok(ProbeConfig {
            axis,
            position_mm: self.finite(&p.position_mm, "probe", "position_mm")?,
            polarity: self.polarity(p.polarity.as_ref(), "probe", "polarity")?,
        })
    }

    fn link(&self, l: &RawLink) -> Res<LinkConfig> {
        let mut link = LinkConfig::default();
        if let Some(b) = &l.tcp_bind {
            link.tcp_bind = match b.get_ref().parse::<IpAddr>() {
                Ok(ip) => ip,
                Err(_) => {
                    return self.err(
                        Some(b.span().start),
                        "link",
                        "tcp_bind",
                        format!("must be an IP address (is \"{}\")", b.get_ref()),
                    );
                }
            };
        }
        if let Some(p) = &l.tcp_port {
            link.tcp_port = self.integer(p, "link", "tcp_port", 0..=i64::from(u16::MAX))? as u16;
        }
        if let Some(p) = &l.http_port {
            link.http_port = self.integer(p, "link", "http_port", 0..=i64::from(u16::MAX))? as u16;
        }
        Ok(link)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = r#"
[[axis]]
letter = "X"
steps_per_mm = 80
max_rate_mm_min = 6000
accel_mm_s2 = 500
travel_min_mm = 0
travel_max_mm = 300
"#;

    fn invalid(text: &str) -> MachineFileError {
        match MachineConfig::from_toml_str(text) {
            Ok(_) => panic!("accepted:\n{text}"),
            Err(e) => e,
        }
    }

    #[test]
    fn bundled_files_are_valid() {
        for (name, text) in BUNDLED {
            let m = MachineConfig::from_toml_str(text)
                .unwrap_or_else(|e| panic!("bundled machine {name}: {e}"));
            assert!(!m.axes.is_empty());
        }
        let router = MachineConfig::default_router();
        let letters: String = router.axes.iter().map(|a| a.letter).collect();
        assert_eq!(letters, "XYZA");
        assert_eq!(router.axes[0].steps_per_mm, 80.0);
        assert_eq!(router.axes[2].steps_per_mm, 400.0);
        assert_eq!(router.axes[3].kind, AxisKind::Rotary);
        assert_eq!(router.tick_hz, DEFAULT_TICK_HZ);
        assert_eq!(router.link.tcp_port, DEFAULT_TCP_PORT);
        assert_eq!(router.link.http_port, DEFAULT_HTTP_PORT);
        let printer =
            MachineConfig::from_toml_str(MachineConfig::bundled_toml("printer").unwrap()).unwrap();
        assert_eq!(printer.heaters.len(), 2);
        assert_eq!(printer.axis_index('e'), Some(3));
        assert_eq!(printer.beeper, Some(BeeperConfig { waiting_tones: 4 }));
        assert_eq!(router.beeper, None);
    }

    #[test]
    fn minimal_file_gets_defaults() {
        let m = MachineConfig::from_toml_str(MINIMAL).unwrap();
        let x = &m.axes[0];
        assert_eq!(x.kind, AxisKind::Linear);
        assert_eq!(x.start_mm, 150.0);
        assert_eq!(x.step_timing, StepTiming::CONSERVATIVE);
        assert_eq!(x.mm_to_steps(1.5), 120);
        assert_eq!(x.steps_to_mm(-80), -1.0);
        assert!(x.homing.is_none() && x.switches.is_empty());
        assert_eq!(m.link, LinkConfig::default());
        assert_eq!(m.beeper, None);
    }

    #[test]
    fn a_beeper_keeps_at_least_marlins_four_tones_waiting() {
        let m = MachineConfig::from_toml_str(&format!("{MINIMAL}[beeper]\n")).unwrap();
        assert_eq!(m.beeper, Some(BeeperConfig { waiting_tones: 4 }));
        let m = MachineConfig::from_toml_str(&format!("{MINIMAL}[beeper]\nwaiting_tones = 16\n"))
            .unwrap();
        assert_eq!(m.beeper, Some(BeeperConfig { waiting_tones: 16 }));
        let e = invalid(&format!("{MINIMAL}[beeper]\nwaiting_tones = 3\n"));
        assert_eq!(
            e.to_string(),
            "machine file line 10: beeper: waiting_tones must be in 4..=64 (is 3)"
        );
        let e = invalid(&format!("{MINIMAL}[beeper]\npitch_hz = 2700\n"));
        assert!(e.to_string().contains("pitch_hz"), "{e}");
    }

    #[test]
    fn a_probe_closes_along_its_axis_normally_open_by_default() {
        let router = MachineConfig::default_router();
        assert_eq!(
            router.probe,
            Some(ProbeConfig {
                axis: 2,
                position_mm: 20.0,
                polarity: SwitchPolarity::NormallyOpen
            })
        );
        let printer =
            MachineConfig::from_toml_str(MachineConfig::bundled_toml("printer").unwrap()).unwrap();
        assert_eq!(printer.probe, None);
        assert_eq!(MachineConfig::from_toml_str(MINIMAL).unwrap().probe, None);

        let m = MachineConfig::from_toml_str(&format!(
            "{MINIMAL}[probe]\naxis = \"X\"\nposition_mm = -2\npolarity = \"normally_closed\"\n"
        ))
        .unwrap();
        assert_eq!(
            m.probe,
            Some(ProbeConfig {
                axis: 0,
                position_mm: -2.0,
                polarity: SwitchPolarity::NormallyClosed
            })
        );
    }

    #[test]
    fn probe_errors_name_the_probe_and_the_field() {
        // No axis given: Z, which this machine does not have.
        let e = invalid(&format!("{MINIMAL}[probe]\nposition_mm = 20\n"));
        assert_eq!(e.field(), Some("axis"));
        assert_eq!(e.line(), Some(9), "{e}");
        assert_eq!(
            e.to_string(),
            "machine file line 9: probe: axis must be an axis of the machine: one of \"X\" \
             (is \"Z\")"
        );
        let e = invalid(&format!(
            "{MINIMAL}[probe]\naxis = \"XY\"\nposition_mm = 20\n"
        ));
        assert_eq!((e.field(), e.line()), (Some("axis"), Some(10)), "{e}");
        let e = invalid(&format!(
            "{MINIMAL}[probe]\naxis = \"X\"\nposition_mm = nan\n"
        ));
        assert_eq!(
            e.to_string(),
            "machine file line 11: probe: position_mm must be a finite number"
        );
        let e = invalid(&format!(
            "{MINIMAL}[probe]\naxis = \"X\"\nposition_mm = \"low\"\n"
        ));
        assert!(matches!(e, MachineFileError::Syntax { .. }), "{e}");
        assert_eq!(e.line(), Some(11), "{e}");
        let e = invalid(&format!("{MINIMAL}[probe]\naxis = \"X\"\n"));
        assert!(e.to_string().contains("position_mm"), "{e}");
        let e = invalid(&format!(
            "{MINIMAL}[probe]\naxis = \"X\"\nposition_mm = 0\npolarity = \"open\"\n"
        ));
        assert_eq!((e.field(), e.line()), (Some("polarity"), Some(12)), "{e}");
        assert!(e.to_string().contains("\"normally_closed\""), "{e}");
        let e = invalid(&format!(
            "{MINIMAL}[probe]\naxis = \"X\"\nposition_mm = 0\nside = \"min\"\n"
        ));
        assert!(e.to_string().contains("side"), "{e}");
        let printer = MachineConfig::bundled_toml("printer").unwrap();
        let e = invalid(&format!(
            "{printer}\n[probe]\naxis = \"E\"\nposition_mm = 0\n"
        ));
        assert_eq!(e.field(), Some("axis"));
        assert!(e.to_string().contains("extruder"), "{e}");
    }

    #[test]
    fn bad_value_names_line_section_and_field() {
        let text = MINIMAL.replace("steps_per_mm = 80", "steps_per_mm = 0");
        let e = invalid(&text);
        assert_eq!(e.line(), Some(4));
        assert_eq!(e.field(), Some("steps_per_mm"));
        assert_eq!(
            e.to_string(),
            "machine file line 4: axis X: steps_per_mm must be > 0"
        );
    }

    #[test]
    fn errors_in_the_default_file_point_at_the_right_line() {
        let text = MachineConfig::bundled_toml("default").unwrap();
        // Break the Y axis's steps_per_mm and check the error names its line.
        let y_at = text.find("letter = \"Y\"").unwrap();
        let rel = text[y_at..].find("steps_per_mm").unwrap();
        let at = y_at + rel;
        let line = line_of(text, at);
        let end = at + text[at..].find('\n').unwrap();
        let broken = format!("{}steps_per_mm = -80.0{}", &text[..at], &text[end..]);
        let e = invalid(&broken);
        assert_eq!(
            e.to_string(),
            format!("machine file line {line}: axis Y: steps_per_mm must be > 0")
        );
    }

    #[test]
    fn a_second_axis_with_the_same_letter_is_refused_at_its_line() {
        let text = MachineConfig::bundled_toml("default").unwrap();
        // Rename the Y axis to X: the error points at the second `letter = "X"`.
        let y_at = text.find("letter = \"Y\"").unwrap();
        let line = line_of(text, y_at);
        let twice = text.replacen("letter = \"Y\"", "letter = \"X\"", 1);
        let e = invalid(&twice);
        assert_eq!(
            e.to_string(),
            format!("machine file line {line}: axis X: letter is used by another axis")
        );
    }

    #[test]
    fn syntax_and_type_errors_carry_a_line() {
        let e = invalid(&MINIMAL.replace("accel_mm_s2 = 500", "accel_mm_s2 = \"fast\""));
        assert!(matches!(e, MachineFileError::Syntax { .. }));
        assert_eq!(e.line(), Some(6), "{e}");
        let e = invalid(&format!("{MINIMAL}stepz_per_mm = 3\n"));
        assert!(e.to_string().contains("stepz_per_mm"), "{e}");
        let e = invalid(&MINIMAL.replace("accel_mm_s2 = 500\n", ""));
        assert!(e.to_string().contains("accel_mm_s2"), "{e}");
        let e = invalid("[[axis]\n");
        assert_eq!(e.line(), Some(1), "{e}");
    }

    #[test]
    fn consistency_errors() {
        let dup = format!("{MINIMAL}{MINIMAL}");
        let e = invalid(&dup);
        assert_eq!(e.field(), Some("letter"));
        assert_eq!(e.line(), Some(11));

        let e = invalid(&MINIMAL.replace("travel_max_mm = 300", "travel_max_mm = -1"));
        assert_eq!(e.field(), Some("travel_max_mm"));

        let e = invalid(&MINIMAL.replace("travel_min_mm = 0\ntravel_max_mm = 300\n", ""));
        assert_eq!(e.field(), Some("travel_min_mm"));

        let e = invalid(&MINIMAL.replace("\"X\"", "\"Q\""));
        assert_eq!(e.field(), Some("letter"));

        let e = invalid(&format!(
            "{MINIMAL}[axis.homing]\ndirection = \"negative\"\nseek_mm_min = 1000\n\
             locate_mm_min = 100\npull_off_mm = 1\n"
        ));
        assert_eq!(e.field(), Some("homing.direction"));
        assert_eq!(e.line(), Some(10));

        let e = invalid(&format!(
            "{MINIMAL}[[axis.switch]]\nside = \"min\"\nposition_mm = 0\npolarity = \"open\"\n"
        ));
        assert_eq!(e.field(), Some("switch.polarity"));
        assert!(e.to_string().contains("\"normally_open\""), "{e}");

        // 6000 mm/min at 8000 steps/mm is 800 kHz: beyond a 2 µs pulse driver.
        let e = invalid(&MINIMAL.replace("steps_per_mm = 80", "steps_per_mm = 8000"));
        assert_eq!(e.field(), Some("max_rate_mm_min"));

        let e = invalid(&format!("tick_hz = 5\n{MINIMAL}"));
        assert_eq!((e.field(), e.line()), (Some("tick_hz"), Some(1)));

        let e = invalid(&format!("{MINIMAL}[link]\ntcp_port = 70000\n"));
        assert_eq!(e.field(), Some("tcp_port"));
        let e = invalid(&format!("{MINIMAL}[link]\nhttp_port = -1\n"));
        assert_eq!(e.field(), Some("http_port"));
        let e = invalid(&format!("{MINIMAL}[link]\ntcp_bind = \"localhost:1\"\n"));
        assert_eq!(e.field(), Some("tcp_bind"));
    }

    #[test]
    fn heaters_and_outputs() {
        let text = format!(
            "{MINIMAL}[[heater]]\nname = \"bed\"\npower_w = 200\nheat_capacity_j_per_k = 400\n\
             loss_w_per_k = 0\n"
        );
        let e = invalid(&text);
        assert_eq!(
            e.to_string(),
            "machine file line 13: heater bed: loss_w_per_k must be > 0"
        );
        let e = invalid(&format!(
            "{MINIMAL}[[output]]\nname = \"fan\"\nmax_duty = 0\n"
        ));
        assert_eq!(e.field(), Some("max_duty"));
        let e = invalid(&format!(
            "{MINIMAL}[[output]]\nname = \"fan\"\nmax_duty = 255\n[[output]]\nname = \"fan\"\nmax_duty = 1\n"
        ));
        assert_eq!(e.field(), Some("name"));
    }

    #[test]
    fn digital_outputs_are_active_high_by_default_and_named_once() {
        let router = MachineConfig::default_router();
        assert_eq!(
            router.digital_outputs,
            [
                DigitalOutputConfig {
                    name: FLOOD.to_string(),
                    active: PinState::High
                },
                DigitalOutputConfig {
                    name: MIST.to_string(),
                    active: PinState::High
                }
            ]
        );
        assert_eq!(
            (router.flood_output(), router.mist_output()),
            (Some(0), Some(1))
        );
        assert!(
            MachineConfig::from_toml_str(MINIMAL)
                .unwrap()
                .digital_outputs
                .is_empty()
        );

        let m = MachineConfig::from_toml_str(&format!(
            "{MINIMAL}[[digital_output]]\nname = \"vacuum\"\nactive = \"low\"\n\
             [[digital_output]]\nname = \"mist\"\n"
        ))
        .unwrap();
        assert_eq!(m.digital_outputs[0].active, PinState::Low);
        assert_eq!((m.flood_output(), m.mist_output()), (None, Some(1)));
        assert_eq!(m.digital_output_index("vacuum"), Some(0));

        let e = invalid(&format!(
            "{MINIMAL}[[digital_output]]\nname = \"flood\"\n[[digital_output]]\nname = \"flood\"\n"
        ));
        assert_eq!(
            e.to_string(),
            "machine file line 12: digital_output flood: name is used by another digital_output"
        );
        let e = invalid(&format!(
            "{MINIMAL}[[digital_output]]\nname = \"flood\"\nactive = \"on\"\n"
        ));
        assert_eq!(
            e.to_string(),
            "machine file line 11: digital_output flood: active must be one of \"high\", \
             \"low\" (is \"on\")"
        );
        let e = invalid(&format!(
            "{MINIMAL}[[digital_output]]\nname = \"flood coolant\"\n"
        ));
        assert_eq!((e.field(), e.line()), (Some("name"), Some(10)), "{e}");
        // Unknown and missing fields are syntax errors at their line.
        let e = invalid(&format!(
            "{MINIMAL}[[digital_output]]\nname = \"flood\"\nmax_duty = 1\n"
        ));
        assert!(matches!(e, MachineFileError::Syntax { .. }), "{e}");
        assert!(e.to_string().contains("max_duty"), "{e}");
        let e = invalid(&format!("{MINIMAL}[[digital_output]]\nactive = \"low\"\n"));
        assert!(e.to_string().contains("name"), "{e}");
    }

    #[test]
    fn names_and_sides_say_what_the_parts_are() {
        let router = MachineConfig::default_router();
        assert_eq!(router.slowest_step_timing(), StepTiming::CONSERVATIVE);
        assert_eq!((router.bed_heater(), router.hot_end_heater()), (None, None));
        assert_eq!(router.spindle_output(), Some(0));
        assert_eq!(router.fan_outputs().count(), 0);
        let sides: Vec<_> = router
            .axes
            .iter()
            .map(|a| a.homing_switch().map(|s| s.side))
            .collect();
        // X and Y have switches at both ends; Z homes up; A does not home.
        assert_eq!(
            sides,
            [
                Some(SwitchSide::Min),
                Some(SwitchSide::Min),
                Some(SwitchSide::Max),
                None
            ]
        );

        let printer =
            MachineConfig::from_toml_str(MachineConfig::bundled_toml("printer").unwrap()).unwrap();
        assert_eq!(
            (printer.bed_heater(), printer.hot_end_heater()),
            (Some(1), Some(0))
        );
        assert_eq!(printer.spindle_output(), None);
        assert_eq!(printer.fan_outputs().collect::<Vec<_>>(), [0]);
    }
}
