//! SysTick as the step clock (the `qemu` build).
//!
//! QEMU 7.2's `netduinoplus2` runs SysTick at the 168 MHz of its board model and nothing else
//! reliably (its TIM2–5 fire erratically). SysTick is a 24-bit down-counter with no compare,
//! so the time base is built in software:
//!
//! - SysTick runs in fixed periods, reloading by itself. Its handler, the step interrupt, adds
//!   the period that just ended to a 32-bit tick count: that count is the [`Instant`], in
//!   168 MHz ticks. The counter register is never rewritten while running, so no tick is ever
//!   counted twice and the count never goes back; if the handler is held off for longer than a
//!   period (a host that deschedules QEMU), the periods missed are lost and the clock runs
//!   slow, which the kernel cannot tell from a slower machine.
//! - The step alarm is a compare made by that handler: the alarm fires at the first period
//!   end at or after its instant, so its resolution is the period. While an alarm is armed
//!   the period is [`FINE_US`] (20 µs, 50 000 interrupts a second); otherwise it is the 1 ms
//!   service tick, so an idle machine costs QEMU 1 000 interrupts a second. Only the handler
//!   writes the reload value, and a value written takes effect at the next period start: the
//!   first alarm after an idle spell may be up to 1 ms late, which the step generator treats
//!   like any late interrupt.
//! - An alarm set for an instant already past pends SysTick at once; the handler tells that
//!   entry from a period end by SysTick's COUNTFLAG, which only a period end sets.
//!
//! This build is for QEMU only: on silicon, the same code would count the real core clock
//! while claiming 168 MHz.

use core::cell::Cell;
use core::sync::atomic::{AtomicU32, Ordering};

use cortex_m::peripheral::syst::SystClkSource;
use cortex_m::peripheral::{SCB, SYST};
use critical_section::Mutex;
use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::clock::{Alarm, Clock};
use forja_hal_abstraction::time::Instant;

use super::{AlarmError, Events, SERVICE_HZ};
use forja_app::firmware::SetupError;

/// The SysTick period while a step alarm is armed, in microseconds.
pub const FINE_US: u32 = 20;

/// The largest SysTick period (24-bit reload value + 1).
const MAX_PERIOD: u32 = 1 << 24;

/// The tick count: written only by the SysTick handler, read anywhere.
static NOW: AtomicU32 = AtomicU32::new(0);

/// The armed step alarm, shared between the handler and the thread side.
static ALARM: Mutex<Cell<Option<u32>>> = Mutex::new(Cell::new(None));

/// A copyable, lock-free reader of the SysTick tick count.
#[derive(Debug, Clone, Copy)]
pub struct SysTickClock {
    tick_hz: u32,
}

impl Clock for SysTickClock {
    #[inline]
    fn now(&self) -> Instant {
        Instant::from_ticks(NOW.load(Ordering::Acquire))
    }

    fn tick_hz(&self) -> u32 {
        self.tick_hz
    }
}

/// SysTick in fixed periods, with the step alarm and service tick compared in its handler.
pub struct StepTimer {
    syst: SYST,
    clock: SysTickClock,
    /// Length of the period now running (loaded at its start).
    running: u32,
    /// Length written to the reload register, loaded at the next period start.
    reload: u32,
    fine: u32,
    coarse: u32,
    next_service: u32,
}

impl StepTimer {
    /// Start SysTick on the core clock, counting `tick_hz` ticks a second.
    ///
    /// Context: init. Errors: [`SetupError::StepTimer`] when `tick_hz` gives a period of less
    /// than 2 ticks or of more than 2²⁴.
    pub fn new(mut syst: SYST, tick_hz: u32) -> Result<Self, SetupError> {
        let fine = tick_hz / 1_000_000 * FINE_US;
        let coarse = tick_hz / SERVICE_HZ;
        if fine < 2 || coarse > MAX_PERIOD || coarse < fine {
            return Err(SetupError::StepTimer);
        }
        syst.disable_counter();
        syst.set_clock_source(SystClkSource::Core);
        syst.set_reload(coarse - 1);
        syst.clear_current();
        syst.enable_interrupt();
        syst.enable_counter();
        Ok(Self {
            syst,
            clock: SysTickClock { tick_hz },
            running: coarse,
            reload: coarse,
            fine,
            coarse,
            next_service: coarse,
        })
    }

    /// A lock-free reader of this timer's time.
    pub fn clock(&self) -> SysTickClock {
        self.clock
    }

    /// The step interrupt's entry: account the period that ended and report what is due.
    ///
    /// Context: the SysTick exception. Never blocks.
    pub fn on_interrupt(&mut self) -> Events {
        let mut now = NOW.load(Ordering::Relaxed);
        if self.syst.has_wrapped() {
            now = now.wrapping_add(self.running);
            NOW.store(now, Ordering::Release);
            // The period that started at this wrap loaded the reload value written last time.
            self.running = self.reload;
        }
        let at = Instant::from_ticks(now);
        let step = critical_section::with(|cs| {
            let alarm = ALARM.borrow(cs);
            match alarm.get() {
                Some(t) if at.is_at_or_after(Instant::from_ticks(t)) => {
                    alarm.set(None);
                    Some(at)
                }
                _ => None,
            }
        });
        let service = at.is_at_or_after(Instant::from_ticks(self.next_service));
        if service {
            self.next_service = self.next_service.wrapping_add(self.coarse);
            // After a long stall, do not report a burst of ticks: restart from now.
            if at.is_at_or_after(Instant::from_ticks(self.next_service)) {
                self.next_service = now.wrapping_add(self.coarse);
            }
        }
        Events { step, service }
    }

    /// Choose the next period's length: fine while an alarm is armed, coarse otherwise.
    ///
    /// Context: the SysTick exception, after the step generator has re-armed (or not).
    pub fn finish(&mut self) {
        let armed = critical_section::with(|cs| ALARM.borrow(cs).get().is_some());
        let want = if armed { self.fine } else { self.coarse };
        if want != self.reload {
            self.syst.set_reload(want - 1);
            self.reload = want;
        }
    }
}

impl ErrorType for StepTimer {
    type Error = AlarmError;
}

impl Alarm for StepTimer {
    fn set_alarm(&mut self, at: Instant) -> Result<(), Self::Error> {
        critical_section::with(|cs| ALARM.borrow(cs).set(Some(at.ticks())));
        // Due already, or the periods are still coarse: run the handler now. Only the handler
        // writes the reload value, right after a period start, so that it always knows the
        // length of the period running.
        if self.reload != self.fine || self.clock.now().is_at_or_after(at) {
            SCB::set_pendst();
        }
        Ok(())
    }

    fn clear_alarm(&mut self) {
        critical_section::with(|cs| ALARM.borrow(cs).set(None));
        SCB::clear_pendst();
    }
}
