//! The controller's settings: the keys of frame 00/50, their values, and how they are kept.
//!
//! A [`Settings`] holds the machine configuration the kernel is built from, plus the settings
//! of the link. A board loads it at start-up ([`Settings::load`]) from its record storage,
//! builds the kernel from [`Settings::machine`], and gives both to the controller, which
//! answers frame 00 (set or read) with frame 50 (`key=value`) and writes every change to the
//! storage at once.
//!
//! # Keys
//!
//! | key | value | record key |
//! |---|---|---|
//! | `<axis>.steps_per_mm` | steps per mm (per degree for a rotary axis), `> 0` | `0x0100 + 8·(letter − 'A') + 0` |
//! | `<axis>.max_rate` | maximum rate, mm/min, `> 0` | `… + 1` |
//! | `<axis>.accel` | acceleration, mm/s², `> 0` | `… + 2` |
//! | `<axis>.min` | lowest machine position, mm | `… + 3` |
//! | `<axis>.max` | highest machine position, mm (`> min`) | `… + 4` |
//! | `<axis>.homing_seek` | homing: fast approach to the switch, mm/min, `> 0`, at most `max_rate` (only an axis that homes) | `… + 5` |
//! | `<axis>.homing_locate` | homing: slow approach, mm/min, `> 0`, at most `homing_seek` | `… + 6` |
//! | `<axis>.homing_pull_off` | homing: back-off and final pull-off, mm, `>= 0`, below the travel | `… + 7` |
//! | `jog_feed` | feed of frame-01 jogs, mm/min | `0x0200` |
//! | `default_feed` | feed of `G1` before any `F`, mm/min | `0x0201` |
//! | `junction_deviation` | mm, `>= 0` | `0x0202` |
//! | `hard_limits` | `0` or `1` | `0x0203` |
//! | `soft_limits` | `off`, `homed` or `always` | `0x0204` |
//! | `keep_alive_ms` | period of frame 55, 100..=600000 ms | `0x0205` |
//! | `link.ssid` | network name for a WiFi board, at most 32 bytes | `0x0206` |
//! | `link.password` | its password, at most 35 bytes; read back as `<hidden>` | `0x0207` |
//! | `power_loss_recovery` | `1` (the default): a running program records its progress for `M1000`; `0`: not (`M413 S0|S1` sets it too) | `0x0208` |
//! | `print_accel` | `M204 P`: acceleration of printing moves, mm/s², `> 0`; `0` (the default): the per-axis limits alone | `0x0209` |
//! | `retract_accel` | `M204 R`: of retracting moves, as `print_accel` | `0x020A` |
//! | `travel_accel` | `M204 T`: of travel moves, as `print_accel` | `0x020B` |
//! | `min_print_feed` | `M205 S`: the slowest feed of printing moves, mm/s, `>= 0` | `0x020C` |
//! | `min_travel_feed` | `M205 T`: the slowest feed of travel moves, mm/s, `>= 0` | `0x020D` |
//! | `status_mask` | grbl's `$10`: bit 0 reports `MPos` (else `WPos`), bit 1 the buffer state `Bf`; 0..=255, default 1 | `0x020E` |
//! | `arc_tolerance` | grbl's `$12`: largest distance between an arc and its chords, mm, `> 0` | `0x020F` |
//! | `report_inches` | grbl's `$13`: `1`: grbl's reports give positions and rates in inches; `0` (the default): mm | `0x0210` |
//! | `laser_mode` | grbl's `$32`: `1`: the spindle output is a laser's (`M4` power follows the speed, off in rapids); `0` (the default): a spindle | `0x0211` |
//! | `startup_line0`, `startup_line1` | grbl's `$N0`, `$N1`: a G-code line run at every grbl reset and at power-on, at most [`MAX_STARTUP_LINE_LEN`] bytes; empty (the default): none | `0x0212`, `0x0213` |
//!
//! `<axis>` is the axis letter in lower case (`x.steps_per_mm`); keys are matched without
//! regard to case. A value is refused (and nothing changes) when it does not parse, or when the
//! machine configuration it makes does not validate, with the configuration error's code.
//! Values are stored with `postcard` (an `f32`, a `bool`, a `u32`, the `SoftLimits` enum or a
//! string), one record per key. The homing keys exist only for an axis that homes (frame 00
//! names no other, and frame 50's list leaves them out).
//!
//! Settings take effect when the board next builds the kernel (at its next start): the kernel
//! is built once from [`Settings::machine`] and given [`Settings::path_limits`]. The grbl
//! dialect's own (`status_mask`, `report_inches`, `laser_mode`, the startup lines) take effect
//! at once. `M500` stores the planner settings the kernel runs with (`M92`, `M201`, `M203`,
//! `M204`, `M205`), `M501` gives it the stored ones, `M502` the board's defaults
//! ([`Settings::defaults`]), `M503` reports them (`forja_app::controller`). Frame 50 answers
//! with the stored value.
//! Frames carry no `*`, so a password containing `*` cannot be set over the link.

use core::fmt;

use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::{Error as _, ErrorKind};
use forja_protocol::error::WireError;
use forja_protocol::gcode::Decimal;
use serde::Serialize;
use serde::de::DeserializeOwned;

use super::text::Text;
use crate::error::StoreRefusal;
use forja_hal_abstraction::program::StoreError;
use forja_motion::PathLimits;
use forja_motion::config::{AxisConfig, HomingConfig, MachineConfig, SoftLimits};
use forja_motion::error::ConfigError;
use forja_protocol::gcode::MAX_LINE_LEN;

/// The period of frame 55 when no setting says otherwise, ms.
pub const DEFAULT_KEEP_ALIVE_MS: u32 = 1000;

/// The longest network name `link.ssid` takes.
pub const MAX_SSID_LEN: usize = 32;

/// The longest password `link.password` takes (what one frame 00 can carry after the key).
pub const MAX_PASSWORD_LEN: usize = 35;

/// The longest startup line (`startup_line0`, `startup_line1`): what a `$N0=` line of
/// [`MAX_LINE_LEN`] bytes carries after its `$N0=`.
pub const MAX_STARTUP_LINE_LEN: usize = MAX_LINE_LEN - 4;

/// The room for one stored value: a startup line with its `postcard` length.
const RECORD_LEN: usize = MAX_STARTUP_LINE_LEN + 4;

/// The first record key of the axis settings.
pub const AXIS_RECORDS: u16 = 0x0100;

/// The first record key of the machine-wide settings.
pub const GLOBAL_RECORDS: u16 = 0x0200;

/// One per-axis setting.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AxisField {
    /// `steps_per_mm`.
    StepsPerMm,
    /// `max_rate`, mm/min.
    MaxRate,
    /// `accel`, mm/s².
    Accel,
    /// `min`, mm.
    Min,
    /// `max`, mm.
    Max,
    /// `homing_seek`, mm/min (an axis that homes).
    HomingSeek,
    /// `homing_locate`, mm/min (an axis that homes).
    HomingLocate,
    /// `homing_pull_off`, mm (an axis that homes).
    HomingPullOff,
}

impl AxisField {
    const ALL: [AxisField; 8] = [
        Self::StepsPerMm,
        Self::MaxRate,
        Self::Accel,
        Self::Min,
        Self::Max,
        Self::HomingSeek,
        Self::HomingLocate,
        Self::HomingPullOff,
    ];

    fn name(self) -> &'static str {
        match self {
            Self::StepsPerMm => "steps_per_mm",
            Self::MaxRate => "max_rate",
            Self::Accel => "accel",
            Self::Min => "min",
            Self::Max => "max",
            Self::HomingSeek => "homing_seek",
            Self::HomingLocate => "homing_locate",
            Self::HomingPullOff => "homing_pull_off",
        }
    }

    /// The field's value on axis `a` (0 for a homing field of an axis that does not home).
    pub(crate) fn value_of(self, a: &AxisConfig) -> f32 {
        let homing = |f: fn(&HomingConfig) -> f32| a.homing.as_ref().map_or(0.0, f);
        match self {
            Self::StepsPerMm => a.steps_per_mm,
            Self::MaxRate => a.max_rate_mm_min,
            Self::Accel => a.accel_mm_s2,
            Self::Min => a.min_mm,
            Self::Max => a.max_mm,
            Self::HomingSeek => homing(|h| h.seek_mm_min),
            Self::HomingLocate => homing(|h| h.locate_mm_min),
            Self::HomingPullOff => homing(|h| h.pull_off_mm),
        }
    }

    /// Whether the field is one of the axis's homing settings.
    fn is_homing(self) -> bool {
        matches!(
            self,
            Self::HomingSeek | Self::HomingLocate | Self::HomingPullOff
        )
    }
}

/// A setting, named by a key of the table in the [module documentation](self).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Key {
    /// A per-axis setting of axis index `axis`.
    Axis {
        /// The axis index in the machine configuration.
        axis: usize,
        /// Which setting.
        field: AxisField,
    },
    /// `jog_feed`.
    JogFeed,
    /// `default_feed`.
    DefaultFeed,
    /// `junction_deviation`.
    JunctionDeviation,
    /// `hard_limits`.
    HardLimits,
    /// `soft_limits`.
    SoftLimits,
    /// `keep_alive_ms`.
    KeepAliveMs,
    /// `link.ssid`.
    LinkSsid,
    /// `link.password`.
    LinkPassword,
    /// `power_loss_recovery`.
    PowerLossRecovery,
    /// `print_accel`.
    PrintAccel,
    /// `retract_accel`.
    RetractAccel,
    /// `travel_accel`.
    TravelAccel,
    /// `min_print_feed`.
    MinPrintFeed,
    /// `min_travel_feed`.
    MinTravelFeed,
    /// `status_mask` (grbl's `$10`).
    StatusMask,
    /// `arc_tolerance` (grbl's `$12`).
    ArcTolerance,
    /// `report_inches` (grbl's `$13`).
    ReportInches,
    /// `laser_mode` (grbl's `$32`).
    LaserMode,
    /// `startup_line0` or `startup_line1` (grbl's `$N0`, `$N1`), by index.
    StartupLine(u8),
}

const GLOBALS: [(&str, Key); 20] = [
    ("jog_feed", Key::JogFeed),
    ("default_feed", Key::DefaultFeed),
    ("junction_deviation", Key::JunctionDeviation),
    ("hard_limits", Key::HardLimits),
    ("soft_limits", Key::SoftLimits),
    ("keep_alive_ms", Key::KeepAliveMs),
    ("link.ssid", Key::LinkSsid),
    ("link.password", Key::LinkPassword),
    ("power_loss_recovery", Key::PowerLossRecovery),
    ("print_accel", Key::PrintAccel),
    ("retract_accel", Key::RetractAccel),
    ("travel_accel", Key::TravelAccel),
    ("min_print_feed", Key::MinPrintFeed),
    ("min_travel_feed", Key::MinTravelFeed),
    ("status_mask", Key::StatusMask),
    ("arc_tolerance", Key::ArcTolerance),
    ("report_inches", Key::ReportInches),
    ("laser_mode", Key::LaserMode),
    ("startup_line0", Key::StartupLine(0)),
    ("startup_line1", Key::StartupLine(1)),
];

impl Key {
    /// The setting named `name` on `machine`, if any (case-insensitive).
    pub fn parse<const N: usize>(name: &str, machine: &MachineConfig<N>) -> Option<Key> {
        if let Some((_, key)) = GLOBALS.iter().find(|(n, _)| n.eq_ignore_ascii_case(name)) {
            return Some(*key);
        }
        let (letter, field) = name.split_once('.')?;
        let [letter] = letter.as_bytes() else {
            return None;
        };
        let axis = machine.axis_index(letter.to_ascii_uppercase())?;
        let field = AxisField::ALL
            .into_iter()
            .find(|f| f.name().eq_ignore_ascii_case(field))?;
        let key = Key::Axis { axis, field };
        key.applies_to(machine).then_some(key)
    }

    /// Whether `machine` has this setting: the homing settings only on an axis that homes.
    pub fn applies_to<const N: usize>(&self, machine: &MachineConfig<N>) -> bool {
        match *self {
            Key::Axis { axis, field } => machine
                .axes
                .get(axis)
                .is_some_and(|a| !field.is_homing() || a.homing.is_some()),
            _ => true,
        }
    }

    /// Every key of a machine of `N` axes, axes first (the homing keys of every axis among
    /// them: see [`Key::applies_to`]).
    pub fn all<const N: usize>() -> impl Iterator<Item = Key> {
        (0..N)
            .flat_map(|axis| {
                AxisField::ALL
                    .into_iter()
                    .map(move |field| Key::Axis { axis, field })
            })
            .chain(GLOBALS.into_iter().map(|(_, k)| k))
    }

    /// The record key the value is stored under (see the module table).
    pub fn record<const N: usize>(&self, machine: &MachineConfig<N>) -> u16 {
        match *self {
            Key::Axis { axis, field } => {
                let letter = machine.axes.get(axis).map_or(b'A', |a| a.letter);
                AXIS_RECORDS
                    + 8 * u16::from(letter.saturating_sub(b'A'))
                    + AxisField::ALL.iter().position(|f| *f == field).unwrap_or(0) as u16
            }
            key => {
                let index = GLOBALS.iter().position(|(_, k)| *k == key).unwrap_or(0);
                GLOBAL_RECORDS + index as u16
            }
        }
    }

    /// Write the canonical name (`x.steps_per_mm`).
    pub fn write_name<const N: usize>(
        &self,
        machine: &MachineConfig<N>,
        out: &mut impl fmt::Write,
    ) -> fmt::Result {
        match *self {
            Key::Axis { axis, field } => {
                let letter = machine.axes.get(axis).map_or(b'?', |a| a.letter);
                out.write_char(char::from(letter.to_ascii_lowercase()))?;
                out.write_char('.')?;
                out.write_str(field.name())
            }
            key => {
                let name = GLOBALS
                    .iter()
                    .find(|(_, k)| *k == key)
                    .map_or("?", |(n, _)| n);
                out.write_str(name)
            }
        }
    }
}

/// A setting that was not changed (or not read).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum SettingError {
    /// No setting has this key. Code 190.
    UnknownKey,
    /// The value does not parse for this setting, or is out of its range. Code 191.
    BadValue,
    /// The value parses but makes the machine configuration invalid (its code, 100–116).
    Invalid(ConfigError),
    /// The storage failed; the old value is kept (174, or 171 when it is full).
    Storage(StoreError),
}

impl WireError for SettingError {
    fn code(&self) -> u16 {
        match self {
            Self::UnknownKey => 190,
            Self::BadValue => 191,
            Self::Invalid(e) => e.code(),
            Self::Storage(e) => StoreRefusal(*e).code(),
        }
    }

    fn name(&self) -> &'static str {
        match self {
            Self::UnknownKey => "unknown-setting",
            Self::BadValue => "bad-setting",
            Self::Invalid(e) => e.name(),
            Self::Storage(e) => StoreRefusal(*e).name(),
        }
    }
}

impl fmt::Display for SettingError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A [`RecordStorage`] that keeps nothing: reads find nothing, writes succeed. For a board
/// without persistent storage (settings then last until the next start).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NoStorage;

impl forja_hal_abstraction::ErrorType for NoStorage {
    type Error = core::convert::Infallible;
}

impl RecordStorage for NoStorage {
    fn read(&mut self, _: u16, _: &mut [u8]) -> Result<Option<usize>, Self::Error> {
        Ok(None)
    }
    fn write(&mut self, _: u16, _: &[u8]) -> Result<(), Self::Error> {
        Ok(())
    }
    fn remove(&mut self, _: u16) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// What [`Settings::load`] found in the storage.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LoadReport {
    /// Stored values applied.
    pub applied: u16,
    /// Stored values ignored: unreadable, not decodable, or making the configuration invalid.
    pub ignored: u16,
}

/// The settings: the machine configuration and the link's settings.
#[derive(Debug, Clone, Copy)]
pub struct Settings<const N: usize> {
    machine: MachineConfig<N>,
    /// The board's configuration before any stored value (`M502`).
    defaults: MachineConfig<N>,
    /// `M204`, `M205 S`/`T`.
    path: PathLimits,
    keep_alive_ms: u32,
    ssid: Text<MAX_SSID_LEN>,
    password: Text<MAX_PASSWORD_LEN>,
    power_loss_recovery: bool,
    /// grbl's `$10`.
    status_mask: u8,
    /// grbl's `$13`.
    report_inches: bool,
    /// grbl's `$32`.
    laser_mode: bool,
    /// grbl's `$N0`, `$N1`.
    startup: [Text<MAX_STARTUP_LINE_LEN>; 2],
}

/// One setting's value, decoded.
#[derive(Debug, Clone, Copy)]
enum Value<'a> {
    Number(f32),
    Flag(bool),
    Limits(SoftLimits),
    /// A whole number (`keep_alive_ms`, `status_mask`).
    Whole(u32),
    Text(&'a str),
}

/// What [`Settings::load`] made of one key's record.
enum Loaded {
    /// No record.
    Absent,
    /// The record did not read or decode.
    Unreadable,
    /// Applied.
    Applied,
    /// It decodes, but the configuration it makes does not validate (now: another stored
    /// value may make it valid).
    Refused,
}

/// A setting's number as frame 50 and `M500` write it: an `f32`'s seven significant digits
/// (`80`, `0.013`), written as a decimal, not with the float formatting of `core`, which the
/// firmware image then leaves out.
pub(crate) fn write_number(out: &mut impl fmt::Write, v: f32) -> fmt::Result {
    match Decimal::from_f32_significant(v) {
        Some(d) => super::text::write_decimal(out, d),
        None => out.write_str("?"),
    }
}

fn encode<'b>(value: &impl Serialize, buf: &'b mut [u8]) -> Option<&'b [u8]> {
    postcard::to_slice(value, buf).ok().map(|b| &*b)
}

fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Option<T> {
    postcard::from_bytes(bytes).ok()
}

fn store_error(kind: ErrorKind) -> StoreError {
    match kind {
        ErrorKind::Full => StoreError::Full,
        _ => StoreError::Device,
    }
}

impl<const N: usize> Settings<N> {
    /// `machine` with the default link settings (keep-alive every
    /// [`DEFAULT_KEEP_ALIVE_MS`], no network name or password), power-loss recovery on, and
    /// grbl's defaults (`$10=1`, `$13=0`, `$32=0`, no startup lines).
    pub fn new(machine: MachineConfig<N>) -> Self {
        Self {
            defaults: machine,
            path: PathLimits::NONE,
            machine,
            keep_alive_ms: DEFAULT_KEEP_ALIVE_MS,
            ssid: Text::new(),
            password: Text::new(),
            power_loss_recovery: true,
            status_mask: 1,
            report_inches: false,
            laser_mode: false,
            startup: [Text::new(); 2],
        }
    }

    /// `machine` with every value found in `storage` applied over it. A stored value that
    /// cannot be read or decoded, or that would make the configuration invalid, is ignored
    /// (and counted). Values that depend on one another (a homing seek rate lowered below the
    /// default locate rate, and the locate rate with it) are applied whatever order they are
    /// stored in: a value refused is tried again once others were applied.
    ///
    /// Context: thread, at start-up. Blocks for the storage reads.
    pub fn load<S: RecordStorage>(
        machine: MachineConfig<N>,
        storage: &mut S,
    ) -> (Self, LoadReport) {
        let mut settings = Self::new(machine);
        let mut report = LoadReport::default();
        // Keys whose value decodes and was refused: bit `i` for the `i`-th of `Key::all`.
        let mut refused: u128 = 0;
        for (i, key) in Key::all::<N>().enumerate() {
            match settings.load_one(key, storage) {
                Loaded::Absent => {}
                Loaded::Applied => report.applied += 1,
                Loaded::Unreadable => report.ignored += 1,
                Loaded::Refused => match 1u128.checked_shl(i as u32) {
                    Some(bit) => refused |= bit,
                    None => report.ignored += 1,
                },
            }
        }
        let mut progress = true;
        while refused != 0 && progress {
            progress = false;
            for (i, key) in Key::all::<N>().enumerate() {
                let bit = 1u128.checked_shl(i as u32).unwrap_or(0);
                if refused & bit != 0 && matches!(settings.load_one(key, storage), Loaded::Applied)
                {
                    refused &= !bit;
                    report.applied += 1;
                    progress = true;
                }
            }
        }
        report.ignored += refused.count_ones() as u16;
        (settings, report)
    }

    /// Read the record of `key` and apply it, if the configuration it makes validates.
    fn load_one<S: RecordStorage>(&mut self, key: Key, storage: &mut S) -> Loaded {
        let mut buf = [0u8; RECORD_LEN];
        let len = match storage.read(key.record(&self.machine), &mut buf) {
            Ok(Some(len)) => len,
            Ok(None) => return Loaded::Absent,
            Err(_) => return Loaded::Unreadable,
        };
        let bytes = buf.get(..len).unwrap_or(&[]);
        let value = match key {
            Key::HardLimits | Key::PowerLossRecovery | Key::ReportInches | Key::LaserMode => {
                decode::<bool>(bytes).map(Value::Flag)
            }
            Key::SoftLimits => decode::<SoftLimits>(bytes).map(Value::Limits),
            Key::KeepAliveMs | Key::StatusMask => decode::<u32>(bytes).map(Value::Whole),
            Key::LinkSsid | Key::LinkPassword | Key::StartupLine(_) => {
                postcard::from_bytes::<&str>(bytes).ok().map(Value::Text)
            }
            _ => decode::<f32>(bytes).map(Value::Number),
        };
        let Some(value) = value else {
            return Loaded::Unreadable;
        };
        let mut next = *self;
        if next.apply(key, value).is_ok() && next.machine.validate().is_ok() {
            *self = next;
            Loaded::Applied
        } else {
            Loaded::Refused
        }
    }

    /// The board's machine configuration, before any stored value (what `M502` goes back to).
    pub fn defaults(&self) -> &MachineConfig<N> {
        &self.defaults
    }

    /// The path limits (`M204`, `M205 S`/`T`) to give the kernel after it is built.
    pub fn path_limits(&self) -> PathLimits {
        self.path
    }

    /// The machine configuration to build the kernel from.
    pub fn machine(&self) -> &MachineConfig<N> {
        &self.machine
    }

    /// The period of frame 55, ms.
    pub fn keep_alive_ms(&self) -> u32 {
        self.keep_alive_ms
    }

    /// The network name for a WiFi board (empty when not set).
    pub fn ssid(&self) -> &str {
        self.ssid.as_str()
    }

    /// The network password for a WiFi board (empty when not set).
    pub fn password(&self) -> &str {
        self.password.as_str()
    }

    /// Whether a running stored program records its progress, for `M1000` after a power cut.
    pub fn power_loss_recovery(&self) -> bool {
        self.power_loss_recovery
    }

    /// grbl's status report mask (`$10`): bit 0 reports `MPos` (else `WPos`), bit 1 `Bf`.
    pub fn status_mask(&self) -> u8 {
        self.status_mask
    }

    /// Whether grbl's reports give positions and rates in inches (`$13`).
    pub fn report_inches(&self) -> bool {
        self.report_inches
    }

    /// Whether the spindle output drives a laser (grbl's laser mode, `$32`).
    pub fn laser_mode(&self) -> bool {
        self.laser_mode
    }

    /// grbl's startup line `index` (`$N0`, `$N1`); empty when not set or `index` is not 0 or 1.
    pub fn startup_line(&self, index: u8) -> &str {
        self.startup
            .get(usize::from(index))
            .map_or("", |t| t.as_str())
    }

    fn apply(&mut self, key: Key, value: Value<'_>) -> Result<(), SettingError> {
        let m = &mut self.machine;
        match (key, value) {
            (Key::Axis { axis, field }, Value::Number(v)) => {
                let a = m.axes.get_mut(axis).ok_or(SettingError::UnknownKey)?;
                match field {
                    AxisField::StepsPerMm => a.steps_per_mm = v,
                    AxisField::MaxRate => a.max_rate_mm_min = v,
                    AxisField::Accel => a.accel_mm_s2 = v,
                    AxisField::Min => a.min_mm = v,
                    AxisField::Max => a.max_mm = v,
                    AxisField::HomingSeek | AxisField::HomingLocate | AxisField::HomingPullOff => {
                        let h = a.homing.as_mut().ok_or(SettingError::UnknownKey)?;
                        match field {
                            AxisField::HomingSeek => h.seek_mm_min = v,
                            AxisField::HomingLocate => h.locate_mm_min = v,
                            _ => h.pull_off_mm = v,
                        }
                    }
                }
            }
            (Key::ArcTolerance, Value::Number(v)) => m.arc_tolerance_mm = v,
            (Key::StatusMask, Value::Whole(v)) => {
                self.status_mask = u8::try_from(v).map_err(|_| SettingError::BadValue)?;
            }
            (Key::ReportInches, Value::Flag(v)) => self.report_inches = v,
            (Key::LaserMode, Value::Flag(v)) => self.laser_mode = v,
            (Key::StartupLine(i), Value::Text(t)) => {
                let slot = self
                    .startup
                    .get_mut(usize::from(i))
                    .ok_or(SettingError::UnknownKey)?;
                if !slot.set(t.as_bytes()) {
                    return Err(SettingError::BadValue);
                }
            }
            (Key::JogFeed, Value::Number(v)) => m.jog_feed_mm_min = v,
            (Key::DefaultFeed, Value::Number(v)) => m.default_feed_mm_min = v,
            (Key::JunctionDeviation, Value::Number(v)) => m.junction_deviation_mm = v,
            (Key::HardLimits, Value::Flag(v)) => m.hard_limits = v,
            (Key::PowerLossRecovery, Value::Flag(v)) => self.power_loss_recovery = v,
            (Key::PrintAccel | Key::RetractAccel | Key::TravelAccel, Value::Number(v)) => {
                if v < 0.0 {
                    return Err(SettingError::BadValue);
                }
                let cap = (v > 0.0).then_some(v);
                match key {
                    Key::PrintAccel => self.path.print_accel_mm_s2 = cap,
                    Key::RetractAccel => self.path.retract_accel_mm_s2 = cap,
                    _ => self.path.travel_accel_mm_s2 = cap,
                }
            }
            (Key::MinPrintFeed | Key::MinTravelFeed, Value::Number(v)) => {
                if v < 0.0 {
                    return Err(SettingError::BadValue);
                }
                match key {
                    Key::MinPrintFeed => self.path.min_extruding_feed_mm_s = v,
                    _ => self.path.min_travel_feed_mm_s = v,
                }
            }
            (Key::SoftLimits, Value::Limits(v)) => m.soft_limits = v,
            (Key::KeepAliveMs, Value::Whole(v)) if (100..=600_000).contains(&v) => {
                self.keep_alive_ms = v;
            }
            (Key::LinkSsid, Value::Text(t)) => {
                if !self.ssid.set(t.as_bytes()) {
                    return Err(SettingError::BadValue);
                }
            }
            (Key::LinkPassword, Value::Text(t)) => {
                if !self.password.set(t.as_bytes()) {
                    return Err(SettingError::BadValue);
                }
            }
            _ => return Err(SettingError::BadValue),
        }
        Ok(())
    }

    fn parse_value(key: Key, text: &str) -> Result<Value<'_>, SettingError> {
        let number = || {
            Decimal::parse(text.as_bytes())
                .map(Decimal::to_f32)
                .filter(|v| v.is_finite())
                .ok_or(SettingError::BadValue)
        };
        Ok(match key {
            Key::HardLimits | Key::PowerLossRecovery | Key::ReportInches | Key::LaserMode => {
                match text {
                    "0" => Value::Flag(false),
                    "1" => Value::Flag(true),
                    _ => return Err(SettingError::BadValue),
                }
            }
            Key::SoftLimits => Value::Limits(match text {
                t if t.eq_ignore_ascii_case("off") => SoftLimits::Off,
                t if t.eq_ignore_ascii_case("homed") => SoftLimits::WhenHomed,
                t if t.eq_ignore_ascii_case("always") => SoftLimits::Always,
                _ => return Err(SettingError::BadValue),
            }),
            Key::KeepAliveMs | Key::StatusMask => Value::Whole(
                Decimal::parse(text.as_bytes())
                    .and_then(Decimal::as_u32)
                    .ok_or(SettingError::BadValue)?,
            ),
            Key::LinkSsid | Key::LinkPassword | Key::StartupLine(_) => Value::Text(text),
            _ => Value::Number(number()?),
        })
    }

    /// Every setting of the machine and the planner back to the board's defaults, with grbl's
    /// `status_mask`, `report_inches` and `laser_mode`, their stored records removed (grbl's
    /// `$RST=$`); the link's (keep-alive, network name and password, power-loss recovery) are
    /// kept, so that a board on WiFi stays reachable, and so are the startup lines (grbl clears
    /// them with `$RST=*` only).
    ///
    /// Context: thread. Blocks for the storage writes. Errors: the storage's; the settings in
    /// RAM are then unchanged, and the records removed before the failure stay removed (they
    /// were the defaults' anyway at the next start).
    pub fn restore_defaults<S: RecordStorage>(
        &mut self,
        storage: &mut S,
    ) -> Result<(), SettingError> {
        let keep = |k: &Key| {
            matches!(
                k,
                Key::KeepAliveMs
                    | Key::LinkSsid
                    | Key::LinkPassword
                    | Key::PowerLossRecovery
                    | Key::StartupLine(_)
            )
        };
        for key in Key::all::<N>().filter(|k| !keep(k)) {
            storage
                .remove(key.record(&self.machine))
                .map_err(|e| SettingError::Storage(store_error(e.kind())))?;
        }
        self.machine = self.defaults;
        self.path = PathLimits::NONE;
        self.status_mask = 1;
        self.report_inches = false;
        self.laser_mode = false;
        Ok(())
    }

    /// Set `key` to `value` (text as frame 00 carries it), check the machine configuration it
    /// makes with `check`, and store it. Returns the setting. On any error nothing changes,
    /// in RAM or in the storage.
    ///
    /// Context: thread. Blocks for the storage write.
    pub fn set<S: RecordStorage>(
        &mut self,
        key: &str,
        value: &str,
        storage: &mut S,
        check: &dyn Fn(&MachineConfig<N>) -> Result<(), ConfigError>,
    ) -> Result<Key, SettingError> {
        let key = Key::parse(key, &self.machine).ok_or(SettingError::UnknownKey)?;
        self.set_all(&[key], value, storage, check)?;
        Ok(key)
    }

    /// Set every key of `keys` to `value` (grbl's `$25`: the seek rate of every axis that
    /// homes), check the machine configuration they make together with `check`, and store them
    /// one after another. On an error of the values or of `check` nothing changes; on a storage
    /// error the keys stored before it keep their new value (in RAM too).
    ///
    /// Context: thread. Blocks for the storage writes.
    pub fn set_all<S: RecordStorage>(
        &mut self,
        keys: &[Key],
        value: &str,
        storage: &mut S,
        check: &dyn Fn(&MachineConfig<N>) -> Result<(), ConfigError>,
    ) -> Result<(), SettingError> {
        let mut next = *self;
        for &key in keys {
            if !key.applies_to(&self.machine) {
                return Err(SettingError::UnknownKey);
            }
            next.apply(key, Self::parse_value(key, value)?)?;
        }
        check(&next.machine).map_err(SettingError::Invalid)?;
        for &key in keys {
            let parsed = Self::parse_value(key, value)?;
            let mut buf = [0u8; RECORD_LEN];
            let bytes = match parsed {
                Value::Number(v) => encode(&v, &mut buf),
                Value::Flag(v) => encode(&v, &mut buf),
                Value::Limits(v) => encode(&v, &mut buf),
                Value::Whole(v) => encode(&v, &mut buf),
                Value::Text(v) => encode(&v, &mut buf),
            }
            .ok_or(SettingError::BadValue)?;
            storage
                .write(key.record(&self.machine), bytes)
                .map_err(|e| SettingError::Storage(store_error(e.kind())))?;
            self.apply(key, parsed)?;
        }
        Ok(())
    }

    /// Write the setting `key` as frame 50 shows it, `name=value` (`x.steps_per_mm=80`).
    pub fn write_line(&self, key: Key, out: &mut impl fmt::Write) -> fmt::Result {
        key.write_name(&self.machine, out)?;
        out.write_char('=')?;
        self.write_value(key, out)
    }

    /// Write the value of `key` as frame 50 shows it (`<hidden>` for the password).
    pub fn write_value(&self, key: Key, out: &mut impl fmt::Write) -> fmt::Result {
        let m = &self.machine;
        match key {
            Key::Axis { axis, field } => {
                let Some(a) = m.axes.get(axis) else {
                    return Ok(());
                };
                write_number(out, field.value_of(a))
            }
            Key::JogFeed => write_number(out, m.jog_feed_mm_min),
            Key::DefaultFeed => write_number(out, m.default_feed_mm_min),
            Key::JunctionDeviation => write_number(out, m.junction_deviation_mm),
            Key::HardLimits => out.write_str(if m.hard_limits { "1" } else { "0" }),
            Key::SoftLimits => out.write_str(match m.soft_limits {
                SoftLimits::Off => "off",
                SoftLimits::WhenHomed => "homed",
                SoftLimits::Always => "always",
            }),
            Key::KeepAliveMs => super::text::write_integer(out, i64::from(self.keep_alive_ms)),
            Key::LinkSsid => out.write_str(self.ssid.as_str()),
            Key::LinkPassword => out.write_str("<hidden>"),
            Key::PowerLossRecovery => {
                out.write_str(if self.power_loss_recovery { "1" } else { "0" })
            }
            Key::PrintAccel => write_number(out, self.path.print_accel_mm_s2.unwrap_or(0.0)),
            Key::RetractAccel => write_number(out, self.path.retract_accel_mm_s2.unwrap_or(0.0)),
            Key::TravelAccel => write_number(out, self.path.travel_accel_mm_s2.unwrap_or(0.0)),
            Key::MinPrintFeed => write_number(out, self.path.min_extruding_feed_mm_s),
            Key::MinTravelFeed => write_number(out, self.path.min_travel_feed_mm_s),
            Key::StatusMask => super::text::write_integer(out, i64::from(self.status_mask)),
            Key::ArcTolerance => write_number(out, m.arc_tolerance_mm),
            Key::ReportInches => out.write_str(if self.report_inches { "1" } else { "0" }),
            Key::LaserMode => out.write_str(if self.laser_mode { "1" } else { "0" }),
            Key::StartupLine(i) => out.write_str(self.startup_line(i)),
        }
    }
}

/// Every setting of the machine, one `name=value` line each ([`Settings::write_line`]), in the
/// order of [`Key::all`].
impl<const N: usize> fmt::Display for Settings<N> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for key in Key::all::<N>().filter(|k| k.applies_to(&self.machine)) {
            self.write_line(key, f)?;
            f.write_str("\n")?;
        }
        Ok(())
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use forja_motion::config::AxisConfig;
    use std::string::String;
    use std::vec::Vec;

    /// Records in a vector, for tests.
    #[derive(Default)]
    pub(crate) struct VecStorage {
        pub(crate) records: Vec<(u16, Vec<u8>)>,
        pub(crate) fail: bool,
    }

    #[derive(Debug)]
    pub(crate) struct Failed;

    impl forja_hal_abstraction::Error for Failed {
        fn kind(&self) -> ErrorKind {
            ErrorKind::Hardware
        }
    }

    impl forja_hal_abstraction::ErrorType for VecStorage {
        type Error = Failed;
    }

    impl RecordStorage for VecStorage {
        fn read(&mut self, key: u16, buf: &mut [u8]) -> Result<Option<usize>, Failed> {
            let Some((_, v)) = self.records.iter().rev().find(|(k, _)| *k == key) else {
                return Ok(None);
            };
            buf[..v.len()].copy_from_slice(v);
            Ok(Some(v.len()))
        }
        fn write(&mut self, key: u16, value: &[u8]) -> Result<(), Failed> {
            if self.fail {
                return Err(Failed);
            }
            self.records.push((key, value.to_vec()));
            Ok(())
        }
        fn remove(&mut self, key: u16) -> Result<(), Failed> {
            self.records.retain(|(k, _)| *k != key);
            Ok(())
        }
    }

    fn machine() -> MachineConfig<2> {
        MachineConfig::new([
            AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 200.0),
            AxisConfig::linear(b'Y', 80.0, 6000.0, 500.0, 200.0),
        ])
    }

    fn read(s: &Settings<2>, key: &str) -> String {
        let k = Key::parse(key, s.machine()).unwrap();
        let mut out = String::new();
        s.write_value(k, &mut out).unwrap();
        out
    }

    #[test]
    fn set_store_and_load_back() {
        let mut storage = VecStorage::default();
        let mut s = Settings::new(machine());
        let ok = |m: &MachineConfig<2>| m.validate();
        s.set("x.steps_per_mm", "100.5", &mut storage, &ok).unwrap();
        s.set("Y.MAX", "250", &mut storage, &ok).unwrap();
        s.set("soft_limits", "always", &mut storage, &ok).unwrap();
        s.set("keep_alive_ms", "2500", &mut storage, &ok).unwrap();
        s.set("link.ssid", "workshop", &mut storage, &ok).unwrap();
        s.set("link.password", "s3cret", &mut storage, &ok).unwrap();
        assert_eq!(read(&s, "x.steps_per_mm"), "100.5");
        assert_eq!(read(&s, "link.password"), "<hidden>");
        let (back, report) = Settings::load(machine(), &mut storage);
        assert_eq!(
            report,
            LoadReport {
                applied: 6,
                ignored: 0
            }
        );
        assert_eq!(back.machine().axes[0].steps_per_mm, 100.5);
        assert_eq!(back.machine().axes[1].max_mm, 250.0);
        assert_eq!(back.machine().soft_limits, SoftLimits::Always);
        assert_eq!(back.keep_alive_ms(), 2500);
        assert_eq!((back.ssid(), back.password()), ("workshop", "s3cret"));
        let mut name = String::new();
        Key::parse("Y.MAX", back.machine())
            .unwrap()
            .write_name(back.machine(), &mut name)
            .unwrap();
        assert_eq!(name, "y.max");
    }

    #[test]
    fn refused_values_change_nothing() {
        let mut storage = VecStorage::default();
        let mut s = Settings::new(machine());
        let ok = |m: &MachineConfig<2>| m.validate();
        assert_eq!(
            s.set("z.max", "5", &mut storage, &ok),
            Err(SettingError::UnknownKey)
        );
        assert_eq!(
            s.set("x.max", "abc", &mut storage, &ok),
            Err(SettingError::BadValue)
        );
        assert_eq!(
            s.set("x.max", "-5", &mut storage, &ok),
            Err(SettingError::Invalid(ConfigError::Travel(0)))
        );
        assert_eq!(
            s.set("keep_alive_ms", "5", &mut storage, &ok),
            Err(SettingError::BadValue)
        );
        storage.fail = true;
        assert_eq!(
            s.set("x.max", "150", &mut storage, &ok),
            Err(SettingError::Storage(StoreError::Device))
        );
        assert!(storage.records.is_empty());
        assert_eq!(read(&s, "x.max"), "200");
        // A stored value that no longer validates is ignored at load.
        storage.fail = false;
        let mut buf = [0u8; 8];
        let bytes = postcard::to_slice(&-1f32, &mut buf).unwrap().to_vec();
        storage
            .records
            .push((Key::JogFeed.record(s.machine()), bytes));
        let (back, report) = Settings::load(machine(), &mut storage);
        assert_eq!(report.ignored, 1);
        assert_eq!(back.machine().jog_feed_mm_min, 1000.0);
    }

    #[test]
    fn every_setting_is_a_line_as_frame_50_shows_it() {
        let mut storage = VecStorage::default();
        let mut s = Settings::new(machine());
        let ok = |m: &MachineConfig<2>| m.validate();
        s.set("y.max", "250", &mut storage, &ok).unwrap();
        s.set("link.password", "s3cret", &mut storage, &ok).unwrap();
        let mut line = String::new();
        s.write_line(
            Key::Axis {
                axis: 1,
                field: AxisField::Max,
            },
            &mut line,
        )
        .unwrap();
        assert_eq!(line, "y.max=250");
        let text = std::format!("{s}");
        let lines: Vec<&str> = text.lines().collect();
        // Neither axis homes: no homing keys.
        assert_eq!(lines.len(), Key::all::<2>().count() - 2 * 3);
        assert!(!text.contains("homing"));
        assert_eq!(lines[0], "x.steps_per_mm=80");
        assert!(lines.contains(&"y.max=250"));
        assert!(lines.contains(&"link.password=<hidden>"));
        assert!(text.ends_with('\n'));
    }

    /// `machine()` with X homing (seek 3000, locate 300, pull-off 1 mm).
    fn homing_machine() -> MachineConfig<2> {
        let mut m = machine();
        m.axes[0] = m.axes[0].with_homing(HomingConfig {
            direction: forja_motion::config::HomeDirection::Min,
            seek_mm_min: 3000.0,
            locate_mm_min: 300.0,
            pull_off_mm: 1.0,
            switch: 0,
            order: 0,
        });
        m
    }

    #[test]
    fn grbl_settings_and_homing_keys_are_stored_and_loaded_back() {
        let mut storage = VecStorage::default();
        let mut s = Settings::new(homing_machine());
        let ok = |m: &MachineConfig<2>| m.validate();
        assert_eq!(
            (
                s.status_mask(),
                s.report_inches(),
                s.laser_mode(),
                s.startup_line(0)
            ),
            (1, false, false, "")
        );
        s.set("status_mask", "3", &mut storage, &ok).unwrap();
        s.set("arc_tolerance", "0.01", &mut storage, &ok).unwrap();
        s.set("report_inches", "1", &mut storage, &ok).unwrap();
        s.set("laser_mode", "1", &mut storage, &ok).unwrap();
        s.set("startup_line0", "G54 G21", &mut storage, &ok)
            .unwrap();
        s.set("startup_line1", "G0 X1 (move)", &mut storage, &ok)
            .unwrap();
        s.set("x.homing_pull_off", "2.5", &mut storage, &ok)
            .unwrap();
        assert_eq!(read(&s, "x.homing_seek"), "3000");
        assert_eq!(read(&s, "startup_line1"), "G0 X1 (move)");
        // Only an axis that homes has them.
        assert_eq!(Key::parse("y.homing_seek", s.machine()), None);
        assert_eq!(
            s.set("y.homing_seek", "100", &mut storage, &ok),
            Err(SettingError::UnknownKey)
        );
        // Refused values change nothing.
        for (key, value) in [
            ("status_mask", "256"),
            ("report_inches", "2"),
            ("x.homing_locate", "5000"),
            ("arc_tolerance", "0"),
        ] {
            assert!(
                s.set(key, value, &mut storage, &ok).is_err(),
                "{key}={value}"
            );
        }
        let long = "G".repeat(MAX_STARTUP_LINE_LEN + 1);
        assert_eq!(
            s.set("startup_line0", &long, &mut storage, &ok),
            Err(SettingError::BadValue)
        );
        let longest = "G".repeat(MAX_STARTUP_LINE_LEN);
        s.set("startup_line1", &longest, &mut storage, &ok).unwrap();
        let (back, report) = Settings::load(homing_machine(), &mut storage);
        assert_eq!(
            report,
            LoadReport {
                applied: 7,
                ignored: 0
            }
        );
        assert_eq!(back.status_mask(), 3);
        assert!(back.report_inches() && back.laser_mode());
        assert_eq!(back.machine().arc_tolerance_mm, 0.01);
        assert_eq!(back.startup_line(0), "G54 G21");
        assert_eq!(back.startup_line(1), longest);
        assert_eq!(back.machine().axes[0].homing.unwrap().pull_off_mm, 2.5);
        let text = std::format!("{back}");
        assert!(
            text.contains(
                "x.homing_seek=3000
"
            ),
            "{text}"
        );
        assert!(!text.contains("y.homing"), "{text}");
        // `$RST=$` puts grbl's settings back and keeps the startup lines.
        let mut back = back;
        back.restore_defaults(&mut storage).unwrap();
        assert_eq!(
            (back.status_mask(), back.report_inches(), back.laser_mode()),
            (1, false, false)
        );
        assert_eq!(back.startup_line(0), "G54 G21");
        let (again, _) = Settings::load(homing_machine(), &mut storage);
        assert_eq!(again.status_mask(), 1);
        assert_eq!(again.startup_line(0), "G54 G21");
    }

    #[test]
    fn values_that_depend_on_one_another_load_in_any_order() {
        let mut storage = VecStorage::default();
        let mut s = Settings::new(homing_machine());
        let ok = |m: &MachineConfig<2>| m.validate();
        // The locate rate first, then a seek rate below the default locate rate: stored in
        // that order, loaded in the order of the keys (seek first).
        s.set("x.homing_locate", "50", &mut storage, &ok).unwrap();
        s.set("x.homing_seek", "100", &mut storage, &ok).unwrap();
        let (back, report) = Settings::load(homing_machine(), &mut storage);
        assert_eq!(
            report,
            LoadReport {
                applied: 2,
                ignored: 0
            }
        );
        let h = back.machine().axes[0].homing.unwrap();
        assert_eq!((h.seek_mm_min, h.locate_mm_min), (100.0, 50.0));
    }

    #[test]
    fn set_all_sets_every_key_or_none() {
        let mut storage = VecStorage::default();
        let mut m = homing_machine();
        m.axes[1] = m.axes[1].with_homing(m.axes[0].homing.unwrap());
        let mut s = Settings::new(m);
        let ok = |m: &MachineConfig<2>| m.validate();
        let seek = [0, 1].map(|axis| Key::Axis {
            axis,
            field: AxisField::HomingSeek,
        });
        s.set_all(&seek, "2000", &mut storage, &ok).unwrap();
        assert_eq!(read(&s, "x.homing_seek"), "2000");
        assert_eq!(read(&s, "y.homing_seek"), "2000");
        // Above Y's rate only: neither changes.
        s.set("y.max_rate", "1500", &mut storage, &ok).unwrap_err();
        s.set("y.homing_seek", "1000", &mut storage, &ok).unwrap();
        s.set("y.max_rate", "1500", &mut storage, &ok).unwrap();
        assert_eq!(
            s.set_all(&seek, "1800", &mut storage, &ok),
            Err(SettingError::Invalid(ConfigError::SeekRate(1)))
        );
        assert_eq!(read(&s, "x.homing_seek"), "2000");
        let (back, _) = Settings::load(m, &mut storage);
        assert_eq!(back.machine().axes[0].homing.unwrap().seek_mm_min, 2000.0);
        assert_eq!(back.machine().axes[1].homing.unwrap().seek_mm_min, 1000.0);
    }

    #[test]
    fn record_keys_are_distinct() {
        let m = machine();
        let keys: Vec<u16> = Key::all::<2>().map(|k| k.record(&m)).collect();
        for (i, k) in keys.iter().enumerate() {
            assert!(!keys[..i].contains(k));
        }
        assert_eq!(keys[0], 0x0100 + 8 * 23);
        // The axis keys of X end before Y's begin.
        assert_eq!(keys[7], 0x0100 + 8 * 23 + 7);
        assert_eq!(keys[8], 0x0100 + 8 * 24);
        assert_eq!(Key::StartupLine(1).record(&m), 0x0213);
    }
}
