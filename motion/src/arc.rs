//! `G2`/`G3` arcs cut into chords.
//!
//! Thread side. The arc is computed in double precision around its centre; it is cut into the
//! fewest equal-angle chords whose sagitta (the largest distance between chord and arc,
//! `r·(1 − cos(φ/2))` for a chord of angle `φ`) is at most the configured tolerance. The other
//! axes (helix, extruder) move linearly with the angle. Every chord end is rounded to the
//! nanometre, and the last chord ends exactly at the programmed end point.

use libm::{ceil, sqrt};

use crate::error::CommandError;
use crate::trig::{atan2, sin_cos};

/// Positions in nanometres.
pub(crate) type Nm = i64;

/// Largest number of chords in one arc (a 2 m radius at 0.5 µm would need more; such an arc
/// gets a slightly larger sagitta, which stays far below a step).
const MAX_SEGMENTS: u32 = 65_535;

/// An arc being cut, yielding chord end points in machine nanometres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct ArcCutter<const N: usize> {
    start: [Nm; N],
    end: [Nm; N],
    ax: (usize, usize),
    center_mm: (f64, f64),
    radius_mm: f64,
    angle0: f64,
    sweep: f64,
    segments: u32,
    next: u32,
}

/// How the arc's centre is given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum ArcCenter {
    /// Offsets from the start point along the two plane axes, nm (`I`/`J`/`K`).
    Offset(Nm, Nm),
    /// Radius in nm (`R`); negative for the longer way round.
    Radius(Nm),
}

fn mm(nm: Nm) -> f64 {
    nm as f64 * 1e-6
}

fn to_nm(mm: f64) -> Nm {
    libm::round(mm * 1e6) as Nm
}

/// `d × k / n` rounded toward zero, exact, for `k < n`: the distance an axis moving with the arc
/// (a helix) has gone at chord `k` of `n`. In 64-bit integers (an `i128` division costs a
/// thousand bytes of code on a 32-bit core): `d = q·n + r` gives `q·k + r·k / n`, where
/// `r·k < n²` fits for any `n` below 2³².
fn part_of(d: Nm, k: u32, n: u32) -> Nm {
    let (k, n) = (u64::from(k), u64::from(n.max(1)));
    let magnitude = d.unsigned_abs();
    let part = magnitude / n * k + magnitude % n * k / n;
    let part = part.cast_signed();
    if d < 0 { -part } else { part }
}

impl<const N: usize> ArcCutter<N> {
    /// Plan an arc from `start` to `end` (machine nm) in the plane of axes `ax`, clockwise
    /// when `cw`.
    pub(crate) fn new(
        start: [Nm; N],
        end: [Nm; N],
        ax: (usize, usize),
        center: ArcCenter,
        cw: bool,
        tolerance_mm: f64,
    ) -> Result<Self, CommandError> {
        let (a0, a1) = ax;
        let p0 = (
            mm(start.get(a0).copied().unwrap_or(0)),
            mm(start.get(a1).copied().unwrap_or(0)),
        );
        let p1 = (
            mm(end.get(a0).copied().unwrap_or(0)),
            mm(end.get(a1).copied().unwrap_or(0)),
        );
        let (off, radius) = match center {
            ArcCenter::Offset(i, j) => {
                let off = (mm(i), mm(j));
                let r = sqrt(off.0 * off.0 + off.1 * off.1);
                let c = (p0.0 + off.0, p0.1 + off.1);
                let (dx, dy) = (p1.0 - c.0, p1.1 - c.1);
                let r_end = sqrt(dx * dx + dy * dy);
                let diff = (r_end - r).abs();
                if diff > 0.005 && diff > 0.001 * r {
                    return Err(CommandError::ArcGeometry);
                }
                (off, r)
            }
            ArcCenter::Radius(r_nm) => {
                let mut r = mm(r_nm);
                let x = p1.0 - p0.0;
                let y = p1.1 - p0.1;
                let d = sqrt(x * x + y * y);
                let disc = 4.0 * r * r - x * x - y * y;
                if d == 0.0 || disc < -1e-9 {
                    return Err(CommandError::ArcGeometry);
                }
                let mut h = -sqrt(disc.max(0.0)) / d;
                if !cw {
                    h = -h;
                }
                if r < 0.0 {
                    h = -h;
                    r = -r;
                }
                ((0.5 * (x - y * h), 0.5 * (y + x * h)), r)
            }
        };
        if radius.is_nan() || radius <= 1e-6 {
            return Err(CommandError::ArcGeometry);
        }
        let c = (p0.0 + off.0, p0.1 + off.1);
        let r0 = (-off.0, -off.1);
        let rt = (p1.0 - c.0, p1.1 - c.1);
        let mut sweep = atan2(r0.0 * rt.1 - r0.1 * rt.0, r0.0 * rt.0 + r0.1 * rt.1);
        const EPS: f64 = 5e-7;
        let tau = 2.0 * core::f64::consts::PI;
        if cw {
            if sweep >= -EPS {
                sweep -= tau;
            }
        } else if sweep <= EPS {
            sweep += tau;
        }
        // The chord's half angle θ has cos θ = 1 − t and sin θ = √(t·(2 − t)), t = tol / r.
        let t = tolerance_mm.min(radius) / radius;
        let max_angle = 2.0 * atan2(sqrt(t * (2.0 - t)), 1.0 - t);
        let segments = ceil(sweep.abs() / max_angle).clamp(1.0, f64::from(MAX_SEGMENTS)) as u32;
        Ok(Self {
            start,
            end,
            ax,
            center_mm: c,
            radius_mm: radius,
            angle0: atan2(r0.1, r0.0),
            sweep,
            segments,
            next: 1,
        })
    }

    /// The arc's length, mm: along the circle, and along the other axes that move with it (a
    /// helix).
    pub(crate) fn length_mm(&self) -> f64 {
        let along = self.radius_mm * self.sweep.abs();
        let mut sum = along * along;
        for i in 0..N {
            if i != self.ax.0 && i != self.ax.1 {
                let (s, e) = (
                    self.start.get(i).copied().unwrap_or(0),
                    self.end.get(i).copied().unwrap_or(0),
                );
                let d = mm(e.saturating_sub(s));
                sum += d * d;
            }
        }
        sqrt(sum)
    }

    /// Chords still to come.
    #[cfg(test)]
    pub(crate) fn remaining(&self) -> u32 {
        self.segments + 1 - self.next
    }

    /// Whether the next chord is the first.
    pub(crate) fn is_first(&self) -> bool {
        self.next == 1
    }

    /// The end of chord `k` (1-based) without advancing.
    fn point(&self, k: u32) -> [Nm; N] {
        if k >= self.segments {
            return self.end;
        }
        let f = f64::from(k) / f64::from(self.segments);
        let (sin, cos) = sin_cos(self.angle0 + self.sweep * f);
        let mut p = [0; N];
        for (i, x) in p.iter_mut().enumerate() {
            let (s, e) = (
                self.start.get(i).copied().unwrap_or(0),
                self.end.get(i).copied().unwrap_or(0),
            );
            *x = if i == self.ax.0 {
                to_nm(self.center_mm.0 + self.radius_mm * cos)
            } else if i == self.ax.1 {
                to_nm(self.center_mm.1 + self.radius_mm * sin)
            } else {
                s + part_of(e - s, k, self.segments)
            };
        }
        p
    }

    /// The next chord's end, without advancing.
    pub(crate) fn peek(&self) -> Option<[Nm; N]> {
        (self.next <= self.segments).then(|| self.point(self.next))
    }

    /// Advance past the chord returned by [`ArcCutter::peek`].
    pub(crate) fn advance(&mut self) {
        self.next += 1;
    }

    /// The extreme positions the arc reaches on each axis: `(min, max)` in nm.
    pub(crate) fn bounds(&self) -> ([Nm; N], [Nm; N]) {
        let mut lo = [0; N];
        let mut hi = [0; N];
        for i in 0..N {
            let (s, e) = (
                self.start.get(i).copied().unwrap_or(0),
                self.end.get(i).copied().unwrap_or(0),
            );
            lo[i] = s.min(e);
            hi[i] = s.max(e);
        }
        // The circle's extreme points at 0°, 90°, 180°, 270° that the sweep crosses.
        let quarter = core::f64::consts::FRAC_PI_2;
        for k in -8i32..=8 {
            let a = f64::from(k) * quarter;
            let rel = (a - self.angle0) / self.sweep;
            if (0.0..=1.0).contains(&rel) {
                let (sin, cos) = sin_cos(a);
                let x = to_nm(self.center_mm.0 + self.radius_mm * cos);
                let y = to_nm(self.center_mm.1 + self.radius_mm * sin);
                for (axis, v) in [(self.ax.0, x), (self.ax.1, y)] {
                    if let (Some(l), Some(h)) = (lo.get_mut(axis), hi.get_mut(axis)) {
                        *l = (*l).min(v);
                        *h = (*h).max(v);
                    }
                }
            }
        }
        (lo, hi)
    }

    /// The arc's radius, mm.
    #[cfg(test)]
    pub(crate) fn radius_mm(&self) -> f64 {
        self.radius_mm
    }

    /// The arc's centre in the plane, mm.
    #[cfg(test)]
    pub(crate) fn center_mm(&self) -> (f64, f64) {
        self.center_mm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dist_to_circle(p: (f64, f64), c: (f64, f64), r: f64) -> f64 {
        (sqrt((p.0 - c.0) * (p.0 - c.0) + (p.1 - c.1) * (p.1 - c.1)) - r).abs()
    }

    #[test]
    fn quarter_circle_ends_exactly_and_keeps_the_sagitta() {
        let start = [10_000_000, 0, 0];
        let end = [0, 10_000_000, 5_000_000];
        let mut arc = ArcCutter::<3>::new(
            start,
            end,
            (0, 1),
            ArcCenter::Offset(-10_000_000, 0),
            false,
            0.002,
        )
        .expect("arc");
        let tol = 0.002;
        let mut prev = start;
        let mut last = start;
        let mut n = 0;
        while let Some(p) = arc.peek() {
            arc.advance();
            let q = (mm(p[0]), mm(p[1]));
            assert!(dist_to_circle(q, (0.0, 0.0), 10.0) < 1e-6);
            // The chord's midpoint is within the tolerance of the arc.
            let mid = ((mm(prev[0]) + q.0) / 2.0, (mm(prev[1]) + q.1) / 2.0);
            assert!(dist_to_circle(mid, (0.0, 0.0), 10.0) <= tol + 1e-6);
            prev = p;
            last = p;
            n += 1;
        }
        assert_eq!(last, end);
        assert!(n > 10);
        assert_eq!(arc.remaining(), 0);
    }

    #[test]
    fn radius_form_and_full_circle() {
        // G2 X10 Y0 R5 from the origin: a half circle centred at (5, 0), clockwise (over +Y).
        let arc = ArcCutter::<2>::new(
            [0, 0],
            [10_000_000, 0],
            (0, 1),
            ArcCenter::Radius(5_000_000),
            true,
            0.01,
        )
        .expect("arc");
        assert!((arc.radius_mm() - 5.0).abs() < 1e-9);
        assert!((arc.center_mm().0 - 5.0).abs() < 1e-9);
        let (_, hi) = arc.bounds();
        assert_eq!(hi[1], 5_000_000);
        // A full circle: start equals end.
        let arc = ArcCutter::<2>::new(
            [0, 0],
            [0, 0],
            (0, 1),
            ArcCenter::Offset(5_000_000, 0),
            true,
            0.01,
        )
        .expect("circle");
        let (lo, hi) = arc.bounds();
        assert_eq!((lo[0], hi[0]), (0, 10_000_000));
        assert_eq!((lo[1], hi[1]), (-5_000_000, 5_000_000));
    }

    #[test]
    fn chord_ends_agree_with_libms_trigonometry_to_the_nanometre() {
        let mut x = 0x1234_5678_9abc_def1u64;
        let (mut chords, mut off_by_one) = (0u32, 0u32);
        for _ in 0..2_000 {
            let mut nm =
                |span: i64| (crate::testing::xorshift(&mut x) % (2 * span as u64)) as i64 - span;
            let start = [nm(300_000_000), nm(300_000_000)];
            let (i, j) = (nm(200_000_000), nm(200_000_000));
            let cw = nm(1) < 0;
            // The end on the circle, at a random angle.
            let (r, a) = (mm(i).hypot(mm(j)), mm(nm(3_141_592)));
            let c = (mm(start[0]) + mm(i), mm(start[1]) + mm(j));
            let end = [to_nm(c.0 + r * libm::cos(a)), to_nm(c.1 + r * libm::sin(a))];
            let Ok(mut arc) =
                ArcCutter::<2>::new(start, end, (0, 1), ArcCenter::Offset(i, j), cw, 0.002)
            else {
                continue;
            };
            let sweep = libm::atan2(
                mm(-i) * (mm(end[1]) - c.1) - mm(-j) * (mm(end[0]) - c.0),
                mm(-i) * (mm(end[0]) - c.0) + mm(-j) * (mm(end[1]) - c.1),
            );
            let segments = arc.remaining();
            let max_angle = 2.0 * libm::acos(1.0 - 0.002f64.min(arc.radius_mm()) / arc.radius_mm());
            let expected = libm::ceil(arc.sweep.abs() / max_angle).max(1.0) as u32;
            assert!(
                segments.abs_diff(expected) <= 1,
                "{segments} chords, libm {expected}"
            );
            // The cutter's sweep is libm's angle between start and end, give or take a turn.
            let turns = (arc.sweep - sweep) / core::f64::consts::TAU;
            assert!(
                (turns - libm::round(turns)).abs() < 1e-12,
                "sweep {} against {sweep}",
                arc.sweep
            );
            let angle0 = libm::atan2(mm(-j), mm(-i));
            assert!((arc.angle0 - angle0).abs() < 1e-15);
            let mut k = 0;
            while let Some(p) = arc.peek() {
                arc.advance();
                k += 1;
                if k == segments {
                    assert_eq!(p, end);
                    break;
                }
                let angle = angle0 + arc.sweep * f64::from(k) / f64::from(segments);
                let q = [
                    to_nm(c.0 + arc.radius_mm() * libm::cos(angle)),
                    to_nm(c.1 + arc.radius_mm() * libm::sin(angle)),
                ];
                for (got, want) in p.iter().zip(q) {
                    assert!(
                        got.abs_diff(want) <= 1,
                        "chord end {got} nm, libm {want} nm"
                    );
                    off_by_one += u32::from(*got != want);
                }
                chords += 1;
            }
        }
        // Rounding to the nanometre rarely meets a last-place difference.
        assert!(
            chords > 100_000 && off_by_one * 1000 < chords,
            "{off_by_one} of {chords}"
        );
    }

    #[test]
    fn a_helix_axis_moves_by_the_exact_fraction_of_its_distance() {
        let mut x = 0x0bad_cafe_f00d_1234u64;
        for _ in 0..100_000 {
            let r = crate::testing::xorshift(&mut x);
            let d = (r >> 1).cast_signed() >> (r % 48);
            let d = if r & 1 == 0 { d } else { -d };
            let n = (crate::testing::xorshift(&mut x) % u64::from(MAX_SEGMENTS)) as u32 + 1;
            let k = (crate::testing::xorshift(&mut x) % u64::from(n)) as u32;
            let exact = i128::from(d) * i128::from(k) / i128::from(n);
            assert_eq!(i128::from(part_of(d, k, n)), exact, "{d} × {k} / {n}");
        }
        for d in [i64::MAX, i64::MIN, i64::MIN + 1] {
            let exact = i128::from(d) * 65_534 / 65_535;
            assert_eq!(i128::from(part_of(d, 65_534, 65_535)), exact);
        }
    }

    #[test]
    fn end_off_the_circle_is_refused() {
        assert_eq!(
            ArcCutter::<2>::new(
                [0, 0],
                [20_000_000, 0],
                (0, 1),
                ArcCenter::Offset(5_000_000, 0),
                true,
                0.01
            ),
            Err(CommandError::ArcGeometry)
        );
        assert_eq!(
            ArcCutter::<2>::new(
                [0, 0],
                [20_000_000, 0],
                (0, 1),
                ArcCenter::Radius(5_000_000),
                true,
                0.01
            ),
            Err(CommandError::ArcGeometry)
        );
    }
}
