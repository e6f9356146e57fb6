//! Monotonic clock and the one-shot step alarm.

use crate::ErrorType;
use crate::time::Instant;

/// A free-running monotonic tick counter.
pub trait Clock {
    /// The current time.
    ///
    /// Context: either. Never blocks. Cannot fail: a board whose counter can fail is not usable.
    fn now(&self) -> Instant;

    /// Ticks per second of [`Clock::now`]; constant for the life of the clock.
    ///
    /// Context: either. Never blocks.
    fn tick_hz(&self) -> u32;
}

impl<T: Clock + ?Sized> Clock for &T {
    fn now(&self) -> Instant {
        T::now(self)
    }
    fn tick_hz(&self) -> u32 {
        T::tick_hz(self)
    }
}

impl<T: Clock + ?Sized> Clock for &mut T {
    fn now(&self) -> Instant {
        T::now(self)
    }
    fn tick_hz(&self) -> u32 {
        T::tick_hz(self)
    }
}

/// A one-shot alarm on the same time base as the board's [`Clock`]; it raises the step interrupt.
pub trait Alarm: ErrorType {
    /// Arm the alarm to fire at `at`, replacing any armed one. An instant already past fires
    /// as soon as possible (never "in 2³² ticks").
    ///
    /// Context: either (normally the step interrupt re-arming itself). Never blocks.
    /// Errors: the timer could not be programmed; the caller stops motion with an alarm.
    fn set_alarm(&mut self, at: Instant) -> Result<(), Self::Error>;

    /// Disarm the alarm; a pending, not yet handled interrupt is cleared.
    ///
    /// Context: either. Never blocks. Cannot fail.
    fn clear_alarm(&mut self);
}

impl<T: Alarm + ?Sized> Alarm for &mut T {
    fn set_alarm(&mut self, at: Instant) -> Result<(), Self::Error> {
        T::set_alarm(self, at)
    }
    fn clear_alarm(&mut self) {
        T::clear_alarm(self)
    }
}
