//! The web link: an HTTP listener that serves the operator's page (`forja-web`'s assets) and
//! carries the link's protocols over a WebSocket at `/ws`, like the ESP32 board's web server.

use std::cell::RefCell;
use std::collections::VecDeque;
use std::io::{self, Read as _, Write as _};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::rc::Rc;
use std::time::{Duration, Instant};

use forja_drivers::port_link::{Admission, Admit};
use forja_hal_abstraction::link::{LinkState, LinkStatus};
use forja_web::http::{self, MAX_HEAD_LEN, Parsed, RequestError, Route};
use forja_web::websocket::{
    self, CONTROL_NOTICE, Decoder, Event, MAX_MESSAGE_LEN, Opcode, WATCHING_NOTICE, close_code,
};

use super::{BufferedPort, Buffers, PortLink, TX_CAPACITY, buffered_link};

/// Most connections [`WebLink`] holds that have not become WebSockets (reading a request,
/// sending an answer); one more is closed at once.
pub const MAX_HTTP: usize = 16;

/// Most watchers at once; one more is closed with 1008 (policy).
pub const MAX_WATCHERS: usize = 8;

/// A connection that has not sent its request head, or has not taken its answer, by then is
/// closed (wall-clock time: sockets are real).
pub const HTTP_TIMEOUT: Duration = Duration::from_secs(10);

/// Framed bytes a client may leave unsent before the link stops framing more for it: past
/// that a controller's replies wait in the transmit buffer (and a controller that lets
/// [`TX_CAPACITY`] of them back up is dropped), a watcher is dropped.
const OUTBOUND_HIGH: usize = 16 * 1024;

/// Undecoded bytes held per client: the socket is not read past that, so a client that sends
/// faster than the controller reads is held back by TCP flow control.
const INBOUND_MAX: usize = 8 * 1024;

/// Bytes a link of the board sends its controlling host, copied for the web link's watchers
/// ([`WebLink::tap`], [`Tapped`]): a page watches a machine that a sender on the TCP port
/// controls.
#[derive(Debug, Clone, Default)]
pub struct Tap(Rc<RefCell<VecDeque<u8>>>);

impl Tap {
    fn push(&self, bytes: &[u8]) {
        let mut q = self.0.borrow_mut();
        if q.len() + bytes.len() <= TX_CAPACITY {
            q.extend(bytes);
        }
    }

    fn take(&self) -> Vec<u8> {
        self.0.borrow_mut().drain(..).collect()
    }
}

/// A link whose writes (what its controlling host is sent) are copied into a [`Tap`]: give it
/// the [`WebLink::tap`] of the board's web link. Reads, state and sessions are the wrapped
/// link's. Wrap a link whose writes go only to its controlling host (a [`super::TcpLink`]: it
/// refuses a second client on its own socket, not through its writes).
#[derive(Debug)]
pub struct Tapped<L> {
    link: L,
    tap: Tap,
}

impl<L: PortLink> Tapped<L> {
    /// Copy what `link` sends its host into `tap`.
    pub fn new(link: L, tap: Tap) -> Self {
        Self { link, tap }
    }

    /// The wrapped link.
    pub fn inner(&self) -> &L {
        &self.link
    }
}

impl<L: PortLink> embedded_io::ErrorType for Tapped<L> {
    type Error = L::Error;
}

impl<L: PortLink> embedded_io::Read for Tapped<L> {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        self.link.read(buf)
    }
}

impl<L: PortLink> embedded_io::ReadReady for Tapped<L> {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        self.link.read_ready()
    }
}

impl<L: PortLink> embedded_io::Write for Tapped<L> {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        if self.link.state() == LinkState::Connected {
            self.tap.push(buf);
        }
        self.link.write(buf)
    }
    fn flush(&mut self) -> Result<(), Self::Error> {
        self.link.flush()
    }
}

impl<L: PortLink + embedded_io::WriteReady> embedded_io::WriteReady for Tapped<L> {
    fn write_ready(&mut self) -> Result<bool, Self::Error> {
        self.link.write_ready()
    }
}

impl<L: PortLink> LinkStatus for Tapped<L> {
    fn state(&self) -> LinkState {
        self.link.state()
    }
}

impl<L: PortLink> PortLink for Tapped<L> {
    fn poll(&mut self) -> Result<(), Self::Error> {
        self.link.poll()
    }
    fn connections(&self) -> u64 {
        self.link.connections()
    }
    fn admit(&mut self, gate: &mut dyn Admission, now_ms: u32) -> Result<bool, Self::Error> {
        self.link.admit(gate, now_ms)
    }
    fn discard_input(&mut self) -> Result<usize, Self::Error> {
        self.link.discard_input()
    }
    fn hang_up(&mut self) {
        self.link.hang_up();
    }
}

/// A connection that has not become a WebSocket: reading its request head.
#[derive(Debug)]
struct HttpConn {
    stream: TcpStream,
    head: Vec<u8>,
    since: Instant,
}

/// A connection being closed: what it is still to be sent, then an orderly close (its input
/// read and dropped until it closes too, so that it gets a FIN rather than a reset).
#[derive(Debug)]
struct Leaving {
    stream: TcpStream,
    out: VecDeque<u8>,
    shut: bool,
    since: Instant,
}

/// A WebSocket client: the controller, or a watcher.
#[derive(Debug)]
struct Peer {
    stream: TcpStream,
    decoder: Decoder,
    /// Received bytes not decoded yet.
    inbound: Vec<u8>,
    /// Framed bytes not sent yet.
    outbound: VecDeque<u8>,
    /// A close frame is queued (the client's close echoed, or a protocol error answered), or
    /// the connection failed: the peer is to leave.
    leaving: bool,
}

impl Peer {
    fn new(stream: TcpStream, inbound: Vec<u8>) -> Self {
        Self {
            stream,
            decoder: Decoder::new(MAX_MESSAGE_LEN),
            inbound,
            outbound: VecDeque::new(),
            leaving: false,
        }
    }

    /// Queue one server frame.
    fn frame(&mut self, opcode: Opcode, payload: &[u8]) {
        let mut header = [0u8; websocket::MAX_HEADER];
        let n = websocket::write_header(&mut header, opcode, payload.len()).unwrap_or(0);
        self.outbound.extend(header.get(..n).unwrap_or_default());
        self.outbound.extend(payload);
    }

    /// Queue a close frame and leave.
    fn close(&mut self, code: u16, reason: &str) {
        let mut frame = [0u8; 2 + websocket::MAX_CONTROL];
        let n = websocket::write_close(&mut frame, code, reason).unwrap_or(0);
        self.outbound.extend(frame.get(..n).unwrap_or_default());
        self.leaving = true;
    }

    /// Read what the socket has, as room allows. A closed or failed connection leaves.
    fn receive(&mut self) {
        let mut chunk = [0u8; 4096];
        while !self.leaving && self.inbound.len() < INBOUND_MAX {
            let room = (INBOUND_MAX - self.inbound.len()).min(chunk.len());
            match self.stream.read(chunk.get_mut(..room).unwrap_or_default()) {
                Ok(0) => self.leaving = true,
                Ok(n) => self.inbound.extend(chunk.get(..n).unwrap_or_default()),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(_) => self.leaving = true,
            }
        }
    }

    /// Decode the received frames while `room` takes a whole data piece: data bytes go to
    /// `data` (`None`: dropped), pings are answered, a close is echoed, a protocol error is
    /// answered with its close code. Returns the data bytes decoded.
    fn decode(&mut self, mut room: usize, mut data: Option<&mut VecDeque<u8>>) -> usize {
        let mut used = 0;
        let mut decoded = 0;
        while !self.leaving && room >= websocket::CHUNK {
            let window = self.inbound.get(used..).unwrap_or_default();
            if window.is_empty() {
                break;
            }
            let before = window.len();
            match self.decoder.feed(window) {
                Ok(fed) => {
                    used += before - fed.remaining.len();
                    match fed.event {
                        None => break,
                        Some(Event::Data(bytes)) => {
                            decoded += bytes.len();
                            room -= bytes.len();
                            if let Some(rx) = data.as_deref_mut() {
                                rx.extend(bytes);
                            }
                        }
                        Some(Event::Ping(payload)) => {
                            let payload = payload.to_vec();
                            self.frame(Opcode::Pong, &payload);
                        }
                        Some(Event::Pong(_)) => {}
                        Some(Event::Close { code, .. }) => {
                            self.close(code.unwrap_or(close_code::NORMAL), "");
                        }
                    }
                }
                Err(e) => {
                    self.close(e.close_code(), e.reason());
                    used = self.inbound.len();
                }
            }
        }
        self.inbound.drain(..used.min(self.inbound.len()));
        decoded
    }

    /// Send what is queued, as the socket takes it. A failed connection leaves.
    fn send(&mut self) {
        while !self.outbound.is_empty() {
            let pending = self.outbound.make_contiguous();
            match self.stream.write(pending) {
                Ok(0) => {
                    self.leaving = true;
                    self.outbound.clear();
                }
                Ok(n) => {
                    self.outbound.drain(..n);
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(_) => {
                    self.leaving = true;
                    self.outbound.clear();
                }
            }
        }
    }
}

/// Counters of a [`WebLink`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct WebStats {
    /// Assets served (200).
    pub served: u64,
    /// Requests refused (404, 400, 405, …).
    pub refused_requests: u64,
    /// WebSocket clients that became watchers.
    pub watchers: u64,
    /// WebSocket clients closed for a protocol error (a malformed frame, a message too long).
    pub protocol_errors: u64,
    /// Controlling clients dropped because their replies backed up past [`TX_CAPACITY`]
    /// bytes, and watchers dropped for not reading.
    pub overflows: u64,
}

/// An HTTP listener that serves the operator's page and carries the link over a WebSocket,
/// with one controlling client at a time and any number (up to [`MAX_WATCHERS`]) of watchers.
///
/// - `GET` (or `HEAD`) of a path of `forja_web::ASSETS` (`/` is the page) is answered with the
///   asset's gzip bytes; any other request with its refusal (`forja_web::http`: 404, 400,
///   405, 413, …); the connection is then closed.
/// - `GET /ws` with a valid WebSocket handshake becomes a WebSocket. At the next
///   [`PortLink::admit`] the port's session rules ([`Admission`]) decide: [`Admit::Control`]
///   makes it the controlling client, sent [`CONTROL_NOTICE`] first; [`Admit::Refuse`] (a
///   client is in control, on this port or another port of the board) makes it a watcher,
///   sent [`WATCHING_NOTICE`].
/// - The controlling client's text and binary payload bytes are the link's input; what the
///   controller writes is sent to it as text frames ([`websocket::text_ready`] keeps them
///   UTF-8), and copied to every watcher, with what the board's other links send their
///   controlling host through the [`Tap`] ([`WebLink::tap`]).
/// - A watcher's payload bytes never reach the controller: each batch is answered with the
///   busy message (the controller's busy refusal). Pings are answered with pongs.
/// - When the controlling client leaves (closes, breaks the protocol, is dropped for not
///   reading, or is hung up on for its silence: a close frame 1000), the session hears of it
///   at the next `admit`, and the watcher that has watched longest is offered control there
///   (sent [`CONTROL_NOTICE`] if the rules admit it). A client that arrives meanwhile waits
///   behind the watchers.
/// - A malformed frame is answered with a close frame of its code (1002, 1009) and the
///   connection is closed; nothing of that frame reaches the controller.
///
/// Nothing waits for a client, as on [`super::TcpLink`]. Implements [`PortLink`].
#[derive(Debug)]
pub struct WebLink {
    listener: TcpListener,
    http: Vec<HttpConn>,
    /// WebSockets whose handshake is done, waiting for the session rules.
    upgraded: VecDeque<Peer>,
    controller: Option<Peer>,
    watchers: VecDeque<Peer>,
    leaving: Vec<Leaving>,
    bufs: Buffers,
    busy_message: Vec<u8>,
    tap: Tap,
    connections: u64,
    stats: WebStats,
    /// The controlling client went away and the session was not told yet.
    closed: bool,
}

impl WebLink {
    /// Listen on `addr` (port 0: any free port; see [`WebLink::local_addr`]). A watcher that
    /// sends is answered with `busy_message`.
    ///
    /// Errors: the address cannot be bound (in use, not local, no permission).
    pub fn bind(addr: SocketAddr, busy_message: impl Into<Vec<u8>>) -> io::Result<Self> {
        let listener = TcpListener::bind(addr)?;
        listener.set_nonblocking(true)?;
        Ok(Self {
            listener,
            http: Vec::new(),
            upgraded: VecDeque::new(),
            controller: None,
            watchers: VecDeque::new(),
            leaving: Vec::new(),
            bufs: Buffers::default(),
            busy_message: busy_message.into(),
            tap: Tap::default(),
            connections: 0,
            stats: WebStats::default(),
            closed: false,
        })
    }

    /// The address actually listened on (with the port chosen when bound to port 0).
    ///
    /// Errors: as `TcpListener::local_addr` (practically never).
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// Where another link of the board copies what it sends its controlling host, for this
    /// link's watchers: wrap that link in a [`Tapped`] with it.
    pub fn tap(&self) -> Tap {
        self.tap.clone()
    }

    /// What the link has done.
    pub fn stats(&self) -> WebStats {
        self.stats
    }

    /// Watchers connected now.
    pub fn watching(&self) -> usize {
        self.watchers.len()
    }

    /// Close the controlling client's WebSocket with close code `code`; the session hears of
    /// it at the next [`PortLink::admit`].
    fn disconnect(&mut self, code: Option<(u16, &str)>) {
        if let Some(mut peer) = self.controller.take() {
            if let Some((code, reason)) = code {
                peer.close(code, reason);
            }
            self.leave(peer);
            self.closed = true;
        }
        self.bufs.tx.clear();
    }

    /// Let `peer` go: what it was still to be sent, then an orderly close.
    fn leave(&mut self, peer: Peer) {
        if peer.decoder.error().is_some() {
            self.stats.protocol_errors += 1;
        }
        self.leaving.push(Leaving {
            stream: peer.stream,
            out: peer.outbound,
            shut: false,
            since: Instant::now(),
        });
    }

    /// Accept the connections waiting on the listener.
    fn accept(&mut self) {
        for _ in 0..MAX_HTTP {
            match self.listener.accept() {
                Ok((stream, _)) => {
                    if self.http.len() >= MAX_HTTP || stream.set_nonblocking(true).is_err() {
                        continue;
                    }
                    let _ = stream.set_nodelay(true);
                    self.http.push(HttpConn {
                        stream,
                        head: Vec::new(),
                        since: Instant::now(),
                    });
                }
                Err(_) => return,
            }
        }
    }

    /// Read the request heads and answer the complete ones.
    fn serve_http(&mut self) {
        let mut i = 0;
        while let Some(conn) = self.http.get_mut(i) {
            let mut chunk = [0u8; 1024];
            let mut gone = conn.since.elapsed() >= HTTP_TIMEOUT;
            while !gone && conn.head.len() < MAX_HEAD_LEN {
                let room = (MAX_HEAD_LEN - conn.head.len()).min(chunk.len());
                match conn.stream.read(chunk.get_mut(..room).unwrap_or_default()) {
                    Ok(0) => gone = true,
                    Ok(n) => conn.head.extend(chunk.get(..n).unwrap_or_default()),
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                    Err(_) => gone = true,
                }
            }
            let parsed = http::parse(&conn.head).map(|p| match p {
                Parsed::Partial => None,
                Parsed::Complete { request, head_len } => Some(answer(&request, head_len)),
            });
            match parsed {
                Ok(None) if !gone => i += 1,
                Ok(None) => {
                    self.http.swap_remove(i);
                }
                Ok(Some(Answer::Upgrade { reply, head_len })) => {
                    let conn = self.http.swap_remove(i);
                    let rest = conn.head.get(head_len..).unwrap_or_default().to_vec();
                    let mut peer = Peer::new(conn.stream, rest);
                    peer.outbound.extend(reply);
                    self.upgraded.push_back(peer);
                }
                Ok(Some(Answer::Asset(out))) => {
                    self.stats.served += 1;
                    self.answer_and_close(i, out);
                }
                Ok(Some(Answer::Refuse(e))) | Err(e) => {
                    self.stats.refused_requests += 1;
                    let mut out = [0u8; 256];
                    let n = http::write_error(&mut out, e).unwrap_or(0);
                    self.answer_and_close(i, out.get(..n).unwrap_or_default().to_vec());
                }
            }
        }
    }

    fn answer_and_close(&mut self, i: usize, out: Vec<u8>) {
        let conn = self.http.swap_remove(i);
        self.leaving.push(Leaving {
            stream: conn.stream,
            out: out.into(),
            shut: false,
            since: Instant::now(),
        });
    }

    /// Send and close the connections that are leaving.
    fn serve_leaving(&mut self) {
        self.leaving.retain_mut(|l| {
            if l.since.elapsed() >= HTTP_TIMEOUT {
                let _ = l.stream.shutdown(Shutdown::Both);
                return false;
            }
            while !l.out.is_empty() {
                match l.stream.write(l.out.make_contiguous()) {
                    Ok(0) => return false,
                    Ok(n) => {
                        l.out.drain(..n);
                    }
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => return true,
                    Err(_) => return false,
                }
            }
            if !l.shut {
                l.shut = true;
                let _ = l.stream.shutdown(Shutdown::Write);
            }
            let mut sink = [0u8; 1024];
            loop {
                match l.stream.read(&mut sink) {
                    Ok(0) => return false,
                    Ok(_) => {}
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => return true,
                    Err(_) => return false,
                }
            }
        });
    }

    /// The controlling client's input into the receive buffer, as it has room.
    fn receive(&mut self) {
        let room = self.bufs.rx_room();
        let Some(peer) = self.controller.as_mut() else {
            return;
        };
        peer.receive();
        peer.decode(room, Some(&mut self.bufs.rx));
        if peer.leaving {
            self.disconnect(None);
        }
    }

    /// The controller's replies to its client, and copies to the watchers, as text frames.
    fn send(&mut self) {
        if let Some(peer) = self.controller.as_mut() {
            if peer.outbound.len() < OUTBOUND_HIGH && !self.bufs.tx.is_empty() {
                let ready = websocket::text_ready(self.bufs.tx.make_contiguous(), false);
                let text: Vec<u8> = self.bufs.tx.drain(..ready).collect();
                if !text.is_empty() {
                    peer.frame(Opcode::Text, &text);
                    for w in &mut self.watchers {
                        w.frame(Opcode::Text, &text);
                    }
                }
            }
            peer.send();
            if peer.leaving {
                self.disconnect(None);
            }
        }
        let mut tapped = self.tap.take();
        if !tapped.is_empty() && !self.watchers.is_empty() {
            let n = websocket::text_ready(&mut tapped, true);
            for w in &mut self.watchers {
                w.frame(Opcode::Text, tapped.get(..n).unwrap_or_default());
            }
        }
    }

    /// The watchers: their input refused, their frames sent; those that leave or do not read
    /// are let go.
    fn serve_watchers(&mut self) {
        let mut kept = VecDeque::with_capacity(self.watchers.len());
        while let Some(mut w) = self.watchers.pop_front() {
            w.receive();
            if w.decode(usize::MAX, None) > 0 && !w.leaving {
                w.frame(Opcode::Text, &self.busy_message);
            }
            w.send();
            if w.outbound.len() > TX_CAPACITY {
                self.stats.overflows += 1;
                let _ = w.stream.shutdown(Shutdown::Both);
            } else if w.leaving {
                self.leave(w);
            } else {
                kept.push_back(w);
            }
        }
        self.watchers = kept;
    }

    /// Tell `gate` that the controlling client went away, if it did.
    fn report_close(&mut self, gate: &mut dyn Admission) {
        if std::mem::take(&mut self.closed) {
            gate.on_disconnect();
        }
    }

    /// Make `peer` the controlling client.
    fn take_control(&mut self, mut peer: Peer) {
        // Nothing of the previous client reaches this one, nor runs in its session.
        self.bufs.rx.clear();
        self.bufs.tx.clear();
        peer.frame(Opcode::Text, CONTROL_NOTICE);
        peer.send();
        self.controller = Some(peer);
        self.connections += 1;
    }

    /// Make `peer` a watcher, or close it when there are enough.
    fn watch(&mut self, mut peer: Peer) {
        if self.watchers.len() >= MAX_WATCHERS {
            peer.close(close_code::POLICY, "too many clients");
            return self.leave(peer);
        }
        self.stats.watchers += 1;
        peer.frame(Opcode::Text, WATCHING_NOTICE);
        peer.send();
        self.watchers.push_back(peer);
    }
}

/// What a complete request is answered with.
enum Answer {
    /// 101, then the connection is a WebSocket; `head_len` bytes were the request.
    Upgrade { reply: Vec<u8>, head_len: usize },
    /// 200 and the asset (head and body), then close.
    Asset(Vec<u8>),
    /// The refusal, then close.
    Refuse(RequestError),
}

fn answer(request: &http::Request<'_>, head_len: usize) -> Answer {
    let mut head = [0u8; 256];
    match request.route() {
        Route::WebSocket { key } => {
            let n = http::write_switching_protocols(&mut head, key).unwrap_or(0);
            Answer::Upgrade {
                reply: head.get(..n).unwrap_or_default().to_vec(),
                head_len,
            }
        }
        Route::Asset { asset, body } => {
            let n = http::write_asset_head(&mut head, asset).unwrap_or(0);
            let mut out = head.get(..n).unwrap_or_default().to_vec();
            if body {
                out.extend(asset.gzip);
            }
            Answer::Asset(out)
        }
        Route::Refuse(e) => Answer::Refuse(e),
    }
}

impl BufferedPort for WebLink {
    fn buffers(&mut self) -> &mut Buffers {
        &mut self.bufs
    }

    fn is_connected(&self) -> bool {
        self.controller.is_some()
    }

    fn service(&mut self) -> io::Result<()> {
        self.accept();
        self.serve_http();
        self.receive();
        self.send();
        self.serve_watchers();
        self.serve_leaving();
        Ok(())
    }

    fn overflow(&mut self, _lost: usize) {
        self.stats.overflows += 1;
        self.disconnect(Some((close_code::POLICY, "replies not read")));
    }

    fn hang_up(&mut self) {
        self.disconnect(Some((close_code::NORMAL, "idle time-out")));
    }

    fn admit(&mut self, gate: &mut dyn Admission, now_ms: u32) -> io::Result<bool> {
        self.report_close(gate);
        let mut admitted = false;
        // The watcher that has watched longest is offered control first.
        if self.controller.is_none()
            && !self.watchers.is_empty()
            && gate.on_connect(now_ms) == Admit::Control
            && let Some(w) = self.watchers.pop_front()
        {
            self.take_control(w);
            admitted = true;
        }
        while let Some(peer) = self.upgraded.pop_front() {
            if self.controller.is_none() && gate.on_connect(now_ms) == Admit::Control {
                self.take_control(peer);
                admitted = true;
            } else {
                self.watch(peer);
            }
        }
        Ok(admitted)
    }
}

buffered_link!(WebLink);

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use embedded_io::{Read, ReadReady, Write};
    use forja_drivers::port_link::SingleClient;

    use super::*;
    use crate::link::web_client::{ServerFrame, WsClient, http_request};

    const WAIT: Duration = Duration::from_secs(5);

    fn link() -> WebLink {
        WebLink::bind(
            "127.0.0.1:0".parse().unwrap(),
            b"// E300 link-busy\n".to_vec(),
        )
        .unwrap()
    }

    /// A board's turn: the link serviced, its clients admitted.
    fn turn(link: &mut WebLink, gate: &mut SingleClient) -> bool {
        PortLink::poll(link).unwrap();
        PortLink::admit(link, gate, 0).unwrap()
    }

    /// Turn until `done`, at most five seconds.
    fn until(
        link: &mut WebLink,
        gate: &mut SingleClient,
        mut done: impl FnMut(&mut WebLink) -> bool,
    ) {
        let start = Instant::now();
        while !done(link) {
            assert!(start.elapsed() < WAIT, "timed out");
            turn(link, gate);
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// What the link received, read as the controller reads it.
    fn read_all(link: &mut WebLink) -> Vec<u8> {
        let mut out = Vec::new();
        let mut buf = [0u8; 256];
        while link.read_ready().unwrap() {
            let n = link.read(&mut buf).unwrap();
            out.extend(&buf[..n]);
        }
        out
    }

    /// The next frame `client` receives while the link is served from this thread.
    fn next_frame(
        link: &mut WebLink,
        gate: &mut SingleClient,
        client: &mut WsClient,
    ) -> ServerFrame {
        let start = Instant::now();
        loop {
            assert!(start.elapsed() < WAIT, "no frame");
            turn(link, gate);
            if let Ok(f) = client.frame(Duration::from_millis(2)) {
                return f;
            }
        }
    }

    /// The text `client` receives until it holds `want`, while the link is served from this
    /// thread.
    fn text_until(
        link: &mut WebLink,
        gate: &mut SingleClient,
        client: &mut WsClient,
        want: &str,
    ) -> String {
        let mut text = String::new();
        while !text.contains(want) {
            let f = next_frame(link, gate, client);
            assert_eq!(
                f.opcode, 0x1,
                "{f:?} while waiting for {want:?} after {text:?}"
            );
            text.push_str(&String::from_utf8_lossy(&f.payload));
        }
        text
    }

    /// Connect a WebSocket client while the link is served from this thread.
    fn connect(link: &mut WebLink, gate: &mut SingleClient) -> WsClient {
        let addr = link.local_addr().unwrap();
        let client = std::thread::spawn(move || WsClient::connect(addr).unwrap());
        let start = Instant::now();
        while !client.is_finished() {
            assert!(start.elapsed() < WAIT, "no handshake");
            turn(link, gate);
            std::thread::sleep(Duration::from_millis(1));
        }
        client.join().unwrap()
    }

    /// An HTTP request answered while the link is served from this thread.
    fn request(
        link: &mut WebLink,
        gate: &mut SingleClient,
        bytes: &'static [u8],
    ) -> crate::link::web_client::HttpAnswer {
        let addr = link.local_addr().unwrap();
        let client = std::thread::spawn(move || http_request(addr, bytes).unwrap());
        while !client.is_finished() {
            turn(link, gate);
            std::thread::sleep(Duration::from_millis(1));
        }
        client.join().unwrap()
    }

    #[test]
    fn the_page_is_served_compressed_and_the_rest_refused() {
        let mut link = link();
        let mut gate = SingleClient::new();
        let page = request(&mut link, &mut gate, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n");
        assert_eq!(page.status, 200);
        assert_eq!(page.header("Content-Encoding"), Some("gzip"));
        assert_eq!(page.body, forja_web::asset("/").unwrap().gzip);
        let head = request(&mut link, &mut gate, b"HEAD / HTTP/1.1\r\n\r\n");
        assert_eq!((head.status, head.body.len()), (200, 0));
        let missing = request(&mut link, &mut gate, b"GET /nothing HTTP/1.1\r\n\r\n");
        assert_eq!(missing.status, 404);
        let upload = request(
            &mut link,
            &mut gate,
            b"POST / HTTP/1.1\r\nContent-Length: 8\r\n\r\n\x00\xff\x13garb",
        );
        assert_eq!(upload.status, 405);
        assert_eq!(upload.header("Allow"), Some("GET, HEAD"));
        let garbage = request(
            &mut link,
            &mut gate,
            b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\n",
        );
        assert_eq!(garbage.status, 400);
        let not_ws = request(&mut link, &mut gate, b"GET /ws HTTP/1.1\r\nHost: x\r\n\r\n");
        assert_eq!(not_ws.status, 400);
        let s = link.stats();
        assert_eq!((s.served, s.refused_requests), (2, 4));
        assert_eq!(
            link.state(),
            LinkState::Disconnected,
            "no client took control"
        );
        assert!(
            read_all(&mut link).is_empty(),
            "nothing reached the controller"
        );
    }

    #[test]
    fn the_controller_speaks_through_the_websocket() {
        let mut link = link();
        let mut gate = SingleClient::new();
        let mut page = connect(&mut link, &mut gate);
        until(&mut link, &mut gate, |l| l.state() == LinkState::Connected);
        assert_eq!(link.connections(), 1);
        assert!(page.text_until("// control: ", WAIT).is_ok());
        page.send_text("G28\nM114\n").unwrap();
        page.send_frame(Opcode::Binary, b"?").unwrap();
        let mut got = Vec::new();
        until(&mut link, &mut gate, |l| {
            got.extend(read_all(l));
            got.len() >= 10
        });
        assert_eq!(got, b"G28\nM114\n?");
        link.write_all(b"ok\nX:0.00 ").unwrap();
        link.write_all(b"Y:0.00\nok\n").unwrap();
        let text = page.text_until("Y:0.00\nok\n", WAIT).unwrap();
        assert!(text.starts_with("ok\n"), "{text:?}");
        // A ping is answered with a pong, and the client's close is echoed.
        page.send_frame(Opcode::Ping, b"p").unwrap();
        let pong = next_frame(&mut link, &mut gate, &mut page);
        assert_eq!((pong.opcode, pong.payload.as_slice()), (0xA, &b"p"[..]));
        page.send_frame(Opcode::Close, &1000u16.to_be_bytes())
            .unwrap();
        until(&mut link, &mut gate, |l| {
            l.state() == LinkState::Disconnected
        });
        assert_eq!(page.frame(WAIT).unwrap().close_code(), Some(1000));
        assert_eq!(
            gate.state(),
            LinkState::Disconnected,
            "the session heard of it"
        );
    }

    #[test]
    fn a_second_client_watches_and_takes_over_when_the_controller_leaves() {
        let mut link = link();
        let mut gate = SingleClient::new();
        let mut first = connect(&mut link, &mut gate);
        until(&mut link, &mut gate, |l| l.state() == LinkState::Connected);
        let mut second = connect(&mut link, &mut gate);
        until(&mut link, &mut gate, |l| l.watching() == 1);
        let notice = second.text_until("\n", WAIT).unwrap();
        assert_eq!(notice.as_bytes(), WATCHING_NOTICE);
        first.text_until("// control: ", WAIT).unwrap();

        // The watcher sees what the controller is sent.
        link.write_all(b"ok\nN51E+00010.0000x*F\n").unwrap();
        assert_eq!(
            second.text_until("N51", WAIT).unwrap(),
            "ok\nN51E+00010.0000x*F\n"
        );

        // Its commands never reach the controller and are refused.
        second.send_text("G1 X100\nM112\n").unwrap();
        let refusal = {
            let mut text = String::new();
            let start = Instant::now();
            while !text.contains("E300") {
                assert!(start.elapsed() < WAIT);
                turn(&mut link, &mut gate);
                if let Ok(f) = second.frame(Duration::from_millis(5)) {
                    text.push_str(&String::from_utf8_lossy(&f.payload));
                }
            }
            text
        };
        assert_eq!(refusal, "// E300 link-busy\n");
        assert!(
            read_all(&mut link).is_empty(),
            "nothing of the watcher's was read"
        );
        assert_eq!(
            first.text_until("", Duration::ZERO).unwrap(),
            "",
            "the controller saw nothing"
        );

        // The controller leaves: the watcher is offered control.
        drop(first);
        until(&mut link, &mut gate, |l| {
            l.state() == LinkState::Connected && l.watching() == 0
        });
        assert_eq!(link.connections(), 2);
        second
            .text_until("// control: this client controls the machine\n", WAIT)
            .unwrap();
        second.send_text("M105\n").unwrap();
        let mut got = Vec::new();
        until(&mut link, &mut gate, |l| {
            got.extend(read_all(l));
            !got.is_empty()
        });
        assert_eq!(got, b"M105\n");
    }

    #[test]
    fn a_malformed_frame_closes_with_its_code_and_changes_nothing() {
        let mut link = link();
        let mut gate = SingleClient::new();
        let cases: [(&[u8], u16); 3] = [
            // Unmasked.
            (b"\x81\x04G28\n", 1002),
            // A reserved opcode.
            (b"\x83\x84\x00\x00\x00\x00G28\n", 1002),
            // Longer than a message may be.
            (
                b"\x81\xff\x00\x00\x00\x00\x00\x10\x00\x01\x00\x00\x00\x00",
                1009,
            ),
        ];
        for (frame, code) in cases {
            let mut page = connect(&mut link, &mut gate);
            until(&mut link, &mut gate, |l| l.state() == LinkState::Connected);
            page.text_until("// control: ", WAIT).unwrap();
            page.send_raw(frame).unwrap();
            until(&mut link, &mut gate, |l| {
                l.state() == LinkState::Disconnected
            });
            let close = loop {
                let f = page.frame(WAIT).unwrap();
                if f.opcode == 0x8 {
                    break f;
                }
            };
            assert_eq!(close.close_code(), Some(code), "{frame:?}");
            assert!(
                read_all(&mut link).is_empty(),
                "nothing reached the controller"
            );
            turn(&mut link, &mut gate);
        }
        assert_eq!(link.stats().protocol_errors, 3);
    }

    #[test]
    fn a_silent_controller_is_hung_up_on_with_a_close_frame() {
        let mut link = link();
        let mut gate = SingleClient::new();
        let mut page = connect(&mut link, &mut gate);
        until(&mut link, &mut gate, |l| l.state() == LinkState::Connected);
        PortLink::hang_up(&mut link);
        assert_eq!(link.state(), LinkState::Disconnected);
        while gate.state() == LinkState::Connected {
            turn(&mut link, &mut gate);
        }
        let close = loop {
            let f = page.frame(WAIT).unwrap();
            if f.opcode == 0x8 {
                break f;
            }
        };
        assert_eq!(close.close_code(), Some(1000));
    }

    #[test]
    fn watchers_see_what_a_tapped_link_sends() {
        let mut link = link();
        let mut taken = SingleClient::new();
        // Another port has the machine: every web client watches.
        assert_eq!(taken.on_connect(0), Admit::Control);
        let mut page = connect(&mut link, &mut taken);
        until(&mut link, &mut taken, |l| l.watching() == 1);
        page.text_until("// watching: ", WAIT).unwrap();
        let (memory, _host) = crate::link::MemoryLink::pair();
        let mut tcp = Tapped::new(memory, link.tap());
        tcp.write_all(b"ok\nT:20.0 /0.0\n").unwrap();
        assert_eq!(
            text_until(&mut link, &mut taken, &mut page, "T:20"),
            "ok\nT:20.0 /0.0\n"
        );
    }
}
