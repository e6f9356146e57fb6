//! One streaming decoder for a link that mixes 53-byte frames and G-code lines.
//!
//! Feed it bytes as they arrive, split anywhere; it yields whole records, each once, in order,
//! and the same records whatever the split (postcard's accumulator shape):
//!
//! ```
//! use forja_protocol::stream::{Decoder, Event};
//!
//! let mut decoder = Decoder::new();
//! let mut lines = 0;
//! let mut frames = 0;
//! for chunk in [&b"N5 G28*2"[..], b"2\nN02Zero**********", b"*******************************ZeroF\n"] {
//!     decoder.feed_all(chunk, |event| match event {
//!         Event::Line(_) => lines += 1,
//!         Event::Frame(_) => frames += 1,
//!         _ => {}
//!     });
//! }
//! assert_eq!((lines, frames), (1, 1));
//! ```
//!
//! ## Rules
//!
//! - A record ends at `\n` or `\r` (so CR, LF and CRLF all work); empty records are dropped,
//!   or given as empty lines when asked for (grbl's blank lines: [`Decoder::set_blank_lines`]).
//! - A record that [is a frame](crate::frame::is_frame) is [`Event::Frame`]; any other is
//!   [`Event::Line`], the terminator stripped. A frame needs no terminator: one is complete when
//!   its 53rd byte is followed by a terminator, by `N` (the next frame) or by a control byte;
//!   [`Decoder::flush`] completes one at the end of the input.
//! - A 53-byte record that has the shape of a frame but [parses](crate::gcode::Line::parse) as a
//!   numbered, checksummed G-code line (`N12 G1 X5*71 ; …F`) is a line: no frame parses as one
//!   (a frame's `*` padding is not a checksum, and a frame without padding has no `*`), so the
//!   line is answered as a line and its resend ends.
//! - A record longer than [`MAX_LINE_LEN`] is discarded to its
//!   terminator and reported once as [`Event::TooLong`], never truncated.
//! - A control byte (other than tab, CR, LF) is garbage: the record it falls in is discarded,
//!   and so is everything up to the next terminator or `N`, where decoding resumes. The run is
//!   reported once as [`Event::Garbage`] with its length, and whether printable bytes were
//!   among them (a line, or part of one, was lost). Bytes before a frame at the end of a
//!   record (`xyzN02…F`) are garbage too.
//! - Memory is one [`MAX_LINE_LEN`] buffer; no input can make it
//!   grow, loop or panic.

use heapless::Vec;

use crate::frame::{FRAME_LEN, Frame, START};
use crate::gcode::{MAX_LINE_LEN, is_checked_line};

/// Whether `bytes` is a frame record: it [is a frame](crate::frame::is_frame) and does not
/// parse as a numbered, checksummed G-code line (see the module's rules).
pub fn is_frame_record(bytes: &[u8]) -> bool {
    crate::frame::is_frame(bytes) && !is_checked_line(bytes)
}

/// One record, or one report, out of the stream.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Event<'a> {
    /// A G-code line (or, on a client, a reply line), without terminator; empty only for a
    /// blank line when [`Decoder::set_blank_lines`] asks for them. Parse it with
    /// [`crate::gcode::Line::parse`] or [`crate::reply::Reply::parse`].
    Line(&'a [u8]),
    /// A structurally valid frame. Decode it with [`crate::frame::ClientMessage::parse`] on the
    /// controller or [`crate::frame::ControllerMessage::parse`] on the client.
    Frame(Frame<'a>),
    /// Bytes were dropped (report as [`crate::error::FrameError::Structure`], code 21, to a
    /// frame client; to a G-code host, a lost line is [`crate::error::LineError::UnexpectedCharacter`],
    /// code 8).
    Garbage {
        /// How many.
        skipped: usize,
        /// Whether printable bytes were among them: a record (a line, or part of one) was lost,
        /// not only control bytes between records.
        text: bool,
    },
    /// A line longer than [`MAX_LINE_LEN`] was dropped (report as
    /// [`crate::error::LineError::TooLong`], code 1).
    TooLong {
        /// Its length, terminator excluded.
        len: usize,
    },
}

/// What one [`Decoder::feed`] call gives.
#[derive(Debug)]
pub struct FeedResult<'d, 'i> {
    /// The next event, or `None` when the input is used up and nothing is pending.
    pub event: Option<Event<'d>>,
    /// The input not yet looked at: pass it to the next call.
    pub remaining: &'i [u8],
}

/// Counters of what a [`Decoder`] has seen (wrapping).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Stats {
    /// [`Event::Line`]s given.
    pub lines: u32,
    /// [`Event::Frame`]s given.
    pub frames: u32,
    /// Bytes dropped as garbage.
    pub garbage_bytes: u32,
    /// [`Event::Garbage`]s given (runs of garbage).
    pub garbage_runs: u32,
    /// [`Event::TooLong`]s given.
    pub too_long: u32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum State {
    /// Accumulating a record into the buffer.
    Record,
    /// Dropping garbage until a terminator or `N`.
    Skip { skipped: usize, text: bool },
    /// Dropping a too-long line until its terminator.
    Overlong { len: usize },
}

/// What the state machine found; the event is built from it and the buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Ready {
    Line,
    Frame,
    Garbage(usize, bool),
    TooLong(usize),
}

/// The mixed-link decoder: bounded memory, no allocation, never panics.
#[derive(Clone, Debug)]
pub struct Decoder {
    buf: Vec<u8, MAX_LINE_LEN>,
    state: State,
    /// The last event borrowed the buffer: clear it before going on.
    clear: bool,
    /// The next record starts with the `N` that ended the previous one.
    start_with_n: bool,
    /// A frame at this offset of the buffer is still to be given (after its garbage prefix).
    pending_frame: Option<usize>,
    /// Empty records are given as empty lines ([`Decoder::set_blank_lines`]).
    blank_lines: bool,
    /// The last byte taken was `\r` (a `\n` right after it ends the same line).
    after_cr: bool,
    stats: Stats,
}

impl Default for Decoder {
    fn default() -> Self {
        Self::new()
    }
}

fn is_terminator(b: u8) -> bool {
    b == b'\n' || b == b'\r'
}

/// Control bytes other than tab, CR and LF, and DEL.
fn is_garbage(b: u8) -> bool {
    (b < b' ' && b != b'\t' && !is_terminator(b)) || b == 0x7f
}

impl Decoder {
    /// An empty decoder, at the start of a record.
    pub const fn new() -> Self {
        Self {
            buf: Vec::new(),
            state: State::Record,
            clear: false,
            start_with_n: false,
            pending_frame: None,
            blank_lines: false,
            after_cr: false,
            stats: Stats {
                lines: 0,
                frames: 0,
                garbage_bytes: 0,
                garbage_runs: 0,
                too_long: 0,
            },
        }
    }

    /// Forget any partial record (after the link was reset). The counters are kept.
    pub fn reset(&mut self) {
        self.buf.clear();
        self.state = State::Record;
        self.clear = false;
        self.start_with_n = false;
        self.pending_frame = None;
    }

    /// Give an empty record as an empty [`Event::Line`] (`on`), or drop it (the default).
    /// grbl answers a blank line `ok`, and a sender that counts characters counts on that
    /// answer. A `\n` right after a `\r` ends the same line (CRLF), not an empty one.
    pub fn set_blank_lines(&mut self, on: bool) {
        self.blank_lines = on;
    }

    /// What has been seen so far.
    pub fn stats(&self) -> Stats {
        self.stats
    }

    /// Bytes dropped as garbage so far (the same as `stats().garbage_bytes`).
    pub fn skipped(&self) -> u32 {
        self.stats.garbage_bytes
    }

    /// The record taken so far and not yet given: what [`flush`](Self::flush) would give as a
    /// line or a frame now. Empty between records and while dropping garbage or a too-long
    /// line. (A controller takes an unterminated record only when it is whole: a frame, or a
    /// numbered line whose check verifies.)
    pub fn partial(&self) -> &[u8] {
        if self.clear || self.start_with_n || self.pending_frame.is_some() {
            return &[];
        }
        match self.state {
            State::Record => &self.buf,
            _ => &[],
        }
    }

    /// Take bytes until one event is complete. Call again with
    /// [`remaining`](FeedResult::remaining) until `event` is `None`: then all of `input` has
    /// been taken and nothing is pending.
    ///
    /// ```
    /// # use forja_protocol::stream::Decoder;
    /// # let mut decoder = Decoder::new();
    /// let mut window: &[u8] = b"G28\nG1 X5\n";
    /// loop {
    ///     let fed = decoder.feed(window);
    ///     window = fed.remaining;
    ///     let Some(event) = fed.event else { break };
    ///     // handle `event`
    /// }
    /// ```
    pub fn feed<'d, 'i>(&'d mut self, input: &'i [u8]) -> FeedResult<'d, 'i> {
        if let Some(at) = self.pending_frame.take() {
            return FeedResult {
                event: self.deliver_frame_at(at),
                remaining: input,
            };
        }
        self.prepare();
        let mut i = 0;
        while let Some(rest) = input.get(i..).filter(|rest| !rest.is_empty()) {
            let taken = self.take_run(rest);
            if taken > 0 {
                i += taken;
                self.after_cr = false;
                continue;
            }
            let Some(&b) = rest.first() else { break };
            i += 1;
            let ready = self.step(b);
            self.after_cr = b == b'\r';
            if let Some(ready) = ready {
                return FeedResult {
                    event: Some(self.event(ready)),
                    remaining: input.get(i..).unwrap_or(&[]),
                };
            }
        }
        FeedResult {
            event: None,
            remaining: &[],
        }
    }

    /// Feed all of `input`, calling `on_event` for each event.
    pub fn feed_all(&mut self, input: &[u8], mut on_event: impl FnMut(Event<'_>)) {
        let mut window = input;
        loop {
            let fed = self.feed(window);
            window = fed.remaining;
            match fed.event {
                Some(event) => on_event(event),
                None => break,
            }
        }
    }

    /// End of input (or the link went idle): give what is pending as if a terminator had come.
    /// Call until it returns `None`.
    pub fn flush(&mut self) -> Option<Event<'_>> {
        if let Some(at) = self.pending_frame.take() {
            return self.deliver_frame_at(at);
        }
        self.prepare();
        let ready = match self.state {
            State::Skip { skipped, text } => Some(Ready::Garbage(skipped, text)),
            State::Overlong { len } => Some(Ready::TooLong(len)),
            State::Record => self.end_record(),
        };
        self.state = State::Record;
        ready.map(|r| self.event(r))
    }

    /// Start of a call: finish what the previous event left.
    fn prepare(&mut self) {
        if self.clear {
            self.buf.clear();
            self.clear = false;
        }
        if self.start_with_n {
            self.start_with_n = false;
            // The buffer is empty here, so this cannot fail.
            let _ = self.buf.push(START);
        }
    }

    fn deliver_frame_at(&mut self, at: usize) -> Option<Event<'_>> {
        self.clear = true;
        let frame = self
            .buf
            .get(at..at + FRAME_LEN)
            .and_then(|bytes| Frame::new_checked(bytes).ok())?;
        self.stats.frames = self.stats.frames.wrapping_add(1);
        Some(Event::Frame(frame))
    }

    /// Take in bulk the bytes at the start of `rest` that cannot complete an event: ordinary
    /// bytes of a record (stopping before the byte that follows a possible frame, and before a
    /// full buffer), bytes of a garbage run or of a too-long line. Returns how many; 0 when the
    /// first byte needs [`step`](Self::step).
    fn take_run(&mut self, rest: &[u8]) -> usize {
        match self.state {
            State::Record => {
                let len = self.buf.len();
                let room = match len.cmp(&FRAME_LEN) {
                    core::cmp::Ordering::Less => FRAME_LEN - len,
                    core::cmp::Ordering::Equal => 0,
                    core::cmp::Ordering::Greater => MAX_LINE_LEN - len,
                };
                let n = rest
                    .iter()
                    .take(room)
                    .take_while(|&&b| !is_terminator(b) && !is_garbage(b))
                    .count();
                // `n` is within the buffer's room, so this cannot fail.
                let _ = self.buf.extend_from_slice(rest.get(..n).unwrap_or(&[]));
                n
            }
            State::Skip { skipped, text } => {
                let run = rest
                    .iter()
                    .take_while(|&&b| !is_terminator(b) && b != START);
                let (n, printable) =
                    run.fold((0, false), |(n, p), &b| (n + 1, p || !is_garbage(b)));
                self.state = State::Skip {
                    skipped: skipped.saturating_add(n),
                    text: text || printable,
                };
                n
            }
            State::Overlong { len } => {
                let n = rest.iter().take_while(|&&b| !is_terminator(b)).count();
                self.state = State::Overlong {
                    len: len.saturating_add(n),
                };
                n
            }
        }
    }

    /// One byte through the state machine.
    fn step(&mut self, b: u8) -> Option<Ready> {
        match self.state {
            State::Skip { skipped, text } => {
                if is_terminator(b) || b == START {
                    self.state = State::Record;
                    self.start_with_n = b == START;
                    return Some(Ready::Garbage(skipped, text));
                }
                self.state = State::Skip {
                    skipped: skipped.saturating_add(1),
                    text: text || !is_garbage(b),
                };
                None
            }
            State::Overlong { len } => {
                if is_terminator(b) {
                    self.state = State::Record;
                    return Some(Ready::TooLong(len));
                }
                self.state = State::Overlong {
                    len: len.saturating_add(1),
                };
                None
            }
            State::Record => {
                if is_terminator(b) {
                    let crlf = b == b'\n' && self.after_cr;
                    if self.buf.is_empty() && self.blank_lines && !crlf {
                        return Some(Ready::Line);
                    }
                    return self.end_record();
                }
                let frame_done = is_frame_record(&self.buf);
                if is_garbage(b) {
                    self.state = State::Skip {
                        skipped: if frame_done { 1 } else { self.buf.len() + 1 },
                        text: !frame_done && !self.buf.is_empty(),
                    };
                    if frame_done {
                        return Some(Ready::Frame);
                    }
                    self.buf.clear();
                    return None;
                }
                if b == START && frame_done {
                    self.start_with_n = true;
                    return Some(Ready::Frame);
                }
                if self.buf.push(b).is_err() {
                    self.state = State::Overlong {
                        len: self.buf.len() + 1,
                    };
                    self.buf.clear();
                }
                None
            }
        }
    }

    /// A terminator (or a flush) ends the record in the buffer.
    fn end_record(&mut self) -> Option<Ready> {
        let len = self.buf.len();
        if len == 0 {
            return None;
        }
        if is_frame_record(&self.buf) {
            return Some(Ready::Frame);
        }
        if let Some(at) = len.checked_sub(FRAME_LEN).filter(|&at| at > 0)
            && self.buf.get(at..).is_some_and(is_frame_record)
        {
            self.pending_frame = Some(at);
            return Some(Ready::Garbage(at, true));
        }
        Some(Ready::Line)
    }

    fn event(&mut self, ready: Ready) -> Event<'_> {
        let stats = &mut self.stats;
        // The buffer is cleared at the next call unless a frame in it is still to be given.
        self.clear = self.pending_frame.is_none();
        match ready {
            Ready::Line => {
                stats.lines = stats.lines.wrapping_add(1);
                Event::Line(&self.buf)
            }
            Ready::Frame => match Frame::new_checked(&self.buf) {
                Ok(frame) => {
                    stats.frames = stats.frames.wrapping_add(1);
                    Event::Frame(frame)
                }
                // Unreachable: `Ready::Frame` is only given for a buffer that is a frame.
                Err(_) => Event::Line(&self.buf),
            },
            Ready::Garbage(skipped, text) => {
                stats.garbage_runs = stats.garbage_runs.wrapping_add(1);
                stats.garbage_bytes = stats
                    .garbage_bytes
                    .wrapping_add(u32::try_from(skipped).unwrap_or(u32::MAX));
                Event::Garbage { skipped, text }
            }
            Ready::TooLong(len) => {
                stats.too_long = stats.too_long.wrapping_add(1);
                Event::TooLong { len }
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic, clippy::indexing_slicing)]
mod tests {
    extern crate std;
    use std::vec::Vec as StdVec;

    use super::*;

    /// An owned copy of an event, to compare runs.
    #[derive(Clone, Debug, PartialEq, Eq)]
    pub(crate) enum Owned {
        Line(StdVec<u8>),
        Frame(StdVec<u8>),
        Garbage(usize),
        TooLong(usize),
    }

    pub(crate) fn owned(event: Event<'_>) -> Owned {
        match event {
            Event::Line(b) => Owned::Line(b.to_vec()),
            Event::Frame(f) => Owned::Frame(f.as_bytes().to_vec()),
            Event::Garbage { skipped, .. } => Owned::Garbage(skipped),
            Event::TooLong { len } => Owned::TooLong(len),
        }
    }

    /// Every event of `input` fed in chunks of `sizes` (cycled), then flushed.
    pub(crate) fn run(input: &[u8], sizes: &[usize]) -> StdVec<Owned> {
        let mut decoder = Decoder::new();
        let mut events = StdVec::new();
        let mut rest = input;
        let mut k = 0;
        while !rest.is_empty() {
            let n = sizes
                .get(k % sizes.len().max(1))
                .copied()
                .unwrap_or(1)
                .clamp(1, rest.len());
            k += 1;
            let (chunk, after) = rest.split_at(n);
            rest = after;
            decoder.feed_all(chunk, |e| events.push(owned(e)));
        }
        while let Some(e) = decoder.flush() {
            events.push(owned(e));
        }
        events
    }

    const ZERO: &[u8] = b"N02Zero*****************************************ZeroF";
    const STOP: &[u8] = b"N02Stop*****************************************StopF";

    fn line(b: &[u8]) -> Owned {
        Owned::Line(b.to_vec())
    }

    fn frame(b: &[u8]) -> Owned {
        Owned::Frame(b.to_vec())
    }

    #[test]
    fn lines_and_frames_with_every_terminator() {
        let mut input = StdVec::new();
        input.extend_from_slice(b"N3 T0*57\r\nN4 G92 E0*67\rN5 G28*22\n\n\r\n");
        input.extend_from_slice(ZERO);
        input.extend_from_slice(b"\r\n");
        input.extend_from_slice(STOP);
        input.extend_from_slice(ZERO);
        input.extend_from_slice(b"\nG1 X5");
        let expected = [
            line(b"N3 T0*57"),
            line(b"N4 G92 E0*67"),
            line(b"N5 G28*22"),
            frame(ZERO),
            frame(STOP),
            frame(ZERO),
            line(b"G1 X5"),
        ];
        for sizes in [&[1usize][..], &[2], &[3, 7], &[53], &[1000]] {
            assert_eq!(run(&input, sizes), expected, "{sizes:?}");
        }
    }

    #[test]
    fn a_frame_without_terminator_waits_for_the_next_byte() {
        let mut decoder = Decoder::new();
        let fed = decoder.feed(ZERO);
        assert!(fed.event.is_none());
        assert_eq!(decoder.flush().map(owned), Some(frame(ZERO)));
        assert_eq!(decoder.flush(), None);
        // A printable byte after the 53rd makes it a (long) G-code line instead.
        let mut input = ZERO.to_vec();
        input.extend_from_slice(b"1200*7\n");
        assert_eq!(run(&input, &[5]), [line(&input[..input.len() - 1])]);
    }

    #[test]
    fn garbage_is_skipped_to_the_next_start_and_counted() {
        let mut input = StdVec::new();
        input.extend_from_slice(b"\x00\xff\x01junk");
        input.extend_from_slice(ZERO);
        input.extend_from_slice(b"\nG1 X\x075 Y3\nG28\n");
        let expected = [
            Owned::Garbage(7),
            frame(ZERO),
            Owned::Garbage(9),
            line(b"G28"),
        ];
        // 0xff is not garbage by itself, but it falls in the run started by 0x00.
        for sizes in [&[1usize][..], &[4], &[100]] {
            assert_eq!(run(&input, sizes), expected, "{sizes:?}");
        }
        let mut decoder = Decoder::new();
        decoder.feed_all(&input, |_| {});
        assert_eq!(decoder.skipped(), 16);
        assert_eq!(
            decoder.stats(),
            Stats {
                lines: 1,
                frames: 1,
                garbage_bytes: 16,
                garbage_runs: 2,
                too_long: 0
            }
        );
    }

    #[test]
    fn printable_garbage_before_a_frame() {
        let mut input = b"xyz".to_vec();
        input.extend_from_slice(ZERO);
        input.push(b'\n');
        assert_eq!(run(&input, &[1]), [Owned::Garbage(3), frame(ZERO)]);
        assert_eq!(
            run(&input[..input.len() - 1], &[9]),
            [Owned::Garbage(3), frame(ZERO)]
        );
    }

    #[test]
    fn a_frame_followed_by_a_control_byte() {
        let mut input = ZERO.to_vec();
        input.extend_from_slice(b"\x00\x00\nG28\n");
        assert_eq!(
            run(&input, &[1]),
            [frame(ZERO), Owned::Garbage(2), line(b"G28")]
        );
    }

    #[test]
    fn too_long_lines_are_dropped_whole() {
        let mut input = StdVec::new();
        input.extend(core::iter::repeat_n(b'X', MAX_LINE_LEN));
        input.push(b'\n');
        input.extend(core::iter::repeat_n(b'Y', MAX_LINE_LEN + 10));
        input.extend_from_slice(b"\x00N\nG28\n");
        input.extend(core::iter::repeat_n(b'Z', MAX_LINE_LEN + 1));
        let expected = [
            line(&[b'X'; MAX_LINE_LEN]),
            Owned::TooLong(MAX_LINE_LEN + 12),
            line(b"G28"),
            Owned::TooLong(MAX_LINE_LEN + 1),
        ];
        for sizes in [&[1usize][..], &[255], &[1000]] {
            assert_eq!(run(&input, sizes), expected, "{sizes:?}");
        }
    }

    #[test]
    fn a_checksummed_line_shaped_like_a_frame_is_a_line() {
        // 53 bytes, `N`, two digits, `F` at the end: the shape of a frame, but a valid numbered
        // line (a comment after the checksum).
        let mut body = b"N12 G1 X5".to_vec();
        let cs = crate::gcode::checksum(&body);
        body.extend_from_slice(std::format!("*{cs} ;").as_bytes());
        while body.len() < FRAME_LEN - 1 {
            body.push(b'x');
        }
        body.push(b'F');
        assert!(crate::frame::is_frame(&body));
        assert!(!is_frame_record(&body));
        let mut input = body.clone();
        input.extend_from_slice(b"\r\n");
        for sizes in [&[1usize][..], &[53], &[1000]] {
            assert_eq!(run(&input, sizes), [line(&body)], "{sizes:?}");
            assert_eq!(run(&body, sizes), [line(&body)], "{sizes:?}");
        }
        // Frames stay frames, whatever their padding.
        assert!(is_frame_record(ZERO));
        let mut bare = b"N03".to_vec();
        bare.resize(FRAME_LEN - 1, b'7');
        bare.push(b'F');
        assert!(is_frame_record(&bare));
    }

    #[test]
    fn garbage_tells_whether_text_was_lost() {
        let mut decoder = Decoder::new();
        let mut seen = StdVec::new();
        decoder.feed_all(b"M114\x00\n\x00\x01\nG28\n\x00G1\n", |e| {
            if let Event::Garbage { skipped, text } = e {
                seen.push((skipped, text));
            }
        });
        assert_eq!(seen, [(5, true), (2, false), (3, true)]);
    }

    #[test]
    fn the_partial_record_is_what_a_flush_would_give() {
        let mut decoder = Decoder::new();
        decoder.feed_all(b"G28\nM11", |_| {});
        assert_eq!(decoder.partial(), b"M11");
        decoder.feed_all(b"4\n", |_| {});
        assert_eq!(decoder.partial(), b"");
        decoder.feed_all(b"G1\x00X", |_| {});
        assert_eq!(decoder.partial(), b"");
    }

    #[test]
    fn reset_forgets_the_partial_record() {
        let mut decoder = Decoder::new();
        decoder.feed_all(b"G1 X", |_| {});
        decoder.reset();
        let mut events = StdVec::new();
        decoder.feed_all(b"G28\n", |e| events.push(owned(e)));
        assert_eq!(events, [line(b"G28")]);
    }
}

#[cfg(test)]
mod blank_line_tests {
    extern crate std;
    use std::vec::Vec as StdVec;

    use super::*;

    fn lines(decoder: &mut Decoder, input: &[u8]) -> StdVec<StdVec<u8>> {
        let mut out = StdVec::new();
        decoder.feed_all(input, |e| {
            if let Event::Line(l) = e {
                out.push(l.to_vec());
            }
        });
        out
    }

    #[test]
    fn blank_lines_are_given_only_when_asked_for_and_crlf_is_one_line_end() {
        let mut d = Decoder::new();
        assert_eq!(
            lines(&mut d, b"G1\n\n\r\nG2\r\n"),
            [b"G1".to_vec(), b"G2".to_vec()]
        );
        let mut d = Decoder::new();
        d.set_blank_lines(true);
        let got = lines(&mut d, b"G1\n\nG2\r\n\r\n\r\rG3\n");
        // G1, a blank, G2 (its CRLF one end), a blank by CRLF, two by lone CRs, G3.
        let want: StdVec<&[u8]> = std::vec![b"G1", b"", b"G2", b"", b"", b"", b"G3"];
        assert_eq!(got, want);
    }
}
