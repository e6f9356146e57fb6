//! Limit switch inputs: each a debounced [`LimitInput`] that the step interrupt samples, and an
//! edge source of IO_IRQ_BANK0, whose handler ([`on_interrupt`]) reports the edge to the step
//! interrupt through the kernel's [`SwitchAlert`] (a switch hit mid-move stops it at the next
//! step) and counts it for the thread side ([`Edges`]).

use core::sync::atomic::{AtomicU32, Ordering};

use forja_drivers::limit::{LimitConfig, LimitInput, Polarity};
use forja_motion::SwitchAlert;
use rp2040_hal::gpio::{DynPinId, FunctionSioInput, Interrupt, Pin, PullType};
use rp2040_hal::pac;

/// Samples that must agree before a switch changes state (at the step rate, a few tens of µs).
pub const DEBOUNCE_SAMPLES: u8 = 3;

/// One limit switch, on an input with pull `P`.
pub type Limit<P> = LimitInput<Pin<DynPinId, FunctionSioInput, P>>;

/// Switch interrupts so far, wrapping; written only by [`on_interrupt`].
static EDGES: AtomicU32 = AtomicU32::new(0);

/// Make each input an interrupt source on both edges and wrap it in a [`LimitInput`] that
/// reads with `polarity`.
///
/// Context: init.
pub fn switches<P: PullType, const K: usize>(
    pins: [Pin<DynPinId, FunctionSioInput, P>; K],
    polarity: Polarity,
) -> [Limit<P>; K] {
    let config = LimitConfig::new(polarity, DEBOUNCE_SAMPLES);
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
    EDGES.store(
        EDGES.load(Ordering::Relaxed).wrapping_add(1),
        Ordering::Relaxed,
    );
}

/// The thread side's view of the switch interrupts: whether any came since it last looked.
/// (The Cortex-M0+ has no atomic swap: the interrupt counts, the thread side compares.)
#[derive(Debug)]
pub struct Edges {
    seen: u32,
}

impl Edges {
    /// Start looking from now.
    pub fn new() -> Self {
        Self {
            seen: EDGES.load(Ordering::Relaxed),
        }
    }

    /// Whether switch interrupts came since the last call (or [`Edges::new`]).
    ///
    /// Context: thread.
    pub fn take(&mut self) -> bool {
        let edges = EDGES.load(Ordering::Relaxed);
        let news = edges != self.seen;
        self.seen = edges;
        news
    }
}

impl Default for Edges {
    fn default() -> Self {
        Self::new()
    }
}
