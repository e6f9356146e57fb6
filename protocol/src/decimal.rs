//! Exact decimal numbers as written on the wire.

use core::fmt;

use crate::error::EncodeError;
use crate::write::{FmtSink, Sink};

/// The largest number of fractional digits a [`Decimal`] read from the wire may have.
pub const MAX_SCALE: u8 = 18;

/// An exact decimal as written: `value = mantissa / 10^scale`.
///
/// `"1500.0"` is `(15000, 1)`, `"-3"` is `(-3, 0)`, `".5"` is `(5, 1)`. No float is ever parsed:
/// a number is read digit by digit into the `i64` mantissa, and rejected (never wrapped or
/// rounded) when the mantissa would leave `i64` or when it has more than [`MAX_SCALE`]
/// fractional digits. Any number of up to 18 digits is therefore accepted.
///
/// Equality is on the written form: `1.0` and `1` are different values of this type (they
/// re-encode differently); compare [`Decimal::as_integer`] or [`Decimal::round_to_scale`] for
/// numeric equality.
///
/// Stored in 12 bytes at 4-byte alignment (the mantissa as two 32-bit halves), so that a
/// [`crate::gcode::Word`] is 16 bytes and a parsed line's words copy in two thirds the time
/// on a 32-bit core.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct Decimal {
    /// The mantissa's low 32 bits.
    low: u32,
    /// The mantissa's high 32 bits.
    high: i32,
    scale: u8,
}

impl fmt::Debug for Decimal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Decimal")
            .field("mantissa", &self.mantissa())
            .field("scale", &self.scale)
            .finish()
    }
}

#[cfg(feature = "defmt")]
impl defmt::Format for Decimal {
    fn format(&self, f: defmt::Formatter<'_>) {
        defmt::write!(
            f,
            "Decimal {{ mantissa: {=i64}, scale: {=u8} }}",
            self.mantissa(),
            self.scale
        );
    }
}

/// Why [`parse_prefix`] stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum NumberError {
    /// No digit where a number was expected.
    NoDigits,
    /// More than 18 fractional digits, or a mantissa beyond `i64`.
    OutOfRange,
}

/// The powers of ten an `i64` holds, `10^0..=10^18`.
// Evaluated by the compiler: an index out of range would fail the build, not panic.
#[allow(clippy::indexing_slicing)]
const POWERS_OF_TEN: [i64; 19] = {
    let mut p = [1i64; 19];
    let mut i = 1;
    while i < 19 {
        p[i] = p[i - 1] * 10;
        i += 1;
    }
    p
};

/// `10^exp`, or `None` beyond `i64` (`exp` over 18): the scale of a [`Decimal`] as a divisor
/// or factor, in one load from a table, where a computed power is a loop of checked 64-bit
/// multiplications on a 32-bit core.
pub fn pow10(exp: u8) -> Option<i64> {
    POWERS_OF_TEN.get(usize::from(exp)).copied()
}

impl Decimal {
    /// Zero, written `0`.
    pub const ZERO: Self = Self::new(0, 0);

    /// `mantissa / 10^scale`.
    pub const fn new(mantissa: i64, scale: u8) -> Self {
        Self {
            low: mantissa as u32,
            high: (mantissa >> 32) as i32,
            scale,
        }
    }

    /// An integer, written without a decimal point.
    pub const fn from_integer(value: i64) -> Self {
        Self::new(value, 0)
    }

    /// The digits as an integer (the value times `10^scale`).
    pub const fn mantissa(self) -> i64 {
        ((self.high as i64) << 32) | self.low as i64
    }

    /// How many digits follow the decimal point.
    pub const fn scale(self) -> u8 {
        self.scale
    }

    /// The nearest `f32` (within one unit in the last place).
    pub fn to_f32(self) -> f32 {
        let mut value = self.mantissa() as f32;
        let mut scale = self.scale;
        while scale > 0 {
            let step = scale.min(10);
            value /= POW10_F32.get(usize::from(step)).copied().unwrap_or(1e10);
            scale -= step;
        }
        value
    }

    /// The nearest `f64` (exact division when the mantissa is below 2^53 and the scale at most
    /// 22).
    pub fn to_f64(self) -> f64 {
        let mut value = self.mantissa() as f64;
        let mut scale = self.scale;
        while scale > 0 {
            let step = scale.min(22);
            value /= POW10_F64.get(usize::from(step)).copied().unwrap_or(1e22);
            scale -= step;
        }
        value
    }

    /// The value as an integer when its fractional part is zero: `"1.0"` gives `Some(1)`,
    /// `"1.5"` gives `None`.
    pub fn as_integer(self) -> Option<i64> {
        match pow10(self.scale) {
            Some(p) if self.mantissa() % p == 0 => Some(self.mantissa() / p),
            Some(_) => None,
            // 10^scale exceeds any mantissa: only zero is an integer.
            None => (self.mantissa() == 0).then_some(0),
        }
    }

    /// The value as a `u32` when it is a non-negative integer that fits.
    pub fn as_u32(self) -> Option<u32> {
        self.as_integer().and_then(|v| u32::try_from(v).ok())
    }

    /// The value times `10^scale`, rounded half away from zero: `Decimal("1.23456")
    /// .round_to_scale(4)` is `Some(12346)`. `None` when the result leaves `i64`.
    pub fn round_to_scale(self, scale: u8) -> Option<i64> {
        if scale >= self.scale {
            let factor = pow10(scale - self.scale)?;
            return self.mantissa().checked_mul(factor);
        }
        let Some(divisor) = pow10(self.scale - scale) else {
            // Dividing by more than 10^18 leaves less than one half unit.
            return Some(0);
        };
        let quotient = self.mantissa() / divisor;
        let remainder = self.mantissa() % divisor;
        let half = divisor / 2;
        Some(if remainder.unsigned_abs() >= half.unsigned_abs() {
            quotient + remainder.signum()
        } else {
            quotient
        })
    }

    /// `value` rounded half away from zero to `scale` fractional digits; `None` when it is not
    /// finite, `scale` exceeds [`MAX_SCALE`] or the result leaves `i64`.
    pub fn from_f32(value: f32, scale: u8) -> Option<Self> {
        if !value.is_finite() || scale > MAX_SCALE {
            return None;
        }
        let scaled = f64::from(value) * *POW10_F64.get(usize::from(scale))?;
        let rounded = if scaled < 0.0 {
            scaled - 0.5
        } else {
            scaled + 0.5
        };
        // 2^63 as f64; `as` saturates, so check the range first to refuse instead.
        if !(-9.223_372_036_854_775e18..9.223_372_036_854_775e18).contains(&rounded) {
            return None;
        }
        Some(Self::new(rounded as i64, scale))
    }

    /// `value` to an `f32`'s precision, seven significant digits (at most six after the point),
    /// without trailing fractional zeros: `80`, `93.45678`, `0.013`, as a person writes the
    /// value that was typed. Reports write numbers with it, so that no float formatting is
    /// needed. `None` when it is not finite or beyond `1e12`.
    pub fn from_f32_significant(value: f32) -> Option<Self> {
        if !value.is_finite() || value.abs() >= 1e12 {
            return None;
        }
        let mut whole_digits = 1u8;
        let mut limit = 10.0f32;
        while value.abs() >= limit && whole_digits < 12 {
            whole_digits += 1;
            limit *= 10.0;
        }
        let scale = 7u8.saturating_sub(whole_digits).min(6);
        let mut d = Self::from_f32(value, scale)?;
        while d.scale > 0 && d.mantissa() % 10 == 0 {
            d = Self::new(d.mantissa() / 10, d.scale - 1);
        }
        Some(d)
    }

    /// The whole of `text` as a number (`[+-]digits[.digits]`, at least one digit); `None`
    /// otherwise or when out of range.
    pub fn parse(text: &[u8]) -> Option<Self> {
        match parse_prefix(text) {
            Ok((value, used)) if used == text.len() => Some(value),
            _ => None,
        }
    }

    /// Whether the value is below zero.
    pub const fn is_negative(self) -> bool {
        self.mantissa() < 0
    }

    /// The exact digits (as `Display` writes them: `1500.0`, `-3`, `0.25`) at the start of
    /// `buf`: their length, `None` when they do not fit.
    pub fn encode(self, buf: &mut [u8]) -> Option<usize> {
        let mut out = crate::write::Cursor::new(buf);
        self.write(&mut out).ok()?;
        Some(out.len())
    }

    /// Write the digits, refusing what [`Decimal::parse`] would not read back: a scale over
    /// [`MAX_SCALE`] or the mantissa `i64::MIN`.
    pub(crate) fn write_checked<S: Sink>(self, out: &mut S) -> Result<(), EncodeError> {
        if self.scale > MAX_SCALE || self.mantissa() == i64::MIN {
            return Err(EncodeError::OutOfRange);
        }
        self.write(out)
    }

    pub(crate) fn write<S: Sink>(self, out: &mut S) -> Result<(), EncodeError> {
        if self.mantissa() < 0 {
            out.put(b'-')?;
        }
        let mut digits = [0u8; 20];
        let n = crate::write::digits_of(self.mantissa().unsigned_abs(), &mut digits);
        let digits = digits.get(digits.len() - n..).unwrap_or(&[]);
        let scale = usize::from(self.scale);
        if scale == 0 {
            return out.put_all(digits);
        }
        if n > scale {
            let (int, frac) = digits.split_at(n - scale);
            out.put_all(int)?;
            out.put(b'.')?;
            out.put_all(frac)
        } else {
            out.put_all(b"0.")?;
            (n..scale).try_for_each(|_| out.put(b'0'))?;
            out.put_all(digits)
        }
    }
}

impl Default for Decimal {
    fn default() -> Self {
        Self::ZERO
    }
}

impl From<i32> for Decimal {
    fn from(value: i32) -> Self {
        Self::from_integer(i64::from(value))
    }
}

impl fmt::Display for Decimal {
    /// The exact digits: `1500.0`, `-3`, `0.25`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.write(&mut FmtSink(f)).map_err(|_| fmt::Error)
    }
}

const POW10_F32: [f32; 11] = [1.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10];
const POW10_F64: [f64; 23] = [
    1.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

/// `magnitude` followed by the `count` digits of `chunk` (at most nine), or
/// [`NumberError::OutOfRange`] beyond `i64`.
fn join_digits(magnitude: i64, chunk: u32, count: u8) -> Result<i64, NumberError> {
    if magnitude == 0 {
        return Ok(i64::from(chunk));
    }
    pow10(count)
        .and_then(|p| magnitude.checked_mul(p))
        .and_then(|m| m.checked_add(i64::from(chunk)))
        .ok_or(NumberError::OutOfRange)
}

/// Reads `[+-]digits[.digits]` (at least one digit) from the start of `text`; returns the value
/// and how many bytes it took.
pub(crate) fn parse_prefix(text: &[u8]) -> Result<(Decimal, usize), NumberError> {
    let mut i = 0;
    let negative = match text.first() {
        Some(b'-') => {
            i = 1;
            true
        }
        Some(b'+') => {
            i = 1;
            false
        }
        _ => false,
    };
    let mut magnitude: i64 = 0;
    // Digits gather in 32 bits, nine at a time (below 10⁹), and join the 64-bit magnitude
    // with an overflow check once per nine: a 64-bit checked multiplication per digit costs
    // tens of instructions on a 32-bit core.
    let mut chunk: u32 = 0;
    let mut chunk_digits = 0u8;
    let mut digits = 0usize;
    let mut scale: Option<u8> = None;
    while let Some(&b) = text.get(i) {
        match b {
            b'0'..=b'9' => {
                chunk = chunk * 10 + u32::from(b - b'0');
                chunk_digits += 1;
                if chunk_digits == 9 {
                    magnitude = join_digits(magnitude, chunk, 9)?;
                    (chunk, chunk_digits) = (0, 0);
                }
                digits += 1;
                if let Some(s) = scale.as_mut() {
                    *s += 1;
                    if *s > MAX_SCALE {
                        return Err(NumberError::OutOfRange);
                    }
                }
            }
            b'.' if scale.is_none() => scale = Some(0),
            _ => break,
        }
        i += 1;
    }
    if digits == 0 {
        return Err(NumberError::NoDigits);
    }
    let magnitude = join_digits(magnitude, chunk, chunk_digits)?;
    let mantissa = if negative { -magnitude } else { magnitude };
    Ok((Decimal::new(mantissa, scale.unwrap_or(0)), i))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic, clippy::indexing_slicing)]
mod tests {

    #[test]
    fn a_float_is_written_to_its_precision() {
        let shown = |v: f32| std::format!("{}", Decimal::from_f32_significant(v).unwrap());
        assert_eq!(shown(80.0), "80");
        assert_eq!(shown(93.45678), "93.45678");
        assert_eq!(shown(0.013), "0.013");
        assert_eq!(shown(0.1), "0.1");
        assert_eq!(shown(12_000.0), "12000");
        assert_eq!(shown(-2.5), "-2.5");
        assert_eq!(shown(1_234_567.0), "1234567");
        assert_eq!(Decimal::from_f32_significant(f32::NAN), None);
    }
    extern crate std;
    use std::string::ToString;

    use super::*;

    fn d(text: &str) -> Decimal {
        Decimal::parse(text.as_bytes()).unwrap()
    }

    #[test]
    fn parses_as_written() {
        assert_eq!(d("1500.0"), Decimal::new(15000, 1));
        assert_eq!(d("-3"), Decimal::new(-3, 0));
        assert_eq!(d(".5"), Decimal::new(5, 1));
        assert_eq!(d("5."), Decimal::new(5, 0));
        assert_eq!(d("+0.25"), Decimal::new(25, 2));
        assert_eq!(d("-0.0001"), Decimal::new(-1, 4));
        assert_eq!(Decimal::parse(b""), None);
        assert_eq!(Decimal::parse(b"-"), None);
        assert_eq!(Decimal::parse(b"."), None);
        assert_eq!(Decimal::parse(b"1.2.3"), None);
        assert_eq!(Decimal::parse(b"1e5"), None);
    }

    #[test]
    fn limits() {
        assert_eq!(
            d("999999999999999999"),
            Decimal::new(999_999_999_999_999_999, 0)
        );
        assert_eq!(d("9223372036854775807"), Decimal::new(i64::MAX, 0));
        assert_eq!(
            parse_prefix(b"9223372036854775808"),
            Err(NumberError::OutOfRange)
        );
        assert_eq!(d("0.000000000000000001"), Decimal::new(1, 18));
        assert_eq!(
            parse_prefix(b"0.0000000000000000001"),
            Err(NumberError::OutOfRange)
        );
        assert_eq!(d("-9223372036854775807"), Decimal::new(-i64::MAX, 0));
    }

    #[test]
    fn displays_exact_digits() {
        for text in ["1500.0", "-3", "0.25", "0.005", "-0.0001", "0", "123.456"] {
            assert_eq!(d(text).to_string(), text);
        }
        assert_eq!(
            Decimal::new(i64::MIN, 0).to_string(),
            "-9223372036854775808"
        );
        assert_eq!(Decimal::new(1, 30).to_string().len(), 32);
        for value in [d("-0.0001"), d("1500.0"), Decimal::new(i64::MIN, 0)] {
            let mut buf = [0u8; 24];
            let n = value.encode(&mut buf).unwrap();
            assert_eq!(&buf[..n], value.to_string().as_bytes());
        }
        assert_eq!(Decimal::new(1, 30).encode(&mut [0u8; 31]), None);
    }

    #[test]
    fn conversions() {
        assert_eq!(d("1.0").as_integer(), Some(1));
        assert_eq!(d("1.5").as_integer(), None);
        assert_eq!(d("-7").as_integer(), Some(-7));
        assert_eq!(d("-7").as_u32(), None);
        assert_eq!(d("4294967295").as_u32(), Some(u32::MAX));
        assert_eq!(d("4294967296").as_u32(), None);
        assert_eq!(Decimal::new(0, 40).as_integer(), Some(0));
        assert_eq!(Decimal::new(5, 40).as_integer(), None);
        assert_eq!(d("1500.0").to_f32(), 1500.0);
        assert_eq!(d("0.1").to_f64(), 0.1);
        assert_eq!(d("-2.5").to_f64(), -2.5);
        assert_eq!(d("1.23456").round_to_scale(4), Some(12346));
        assert_eq!(d("-1.23455").round_to_scale(4), Some(-12346));
        assert_eq!(d("-1.23454").round_to_scale(4), Some(-12345));
        assert_eq!(d("2").round_to_scale(4), Some(20000));
        assert_eq!(Decimal::new(i64::MAX, 0).round_to_scale(1), None);
        assert_eq!(Decimal::new(9, 30).round_to_scale(2), Some(0));
        assert_eq!(Decimal::from_f32(201.0, 1), Some(Decimal::new(2010, 1)));
        assert_eq!(Decimal::from_f32(-0.125, 2), Some(Decimal::new(-13, 2)));
        assert_eq!(Decimal::from_f32(f32::NAN, 2), None);
        assert_eq!(Decimal::from_f32(1e30, 2), None);
    }
}
