//! A blocking HTTP and WebSocket client for [`super::WebLink`], as a browser speaks to it:
//! for tests and tools on the host.

use std::io::{self, Read as _, Write as _};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use forja_web::websocket::{MAX_HEADER, Opcode, write_header};

/// An HTTP answer: its status code, its head and its body (as sent: gzip for an asset).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HttpAnswer {
    /// The status code.
    pub status: u16,
    /// The head, status line and headers, as text.
    pub head: String,
    /// The body.
    pub body: Vec<u8>,
}

impl HttpAnswer {
    /// The value of header `name` (any case), if sent.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.head.lines().find_map(|l| {
            let (n, v) = l.split_once(':')?;
            n.eq_ignore_ascii_case(name).then_some(v.trim())
        })
    }
}

/// Send `request` (a whole request, head and any body) to `addr` and read the answer until
/// the server closes.
///
/// Errors: the connection fails, or the answer is not HTTP.
pub fn http_request(addr: SocketAddr, request: &[u8]) -> io::Result<HttpAnswer> {
    let mut stream = TcpStream::connect(addr)?;
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    stream.write_all(request)?;
    let mut bytes = Vec::new();
    stream.read_to_end(&mut bytes)?;
    let bad = || io::Error::new(io::ErrorKind::InvalidData, "not an HTTP answer");
    let end = bytes
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or_else(bad)?;
    let head = String::from_utf8_lossy(bytes.get(..end).unwrap_or_default()).into_owned();
    let status = head
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .ok_or_else(bad)?;
    let body = bytes.get(end + 4..).unwrap_or_default().to_vec();
    Ok(HttpAnswer { status, head, body })
}

/// A WebSocket client: masked frames out, the server's frames in.
#[derive(Debug)]
pub struct WsClient {
    stream: TcpStream,
    /// Received bytes not yet made frames of.
    pending: Vec<u8>,
}

/// A frame from the server.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServerFrame {
    /// Its opcode bits (0x1 text, 0x8 close, 0xA pong, …).
    pub opcode: u8,
    /// Its payload.
    pub payload: Vec<u8>,
}

impl ServerFrame {
    /// A close frame's code.
    pub fn close_code(&self) -> Option<u16> {
        match (self.opcode, self.payload.as_slice()) {
            (0x8, [hi, lo, ..]) => Some(u16::from_be_bytes([*hi, *lo])),
            _ => None,
        }
    }
}

impl WsClient {
    /// Open `ws://addr/ws` with the handshake of RFC 6455 (the example key).
    ///
    /// Errors: the connection fails or the server does not answer 101.
    pub fn connect(addr: SocketAddr) -> io::Result<Self> {
        let mut stream = TcpStream::connect(addr)?;
        stream.set_read_timeout(Some(Duration::from_secs(5)))?;
        write!(
            stream,
            "GET /ws HTTP/1.1\r\nHost: {addr}\r\nOrigin: http://{addr}\r\nUpgrade: websocket\r\n\
             Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\
             Sec-WebSocket-Version: 13\r\n\r\n"
        )?;
        let mut head = Vec::new();
        let mut byte = [0u8; 1];
        while !head.ends_with(b"\r\n\r\n") {
            stream.read_exact(&mut byte)?;
            head.extend(byte);
        }
        let head = String::from_utf8_lossy(&head);
        if !head.starts_with("HTTP/1.1 101 ")
            || !head.contains("Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=")
        {
            return Err(io::Error::other(format!("no upgrade: {head}")));
        }
        Ok(Self {
            stream,
            pending: Vec::new(),
        })
    }

    /// Send raw bytes, frames or not.
    ///
    /// Errors: the connection fails.
    pub fn send_raw(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.stream.write_all(bytes)
    }

    /// Send one masked frame.
    ///
    /// Errors: the connection fails.
    pub fn send_frame(&mut self, opcode: Opcode, payload: &[u8]) -> io::Result<()> {
        let mut header = [0u8; MAX_HEADER];
        let n = write_header(&mut header, opcode, payload.len()).map_err(io::Error::other)?;
        let mut frame = header.get(..n).unwrap_or_default().to_vec();
        if let Some(b1) = frame.get_mut(1) {
            *b1 |= 0x80;
        }
        let mask = [0x5a, 0xa5, 0x3c, 0xc3];
        frame.extend(mask);
        frame.extend(payload.iter().zip(mask.iter().cycle()).map(|(b, m)| b ^ m));
        self.send_raw(&frame)
    }

    /// Send `text` as one text frame.
    ///
    /// Errors: the connection fails.
    pub fn send_text(&mut self, text: &str) -> io::Result<()> {
        self.send_frame(Opcode::Text, text.as_bytes())
    }

    /// The next frame from the server, waiting at most `timeout`.
    ///
    /// Errors: nothing came in time (`TimedOut`), the connection closed or failed.
    pub fn frame(&mut self, timeout: Duration) -> io::Result<ServerFrame> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(frame) = self.take_frame() {
                return Ok(frame);
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(io::ErrorKind::TimedOut.into());
            }
            self.stream.set_read_timeout(Some(left))?;
            let mut chunk = [0u8; 4096];
            match self.stream.read(&mut chunk) {
                Ok(0) => return Err(io::ErrorKind::UnexpectedEof.into()),
                Ok(n) => self.pending.extend(chunk.get(..n).unwrap_or_default()),
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                    ) => {}
                Err(e) => return Err(e),
            }
        }
    }

    /// The text the server sends until it holds `want`, waiting at most `timeout`; what came
    /// (text frames only, concatenated).
    ///
    /// Errors: `want` did not come in time (`TimedOut`, with the text received), the
    /// connection closed or failed.
    pub fn text_until(&mut self, want: &str, timeout: Duration) -> io::Result<String> {
        let deadline = Instant::now() + timeout;
        let mut text = String::new();
        while !text.contains(want) {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.frame(left) {
                Ok(f) if f.opcode == 0x1 => text.push_str(&String::from_utf8_lossy(&f.payload)),
                Ok(_) => {}
                Err(e) if e.kind() == io::ErrorKind::TimedOut => {
                    return Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        format!("{want:?} not received; got {text:?}"),
                    ));
                }
                Err(e) => return Err(e),
            }
        }
        Ok(text)
    }

    /// A whole server frame from the bytes received, if they hold one.
    fn take_frame(&mut self) -> Option<ServerFrame> {
        let p = &self.pending;
        let (&b0, &b1) = (p.first()?, p.get(1)?);
        let (len, start) = match b1 & 0x7f {
            126 => (usize::from(u16::from_be_bytes([*p.get(2)?, *p.get(3)?])), 4),
            127 => {
                let bytes: [u8; 8] = p.get(2..10)?.try_into().ok()?;
                (usize::try_from(u64::from_be_bytes(bytes)).ok()?, 10)
            }
            n => (usize::from(n), 2),
        };
        let payload = p.get(start..start + len)?.to_vec();
        self.pending.drain(..start + len);
        Some(ServerFrame {
            opcode: b0 & 0x0f,
            payload,
        })
    }
}
