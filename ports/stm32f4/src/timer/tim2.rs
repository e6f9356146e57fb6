//! TIM2 as the step clock (real boards).
//!
//! TIM2 is a 32-bit timer on every STM32F4. It counts up from 0 to `u32::MAX` and wraps, at
//! the board's tick rate after its prescaler: the counter *is* the [`Instant`]. Compare
//! channel 1 raises the step alarm at its exact tick; compare channel 2 raises the service
//! tick every 1 / [`SERVICE_HZ`] s. Both share the TIM2 interrupt, which is the step interrupt.
//!
//! A compare matches only when the counter equals it, so an alarm set for an instant that
//! has already passed would wait a whole counter cycle: [`Alarm::set_alarm`] checks after
//! programming the compare and, if the instant has passed, pends the interrupt itself.

use core::sync::atomic::{AtomicBool, Ordering};

use cortex_m::peripheral::NVIC;
use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::clock::{Alarm, Clock};
use forja_hal_abstraction::time::Instant;
use stm32f4xx_hal::pac::{self, Interrupt};
use stm32f4xx_hal::rcc::{BusTimerClock, Enable, Rcc, Reset};

use super::{AlarmError, Events, SERVICE_HZ};
use forja_app::firmware::SetupError;

/// Status and interrupt-enable bits of the two compare channels.
const CC1: u32 = 1 << 1;
const CC2: u32 = 1 << 2;

/// Set when [`Alarm::set_alarm`] pended the interrupt for an instant already past.
static FORCED: AtomicBool = AtomicBool::new(false);

/// A copyable, lock-free reader of TIM2's counter.
#[derive(Debug, Clone, Copy)]
pub struct Tim2Clock {
    tick_hz: u32,
}

impl Clock for Tim2Clock {
    #[inline]
    fn now(&self) -> Instant {
        // SAFETY: a read of the counter register, which has no side effect.
        let tim = unsafe { &*pac::TIM2::ptr() };
        Instant::from_ticks(tim.cnt().read().bits())
    }

    fn tick_hz(&self) -> u32 {
        self.tick_hz
    }
}

/// TIM2 running free, with the step alarm on channel 1 and the service tick on channel 2.
pub struct StepTimer {
    tim: pac::TIM2,
    clock: Tim2Clock,
    service_ticks: u32,
}

impl StepTimer {
    /// Start TIM2 counting at `tick_hz`, which must divide the timer's input clock.
    ///
    /// Context: init. Errors: [`SetupError::StepTimer`] when `tick_hz` does not divide the
    /// timer clock or needs a prescaler above 65536.
    pub fn new(tim: pac::TIM2, tick_hz: u32, rcc: &mut Rcc) -> Result<Self, SetupError> {
        let input_hz =
            <pac::TIM2 as stm32f4xx_hal::rcc::RccBus>::Bus::timer_clock(&rcc.clocks).raw();
        let divider = input_hz / tick_hz.max(1);
        if divider == 0 || divider > 0x1_0000 || divider * tick_hz != input_hz {
            return Err(SetupError::StepTimer);
        }
        pac::TIM2::enable(rcc);
        pac::TIM2::reset(rcc);
        // SAFETY (register writes below): plain configuration values in range.
        tim.psc().write(|w| unsafe { w.bits(divider - 1) });
        tim.arr().write(|w| unsafe { w.bits(u32::MAX) });
        // Load the prescaler now (update event), then clear the flag it raised.
        tim.egr().write(|w| w.ug().set_bit());
        tim.sr().write(|w| unsafe { w.bits(0) });
        let service_ticks = tick_hz / SERVICE_HZ;
        tim.ccr2().write(|w| unsafe { w.bits(service_ticks) });
        tim.dier().write(|w| unsafe { w.bits(CC2) });
        tim.cr1().write(|w| w.cen().set_bit());
        Ok(Self {
            tim,
            clock: Tim2Clock { tick_hz },
            service_ticks,
        })
    }

    /// A lock-free reader of this timer's time.
    pub fn clock(&self) -> Tim2Clock {
        self.clock
    }

    /// The step interrupt's entry: acknowledge the timer and report what is due.
    ///
    /// Context: the TIM2 interrupt. A few register accesses.
    pub fn on_interrupt(&mut self) -> Events {
        let sr = self.tim.sr().read().bits();
        let dier = self.tim.dier().read().bits();
        let forced = FORCED.swap(false, Ordering::Relaxed);
        let step_due = dier & CC1 != 0 && (sr & CC1 != 0 || forced);
        let service = sr & CC2 != 0;
        // rc_w0 flags: write 0 to the ones handled, 1 to leave the others alone.
        // SAFETY: clearing status flags.
        self.tim
            .sr()
            .write(|w| unsafe { w.bits(!(sr & (CC1 | CC2))) });
        if step_due {
            self.disarm();
        }
        if service {
            let next = self
                .tim
                .ccr2()
                .read()
                .bits()
                .wrapping_add(self.service_ticks);
            // SAFETY: any compare value is valid.
            self.tim.ccr2().write(|w| unsafe { w.bits(next) });
        }
        Events {
            step: step_due.then(|| self.clock.now()),
            service,
        }
    }

    /// Nothing to do after the handler on TIM2 (the compare is already programmed); present so
    /// that both step timers are driven alike.
    ///
    /// Context: the TIM2 interrupt.
    pub fn finish(&mut self) {}

    fn disarm(&mut self) {
        let dier = self.tim.dier().read().bits();
        // SAFETY: interrupt enable bits of this timer.
        self.tim.dier().write(|w| unsafe { w.bits(dier & !CC1) });
        self.tim.sr().write(|w| unsafe { w.bits(!CC1) });
        FORCED.store(false, Ordering::Relaxed);
    }
}

impl ErrorType for StepTimer {
    type Error = AlarmError;
}

impl Alarm for StepTimer {
    fn set_alarm(&mut self, at: Instant) -> Result<(), Self::Error> {
        // SAFETY (register writes): any compare value is valid; enable bits of this timer.
        self.tim.ccr1().write(|w| unsafe { w.bits(at.ticks()) });
        self.tim.sr().write(|w| unsafe { w.bits(!CC1) });
        let dier = self.tim.dier().read().bits();
        self.tim.dier().write(|w| unsafe { w.bits(dier | CC1) });
        if self.clock.now().is_at_or_after(at) {
            FORCED.store(true, Ordering::Relaxed);
            NVIC::pend(Interrupt::TIM2);
        }
        Ok(())
    }

    fn clear_alarm(&mut self) {
        self.disarm();
    }
}
