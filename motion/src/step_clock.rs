//! Step clocks: the tick of each step of one axis through one phase of a velocity profile,
//! from integer recurrences (thread side).
//!
//! In a phase of constant speed `v`, the steps of an axis are equally spaced in time: the
//! clock adds a 32.32 fixed-point interval per step. In a phase of constant acceleration `a`
//! from speed `v₀`, the point `x` along the path is reached at `t = (√(v₀² + 2ax) − v₀)/a`
//! (speeding up) or `(v₀ − √(v₀² − 2ax))/a` (slowing down). With `F` ticks per second, that
//! is `F·t = c ± √Y` with `Y = (F·v₀/a)² ± (2F²/a)·x`, and `Y` changes by the same amount at
//! every step of an axis. The clock keeps `W = Y·4^k` as an integer and `R = ⌊√W⌋`, the
//! square root in units of `2^−k` tick: the next `R` is predicted as the last one plus the
//! last increment, then corrected unit by unit against `W` (one 32×32 multiplication each); a
//! prediction off by more than [`MAX_NUDGES`] units (the first steps from rest, where the
//! intervals shrink fastest) takes one Newton step first (a 32-bit division), and a full
//! square root ([`isqrt`]: single precision's estimate and a Newton step in integers) only
//! when that is out of reach. [`StepClock::walk`] runs a clock through many
//! steps at once, for the loop that takes one axis's steps in a row.
//!
//! Accuracy: with `k` = [`RAMP_BITS`] = 4, `R` is within one unit (1/16 tick) below `√W`, the
//! offset `c` is rounded to half a unit, and the per-step change of `W` to half a unit of `W`
//! (which moves `R` by `m/(4R)` units after `m` steps); the cruise's interval is exact to
//! 2^−33 tick per step. A step's tick, its time rounded to the nearest tick, is thus within
//! 0.6 tick of the exact time. A phase whose times do not fit the fixed-point ranges (a ramp
//! longer than about 2^27 ticks, 16 s at 8 MHz; a cruise longer than 2^32 ticks) gets no
//! clock: its caller times its steps in double precision.

use libm::round;

use crate::bound::at_most;
use crate::whole::{floor_and_fraction, round_up_half, round_up_half_scaled};

/// Fraction bits of a ramp's times: `R` counts sixteenths of a tick.
const RAMP_BITS: u32 = 4;
/// `2^RAMP_BITS`.
const RAMP_UNIT: f64 = (1u32 << RAMP_BITS) as f64;
/// Corrections by one unit tried before a full square root.
const MAX_NUDGES: u32 = 2;
/// Fraction bits of a cruise's times (32.32 fixed point).
const CRUISE_BITS: u32 = 32;
/// `2^CRUISE_BITS`.
const CRUISE_UNIT: f64 = 4_294_967_296.0;

/// The steps of one axis through one phase. See the [module documentation](self).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum StepClock {
    /// Constant speed.
    Cruise {
        /// The tick the times count from.
        base: u64,
        /// The current step's time plus half a tick, ticks since `base`, 32.32 fixed point.
        time: u64,
        /// Ticks per step, 32.32 fixed point.
        interval: u64,
    },
    /// Constant acceleration.
    Ramp {
        /// The tick the times count from.
        base: u64,
        /// `Y·4^k` at the current step.
        w: u64,
        /// Its change per step.
        dw: u64,
        /// `⌊√w⌋`.
        r: u32,
        /// The last change of `r`.
        d: u32,
        /// `(c + ½)·2^k`, modulo 2^32: the step's tick is `base + (off ± r) >> k`.
        off: u32,
        /// Speeding up (`+√Y`, `W` growing) or slowing down.
        up: bool,
    },
}

impl StepClock {
    /// A clock for `steps` steps at constant speed: the first one at `first` ticks after
    /// `base` (exact, `≥ −½`), the others `interval` ticks apart. `None` beyond its range.
    #[cfg(test)]
    pub(crate) fn cruise(base: u64, first: f64, interval: f64, steps: u32) -> Option<Self> {
        let start = first + 0.5;
        if start.is_sign_negative() {
            return None;
        }
        Self::cruise_at(
            base,
            round_up_half_scaled(start, CRUISE_BITS),
            interval,
            steps,
        )
    }

    /// ½ tick in the cruise's fixed point: each step's time is rounded with it.
    const HALF: u64 = 1 << (CRUISE_BITS - 1);

    /// Where a phase that starts at `start` ticks counts its cruises from: the whole tick
    /// (`base`) and the fraction past it, in the cruise's fixed point ([`StepClock::cruise_from`]).
    #[inline]
    pub(crate) fn phase_start(start: f64) -> (u64, u64) {
        floor_and_fraction(start, CRUISE_BITS)
    }

    /// A clock for `steps` steps at constant speed: the first one `first` ticks (`≥ 0`) after
    /// the phase's start, which is `start` (a fraction of a tick in fixed point,
    /// [`StepClock::phase_start`]) after `base`; the others `interval` ticks apart. The start
    /// is shared by the phase's axes, the fraction and the ½ of rounding added here in
    /// integers. `None` beyond its range.
    #[inline]
    pub(crate) fn cruise_from(
        base: u64,
        start: u64,
        first: f64,
        interval: f64,
        steps: u32,
    ) -> Option<Self> {
        if first.is_sign_negative() {
            return None;
        }
        let time = round_up_half_scaled(first, CRUISE_BITS)
            .checked_add(start)?
            .checked_add(Self::HALF)?;
        Self::cruise_at(base, time, interval, steps)
    }

    /// A cruise whose first step's time, plus ½, is `time` after `base` in its fixed point,
    /// the others `interval` ticks apart. `None` beyond its range.
    #[inline(always)]
    fn cruise_at(base: u64, time: u64, interval: f64, steps: u32) -> Option<Self> {
        // The range is checked in the clock's own integers: the interval not negative, the
        // last step's `time` below `2^32 − ½` ticks (its tick below `base + 2^32 − 1`).
        if interval.is_sign_negative() {
            return None;
        }
        let interval = round_up_half_scaled(interval, CRUISE_BITS);
        let last = interval
            .checked_mul(u64::from(steps.saturating_sub(1)))?
            .checked_add(time)?;
        if last >= u64::MAX - (1 << (CRUISE_BITS - 1)) {
            return None;
        }
        Some(Self::Cruise {
            base,
            time,
            interval,
        })
    }

    /// A clock for `steps` steps at constant acceleration: step `m` (from 0) is at
    /// `base + c ± √(y + m·dy)` ticks (`+`, `y` growing, when `up`; else `−`, `y` shrinking),
    /// with `y ≥ 0` and `dy ≥ 0` in ticks². `None` beyond its range.
    pub(crate) fn ramp(base: u64, c: f64, y: f64, dy: f64, up: bool, steps: u32) -> Option<Self> {
        // The largest `√Y` (the last step speeding up, the first slowing down) and the largest
        // time since `base` must fit `r`'s 31 bits and the ticks' 32, in units: compared
        // squared, with no square root.
        let y_max = if up {
            y + dy * f64::from(steps.saturating_sub(1))
        } else {
            y
        };
        let tau_limit = if up {
            at_most(
                2_147_483_648.0 / RAMP_UNIT,
                CRUISE_UNIT / RAMP_UNIT - 2.0 - c,
            )
        } else {
            2_147_483_648.0 / RAMP_UNIT
        };
        let fits = y >= 0.0
            && dy >= 0.0
            && tau_limit > 0.0
            && y_max < tau_limit * tau_limit
            && (c + 2.0) * RAMP_UNIT < CRUISE_UNIT
            && (c + 0.5) * RAMP_UNIT > -CRUISE_UNIT;
        if !fits {
            return None;
        }
        let scale = RAMP_UNIT * RAMP_UNIT;
        let w = round_up_half(y * scale);
        let dw = round_up_half(dy * scale);
        let r = isqrt(w);
        // The first increment, `√(w ± dw) − √w ≈ dw / 2√w`: a guess the first step corrects.
        let d = at_most(
            dy * scale / (2.0 * f64::from(r) + 1.0),
            f64::from(u32::MAX >> 1),
        ) as u32;
        // Wrapping: `off ± r` is a time since `base` in [0, 2^32) units, whatever `off`'s sign.
        let off = round((c + 0.5) * RAMP_UNIT) as i64 as u32;
        Some(Self::Ramp {
            base,
            w,
            dw,
            r,
            d,
            off,
            up,
        })
    }

    /// The current step's tick.
    #[inline]
    pub(crate) fn tick(&self) -> u64 {
        match *self {
            Self::Cruise { base, time, .. } => base + (time >> 32),
            Self::Ramp {
                base, r, off, up, ..
            } => {
                let units = if up {
                    off.wrapping_add(r)
                } else {
                    off.wrapping_sub(r)
                };
                base + u64::from(units >> RAMP_BITS)
            }
        }
    }

    /// Move to the next step; returns its tick, and whether it took a full square root (the
    /// first steps of a ramp from rest: about a hundred instructions instead of a few dozen).
    #[inline]
    pub(crate) fn advance(&mut self) -> (u64, bool) {
        let mut rooted = false;
        match self {
            Self::Cruise { time, interval, .. } => *time = time.wrapping_add(*interval),
            Self::Ramp {
                w, dw, r, d, up, ..
            } => {
                let (w_next, guess) = if *up {
                    (w.wrapping_add(*dw), r.wrapping_add(*d))
                } else {
                    (w.saturating_sub(*dw), r.saturating_sub(*d))
                };
                let next;
                (next, rooted) = nudge(guess, w_next);
                *d = next.abs_diff(*r);
                *r = next;
                *w = w_next;
            }
        }
        (self.tick(), rooted)
    }
}

/// A cruise's steps in 32-bit ticks ([`StepClock::near`]): the fraction of a tick its
/// current step is at, and its interval in whole ticks and a fraction (32.32, as the clock's).
#[derive(Debug, Clone, Copy)]
pub(crate) struct CruiseGaps {
    frac: u32,
    whole: u32,
    part: u32,
}

impl CruiseGaps {
    /// No steps: for an axis that has none left.
    pub(crate) const NONE: Self = Self {
        frac: 0,
        whole: 0,
        part: 0,
    };

    /// The tick of the step after the one at `tick`; the gaps move on to it.
    #[inline(always)]
    pub(crate) fn after(&mut self, tick: u32) -> u32 {
        let (frac, carry) = self.frac.overflowing_add(self.part);
        self.frac = frac;
        tick.wrapping_add(self.whole).wrapping_add(u32::from(carry))
    }

    /// The fewest whole ticks from one step to the next, at least one.
    #[cfg(any(test, target_arch = "arm"))]
    #[inline(always)]
    pub(crate) fn shortest(&self) -> u32 {
        self.whole.max(1)
    }

    /// The tick of the step before the one at `tick`, which [`CruiseGaps::after`] moved on
    /// to (its fraction is the gaps' now, past a carry when it is below the interval's).
    #[cfg(any(test, target_arch = "arm"))]
    #[inline(always)]
    pub(crate) fn before(&self, tick: u32) -> u32 {
        let carry = self.frac < self.part;
        tick.wrapping_sub(self.whole).wrapping_sub(u32::from(carry))
    }

    /// The step at `tick` and the interval, each as one 32.32 number of ticks: the interval
    /// added to the step gives the next, as [`CruiseGaps::after`] does.
    #[cfg(any(test, not(target_arch = "arm")))]
    #[inline(always)]
    pub(crate) const fn fixed_from(self, tick: u32) -> (u64, u64) {
        (
            (tick as u64) << 32 | self.frac as u64,
            (self.whole as u64) << 32 | self.part as u64,
        )
    }
}

impl StepClock {
    /// A cruise's fewest and most ticks from one step to the next (its interval rounded down
    /// and up); `None` for a ramp.
    pub(crate) fn cruise_gaps(&self) -> Option<(u64, u64)> {
        let (_, _, interval) = self.cruise_state()?;
        Some((interval >> 32, (interval >> 32) + 1))
    }

    /// The span a walk in 32-bit ticks from `origin` ([`StepClock::near`]) may cover up to
    /// `horizon`: to it, or to half the 32-bit range, where a step's tick plus one interval
    /// still fits.
    #[inline(always)]
    pub(crate) fn span(origin: u64, horizon: u64) -> u32 {
        horizon.saturating_sub(origin).min(1 << 31) as u32
    }

    /// This cruise from its current step on, in 32-bit ticks from `origin`: that step's
    /// tick (at most `span`: a step at or past it stands at `span`), and the gaps that lead
    /// from each step to the next. `None` for a ramp.
    ///
    /// The walks of steady cruises ([`crate::prep`]) merge and write steps in these ticks,
    /// and then move the clock on with [`StepClock::skip`]: a step costs a 32-bit addition
    /// with carry, where the clock's own time is 64-bit.
    #[inline(always)]
    pub(crate) fn near(&self, origin: u64, span: u32) -> Option<(u32, CruiseGaps)> {
        let (base, time, interval) = self.cruise_state()?;
        let tick = (base + (time >> 32)).saturating_sub(origin);
        let gaps = CruiseGaps {
            frac: time as u32,
            whole: (interval >> 32) as u32,
            part: interval as u32,
        };
        Some((tick.min(u64::from(span)) as u32, gaps))
    }

    /// The tick of the step `steps` after the current one, on a cruise; `None` for a ramp or
    /// past the 64-bit range. [`CruiseGaps::after`] reaches the same tick `steps` times on.
    #[inline(always)]
    pub(crate) fn tick_ahead(&self, steps: u32) -> Option<u64> {
        let (base, time, interval) = self.cruise_state()?;
        let time = u64::from(steps).checked_mul(interval)?.checked_add(time)?;
        base.checked_add(time >> 32)
    }

    /// A cruise's base tick, time and interval (32.32); `None` for a ramp.
    #[inline(always)]
    fn cruise_state(&self) -> Option<(u64, u64, u64)> {
        match *self {
            Self::Cruise {
                base,
                time,
                interval,
            } => Some((base, time, interval)),
            Self::Ramp { .. } => None,
        }
    }

    /// A cruise moved on by `steps` (at least one) of its steps: returns the tick of the last
    /// of them. A ramp stays (its steps are never skipped).
    #[inline(always)]
    pub(crate) fn skip(&mut self, steps: u32) -> u64 {
        match self {
            Self::Cruise {
                base,
                time,
                interval,
            } => {
                let last = time.wrapping_add(u64::from(steps.saturating_sub(1)) * *interval);
                *time = last.wrapping_add(*interval);
                *base + (last >> 32)
            }
            Self::Ramp { .. } => self.tick(),
        }
    }

    /// Walk the steps from the current one while `take` accepts their ticks, at most
    /// `max_steps` of them and until their work reaches `max_work` (a step counts 1, one
    /// timed by a full square root `1 + root_work`). The clock stays at the first step not
    /// taken. Returns the steps taken and their work.
    ///
    /// The loop of a run of one axis's steps: the clock's kind is matched once and its state
    /// kept in registers, where [`StepClock::advance`] matches it at every step.
    #[inline(always)]
    pub(crate) fn walk(
        &mut self,
        max_steps: u32,
        max_work: u32,
        root_work: u32,
        mut take: impl FnMut(u64) -> bool,
    ) -> (u32, u32) {
        let mut steps = 0;
        let mut work = 0;
        match self {
            Self::Cruise {
                base,
                time,
                interval,
            } => {
                let (base, interval) = (*base, *interval);
                let mut t = *time;
                while steps < max_steps && work < max_work && take(base + (t >> 32)) {
                    t = t.wrapping_add(interval);
                    steps += 1;
                    work += 1;
                }
                *time = t;
            }
            Self::Ramp {
                base,
                w,
                dw,
                r,
                d,
                off,
                up,
            } => {
                let (base, dw, off, up) = (*base, *dw, *off, *up);
                let (mut w_now, mut r_now, mut d_now) = (*w, *r, *d);
                while steps < max_steps && work < max_work {
                    let units = if up {
                        off.wrapping_add(r_now)
                    } else {
                        off.wrapping_sub(r_now)
                    };
                    if !take(base + u64::from(units >> RAMP_BITS)) {
                        break;
                    }
                    let (w_next, guess) = if up {
                        (w_now.wrapping_add(dw), r_now.wrapping_add(d_now))
                    } else {
                        (w_now.saturating_sub(dw), r_now.saturating_sub(d_now))
                    };
                    let (next, rooted) = nudge(guess, w_next);
                    work += if rooted { 1 + root_work } else { 1 };
                    d_now = next.abs_diff(r_now);
                    r_now = next;
                    w_now = w_next;
                    steps += 1;
                }
                (*w, *r, *d) = (w_now, r_now, d_now);
            }
        }
        (steps, work)
    }
}

/// `⌊√w⌋` from a guess: corrected by single units, after one Newton step when the guess is
/// off by more than [`MAX_NUDGES`] units (a 32-bit division), or computed anew when even
/// that is out of reach.
/// Returns the root, and whether it took a full square root.
#[inline(always)]
fn nudge(guess: u32, w: u64) -> (u32, bool) {
    let mut r = guess;
    let mut sq = u64::from(r) * u64::from(r);
    // Off by more than the unit corrections reach: one Newton step, r + (w − r²)/2r, when the
    // error fits 32 bits (all but the first steps from rest).
    let reach = u64::from(MAX_NUDGES) * (2 * u64::from(r) + u64::from(MAX_NUDGES));
    if sq.abs_diff(w) > reach && r > 0 {
        let error = w as i64 - sq as i64;
        let (Ok(error), Ok(twice)) = (i32::try_from(error), i32::try_from(2 * u64::from(r))) else {
            return (isqrt(w), true);
        };
        let step = error / twice;
        r = r.wrapping_add_signed(step);
        sq = u64::from(r) * u64::from(r);
    }
    for _ in 0..MAX_NUDGES {
        if sq > w {
            // (r − 1)² = r² − 2r + 1
            sq -= 2 * u64::from(r) - 1;
            r -= 1;
        } else if sq + 2 * u64::from(r) < w {
            // (r + 1)² = r² + 2r + 1 ≤ w
            sq += 2 * u64::from(r) + 1;
            r += 1;
        } else {
            return (r, false);
        }
    }
    if sq <= w && w - sq <= 2 * u64::from(r) {
        (r, false)
    } else {
        (isqrt(w), true)
    }
}

/// The largest root of a `w` below 2^62.
const MAX_ROOT: u32 = (1 << 31) - 1;

/// `⌊√w⌋` for `w < 2^62`, in a few dozen instructions where a square root in double
/// precision takes hundreds on the cores without a double-precision FPU (the M4, the
/// ESP32-C3): [`root_estimate`], then the last unit in integers.
#[cold]
#[inline(never)]
fn isqrt(w: u64) -> u32 {
    let mut r = root_estimate(w);
    while u64::from(r) * u64::from(r) > w {
        r -= 1;
    }
    while u64::from(r + 1) * u64::from(r + 1) <= w {
        r += 1;
    }
    r
}

/// `√w` within a unit, for `w < 2^62`: single precision's root of `w` in single precision
/// ([`crate::fpu::approx_f32`], within 2⁻²²), so within 2⁻²² of `√w` and at most 2⁹ units
/// off, then one Newton step `r + (w − r²)/2r` in a 32-bit division, the error and the divisor
/// shifted alike to fit it (the divisor keeps at least 23 bits).
/// The estimate is at most one unit from `⌊√w⌋`.
#[inline(always)]
fn root_estimate(w: u64) -> u32 {
    root_estimate_from(w, crate::fpu::approx_f32(w))
}

/// [`root_estimate`] of `w`, given `w` in single precision (`w_f32`, within 2⁻²² of it).
#[inline(always)]
fn root_estimate_from(w: u64, w_f32: f32) -> u32 {
    let r = (crate::fpu::sqrtf(w_f32) as u32).min(MAX_ROOT);
    let sq = u64::from(r) * u64::from(r);
    let error = w.abs_diff(sq);
    let twice = 2 * u64::from(r);
    if error <= u64::from(r) {
        return r;
    }
    let bits = |x: u64| 64 - x.leading_zeros();
    let shift = bits(error).max(bits(twice)).saturating_sub(32);
    let divisor = (twice >> shift) as u32;
    if divisor == 0 {
        return r;
    }
    let error = (error >> shift) as u32;
    // Newton's step lands at or just above `√w`: rounded down going up, up going down.
    if w > sq {
        r.saturating_add(error / divisor).min(MAX_ROOT)
    } else {
        r - error.div_ceil(divisor).min(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every tick of `clock` over `steps` steps against the exact times `exact(m)`: within
    /// 0.6 tick.
    fn check(mut clock: StepClock, steps: u32, exact: impl Fn(u32) -> f64) {
        for m in 0..steps {
            let tick = if m == 0 {
                clock.tick()
            } else {
                clock.advance().0
            };
            let t = exact(m);
            assert!(
                (tick as f64 - t).abs() <= 0.6,
                "step {m}: tick {tick}, exact {t}"
            );
        }
    }

    /// Square roots over every bit length, at and around the perfect squares: exact, and the
    /// estimate before the last correction within a unit.
    #[test]
    fn isqrt_is_exact_and_its_estimate_within_a_unit() {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut random = move || crate::testing::xorshift(&mut seed);
        for _ in 0..200_000 {
            let bits = random() % 63;
            let w = random() >> (64 - bits).min(63);
            let k = u64::from(isqrt(w));
            let r = random() as u32 & MAX_ROOT;
            let near_square = u64::from(r) * u64::from(r);
            for w in [
                w,
                near_square.saturating_sub(1),
                near_square,
                near_square + 2 * u64::from(r),
            ] {
                let k = u64::from(isqrt(w));
                assert!(k * k <= w && (k + 1) * (k + 1) > w, "{w}");
                let estimate = u64::from(root_estimate(w));
                assert!(estimate.abs_diff(k) <= 1, "{w}: {estimate} for {k}");
                // As on hard-float Arm, from the conversion by halves.
                let estimate = u64::from(root_estimate_from(w, crate::fpu::split_f32(w)));
                assert!(
                    estimate.abs_diff(k) <= 1,
                    "{w}: {estimate} for {k} (by halves)"
                );
            }
            assert!(k < 1 << 31);
        }
    }

    #[test]
    fn isqrt_is_exact() {
        for w in [0u64, 1, 2, 3, 4, 15, 16, 17, (1 << 62) - 1, 999_999_999_999] {
            let r = u64::from(isqrt(w));
            assert!(r * r <= w && (r + 1) * (r + 1) > w, "{w}");
        }
        assert_eq!(nudge(10, 99), (9, false));
        assert_eq!(nudge(1, 99).0, 9);
        assert_eq!(nudge(9, 100), (10, false));
        // Far off: a Newton step, then units.
        assert_eq!(nudge(1990, 4_000_000), (2000, false));
        assert_eq!(nudge(2010, 4_000_000), (2000, false));
        assert_eq!(nudge(1000, 4_000_000), (2000, true));
    }

    #[test]
    fn a_cruise_seen_near_steps_as_its_clock_and_skips_to_the_same_step() {
        let start = StepClock::cruise(5_000_000_000, 3.7, 61.803_398_87, 100_000);
        let start = start.expect("in range");
        let origin = start.tick() - 17;
        let (mut near, mut gaps) = start.near(origin, 1 << 31).expect("a cruise");
        let mut clock = start;
        for steps in 1..=50_000u32 {
            assert_eq!(origin + u64::from(near), clock.tick(), "step {steps}");
            near = gaps.after(near);
            clock.advance();
            if steps % 9_973 == 0 {
                assert_eq!(start.tick_ahead(steps), Some(origin + u64::from(near)));
                let mut skipped = start;
                let last = skipped.skip(steps);
                assert_eq!(skipped, clock, "skip {steps}");
                assert_eq!(origin + u64::from(near), skipped.tick());
                let mut previous = start;
                for _ in 1..steps {
                    previous.advance();
                }
                assert_eq!(last, previous.tick(), "the last step skipped");
            }
        }
        // A step at or past the span stands at the span; a ramp has no gaps.
        assert_eq!(start.near(origin, 10).map(|(t, _)| t), Some(10));
        let ramp = StepClock::ramp(0, 0.0, 100.0, 10.0, true, 10).expect("in range");
        assert!(ramp.near(0, 1 << 31).is_none());
        assert_eq!(ramp.tick_ahead(1), None);
        assert_eq!(start.tick_ahead(0), Some(start.tick()));
        // Steps past the 64-bit range of the clock's 32.32 time.
        assert_eq!(start.tick_ahead(u32::MAX), None);
    }

    #[test]
    fn a_cruise_adds_its_interval() {
        let clock = StepClock::cruise(1000, 12.25, 123.456, 10_000);
        let clock = clock.expect("in range");
        check(clock, 10_000, |m| 1000.0 + 12.25 + 123.456 * f64::from(m));
        assert!(StepClock::cruise(0, 0.0, 1e6, 10_000).is_none());
        // A first step up to ½ tick before the base is in range (its tick rounds to the base).
        for first in [-0.5, -0.25] {
            let clock = StepClock::cruise(1000, first, 10.0, 5).map(|c| c.tick());
            assert_eq!(clock, Some(1000), "{first}");
        }
        assert!(StepClock::cruise(1000, -0.75, 10.0, 5).is_none());
    }

    /// Ramps from rest and between speeds, up and down, on 1 MHz and 8 MHz clocks and a
    /// range of step lengths and accelerations: every step within 0.6 tick.
    #[test]
    fn ramps_land_within_a_tick() {
        for &f in &[1e6, 8e6, 2.5e7] {
            for &(a, h) in &[
                (3000.0f64, 1.0 / 80.0),
                (200.0, 1.0 / 400.0),
                (50.0, 0.01),
                (20_000.0, 1.0 / 3200.0),
            ] {
                for &(v0, v1) in &[
                    (0.0f64, 200.0f64),
                    (13.0, 100.0),
                    (100.0, 0.0),
                    (150.0, 40.0),
                ] {
                    let up = v1 > v0;
                    let length: f64 = ((v1 * v1 - v0 * v0) / (2.0 * a)).abs();
                    let steps = (length / h) as u32;
                    if steps == 0 {
                        continue;
                    }
                    let base = 777u64;
                    let rel0 = 0.3;
                    let cc = f * v0 / a;
                    // Step m at x = h·(m + ½).
                    let x0 = 0.5 * h;
                    let k = 2.0 * f * f / a;
                    let (c, y) = if up {
                        (rel0 - cc, cc * cc + k * x0)
                    } else {
                        (rel0 + cc, cc * cc - k * x0)
                    };
                    let Some(clock) = StepClock::ramp(base, c, y, k * h, up, steps) else {
                        continue;
                    };
                    check(clock, steps, |m| {
                        let x = h * (f64::from(m) + 0.5);
                        let t = if up {
                            ((v0 * v0 + 2.0 * a * x).sqrt() - v0) / a
                        } else {
                            (v0 - (v0 * v0 - 2.0 * a * x).max(0.0).sqrt()) / a
                        };
                        base as f64 + rel0 + t * f
                    });
                }
            }
        }
    }

    #[test]
    fn a_ramp_out_of_range_has_no_clock() {
        // 100 s of ramp at 8 MHz.
        let tau = 8e8;
        assert!(StepClock::ramp(0, -tau, tau * tau, 1.0, true, 10).is_none());
    }
}
