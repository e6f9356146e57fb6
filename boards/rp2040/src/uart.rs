//! The host link: UART0, interrupt-driven, through [`forja_drivers::uart::UartBuffers`].
//!
//! One interrupt serves both directions. Receiving: the UART's 32-byte FIFO is emptied into
//! the receive queue (its interrupt comes at the FIFO's half mark, or after 32 bit times of
//! quiet). Transmitting: the FIFO is filled from the transmit queue; while bytes remain, the
//! transmit interrupt (the FIFO draining to half) is enabled to come back, and it is disabled
//! when the queue runs dry. The writer's kick ([`kick`]) pends the interrupt, so only its
//! handler changes the UART's interrupt enables.

use cortex_m::peripheral::NVIC;
use forja_drivers::uart::{UartBuffers, UartLink, UartReader, UartRxIrq, UartTxIrq, UartWriter};
use rp2040_hal::pac::{Interrupt, UART0};
use rp2040_hal::uart::{Enabled, UartPeripheral};

use crate::board::HostUartPins;

/// Bytes of the receive queue: several G-code lines or frames.
pub const RX_LEN: usize = 512;

/// Bytes of the transmit queue.
pub const TX_LEN: usize = 256;

/// The queues between the UART's interrupt and the controller task.
pub static QUEUES: UartBuffers<RX_LEN, TX_LEN> = UartBuffers::new();

/// The enabled UART0.
pub type Uart = UartPeripheral<Enabled, UART0, HostUartPins>;

/// Pend the UART's interrupt, so that it sends what was queued.
///
/// Context: any. One register write.
pub fn kick() {
    NVIC::pend(Interrupt::UART0_IRQ);
}

/// The UART and the interrupt ends of its queues.
pub struct HostUart {
    uart: Uart,
    rx: UartRxIrq<'static, RX_LEN>,
    tx: UartTxIrq<'static, TX_LEN>,
}

impl HostUart {
    /// Take over an enabled UART and enable its receive interrupts (the NVIC line is unmasked
    /// by RTIC).
    ///
    /// Context: init.
    pub fn new(
        mut uart: Uart,
        rx: UartRxIrq<'static, RX_LEN>,
        tx: UartTxIrq<'static, TX_LEN>,
    ) -> Self {
        uart.enable_rx_interrupt();
        Self { uart, rx, tx }
    }

    /// Move bytes between the UART and the queues; `true` when bytes were received. A byte
    /// received damaged (framing, parity, break) is dropped, and bytes that found the FIFO
    /// full are lost; the protocol's checksums and resends recover the line.
    ///
    /// Context: the UART interrupt. A few register accesses per byte.
    pub fn on_interrupt(&mut self) -> bool {
        let mut received = false;
        let mut fifo = [0u8; 32];
        loop {
            match self.uart.read_raw(&mut fifo) {
                Ok(n) => {
                    received = true;
                    self.rx.push_slice(&fifo[..n]);
                }
                Err(nb::Error::Other(error)) => {
                    received |= !error.discarded.is_empty();
                    self.rx.push_slice(error.discarded);
                }
                Err(nb::Error::WouldBlock) => break,
            }
        }
        let uart = &self.uart;
        while self.tx.drain_with(|bytes| match uart.write_raw(bytes) {
            Ok(rest) => bytes.len() - rest.len(),
            Err(_) => 0,
        }) > 0
        {}
        if self.tx.is_empty() {
            self.uart.disable_tx_interrupt();
        } else {
            self.uart.enable_tx_interrupt();
        }
        received
    }
}

/// The host link as the controller takes it: the drivers' `UartLink` over the thread ends of
/// the two queues; the writer kicks the UART interrupt after queueing ([`link`]).
pub type HostLink = UartLink<'static, RX_LEN, TX_LEN>;

/// Join the two thread ends into the host link.
pub fn link(reader: UartReader<'static, RX_LEN>, writer: UartWriter<'static, TX_LEN>) -> HostLink {
    UartLink::new(reader, writer.with_kick(kick))
}
