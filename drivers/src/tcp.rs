//! A TCP host link over `embassy-net`: a server on one port with one controlling client at a
//! time, and the controller's end of it as an `embedded-io` link. Any board with an
//! `embassy-net` stack (WiFi, Ethernet) serves its host this way. Behind the `embassy-net`
//! feature.
//!
//! A [`TcpServer`] lives in a `static`, its [`TcpQueues`] in another. The board's listening
//! tasks run [`TcpServer::listen`] on its stacks; the controller's task
//! [takes](TcpServer::take) the [`TcpLink`] once and polls the controller over it:
//!
//! ```text
//!  client ──TCP── listen task(s) ──receive queue──► TcpLink ──► Controller::poll
//!                 (TcpServer::listen) ◄─transmit queue── TcpLink ◄── replies, 54, 55
//! ```
//!
//! # Session
//!
//! Who controls is the session rules' decision: the server's [`Admission`] (the application's
//! `forja_app::session::LinkSession`). The listening tasks report connections and
//! disconnections to it and carry out its answer; the controller's task greets a new
//! controlling client and keeps it alive itself, into the same outgoing stream as its replies,
//! so that a 54 or 55 never lands inside another line:
//!
//! | when | who | does |
//! |---|---|---|
//! | [`Admit::Control`] | listening task | serves the client as the controller; the controller's task finds [`TcpLink::take_greeting`] true and calls `Controller::on_connect` (frame 54, a fresh decoder) |
//! | a keep-alive is due (the rules', through [`TcpLink::admission`]) | controller's task | `Controller::keep_alive(n)` (frame 55), counted with [`TcpLink::count_keep_alive`] |
//! | [`Admit::Refuse`] | listening task | sends the new client the refusal it was given (the application's `busy_refusal`) and closes it |
//!
//! Give each stack at least two listening tasks: one can hold the controlling client while
//! another is free to accept, and refuse, a second one. The rules are shared by every task of
//! the server, so they hold across all the board's stacks.
//!
//! A client that goes away (closes, resets, or stops acknowledging for [`CLIENT_TIMEOUT`]
//! because its network dropped: the keep-alives make the loss visible) ends the session; the
//! next client to connect becomes the controller.
//!
//! # Bytes
//!
//! Bytes move between the sockets and the controller through two queues (embassy-sync pipes
//! of `RX` and `TX` bytes, [`TcpQueues`]). The controller runs in a task of the same executor as the
//! sockets, so nothing on its side may wait for them:
//!
//! - **Input.** Received bytes are read from the socket only when the receive queue has room,
//!   so a client that sends faster than the controller reads is held back by TCP flow control,
//!   never dropped. `read_ready` says `true` only while the transmit queue also has
//!   [`TX_HEADROOM`] bytes free (`TX` must be larger): a client that does not read its replies
//!   stops being read.
//! - **Output.** Writes never wait: what does not fit in the transmit queue is dropped and
//!   counted (`tx_dropped`), which the headroom makes a client's fault only. With no client
//!   connected, writes are discarded at once (like a UART with nothing attached), so the
//!   controller never waits for an absent host; at each new connection anything still queued
//!   from the previous one is dropped.
//! - **Waking.** [`TcpLink::wait`] returns when bytes arrive, a client connects or leaves, or
//!   at a deadline: the controller's task sleeps in it between polls.
//!
//! Nothing here depends on the motion side: a program stored on the board runs on while the
//! link is down.
//!
//! # Observing the link
//!
//! [`LinkCounters`] count connections, refusals, keep-alives, bytes and dropped replies. The
//! board keeps them in a `static` of its own, at a symbol a debugger can find.
//!
//! # Execution context
//!
//! Thread only: tasks of one executor. The queues and the session rules are shared through
//! critical sections of a few instructions; nothing here runs in an interrupt.

use core::cell::RefCell;
use core::convert::Infallible;
use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use embassy_futures::select::{Either, select};
use embassy_net::tcp::TcpSocket;
use embassy_net::{IpListenEndpoint, Stack};
use embassy_sync::blocking_mutex::Mutex;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::pipe::Pipe;
use embassy_sync::signal::Signal;
use embassy_time::{Duration, Instant, Timer, with_deadline, with_timeout};
use forja_hal_abstraction::link::{LinkState, LinkStatus};

use crate::port_link::{Admission, Admit};
use crate::web::Mirror;

/// Most bytes of a frame header a framing puts before a payload.
pub(crate) const MAX_HEADER: usize = forja_web::websocket::MAX_HEADER;

/// A client that acknowledges nothing for this long is gone.
pub const CLIENT_TIMEOUT: Duration = Duration::from_secs(10);

/// Free bytes the transmit queue must have for the controller to read more input: more than
/// the longest burst of replies one poll writes for 128 bytes of input (an `M115` answer, a
/// status frame, a keep-alive).
pub const TX_HEADROOM: usize = 512;

/// Bytes of each socket's receive and transmit buffers.
const SOCKET_BUF: usize = 1536;

/// Bytes moved between a socket and a queue at a time.
pub(crate) const CHUNK: usize = 512;

/// How long a refused client is given to receive the refusal.
pub(crate) const REFUSAL_TIMEOUT: Duration = Duration::from_millis(500);

/// The milliseconds of the session clock (embassy's time base, wrapping).
pub fn now_ms() -> u32 {
    Instant::now().as_millis() as u32
}

/// Counters of a TCP link, wrapping. Each is written by one context at a time (the serving
/// task, or the controller's task for `keep_alives` and `tx_dropped`).
#[repr(C)]
#[derive(Debug)]
pub struct LinkCounters {
    /// Clients that became the controller.
    pub connections: AtomicU32,
    /// Clients refused because another was in control.
    pub refused: AtomicU32,
    /// Keep-alives (55) sent.
    pub keep_alives: AtomicU32,
    /// Bytes received from controlling clients.
    pub rx_bytes: AtomicU32,
    /// Bytes sent to controlling clients, 54 and 55 included.
    pub tx_bytes: AtomicU32,
    /// Reply bytes dropped because the transmit queue was full (a client that does not read).
    pub tx_dropped: AtomicU32,
}

impl LinkCounters {
    /// All zero.
    pub const fn new() -> Self {
        Self {
            connections: AtomicU32::new(0),
            refused: AtomicU32::new(0),
            keep_alives: AtomicU32::new(0),
            rx_bytes: AtomicU32::new(0),
            tx_bytes: AtomicU32::new(0),
            tx_dropped: AtomicU32::new(0),
        }
    }
}

impl Default for LinkCounters {
    fn default() -> Self {
        Self::new()
    }
}

pub(crate) fn bump(counter: &AtomicU32, by: usize) {
    // One writer at a time, and targets without read-modify-write atomics (RISC-V `imc`): load
    // and store.
    counter.store(
        counter.load(Ordering::Relaxed).wrapping_add(by as u32),
        Ordering::Relaxed,
    );
}

/// The session rules, and whether their controlling client was not yet greeted (54).
struct Shared<A> {
    admission: A,
    greet: bool,
}

type Queue<const N: usize> = Pipe<CriticalSectionRawMutex, N>;

/// The byte queues of a TCP link: `RX` bytes from the client to the controller, `TX` bytes back.
/// Put them in a `static` of their own, apart from the [`TcpServer`]: all zero at start, they
/// take RAM but no room in the firmware image.
pub struct TcpQueues<const RX: usize, const TX: usize> {
    rx: Queue<RX>,
    tx: Queue<TX>,
}

impl<const RX: usize, const TX: usize> TcpQueues<RX, TX> {
    /// Empty queues.
    pub const fn new() -> Self {
        Self {
            rx: Pipe::new(),
            tx: Pipe::new(),
        }
    }
}

impl<const RX: usize, const TX: usize> Default for TcpQueues<RX, TX> {
    fn default() -> Self {
        Self::new()
    }
}

/// The server side of a TCP host link: its queues, the session rules `A` that admit its
/// clients, the counters. Put it in a `static`, run [`TcpServer::listen`] in each listening
/// task and give the controller its [`TcpLink`] ([`TcpServer::take`]).
pub struct TcpServer<A, const RX: usize, const TX: usize> {
    rx: &'static Queue<RX>,
    tx: &'static Queue<TX>,
    /// Raised by the link's writes, so that the serving task sends at once.
    tx_kick: Signal<CriticalSectionRawMutex, ()>,
    /// Raised when bytes reach the receive queue or a client comes or goes, to wake the
    /// controller's task ([`TcpLink::wait`]).
    wake: Signal<CriticalSectionRawMutex, ()>,
    shared: Mutex<CriticalSectionRawMutex, RefCell<Shared<A>>>,
    taken: AtomicBool,
    counters: &'static LinkCounters,
    /// Where what the controlling client is sent is copied for the web page's watchers.
    pub(crate) mirror: Option<&'static Mirror>,
}

impl<A: Admission, const RX: usize, const TX: usize> TcpServer<A, RX, TX> {
    /// A server whose clients `admission` admits or refuses (give it with no client in
    /// control); bytes through `queues`, counted in `counters`.
    pub const fn new(
        queues: &'static TcpQueues<RX, TX>,
        counters: &'static LinkCounters,
        admission: A,
    ) -> Self {
        Self {
            rx: &queues.rx,
            tx: &queues.tx,
            tx_kick: Signal::new(),
            wake: Signal::new(),
            shared: Mutex::new(RefCell::new(Shared {
                admission,
                greet: false,
            })),
            taken: AtomicBool::new(false),
            counters,
            mirror: None,
        }
    }

    /// The same server, copying every byte its controlling client is sent (on raw TCP or the
    /// web page's WebSocket) into `mirror`, for the page's watchers
    /// ([`crate::web`]).
    pub const fn with_mirror(mut self, mirror: &'static Mirror) -> Self {
        self.mirror = Some(mirror);
        self
    }

    /// Run `f` on the session rules and return what it returns: at init, to set them up (the
    /// keep-alive interval of the stored settings); later, to read them.
    ///
    /// Context: thread. `f` runs in a critical section: keep it to a few instructions, and do
    /// not call back into the server from it.
    pub fn admission<R>(&self, f: impl FnOnce(&mut A) -> R) -> R {
        self.shared.lock(|s| f(&mut s.borrow_mut().admission))
    }

    /// The controller's end; `None` after the first call.
    ///
    /// Context: init. Takes a critical section for a few instructions.
    pub fn take(&self) -> Option<TcpLink<'_, A, RX, TX>> {
        let first = critical_section::with(|_| {
            let first = !self.taken.load(Ordering::Relaxed);
            self.taken.store(true, Ordering::Relaxed);
            first
        });
        first.then_some(TcpLink { server: self })
    }

    /// The counters this server keeps.
    pub fn counters(&self) -> &LinkCounters {
        self.counters
    }

    /// Whether a client is in control, as the session rules say.
    pub(crate) fn is_connected(&self) -> bool {
        self.admission(|a| a.state() == LinkState::Connected)
    }

    /// A client connected at `now_ms`: the session rules decide whether it is the controller.
    /// A new controller finds the transmit queue empty (what was queued before it belongs to
    /// nobody) and is greeted by the controller's task.
    pub(crate) fn connect(&self, now_ms: u32) -> Admit {
        let admit = self.shared.lock(|s| {
            let mut s = s.borrow_mut();
            let admit = s.admission.on_connect(now_ms);
            if admit == Admit::Control {
                self.tx.clear();
                s.greet = true;
            }
            admit
        });
        if admit == Admit::Control {
            bump(&self.counters.connections, 1);
            self.wake.signal(());
        }
        admit
    }

    /// The controlling client went away: the session ends, its unsent replies are dropped.
    pub(crate) fn disconnect(&self) {
        self.admission(A::on_disconnect);
        self.tx.clear();
        self.wake.signal(());
    }

    /// Serve one listening socket on `port` of `stack` for ever: accept a client, then either
    /// serve it as the controller or refuse it and close it, as the session rules decide. A refused
    /// client is sent what `refusal` writes into a buffer of `R` bytes (it returns the length):
    /// the application's `busy_refusal`.
    ///
    /// Context: a task (at least two per stack, see the [module documentation](self)). Never
    /// returns.
    pub async fn listen<const R: usize>(
        &self,
        stack: Stack<'_>,
        port: u16,
        refusal: fn(&mut [u8; R]) -> usize,
    ) -> ! {
        accept_forever(stack, port, None, async |socket| {
            match self.connect(now_ms()) {
                Admit::Control => {
                    self.serve(socket, &mut Raw, &[]).await;
                    self.disconnect();
                }
                Admit::Refuse => self.refuse(socket, refusal).await,
            }
        })
        .await
    }

    /// Tell a second client that another is in control, with what `refusal` writes.
    pub(crate) async fn refuse<S: embedded_io_async::Write, const R: usize>(
        &self,
        socket: &mut S,
        refusal: fn(&mut [u8; R]) -> usize,
    ) {
        bump(&self.counters.refused, 1);
        let mut message = [0u8; R];
        let len = refusal(&mut message);
        let _ = with_timeout(
            REFUSAL_TIMEOUT,
            send(socket, message.get(..len).unwrap_or_default()),
        )
        .await;
    }

    /// Serve the controlling client until it goes away: the link bytes its bytes carry
    /// (`framing`: as they are, or in WebSocket frames) into the receive queue, as room allows
    /// (`initial`: bytes it sent before, at most [`CHUNK`]), the transmit queue to it, copied
    /// into the mirror if any.
    pub(crate) async fn serve<S, F>(&self, socket: &mut S, framing: &mut F, initial: &[u8])
    where
        S: embedded_io_async::Read + embedded_io_async::Write,
        F: Framing,
    {
        let mut raw = [0u8; CHUNK];
        let mut inbound = [0u8; CHUNK];
        // Link bytes not yet in the receive queue: inbound[start..end].
        let (mut start, mut end) = (0usize, 0usize);
        // A frame's header, then its payload from MAX_HEADER on; `carry` bytes held back from
        // the last frame (the start of a character) begin the next payload.
        let mut outbound = [0u8; MAX_HEADER + CHUNK];
        let mut carry = 0usize;
        let mut woke = None;
        if let Some(first) = raw.get_mut(..initial.len()).filter(|_| !initial.is_empty()) {
            first.copy_from_slice(initial);
            woke = Some(Wake::Received(Some(initial.len())));
        }
        loop {
            match woke {
                None => {}
                Some(Wake::Received(None | Some(0))) => return,
                Some(Wake::Received(Some(n))) => {
                    let mut reply = Reply::new();
                    let raw = raw.get(..n).unwrap_or_default();
                    let received = framing.receive(raw, &mut inbound, &mut reply);
                    end = *received.as_ref().unwrap_or(&0);
                    bump(&self.counters.rx_bytes, end);
                    start = inbound
                        .get(..end)
                        .map_or(0, |b| self.rx.try_write(b).unwrap_or(0));
                    self.wake.signal(());
                    let replied = send(socket, reply.bytes()).await;
                    if replied.is_err() || received.is_err() {
                        return;
                    }
                }
                Some(Wake::Queued(n)) => {
                    start += n;
                    self.wake.signal(());
                }
                Some(Wake::ToSend(n)) => {
                    if let (Some(m), Some(fresh)) = (
                        self.mirror,
                        outbound.get(MAX_HEADER + carry..MAX_HEADER + carry + n),
                    ) {
                        m.push(fresh);
                    }
                    match send_framed(socket, framing, &mut outbound, &mut carry, n).await {
                        Ok(sent) => bump(&self.counters.tx_bytes, sent),
                        Err(()) => return,
                    }
                }
            }
            let receive = async {
                match inbound.get(start..end).filter(|rest| !rest.is_empty()) {
                    Some(rest) => Wake::Queued(self.rx.write(rest).await),
                    None => Wake::Received(socket.read(&mut raw).await.ok()),
                }
            };
            let transmit = async {
                if self.tx.is_empty() {
                    self.tx_kick.wait().await;
                }
                let room = outbound.get_mut(MAX_HEADER + carry..).unwrap_or_default();
                Wake::ToSend(self.tx.try_read(room).unwrap_or(0))
            };
            woke = Some(match select(receive, transmit).await {
                Either::First(w) | Either::Second(w) => w,
            });
        }
    }
}

/// Frame and send the `carry` bytes held back at `outbound[MAX_HEADER..]` and the `n` bytes
/// after them; what `framing` holds back stays there for the next call (`carry`). Returns the
/// link bytes sent. Errors: the connection is gone.
pub(crate) async fn send_framed<S: embedded_io_async::Write, F: Framing>(
    socket: &mut S,
    framing: &mut F,
    outbound: &mut [u8; MAX_HEADER + CHUNK],
    carry: &mut usize,
    n: usize,
) -> Result<usize, ()> {
    let taken = *carry + n;
    let payload = outbound
        .get_mut(MAX_HEADER..MAX_HEADER + taken)
        .unwrap_or_default();
    let mut header = [0u8; MAX_HEADER];
    let (h, m) = framing.frame(payload, &mut header);
    let from = MAX_HEADER - h.min(MAX_HEADER);
    if let Some(slot) = outbound.get_mut(from..MAX_HEADER) {
        slot.copy_from_slice(header.get(..h).unwrap_or_default());
    }
    send(
        socket,
        outbound.get(from..MAX_HEADER + m).unwrap_or_default(),
    )
    .await?;
    outbound.copy_within(MAX_HEADER + m..MAX_HEADER + taken, MAX_HEADER);
    *carry = taken - m;
    Ok(m)
}

/// How a connection's bytes carry the link's bytes: as they are (the raw TCP link, [`Raw`]),
/// or in WebSocket frames (the web page's, [`crate::web`]).
pub(crate) trait Framing {
    /// `raw` arrived from the client: write the link bytes it carries into `data` (which is
    /// as long as any `raw`) and return how many; queue what the client is to be sent at once
    /// (a pong, a close frame) in `reply`. `Err`: the connection ends once `reply` is sent.
    fn receive(&mut self, raw: &[u8], data: &mut [u8], reply: &mut Reply) -> Result<usize, ()>;

    /// Make ready `payload`, link bytes taken from the transmit queue: how many of its first
    /// bytes to send now (the rest is kept for the next call), and the header that goes
    /// before them, written into `header` (its length; 0 for none).
    fn frame(&mut self, payload: &mut [u8], header: &mut [u8; MAX_HEADER]) -> (usize, usize);
}

/// The raw TCP link: the link's bytes as they are.
pub(crate) struct Raw;

impl Framing for Raw {
    fn receive(&mut self, raw: &[u8], data: &mut [u8], _: &mut Reply) -> Result<usize, ()> {
        let n = raw.len().min(data.len());
        if let (Some(d), Some(r)) = (data.get_mut(..n), raw.get(..n)) {
            d.copy_from_slice(r);
        }
        Ok(n)
    }

    fn frame(&mut self, payload: &mut [u8], _: &mut [u8; MAX_HEADER]) -> (usize, usize) {
        (0, payload.len())
    }
}

/// What a connection's client is sent at once, apart from the link's bytes: pongs, a close
/// frame.
pub(crate) struct Reply {
    buf: [u8; 256],
    len: usize,
}

impl Reply {
    pub(crate) const fn new() -> Self {
        Self {
            buf: [0; 256],
            len: 0,
        }
    }

    /// Queue `bytes` whole, if they fit.
    pub(crate) fn push(&mut self, bytes: &[u8]) {
        let end = self.len + bytes.len();
        if let Some(slot) = self.buf.get_mut(self.len..end) {
            slot.copy_from_slice(bytes);
            self.len = end;
        }
    }

    pub(crate) fn bytes(&self) -> &[u8] {
        self.buf.get(..self.len).unwrap_or_default()
    }
}

/// Accept clients on `port` of `stack` for ever, one at a time on one socket of
/// [`SOCKET_BUF`]-byte buffers: each is set up ([`CLIENT_TIMEOUT`], TCP keep-alives every
/// `keep_alive` if any, no Nagle) and handed to `serve`, then closed, its last bytes given
/// [`REFUSAL_TIMEOUT`] to leave.
pub(crate) async fn accept_forever(
    stack: Stack<'_>,
    port: u16,
    keep_alive: Option<Duration>,
    mut serve: impl AsyncFnMut(&mut TcpSocket<'_>),
) -> ! {
    let mut rx_buf = [0u8; SOCKET_BUF];
    let mut tx_buf = [0u8; SOCKET_BUF];
    let mut socket = TcpSocket::new(stack, &mut rx_buf, &mut tx_buf);
    let endpoint = IpListenEndpoint { addr: None, port };
    loop {
        socket.set_timeout(None);
        socket.set_keep_alive(None);
        if socket.accept(endpoint).await.is_err() {
            socket.abort();
            Timer::after(Duration::from_millis(100)).await;
            continue;
        }
        socket.set_timeout(Some(CLIENT_TIMEOUT));
        socket.set_keep_alive(keep_alive);
        socket.set_nagle_enabled(false);
        serve(&mut socket).await;
        socket.close();
        let _ = with_timeout(REFUSAL_TIMEOUT, socket.flush()).await;
        socket.abort();
    }
}

/// What woke the serving loop.
enum Wake {
    /// Bytes from the client (`None`: the connection failed).
    Received(Option<usize>),
    /// Bytes held back were queued.
    Queued(usize),
    /// Bytes taken from the transmit queue, to send.
    ToSend(usize),
}

/// Write all of `bytes` to `socket`. Errors: the connection is gone.
pub(crate) async fn send<S: embedded_io_async::Write>(
    socket: &mut S,
    mut bytes: &[u8],
) -> Result<(), ()> {
    while !bytes.is_empty() {
        match socket.write(bytes).await {
            Ok(0) | Err(_) => return Err(()),
            Ok(n) => bytes = bytes.get(n..).unwrap_or_default(),
        }
    }
    Ok(())
}

/// The controller's end of a [`TcpServer`]: `embedded-io` reads and writes over the queues,
/// whether a client is in control, its greeting and the session rules. See the
/// [module documentation](self) for the rules.
///
/// The blocking [`embedded_io::Read::read`] on an empty queue spins until a serving task has
/// run: from a task, read only what [`embedded_io::ReadReady`] announces (as
/// `Controller::poll` does), or use [`TcpLink::try_read`] or the async traits.
pub struct TcpLink<'a, A, const RX: usize, const TX: usize> {
    server: &'a TcpServer<A, RX, TX>,
}

impl<A: Admission, const RX: usize, const TX: usize> TcpLink<'_, A, RX, TX> {
    /// Copy received bytes into `buf`, as many as are there; `0` when none are waiting.
    ///
    /// Context: thread. Never blocks.
    pub fn try_read(&mut self, buf: &mut [u8]) -> usize {
        self.server.rx.try_read(buf).unwrap_or(0)
    }

    /// Queue as much of `bytes` as fits for the controlling client; all of it is taken (and
    /// dropped) while no client is connected.
    ///
    /// Context: thread. Never blocks.
    pub fn try_write(&mut self, bytes: &[u8]) -> usize {
        if !self.is_connected() {
            return bytes.len();
        }
        let n = self.server.tx.try_write(bytes).unwrap_or(0);
        if n > 0 {
            self.server.tx_kick.signal(());
        }
        n
    }

    fn is_connected(&self) -> bool {
        self.server.is_connected()
    }

    /// Whether a new controlling client is waiting for its greeting: `true` once for each
    /// client admitted since the last call and still connected. The caller greets it (frame
    /// 54, `Controller::on_connect`) before anything else is written to it.
    ///
    /// Context: the controller's task. Never blocks.
    pub fn take_greeting(&mut self) -> bool {
        self.server.shared.lock(|s| {
            let mut s = s.borrow_mut();
            core::mem::replace(&mut s.greet, false) && s.admission.state() == LinkState::Connected
        })
    }

    /// Run `f` on the session rules and return what it returns (as [`TcpServer::admission`]):
    /// the controller's task polls its keep-alives this way.
    ///
    /// Context: the controller's task. `f` runs in a critical section: keep it to a few
    /// instructions.
    pub fn admission<R>(&mut self, f: impl FnOnce(&mut A) -> R) -> R {
        self.server.admission(f)
    }

    /// Count a keep-alive (frame 55) the controller sent ([`LinkCounters::keep_alives`]).
    ///
    /// Context: the controller's task, the counter's one writer. Never blocks.
    pub fn count_keep_alive(&mut self) {
        bump(&self.server.counters.keep_alives, 1);
    }

    /// Wait until bytes arrive, a client connects or leaves, or `deadline` (embassy time).
    ///
    /// Context: the controller's task. Always lets the other tasks run once, even with a
    /// deadline already past. Bytes that were waiting before the call do not end the wait:
    /// the controller reads all it can take at each poll, so bytes still queued after it are
    /// held back on purpose.
    pub async fn wait(&mut self, deadline: Instant) {
        if deadline <= Instant::now() {
            embassy_futures::yield_now().await;
        } else {
            let _ = with_deadline(deadline, self.server.wake.wait()).await;
        }
    }

    /// How many clients have been in control so far.
    pub fn connections(&self) -> u32 {
        self.server.counters.connections.load(Ordering::Relaxed)
    }
}

impl<A: Admission, const RX: usize, const TX: usize> LinkStatus for TcpLink<'_, A, RX, TX> {
    fn state(&self) -> LinkState {
        self.server.admission(|a| a.state())
    }
}

impl<A: Admission, const RX: usize, const TX: usize> embedded_io::ErrorType
    for TcpLink<'_, A, RX, TX>
{
    type Error = Infallible;
}

impl<A: Admission, const RX: usize, const TX: usize> embedded_io::ReadReady
    for TcpLink<'_, A, RX, TX>
{
    /// Bytes are waiting, and the transmit queue has room for their replies
    /// ([`TX_HEADROOM`]).
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        Ok(!self.server.rx.is_empty() && self.server.tx.free_capacity() >= TX_HEADROOM)
    }
}

impl<A: Admission, const RX: usize, const TX: usize> embedded_io::Read for TcpLink<'_, A, RX, TX> {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        Ok(crate::uart::read_blocking(buf, |b| self.try_read(b)))
    }
}

impl<A: Admission, const RX: usize, const TX: usize> embedded_io::WriteReady
    for TcpLink<'_, A, RX, TX>
{
    fn write_ready(&mut self) -> Result<bool, Self::Error> {
        Ok(!self.is_connected() || !self.server.tx.is_full())
    }
}

impl<A: Admission, const RX: usize, const TX: usize> embedded_io::Write for TcpLink<'_, A, RX, TX> {
    /// Queue `buf` for the client; never waits. What does not fit is dropped (and counted).
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        let n = self.try_write(buf);
        if n < buf.len() {
            bump(&self.server.counters.tx_dropped, buf.len() - n);
        }
        Ok(buf.len())
    }

    /// Nothing to do: the serving task sends queued bytes as soon as it runs.
    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

impl<A: Admission, const RX: usize, const TX: usize> embedded_io_async::Read
    for TcpLink<'_, A, RX, TX>
{
    async fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        if buf.is_empty() {
            return Ok(0);
        }
        Ok(self.server.rx.read(buf).await)
    }
}

impl<A: Admission, const RX: usize, const TX: usize> embedded_io_async::Write
    for TcpLink<'_, A, RX, TX>
{
    async fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        if buf.is_empty() || !self.is_connected() {
            return Ok(buf.len());
        }
        let n = self.server.tx.write(buf).await;
        self.server.tx_kick.signal(());
        Ok(n)
    }

    async fn flush(&mut self) -> Result<(), Self::Error> {
        while self.is_connected() && !self.server.tx.is_empty() {
            Timer::after(Duration::from_millis(1)).await;
        }
        Ok(())
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::port_link::SingleClient;
    use core::task::Poll;
    use embassy_futures::block_on;
    use embedded_io::{Read, ReadReady, Write, WriteReady};
    use std::vec::Vec;

    pub(crate) fn server<const RX: usize, const TX: usize>()
    -> &'static TcpServer<SingleClient, RX, TX> {
        let queues = Box::leak(Box::new(TcpQueues::new()));
        let counters = Box::leak(Box::new(LinkCounters::new()));
        Box::leak(Box::new(TcpServer::new(
            queues,
            counters,
            SingleClient::new(),
        )))
    }

    /// A client on the other end of a socket: it sends `inbound`, one chunk per read, keeps
    /// what it is sent, and closes once it has received `close_after` bytes.
    pub(crate) struct Client {
        pub(crate) inbound: Vec<&'static [u8]>,
        pub(crate) received: Vec<u8>,
        pub(crate) close_after: usize,
    }

    impl embedded_io_async::ErrorType for Client {
        type Error = Infallible;
    }

    impl embedded_io_async::Read for Client {
        async fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
            core::future::poll_fn(|_| {
                if !self.inbound.is_empty() {
                    let chunk = self.inbound.remove(0);
                    buf[..chunk.len()].copy_from_slice(chunk);
                    Poll::Ready(Ok(chunk.len()))
                } else if self.received.len() >= self.close_after {
                    Poll::Ready(Ok(0))
                } else {
                    Poll::Pending
                }
            })
            .await
        }
    }

    impl embedded_io_async::Write for Client {
        async fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
            self.received.extend_from_slice(buf);
            Ok(buf.len())
        }

        async fn flush(&mut self) -> Result<(), Self::Error> {
            Ok(())
        }
    }

    #[test]
    fn the_link_is_taken_once() {
        let s = server::<64, 1024>();
        assert!(s.take().is_some());
        assert!(s.take().is_none());
    }

    #[test]
    fn replies_without_a_client_are_discarded() {
        let s = server::<64, 1024>();
        let mut link = s.take().unwrap();
        assert_eq!(link.state(), LinkState::Disconnected);
        assert_eq!(link.write(b"ok\n").unwrap(), 3);
        assert!(s.tx.is_empty(), "nothing queued for nobody");
        assert!(link.write_ready().unwrap());
        assert_eq!(s.counters().tx_dropped.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn the_first_client_is_greeted_once_and_a_second_is_refused() {
        let s = server::<64, 1024>();
        let mut link = s.take().unwrap();
        assert!(!link.take_greeting(), "nobody to greet");
        assert_eq!(s.connect(1_000), Admit::Control);
        assert_eq!(s.connect(1_010), Admit::Refuse);
        assert_eq!(link.state(), LinkState::Connected);
        assert!(
            link.admission(|a| a.state() == LinkState::Connected),
            "the rules were asked"
        );
        assert!(link.take_greeting());
        assert!(!link.take_greeting(), "greeted once");
        assert_eq!(link.connections(), 1);
        link.count_keep_alive();
        assert_eq!(s.counters().keep_alives.load(Ordering::Relaxed), 1);
        s.disconnect();
        assert_eq!(link.state(), LinkState::Disconnected);
        assert!(
            !s.admission(|a| a.state() == LinkState::Connected),
            "the rules heard of the close"
        );
        assert!(!link.take_greeting());
        assert_eq!(s.connect(3_000), Admit::Control);
        assert!(link.take_greeting(), "the next client is greeted");
        assert_eq!(link.connections(), 2);
    }

    #[test]
    fn a_client_that_leaves_before_its_greeting_is_not_greeted() {
        let s = server::<64, 1024>();
        let mut link = s.take().unwrap();
        s.connect(0);
        s.disconnect();
        assert!(!link.take_greeting());
    }

    #[test]
    fn a_new_controller_does_not_get_the_replies_queued_for_the_last() {
        let s = server::<64, 1024>();
        let mut link = s.take().unwrap();
        s.connect(0);
        link.write_all(b"ok\n").unwrap();
        assert!(!s.tx.is_empty());
        s.disconnect();
        assert!(s.tx.is_empty(), "dropped when the client left");
        s.connect(10);
        link.write_all(b"ok\n").unwrap();
        // The session ends before its serving task has cleared the queue.
        s.admission(|a| a.on_disconnect());
        s.connect(30);
        assert!(s.tx.is_empty(), "dropped when the next client came");
    }

    #[test]
    fn input_is_read_only_while_its_replies_have_room() {
        let s = server::<64, 1024>();
        let mut link = s.take().unwrap();
        s.connect(0);
        assert!(!link.read_ready().unwrap(), "nothing received");
        s.rx.try_write(b"G0\n").unwrap();
        assert!(link.read_ready().unwrap());
        let fill = [b'x'; 1024 - TX_HEADROOM + 1];
        assert_eq!(link.try_write(&fill), fill.len());
        assert!(!link.read_ready().unwrap(), "less than the headroom free");
        let mut buf = [0u8; 8];
        assert_eq!(link.read(&mut buf).unwrap(), 3);
        assert_eq!(&buf[..3], b"G0\n");
        assert_eq!(link.try_read(&mut buf), 0);
    }

    #[test]
    fn a_full_transmit_queue_drops_and_counts_what_does_not_fit() {
        let s = server::<64, 1024>();
        let mut link = s.take().unwrap();
        s.connect(0);
        assert_eq!(link.write(&[b'x'; 1000]).unwrap(), 1000);
        assert_eq!(link.write(&[b'y'; 100]).unwrap(), 100, "never waits");
        assert_eq!(s.counters().tx_dropped.load(Ordering::Relaxed), 76);
        assert!(!link.write_ready().unwrap());
    }

    #[test]
    fn serving_moves_bytes_both_ways_until_the_client_closes() {
        let s = server::<64, 1024>();
        let mut link = s.take().unwrap();
        s.connect(0);
        link.write_all(b"start\n").unwrap();
        let mut client = Client {
            inbound: std::vec![b"M115\n", b"G0 X1\n"],
            received: Vec::new(),
            close_after: 6,
        };
        block_on(s.serve(&mut client, &mut Raw, &[]));
        assert_eq!(client.received, b"start\n");
        let mut buf = [0u8; 32];
        let n = link.try_read(&mut buf);
        assert_eq!(&buf[..n], b"M115\nG0 X1\n");
        let counters = s.counters();
        assert_eq!(counters.rx_bytes.load(Ordering::Relaxed), 11);
        assert_eq!(counters.tx_bytes.load(Ordering::Relaxed), 6);
    }

    #[test]
    fn a_client_faster_than_the_controller_is_held_back_not_dropped() {
        let s = server::<8, 1024>();
        let mut link = s.take().unwrap();
        s.connect(0);
        let mut client = Client {
            inbound: std::vec![b"G1 X10 Y20\n"],
            received: Vec::new(),
            close_after: 0,
        };
        let mut received = Vec::new();
        let mut raw = Raw;
        let mut serving = core::pin::pin!(s.serve(&mut client, &mut raw, &[]));
        let waker = core::task::Waker::noop();
        let mut cx = core::task::Context::from_waker(waker);
        while serving.as_mut().poll(&mut cx).is_pending() {
            let mut buf = [0u8; 3];
            let n = link.try_read(&mut buf);
            received.extend_from_slice(&buf[..n]);
        }
        let mut buf = [0u8; 8];
        loop {
            let n = link.try_read(&mut buf);
            if n == 0 {
                break;
            }
            received.extend_from_slice(&buf[..n]);
        }
        assert_eq!(received, b"G1 X10 Y20\n");
    }

    #[test]
    fn a_refused_client_gets_the_refusal() {
        let s = server::<64, 1024>();
        let mut client = Client {
            inbound: Vec::new(),
            received: Vec::new(),
            close_after: 0,
        };
        fn busy(out: &mut [u8; 32]) -> usize {
            let message = b"// E300 link-busy\n";
            out[..message.len()].copy_from_slice(message);
            message.len()
        }
        block_on(s.refuse(&mut client, busy));
        assert_eq!(client.received, b"// E300 link-busy\n");
        assert_eq!(s.counters().refused.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn the_wait_ends_at_news_or_at_the_deadline() {
        let s = server::<64, 1024>();
        let mut link = s.take().unwrap();
        let start = Instant::now();
        block_on(link.wait(start + Duration::from_millis(20)));
        assert!(Instant::now() >= start + Duration::from_millis(20));
        s.connect(0);
        let start = Instant::now();
        block_on(link.wait(start + Duration::from_secs(60)));
        assert!(Instant::now() < start + Duration::from_secs(60), "woken");
    }
}
