//! The step clock: a free-running [`Clock`] and the one-shot step [`Alarm`] on one hardware
//! timer, plus the 1 kHz service tick that wakes the thread side.
//!
//! | build | timer | `tick_hz` | alarm |
//! |---|---|---|---|
//! | silicon | TIM2, 32 bits, prescaled (`tim2`) | the board's step rate | compare channel 1, exact to the tick |
//! | `qemu` | SysTick, the only timer QEMU 7.2 runs reliably (`systick`) | the core clock | checked on every SysTick wrap |
//!
//! Both give the same interface: [`start`] makes the build's [`StepTimer`], the step
//! interrupt's resource (its handler is bound to TIM2, or to SysTick under `qemu`); the handler
//! calls [`StepTimer::serve`], which runs the step generator when the alarm is due and says
//! whether a service tick has passed; [`StepTimer::clock`] gives a copyable [`StepClock`] that
//! any context may read without a lock.
//!
//! [`Clock`]: forja_hal_abstraction::clock::Clock

#[cfg(feature = "qemu")]
pub mod systick;
#[cfg(not(feature = "qemu"))]
pub mod tim2;

#[cfg(feature = "qemu")]
pub use systick::{StepTimer, SysTickClock as StepClock};
#[cfg(not(feature = "qemu"))]
pub use tim2::{StepTimer, Tim2Clock as StepClock};

use cortex_m::peripheral::SYST;
use forja_app::firmware::SetupError;
use forja_hal_abstraction::clock::Alarm;
use forja_hal_abstraction::time::Instant;
use stm32f4xx_hal::pac;
use stm32f4xx_hal::rcc::Rcc;

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
/// programmed; it exists because [`Alarm`] names an error type.
pub type AlarmError = core::convert::Infallible;

/// Start this build's step timer counting `tick_hz` ticks a second: TIM2 on silicon (the
/// rate must divide its input clock), SysTick under `qemu` (the rate is the core clock's).
/// The other peripheral is left as it is.
///
/// Context: init. Errors: [`SetupError::StepTimer`] when the rate cannot be reached.
pub fn start(
    tim2: pac::TIM2,
    syst: SYST,
    tick_hz: u32,
    rcc: &mut Rcc,
) -> Result<StepTimer, SetupError> {
    #[cfg(not(feature = "qemu"))]
    {
        let _ = syst;
        StepTimer::new(tim2, tick_hz, rcc)
    }
    #[cfg(feature = "qemu")]
    {
        let _ = (tim2, rcc);
        StepTimer::new(syst, tick_hz)
    }
}

impl StepTimer {
    /// The step interrupt's work: acknowledge the timer; when the step alarm is due, run
    /// `step` (the step generator) at the current time and re-arm the alarm at what it
    /// returns; choose the next period. Returns whether a service tick has passed.
    ///
    /// Context: the step timer's interrupt. Never blocks.
    #[inline]
    pub fn serve(&mut self, step: impl FnOnce(Instant) -> Option<Instant>) -> bool {
        let events = self.on_interrupt();
        if let Some(now) = events.step
            && let Some(at) = step(now)
        {
            let _ = self.set_alarm(at);
        }
        self.finish();
        events.service
    }
}
