//! Byte sinks and integer formatting shared by the encoders (no `core::fmt` on these paths:
//! it is large in flash and slow).

use crate::error::EncodeError;

/// Something bytes are written to.
pub(crate) trait Sink {
    /// Write one byte.
    fn put(&mut self, byte: u8) -> Result<(), EncodeError>;

    /// Write every byte of `bytes`.
    fn put_all(&mut self, bytes: &[u8]) -> Result<(), EncodeError> {
        bytes.iter().try_for_each(|&b| self.put(b))
    }

    /// Write `value` in decimal, without sign or padding.
    fn put_u64(&mut self, value: u64) -> Result<(), EncodeError> {
        let mut digits = [0u8; 20];
        let n = digits_of(value, &mut digits);
        self.put_all(digits.get(digits.len() - n..).unwrap_or(&[]))
    }

    /// Write `value` in decimal, with `-` when negative.
    fn put_i64(&mut self, value: i64) -> Result<(), EncodeError> {
        if value < 0 {
            self.put(b'-')?;
        }
        self.put_u64(value.unsigned_abs())
    }

    /// Write `value` in exactly `width` decimal digits, zero-padded.
    fn put_padded(&mut self, value: u64, width: usize) -> Result<(), EncodeError> {
        let mut digits = [0u8; 20];
        let n = digits_of(value, &mut digits);
        if n > width {
            return Err(EncodeError::OutOfRange);
        }
        (n..width).try_for_each(|_| self.put(b'0'))?;
        self.put_all(digits.get(digits.len() - n..).unwrap_or(&[]))
    }
}

/// The decimal digits of `value`, right-aligned in `out`; returns how many.
pub(crate) fn digits_of(mut value: u64, out: &mut [u8; 20]) -> usize {
    let mut n = 0;
    for slot in out.iter_mut().rev() {
        *slot = b'0' + (value % 10) as u8;
        value /= 10;
        n += 1;
        if value == 0 {
            break;
        }
    }
    n
}

/// A sink over a caller's buffer.
pub(crate) struct Cursor<'a> {
    buf: &'a mut [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    pub(crate) fn new(buf: &'a mut [u8]) -> Self {
        Self { buf, pos: 0 }
    }

    /// Bytes written so far.
    pub(crate) fn len(&self) -> usize {
        self.pos
    }

    /// The bytes written so far.
    pub(crate) fn written(&self) -> &[u8] {
        self.buf.get(..self.pos).unwrap_or(&[])
    }

    /// Fill the rest of the buffer with `byte`.
    pub(crate) fn fill(&mut self, byte: u8) {
        if let Some(rest) = self.buf.get_mut(self.pos..) {
            rest.fill(byte);
        }
        self.pos = self.buf.len();
    }
}

impl Sink for Cursor<'_> {
    fn put(&mut self, byte: u8) -> Result<(), EncodeError> {
        let slot = self
            .buf
            .get_mut(self.pos)
            .ok_or(EncodeError::BufferTooSmall)?;
        *slot = byte;
        self.pos += 1;
        Ok(())
    }
}

/// A sink that only XORs and counts what it is given: the checksum of a line's canonical form.
#[derive(Default)]
pub(crate) struct Xor {
    pub(crate) value: u8,
    pub(crate) len: usize,
}

impl Sink for Xor {
    fn put(&mut self, byte: u8) -> Result<(), EncodeError> {
        self.value ^= byte;
        self.len = self.len.saturating_add(1);
        Ok(())
    }
}

/// Adapts a [`core::fmt::Formatter`] for `Display` impls that reuse the encoders.
pub(crate) struct FmtSink<'a, 'b>(pub(crate) &'a mut core::fmt::Formatter<'b>);

impl Sink for FmtSink<'_, '_> {
    fn put(&mut self, byte: u8) -> Result<(), EncodeError> {
        core::fmt::Write::write_char(self.0, char::from(byte))
            .map_err(|_| EncodeError::BufferTooSmall)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic, clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn integers() {
        let mut buf = [0u8; 64];
        let mut c = Cursor::new(&mut buf);
        c.put_u64(0).unwrap();
        c.put(b' ').unwrap();
        c.put_i64(i64::MIN).unwrap();
        c.put(b' ').unwrap();
        c.put_u64(u64::MAX).unwrap();
        c.put(b' ').unwrap();
        c.put_padded(42, 4).unwrap();
        assert_eq!(
            c.written(),
            b"0 -9223372036854775808 18446744073709551615 0042"
        );
        assert_eq!(c.put_padded(12345, 4), Err(EncodeError::OutOfRange));
    }

    #[test]
    fn full_buffer() {
        let mut buf = [0u8; 2];
        let mut c = Cursor::new(&mut buf);
        assert_eq!(c.put_u64(123), Err(EncodeError::BufferTooSmall));
    }
}
