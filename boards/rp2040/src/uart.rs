//! The host link: UART0, interrupt-driven, through [`forja_drivers::uart::UartBuffers`].
//!
//! One interrupt serves both directions. Receiving: the UART's 32-byte FIFO is emptied into
//! the receive queue (its interrupt comes at the FIFO's half mark, or after 32 bit times of
//! quiet). Transmitting: the FIFO is filled from the transmit queue; while bytes remain, the
//! transmit interrupt (the FIFO draining to half) is enabled to come back, and it is disabled
//! when the queue runs dry. The writer's kick ([`kick`]) pends the interrupt, so only its
//! handler changes the UART's interrupt enables.

use cortex_m::peripheral::NVIC;
use forja_drivers::uart::{UartBuffers, UartReader, UartRxIrq, UartTxIrq, UartWriter};
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

/// The host link as the controller takes it: the thread ends of the two queues as one
/// `Read + ReadReady + Write`.
pub struct HostLink {
    reader: UartReader<'static, RX_LEN>,
    writer: UartWriter<'static, TX_LEN>,
}

impl HostLink {
    /// Join the two ends; the writer kicks the UART interrupt after queueing.
    pub fn new(reader: UartReader<'static, RX_LEN>, writer: UartWriter<'static, TX_LEN>) -> Self {
        Self {
            reader,
            writer: writer.with_kick(kick),
        }
    }

    /// Whether received bytes wait.
    ///
    /// Context: the controller task.
    pub fn has_input(&mut self) -> bool {
        embedded_io::ReadReady::read_ready(&mut self.reader).unwrap_or(false)
    }
}

impl embedded_io::ErrorType for HostLink {
    type Error = core::convert::Infallible;
}

impl embedded_io::Read for HostLink {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        self.reader.read(buf)
    }
}

impl embedded_io::ReadReady for HostLink {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        self.reader.read_ready()
    }
}

impl embedded_io::Write for HostLink {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.writer.write(buf)
    }

    fn flush(&mut self) -> Result<(), Self::Error> {
        self.writer.flush()
    }
}
