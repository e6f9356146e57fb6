//! The step context: what the step interrupt owns, and the body of its handler.
//!
//! The step interrupt is the highest-priority interrupt of the board
//! (`Priority::max()`, bound in `main.rs`), raised by the step alarm of [`crate::timer`]. It
//! owns the [`StepTimer`], the motion kernel's [`StepGenerator`], the STEP/DIR lines and the
//! limit switch inputs, kept in [`STEP`] behind a critical section so that the thread side can
//! reach the timer too (the controller task arms the alarm to start motion, [`arm`]), and the
//! switch interrupt the switch inputs ([`crate::limits::on_interrupt`]).
//! Everything it runs is integer-only, allocation-free and panic-free: acknowledge the timer,
//! `StepGenerator::on_alarm` (pin writes, and switch reads while the generator samples the
//! switches: from each motion's start until they are all released and settled, during homing,
//! and after the switch interrupt reports an edge), re-arm the timer. The interrupt has a
//! budget of a few microseconds.
//!
//! The step generator is handed over with [`attach`] once the kernel is built from the stored
//! settings, and the switch inputs start raising the switch interrupt then; before that (and
//! in [`self_test`], at every boot) the handler only acknowledges the timer.
//! [`FORJA_STEP_COUNTERS`] counts the alarms and the switch edges; a debugger can read it.
//!
//! # Latency
//!
//! esp-hal's critical sections mask every interrupt, this one included: flash operations of
//! the store (which run in a critical section with the cache off, see [`crate::storage`]) and
//! the WiFi driver's short critical sections delay the step interrupt by as long as they last,
//! and so does the switch interrupt, which esp-hal runs with interrupts masked.

use core::cell::RefCell;
use core::sync::atomic::{AtomicU32, Ordering};

use critical_section::Mutex;
use embassy_time::{Duration, Timer};
use forja_hal_abstraction::clock::{Alarm, Clock};
use forja_hal_abstraction::time::Instant;
use forja_motion::StepGenerator;

use crate::board::{AXES, LIMITS};
use crate::hardware::{Limit, SetupError, Stepper};
use crate::limits;
use crate::timer::{StepClock, StepTimer};

/// Events of the step queue between the kernel and the step interrupt (a power of two; 8 KiB,
/// the simulator's size).
pub const QUEUE_EVENTS: usize = 1024;

/// The interrupt side of the motion kernel on this board.
pub type Generator = StepGenerator<'static, AXES, QUEUE_EVENTS>;

/// What the step interrupt owns.
pub struct StepContext {
    /// The step alarm.
    pub timer: StepTimer,
    /// The STEP and DIR lines of each motor driver, in axis order.
    pub steppers: [Stepper; AXES],
    /// The limit switches, indexed by each homed axis's `homing.switch`; the switch interrupt
    /// acknowledges their GPIO interrupt here.
    pub limits: [Limit; LIMITS],
    /// The kernel's step generator, once [`attach`]ed.
    pub generator: Option<Generator>,
}

/// The step context, once installed.
pub static STEP: Mutex<RefCell<Option<StepContext>>> = Mutex::new(RefCell::new(None));

/// Counters of the step and switch interrupts, wrapping, at a symbol a debugger can find.
#[repr(C)]
pub struct StepCounters {
    /// Step alarms handled.
    pub alarms: AtomicU32,
    /// Interrupts with no alarm due (spurious or cleared ones).
    pub spurious: AtomicU32,
    /// Switch interrupts that acknowledged a switch edge (counted by the switch interrupt).
    pub switch_edges: AtomicU32,
}

/// The step and switch interrupts' counters.
#[unsafe(no_mangle)]
pub static FORJA_STEP_COUNTERS: StepCounters = StepCounters {
    alarms: AtomicU32::new(0),
    spurious: AtomicU32::new(0),
    switch_edges: AtomicU32::new(0),
};

/// Add one to `counter`, wrapping.
///
/// Context: the one interrupt that writes `counter`.
pub(crate) fn bump(counter: &AtomicU32) {
    // Single writer per counter (the step interrupt, or the switch interrupt for
    // `switch_edges`): load and store, no read-modify-write atomics.
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

/// Hand the kernel's step generator to the step interrupt, and make the switch inputs raise
/// the switch interrupt on every edge ([`limits::listen`]), which reports them through the
/// generator's `SwitchAlert`.
///
/// Context: init, after [`install`] and [`self_test`], before the first [`arm`], with the
/// switch interrupt bound.
pub fn attach(generator: Generator) {
    with(|context| {
        context.generator = Some(generator);
        limits::listen(&mut context.limits);
    });
}

/// Arm the step alarm at `at` (an instant already past fires at once): what the controller
/// task does with `PollOutcome::arm_alarm`.
///
/// Context: thread. A few register writes with interrupts masked.
pub fn arm(at: Instant) {
    with(|context| {
        let _ = context.timer.set_alarm(at);
    });
}

/// Run `f` on the step context, with interrupts masked; `None` before [`install`].
///
/// Context: either. Keep `f` short: the step interrupt waits for it.
pub fn with<R>(f: impl FnOnce(&mut StepContext) -> R) -> Option<R> {
    critical_section::with(|cs| STEP.borrow(cs).borrow_mut().as_mut().map(f))
}

/// The body of the step interrupt: acknowledge the timer and, when the alarm was due, run the
/// step generator and arm the alarm at the instant it returns (none: the generator is idle
/// until the controller task arms it again).
///
/// Context: the step interrupt.
#[inline]
pub fn on_interrupt() {
    let due = with(|context| {
        let now = context.timer.on_interrupt()?;
        let StepContext {
            timer,
            steppers,
            limits,
            generator,
        } = context;
        if let Some(next) = generator
            .as_mut()
            .and_then(|g| g.on_alarm(now, steppers, limits))
        {
            let _ = timer.set_alarm(next);
        }
        Some(())
    })
    .flatten();
    match due {
        Some(()) => bump(&FORJA_STEP_COUNTERS.alarms),
        None => bump(&FORJA_STEP_COUNTERS.spurious),
    }
}

/// Check the step alarm end to end at boot: an alarm 100 µs ahead must fire once, and an
/// alarm already past must fire at once. Each is given 5 ms.
///
/// Context: init, after [`install`], with the step interrupt bound.
/// Errors: [`SetupError::StepTimer`] when an alarm did not fire.
pub async fn self_test(clock: StepClock) -> Result<(), SetupError> {
    let ahead = ticks_for_us(clock, 100);
    for offset in [ahead, 0u32.wrapping_sub(ahead)] {
        let before = FORJA_STEP_COUNTERS.alarms.load(Ordering::Relaxed);
        let at = Instant::from_ticks(clock.now().ticks().wrapping_add(offset));
        if with(|context| context.timer.set_alarm(at).is_ok()) != Some(true) {
            return Err(SetupError::StepTimer);
        }
        Timer::after(Duration::from_millis(5)).await;
        let after = FORJA_STEP_COUNTERS.alarms.load(Ordering::Relaxed);
        if after.wrapping_sub(before) != 1 {
            return Err(SetupError::StepTimer);
        }
    }
    Ok(())
}

/// `us` microseconds in ticks of `clock`.
fn ticks_for_us(clock: StepClock, us: u32) -> u32 {
    forja_hal_abstraction::time::Duration::from_micros_ceil(us, clock.tick_hz()).ticks()
}
