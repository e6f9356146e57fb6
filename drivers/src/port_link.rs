//! What a host link must do to be one of a board's ports: the contract between a link (a
//! UART, a TCP server, the simulator's sockets and terminals) and the application layer that
//! serves one controlling host across the board's ports (`forja_app::hosts`).
//!
//! A [`PortLink`] is an `embedded-io` byte stream ([`Read`], [`ReadReady`], [`Write`]) that
//! also says whether a host is there ([`LinkStatus`]), counts the hosts that arrive, and, on a
//! connection-oriented link, asks the port's session rules ([`Admission`]) whether to admit or
//! refuse each client.
//!
//! The rules themselves (one controlling client, keep-alives, the idle time-out) are the
//! application's (`forja_app::session::LinkSession`); a link only carries out their answer,
//! [`Admit`].
//!
//! A `&mut` of a link is a link; with the `alloc` feature a `Box` of one is too, so that a
//! board may serve links of several types as `Box<dyn …>` (the simulator does).
//!
//! # Execution context
//!
//! Thread. No method blocks, writes included: a link drops or discards what its host does not
//! read, so that serving hosts never holds up motion.

use embedded_io::{Read, ReadReady, Write};
use forja_hal_abstraction::link::{LinkState, LinkStatus};

#[cfg(feature = "alloc")]
extern crate alloc;

/// Whether a client that connected may control the machine: the answer of the application's
/// session rules ([`Admission::on_connect`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Admit {
    /// The client becomes the controlling client: the link serves it, and the caller greets it
    /// (frame 54).
    Control,
    /// Another client is in control (on this link, or on another link of the board): the link
    /// sends the new client its busy message and closes it; the controlling client is
    /// untouched.
    Refuse,
}

/// The session rules a connection-oriented link asks about its clients (implemented by
/// `forja_app::session::LinkSession`). [`LinkStatus`] says whether a client is in control.
///
/// The link reports what happens on its connections, in the order it happened; the rules
/// decide. Object safe: a link takes it as `&mut dyn Admission` ([`PortLink::admit`]).
///
/// Context: thread (the task that serves the link's connections). No method blocks or fails.
pub trait Admission: LinkStatus {
    /// A client connected at `now_ms` (milliseconds of a wrapping `u32` clock): whether it
    /// becomes the controlling client or is refused. A refused client never joins the session:
    /// do not report its disconnection.
    fn on_connect(&mut self, now_ms: u32) -> Admit;

    /// The controlling client went away (closed, reset, timed out, or was hung up on). Call it
    /// for the controlling client only. Idempotent.
    fn on_disconnect(&mut self);
}

/// The simplest session rules: the first client to connect controls until it leaves, and any
/// other is refused meanwhile. No keep-alives, no idle time-out, no lock: the application's
/// session (`forja_app::session::LinkSession`) adds those; this serves a link's own tests and
/// a board that needs none of them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SingleClient {
    connected: bool,
}

impl SingleClient {
    /// Nobody connected.
    pub const fn new() -> Self {
        Self { connected: false }
    }
}

impl LinkStatus for SingleClient {
    fn state(&self) -> LinkState {
        if self.connected {
            LinkState::Connected
        } else {
            LinkState::Disconnected
        }
    }
}

impl Admission for SingleClient {
    fn on_connect(&mut self, _now_ms: u32) -> Admit {
        if core::mem::replace(&mut self.connected, true) {
            Admit::Refuse
        } else {
            Admit::Control
        }
    }

    fn on_disconnect(&mut self) {
        self.connected = false;
    }
}

/// A host link that a board serves as one of its ports: bytes in both directions, whether a
/// host is there ([`LinkStatus`]), and the connections of its hosts.
///
/// Context: thread. No method blocks, writes included: a link drops or discards what its host
/// does not read.
pub trait PortLink: Read + ReadReady + Write + LinkStatus {
    /// Service the link: notice peers that arrive and leave, move bytes between the link and
    /// its buffers.
    ///
    /// Errors: the link itself failed (a listening socket, a terminal); a peer that goes away
    /// is a state change, not an error.
    fn poll(&mut self) -> Result<(), Self::Error>;

    /// How many hosts have arrived on the link so far: a change is a new host, whose decoder
    /// starts afresh.
    fn connections(&self) -> u64;

    /// Let `gate` decide, at `now_ms`, on what happened on a connection-oriented link since the
    /// last call, in the order it happened: a controlling client that closed is
    /// [`Admission::on_disconnect`], each client that connected is [`Admission::on_connect`],
    /// and the link carries out the answer: [`Admit::Control`] makes it the controlling
    /// client, [`Admit::Refuse`] sends it the link's busy message and closes it. Returns
    /// whether a client became the controlling one (the caller greets it with frame 54); the
    /// keep-alives are the caller's, from its session rules.
    ///
    /// A connection-oriented link admits nobody unless this is called. Give a link the same
    /// `gate` at every call, and no other link that `gate`. A link without connections (a
    /// terminal, a UART) admits nobody, which is the provided implementation.
    ///
    /// Errors: as [`PortLink::poll`].
    fn admit(&mut self, gate: &mut dyn Admission, now_ms: u32) -> Result<bool, Self::Error> {
        let _ = (gate, now_ms);
        Ok(false)
    }

    /// Drop every byte received and not yet read (the session of the host that sent it has
    /// ended, or that host is not the controlling one). Returns how many were dropped. Bytes
    /// that arrive later are received as usual.
    ///
    /// Errors: as [`PortLink::poll`].
    fn discard_input(&mut self) -> Result<usize, Self::Error>;

    /// Close the controlling host's connection (its session timed out); its session hears of
    /// it at the next [`PortLink::admit`]. A link that cannot (a terminal, a UART) does
    /// nothing, which is the provided implementation.
    fn hang_up(&mut self) {}
}

impl<T: PortLink + ?Sized> PortLink for &mut T {
    fn poll(&mut self) -> Result<(), Self::Error> {
        T::poll(self)
    }
    fn connections(&self) -> u64 {
        T::connections(self)
    }
    fn admit(&mut self, gate: &mut dyn Admission, now_ms: u32) -> Result<bool, Self::Error> {
        T::admit(self, gate, now_ms)
    }
    fn discard_input(&mut self) -> Result<usize, Self::Error> {
        T::discard_input(self)
    }
    fn hang_up(&mut self) {
        T::hang_up(self);
    }
}

#[cfg(feature = "alloc")]
impl<T: PortLink + ?Sized> PortLink for alloc::boxed::Box<T> {
    fn poll(&mut self) -> Result<(), Self::Error> {
        T::poll(self)
    }
    fn connections(&self) -> u64 {
        T::connections(self)
    }
    fn admit(&mut self, gate: &mut dyn Admission, now_ms: u32) -> Result<bool, Self::Error> {
        T::admit(self, gate, now_ms)
    }
    fn discard_input(&mut self) -> Result<usize, Self::Error> {
        T::discard_input(self)
    }
    fn hang_up(&mut self) {
        T::hang_up(self);
    }
}

#[cfg(test)]
mod tests {
    use core::convert::Infallible;

    use embedded_io::ErrorType;

    use super::*;

    /// A connection-oriented link with one client waiting, which it admits through the
    /// session rules.
    #[derive(Default)]
    struct Socket {
        rx: std::vec::Vec<u8>,
        waiting: bool,
        connected: bool,
        connections: u64,
    }

    impl ErrorType for Socket {
        type Error = Infallible;
    }

    impl Read for Socket {
        fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
            let n = buf.len().min(self.rx.len());
            buf[..n].copy_from_slice(&self.rx[..n]);
            self.rx.drain(..n);
            Ok(n)
        }
    }

    impl ReadReady for Socket {
        fn read_ready(&mut self) -> Result<bool, Infallible> {
            Ok(!self.rx.is_empty())
        }
    }

    impl Write for Socket {
        fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
            Ok(buf.len())
        }
        fn flush(&mut self) -> Result<(), Infallible> {
            Ok(())
        }
    }

    impl LinkStatus for Socket {
        fn state(&self) -> LinkState {
            if self.connected {
                LinkState::Connected
            } else {
                LinkState::Disconnected
            }
        }
    }

    impl PortLink for Socket {
        fn poll(&mut self) -> Result<(), Infallible> {
            if self.waiting {
                self.connections += 1;
            }
            Ok(())
        }
        fn connections(&self) -> u64 {
            self.connections
        }
        fn admit(&mut self, gate: &mut dyn Admission, now_ms: u32) -> Result<bool, Infallible> {
            if !core::mem::take(&mut self.waiting) {
                return Ok(false);
            }
            self.connected = gate.on_connect(now_ms) == Admit::Control;
            Ok(self.connected)
        }
        fn discard_input(&mut self) -> Result<usize, Infallible> {
            Ok(self.rx.drain(..).count())
        }
        fn hang_up(&mut self) {
            self.connected = false;
        }
    }

    /// Serve `link` for one client: poll, admit, drop its input, hang up.
    fn serve<L: PortLink>(mut link: L, gate: &mut dyn Admission) -> (u64, bool, usize, LinkState) {
        link.poll().ok();
        let admitted = link.admit(gate, 5).unwrap_or(false);
        let dropped = link.discard_input().unwrap_or(0);
        link.hang_up();
        (link.connections(), admitted, dropped, link.state())
    }

    fn socket() -> Socket {
        Socket {
            rx: b"G1 X1\n".to_vec(),
            waiting: true,
            ..Socket::default()
        }
    }

    #[test]
    fn a_borrowed_link_is_the_link() {
        let mut link = socket();
        let mut gate = SingleClient::new();
        let served = serve(&mut link, &mut gate);
        assert_eq!(served, (1, true, 6, LinkState::Disconnected));
        assert_eq!(
            gate.state(),
            LinkState::Connected,
            "the session hears of the hang-up at the next admit"
        );
        assert!(link.rx.is_empty());
    }

    #[test]
    fn a_link_without_connections_admits_nobody() {
        struct Uart(Socket);
        impl ErrorType for Uart {
            type Error = Infallible;
        }
        impl Read for Uart {
            fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
                self.0.read(buf)
            }
        }
        impl ReadReady for Uart {
            fn read_ready(&mut self) -> Result<bool, Infallible> {
                self.0.read_ready()
            }
        }
        impl Write for Uart {
            fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
                Ok(buf.len())
            }
            fn flush(&mut self) -> Result<(), Infallible> {
                Ok(())
            }
        }
        impl LinkStatus for Uart {
            fn state(&self) -> LinkState {
                LinkState::Connected
            }
        }
        impl PortLink for Uart {
            fn poll(&mut self) -> Result<(), Infallible> {
                Ok(())
            }
            fn connections(&self) -> u64 {
                1
            }
            fn discard_input(&mut self) -> Result<usize, Infallible> {
                self.0.discard_input()
            }
        }
        let mut gate = SingleClient::new();
        let served = serve(Uart(socket()), &mut gate);
        assert_eq!(
            served,
            (1, false, 6, LinkState::Connected),
            "hanging up does nothing"
        );
        assert_eq!(gate.state(), LinkState::Disconnected);
    }

    #[cfg(feature = "alloc")]
    #[test]
    fn a_boxed_link_is_the_link_in_it() {
        let link: std::boxed::Box<dyn PortLink<Error = Infallible>> =
            std::boxed::Box::new(socket());
        let mut gate = SingleClient::new();
        let served = serve(link, &mut gate);
        assert_eq!(served, (1, true, 6, LinkState::Disconnected));
    }
}
