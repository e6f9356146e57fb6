//! The limit switches, read by two contexts: the step interrupt (homing, hard limits) and the
//! controller's `M119`, as on the simulator, where each has its own reader of the same switch.
//!
//! The step interrupt owns each switch's [`Input`] in a debounced
//! [`LimitInput`](forja_drivers::limit::LimitInput). The thread side reads the same pad through
//! a [`SwitchLevel`]: esp-hal's [`InputSignal`] of the input, a read-only view of its level that
//! never reconfigures the pin (it is frozen), wrapped in a [`LimitInput`] without debounce, so
//! that a read from the thread never disturbs the interrupt's filter.
//!
//! [`Input`]: esp_hal::gpio::Input

use core::convert::Infallible;

use embedded_hal::digital::{ErrorType, InputPin};
use esp_hal::gpio::Input;
use esp_hal::gpio::interconnect::InputSignal;
use forja_drivers::limit::{LimitConfig, LimitInput};

use crate::board::LIMIT_POLARITY;

/// The level of a switch input, for the thread side.
pub struct SwitchLevel(InputSignal<'static>);

impl SwitchLevel {
    /// A reader of `input`'s level; `input` stays where it is (with the step interrupt).
    ///
    /// Context: init.
    pub fn of(input: &Input<'static>) -> Self {
        Self(input.peripheral_input().freeze())
    }
}

impl ErrorType for SwitchLevel {
    type Error = Infallible;
}

impl InputPin for SwitchLevel {
    fn is_high(&mut self) -> Result<bool, Self::Error> {
        Ok(self.0.is_input_high())
    }

    fn is_low(&mut self) -> Result<bool, Self::Error> {
        Ok(!self.0.is_input_high())
    }
}

/// One switch as the thread side reads it (`M119`): every read is a fresh sample.
pub type ThreadLimit = LimitInput<SwitchLevel>;

/// The thread side's reader of `input`.
///
/// Context: init.
pub fn thread_side(input: &Input<'static>) -> ThreadLimit {
    LimitInput::new(SwitchLevel::of(input), LimitConfig::new(LIMIT_POLARITY, 1))
}
