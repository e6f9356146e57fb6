//! A one-shot TIMG1 timer as the step alarm (the original ESP32, which has no SYSTIMER).
//!
//! The clock is esp-hal's own time base (`esp_hal::time::Instant`), in microseconds: the
//! [`Instant`] is its count truncated to 32 bits, at 1 MHz. The alarm is TIMG1's timer 0 as an
//! esp-hal `OneShotTimer`, which is programmed with a delay rather than a target: the delay is
//! computed from the current time, so an alarm lands within a microsecond of its instant. An
//! instant already past is scheduled [`MIN_LEAD_US`] ahead, that is as soon as possible.

use esp_hal::Blocking;
use esp_hal::interrupt::InterruptHandler;
use esp_hal::peripherals::TIMG1;
use esp_hal::time::Duration;
use esp_hal::timer::OneShotTimer;
use esp_hal::timer::timg::TimerGroup;
use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::clock::{Alarm, Clock};
use forja_hal_abstraction::time::Instant;

use super::AlarmError;

/// Ticks per second of the clock: microseconds.
pub const TICK_HZ: u32 = 1_000_000;

/// The shortest delay programmed.
pub const MIN_LEAD_US: u64 = 1;

/// A copyable, lock-free reader of esp-hal's time base.
#[derive(Debug, Clone, Copy)]
pub struct OneShotClock;

impl Clock for OneShotClock {
    #[inline]
    fn now(&self) -> Instant {
        let us = esp_hal::time::Instant::now()
            .duration_since_epoch()
            .as_micros();
        // Truncation to 32 bits is the definition of the Instant.
        Instant::from_ticks(us as u32)
    }

    fn tick_hz(&self) -> u32 {
        TICK_HZ
    }
}

/// TIMG1 timer 0 as the one-shot step alarm.
pub struct StepTimer {
    timer: OneShotTimer<'static, Blocking>,
    armed: bool,
}

impl StepTimer {
    /// Take TIMG1's timer 0 and bind `handler` (the step interrupt) to it.
    ///
    /// Context: init.
    pub fn new(timg1: TIMG1<'static>, handler: InterruptHandler) -> Self {
        let group = TimerGroup::new(timg1);
        let mut timer = OneShotTimer::new(group.timer0);
        timer.set_interrupt_handler(handler);
        timer.listen();
        Self {
            timer,
            armed: false,
        }
    }

    /// A lock-free reader of this timer's time.
    pub fn clock(&self) -> OneShotClock {
        OneShotClock
    }

    /// The step interrupt's entry: acknowledge the timer and, if the step alarm was due,
    /// return the current time for the step generator.
    ///
    /// Context: the step interrupt.
    #[inline]
    pub fn on_interrupt(&mut self) -> Option<Instant> {
        self.timer.clear_interrupt();
        let due = core::mem::replace(&mut self.armed, false);
        due.then(|| self.clock().now())
    }
}

impl ErrorType for StepTimer {
    type Error = AlarmError;
}

impl Alarm for StepTimer {
    fn set_alarm(&mut self, at: Instant) -> Result<(), Self::Error> {
        let ahead = at.signed_ticks_since(self.clock().now());
        let delay = if ahead > 0 {
            (ahead as u64).max(MIN_LEAD_US)
        } else {
            MIN_LEAD_US
        };
        self.timer.stop();
        self.timer.clear_interrupt();
        // A delay of at most 2³¹ µs always fits the 54-bit timer: this cannot fail.
        let _ = self.timer.schedule(Duration::from_micros(delay));
        self.armed = true;
        Ok(())
    }

    fn clear_alarm(&mut self) {
        self.timer.stop();
        self.timer.clear_interrupt();
        self.armed = false;
    }
}
