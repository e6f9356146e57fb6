//! Doubles to unsigned integers from their bits.
//!
//! None of the boards' cores has double-precision hardware. A conversion `x as u64` in
//! software is a library call with two comparisons around it (for Rust's saturation), each a
//! call of its own: about 130 instructions on the Cortex-M4, more on RISC-V; `libm::floor` and
//! `libm::ceil` add a call each. Segment preparation converts several values at every phase of
//! every block. Here each conversion is a few integer shifts on the value's bits, exact, and
//! saturating as `as` is: below 0 (and −0) gives 0, 2⁶⁴ or more (and infinity, NaN)
//! `u64::MAX`.

/// The exponent field of 2⁶⁴: from it on, `u64::MAX`.
const SATURATED: u32 = 1087;
/// The exponent field from which a value is an integer (its last mantissa bit is 2⁰).
const INTEGER: u32 = 1075;

/// `x · 2^scale` as an integer when it is one or saturates (`Ok`), else `Err((m, s))` with
/// `x · 2^scale = m · 2^−s` (`s ≥ 1`; for 0 and the subnormals, `s` is beyond 64).
#[inline(always)]
fn split(x: f64, scale: u32) -> Result<u64, (u64, u32)> {
    let bits = x.to_bits();
    let exponent = ((bits >> 52) & 0x7FF) as u32 + scale;
    // The leading bit restored.
    let mantissa = (bits & ((1 << 52) - 1)) | (1 << 52);
    if bits >> 63 != 0 {
        Ok(0)
    } else if exponent >= SATURATED {
        Ok(u64::MAX)
    } else if exponent >= INTEGER {
        // 53 bits shifted by at most 11.
        Ok(mantissa << (exponent - INTEGER))
    } else {
        Err((mantissa, INTEGER - exponent))
    }
}

/// `⌊x⌋`, saturating (see the module).
#[inline]
pub(crate) fn floor_u64(x: f64) -> u64 {
    match split(x, 0) {
        Ok(whole) => whole,
        Err((mantissa, shift)) => mantissa.checked_shr(shift).unwrap_or(0),
    }
}

/// `⌈x⌉`, saturating (see the module).
#[inline]
pub(crate) fn ceil_u64(x: f64) -> u64 {
    // +0 (−0 is negative).
    if x.to_bits() == 0 {
        return 0;
    }
    match split(x, 0) {
        Ok(whole) => whole,
        Err((mantissa, shift)) => match mantissa.checked_shr(shift) {
            Some(whole) if whole << shift == mantissa => whole,
            Some(whole) => whole + 1,
            // Above 0 and below 1.
            None => 1,
        },
    }
}

/// `x` rounded to the nearest integer, halves up, saturating (see the module). Exact, where
/// `(x + 0.5) as u64` could round in the addition.
#[inline]
pub(crate) fn round_up_half(x: f64) -> u64 {
    round_up_half_scaled(x, 0)
}

/// `x · 2^scale` rounded as [`round_up_half`] rounds: a value in fixed point with `scale`
/// fraction bits, without the multiplication.
#[inline]
pub(crate) fn round_up_half_scaled(x: f64, scale: u32) -> u64 {
    match split(x, scale) {
        Ok(whole) => whole,
        Err((mantissa, shift)) => shifted_rounding_up_half(mantissa, shift),
    }
}

/// `m / 2^shift` (`shift ≥ 1`) rounded to the nearest integer, halves up: shifted right to
/// keep one bit below the point, then rounded up on it.
#[inline(always)]
fn shifted_rounding_up_half(m: u64, shift: u32) -> u64 {
    m.checked_shr(shift - 1)
        .map_or(0, |halves| (halves + 1) >> 1)
}

/// `⌊x⌋`, and `x − ⌊x⌋` as an integer in fixed point with `scale` fraction bits, rounded as
/// [`round_up_half_scaled`] rounds (it can reach `2^scale`): the whole and the fraction of a
/// time apart, each exact to its last bit, without a conversion back and a subtraction in
/// software double precision. Saturating as [`floor_u64`] (with no fraction then).
#[inline]
pub(crate) fn floor_and_fraction(x: f64, scale: u32) -> (u64, u64) {
    match split(x, 0) {
        Ok(whole) => (whole, 0),
        Err((mantissa, shift)) => {
            let whole = mantissa.checked_shr(shift).unwrap_or(0);
            // The mantissa's bits below the point, `shift` of them: all of it past 63.
            let below = match 1u64.checked_shl(shift) {
                Some(one) => mantissa & (one - 1),
                None => mantissa,
            };
            let fraction = if shift <= scale {
                below << (scale - shift)
            } else {
                shifted_rounding_up_half(below, shift - scale)
            };
            (whole, fraction)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random doubles of every scale from 2⁻⁴ to 2⁶⁶, with a fraction or without.
    fn samples() -> impl Iterator<Item = f64> {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        (0..300_000).map(move |k| {
            let bits = crate::testing::xorshift(&mut seed);
            let scale = f64::from((bits >> 57) as u32 % 70) - 4.0;
            let x = (bits >> 11) as f64 / (1u64 << 53) as f64 * libm::exp2(scale);
            if k % 3 == 0 { libm::floor(x) } else { x }
        })
    }

    #[test]
    fn floor_and_ceil_are_libm_s_saturated() {
        for x in samples() {
            assert_eq!(floor_u64(x), libm::floor(x) as u64, "{x}");
            assert_eq!(ceil_u64(x), libm::ceil(x) as u64, "{x}");
        }
        for x in [
            0.0,
            -0.0,
            -0.5,
            -3.0,
            f64::MIN_POSITIVE,
            5e-324,
            0.999_999_999_999_999_9,
            1.0,
            18_446_744_073_709_549_568.0,
            18_446_744_073_709_551_616.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ] {
            assert_eq!(floor_u64(x), libm::floor(x) as u64, "{x}");
            assert_eq!(ceil_u64(x), libm::ceil(x) as u64, "{x}");
        }
        assert_eq!(floor_u64(f64::NAN), u64::MAX);
    }

    #[test]
    fn a_value_splits_into_its_floor_and_its_fraction_rounded_in_fixed_point() {
        // `x − ⌊x⌋` is exact in double precision, and so is its product by a power of two.
        let expected = |x: f64, scale: u32| {
            let floor = libm::floor(x);
            let fraction = (x - floor) * libm::exp2(f64::from(scale));
            (floor as u64, round_up_half(fraction))
        };
        let mut fractions = 0;
        for x in samples() {
            for scale in [32, 20] {
                assert_eq!(floor_and_fraction(x, scale), expected(x, scale), "{x}");
            }
            fractions += u32::from(floor_and_fraction(x, 32).1 != 0);
        }
        assert!(fractions > 100_000, "{fractions} with a fraction");
        for x in [0.0, 5e-324, 0.5, 0.999_999_999_999_999_9, 1.0, 2.5e9 + 0.25] {
            assert_eq!(floor_and_fraction(x, 32), expected(x, 32), "{x}");
        }
        // Saturated or negative: no fraction.
        for (x, whole) in [
            (-0.0, 0),
            (-2.5, 0),
            (f64::INFINITY, u64::MAX),
            (1e20, u64::MAX),
        ] {
            assert_eq!(floor_and_fraction(x, 32), (whole, 0), "{x}");
        }
    }

    #[test]
    fn rounding_rounds_halves_up() {
        for (x, rounded) in [
            (0.0, 0),
            (-0.0, 0),
            (-0.7, 0),
            (f64::MIN_POSITIVE, 0),
            (0.25, 0),
            (0.499_999_999_999_999_9, 0),
            (0.5, 1),
            (1.0, 1),
            (1.5, 2),
            (2.5, 3),
            (2.499_999, 2),
            (4_503_599_627_370_495.5, 4_503_599_627_370_496),
            (1.8e19, 18_000_000_000_000_000_000),
            (18_446_744_073_709_549_568.0, 18_446_744_073_709_549_568),
            (18_446_744_073_709_551_616.0, u64::MAX),
            (1e30, u64::MAX),
        ] {
            assert_eq!(round_up_half(x), rounded, "{x}");
        }
        // Against `⌊x + ½⌋` wherever the addition is exact (below 2⁵²), and scaled as the
        // step clocks scale.
        for x in samples().filter(|x| *x < 4_503_599_627_370_496.0) {
            assert_eq!(round_up_half(x), libm::floor(x + 0.5) as u64, "{x}");
            let scaled = x / 4_294_967_296.0;
            assert_eq!(round_up_half_scaled(scaled, 32), round_up_half(x), "{x}");
        }
        assert_eq!(round_up_half_scaled(0.0, 32), 0);
        assert_eq!(round_up_half_scaled(-1.0, 32), 0);
        assert_eq!(round_up_half_scaled(4_294_967_296.0, 32), u64::MAX);
        assert_eq!(
            round_up_half_scaled(4_294_967_295.5, 32),
            18_446_744_071_562_067_968
        );
    }
}
