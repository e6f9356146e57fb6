//! The step clock: a free-running [`Clock`] and the one-shot step [`Alarm`] on one hardware
//! timer, whose interrupt is the step interrupt.
//!
//! | chips | timer | `tick_hz` | alarm |
//! |---|---|---|---|
//! | ESP32-C3, -C6, -S3 | SYSTIMER unit 0 (52 bits, already counting for esp-hal), comparator 0 | 16 MHz | target mode, exact to the tick: see `systimer` |
//! | ESP32 (no SYSTIMER) | esp-hal's time base and a one-shot TIMG1 timer | 1 MHz | relative to now, to the microsecond: see `oneshot` |
//!
//! Both give the same interface to the firmware: [`StepTimer`] is owned by the step context
//! ([`crate::step`]); its interrupt handler calls `on_interrupt`, which acknowledges the
//! timer and says whether the step alarm was due; [`StepTimer::clock`] gives a copyable
//! [`StepClock`] that any context reads without a lock. The [`Instant`] is the counter
//! truncated to 32 bits: it wraps every 268 s at 16 MHz (every 71 min at 1 MHz).
//!
//! [`Clock`]: forja_hal_abstraction::clock::Clock
//! [`Alarm`]: forja_hal_abstraction::clock::Alarm
//! [`Instant`]: forja_hal_abstraction::time::Instant

#[cfg(feature = "esp32")]
pub mod oneshot;
#[cfg(not(feature = "esp32"))]
pub mod systimer;

#[cfg(feature = "esp32")]
pub use oneshot::{OneShotClock as StepClock, StepTimer};
#[cfg(not(feature = "esp32"))]
pub use systimer::{StepTimer, SysTimerClock as StepClock};

/// The step alarm could not be set. Never returned by these timers, which can always be
/// programmed; it exists because [`Alarm`](forja_hal_abstraction::clock::Alarm) names an
/// error type.
pub type AlarmError = core::convert::Infallible;
