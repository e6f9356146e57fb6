//! What a host link must do to be one of a board's ports: the contract between a link (a
//! UART, a TCP server, the simulator's sockets and terminals) and the application layer that
//! serves one controlling host across the board's ports (`forja_app::hosts`).
//!
//! A [`PortLink`] is an `embedded-io` byte stream ([`Read`], [`ReadReady`], [`Write`]) that
//! also says whether a host is there ([`LinkStatus`]), counts the hosts that arrive, and, on a
//! connection-oriented link, lets the port's [`LinkSession`] admit or refuse its clients.
//!
//! A `&mut` of a link is a link; with the `alloc` feature a `Box` of one is too, so that a
//! board may serve links of several types as `Box<dyn …>` (the simulator does).
//!
//! # Execution context
//!
//! Thread. No method blocks, writes included: a link drops or discards what its host does not
//! read, so that serving hosts never holds up motion.

use embedded_io::{Read, ReadReady, Write};
use forja_hal_abstraction::link::LinkStatus;

use crate::session::LinkSession;

#[cfg(feature = "alloc")]
extern crate alloc;

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

    /// Let `session` decide, at `now_ms`, on what happened on a connection-oriented link since
    /// the last call, in the order it happened: a controlling client that closed is
    /// [`LinkSession::on_disconnect`], each client that connected is
    /// [`LinkSession::on_connect`], and the link carries out the answer:
    /// [`SessionAction::SendConnected`] makes it the controlling client,
    /// [`SessionAction::RefuseSecondClient`] sends it the link's busy message and closes it.
    /// Returns whether a client became the controlling one (the caller greets it with frame
    /// 54); the keep-alives are the caller's, from [`LinkSession::poll`].
    ///
    /// A connection-oriented link admits nobody unless this is called. Give a link the same
    /// session at every call, and no other link that session. A link without connections (a
    /// terminal, a UART) admits nobody, which is the provided implementation.
    ///
    /// Errors: as [`PortLink::poll`].
    ///
    /// [`SessionAction::SendConnected`]: crate::session::SessionAction::SendConnected
    /// [`SessionAction::RefuseSecondClient`]: crate::session::SessionAction::RefuseSecondClient
    fn admit(&mut self, session: &mut LinkSession, now_ms: u32) -> Result<bool, Self::Error> {
        let _ = (session, now_ms);
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
    fn admit(&mut self, session: &mut LinkSession, now_ms: u32) -> Result<bool, Self::Error> {
        T::admit(self, session, now_ms)
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
    fn admit(&mut self, session: &mut LinkSession, now_ms: u32) -> Result<bool, Self::Error> {
        T::admit(self, session, now_ms)
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
    use forja_hal_abstraction::link::LinkState;

    use super::*;

    /// A connection-oriented link with one client waiting, which it admits through the
    /// session.
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
        fn admit(&mut self, session: &mut LinkSession, now_ms: u32) -> Result<bool, Infallible> {
            if !core::mem::take(&mut self.waiting) {
                return Ok(false);
            }
            self.connected =
                session.on_connect(now_ms) == crate::session::SessionAction::SendConnected;
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
    fn serve<L: PortLink>(mut link: L, session: &mut LinkSession) -> (u64, bool, usize, LinkState) {
        link.poll().ok();
        let admitted = link.admit(session, 5).unwrap_or(false);
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
        let mut session = LinkSession::new(1_000);
        let served = serve(&mut link, &mut session);
        assert_eq!(served, (1, true, 6, LinkState::Disconnected));
        assert!(
            session.is_connected(),
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
        let mut session = LinkSession::new(1_000);
        let served = serve(Uart(socket()), &mut session);
        assert_eq!(
            served,
            (1, false, 6, LinkState::Connected),
            "hanging up does nothing"
        );
        assert!(!session.is_connected());
    }

    #[cfg(feature = "alloc")]
    #[test]
    fn a_boxed_link_is_the_link_in_it() {
        let link: std::boxed::Box<dyn PortLink<Error = Infallible>> =
            std::boxed::Box::new(socket());
        let mut session = LinkSession::new(1_000);
        let served = serve(link, &mut session);
        assert_eq!(served, (1, true, 6, LinkState::Disconnected));
    }
}
