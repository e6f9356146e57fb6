//! The TCP link, like the ESP32 board's WiFi link.

use std::io::{self, Read as _, Write as _};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};

use forja_drivers::port_link::{Admission, Admit};

use super::{BufferedPort, Buffers, buffered_link};

/// Most clients [`PortLink::admit`](super::PortLink::admit) accepts in one call.
pub const ACCEPTS_PER_ADMIT: usize = 16;

/// Most bytes read (and dropped) from a refused client before it is closed, so that it gets
/// an orderly close rather than a reset.
pub const REFUSE_DRAIN: usize = 16 * 1024;

/// A TCP listener with one controlling client at a time.
///
/// Who controls is decided by the port's session rules ([`Admission`]; on the simulator board
/// the application's `LinkSession`, the ESP32 board's WiFi link's rules):
/// [`PortLink::admit`](super::PortLink::admit) accepts the clients waiting on the listener and
/// reports each to the rules (`on_connect`), after reporting the close of the controlling
/// client (`on_disconnect`), so that a host that closes and reconnects at once is admitted.
/// The first client controls the machine until it closes; a client that connects while
/// another is in control ([`Admit::Refuse`]) is sent the busy message (given by the
/// protocol layer, e.g. an error line) and closed, and the controlling client is untouched;
/// [`TcpLink::refused`] counts them. Until `admit` is called, clients wait in the listener's
/// backlog. If a refused client has already sent bytes that arrive after its connection is
/// drained, the operating system may reset the connection rather than close it, and the
/// message can be lost; a host that waits for the controller to speak first always receives
/// it.
///
/// A new controlling client starts with empty buffers: it never reads a reply meant for the
/// previous one, and nothing the previous one sent is read after it takes control. Bytes
/// received from a client stay in the receive buffer after it disconnects, until
/// [`PortLink::discard_input`](super::PortLink::discard_input) or the next client takes
/// control; unsent replies are discarded at once.
///
/// Nothing here waits for a client: a controlling client that lets [`super::TX_CAPACITY`]
/// bytes of replies back up (it stopped reading) is dropped ([`TcpLink::overflows`]); a
/// refused client gets its busy message only if its socket takes it at once; each
/// [`PortLink::admit`](super::PortLink::admit) accepts at most `ACCEPTS_PER_ADMIT` clients
/// (the others wait in the backlog for the next call) and reads at most `REFUSE_DRAIN`
/// bytes from each refused one. Implements [`super::PortLink`].
#[derive(Debug)]
pub struct TcpLink {
    listener: TcpListener,
    client: Option<TcpStream>,
    peer: Option<SocketAddr>,
    bufs: Buffers,
    busy_message: Vec<u8>,
    connections: u64,
    refused: u64,
    overflows: u64,
    /// The controlling client went away and the session was not told yet.
    closed: bool,
}

impl TcpLink {
    /// Listen on `addr` (port 0: any free port; see [`TcpLink::local_addr`]). A second client
    /// while one is connected receives `busy_message` and is closed.
    ///
    /// Errors: the address cannot be bound (in use, not local, no permission).
    pub fn bind(addr: SocketAddr, busy_message: impl Into<Vec<u8>>) -> io::Result<Self> {
        let listener = TcpListener::bind(addr)?;
        listener.set_nonblocking(true)?;
        Ok(Self {
            listener,
            client: None,
            peer: None,
            bufs: Buffers::default(),
            busy_message: busy_message.into(),
            connections: 0,
            refused: 0,
            overflows: 0,
            closed: false,
        })
    }

    /// The address actually listened on (with the port chosen when bound to port 0).
    ///
    /// Errors: as `TcpListener::local_addr` (practically never).
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// The controlling client's address, while one is connected.
    pub fn peer_addr(&self) -> Option<SocketAddr> {
        self.peer
    }

    /// Clients refused because another was in control.
    pub fn refused(&self) -> u64 {
        self.refused
    }

    /// Controlling clients dropped because their replies backed up past
    /// [`super::TX_CAPACITY`] bytes (they stopped reading).
    pub fn overflows(&self) -> u64 {
        self.overflows
    }

    /// Close the controlling client's connection, if any; the session hears of it at the next
    /// [`PortLink::admit`](super::PortLink::admit).
    pub fn disconnect(&mut self) {
        if let Some(client) = self.client.take() {
            let _ = client.shutdown(Shutdown::Both);
            self.closed = true;
        }
        self.peer = None;
        self.bufs.tx.clear();
    }

    fn refuse(&mut self, mut stream: TcpStream) {
        self.refused += 1;
        if stream.set_nonblocking(true).is_err() {
            return;
        }
        // Drain what the client already sent (within a bound: a flooding client is not
        // waited for), so that closing sends FIN rather than RST.
        let mut sink = [0u8; 4096];
        let mut drained = 0;
        while drained < REFUSE_DRAIN {
            match stream.read(&mut sink) {
                Ok(n) if n > 0 => drained += n,
                _ => break,
            }
        }
        // A fresh socket takes a short message at once; one that does not is not waited for.
        let _ = stream.write(&self.busy_message);
        let _ = stream.shutdown(Shutdown::Write);
    }

    fn receive(&mut self) {
        let Some(client) = self.client.as_mut() else {
            return;
        };
        let mut chunk = [0u8; 4096];
        loop {
            let room = self.bufs.rx_room().min(chunk.len());
            if room == 0 {
                return;
            }
            match client.read(&mut chunk[..room]) {
                Ok(0) => return self.disconnect(),
                Ok(n) => self.bufs.rx.extend(&chunk[..n]),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(_) => return self.disconnect(),
            }
        }
    }

    fn send(&mut self) {
        let Some(client) = self.client.as_mut() else {
            return;
        };
        while !self.bufs.tx.is_empty() {
            let pending = self.bufs.tx.make_contiguous();
            match client.write(pending) {
                Ok(0) => return self.disconnect(),
                Ok(n) => {
                    self.bufs.tx.drain(..n);
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(_) => return self.disconnect(),
            }
        }
    }

    /// The client waiting on the listener, if any.
    fn accept(&mut self) -> io::Result<Option<(TcpStream, SocketAddr)>> {
        loop {
            match self.listener.accept() {
                Ok(waiting) => return Ok(Some(waiting)),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(None),
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::Interrupted
                            | io::ErrorKind::ConnectionAborted
                            | io::ErrorKind::ConnectionReset
                    ) => {}
                Err(e) => return Err(e),
            }
        }
    }

    /// Tell `gate` that the controlling client went away, if it did.
    fn report_close(&mut self, gate: &mut dyn Admission) {
        if std::mem::take(&mut self.closed) {
            gate.on_disconnect();
        }
    }

    /// Make `stream` the controlling client. Errors: it cannot be made non-blocking.
    fn take_control(&mut self, stream: TcpStream, addr: SocketAddr) -> io::Result<()> {
        stream.set_nonblocking(true)?;
        let _ = stream.set_nodelay(true);
        // Nothing of the previous client reaches this one, nor runs in its session.
        self.bufs.rx.clear();
        self.bufs.tx.clear();
        self.client = Some(stream);
        self.peer = Some(addr);
        self.connections += 1;
        Ok(())
    }
}

impl BufferedPort for TcpLink {
    fn buffers(&mut self) -> &mut Buffers {
        &mut self.bufs
    }

    fn is_connected(&self) -> bool {
        self.client.is_some()
    }

    fn service(&mut self) -> io::Result<()> {
        self.receive();
        self.send();
        Ok(())
    }

    fn overflow(&mut self, _lost: usize) {
        self.overflows += 1;
        self.disconnect();
    }

    fn hang_up(&mut self) {
        self.disconnect();
    }

    fn admit(&mut self, gate: &mut dyn Admission, now_ms: u32) -> io::Result<bool> {
        self.report_close(gate);
        let mut admitted = false;
        for _ in 0..ACCEPTS_PER_ADMIT {
            let Some((stream, addr)) = self.accept()? else {
                break;
            };
            // The controlling client may have closed after the last read, just before this one
            // connected (a host that reconnects at once): look again, so that the session
            // hears of the close first. A host closes before it reconnects, so its close is
            // there to be seen.
            self.receive();
            self.report_close(gate);
            match gate.on_connect(now_ms) {
                Admit::Control => match self.take_control(stream, addr) {
                    Ok(()) => admitted = true,
                    Err(_) => gate.on_disconnect(),
                },
                Admit::Refuse => self.refuse(stream),
            }
        }
        Ok(admitted)
    }
}

buffered_link!(TcpLink);

#[cfg(test)]
mod tests {
    use forja_hal_abstraction::link::{LinkState, LinkStatus};

    use forja_drivers::port_link::SingleClient;

    use super::*;
    use crate::link::PortLink;

    /// What the link reported to the session rules.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    enum Report {
        Connect(u32),
        Disconnect,
    }

    /// One controlling client ([`SingleClient`]), with what the link reported to it.
    #[derive(Default)]
    struct Recorded {
        rules: SingleClient,
        reports: Vec<Report>,
    }

    impl LinkStatus for Recorded {
        fn state(&self) -> LinkState {
            self.rules.state()
        }
    }

    impl Admission for Recorded {
        fn on_connect(&mut self, now_ms: u32) -> Admit {
            self.reports.push(Report::Connect(now_ms));
            self.rules.on_connect(now_ms)
        }
        fn on_disconnect(&mut self) {
            self.reports.push(Report::Disconnect);
            self.rules.on_disconnect();
        }
    }

    fn link() -> TcpLink {
        TcpLink::bind("127.0.0.1:0".parse().unwrap(), b"busy\n".to_vec()).unwrap()
    }

    /// A host that closes and reconnects at once: its close may arrive after the link's last
    /// read and before it accepts the new connection, which must not be refused for it.
    #[test]
    fn a_host_that_reconnects_at_once_is_not_refused() {
        let mut link = link();
        let mut gate = Recorded::default();
        let addr = link.local_addr().unwrap();
        let first = TcpStream::connect(addr).unwrap();
        while link.connections() == 0 {
            link.poll().unwrap();
            PortLink::admit(&mut link, &mut gate, 0).unwrap();
        }
        // The close and the new connection both come between two reads.
        drop(first);
        let mut second = TcpStream::connect(addr).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        assert!(
            PortLink::admit(&mut link, &mut gate, 10).unwrap(),
            "admitted"
        );
        assert_eq!(link.refused(), 0);
        assert_eq!(link.connections(), 2);
        assert_eq!(
            gate.reports,
            [Report::Connect(0), Report::Disconnect, Report::Connect(10)],
            "the close reported before the new connection"
        );
        embedded_io::Write::write_all(&mut link, b"ok\n").unwrap();
        let mut buf = [0u8; 3];
        second.read_exact(&mut buf).unwrap();
        assert_eq!(&buf, b"ok\n");
    }

    /// Admission is the session rules': rules that already have a controller refuse the first
    /// client of a new link, and rules that have none admit it.
    #[test]
    fn the_session_decides() {
        let mut link = link();
        let addr = link.local_addr().unwrap();
        let mut taken = SingleClient::new();
        assert_eq!(taken.on_connect(0), Admit::Control);
        let mut refused = TcpStream::connect(addr).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        assert!(!PortLink::admit(&mut link, &mut taken, 5).unwrap());
        assert_eq!((link.connections(), link.refused()), (0, 1));
        let mut text = String::new();
        refused.read_to_string(&mut text).unwrap();
        assert_eq!(text, "busy\n");

        taken.on_disconnect();
        let _admitted = TcpStream::connect(addr).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        assert!(PortLink::admit(&mut link, &mut taken, 5).unwrap());
        assert_eq!((link.connections(), link.refused()), (1, 1));
        assert_eq!(taken.state(), LinkState::Connected);
    }
}
