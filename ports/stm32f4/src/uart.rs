//! The host UART: interrupt-driven, through [`forja_drivers::uart::UartBuffers`], and the
//! link's counters.
//!
//! One interrupt handler ([`HostUart::on_interrupt`]) serves both directions. Receiving: every
//! byte the UART holds goes into the receive queue; a full queue drops it and counts an overrun
//! there; a byte lost by the UART itself (hardware overrun, framing or noise error) is counted
//! in [`HostUart::errors`]. Transmitting: while the transmit register is empty and the queue has
//! bytes, the next one is written; when the register is full the transmit-empty interrupt is
//! enabled to come back, and when the queue runs dry it is disabled. The writer's kick (the
//! board's: it pends this interrupt) makes only the handler ever change the UART's interrupt
//! enables (no read-modify-write races with thread code).
//!
//! The controller sees the other ends of the queues as one [`HostLink`] (the drivers'
//! `UartLink`, `Read + ReadReady + Write`): writing queues bytes for the interrupt and waits
//! (spinning) only when the transmit queue is full, which the higher-priority UART interrupt
//! drains meanwhile.
//!
//! # Counters
//!
//! [`LINK_COUNTERS`] is a fixed block in RAM that a debugger (probe-rs, gdb, QEMU's monitor)
//! can read by its symbol name, `FORJA_LINK_COUNTERS`: bytes received, lines answered, frames
//! and garbage runs seen, bytes dropped, UART errors. It is how the link is observed without
//! printing anything on it.

use core::sync::atomic::{AtomicU32, Ordering};

use embedded_hal_nb::serial::Read;
use forja_app::controller::Stats;
use forja_app::firmware::SetupError;
use forja_drivers::uart::{UartBuffers, UartLink, UartRxIrq, UartTxIrq};
use stm32f4xx_hal::prelude::*;
use stm32f4xx_hal::serial::{Event, Instance, Serial};

/// Bytes of the receive queue: several G-code lines or frames.
pub const RX_LEN: usize = 512;

/// Bytes of the transmit queue.
pub const TX_LEN: usize = 256;

/// The queues between the host UART's interrupt and the controller.
static QUEUES: UartBuffers<RX_LEN, TX_LEN> = UartBuffers::new();

/// The host link as the controller takes it: the thread ends of the UART queues.
pub type HostLink = UartLink<'static, RX_LEN, TX_LEN>;

/// The host UART `U` and the interrupt ends of its queues.
pub struct HostUart<U: Instance> {
    serial: Serial<U>,
    rx: UartRxIrq<'static, RX_LEN>,
    tx: UartTxIrq<'static, TX_LEN>,
    errors: u32,
}

impl<U: Instance> HostUart<U> {
    /// Take over a configured UART and enable its receive interrupt (the NVIC line is the
    /// board's to unmask); `kick` pends the UART's interrupt, so that its handler sends what
    /// the link queued. Returns the UART's interrupt side and the host link.
    ///
    /// Context: init, once. Errors: [`SetupError::LinkQueues`] on a second call.
    pub fn start(mut serial: Serial<U>, kick: fn()) -> Result<(Self, HostLink), SetupError> {
        let parts = QUEUES.split().ok_or(SetupError::LinkQueues)?;
        serial.listen(Event::RxNotEmpty);
        let uart = Self {
            serial,
            rx: parts.rx_irq,
            tx: parts.tx_irq,
            errors: 0,
        };
        Ok((
            uart,
            UartLink::new(parts.reader, parts.writer.with_kick(kick)),
        ))
    }

    /// Move bytes between the UART and the queues; `true` when bytes were received. The UART's
    /// error count goes to [`LINK_COUNTERS`].
    ///
    /// Context: the host UART interrupt. A few register accesses per byte.
    pub fn on_interrupt(&mut self) -> bool {
        let mut received = false;
        loop {
            match self.serial.read() {
                Ok(byte) => {
                    // A full queue counts the byte as an overrun itself.
                    self.rx.push(byte);
                    received = true;
                }
                Err(nb::Error::WouldBlock) => break,
                // Reading cleared the error; the byte is gone.
                Err(nb::Error::Other(_)) => self.errors = self.errors.wrapping_add(1),
            }
        }
        // Fill the data register while it is empty. On silicon that is one or two bytes (the
        // register, then the shift register); QEMU sends synchronously, so its register is
        // always empty and the loop drains the queue (QEMU 7.2 raises no transmit interrupts
        // at all, so it must).
        loop {
            if !self.serial.is_tx_empty() {
                self.serial.listen(Event::TxEmpty);
                break;
            }
            match self.tx.pop() {
                // The data register is empty: the write cannot block.
                Some(byte) => {
                    let _ = embedded_hal_nb::serial::Write::write(&mut self.serial, byte);
                }
                None => {
                    self.serial.unlisten(Event::TxEmpty);
                    break;
                }
            }
        }
        LINK_COUNTERS
            .uart_errors
            .store(self.errors, Ordering::Relaxed);
        received
    }

    /// Bytes the UART lost to hardware errors (overrun, framing, noise), wrapping.
    pub fn errors(&self) -> u32 {
        self.errors
    }
}

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

impl LinkCounters {
    /// Publish the controller's counters (`stats`) and the link's.
    ///
    /// Context: the controller's (the one context that polls it).
    pub fn publish(&self, link: &HostLink, stats: &Stats) {
        self.rx_bytes.store(link.received(), Ordering::Relaxed);
        self.lines.store(stats.oks, Ordering::Relaxed);
        self.frames.store(stats.frames, Ordering::Relaxed);
        self.dropped.store(stats.garbage_runs, Ordering::Relaxed);
        self.rx_overruns.store(link.overruns(), Ordering::Relaxed);
    }
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
