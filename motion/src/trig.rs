//! Double-precision trigonometry for arcs: the sine and cosine of the angles an arc sweeps, and
//! the angle of a vector.
//!
//! Thread side. An arc's angles stay within a few turns of zero, so the reduction to
//! `[−π/4, π/4]` needs π/2 in two parts only (no reduction for huge arguments), and short
//! polynomials finish the job. Each result is within a few units in the last place of the exact
//! value: a chord end 2 m from its centre moves by less than a picometre, far below the
//! nanometre every position is rounded to. Small code matters here: the boards' flash holds
//! the whole firmware, and these functions take about a quarter of the code of `libm`'s
//! general-purpose ones (2 KiB against 8 KiB on the Cortex-M4).

use core::f64::consts::{FRAC_2_PI, FRAC_PI_2, FRAC_PI_4, PI};

use libm::{round, sqrt};

/// π/2 in two parts: `PIO2_HI` holds its first 33 significant bits, so `k × PIO2_HI` is exact
/// for every `|k| < 2^20`; `PIO2_LO` is the rest, rounded.
const PIO2_HI: f64 = 1.570_796_326_734_125_6;
const PIO2_LO: f64 = 6.077_100_506_506_192e-11;

/// tan(π/8) = √2 − 1.
const TAN_PI_8: f64 = 0.414_213_562_373_095_03;

/// `1 / n!`, correctly rounded: `n!` is exact in `f64` up to `18!`.
const fn inverse_factorial(n: u32) -> f64 {
    let mut f = 1.0;
    let mut i = 2;
    while i <= n {
        f *= i as f64;
        i += 1;
    }
    1.0 / f
}

/// The sine's Taylor coefficients after `x`: `(−1)^k / (2k + 1)!` for `k` = 1 to 8. At
/// `|x| ≤ π/4` the first term left out, `x^19 / 19!`, is below 10⁻¹⁹.
const SIN: [f64; 8] = {
    let mut c = [0.0; 8];
    let mut k = 0;
    while k < 8 {
        let v = inverse_factorial(2 * (k as u32 + 1) + 1);
        c[k] = if k % 2 == 0 { -v } else { v };
        k += 1;
    }
    c
};

/// The cosine's Taylor coefficients after `1`: `(−1)^k / (2k)!` for `k` = 1 to 9; the first
/// term left out, `x^20 / 20!`, is below 10⁻²⁰ at `|x| ≤ π/4`.
const COS: [f64; 9] = {
    let mut c = [0.0; 9];
    let mut k = 0;
    while k < 9 {
        let v = inverse_factorial(2 * (k as u32 + 1));
        c[k] = if k % 2 == 0 { -v } else { v };
        k += 1;
    }
    c
};

/// `Σ coefficients[i] × z^i`, by Horner's rule.
fn horner(coefficients: &[f64], z: f64) -> f64 {
    coefficients.iter().rev().fold(0.0, |acc, &c| acc * z + c)
}

/// `(sin x, cos x)`, for `|x|` below about 10⁶ (an arc's angles are a few turns at most);
/// beyond, the reduction loses accuracy. NaN gives NaN.
pub(crate) fn sin_cos(x: f64) -> (f64, f64) {
    // x = k·π/2 + r with |r| ≤ π/4 (and a rounding's worth).
    let k = round(x * FRAC_2_PI);
    let r = (x - k * PIO2_HI) - k * PIO2_LO;
    let z = r * r;
    let s = r + r * z * horner(&SIN, z);
    let c = 1.0 + z * horner(&COS, z);
    // `as` saturates, and NaN becomes 0: the quadrant never fails.
    match (k as i64) & 3 {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// The angle of the vector `(x, y)` from the positive x axis, in `[−π, π]`, as
/// `atan2(y, x)` of C: the sign of `y` (zero included) gives the sign of the result, and
/// `(±0, −x)` is `±π`. NaN in gives NaN; the arguments are finite otherwise.
pub(crate) fn atan2(y: f64, x: f64) -> f64 {
    if x.is_nan() || y.is_nan() {
        return f64::NAN;
    }
    let (ax, ay) = (x.abs(), y.abs());
    // The angle of (|x|, |y|), in [0, π/2].
    let first = if ay <= ax {
        if ax == 0.0 { 0.0 } else { atan_unit(ay / ax) }
    } else {
        FRAC_PI_2 - atan_unit(ax / ay)
    };
    let half = if x.is_sign_negative() {
        PI - first
    } else {
        first
    };
    if y.is_sign_negative() { -half } else { half }
}

/// `atan t` for `t` in `[0, 1]`.
fn atan_unit(t: f64) -> f64 {
    // Above tan(π/8): atan t = π/4 + atan((t − 1)/(t + 1)), whose argument is in [1 − √2, 0].
    let (base, u) = if t > TAN_PI_8 {
        (FRAC_PI_4, (t - 1.0) / (t + 1.0))
    } else {
        (0.0, t)
    };
    // Halved: atan u = 2·atan(u / (1 + √(1 + u²))), whose argument is below tan(π/16) ≈ 0.2 in
    // magnitude; there the series to v^25 leaves out less than 10⁻¹⁹.
    let v = u / (1.0 + sqrt(1.0 + u * u));
    let z = v * v;
    base + 2.0 * (v + v * z * horner(&ATAN, z))
}

/// The arctangent's Taylor coefficients after `v`: `(−1)^k / (2k + 1)` for `k` = 1 to 12.
const ATAN: [f64; 12] = {
    let mut c = [0.0; 12];
    let mut k = 0;
    while k < 12 {
        let v = 1.0 / (2 * (k + 1) + 1) as f64;
        c[k] = if k % 2 == 0 { -v } else { v };
        k += 1;
    }
    c
};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::xorshift;

    /// A uniform value in `[−1, 1)`.
    fn unit(state: &mut u64) -> f64 {
        (xorshift(state) >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }

    #[test]
    fn sine_and_cosine_match_libm_over_an_arcs_angles_and_beyond() {
        let mut state = 0x9e37_79b9_7f4a_7c15;
        let mut worst = 0.0f64;
        for i in 0..200_000 {
            // Mostly an arc's range (a few turns), some far beyond it.
            let scale = if i % 10 == 0 { 1.0e5 } else { 4.0 * PI };
            let x = unit(&mut state) * scale;
            let (s, c) = sin_cos(x);
            worst = worst
                .max((s - libm::sin(x)).abs())
                .max((c - libm::cos(x)).abs());
        }
        assert!(worst < 4e-16, "worst error {worst:e}");
    }

    #[test]
    fn sine_and_cosine_at_the_quadrants() {
        assert_eq!(sin_cos(0.0), (0.0, 1.0));
        for k in -8i32..=8 {
            let (s, c) = sin_cos(f64::from(k) * FRAC_PI_2);
            let (es, ec) =
                [(0.0, 1.0), (1.0, 0.0), (0.0, -1.0), (-1.0, 0.0)][k.rem_euclid(4) as usize];
            assert!(
                (s - es).abs() < 1e-15 && (c - ec).abs() < 1e-15,
                "{k}: {s} {c}"
            );
        }
        let (s, c) = sin_cos(f64::NAN);
        assert!(s.is_nan() && c.is_nan());
    }

    #[test]
    fn atan2_matches_libm_at_every_scale_and_quadrant() {
        let mut state = 0x2545_f491_4f6c_dd1d;
        let mut worst = 0.0f64;
        for i in 0..200_000 {
            let scale = [1e-9, 1e-3, 1.0, 1e3, 1e9][i % 5];
            let (y, x) = (unit(&mut state) * scale, unit(&mut state) * scale);
            let a = atan2(y, x);
            let e = libm::atan2(y, x);
            worst = worst.max((a - e).abs() / e.abs().max(1e-300));
        }
        assert!(worst < 1e-15, "worst relative error {worst:e}");
        // Near-parallel and near-perpendicular vectors (an arc's sweep of almost none or a
        // half turn).
        for (y, x) in [
            (1e-12, 1.0),
            (-1e-12, 1.0),
            (1e-12, -1.0),
            (-1e-12, -1.0),
            (1.0, 1e-12),
        ] {
            let (a, e) = (atan2(y, x), libm::atan2(y, x));
            assert!((a - e).abs() <= 4e-16 * e.abs(), "{y} {x}: {a} {e}");
        }
    }

    #[test]
    fn atan2_at_the_axes_and_signed_zeros() {
        assert_eq!(atan2(0.0, 1.0), 0.0);
        assert_eq!(atan2(0.0, 0.0), 0.0);
        assert!(atan2(-0.0, 1.0).is_sign_negative());
        assert_eq!(atan2(0.0, -1.0), PI);
        assert_eq!(atan2(-0.0, -1.0), -PI);
        assert_eq!(atan2(1.0, 0.0), FRAC_PI_2);
        assert_eq!(atan2(-1.0, 0.0), -FRAC_PI_2);
        assert_eq!(atan2(1.0, 1.0), FRAC_PI_4);
        assert!(atan2(f64::NAN, 1.0).is_nan() && atan2(1.0, f64::NAN).is_nan());
    }
}
