//! Limit switch inputs: each a debounced [`LimitInput`] that the step interrupt samples, and an
//! edge source of IO_IRQ_BANK0, whose handler ([`on_interrupt`]) reports the edge to the step
//! interrupt through the kernel's [`SwitchAlert`] (a switch hit mid-move stops it at the next
//! step) and counts it for the controller task ([`edges`]).

use core::sync::atomic::{AtomicU32, Ordering};

use forja_drivers::limit::{LimitConfig, LimitInput};
use forja_motion::SwitchAlert;
use rp2040_hal::gpio::Interrupt;
use rp2040_hal::pac;

use crate::board::{Input, LIMIT_POLARITY, LIMITS};

/// Samples that must agree before a switch changes state (at the step rate, a few tens of µs).
pub const DEBOUNCE_SAMPLES: u8 = 3;

/// One limit switch.
pub type Limit = LimitInput<Input>;

/// Switch interrupts so far, wrapping; written only by [`on_interrupt`].
static EDGES: AtomicU32 = AtomicU32::new(0);

/// Make each input an interrupt source on both edges and wrap it in a [`LimitInput`].
///
/// Context: init.
pub fn switches(pins: [Input; LIMITS]) -> [Limit; LIMITS] {
    let config = LimitConfig::new(LIMIT_POLARITY, DEBOUNCE_SAMPLES);
    pins.map(|pin| {
        pin.set_interrupt_enabled(Interrupt::EdgeLow, true);
        pin.set_interrupt_enabled(Interrupt::EdgeHigh, true);
        LimitInput::new(pin, config)
    })
}

/// Acknowledge the switch inputs' edges and report them.
///
/// Context: IO_IRQ_BANK0, whose only sources are the switch inputs. A few register accesses.
pub fn on_interrupt(alert: &SwitchAlert<'_>) {
    // SAFETY: reads of the core's interrupt status and write-1-to-clear writes of the edges
    // found there; nothing else uses GPIO interrupts.
    let io = unsafe { &*pac::IO_BANK0::ptr() };
    for bank in 0..4 {
        let fired = io.proc0_ints(bank).read().bits();
        io.intr(bank).write(|w| unsafe { w.bits(fired) });
    }
    alert.notify();
    EDGES.store(edges().wrapping_add(1), Ordering::Relaxed);
}

/// Switch interrupts so far, wrapping: the controller task compares it with the last value
/// it saw.
///
/// Context: any.
pub fn edges() -> u32 {
    EDGES.load(Ordering::Relaxed)
}
