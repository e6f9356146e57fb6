//! The host link as the controller sees it ([`HostLink`]), and its counters.
//!
//! [`HostLink`] is the drivers' `UartLink`: the two thread-side ends of the UART queues as the
//! one `Read + ReadReady + Write` object that the controller takes. Writing queues bytes for the UART interrupt and waits (spinning)
//! only when the 256-byte transmit queue is full, which the higher-priority UART interrupt
//! drains meanwhile.
//!
//! [`LINK_COUNTERS`] is a fixed block in RAM that a debugger (probe-rs, gdb, QEMU's monitor)
//! can read by its symbol name, `FORJA_LINK_COUNTERS`: bytes received, lines answered, frames
//! and garbage runs seen, bytes dropped. It is how the link is observed without printing
//! anything on it.

use core::sync::atomic::{AtomicU32, Ordering};

use forja_app::controller::Stats;
use forja_drivers::uart::UartLink;

use crate::uart::{RX_LEN, TX_LEN};

/// Counters of the host link, wrapping. Each is written by one context only.
#[repr(C)]
pub struct LinkCounters {
    /// Bytes taken from the receive queue.
    pub rx_bytes: AtomicU32,
    /// G-code lines answered with `ok`.
    pub lines: AtomicU32,
    /// Frames received.
    pub frames: AtomicU32,
    /// Runs of garbage bytes skipped.
    pub dropped: AtomicU32,
    /// Bytes dropped because the receive queue was full.
    pub rx_overruns: AtomicU32,
    /// Bytes the UART lost to hardware errors (overrun, framing, noise).
    pub uart_errors: AtomicU32,
}

/// The link counters, at a symbol a debugger can find.
#[unsafe(no_mangle)]
pub static FORJA_LINK_COUNTERS: LinkCounters = LinkCounters {
    rx_bytes: AtomicU32::new(0),
    lines: AtomicU32::new(0),
    frames: AtomicU32::new(0),
    dropped: AtomicU32::new(0),
    rx_overruns: AtomicU32::new(0),
    uart_errors: AtomicU32::new(0),
};

/// Shorter name of [`FORJA_LINK_COUNTERS`].
pub use FORJA_LINK_COUNTERS as LINK_COUNTERS;

/// The host link: the controller's ends of the UART queues, joined by the drivers.
pub type HostLink = UartLink<'static, RX_LEN, TX_LEN>;

/// Publish the controller's counters and the link's in [`LINK_COUNTERS`].
///
/// Context: the controller task.
pub fn publish(link: &HostLink, stats: &Stats) {
    let c = &LINK_COUNTERS;
    c.rx_bytes.store(link.received(), Ordering::Relaxed);
    c.lines.store(stats.oks, Ordering::Relaxed);
    c.frames.store(stats.frames, Ordering::Relaxed);
    c.dropped.store(stats.garbage_runs, Ordering::Relaxed);
    c.rx_overruns.store(link.overruns(), Ordering::Relaxed);
}

/// Record the UART's hardware error count.
///
/// Context: the host UART interrupt.
pub fn note_uart_errors(errors: u32) {
    LINK_COUNTERS.uart_errors.store(errors, Ordering::Relaxed);
}
