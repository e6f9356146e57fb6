//! Small fixed-capacity text, and the `E<code> <name> <detail>` text of refusals and faults.

use core::fmt;

use forja_protocol::error::WireError;

use forja_motion::error::{Alarm, CommandError};

use crate::error::{JobError, StoreRefusal};

use forja_hal_abstraction::program::StoreError;

/// ASCII text of at most `C` bytes, written with `core::fmt`. What does not fit is dropped
/// (the write reports an error, the text keeps what fit).
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
        core::str::from_utf8(self.as_bytes()).unwrap_or("")
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
}

impl<const C: usize> fmt::Write for Text<C> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        append_printable(&mut self.buf, &mut self.len, s)
    }
}

/// Append `s` to the text `buf[..*len]`: printable ASCII, `?` for any other byte and for `*`;
/// what does not fit is dropped with an error. One copy for every capacity of [`Text`].
#[inline(never)]
fn append_printable(buf: &mut [u8], len: &mut usize, s: &str) -> fmt::Result {
    for &b in s.as_bytes() {
        let slot = buf.get_mut(*len).ok_or(fmt::Error)?;
        // Only printable ASCII goes on the wire.
        *slot = if (b' '..=b'~').contains(&b) && b != b'*' {
            b
        } else {
            b'?'
        };
        *len += 1;
    }
    Ok(())
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
        let _ = fmt::Write::write_str(&mut text, error.name());
        Self {
            code: error.code(),
            text,
        }
    }

    /// `error`'s code and name, then a space and `detail`.
    #[inline(never)]
    pub(crate) fn with(error: &dyn WireError, detail: fmt::Arguments<'_>) -> Self {
        let mut r = Self::new(error);
        let _ = fmt::Write::write_str(&mut r.text, " ");
        let _ = fmt::Write::write_fmt(&mut r.text, detail);
        r
    }

    pub(crate) fn text(&self) -> &str {
        self.text.as_str()
    }
}

/// An ASCII letter for messages, `?` for anything else.
pub(crate) fn letter(b: u8) -> char {
    if b.is_ascii_graphic() { b as char } else { '?' }
}

/// A command error, its detail naming what was wrong: the command, the word or the axis.
#[inline(never)]
pub(crate) fn command_refusal(e: &CommandError, letters: &[u8]) -> Refusal {
    let axis = |i: u8| letters.get(usize::from(i)).copied().map_or('?', letter);
    match *e {
        CommandError::Unsupported {
            letter: l,
            number: Some(n),
        } => Refusal::with(e, format_args!("{}{n}", letter(l))),
        CommandError::Unsupported { letter: l, .. }
        | CommandError::BadValue { letter: l }
        | CommandError::MissingValue { letter: l }
        | CommandError::UnknownAxis { letter: l }
        | CommandError::RepeatedWord { letter: l } => {
            Refusal::with(e, format_args!("{}", letter(l)))
        }
        CommandError::SoftLimit { axis: a } | CommandError::OutOfReach { axis: a } => {
            Refusal::with(e, format_args!("{}", axis(a)))
        }
        _ => Refusal::new(e),
    }
}

/// An alarm, naming its axis where it has one.
#[inline(never)]
pub(crate) fn alarm_refusal(a: &Alarm, letters: &[u8]) -> Refusal {
    let axis = |i: u8| letters.get(usize::from(i)).copied().map_or('?', letter);
    match *a {
        Alarm::HardLimit { axis: i }
        | Alarm::HomingSwitchNotFound { axis: i }
        | Alarm::HomingSwitchStuck { axis: i }
        | Alarm::DriverFault { axis: i } => Refusal::with(a, format_args!("{}", axis(i))),
        _ => Refusal::new(a),
    }
}

/// A job error, naming the program line and, for a refused line, the inner error.
#[inline(never)]
pub(crate) fn job_refusal(e: &JobError) -> Refusal {
    match *e {
        JobError::Line { line, error } => {
            Refusal::with(e, format_args!("{line:04} {}", error.name()))
        }
        JobError::Syntax { line } => Refusal::with(e, format_args!("{line:04}")),
        _ => Refusal::new(e),
    }
}

/// A program store error, naming the line expected next when the order was wrong.
#[inline(never)]
pub(crate) fn store_refusal(e: &StoreError) -> Refusal {
    match *e {
        StoreError::OutOfOrder { expected, got } => Refusal::with(
            &StoreRefusal(*e),
            format_args!("{got:04} expected {expected:04}"),
        ),
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
        let long = Refusal::with(
            &StoreRefusal(StoreError::Full),
            format_args!("{}", "x".repeat(100)),
        );
        assert_eq!(long.text().len(), REFUSAL_TEXT);
    }

    #[test]
    fn text_keeps_to_printable_ascii_without_stars() {
        let mut t = Text::<8>::new();
        let _ = fmt::Write::write_str(&mut t, "a*b\n");
        assert_eq!(t.as_str(), "a?b?");
        assert!(!t.set(b"\x01"));
        assert!(t.set(b"ok"));
        assert_eq!(t.as_str(), "ok");
    }
}
