//! Host links: TCP (like the ESP32's WiFi), the web page's WebSocket (like the ESP32's web
//! server), a pseudo-terminal (like a UART), an in-process
//! pair, and a fault injector over any of them.
//!
//! Every link is a [`PortLink`], the contract of a firmware board's links: bytes move through
//! `embedded-io` ([`Read`], [`ReadReady`], [`Write`], and [`WriteReady`] too) exactly as on
//! the firmware boards, and
//! [`LinkStatus`](forja_hal_abstraction::link::LinkStatus) says whether a host is at the
//! other end. The protocol code does not know which link it is on.
//!
//! | link | what | connected while |
//! |---|---|---|
//! | [`TcpLink`] | a listening socket, one controlling client at a time, as the port's session rules decide ([`Admission`], [`PortLink::admit`]) | a client is admitted and has not closed |
//! | [`WebLink`] | an HTTP listener serving the operator's page and a WebSocket at `/ws`: one controlling client, the others watch ([`WebLink`]) | a WebSocket client is admitted and has not closed |
//! | [`PtyLink`] | a pseudo-terminal pair; host software opens the slave (`/dev/pts/N`) | some process holds the slave open |
//! | [`MemoryLink`] | an in-process pipe to a [`MemoryHost`], for tests and scripted jobs | the [`MemoryHost`] exists |
//! | [`FaultInjector`] | wraps any of them; corrupts and drops received bytes | as the wrapped link |
//!
//! # Polling
//!
//! OS links are non-blocking and buffered: [`PortLink::poll`] (context: thread; never blocks)
//! notices the loss of a peer, moves received bytes into the receive buffer and sends what the
//! transmit buffer holds; on a connection-oriented link, [`PortLink::admit`] then lets the
//! port's session rules ([`Admission`], the application's) admit or refuse the peers that
//! connected. The simulation's thread
//! side calls both once per turn, then reads while [`ReadReady::read_ready`] says so; that read
//! never blocks.
//! [`ReadReady::read_ready`] on an empty buffer and every [`Write::write`] service the link
//! too, so received bytes are seen and replies leave without waiting for the next poll.
//!
//! The plain blocking methods keep their `embedded-io` meaning, for code that does not poll:
//! [`Read::read`] with an empty buffer polls and waits (in steps of a millisecond) until a byte
//! arrives. The simulation never calls it without [`ReadReady::read_ready`] first.
//!
//! # Writing never blocks
//!
//! [`Write::write`] queues the whole of `buf` in the transmit buffer, sends what the peer takes
//! now, and returns `buf.len()` at once: the firmware never waits for a host. With no peer
//! connected the bytes are discarded (like a UART with nothing attached). When the transmit
//! buffer cannot take the whole of `buf` (the peer has stopped reading: [`TX_CAPACITY`] bytes
//! of replies wait, besides what the operating system holds), the link's overflow rule applies,
//! and a reply is never cut in two:
//!
//! | link | a peer that stops reading |
//! |---|---|
//! | [`TcpLink`] | is dropped: its connection is closed ([`TcpLink::overflows`] counts them), and the next client may connect |
//! | [`WebLink`] | is dropped: its WebSocket is closed with 1008 ([`WebStats::overflows`]), and a watcher or the next client may take control |
//! | [`PtyLink`] | the writes that do not fit are discarded whole and counted ([`PtyLink::tx_discarded`]): a terminal cannot be closed from this side |
//!
//! [`Write::flush`] sends what it can and waits for the rest at most [`FLUSH_LIMIT`]; it fails
//! with `TimedOut` if the peer has not taken it by then.
//!
//! Receive buffers hold at most [`RX_CAPACITY`] bytes: past that, OS links stop reading and
//! the host is held back by TCP flow control or the terminal's buffer, as flow control would
//! on a UART. Transmit buffers hold [`TX_CAPACITY`] bytes. [`PortLink::discard_input`] drops
//! what was received and not yet read, when the session of the host that sent it has ended:
//! the buffered links clear their buffers, the in-process link its pipe.

mod fault;
mod memory;
mod pty;
mod tcp;
mod web;
pub mod web_client;

use std::collections::VecDeque;
use std::io;

pub use embedded_io::{Read, ReadReady, Write, WriteReady};
pub use fault::{FaultConfig, FaultConfigError, FaultInjector, FaultStats, FaultyBytes};
pub use memory::{MemoryHost, MemoryLink};
pub use pty::PtyLink;
pub use tcp::TcpLink;
pub use web::{MAX_HTTP, MAX_WATCHERS, Tap, Tapped, WebLink, WebStats};

/// The page [`WebLink`] serves and the codecs it speaks with (the page's own crate).
pub use forja_web;

/// What every link here is: a link a board serves as a port, the firmware boards' contract.
pub use forja_drivers::port_link::PortLink;

use forja_drivers::port_link::Admission;
use forja_hal_abstraction::link::LinkState;

/// Most bytes a link's receive buffer holds.
pub const RX_CAPACITY: usize = 64 * 1024;

/// Most bytes a link's transmit buffer holds.
pub const TX_CAPACITY: usize = 64 * 1024;

/// How long blocking link calls sleep between two polls.
const BLOCKING_POLL: std::time::Duration = std::time::Duration::from_millis(1);

/// Longest [`Write::flush`] waits for a peer to take what is queued.
pub const FLUSH_LIMIT: std::time::Duration = std::time::Duration::from_millis(500);

/// The receive and transmit buffers of an OS link.
#[derive(Debug, Default)]
pub(crate) struct Buffers {
    pub(crate) rx: VecDeque<u8>,
    pub(crate) tx: VecDeque<u8>,
}

impl Buffers {
    pub(crate) fn rx_room(&self) -> usize {
        RX_CAPACITY.saturating_sub(self.rx.len())
    }

    /// Move up to `buf.len()` received bytes into `buf`.
    pub(crate) fn take_rx(&mut self, buf: &mut [u8]) -> usize {
        let n = buf.len().min(self.rx.len());
        for (dst, src) in buf.iter_mut().zip(self.rx.drain(..n)) {
            *dst = src;
        }
        n
    }

    /// Queue the whole of `buf` for transmission, if it fits; `false` (nothing queued) if not.
    pub(crate) fn put_tx(&mut self, buf: &[u8]) -> bool {
        if buf.len() > TX_CAPACITY.saturating_sub(self.tx.len()) {
            return false;
        }
        self.tx.extend(buf);
        true
    }

    /// Drop the received bytes not yet read; returns how many.
    pub(crate) fn clear_rx(&mut self) -> usize {
        let n = self.rx.len();
        self.rx.clear();
        n
    }
}

/// The parts of an OS link that the shared `embedded-io` implementation needs.
pub(crate) trait BufferedPort {
    fn buffers(&mut self) -> &mut Buffers;
    fn is_connected(&self) -> bool;
    fn service(&mut self) -> io::Result<()>;
    fn admit(&mut self, _gate: &mut dyn Admission, _now_ms: u32) -> io::Result<bool> {
        Ok(false)
    }
    /// `lost` bytes of one write did not fit in the transmit buffer (the peer stopped reading):
    /// drop the peer, or count them as discarded.
    fn overflow(&mut self, lost: usize);
    fn hang_up(&mut self) {}
}

pub(crate) fn port_read<P: BufferedPort>(port: &mut P, buf: &mut [u8]) -> io::Result<usize> {
    if buf.is_empty() {
        return Ok(0);
    }
    loop {
        let n = port.buffers().take_rx(buf);
        if n > 0 {
            return Ok(n);
        }
        port.service()?;
        if port.buffers().rx.is_empty() {
            std::thread::sleep(BLOCKING_POLL);
        }
    }
}

pub(crate) fn port_write<P: BufferedPort>(port: &mut P, buf: &[u8]) -> io::Result<usize> {
    if buf.is_empty() || !port.is_connected() {
        return Ok(buf.len());
    }
    if !port.buffers().put_tx(buf) {
        // Make what room the peer allows now, then try once more.
        port.service()?;
        if port.is_connected() && !port.buffers().put_tx(buf) {
            port.overflow(buf.len());
            return Ok(buf.len());
        }
    }
    // Send at once rather than at the next poll: replies go out with no added latency.
    port.service()?;
    Ok(buf.len())
}

pub(crate) fn port_flush<P: BufferedPort>(port: &mut P) -> io::Result<()> {
    let start = std::time::Instant::now();
    loop {
        port.service()?;
        if !port.is_connected() || port.buffers().tx.is_empty() {
            return Ok(());
        }
        if start.elapsed() >= FLUSH_LIMIT {
            return Err(io::Error::new(
                io::ErrorKind::TimedOut,
                "the peer does not take what is sent",
            ));
        }
        std::thread::sleep(BLOCKING_POLL);
    }
}

pub(crate) fn port_write_ready<P: BufferedPort>(port: &mut P) -> bool {
    !port.is_connected() || port.buffers().tx.len() < TX_CAPACITY
}

pub(crate) fn state(connected: bool) -> LinkState {
    if connected {
        LinkState::Connected
    } else {
        LinkState::Disconnected
    }
}

/// Implements `embedded-io`, `LinkStatus` and [`PortLink`] for a [`BufferedPort`].
macro_rules! buffered_link {
    ($ty:ty) => {
        impl embedded_io::ErrorType for $ty {
            type Error = std::io::Error;
        }

        impl embedded_io::ReadReady for $ty {
            fn read_ready(&mut self) -> Result<bool, std::io::Error> {
                if $crate::link::BufferedPort::buffers(self).rx.is_empty() {
                    $crate::link::BufferedPort::service(self)?;
                }
                Ok(!$crate::link::BufferedPort::buffers(self).rx.is_empty())
            }
        }

        impl embedded_io::Read for $ty {
            fn read(&mut self, buf: &mut [u8]) -> Result<usize, std::io::Error> {
                $crate::link::port_read(self, buf)
            }
        }

        impl embedded_io::WriteReady for $ty {
            fn write_ready(&mut self) -> Result<bool, std::io::Error> {
                Ok($crate::link::port_write_ready(self))
            }
        }

        impl embedded_io::Write for $ty {
            fn write(&mut self, buf: &[u8]) -> Result<usize, std::io::Error> {
                $crate::link::port_write(self, buf)
            }

            fn flush(&mut self) -> Result<(), std::io::Error> {
                $crate::link::port_flush(self)
            }
        }

        impl forja_hal_abstraction::link::LinkStatus for $ty {
            fn state(&self) -> forja_hal_abstraction::link::LinkState {
                $crate::link::state($crate::link::BufferedPort::is_connected(self))
            }
        }

        impl $crate::link::PortLink for $ty {
            fn poll(&mut self) -> Result<(), std::io::Error> {
                $crate::link::BufferedPort::service(self)
            }

            fn connections(&self) -> u64 {
                self.connections
            }

            fn admit(
                &mut self,
                gate: &mut dyn forja_drivers::port_link::Admission,
                now_ms: u32,
            ) -> Result<bool, std::io::Error> {
                $crate::link::BufferedPort::admit(self, gate, now_ms)
            }

            fn discard_input(&mut self) -> Result<usize, std::io::Error> {
                Ok($crate::link::BufferedPort::buffers(self).clear_rx())
            }

            fn hang_up(&mut self) {
                $crate::link::BufferedPort::hang_up(self)
            }
        }
    };
}
pub(crate) use buffered_link;
