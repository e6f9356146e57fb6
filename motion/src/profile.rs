//! Velocity profiles along one block: the trapezoid (or triangle) from an anchor point.
//!
//! Thread side only (floating point). A profile starts at an anchor — the start of a block, or
//! the point of the last prepared step when the plan changed — with a known speed, and covers
//! the rest of the block in up to three phases at constant acceleration: a ramp from the
//! anchor speed to the cruise speed (up, or down after an `F` decrease), a cruise, and a ramp
//! down to the exit speed. A feed-hold profile only decelerates, and may stop inside the block.

use libm::sqrt;

use crate::bound::{at_least, at_least_zero, at_most, is_positive, is_zero, sum};

/// Phases of a profile: [`Profile::phase`] takes `0..PHASES`.
pub(crate) const PHASES: usize = 3;

/// How the speed changes through a phase.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Shape {
    /// Speeding up at the profile's acceleration.
    Up,
    /// Constant speed.
    Cruise,
    /// Slowing down at the profile's acceleration.
    Down,
}

/// One phase of a [`Profile`]: from `start` mm past the anchor (to [`Profile::phase_end`]),
/// entered at `t_start` s at `v_start` mm/s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Phase {
    pub start: f64,
    pub t_start: f64,
    pub v_start: f64,
    pub shape: Shape,
}

/// One velocity profile. Lengths in mm, speeds in mm/s, times in s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Profile {
    v0: f64,
    a: f64,
    d1: f64,
    up1: bool,
    v1: f64,
    t1: f64,
    d2: f64,
    t2: f64,
    d3: f64,
    v3: f64,
    t3: f64,
    stops: bool,
}

impl Profile {
    /// Cover `r` mm starting at `v0`, cruising at most at `vn`, ending at `ve` (lowered to what
    /// is reachable, raised to what deceleration allows), with acceleration `a`.
    pub(crate) fn plan(r: f64, v0: f64, vn: f64, ve: f64, a: f64) -> Self {
        // Entered, cruised and left at one speed (a chain of short moves at one feed): all of
        // it a cruise, as `plan_ramps` finds, without its divisions.
        // Compared by their bits (equal bits, equal speeds), where a comparison is a call.
        if v0.to_bits() == vn.to_bits() && ve.to_bits() == vn.to_bits() {
            return Self::from_phases(v0, a, 0.0, true, vn, at_least_zero(r), 0.0, ve, false);
        }
        Self::plan_ramps(r, v0, vn, ve, a)
    }

    /// [`Profile::plan`] in general: the ramps' lengths worked out.
    fn plan_ramps(r: f64, v0: f64, vn: f64, ve: f64, a: f64) -> Self {
        let r = at_least_zero(r);
        let two_a = 2.0 * a;
        // The exit speed within what the block can reach from v0, compared squared: a square
        // root (a few hundred instructions in software) only when it is out of reach.
        let (v0_sq, ve_sq, change) = (v0 * v0, ve * ve, two_a * r);
        let ve = if ve_sq > v0_sq + change {
            sqrt(v0_sq + change)
        } else if ve_sq < v0_sq - change {
            sqrt(v0_sq - change)
        } else {
            ve
        };
        let (d1, up1, v1, d3);
        if v0 > vn {
            let vc = at_least(vn, ve);
            d1 = at_most((v0 * v0 - vc * vc) / two_a, r);
            up1 = false;
            v1 = vc;
            d3 = at_least_zero(at_most((vc * vc - ve * ve) / two_a, r - d1));
        } else {
            let full1 = (vn * vn - v0 * v0) / two_a;
            let full3 = (vn * vn - ve * ve) / two_a;
            if full1 + full3 <= r {
                d1 = full1;
                v1 = vn;
                d3 = full3;
            } else {
                let peak = sqrt(at_least_zero((two_a * r + v0 * v0 + ve * ve) * 0.5));
                let peak = at_least(at_least(peak, v0), ve);
                v1 = peak;
                d1 = ((peak * peak - v0 * v0) / two_a).clamp(0.0, r);
                d3 = at_least_zero(r - d1);
            }
            up1 = true;
        }
        let d2 = at_least_zero(r - d1 - d3);
        // The end of the last phase is the exit speed, unless a phase was cut short: compared
        // squared, within rounding, before a square root.
        let v3_sq = at_least_zero(v1 * v1 - two_a * d3);
        let v3 = if (v3_sq - ve * ve).abs() <= 1e-12 * (v1 * v1) {
            ve
        } else {
            sqrt(v3_sq)
        };
        Self::from_phases(v0, a, d1, up1, v1, d2, d3, v3, false)
    }

    /// Decelerate from `v0` at `a` over at most `r` mm: stop inside the block if possible.
    pub(crate) fn hold(r: f64, v0: f64, a: f64) -> Self {
        let r = at_least_zero(r);
        let stop_mm = v0 * v0 / (2.0 * a);
        if stop_mm < r {
            Self::from_phases(v0, a, 0.0, false, v0, 0.0, stop_mm, 0.0, true)
        } else {
            let v3 = sqrt(at_least_zero(v0 * v0 - 2.0 * a * r));
            Self::from_phases(v0, a, 0.0, false, v0, 0.0, r, v3, false)
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn from_phases(
        v0: f64,
        a: f64,
        d1: f64,
        up1: bool,
        v1: f64,
        d2: f64,
        d3: f64,
        v3: f64,
        stops: bool,
    ) -> Self {
        let t1 = if is_positive(d1) {
            2.0 * d1 / (v0 + v1)
        } else {
            0.0
        };
        let t2 = if is_positive(d2) { d2 / v1 } else { 0.0 };
        let t3 = if is_positive(d3) {
            2.0 * d3 / (v1 + v3)
        } else {
            0.0
        };
        Self {
            v0,
            a,
            d1,
            up1,
            v1,
            t1,
            d2,
            t2,
            d3,
            v3,
            t3,
            stops,
        }
    }

    /// Where phase `p` ([`Profile::phase`]) ends, mm past the anchor: apart from the phase, as
    /// its sum is needed only for a phase that does not end the profile.
    pub(crate) fn phase_end(&self, p: usize) -> f64 {
        match p {
            0 => self.d1,
            1 => self.d1 + self.d2,
            _ => self.length(),
        }
    }

    /// Phase `p` (0, 1 or 2 of [`PHASES`]): the ramp from the anchor speed, the cruise, the
    /// ramp down. A phase that does not occur is empty (its end, [`Profile::phase_end`], is
    /// its start).
    pub(crate) fn phase(&self, p: usize) -> Phase {
        match p {
            0 => Phase {
                start: 0.0,
                t_start: 0.0,
                v_start: self.v0,
                shape: if self.up1 { Shape::Up } else { Shape::Down },
            },
            1 => Phase {
                start: self.d1,
                t_start: self.t1,
                v_start: self.v1,
                shape: Shape::Cruise,
            },
            _ => Phase {
                start: self.phase_end(1),
                t_start: self.t1 + self.t2,
                v_start: self.v1,
                shape: Shape::Down,
            },
        }
    }

    /// Whether phase `p` (0 to 2) has no length: it holds no step, and finding the steps of
    /// the phases around it does not need its bounds. One integer comparison (a length is
    /// never negative).
    pub(crate) fn is_empty(&self, p: usize) -> bool {
        let length = match p {
            0 => self.d1,
            1 => self.d2,
            _ => self.d3,
        };
        is_zero(length)
    }

    /// Whether the profile is one cruise: its ramps are empty.
    pub(crate) fn is_cruise(&self) -> bool {
        self.is_empty(0) && self.is_empty(2)
    }

    /// Whether every phase after `p` is empty ([`Profile::is_empty`]): `p` ends the profile.
    pub(crate) fn ends_with(&self, p: usize) -> bool {
        (p + 1..PHASES).all(|q| self.is_empty(q))
    }

    /// Whether the profile ends at rest inside the block (a completed hold): no point past
    /// [`Profile::length`] (give or take rounding) is reached.
    pub(crate) fn stops(&self) -> bool {
        self.stops
    }

    /// Length covered, mm (less than the block's rest when a hold stops inside it).
    pub(crate) fn length(&self) -> f64 {
        self.d1 + self.d2 + self.d3
    }

    /// Time to cover the profile, s.
    pub(crate) fn duration(&self) -> f64 {
        // `t1 + t2 + t3` without the additions of the phases that take no time (a block at
        // one speed has one phase): `x + 0` is `x`.
        let mut t = self.t2;
        if !is_zero(self.t1) {
            t = sum(self.t1, t);
        }
        if !is_zero(self.t3) {
            t = sum(t, self.t3);
        }
        t
    }

    /// Speed at the end, mm/s.
    pub(crate) fn exit_speed(&self) -> f64 {
        self.v3
    }

    /// Time from the anchor to `x` mm past it, s; `None` beyond a hold's stopping point.
    pub(crate) fn time_at(&self, x: f64) -> Option<f64> {
        if x <= 0.0 {
            return Some(0.0);
        }
        let two_a = 2.0 * self.a;
        if x < self.d1 {
            let v = if self.up1 {
                sqrt(self.v0 * self.v0 + two_a * x)
            } else {
                sqrt(at_least_zero(self.v0 * self.v0 - two_a * x))
            };
            return Some(2.0 * x / (self.v0 + v));
        }
        let x = x - self.d1;
        if x < self.d2 {
            return Some(self.t1 + x / self.v1);
        }
        let x = x - self.d2;
        if x < self.d3 {
            let v = sqrt(at_least_zero(self.v1 * self.v1 - two_a * x));
            let sum = self.v1 + v;
            if sum <= 0.0 {
                return None;
            }
            return Some(self.t1 + self.t2 + 2.0 * x / sum);
        }
        // At or past the end: within rounding of the end point, it is the end.
        if self.stops && x > self.d3 * (1.0 + 1e-9) + 1e-12 {
            return None;
        }
        Some(self.duration())
    }

    /// Speed `x` mm past the anchor, mm/s.
    pub(crate) fn speed_at(&self, x: f64) -> f64 {
        let two_a = 2.0 * self.a;
        if x <= 0.0 {
            return self.v0;
        }
        if x < self.d1 {
            return if self.up1 {
                sqrt(self.v0 * self.v0 + two_a * x)
            } else {
                sqrt(at_least_zero(self.v0 * self.v0 - two_a * x))
            };
        }
        let x = x - self.d1;
        if x < self.d2 {
            return self.v1;
        }
        let x = at_most(x - self.d2, self.d3);
        sqrt(at_least_zero(self.v1 * self.v1 - two_a * x))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-9 * (1.0 + a.abs().max(b.abs()))
    }

    #[test]
    fn a_block_at_one_speed_is_planned_as_in_general() {
        let mut seed = 0x0123_4567_89ab_cdef_u64;
        for _ in 0..10_000 {
            let mut draw =
                |scale: f64| (crate::testing::xorshift(&mut seed) % 1_000_000) as f64 / 1e6 * scale;
            let (r, v, a) = (draw(20.0) - 1.0, draw(400.0), 1.0 + draw(20_000.0));
            assert_eq!(
                Profile::plan(r, v, v, v, a),
                Profile::plan_ramps(r, v, v, v, a)
            );
        }
        assert_eq!(
            Profile::plan(0.0, 0.0, 0.0, 0.0, 1.0),
            Profile::plan_ramps(0.0, 0.0, 0.0, 0.0, 1.0)
        );
    }

    #[test]
    fn trapezoid_from_rest_to_rest() {
        // 100 mm, cruise 50 mm/s, a = 500: ramps of 2.5 mm and 0.1 s each.
        let p = Profile::plan(100.0, 0.0, 50.0, 0.0, 500.0);
        assert!(close(p.length(), 100.0));
        assert!(close(p.duration(), 0.1 + 95.0 / 50.0 + 0.1));
        assert!(close(p.time_at(2.5).unwrap_or(0.0), 0.1));
        assert!(close(p.speed_at(50.0), 50.0));
        assert!(close(p.exit_speed(), 0.0));
    }

    #[test]
    fn triangle_when_too_short() {
        let p = Profile::plan(1.0, 0.0, 100.0, 0.0, 500.0);
        // Peak speed sqrt(a * r) = sqrt(500).
        assert!(close(p.speed_at(0.5), sqrt(500.0)));
        assert!(close(p.duration(), 2.0 * sqrt(500.0) / 500.0));
    }

    #[test]
    fn decelerates_to_a_lower_feed_inside_the_block() {
        let p = Profile::plan(10.0, 50.0, 25.0, 25.0, 500.0);
        assert!(close(p.speed_at(10.0), 25.0));
        assert!(close(p.speed_at(0.0), 50.0));
        assert!(p.speed_at(1.875) <= 25.0 + 1e-9);
    }

    #[test]
    fn unreachable_exit_is_lowered() {
        let p = Profile::plan(1.0, 0.0, 100.0, 100.0, 500.0);
        assert!(close(p.exit_speed(), sqrt(1000.0)));
    }

    #[test]
    fn hold_stops_inside_or_carries_on() {
        let p = Profile::hold(10.0, 50.0, 500.0);
        assert!(p.stops());
        assert!(close(p.length(), 2.5));
        assert_eq!(p.time_at(3.0), None);
        assert!(close(p.time_at(2.5).unwrap_or(0.0), 0.1));
        let p = Profile::hold(1.0, 50.0, 500.0);
        assert!(!p.stops());
        assert!(close(p.exit_speed(), sqrt(2500.0 - 1000.0)));
    }
}
