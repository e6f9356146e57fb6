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
//!
//! `<axis>` is the axis letter in lower case (`x.steps_per_mm`); keys are matched without
//! regard to case. A value is refused (and nothing changes) when it does not parse, or when the
//! machine configuration it makes does not validate, with the configuration error's code.
//! Values are stored with `postcard` (an `f32`, a `bool`, a `u32`, the `SoftLimits` enum or a
//! string), one record per key.
//!
//! Settings take effect when the board next builds the kernel (at its next start): the kernel
//! is built once from [`Settings::machine`] and given [`Settings::path_limits`]. `M500` stores
//! the planner settings the kernel runs with (`M92`, `M201`, `M203`, `M204`, `M205`), `M501`
//! gives it the stored ones, `M502` the board's defaults ([`Settings::defaults`]), `M503`
//! reports them (`forja_app::controller`). Frame 50 answers with the stored value.
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
use forja_motion::config::{MachineConfig, SoftLimits};
use forja_motion::error::ConfigError;

/// The period of frame 55 when no setting says otherwise, ms.
pub const DEFAULT_KEEP_ALIVE_MS: u32 = 1000;

/// The longest network name `link.ssid` takes.
pub const MAX_SSID_LEN: usize = 32;

/// The longest password `link.password` takes (what one frame 00 can carry after the key).
pub const MAX_PASSWORD_LEN: usize = 35;

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
}

impl AxisField {
    const ALL: [AxisField; 5] = [
        Self::StepsPerMm,
        Self::MaxRate,
        Self::Accel,
        Self::Min,
        Self::Max,
    ];

    fn name(self) -> &'static str {
        match self {
            Self::StepsPerMm => "steps_per_mm",
            Self::MaxRate => "max_rate",
            Self::Accel => "accel",
            Self::Min => "min",
            Self::Max => "max",
        }
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
}

const GLOBALS: [(&str, Key); 14] = [
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
        Some(Key::Axis { axis, field })
    }

    /// Every key of `machine`, axes first.
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
                write!(
                    out,
                    "{}.{}",
                    char::from(letter.to_ascii_lowercase()),
                    field.name()
                )
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
#[derive(Debug, Clone)]
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
}

/// One setting's value, decoded.
#[derive(Debug, Clone, Copy)]
enum Value<'a> {
    Number(f32),
    Flag(bool),
    Limits(SoftLimits),
    Millis(u32),
    Text(&'a str),
}

/// A setting's number as frame 50 and `M500` write it: an `f32`'s seven significant digits
/// (`80`, `0.013`), written as a decimal, not with the float formatting of `core`, which the
/// firmware image then leaves out.
pub(crate) fn write_number(out: &mut impl fmt::Write, v: f32) -> fmt::Result {
    match Decimal::from_f32_significant(v) {
        Some(d) => write!(out, "{d}"),
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
    /// [`DEFAULT_KEEP_ALIVE_MS`], no network name or password) and power-loss recovery on.
    pub fn new(machine: MachineConfig<N>) -> Self {
        Self {
            defaults: machine.clone(),
            path: PathLimits::NONE,
            machine,
            keep_alive_ms: DEFAULT_KEEP_ALIVE_MS,
            ssid: Text::new(),
            password: Text::new(),
            power_loss_recovery: true,
        }
    }

    /// `machine` with every value found in `storage` applied over it. A stored value that
    /// cannot be read or decoded, or that would make the configuration invalid, is ignored
    /// (and counted).
    ///
    /// Context: thread, at start-up. Blocks for the storage reads.
    pub fn load<S: RecordStorage>(
        machine: MachineConfig<N>,
        storage: &mut S,
    ) -> (Self, LoadReport) {
        let mut settings = Self::new(machine);
        let mut report = LoadReport::default();
        for key in Key::all::<N>() {
            let mut buf = [0u8; 64];
            let record = key.record(&settings.machine);
            let len = match storage.read(record, &mut buf) {
                Ok(Some(len)) => len,
                Ok(None) => continue,
                Err(_) => {
                    report.ignored += 1;
                    continue;
                }
            };
            let bytes = buf.get(..len).unwrap_or(&[]);
            let value = match key {
                Key::HardLimits | Key::PowerLossRecovery => decode::<bool>(bytes).map(Value::Flag),
                Key::SoftLimits => decode::<SoftLimits>(bytes).map(Value::Limits),
                Key::KeepAliveMs => decode::<u32>(bytes).map(Value::Millis),
                Key::LinkSsid | Key::LinkPassword => {
                    postcard::from_bytes::<&str>(bytes).ok().map(Value::Text)
                }
                _ => decode::<f32>(bytes).map(Value::Number),
            };
            let mut next = settings.clone();
            let applied = value.is_some_and(|v| next.apply(key, v).is_ok())
                && next.machine.validate().is_ok();
            if applied {
                settings = next;
                report.applied += 1;
            } else {
                report.ignored += 1;
            }
        }
        (settings, report)
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
            (Key::KeepAliveMs, Value::Millis(v)) if (100..=600_000).contains(&v) => {
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
            Key::HardLimits | Key::PowerLossRecovery => match text {
                "0" => Value::Flag(false),
                "1" => Value::Flag(true),
                _ => return Err(SettingError::BadValue),
            },
            Key::SoftLimits => Value::Limits(match text {
                t if t.eq_ignore_ascii_case("off") => SoftLimits::Off,
                t if t.eq_ignore_ascii_case("homed") => SoftLimits::WhenHomed,
                t if t.eq_ignore_ascii_case("always") => SoftLimits::Always,
                _ => return Err(SettingError::BadValue),
            }),
            Key::KeepAliveMs => Value::Millis(
                Decimal::parse(text.as_bytes())
                    .and_then(Decimal::as_u32)
                    .ok_or(SettingError::BadValue)?,
            ),
            Key::LinkSsid | Key::LinkPassword => Value::Text(text),
            _ => Value::Number(number()?),
        })
    }

    /// Every setting of the machine and the planner back to the board's defaults, their stored
    /// records removed (grbl's `$RST=$`); the link's (keep-alive, network name and password,
    /// power-loss recovery) are kept, so that a board on WiFi stays reachable.
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
                Key::KeepAliveMs | Key::LinkSsid | Key::LinkPassword | Key::PowerLossRecovery
            )
        };
        for key in Key::all::<N>().filter(|k| !keep(k)) {
            storage
                .remove(key.record(&self.machine))
                .map_err(|e| SettingError::Storage(store_error(e.kind())))?;
        }
        self.machine = self.defaults.clone();
        self.path = PathLimits::NONE;
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
        check: impl FnOnce(&MachineConfig<N>) -> Result<(), ConfigError>,
    ) -> Result<Key, SettingError> {
        let key = Key::parse(key, &self.machine).ok_or(SettingError::UnknownKey)?;
        let parsed = Self::parse_value(key, value)?;
        let mut next = self.clone();
        next.apply(key, parsed)?;
        check(&next.machine).map_err(SettingError::Invalid)?;
        let mut buf = [0u8; 64];
        let bytes = match parsed {
            Value::Number(v) => encode(&v, &mut buf),
            Value::Flag(v) => encode(&v, &mut buf),
            Value::Limits(v) => encode(&v, &mut buf),
            Value::Millis(v) => encode(&v, &mut buf),
            Value::Text(v) => encode(&v, &mut buf),
        }
        .ok_or(SettingError::BadValue)?;
        storage
            .write(key.record(&self.machine), bytes)
            .map_err(|e| SettingError::Storage(store_error(e.kind())))?;
        *self = next;
        Ok(key)
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
                let v = match field {
                    AxisField::StepsPerMm => a.steps_per_mm,
                    AxisField::MaxRate => a.max_rate_mm_min,
                    AxisField::Accel => a.accel_mm_s2,
                    AxisField::Min => a.min_mm,
                    AxisField::Max => a.max_mm,
                };
                write_number(out, v)
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
            Key::KeepAliveMs => write!(out, "{}", self.keep_alive_ms),
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
        }
    }
}

/// Every setting, one `name=value` line each ([`Settings::write_line`]), in the order of
/// [`Key::all`].
impl<const N: usize> fmt::Display for Settings<N> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for key in Key::all::<N>() {
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
        s.set("x.steps_per_mm", "100.5", &mut storage, ok).unwrap();
        s.set("Y.MAX", "250", &mut storage, ok).unwrap();
        s.set("soft_limits", "always", &mut storage, ok).unwrap();
        s.set("keep_alive_ms", "2500", &mut storage, ok).unwrap();
        s.set("link.ssid", "workshop", &mut storage, ok).unwrap();
        s.set("link.password", "s3cret", &mut storage, ok).unwrap();
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
            s.set("z.max", "5", &mut storage, ok),
            Err(SettingError::UnknownKey)
        );
        assert_eq!(
            s.set("x.max", "abc", &mut storage, ok),
            Err(SettingError::BadValue)
        );
        assert_eq!(
            s.set("x.max", "-5", &mut storage, ok),
            Err(SettingError::Invalid(ConfigError::Travel(0)))
        );
        assert_eq!(
            s.set("keep_alive_ms", "5", &mut storage, ok),
            Err(SettingError::BadValue)
        );
        storage.fail = true;
        assert_eq!(
            s.set("x.max", "150", &mut storage, ok),
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
        s.set("y.max", "250", &mut storage, ok).unwrap();
        s.set("link.password", "s3cret", &mut storage, ok).unwrap();
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
        assert_eq!(lines.len(), Key::all::<2>().count());
        assert_eq!(lines[0], "x.steps_per_mm=80");
        assert!(lines.contains(&"y.max=250"));
        assert!(lines.contains(&"link.password=<hidden>"));
        assert!(text.ends_with('\n'));
    }

    #[test]
    fn record_keys_are_distinct() {
        let m = machine();
        let keys: Vec<u16> = Key::all::<2>().map(|k| k.record(&m)).collect();
        for (i, k) in keys.iter().enumerate() {
            assert!(!keys[..i].contains(k));
        }
        assert_eq!(keys[0], 0x0100 + 8 * 23);
    }
}
