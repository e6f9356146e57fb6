//! The host link on a UART, interrupt-driven, through [`forja_drivers::uart::UartBuffers`].
//!
//! One interrupt ([`HostUart::on_interrupt`]) serves both directions. Receiving: the UART's
//! 32-byte FIFO is emptied into the receive queue (its interrupt comes at the FIFO's half mark,
//! or after 32 bit times of quiet). Transmitting: the FIFO is filled from the transmit queue;
//! while bytes remain, the transmit interrupt (the FIFO draining to half) is enabled to come
//! back, and it is disabled when the queue runs dry. The writer's kick (the board's: it pends
//! this interrupt) makes only its handler change the UART's interrupt enables.

use forja_app::firmware::SetupError;
use forja_drivers::uart::{UartBuffers, UartLink, UartRxIrq, UartTxIrq};
use rp2040_hal::uart::{Enabled, UartDevice, UartPeripheral, ValidUartPinout};

/// Bytes of the receive queue: several G-code lines or frames.
pub const RX_LEN: usize = 512;

/// Bytes of the transmit queue.
pub const TX_LEN: usize = 256;

/// The queues between the UART's interrupt and the controller.
static QUEUES: UartBuffers<RX_LEN, TX_LEN> = UartBuffers::new();

/// The host link as the controller takes it: the drivers' `UartLink` over the thread ends of
/// the two queues; the writer kicks the UART interrupt after queueing.
pub type HostLink = UartLink<'static, RX_LEN, TX_LEN>;

/// The enabled UART `D` on its pins `P`, and the interrupt ends of its queues.
pub struct HostUart<D: UartDevice, P: ValidUartPinout<D>> {
    uart: UartPeripheral<Enabled, D, P>,
    rx: UartRxIrq<'static, RX_LEN>,
    tx: UartTxIrq<'static, TX_LEN>,
}

impl<D: UartDevice, P: ValidUartPinout<D>> HostUart<D, P> {
    /// Take over an enabled UART and enable its receive interrupts (the NVIC line is the
    /// board's to unmask); `kick` pends the UART's interrupt, so that its handler sends what
    /// the link queued. Returns the UART's interrupt side and the host link.
    ///
    /// Context: init, once. Errors: [`SetupError::LinkQueues`] on a second call.
    pub fn start(
        mut uart: UartPeripheral<Enabled, D, P>,
        kick: fn(),
    ) -> Result<(Self, HostLink), SetupError> {
        let parts = QUEUES.split().ok_or(SetupError::LinkQueues)?;
        uart.enable_rx_interrupt();
        let link = UartLink::new(parts.reader, parts.writer.with_kick(kick));
        let uart = Self {
            uart,
            rx: parts.rx_irq,
            tx: parts.tx_irq,
        };
        Ok((uart, link))
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
