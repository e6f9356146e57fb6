//! The operator's web page over `embassy-net`: an HTTP server that serves `forja-web`'s assets
//! and carries the host link over a WebSocket at `/ws`, into the same queues and under the
//! same session rules as the raw TCP link ([`crate::tcp`]). Behind the `embassy-net` feature.
//!
//! The board runs [`TcpServer::listen_web`] in a few tasks per stack, beside the raw TCP
//! link's [`TcpServer::listen`] tasks, on the same [`TcpServer`]:
//!
//! ```text
//!  browser ─HTTP─ web task ── GET /, … ──► forja_web asset (gzip, from flash), close
//!                          └─ GET /ws ──► WebSocket ─► admission (the server's rules)
//!                                 Control: CONTROL_NOTICE, then frames ⇄ the link's queues
//!                                 Refuse:  WATCHING_NOTICE, then the mirror ─► text frames
//! ```
//!
//! # One controller across raw TCP and the page
//!
//! A WebSocket is admitted by the server's session rules exactly as a raw TCP client is: the
//! first client of either kind controls the machine. A WebSocket client that is refused
//! (another client, raw or web, is in control) is not closed but **watches**:
//!
//! - it is sent [`WATCHING_NOTICE`], then a copy of every byte the controlling client is sent
//!   (replies, positions, progress, keep-alives), read from the server's [`Mirror`] at most
//!   every [`WATCH_POLL`]; a watcher that falls more than [`MIRROR_LEN`] bytes behind skips
//!   to the next line;
//! - whatever it sends is decoded and dropped, never queued for the controller, and each batch
//!   is answered with the busy refusal (`// E300 link-busy`);
//! - when no client is in control, the watcher that has watched longest takes control at its
//!   next look (within [`WATCH_POLL`]): it is sent [`CONTROL_NOTICE`], and the controller task
//!   greets it with frame 54 as any new controlling client. A page that connects while others
//!   watch joins them; a raw TCP client is admitted or refused at once, as always.
//!
//! At most [`MAX_WATCHERS`] watch at once; one more is closed with 1008.
//!
//! # Bytes
//!
//! The controlling WebSocket's text and binary payload bytes are the link's bytes, held back
//! by the receive queue as a raw client's are (a frame is not read further while the queue is
//! full). What the controller writes is sent as text frames, as the transmit queue gives it
//! (a frame may hold several lines or part of one), made UTF-8
//! (`forja_web::websocket::text_ready`). Pings are answered with pongs; a close is echoed; a
//! malformed frame is answered with a close frame of its code (1002, 1009) and the connection
//! is closed, with nothing of that frame queued.
//!
//! Every other request is answered and closed: an asset with its gzip bytes, straight from
//! flash; anything else with its refusal (404, 400, 405, 413, …). A client that has not sent
//! its request head within [`HTTP_TIMEOUT`] is closed.
//!
//! # Execution context
//!
//! Tasks of the same executor as the raw TCP link's; nothing runs in an interrupt. The mirror
//! and the watchers' order are shared through critical sections of a few instructions.

use core::cell::RefCell;
use core::sync::atomic::AtomicU32;

use embassy_futures::select::{Either, select};
use embassy_net::Stack;
use embassy_sync::blocking_mutex::Mutex;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_time::{Duration, Timer, with_timeout};
use forja_web::http::{self, MAX_HEAD_LEN, Parsed, RequestError, Route};
use forja_web::websocket::{
    self, CONTROL_NOTICE, Decoder, Event, MAX_CONTROL, MAX_MESSAGE_LEN, Opcode, WATCHING_NOTICE,
    close_code,
};

use crate::port_link::{Admission, Admit};
use crate::tcp::{
    CHUNK, Framing, MAX_HEADER, Reply, TcpServer, accept_forever, bump, now_ms, send, send_framed,
};

/// Bytes of the [`Mirror`]: how far a watcher may fall behind the controlling client.
pub const MIRROR_LEN: usize = 1024;

/// Most WebSocket clients watching at once.
pub const MAX_WATCHERS: usize = 4;

/// How often a watcher looks at the mirror and whether control is free.
pub const WATCH_POLL: Duration = Duration::from_millis(50);

/// A client that has not sent its request head, or taken its answer, by then is closed.
pub const HTTP_TIMEOUT: Duration = Duration::from_secs(10);

/// TCP keep-alive of a web connection: a watcher's network that drops is noticed although it
/// sends nothing.
const KEEP_ALIVE: Duration = Duration::from_secs(5);

/// Counters of the web server, wrapping; each written by the web tasks only.
#[repr(C)]
#[derive(Debug)]
pub struct WebCounters {
    /// Assets served (200).
    pub served: AtomicU32,
    /// Requests refused (404, 400, 405, …).
    pub refused: AtomicU32,
    /// WebSocket clients that watched.
    pub watchers: AtomicU32,
    /// WebSocket clients closed for a malformed frame.
    pub protocol_errors: AtomicU32,
}

impl WebCounters {
    /// All zero.
    pub const fn new() -> Self {
        Self {
            served: AtomicU32::new(0),
            refused: AtomicU32::new(0),
            watchers: AtomicU32::new(0),
            protocol_errors: AtomicU32::new(0),
        }
    }
}

impl Default for WebCounters {
    fn default() -> Self {
        Self::new()
    }
}

/// A copy of what the controlling client is sent, for the watchers, and the order in which
/// they watch. Put it in a `static` and give it to the server ([`TcpServer::with_mirror`]).
pub struct Mirror {
    state: Mutex<CriticalSectionRawMutex, RefCell<MirrorState>>,
}

struct MirrorState {
    ring: [u8; MIRROR_LEN],
    /// Bytes pushed so far (wrapping): the next byte goes to `ring[written % MIRROR_LEN]`.
    written: u32,
    /// Each watcher's ticket (0: a free place); the smallest watched longest.
    tickets: [u32; MAX_WATCHERS],
    next_ticket: u32,
}

impl Mirror {
    /// Empty, nobody watching.
    pub const fn new() -> Self {
        Self {
            state: Mutex::new(RefCell::new(MirrorState {
                ring: [0; MIRROR_LEN],
                written: 0,
                tickets: [0; MAX_WATCHERS],
                next_ticket: 1,
            })),
        }
    }

    fn with<R>(&self, f: impl FnOnce(&mut MirrorState) -> R) -> R {
        self.state.lock(|s| f(&mut s.borrow_mut()))
    }

    /// Copy `bytes` (sent to the controlling client) for the watchers.
    pub(crate) fn push(&self, bytes: &[u8]) {
        self.with(|s| {
            for &b in bytes {
                if let Some(slot) = s.ring.get_mut(s.written as usize % MIRROR_LEN) {
                    *slot = b;
                }
                s.written = s.written.wrapping_add(1);
            }
        });
    }

    /// Where a new watcher starts reading: what comes next.
    fn position(&self) -> u32 {
        self.with(|s| s.written)
    }

    /// Copy what was pushed since `pos` into `out` and move `pos` on; how many bytes. A
    /// reader more than [`MIRROR_LEN`] bytes behind skips to the first line still whole.
    fn read(&self, pos: &mut u32, out: &mut [u8]) -> usize {
        self.with(|s| {
            let behind = s.written.wrapping_sub(*pos) as usize;
            if behind > MIRROR_LEN {
                *pos = s.written.wrapping_sub(MIRROR_LEN as u32);
                while *pos != s.written {
                    let b = s.ring.get(*pos as usize % MIRROR_LEN).copied();
                    *pos = pos.wrapping_add(1);
                    if b == Some(b'\n') {
                        break;
                    }
                }
            }
            let mut n = 0;
            for slot in out.iter_mut() {
                if *pos == s.written {
                    break;
                }
                *slot = s.ring.get(*pos as usize % MIRROR_LEN).copied().unwrap_or(0);
                *pos = pos.wrapping_add(1);
                n += 1;
            }
            n
        })
    }

    /// A new watcher: its place, or `None` when [`MAX_WATCHERS`] watch already.
    fn join(&self) -> Option<usize> {
        self.with(|s| {
            let place = s.tickets.iter().position(|&t| t == 0)?;
            let ticket = s.next_ticket;
            s.next_ticket = s.next_ticket.wrapping_add(1).max(1);
            if let Some(t) = s.tickets.get_mut(place) {
                *t = ticket;
            }
            Some(place)
        })
    }

    /// The watcher at `place` stops watching.
    fn leave(&self, place: usize) {
        self.with(|s| {
            if let Some(t) = s.tickets.get_mut(place) {
                *t = 0;
            }
        });
    }

    /// Whether any client watches.
    fn has_watchers(&self) -> bool {
        self.with(|s| s.tickets.iter().any(|&t| t != 0))
    }

    /// Whether the watcher at `place` has watched longest.
    fn is_first(&self, place: usize) -> bool {
        self.with(|s| {
            let mine = s.tickets.get(place).copied().unwrap_or(0);
            let age = |t: u32| t.wrapping_sub(s.next_ticket);
            mine != 0 && s.tickets.iter().all(|&t| t == 0 || age(t) >= age(mine))
        })
    }
}

impl Default for Mirror {
    fn default() -> Self {
        Self::new()
    }
}

/// The WebSocket framing of the link's bytes (see [`Framing`]).
pub(crate) struct WsFraming<'c> {
    decoder: Decoder,
    counters: &'c WebCounters,
}

impl<'c> WsFraming<'c> {
    pub(crate) const fn new(counters: &'c WebCounters) -> Self {
        Self {
            decoder: Decoder::new(MAX_MESSAGE_LEN),
            counters,
        }
    }
}

/// Queue a close frame of `code` in `reply`.
fn close_into(reply: &mut Reply, code: u16, reason: &str) {
    let mut frame = [0u8; 2 + MAX_CONTROL];
    let n = websocket::write_close(&mut frame, code, reason).unwrap_or(0);
    reply.push(frame.get(..n).unwrap_or_default());
}

impl Framing for WsFraming<'_> {
    fn receive(&mut self, raw: &[u8], data: &mut [u8], reply: &mut Reply) -> Result<usize, ()> {
        let mut n = 0;
        let mut closed = false;
        let fed = self.decoder.feed_all(raw, |event| match event {
            Event::Data(bytes) => {
                if let Some(slot) = data.get_mut(n..n + bytes.len()) {
                    slot.copy_from_slice(bytes);
                    n += bytes.len();
                }
            }
            Event::Ping(payload) => {
                let mut pong = [0u8; 2 + MAX_CONTROL];
                let len = websocket::write_frame(&mut pong, Opcode::Pong, payload).unwrap_or(0);
                reply.push(pong.get(..len).unwrap_or_default());
            }
            Event::Pong(_) => {}
            Event::Close { code, .. } => {
                closed = true;
                close_into(reply, code.unwrap_or(close_code::NORMAL), "");
            }
        });
        if let Err(e) = fed {
            bump(&self.counters.protocol_errors, 1);
            close_into(reply, e.close_code(), e.reason());
            return Err(());
        }
        if closed { Err(()) } else { Ok(n) }
    }

    fn frame(&mut self, payload: &mut [u8], header: &mut [u8; MAX_HEADER]) -> (usize, usize) {
        let ready = websocket::text_ready(payload, false);
        if ready == 0 {
            return (0, 0);
        }
        let h = websocket::write_header(header, Opcode::Text, ready).unwrap_or(0);
        (h, ready)
    }
}

/// Send `text` to a WebSocket client as one text frame. Errors: the connection is gone.
async fn send_text<S: embedded_io_async::Write>(socket: &mut S, text: &[u8]) -> Result<(), ()> {
    let mut header = [0u8; MAX_HEADER];
    let h = websocket::write_header(&mut header, Opcode::Text, text.len()).map_err(|_| ())?;
    send(socket, header.get(..h).unwrap_or_default()).await?;
    send(socket, text).await
}

/// How a watcher's watch ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Watched {
    /// It left (closed, broke the protocol, its connection failed).
    Left,
    /// It took control.
    Control,
}

/// Read a request head into `head` until it parses: `Ok((head_len, received))`, or the
/// refusal. Errors (outer): the connection closed or failed first.
async fn read_head<S: embedded_io_async::Read>(
    socket: &mut S,
    head: &mut [u8; MAX_HEAD_LEN],
) -> Result<Result<(usize, usize), RequestError>, ()> {
    let mut len = 0;
    loop {
        let room = head.get_mut(len..).unwrap_or_default();
        match socket.read(room).await {
            Ok(0) | Err(_) => return Err(()),
            Ok(n) => len += n,
        }
        match http::parse(head.get(..len).unwrap_or_default()) {
            Ok(Parsed::Partial) => {}
            Ok(Parsed::Complete { head_len, .. }) => return Ok(Ok((head_len, len))),
            Err(e) => return Ok(Err(e)),
        }
    }
}

impl<A: Admission, const RX: usize, const TX: usize> TcpServer<A, RX, TX> {
    /// Serve one listening socket of the web page on `port` of `stack` for ever: each
    /// connection is answered and closed, or becomes a WebSocket that controls or watches (see
    /// the [module documentation](self)). A watcher that sends is answered with what `refusal`
    /// writes into a buffer of `R` bytes (the application's `busy_refusal`). Counted in
    /// `counters`.
    ///
    /// Context: a task. Give each stack enough of them for the page's connections: a
    /// WebSocket holds its task, and a page loads its assets on others (three: one
    /// controlling page, one watcher, one loading). Never returns.
    pub async fn listen_web<const R: usize>(
        &self,
        stack: Stack<'_>,
        port: u16,
        counters: &WebCounters,
        refusal: fn(&mut [u8; R]) -> usize,
    ) -> ! {
        accept_forever(stack, port, Some(KEEP_ALIVE), async |socket| {
            self.serve_web(socket, counters, refusal).await;
        })
        .await
    }

    /// Serve one web connection until it is answered, or until its WebSocket ends.
    pub(crate) async fn serve_web<S, const R: usize>(
        &self,
        socket: &mut S,
        counters: &WebCounters,
        refusal: fn(&mut [u8; R]) -> usize,
    ) where
        S: embedded_io_async::Read + embedded_io_async::Write,
    {
        let mut head = [0u8; MAX_HEAD_LEN];
        let Ok(Ok(read)) = with_timeout(HTTP_TIMEOUT, read_head(socket, &mut head)).await else {
            return;
        };
        let (route, initial) = match read {
            Ok((head_len, len)) => match http::parse(head.get(..len).unwrap_or_default()) {
                Ok(Parsed::Complete { request, .. }) => {
                    (request.route(), head.get(head_len..len).unwrap_or_default())
                }
                Ok(Parsed::Partial) => return,
                Err(e) => (Route::Refuse(e), &[][..]),
            },
            Err(e) => (Route::Refuse(e), &[][..]),
        };
        let mut out = [0u8; 256];
        match route {
            Route::Refuse(e) => {
                bump(&counters.refused, 1);
                let n = http::write_error(&mut out, e).unwrap_or(0);
                let _ = with_timeout(HTTP_TIMEOUT, send(socket, out.get(..n).unwrap_or_default()))
                    .await;
            }
            Route::Asset { asset, body } => {
                bump(&counters.served, 1);
                let n = http::write_asset_head(&mut out, asset).unwrap_or(0);
                let _ = with_timeout(HTTP_TIMEOUT, async {
                    send(socket, out.get(..n).unwrap_or_default()).await?;
                    if body {
                        send(socket, asset.gzip).await?;
                    }
                    Ok::<(), ()>(())
                })
                .await;
            }
            Route::WebSocket { key } => {
                let n = http::write_switching_protocols(&mut out, key).unwrap_or(0);
                if send(socket, out.get(..n).unwrap_or_default()).await.is_ok() {
                    self.serve_websocket(socket, counters, initial, refusal)
                        .await;
                }
            }
        }
    }

    /// A WebSocket: the controlling client or a watcher, as the session rules decide.
    async fn serve_websocket<S, const R: usize>(
        &self,
        socket: &mut S,
        counters: &WebCounters,
        initial: &[u8],
        refusal: fn(&mut [u8; R]) -> usize,
    ) where
        S: embedded_io_async::Read + embedded_io_async::Write,
    {
        let mut framing = WsFraming::new(counters);
        let mut reply = Reply::new();
        if initial.len() > CHUNK {
            close_into(
                &mut reply,
                close_code::POLICY,
                "frames before the handshake",
            );
            let _ = send(socket, reply.bytes()).await;
            return;
        }
        // While pages watch, control is theirs to take first: a new page joins them.
        let watched = self.mirror.is_some_and(Mirror::has_watchers);
        let role = if !watched && self.connect(now_ms()) == Admit::Control {
            Watched::Control
        } else {
            let mut busy = [0u8; R];
            let len = refusal(&mut busy);
            let busy = busy.get(..len).unwrap_or_default();
            match self.mirror.map(|m| (m, m.join())) {
                Some((mirror, Some(place))) => {
                    bump(&counters.watchers, 1);
                    let watched = match send_text(socket, WATCHING_NOTICE).await {
                        Ok(()) => self.watch(socket, &mut framing, mirror, place, busy).await,
                        Err(()) => Watched::Left,
                    };
                    mirror.leave(place);
                    watched
                }
                // No mirror, or enough watchers: refused as a raw client is.
                _ => {
                    bump(&self.counters().refused, 1);
                    let _ = send_text(socket, busy).await;
                    close_into(&mut reply, close_code::POLICY, "another client controls");
                    let _ = send(socket, reply.bytes()).await;
                    Watched::Left
                }
            }
        };
        if role == Watched::Control {
            if send_text(socket, CONTROL_NOTICE).await.is_ok() {
                self.serve(socket, &mut framing, initial).await;
            }
            self.disconnect();
        }
    }

    /// Watch: the mirror to the client, its input refused with `busy`, until it leaves or
    /// takes control (when nobody has it and it has watched longest).
    async fn watch<S>(
        &self,
        socket: &mut S,
        framing: &mut WsFraming<'_>,
        mirror: &Mirror,
        place: usize,
        busy: &[u8],
    ) -> Watched
    where
        S: embedded_io_async::Read + embedded_io_async::Write,
    {
        let mut pos = mirror.position();
        let mut raw = [0u8; CHUNK];
        let mut data = [0u8; CHUNK];
        let mut out = [0u8; MAX_HEADER + CHUNK];
        let mut carry = 0usize;
        loop {
            if let Either::First(read) =
                select(socket.read(&mut raw), Timer::after(WATCH_POLL)).await
            {
                let Ok(n) = read
                    .map_err(drop)
                    .and_then(|n| if n == 0 { Err(()) } else { Ok(n) })
                else {
                    return Watched::Left;
                };
                let mut reply = Reply::new();
                let got = framing.receive(raw.get(..n).unwrap_or_default(), &mut data, &mut reply);
                if got.is_ok_and(|n| n > 0) && send_text(socket, busy).await.is_err() {
                    return Watched::Left;
                }
                if send(socket, reply.bytes()).await.is_err() || got.is_err() {
                    return Watched::Left;
                }
            }
            loop {
                let room = out.get_mut(MAX_HEADER + carry..).unwrap_or_default();
                let n = mirror.read(&mut pos, room);
                if n == 0 {
                    break;
                }
                if send_framed(socket, framing, &mut out, &mut carry, n)
                    .await
                    .is_err()
                {
                    return Watched::Left;
                }
            }
            if !self.is_connected()
                && mirror.is_first(place)
                && self.connect(now_ms()) == Admit::Control
            {
                return Watched::Control;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use core::convert::Infallible;
    use core::future::Future;
    use core::pin::Pin;
    use core::sync::atomic::Ordering;
    use core::task::{Context, Poll, Waker};
    use std::cell::RefCell;
    use std::collections::VecDeque;
    use std::rc::Rc;
    use std::time::Instant;
    use std::vec::Vec;

    use embedded_io::{ReadReady as _, Write as _};
    use forja_hal_abstraction::link::{LinkState, LinkStatus as _};

    use super::*;
    use crate::port_link::SingleClient;
    use crate::tcp::TcpQueues;
    use crate::tcp::tests::server;

    /// A server whose watchers read a mirror of their own.
    fn mirrored() -> &'static TcpServer<SingleClient, 64, 1024> {
        let queues = std::boxed::Box::leak(std::boxed::Box::new(TcpQueues::new()));
        let counters = std::boxed::Box::leak(std::boxed::Box::new(crate::tcp::LinkCounters::new()));
        let mirror = std::boxed::Box::leak(std::boxed::Box::new(Mirror::new()));
        std::boxed::Box::leak(std::boxed::Box::new(
            TcpServer::new(queues, counters, SingleClient::new()).with_mirror(mirror),
        ))
    }

    fn counters() -> &'static WebCounters {
        std::boxed::Box::leak(std::boxed::Box::new(WebCounters::new()))
    }

    fn busy(out: &mut [u8; 32]) -> usize {
        let message = b"// E300 link-busy\n";
        out[..message.len()].copy_from_slice(message);
        message.len()
    }

    /// The two ends of a connection: what the client sends, what it received, whether it
    /// closed.
    #[derive(Default)]
    struct Wire {
        to_server: VecDeque<u8>,
        from_server: Vec<u8>,
        closed: bool,
    }

    #[derive(Clone, Default)]
    struct Socket(Rc<RefCell<Wire>>);

    impl Socket {
        fn send(&self, bytes: &[u8]) {
            self.0.borrow_mut().to_server.extend(bytes);
        }
        fn received(&self) -> Vec<u8> {
            self.0.borrow().from_server.clone()
        }
        fn close(&self) {
            self.0.borrow_mut().closed = true;
        }
    }

    impl embedded_io_async::ErrorType for Socket {
        type Error = Infallible;
    }

    impl embedded_io_async::Read for Socket {
        async fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
            core::future::poll_fn(|_| {
                let mut w = self.0.borrow_mut();
                if !w.to_server.is_empty() {
                    let n = buf.len().min(w.to_server.len());
                    for (d, s) in buf.iter_mut().zip(w.to_server.drain(..n)) {
                        *d = s;
                    }
                    Poll::Ready(Ok(n))
                } else if w.closed {
                    Poll::Ready(Ok(0))
                } else {
                    Poll::Pending
                }
            })
            .await
        }
    }

    impl embedded_io_async::Write for Socket {
        async fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
            self.0.borrow_mut().from_server.extend_from_slice(buf);
            Ok(buf.len())
        }

        async fn flush(&mut self) -> Result<(), Self::Error> {
            Ok(())
        }
    }

    /// Poll `task` until it ends or `done` holds (at most five seconds); whether it ended.
    fn run_until<F: Future>(mut task: Pin<&mut F>, mut done: impl FnMut() -> bool) -> bool {
        let mut cx = Context::from_waker(Waker::noop());
        let start = Instant::now();
        loop {
            if task.as_mut().poll(&mut cx).is_ready() {
                return true;
            }
            if done() {
                return false;
            }
            assert!(start.elapsed().as_secs() < 5, "timed out");
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
    }

    /// Read `n` bytes from `link` while `task` runs.
    fn read_while<F: Future>(
        task: Pin<&mut F>,
        link: &mut crate::tcp::TcpLink<'_, SingleClient, 64, 1024>,
        n: usize,
    ) -> Vec<u8> {
        let mut got = Vec::new();
        run_until(task, || {
            let mut buf = [0u8; 16];
            let k = link.try_read(&mut buf);
            got.extend(&buf[..k]);
            got.len() >= n
        });
        got
    }

    /// A masked client frame.
    fn frame(first: u8, payload: &[u8]) -> Vec<u8> {
        let mask = [0x11, 0x22, 0x33, 0x44];
        let mut f = std::vec![first, 0x80 | payload.len() as u8];
        f.extend(mask);
        f.extend(payload.iter().zip(mask.iter().cycle()).map(|(b, m)| b ^ m));
        f
    }

    /// The text of the server's unmasked frames in `bytes` (after the 101's head), and the
    /// close code if one came.
    fn frames(bytes: &[u8]) -> (Vec<u8>, Option<u16>) {
        let head = bytes.windows(4).position(|w| w == b"\r\n\r\n").unwrap() + 4;
        let mut rest = &bytes[head..];
        let (mut text, mut close) = (Vec::new(), None);
        while rest.len() >= 2 {
            let (len, start) = match rest[1] {
                126 => (usize::from(u16::from_be_bytes([rest[2], rest[3]])), 4),
                n => (usize::from(n), 2),
            };
            let payload = &rest[start..start + len];
            match rest[0] {
                0x81 => text.extend(payload),
                0x88 => close = Some(u16::from_be_bytes([payload[0], payload[1]])),
                _ => {}
            }
            rest = &rest[start + len..];
        }
        (text, close)
    }

    const UPGRADE: &[u8] = b"GET /ws HTTP/1.1\r\nHost: forja\r\nUpgrade: websocket\r\n\
        Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\
        Sec-WebSocket-Version: 13\r\n\r\n";

    #[test]
    fn the_mirror_keeps_what_the_controller_is_sent_and_a_laggard_skips_to_a_line() {
        let m = Mirror::new();
        let mut pos = m.position();
        m.push(b"ok\nX:1\n");
        let mut out = [0u8; 4];
        assert_eq!(m.read(&mut pos, &mut out), 4);
        assert_eq!(&out, b"ok\nX");
        assert_eq!(m.read(&mut pos, &mut out), 3);
        assert_eq!(&out[..3], b":1\n");
        assert_eq!(m.read(&mut pos, &mut out), 0);
        let mut late = m.position();
        for _ in 0..300 {
            m.push(b"ok\nX:2\n");
        }
        let mut all = Vec::new();
        let mut buf = [0u8; 100];
        loop {
            let n = m.read(&mut late, &mut buf);
            if n == 0 {
                break;
            }
            all.extend(&buf[..n]);
        }
        assert!(all.len() < MIRROR_LEN);
        assert!(
            all.starts_with(b"ok\n") || all.starts_with(b"X:2\n"),
            "a whole line first"
        );
        assert!(all.ends_with(b"ok\nX:2\n"));
    }

    #[test]
    fn watchers_take_control_in_the_order_they_came() {
        let m = Mirror::new();
        let places: Vec<_> = (0..MAX_WATCHERS).map(|_| m.join().unwrap()).collect();
        assert_eq!(m.join(), None, "no more room");
        assert!(m.is_first(places[0]));
        assert!(!m.is_first(places[1]));
        m.leave(places[0]);
        assert!(m.is_first(places[1]));
        let again = m.join().unwrap();
        assert_eq!(again, places[0], "the free place is taken again");
        assert!(!m.is_first(again), "the newcomer waits behind the others");
    }

    #[test]
    fn the_page_is_served_and_the_rest_refused() {
        let s = server::<64, 1024>();
        let c = counters();
        let cases: [(&[u8], &str); 4] = [
            (b"GET / HTTP/1.1\r\n\r\n", "HTTP/1.1 200 OK\r\n"),
            (b"GET /nothing HTTP/1.1\r\n\r\n", "HTTP/1.1 404 "),
            (
                b"POST /job HTTP/1.1\r\nContent-Length: 4\r\n\r\n\x00\x01\x02\x03",
                "HTTP/1.1 405 ",
            ),
            (b"\x00\x01\x02garbage\r\n\r\n", "HTTP/1.1 400 "),
        ];
        for (request, status) in cases {
            let socket = Socket::default();
            socket.send(request);
            let mut end = socket.clone();
            embassy_futures::block_on(s.serve_web(&mut end, c, busy));
            let answer = socket.received();
            assert!(answer.starts_with(status.as_bytes()), "{request:?}");
            if status.contains("200") {
                assert!(answer.ends_with(forja_web::asset("/").unwrap().gzip));
            }
        }
        assert_eq!(c.served.load(Ordering::Relaxed), 1);
        assert_eq!(c.refused.load(Ordering::Relaxed), 3);
        assert!(
            s.take().unwrap().try_read(&mut [0u8; 8]) == 0,
            "nothing queued"
        );
    }

    #[test]
    fn a_page_in_control_speaks_the_link_through_frames() {
        let s = mirrored();
        let mut link = s.take().unwrap();
        let c = counters();
        let socket = Socket::default();
        socket.send(UPGRADE);
        socket.send(&frame(0x81, b"M105\n"));
        socket.send(&frame(0x89, b"hi"));
        let mut end = socket.clone();
        let mut task = core::pin::pin!(s.serve_web(&mut end, c, busy));
        let got = read_while(task.as_mut(), &mut link, 5);
        assert_eq!(got, b"M105\n");
        assert!(link.take_greeting(), "admitted as the controller");
        link.write_all(b"ok T:20.0 /0.0\n").unwrap();
        run_until(task.as_mut(), || {
            frames(&socket.received()).0.ends_with(b"/0.0\n")
        });
        let (text, _) = frames(&socket.received());
        let mut expect = CONTROL_NOTICE.to_vec();
        expect.extend(b"ok T:20.0 /0.0\n");
        assert_eq!(text, expect);
        assert!(
            socket
                .received()
                .windows(4)
                .any(|w| w == [0x8A, 2, b'h', b'i']),
            "the ping was answered"
        );
        // A malformed frame: closed with 1002, nothing of it queued.
        socket.send(b"\x81\x04G28\n");
        assert!(run_until(task.as_mut(), || false), "the connection ends");
        assert_eq!(frames(&socket.received()).1, Some(1002));
        assert!(!link.read_ready().unwrap());
        assert_eq!(link.state(), LinkState::Disconnected);
        assert_eq!(c.protocol_errors.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn a_page_that_comes_while_others_watch_joins_them() {
        let s = mirrored();
        let link = s.take().unwrap();
        let waiting = s.mirror.unwrap().join().unwrap();
        let socket = Socket::default();
        socket.send(UPGRADE);
        let mut end = socket.clone();
        let c = counters();
        let mut task = core::pin::pin!(s.serve_web(&mut end, c, busy));
        run_until(task.as_mut(), || {
            frames(&socket.received()).0 == WATCHING_NOTICE
        });
        assert_eq!(link.state(), LinkState::Disconnected, "nobody took control");
        s.mirror.unwrap().leave(waiting);
        run_until(task.as_mut(), || {
            frames(&socket.received()).0.ends_with(CONTROL_NOTICE)
        });
        assert_eq!(link.state(), LinkState::Connected);
    }

    #[test]
    fn a_second_page_watches_is_refused_and_takes_over() {
        let s = mirrored();
        let mut link = s.take().unwrap();
        let c = counters();
        // A raw TCP client controls the machine.
        assert_eq!(s.connect(0), Admit::Control);
        let socket = Socket::default();
        socket.send(UPGRADE);
        let mut end = socket.clone();
        let mut task = core::pin::pin!(s.serve_web(&mut end, c, busy));
        run_until(task.as_mut(), || {
            frames(&socket.received()).0 == WATCHING_NOTICE
        });
        assert_eq!(c.watchers.load(Ordering::Relaxed), 1);

        // What the controller is sent reaches the watcher through the mirror: the raw
        // client's serving task copies it there as it sends it.
        link.write_all(b"ok\n").unwrap();
        let tcp_client = Socket::default();
        let mut tcp_end = tcp_client.clone();
        let mut raw = crate::tcp::Raw;
        {
            let mut tcp_task = core::pin::pin!(s.serve(&mut tcp_end, &mut raw, b"G0\n"));
            run_until(tcp_task.as_mut(), || tcp_client.received() == b"ok\n");
        }
        let mut own = [0u8; 8];
        assert_eq!(link.try_read(&mut own), 3, "the controller's own input");
        run_until(task.as_mut(), || {
            frames(&socket.received()).0.ends_with(b"ok\n")
        });
        assert_eq!(
            frames(&socket.received()).0,
            [WATCHING_NOTICE, b"ok\n"].concat()
        );

        // The watcher's lines are refused, never queued.
        socket.send(&frame(0x81, b"G1 X100\n"));
        run_until(task.as_mut(), || {
            frames(&socket.received())
                .0
                .ends_with(b"// E300 link-busy\n")
        });
        assert_eq!(link.try_read(&mut own), 0);

        // The controller leaves: the watcher takes control.
        s.disconnect();
        run_until(task.as_mut(), || {
            frames(&socket.received()).0.ends_with(CONTROL_NOTICE)
        });
        assert!(link.take_greeting());
        socket.send(&frame(0x81, b"M114\n"));
        let got = read_while(task.as_mut(), &mut link, 5);
        assert_eq!(got, b"M114\n");
        socket.close();
        assert!(run_until(task.as_mut(), || false));
        assert_eq!(link.state(), LinkState::Disconnected);
    }
}
