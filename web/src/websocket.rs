//! A sans-IO WebSocket codec (RFC 6455), server side: a streaming [`Decoder`] of the client's
//! frames and writers of the server's.
//!
//! The decoder takes the bytes of a connection as they arrive, split anywhere
//! ([`Decoder::feed`], as `forja_protocol::stream::Decoder` does for a link), and gives the
//! payload of data frames unmasked, in pieces of at most [`CHUNK`] bytes, as it comes: no
//! message is held whole, so a board's memory does not grow with a message. Control frames
//! (ping, pong, close) are given whole. Everything that RFC 6455 requires of a client is
//! checked in the frame's header, before any byte of its payload is given, so a malformed frame
//! gives nothing:
//!
//! | error | close code |
//! |---|---|
//! | [`FrameError::Unmasked`], [`FrameError::ReservedBits`], [`FrameError::BadOpcode`], [`FrameError::ControlTooLong`], [`FrameError::FragmentedControl`], [`FrameError::UnexpectedContinuation`], [`FrameError::ExpectedContinuation`], [`FrameError::BadClose`] | 1002 (protocol error) |
//! | [`FrameError::TooLong`]: a message longer than the decoder's limit | 1009 (message too big) |
//!
//! After an error the decoder gives nothing more; the server sends the close frame of
//! [`FrameError::close_code`] ([`write_close`]) and closes the connection. After a close frame
//! from the client the decoder takes and ignores whatever follows.
//!
//! Text and binary messages are both data: their bytes are a link's bytes, and what they mean
//! is for the protocol decoder behind the link to judge (a byte that neither G-code nor a frame
//! can carry is garbage there, as on a UART). The text of a text message is therefore not
//! checked for UTF-8 here.
//!
//! The server's frames are unmasked and unfragmented ([`write_header`], [`write_frame`]); a
//! text frame must carry UTF-8, which [`text_ready`] makes of a link's reply bytes.
//!
//! # Execution context
//!
//! Either; nothing blocks, allocates or panics, whatever the input.

use core::fmt;

use crate::http::{BufferTooSmall, Out};

/// The payload of a data frame is given in pieces of at most this many bytes.
pub const CHUNK: usize = 256;

/// Most payload bytes of a control frame (RFC 6455 §5.5).
pub const MAX_CONTROL: usize = 125;

/// Most bytes of a server frame's header ([`write_header`]).
pub const MAX_HEADER: usize = 10;

/// The limit boards give their decoders: at most 64 KiB in one message (a page sends a few
/// lines per message).
pub const MAX_MESSAGE_LEN: u64 = 64 * 1024;

/// The line a WebSocket client is sent first when it becomes a watcher: another client
/// controls the machine, this one sees what the controller sends and its own input is refused.
pub const WATCHING_NOTICE: &[u8] = b"// watching: another client controls the machine\n";

/// The line a WebSocket client is sent first when it becomes the controlling client (at once,
/// or when the controller it watched left).
pub const CONTROL_NOTICE: &[u8] = b"// control: this client controls the machine\n";

/// A frame's opcode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Opcode {
    /// 0x0: the next frame of a fragmented message.
    Continuation,
    /// 0x1: a text message.
    Text,
    /// 0x2: a binary message.
    Binary,
    /// 0x8: the closing handshake.
    Close,
    /// 0x9: ping, answered with a pong carrying the same payload.
    Ping,
    /// 0xA: pong.
    Pong,
}

impl Opcode {
    const fn bits(self) -> u8 {
        match self {
            Self::Continuation => 0x0,
            Self::Text => 0x1,
            Self::Binary => 0x2,
            Self::Close => 0x8,
            Self::Ping => 0x9,
            Self::Pong => 0xA,
        }
    }

    const fn from_bits(bits: u8) -> Option<Self> {
        Some(match bits {
            0x0 => Self::Continuation,
            0x1 => Self::Text,
            0x2 => Self::Binary,
            0x8 => Self::Close,
            0x9 => Self::Ping,
            0xA => Self::Pong,
            _ => return None,
        })
    }

    const fn is_control(self) -> bool {
        matches!(self, Self::Close | Self::Ping | Self::Pong)
    }
}

/// Close codes (RFC 6455 §7.4.1) a board sends.
pub mod close_code {
    /// 1000: normal closure (the server's idle time-out, the echo of a client's close).
    pub const NORMAL: u16 = 1000;
    /// 1001: the server is going away.
    pub const GOING_AWAY: u16 = 1001;
    /// 1002: the client broke the protocol.
    pub const PROTOCOL_ERROR: u16 = 1002;
    /// 1003: data of a kind the server does not take.
    pub const UNSUPPORTED_DATA: u16 = 1003;
    /// 1008: a message that breaks the server's policy (a client that does not read).
    pub const POLICY: u16 = 1008;
    /// 1009: a message larger than the server takes.
    pub const TOO_BIG: u16 = 1009;
}

/// A client frame that breaks RFC 6455 or the decoder's limit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum FrameError {
    /// A client frame without a mask.
    Unmasked,
    /// RSV1–3 set (no extension was agreed).
    ReservedBits,
    /// An opcode RFC 6455 reserves (3–7, 0xB–0xF).
    BadOpcode,
    /// A control frame with more than [`MAX_CONTROL`] payload bytes.
    ControlTooLong,
    /// A control frame without FIN.
    FragmentedControl,
    /// A continuation frame with no message begun.
    UnexpectedContinuation,
    /// A text or binary frame while a fragmented message is still open.
    ExpectedContinuation,
    /// A message longer than the decoder's limit, or a 64-bit length with its top bit set.
    TooLong,
    /// A close frame whose payload is one byte, or whose code may not be sent.
    BadClose,
}

impl FrameError {
    /// The code of the close frame that answers it: 1009 for [`FrameError::TooLong`], 1002
    /// for the others.
    pub const fn close_code(self) -> u16 {
        match self {
            Self::TooLong => close_code::TOO_BIG,
            _ => close_code::PROTOCOL_ERROR,
        }
    }
}

impl FrameError {
    /// A short description, the reason of the close frame that answers it.
    pub const fn reason(self) -> &'static str {
        match self {
            Self::Unmasked => "unmasked client frame",
            Self::ReservedBits => "reserved bits set",
            Self::BadOpcode => "reserved opcode",
            Self::ControlTooLong => "control frame too long",
            Self::FragmentedControl => "fragmented control frame",
            Self::UnexpectedContinuation => "continuation without a message",
            Self::ExpectedContinuation => "new message inside a fragmented one",
            Self::TooLong => "message too long",
            Self::BadClose => "bad close frame",
        }
    }
}

impl fmt::Display for FrameError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.reason())
    }
}

impl core::error::Error for FrameError {}

/// What the decoder found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event<'d> {
    /// Payload bytes of a text or binary message, unmasked: at most [`CHUNK`] bytes; a message
    /// comes in as many pieces as it takes.
    Data(&'d [u8]),
    /// A ping: answer it with a pong carrying the same payload ([`write_frame`]).
    Ping(&'d [u8]),
    /// A pong (an answer to a ping, or unsolicited): nothing to do.
    Pong(&'d [u8]),
    /// The client closes: answer with a close frame (echoing `code`, or
    /// [`close_code::NORMAL`]) and close the connection. The decoder ignores what follows.
    Close {
        /// The status code, if the client sent one.
        code: Option<u16>,
        /// The reason, if any (not checked for UTF-8).
        reason: &'d [u8],
    },
}

/// What [`Decoder::feed`] gives: the next event, and the input it has not looked at.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FeedResult<'d, 'i> {
    /// The next event, or `None` when the input is used up.
    pub event: Option<Event<'d>>,
    /// The input not yet looked at: pass it to the next call.
    pub remaining: &'i [u8],
}

/// Where the decoder is in a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// Reading a header: `have` of its bytes are in `header`.
    Header,
    /// Reading the payload: `left` bytes of it.
    Payload,
    /// A client close came; everything after it is ignored.
    Closed,
    /// A protocol error; nothing more is decoded.
    Failed(FrameError),
}

/// The streaming decoder of one connection's client frames. See the
/// [module documentation](self).
#[derive(Debug, Clone)]
pub struct Decoder {
    state: State,
    header: [u8; 14],
    have: usize,
    opcode: Opcode,
    mask: [u8; 4],
    /// Bytes of the current frame's payload unmasked so far (indexes the mask).
    done: u64,
    /// Bytes of the current frame's payload still to come.
    left: u64,
    /// A data message is open (its last frame had no FIN).
    open: bool,
    /// Bytes of the open message so far.
    message: u64,
    max_message: u64,
    /// Unmasked payload: a data piece, or a whole control frame.
    buf: [u8; CHUNK],
    /// Bytes of a control frame's payload in `buf`.
    control: usize,
}

impl Decoder {
    /// A decoder for a new connection, taking messages of at most `max_message_len` bytes
    /// (boards give [`MAX_MESSAGE_LEN`]).
    pub const fn new(max_message_len: u64) -> Self {
        Self {
            state: State::Header,
            header: [0; 14],
            have: 0,
            opcode: Opcode::Continuation,
            mask: [0; 4],
            done: 0,
            left: 0,
            open: false,
            message: 0,
            max_message: max_message_len,
            buf: [0; CHUNK],
            control: 0,
        }
    }

    /// The error that stopped the decoder, if any.
    pub fn error(&self) -> Option<FrameError> {
        match self.state {
            State::Failed(e) => Some(e),
            _ => None,
        }
    }

    /// Whether the client sent its close frame.
    pub fn is_closed(&self) -> bool {
        self.state == State::Closed
    }

    /// Decode `input` up to the next event. Call again with [`FeedResult::remaining`] until
    /// `event` is `None` (the input is used up). The same events come for any split of the
    /// same bytes (data pieces apart: their cut follows the input's).
    ///
    /// Errors: the first [`FrameError`] of the stream, again at every later call. Nothing of
    /// the frame in error is given.
    pub fn feed<'d, 'i>(&'d mut self, input: &'i [u8]) -> Result<FeedResult<'d, 'i>, FrameError> {
        let mut rest = input;
        loop {
            match self.state {
                State::Failed(e) => return Err(e),
                State::Closed => {
                    return Ok(FeedResult {
                        event: None,
                        remaining: &[],
                    });
                }
                State::Header => {
                    let Some((&byte, tail)) = rest.split_first() else {
                        return Ok(FeedResult {
                            event: None,
                            remaining: rest,
                        });
                    };
                    rest = tail;
                    if let Some(slot) = self.header.get_mut(self.have) {
                        *slot = byte;
                    }
                    self.have += 1;
                    match self.header_done() {
                        Err(e) => {
                            self.state = State::Failed(e);
                            return Err(e);
                        }
                        Ok(false) => {}
                        Ok(true) => {
                            self.state = State::Payload;
                            if self.left == 0 && self.frame_end()?.is_some() {
                                return Ok(self.control_event(rest));
                            }
                        }
                    }
                }
                State::Payload => {
                    if rest.is_empty() {
                        return Ok(FeedResult {
                            event: None,
                            remaining: rest,
                        });
                    }
                    let (piece, remaining) = self.payload(rest);
                    rest = remaining;
                    if self.left == 0 && self.frame_end()?.is_some() {
                        return Ok(self.control_event(rest));
                    }
                    if let Some(len) = piece {
                        return Ok(FeedResult {
                            event: self.buf.get(..len).map(Event::Data),
                            remaining: rest,
                        });
                    }
                }
            }
        }
    }

    /// Give every event of `input` to `on_event`; the error that stops the stream, if any.
    ///
    /// Errors: as [`Decoder::feed`]; the events before the error were given.
    pub fn feed_all(
        &mut self,
        input: &[u8],
        mut on_event: impl FnMut(Event<'_>),
    ) -> Result<(), FrameError> {
        let mut window = input;
        loop {
            let fed = self.feed(window)?;
            window = fed.remaining;
            match fed.event {
                Some(event) => on_event(event),
                None => return Ok(()),
            }
        }
    }

    /// Whether the header in `header[..have]` is complete, having checked it; on completion
    /// the frame's fields are set.
    fn header_done(&mut self) -> Result<bool, FrameError> {
        let [b0, b1, ..] = self.header;
        if self.have == 1 {
            if b0 & 0x70 != 0 {
                return Err(FrameError::ReservedBits);
            }
            let opcode = Opcode::from_bits(b0 & 0x0F).ok_or(FrameError::BadOpcode)?;
            let fin = b0 & 0x80 != 0;
            if opcode.is_control() && !fin {
                return Err(FrameError::FragmentedControl);
            }
            match opcode {
                Opcode::Continuation if !self.open => {
                    return Err(FrameError::UnexpectedContinuation);
                }
                Opcode::Text | Opcode::Binary if self.open => {
                    return Err(FrameError::ExpectedContinuation);
                }
                _ => {}
            }
            return Ok(false);
        }
        if self.have == 2 {
            if b1 & 0x80 == 0 {
                return Err(FrameError::Unmasked);
            }
            let opcode = self.current_opcode();
            if opcode.is_control() && b1 & 0x7F > MAX_CONTROL as u8 {
                return Err(FrameError::ControlTooLong);
            }
        }
        let extra = match b1 & 0x7F {
            126 => 2,
            127 => 8,
            _ => 0,
        };
        if self.have < 2 + extra + 4 {
            return Ok(false);
        }
        let length = match extra {
            0 => u64::from(b1 & 0x7F),
            _ => self
                .header
                .get(2..2 + extra)
                .unwrap_or_default()
                .iter()
                .fold(0u64, |acc, &b| (acc << 8) | u64::from(b)),
        };
        if length >> 63 != 0 {
            return Err(FrameError::TooLong);
        }
        let opcode = self.current_opcode();
        if !opcode.is_control() {
            let start = if opcode == Opcode::Continuation {
                self.message
            } else {
                0
            };
            let total = start.saturating_add(length);
            if total > self.max_message {
                return Err(FrameError::TooLong);
            }
            self.message = total;
            self.open = b0 & 0x80 == 0;
        }
        for (i, m) in self.mask.iter_mut().enumerate() {
            *m = self.header.get(2 + extra + i).copied().unwrap_or(0);
        }
        self.opcode = opcode;
        self.left = length;
        self.done = 0;
        self.control = 0;
        self.have = 0;
        Ok(true)
    }

    fn current_opcode(&self) -> Opcode {
        Opcode::from_bits(self.header.first().copied().unwrap_or(0) & 0x0F)
            .unwrap_or(Opcode::Continuation)
    }

    /// Unmask payload bytes from `input`: a data frame's into a piece (its length returned),
    /// a control frame's after what it already has.
    fn payload<'i>(&mut self, input: &'i [u8]) -> (Option<usize>, &'i [u8]) {
        let (start, room) = if self.opcode.is_control() {
            (self.control, MAX_CONTROL.saturating_sub(self.control))
        } else {
            (0, CHUNK)
        };
        let n = input
            .len()
            .min(room)
            .min(usize::try_from(self.left).unwrap_or(usize::MAX));
        let (taken, rest) = input.split_at(n.min(input.len()));
        let dst = self
            .buf
            .get_mut(start..start + taken.len())
            .unwrap_or_default();
        for (d, &s) in dst.iter_mut().zip(taken) {
            let key = self
                .mask
                .get((self.done % 4) as usize)
                .copied()
                .unwrap_or(0);
            *d = s ^ key;
            self.done += 1;
        }
        self.left -= taken.len() as u64;
        if self.opcode.is_control() {
            self.control += taken.len();
            (None, rest)
        } else {
            (Some(taken.len()).filter(|&n| n > 0), rest)
        }
    }

    /// The frame's payload is all in: `Some` for a control frame, whose event
    /// [`Decoder::control_event`] gives, `None` for a data frame (its pieces were given).
    /// Readies the decoder for the next header.
    ///
    /// Errors: a close frame's payload is not a code a peer may send
    /// ([`FrameError::BadClose`]).
    fn frame_end(&mut self) -> Result<Option<Opcode>, FrameError> {
        self.state = State::Header;
        match self.opcode {
            Opcode::Close => {
                self.check_close()
                    .inspect_err(|&e| self.state = State::Failed(e))?;
                self.state = State::Closed;
                Ok(Some(Opcode::Close))
            }
            Opcode::Ping | Opcode::Pong => Ok(Some(self.opcode)),
            Opcode::Text | Opcode::Binary | Opcode::Continuation => {
                if !self.open {
                    self.message = 0;
                }
                Ok(None)
            }
        }
    }

    /// A close frame's payload: no code, or a code a peer may send and a reason.
    fn check_close(&self) -> Result<(), FrameError> {
        match self.close_code() {
            Some(1000..=1003 | 1007..=1011 | 3000..=4999) | None if self.control != 1 => Ok(()),
            _ => Err(FrameError::BadClose),
        }
    }

    fn close_code(&self) -> Option<u16> {
        match self.buf.get(..self.control)? {
            [hi, lo, ..] => Some(u16::from_be_bytes([*hi, *lo])),
            _ => None,
        }
    }

    /// The event of the control frame that just ended.
    fn control_event<'i>(&self, remaining: &'i [u8]) -> FeedResult<'_, 'i> {
        let payload = self.buf.get(..self.control).unwrap_or_default();
        let event = match self.opcode {
            Opcode::Ping => Event::Ping(payload),
            Opcode::Pong => Event::Pong(payload),
            _ => Event::Close {
                code: self.close_code(),
                reason: payload.get(2..).unwrap_or_default(),
            },
        };
        FeedResult {
            event: Some(event),
            remaining,
        }
    }
}

/// Write the header of an unmasked, final server frame of `opcode` with `len` payload bytes
/// into `out`; returns its length (2, 4 or 10 bytes, at most [`MAX_HEADER`]). The payload
/// follows it as it is.
///
/// Errors: `out` is too small.
pub fn write_header(out: &mut [u8], opcode: Opcode, len: usize) -> Result<usize, BufferTooSmall> {
    let mut w = Out::new(out);
    w.put(&[0x80 | opcode.bits()])?;
    match len {
        0..=125 => w.put(&[len as u8])?,
        126..=0xFFFF => w.put(&[126])?.put(&(len as u16).to_be_bytes())?,
        _ => w.put(&[127])?.put(&(len as u64).to_be_bytes())?,
    };
    Ok(w.len())
}

/// Write a whole unmasked server frame (header and `payload`) into `out`; returns its length.
///
/// Errors: `out` is too small.
pub fn write_frame(
    out: &mut [u8],
    opcode: Opcode,
    payload: &[u8],
) -> Result<usize, BufferTooSmall> {
    let header = write_header(out, opcode, payload.len())?;
    let mut w = Out::new(out.get_mut(header..).unwrap_or_default());
    w.put(payload)?;
    Ok(header + w.len())
}

/// Write a close frame with `code` and `reason` (cut to fit the 125 bytes of a control
/// frame) into `out`; returns its length.
///
/// Errors: `out` is too small (2 + 125 bytes always suffice).
pub fn write_close(out: &mut [u8], code: u16, reason: &str) -> Result<usize, BufferTooSmall> {
    let mut payload = [0u8; MAX_CONTROL];
    let mut w = Out::new(&mut payload);
    w.put(&code.to_be_bytes())?;
    let reason = reason.as_bytes();
    w.put(
        reason
            .get(..reason.len().min(MAX_CONTROL - 2))
            .unwrap_or_default(),
    )?;
    let len = w.len();
    write_frame(out, Opcode::Close, payload.get(..len).unwrap_or_default())
}

/// Make the start of `bytes` fit a text frame: every byte that is not part of valid UTF-8 is
/// replaced by `?` in place, and the length of the prefix to send now is returned: all of it,
/// but for a character whose last bytes have not come yet (at most 3 bytes held back for
/// the next call, when the bytes after them may complete it). With `end` (nothing more will
/// come), nothing is held back: an unfinished character becomes `?`s.
///
/// A link's reply bytes are ASCII but for text the host itself sent (an `M117` message, a
/// file name): this keeps a browser, which closes a connection on a text frame that is not
/// UTF-8, from losing the link for one stray byte.
pub fn text_ready(bytes: &mut [u8], end: bool) -> usize {
    let mut i = 0;
    while let Some(&b) = bytes.get(i) {
        let need = match b {
            0x00..=0x7F => 0,
            0xC2..=0xDF => 1,
            0xE0..=0xEF => 2,
            0xF0..=0xF4 => 3,
            _ => {
                if let Some(x) = bytes.get_mut(i) {
                    *x = b'?';
                }
                i += 1;
                continue;
            }
        };
        // The range the second byte must be in (no overlong form, no surrogate, ≤ U+10FFFF).
        let second = match b {
            0xE0 => 0xA0..=0xBF,
            0xED => 0x80..=0x9F,
            0xF0 => 0x90..=0xBF,
            0xF4 => 0x80..=0x8F,
            _ => 0x80..=0xBF,
        };
        let mut good = 0;
        for k in 1..=need {
            let Some(&c) = bytes.get(i + k) else { break };
            let ok = if k == 1 {
                second.contains(&c)
            } else {
                (0x80..=0xBF).contains(&c)
            };
            if !ok {
                break;
            }
            good = k;
        }
        if good == need {
            i += need + 1;
        } else if i + good + 1 == bytes.len() && !end {
            // A character whose next bytes are still to come.
            return i;
        } else {
            for x in bytes.iter_mut().skip(i).take(good + 1) {
                *x = b'?';
            }
            i += good + 1;
        }
    }
    i
}

#[cfg(test)]
mod tests {
    use std::vec::Vec;

    use super::*;

    /// A masked client frame.
    fn client(first: u8, payload: &[u8], mask: [u8; 4]) -> Vec<u8> {
        let mut f = std::vec![first];
        match payload.len() {
            n @ 0..=125 => f.push(0x80 | n as u8),
            n @ 126..=0xFFFF => {
                f.push(0x80 | 126);
                f.extend((n as u16).to_be_bytes());
            }
            n => {
                f.push(0x80 | 127);
                f.extend((n as u64).to_be_bytes());
            }
        }
        f.extend(mask);
        f.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
        f
    }

    /// What the decoder gives for `input` fed in pieces of `step` bytes.
    #[derive(Debug, Default, PartialEq)]
    struct Seen {
        data: Vec<u8>,
        pings: Vec<Vec<u8>>,
        pongs: usize,
        close: Option<(Option<u16>, Vec<u8>)>,
        error: Option<FrameError>,
    }

    fn decode(input: &[u8], step: usize, max: u64) -> Seen {
        let mut d = Decoder::new(max);
        let mut seen = Seen::default();
        for piece in input.chunks(step.max(1)) {
            let r = d.feed_all(piece, |e| match e {
                Event::Data(b) => {
                    assert!(b.len() <= CHUNK);
                    seen.data.extend_from_slice(b);
                }
                Event::Ping(p) => seen.pings.push(p.to_vec()),
                Event::Pong(_) => seen.pongs += 1,
                Event::Close { code, reason } => seen.close = Some((code, reason.to_vec())),
            });
            if let Err(e) = r {
                seen.error = Some(e);
                break;
            }
        }
        seen
    }

    #[test]
    fn rfc_6455_examples() {
        // §5.7: a single-frame masked text message "Hello".
        let hello = [
            0x81, 0x85, 0x37, 0xfa, 0x21, 0x3d, 0x7f, 0x9f, 0x4d, 0x51, 0x58,
        ];
        assert_eq!(decode(&hello, 64, 100).data, b"Hello");
        // The server's unmasked "Hello".
        let mut out = [0u8; 16];
        let n = write_frame(&mut out, Opcode::Text, b"Hello").unwrap();
        assert_eq!(&out[..n], &[0x81, 0x05, 0x48, 0x65, 0x6c, 0x6c, 0x6f]);
    }

    #[test]
    fn the_same_bytes_decode_alike_however_split() {
        let mut input = client(0x01, b"G28\nG1 X1", [1, 2, 3, 4]);
        input.extend(client(0x89, b"ping!", [9, 8, 7, 6]));
        input.extend(client(0x80, b"0 F600\n", [5, 5, 5, 5]));
        let long: Vec<u8> = (0..1000u32).map(|i| b'a' + (i % 26) as u8).collect();
        input.extend(client(0x82, &long, [0xde, 0xad, 0xbe, 0xef]));
        input.extend(client(0x8A, b"", [0; 4]));
        input.extend(client(0x88, b"\x03\xe8bye", [7, 7, 7, 7]));
        input.extend(b"anything after the close is ignored");
        let mut expect = b"G28\nG1 X10 F600\n".to_vec();
        expect.extend(&long);
        for step in [1, 2, 3, 7, 64, 5000] {
            let seen = decode(&input, step, MAX_MESSAGE_LEN);
            assert_eq!(seen.data, expect, "step {step}");
            assert_eq!(seen.pings, [b"ping!".to_vec()]);
            assert_eq!(seen.pongs, 1);
            assert_eq!(seen.close, Some((Some(1000), b"bye".to_vec())));
            assert_eq!(seen.error, None);
        }
    }

    #[test]
    fn broken_frames_are_named_and_give_nothing() {
        let cases: [(Vec<u8>, FrameError, u16); 9] = [
            (
                [0x81, 0x03, b'G', b'2', b'8'].to_vec(),
                FrameError::Unmasked,
                1002,
            ),
            (client(0xC1, b"x", [1; 4]), FrameError::ReservedBits, 1002),
            (client(0x83, b"x", [1; 4]), FrameError::BadOpcode, 1002),
            (
                client(0x89, &[0; 126], [1; 4]),
                FrameError::ControlTooLong,
                1002,
            ),
            (
                client(0x09, b"x", [1; 4]),
                FrameError::FragmentedControl,
                1002,
            ),
            (
                client(0x80, b"x", [1; 4]),
                FrameError::UnexpectedContinuation,
                1002,
            ),
            (
                [client(0x01, b"a", [1; 4]), client(0x81, b"b", [1; 4])].concat(),
                FrameError::ExpectedContinuation,
                1002,
            ),
            (
                client(0x81, &[b'x'; 101], [1; 4]),
                FrameError::TooLong,
                1009,
            ),
            (client(0x88, &[3], [1; 4]), FrameError::BadClose, 1002),
        ];
        for (input, error, code) in cases {
            for step in [1, 100] {
                let seen = decode(&input, step, 100);
                assert_eq!(seen.error, Some(error), "{input:?}");
                assert_eq!(error.close_code(), code);
                let partial_message_ok = error == FrameError::ExpectedContinuation;
                assert!(
                    seen.data.is_empty() || partial_message_ok,
                    "{error}: nothing given"
                );
            }
        }
        let mut d = Decoder::new(100);
        assert_eq!(d.feed(&[0x81, 0x01]).unwrap_err(), FrameError::Unmasked);
        assert_eq!(
            d.feed(b"more").unwrap_err(),
            FrameError::Unmasked,
            "stays failed"
        );
        assert_eq!(d.error(), Some(FrameError::Unmasked));
        let huge = [0x82, 0xFF, 0x80, 0, 0, 0, 0, 0, 0, 0, 1, 2, 3, 4];
        assert_eq!(decode(&huge, 1, u64::MAX).error, Some(FrameError::TooLong));
        let close_1005 = client(0x88, &1005u16.to_be_bytes(), [1; 4]);
        assert_eq!(decode(&close_1005, 3, 10).error, Some(FrameError::BadClose));
    }

    #[test]
    fn a_fragmented_message_counts_against_the_limit_whole() {
        let input = [
            client(0x01, &[b'a'; 60], [1; 4]),
            client(0x80, &[b'b'; 60], [2; 4]),
        ]
        .concat();
        assert_eq!(decode(&input, 9, 100).error, Some(FrameError::TooLong));
        assert_eq!(decode(&input, 9, 120).data.len(), 120);
        let two = [input.clone(), input].concat();
        assert_eq!(
            decode(&two, 9, 120).data.len(),
            240,
            "the count starts again"
        );
    }

    #[test]
    fn server_frames_and_their_lengths() {
        let mut out = [0u8; 16];
        assert_eq!(write_header(&mut out, Opcode::Text, 125), Ok(2));
        assert_eq!(out[..2], [0x81, 125]);
        assert_eq!(write_header(&mut out, Opcode::Binary, 126), Ok(4));
        assert_eq!(out[..4], [0x82, 126, 0, 126]);
        assert_eq!(write_header(&mut out, Opcode::Text, 70_000), Ok(10));
        assert_eq!(out[..10], [0x81, 127, 0, 0, 0, 0, 0, 1, 0x11, 0x70]);
        assert_eq!(
            write_header(&mut out[..3], Opcode::Text, 126),
            Err(BufferTooSmall)
        );
        let mut close = [0u8; 127];
        let long_reason = "x".repeat(200);
        let n = write_close(&mut close, 1009, &long_reason).unwrap();
        assert_eq!(n, 127);
        assert_eq!(close[..4], [0x88, 125, 0x03, 0xF1]);
        let seen = decode(&[0x89, 0x80, 0, 0, 0, 0], 1, 10);
        assert_eq!(seen.pings, [Vec::<u8>::new()]);
    }

    #[test]
    fn reply_bytes_are_made_utf8_for_text_frames() {
        let mut b = *b"ok\n\xC3";
        assert_eq!(
            text_ready(&mut b, false),
            3,
            "the start of a character waits"
        );
        assert_eq!(text_ready(&mut b, true), 4);
        assert_eq!(&b, b"ok\n?");
        let mut b = *b"\xE2\x82\xAC=\xFF\xC3(\xED\xA0\x80";
        assert_eq!(text_ready(&mut b, false), b.len());
        assert_eq!(&b, b"\xE2\x82\xAC=??(???");
        let mut b = *b"\xF0\x9F\x98";
        assert_eq!(text_ready(&mut b, false), 0);
        let mut b = *b"\xF0\x9F\x98\x80";
        assert_eq!(text_ready(&mut b, false), 4);
        assert!(core::str::from_utf8(&b).is_ok());
    }
}
