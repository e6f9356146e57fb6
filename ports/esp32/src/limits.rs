//! The limit switches, read by two contexts: the step interrupt (homing, hard limits) and the
//! controller's `M119`, as on the simulator, where each has its own reader of the same switch.
//!
//! The step interrupt owns each switch's [`Input`] in a debounced [`Limit`]. The thread side
//! reads the same pad through a [`SwitchLevel`]: esp-hal's [`InputSignal`] of the input, a
//! read-only view of its level that never reconfigures the pin (it is frozen), wrapped in a
//! [`LimitInput`] without debounce ([`ThreadLimit`]), so that a read from the thread never
//! disturbs the interrupt's filter.
//!
//! # The switch interrupt
//!
//! The step interrupt does not read the switches at every step: it samples them from the start
//! of each motion until they are all released and settled, during homing, and after an edge
//! is reported through the step generator's [`SwitchAlert`](forja_motion::SwitchAlert). Every
//! switch input therefore raises esp-hal's GPIO interrupt on both edges ([`listen`], from
//! [`StepCell::attach`](crate::step::StepCell::attach)), whose handler (the board binds it
//! below the step interrupt's priority, and calls
//! [`StepCell::on_switch_interrupt`](crate::step::StepCell::on_switch_interrupt))
//! acknowledges the inputs ([`acknowledge`]) and reports the edge: a hard limit hit in the
//! middle of a move stops it at the next step.
//!
//! The inputs start listening only once the step context holds them and the step generator is
//! attached: the GPIO interrupt stays raised until its status bits are cleared, and only the
//! handler, through the step context, can clear them.

use core::convert::Infallible;

use embedded_hal::digital::{ErrorType, InputPin};
use esp_hal::gpio::interconnect::InputSignal;
use esp_hal::gpio::{Event, Input};
use forja_drivers::limit::{LimitConfig, LimitInput, Polarity};

/// Samples that must agree before a switch changes state, for the step interrupt.
pub const DEBOUNCE_SAMPLES: u8 = 3;

/// One limit switch as the step interrupt reads it, debounced.
pub type Limit = LimitInput<Input<'static>>;

/// The step interrupt's reader of `input`, debounced over [`DEBOUNCE_SAMPLES`].
///
/// Context: init.
pub fn step_side(input: Input<'static>, polarity: Polarity) -> Limit {
    LimitInput::new(input, LimitConfig::new(polarity, DEBOUNCE_SAMPLES))
}

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
pub fn thread_side(input: &Input<'static>, polarity: Polarity) -> ThreadLimit {
    LimitInput::new(SwitchLevel::of(input), LimitConfig::new(polarity, 1))
}

/// Make each of `switches` raise the GPIO interrupt on both edges (esp-hal clears a stale
/// interrupt status of the pin first).
///
/// Context: init, inside the step context's critical section
/// ([`StepCell::attach`](crate::step::StepCell::attach)), once the switch interrupt is bound.
pub fn listen(switches: &mut [Limit]) {
    for switch in switches {
        switch.pin_mut().listen(Event::AnyEdge);
    }
}

/// Clear the GPIO interrupt status of each of `switches` that has it set; whether any had.
///
/// Context: the switch interrupt. Two register accesses per switch.
pub fn acknowledge(switches: &mut [Limit]) -> bool {
    let mut fired = false;
    for switch in switches {
        let pin = switch.pin_mut();
        if pin.is_interrupt_set() {
            pin.clear_interrupt();
            fired = true;
        }
    }
    fired
}
