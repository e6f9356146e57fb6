//! Host links.
//!
//! Bytes move over [`embedded-io`](https://docs.rs/embedded-io) `Read`/`Write` (or their
//! non-blocking `ReadReady`/`WriteReady` forms); this module only adds what a byte stream
//! cannot say: whether anybody is at the other end.

/// Whether a host is at the other end of a link.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LinkState {
    /// No host: a UART with no activity detection, a closed TCP socket, a dropped WiFi.
    Disconnected,
    /// A host is attached and bytes can flow.
    Connected,
}

/// The connection state of a link.
pub trait LinkStatus {
    /// The current state.
    ///
    /// Context: thread. Never blocks. Cannot fail: a link that cannot tell says `Connected`.
    fn state(&self) -> LinkState;
}

impl<T: LinkStatus + ?Sized> LinkStatus for &T {
    fn state(&self) -> LinkState {
        T::state(self)
    }
}

impl<T: LinkStatus + ?Sized> LinkStatus for &mut T {
    fn state(&self) -> LinkState {
        T::state(self)
    }
}
