//! Limit switch inputs: debounced [`LimitInput`]s, and their EXTI lines.
//!
//! The EXTI interrupt on either edge of any switch input ([`Limits::on_interrupt`], bound by the
//! board to the EXTI vectors of its switch lines) reports the edge to the step interrupt
//! ([`SwitchAlert`]), which then samples the switches at each step until they are all released
//! and settled: a hard limit hit in the middle of a move stops it at the next step, without a
//! switch read at every step. It also records the lines for the thread side ([`take_fired`]),
//! so that a switch hit while idle (a machine pushed by hand) is seen at once.
//!
//! In QEMU the GPIO inputs read low and never change: a pin map for it chooses the polarity
//! that makes that the released state.

use core::sync::atomic::{AtomicU32, Ordering};

use forja_drivers::limit::{LimitConfig, LimitInput, Polarity};
use forja_motion::SwitchAlert;
use stm32f4xx_hal::gpio::{Edge, ErasedPin, ExtiPin, Input, PinExt};
use stm32f4xx_hal::pac::EXTI;
use stm32f4xx_hal::syscfg::SysCfg;

/// Samples that must agree before a switch changes state (at the step rate, a few tens of µs).
pub const DEBOUNCE_SAMPLES: u8 = 3;

/// One limit switch.
pub type Limit = LimitInput<ErasedPin<Input>>;

/// EXTI lines that fired since the thread side last looked, one bit per line.
static FIRED: AtomicU32 = AtomicU32::new(0);

/// The EXTI lines of the limit switch inputs.
pub struct Limits {
    lines: u32,
    alert: Option<SwitchAlert<'static>>,
}

impl Limits {
    /// Configure each pin as an EXTI source on both edges and wrap it in a [`LimitInput`] that
    /// reads with `polarity`: the lines, and the switches in limit input order (for the step
    /// interrupt).
    ///
    /// Context: init.
    pub fn new<const K: usize>(
        pins: [ErasedPin<Input>; K],
        polarity: Polarity,
        syscfg: &mut SysCfg,
        exti: &mut EXTI,
    ) -> (Self, [Limit; K]) {
        let mut lines = 0;
        let config = LimitConfig::new(polarity, DEBOUNCE_SAMPLES);
        let switches = pins.map(|mut pin| {
            pin.make_interrupt_source(syscfg);
            pin.trigger_on_edge(exti, Edge::RisingFalling);
            pin.enable_interrupt(exti);
            lines |= 1 << pin.pin_id();
            LimitInput::new(pin, config)
        });
        (Self { lines, alert: None }, switches)
    }

    /// Report the edges to the step interrupt through `alert` from now on.
    ///
    /// Context: init, once the kernel is split.
    pub fn attach(&mut self, alert: SwitchAlert<'static>) {
        self.alert = Some(alert);
    }

    /// Acknowledge the switch lines of an EXTI interrupt, report the edge to the step
    /// interrupt and remember the lines for the thread side.
    ///
    /// Context: the EXTI interrupts of the switch lines. Two register accesses.
    pub fn on_interrupt(&mut self) {
        // SAFETY: EXTI_PR is write-1-to-clear; only the switch lines are cleared, and EXTI
        // has no other user.
        let exti = unsafe { &*EXTI::ptr() };
        let pending = exti.pr().read().bits() & self.lines;
        exti.pr().write(|w| unsafe { w.bits(pending) });
        if pending != 0
            && let Some(alert) = &self.alert
        {
            alert.notify();
        }
        FIRED.fetch_or(pending, Ordering::Relaxed);
    }
}

/// Take the set of EXTI lines that fired since the last call (bit *n* = line *n*).
///
/// Context: thread.
pub fn take_fired() -> u32 {
    FIRED.swap(0, Ordering::Relaxed)
}
