//! A sans-IO HTTP/1.1 codec for the few requests a board serves: the head of a request, parsed
//! from the bytes received so far, and the heads of the answers, written into the caller's
//! buffer.
//!
//! A board reads a connection's bytes into a buffer of [`MAX_HEAD_LEN`] bytes and calls
//! [`parse`] after each read until it gives a [`Request`] (or an error); it then answers with
//! one of the writers below and closes the connection (every answer says
//! `Connection: close`), except after [`write_switching_protocols`], where the connection
//! carries WebSocket frames ([`crate::websocket`]). What a board serves:
//!
//! | request | answer |
//! |---|---|
//! | `GET` or `HEAD` of an [`asset`](crate::asset) | 200, its gzip bytes: [`write_asset_head`] |
//! | `GET /ws` asking for a WebSocket ([`Request::websocket`]) | 101: [`write_switching_protocols`] |
//! | anything else | the error's status: [`write_error`] (404, 400, 403, 405, 413, 426, 431, 505) |
//!
//! No request here carries a body: a method that would (`POST`, `PUT`, …) is answered 405, a
//! `GET` with one 413, and the body is never read.
//!
//! # Execution context
//!
//! Either; nothing blocks, allocates or panics, whatever the input.

use core::fmt;

use crate::Asset;
use crate::accept::{ACCEPT_LEN, accept_key, is_valid_key};

/// Most bytes a request head may take, its blank line included; a longer one is
/// [`RequestError::TooLong`] (431). A browser's requests take well under 1 KiB.
pub const MAX_HEAD_LEN: usize = 2048;

/// The path of the WebSocket that carries the link ([`Request::websocket`]).
pub const WEBSOCKET_PATH: &str = "/ws";

/// The request methods a board serves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Method {
    /// `GET`: an asset, or the WebSocket.
    Get,
    /// `HEAD`: an asset's head only.
    Head,
}

/// Why a request is refused. Each has its answer's status ([`RequestError::status`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum RequestError {
    /// The head is longer than [`MAX_HEAD_LEN`] (431).
    TooLong,
    /// The head is not HTTP/1.x: a bad request line, a header line without `:`, a control
    /// byte, a folded header line, a `Content-Length` that is not a number (400).
    Malformed,
    /// A method other than `GET` and `HEAD` (405).
    UnsupportedMethod,
    /// An HTTP version other than 1.0 and 1.1 (505).
    UnsupportedVersion,
    /// A request with a body: nothing served takes one (413).
    Body,
    /// No asset at that path (404).
    NotFound,
    /// A WebSocket request without `Upgrade: websocket`, `Connection: Upgrade` or a valid
    /// `Sec-WebSocket-Key` (400).
    BadUpgrade,
    /// A WebSocket request of a version other than 13 (426, with `Sec-WebSocket-Version: 13`).
    WebSocketVersion,
    /// A WebSocket request from a page of another site: its `Origin` is not the `Host` it
    /// asked (403). A page elsewhere on the web cannot drive the machine through the
    /// operator's browser.
    ForeignOrigin,
}

impl RequestError {
    /// The status of the answer.
    pub const fn status(self) -> Status {
        match self {
            Self::TooLong => Status::HeaderFieldsTooLarge,
            Self::Malformed | Self::BadUpgrade => Status::BadRequest,
            Self::UnsupportedMethod => Status::MethodNotAllowed,
            Self::UnsupportedVersion => Status::VersionNotSupported,
            Self::Body => Status::PayloadTooLarge,
            Self::NotFound => Status::NotFound,
            Self::WebSocketVersion => Status::UpgradeRequired,
            Self::ForeignOrigin => Status::Forbidden,
        }
    }
}

impl fmt::Display for RequestError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::TooLong => "request head too long",
            Self::Malformed => "malformed request",
            Self::UnsupportedMethod => "method not allowed (GET and HEAD only)",
            Self::UnsupportedVersion => "HTTP version not supported",
            Self::Body => "no request here takes a body",
            Self::NotFound => "not found",
            Self::BadUpgrade => "not a valid WebSocket request",
            Self::WebSocketVersion => "WebSocket version 13 only",
            Self::ForeignOrigin => "WebSocket from another site's page",
        })
    }
}

impl core::error::Error for RequestError {}

/// The statuses a board answers with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum Status {
    /// 101: the connection is a WebSocket from now on.
    SwitchingProtocols,
    /// 200.
    Ok,
    /// 400.
    BadRequest,
    /// 403.
    Forbidden,
    /// 404.
    NotFound,
    /// 405.
    MethodNotAllowed,
    /// 413.
    PayloadTooLarge,
    /// 426.
    UpgradeRequired,
    /// 431.
    HeaderFieldsTooLarge,
    /// 505.
    VersionNotSupported,
}

impl Status {
    /// The code and reason phrase, as on the status line.
    pub const fn line(self) -> &'static str {
        match self {
            Self::SwitchingProtocols => "101 Switching Protocols",
            Self::Ok => "200 OK",
            Self::BadRequest => "400 Bad Request",
            Self::Forbidden => "403 Forbidden",
            Self::NotFound => "404 Not Found",
            Self::MethodNotAllowed => "405 Method Not Allowed",
            Self::PayloadTooLarge => "413 Payload Too Large",
            Self::UpgradeRequired => "426 Upgrade Required",
            Self::HeaderFieldsTooLarge => "431 Request Header Fields Too Large",
            Self::VersionNotSupported => "505 HTTP Version Not Supported",
        }
    }

    /// The numeric code.
    pub fn code(self) -> u16 {
        self.line()
            .bytes()
            .take(3)
            .fold(0, |acc, d| acc * 10 + u16::from(d.wrapping_sub(b'0')))
    }
}

/// A parsed request head: what a board needs of it. Borrows the received bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Request<'a> {
    /// The method.
    pub method: Method,
    /// The request target as sent (`/`, `/ws`, `/app.js?v=2`).
    pub target: &'a str,
    /// `Upgrade` names `websocket`.
    pub upgrade_websocket: bool,
    /// `Connection` names `upgrade`.
    pub connection_upgrade: bool,
    /// `Sec-WebSocket-Key`, if sent.
    pub websocket_key: Option<&'a str>,
    /// `Sec-WebSocket-Version`, if sent.
    pub websocket_version: Option<&'a str>,
    /// `Host`, if sent.
    pub host: Option<&'a str>,
    /// `Origin`, if sent.
    pub origin: Option<&'a str>,
    /// `Content-Length`, if sent.
    pub content_length: Option<u64>,
    /// `Transfer-Encoding` was sent (a body of unknown length).
    pub transfer_encoding: bool,
}

/// What [`parse`] found in the bytes received so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Parsed<'a> {
    /// The head is not complete yet: read more and parse again.
    Partial,
    /// A whole head: the request, and how many bytes it took (what follows is not read).
    Complete {
        /// The request.
        request: Request<'a>,
        /// Bytes of the head, its blank line included.
        head_len: usize,
    },
}

/// Parse the head of a request from the bytes received so far (lines end with `\r\n` or a
/// bare `\n`).
///
/// Errors: [`RequestError::TooLong`] once `bytes` holds [`MAX_HEAD_LEN`] bytes without the
/// head's end; [`RequestError::Malformed`], [`RequestError::UnsupportedMethod`],
/// [`RequestError::UnsupportedVersion`], [`RequestError::Body`] as soon as the complete head
/// shows it. A request line is checked as soon as it is complete, so a client that sends
/// garbage is answered without waiting for a blank line.
pub fn parse(bytes: &[u8]) -> Result<Parsed<'_>, RequestError> {
    let window = bytes.get(..MAX_HEAD_LEN).unwrap_or(bytes);
    let Some(head_len) = head_end(window) else {
        if let Some(line) = first_line(window) {
            request_line(line)?;
        }
        return if bytes.len() >= MAX_HEAD_LEN {
            Err(RequestError::TooLong)
        } else {
            Ok(Parsed::Partial)
        };
    };
    let head = window.get(..head_len).unwrap_or_default();
    let mut lines = head.split(|&b| b == b'\n').map(trim_cr);
    let (method, target) = request_line(lines.next().unwrap_or_default())?;
    let mut request = Request {
        method,
        target,
        upgrade_websocket: false,
        connection_upgrade: false,
        websocket_key: None,
        websocket_version: None,
        host: None,
        origin: None,
        content_length: None,
        transfer_encoding: false,
    };
    for line in lines.filter(|l| !l.is_empty()) {
        header(&mut request, line)?;
    }
    let has_body = request.transfer_encoding || request.content_length.is_some_and(|n| n > 0);
    if has_body {
        return Err(RequestError::Body);
    }
    Ok(Parsed::Complete { request, head_len })
}

/// The length of the head (up to and including its blank line), if it is complete.
fn head_end(bytes: &[u8]) -> Option<usize> {
    let mut line_start = 0;
    for (i, &b) in bytes.iter().enumerate() {
        if b == b'\n' {
            let line = bytes.get(line_start..i).map(trim_cr).unwrap_or_default();
            if line.is_empty() && line_start > 0 {
                return Some(i + 1);
            }
            line_start = i + 1;
        }
    }
    None
}

/// The first line, once its end has arrived.
fn first_line(bytes: &[u8]) -> Option<&[u8]> {
    let end = bytes.iter().position(|&b| b == b'\n')?;
    bytes.get(..end).map(trim_cr)
}

fn trim_cr(line: &[u8]) -> &[u8] {
    line.strip_suffix(b"\r").unwrap_or(line)
}

/// `METHOD SP target SP HTTP/1.x`.
fn request_line(line: &[u8]) -> Result<(Method, &str), RequestError> {
    let mut parts = line.split(|&b| b == b' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(RequestError::Malformed);
    };
    if method.is_empty() || !method.iter().all(|&b| is_token(b)) {
        return Err(RequestError::Malformed);
    }
    let target = core::str::from_utf8(target).map_err(|_| RequestError::Malformed)?;
    if !target.starts_with('/') || !target.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(RequestError::Malformed);
    }
    let digits = version
        .strip_prefix(b"HTTP/")
        .ok_or(RequestError::Malformed)?;
    match digits {
        b"1.1" | b"1.0" => {}
        [a, b'.', b] if a.is_ascii_digit() && b.is_ascii_digit() => {
            return Err(RequestError::UnsupportedVersion);
        }
        _ => return Err(RequestError::Malformed),
    }
    match method {
        b"GET" => Ok((Method::Get, target)),
        b"HEAD" => Ok((Method::Head, target)),
        _ => Err(RequestError::UnsupportedMethod),
    }
}

/// A `tchar` of RFC 9110.
fn is_token(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b"!#$%&'*+-.^_`|~".contains(&b)
}

/// One header line into `request`.
fn header<'a>(request: &mut Request<'a>, line: &'a [u8]) -> Result<(), RequestError> {
    if line.first().is_some_and(|&b| b == b' ' || b == b'\t') {
        return Err(RequestError::Malformed);
    }
    let colon = line
        .iter()
        .position(|&b| b == b':')
        .ok_or(RequestError::Malformed)?;
    let name = line.get(..colon).unwrap_or_default();
    let value = line.get(colon + 1..).unwrap_or_default();
    if name.is_empty() || !name.iter().all(|&b| is_token(b)) {
        return Err(RequestError::Malformed);
    }
    if value.iter().any(|&b| b != b'\t' && (b < 0x20 || b == 0x7f)) {
        return Err(RequestError::Malformed);
    }
    let value = value.trim_ascii();
    let text = || core::str::from_utf8(value).map_err(|_| RequestError::Malformed);
    let is = |n: &str| name.eq_ignore_ascii_case(n.as_bytes());
    if is("upgrade") {
        request.upgrade_websocket |= has_token(value, b"websocket");
    } else if is("connection") {
        request.connection_upgrade |= has_token(value, b"upgrade");
    } else if is("sec-websocket-key") {
        request.websocket_key = Some(text()?);
    } else if is("sec-websocket-version") {
        request.websocket_version = Some(text()?);
    } else if is("host") {
        request.host = Some(text()?);
    } else if is("origin") {
        request.origin = Some(text()?);
    } else if is("transfer-encoding") {
        request.transfer_encoding = true;
    } else if is("content-length") {
        let n = decimal(value).ok_or(RequestError::Malformed)?;
        if request.content_length.is_some_and(|m| m != n) {
            return Err(RequestError::Malformed);
        }
        request.content_length = Some(n);
    }
    Ok(())
}

/// Whether the comma-separated list `value` holds `token` (any case).
fn has_token(value: &[u8], token: &[u8]) -> bool {
    value
        .split(|&b| b == b',')
        .any(|t| t.trim_ascii().eq_ignore_ascii_case(token))
}

/// A decimal number of at most 18 digits.
fn decimal(digits: &[u8]) -> Option<u64> {
    if digits.is_empty() || digits.len() > 18 || !digits.iter().all(u8::is_ascii_digit) {
        return None;
    }
    Some(
        digits
            .iter()
            .fold(0u64, |acc, &d| acc * 10 + u64::from(d - b'0')),
    )
}

impl<'a> Request<'a> {
    /// The path of the target, without its query.
    pub fn path(&self) -> &'a str {
        self.target.split('?').next().unwrap_or(self.target)
    }

    /// Whether this request is for the WebSocket path ([`WEBSOCKET_PATH`]).
    pub fn wants_websocket(&self) -> bool {
        self.path() == WEBSOCKET_PATH
    }

    /// The client's `Sec-WebSocket-Key`, if this is a valid WebSocket opening handshake
    /// (RFC 6455 §4.2.1): a `GET` with `Upgrade: websocket`, `Connection: Upgrade`, a key of
    /// 16 bytes in base64, version 13, and no `Origin` or one whose host is the `Host` asked
    /// (a page served by the board itself).
    ///
    /// Errors: [`RequestError::UnsupportedMethod`], [`RequestError::BadUpgrade`],
    /// [`RequestError::WebSocketVersion`], [`RequestError::ForeignOrigin`].
    pub fn websocket(&self) -> Result<&'a str, RequestError> {
        if self.method != Method::Get {
            return Err(RequestError::UnsupportedMethod);
        }
        let key = self
            .websocket_key
            .filter(|k| is_valid_key(k.as_bytes()))
            .filter(|_| self.upgrade_websocket && self.connection_upgrade)
            .ok_or(RequestError::BadUpgrade)?;
        if self.websocket_version != Some("13") {
            return Err(RequestError::WebSocketVersion);
        }
        if let Some(origin) = self.origin {
            let origin_host = origin.split_once("://").map_or(origin, |(_, h)| h);
            let same = self
                .host
                .is_some_and(|h| h.eq_ignore_ascii_case(origin_host));
            if !same {
                return Err(RequestError::ForeignOrigin);
            }
        }
        Ok(key)
    }

    /// What to answer: the asset at the path, or the reason there is none.
    ///
    /// Errors: [`RequestError::NotFound`].
    pub fn asset(&self) -> Result<&'static Asset, RequestError> {
        crate::asset(self.path()).ok_or(RequestError::NotFound)
    }
}

/// What a request is answered with ([`Request::route`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Route<'a> {
    /// 200 and the asset: its head ([`write_asset_head`]), then its gzip bytes unless `body`
    /// is `false` (a `HEAD`); then close.
    Asset {
        /// The asset.
        asset: &'static Asset,
        /// Whether the body is sent (`GET`) or not (`HEAD`).
        body: bool,
    },
    /// 101 ([`write_switching_protocols`] with `key`); the connection is a WebSocket from then
    /// on.
    WebSocket {
        /// The client's `Sec-WebSocket-Key`.
        key: &'a str,
    },
    /// The refusal ([`write_error`]), then close.
    Refuse(RequestError),
}

impl<'a> Request<'a> {
    /// What to answer: the WebSocket at [`WEBSOCKET_PATH`], an asset, or a refusal.
    pub fn route(&self) -> Route<'a> {
        let routed = if self.wants_websocket() {
            self.websocket().map(|key| Route::WebSocket { key })
        } else {
            self.asset().map(|asset| Route::Asset {
                asset,
                body: self.method == Method::Get,
            })
        };
        routed.unwrap_or_else(Route::Refuse)
    }
}

/// The caller's buffer is too small for the answer's head.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct BufferTooSmall;

impl fmt::Display for BufferTooSmall {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("buffer too small for the response head")
    }
}

impl core::error::Error for BufferTooSmall {}

/// Bytes appended to a caller's buffer.
pub(crate) struct Out<'b> {
    buf: &'b mut [u8],
    len: usize,
}

impl<'b> Out<'b> {
    pub(crate) fn new(buf: &'b mut [u8]) -> Self {
        Self { buf, len: 0 }
    }

    pub(crate) fn put(&mut self, bytes: &[u8]) -> Result<&mut Self, BufferTooSmall> {
        let end = self.len.checked_add(bytes.len()).ok_or(BufferTooSmall)?;
        self.buf
            .get_mut(self.len..end)
            .ok_or(BufferTooSmall)?
            .copy_from_slice(bytes);
        self.len = end;
        Ok(self)
    }

    fn number(&mut self, mut n: usize) -> Result<&mut Self, BufferTooSmall> {
        let mut digits = [0u8; 20];
        let mut at = digits.len();
        loop {
            at -= 1;
            if let Some(d) = digits.get_mut(at) {
                *d = b'0' + (n % 10) as u8;
            }
            n /= 10;
            if n == 0 || at == 0 {
                break;
            }
        }
        self.put(digits.get(at..).unwrap_or_default())
    }

    fn status(&mut self, status: Status) -> Result<&mut Self, BufferTooSmall> {
        self.put(b"HTTP/1.1 ")?
            .put(status.line().as_bytes())?
            .put(b"\r\n")
    }

    fn header(&mut self, name: &str, value: &[u8]) -> Result<&mut Self, BufferTooSmall> {
        self.put(name.as_bytes())?
            .put(b": ")?
            .put(value)?
            .put(b"\r\n")
    }

    pub(crate) fn len(&self) -> usize {
        self.len
    }
}

/// Write the head of a 200 answer carrying `asset` into `out`; returns its length. The body
/// that follows is [`Asset::gzip`], sent as it is (`Content-Encoding: gzip`), left out for a
/// `HEAD`. `Cache-Control: no-cache`: a browser asks again after a firmware update.
///
/// Errors: `out` is too small (240 bytes always suffice).
pub fn write_asset_head(out: &mut [u8], asset: &Asset) -> Result<usize, BufferTooSmall> {
    let mut w = Out::new(out);
    w.status(Status::Ok)?
        .header("Content-Type", asset.content_type.as_bytes())?
        .header("Content-Encoding", b"gzip")?
        .put(b"Content-Length: ")?
        .number(asset.gzip.len())?
        .put(b"\r\n")?
        .header("Cache-Control", b"no-cache")?
        .header("Connection", b"close")?
        .put(b"\r\n")?;
    Ok(w.len())
}

/// Write the whole answer to a refused request into `out` (a short plain-text body naming the
/// error); returns its length. A 405 names the methods served (`Allow: GET, HEAD`), a 426
/// the WebSocket version (`Sec-WebSocket-Version: 13`).
///
/// Errors: `out` is too small (256 bytes always suffice).
pub fn write_error(out: &mut [u8], error: RequestError) -> Result<usize, BufferTooSmall> {
    let status = error.status();
    let mut body = [0u8; 96];
    let mut b = Out::new(&mut body);
    b.put(status.line().as_bytes())?.put(b": ")?;
    write_display(&mut b, &error)?;
    b.put(b"\n")?;
    let body_len = b.len();
    let mut w = Out::new(out);
    w.status(status)?
        .header("Content-Type", b"text/plain; charset=utf-8")?
        .put(b"Content-Length: ")?
        .number(body_len)?
        .put(b"\r\n")?;
    match error {
        RequestError::UnsupportedMethod => {
            w.header("Allow", b"GET, HEAD")?;
        }
        RequestError::WebSocketVersion => {
            w.header("Sec-WebSocket-Version", b"13")?;
        }
        _ => {}
    }
    w.header("Connection", b"close")?
        .put(b"\r\n")?
        .put(body.get(..body_len).unwrap_or_default())?;
    Ok(w.len())
}

/// The error's `Display` into `w`.
fn write_display(w: &mut Out<'_>, error: &RequestError) -> Result<(), BufferTooSmall> {
    struct Adapter<'w, 'b>(&'w mut Out<'b>);
    impl fmt::Write for Adapter<'_, '_> {
        fn write_str(&mut self, s: &str) -> fmt::Result {
            self.0.put(s.as_bytes()).map(|_| ()).map_err(|_| fmt::Error)
        }
    }
    fmt::write(&mut Adapter(w), format_args!("{error}")).map_err(|_| BufferTooSmall)
}

/// Write the 101 answer accepting a WebSocket whose client sent `key`
/// ([`Request::websocket`]) into `out`; returns its length. No subprotocol, no extension.
///
/// Errors: `out` is too small (129 bytes always suffice).
pub fn write_switching_protocols(out: &mut [u8], key: &str) -> Result<usize, BufferTooSmall> {
    let accept: [u8; ACCEPT_LEN] = accept_key(key.as_bytes());
    let mut w = Out::new(out);
    w.status(Status::SwitchingProtocols)?
        .header("Upgrade", b"websocket")?
        .header("Connection", b"Upgrade")?
        .header("Sec-WebSocket-Accept", &accept)?
        .put(b"\r\n")?;
    Ok(w.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    const UPGRADE: &[u8] = b"GET /ws HTTP/1.1\r\nHost: 192.168.4.1\r\nUpgrade: websocket\r\n\
        Connection: keep-alive, Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\
        Origin: http://192.168.4.1\r\nSec-WebSocket-Version: 13\r\n\r\n";

    fn complete(bytes: &[u8]) -> Request<'_> {
        match parse(bytes) {
            Ok(Parsed::Complete { request, head_len }) => {
                assert_eq!(head_len, bytes.len());
                request
            }
            other => panic!("{other:?}"),
        }
    }

    fn text(out: &[u8]) -> &str {
        core::str::from_utf8(out).unwrap()
    }

    #[test]
    fn a_get_of_the_page() {
        let r = complete(b"GET /?v=1 HTTP/1.1\r\nHost: forja\r\nAccept: */*\r\n\r\n");
        assert_eq!((r.method, r.target, r.path()), (Method::Get, "/?v=1", "/"));
        assert_eq!(r.host, Some("forja"));
        assert!(!r.wants_websocket());
        let asset = r.asset().unwrap();
        let mut out = [0u8; 240];
        let n = write_asset_head(&mut out, asset).unwrap();
        let head = text(&out[..n]);
        assert!(head.starts_with("HTTP/1.1 200 OK\r\n"), "{head}");
        assert!(head.contains("Content-Encoding: gzip\r\n"));
        assert!(head.contains(&std::format!("Content-Length: {}\r\n", asset.gzip.len())));
        assert!(head.contains("Content-Type: text/html"));
        assert!(head.contains("Cache-Control: no-cache\r\n"));
        assert!(head.ends_with("\r\n\r\n"));
    }

    #[test]
    fn requests_are_routed() {
        let page = complete(b"HEAD / HTTP/1.1\r\n\r\n");
        assert!(matches!(page.route(), Route::Asset { body: false, .. }));
        assert_eq!(
            complete(UPGRADE).route(),
            Route::WebSocket {
                key: "dGhlIHNhbXBsZSBub25jZQ=="
            }
        );
        let plain_ws = complete(b"GET /ws HTTP/1.1\r\n\r\n");
        assert_eq!(plain_ws.route(), Route::Refuse(RequestError::BadUpgrade));
        let missing = complete(b"GET /x.js HTTP/1.1\r\n\r\n");
        assert_eq!(missing.route(), Route::Refuse(RequestError::NotFound));
    }

    #[test]
    fn a_head_arrives_in_pieces_and_bare_newlines_do() {
        let bytes = b"HEAD /nothing HTTP/1.0\nHost: x\n\n";
        for cut in 0..bytes.len() {
            assert_eq!(parse(&bytes[..cut]), Ok(Parsed::Partial), "{cut}");
        }
        let r = complete(bytes);
        assert_eq!(r.method, Method::Head);
        assert_eq!(r.asset(), Err(RequestError::NotFound));
    }

    #[test]
    fn the_rfc_6455_handshake() {
        let r = complete(UPGRADE);
        assert!(r.wants_websocket());
        let key = r.websocket().unwrap();
        let mut out = [0u8; 129];
        let n = write_switching_protocols(&mut out, key).unwrap();
        assert_eq!(
            text(&out[..n]),
            "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
             Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n\r\n"
        );
        assert_eq!(
            write_switching_protocols(&mut out[..128], key),
            Err(BufferTooSmall)
        );
    }

    #[test]
    fn bad_handshakes_are_named() {
        let swap = |from: &str, to: &str| {
            std::string::String::from_utf8(UPGRADE.to_vec())
                .unwrap()
                .replace(from, to)
        };
        let cases = [
            (
                swap("Upgrade: websocket", "Upgrade: h2c"),
                RequestError::BadUpgrade,
            ),
            (
                swap("keep-alive, Upgrade", "keep-alive"),
                RequestError::BadUpgrade,
            ),
            (
                swap("dGhlIHNhbXBsZSBub25jZQ==", "short=="),
                RequestError::BadUpgrade,
            ),
            (
                swap("Version: 13", "Version: 8"),
                RequestError::WebSocketVersion,
            ),
            (
                swap("http://192.168.4.1", "https://evil.example"),
                RequestError::ForeignOrigin,
            ),
        ];
        for (head, error) in cases {
            assert_eq!(complete(head.as_bytes()).websocket(), Err(error), "{head}");
        }
        let no_origin = swap("Origin: http://192.168.4.1\r\n", "");
        assert!(complete(no_origin.as_bytes()).websocket().is_ok());
    }

    #[test]
    fn refusals_carry_their_status() {
        let cases: [(&[u8], RequestError, u16); 7] = [
            (
                b"POST /upload HTTP/1.1\r\n",
                RequestError::UnsupportedMethod,
                405,
            ),
            (b"\x00\x01garbage\x7f\n", RequestError::Malformed, 400),
            (b"GET / HTTP/2.0\r\n", RequestError::UnsupportedVersion, 505),
            (b"GET nothing HTTP/1.1\r\n", RequestError::Malformed, 400),
            (
                b"GET / HTTP/1.1\r\nContent-Length: 5\r\n\r\n",
                RequestError::Body,
                413,
            ),
            (
                b"GET / HTTP/1.1\r\nContent-Length: x\r\n\r\n",
                RequestError::Malformed,
                400,
            ),
            (
                b"GET / HTTP/1.1\r\n folded\r\n\r\n",
                RequestError::Malformed,
                400,
            ),
        ];
        for (bytes, error, code) in cases {
            assert_eq!(parse(bytes), Err(error), "{bytes:?}");
            assert_eq!(error.status().code(), code);
            let mut out = [0u8; 256];
            let n = write_error(&mut out, error).unwrap();
            let answer = text(&out[..n]);
            assert!(
                answer.starts_with(&std::format!("HTTP/1.1 {code} ")),
                "{answer}"
            );
            assert!(answer.contains("Connection: close\r\n"));
        }
        let mut out = [0u8; 256];
        let n = write_error(&mut out, RequestError::UnsupportedMethod).unwrap();
        assert!(text(&out[..n]).contains("Allow: GET, HEAD\r\n"));
    }

    #[test]
    fn a_head_that_never_ends_is_too_long() {
        let mut bytes = std::vec::Vec::from(&b"GET / HTTP/1.1\r\n"[..]);
        bytes.resize(MAX_HEAD_LEN - 1, b'a');
        assert_eq!(parse(&bytes), Ok(Parsed::Partial));
        bytes.push(b'a');
        assert_eq!(parse(&bytes), Err(RequestError::TooLong));
        assert_eq!(RequestError::TooLong.status().code(), 431);
    }

    #[test]
    fn every_answer_fits_its_stated_buffer() {
        let errors = [
            RequestError::TooLong,
            RequestError::Malformed,
            RequestError::UnsupportedMethod,
            RequestError::UnsupportedVersion,
            RequestError::Body,
            RequestError::NotFound,
            RequestError::BadUpgrade,
            RequestError::WebSocketVersion,
            RequestError::ForeignOrigin,
        ];
        for e in errors {
            assert!(write_error(&mut [0u8; 256], e).is_ok(), "{e}");
        }
        for a in crate::ASSETS {
            assert!(write_asset_head(&mut [0u8; 240], a).is_ok(), "{}", a.path);
        }
    }
}
