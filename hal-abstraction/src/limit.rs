//! Limit switches (end-stops).

use crate::ErrorType;

/// One end-stop. The driver applies polarity and debounce: `true` always means "at the limit".
///
/// The step interrupt samples switches only while one may matter: from the start of each
/// motion until every switch reads released and settled, during homing, and after the board
/// reports an input edge (see `forja_motion::SwitchAlert`). A board therefore reports every
/// edge of a switch input, from a pin-change interrupt, so that a switch hit in the middle of
/// a move is seen at the next step.
pub trait LimitSwitch: ErrorType {
    /// Take a sample: whether the switch is triggered now.
    ///
    /// Context: either (the step interrupt polls it during homing and for hard limits).
    /// Never blocks. Errors: the input could not be read; the kernel treats it as triggered.
    fn is_triggered(&mut self) -> Result<bool, Self::Error>;

    /// Whether the reported state may be about to change: the latest samples disagree with it
    /// and a debounce is still counting them. The step interrupt keeps sampling while any
    /// switch is changing. Without a debounce, never (the default).
    ///
    /// Context: either. No sample is taken.
    fn is_changing(&self) -> bool {
        false
    }
}

impl<T: LimitSwitch + ?Sized> LimitSwitch for &mut T {
    fn is_triggered(&mut self) -> Result<bool, Self::Error> {
        T::is_triggered(self)
    }

    fn is_changing(&self) -> bool {
        T::is_changing(self)
    }
}
