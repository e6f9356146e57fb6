//! General-purpose outputs on GPIO lines: a relay, a vacuum, a clamp, a coolant valve.
//!
//! [`Output`] is a [`DigitalOutput`] over any `embedded-hal` [`OutputPin`]: it applies the
//! line's active level, so that "on" is "on" whatever the wiring, and remembers what it was
//! last told. [`crate::coolant::Coolant`] is built from two of them.
//!
//! # Execution context
//!
//! Thread. No method blocks: each is one pin write.
//!
//! # Errors
//!
//! A pin that refuses a write gives its `embedded-hal` [`digital::ErrorKind`]; through
//! [`DigitalOutput`] it is [`DeviceError::Hardware`]. The recorded state is unchanged.

use embedded_hal::digital::{self, OutputPin, PinState};
use forja_hal_abstraction::device::{DeviceError, DigitalOutput};

use crate::pin::{drive, opposite};

/// One output line with its active level. See the [module documentation](self).
#[derive(Debug)]
pub struct Output<P> {
    pin: P,
    active: PinState,
    on: bool,
}

impl<P: OutputPin> Output<P> {
    /// An output on `pin`, on when the pin is at `active`; switched off.
    ///
    /// Context: thread. Errors: the pin refused the write.
    pub fn new(pin: P, active: PinState) -> Result<Self, digital::ErrorKind> {
        let mut output = Self {
            pin,
            active,
            on: true,
        };
        output.set(false)?;
        Ok(output)
    }

    /// Switch the output on (`true`) or off.
    ///
    /// Context: thread. Errors: the pin refused the write (the recorded state is unchanged).
    pub fn set(&mut self, on: bool) -> Result<(), digital::ErrorKind> {
        let level = if on {
            self.active
        } else {
            opposite(self.active)
        };
        drive(&mut self.pin, level)?;
        self.on = on;
        Ok(())
    }

    /// Whether the output was last switched on.
    pub fn is_on(&self) -> bool {
        self.on
    }

    /// Give the pin back, as last driven.
    pub fn release(self) -> P {
        self.pin
    }
}

impl<P: OutputPin> DigitalOutput for Output<P> {
    fn set_on(&mut self, on: bool) -> Result<(), DeviceError> {
        self.set(on).map_err(|_| DeviceError::Hardware)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_fakes::{FailingPin, FakeOutput};

    #[test]
    fn starts_off_and_applies_the_active_level() {
        let pin = FakeOutput::new();
        let mut out = Output::new(pin.clone(), PinState::Low).unwrap();
        assert_eq!(pin.level(), Some(PinState::High), "active-low, off");
        assert!(!out.is_on());
        let device: &mut dyn DigitalOutput = &mut out;
        device.set_on(true).unwrap();
        assert_eq!(pin.level(), Some(PinState::Low));
        assert!(out.is_on());
        let _: FakeOutput = out.release();
    }

    #[test]
    fn a_pin_that_fails_is_a_hardware_error() {
        assert!(Output::new(FailingPin, PinState::High).is_err());
        let mut out = Output {
            pin: FailingPin,
            active: PinState::High,
            on: false,
        };
        assert_eq!(out.set_on(true), Err(DeviceError::Hardware));
        assert!(!out.is_on(), "unchanged");
    }
}
