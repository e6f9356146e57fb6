//! RepRap G-code lines (seed `003_…txt`): words, comments, `N` line numbers with the `*`
//! checksum, and line-number continuity.
//!
//! ```
//! use forja_protocol::gcode::{Line, LineNumbering};
//!
//! let line = Line::parse(b"N7 G1 X2.0 Y2.0 F3000.0*85").unwrap();
//! assert_eq!(line.number(), Some(7));
//! assert_eq!(line.get(b'F').unwrap().to_f32(), 3000.0);
//!
//! let mut numbering = LineNumbering::new();
//! numbering.set_expected(7);
//! assert!(numbering.accept(&line).is_ok());
//! assert_eq!(numbering.expected(), 8);
//!
//! let mut out = [0u8; 64];
//! let n = line.encode(&mut out).unwrap();
//! assert_eq!(&out[..n], b"N7 G1 X2.0 Y2.0 F3000.0*85");
//! ```

use heapless::Vec;

pub use crate::decimal::{Decimal, MAX_SCALE, pow10};
use crate::decimal::{NumberError, parse_prefix};
pub use crate::error::{EncodeError, LineError};
use crate::write::{Cursor, Sink, Xor};

/// The longest line accepted, in bytes, terminator excluded. A longer line is
/// [`LineError::TooLong`], never truncated.
pub const MAX_LINE_LEN: usize = 256;

/// The most words one line may hold (the `N` line number not counted): more than any
/// command takes (a move naming nine axes with its feed and spindle speed is 12; Marlin's
/// widest, `M906 X Y Z I J K U V W E T`, 11). Every parsed line is copied whole on its way to
/// the kernel, so its size is paid on every line.
pub const MAX_WORDS: usize = 20;

/// The M-codes whose argument is free text rather than words: `M23`, `M28`, `M29`, `M30`,
/// `M32` (file names), `M117` (a message) and `M118` (a line for the host). See
/// [`Line::text_arg`].
pub const TEXT_COMMANDS: [i64; 7] = [23, 28, 29, 30, 32, 117, 118];

/// The checksum of a line: the XOR of every byte of `bytes` up to, not including, the first `*`
/// (the seed's C snippet, byte for byte).
pub fn checksum(bytes: &[u8]) -> u8 {
    bytes
        .iter()
        .take_while(|&&b| b != b'*')
        .fold(0, |cs, &b| cs ^ b)
}

/// The CRC-16 of a line (CRC-16/CCITT-FALSE: polynomial `0x1021`, initial value `0xFFFF`,
/// no reflection, no final XOR) over every byte of `bytes` up to, not including, the first `*`.
///
/// A host that can send it writes it after `*` as exactly five decimal digits, zero-padded
/// (`N5 G28*04621`), a form a host that sends the XOR [`checksum`] never writes (that one has one
/// to three digits). Unlike the XOR it catches every error of up to 16 adjacent bits, every odd
/// number of flipped bits, two equal bytes lost and bytes swapped.
///
/// ```
/// assert_eq!(forja_protocol::gcode::crc16(b"123456789"), 0x29B1);
/// ```
pub fn crc16(bytes: &[u8]) -> u16 {
    bytes
        .iter()
        .take_while(|&&b| b != b'*')
        .fold(0xFFFF, |crc, &b| {
            (0..8).fold(crc ^ (u16::from(b) << 8), |c, _| {
                if c & 0x8000 != 0 {
                    (c << 1) ^ 0x1021
                } else {
                    c << 1
                }
            })
        })
}

/// The digits of a CRC-16 field after `*`.
const CRC_DIGITS: usize = 5;

/// The check a numbered line carries after `*`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Check {
    /// The RepRap XOR [`checksum`]: one to three digits.
    Xor,
    /// The [`crc16`]: exactly five digits.
    Crc16,
}

/// One word: a letter and its number, such as `G1`, `X-2.5` or `F3000.0`, or a parameter
/// letter alone (`X` in `G28 X Y`, a [bare](Self::bare) word).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Word {
    /// The letter, ASCII upper case (lower case input is folded).
    pub letter: u8,
    /// The number, exactly as written; zero, and not to be read, for a bare word.
    pub value: Decimal,
    /// The letter was written without a number: a flag such as the axes of `G28 X Y` or
    /// `M84 X Y E`. [`Line::get`] does not see it; [`Line::mentions`] does.
    pub bare: bool,
}

impl Word {
    /// A word from its parts (`letter` should be an upper-case ASCII letter).
    pub const fn new(letter: u8, value: Decimal) -> Self {
        Self {
            letter,
            value,
            bare: false,
        }
    }

    /// A parameter letter without a number (`letter` should be an upper-case ASCII letter other
    /// than `G`, `M`, `N` and `T`, which always take one).
    pub const fn bare(letter: u8) -> Self {
        Self {
            letter,
            value: Decimal::new(0, 0),
            bare: true,
        }
    }

    /// Whether this word is `letter` followed by the integer `number` (`G1`, `M110`, `G1.0`).
    pub fn is(&self, letter: u8, number: i64) -> bool {
        self.letter == letter.to_ascii_uppercase()
            && !self.bare
            && self.value.as_integer() == Some(number)
    }

    fn write<S: Sink>(&self, out: &mut S) -> Result<(), EncodeError> {
        out.put(self.letter)?;
        if self.bare {
            return Ok(());
        }
        self.value.write_checked(out)
    }
}

/// Letters that never stand alone: a command (`G`, `M`, `T`) or the line number (`N`).
fn takes_a_number(letter: u8) -> bool {
    matches!(letter, b'G' | b'M' | b'N' | b'T')
}

/// One G-code line, parsed.
///
/// Holds the line number, the words in order (comments dropped) and, for the commands of
/// [`TEXT_COMMANDS`], the free text after the command word, borrowed from the input.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Line<'a> {
    /// `-1..=u32::MAX`; `-1` only on an `M110` line.
    number: Option<i64>,
    words: Vec<Word, MAX_WORDS, u8>,
    text: Option<&'a [u8]>,
    /// The line carries (or is to be written with) the CRC-16 rather than the XOR.
    crc: bool,
}

impl<'a> Line<'a> {
    /// Parse one line without its terminator (a trailing CR or LF is tolerated and ignored).
    ///
    /// - Words are a letter and a number (`[+-]digits[.digits]`); spaces between words are
    ///   optional, letters are folded to upper case. A parameter letter followed by a blank,
    ///   another letter, a comment or the end is a [bare](Word::bare) word (`G28 X Y`); `G`,
    ///   `M`, `N` and `T` always need a number ([`LineError::MissingValue`]), as does a letter
    ///   followed by anything else (`X-`).
    /// - `;` comments run to the end of the line, `(…)` comments to the next `)`.
    /// - The checksum marker is the first `*` (in a `;` comment, only when a checksum follows
    ///   it). One to three digits after it are the XOR [`checksum`], exactly five the [`crc16`].
    ///   The check is checked first, then the presence of both `N` and `*` or neither, then the
    ///   body.
    /// - A record of one to five digits alone is [`LineError::Fragment`]: the checksum of a
    ///   line whose `*` was damaged into a line end.
    /// - `N` must be the first word; an `N` word further on (`M110 N0`) is a parameter and is
    ///   kept in [`words`](Self::words).
    /// - After one of [`TEXT_COMMANDS`] the rest of the line (up to `*` or `;`) is its text.
    ///
    /// Returns the line by value, which copies its words once on the way out (a few hundred
    /// bytes); [`Line::parse_in`] parses into storage the caller already has.
    #[inline]
    pub fn parse(bytes: &'a [u8]) -> Result<Line<'a>, LineError> {
        let mut line = Line::empty();
        line.parse_in(bytes)?;
        Ok(line)
    }

    /// A line with no number, no words and no text: the storage [`Line::parse_in`] fills.
    pub const fn empty() -> Self {
        Line {
            number: None,
            words: Vec::new(),
            text: None,
            crc: false,
        }
    }

    /// [`Line::parse`] into this line, whatever it held: the words are written in place, with
    /// no copy of the line. On an error the line is left [empty](Line::empty).
    ///
    /// This is the parse of the paths that take every line of a program (the controller's
    /// lines, the jobs), where the copy `parse` makes would be a tenth of planning a move.
    pub fn parse_in(&mut self, bytes: &'a [u8]) -> Result<(), LineError> {
        self.words.clear();
        match Self::parse_into(bytes, &mut self.words) {
            Ok((number, text, crc)) => {
                self.number = number;
                self.text = text;
                self.crc = crc;
                Ok(())
            }
            Err(e) => {
                // Field by field: assigning `Line::empty()` would write the words' storage.
                self.words.clear();
                self.number = None;
                self.text = None;
                self.crc = false;
                Err(e)
            }
        }
    }

    /// [`Line::parse`] of everything but the words' storage: the words into `words`, the rest
    /// returned (the line number, the text, whether the line carries the CRC-16).
    #[allow(clippy::type_complexity)]
    fn parse_into(
        bytes: &'a [u8],
        words: &mut Words,
    ) -> Result<(Option<i64>, Option<&'a [u8]>, bool), LineError> {
        let bytes = trim_terminators(bytes);
        if bytes.len() > MAX_LINE_LEN {
            return Err(LineError::TooLong);
        }
        if is_fragment(bytes) {
            return Err(LineError::Fragment);
        }
        let marker = checksum_marker(bytes)?;
        let body = match marker {
            Some((at, field)) => {
                let (body, _) = bytes.split_at_checked(at).unwrap_or((bytes, &[]));
                match field {
                    Field::Xor(received) => {
                        let computed = checksum(body);
                        if computed != received {
                            return Err(LineError::ChecksumMismatch { computed, received });
                        }
                    }
                    Field::Crc(received) => {
                        let computed = crc16(body);
                        if computed != received {
                            return Err(LineError::CrcMismatch { computed, received });
                        }
                    }
                }
                body
            }
            None => bytes,
        };
        let (number, rest) = parse_line_number(body)?;
        match (number, marker) {
            (Some(_), None) => return Err(LineError::MissingChecksum),
            (None, Some(_)) => return Err(LineError::MissingLineNumber),
            _ => {}
        }
        let line = number.and_then(|n| u32::try_from(n).ok());
        let text = parse_body(rest, line, words)?;
        if number == Some(-1) && !words.first().is_some_and(|w| w.is(b'M', 110)) {
            return Err(LineError::BadLineNumber);
        }
        Ok((number, text, matches!(marker, Some((_, Field::Crc(_))))))
    }

    /// A line from its parts, to be [encoded](Self::encode) (a host sending a program).
    ///
    /// `words` must not include the line number. `text` is for a line whose only word is one
    /// of [`TEXT_COMMANDS`]; it must be printable ASCII without `*` or `;`, and without
    /// surrounding spaces. Fails with [`EncodeError::TooLong`] beyond [`MAX_WORDS`],
    /// [`EncodeError::OutOfRange`] for a letter that is not upper-case ASCII, a first word `N`
    /// (it would read back as the line number) or words after a text command,
    /// [`EncodeError::InvalidText`] for a bad text or a text after another command.
    pub fn from_parts(
        number: Option<u32>,
        words: &[Word],
        text: Option<&'a [u8]>,
    ) -> Result<Line<'a>, EncodeError> {
        let takes_text = words.first().is_some_and(is_text_command);
        let misplaced =
            words.first().is_some_and(|w| w.letter == b'N') || (takes_text && words.len() > 1);
        let malformed =
            |w: &Word| !w.letter.is_ascii_uppercase() || (w.bare && takes_a_number(w.letter));
        if misplaced || words.iter().any(malformed) {
            return Err(EncodeError::OutOfRange);
        }
        let text = text.filter(|t| !t.is_empty());
        if let Some(t) = text {
            let printable = t
                .iter()
                .all(|&b| (b' '..=b'~').contains(&b) && b != b'*' && b != b';');
            if !takes_text || !printable || trim(t).len() != t.len() {
                return Err(EncodeError::InvalidText);
            }
        }
        Ok(Line {
            number: number.map(i64::from),
            words: Vec::from_slice(words).map_err(|_| EncodeError::TooLong)?,
            text,
            crc: false,
        })
    }

    /// The same line, to be [encoded](Self::encode) with `check` after `*` when numbered
    /// ([`from_parts`](Self::from_parts) gives the XOR).
    pub fn with_check(mut self, check: Check) -> Self {
        self.crc = check == Check::Crc16;
        self
    }

    /// The check the line carried (or is to be written with): `None` for a line without `N`.
    pub fn check(&self) -> Option<Check> {
        self.number?;
        Some(if self.crc { Check::Crc16 } else { Check::Xor })
    }

    /// The line number, if the line has one (`None` too for the `N-1 M110` reset that some
    /// hosts send, after which line 0 is expected).
    pub fn number(&self) -> Option<u32> {
        self.number.and_then(|n| u32::try_from(n).ok())
    }

    /// The XOR checksum of the line as [encoded](Self::encode), for a numbered line. For a line
    /// received in canonical form with the XOR this is the checksum it carried;
    /// [`parse`](Self::parse) has checked the one it carried either way.
    pub fn checksum(&self) -> Option<u8> {
        self.number?;
        let mut xor = Xor::default();
        self.write_body(&mut xor).ok()?;
        Some(xor.value)
    }

    /// The words in order, without the `N` line number.
    pub fn words(&self) -> &[Word] {
        &self.words
    }

    /// The number of the first word with `letter` (upper or lower case) that has one.
    pub fn get(&self, letter: u8) -> Option<Decimal> {
        let letter = letter.to_ascii_uppercase();
        self.words
            .iter()
            .find(|w| w.letter == letter && !w.bare)
            .map(|w| w.value)
    }

    /// Whether `letter` is on the line, with a number or [bare](Word::bare) (`G28 X`).
    pub fn mentions(&self, letter: u8) -> bool {
        let letter = letter.to_ascii_uppercase();
        self.words.iter().any(|w| w.letter == letter)
    }

    /// The first [bare](Word::bare) word's letter, if any.
    pub fn bare_letter(&self) -> Option<u8> {
        self.words.iter().find(|w| w.bare).map(|w| w.letter)
    }

    /// Whether a word with `letter` and a number is present.
    pub fn has(&self, letter: u8) -> bool {
        self.get(letter).is_some()
    }

    /// The command word: the first word, when it is a `G`, `M` or `T` word.
    pub fn command(&self) -> Option<Word> {
        self.words
            .first()
            .filter(|w| matches!(w.letter, b'G' | b'M' | b'T'))
            .copied()
    }

    /// Whether the command word is `letter` + `number` (`line.is_command(b'M', 110)`).
    pub fn is_command(&self, letter: u8, number: i64) -> bool {
        self.command().is_some_and(|w| w.is(letter, number))
    }

    /// Whether the line holds nothing: blank, comments only, or a line number alone.
    pub fn is_empty(&self) -> bool {
        self.words.is_empty() && self.text.is_none()
    }

    /// The free text of a command of [`TEXT_COMMANDS`] (the `M117` message, the `M23`/`M28`/
    /// `M29`/`M30` file name): the bytes after the command word, up to `*` or `;`, trimmed of
    /// spaces and tabs. `None` for other commands and when the text is empty.
    pub fn text_arg(&self) -> Option<&'a [u8]> {
        self.text
    }

    /// Write the canonical form into `out` and return its length: `N<n>` if numbered, the
    /// words separated by one space, the text after one space, then `*<checksum>` if numbered
    /// (its [`check`](Self::check): the XOR, or the five digits of the CRC-16). No terminator
    /// is written. `"N3 T0*57"` encodes to itself.
    ///
    /// Fails with [`EncodeError::BufferTooSmall`] when `out` is too small and
    /// [`EncodeError::TooLong`] when the result exceeds [`MAX_LINE_LEN`].
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, EncodeError> {
        let mut cursor = Cursor::new(out);
        self.write_body(&mut cursor)?;
        if let Some(check) = self.check() {
            put_check(&mut cursor, check)?;
        }
        if cursor.len() > MAX_LINE_LEN {
            return Err(EncodeError::TooLong);
        }
        Ok(cursor.len())
    }

    fn write_body<S: Sink>(&self, out: &mut S) -> Result<(), EncodeError> {
        let mut first = true;
        if let Some(n) = self.number {
            out.put(b'N')?;
            out.put_i64(n)?;
            first = false;
        }
        for word in &self.words {
            if !first {
                out.put(b' ')?;
            }
            word.write(out)?;
            first = false;
        }
        if let Some(text) = self.text {
            out.put(b' ')?;
            out.put_all(text)?;
        }
        Ok(())
    }
}

/// Write `*` and the check of what `cursor` holds.
fn put_check(cursor: &mut Cursor<'_>, check: Check) -> Result<(), EncodeError> {
    match check {
        Check::Xor => {
            let cs = checksum(cursor.written());
            cursor.put(b'*')?;
            cursor.put_u64(u64::from(cs))
        }
        Check::Crc16 => {
            let crc = crc16(cursor.written());
            cursor.put(b'*')?;
            let mut divisor = 10_000u16;
            while divisor > 0 {
                cursor.put(b'0' + ((crc / divisor) % 10) as u8)?;
                divisor /= 10;
            }
            Ok(())
        }
    }
}

/// Whether `bytes` is a numbered line whose check (the XOR or the CRC-16) verifies: a record
/// that is whole even without its terminator, and that no frame can be (a frame's `*` padding
/// is no check).
pub fn is_checked_line(bytes: &[u8]) -> bool {
    Line::parse(bytes).is_ok_and(|line| line.check().is_some())
}

/// Write `body` (one line of a program, without terminator) as numbered line `number`:
/// `N<number> <body>*<checksum>`, with the body's comments and surrounding spaces removed.
/// What a host sends when it streams a file with line numbers. Returns the length written.
pub fn write_numbered(number: u32, body: &[u8], out: &mut [u8]) -> Result<usize, EncodeError> {
    write_checked(number, body, Check::Xor, out)
}

/// [`write_numbered`] with the check of choice: `Check::Crc16` writes
/// `N<number> <body>*<five digits>`, for a controller that announces `LINE_CHECK:CRC16` in its
/// `M115` answer.
pub fn write_checked(
    number: u32,
    body: &[u8],
    check: Check,
    out: &mut [u8],
) -> Result<usize, EncodeError> {
    let body = trim(strip_comments(body));
    if body.contains(&b'*') || body.iter().any(|&b| b < b' ' && b != b'\t') {
        return Err(EncodeError::InvalidText);
    }
    let mut cursor = Cursor::new(out);
    cursor.put(b'N')?;
    cursor.put_u64(u64::from(number))?;
    if !body.is_empty() {
        cursor.put(b' ')?;
        cursor.put_all(body)?;
    }
    put_check(&mut cursor, check)?;
    if cursor.len() > MAX_LINE_LEN {
        return Err(EncodeError::TooLong);
    }
    Ok(cursor.len())
}

/// `bytes` up to its first `;` comment, with `(…)` comments kept (they may be text).
fn strip_comments(bytes: &[u8]) -> &[u8] {
    let end = bytes.iter().position(|&b| b == b';').unwrap_or(bytes.len());
    bytes.get(..end).unwrap_or(bytes)
}

fn trim_terminators(mut bytes: &[u8]) -> &[u8] {
    while let [rest @ .., b'\r' | b'\n'] = bytes {
        bytes = rest;
    }
    bytes
}

fn is_blank(b: u8) -> bool {
    b == b' ' || b == b'\t'
}

fn trim(mut bytes: &[u8]) -> &[u8] {
    while let [first, rest @ ..] = bytes {
        if !is_blank(*first) {
            break;
        }
        bytes = rest;
    }
    while let [rest @ .., last] = bytes {
        if !is_blank(*last) {
            break;
        }
        bytes = rest;
    }
    bytes
}

/// Whether `bytes` (terminators trimmed) is one to five digits between blanks and nothing else.
fn is_fragment(bytes: &[u8]) -> bool {
    let digits = trim(bytes);
    (1..=CRC_DIGITS).contains(&digits.len()) && digits.iter().all(u8::is_ascii_digit)
}

/// The check written after `*`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Field {
    Xor(u8),
    Crc(u16),
}

/// The checksum marker and the check after it, if the line has them.
///
/// The marker is the first `*` of the line, as in the seed's C snippet. A `*` inside a `;`
/// comment is the marker only when a well-formed checksum follows it (so that a line whose `N`
/// was damaged into `;` is still caught); otherwise it is comment text.
fn checksum_marker(bytes: &[u8]) -> Result<Option<(usize, Field)>, LineError> {
    let Some(at) = bytes.iter().position(|&b| b == b'*') else {
        return Ok(None);
    };
    let in_comment = bytes.iter().take(at).any(|&b| b == b';');
    match parse_checksum_field(bytes.get(at + 1..).unwrap_or(&[])) {
        Ok(received) => Ok(Some((at, received))),
        Err(_) if in_comment => Ok(None),
        Err(e) => Err(e),
    }
}

/// The number after `*`: 1 to 3 digits, at most 255 (the XOR), or exactly 5 digits, at most
/// 65535 (the CRC-16); then only spaces and a comment.
fn parse_checksum_field(field: &[u8]) -> Result<Field, LineError> {
    let digits = field.iter().take_while(|b| b.is_ascii_digit()).count();
    if !(1..=3).contains(&digits) && digits != CRC_DIGITS {
        return Err(LineError::BadChecksum);
    }
    let value = field
        .iter()
        .take(digits)
        .fold(0u32, |v, &b| v * 10 + u32::from(b - b'0'));
    let after = trim(field.get(digits..).unwrap_or(&[]));
    if !matches!(after.first(), None | Some(b';' | b'(')) {
        return Err(LineError::BadChecksum);
    }
    if digits == CRC_DIGITS {
        u16::try_from(value)
            .map(Field::Crc)
            .map_err(|_| LineError::BadChecksum)
    } else {
        u8::try_from(value)
            .map(Field::Xor)
            .map_err(|_| LineError::BadChecksum)
    }
}

/// `bytes` after its leading spaces, tabs and closed `(…)` comments.
fn skip_blanks_and_comments(mut bytes: &[u8]) -> &[u8] {
    loop {
        match bytes.split_first() {
            Some((b, rest)) if is_blank(*b) => bytes = rest,
            Some((b'(', rest)) => match rest.iter().position(|&c| c == b')') {
                Some(close) => bytes = rest.get(close + 1..).unwrap_or(&[]),
                None => return bytes,
            },
            _ => return bytes,
        }
    }
}

/// The leading `N` word (the first word, after any comment), if any, and the bytes after it.
fn parse_line_number(body: &[u8]) -> Result<(Option<i64>, &[u8]), LineError> {
    let rest = skip_blanks_and_comments(body);
    let Some((b'N' | b'n', after)) = rest.split_first() else {
        return Ok((None, body));
    };
    let (negative, digits_from) = match after.first() {
        Some(b'-') => (true, 1),
        _ => (false, 0),
    };
    let digits = after
        .get(digits_from..)
        .unwrap_or(&[])
        .iter()
        .take_while(|b| b.is_ascii_digit())
        .count();
    let end = digits_from + digits;
    let delimited = match after.get(end) {
        None => true,
        Some(&b) => is_blank(b) || b.is_ascii_alphabetic() || matches!(b, b'(' | b';'),
    };
    if digits == 0 || digits > 10 || !delimited {
        return Err(LineError::BadLineNumber);
    }
    let magnitude = after
        .get(digits_from..end)
        .unwrap_or(&[])
        .iter()
        .fold(0i64, |v, &b| v * 10 + i64::from(b - b'0'));
    let value = if negative { -magnitude } else { magnitude };
    if !(-1..=i64::from(u32::MAX)).contains(&value) {
        return Err(LineError::BadLineNumber);
    }
    Ok((Some(value), after.get(end..).unwrap_or(&[])))
}

type Words = Vec<Word, MAX_WORDS, u8>;

/// The words of a line body (after the line number, before the checksum marker), into
/// `words`; returns the text of a text command.
fn parse_body<'a>(
    body: &'a [u8],
    line: Option<u32>,
    words: &mut Words,
) -> Result<Option<&'a [u8]>, LineError> {
    let mut i = 0;
    while let Some(&b) = body.get(i) {
        match b {
            b' ' | b'\t' => i += 1,
            b';' => break,
            b'(' => {
                let close = body
                    .get(i..)
                    .and_then(|rest| rest.iter().position(|&c| c == b')'))
                    .ok_or(LineError::UnclosedComment { line })?;
                i += close + 1;
            }
            b'A'..=b'Z' | b'a'..=b'z' => {
                let letter = b.to_ascii_uppercase();
                let rest = body.get(i + 1..).unwrap_or(&[]);
                let (word, used) = match parse_prefix(rest) {
                    Ok((value, used)) => (Word::new(letter, value), used),
                    // A parameter letter that ends where it starts: a flag (`G28 X Y`).
                    Err(NumberError::NoDigits) if !takes_a_number(letter) && ends_a_word(rest) => {
                        (Word::bare(letter), 0)
                    }
                    Err(NumberError::NoDigits) => return Err(LineError::MissingValue { line }),
                    Err(NumberError::OutOfRange) => {
                        return Err(LineError::NumberOutOfRange { line });
                    }
                };
                words
                    .push(word)
                    .map_err(|_| LineError::TooManyWords { line })?;
                i += 1 + used;
                if words.len() == 1 && is_text_command(&word) {
                    return parse_text(body.get(i..).unwrap_or(&[]), line);
                }
            }
            _ => return Err(LineError::UnexpectedCharacter { line }),
        }
    }
    Ok(None)
}

/// Whether `rest` (what follows a letter) starts where a word may end: nothing, a blank,
/// another letter or a comment.
fn ends_a_word(rest: &[u8]) -> bool {
    match rest.first() {
        None => true,
        Some(&b) => is_blank(b) || b.is_ascii_alphabetic() || matches!(b, b'(' | b';'),
    }
}

fn is_text_command(word: &Word) -> bool {
    word.letter == b'M'
        && word
            .value
            .as_integer()
            .is_some_and(|n| TEXT_COMMANDS.contains(&n))
}

/// The free text of a text command: up to `;`, trimmed, no control bytes.
fn parse_text(rest: &[u8], line: Option<u32>) -> Result<Option<&[u8]>, LineError> {
    let text = trim(strip_comments(rest));
    if text.iter().any(|&b| (b < b' ' && b != b'\t') || b == 0x7f) {
        return Err(LineError::UnexpectedCharacter { line });
    }
    Ok((!text.is_empty()).then_some(text))
}

/// What to answer for a line that could not be taken, from
/// [`LineNumbering::recover`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Recovery {
    /// Ask for this line again: reply `rs <line>` (see [`crate::reply::Reply::Resend`]).
    Resend(u32),
    /// The line arrived but cannot be run: report the error (`!! E<code> …`, see
    /// [`crate::reply::Reply::Fault`]) and reply `ok`, so that the host goes on. Resending it
    /// would not help.
    Reject,
    /// Answer nothing: the record is the rest of a line that has been answered already (see
    /// [`LineError::Fragment`]). One line sent, one reply.
    Drop,
}

/// Whether `line` may come without number and check on a strong link: nothing but a comment,
/// a report (`M105`, `M114`, `M115`, `M119`) or the emergency stop `M112`.
fn is_report_or_stop(line: &Line<'_>) -> bool {
    line.words().first().is_none_or(|w| {
        w.letter == b'M' && matches!(w.value.as_integer(), Some(105 | 112 | 114 | 115 | 119))
    })
}

/// Line-number continuity for one link.
///
/// After [`new`](Self::new) the first line expected is 1 (a host that starts otherwise sends
/// `M110` first: `M110 N0`, `N0 M110` or `N-1 M110`). Each accepted numbered line moves the
/// expectation to its number plus one (wrapping after `u32::MAX`); lines without a number are
/// not checked and do not move it. An `M110` line is always accepted and sets the counter: to
/// its `N` parameter if it has one (`M110 N100`: line 101 is next), else to its own line number
/// (`N123 M110`: line 124 is next).
///
/// A numbered line that carries the [`crc16`] switches the link to the strong check: from then
/// on a numbered line with only the XOR is [`LineError::WeakChecksum`] (asked again), since a
/// damaged line of a host that sends the CRC can pass the XOR; so is a line without number
/// other than a comment, a report (`M105`, `M114`, `M115`, `M119`) or `M112`, since a CRC line
/// whose `N` was damaged and whose `*` was lost arrives as one. An `M110` sets the check the
/// link requires to its own (so a host that sends only the XOR can take over with its `M110`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LineNumbering {
    expected: u32,
    numbered: bool,
    strong: bool,
}

impl Default for LineNumbering {
    fn default() -> Self {
        Self::new()
    }
}

impl LineNumbering {
    /// A fresh link: line 1 is expected.
    pub const fn new() -> Self {
        Self {
            expected: 1,
            numbered: false,
            strong: false,
        }
    }

    /// Check a parsed line. `Ok(())` takes it (and advances the counter if numbered);
    /// [`LineError::OutOfOrder`] means it must not be run and `expected` must be asked again,
    /// as does [`LineError::WeakChecksum`] (a numbered line with the XOR on a link that requires
    /// the CRC-16). An `M110` with an `N` parameter that is not an integer in `-1..=u32::MAX` is
    /// [`LineError::BadLineNumber`].
    pub fn accept(&mut self, line: &Line<'_>) -> Result<(), LineError> {
        if line.is_command(b'M', 110) {
            let current = match line.get(b'N') {
                Some(param) => Some(
                    param
                        .as_integer()
                        .filter(|n| (-1..=i64::from(u32::MAX)).contains(n))
                        .ok_or(LineError::BadLineNumber)?,
                ),
                None => line.number,
            };
            if let Some(current) = current {
                // -1 + 1 = 0; u32::MAX + 1 wraps to 0 like any other line.
                self.expected = (current + 1) as u32;
            }
            self.numbered |= line.number.is_some();
            self.strong = line.crc;
            return Ok(());
        }
        let Some(got) = line.number() else {
            // On a strong link a line without number is as likely a numbered line whose `N`
            // was damaged and whose `*` was lost (`J1580 G1 X-0.15 Y0.1564948`) as a typed one:
            // only what cannot move the machine is taken.
            if self.strong && !is_report_or_stop(line) {
                return Err(LineError::WeakChecksum);
            }
            return Ok(());
        };
        if self.strong && !line.crc {
            return Err(LineError::WeakChecksum);
        }
        if got != self.expected {
            return Err(LineError::OutOfOrder {
                expected: self.expected,
                got,
            });
        }
        self.expected = got.wrapping_add(1);
        self.numbered = true;
        self.strong |= line.crc;
        Ok(())
    }

    /// The line number expected next.
    pub fn expected(&self) -> u32 {
        self.expected
    }

    /// Expect `line` next (as if `N<line - 1> M110` had been received).
    pub fn set_expected(&mut self, line: u32) {
        self.expected = line;
    }

    /// What to answer for a line that failed [`Line::parse`] or [`accept`](Self::accept) (or
    /// for a [`crate::stream::Event::TooLong`], as [`LineError::TooLong`]):
    ///
    /// - a framing error (damaged checksum, `N` or `*` field, line out of order) asks a resend
    ///   of the expected line;
    /// - a line too long asks a resend if the host numbers its lines (a lost terminator is the
    ///   likely cause), else is rejected;
    /// - a body error on an intact line is rejected; if that line carried the expected number
    ///   the counter moves past it, so that the host's next line is in order; if it carried
    ///   another number, the expected line is asked again;
    /// - a [`LineError::Fragment`] (a checksum alone) from a host that numbers its lines gets no
    ///   answer: it is the rest of a line cut in two by a damaged `*`, whose first part, a
    ///   numbered line without checksum, was asked again already. From a host that does not
    ///   number its lines it is rejected like any line that is not G-code.
    pub fn recover(&mut self, error: &LineError) -> Recovery {
        match *error {
            LineError::TooLong | LineError::Fragment if !self.numbered => Recovery::Reject,
            LineError::Fragment => Recovery::Drop,
            LineError::OutOfOrder { expected, .. } => Recovery::Resend(expected),
            e if e.is_framing() => Recovery::Resend(self.expected),
            e => match e.line() {
                Some(n) if n == self.expected => {
                    self.expected = n.wrapping_add(1);
                    Recovery::Reject
                }
                Some(_) => Recovery::Resend(self.expected),
                // On a strong link, a scrap of a damaged CRC line (see `accept`).
                None if self.strong => Recovery::Resend(self.expected),
                None => Recovery::Reject,
            },
        }
    }

    /// What to answer for a [`crate::stream::Event::Garbage`] on a G-code link: the dropped
    /// bytes may have held a line, so a host that numbers its lines is asked to resend the
    /// expected one (harmless if it was not sent yet: it is the next line anyway); a host that
    /// does not number them cannot resend, and the garbage is only reported.
    pub fn recover_garbage(&self) -> Recovery {
        if self.numbered {
            Recovery::Resend(self.expected)
        } else {
            Recovery::Reject
        }
    }

    /// Whether the host numbers its lines (a numbered line has been accepted).
    pub fn is_numbered(&self) -> bool {
        self.numbered
    }

    /// Whether the link requires the CRC-16 on numbered lines (see the type's documentation).
    pub fn is_strong(&self) -> bool {
        self.strong
    }

    /// Ask line `line` again after it was [accepted](Self::accept): the interpreter refused it
    /// for a reason damage on the link can cause, and refusing changed nothing. The counter goes
    /// back to `line` (only from `line + 1`, so only the last line accepted can be given back).
    /// Returns whether it did.
    pub fn give_back(&mut self, line: u32) -> bool {
        if self.expected != line.wrapping_add(1) {
            return false;
        }
        self.expected = line;
        true
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic, clippy::indexing_slicing)]
mod tests {
    extern crate std;
    use std::vec::Vec as StdVec;

    use super::*;

    const SEED_BLOCK: [&str; 6] = [
        "N3 T0*57",
        "N4 G92 E0*67",
        "N5 G28*22",
        "N6 G1 F1500.0*82",
        "N7 G1 X2.0 Y2.0 F3000.0*85",
        "N8 G1 X3.0 Y3.0*33",
    ];

    fn w(letter: u8, m: i64, s: u8) -> Word {
        Word::new(letter, Decimal::new(m, s))
    }

    fn encode(line: &Line<'_>) -> StdVec<u8> {
        let mut out = [0u8; 300];
        let n = line.encode(&mut out).unwrap();
        out[..n].to_vec()
    }

    #[test]
    fn the_seed_block_decodes_and_re_encodes_byte_for_byte() {
        let expected: [(u32, &[Word]); 6] = [
            (3, &[w(b'T', 0, 0)]),
            (4, &[w(b'G', 92, 0), w(b'E', 0, 0)]),
            (5, &[w(b'G', 28, 0)]),
            (6, &[w(b'G', 1, 0), w(b'F', 15000, 1)]),
            (
                7,
                &[
                    w(b'G', 1, 0),
                    w(b'X', 20, 1),
                    w(b'Y', 20, 1),
                    w(b'F', 30000, 1),
                ],
            ),
            (8, &[w(b'G', 1, 0), w(b'X', 30, 1), w(b'Y', 30, 1)]),
        ];
        let mut numbering = LineNumbering::new();
        numbering.set_expected(3);
        for (text, (number, words)) in SEED_BLOCK.iter().zip(expected) {
            let line = Line::parse(text.as_bytes()).unwrap();
            assert_eq!(line.number(), Some(number));
            assert_eq!(line.words(), words);
            let cs: u8 = text.rsplit('*').next().unwrap().parse().unwrap();
            assert_eq!(line.checksum(), Some(cs));
            assert_eq!(encode(&line), text.as_bytes());
            numbering.accept(&line).unwrap();
        }
        assert_eq!(numbering.expected(), 9);
    }

    #[test]
    fn the_seed_comment_examples() {
        let line = Line::parse(b"N3 T0*57 ;This is a comment").unwrap();
        assert_eq!(line.words(), &[w(b'T', 0, 0)]);
        assert!(Line::parse(b"; So is this").unwrap().is_empty());
        assert!(Line::parse(b"").unwrap().is_empty());
        assert!(Line::parse(b"   \t").unwrap().is_empty());
        let line = Line::parse(b"G1 (move) X5 (fast) F3000 ; done").unwrap();
        assert_eq!(
            line.words(),
            &[w(b'G', 1, 0), w(b'X', 5, 0), w(b'F', 3000, 0)]
        );
    }

    #[test]
    fn terminators_and_case() {
        for text in [
            &b"g1 x90.6 y13.8 e22.4\r\n"[..],
            b"G1 X90.6 Y13.8 E22.4\n",
            b"G1X90.6Y13.8E22.4\r",
        ] {
            let line = Line::parse(text).unwrap();
            assert_eq!(encode(&line), b"G1 X90.6 Y13.8 E22.4");
        }
    }

    #[test]
    fn both_or_neither() {
        assert_eq!(Line::parse(b"N5 G28"), Err(LineError::MissingChecksum));
        let computed = checksum(b"G28");
        assert_eq!(
            Line::parse(b"G28*22"),
            Err(LineError::ChecksumMismatch {
                computed,
                received: 22
            })
        );
        let unnumbered = std::format!("G28*{computed}");
        assert_eq!(
            Line::parse(unnumbered.as_bytes()),
            Err(LineError::MissingLineNumber)
        );
        assert_eq!(
            Line::parse(b"N5 G28*23"),
            Err(LineError::ChecksumMismatch {
                computed: 22,
                received: 23
            })
        );
        assert_eq!(Line::parse(b"N5 G28*"), Err(LineError::BadChecksum));
        assert_eq!(Line::parse(b"N5 G28*256"), Err(LineError::BadChecksum));
        assert_eq!(Line::parse(b"N5 G28*22x"), Err(LineError::BadChecksum));
        assert_eq!(Line::parse(b"N5 G28*22 x"), Err(LineError::BadChecksum));
        assert!(Line::parse(b"N5 G28*22 (ok) ").is_ok());
        // A `*` inside a `;` comment is comment text, unless a checksum follows it.
        assert_eq!(
            Line::parse(b"N5 G28 ; a*b"),
            Err(LineError::MissingChecksum)
        );
        assert!(Line::parse(b"G28 ; a*b").is_ok());
        assert!(Line::parse(b"; ***** header *****").unwrap().is_empty());
        assert_eq!(
            Line::parse(b";3 T0*57"),
            Err(LineError::ChecksumMismatch {
                computed: checksum(b";3 T0"),
                received: 57
            })
        );
    }

    #[test]
    fn line_numbers() {
        assert_eq!(
            Line::parse(b"N G1*99"),
            Err(LineError::ChecksumMismatch {
                computed: checksum(b"N G1"),
                received: 99
            })
        );
        let mut buf = [0u8; 64];
        for body in [
            &b"N1.5 G1"[..],
            b"N G1",
            b"N-2 G1",
            b"N4294967296 G1",
            b"N-1 G1",
        ] {
            let cs = checksum(body);
            let mut line = body.to_vec();
            line.push(b'*');
            line.extend_from_slice(cs.to_string().as_bytes());
            assert_eq!(
                Line::parse(&line),
                Err(LineError::BadLineNumber),
                "{:?}",
                std::str::from_utf8(body)
            );
        }
        let n = write_numbered(4_294_967_295, b"G1", &mut buf).unwrap();
        assert_eq!(Line::parse(&buf[..n]).unwrap().number(), Some(u32::MAX));
        let n = write_numbered(12, b"G1X5", &mut buf).unwrap();
        let line = Line::parse(&buf[..n]).unwrap();
        assert_eq!(line.words(), &[w(b'G', 1, 0), w(b'X', 5, 0)]);
        // The first word, even after a comment, is the line number.
        assert_eq!(Line::parse(b"(c) N-9"), Err(LineError::BadLineNumber));
        assert_eq!(Line::parse(b"(c)N5 G1*79").map(|l| l.number()), Ok(Some(5)));
        // No space needed after the number.
        let line = Line::parse(b"N12G1X5*86").unwrap();
        assert_eq!(line.number(), Some(12));
    }

    use std::string::ToString;

    #[test]
    fn words_and_errors() {
        // A parameter letter alone is a flag; a command letter alone is an error.
        let line = Line::parse(b"g28 x Y(home)E;").unwrap();
        assert_eq!(
            line.words(),
            &[
                w(b'G', 28, 0),
                Word::bare(b'X'),
                Word::bare(b'Y'),
                Word::bare(b'E')
            ]
        );
        assert_eq!((line.get(b'X'), line.has(b'X')), (None, false));
        assert!(line.mentions(b'x') && !line.mentions(b'Z'));
        assert_eq!(line.bare_letter(), Some(b'X'));
        assert_eq!(Line::parse(b"G1 X").unwrap().bare_letter(), Some(b'X'));
        let mut buf = [0u8; 32];
        let n = line.encode(&mut buf).unwrap();
        assert_eq!(&buf[..n], b"G28 X Y E");
        assert_eq!(Line::parse(&buf[..n]), Ok(line));
        for text in [&b"G"[..], b"G1 M", b"T", b"X1 N"] {
            assert_eq!(
                Line::parse(text),
                Err(LineError::MissingValue { line: None }),
                "{:?}",
                std::str::from_utf8(text)
            );
        }
        assert_eq!(
            Line::from_parts(None, &[Word::bare(b'G')], None),
            Err(EncodeError::OutOfRange)
        );
        assert_eq!(
            Line::parse(b"G1 X-"),
            Err(LineError::MissingValue { line: None })
        );
        assert_eq!(
            Line::parse(b"G1 #5"),
            Err(LineError::UnexpectedCharacter { line: None })
        );
        assert_eq!(
            Line::parse(b"G1 X1.2.3"),
            Err(LineError::UnexpectedCharacter { line: None })
        );
        assert_eq!(
            Line::parse("G1 X1 é".as_bytes()),
            Err(LineError::UnexpectedCharacter { line: None })
        );
        assert!(Line::parse("G1 X1 ; é".as_bytes()).is_ok());
        assert_eq!(
            Line::parse(b"G1 (x"),
            Err(LineError::UnclosedComment { line: None })
        );
        assert_eq!(
            Line::parse(b"G1 X0.0000000000000000001"),
            Err(LineError::NumberOutOfRange { line: None })
        );
        let mut many = StdVec::new();
        for _ in 0..MAX_WORDS {
            many.extend_from_slice(b"X1 ");
        }
        assert_eq!(Line::parse(&many).unwrap().words().len(), MAX_WORDS);
        many.extend_from_slice(b"Y2");
        assert_eq!(
            Line::parse(&many),
            Err(LineError::TooManyWords { line: None })
        );
        let mut buf = [0u8; 64];
        let n = write_numbered(9, b"G1 X5 #", &mut buf).unwrap();
        assert_eq!(
            Line::parse(&buf[..n]),
            Err(LineError::UnexpectedCharacter { line: Some(9) })
        );
    }

    #[test]
    fn length_limit() {
        let mut long = [b' '; MAX_LINE_LEN + 1];
        long[0] = b'G';
        long[1] = b'1';
        assert!(Line::parse(&long[..MAX_LINE_LEN]).is_ok());
        assert_eq!(Line::parse(&long), Err(LineError::TooLong));
        // The canonical form of an accepted line may be longer than the limit.
        let tight = b"X1".repeat(MAX_WORDS);
        let line = Line::parse(&tight).unwrap();
        let mut out = [0u8; 512];
        assert_eq!(line.encode(&mut out), Ok(MAX_WORDS * 3 - 1));
        let mut small = [0u8; 4];
        assert_eq!(line.encode(&mut small), Err(EncodeError::BufferTooSmall));
    }

    #[test]
    fn text_arguments() {
        let line = Line::parse(b"M23 filename.gco").unwrap();
        assert_eq!(line.text_arg(), Some(&b"filename.gco"[..]));
        assert_eq!(line.words(), &[w(b'M', 23, 0)]);
        let line = Line::parse(b"M117 Hello (world) X5 ; comment").unwrap();
        assert_eq!(line.text_arg(), Some(&b"Hello (world) X5"[..]));
        assert_eq!(encode(&line), b"M117 Hello (world) X5");
        let mut buf = [0u8; 64];
        let n = write_numbered(3, b"M28 part.g", &mut buf).unwrap();
        let line = Line::parse(&buf[..n]).unwrap();
        assert_eq!(line.text_arg(), Some(&b"part.g"[..]));
        assert_eq!(encode(&line), &buf[..n]);
        assert_eq!(Line::parse(b"M117").unwrap().text_arg(), None);
        assert_eq!(Line::parse(b"M117   ").unwrap().text_arg(), None);
        assert_eq!(Line::parse(b"G1 M117 x1").unwrap().text_arg(), None);
        assert_eq!(Line::parse(b"M1170").unwrap().text_arg(), None);
    }

    #[test]
    fn from_parts() {
        let line = Line::from_parts(Some(3), &[w(b'T', 0, 0)], None).unwrap();
        assert_eq!(encode(&line), b"N3 T0*57");
        assert_eq!(line.checksum(), Some(57));
        assert_eq!(line, Line::parse(b"N3 T0*57").unwrap());
        assert_eq!(
            Line::from_parts(None, &[w(b'g', 1, 0)], None),
            Err(EncodeError::OutOfRange)
        );
        assert_eq!(
            Line::from_parts(None, &[w(b'M', 117, 0)], Some(b"a*b")),
            Err(EncodeError::InvalidText)
        );
        assert_eq!(
            Line::from_parts(None, &[], Some(b"x")),
            Err(EncodeError::InvalidText)
        );
        assert_eq!(
            Line::from_parts(None, &[w(b'G', 1, 0)], Some(b"x")),
            Err(EncodeError::InvalidText)
        );
        assert_eq!(
            Line::from_parts(None, &[w(b'N', 1, 0)], None),
            Err(EncodeError::OutOfRange)
        );
        assert_eq!(
            Line::from_parts(None, &[w(b'M', 117, 0), w(b'X', 1, 0)], None),
            Err(EncodeError::OutOfRange)
        );
        let msg = Line::from_parts(Some(2), &[w(b'M', 117, 0)], Some(b"Hi there")).unwrap();
        assert_eq!(encode(&msg), b"N2 M117 Hi there*105".to_vec());
    }

    #[test]
    fn numbering() {
        let mut n = LineNumbering::new();
        assert_eq!(n.expected(), 1);
        let parse = |t: &'static [u8]| Line::parse(t).unwrap();
        assert!(n.accept(&parse(b"G28")).is_ok());
        assert_eq!(n.expected(), 1);
        // OctoPrint: "M110 N0" then N1, N2...
        assert!(n.accept(&parse(b"M110 N0")).is_ok());
        assert_eq!(n.expected(), 1);
        // Printrun: "N-1 M110" then N0, N1...
        let line = Line::parse(b"N-1 M110*15").unwrap();
        assert_eq!(line.number(), None);
        assert!(n.accept(&line).is_ok());
        assert_eq!(n.expected(), 0);
        // The seed: "N123 M110" sets the current line, 124 is next.
        let mut buf2 = [0u8; 64];
        let len = write_numbered(123, b"M110", &mut buf2).unwrap();
        assert!(n.accept(&Line::parse(&buf2[..len]).unwrap()).is_ok());
        assert_eq!(n.expected(), 124);
        let len = write_numbered(125, b"G1", &mut buf2).unwrap();
        let line = Line::parse(&buf2[..len]).unwrap();
        let err = n.accept(&line).unwrap_err();
        assert_eq!(
            err,
            LineError::OutOfOrder {
                expected: 124,
                got: 125
            }
        );
        assert_eq!(err.resend_line(), Some(124));
        assert_eq!(n.recover(&err), Recovery::Resend(124));
        assert_eq!(n.expected(), 124);
        assert_eq!(
            n.recover(&LineError::ChecksumMismatch {
                computed: 1,
                received: 2
            }),
            Recovery::Resend(124)
        );
        // A body error on the expected line: rejected, and the counter moves past it.
        assert_eq!(
            n.recover(&LineError::MissingValue { line: Some(124) }),
            Recovery::Reject
        );
        assert_eq!(n.expected(), 125);
        assert_eq!(
            n.recover(&LineError::MissingValue { line: Some(7) }),
            Recovery::Resend(125)
        );
        assert_eq!(
            n.recover(&LineError::MissingValue { line: None }),
            Recovery::Reject
        );
        assert_eq!(n.recover(&LineError::TooLong), Recovery::Resend(125));
        assert_eq!(
            LineNumbering::new().recover(&LineError::TooLong),
            Recovery::Reject
        );
        assert_eq!(n.recover_garbage(), Recovery::Resend(125));
        assert!(n.is_numbered());
        assert_eq!(LineNumbering::new().recover_garbage(), Recovery::Reject);
        // An M110 parameter out of range.
        assert_eq!(
            n.accept(&parse(b"M110 N4294967296")),
            Err(LineError::BadLineNumber)
        );
        assert_eq!(
            n.accept(&parse(b"M110 N1.5")),
            Err(LineError::BadLineNumber)
        );
        n.set_expected(u32::MAX);
        let len = write_numbered(u32::MAX, b"G1", &mut buf2).unwrap();
        assert!(n.accept(&Line::parse(&buf2[..len]).unwrap()).is_ok());
        assert_eq!(n.expected(), 0);
    }

    #[test]
    fn the_crc_is_five_digits_after_the_star_and_round_trips() {
        assert_eq!(crc16(b"123456789"), 0x29B1);
        assert_eq!(crc16(b"123456789*00000"), 0x29B1);
        let mut buf = [0u8; 64];
        let n = write_checked(5, b"G28", Check::Crc16, &mut buf).unwrap();
        let text = std::format!("N5 G28*{:05}", crc16(b"N5 G28"));
        assert_eq!(&buf[..n], text.as_bytes());
        let line = Line::parse(&buf[..n]).unwrap();
        assert_eq!(line.check(), Some(Check::Crc16));
        assert_eq!(encode(&line), text.as_bytes());
        let xor = Line::parse(b"N5 G28*22").unwrap();
        assert_eq!(xor.check(), Some(Check::Xor));
        assert_eq!(Line::parse(b"G28").unwrap().check(), None);
        assert_eq!(
            encode(&xor.clone().with_check(Check::Crc16)),
            text.as_bytes()
        );
        // A damaged digit, a damaged body, a field of four or six digits.
        let mut damaged = buf;
        damaged[n - 1] = if damaged[n - 1] == b'0' { b'1' } else { b'0' };
        assert!(matches!(
            Line::parse(&damaged[..n]),
            Err(LineError::CrcMismatch { .. })
        ));
        assert!(matches!(
            Line::parse(std::format!("N5 G29*{:05}", crc16(b"N5 G28")).as_bytes()),
            Err(LineError::CrcMismatch { .. })
        ));
        assert_eq!(Line::parse(b"N5 G28*0022"), Err(LineError::BadChecksum));
        assert_eq!(Line::parse(b"N5 G28*000022"), Err(LineError::BadChecksum));
        assert_eq!(Line::parse(b"N5 G28*70000"), Err(LineError::BadChecksum));
    }

    #[test]
    fn the_crc_sees_what_the_xor_misses() {
        // The same bit flipped in two bytes, and two bytes swapped: the XOR matches.
        let mut buf = [0u8; 64];
        for (sent, got) in [
            (&b"G1 X10 Y20"[..], &b"G1 X11 Y21"[..]),
            (b"G1 X12 Y20", b"G1 X21 Y20"),
            (b"G1 X5 F3000", b"G1 X7 F1000"),
        ] {
            let n = write_numbered(7, sent, &mut buf).unwrap();
            let xor = std::str::from_utf8(&buf[..n])
                .unwrap()
                .rsplit('*')
                .next()
                .unwrap();
            let damaged = std::format!("N7 {}*{xor}", std::str::from_utf8(got).unwrap());
            assert!(Line::parse(damaged.as_bytes()).is_ok(), "{damaged}");
            let n = write_checked(7, sent, Check::Crc16, &mut buf).unwrap();
            let crc = std::str::from_utf8(&buf[..n])
                .unwrap()
                .rsplit('*')
                .next()
                .unwrap();
            let damaged = std::format!("N7 {}*{crc}", std::str::from_utf8(got).unwrap());
            assert!(matches!(
                Line::parse(damaged.as_bytes()),
                Err(LineError::CrcMismatch { .. })
            ));
        }
    }

    #[test]
    fn once_a_line_carries_the_crc_every_numbered_line_must() {
        let mut buf = [0u8; 64];
        let mut n = LineNumbering::new();
        let len = write_checked(0, b"M110 N0", Check::Crc16, &mut buf).unwrap();
        n.accept(&Line::parse(&buf[..len]).unwrap()).unwrap();
        assert!(n.is_strong());
        let len = write_numbered(1, b"G1 X5", &mut buf).unwrap();
        let weak = Line::parse(&buf[..len]).unwrap();
        assert_eq!(n.accept(&weak), Err(LineError::WeakChecksum));
        assert_eq!(n.recover(&LineError::WeakChecksum), Recovery::Resend(1));
        let len = write_checked(1, b"G1 X5", Check::Crc16, &mut buf).unwrap();
        n.accept(&Line::parse(&buf[..len]).unwrap()).unwrap();
        assert_eq!(n.expected(), 2);
        // Unnumbered reports and M112 are taken; other unnumbered lines are asked again.
        n.accept(&Line::parse(b"M105").unwrap()).unwrap();
        n.accept(&Line::parse(b"M115").unwrap()).unwrap();
        n.accept(&Line::parse(b"M112").unwrap()).unwrap();
        n.accept(&Line::parse(b"; note").unwrap()).unwrap();
        assert_eq!(
            n.accept(&Line::parse(b"G28").unwrap()),
            Err(LineError::WeakChecksum)
        );
        assert_eq!(n.expected(), 2);
        // A host that sends only the XOR takes over with its M110.
        n.accept(&Line::parse(b"N-1 M110*15").unwrap()).unwrap();
        assert!(!n.is_strong());
        let len = write_numbered(0, b"G1 X5", &mut buf).unwrap();
        n.accept(&Line::parse(&buf[..len]).unwrap()).unwrap();
        // A CRC line switches a link to the strong check.
        let len = write_checked(1, b"G1 X6", Check::Crc16, &mut buf).unwrap();
        n.accept(&Line::parse(&buf[..len]).unwrap()).unwrap();
        assert!(n.is_strong());
    }

    #[test]
    fn a_crc_line_with_its_n_damaged_and_its_star_lost_does_not_run_on_a_strong_link() {
        // Seen in the 20,000-line soak (host/tests/soak.rs): `N1580 G1 X-0.15 Y0.15*64948`
        // with `N` flipped into `J` and the `*` dropped parses as a line without number, a
        // move with the checksum's digits in its Y value.
        let mut buf = [0u8; 64];
        let mut n = LineNumbering::new();
        n.set_expected(1579);
        let len = write_checked(1579, b"G1 X0.10 Y-0.10", Check::Crc16, &mut buf).unwrap();
        n.accept(&Line::parse(&buf[..len]).unwrap()).unwrap();
        let damaged = Line::parse(b"J1580 G1 X-0.15 Y0.1564948").unwrap();
        assert_eq!(damaged.number(), None);
        assert_eq!(n.accept(&damaged), Err(LineError::WeakChecksum));
        assert_eq!(n.recover(&LineError::WeakChecksum), Recovery::Resend(1580));
        // The rest of `N6128 G1 X-0.05 Y0.05*53100` cut by a `*` damaged into a line end, with
        // one more byte damaged: not a checksum alone, not G-code either. Asked again.
        let scrap = Line::parse(b"%3100").unwrap_err();
        assert_eq!(n.recover(&scrap), Recovery::Resend(1580));
        // A host that does not send the CRC keeps sending lines without number.
        let mut plain = LineNumbering::new();
        plain
            .accept(&Line::parse(b"N1 G1 X5*100").unwrap())
            .unwrap();
        plain.accept(&damaged).unwrap();
        assert_eq!(plain.recover(&scrap), Recovery::Reject);
    }

    #[test]
    fn a_checksum_alone_is_the_fragment_of_a_cut_line() {
        // "N5 G28*22" with its `*` damaged into a line end arrives as two records.
        assert_eq!(Line::parse(b"N5 G28"), Err(LineError::MissingChecksum));
        assert_eq!(Line::parse(b"22"), Err(LineError::Fragment));
        assert_eq!(Line::parse(b"04621\r\n"), Err(LineError::Fragment));
        assert_eq!(
            Line::parse(b"123456"),
            Err(LineError::UnexpectedCharacter { line: None })
        );
        let mut numbered = LineNumbering::new();
        numbered.set_expected(5);
        let mut buf = [0u8; 32];
        let len = write_numbered(5, b"G28", &mut buf).unwrap();
        numbered.accept(&Line::parse(&buf[..len]).unwrap()).unwrap();
        // One reply for the two records: `rs` for the first, nothing for the second.
        assert_eq!(
            numbered.recover(&LineError::MissingChecksum),
            Recovery::Resend(6)
        );
        assert_eq!(numbered.recover(&LineError::Fragment), Recovery::Drop);
        assert_eq!(
            LineNumbering::new().recover(&LineError::Fragment),
            Recovery::Reject
        );
    }

    #[test]
    fn only_the_last_line_accepted_can_be_given_back() {
        let mut n = LineNumbering::new();
        let mut buf = [0u8; 32];
        let len = write_numbered(1, b"G1 Q5", &mut buf).unwrap();
        n.accept(&Line::parse(&buf[..len]).unwrap()).unwrap();
        assert!(!n.give_back(0));
        assert!(n.give_back(1));
        assert_eq!(n.expected(), 1);
        assert!(!n.give_back(1));
        assert!(n.accept(&Line::parse(&buf[..len]).unwrap()).is_ok());
    }

    #[test]
    fn printrun_reset_round_trips() {
        let line = Line::parse(b"N-1 M110*15").unwrap();
        assert_eq!(encode(&line), b"N-1 M110*15");
        assert_eq!(line.checksum(), Some(15));
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod comment_tests {
    use super::*;

    #[test]
    fn a_semicolon_inside_parentheses_is_comment_text() {
        let l = Line::parse(b"(tool: 3.175 mm; stock top at Z0; zero here)").unwrap();
        assert!(l.is_empty());
        let l = Line::parse(b"G1 X5 (a; b) Y6 ; the rest").unwrap();
        assert_eq!(l.get(b'Y').and_then(|v| v.as_integer()), Some(6));
    }
}
