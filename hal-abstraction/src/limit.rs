//! Limit switches (end-stops).

use crate::ErrorType;

/// One end-stop. The driver applies polarity and debounce: `true` always means "at the limit".
pub trait LimitSwitch: ErrorType {
    /// Whether the switch is triggered now.
    ///
    /// Context: either (the step interrupt polls it during homing and for hard limits).
    /// Never blocks. Errors: the input could not be read; the kernel treats it as triggered.
    fn is_triggered(&mut self) -> Result<bool, Self::Error>;
}

impl<T: LimitSwitch + ?Sized> LimitSwitch for &mut T {
    fn is_triggered(&mut self) -> Result<bool, Self::Error> {
        T::is_triggered(self)
    }
}
