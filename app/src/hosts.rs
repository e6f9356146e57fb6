//! One controlling host across a board's ports.
//!
//! A board may serve hosts on more than one link (a UART and a WiFi socket; the simulator's TCP
//! port and its pseudo-terminal), and it has one controller, which serves one host at a time
//! across all of them. The board keeps a [`Port`] for each link and calls [`Arbiter::poll`] for
//! each turn of its thread side, instead of polling the controller on a link itself. Each turn:
//!
//! 1. Every link is serviced ([`PortLink::poll`]), and its [`LinkSession`] decides on the
//!    clients that connected to a connection-oriented link ([`PortLink::admit`]). While
//!    another port's host is in control the session is
//!    [locked](LinkSession::set_locked): the client is sent the link's busy message and closed.
//! 2. The controlling host's session goes on, or ends:
//!    - its host left (closed, hung up, dropped for not reading): what it sent before leaving
//!      still runs, in its session (its replies are discarded), until it is read and no line
//!      of it is held — unless another host wants control first: then the rest is dropped;
//!    - it was silent for the session's idle time-out (silence counts only while the
//!      controller owes it nothing: no held line, homing cycle or heater wait, and no
//!      reports it asked for every period, `M155 S` or `M27 S`): a
//!      connection-oriented link closes it ([`PortLink::hang_up`]) and its session ends; a link
//!      that cannot be closed (a terminal) only gives up control, and takes it back with its
//!      next byte, in the same session, if no other host took control in between.
//! 3. With no host in control, the first port (in slice order) whose host has just arrived,
//!    or that has input, takes control. A new session starts with no byte of the previous
//!    one: no unread input (the controller's and the link's), no held or queued line, no
//!    unsent reply; line 1 is expected. On a port with frames the host is greeted with frame
//!    54 and kept alive with frame 55 every interval of its session; the first host of a port
//!    without frames receives `start`.
//! 4. While a host is in control, input that arrives on any other port is never run: it is
//!    discarded, and the host, if one is there, is sent the busy message
//!    ([`Arbiter::set_busy_message`], by default the controller's [`busy_refusal`]) once per
//!    turn. An `M112` line among it is carried out
//!    all the same: an emergency stop acts from any host, as realtime commands do from every
//!    connection of FluidNC and grblHAL. The fault goes to the controlling host. With no
//!    host in control no input is discarded: input that lands after the turn looked for it
//!    (a terminal's host back from its silence as it gave up control) takes control at the
//!    next turn.
//! 5. The controller reads at most the read budget ([`Arbiter::new`]) of the controlling
//!    port: a flood never keeps the thread side from the kernel, and the link holds the rest
//!    back.
//!
//! # Contract
//!
//! - Context: thread, like [`Controller::poll`], which [`Arbiter::poll`] calls once per turn.
//! - Nothing of a turn waits for a host, provided the links' writes never block (a link drops
//!   or discards what a host does not read): motion and the stop flag go on whatever hosts do.
//! - No allocation: the ports are the board's slice, the busy message any `AsRef<[u8]>`.
//! - A link's failure is kept, the first one per port ([`Port::failure`]), for the board to
//!   report; the port is still polled.

use embedded_io::{ErrorType, Read, ReadReady, Write};
use forja_hal_abstraction::link::LinkState;
use forja_hal_abstraction::program::ProgramStore;
use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::time::Instant;
use forja_protocol::stream::{Decoder, Event};

use crate::controller::{
    BUSY_REFUSAL_LEN, Controller, Peripherals, PollOutcome, Realtime, busy_refusal, realtime,
};
use crate::session::{Admission, LinkSession, SessionAction};

/// What a link must do to be one of the ports: the drivers' link contract
/// ([`forja_drivers::port_link`]).
pub use forja_drivers::port_link::PortLink;

/// What happened to the hosts of a port, counted from its start.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PortStats {
    /// Sessions begun on the port.
    pub sessions: u64,
    /// Times its controlling host was silent for the idle time-out.
    pub idle_timeouts: u64,
    /// Bytes received while another port's host was in control: discarded, never run.
    pub refused_bytes: u64,
    /// Busy messages sent.
    pub busy_replies: u64,
    /// Bytes a host that left had sent and that were dropped unread, because another host
    /// took control first (or it was silent for the time-out).
    pub dropped_bytes: u64,
    /// `M112` lines found in the refused bytes and carried out: an emergency stop acts from
    /// any host.
    pub emergency_stops: u64,
}

/// One of a board's ports: its link, the link's session (admission of clients, keep-alives,
/// the idle time-out), its counters and its first failure.
pub struct Port<L: ErrorType> {
    link: L,
    session: LinkSession,
    /// Whether the host is greeted with frame 54 and kept alive with frame 55.
    frames: bool,
    /// The link's connection count at the last look.
    seen: u64,
    /// A host arrived (the count changed) and has not been served yet.
    fresh: bool,
    failure: Option<L::Error>,
    stats: PortStats,
    /// The input received while another host is in control, cut into records as the
    /// controller cuts its own link's, each line looked at for `M112`.
    refused: Decoder,
}

impl<L: PortLink> Port<L> {
    /// Serve `link` under `session` (its keep-alive interval and idle time-out); `frames`:
    /// greet each host with frame 54 and keep it alive with frame 55 (a link with sessions:
    /// TCP, WiFi); without, the port's first host receives `start`.
    pub fn new(link: L, session: LinkSession, frames: bool) -> Self {
        Self {
            link,
            session,
            frames,
            seen: 0,
            fresh: false,
            failure: None,
            stats: PortStats::default(),
            refused: Decoder::new(),
        }
    }

    /// The link.
    pub fn link(&self) -> &L {
        &self.link
    }

    /// The link, mutably.
    pub fn link_mut(&mut self) -> &mut L {
        &mut self.link
    }

    /// What happened to the port's hosts.
    pub fn stats(&self) -> PortStats {
        self.stats
    }

    /// The link's first failure, if it failed.
    pub fn failure(&self) -> Option<&L::Error> {
        self.failure.as_ref()
    }

    /// Serve the port's next hosts under `session` (another keep-alive interval or idle
    /// time-out).
    pub fn set_session(&mut self, session: LinkSession) {
        self.session = session;
    }

    fn present(&self) -> bool {
        self.link.state() == LinkState::Connected
    }

    /// Whether this port's host wants control: one just arrived, or it has input.
    fn wants_control(&mut self) -> bool {
        (self.fresh && self.present()) || self.link.read_ready().unwrap_or(false)
    }

    fn fail(&mut self, error: L::Error) {
        self.failure.get_or_insert(error);
    }

    /// Take and drop the input of a host that is not in control, reading at most `limit`
    /// bytes and discarding the rest, and find the `M112` lines among what was read (the
    /// records of the stream decoder, and among its lines [`realtime`], whatever the
    /// checksum). Returns the bytes dropped and whether an `M112` came.
    fn refuse_input(&mut self, limit: usize) -> Result<(usize, bool), L::Error> {
        let mut buf = [0u8; 256];
        let mut dropped = 0;
        let mut stop = false;
        while dropped < limit && self.link.read_ready()? {
            let n = self.link.read(&mut buf)?;
            if n == 0 {
                break;
            }
            dropped += n;
            self.refused.feed_all(buf.get(..n).unwrap_or(&[]), |event| {
                if let Event::Line(line) = event {
                    stop |= realtime(line) == Some(Realtime::EmergencyStop);
                }
            });
        }
        dropped += self.link.discard_input()?;
        Ok((dropped, stop))
    }
}

/// Who has the board's controller: one controlling host across the ports. See the
/// [module documentation](self).
#[derive(Debug)]
pub struct Arbiter<M> {
    /// The port whose host is in control.
    active: Option<usize>,
    /// The port whose session the controller's link state belongs to (it stays when a
    /// terminal's host gives up control for silence, and goes when the session ends).
    owner: Option<usize>,
    /// What a refused host is sent; `None`: the controller's [`busy_refusal`].
    busy_message: Option<M>,
    /// `start` was sent.
    booted: bool,
    read_budget: usize,
    refused_budget: usize,
}

impl<M: AsRef<[u8]>> Arbiter<M> {
    /// No host in control yet. Each turn the controller reads at most `read_budget` bytes of
    /// the controlling port, and at most `refused_budget` bytes of every other port are read
    /// for `M112` (the rest is discarded unread).
    pub const fn new(read_budget: usize, refused_budget: usize) -> Self {
        Self {
            active: None,
            owner: None,
            busy_message: None,
            booted: false,
            read_budget,
            refused_budget,
        }
    }

    /// What a host whose input is refused (another host is in control) is sent, instead of
    /// the controller's [`busy_refusal`].
    pub fn set_busy_message(&mut self, message: M) {
        self.busy_message = Some(message);
    }

    /// The index of the port whose host is in control, if any.
    pub fn active(&self) -> Option<usize> {
        self.active
    }

    /// One turn of the thread side at `now` (`now_ms` on the sessions' clock): the links
    /// serviced, control decided, the other ports' input refused, and the controller polled on
    /// the controlling port (on a silent link when no host is in control). Returns what the
    /// controller's poll returned: arm the step alarm at its `arm_alarm`.
    ///
    /// Give it the same ports in the same order at every turn. Context: thread. Never blocks.
    pub fn poll<L, const N: usize, const B: usize, const Q: usize, P, X, S>(
        &mut self,
        ports: &mut [Port<L>],
        controller: &mut Controller<'_, N, B, Q, P, X, S>,
        now: Instant,
        now_ms: u32,
    ) -> PollOutcome
    where
        L: PortLink,
        P: ProgramStore,
        X: Peripherals<N>,
        S: RecordStorage,
    {
        // The controlling host, if it is still there: every other port refuses new clients.
        let holder = self
            .active
            .filter(|&a| ports.get(a).is_some_and(Port::present));
        for (i, p) in ports.iter_mut().enumerate() {
            p.session.set_locked(holder.is_some_and(|a| a != i));
            if let Err(e) = p
                .link
                .poll()
                .and_then(|()| p.link.admit(&mut p.session, now_ms))
            {
                p.fail(e);
            }
            let seen = p.link.connections();
            if core::mem::replace(&mut p.seen, seen) != seen {
                p.fresh = true;
            }
        }
        Turn {
            arbiter: self,
            controller,
            now_ms,
        }
        .serve(ports);
        let Some(p) = self.active.and_then(|i| ports.get_mut(i)) else {
            return controller.poll(now, &mut Silent);
        };
        if p.frames {
            while let Some(SessionAction::SendKeepAlive(n)) = p.session.poll(now_ms) {
                controller.keep_alive(n, &mut p.link);
            }
        }
        let mut link = Budgeted {
            link: &mut p.link,
            left: self.read_budget,
            read: 0,
        };
        let outcome = controller.poll(now, &mut link);
        if link.read > 0 || controller.is_holding() || controller.owes_reports() {
            p.session.on_input(now_ms);
        }
        outcome
    }

    /// Send the busy message to a refused host.
    fn send_busy<W: Write>(&self, link: &mut W) {
        let _ = match &self.busy_message {
            Some(message) => link.write_all(message.as_ref()),
            None => {
                let mut out = [0u8; BUSY_REFUSAL_LEN];
                let len = busy_refusal(&mut out);
                link.write_all(out.get(..len).unwrap_or_default())
            }
        };
    }
}

/// The arbiter and the controller for the part of a turn that decides who is in control.
struct Turn<'t, 'q, M, const N: usize, const B: usize, const Q: usize, P, X, S> {
    arbiter: &'t mut Arbiter<M>,
    controller: &'t mut Controller<'q, N, B, Q, P, X, S>,
    now_ms: u32,
}

impl<M, const N: usize, const B: usize, const Q: usize, P, X, S> Turn<'_, '_, M, N, B, Q, P, X, S>
where
    M: AsRef<[u8]>,
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// Decide who is in control this turn, greet a new host, refuse the input of the others.
    fn serve<L: PortLink>(&mut self, ports: &mut [Port<L>]) {
        if let Some(i) = self.arbiter.active {
            let others_want = ports
                .iter_mut()
                .enumerate()
                .any(|(j, q)| j != i && q.wants_control());
            if let Some(p) = ports.get_mut(i) {
                if !p.present() {
                    // Its host left: what it sent runs on, unless someone else wants control.
                    let draining =
                        p.link.read_ready().unwrap_or(false) || self.controller.is_holding();
                    if others_want || !draining {
                        self.end_session(p);
                    }
                } else if p.fresh {
                    // A new host on the same port (a client that reconnected at once).
                    self.begin_session(p, i);
                } else if p.session.poll_idle(self.now_ms) {
                    p.stats.idle_timeouts += 1;
                    p.link.hang_up();
                    if p.present() {
                        // A terminal cannot be hung up: it only gives up control.
                        self.arbiter.active = None;
                    } else {
                        self.end_session(p);
                    }
                }
            }
        }
        if self.arbiter.active.is_none() {
            for (i, p) in ports.iter_mut().enumerate() {
                if !p.wants_control() {
                    continue;
                }
                if p.fresh || self.arbiter.owner != Some(i) {
                    self.begin_session(p, i);
                } else {
                    // The same host, back after giving up control: its session goes on.
                    self.arbiter.active = Some(i);
                    p.session.set_locked(false);
                    p.session.on_connect(self.now_ms);
                }
                break;
            }
        }
        // With nobody in control nobody's input is refused: input that came after the look
        // above (a host back from its silence as control was given up) takes control at the
        // next turn.
        let Some(active) = self.arbiter.active else {
            return;
        };
        let mut stop = false;
        for (i, p) in ports.iter_mut().enumerate() {
            if active == i {
                // The port's input goes to the controller now.
                p.refused.reset();
                continue;
            }
            match p.refuse_input(self.arbiter.refused_budget) {
                Ok((0, _)) => {}
                Ok((n, m112)) => {
                    stop |= m112;
                    p.stats.refused_bytes += n as u64;
                    if m112 {
                        p.stats.emergency_stops += 1;
                    }
                    if p.present() {
                        p.stats.busy_replies += 1;
                        self.arbiter.send_busy(&mut p.link);
                    }
                }
                Err(e) => p.fail(e),
            }
        }
        if stop {
            // The fault goes to the controlling host, whose waiting lines are answered.
            match ports.get_mut(active) {
                Some(p) => self.controller.emergency_stop(&mut p.link),
                None => self.controller.emergency_stop(&mut Silent),
            }
        }
    }

    /// Start a new session with the host of port `i`: nothing of the previous session is
    /// kept; frame 54 to a host on a port with frames, `start` to the first host of a port
    /// without.
    fn begin_session<L: PortLink>(&mut self, p: &mut Port<L>, i: usize) {
        p.fresh = false;
        p.session.set_locked(false);
        if !p.session.is_connected() {
            // A link without connections: the session only times the host's silence.
            p.session.on_connect(self.now_ms);
        }
        self.arbiter.active = Some(i);
        self.arbiter.owner = Some(i);
        p.stats.sessions += 1;
        if p.frames {
            self.controller.on_connect(&mut p.link);
        } else {
            self.controller.reset_link();
            if !self.arbiter.booted {
                self.arbiter.booted = true;
                self.controller.boot(&mut p.link);
            }
        }
    }

    /// End the session of the controlling host of `p`: what it sent and was not read is
    /// dropped, and so are its held line and partial input.
    fn end_session<L: PortLink>(&mut self, p: &mut Port<L>) {
        match p.link.discard_input() {
            Ok(n) => p.stats.dropped_bytes += n as u64,
            Err(e) => p.fail(e),
        }
        p.session.on_disconnect();
        self.controller.reset_link();
        self.arbiter.active = None;
        self.arbiter.owner = None;
    }
}

/// A link that lets the controller read at most a fixed number of bytes.
struct Budgeted<'a, L: ?Sized> {
    link: &'a mut L,
    left: usize,
    read: usize,
}

impl<L: ErrorType + ?Sized> ErrorType for Budgeted<'_, L> {
    type Error = L::Error;
}

impl<L: ReadReady + ?Sized> ReadReady for Budgeted<'_, L> {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        if self.left == 0 {
            return Ok(false);
        }
        self.link.read_ready()
    }
}

impl<L: Read + ?Sized> Read for Budgeted<'_, L> {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = buf.len().min(self.left);
        let Some(buf) = buf.get_mut(..n) else {
            return Ok(0);
        };
        if buf.is_empty() {
            return Ok(0);
        }
        let got = self.link.read(buf)?;
        self.left = self.left.saturating_sub(got);
        self.read += got;
        Ok(got)
    }
}

impl<L: Write + ?Sized> Write for Budgeted<'_, L> {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.link.write(buf)
    }
    fn flush(&mut self) -> Result<(), Self::Error> {
        self.link.flush()
    }
}

/// A link that has nothing to say and hears nothing: the controller's link while no host is
/// served.
struct Silent;

impl ErrorType for Silent {
    type Error = core::convert::Infallible;
}

impl Read for Silent {
    fn read(&mut self, _: &mut [u8]) -> Result<usize, Self::Error> {
        Ok(0)
    }
}

impl ReadReady for Silent {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        Ok(false)
    }
}

impl Write for Silent {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        Ok(buf.len())
    }
    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use std::collections::VecDeque;
    use std::vec::Vec;

    use forja_hal_abstraction::link::LinkStatus;
    use forja_hal_abstraction::program::RamStore;
    use forja_hal_abstraction::stepper::StepTiming;
    use forja_motion::{AxisConfig, MachineConfig, StepQueue, split};

    use super::*;
    use crate::controller::{ControllerConfig, NoPeripherals};

    /// A host's end of a link, in memory.
    #[derive(Default)]
    struct Mem {
        rx: VecDeque<u8>,
        tx: Vec<u8>,
        gone: bool,
        connections: u64,
        /// Bytes that arrive just after the next look at whether input waits (as a UART's
        /// interrupt fills its buffer between two reads of the thread side).
        arriving: Vec<u8>,
    }

    impl Mem {
        fn sent(&mut self, bytes: &[u8]) {
            self.rx.extend(bytes);
        }
    }

    impl ErrorType for Mem {
        type Error = core::convert::Infallible;
    }

    impl Read for Mem {
        fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
            let n = buf.len().min(self.rx.len());
            for (d, s) in buf.iter_mut().zip(self.rx.drain(..n)) {
                *d = s;
            }
            Ok(n)
        }
    }

    impl ReadReady for Mem {
        fn read_ready(&mut self) -> Result<bool, Self::Error> {
            let ready = !self.rx.is_empty();
            self.rx.extend(self.arriving.drain(..));
            Ok(ready)
        }
    }

    impl Write for Mem {
        fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
            self.tx.extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> Result<(), Self::Error> {
            Ok(())
        }
    }

    impl LinkStatus for Mem {
        fn state(&self) -> LinkState {
            if self.gone {
                LinkState::Disconnected
            } else {
                LinkState::Connected
            }
        }
    }

    impl PortLink for Mem {
        fn poll(&mut self) -> Result<(), Self::Error> {
            Ok(())
        }
        fn connections(&self) -> u64 {
            self.connections
        }
        fn discard_input(&mut self) -> Result<usize, Self::Error> {
            let n = self.rx.len();
            self.rx.clear();
            Ok(n)
        }
    }

    type Ctl = Controller<'static, 1, 8, 64, RamStore<4>, NoPeripherals>;

    fn controller() -> Ctl {
        let queue = std::boxed::Box::leak(std::boxed::Box::new(StepQueue::new()));
        let machine = MachineConfig::new([AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 300.0)]);
        let timing = StepTiming::CONSERVATIVE;
        let (kernel, _) = split(queue, machine, 1_000_000, timing).unwrap();
        Controller::new(
            kernel,
            RamStore::new(),
            NoPeripherals,
            ControllerConfig::new("test", timing),
        )
    }

    fn ports() -> [Port<Mem>; 2] {
        [false, false].map(|frames| Port::new(Mem::default(), LinkSession::new(1_000), frames))
    }

    fn text(bytes: &[u8]) -> &str {
        core::str::from_utf8(bytes).unwrap()
    }

    #[test]
    fn the_first_host_with_input_takes_control_and_the_others_are_refused() {
        let mut c = controller();
        let mut ports = ports();
        let mut arbiter = Arbiter::<&[u8]>::new(4096, 4096);
        ports[0].link_mut().sent(b"M400\n");
        ports[1].link_mut().sent(b"M400\nG1 X10 F600\n");
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(0), 0);
        assert_eq!(arbiter.active(), Some(0));
        assert!(text(&ports[0].link().tx).starts_with("start\n"));
        assert!(text(&ports[0].link().tx).contains("ok"));
        // The refused host's lines never run; it is told so, in both protocols.
        let mut refusal = [0u8; BUSY_REFUSAL_LEN];
        let len = busy_refusal(&mut refusal);
        assert_eq!(ports[1].link().tx, refusal[..len]);
        let stats = ports[1].stats();
        assert_eq!((stats.refused_bytes, stats.busy_replies), (17, 1));
        assert!(c.kernel().is_idle(), "the refused G1 did not run");

        // The board's own busy message, once per turn with input.
        arbiter.set_busy_message(b"busy\n");
        ports[1].link_mut().tx.clear();
        ports[1].link_mut().sent(b"M400\n");
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(1_000), 1);
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(2_000), 2);
        assert_eq!(text(&ports[1].link().tx), "busy\n");
        assert_eq!(ports[1].stats().sessions, 0);
    }

    /// A controller, two terminal ports whose sessions time out after 5 s of silence, and an
    /// arbiter that gave the first port control with `first_line` at 0 ms.
    fn in_control_with_idle_timeout(
        first_line: &[u8],
    ) -> (Ctl, [Port<Mem>; 2], Arbiter<&'static [u8]>) {
        let mut c = controller();
        let mut ports = [false, false].map(|frames| {
            Port::new(
                Mem::default(),
                LinkSession::new(1_000).with_idle_timeout(5_000),
                frames,
            )
        });
        let mut arbiter = Arbiter::<&[u8]>::new(4096, 4096);
        ports[0].link_mut().sent(first_line);
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(0), 0);
        assert_eq!(arbiter.active(), Some(0));
        (c, ports, arbiter)
    }

    /// One turn at each whole second of `seconds` (the step clock at 1 MHz).
    fn poll_each_second(
        arbiter: &mut Arbiter<&'static [u8]>,
        ports: &mut [Port<Mem>],
        c: &mut Ctl,
        seconds: core::ops::RangeInclusive<u32>,
    ) {
        for ms in seconds.map(|s| s * 1_000) {
            arbiter.poll(ports, c, Instant::from_ticks(ms * 1_000), ms);
        }
    }

    /// A host that asked for periodic reports owes the controller no byte: it keeps control
    /// and its reports through a silence longer than the idle time-out, as OctoPrint during
    /// a print from the card.
    #[test]
    fn a_host_that_asked_for_reports_keeps_control_through_its_silence() {
        let (mut c, mut ports, mut arbiter) = in_control_with_idle_timeout(b"M27 S1\n");
        poll_each_second(&mut arbiter, &mut ports, &mut c, 1..=20);
        assert_eq!(arbiter.active(), Some(0));
        assert_eq!(ports[0].stats().idle_timeouts, 0);
        let reports = text(&ports[0].link().tx).matches("Not SD printing").count();
        assert!(reports >= 19, "{}", text(&ports[0].link().tx));

        // Without reports asked for, the same silence ends its control.
        ports[0].link_mut().sent(b"M27 S0\n");
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(21_000_000), 21_000);
        poll_each_second(&mut arbiter, &mut ports, &mut c, 22..=30);
        assert_eq!(ports[0].stats().idle_timeouts, 1);
    }

    /// A terminal whose host fell silent gives up control; what the host sends next takes it
    /// back, even when it lands in the very turn control was given up, after the look for
    /// a host that wants control: with nobody in control, nobody's input is refused.
    #[test]
    fn a_terminal_back_from_its_silence_takes_control_back_with_its_first_line() {
        let (mut c, mut ports, mut arbiter) = in_control_with_idle_timeout(b"M105\n");
        poll_each_second(&mut arbiter, &mut ports, &mut c, 1..=4);
        assert_eq!(arbiter.active(), Some(0));
        // The silence ends control at 6 s, as the host's next line comes in.
        ports[0].link_mut().arriving.extend_from_slice(b"G92 X5\n");
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(6_000_000), 6_000);
        assert_eq!(ports[0].stats().idle_timeouts, 1);
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(6_001_000), 6_001);
        assert_eq!(arbiter.active(), Some(0));
        let stats = ports[0].stats();
        assert_eq!((stats.refused_bytes, stats.busy_replies), (0, 0));
        assert_eq!(c.kernel().position().work_mm[0], 5.0, "the G92 line ran");
    }

    #[test]
    fn an_emergency_stop_from_a_refused_host_is_carried_out() {
        let mut c = controller();
        let mut ports = ports();
        let mut arbiter = Arbiter::<&[u8]>::new(4096, 4096);
        ports[0].link_mut().sent(b"M400\n");
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(0), 0);
        ports[1].link_mut().sent(b"N7 M112*99\n");
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(1_000), 1);
        assert_eq!(ports[1].stats().emergency_stops, 1);
        assert_eq!(arbiter.active(), Some(0));
        // The fault goes to the controlling host.
        assert!(
            text(&ports[0].link().tx).contains("Error:E153"),
            "{}",
            text(&ports[0].link().tx)
        );
        assert!(!text(&ports[1].link().tx).contains("Error:E153"));
    }

    #[test]
    fn the_controller_reads_at_most_the_budget_and_a_host_that_left_is_replaced() {
        let mut c = controller();
        let mut ports = ports();
        let mut arbiter = Arbiter::<&[u8]>::new(16, 4096);
        let flood = b"M400\n".repeat(20);
        ports[0].link_mut().sent(&flood);
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(0), 0);
        assert!(ports[0].link().rx.len() >= flood.len() - 16);

        // Its host leaves with lines unread while another wants control: they are dropped.
        let unread = ports[0].link().rx.len() as u64;
        ports[0].link_mut().gone = true;
        ports[1].link_mut().sent(b"M400\n");
        arbiter.poll(&mut ports, &mut c, Instant::from_ticks(1_000), 1);
        assert_eq!(ports[0].stats().dropped_bytes, unread);
        assert_eq!(arbiter.active(), Some(1));
        assert_eq!(ports[1].stats().sessions, 1);
        // `start` went to the first host only.
        assert!(!text(&ports[1].link().tx).contains("start"));
    }
}
