//! The step clock and its alarms, on the RP2040's TIMER: a microsecond counter whose low word
//! is the kernel's [`Instant`] (1 MHz, wrapping every 71.6 minutes), with alarms that compare
//! that word. Alarm `N` ([`TimerAlarm<N>`](TimerAlarm)) raises TIMER_IRQ_`N`; a board takes
//! one for the step alarm (alarm 0 on the SKR Pico) and may take another to wake its
//! controller task (alarm 1).
//!
//! `rp2040-hal`'s own alarms (`timer::Alarm0`…) schedule 64-bit instants and force an alarm
//! only when its instant is strictly past once written; the kernel's instants are the counter's
//! low word, and an alarm written for the very microsecond the counter reads is forced here
//! too, so these alarms compare that word themselves.
//!
//! An alarm fires only when the counter equals its target, so one set for an instant already
//! past would wait a whole wrap: [`TimerAlarm::set_alarm`] disarms it and forces its interrupt
//! (INTF) when the instant has passed once the target is written. The alarms' interrupt
//! enables are set once; everything else is written a bit at a time (write-1-to-clear, or the
//! set and clear aliases of the register), so the two alarms, owned by tasks of different
//! priorities, never race on a register.

use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::clock::{Alarm, Clock};
use forja_hal_abstraction::time::Instant;
use rp2040_hal::pac;

/// The counter's rate, set by the watchdog's tick generator from the 12 MHz reference clock
/// (`init_clocks_and_plls`).
pub const TICK_HZ: u32 = 1_000_000;

/// Offsets of a register's atomic set and clear aliases (RP2040 datasheet §2.1.2).
const SET: usize = 0x2000;
const CLEAR: usize = 0x3000;

fn timer() -> &'static pac::timer::RegisterBlock {
    // SAFETY: the TIMER is out of reset (`rp2040_hal::Timer::new`) before any of this runs;
    // every access below is a read or touches only the caller's alarm bit.
    unsafe { &*pac::TIMER::ptr() }
}

/// Write `bits` to the `alias` of `register`.
fn write_alias(register: *mut u32, alias: usize, bits: u32) {
    // SAFETY: the alias of a TIMER register, which sets or clears exactly `bits`.
    unsafe { ((register as usize + alias) as *mut u32).write_volatile(bits) }
}

/// A copyable, lock-free reader of the counter.
#[derive(Debug, Clone, Copy)]
pub struct TimerClock;

impl Clock for TimerClock {
    #[inline]
    fn now(&self) -> Instant {
        Instant::from_ticks(timer().timerawl().read().bits())
    }

    fn tick_hz(&self) -> u32 {
        TICK_HZ
    }
}

/// Alarm `N` of the TIMER.
#[derive(Debug)]
pub struct TimerAlarm<const N: usize>(());

impl<const N: usize> TimerAlarm<N> {
    const BIT: u32 = 1 << N;

    /// Take alarm `N`, disarmed, with its interrupt enabled.
    ///
    /// Context: init, once for each `N` (the TIMER out of reset).
    pub fn new(_timer: &rp2040_hal::Timer) -> Self {
        let mut alarm = Self(());
        alarm.clear_alarm();
        write_alias(timer().inte().as_ptr(), SET, Self::BIT);
        alarm
    }

    /// Whether the alarm has fired (or was forced); if so, acknowledge it. An alarm that has
    /// not fired stays armed.
    ///
    /// Context: the alarm's interrupt. A few register accesses.
    pub fn take(&mut self) -> bool {
        let fired = timer().ints().read().bits() & Self::BIT != 0;
        if fired {
            self.clear_alarm();
        }
        fired
    }
}

impl<const N: usize> ErrorType for TimerAlarm<N> {
    type Error = core::convert::Infallible;
}

impl<const N: usize> Alarm for TimerAlarm<N> {
    fn set_alarm(&mut self, at: Instant) -> Result<(), Self::Error> {
        let t = timer();
        // SAFETY: ALARM0..ALARM3 are consecutive words; any target is valid, and writing it
        // arms the alarm.
        unsafe { t.alarm0().as_ptr().add(N).write_volatile(at.ticks()) };
        if TimerClock.now().is_at_or_after(at) {
            // SAFETY: ARMED is write-1-to-disarm.
            t.armed().write(|w| unsafe { w.bits(Self::BIT) });
            write_alias(t.intf().as_ptr(), SET, Self::BIT);
        }
        Ok(())
    }

    fn clear_alarm(&mut self) {
        let t = timer();
        // SAFETY: ARMED and INTR are write-1-to-clear.
        t.armed().write(|w| unsafe { w.bits(Self::BIT) });
        write_alias(t.intf().as_ptr(), CLEAR, Self::BIT);
        t.intr().write(|w| unsafe { w.bits(Self::BIT) });
    }
}
