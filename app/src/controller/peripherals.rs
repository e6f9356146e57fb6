//! What a board gives the controller besides the motion kernel — its devices (the hot end,
//! the bed, fans, the spindle, coolant, outputs, the beeper), motor power and the end-stops as
//! the thread side reads them — and the G-code rules the controller applies to them.
//!
//! [`Peripherals`] is the board's description of which devices it has: one small accessor
//! each, answering the device as a trait object of `forja_hal_abstraction::device`, or `None`
//! where the board has no such device. A board lists its parts in a
//! [`Parts`](crate::peripherals::Parts), which implements it; a motion-only board's
//! [`MotorPeripherals`](crate::peripherals::MotorPeripherals) and [`NoPeripherals`] do too.
//!
//! The rules of the G-code stream are the controller's, not the devices': an `M3`/`M4` without
//! `S` runs at the last speed commanded, `M109`/`M116` wait until every heater with a target is
//! within [`ControllerConfig::heater_tolerance_mc`](super::ControllerConfig::heater_tolerance_mc)
//! of it, `M9` turns both coolant lines off, program end stops the spindle and the coolant, and
//! alarms turn the heaters, the fans, the spindle and the coolant off. An `M300` tone goes to
//! the beeper as its line is read, and the line is answered without waiting for it: the beeper
//! plays its tones one after another (see `forja_hal_abstraction::device::Beeper`).
//!
//! The spindle runs at the speed the G-code commands (`S`, on its own line or riding on the
//! moves of a motion line) times grbl's spindle override (`0x99`–`0x9D`, 10–200 %); grbl's
//! spindle stop (`0x9E`) stops it during a hold until cycle start. In grbl's laser mode (`$32`)
//! the output is a laser's: off during rapids and outside `G1`/`G2`/`G3`, `M3` at constant
//! power, `M4` at a power that follows the speed (`motion_now().fraction` of the kernel).

use core::fmt;

use forja_hal_abstraction::device::{
    Beeper, CoolantControl, DeviceError, DigitalOutput, FanControl, Rotation, SpindleControl,
    TemperatureControl,
};
use forja_hal_abstraction::files::FileStore;
use forja_protocol::error::WireError;

use forja_motion::effect::{Coolant, Heater, Spindle};

/// Current and target temperature of one heater, in thousandths of a degree Celsius.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Reading {
    /// The last measured temperature.
    pub current_mc: i32,
    /// The target; 0 when the heater is off.
    pub target_mc: i32,
    /// The heater power, 0 to [`FULL_POWER`](forja_hal_abstraction::thermal::FULL_POWER).
    pub power: u16,
}

/// The temperatures of `M105` and of the `M109`/`M116` progress lines; `None` where the board
/// has no such heater.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Temperatures {
    /// The hot end (the current tool's).
    pub hot_end: Option<Reading>,
    /// The bed.
    pub bed: Option<Reading>,
}

/// A peripheral refused a command or reported a fault.
///
/// Codes are stable wire codes: 194–196 are the controller's (see the
/// [controller module](super)), a thermal fault carries the code of the driver that found it
/// (210–215 for `forja-drivers` heaters).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum PeripheralError {
    /// The board has no such heater, fan, spindle, coolant, output or beeper. Code 194.
    NoDevice,
    /// A value the device cannot take: a target above its maximum, a speed it cannot run, a
    /// direction it cannot turn, a coolant line it does not have. Nothing changed. Code 195.
    OutOfRange,
    /// An output could not be driven. Code 196.
    Hardware,
    /// A heater shut itself down (sensor fault, heating stalled, thermal runaway,
    /// over-temperature): the controller raises an alarm and shuts everything down.
    Thermal {
        /// The driver's stable code.
        code: u16,
        /// The driver's stable short name (kebab-case).
        name: &'static str,
    },
}

impl From<DeviceError> for PeripheralError {
    fn from(e: DeviceError) -> Self {
        match e {
            DeviceError::OutOfRange => Self::OutOfRange,
            DeviceError::Thermal { code, name } => Self::Thermal { code, name },
            _ => Self::Hardware,
        }
    }
}

impl WireError for PeripheralError {
    fn code(&self) -> u16 {
        match self {
            Self::NoDevice => 194,
            Self::OutOfRange => 195,
            Self::Hardware => 196,
            Self::Thermal { code, .. } => *code,
        }
    }

    fn name(&self) -> &'static str {
        match self {
            Self::NoDevice => "no-device",
            Self::OutOfRange => "device-range",
            Self::Hardware => "device-fault",
            Self::Thermal { name, .. } => name,
        }
    }
}

impl fmt::Display for PeripheralError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// The board's description of which devices it has, as the controller reaches them.
///
/// Each accessor answers one device, or `None` when the board has none (the default): the
/// controller then refuses its commands with [`PeripheralError::NoDevice`]. The devices follow
/// the contract of `forja_hal_abstraction::device`; the controller applies the G-code rules
/// (see the [module documentation](self)).
///
/// Context: every method is called from the controller's thread context (the task or main
/// loop that runs `Controller::poll`), never from an interrupt. An accessor only answers the
/// device: it never blocks.
pub trait Peripherals<const N: usize> {
    /// The hot end (of tool 0; `M104`, `M109`, `M105`).
    fn hot_end(&mut self) -> Option<&mut dyn TemperatureControl> {
        None
    }

    /// The bed (`M140`, `M105`).
    fn bed(&mut self) -> Option<&mut dyn TemperatureControl> {
        None
    }

    /// The heated chamber (`M141`).
    fn chamber(&mut self) -> Option<&mut dyn TemperatureControl> {
        None
    }

    /// General-purpose output `index`, the `P` word of `M42` (0 to 255).
    fn output(&mut self, index: u8) -> Option<&mut dyn DigitalOutput> {
        let _ = index;
        None
    }

    /// The output that switches the machine's power supply (`M80`, `M81`).
    fn power_supply(&mut self) -> Option<&mut dyn DigitalOutput> {
        None
    }

    /// Fan `index`, the `P` word of `M106`/`M107` (0 to 255).
    fn fan(&mut self, index: u8) -> Option<&mut dyn FanControl> {
        let _ = index;
        None
    }

    /// The spindle (`M3`, `M4`, `M5`).
    fn spindle(&mut self) -> Option<&mut dyn SpindleControl> {
        None
    }

    /// The coolant (`M7`, `M8`, `M9`).
    fn coolant(&mut self) -> Option<&mut dyn CoolantControl> {
        None
    }

    /// The beeper (`M300`).
    fn beeper(&mut self) -> Option<&mut dyn Beeper> {
        None
    }

    /// Energise (`true`) or release every stepper driver. The controller energises them
    /// before any motion and releases them on `M18`/`M84`, `M0` and `M112`.
    ///
    /// Errors: [`DeviceError::Hardware`] when an enable line could not be driven.
    fn set_motors(&mut self, enabled: bool) -> Result<(), DeviceError>;

    /// The end-stop of axis `axis` as the thread side reads it (`M119`): `Some(true)` when
    /// triggered (a switch that cannot be read reads as triggered, as the kernel takes it),
    /// `None` for an axis without a switch read here (the default).
    fn endstop(&mut self, axis: usize) -> Option<bool> {
        let _ = axis;
        None
    }

    /// The file store that serves the SD-card commands (`M20`–`M32`): an SD card, a
    /// directory, RAM. `None` (the default): the board has no card, and answers those
    /// commands as Marlin without one does.
    fn files(&mut self) -> Option<&mut dyn FileStore> {
        None
    }
}

impl<const N: usize, T: Peripherals<N> + ?Sized> Peripherals<N> for &mut T {
    fn hot_end(&mut self) -> Option<&mut dyn TemperatureControl> {
        T::hot_end(self)
    }
    fn bed(&mut self) -> Option<&mut dyn TemperatureControl> {
        T::bed(self)
    }
    fn chamber(&mut self) -> Option<&mut dyn TemperatureControl> {
        T::chamber(self)
    }
    fn output(&mut self, index: u8) -> Option<&mut dyn DigitalOutput> {
        T::output(self, index)
    }
    fn power_supply(&mut self) -> Option<&mut dyn DigitalOutput> {
        T::power_supply(self)
    }
    fn fan(&mut self, index: u8) -> Option<&mut dyn FanControl> {
        T::fan(self, index)
    }
    fn spindle(&mut self) -> Option<&mut dyn SpindleControl> {
        T::spindle(self)
    }
    fn coolant(&mut self) -> Option<&mut dyn CoolantControl> {
        T::coolant(self)
    }
    fn beeper(&mut self) -> Option<&mut dyn Beeper> {
        T::beeper(self)
    }
    fn set_motors(&mut self, enabled: bool) -> Result<(), DeviceError> {
        T::set_motors(self, enabled)
    }
    fn endstop(&mut self, axis: usize) -> Option<bool> {
        T::endstop(self, axis)
    }
    fn files(&mut self) -> Option<&mut dyn FileStore> {
        T::files(self)
    }
}

/// A board with no heater, fan, spindle or coolant, and no switch reads on the thread side:
/// every command to a device is [`PeripheralError::NoDevice`], motor power is accepted and
/// ignored (the drivers are always energised).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NoPeripherals;

impl<const N: usize> Peripherals<N> for NoPeripherals {
    fn set_motors(&mut self, _: bool) -> Result<(), DeviceError> {
        Ok(())
    }
}

/// What the spindle follows of the motion now (the controller's poll gives it, from the
/// kernel's `motion_now`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub(crate) struct SpindleMotion {
    /// The spindle speed `S` in force for the motion now (the move's; at rest, the modal one).
    pub(crate) rpm: u32,
    /// grbl's laser mode (`$32`).
    pub(crate) laser: bool,
    /// The speed as a fraction of the move's programmed speed, 0 to 1 (0 at rest): an `M4`
    /// laser's power follows it.
    pub(crate) fraction: f32,
    /// The laser may be on: a feed move (`G1`, `G2`, `G3`) runs, or, at rest, the motion mode
    /// is one of those (grbl: never in a rapid, a probing move or homing).
    pub(crate) cutting: bool,
    /// A feed hold (or an `M0`/`M6` pause) has come to rest: a laser goes off (grbl's
    /// spindle stop, at the start of each such hold; `0x9E` turns it on again).
    pub(crate) held: bool,
    /// The machine runs (motion, a dwell, homing): a hold that ends into it was resumed, and
    /// the spindle stopped during it runs again.
    pub(crate) running: bool,
}

/// The board's peripherals with the controller's G-code rules and what they remember.
pub(crate) struct Devices<X, const N: usize> {
    /// The board's description of its devices.
    pub(crate) parts: X,
    /// The speed of the last `M3`/`M4` that ran, or of the last `S`, rpm: an `M3`/`M4` without
    /// `S` runs at it.
    rpm: u32,
    /// The spindle as last commanded: direction and programmed rpm, `None` when stopped.
    spindle: Option<(Rotation, u32)>,
    /// grbl's spindle override, percent (10–200).
    spindle_override: u8,
    /// grbl's spindle stop (`0x9E`, or a laser at the start of a hold): the output is off while
    /// the spindle stays commanded.
    spindle_stopped: bool,
    /// What the spindle follows of the motion, as last given.
    motion: SpindleMotion,
    /// What the spindle's driver was last told: direction and rpm, `None` when stopped.
    output: Option<(Rotation, u32)>,
    /// Mist coolant as last commanded.
    mist: bool,
    /// Flood coolant as last commanded.
    flood: bool,
    /// Whether the motors were last energised.
    pub(crate) motors_on: bool,
    /// The axes an `M84 X Y` released while the others keep the drivers energised (bit `i`
    /// for axis `i`).
    released: u8,
    /// The time of the last temperature loop, ms.
    now_ms: u32,
}

/// The reading of a zone: its last measurement (0 before the first) and its target.
fn reading(zone: &dyn TemperatureControl) -> Reading {
    Reading {
        current_mc: zone.current_mc().unwrap_or(0),
        target_mc: zone.target_mc(),
        power: zone.power(),
    }
}

/// The heaters a heating wait is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum HeatZones {
    /// `M109`: the hot end.
    HotEnd,
    /// `M190`: the bed.
    Bed,
    /// The chamber.
    Chamber,
    /// `M116`: every heater.
    All,
}

/// What a heating wait waits for (`M109`, `M190`, `M116`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct HeatWait {
    /// The heaters.
    pub(crate) zones: HeatZones,
    /// `S` (Marlin's rule): only a heater below its target holds the wait; `R` and `M116`:
    /// a heater above it holds it too, until it has cooled to the target.
    pub(crate) heating_only: bool,
}

impl HeatWait {
    /// `M116`: every heater at its target.
    pub(crate) const ALL: HeatWait = HeatWait {
        zones: HeatZones::All,
        heating_only: false,
    };
}

/// Whether `zone` holds up no wait: it is off, or its last measurement is within
/// `tolerance_mc` of its target (or above it, when `heating_only`). A faulted zone, or one not
/// measured yet, holds the wait (the fault stops the machine).
fn at_target(zone: &dyn TemperatureControl, tolerance_mc: i32, heating_only: bool) -> bool {
    if zone.fault().is_some() {
        return false;
    }
    let target = i64::from(zone.target_mc());
    let tolerance = i64::from(tolerance_mc);
    target == 0
        || zone.current_mc().is_some_and(|mc| {
            let below = target - i64::from(mc);
            if heating_only {
                below <= tolerance
            } else {
                below.abs() <= tolerance
            }
        })
}

/// The speed of an `M3`/`M4`: its `S` word rounded to whole rpm, or `last` without one.
fn rpm_or(word: Option<i64>, last: u32) -> u32 {
    word.map_or(last, |v| v.clamp(0, i64::from(u32::MAX)) as u32)
}

/// The speed of an `M3`/`M4` with the `S` word `rpm`, or `last` without one.
fn rpm_or_last(rpm: Option<forja_protocol::gcode::Decimal>, last: u32) -> u32 {
    rpm_or(rpm.and_then(|d| d.round_to_scale(0)), last)
}

impl<X: Peripherals<N>, const N: usize> Devices<X, N> {
    pub(crate) fn new(parts: X) -> Self {
        Self {
            parts,
            rpm: 0,
            spindle: None,
            spindle_override: 100,
            spindle_stopped: false,
            motion: SpindleMotion::default(),
            output: None,
            mist: false,
            flood: false,
            motors_on: false,
            released: 0,
            now_ms: 0,
        }
    }

    /// The spindle's direction and speed as last commanded (the programmed `S`, without the
    /// override), `None` when stopped (grbl's `$G`).
    pub(crate) fn spindle_state(&self) -> Option<(Rotation, u32)> {
        self.spindle
    }

    /// What the spindle's driver runs at now: direction and rpm (the override and a laser's
    /// power applied), `None` when it is stopped (grbl's `FS:` and `A:`).
    pub(crate) fn spindle_output(&self) -> Option<(Rotation, u32)> {
        self.output
    }

    /// grbl's spindle override, percent.
    pub(crate) fn spindle_override(&self) -> u8 {
        self.spindle_override
    }

    /// Set grbl's spindle override (10–200 %): the running spindle changes speed at once, and
    /// later `M3`/`M4`/`S` run at it too.
    ///
    /// Errors: the driver's; the override is set even then.
    pub(crate) fn set_spindle_override(&mut self, percent: u8) -> Result<(), PeripheralError> {
        self.spindle_override = percent.clamp(10, 200);
        self.drive()
    }

    /// grbl's spindle stop (`0x9E`, during a hold at rest): a running spindle stops, a stopped
    /// one starts again. Nothing when no spindle is commanded.
    ///
    /// Errors: the driver's.
    pub(crate) fn toggle_spindle_stop(&mut self) -> Result<(), PeripheralError> {
        if self.spindle.is_none() {
            return Ok(());
        }
        self.spindle_stopped = !self.spindle_stopped;
        self.drive()
    }

    /// A safety door opened in a hold: the spindle stops, to run again at cycle start
    /// ([`Devices::restore_spindle`]).
    ///
    /// Errors: the driver's.
    pub(crate) fn stop_spindle_in_hold(&mut self) -> Result<(), PeripheralError> {
        if self.spindle.is_none() || self.spindle_stopped {
            return Ok(());
        }
        self.spindle_stopped = true;
        self.drive()
    }

    /// Cycle start: a spindle stopped by grbl's spindle stop runs again.
    ///
    /// Errors: the driver's.
    pub(crate) fn restore_spindle(&mut self) -> Result<(), PeripheralError> {
        self.spindle_stopped = false;
        self.drive()
    }

    /// Follow the motion now (the controller's poll, cheap): a running spindle takes the `S` the
    /// motion carries when it differs from the one commanded (an `S` on a motion line), and a
    /// laser's power follows the speed. The driver is told only what changed.
    ///
    /// Errors: the driver's.
    pub(crate) fn follow(&mut self, motion: SpindleMotion) -> Result<(), PeripheralError> {
        let hold_starts = motion.held && !self.motion.held;
        if self.motion.held && !motion.held && motion.running {
            // Resumed (cycle start, frame `Start`): the spindle stopped in the hold runs again.
            self.spindle_stopped = false;
        }
        self.motion = motion;
        match self.spindle {
            None => {
                // The speed of the next `M3`/`M4` without `S`.
                self.rpm = motion.rpm;
                return Ok(());
            }
            Some((rotation, rpm)) if rpm != motion.rpm => {
                self.spindle = Some((rotation, motion.rpm));
                self.rpm = motion.rpm;
            }
            Some(_) => {}
        }
        if motion.laser && hold_starts {
            self.spindle_stopped = true;
        }
        self.drive()
    }

    /// What the driver should run at now: the commanded direction and speed, the override and
    /// the spindle stop applied, and in laser mode the power the motion allows (none unless
    /// `may_cut`).
    fn wanted_output(&self, may_cut: bool) -> Option<(Rotation, u32)> {
        let (rotation, rpm) = self.spindle?;
        if self.spindle_stopped {
            return None;
        }
        let rpm = (u64::from(rpm) * u64::from(self.spindle_override) / 100).min(u64::from(u32::MAX))
            as u32;
        let m = &self.motion;
        let power = match rotation {
            _ if !m.laser => rpm,
            _ if !(may_cut && m.cutting) => 0,
            Rotation::Clockwise => rpm,
            Rotation::CounterClockwise => {
                libm::roundf(rpm as f32 * m.fraction.clamp(0.0, 1.0)) as u32
            }
        };
        Some((rotation, power))
    }

    /// Tell the driver [`Devices::wanted_output`] when it differs from what it was last told.
    fn drive(&mut self) -> Result<(), PeripheralError> {
        let want = self.wanted_output(true);
        if want == self.output {
            return Ok(());
        }
        self.command_output(want)
    }

    /// Tell the driver `want` (run or stop), and remember it once it obeyed.
    fn command_output(&mut self, want: Option<(Rotation, u32)>) -> Result<(), PeripheralError> {
        let spindle = self.parts.spindle().ok_or(PeripheralError::NoDevice)?;
        match want {
            Some((rotation, rpm)) => spindle.run(rotation, rpm)?,
            None => spindle.stop()?,
        }
        self.output = want;
        Ok(())
    }

    /// Mist and flood as last commanded.
    pub(crate) fn coolant_state(&self) -> (bool, bool) {
        (self.mist, self.flood)
    }

    /// The zone a temperature command names: the hot end for the current tool (`T0`, or no
    /// `T`) and the bed.
    fn zone(&mut self, heater: Heater) -> Option<&mut dyn TemperatureControl> {
        match heater {
            Heater::Extruder(None | Some(0)) => self.parts.hot_end(),
            Heater::Bed => self.parts.bed(),
            Heater::Chamber => self.parts.chamber(),
            Heater::Extruder(Some(_)) => None,
        }
    }

    /// Set the target of `heater`, millidegrees; 0 turns it off.
    ///
    /// Errors: [`PeripheralError::NoDevice`], [`PeripheralError::OutOfRange`] (a target above
    /// its maximum; the old target stays), [`PeripheralError::Thermal`] while a fault is
    /// latched (until [`Devices::reset`]).
    pub(crate) fn set_temperature(
        &mut self,
        heater: Heater,
        mc: i32,
    ) -> Result<(), PeripheralError> {
        let zone = self.zone(heater).ok_or(PeripheralError::NoDevice)?;
        Ok(zone.set_target_mc(mc)?)
    }

    /// Current and target temperatures of the hot end and the bed (`M105`).
    pub(crate) fn temperatures(&mut self) -> Temperatures {
        Temperatures {
            hot_end: self.parts.hot_end().map(|z| reading(z)),
            bed: self.parts.bed().map(|z| reading(z)),
        }
    }

    /// Whether the heaters of `wait` no longer hold it (a heater the board lacks holds
    /// nothing).
    pub(crate) fn heat_done(&mut self, wait: HeatWait, tolerance_mc: i32) -> bool {
        let check = |z: &mut dyn TemperatureControl| at_target(z, tolerance_mc, wait.heating_only);
        let hot_end = !matches!(wait.zones, HeatZones::HotEnd | HeatZones::All)
            || self.parts.hot_end().is_none_or(check);
        let bed = !matches!(wait.zones, HeatZones::Bed | HeatZones::All)
            || self.parts.bed().is_none_or(check);
        let chamber = !matches!(wait.zones, HeatZones::Chamber | HeatZones::All)
            || self.parts.chamber().is_none_or(check);
        hot_end && bed && chamber
    }

    /// Switch general-purpose output `index` (`M42`).
    ///
    /// Errors: [`PeripheralError::NoDevice`], a device fault.
    pub(crate) fn set_output(&mut self, index: u8, on: bool) -> Result<(), PeripheralError> {
        let output = self.parts.output(index).ok_or(PeripheralError::NoDevice)?;
        Ok(output.set_on(on)?)
    }

    /// Switch the power supply (`M80`, `M81`).
    ///
    /// Errors: [`PeripheralError::NoDevice`], a device fault.
    pub(crate) fn set_power_supply(&mut self, on: bool) -> Result<(), PeripheralError> {
        let supply = self.parts.power_supply().ok_or(PeripheralError::NoDevice)?;
        Ok(supply.set_on(on)?)
    }

    /// Hand the beeper a tone of `frequency_hz` (0: a pause) for `duration_ms` (`M300`): it
    /// sounds after the tones before it, and the controller does not wait for it.
    ///
    /// Errors: [`PeripheralError::NoDevice`], a device fault.
    pub(crate) fn tone(
        &mut self,
        frequency_hz: u16,
        duration_ms: u16,
    ) -> Result<(), PeripheralError> {
        let beeper = self.parts.beeper().ok_or(PeripheralError::NoDevice)?;
        Ok(beeper.tone(frequency_hz, duration_ms)?)
    }

    /// Run fan `index` at `duty` out of 255 (`M106`, `M107`).
    pub(crate) fn set_fan(&mut self, index: u8, duty: u8) -> Result<(), PeripheralError> {
        let fan = self.parts.fan(index).ok_or(PeripheralError::NoDevice)?;
        Ok(fan.set_duty(duty)?)
    }

    /// Start, reverse or stop the spindle (`M3`, `M4`, `M5`); a speed of `None` is the last
    /// one that ran. `S` alone sets the speed of the running spindle (of the next start when
    /// it is stopped, or on a machine without one). The driver is told at once, at the speed
    /// times the override (a laser: at the power the motion allows); `M5` always stops it, and
    /// `M3`/`M4`/`M5` end grbl's spindle stop.
    ///
    /// Errors: [`PeripheralError::NoDevice`] (not for `S` alone), the driver's; nothing changes
    /// then.
    pub(crate) fn set_spindle(&mut self, command: Spindle) -> Result<(), PeripheralError> {
        let (rotation, rpm) = match command {
            Spindle::Speed { rpm } => {
                let rpm = rpm_or(rpm.round_to_scale(0), self.rpm);
                self.rpm = rpm;
                let Some((rotation, _)) = self.spindle else {
                    return Ok(());
                };
                if self.parts.spindle().is_none() {
                    return Ok(());
                }
                (rotation, rpm)
            }
            Spindle::Clockwise { rpm } => (Rotation::Clockwise, rpm_or_last(rpm, self.rpm)),
            Spindle::CounterClockwise { rpm } => {
                (Rotation::CounterClockwise, rpm_or_last(rpm, self.rpm))
            }
            Spindle::Off => {
                let spindle = self.parts.spindle().ok_or(PeripheralError::NoDevice)?;
                spindle.stop()?;
                self.spindle = None;
                self.spindle_stopped = false;
                self.output = None;
                return Ok(());
            }
        };
        if self.parts.spindle().is_none() {
            return Err(PeripheralError::NoDevice);
        }
        let before = (self.spindle, self.spindle_stopped);
        self.spindle = Some((rotation, rpm));
        if !matches!(command, Spindle::Speed { .. }) {
            self.spindle_stopped = false;
        }
        // A laser starts off: the next poll gives it the power the motion then allows.
        let want = self.wanted_output(false);
        if let Err(e) = self.command_output(want) {
            (self.spindle, self.spindle_stopped) = before;
            return Err(e);
        }
        self.rpm = rpm;
        Ok(())
    }

    /// Mist on (`M7`), flood on (`M8`), or both off (`M9`: both lines are written even when
    /// one fails; the first error is returned).
    pub(crate) fn set_coolant(&mut self, command: Coolant) -> Result<(), PeripheralError> {
        let coolant = self.parts.coolant().ok_or(PeripheralError::NoDevice)?;
        match command {
            Coolant::Mist => {
                coolant.set_mist(true)?;
                self.mist = true;
            }
            Coolant::Flood => {
                coolant.set_flood(true)?;
                self.flood = true;
            }
            Coolant::Off => {
                let mist = coolant.set_mist(false);
                coolant.set_flood(false).and(mist)?;
                (self.mist, self.flood) = (false, false);
            }
        }
        Ok(())
    }

    /// Turn mist (`flood == false`) or flood coolant on or off alone (grbl's realtime
    /// toggles `0xA0`/`0xA1`).
    ///
    /// Errors: [`PeripheralError::NoDevice`], a device fault.
    pub(crate) fn set_coolant_line(
        &mut self,
        flood: bool,
        on: bool,
    ) -> Result<(), PeripheralError> {
        let coolant = self.parts.coolant().ok_or(PeripheralError::NoDevice)?;
        if flood {
            coolant.set_flood(on)?;
            self.flood = on;
        } else {
            coolant.set_mist(on)?;
            self.mist = on;
        }
        Ok(())
    }

    /// End of program (`M2`, `M30`): the spindle and the coolant off, those the board has.
    ///
    /// Errors: the first device that could not be stopped, with its name for the refusal
    /// (`spindle`, `coolant`); both are stopped even when one fails.
    pub(crate) fn end_program(&mut self) -> Result<(), (PeripheralError, &'static str)> {
        let present = |r: Result<(), PeripheralError>, what| match r {
            Ok(()) | Err(PeripheralError::NoDevice) => Ok(()),
            Err(e) => Err((e, what)),
        };
        let spindle = present(self.set_spindle(Spindle::Off), "spindle");
        let coolant = present(self.set_coolant(Coolant::Off), "coolant");
        spindle.and(coolant)
    }

    /// Energise or release the motors.
    pub(crate) fn set_motors(&mut self, enabled: bool) -> Result<(), PeripheralError> {
        self.parts.set_motors(enabled)?;
        self.motors_on = enabled;
        self.released = 0;
        Ok(())
    }

    /// `M17` (`enabled`) or `M18`/`M84` for `axes` (bit `i` for axis `i`). The board's motors
    /// have one power decision, so, as Marlin does with a shared enable line, releasing some
    /// axes keeps the drivers energised until every axis has been released.
    pub(crate) fn set_axis_motors(
        &mut self,
        enabled: bool,
        axes: u8,
    ) -> Result<(), PeripheralError> {
        let every = ((1u16 << N.min(8)) - 1) as u8;
        if enabled || (self.released | axes) & every == every {
            return self.set_motors(enabled);
        }
        self.released |= axes;
        Ok(())
    }

    /// The end-stop of each axis as the thread side reads it (`M119`).
    pub(crate) fn endstops(&mut self) -> [Option<bool>; N] {
        core::array::from_fn(|axis| self.parts.endstop(axis))
    }

    /// Call `f` on every temperature zone the board has: the hot end, then the bed.
    fn each_zone(&mut self, mut f: impl FnMut(&mut dyn TemperatureControl)) {
        if let Some(zone) = self.parts.hot_end() {
            f(zone);
        }
        if let Some(zone) = self.parts.bed() {
            f(zone);
        }
        if let Some(zone) = self.parts.chamber() {
            f(zone);
        }
    }

    /// Run the temperature loops at `now_ms`.
    ///
    /// Errors: the first thermal fault, found now or latched before; its zone has turned its
    /// heater off.
    pub(crate) fn poll(&mut self, now_ms: u32) -> Result<(), PeripheralError> {
        self.now_ms = now_ms;
        let mut first = Ok(());
        self.each_zone(|zone| {
            let run = zone.run(now_ms);
            first = first.and(run);
        });
        Ok(first?)
    }

    /// Heaters, fans, spindle and coolant off, at once (`M112`, `M0`, alarms, thermal
    /// faults). A device that does not obey is left as it is.
    pub(crate) fn shutdown(&mut self) {
        let now_ms = self.now_ms;
        self.each_zone(|zone| {
            let _ = zone.set_target_mc(0);
            // Apply the zero power now rather than at the next period.
            let _ = zone.run(now_ms);
        });
        for index in 0..=u8::MAX {
            if let Some(fan) = self.parts.fan(index) {
                let _ = fan.set_duty(0);
            }
        }
        let _ = self.end_program();
    }

    /// Clear latched heater faults (`M999`, frame `Reset`): heaters stay off until a new
    /// target. The spindle and the coolant stop, as grbl's reset stops them (the reset's modal
    /// state has no spindle running, and its `S` is 0).
    pub(crate) fn reset(&mut self) {
        self.each_zone(|zone| zone.clear_fault());
        let _ = self.end_program();
    }
}
