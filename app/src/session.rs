//! Session rules of connection-oriented links (the ESP32's WiFi/TCP link, the simulator's TCP
//! link): one controlling client at a time, a greeting on connect, periodic keep-alives, and
//! optionally an idle time-out for a controlling client that has gone silent.
//!
//! [`LinkSession`] is sans-IO. The caller owns the sockets and the clock. The link reports
//! connections and disconnections through the drivers' admission contract ([`Admission`],
//! which [`PortLink::admit`](forja_drivers::port_link::PortLink::admit) and the drivers' TCP
//! server call) and carries out its answer ([`Admit`]); the controller's side calls
//! [`LinkSession::poll`] with the time and sends what it is asked ([`SessionAction`]),
//! encoding the messages with the protocol crate:
//!
//! | answer or action | the caller |
//! |---|---|
//! | [`Admit::Control`] | the link serves the new client as the controlling one; the controller greets it: [`SessionAction::SendConnected`], message 54 (connected) |
//! | [`SessionAction::SendKeepAlive`] | sends message 55 (keep-alive) with the counter |
//! | [`Admit::Refuse`] | the link sends the refusal to the *new* client and closes it; the controlling client is untouched |
//!
//! ```
//! use forja_app::session::{Admission, Admit, LinkSession, SessionAction};
//!
//! let mut session = LinkSession::new(1_000);
//! assert_eq!(session.on_connect(0), Admit::Control);
//! assert_eq!(session.on_connect(10), Admit::Refuse);
//! assert_eq!(session.poll(999), None);
//! assert_eq!(session.poll(1_000), Some(SessionAction::SendKeepAlive(0)));
//! assert_eq!(session.poll_at(), Some(2_000));
//! ```
//!
//! # Idle time-out
//!
//! With [`LinkSession::with_idle_timeout`], a controlling client that is not heard from for
//! that long loses control: [`LinkSession::poll_idle`] ends the session and the caller closes
//! the client's connection. What keeps a client in control is the caller's to report with
//! [`LinkSession::on_input`]: any byte received from it, and every moment the controller owes
//! it an answer (a held line, a homing cycle, a heater wait) or the reports it asked for every
//! period (`M155 S`, `M27 S`), so that a client waiting for an answer is never dropped for its
//! silence. Any other client that only watches must therefore poll (`M105`, `?`, a frame 04)
//! more often than the time-out.
//!
//! ```
//! use forja_app::session::{Admission, Admit, LinkSession};
//!
//! let mut session = LinkSession::new(1_000).with_idle_timeout(5_000);
//! assert_eq!(session.on_connect(0), Admit::Control);
//! session.on_input(3_000);
//! assert!(!session.poll_idle(7_999));
//! assert!(session.poll_idle(8_000), "silent for 5 s");
//! assert!(!session.is_connected());
//! assert_eq!(session.on_connect(8_010), Admit::Control);
//! ```
//!
//! # Several links, one machine
//!
//! A board with several links (the simulator's TCP port and its pseudo-terminal) keeps one
//! controlling host across all of them: while another link's host is in control, the session
//! is [locked](LinkSession::set_locked) and refuses every client, as it refuses a second one.
//!
//! Times are milliseconds of a wrapping `u32` clock; deadlines compare correctly while they are
//! less than 2³¹ ms (24 days) apart.
//!
//! # Execution context
//!
//! Thread (the network task, or the board's host task). Never blocks, never fails.

use forja_hal_abstraction::link::{LinkState, LinkStatus};

/// The contract the drivers' connection-oriented links ask, and their answer: implemented
/// here by [`LinkSession`].
pub use forja_drivers::port_link::{Admission, Admit};

/// What the controller is asked to send its controlling client (see
/// [`Firmware::session`](crate::firmware::Firmware::session)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SessionAction {
    /// Send message 54 (connected) to the client that just became the controller (it was
    /// admitted: [`Admit::Control`]).
    SendConnected,
    /// Send message 55 (keep-alive) carrying this counter, which starts at 0 for each session
    /// and increments (wrapping) with each keep-alive ([`LinkSession::poll`]).
    SendKeepAlive(u32),
}

/// The session of one link: who is in control and when the next keep-alive is due.
#[derive(Debug, Clone)]
pub struct LinkSession {
    keep_alive_interval_ms: u32,
    connected: bool,
    next_keep_alive_ms: u32,
    counter: u32,
    /// Silence after which the controlling client loses control, ms (`None`: never).
    idle_timeout_ms: Option<u32>,
    /// When the controlling client was last heard from.
    heard_ms: u32,
    /// Another link of the board has the machine.
    locked: bool,
}

/// `true` when `a` is at or after `b` on a wrapping millisecond clock.
const fn at_or_after(a: u32, b: u32) -> bool {
    (a.wrapping_sub(b) as i32) >= 0
}

impl LinkSession {
    /// No client, keep-alives every `keep_alive_interval_ms` once one connects (at least
    /// 1 ms).
    pub const fn new(keep_alive_interval_ms: u32) -> Self {
        Self {
            keep_alive_interval_ms: if keep_alive_interval_ms == 0 {
                1
            } else {
                keep_alive_interval_ms
            },
            connected: false,
            next_keep_alive_ms: 0,
            counter: 0,
            idle_timeout_ms: None,
            heard_ms: 0,
            locked: false,
        }
    }

    /// The same session, where a controlling client that is not heard from for `timeout_ms`
    /// (at least 1 ms, less than 2³¹ ms) loses control: see [`LinkSession::poll_idle`].
    pub const fn with_idle_timeout(mut self, timeout_ms: u32) -> Self {
        self.idle_timeout_ms = Some(if timeout_ms == 0 { 1 } else { timeout_ms });
        self
    }

    /// The idle time-out, if any.
    pub const fn idle_timeout_ms(&self) -> Option<u32> {
        self.idle_timeout_ms
    }

    /// Another link of the board has its controlling host (`true`) or no longer has
    /// (`false`): while locked, every client that connects is refused ([`Admit::Refuse`]). The
    /// controlling client
    /// of this session, if any, is untouched.
    pub fn set_locked(&mut self, locked: bool) {
        self.locked = locked;
    }

    /// Whether another link of the board has the machine.
    pub fn is_locked(&self) -> bool {
        self.locked
    }

    /// The controlling client was heard from at `now_ms` (it sent a byte), or is waiting for
    /// an answer the controller owes it: its silence starts again from `now_ms`. Ignored
    /// without a controlling client.
    pub fn on_input(&mut self, now_ms: u32) {
        if self.connected {
            self.heard_ms = now_ms;
        }
    }

    /// Whether the controlling client has been silent for the idle time-out at `now_ms`. If
    /// so, the session ends (as [`LinkSession::on_disconnect`]) and the caller closes the
    /// client's connection; the next client to connect is admitted. Always `false` without a
    /// time-out or a controlling client.
    pub fn poll_idle(&mut self, now_ms: u32) -> bool {
        match self.idle_timeout_ms {
            Some(timeout) if self.connected => {
                let due = self.heard_ms.wrapping_add(timeout);
                if at_or_after(now_ms, due) {
                    self.connected = false;
                    true
                } else {
                    false
                }
            }
            _ => false,
        }
    }

    /// Whether a client is in control.
    pub fn is_connected(&self) -> bool {
        self.connected
    }

    /// The action due at `now_ms`, if any: a keep-alive when its time has come. Call again
    /// until it returns `None`, and at the latest at [`LinkSession::poll_at`].
    ///
    /// A late call sends one keep-alive, not one per missed interval, and the next one is due
    /// a full interval later.
    pub fn poll(&mut self, now_ms: u32) -> Option<SessionAction> {
        if !self.connected || !at_or_after(now_ms, self.next_keep_alive_ms) {
            return None;
        }
        let counter = self.counter;
        self.counter = counter.wrapping_add(1);
        let next = self
            .next_keep_alive_ms
            .wrapping_add(self.keep_alive_interval_ms);
        self.next_keep_alive_ms = if at_or_after(now_ms, next) {
            now_ms.wrapping_add(self.keep_alive_interval_ms)
        } else {
            next
        };
        Some(SessionAction::SendKeepAlive(counter))
    }

    /// When [`LinkSession::poll`] has something to do next; `None` while nobody is connected.
    /// (The idle time-out, if any, is due at [`LinkSession::idle_at`].)
    pub fn poll_at(&self) -> Option<u32> {
        self.connected.then_some(self.next_keep_alive_ms)
    }

    /// When [`LinkSession::poll_idle`] ends the session unless the client is heard from
    /// before; `None` without a time-out or a controlling client.
    pub fn idle_at(&self) -> Option<u32> {
        let timeout = self.idle_timeout_ms?;
        self.connected.then(|| self.heard_ms.wrapping_add(timeout))
    }
}

impl LinkStatus for LinkSession {
    /// `Connected` while a client is in control.
    fn state(&self) -> LinkState {
        if self.connected {
            LinkState::Connected
        } else {
            LinkState::Disconnected
        }
    }
}

impl Admission for LinkSession {
    /// A client connected at `now_ms`. The first one becomes the controller
    /// ([`Admit::Control`]; its first keep-alive is due one interval later, its silence
    /// counts from now); any other, while one is in control or the session is
    /// [locked](LinkSession::set_locked), is refused ([`Admit::Refuse`]) and does not change
    /// the session.
    fn on_connect(&mut self, now_ms: u32) -> Admit {
        if self.connected || self.locked {
            return Admit::Refuse;
        }
        self.connected = true;
        self.counter = 0;
        self.next_keep_alive_ms = now_ms.wrapping_add(self.keep_alive_interval_ms);
        self.heard_ms = now_ms;
        Admit::Control
    }

    /// The controlling client went away (closed, reset, timed out, or was hung up on). Call it
    /// for the controller only: a refused client never joined the session. Idempotent.
    fn on_disconnect(&mut self) {
        self.connected = false;
    }
}

#[cfg(test)]
mod tests {
    use std::vec::Vec;

    use super::*;

    #[test]
    fn one_controller_at_a_time() {
        let mut s = LinkSession::new(500);
        assert_eq!(s.state(), LinkState::Disconnected);
        assert_eq!(s.poll_at(), None);
        assert_eq!(s.on_connect(100), Admit::Control);
        assert_eq!(s.state(), LinkState::Connected);
        assert_eq!(s.on_connect(200), Admit::Refuse);
        assert_eq!(s.on_connect(300), Admit::Refuse);
        assert!(s.is_connected(), "refusals leave the controller in place");
        assert_eq!(s.poll_at(), Some(600));
        s.on_disconnect();
        assert_eq!(s.state(), LinkState::Disconnected);
        s.on_disconnect();
        assert_eq!(s.poll(10_000), None);
        assert_eq!(s.on_connect(1_000), Admit::Control);
    }

    #[test]
    fn keep_alives_are_periodic_and_counted() {
        let mut s = LinkSession::new(1_000);
        s.on_connect(0);
        let mut sent = Vec::new();
        for now in (0..=5_000).step_by(10) {
            while let Some(a) = s.poll(now) {
                sent.push((now, a));
            }
        }
        let expect: Vec<_> = (0..5)
            .map(|i| ((i + 1) * 1_000, SessionAction::SendKeepAlive(i)))
            .collect();
        assert_eq!(sent, expect);
    }

    #[test]
    fn a_new_session_restarts_the_counter() {
        let mut s = LinkSession::new(100);
        s.on_connect(0);
        assert_eq!(s.poll(100), Some(SessionAction::SendKeepAlive(0)));
        assert_eq!(s.poll(200), Some(SessionAction::SendKeepAlive(1)));
        s.on_disconnect();
        s.on_connect(250);
        assert_eq!(s.poll(300), None);
        assert_eq!(s.poll(350), Some(SessionAction::SendKeepAlive(0)));
    }

    #[test]
    fn a_late_poll_sends_one_keep_alive_not_a_burst() {
        let mut s = LinkSession::new(100);
        s.on_connect(0);
        assert_eq!(s.poll(1_050), Some(SessionAction::SendKeepAlive(0)));
        assert_eq!(s.poll(1_050), None);
        assert_eq!(s.poll_at(), Some(1_150));
    }

    #[test]
    fn the_clock_may_wrap() {
        let mut s = LinkSession::new(1_000);
        s.on_connect(u32::MAX - 500);
        assert_eq!(s.poll(u32::MAX), None);
        assert_eq!(s.poll_at(), Some(499));
        assert_eq!(s.poll(499), Some(SessionAction::SendKeepAlive(0)));
    }

    #[test]
    fn a_silent_controller_times_out_and_input_keeps_it() {
        let mut s = LinkSession::new(1_000).with_idle_timeout(3_000);
        assert_eq!(s.idle_timeout_ms(), Some(3_000));
        assert!(!s.poll_idle(10_000), "nobody to time out");
        assert_eq!(s.on_connect(100), Admit::Control);
        assert_eq!(s.idle_at(), Some(3_100));
        s.on_input(2_000);
        assert!(!s.poll_idle(4_999));
        assert!(s.is_connected());
        assert!(s.poll_idle(5_000));
        assert!(!s.is_connected(), "the session ended");
        assert_eq!(s.state(), LinkState::Disconnected);
        assert!(!s.poll_idle(9_000), "once");
        assert_eq!(s.poll(9_000), None, "no keep-alive after it");
        s.on_disconnect();
        assert_eq!(s.on_connect(9_000), Admit::Control);
        assert!(
            !s.poll_idle(11_999),
            "the new client's silence starts at its connection"
        );
        assert!(s.poll_idle(12_000));
    }

    #[test]
    fn without_a_time_out_silence_is_allowed() {
        let mut s = LinkSession::new(1_000);
        s.on_connect(0);
        assert!(!s.poll_idle(u32::MAX / 2));
        assert_eq!(s.idle_at(), None);
        assert!(s.is_connected());
    }

    #[test]
    fn a_locked_session_refuses_every_client() {
        let mut s = LinkSession::new(1_000);
        s.set_locked(true);
        assert!(s.is_locked());
        assert_eq!(s.on_connect(0), Admit::Refuse);
        assert!(!s.is_connected());
        s.set_locked(false);
        assert_eq!(s.on_connect(1), Admit::Control);
        s.set_locked(true);
        assert!(s.is_connected(), "locking leaves the controller in place");
    }

    #[test]
    fn zero_interval_is_one_millisecond() {
        let mut s = LinkSession::new(0);
        s.on_connect(5);
        assert_eq!(s.poll(5), None);
        assert_eq!(s.poll(6), Some(SessionAction::SendKeepAlive(0)));
    }
}
