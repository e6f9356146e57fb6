//! The byte link to a controller: a serial port or a TCP connection.
//!
//! [`Link`] is the one interface the rest of the client uses: write bytes, read what has
//! arrived within a time limit. [`LinkSpec::open`] opens either kind with errors a person can
//! act on ("no such serial port /dev/ttyUSB0 …", "nothing is listening at 127.0.0.1:2323 …").
//! [`Connection`] adds the stream decoder: the bytes become reply lines and frames.

use std::collections::VecDeque;
use std::fmt;
use std::io::{self, Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

use forja_protocol::frame::FRAME_LEN;
use forja_protocol::stream::{Decoder, Event};

/// A byte link to a controller.
///
/// Context: one thread. `read` blocks at most `timeout`; `write_all` blocks until the bytes
/// are handed to the operating system.
pub trait Link: Send {
    /// Write all of `bytes`.
    fn write_all(&mut self, bytes: &[u8]) -> io::Result<()>;
    /// Read what has arrived, waiting at most `timeout` for the first byte. `Ok(0)` when
    /// nothing came in time; an error when the link is gone.
    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize>;
    /// The link's rate in bits a second, when it has one (a serial port's baud rate).
    fn bit_rate(&self) -> Option<u32> {
        None
    }
}

/// Where the controller is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum LinkSpec {
    /// A serial port (a USB adapter, a UART, a pseudo-terminal) at a baud rate.
    Serial {
        /// Its path, e.g. `/dev/ttyUSB0` or `COM3`.
        path: String,
        /// Bits a second.
        baud: u32,
    },
    /// A TCP connection, e.g. to a WiFi controller or the simulator.
    Tcp {
        /// `HOST:PORT`.
        address: String,
    },
}

impl fmt::Display for LinkSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Serial { path, baud } => write!(f, "{path} at {baud} baud"),
            Self::Tcp { address } => write!(f, "{address}"),
        }
    }
}

/// A link that could not be opened, worded for the person at the machine.
#[derive(Debug)]
pub struct OpenError {
    message: String,
    source: Option<io::Error>,
}

impl fmt::Display for OpenError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for OpenError {}

impl OpenError {
    /// The operating system's error under the message, if there was one.
    pub fn os_error(&self) -> Option<&io::Error> {
        self.source.as_ref()
    }
}

impl LinkSpec {
    /// Whether the link is TCP (larger buffers than a UART's).
    pub fn is_tcp(&self) -> bool {
        matches!(self, Self::Tcp { .. })
    }

    /// Open the link.
    ///
    /// Errors: the port does not exist, is busy or not accessible; the address does not
    /// resolve; nothing listens there; the connection times out. Each message says what to
    /// check.
    pub fn open(&self) -> Result<Box<dyn Link>, OpenError> {
        match self {
            Self::Serial { path, baud } => open_serial(path, *baud),
            Self::Tcp { address } => open_tcp(address),
        }
    }
}

fn open_serial(path: &str, baud: u32) -> Result<Box<dyn Link>, OpenError> {
    let port = serialport::new(path, baud)
        .timeout(Duration::from_millis(10))
        .open()
        .map_err(|e| {
            let missing = matches!(e.kind(), serialport::ErrorKind::NoDevice)
                || matches!(e.kind(), serialport::ErrorKind::Io(io::ErrorKind::NotFound))
                || !std::path::Path::new(path).exists() && !path.starts_with("COM");
            let message = if missing {
                let ports = serialport::available_ports()
                    .map(|ports| {
                        ports
                            .into_iter()
                            .map(|p| p.port_name)
                            .collect::<Vec<_>>()
                            .join(", ")
                    })
                    .unwrap_or_default();
                let found = if ports.is_empty() {
                    "no serial port was found".to_string()
                } else {
                    format!("serial ports found: {ports}")
                };
                format!(
                    "there is no serial port {path}: is the controller plugged in and powered? \
                     ({found})"
                )
            } else if matches!(
                e.kind(),
                serialport::ErrorKind::Io(io::ErrorKind::PermissionDenied)
            ) || e.description.contains("ermission")
            {
                format!(
                    "no permission to open {path}: add your user to the group that owns it \
                     (often 'dialout'), then log in again"
                )
            } else if e.description.contains("busy") || e.description.contains("Busy") {
                format!("{path} is in use by another program: close it and try again")
            } else {
                format!("cannot open the serial port {path}: {}", e.description)
            };
            OpenError {
                message,
                source: None,
            }
        })?;
    Ok(Box::new(SerialLink { port, baud }))
}

fn open_tcp(address: &str) -> Result<Box<dyn Link>, OpenError> {
    let addrs: Vec<_> = address
        .to_socket_addrs()
        .map_err(|e| OpenError {
            message: format!(
                "cannot find the controller's address \"{address}\" (expected HOST:PORT, e.g. \
                 192.168.1.50:2323): {e}"
            ),
            source: Some(e),
        })?
        .collect();
    let mut last = None;
    for addr in &addrs {
        match TcpStream::connect_timeout(addr, Duration::from_secs(5)) {
            Ok(stream) => {
                stream.set_nodelay(true).ok();
                return Ok(Box::new(TcpLink { stream }));
            }
            Err(e) => last = Some(e),
        }
    }
    let e = last.unwrap_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no address"));
    let message = match e.kind() {
        io::ErrorKind::ConnectionRefused => format!(
            "the controller at {address} refused the connection: nothing is listening on that \
             port (is the controller on, and is the port right?)"
        ),
        io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock => format!(
            "no answer from {address} within 5 s: is the controller on the same network, and \
             is the address right?"
        ),
        _ => format!("cannot connect to {address}: {e}"),
    };
    Err(OpenError {
        message,
        source: Some(e),
    })
}

struct SerialLink {
    port: Box<dyn serialport::SerialPort>,
    baud: u32,
}

impl Link for SerialLink {
    fn write_all(&mut self, bytes: &[u8]) -> io::Result<()> {
        // The port's time-out also bounds writes: retry until everything is out.
        let mut rest = bytes;
        while !rest.is_empty() {
            match self.port.write(rest) {
                Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
                Ok(n) => rest = rest.get(n..).unwrap_or_default(),
                Err(e) if e.kind() == io::ErrorKind::TimedOut => {}
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }

    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        self.port
            .set_timeout(timeout.max(Duration::from_millis(1)))
            .map_err(io::Error::other)?;
        nothing_on_timeout(self.port.read(buf))
    }

    fn bit_rate(&self) -> Option<u32> {
        Some(self.baud)
    }
}

/// A read that ran out of time read nothing: `Ok(0)`, as [`Link::read`] promises.
fn nothing_on_timeout(read: io::Result<usize>) -> io::Result<usize> {
    match read {
        Err(e)
            if matches!(
                e.kind(),
                io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
            ) =>
        {
            Ok(0)
        }
        read => read,
    }
}

struct TcpLink {
    stream: TcpStream,
}

impl Link for TcpLink {
    fn write_all(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.stream.write_all(bytes)
    }

    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        self.stream
            .set_read_timeout(Some(timeout.max(Duration::from_millis(1))))?;
        match self.stream.read(buf) {
            Ok(0) => Err(io::Error::new(
                io::ErrorKind::ConnectionAborted,
                "the controller closed the connection",
            )),
            read => nothing_on_timeout(read),
        }
    }
}

/// One record received from the controller.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Incoming {
    /// A reply line (`ok`, `rs 5`, `// …`, …), without terminator.
    Line(Vec<u8>),
    /// A 53-byte frame.
    Frame([u8; FRAME_LEN]),
    /// Bytes that were neither (a damaged record).
    Garbage(usize),
}

/// What [`Connection::keep_alive`] sends: a lone line end, an empty record, which the
/// controller neither answers nor counts as a line and which changes nothing (a line already
/// sent is always whole: its own terminator went before it).
pub const KEEP_ALIVE: &[u8] = b"\n";

/// How long a [`Connection`] may send nothing before [`Connection::keep_alive`] sends
/// [`KEEP_ALIVE`]: a third of the boards' idle time-out (60 s), after which a silent host
/// loses control.
pub const KEEP_ALIVE_PERIOD: Duration = Duration::from_secs(20);

/// A link with the stream decoder: reply lines and frames in, bytes out.
pub struct Connection {
    link: Box<dyn Link>,
    decoder: Decoder,
    pending: VecDeque<Incoming>,
    /// When bytes last arrived with a record still incomplete.
    partial_since: Option<Instant>,
    bytes_written: u64,
    bytes_read: u64,
    /// Everything written and read, for `--verbose`-style logs: `(sent, bytes)`.
    transcript: Option<Vec<(bool, Vec<u8>)>>,
    /// When bytes were last written.
    last_sent: Instant,
    /// See [`Connection::set_keep_alive_period`].
    keep_alive_period: Duration,
}

impl fmt::Debug for Connection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Connection")
            .field("bytes_written", &self.bytes_written)
            .field("bytes_read", &self.bytes_read)
            .finish_non_exhaustive()
    }
}

/// A record left unterminated this long is taken as it is (a frame sent without a line end).
const FLUSH_AFTER: Duration = Duration::from_millis(50);

impl Connection {
    /// Wrap an open link.
    pub fn new(link: Box<dyn Link>) -> Self {
        Self {
            link,
            decoder: Decoder::new(),
            pending: VecDeque::new(),
            partial_since: None,
            bytes_written: 0,
            bytes_read: 0,
            transcript: None,
            last_sent: Instant::now(),
            keep_alive_period: KEEP_ALIVE_PERIOD,
        }
    }

    /// Open `spec` and wrap it.
    pub fn open(spec: &LinkSpec) -> Result<Self, OpenError> {
        spec.open().map(Self::new)
    }

    /// Keep a transcript of everything written and read.
    pub fn record(&mut self) {
        self.transcript = Some(Vec::new());
    }

    /// The transcript kept since [`record`](Self::record): `(true, bytes)` for what was sent.
    pub fn transcript(&self) -> &[(bool, Vec<u8>)] {
        self.transcript.as_deref().unwrap_or_default()
    }

    /// The link's bit rate, if it has one.
    pub fn bit_rate(&self) -> Option<u32> {
        self.link.bit_rate()
    }

    /// Bytes written so far.
    pub fn bytes_written(&self) -> u64 {
        self.bytes_written
    }

    /// Write `bytes`.
    pub fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        if bytes.is_empty() {
            return Ok(());
        }
        self.link.write_all(bytes)?;
        self.last_sent = self.last_sent.max(Instant::now());
        self.bytes_written += bytes.len() as u64;
        if let Some(t) = &mut self.transcript {
            t.push((true, bytes.to_vec()));
        }
        Ok(())
    }

    /// Send [`KEEP_ALIVE`] after this long without writing (default [`KEEP_ALIVE_PERIOD`]).
    pub fn set_keep_alive_period(&mut self, period: Duration) {
        self.keep_alive_period = period;
    }

    /// Keep the session of an idle operator: send [`KEEP_ALIVE`] if nothing was written for
    /// the keep-alive period. Returns whether it was sent. Call it from every loop that may
    /// wait on the person (the console, `forja status`), at least once a period.
    pub fn keep_alive(&mut self) -> io::Result<bool> {
        self.keep_alive_at(Instant::now())
    }

    /// [`Connection::keep_alive`] as at `now`.
    pub fn keep_alive_at(&mut self, now: Instant) -> io::Result<bool> {
        if now.saturating_duration_since(self.last_sent) < self.keep_alive_period {
            return Ok(false);
        }
        self.send(KEEP_ALIVE)?;
        self.last_sent = self.last_sent.max(now);
        Ok(true)
    }

    /// The next record, waiting at most `timeout` for it. `Ok(None)` when nothing complete
    /// arrived in time.
    pub fn receive(&mut self, timeout: Duration) -> io::Result<Option<Incoming>> {
        if let Some(record) = self.pending.pop_front() {
            return Ok(Some(record));
        }
        let deadline = Instant::now() + timeout;
        let mut buf = [0u8; 4096];
        loop {
            let now = Instant::now();
            let mut wait = deadline.saturating_duration_since(now);
            if let Some(since) = self.partial_since {
                wait = wait.min((since + FLUSH_AFTER).saturating_duration_since(now));
            }
            let n = self.link.read(&mut buf, wait)?;
            if n > 0 {
                let bytes = buf.get(..n).unwrap_or_default();
                self.bytes_read += n as u64;
                if let Some(t) = &mut self.transcript {
                    t.push((false, bytes.to_vec()));
                }
                let pending = &mut self.pending;
                self.decoder
                    .feed_all(bytes, |event| push_event(pending, event));
                self.partial_since =
                    (!bytes.ends_with(b"\n") && !bytes.ends_with(b"\r")).then(Instant::now);
            } else if self
                .partial_since
                .is_some_and(|since| since.elapsed() >= FLUSH_AFTER)
            {
                self.partial_since = None;
                while let Some(event) = self.decoder.flush() {
                    push_event(&mut self.pending, event);
                }
            }
            if let Some(record) = self.pending.pop_front() {
                return Ok(Some(record));
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
        }
    }
}

fn push_event(pending: &mut VecDeque<Incoming>, event: Event<'_>) {
    match event {
        Event::Line(bytes) => pending.push_back(Incoming::Line(bytes.to_vec())),
        Event::Frame(frame) => pending.push_back(Incoming::Frame(*frame.as_bytes())),
        Event::Garbage { skipped, .. } => pending.push_back(Incoming::Garbage(skipped)),
        Event::TooLong { len } => pending.push_back(Incoming::Garbage(len)),
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    /// A link that plays back chunks, one per read.
    struct Script {
        chunks: VecDeque<Vec<u8>>,
        written: Arc<Mutex<Vec<u8>>>,
    }

    impl Link for Script {
        fn write_all(&mut self, bytes: &[u8]) -> io::Result<()> {
            self.written.lock().unwrap().extend_from_slice(bytes);
            Ok(())
        }
        fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
            match self.chunks.pop_front() {
                Some(c) => {
                    buf[..c.len()].copy_from_slice(&c);
                    Ok(c.len())
                }
                None => {
                    std::thread::sleep(timeout.min(Duration::from_millis(5)));
                    Ok(0)
                }
            }
        }
    }

    #[test]
    fn lines_and_frames_are_split_out_of_the_stream() {
        let frame = b"N54Conected*****************************************F";
        let mut c = Connection::new(Box::new(Script {
            chunks: VecDeque::from([
                b"star".to_vec(),
                b"t\nok\r\nrs 4\n".to_vec(),
                frame.to_vec(),
            ]),
            written: Arc::default(),
        }));
        let t = Duration::from_millis(200);
        assert_eq!(
            c.receive(t).unwrap(),
            Some(Incoming::Line(b"start".to_vec()))
        );
        assert_eq!(c.receive(t).unwrap(), Some(Incoming::Line(b"ok".to_vec())));
        assert_eq!(
            c.receive(t).unwrap(),
            Some(Incoming::Line(b"rs 4".to_vec()))
        );
        // A frame without a terminator is taken once the link is quiet.
        assert_eq!(c.receive(t).unwrap(), Some(Incoming::Frame(*frame)));
        assert_eq!(c.receive(Duration::from_millis(10)).unwrap(), None);
    }

    #[test]
    fn refused_and_missing_links_say_what_to_check() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let address = listener.local_addr().unwrap().to_string();
        drop(listener);
        let e = LinkSpec::Tcp {
            address: address.clone(),
        }
        .open()
        .err()
        .unwrap();
        assert!(e.to_string().contains("refused the connection"), "{e}");
        let e = LinkSpec::Serial {
            path: "/dev/ttyFORJA-none".into(),
            baud: 115_200,
        }
        .open()
        .err()
        .unwrap();
        assert!(
            e.to_string()
                .starts_with("there is no serial port /dev/ttyFORJA-none"),
            "{e}"
        );
        let e = LinkSpec::Tcp {
            address: "no-port".into(),
        }
        .open()
        .err()
        .unwrap();
        assert!(e.to_string().contains("expected HOST:PORT"), "{e}");
    }
}
