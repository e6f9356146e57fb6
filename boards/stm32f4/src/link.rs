//! The host link's counters, and the bring-up reader of the link.
//!
//! [`LINK_COUNTERS`] is a fixed block in RAM that a debugger (probe-rs, gdb, QEMU's monitor)
//! can read by its symbol name, `FORJA_LINK_COUNTERS`: bytes received, records decoded,
//! bytes dropped. It is how the link is observed without printing anything on it.
//!
//! Until the controller layer is wired in, [`pump`] is the whole of the controller task: it
//! drains the receive queue into the mixed-stream decoder and counts what it decodes. It
//! answers nothing.

use core::sync::atomic::{AtomicU32, Ordering};

use forja_drivers::uart::UartReader;
use forja_protocol::stream::{Decoder, Event};

use crate::uart::RX_LEN;

/// Counters of the host link, wrapping. Each is written by one context only.
#[repr(C)]
pub struct LinkCounters {
    /// Bytes taken from the receive queue.
    pub rx_bytes: AtomicU32,
    /// G-code lines decoded.
    pub lines: AtomicU32,
    /// Frames decoded.
    pub frames: AtomicU32,
    /// Runs of garbage bytes and over-long lines dropped by the decoder.
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

fn bump(counter: &AtomicU32, by: u32) {
    // Single writer: load and store, no read-modify-write atomics needed.
    counter.store(
        counter.load(Ordering::Relaxed).wrapping_add(by),
        Ordering::Relaxed,
    );
}

/// Drain the receive queue into `decoder`, counting bytes and records.
///
/// Context: the controller task.
pub fn pump(reader: &mut UartReader<'static, RX_LEN>, decoder: &mut Decoder) {
    let mut chunk = [0u8; 64];
    loop {
        let n = reader.try_read(&mut chunk);
        if n == 0 {
            break;
        }
        bump(&LINK_COUNTERS.rx_bytes, n as u32);
        decoder.feed_all(chunk.get(..n).unwrap_or_default(), |event| match event {
            Event::Line(_) => bump(&LINK_COUNTERS.lines, 1),
            Event::Frame(_) => bump(&LINK_COUNTERS.frames, 1),
            _ => bump(&LINK_COUNTERS.dropped, 1),
        });
    }
    LINK_COUNTERS
        .rx_overruns
        .store(reader.overruns(), Ordering::Relaxed);
}

/// Record the UART's hardware error count.
///
/// Context: the host UART interrupt.
pub fn note_uart_errors(errors: u32) {
    LINK_COUNTERS.uart_errors.store(errors, Ordering::Relaxed);
}
