//! Small helpers shared by the pin-driving drivers.

use embedded_hal::digital::{self, ErrorType, OutputPin, PinState};

/// A placeholder for an optional output that the board does not wire (an enable line tied to
/// ground, a spindle without a direction input). Writing it does nothing and cannot fail.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct NoPin;

impl ErrorType for NoPin {
    type Error = core::convert::Infallible;
}

impl OutputPin for NoPin {
    fn set_low(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
    fn set_high(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// Drive `pin` to `level`, reporting only the error's kind (the pin's own error type differs
/// from pin to pin and cannot be carried in one driver error).
///
/// Context: either; as cheap as the pin write.
#[inline(always)]
pub(crate) fn drive<P: OutputPin>(pin: &mut P, level: PinState) -> Result<(), digital::ErrorKind> {
    // `set_state` spelled out: the trait's provided method is not inlined in a build for size,
    // and this runs in the step interrupt.
    match level {
        PinState::High => pin.set_high(),
        PinState::Low => pin.set_low(),
    }
    .map_err(|e| digital::Error::kind(&e))
}

/// The other level.
#[inline]
pub(crate) const fn opposite(level: PinState) -> PinState {
    match level {
        PinState::Low => PinState::High,
        PinState::High => PinState::Low,
    }
}
