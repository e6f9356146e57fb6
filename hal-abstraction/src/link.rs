//! Host links.
//!
//! Bytes move over [`embedded-io`](https://docs.rs/embedded-io) `Read`/`Write` (or their
//! non-blocking `ReadReady`/`WriteReady` forms); this module only adds what a byte stream
//! cannot say: whether anybody is at the other end.
//!
//! With the `alloc` feature, a `Box` of a link is a link too, as in `embedded-io`.

#[cfg(feature = "alloc")]
extern crate alloc;

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

#[cfg(feature = "alloc")]
impl<T: LinkStatus + ?Sized> LinkStatus for alloc::boxed::Box<T> {
    fn state(&self) -> LinkState {
        T::state(self)
    }
}

#[cfg(all(test, feature = "alloc"))]
mod tests {
    use super::alloc::boxed::Box;
    use super::*;

    struct Up;

    impl LinkStatus for Up {
        fn state(&self) -> LinkState {
            LinkState::Connected
        }
    }

    #[test]
    fn a_boxed_link_tells_the_state_of_the_link_in_it() {
        let link: Box<dyn LinkStatus> = Box::new(Up);
        assert_eq!(link.state(), LinkState::Connected);
        assert_eq!(Box::new(&link).state(), LinkState::Connected);
    }
}
