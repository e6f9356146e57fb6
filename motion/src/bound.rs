//! Bounds on double-precision values, one comparison each.
//!
//! `f64::min` and `f64::max` call `fmin` and `fmax` for their rules on NaN; on the boards'
//! cores, none of which has double-precision hardware, each is a library call around a
//! software comparison and a NaN test (about 70 instructions on the Cortex-M4, where a
//! comparison alone is about 20). Segment preparation bounds several values per phase of
//! every block. The value bounded is the first argument: a NaN there gives the bound, as
//! `f64::min` and `f64::max` do. A bound at 0, the most common, is an integer comparison.

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

#[cfg(test)]
mod tests {
    use super::*;

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
