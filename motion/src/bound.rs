//! Bounds on double-precision values, one comparison each, and the tests and operations on
//! them that an integer operation on their bits can do.
//!
//! `f64::min` and `f64::max` call `fmin` and `fmax` for their rules on NaN; on the boards'
//! cores, none of which has double-precision hardware, each is a library call around a
//! software comparison and a NaN test (about 70 instructions on the Cortex-M4, where a
//! comparison alone is about 20). Segment preparation bounds several values per phase of
//! every block. The value bounded is the first argument: a NaN there gives the bound, as
//! `f64::min` and `f64::max` do. A bound at 0, the most common, is an integer comparison.
//! So are a test for 0 or above it and a halving ([`is_zero`], [`is_positive`], [`half`]);
//! [`product`], [`sum`] and [`difference`] keep an operation in the branch that needs it.

/// `x`, or `cap` when `x` is above it or NaN.
#[inline(always)]
pub(crate) fn at_most(x: f64, cap: f64) -> f64 {
    if x < cap { x } else { cap }
}

/// `x`, or `floor` when `x` is below it or NaN.
#[inline(always)]
pub(crate) fn at_least(x: f64, floor: f64) -> f64 {
    if x > floor { x } else { floor }
}

/// `x`, or 0 when `x` is below 0 or NaN (−0 gives +0): [`at_least`]`(x, 0.0)` in one
/// integer comparison of the bits, where a software comparison is a call.
#[inline(always)]
pub(crate) fn at_least_zero(x: f64) -> f64 {
    // Above 0 up to infinity: the bits from 1 to those of infinity, as an unsigned range.
    if (x.to_bits().wrapping_sub(1)) < f64::INFINITY.to_bits() {
        x
    } else {
        0.0
    }
}

/// Whether `x` is 0 (either sign): one integer test of the bits, where `x == 0.0` is a call.
#[inline(always)]
pub(crate) fn is_zero(x: f64) -> bool {
    // In the two halves: a test of all 64 bits is recognised as `x == 0.0`, and compiled to
    // the comparison's call.
    let bits = x.to_bits();
    ((bits as u32) | (((bits >> 32) as u32) << 1)) == 0
}

/// `x / 2`, exact: the exponent lowered by one, where a multiplication by ½ is a call. Values
/// too small for that (2⁻¹⁰²¹ and below), infinities and NaN take the multiplication.
#[inline(always)]
pub(crate) fn half(x: f64) -> f64 {
    const ONE_EXPONENT: u64 = 1 << 52;
    let exponent = (x.to_bits() >> 52) & 0x7ff;
    if (2..0x7ff).contains(&exponent) {
        f64::from_bits(x.to_bits() - ONE_EXPONENT)
    } else {
        product(x, 0.5)
    }
}

/// `x · y` where a branch needs it: in a call of its own, which the compiler does not work
/// out ahead of the branch. An arithmetic operation counts as cheap to the optimiser, which
/// turns a branch around one into a select: both sides are worked out, and in software
/// double precision each side's multiplication is a call of about 70 instructions.
#[inline(never)]
pub(crate) fn product(x: f64, y: f64) -> f64 {
    x * y
}

/// `x + y` where a branch needs it, as [`product`] is.
#[inline(never)]
pub(crate) fn sum(x: f64, y: f64) -> f64 {
    x + y
}

/// `x − y` where a branch needs it, as [`product`] is.
#[inline(never)]
pub(crate) fn difference(x: f64, y: f64) -> f64 {
    x - y
}

/// Whether `x > 0` (up to +∞; not −0 nor NaN): one integer comparison of the bits, where a
/// software comparison is a call.
#[inline(always)]
pub(crate) fn is_positive(x: f64) -> bool {
    x.to_bits().wrapping_sub(1) < f64::INFINITY.to_bits()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bit_tests_are_the_arithmetic() {
        let values = [
            -1.5,
            -0.0,
            0.0,
            2.0,
            3.5e-300,
            f64::MIN_POSITIVE,
            f64::MIN_POSITIVE * 2.0,
            f64::MIN_POSITIVE / 3.0,
            -f64::MIN_POSITIVE * 4.0,
            f64::MAX,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        for x in values {
            assert_eq!(is_zero(x), x == 0.0, "{x}");
            assert_eq!(half(x).to_bits(), (x * 0.5).to_bits(), "{x}");
            assert_eq!(product(x, 3.0).to_bits(), (x * 3.0).to_bits(), "{x}");
            assert_eq!(difference(x, 1.5).to_bits(), (x - 1.5).to_bits(), "{x}");
            assert_eq!(sum(x, 1.5).to_bits(), (x + 1.5).to_bits(), "{x}");
            assert_eq!(is_positive(x), x > 0.0, "{x}");
        }
        assert!(half(f64::NAN).is_nan());
        assert!(!is_positive(f64::NAN) && !is_positive(-f64::NAN));
    }

    #[test]
    fn bounds_are_min_and_max_for_the_bounded_value() {
        let values = [
            -1.5,
            -0.0,
            0.0,
            2.0,
            3.5,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        let bounds = [-1.5, 0.0, 2.0, f64::INFINITY, f64::NEG_INFINITY];
        for x in values {
            for b in bounds {
                assert_eq!(at_most(x, b), x.min(b), "{x} at most {b}");
                assert_eq!(at_least(x, b), x.max(b), "{x} at least {b}");
            }
            assert_eq!(
                at_least_zero(x).to_bits(),
                at_least(x, 0.0).to_bits(),
                "{x}"
            );
        }
        for x in [
            f64::MIN_POSITIVE,
            5e-324,
            -5e-324,
            f64::MAX,
            -f64::MAX,
            -f64::NAN,
        ] {
            assert_eq!(
                at_least_zero(x).to_bits(),
                at_least(x, 0.0).to_bits(),
                "{x}"
            );
        }
    }
}
