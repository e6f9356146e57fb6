//! Step/direction motor drivers.
//!
//! The step generator produces edges; a [`Stepper`] puts them on pins. Timing is the
//! generator's job: it reads [`Stepper::timing`] once, at configuration, and then schedules the
//! falling edge of each pulse and waits out the direction set-up time itself. The methods here
//! therefore only write pins and must be as cheap as a GPIO write.

use crate::ErrorType;

/// Direction of travel of one axis, in machine coordinates (inversion is the driver's business).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Direction {
    /// Towards increasing machine position.
    Positive,
    /// Towards decreasing machine position.
    Negative,
}

/// Timing limits of a driver chip, in nanoseconds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StepTiming {
    /// Minimum high time (and low time) of a step pulse.
    pub min_pulse_ns: u32,
    /// Minimum time between a direction change and the next step edge.
    pub dir_setup_ns: u32,
}

impl StepTiming {
    /// Conservative limits that suit every common driver chip.
    pub const CONSERVATIVE: StepTiming = StepTiming {
        min_pulse_ns: 2_000,
        dir_setup_ns: 1_000,
    };
}

/// One step/direction motor output.
pub trait Stepper: ErrorType {
    /// Set the direction of the following steps.
    ///
    /// Context: interrupt. Never blocks. Errors: the driver reported a fault; motion stops.
    fn set_direction(&mut self, direction: Direction) -> Result<(), Self::Error>;

    /// Begin a step pulse (drive the step line to its active level).
    ///
    /// Context: interrupt. Never blocks. Errors: as [`Stepper::set_direction`]; the line's
    /// level is then unknown, and the step generator still ends the pulse
    /// ([`Stepper::step_end`]) as motion stops, as it does for every line of the same event.
    fn step_begin(&mut self) -> Result<(), Self::Error>;

    /// End a step pulse (return the step line to idle).
    ///
    /// Context: interrupt. Never blocks. Errors: as [`Stepper::set_direction`].
    fn step_end(&mut self) -> Result<(), Self::Error>;

    /// The driver chip's pulse width and direction set-up time.
    ///
    /// Context: either. Never blocks. Cannot fail.
    fn timing(&self) -> StepTiming;
}

impl<T: Stepper + ?Sized> Stepper for &mut T {
    fn set_direction(&mut self, direction: Direction) -> Result<(), Self::Error> {
        T::set_direction(self, direction)
    }
    fn step_begin(&mut self) -> Result<(), Self::Error> {
        T::step_begin(self)
    }
    fn step_end(&mut self) -> Result<(), Self::Error> {
        T::step_end(self)
    }
    fn timing(&self) -> StepTiming {
        T::timing(self)
    }
}

/// The enable line of a motor driver (holding torque on or off).
pub trait StepperEnable: ErrorType {
    /// Energise (`true`) or release (`false`) the motor.
    ///
    /// Context: thread. Never blocks. Errors: the driver reported a fault.
    fn set_enabled(&mut self, enabled: bool) -> Result<(), Self::Error>;
}

impl<T: StepperEnable + ?Sized> StepperEnable for &mut T {
    fn set_enabled(&mut self, enabled: bool) -> Result<(), Self::Error> {
        T::set_enabled(self, enabled)
    }
}
