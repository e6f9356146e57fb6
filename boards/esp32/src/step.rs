//! The step context: what the step interrupt owns, and the body of its handler.
//!
//! The step interrupt is the highest-priority interrupt of the board
//! (`Priority::max()`, bound in `main.rs`), raised by the step alarm of [`crate::timer`]. It
//! owns the [`StepTimer`] and the motor drivers, kept in [`STEP`] behind a critical section so
//! that the thread side can reach them too (to start motion: arm the alarm). Everything it
//! runs is integer-only, allocation-free and panic-free: the interrupt has a budget of a few
//! microseconds.
//!
//! The motion kernel's step generator is called from [`on_interrupt`] once the controller is
//! wired in; until then the handler acknowledges the timer and counts the alarms in
//! [`FORJA_STEP_COUNTERS`], which [`self_test`] checks at every boot and a debugger can read.
//!
//! # Latency
//!
//! esp-hal's critical sections mask every interrupt, this one included: flash operations of
//! the store (which run in a critical section with the cache off, see [`crate::storage`]) and
//! the WiFi driver's short critical sections delay the step interrupt by as long as they last.

use core::cell::RefCell;
use core::sync::atomic::{AtomicU32, Ordering};

use critical_section::Mutex;
use embassy_time::{Duration, Timer};
use forja_hal_abstraction::clock::{Alarm, Clock};
use forja_hal_abstraction::time::Instant;

use crate::board::AXES;
use crate::hardware::{SetupError, Stepper};
use crate::timer::{StepClock, StepTimer};

/// What the step interrupt owns.
pub struct StepContext {
    /// The step alarm.
    pub timer: StepTimer,
    /// The motor drivers, in axis order.
    pub steppers: [Stepper; AXES],
}

/// The step context, once installed.
pub static STEP: Mutex<RefCell<Option<StepContext>>> = Mutex::new(RefCell::new(None));

/// Counters of the step interrupt, wrapping, at a symbol a debugger can find.
#[repr(C)]
pub struct StepCounters {
    /// Step alarms handled.
    pub alarms: AtomicU32,
    /// Interrupts with no alarm due (spurious or cleared ones).
    pub spurious: AtomicU32,
}

/// The step interrupt's counters.
#[unsafe(no_mangle)]
pub static FORJA_STEP_COUNTERS: StepCounters = StepCounters {
    alarms: AtomicU32::new(0),
    spurious: AtomicU32::new(0),
};

fn bump(counter: &AtomicU32) {
    // Single writer (the step interrupt): load and store, no read-modify-write atomics.
    counter.store(
        counter.load(Ordering::Relaxed).wrapping_add(1),
        Ordering::Relaxed,
    );
}

/// Hand the step context to the step interrupt.
///
/// Context: init.
pub fn install(context: StepContext) {
    critical_section::with(|cs| STEP.borrow(cs).replace(Some(context)));
}

/// Run `f` on the step context, with interrupts masked; `None` before [`install`].
///
/// Context: either. Keep `f` short: the step interrupt waits for it.
pub fn with<R>(f: impl FnOnce(&mut StepContext) -> R) -> Option<R> {
    critical_section::with(|cs| STEP.borrow(cs).borrow_mut().as_mut().map(f))
}

/// The body of the step interrupt: acknowledge the timer and, when the alarm was due, run the
/// step generator (once the kernel is wired in) and count it.
///
/// Context: the step interrupt.
#[inline]
pub fn on_interrupt() {
    let due = with(|context| context.timer.on_interrupt()).flatten();
    match due {
        Some(_now) => bump(&FORJA_STEP_COUNTERS.alarms),
        None => bump(&FORJA_STEP_COUNTERS.spurious),
    }
}

/// Check the step alarm end to end at boot: an alarm 100 µs ahead must fire once, and an
/// alarm already past must fire at once. Each is given 5 ms.
///
/// Context: init, after [`install`], with the step interrupt bound.
/// Errors: [`SetupError::StepAlarm`] when an alarm did not fire.
pub async fn self_test(clock: StepClock) -> Result<(), SetupError> {
    let ahead = ticks_for_us(clock, 100);
    for offset in [ahead, 0u32.wrapping_sub(ahead)] {
        let before = FORJA_STEP_COUNTERS.alarms.load(Ordering::Relaxed);
        let at = Instant::from_ticks(clock.now().ticks().wrapping_add(offset));
        if with(|context| context.timer.set_alarm(at).is_ok()) != Some(true) {
            return Err(SetupError::StepAlarm);
        }
        Timer::after(Duration::from_millis(5)).await;
        let after = FORJA_STEP_COUNTERS.alarms.load(Ordering::Relaxed);
        if after.wrapping_sub(before) != 1 {
            return Err(SetupError::StepAlarm);
        }
    }
    Ok(())
}

/// `us` microseconds in ticks of `clock`.
fn ticks_for_us(clock: StepClock, us: u32) -> u32 {
    forja_hal_abstraction::time::Duration::from_micros_ceil(us, clock.tick_hz()).ticks()
}
