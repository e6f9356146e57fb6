//! SYSTIMER as the step clock (ESP32-C3, -C6, -S3).
//!
//! SYSTIMER's unit 0 is a 52-bit counter at 16 MHz (XTAL × 2 / 5) that esp-hal starts at boot
//! and uses for its own time base; it is only read here. Comparator 0, in target mode on unit
//! 0, is the step alarm: its interrupt, `SYSTIMER_TARGET0`, is the step interrupt, which the
//! board binds at the highest priority (see [`crate::step`]).
//!
//! A comparator fires when the counter *reaches* its target: a target already past would not
//! fire until the 52-bit counter wrapped. [`Alarm::set_alarm`] therefore widens the 32-bit
//! [`Instant`] to the counter's 52 bits around the current count and never programs a target
//! less than [`MIN_LEAD_TICKS`] ahead; after programming, it checks that the counter has not
//! already overtaken the target (an interrupt of higher priority could have delayed it) and
//! programs it again if so. ESP-IDF's `systimer_hal_set_alarm_target` follows the same rule.

use core::cell::Cell;

use critical_section::Mutex;
use esp_hal::interrupt::InterruptHandler;
use esp_hal::peripherals::{Interrupt, SYSTIMER};
use esp_hal::timer::systimer::{SystemTimer, Unit};
use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::clock::{Alarm, Clock};
use forja_hal_abstraction::time::Instant;

use super::AlarmError;

/// Ticks per second of unit 0 on every chip with a SYSTIMER but the S2 (which Forja does not
/// support): XTAL 40 MHz × 2 / 5.
pub const TICK_HZ: u32 = 16_000_000;

/// The least distance of a target from the current count: 2 µs.
pub const MIN_LEAD_TICKS: u64 = 32;

/// The comparator used for the step alarm.
const COMPARATOR: usize = 0;

/// Whether the comparator was armed by [`Alarm::set_alarm`] and not yet reported.
static ARMED: Mutex<Cell<bool>> = Mutex::new(Cell::new(false));

/// The 52-bit count of unit 0.
#[inline]
fn count() -> u64 {
    SystemTimer::unit_value(Unit::Unit0)
}

/// A copyable, lock-free reader of SYSTIMER unit 0.
#[derive(Debug, Clone, Copy)]
pub struct SysTimerClock;

impl Clock for SysTimerClock {
    #[inline]
    fn now(&self) -> Instant {
        // Truncation to 32 bits is the definition of the Instant.
        Instant::from_ticks(count() as u32)
    }

    fn tick_hz(&self) -> u32 {
        TICK_HZ
    }
}

/// Comparator 0 of SYSTIMER as the step alarm.
pub struct StepTimer {
    _systimer: SystemTimer<'static>,
}

impl StepTimer {
    /// Take SYSTIMER (which enables its clock without resetting unit 0), put comparator 0 in
    /// target mode on unit 0, disarmed, and bind `handler` (the step interrupt) to it.
    ///
    /// Context: init.
    pub fn new(systimer: SYSTIMER<'static>, handler: InterruptHandler) -> Self {
        let systimer = SystemTimer::new(systimer);
        let regs = SYSTIMER::regs();
        Self::enable(false);
        regs.target_conf(COMPARATOR).modify(|_, w| {
            w.period_mode().clear_bit();
            w.timer_unit_sel().clear_bit()
        });
        regs.int_clr()
            .write(|w| w.target(COMPARATOR as u8).clear_bit_by_one());
        critical_section::with(|_| {
            regs.int_ena()
                .modify(|_, w| w.target(COMPARATOR as u8).set_bit());
        });
        esp_hal::interrupt::bind_handler(Interrupt::SYSTIMER_TARGET0, handler);
        Self {
            _systimer: systimer,
        }
    }

    /// A lock-free reader of this timer's time.
    pub fn clock(&self) -> SysTimerClock {
        SysTimerClock
    }

    /// The step interrupt's entry: acknowledge the comparator and, if the step alarm was due,
    /// disarm it and return the current time for the step generator.
    ///
    /// Context: the step interrupt. A few register accesses.
    #[inline]
    pub fn on_interrupt(&mut self) -> Option<Instant> {
        let regs = SYSTIMER::regs();
        let raised = Self::raised();
        regs.int_clr()
            .write(|w| w.target(COMPARATOR as u8).clear_bit_by_one());
        let armed = critical_section::with(|cs| ARMED.borrow(cs).replace(false));
        if raised && armed {
            Self::enable(false);
            Some(self.clock().now())
        } else {
            None
        }
    }

    /// Start or stop the comparator. `CONF` is shared with esp-hal's own comparator code and
    /// unit set-up, hence the critical section around its read-modify-write.
    fn enable(on: bool) {
        critical_section::with(|_| {
            SYSTIMER::regs()
                .conf()
                .modify(|_, w| w.target0_work_en().bit(on));
        });
    }

    /// Whether the comparator has fired and its interrupt is not yet acknowledged.
    fn raised() -> bool {
        SYSTIMER::regs()
            .int_raw()
            .read()
            .target(COMPARATOR as u8)
            .bit_is_set()
    }

    /// Program the target and latch it into the comparator.
    fn load(target: u64) {
        let regs = SYSTIMER::regs();
        let target = target & SystemTimer::BIT_MASK;
        regs.trgt(COMPARATOR)
            .hi()
            .write(|w| w.hi().set((target >> 32) as u32));
        regs.trgt(COMPARATOR)
            .lo()
            .write(|w| w.lo().set(target as u32));
        regs.comp_load(COMPARATOR).write(|w| w.load().set_bit());
    }
}

impl ErrorType for StepTimer {
    type Error = AlarmError;
}

impl Alarm for StepTimer {
    fn set_alarm(&mut self, at: Instant) -> Result<(), Self::Error> {
        critical_section::with(|cs| {
            Self::enable(false);
            let now = count();
            let ahead = at.signed_ticks_since(Instant::from_ticks(now as u32));
            let mut target = if ahead > 0 {
                now + (ahead as u64).max(MIN_LEAD_TICKS)
            } else {
                now + MIN_LEAD_TICKS
            };
            Self::load(target);
            Self::enable(true);
            // Interrupts are off here, but a flash access by the other core (S3) or a slow bus
            // could still let the counter pass the target before the comparator saw it: if it
            // has passed and the comparator did not fire, re-arm until the target is ahead.
            while count() >= target && !Self::raised() {
                Self::enable(false);
                target = count() + MIN_LEAD_TICKS;
                Self::load(target);
                Self::enable(true);
            }
            ARMED.borrow(cs).set(true);
        });
        Ok(())
    }

    fn clear_alarm(&mut self) {
        critical_section::with(|cs| {
            Self::enable(false);
            ARMED.borrow(cs).set(false);
        });
        SYSTIMER::regs()
            .int_clr()
            .write(|w| w.target(COMPARATOR as u8).clear_bit_by_one());
    }
}
