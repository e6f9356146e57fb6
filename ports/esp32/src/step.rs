//! The step context: what the step interrupt owns, the bodies of the step and switch
//! interrupts, and what the thread side may do to it.
//!
//! The step interrupt is the highest-priority interrupt of the firmware (`Priority::max()`,
//! bound by the board), raised by the step alarm of [`crate::timer`]. It owns the
//! [`StepTimer`], the motion kernel's [`StepGenerator`], the STEP/DIR lines and the limit
//! switch inputs, kept in a [`StepCell`] (a `static` of the board) behind a critical section so
//! that the thread side can reach the timer too (the controller task arms the alarm to start
//! motion, [`StepCell::arm`]), and the switch interrupt the switch inputs
//! ([`StepCell::on_switch_interrupt`]).
//!
//! | context | entry | does |
//! |---|---|---|
//! | step interrupt | [`StepCell::on_step_interrupt`] | acknowledge the timer, `StepGenerator::on_alarm` (pin writes, and switch reads while the generator samples the switches), re-arm the timer |
//! | switch interrupt | [`StepCell::on_switch_interrupt`] | acknowledge the switch inputs, report the edge through the generator's `SwitchAlert` |
//! | thread | [`StepCell::arm`] | arm the alarm where `PollOutcome::arm_alarm` says |
//! | init | [`StepCell::install`], [`StepCell::self_test`], [`StepCell::attach`] | hand over the context, check the alarm, hand over the generator |
//!
//! Everything the interrupts run is integer-only, allocation-free and panic-free, with a
//! budget of a few microseconds. The generator samples the switches from each motion's start
//! until they are all released and settled, during homing, and after the switch interrupt
//! reports an edge.
//!
//! The step generator is handed over with [`StepCell::attach`] once the kernel is built from
//! the stored settings, and the switch inputs start raising the switch interrupt then; before
//! that (and in [`StepCell::self_test`], at every boot) the step interrupt only acknowledges
//! the timer. [`FORJA_STEP_COUNTERS`] counts the alarms and the switch edges; a debugger can
//! read it.
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
use esp_hal::gpio::Output;
use forja_app::firmware::SetupError;
use forja_drivers::stepper::StepDir;
use forja_hal_abstraction::clock::{Alarm, Clock};
use forja_hal_abstraction::time::Instant;
use forja_motion::StepGenerator;

use crate::limits::{self, Limit};
use crate::timer::{StepClock, StepTimer};

/// One motor driver as the step interrupt drives it: its STEP and DIR lines.
pub type Stepper = StepDir<Output<'static>, Output<'static>>;

/// What the step interrupt owns, for `N` axes, a step queue of `Q` events and `K` limit
/// switches.
pub struct StepContext<const N: usize, const Q: usize, const K: usize> {
    /// The step alarm.
    pub timer: StepTimer,
    /// The STEP and DIR lines of each motor driver, in axis order.
    pub steppers: [Stepper; N],
    /// The limit switches, indexed by each homed axis's `homing.switch`; the switch interrupt
    /// acknowledges their GPIO interrupt here.
    pub limits: [Limit; K],
    /// The kernel's step generator, once [attached](StepCell::attach).
    pub generator: Option<StepGenerator<'static, N, Q>>,
}

impl<const N: usize, const Q: usize, const K: usize> StepContext<N, Q, K> {
    /// The step interrupt's parts, without a step generator yet.
    pub fn new(timer: StepTimer, steppers: [Stepper; N], limits: [Limit; K]) -> Self {
        Self {
            timer,
            steppers,
            limits,
            generator: None,
        }
    }
}

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
fn bump(counter: &AtomicU32) {
    // Single writer per counter (the step interrupt, or the switch interrupt for
    // `switch_edges`): load and store, no read-modify-write atomics.
    counter.store(
        counter.load(Ordering::Relaxed).wrapping_add(1),
        Ordering::Relaxed,
    );
}

/// The step context behind its critical section, once installed. The board keeps one in a
/// `static` and calls its interrupt bodies from its handlers.
pub struct StepCell<const N: usize, const Q: usize, const K: usize>(
    Mutex<RefCell<Option<StepContext<N, Q, K>>>>,
);

impl<const N: usize, const Q: usize, const K: usize> Default for StepCell<N, Q, K> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize, const Q: usize, const K: usize> StepCell<N, Q, K> {
    /// Empty: nothing installed.
    pub const fn new() -> Self {
        Self(Mutex::new(RefCell::new(None)))
    }

    /// Hand the step context to the step interrupt.
    ///
    /// Context: init.
    pub fn install(&self, context: StepContext<N, Q, K>) {
        critical_section::with(|cs| self.0.borrow(cs).replace(Some(context)));
    }

    /// Run `f` on the step context, with interrupts masked; `None` before
    /// [`StepCell::install`].
    ///
    /// Context: either. Keep `f` short: the step interrupt waits for it.
    pub fn with<R>(&self, f: impl FnOnce(&mut StepContext<N, Q, K>) -> R) -> Option<R> {
        critical_section::with(|cs| self.0.borrow(cs).borrow_mut().as_mut().map(f))
    }

    /// Hand the kernel's step generator to the step interrupt, and make the switch inputs
    /// raise the switch interrupt on every edge ([`limits::listen`]), which reports them
    /// through the generator's `SwitchAlert`.
    ///
    /// Context: init, after [`StepCell::install`] and [`StepCell::self_test`], before the
    /// first [`StepCell::arm`], with the switch interrupt bound.
    pub fn attach(&self, generator: StepGenerator<'static, N, Q>) {
        self.with(|context| {
            context.generator = Some(generator);
            limits::listen(&mut context.limits);
        });
    }

    /// Arm the step alarm at `at` (an instant already past fires at once): what the controller
    /// task does with `PollOutcome::arm_alarm`.
    ///
    /// Context: thread. A few register writes with interrupts masked.
    pub fn arm(&self, at: Instant) {
        self.with(|context| {
            let _ = context.timer.set_alarm(at);
        });
    }

    /// The body of the step interrupt: acknowledge the timer and, when the alarm was due, run
    /// the step generator and arm the alarm at the instant it returns (none: the generator is
    /// idle until the controller task arms it again).
    ///
    /// Context: the step interrupt.
    #[inline]
    pub fn on_step_interrupt(&self) {
        let due = self
            .with(|context| {
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

    /// The body of the switch interrupt: acknowledge the switch inputs and, when one changed,
    /// report the edge to the step interrupt through the step generator's `SwitchAlert`.
    ///
    /// The acknowledgement comes first, so an edge after it raises the interrupt again, and the
    /// report after it covers every edge before it.
    ///
    /// Context: the switch interrupt (esp-hal's GPIO interrupt, whose handler runs with
    /// interrupts masked). No allocation, no panic; a few register accesses.
    #[inline]
    pub fn on_switch_interrupt(&self) {
        let fired = self.with(|context| {
            let fired = limits::acknowledge(&mut context.limits);
            if fired && let Some(generator) = &context.generator {
                generator.switch_alert().notify();
            }
            fired
        });
        if fired == Some(true) {
            bump(&FORJA_STEP_COUNTERS.switch_edges);
        }
    }

    /// Check the step alarm end to end at boot: an alarm 100 µs ahead must fire once, and an
    /// alarm already past must fire at once. Each is given 5 ms.
    ///
    /// Context: init, after [`StepCell::install`], with the step interrupt bound.
    /// Errors: [`SetupError::StepTimer`] when an alarm did not fire.
    pub async fn self_test(&self, clock: StepClock) -> Result<(), SetupError> {
        let ahead = ticks_for_us(clock, 100);
        for offset in [ahead, 0u32.wrapping_sub(ahead)] {
            let before = FORJA_STEP_COUNTERS.alarms.load(Ordering::Relaxed);
            let at = Instant::from_ticks(clock.now().ticks().wrapping_add(offset));
            if self.with(|context| context.timer.set_alarm(at).is_ok()) != Some(true) {
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
}

/// `us` microseconds in ticks of `clock`.
fn ticks_for_us(clock: StepClock, us: u32) -> u32 {
    forja_hal_abstraction::time::Duration::from_micros_ceil(us, clock.tick_hz()).ticks()
}
