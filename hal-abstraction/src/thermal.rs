//! Heaters and temperature sensors.

use crate::ErrorType;

/// Full heater power for [`Heater::set_power`].
pub const FULL_POWER: u16 = u16::MAX;

/// A heating element (hot end, bed, chamber) driven by a power fraction.
pub trait Heater: ErrorType {
    /// Set the power, from 0 (off) to [`FULL_POWER`].
    ///
    /// Context: thread (the temperature control loop). Never blocks.
    /// Errors: the output could not be driven; the controller shuts all heaters off.
    fn set_power(&mut self, power: u16) -> Result<(), Self::Error>;
}

impl<T: Heater + ?Sized> Heater for &mut T {
    fn set_power(&mut self, power: u16) -> Result<(), Self::Error> {
        T::set_power(self, power)
    }
}

/// A temperature sensor (thermistor, thermocouple).
pub trait TemperatureSensor: ErrorType {
    /// The temperature in thousandths of a degree Celsius.
    ///
    /// Context: thread. May block for one conversion (tens of microseconds).
    /// Errors: [`crate::ErrorKind::SensorFault`] for an open or shorted sensor; the
    /// controller raises a thermal alarm and turns the heater off.
    fn read_millicelsius(&mut self) -> Result<i32, Self::Error>;
}

impl<T: TemperatureSensor + ?Sized> TemperatureSensor for &mut T {
    fn read_millicelsius(&mut self) -> Result<i32, Self::Error> {
        T::read_millicelsius(self)
    }
}
