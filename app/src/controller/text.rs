//! Small fixed-capacity text, and the `E<code> <name> <detail>` text of refusals and faults.

use core::fmt;

use forja_protocol::error::WireError;
use forja_protocol::gcode::Decimal;

use forja_motion::error::{Alarm, CommandError};

use crate::error::{JobError, StoreRefusal};

use forja_hal_abstraction::program::StoreError;

/// ASCII text of at most `C` bytes, written piece by piece (`push`, `push_number`, …) without
/// `core::fmt`, whose formatting machinery would cost some 4 KiB of code on the MCU. What does
/// not fit is dropped (the text keeps what fit).
#[derive(Clone, Copy)]
pub(crate) struct Text<const C: usize> {
    buf: [u8; C],
    len: usize,
}

impl<const C: usize> Text<C> {
    pub(crate) const fn new() -> Self {
        Self {
            buf: [0; C],
            len: 0,
        }
    }

    /// The text (empty if a non-ASCII byte slipped in).
    pub(crate) fn as_str(&self) -> &str {
        as_text(self.as_bytes())
    }

    pub(crate) fn as_bytes(&self) -> &[u8] {
        self.buf.get(..self.len).unwrap_or(&[])
    }

    /// Replace the text with `bytes` when they fit and are printable ASCII.
    pub(crate) fn set(&mut self, bytes: &[u8]) -> bool {
        let Some(dst) = self.buf.get_mut(..bytes.len()) else {
            return false;
        };
        if !bytes.iter().all(|b| (b' '..=b'~').contains(b)) {
            return false;
        }
        dst.copy_from_slice(bytes);
        self.len = bytes.len();
        true
    }

    /// Append `s`.
    pub(crate) fn push(&mut self, s: &str) -> &mut Self {
        self.push_bytes(s.as_bytes())
    }

    /// Append `bytes`: printable ASCII, `?` for any other byte and for `*`.
    pub(crate) fn push_bytes(&mut self, bytes: &[u8]) -> &mut Self {
        append_printable(&mut self.buf, &mut self.len, bytes);
        self
    }

    /// Append the byte `b`, as [`Text::push_bytes`] does.
    pub(crate) fn push_byte(&mut self, b: u8) -> &mut Self {
        self.push_bytes(&[b])
    }

    /// Append `n` in decimal.
    pub(crate) fn push_number(&mut self, n: impl Into<i64>) -> &mut Self {
        self.push_padded(n, 0)
    }

    /// Append `n` in decimal, with at least `width` digits (zeros in front: `0042`).
    pub(crate) fn push_padded(&mut self, n: impl Into<i64>, width: usize) -> &mut Self {
        append_number(&mut self.buf, &mut self.len, n.into(), width);
        self
    }

    /// Append the exact digits of `d` (`1500.0`, `-3`, `0.25`).
    pub(crate) fn push_decimal(&mut self, d: Decimal) -> &mut Self {
        append_decimal(&mut self.buf, &mut self.len, d);
        self
    }
}

/// For code that writes to any `fmt::Write` (settings): `write_str` and `write_char` only, which
/// leave `core::fmt`'s formatting out of the image.
impl<const C: usize> fmt::Write for Text<C> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        let room = C - self.len;
        self.push(s);
        if s.len() > room {
            Err(fmt::Error)
        } else {
            Ok(())
        }
    }
}

/// Write `n` in decimal to `out` (`core::fmt` would bring its integer formatting in).
pub(crate) fn write_integer(out: &mut impl fmt::Write, n: i64) -> fmt::Result {
    let mut digits = Text::<20>::new();
    digits.push_number(n);
    out.write_str(digits.as_str())
}

/// Write the exact digits of `d` to `out` (`1500.0`, `-3`, `0.25`).
pub(crate) fn write_decimal(out: &mut impl fmt::Write, d: Decimal) -> fmt::Result {
    let mut digits = Text::<48>::new();
    digits.push_decimal(d);
    out.write_str(digits.as_str())
}

/// Append `bytes` to the text `buf[..*len]`: printable ASCII, `?` for any other byte and for
/// `*`; what does not fit is dropped. One copy for every capacity of [`Text`].
#[inline(never)]
fn append_printable(buf: &mut [u8], len: &mut usize, bytes: &[u8]) {
    for &b in bytes {
        let Some(slot) = buf.get_mut(*len) else {
            return;
        };
        // Only printable ASCII goes on the wire.
        *slot = if (b' '..=b'~').contains(&b) && b != b'*' {
            b
        } else {
            b'?'
        };
        *len += 1;
    }
}

/// `bytes` as text, empty if they are not UTF-8. One copy for every capacity of [`Text`].
#[inline(never)]
fn as_text(bytes: &[u8]) -> &str {
    core::str::from_utf8(bytes).unwrap_or("")
}

/// Append the exact digits of `d` to the text `buf[..*len]`, as far as they fit.
#[inline(never)]
fn append_decimal(buf: &mut [u8], len: &mut usize, d: Decimal) {
    let mut digits = [0u8; 48];
    let n = d.encode(&mut digits).unwrap_or(0);
    append_printable(buf, len, digits.get(..n).unwrap_or(&[]));
}

/// Append `n` in decimal to the text `buf[..*len]`, as far as it fits: `width` characters at
/// least, the sign included, with zeros after the sign (as `{:0width$}` writes it).
#[inline(never)]
fn append_number(buf: &mut [u8], len: &mut usize, n: i64, width: usize) {
    let mut digits = [0; 20];
    let mut value = n.unsigned_abs();
    let mut first = digits.len();
    while value > 0 || first == digits.len() {
        first -= 1;
        if let Some(d) = digits.get_mut(first) {
            *d = b'0' + (value % 10) as u8;
        }
        value /= 10;
    }
    let digits = digits.get(first..).unwrap_or(&[]);
    if n < 0 {
        append_printable(buf, len, b"-");
    }
    for _ in digits.len() + usize::from(n < 0)..width {
        append_printable(buf, len, b"0");
    }
    append_printable(buf, len, digits);
}

impl<const C: usize> fmt::Debug for Text<C> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self.as_str(), f)
    }
}

/// The room for `<name> <detail>` in a refusal: a 56 frame carries 49 bytes, of which
/// `Error:E<code> ` takes up to 12.
pub(crate) const REFUSAL_TEXT: usize = 37;

/// Why something was refused or stopped, as it goes on the wire: the stable code, and the
/// stable name followed by a short detail.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Refusal {
    pub(crate) code: u16,
    pub(crate) text: Text<REFUSAL_TEXT>,
}

impl Refusal {
    /// `error`'s code and name, without detail. (A trait object, and never inlined: refusals
    /// are the cold path, and one copy serves every error type and every caller.)
    #[inline(never)]
    pub(crate) fn new(error: &dyn WireError) -> Self {
        let mut text = Text::new();
        text.push(error.name());
        Self {
            code: error.code(),
            text,
        }
    }

    /// `error`'s code and name, then a space and `detail`.
    #[inline(never)]
    pub(crate) fn with(error: &dyn WireError, detail: &str) -> Self {
        let mut r = Self::new(error);
        r.detail().push(detail);
        r
    }

    /// `error`'s code and name, then a space and the number `n` in `width` digits at least
    /// (a line number: `0042`).
    #[inline(never)]
    pub(crate) fn numbered(error: &dyn WireError, n: u16, width: usize) -> Self {
        let mut r = Self::new(error);
        r.detail().push_padded(n, width);
        r
    }

    /// The text with a space after it, for the caller to write its detail (or the next part
    /// of it) in.
    pub(crate) fn detail(&mut self) -> &mut Text<REFUSAL_TEXT> {
        self.text.push(" ")
    }

    pub(crate) fn text(&self) -> &str {
        self.text.as_str()
    }
}

/// An ASCII letter for messages, `?` for anything else.
pub(crate) fn letter(b: u8) -> u8 {
    if b.is_ascii_graphic() { b } else { b'?' }
}

/// A command error, its detail naming what was wrong: the command, the word or the axis.
#[inline(never)]
pub(crate) fn command_refusal(e: &CommandError, letters: &[u8]) -> Refusal {
    let axis = |i: u8| letters.get(usize::from(i)).copied().map_or(b'?', letter);
    let mut r = Refusal::new(e);
    match *e {
        CommandError::Unsupported {
            letter: l,
            number: Some(n),
        } => {
            r.detail().push_byte(letter(l)).push_number(n);
        }
        CommandError::Unsupported { letter: l, .. }
        | CommandError::BadValue { letter: l }
        | CommandError::MissingValue { letter: l }
        | CommandError::UnknownAxis { letter: l }
        | CommandError::RepeatedWord { letter: l } => {
            r.detail().push_byte(letter(l));
        }
        CommandError::SoftLimit { axis: a } | CommandError::OutOfReach { axis: a } => {
            r.detail().push_byte(axis(a));
        }
        _ => {}
    }
    r
}

/// An alarm, naming its axis where it has one.
#[inline(never)]
pub(crate) fn alarm_refusal(a: &Alarm, letters: &[u8]) -> Refusal {
    let axis = |i: u8| letters.get(usize::from(i)).copied().map_or(b'?', letter);
    let mut r = Refusal::new(a);
    if let Alarm::HardLimit { axis: i }
    | Alarm::HomingSwitchNotFound { axis: i }
    | Alarm::HomingSwitchStuck { axis: i }
    | Alarm::DriverFault { axis: i } = *a
    {
        r.detail().push_byte(axis(i));
    }
    r
}

/// A job error, naming the program line and, for a refused line, the inner error.
#[inline(never)]
pub(crate) fn job_refusal(e: &JobError) -> Refusal {
    match *e {
        JobError::Line { line, error } => {
            let mut r = Refusal::numbered(e, line, 4);
            r.detail().push(error.name());
            r
        }
        JobError::Syntax { line } => Refusal::numbered(e, line, 4),
        _ => Refusal::new(e),
    }
}

/// A program store error, naming the line expected next when the order was wrong.
#[inline(never)]
pub(crate) fn store_refusal(e: &StoreError) -> Refusal {
    match *e {
        StoreError::OutOfOrder { expected, got } => {
            let mut r = Refusal::numbered(&StoreRefusal(*e), got, 4);
            r.detail().push("expected ").push_padded(expected, 4);
            r
        }
        _ => Refusal::new(&StoreRefusal(*e)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refusals_name_what_was_wrong() {
        let e = CommandError::Unsupported {
            letter: b'M',
            number: Some(20),
        };
        assert_eq!(command_refusal(&e, b"XY").text(), "unsupported-command M20");
        assert_eq!(
            command_refusal(&CommandError::SoftLimit { axis: 1 }, b"XY").text(),
            "soft-limit Y"
        );
        let r = store_refusal(&StoreError::OutOfOrder {
            expected: 3,
            got: 5,
        });
        assert_eq!((r.code, r.text()), (170, "line-order 0005 expected 0003"));
        let long = Refusal::with(&StoreRefusal(StoreError::Full), &"x".repeat(100));
        assert_eq!(long.text().len(), REFUSAL_TEXT);
    }

    #[test]
    fn numbers_are_written_as_core_fmt_writes_them() {
        for n in [0, 7, -7, 42, 12345, i64::MAX, i64::MIN, -1_000_000] {
            for width in [0, 1, 4, 25] {
                let mut t = Text::<40>::new();
                t.push_padded(n, width);
                assert_eq!(t.as_str(), std::format!("{n:0width$}"), "{n} {width}");
            }
        }
        let mut t = Text::<12>::new();
        t.push("d=")
            .push_decimal(Decimal::new(-25, 3))
            .push_number(-0);
        assert_eq!(t.as_str(), "d=-0.0250");
    }

    #[test]
    fn text_keeps_to_printable_ascii_without_stars() {
        let mut t = Text::<8>::new();
        t.push("a*b\n");
        assert_eq!(t.as_str(), "a?b?");
        assert!(!t.set(b"\x01"));
        assert!(t.set(b"ok"));
        assert_eq!(t.as_str(), "ok");
    }
}
