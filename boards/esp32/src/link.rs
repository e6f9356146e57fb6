//! The host link over WiFi: a TCP server on [`PORT`] with one controlling client at a time.
//!
//! # Session
//!
//! The session rules are [`forja_drivers::session::LinkSession`], the same code as the
//! simulator's TCP link and tested there on the host. The listening tasks report connections
//! and disconnections to it; the controller task polls it through [`WifiLink::poll_session`]
//! and writes the messages itself, into the same outgoing stream as its replies, so that a
//! 54 or 55 never lands inside another line:
//!
//! | `LinkSession` says | who | does |
//! |---|---|---|
//! | `SendConnected` | controller task | the client is the controller: `Controller::on_connect` (frame 54, a fresh decoder) |
//! | `SendKeepAlive(n)` | controller task | `Controller::keep_alive(n)` (frame 55), every `keep_alive_ms` |
//! | `RefuseSecondClient` | listening task | sends the new client `busy_refusal` (a 56 frame and a `//` notice line, code 300 `link-busy`) and closes it |
//!
//! Each stack (station and access point) has [`LISTENERS`] listening sockets, each served by
//! its own task ([`listen`]): one can hold the controlling client while another is free to
//! accept, and refuse, a second one. The session is shared by all of them, so the rule holds
//! across both networks.
//!
//! A client that goes away (closes, resets, or stops acknowledging for
//! [`CLIENT_TIMEOUT`] because its WiFi dropped: the keep-alives make the loss visible) ends the
//! session; the next client to connect becomes the controller.
//!
//! # Bytes
//!
//! Bytes move between the sockets and the controller through two static queues (embassy-sync
//! pipes, [`RX_LEN`] and [`TX_LEN`] bytes). The controller's end is [`WifiLink`], the link
//! object of `Controller::poll`: `embedded-io` `Read + ReadReady + Write`, plus
//! [`LinkStatus`]. The controller runs in a task of the same executor as the sockets, so
//! nothing on its side may wait for them:
//!
//! - **Input.** Received bytes are read from the socket only when the receive queue has room,
//!   so a client that sends faster than the controller reads is held back by TCP flow control,
//!   never dropped. `read_ready` says `true` only while the transmit queue also has
//!   [`TX_HEADROOM`] bytes free: a client that does not read its replies stops being read.
//! - **Output.** Writes never wait: what does not fit in the transmit queue is dropped and
//!   counted (`tx_dropped`), which the headroom makes a client's fault only. With no client
//!   connected, writes are discarded at once (like a UART with nothing attached), so the
//!   controller never waits for an absent host; at each new connection anything still queued
//!   from the previous one is dropped.
//! - **Waking.** [`WifiLink::wait`] returns when bytes arrive, a client connects or leaves,
//!   or at a deadline: the controller task sleeps in it between polls.
//!
//! Nothing in this module depends on the motion side: a program stored on the board runs on
//! while the link is down.
//!
//! # Observing the link
//!
//! [`FORJA_LINK_COUNTERS`] counts connections, refusals, keep-alives, bytes and dropped
//! replies; a debugger reads it by its symbol name through the USB Serial/JTAG port.

use core::cell::RefCell;
use core::convert::Infallible;
use core::sync::atomic::{AtomicU32, Ordering};

use embassy_futures::select::{Either, select};
use embassy_net::tcp::TcpSocket;
use embassy_net::{IpListenEndpoint, Stack};
use embassy_sync::blocking_mutex::Mutex;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::pipe::Pipe;
use embassy_sync::signal::Signal;
use embassy_time::{Duration, Instant, Timer, with_deadline, with_timeout};
use forja_app::controller::{BUSY_REFUSAL_LEN, DEFAULT_KEEP_ALIVE_MS, busy_refusal};
use forja_drivers::session::{LinkSession, SessionAction};
use forja_hal_abstraction::link::{LinkState, LinkStatus};

/// The TCP port of the host link, the simulator's too.
pub const PORT: u16 = 2323;

/// Listening sockets per stack.
pub const LISTENERS: usize = 2;

/// A client that acknowledges nothing for this long is gone.
pub const CLIENT_TIMEOUT: Duration = Duration::from_secs(10);

/// Bytes of the receive queue (client to controller).
pub const RX_LEN: usize = 2048;

/// Bytes of the transmit queue (controller to client).
pub const TX_LEN: usize = 2048;

/// Free bytes the transmit queue must have for the controller to read more input: more than
/// the longest burst of replies one poll writes for 128 bytes of input (an `M115` answer, a
/// status frame, a keep-alive).
pub const TX_HEADROOM: usize = 512;

/// Bytes of each socket's receive and transmit buffers.
const SOCKET_BUF: usize = 1536;

/// How long a refused client is given to receive the refusal.
const REFUSAL_TIMEOUT: Duration = Duration::from_millis(500);

type Queue<const N: usize> = Pipe<CriticalSectionRawMutex, N>;

static RX: Queue<RX_LEN> = Pipe::new();
static TX: Queue<TX_LEN> = Pipe::new();
/// Raised by [`WifiLink`] writes, so that the serving task sends at once.
static TX_KICK: Signal<CriticalSectionRawMutex, ()> = Signal::new();
/// Raised when bytes reach the receive queue or a client comes or goes, to wake the
/// controller task ([`WifiLink::wait`]).
static WAKE: Signal<CriticalSectionRawMutex, ()> = Signal::new();

/// The session, and whether its controller was not yet greeted (54).
struct Shared {
    session: LinkSession,
    greet: bool,
}

static SESSION: Mutex<CriticalSectionRawMutex, RefCell<Shared>> =
    Mutex::new(RefCell::new(Shared {
        session: LinkSession::new(DEFAULT_KEEP_ALIVE_MS),
        greet: false,
    }));

/// Whether the [`WifiLink`] was handed out.
static TAKEN: Mutex<CriticalSectionRawMutex, RefCell<bool>> = Mutex::new(RefCell::new(false));

/// Counters of the host link, wrapping. Each is written by one context at a time (the serving
/// task, or the controller task for `keep_alives` and `tx_dropped`).
#[repr(C)]
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

/// The link counters, at a symbol a debugger can find.
#[unsafe(no_mangle)]
pub static FORJA_LINK_COUNTERS: LinkCounters = LinkCounters {
    connections: AtomicU32::new(0),
    refused: AtomicU32::new(0),
    keep_alives: AtomicU32::new(0),
    rx_bytes: AtomicU32::new(0),
    tx_bytes: AtomicU32::new(0),
    tx_dropped: AtomicU32::new(0),
};

fn bump(counter: &AtomicU32, by: usize) {
    // One writer at a time, and a target without read-modify-write atomics (RISC-V `imc`):
    // load and store.
    counter.store(
        counter.load(Ordering::Relaxed).wrapping_add(by as u32),
        Ordering::Relaxed,
    );
}

/// The milliseconds of the session clock (embassy's time base, wrapping).
pub fn now_ms() -> u32 {
    Instant::now().as_millis() as u32
}

fn session<R>(f: impl FnOnce(&mut LinkSession) -> R) -> R {
    SESSION.lock(|s| f(&mut s.borrow_mut().session))
}

/// Start the session with keep-alives every `keep_alive_ms` (the controller's
/// `keep_alive_ms` setting).
///
/// Context: init, before the listening tasks run.
pub fn configure(keep_alive_ms: u32) {
    SESSION.lock(|s| s.borrow_mut().session = LinkSession::new(keep_alive_ms));
}

/// The controller's end of the link: `embedded-io` reads and writes over the queues, and
/// whether a client is in control. See the [module documentation](self) for the rules.
///
/// The blocking [`embedded_io::Read::read`] on an empty queue spins until the network task has
/// run: from an executor task, read only what [`embedded_io::ReadReady`] announces (as
/// `Controller::poll` does), or use [`WifiLink::try_read`] or the async traits.
pub struct WifiLink {
    _private: (),
}

impl WifiLink {
    /// The controller's end; `None` after the first call.
    ///
    /// Context: init.
    pub fn take() -> Option<Self> {
        let first = TAKEN.lock(|t| !t.replace(true));
        first.then_some(Self { _private: () })
    }

    /// Copy received bytes into `buf`, as many as are there; `0` when none are waiting.
    ///
    /// Context: thread. Never blocks.
    pub fn try_read(&mut self, buf: &mut [u8]) -> usize {
        RX.try_read(buf).unwrap_or(0)
    }

    /// Queue as much of `bytes` as fits for the controlling client; all of it is taken (and
    /// dropped) while no client is connected.
    ///
    /// Context: thread. Never blocks.
    pub fn try_write(&mut self, bytes: &[u8]) -> usize {
        if !session(|s| s.is_connected()) {
            return bytes.len();
        }
        let n = TX.try_write(bytes).unwrap_or(0);
        if n > 0 {
            TX_KICK.signal(());
        }
        n
    }

    /// What the session asks of the controller at `now_ms` (embassy milliseconds, see
    /// [`now_ms`]): [`SessionAction::SendConnected`] once for each new controlling client,
    /// then [`SessionAction::SendKeepAlive`] when one is due. Call it until it returns `None`,
    /// and again at the latest at [`WifiLink::session_poll_at`].
    ///
    /// Context: the controller task. Never blocks.
    pub fn poll_session(&mut self, now_ms: u32) -> Option<SessionAction> {
        let action = SESSION.lock(|s| {
            let mut s = s.borrow_mut();
            if core::mem::replace(&mut s.greet, false) && s.session.is_connected() {
                Some(SessionAction::SendConnected)
            } else {
                s.session.poll(now_ms)
            }
        });
        if let Some(SessionAction::SendKeepAlive(_)) = action {
            bump(&FORJA_LINK_COUNTERS.keep_alives, 1);
        }
        action
    }

    /// When [`WifiLink::poll_session`] has something to do next; `None` while no client is
    /// in control.
    pub fn session_poll_at(&self) -> Option<u32> {
        session(|s| s.poll_at())
    }

    /// Wait until bytes arrive, a client connects or leaves, or `deadline` (embassy time).
    ///
    /// Context: the controller task.
    /// Always lets the other tasks run once, even with a deadline already past. Bytes that
    /// were waiting before the call do not end the wait: the controller reads all it can take
    /// at each poll, so bytes still queued after it are held back on purpose.
    pub async fn wait(&mut self, deadline: Instant) {
        if deadline <= Instant::now() {
            embassy_futures::yield_now().await;
        } else {
            let _ = with_deadline(deadline, WAKE.wait()).await;
        }
    }

    /// How many clients have been in control so far.
    pub fn connections(&self) -> u32 {
        FORJA_LINK_COUNTERS.connections.load(Ordering::Relaxed)
    }
}

impl LinkStatus for WifiLink {
    fn state(&self) -> LinkState {
        session(|s| s.state())
    }
}

impl embedded_io::ErrorType for WifiLink {
    type Error = Infallible;
}

impl embedded_io::ReadReady for WifiLink {
    /// Bytes are waiting, and the transmit queue has room for their replies
    /// ([`TX_HEADROOM`]).
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        Ok(!RX.is_empty() && TX.free_capacity() >= TX_HEADROOM)
    }
}

impl embedded_io::Read for WifiLink {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        if buf.is_empty() {
            return Ok(0);
        }
        loop {
            let n = self.try_read(buf);
            if n > 0 {
                return Ok(n);
            }
            core::hint::spin_loop();
        }
    }
}

impl embedded_io::WriteReady for WifiLink {
    fn write_ready(&mut self) -> Result<bool, Self::Error> {
        Ok(!session(|s| s.is_connected()) || !TX.is_full())
    }
}

impl embedded_io::Write for WifiLink {
    /// Queue `buf` for the client; never waits. What does not fit is dropped (and counted).
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        let n = self.try_write(buf);
        if n < buf.len() {
            bump(&FORJA_LINK_COUNTERS.tx_dropped, buf.len() - n);
        }
        Ok(buf.len())
    }

    /// Nothing to do: the serving task sends queued bytes as soon as it runs.
    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

impl embedded_io_async::Read for WifiLink {
    async fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        if buf.is_empty() {
            return Ok(0);
        }
        Ok(RX.read(buf).await)
    }
}

impl embedded_io_async::Write for WifiLink {
    async fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        if buf.is_empty() || !session(|s| s.is_connected()) {
            return Ok(buf.len());
        }
        let n = TX.write(buf).await;
        TX_KICK.signal(());
        Ok(n)
    }

    async fn flush(&mut self) -> Result<(), Self::Error> {
        while session(|s| s.is_connected()) && !TX.is_empty() {
            Timer::after(Duration::from_millis(1)).await;
        }
        Ok(())
    }
}

/// Serve one listening socket of `stack` for ever: accept a client, then either serve it as
/// the controller or refuse it, as the session decides.
///
/// Context: an esp-rtos task ([`LISTENERS`] per stack). Never returns.
pub async fn listen(stack: Stack<'static>) -> ! {
    let mut rx_buf = [0u8; SOCKET_BUF];
    let mut tx_buf = [0u8; SOCKET_BUF];
    let mut socket = TcpSocket::new(stack, &mut rx_buf, &mut tx_buf);
    let endpoint = IpListenEndpoint {
        addr: None,
        port: PORT,
    };
    loop {
        socket.set_timeout(None);
        if socket.accept(endpoint).await.is_err() {
            socket.abort();
            Timer::after(Duration::from_millis(100)).await;
            continue;
        }
        socket.set_timeout(Some(CLIENT_TIMEOUT));
        socket.set_nagle_enabled(false);
        // Whatever the controller queued before a new client arrives belongs to nobody.
        let action = SESSION.lock(|s| {
            let mut s = s.borrow_mut();
            let action = s.session.on_connect(now_ms());
            if action == SessionAction::SendConnected {
                TX.clear();
                s.greet = true;
            }
            action
        });
        match action {
            SessionAction::SendConnected => {
                bump(&FORJA_LINK_COUNTERS.connections, 1);
                WAKE.signal(());
                serve(&mut socket).await;
                session(LinkSession::on_disconnect);
                TX.clear();
                WAKE.signal(());
            }
            _ => refuse(&mut socket).await,
        }
        socket.close();
        let _ = with_timeout(REFUSAL_TIMEOUT, socket.flush()).await;
        socket.abort();
    }
}

/// Write all of `bytes` to `socket`. Errors: the connection is gone.
async fn send(socket: &mut TcpSocket<'_>, mut bytes: &[u8]) -> Result<(), ()> {
    while !bytes.is_empty() {
        match socket.write(bytes).await {
            Ok(0) | Err(_) => return Err(()),
            Ok(n) => bytes = bytes.get(n..).unwrap_or_default(),
        }
    }
    Ok(())
}

/// Tell a second client that another is in control.
async fn refuse(socket: &mut TcpSocket<'_>) {
    bump(&FORJA_LINK_COUNTERS.refused, 1);
    let mut refusal = [0u8; BUSY_REFUSAL_LEN];
    let len = busy_refusal(&mut refusal);
    let _ = with_timeout(
        REFUSAL_TIMEOUT,
        send(socket, refusal.get(..len).unwrap_or_default()),
    )
    .await;
}

/// What woke the serving loop.
enum Wake {
    Received(Result<usize, embassy_net::tcp::Error>),
    Queued(usize),
    ToSend(usize),
}

/// Serve the controlling client until it goes away: its bytes into the receive queue (as
/// room allows), the transmit queue to it.
async fn serve(socket: &mut TcpSocket<'_>) {
    let mut inbound = [0u8; 512];
    // Received bytes not yet in the receive queue: inbound[start..end].
    let (mut start, mut end) = (0usize, 0usize);
    let mut outbound = [0u8; 512];
    loop {
        let receive = async {
            match inbound.get(start..end).filter(|rest| !rest.is_empty()) {
                Some(rest) => Wake::Queued(RX.write(rest).await),
                None => Wake::Received(socket.read(&mut inbound).await),
            }
        };
        let transmit = async {
            if TX.is_empty() {
                TX_KICK.wait().await;
            }
            Wake::ToSend(TX.try_read(&mut outbound).unwrap_or(0))
        };
        let woke = match select(receive, transmit).await {
            Either::First(w) | Either::Second(w) => w,
        };
        match woke {
            Wake::Received(Ok(0) | Err(_)) => return,
            Wake::Received(Ok(n)) => {
                bump(&FORJA_LINK_COUNTERS.rx_bytes, n);
                end = n;
                start = inbound.get(..n).map_or(0, |b| RX.try_write(b).unwrap_or(0));
                WAKE.signal(());
            }
            Wake::Queued(n) => {
                start += n;
                WAKE.signal(());
            }
            Wake::ToSend(n) => {
                if send(socket, outbound.get(..n).unwrap_or_default())
                    .await
                    .is_err()
                {
                    return;
                }
                bump(&FORJA_LINK_COUNTERS.tx_bytes, n);
            }
        }
    }
}
