//! The host UART: interrupt-driven, through [`forja_drivers::uart::UartBuffers`].
//!
//! One interrupt handler serves both directions. Receiving: every byte the UART holds goes into
//! the receive queue; a full queue drops it and counts an overrun there; a byte lost by the
//! UART itself (hardware overrun, framing or noise error) is counted in [`HostUart::errors`].
//! Transmitting: while the transmit register is empty and the queue has bytes, the next one is
//! written; when the register is full the transmit-empty interrupt is enabled to come back,
//! and when the queue runs dry it is disabled. The writer's kick ([`kick`]) pends this interrupt, so that only the handler
//! ever changes the UART's interrupt enables (no read-modify-write races with thread code).

use cortex_m::peripheral::NVIC;
use embedded_hal_nb::serial::Read;
use forja_drivers::uart::{UartBuffers, UartRxIrq, UartTxIrq};
use stm32f4xx_hal::prelude::*;
use stm32f4xx_hal::serial::{Event, Serial};

use crate::board::{HOST_UART_IRQ, HostUsart};

/// Bytes of the receive queue: several G-code lines or frames.
pub const RX_LEN: usize = 512;

/// Bytes of the transmit queue.
pub const TX_LEN: usize = 256;

/// The queues between the host UART's interrupt and the controller task.
pub static QUEUES: UartBuffers<RX_LEN, TX_LEN> = UartBuffers::new();

/// Pend the host UART's interrupt, so that its handler sends what was queued. Handed to
/// [`forja_drivers::uart::UartWriter::with_kick`].
///
/// Context: any. One register write.
pub fn kick() {
    NVIC::pend(HOST_UART_IRQ);
}

/// The host UART and the interrupt ends of its queues.
pub struct HostUart {
    serial: Serial<HostUsart>,
    rx: UartRxIrq<'static, RX_LEN>,
    tx: UartTxIrq<'static, TX_LEN>,
    errors: u32,
}

impl HostUart {
    /// Take over a configured UART: enable its receive interrupt (the NVIC line is unmasked
    /// by RTIC).
    ///
    /// Context: init.
    pub fn new(
        mut serial: Serial<HostUsart>,
        rx: UartRxIrq<'static, RX_LEN>,
        tx: UartTxIrq<'static, TX_LEN>,
    ) -> Self {
        serial.listen(Event::RxNotEmpty);
        Self {
            serial,
            rx,
            tx,
            errors: 0,
        }
    }

    /// Move bytes between the UART and the queues; `true` when bytes were received.
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
        received
    }

    /// Bytes the UART lost to hardware errors (overrun, framing, noise), wrapping.
    pub fn errors(&self) -> u32 {
        self.errors
    }
}
