//! The step clock: a free-running [`Clock`] and the one-shot step [`Alarm`] on one hardware
//! timer, plus the 1 kHz service tick that wakes the thread side.
//!
//! | build | timer | `tick_hz` | alarm |
//! |---|---|---|---|
//! | real boards | TIM2, 32 bits, prescaled | the board's `STEP_TICK_HZ` | compare channel 1, exact to the tick |
//! | `qemu` | SysTick (the only timer QEMU 7.2 runs reliably) | 168 MHz | checked on every SysTick wrap: see [`systick`] |
//!
//! Both give the same interface to the `#[app]` module: the timer is the step interrupt's
//! resource; its interrupt handler calls `on_interrupt`, which says whether the step alarm is
//! due and whether a service tick has passed; `clock()` gives a copyable [`Clock`] that any
//! context may read without a lock.
//!
//! [`Clock`]: forja_hal_abstraction::clock::Clock
//! [`Alarm`]: forja_hal_abstraction::clock::Alarm

#[cfg(feature = "qemu")]
pub mod systick;
#[cfg(not(feature = "qemu"))]
pub mod tim2;

#[cfg(feature = "qemu")]
pub use systick::{StepTimer, SysTickClock as StepClock};
#[cfg(not(feature = "qemu"))]
pub use tim2::{StepTimer, Tim2Clock as StepClock};

use forja_hal_abstraction::time::Instant;

/// Service ticks per second: the rate at which the thread side is woken to poll.
pub const SERVICE_HZ: u32 = 1_000;

/// What one step-timer interrupt found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Events {
    /// The step alarm was due: the current time, for the step generator. The alarm is now
    /// disarmed; the handler re-arms it.
    pub step: Option<Instant>,
    /// At least one service tick (1 / [`SERVICE_HZ`] s) has passed since the last one reported.
    pub service: bool,
}

/// The step alarm could not be set. Never returned by these timers, which can always be
/// programmed; it exists because [`Alarm`](forja_hal_abstraction::clock::Alarm) names an
/// error type.
pub type AlarmError = core::convert::Infallible;
