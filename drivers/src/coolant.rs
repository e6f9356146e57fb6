//! Coolant on two output lines: mist and flood.
//!
//! [`Coolant`] is a [`CoolantControl`] over two [`Output`]s, as grbl and LinuxCNC drive
//! coolant: the mist line (`M7`) and the flood line (`M8`) are switched on each on its own, both
//! may be on at once, and `M9` turns both off (the application's G-code rules). A board without
//! one of the lines leaves it out: turning it on is then [`DeviceError::OutOfRange`] and
//! changes nothing, turning it off does nothing.
//!
//! # Execution context
//!
//! Thread. No method blocks: each is one pin write.

use embedded_hal::digital::OutputPin;
use forja_hal_abstraction::device::{CoolantControl, DeviceError};

use crate::output::Output;
use crate::pin::NoPin;

/// Mist and flood coolant. See the [module documentation](self).
#[derive(Debug)]
pub struct Coolant<M = NoPin, F = NoPin> {
    mist: Option<Output<M>>,
    flood: Option<Output<F>>,
}

impl<F: OutputPin> Coolant<NoPin, F> {
    /// Flood coolant only (the common case: grbl's default).
    pub fn flood(flood: Output<F>) -> Self {
        Self {
            mist: None,
            flood: Some(flood),
        }
    }
}

impl<M: OutputPin> Coolant<M, NoPin> {
    /// Mist coolant only.
    pub fn mist(mist: Output<M>) -> Self {
        Self {
            mist: Some(mist),
            flood: None,
        }
    }
}

impl<M: OutputPin, F: OutputPin> Coolant<M, F> {
    /// Mist and flood coolant.
    pub fn mist_and_flood(mist: Output<M>, flood: Output<F>) -> Self {
        Self {
            mist: Some(mist),
            flood: Some(flood),
        }
    }

    /// Whether the mist is on.
    pub fn is_mist_on(&self) -> bool {
        self.mist.as_ref().is_some_and(Output::is_on)
    }

    /// Whether the flood is on.
    pub fn is_flood_on(&self) -> bool {
        self.flood.as_ref().is_some_and(Output::is_on)
    }

    /// Give the lines back, as last driven.
    pub fn release(self) -> (Option<Output<M>>, Option<Output<F>>) {
        (self.mist, self.flood)
    }
}

/// Switch `line` to `on`; a line the board does not have cannot be turned on.
fn switch<P: OutputPin>(line: Option<&mut Output<P>>, on: bool) -> Result<(), DeviceError> {
    match line {
        Some(output) => output.set(on).map_err(|_| DeviceError::Hardware),
        None if on => Err(DeviceError::OutOfRange),
        None => Ok(()),
    }
}

impl<M: OutputPin, F: OutputPin> CoolantControl for Coolant<M, F> {
    fn set_mist(&mut self, on: bool) -> Result<(), DeviceError> {
        switch(self.mist.as_mut(), on)
    }

    fn set_flood(&mut self, on: bool) -> Result<(), DeviceError> {
        switch(self.flood.as_mut(), on)
    }
}

#[cfg(test)]
mod tests {
    use embedded_hal::digital::PinState;

    use super::*;
    use crate::test_fakes::FakeOutput;

    #[test]
    fn mist_and_flood_switch_on_their_own() {
        let (mist, flood) = (FakeOutput::new(), FakeOutput::new());
        let mut c = Coolant::mist_and_flood(
            Output::new(mist.clone(), PinState::High).unwrap(),
            Output::new(flood.clone(), PinState::Low).unwrap(),
        );
        let device: &mut dyn CoolantControl = &mut c;
        device.set_mist(true).unwrap();
        device.set_flood(true).unwrap();
        assert_eq!(
            (mist.level(), flood.level()),
            (Some(PinState::High), Some(PinState::Low))
        );
        assert!(c.is_mist_on() && c.is_flood_on());
        c.set_mist(false).unwrap();
        assert!(!c.is_mist_on() && c.is_flood_on());
        assert_eq!(mist.level(), Some(PinState::Low));
    }

    #[test]
    fn a_missing_line_cannot_be_turned_on() {
        let flood = FakeOutput::new();
        let mut c = Coolant::flood(Output::new(flood.clone(), PinState::High).unwrap());
        assert_eq!(c.set_mist(true), Err(DeviceError::OutOfRange));
        c.set_mist(false).unwrap();
        c.set_flood(true).unwrap();
        assert_eq!(flood.level(), Some(PinState::High));
        assert!(!c.is_mist_on() && c.is_flood_on());
        let mut c = Coolant::mist(Output::new(FakeOutput::new(), PinState::High).unwrap());
        assert_eq!(c.set_flood(true), Err(DeviceError::OutOfRange));
        c.set_mist(true).unwrap();
        let (mist, flood) = c.release();
        assert!(mist.is_some() && flood.is_none());
    }
}
