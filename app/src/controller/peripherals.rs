//! What a board gives the controller besides the motion kernel: heaters, fans, the spindle,
//! motor power and the end-stops as the thread side sees them.
//!
//! [`Peripherals`] is one small trait so that the controller stays free of drivers and chips.
//! `forja-drivers` implements it once, generically, over its PID heater channels, fans,
//! spindle, stepper enables and limit inputs (`forja_app::peripherals::DriverPeripherals`);
//! a board builds that from its pins and hands it to the controller.

use core::fmt;

use forja_protocol::error::WireError;

use forja_motion::effect::{Heater, Spindle};

/// Current and target temperature of one heater, in thousandths of a degree Celsius.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Reading {
    /// The last measured temperature.
    pub current_mc: i32,
    /// The target; 0 when the heater is off.
    pub target_mc: i32,
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
    /// The board has no such heater, fan or spindle. Code 194.
    NoDevice,
    /// A value the device cannot take: a target above its maximum, a speed it cannot run, a
    /// direction it cannot turn. Nothing changed. Code 195.
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

/// The board's peripherals as the controller drives them.
///
/// Context: every method is called from the controller's thread context (the task or main
/// loop that runs `Controller::poll`), never from an interrupt. None may block for longer
/// than a sensor conversion. Errors are reported to the host as the controller's reply policy
/// says; [`Peripherals::poll`] errors raise an alarm.
pub trait Peripherals<const N: usize> {
    /// Set the target of `heater`, in thousandths of a degree Celsius; 0 turns it off.
    ///
    /// Errors: [`PeripheralError::NoDevice`] for a heater the board does not have,
    /// [`PeripheralError::OutOfRange`] for a target above its maximum (the old target stays),
    /// [`PeripheralError::Thermal`] while a fault is latched (until [`Peripherals::reset`]).
    fn set_temperature(&mut self, heater: Heater, millicelsius: i32)
    -> Result<(), PeripheralError>;

    /// Current and target temperatures of the hot end and the bed (`M105`). Never fails: a
    /// heater whose sensor cannot be read reports its last reading.
    fn temperatures(&mut self) -> Temperatures;

    /// Whether every heater with a target is within its tolerance of it (`M109`, `M116`).
    /// `true` when no heater has a target.
    fn heaters_at_target(&mut self) -> bool;

    /// Run fan `index` at `duty` out of 255 (`M106`, `M107`).
    ///
    /// Errors: [`PeripheralError::NoDevice`], [`PeripheralError::Hardware`].
    fn set_fan(&mut self, index: u8, duty: u8) -> Result<(), PeripheralError>;

    /// Start, reverse or stop the spindle (`M3`, `M4`, `M5`). A speed of `None` keeps the last
    /// one commanded.
    ///
    /// Errors: [`PeripheralError::NoDevice`], [`PeripheralError::OutOfRange`] (reverse on a
    /// spindle without a direction line: nothing changed), [`PeripheralError::Hardware`].
    fn set_spindle(&mut self, spindle: Spindle) -> Result<(), PeripheralError>;

    /// Energise (`true`) or release every stepper driver. The controller energises them
    /// before any motion and releases them on `M18`/`M84`, `M0` and `M112`.
    ///
    /// Errors: [`PeripheralError::Hardware`].
    fn set_motors(&mut self, enabled: bool) -> Result<(), PeripheralError>;

    /// The end-stop of each axis as the thread side reads it (`M119`): `Some(true)` when
    /// triggered, `None` for an axis without a switch.
    fn endstops(&mut self) -> [Option<bool>; N];

    /// Run the temperature loops. Called at the controller's peripheral period with a wrapping
    /// millisecond clock.
    ///
    /// Errors: a thermal fault ([`PeripheralError::Thermal`]) that the heater has already
    /// acted on (its output off); the controller then raises an alarm and calls
    /// [`Peripherals::shutdown`]. A latched fault may be returned again on later calls.
    fn poll(&mut self, now_ms: u32) -> Result<(), PeripheralError>;

    /// Heaters, fans and spindle off, at once (`M112`, alarms, thermal faults). Never fails:
    /// an output that does not obey is left as it is.
    fn shutdown(&mut self);

    /// Clear latched faults after an operator's reset (`M999`, frame `Reset`). Heaters stay
    /// off until a new target is set.
    fn reset(&mut self);
}

impl<const N: usize, T: Peripherals<N> + ?Sized> Peripherals<N> for &mut T {
    fn set_temperature(
        &mut self,
        heater: Heater,
        millicelsius: i32,
    ) -> Result<(), PeripheralError> {
        T::set_temperature(self, heater, millicelsius)
    }
    fn temperatures(&mut self) -> Temperatures {
        T::temperatures(self)
    }
    fn heaters_at_target(&mut self) -> bool {
        T::heaters_at_target(self)
    }
    fn set_fan(&mut self, index: u8, duty: u8) -> Result<(), PeripheralError> {
        T::set_fan(self, index, duty)
    }
    fn set_spindle(&mut self, spindle: Spindle) -> Result<(), PeripheralError> {
        T::set_spindle(self, spindle)
    }
    fn set_motors(&mut self, enabled: bool) -> Result<(), PeripheralError> {
        T::set_motors(self, enabled)
    }
    fn endstops(&mut self) -> [Option<bool>; N] {
        T::endstops(self)
    }
    fn poll(&mut self, now_ms: u32) -> Result<(), PeripheralError> {
        T::poll(self, now_ms)
    }
    fn shutdown(&mut self) {
        T::shutdown(self)
    }
    fn reset(&mut self) {
        T::reset(self)
    }
}

/// A board with no heaters, fans or spindle, and no switch reads on the thread side: every
/// command to a device is [`PeripheralError::NoDevice`], motor power is accepted and ignored.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NoPeripherals;

impl<const N: usize> Peripherals<N> for NoPeripherals {
    fn set_temperature(&mut self, _: Heater, _: i32) -> Result<(), PeripheralError> {
        Err(PeripheralError::NoDevice)
    }
    fn temperatures(&mut self) -> Temperatures {
        Temperatures::default()
    }
    fn heaters_at_target(&mut self) -> bool {
        true
    }
    fn set_fan(&mut self, _: u8, _: u8) -> Result<(), PeripheralError> {
        Err(PeripheralError::NoDevice)
    }
    fn set_spindle(&mut self, _: Spindle) -> Result<(), PeripheralError> {
        Err(PeripheralError::NoDevice)
    }
    fn set_motors(&mut self, _: bool) -> Result<(), PeripheralError> {
        Ok(())
    }
    fn endstops(&mut self) -> [Option<bool>; N] {
        [None; N]
    }
    fn poll(&mut self, _: u32) -> Result<(), PeripheralError> {
        Ok(())
    }
    fn shutdown(&mut self) {}
    fn reset(&mut self) {}
}
