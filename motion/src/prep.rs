//! Segment preparation: planned blocks → timed step events (thread side).
//!
//! For every axis of a block, step `j` (1-based, of `n` steps) sits at path position
//! `L·(j − ½)/n`, the point where the axis's ideal position crosses the half-step; its time is
//! that point's time on the block's velocity profile, rounded to the nearest tick. Every axis
//! thus steps at its own exact time (no Bresenham grid, no jitter beyond one tick), and every
//! block emits exactly its integer step count, so positions never drift.
//!
//! The profile is planned in double precision once per block (and again from the last
//! prepared step when the plan changes: a new exit speed, a feed hold, an override). Each
//! axis then walks its steps through the profile's phases with a [`StepClock`]: integer
//! recurrences that give each step's tick within 0.6 tick of its exact time for a few
//! additions and a multiplication, set up in double precision once per phase. A phase out of
//! the clocks' range is timed step by step in double precision.
//!
//! The per-axis step times are merged into one time-ordered stream of rising edges for the
//! interrupt, which ends each pulse itself. Most steps take the fast path ([`Current::burst`]):
//! a step that needs no adjustment (no direction change, no edge sharing the tick of an event
//! written before the run, no phase change) is written with one set of checks; the others take
//! the general path. The queue is topped up to `queue_lead_ms` of motion (or until it is
//! full), then left to run down to half of it before the next top-up, so that a top-up
//! prepares many steps for the set-up of one call. A direction change is written after the axis's
//! last pulse has ended and at least `dir_setup` before its next rising edge; the step is
//! delayed when there is not room (only ever at a junction where the axis reverses). Two
//! rising edges of one axis are always a high and a low pulse width apart.

use core::sync::atomic::Ordering;

use forja_hal_abstraction::time::Instant;

use crate::bound::{at_least, at_least_zero, difference, half, is_zero, product};
use crate::planner::{Block, BlockKind, Planner};
use crate::profile::{PHASES, Profile, Shape};
use crate::queue::{Event, MAX_DELTA, Producer};
use crate::step_clock::{CruiseGaps, StepClock};
use crate::whole::{ceil_u64, floor_u64};

/// Free slots kept for the events one step can need (the previous edge, a direction change,
/// the splits of a long wait).
const SLOTS_PER_STEP: usize = 4;

/// No axis.
const NO_AXIS: u8 = u8::MAX;

/// The work one [`Prep::fill`] call may do, in units of one step event, so that no call takes
/// long (the link, the heaters and the reports wait behind it): a call stops at this many and
/// says there is more ([`Fill::More`]).
const WORK_PER_FILL: u32 = 64;
/// What planning a profile (a block's start, a re-plan) counts, in steps.
const PROFILE_WORK: u32 = 24;
/// What loading a block at one speed counts, in steps: its profile is one cruise, planned
/// without its ramps' square roots (about 1,500 instructions on the Cortex-M4 with the load).
const CRUISE_PROFILE_WORK: u32 = 8;
/// What setting up an axis's step clock for a phase counts, in steps.
const PHASE_WORK: u32 = 24;
/// What setting up an axis's step clock for a cruise counts, in steps: a few products and
/// sums, without a ramp's square root or a bound of its phase (about 700 instructions on the
/// Cortex-M4, the work of four steps on the general path).
const CRUISE_PHASE_WORK: u32 = 8;
/// What a step timed by a full square root (or in double precision) counts, in steps.
const ROOT_WORK: u32 = 3;
/// Steps of the cruising axes' merged walk ([`Current::run_cruises`]) that count as one: such
/// a step costs about 53 instructions on the Cortex-M4 and 36 on RISC-V, against about 180 on
/// the general path, so that a call prepares three times as many of them for its set-up (the
/// largest calls, within budget, in `docs/performance.md`).
const MERGED_STEPS_PER_WORK: u32 = 3;

/// A speed from the planner's square of it: single precision, as the planner holds it (a
/// square root in double precision would add digits the square does not have, for ten times
/// the instructions in software).
fn speed_of(square: f32) -> f64 {
    f64::from(crate::fpu::sqrtf(square))
}

/// The value kept in `slot`, worked out by `compute` at the first call while the slot holds
/// 0 (a block's values that only some of its phases need: [`Current`]'s `ticks_per_speed`,
/// an axis's `per_mm`).
#[inline(always)]
fn once_needed(slot: &mut f64, compute: impl FnOnce() -> f64) -> f64 {
    if is_zero(*slot) {
        *slot = compute();
    }
    *slot
}

/// The last step of axis `a` in phase `phase` of `profile`, anchored `s_anchor` mm into its
/// block of `mm`: for a phase that ends before the profile, or a profile that stops. Step `j`
/// is at `h·(j − ½)` mm into the block. Its own call, which the compiler does not work out
/// ahead of the branch that needs it (for every phase, inlined). The axis's steps per mm are
/// worked out at its first call of the block: a block at one speed has no such phase, and
/// goes without the division.
#[inline(never)]
fn last_step_in(a: &mut AxisSteps, profile: &Profile, phase: usize, mm: f64, s_anchor: f64) -> u64 {
    let n = a.n;
    let per_mm = once_needed(&mut a.per_mm, || f64::from(n) / mm);
    let offset = if is_zero(s_anchor) {
        0.5
    } else {
        product(s_anchor, per_mm) + 0.5
    };
    let end = profile.phase_end(phase);
    if phase + 1 < PHASES {
        // The last step before the phase's end.
        ceil_u64(end * per_mm + offset).saturating_sub(1)
    } else {
        // Within rounding of a hold's stopping point, a step is at it.
        let end = end * (1.0 + 1e-9) + 1e-12;
        floor_u64(end * per_mm + offset)
    }
}

/// How an axis's steps are timed in its current phase.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Timing {
    /// By a step clock.
    Clock(StepClock),
    /// Step by step in double precision (a phase out of the clocks' range).
    Exact,
}

/// One axis of the block being prepared.
#[derive(Debug, Clone, Copy)]
struct AxisSteps {
    /// Steps of the block.
    n: u32,
    /// The next step to emit (1-based; `n + 1` when all are).
    j: u32,
    /// The profile phase `j` is in ([`PHASES`] once past the last one).
    phase: usize,
    /// The last step of that phase.
    phase_last: u32,
    /// Path length of one step (mm; 0 when the axis has none).
    step_mm: f64,
    /// Its inverse, steps per mm of path, once a phase's bound needed it ([`last_step_in`]);
    /// 0 until then.
    per_mm: f64,
    timing: Timing,
}

impl AxisSteps {
    /// Where step `j` is along the block, mm: the half-step point `step_mm·(j − ½)`.
    fn step_mm_at(&self, j: u32) -> f64 {
        if j == 1 {
            // The same value, without the conversion, the subtraction and the multiplication.
            half(self.step_mm)
        } else {
            product(self.step_mm, f64::from(j) - 0.5)
        }
    }

    /// When every step of the block is emitted: past the last phase, no next step (`next`,
    /// the axis's next tick, is `u64::MAX`); `true` then.
    #[inline(always)]
    fn end_if_done(&mut self, next: &mut u64) -> bool {
        if self.j <= self.n {
            return false;
        }
        self.phase = PHASES;
        *next = u64::MAX;
        true
    }
}

/// One axis in [`Current::run_cruises`], in the form each core's registers hold best (see
/// `PackedLane` and `SplitLane`). Measured on the other core, each form costs the walk 4
/// to 8 instructions a step more.
#[cfg(not(target_arch = "arm"))]
type Lane = PackedLane;
/// One axis in [`Current::run_cruises`] (see the RISC-V build's).
#[cfg(target_arch = "arm")]
type Lane = SplitLane;

/// A [`Lane`] as the time of its next step and its cruise's interval, both in the walk's
/// 32-bit ticks with a 32-bit fraction (32.32), so that a step is one 64-bit addition: RISC-V's
/// 31 registers hold every lane.
#[cfg(any(test, not(target_arch = "arm")))]
#[derive(Debug, Clone, Copy)]
struct PackedLane {
    at: u64,
    interval: u64,
}

#[cfg(any(test, not(target_arch = "arm")))]
impl PackedLane {
    /// An axis with no step left: never the first.
    const DONE: Self = Self::new(u32::MAX, CruiseGaps::NONE);

    /// The axis whose next step is at `tick`, `gaps` leading on from it.
    #[inline(always)]
    const fn new(tick: u32, gaps: CruiseGaps) -> Self {
        let (at, interval) = gaps.fixed_from(tick);
        Self { at, interval }
    }

    /// The tick of its next step.
    #[inline(always)]
    fn next(&self) -> u32 {
        (self.at >> 32) as u32
    }

    /// Move on past its next step (at `tick`, which this form does not need).
    #[inline(always)]
    fn step(&mut self, tick: u32) {
        let _ = tick;
        self.at = self.at.wrapping_add(self.interval);
    }

    /// The most steps it can take before `stop`: its steps are at least its interval's whole
    /// ticks apart (at least one), the first at its next.
    #[inline(always)]
    fn most_before(&self, stop: u32) -> u32 {
        let (next, gap) = (self.next(), (self.interval >> 32) as u32);
        if next >= stop {
            0
        } else {
            (stop - next - 1) / gap.max(1) + 1
        }
    }

    /// The tick of the step before its next (after at least one [`PackedLane::step`]).
    #[inline(always)]
    fn previous(&self) -> u32 {
        (self.at.wrapping_sub(self.interval) >> 32) as u32
    }

    /// [`PackedLane::step`] (this form counts no steps).
    #[inline(always)]
    fn step_uncounted(&mut self, tick: u32) {
        self.step(tick);
    }

    /// This form counts no steps (see [`step_lane`]).
    #[inline(always)]
    fn count(&mut self, steps: u32) {
        let _ = steps;
    }

    /// No step left: never the first again.
    #[inline(always)]
    fn end(&mut self) {
        *self = Self::DONE;
    }
}

/// A [`Lane`] as the tick of its next step apart from its cruise's gaps: on the Cortex-M,
/// whose 13 registers cannot hold every lane, a step reads the tick alone and moves on from
/// the one the scan found.
#[cfg(any(test, target_arch = "arm"))]
#[derive(Debug, Clone, Copy)]
struct SplitLane {
    next: u32,
    gaps: CruiseGaps,
    /// The steps it took (see [`step_lane`]).
    taken: u32,
}

#[cfg(any(test, target_arch = "arm"))]
impl SplitLane {
    /// An axis with no step left: never the first.
    const DONE: Self = Self::new(u32::MAX, CruiseGaps::NONE);

    /// The axis whose next step is at `tick`, `gaps` leading on from it.
    #[inline(always)]
    const fn new(tick: u32, gaps: CruiseGaps) -> Self {
        Self {
            next: tick,
            gaps,
            taken: 0,
        }
    }

    /// The tick of its next step.
    #[inline(always)]
    fn next(&self) -> u32 {
        self.next
    }

    /// Move on past its next step, which is at `tick`, and count it.
    #[inline(always)]
    fn step(&mut self, tick: u32) {
        self.step_uncounted(tick);
        self.count(1);
    }

    /// The tick of the step before its next (after at least one step).
    #[inline(always)]
    fn previous(&self) -> u32 {
        self.gaps.before(self.next)
    }

    /// The most steps it can take before `stop` (see [`PackedLane::most_before`]).
    #[inline(always)]
    fn most_before(&self, stop: u32) -> u32 {
        if self.next >= stop {
            0
        } else {
            (stop - self.next - 1) / self.gaps.shortest() + 1
        }
    }

    /// Move on past its next step, which is at `tick`, counted later ([`SplitLane::count`]).
    #[inline(always)]
    fn step_uncounted(&mut self, tick: u32) {
        self.next = self.gaps.after(tick);
    }

    /// Count `steps` steps taken by [`SplitLane::step_uncounted`].
    #[inline(always)]
    fn count(&mut self, steps: u32) {
        self.taken += steps;
    }

    /// No step left: never the first again (the steps it took stay counted).
    #[inline(always)]
    fn end(&mut self) {
        self.next = u32::MAX;
    }
}

/// How far a [`Current::run_cruises`] walk has come: the tick of its last step (from the
/// walk's origin), the steps it took, the axis of the last, where it stops next (`stop`,
/// see [`next_stop`]) and the axes still walking (a mask).
#[derive(Debug, Clone, Copy)]
struct Walk {
    last: u32,
    steps: u32,
    last_axis: u8,
    stop: u32,
    walking: u8,
}

/// Where a phase starts on the step clocks' timeline, the same for every axis that steps in
/// it ([`Current::enter_phase`]): the tick the clocks count from, the start's fraction of a
/// tick past it (for a cruise in its clock's fixed point, `fraction`, for a ramp as a
/// double, `rel`; the other is 0), and the phase's rate (a cruise's ticks per mm, a ramp's
/// ticks from speed 0 to its start speed).
#[derive(Debug, Clone, Copy)]
struct PhaseStart {
    base: u64,
    fraction: u64,
    rel: f64,
    rate: f64,
}

/// The block being prepared.
#[derive(Debug, Clone, Copy)]
struct Current<const N: usize> {
    axes: [AxisSteps; N],
    /// Tick of the next step of each axis; `u64::MAX` when none.
    next_tick: [u64; N],
    neg: u8,
    mm: f64,
    accel: f64,
    /// Ticks to change speed by 1 mm/s at the block's acceleration, `ticks_per_s / accel`,
    /// once a phase that changes speed needs it (0 until then: a block at one speed, the most
    /// common in a chain of short moves, goes without the division).
    ticks_per_speed: f64,
    /// The block's nominal speed (mm/s), and its square as the planner holds it.
    nominal: f64,
    nominal_sqr: f32,
    s_anchor: f64,
    /// Exact time of the anchor, ticks.
    t_anchor: f64,
    /// Exact time of the profile's end, ticks (the block's end, or a hold's stop):
    /// `t_anchor` plus the profile's duration, worked out with the profile.
    t_end: f64,
    /// The axis of the last emitted step ([`NO_AXIS`]: none since the anchor).
    last_axis: u8,
    /// The one axis that steps, when only one does.
    only_axis: Option<usize>,
    /// Axes whose timing is not set up for the current profile yet: `fill` sets them up one
    /// per turn (each is a few thousand instructions) before the next step.
    unset: u8,
    /// Set through [`Current::set_profile`], which forgets the phases' starts.
    profile: Profile,
    /// Each phase's start on the clocks' timeline, once an axis has entered it.
    starts: [Option<PhaseStart>; PHASES],
    exit_used: f32,
    hold_used: bool,
    /// The largest distance of a step's tick from its exact time in the last
    /// [`Current::burst`], ticks (debug builds).
    #[cfg(debug_assertions)]
    burst_error: f64,
}

impl<const N: usize> Current<N> {
    /// No block: what [`Prep`] holds until it loads one ([`Prep::load`] writes every field).
    fn unloaded() -> Self {
        Current {
            axes: [AxisSteps {
                n: 0,
                j: 1,
                phase: PHASES,
                phase_last: 0,
                step_mm: 0.0,
                per_mm: 0.0,
                timing: Timing::Exact,
            }; N],
            next_tick: [u64::MAX; N],
            neg: 0,
            mm: 0.0,
            accel: 1.0,
            ticks_per_speed: 0.0,
            nominal: 0.0,
            nominal_sqr: 0.0,
            s_anchor: 0.0,
            t_anchor: 0.0,
            t_end: 0.0,
            last_axis: NO_AXIS,
            only_axis: None,
            unset: 0,
            profile: Profile::plan(0.0, 0.0, 0.0, 0.0, 1.0),
            starts: [None; PHASES],
            exit_used: 0.0,
            hold_used: false,
            #[cfg(debug_assertions)]
            burst_error: 0.0,
        }
    }

    /// The horizon of a top-up that has just loaded this block: `horizon`, or past the block's
    /// end when it comes within a quarter of the lead after it. With the end of a block
    /// within a quarter of the lead before the horizon, where a top-up stops ([`Prep::fill`]),
    /// top-ups end with blocks: where blocks are about as long as half the lead (a chain of
    /// short moves), each top-up took a few steps of one block and the rest of the next, each
    /// run of steps with a set-up of its own. The queue then holds up to five quarters of the
    /// lead.
    fn horizon_to_end(&self, horizon: u64, lead_ticks: u32) -> u64 {
        let end = ceil_u64(self.t_end);
        if end > horizon && end - horizon <= u64::from(lead_ticks / 4) {
            end + 1
        } else {
            horizon
        }
    }

    /// Take `profile` from the anchor on: the phases' starts are found anew, and its end.
    fn set_profile(&mut self, profile: Profile, ticks_per_s: f64) {
        self.profile = profile;
        self.t_end = self.t_anchor + profile.duration() * ticks_per_s;
        self.starts = [None; PHASES];
    }

    fn profile_for(&self, v0: f64, exit_sqr: f32, hold: bool) -> Profile {
        let rest = if is_zero(self.s_anchor) {
            self.mm
        } else {
            difference(self.mm, self.s_anchor)
        };
        if hold {
            Profile::hold(rest, v0, self.accel)
        } else {
            // A block left at its nominal speed (a chain of moves at one feed) has that speed
            // already: its square root is not taken again.
            let exit = if exit_sqr.to_bits() == self.nominal_sqr.to_bits() {
                self.nominal
            } else {
                speed_of(exit_sqr)
            };
            Profile::plan(rest, v0, self.nominal, exit, self.accel)
        }
    }

    /// The path position of the last emitted step (the anchor when none), mm.
    fn last_s(&self) -> f64 {
        match self.axes.get(usize::from(self.last_axis)) {
            Some(a) => a.step_mm_at(a.j.saturating_sub(1)),
            None => self.s_anchor,
        }
    }

    /// The path position and exact time (ticks) of the last emitted step.
    fn last_point(&self, ticks_per_s: f64) -> (f64, f64) {
        let s = self.last_s();
        let dt = self
            .profile
            .time_at(s - self.s_anchor)
            .unwrap_or_else(|| self.profile.duration());
        (s, self.t_anchor + dt * ticks_per_s)
    }

    /// Re-plan the rest of the block from the last emitted step (the axes' clocks are set up
    /// again by the next calls of `fill`, see [`Current::unset`]). Once a plan change: out of
    /// `fill`'s loop.
    #[inline(never)]
    fn reanchor(&mut self, exit_sqr: f32, hold: bool, ticks_per_s: f64) {
        let (s, t) = self.last_point(ticks_per_s);
        let v = self.profile.speed_at(s - self.s_anchor);
        self.s_anchor = s;
        self.t_anchor = t;
        self.last_axis = NO_AXIS;
        self.exit_used = exit_sqr;
        self.hold_used = hold;
        self.set_profile(self.profile_for(v, exit_sqr, hold), ticks_per_s);
        for a in self.axes.iter_mut() {
            a.phase = 0;
        }
        self.unset = self.steps_left();
    }

    /// The axes with steps left in the block.
    fn steps_left(&self) -> u8 {
        let mut mask = 0;
        for (i, a) in self.axes.iter().enumerate() {
            if a.j <= a.n {
                mask |= 1 << i;
            }
        }
        mask
    }

    /// Find the phase of axis `i`'s next step, from the one it is in, and set up its timing.
    /// Returns the work it counts ([`PHASE_WORK`], or [`CRUISE_PHASE_WORK`] for a cruise).
    #[inline(never)]
    fn enter_phase(&mut self, i: usize, ticks_per_s: f64) -> u32 {
        let (Some(a), Some(next)) = (self.axes.get_mut(i), self.next_tick.get_mut(i)) else {
            return 1;
        };
        *next = u64::MAX;
        if a.end_if_done(next) {
            return 1;
        }
        let h = a.step_mm;
        // Step j is at h·(j − ½) − s_anchor along the profile. The anchor is the block's start
        // until the block is planned again on its way (a hold, an override, a new exit speed):
        // in software double precision, its products and sums are only worked out then (here
        // and below, the same to the bit).
        let anchored = !is_zero(self.s_anchor);
        while a.phase < PHASES {
            // An empty phase before the last holds no step: passed over without its bounds
            // (a multiplication, an addition and a `ceil` in software double precision).
            if a.phase + 1 < PHASES && self.profile.is_empty(a.phase) {
                a.phase += 1;
                continue;
            }
            let last = if self.profile.stops() || !self.profile.ends_with(a.phase) {
                last_step_in(a, &self.profile, a.phase, self.mm, self.s_anchor)
            } else {
                // The phase that ends the profile, not at a stop, ends at the block's end:
                // `ceil(end·per_mm + offset) − 1` is the block's last step.
                u64::MAX
            };
            let last = last.min(u64::from(a.n));
            if last >= u64::from(a.j) {
                a.phase_last = last as u32;
                break;
            }
            a.phase += 1;
        }
        if a.phase >= PHASES {
            return PHASE_WORK;
        }
        let ph = self.profile.phase(a.phase);
        // The block's first step, in a phase from its start, is half a step into it (`half`:
        // exact, as `× 0.5` is, without the multiplication).
        let first_half_step = !anchored && a.j == 1 && is_zero(ph.start);
        // How far into the phase the next step is, mm.
        let x = if first_half_step {
            half(h)
        } else {
            // Less the anchor only when there is one (`s − 0` is `s`).
            let s = a.step_mm_at(a.j);
            let s = if anchored { s - self.s_anchor } else { s };
            at_least_zero(s - ph.start)
        };
        let steps = a.phase_last - a.j + 1;
        // The phase's start, found by the first axis that enters it.
        let PhaseStart {
            base,
            fraction,
            rel,
            rate,
        } = match self.starts.get(a.phase).copied().flatten() {
            Some(start) => start,
            None => {
                let start = if is_zero(ph.t_start) {
                    self.t_anchor
                } else {
                    self.t_anchor + product(ph.t_start, ticks_per_s)
                };
                let found = match ph.shape {
                    Shape::Cruise => {
                        let (base, fraction) = StepClock::phase_start(start);
                        let rate = ticks_per_s / ph.v_start;
                        PhaseStart {
                            base,
                            fraction,
                            rel: 0.0,
                            rate,
                        }
                    }
                    Shape::Up | Shape::Down => {
                        let base = floor_u64(start);
                        let ticks_per_speed =
                            once_needed(&mut self.ticks_per_speed, || ticks_per_s / self.accel);
                        PhaseStart {
                            base,
                            fraction: 0,
                            rel: start - base as f64,
                            rate: ticks_per_speed * ph.v_start,
                        }
                    }
                };
                if let Some(slot) = self.starts.get_mut(a.phase) {
                    *slot = Some(found);
                }
                found
            }
        };
        let clock = match ph.shape {
            Shape::Cruise => {
                let ticks_per_mm = rate;
                let interval = ticks_per_mm * h;
                // `ticks_per_mm · (h / 2)` is `(ticks_per_mm · h) / 2`, to the bit.
                let first = if first_half_step {
                    half(interval)
                } else {
                    product(ticks_per_mm, x)
                };
                StepClock::cruise_from(base, fraction, first, interval, steps)
            }
            shape => {
                let c = rate;
                let k = 2.0
                    * ticks_per_s
                    * once_needed(&mut self.ticks_per_speed, || ticks_per_s / self.accel);
                let up = shape == Shape::Up;
                let (c, y) = if up {
                    (rel - c, c * c + k * x)
                } else {
                    (rel + c, at_least_zero(c * c - k * x))
                };
                StepClock::ramp(base, c, y, k * h, up, steps)
            }
        };
        match clock {
            Some(clock) => {
                a.timing = Timing::Clock(clock);
                *next = clock.tick();
                if ph.shape == Shape::Cruise {
                    CRUISE_PHASE_WORK
                } else {
                    PHASE_WORK
                }
            }
            None => {
                a.timing = Timing::Exact;
                let tick = self.exact_tick(i, ticks_per_s);
                if let Some(next) = self.next_tick.get_mut(i) {
                    *next = tick;
                }
                PHASE_WORK
            }
        }
    }

    /// The tick of axis `i`'s next step, in double precision.
    #[cold]
    fn exact_tick(&self, i: usize, ticks_per_s: f64) -> u64 {
        self.exact_time(i, ticks_per_s)
            .map_or(u64::MAX, |t| libm::round(t) as u64)
    }

    /// The exact time (ticks) of axis `i`'s next step on the profile; `None` past a hold's
    /// stopping point.
    fn exact_time(&self, i: usize, ticks_per_s: f64) -> Option<f64> {
        let a = self.axes.get(i)?;
        let dt = self.profile.time_at(a.step_mm_at(a.j) - self.s_anchor)?;
        Some(self.t_anchor + dt * ticks_per_s)
    }

    /// Axis `i` has emitted its step: time its next one. Returns the work it took (see
    /// [`WORK_PER_FILL`]).
    #[inline(always)]
    fn advance(&mut self, i: usize, ticks_per_s: f64) -> u32 {
        self.last_axis = i as u8;
        let Some(a) = self.axes.get_mut(i) else {
            return 1;
        };
        a.j += 1;
        if a.j > a.phase_last {
            a.phase += 1;
            return 1 + self.enter_phase(i, ticks_per_s);
        }
        let (tick, rooted) = match &mut a.timing {
            Timing::Clock(clock) => clock.advance(),
            Timing::Exact => (self.exact_tick(i, ticks_per_s), true),
        };
        if let Some(t) = self.next_tick.get_mut(i) {
            *t = tick;
        }
        if rooted { 1 + ROOT_WORK } else { 1 }
    }

    /// The axis whose next step comes first, and that step's tick (`u64::MAX`: none).
    #[inline(always)]
    fn first_step(&self) -> (usize, u64) {
        if let Some(i) = self.only_axis {
            return (i, self.next_tick.get(i).copied().unwrap_or(u64::MAX));
        }
        let mut best = (0, u64::MAX);
        for (i, &t) in self.next_tick.iter().enumerate() {
            if t < best.1 {
                best = (i, t);
            }
        }
        best
    }

    /// Emit the steps that need none of the emitter's care: each step at its own tick, after
    /// the last event (an edge at the same tick joins it on the general path), a full pulse
    /// and as long low after its axis's last rising edge, in the direction its line already
    /// has, not the last of its phase, by a step clock, and before `horizon`. Stops at the
    /// first step that is not such (the general path takes it), at `max_work` or when the
    /// queue's room is used. `first` is the axis whose step comes first and its tick
    /// ([`Current::first_step`]). Returns the work done (0: nothing emitted, nothing changed).
    ///
    /// This is the inner loop of preparation: one axis stepping alone runs in
    /// [`Current::run_alone`], several that all cruise in [`Current::run_cruises`]; the others
    /// go step by step in the order of their next steps.
    #[inline(never)]
    fn burst<const Q: usize>(
        &mut self,
        em: &mut Emitter<N>,
        tx: &mut Producer<'_, N, Q>,
        horizon: u64,
        max_work: u32,
        ticks_per_s: f64,
        first: (usize, u64),
    ) -> u32 {
        let room = em.room.saturating_sub(SLOTS_PER_STEP + 2);
        let room = room.min(u32::MAX as usize) as u32;
        let limit = max_work.min(room);
        if let Some(i) = self.only_axis {
            return self.run_alone(i, em, tx, horizon, limit, ticks_per_s);
        }
        let cruise_steps = max_work.saturating_mul(MERGED_STEPS_PER_WORK).min(room);
        if let Some(steps) = self.run_cruises(em, tx, horizon, cruise_steps, ticks_per_s, first) {
            return steps.div_ceil(MERGED_STEPS_PER_WORK);
        }
        // Step by step, the axis whose step comes first: the axes are kept in the order of
        // their next steps, and an axis that has stepped moves down past those due sooner
        // (one comparison when it stays first).
        let mut order = by_next_step::<N, u64>(|k| self.next_tick.get(k).copied());
        let spacing = 2 * em.pulse;
        let mut last = em.last_tick;
        let mut work = 0u32;
        let mut written = 0usize;
        let mut last_axis = self.last_axis;
        while work < limit {
            let i = usize::from(order.first().copied().unwrap_or(0));
            let t = self.next_tick.get(i).copied().unwrap_or(u64::MAX);
            #[cfg(debug_assertions)]
            let exact = self.exact_time(i, ticks_per_s).unwrap_or(f64::INFINITY);
            let bit = 1u8 << i;
            let (Some(a), Some(rose), Some(next)) = (
                self.axes.get_mut(i),
                em.rose_at.get_mut(i),
                self.next_tick.get_mut(i),
            ) else {
                break;
            };
            let Timing::Clock(clock) = &mut a.timing else {
                break;
            };
            let delta = t.wrapping_sub(last);
            // As in `Current::run_alone`, and not the last step of its phase.
            if t >= horizon
                || delta.wrapping_sub(1) >= u64::from(MAX_DELTA)
                || t - *rose < spacing
                || a.j >= a.phase_last
                || (em.dir_known & bit) == 0
                || (em.dir_neg ^ self.neg) & bit != 0
                || !tx.write(&Event {
                    delta: delta as u32,
                    rise: bit,
                    ..Event::default()
                })
            {
                break;
            }
            written += 1;
            last = t;
            *rose = t;
            a.j += 1;
            let (tick, rooted) = clock.advance();
            *next = tick;
            work += if rooted { 1 + ROOT_WORK } else { 1 };
            last_axis = i as u8;
            #[cfg(debug_assertions)]
            {
                self.burst_error = self.burst_error.max((t as f64 - exact).abs());
            }
            sink_first(&mut order, tick, |k| self.next_tick.get(k).copied());
        }
        if written > 0 {
            self.last_axis = last_axis;
            em.wrote_run(last, written);
        }
        work
    }

    /// [`Current::burst`] when every axis with steps left cruises with steady gaps (see
    /// [`Current::run_alone`]), its direction line set and its last edge a pulse and as long
    /// low before its next step: the axes' clocks are merged with their state in a local
    /// copy, in 32-bit ticks from the last event, each step checked only against one stop
    /// tick (the horizon's, or the last step of an axis's phase if sooner) and the last event
    /// (an edge at the same tick joins it on the general path). At the stop, an axis whose
    /// phase ends its steps in the block takes that last step and is done, and the walk goes
    /// on with the others ([`end_lane`], [`next_stop`]). At most `max_steps` steps;
    /// returns how many it took, or `None` when the axes are not all such (the step-by-step
    /// loop takes them). Out of line: its loop's registers stay its own.
    ///
    /// The merge finds the first axis by a scan of the lanes ([`first_lane`]), which are
    /// matched by constant indices only, so that they stay in registers (all of them on
    /// RISC-V's 31; on the Cortex-M4's 13, the most used). Exactly two lanes walking go
    /// through [`Current::walk_pair`] first, which needs no scan.
    #[inline(never)]
    fn run_cruises<const Q: usize>(
        &mut self,
        em: &mut Emitter<N>,
        tx: &mut Producer<'_, N, Q>,
        horizon: u64,
        max_steps: u32,
        ticks_per_s: f64,
        (first, at): (usize, u64),
    ) -> Option<u32> {
        let _ = ticks_per_s;
        // The first step (`first`'s, at `at`: [`Current::first_step`]) needs the general path
        // (an edge at the last event's tick, the last step of a phase the axis has more steps
        // after, the horizon): found before the set-up, which would be wasted.
        if at == em.last_tick
            || at >= horizon
            || self
                .axes
                .get(first)
                .is_none_or(|a| a.j >= a.phase_last && a.phase_last < a.n)
        {
            return Some(0);
        }
        let spacing = 2 * em.pulse;
        // The walk's ticks count from the last event. It stops before the horizon, within one
        // event's delay of the last event (`bound`), and before the last step of each axis's
        // phase (the general path's), so that every step it takes needs no check but the
        // stop's. An axis whose phase ends its steps in the block takes that last step here
        // and is done (`end_lane`): the walk goes on with the others.
        let origin = em.last_tick;
        let bound = StepClock::span(origin, horizon).min(MAX_DELTA);
        // The walk stops at `hard`: the bound, or the last step of a phase its axis has more
        // steps after. `stop` is the earlier of it and the next end of an axis still walking.
        let (mut hard, mut stop) = (bound, bound);
        // Each axis's last step of its phase, and the axes still walking.
        let mut ends = [u32::MAX; N];
        let mut walking = 0u8;
        let mut lanes = [Lane::DONE; N];
        for (i, (a, lane)) in self.axes.iter().zip(lanes.iter_mut()).enumerate() {
            if a.j > a.n {
                continue;
            }
            let bit = 1u8 << i;
            let Timing::Clock(clock) = &a.timing else {
                return None;
            };
            let rose = em.rose_at.get(i).copied().unwrap_or(0);
            let next = clock.tick();
            if !is_steady(clock, spacing)
                || (em.dir_known & bit) == 0
                || (em.dir_neg ^ self.neg) & bit != 0
                || next.wrapping_sub(rose) < spacing
            {
                return None;
            }
            let (tick, gaps) = clock.near(origin, bound)?;
            let last = clock.tick_ahead(a.phase_last.saturating_sub(a.j))?;
            let end = last.saturating_sub(origin).min(u64::from(u32::MAX)) as u32;
            if let Some(e) = ends.get_mut(i) {
                *e = end;
            }
            walking |= bit;
            if a.phase_last < a.n {
                hard = hard.min(end);
            }
            stop = stop.min(end);
            *lane = Lane::new(tick, gaps);
        }
        // The steps each axis took.
        let mut taken = [0u32; N];
        let written_before = tx.written();
        // Two axes walking (a diagonal, a curve in a plane): their own loop first.
        let exact = (origin, ticks_per_s);
        let mut walk = Walk {
            last: 0,
            steps: 0,
            last_axis: self.last_axis,
            stop,
            walking,
        };
        let rest = walking & walking.wrapping_sub(1);
        if rest != 0 && rest & rest.wrapping_sub(1) == 0 {
            let pair = (
                walking.trailing_zeros() as usize,
                rest.trailing_zeros() as usize,
            );
            let limits = (hard, max_steps);
            self.walk_pair(
                tx, &mut lanes, &mut taken, pair, &ends, limits, &mut walk, exact,
            );
        }
        // The general loop's own copies, whose addresses stay its own: they can live in
        // registers.
        let (mut lanes, mut taken) = (lanes, taken);
        // Steps taken, the tick of the last and its axis.
        let (steps, last, last_axis) = tx.in_run(|tx| {
            let Walk {
                mut last,
                steps,
                mut last_axis,
                mut stop,
                mut walking,
            } = walk;
            // Counted down: the count and its limit in one register.
            let budget = max_steps.saturating_sub(steps);
            let mut left = budget;
            while left > 0 {
                // The axis whose step comes first (of two at the same tick, the lower).
                let (i, t) = first_lane(&lanes);
                // At the stop, the last step of an axis whose steps in the block end with it is
                // taken (and any other at its tick), and that axis is done. At `hard`, the walk
                // ends.
                let at_stop = t >= stop;
                if at_stop && t >= hard {
                    break;
                }
                if !write_step(tx, last, i, t) {
                    break;
                }
                #[cfg(debug_assertions)]
                self.note_walk_error(
                    i,
                    lane_taken(&lanes, &taken, i),
                    origin + u64::from(t),
                    ticks_per_s,
                );
                last = t;
                left -= 1;
                step_lane(&mut lanes, &mut taken, i, t);
                if at_stop && ends.get(i) == Some(&t) {
                    end_lane(&mut lanes, i);
                    walking &= !(1 << i);
                    stop = next_stop(hard, &ends, walking);
                }
            }
            // The last step's axis, found once: of the steps at its tick, the highest axis's
            // was taken last.
            if left < budget {
                last_axis = last_stepped(&lanes, &ends, walking, last);
            }
            (steps + (budget - left), last, last_axis)
        });
        if steps > 0 {
            // Each clock moves on by the steps its axis took (from the steps it had left), in
            // its own 64-bit terms.
            for (k, ((a, next), rose)) in self
                .axes
                .iter_mut()
                .zip(self.next_tick.iter_mut())
                .zip(em.rose_at.iter_mut())
                .enumerate()
            {
                let taken = lane_taken(&lanes, &taken, k);
                if taken == 0 {
                    continue;
                }
                if let Timing::Clock(clock) = &mut a.timing {
                    *rose = clock.skip(taken);
                    *next = clock.tick();
                }
                a.j += taken;
                // An axis that took its last step in the block is done.
                a.end_if_done(next);
            }
            self.last_axis = last_axis;
            let written = tx.written().wrapping_sub(written_before) as usize;
            em.wrote_run(origin + u64::from(last), written);
        }
        Some(steps)
    }

    /// [`Current::run_cruises`]'s walk while exactly two lanes walk, `a` before `b` (a
    /// diagonal or a curve in a plane, the other axes idle): the earlier of their next steps,
    /// or both at one tick as one event, with the two lanes in registers and no scan of the
    /// others. At the stop, as in the general loop, an axis's last step in the block (its
    /// `ends`) is taken and the axis is done (its lane never first again), and the walk goes
    /// on with the other. It ends at `hard`, at a write that fails, and one step short of
    /// `max_steps` (a step of both counts two); the general loop goes on from where it
    /// stopped, with the same lanes, counts and stop.
    #[inline(never)]
    #[allow(clippy::too_many_arguments)]
    fn walk_pair<const Q: usize>(
        &mut self,
        tx: &mut Producer<'_, N, Q>,
        lanes: &mut [Lane; N],
        taken: &mut [u32; N],
        (a, b): (usize, usize),
        ends: &[u32; N],
        (hard, max_steps): (u32, u32),
        walk: &mut Walk,
        exact: (u64, f64),
    ) {
        let _ = exact;
        let (Some(&first), Some(&second)) = (lanes.get(a), lanes.get(b)) else {
            return;
        };
        let (mut la, mut lb) = (first, second);
        // Only the walk's first step can be at the last event's tick (a lane's steps are
        // apart by its gaps, and a step of both at one tick is one event): the general
        // loop's, which joins it to that event.
        if la.next().min(lb.next()) == walk.last || walk.steps + 1 >= max_steps {
            return;
        }
        let (end_a, end_b) = (
            ends.get(a).copied().unwrap_or(0),
            ends.get(b).copied().unwrap_or(0),
        );
        let (edge_a, edge_b) = (1u8 << a, 1u8 << b);
        let (mut last, mut stop, mut walking) = (walk.last, walk.stop, walk.walking);
        // Steps left to the general loop's last (a step of both counts two), and the steps
        // `a` took; `b` took the others.
        let mut left = max_steps - walk.steps - 1;
        let mut took_a = 0u32;
        // The tick of `b`'s last step in the block, once taken (its lane is done then).
        let mut b_ended = None;
        #[cfg(debug_assertions)]
        let (origin, ticks_per_s) = exact;
        #[cfg(debug_assertions)]
        let counted = [lane_taken(lanes, taken, a), lane_taken(lanes, taken, b)];
        // Events of both lanes' steps, in a loop that does not count them as it goes.
        let mut both = 0u32;
        #[cfg(debug_assertions)]
        let mut took_b = 0u32;
        // The steps before the stop, the earlier of the two lanes' next each time, or both at
        // one tick as one event; `$counted`: with the count of steps left checked and kept at
        // each step, else with none (the stop comes first), the steps counted afterwards.
        macro_rules! steps_before_stop {
            ($tx:ident, $counted:literal) => {
                while !$counted || left > 0 {
                    let (ta, tb) = (la.next(), lb.next());
                    if ta < tb {
                        if ta >= stop || !$tx.write_rise(ta.wrapping_sub(last), edge_a) {
                            break;
                        }
                        #[cfg(debug_assertions)]
                        self.note_walk_error(
                            a,
                            counted[0] + took_a,
                            origin + u64::from(ta),
                            ticks_per_s,
                        );
                        la.step_uncounted(ta);
                        took_a += 1;
                        if $counted {
                            left -= 1;
                        }
                        last = ta;
                    } else if tb < ta {
                        if tb >= stop || !$tx.write_rise(tb.wrapping_sub(last), edge_b) {
                            break;
                        }
                        #[cfg(debug_assertions)]
                        {
                            let at = origin + u64::from(tb);
                            self.note_walk_error(b, counted[1] + took_b, at, ticks_per_s);
                            took_b += 1;
                        }
                        lb.step_uncounted(tb);
                        if $counted {
                            left -= 1;
                        }
                        last = tb;
                    } else {
                        if ($counted && left < 2)
                            || ta >= stop
                            || !$tx.write_rise(ta.wrapping_sub(last), edge_a | edge_b)
                        {
                            break;
                        }
                        #[cfg(debug_assertions)]
                        {
                            let at = origin + u64::from(ta);
                            self.note_walk_error(a, counted[0] + took_a, at, ticks_per_s);
                            self.note_walk_error(b, counted[1] + took_b, at, ticks_per_s);
                            took_b += 1;
                        }
                        la.step_uncounted(ta);
                        lb.step_uncounted(ta);
                        took_a += 1;
                        if $counted {
                            left -= 2;
                        } else {
                            both += 1;
                        }
                        last = ta;
                    }
                }
            };
        }
        tx.in_run(|tx| {
            loop {
                // At most the steps each lane can take before the stop, at its shortest gap
                // apart: when they are within `left`, the loop need not count them.
                if la.most_before(stop) + lb.most_before(stop) <= left {
                    let (written, before) = (tx.written(), both);
                    steps_before_stop!(tx, false);
                    left -= tx.written().wrapping_sub(written) + (both - before);
                } else {
                    steps_before_stop!(tx, true);
                }
                // At the stop and before `hard`: the steps at its tick, one of them an axis's
                // last in the block, which is then done.
                let (ta, tb) = (la.next(), lb.next());
                let t = ta.min(tb);
                let (at_a, at_b) = (ta == t, tb == t);
                let steps = u32::from(at_a) + u32::from(at_b);
                if t < stop || t >= hard || left < steps {
                    break;
                }
                let rise = if at_a { edge_a } else { 0 } | if at_b { edge_b } else { 0 };
                if !tx.write_rise(t.wrapping_sub(last), rise) {
                    break;
                }
                #[cfg(debug_assertions)]
                {
                    let at = origin + u64::from(t);
                    if at_a {
                        self.note_walk_error(a, counted[0] + took_a, at, ticks_per_s);
                    }
                    if at_b {
                        self.note_walk_error(b, counted[1] + took_b, at, ticks_per_s);
                        took_b += 1;
                    }
                }
                if at_a {
                    la.step_uncounted(t);
                    took_a += 1;
                    if t == end_a {
                        la.end();
                        walking &= !edge_a;
                    }
                }
                if at_b {
                    lb.step_uncounted(t);
                    if t == end_b {
                        lb.end();
                        walking &= !edge_b;
                        b_ended = Some(t);
                    }
                }
                left -= steps;
                last = t;
                // The next stop: `hard`, or the end of the axis still walking if sooner.
                stop = hard;
                if walking & edge_a != 0 {
                    stop = stop.min(end_a);
                }
                if walking & edge_b != 0 {
                    stop = stop.min(end_b);
                }
            }
        });
        let steps = max_steps - 1 - left;
        let took = steps - walk.steps;
        if took == 0 {
            return;
        }
        // The last event raised `b`'s line (and `a`'s too, at one tick) when `b`'s last step
        // is at its tick.
        let b_at = b_ended.unwrap_or_else(|| lb.previous());
        let b_last = took > took_a && b_at == last;
        for (k, mut lane, took) in [(a, la, took_a), (b, lb, took - took_a)] {
            lane.count(took);
            if let Some(slot) = lanes.get_mut(k) {
                *slot = lane;
            }
            #[cfg(not(target_arch = "arm"))]
            if let Some(count) = taken.get_mut(k) {
                *count += took;
            }
        }
        #[cfg(target_arch = "arm")]
        let _ = taken;
        *walk = Walk {
            last,
            steps,
            last_axis: if b_last { b as u8 } else { a as u8 },
            stop,
            walking,
        };
    }

    /// Debug builds: the step of axis `i` at `tick`, `taken` steps into a walk, is measured
    /// against its exact time on the profile ([`Current::burst_error`]).
    #[cfg(debug_assertions)]
    fn note_walk_error(&mut self, i: usize, taken: u32, tick: u64, ticks_per_s: f64) {
        if let Some(a) = self.axes.get(i) {
            let exact = self
                .profile
                .time_at(a.step_mm_at(a.j + taken) - self.s_anchor)
                .map_or(f64::INFINITY, |dt| self.t_anchor + dt * ticks_per_s);
            self.burst_error = self.burst_error.max((tick as f64 - exact).abs());
        }
    }

    /// [`Current::burst`] when axis `i` is the only one that steps: its steps before
    /// `horizon`, within `max_work`, with the step clock's kind matched once for the run
    /// ([`StepClock::walk`]) and its state in registers.
    #[inline(always)]
    fn run_alone<const Q: usize>(
        &mut self,
        i: usize,
        em: &mut Emitter<N>,
        tx: &mut Producer<'_, N, Q>,
        horizon: u64,
        max_work: u32,
        ticks_per_s: f64,
    ) -> u32 {
        let _ = ticks_per_s;
        let bit = 1u8 << i;
        if (em.dir_known & bit) == 0 || (em.dir_neg ^ self.neg) & bit != 0 {
            return 0;
        }
        let (Some(a), Some(rose), Some(next)) = (
            self.axes.get_mut(i),
            em.rose_at.get_mut(i),
            self.next_tick.get_mut(i),
        ) else {
            return 0;
        };
        #[cfg(debug_assertions)]
        let (mut worst, axis) = (0.0f64, *a);
        #[cfg(debug_assertions)]
        let mut j = axis.j;
        let Timing::Clock(clock) = &mut a.timing else {
            return 0;
        };
        // Two rising edges of the axis are a full pulse and as long low apart.
        let spacing = 2 * em.pulse;
        let mut last = em.last_tick;
        let mut rose_at = *rose;
        #[cfg(debug_assertions)]
        let (profile, s_anchor, t_anchor) = (&self.profile, self.s_anchor, self.t_anchor);
        // The exact time of step `j` of the axis, ticks (the error is measured in debug builds).
        #[cfg(debug_assertions)]
        let exact_at = |j: u32| {
            profile
                .time_at(axis.step_mm_at(j) - s_anchor)
                .map_or(f64::INFINITY, |dt| t_anchor + dt * ticks_per_s)
        };
        let left = a.phase_last.saturating_sub(a.j);
        // A cruise whose steps are always at least `spacing` apart and at most one event's
        // delay: after its first step, which is checked against the last event and the axis's
        // last edge, each of its steps is after the one before by one of its gaps, and only the
        // horizon is checked.
        let steady = is_steady(clock, spacing);
        // The closures are inlined into the walk's loops, also where the board optimises for
        // size.
        let (mut steps, mut work) = clock.walk(
            if steady { left.min(1) } else { left },
            max_work,
            ROOT_WORK,
            #[inline(always)]
            |t| {
                // After the last event and within one event's delay of it (one comparison
                // each way, wrapping), and a pulse and as long low after the axis's last edge
                // (never after the last event).
                let delta = t.wrapping_sub(last);
                if t >= horizon
                    || delta.wrapping_sub(1) >= u64::from(MAX_DELTA)
                    || t - rose_at < spacing
                    || !tx.write(&Event {
                        delta: delta as u32,
                        rise: bit,
                        ..Event::default()
                    })
                {
                    return false;
                }
                #[cfg(debug_assertions)]
                {
                    worst = worst.max((t as f64 - exact_at(j)).abs());
                    j += 1;
                }
                last = t;
                rose_at = t;
                true
            },
        );
        // The rest in 32-bit ticks from the first step.
        let span = StepClock::span(last, horizon);
        if steady
            && steps == 1
            && left > 1
            && let Some((mut t, mut gaps)) = clock.near(last, span)
        {
            let most = (left - 1).min(max_work.saturating_sub(work));
            let mut previous = 0u32;
            let mut more = 0u32;
            while more < most && t < span && tx.write_rise(t.wrapping_sub(previous), bit) {
                #[cfg(debug_assertions)]
                {
                    let gap = u64::from(t - previous);
                    debug_assert!(gap >= spacing && gap <= u64::from(MAX_DELTA));
                    worst = worst.max(((last + u64::from(t)) as f64 - exact_at(j)).abs());
                    j += 1;
                }
                previous = t;
                more += 1;
                t = gaps.after(t);
            }
            if more > 0 {
                last = clock.skip(more);
            }
            steps += more;
            work += more;
        }
        if steps == 0 {
            return 0;
        }
        #[cfg(debug_assertions)]
        {
            self.burst_error = self.burst_error.max(worst);
        }
        a.j += steps;
        *next = clock.tick();
        *rose = last;
        self.last_axis = i as u8;
        em.wrote_run(last, steps as usize);
        work
    }

    fn done(&self) -> bool {
        self.axes.iter().all(|a| a.j > a.n)
    }
}

/// Calls `f` with each axis whose bit is set in `mask`, lowest first.
#[inline(always)]
fn for_each_axis(mut mask: u8, mut f: impl FnMut(usize)) {
    while mask != 0 {
        f(mask.trailing_zeros() as usize);
        mask &= mask - 1;
    }
}

/// Whether `clock` is a cruise whose steps are always at least `spacing` apart (a pulse and as
/// long low) and at most one event's delay: after its first step, each of its steps needs
/// neither check ([`Current::run_alone`], [`Current::run_cruises`]).
#[inline(always)]
fn is_steady(clock: &StepClock, spacing: u64) -> bool {
    clock
        .cruise_gaps()
        .is_some_and(|(fewest, most)| fewest >= spacing.max(1) && most <= u64::from(MAX_DELTA))
}

/// The axes `0..N` in the order of their next steps' ticks (`next_of(axis)`), by insertion:
/// of two at the same tick, the lower axis first.
#[inline(always)]
fn by_next_step<const N: usize, T: Ord>(next_of: impl Fn(usize) -> Option<T>) -> [u8; N] {
    let mut order = [0u8; N];
    for k in 0..N {
        let due = next_of(k);
        let mut p = k;
        while let Some(&before) = order.get(p.wrapping_sub(1)) {
            if next_of(usize::from(before)) <= due {
                break;
            }
            if let Some(slot) = order.get_mut(p) {
                *slot = before;
            }
            p -= 1;
        }
        if let Some(slot) = order.get_mut(p) {
            *slot = k as u8;
        }
    }
    order
}

/// The lane of [`Current::run_cruises`] whose step comes first, and its tick: of two at the
/// same tick, the lower axis.
///
/// The lanes are read by constant indices, written out for the first six axes: a loop over
/// them would index the lanes by a variable, which keeps them in memory, and the Cortex-M
/// firmware's `opt-level = "z"` does not unroll loops. Axes past the sixth are in a loop.
#[inline(always)]
fn first_lane<const N: usize>(lanes: &[Lane; N]) -> (usize, u32) {
    #[inline(always)]
    fn scan<const N: usize>(lanes: &[Lane; N], k: usize, first: &mut (usize, u32)) {
        if let Some(lane) = lanes.get(k)
            && lane.next() < first.1
        {
            *first = (k, lane.next());
        }
    }
    let mut first = (0, u32::MAX);
    scan(lanes, 0, &mut first);
    scan(lanes, 1, &mut first);
    scan(lanes, 2, &mut first);
    scan(lanes, 3, &mut first);
    scan(lanes, 4, &mut first);
    scan(lanes, 5, &mut first);
    for k in 6..N {
        scan(lanes, k, &mut first);
    }
    first
}

/// Lane `i` of [`Current::run_cruises`] took its step at tick `t`: it moves on to its next
/// one, and the step is counted. As in [`first_lane`], by constant indices.
///
/// The steps are counted in `taken` on RISC-V, where a count in each lane kept the lanes in
/// memory, and in the lanes on the Cortex-M (`SplitLane`), where each count kept apart was
/// stored twice ([`lane_taken`] reads them).
#[inline(always)]
fn step_lane<const N: usize>(lanes: &mut [Lane; N], taken: &mut [u32; N], i: usize, t: u32) {
    #[inline(always)]
    fn step_if<const N: usize>(
        lanes: &mut [Lane; N],
        taken: &mut [u32; N],
        k: usize,
        i: usize,
        t: u32,
    ) {
        if k != i {
            return;
        }
        if let Some(lane) = lanes.get_mut(k) {
            lane.step(t);
        }
        #[cfg(not(target_arch = "arm"))]
        if let Some(n) = taken.get_mut(k) {
            *n += 1;
        }
        #[cfg(target_arch = "arm")]
        let _ = taken;
    }
    step_if(lanes, taken, 0, i, t);
    step_if(lanes, taken, 1, i, t);
    step_if(lanes, taken, 2, i, t);
    step_if(lanes, taken, 3, i, t);
    step_if(lanes, taken, 4, i, t);
    step_if(lanes, taken, 5, i, t);
    for k in 6..N {
        step_if(lanes, taken, k, i, t);
    }
}

/// Where a [`Current::run_cruises`] walk stops next: at `hard`, or at the end of an axis
/// still `walking` (a mask), whichever is sooner.
fn next_stop<const N: usize>(hard: u32, ends: &[u32; N], walking: u8) -> u32 {
    let mut stop = hard;
    for (k, &end) in ends.iter().enumerate() {
        if walking & (1 << k) != 0 {
            stop = stop.min(end);
        }
    }
    stop
}

/// Write the rising edge of axis `i` at tick `t` of a [`Current::run_cruises`] walk, whose
/// last step is at `last` ticks from its origin: a new event, or at the tick of an event this
/// walk wrote (two axes stepping together, as on a diagonal) the edge joins it. At the
/// origin's tick (`last` 0: the walk's steps are all past it), the event is the last one
/// before the walk, the general path's to join. `false` when it cannot be written.
#[inline(always)]
fn write_step<const N: usize, const Q: usize>(
    tx: &mut Producer<'_, N, Q>,
    last: u32,
    i: usize,
    t: u32,
) -> bool {
    let delta = t.wrapping_sub(last);
    debug_assert!(delta <= MAX_DELTA);
    let edge = 1u8 << i;
    if delta == 0 {
        last > 0
            && tx.amend_last(&Event {
                rise: edge,
                ..Event::default()
            })
    } else {
        tx.write_rise(delta, edge)
    }
}

/// The highest axis of [`Current::run_cruises`] whose last step is at tick `last`: a lane
/// still `walking` whose previous step is there, or one done whose end (`ends`) is. Lanes
/// that took no step find no tick of theirs there (the walk's steps are all past its origin,
/// and `last` is a step of the walk). As in [`first_lane`], by constant indices.
#[inline(always)]
fn last_stepped<const N: usize>(lanes: &[Lane; N], ends: &[u32; N], walking: u8, last: u32) -> u8 {
    #[inline(always)]
    fn check<const N: usize>(
        (lanes, ends, walking, last): (&[Lane; N], &[u32; N], u8, u32),
        k: usize,
        found: &mut u8,
    ) {
        let at = if walking & (1 << k) != 0 {
            lanes.get(k).map(|lane| lane.previous())
        } else {
            ends.get(k).copied()
        };
        if at == Some(last) {
            *found = k as u8;
        }
    }
    let args = (lanes, ends, walking, last);
    let mut found = NO_AXIS;
    check(args, 0, &mut found);
    check(args, 1, &mut found);
    check(args, 2, &mut found);
    check(args, 3, &mut found);
    check(args, 4, &mut found);
    check(args, 5, &mut found);
    for k in 6..N {
        check(args, k, &mut found);
    }
    found
}

/// Lane `i` of [`Current::run_cruises`] has taken its last step in the block: it is done
/// (its count of steps stays). As in [`first_lane`], by constant indices.
#[inline(always)]
fn end_lane<const N: usize>(lanes: &mut [Lane; N], i: usize) {
    #[inline(always)]
    fn end_if<const N: usize>(lanes: &mut [Lane; N], k: usize, i: usize) {
        if k == i
            && let Some(lane) = lanes.get_mut(k)
        {
            lane.end();
        }
    }
    end_if(lanes, 0, i);
    end_if(lanes, 1, i);
    end_if(lanes, 2, i);
    end_if(lanes, 3, i);
    end_if(lanes, 4, i);
    end_if(lanes, 5, i);
    for k in 6..N {
        end_if(lanes, k, i);
    }
}

/// The steps lane `k` of [`Current::run_cruises`] took (see [`step_lane`]).
#[inline(always)]
fn lane_taken<const N: usize>(lanes: &[Lane; N], taken: &[u32; N], k: usize) -> u32 {
    #[cfg(target_arch = "arm")]
    {
        let _ = taken;
        lanes.get(k).map_or(0, |lane| lane.taken)
    }
    #[cfg(not(target_arch = "arm"))]
    {
        let _ = lanes;
        taken.get(k).copied().unwrap_or(0)
    }
}

/// The first axis of `order` has stepped and its next step is at `tick`: it moves down past
/// the axes due sooner (one comparison when it stays first).
#[inline(always)]
fn sink_first<const N: usize, T: Ord>(
    order: &mut [u8; N],
    tick: T,
    next_of: impl Fn(usize) -> Option<T>,
) {
    let first = order.first().copied().unwrap_or(0);
    let mut p = 0;
    while let Some(&k) = order.get(p + 1) {
        if next_of(usize::from(k)).is_none_or(|due| due >= tick) {
            break;
        }
        if let Some(slot) = order.get_mut(p) {
            *slot = k;
        }
        p += 1;
    }
    if let Some(slot) = order.get_mut(p) {
        *slot = first;
    }
}

/// Builds the event stream: places rising edges and direction changes, and writes events with
/// their deltas into the queue, where they stay unpublished (and the last one can still take
/// an edge at the same tick) until [`Emitter::publish`].
struct Emitter<const N: usize> {
    pulse: u64,
    dir_setup: u64,
    /// The tick of the last event written: no event goes before it.
    last_tick: u64,
    /// The last event written is not published yet: an edge at its tick joins it.
    amendable: bool,
    /// The last event written ends the motion.
    last_rest: bool,
    /// Ticks of all events written (wrapping), against the interrupt's consumed ticks.
    pushed_ticks: u32,
    /// When each axis last rose.
    rose_at: [u64; N],
    /// Queue slots known to be free (at least): writes need no check of their own.
    room: usize,
    dir_neg: u8,
    dir_known: u8,
}

impl<const N: usize> Emitter<N> {
    /// The tick at or after which new events go.
    #[inline(always)]
    fn cursor(&self) -> u64 {
        self.last_tick
    }

    /// Ticks of the events written that are still ahead: those the interrupt has not consumed
    /// (`consumed`, its count of ticks), less the `spent` ticks since its last event.
    #[inline(always)]
    fn ahead(&self, consumed: u32, spent: u32) -> u32 {
        let pending = self.pushed_ticks.wrapping_sub(consumed);
        pending - spent.min(pending)
    }

    /// The fast path ([`Current::burst`]) wrote `written` rising edges into the queue, the
    /// last at tick `last`: count their ticks and room, and let an edge at `last` join them.
    #[inline(always)]
    fn wrote_run(&mut self, last: u64, written: usize) {
        self.pushed_ticks = self
            .pushed_ticks
            .wrapping_add(last.wrapping_sub(self.last_tick) as u32);
        self.last_tick = last;
        self.room = self.room.saturating_sub(written);
        self.amendable = true;
        self.last_rest = false;
    }

    /// The rising edge of axis `i` (direction `neg`) at tick `t`, or as soon after it as
    /// the axis's last pulse and a direction change allow. Returns the tick used.
    #[inline(always)]
    fn rise<const Q: usize>(
        &mut self,
        tx: &mut Producer<'_, N, Q>,
        i: usize,
        neg: u8,
        t: u64,
    ) -> u64 {
        let bit = 1u8 << i;
        let rose = self.rose_at.get(i).copied().unwrap_or(0);
        // A full pulse, then as long low, since the axis's last rising edge.
        let mut t = t.max(self.last_tick).max(rose + 2 * self.pulse);
        if self.dir_known & bit == 0 || self.dir_neg & bit != neg {
            t = self.change_direction(tx, bit, neg, rose, t);
        }
        self.put(
            tx,
            t,
            Event {
                rise: bit,
                ..Event::default()
            },
        );
        if let Some(r) = self.rose_at.get_mut(i) {
            *r = t;
        }
        t
    }

    /// Write the direction `neg` of axis `bit`, which last rose at `rose`, before its rising
    /// edge due at `t`: after that pulse's end and `dir_setup` before the edge, which moves
    /// later when there is not room. Returns the edge's tick.
    #[cold]
    #[inline(never)]
    fn change_direction<const Q: usize>(
        &mut self,
        tx: &mut Producer<'_, N, Q>,
        bit: u8,
        neg: u8,
        rose: u64,
        t: u64,
    ) -> u64 {
        let td = t
            .saturating_sub(self.dir_setup)
            .max(self.last_tick)
            .max(rose + self.pulse);
        self.put(
            tx,
            td,
            Event {
                dir_set: bit,
                dir_neg: neg,
                ..Event::default()
            },
        );
        self.dir_neg = (self.dir_neg & !bit) | neg;
        self.dir_known |= bit;
        t.max(td + self.dir_setup)
    }

    /// End of motion: the last event marked as rest (the interrupt ends the last pulses).
    fn finish_rest<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>) {
        if !self.last_rest {
            let tick = self.last_tick;
            self.put(
                tx,
                tick,
                Event {
                    rest: true,
                    ..Event::default()
                },
            );
        }
    }

    /// Put `ev` at `tick` (never before the last event): into the last event when it is at
    /// that tick, not published and not the end of a motion, else as a new one.
    #[inline(always)]
    fn put<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>, tick: u64, ev: Event) {
        let tick = tick.max(self.last_tick);
        // An event that ends the motion takes nothing more: motion after it is a new event.
        if self.amendable && !self.last_rest && tick == self.last_tick {
            tx.amend_last(&ev);
        } else {
            let mut delta = tick - self.last_tick;
            if delta > u64::from(MAX_DELTA) {
                delta = self.split_wait(tx, delta);
            }
            self.write(
                tx,
                Event {
                    delta: delta as u32,
                    ..ev
                },
            );
            self.pushed_ticks = self.pushed_ticks.wrapping_add(delta as u32);
            self.last_tick = tick;
            self.amendable = true;
        }
        self.last_rest = ev.rest;
    }

    /// Make every event written visible to the interrupt.
    #[inline(always)]
    fn publish<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>) {
        tx.publish();
        self.amendable = false;
    }

    /// Write `ev` into a slot counted in `room`.
    #[inline(always)]
    fn write<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>, ev: Event) {
        if self.room == 0 {
            self.room = tx.free();
        }
        if tx.write(&ev) {
            self.room = self.room.saturating_sub(1);
        }
    }

    /// A wait longer than one event carries: empty events of [`MAX_DELTA`] first. Returns
    /// what is left.
    #[cold]
    fn split_wait<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>, mut delta: u64) -> u64 {
        while delta > u64::from(MAX_DELTA) {
            self.write(
                tx,
                Event {
                    delta: MAX_DELTA,
                    ..Event::default()
                },
            );
            delta -= u64::from(MAX_DELTA);
            self.pushed_ticks = self.pushed_ticks.wrapping_add(MAX_DELTA);
        }
        delta
    }
}

/// Where preparation stands after a [`Prep::fill`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Fill {
    /// More to prepare: call again after the interrupt has consumed some.
    Pending,
    /// Everything planned is in the queue and ends at rest.
    Drained,
    /// A feed hold has come to rest; nothing more until it is released.
    Held,
    /// The call did its share of work ([`WORK_PER_FILL`]) before the queue had its lead:
    /// call again at once.
    More,
}

pub(crate) struct Prep<const N: usize> {
    ticks_per_s: f64,
    em: Emitter<N>,
    /// The block in preparation, when `loaded`: kept in place between blocks, so that loading
    /// one writes its fields instead of moving a whole new `Current` in.
    cur: Current<N>,
    loaded: bool,
    dwell_left: u64,
    t_plan: f64,
    v_carry: f64,
    hold: bool,
    held: bool,
    line: u32,
    /// The block in preparation is a rapid.
    rapid: bool,
    /// The spindle speed of the block in preparation, rpm.
    spindle_rpm: u32,
    /// Ticks of motion queued ahead of the time of the last [`Prep::fill`], after it.
    queued_ticks: u32,
    /// Topping the queue up to its lead: set when it holds less than half of the lead (or
    /// nothing has started), cleared once it holds the lead or is full.
    refilling: bool,
    /// The largest distance of a step's tick from its exact time, ticks (debug builds).
    #[cfg(debug_assertions)]
    worst_error: f64,
}

impl<const N: usize> Prep<N> {
    pub(crate) fn new(tick_hz: u32, pulse_ticks: u32, dir_setup_ticks: u32) -> Self {
        Self {
            ticks_per_s: f64::from(tick_hz),
            em: Emitter {
                pulse: u64::from(pulse_ticks.max(1)),
                dir_setup: u64::from(dir_setup_ticks),
                last_tick: 0,
                amendable: false,
                last_rest: true,
                pushed_ticks: 0,
                rose_at: [0; N],
                room: 0,
                dir_neg: 0,
                dir_known: 0,
            },
            cur: Current::unloaded(),
            loaded: false,
            dwell_left: 0,
            t_plan: 0.0,
            v_carry: 0.0,
            hold: false,
            held: false,
            line: 0,
            rapid: false,
            spindle_rpm: 0,
            queued_ticks: 0,
            refilling: true,
            #[cfg(debug_assertions)]
            worst_error: 0.0,
        }
    }

    /// Forget the block in progress and everything not yet pushed (after a flush).
    pub(crate) fn reset(&mut self, consumed_ticks: u32) {
        let em = &mut self.em;
        em.pushed_ticks = consumed_ticks;
        em.amendable = false;
        em.dir_known = 0;
        em.last_rest = true;
        self.loaded = false;
        self.dwell_left = 0;
        self.v_carry = 0.0;
        self.hold = false;
        self.held = false;
        self.refilling = true;
        // Continue the timeline after everything pushed.
        self.t_plan = at_least(self.t_plan, self.em.last_tick as f64);
    }

    /// Ask for (or release) a feed hold.
    pub(crate) fn set_hold(&mut self, hold: bool) {
        self.hold = hold;
        if !hold {
            self.held = false;
        }
    }

    /// A realtime override changed the nominal speed of the block in preparation (squared):
    /// re-plan the rest of it from the last prepared step.
    pub(crate) fn set_nominal(&mut self, nominal_sqr: f32) {
        if self.loaded {
            let cur = &mut self.cur;
            cur.nominal = speed_of(nominal_sqr);
            cur.nominal_sqr = nominal_sqr;
            // Never equal to the planner's exit: the next fill re-anchors.
            cur.exit_used = f32::NAN;
        }
    }

    /// The motion in preparation: its speed along the path at the last prepared step (mm/s,
    /// 0 at rest: the speed now, `queue_lead_ms` ahead), that speed as a fraction of the
    /// block's nominal speed, whether the block is a rapid, and its spindle speed (rpm).
    pub(crate) fn motion(&self) -> Option<(f64, f64, bool, u32)> {
        let cur = &self.cur;
        let v = if self.loaded {
            cur.profile.speed_at(cur.last_s() - cur.s_anchor)
        } else if self.v_carry > 0.0 {
            // Between two blocks (a top-up ends with a block): the last prepared step is the
            // last block's last, at its exit speed; the block it belongs to is still `cur`.
            self.v_carry
        } else {
            return None;
        };
        let fraction = if cur.nominal > 0.0 {
            v / cur.nominal
        } else {
            0.0
        };
        Some((v, fraction, self.rapid, self.spindle_rpm))
    }

    /// Whether a hold has come to rest in the prepared stream.
    pub(crate) fn is_held(&self) -> bool {
        self.held
    }

    /// Whether a block is being prepared.
    pub(crate) fn is_busy(&self) -> bool {
        self.loaded || self.dwell_left > 0
    }

    /// The source line of the block being prepared, or of the last one.
    pub(crate) fn line(&self) -> u32 {
        self.line
    }

    /// The largest distance of an emitted step's tick from its exact time on the planned
    /// profile so far, in ticks (steps moved by a direction change or a pulse not counted).
    #[cfg(debug_assertions)]
    pub(crate) fn worst_error_ticks(&self) -> f64 {
        self.worst_error
    }

    /// Ticks of motion the queue holds ahead of `now` (the interrupt `running`).
    #[inline(always)]
    pub(crate) fn ahead_of<const Q: usize>(
        &self,
        tx: &Producer<'_, N, Q>,
        now: Instant,
        running: bool,
    ) -> u32 {
        let q = tx.shared();
        let consumed = q.consumed_ticks.load(Ordering::Relaxed);
        // Time already spent after the last consumed event (its successors are due sooner).
        let spent = if running {
            let last = Instant::from_ticks(q.last_event_at.load(Ordering::Relaxed));
            now.saturating_duration_since(last).ticks()
        } else {
            0
        };
        self.em.ahead(consumed, spent)
    }

    /// Whether the queue, holding `ahead` ticks, needs no top-up now; if so, records what it
    /// holds. Topped up to the lead, the queue runs down to half of it before the next top-up:
    /// a call in between prepares nothing and costs little, and each top-up prepares many
    /// steps for one call's set-up. The queue never holds more than five quarters of the lead
    /// (a top-up runs on to the end of a block that ends within a quarter of the lead after
    /// it, [`Current::horizon_to_end`]), so a feed hold still starts decelerating within
    /// that, and the board polls again within half of what it holds, so it never runs dry.
    #[inline(always)]
    pub(crate) fn holds_enough(&mut self, ahead: u32, lead_ticks: u32, running: bool) -> bool {
        let enough = !self.refilling && running && ahead >= lead_ticks / 2;
        if enough {
            self.queued_ticks = ahead;
        }
        enough
    }

    /// Prepare events until `lead_ticks` of motion are queued ahead of `now`, the queue is
    /// full or the plan is exhausted. `running` tells whether the interrupt side is executing
    /// (when it is idle, nothing queued has started yet).
    pub(crate) fn fill<const B: usize, const Q: usize>(
        &mut self,
        planner: &mut Planner<N, B>,
        tx: &mut Producer<'_, N, Q>,
        lead_ticks: u32,
        now: Instant,
        running: bool,
    ) -> Fill {
        let ahead = self.ahead_of(tx, now, running);
        if self.holds_enough(ahead, lead_ticks, running) {
            return Fill::Pending;
        }
        self.refilling = true;
        // Events go up to this tick: `lead_ticks` of motion ahead of now (or to the end of a
        // block that ends a little after, `Current::horizon_to_end`).
        let mut horizon = self.em.last_tick + u64::from(lead_ticks.saturating_sub(ahead));
        let tps = self.ticks_per_s;
        let mut work = self.check_plan(planner);
        self.em.room = tx.free();
        let result = loop {
            if work >= WORK_PER_FILL {
                break Fill::More;
            }
            // A step needs the room of `SLOTS_PER_STEP + 2` slots, and a run of steps
            // ([`Current::burst`]) one more: at less, the room is counted again, and the queue
            // is full if it has no more.
            if self.em.room <= SLOTS_PER_STEP + 2 {
                self.em.room = tx.free();
                if self.em.room <= SLOTS_PER_STEP + 2 {
                    // Full before the lead (fast steps): topped up all the same.
                    self.refilling = false;
                    break Fill::Pending;
                }
            }
            if self.em.cursor() >= horizon {
                self.refilling = false;
                break Fill::Pending;
            }
            if self.dwell_left > 0 {
                let d = self.dwell_left.min(u64::from(MAX_DELTA));
                self.dwell_left -= d;
                let t = self.em.cursor() + d;
                self.em.put(tx, t, Event::default());
                self.t_plan = t as f64;
                continue;
            }
            if !self.loaded {
                // Read in the planner: a copy of the block would cost more than its reading.
                let Some(block) = planner.tail() else {
                    self.em.finish_rest(tx);
                    self.v_carry = 0.0;
                    self.t_plan = at_least(self.t_plan, self.em.last_tick as f64);
                    break Fill::Drained;
                };
                match block.kind {
                    BlockKind::Dwell(ms) => {
                        self.dwell_left = libm::round(f64::from(ms) * tps / 1000.0) as u64;
                        self.t_plan = at_least(self.t_plan, self.em.cursor() as f64);
                        self.line = block.line;
                        planner.retire_tail();
                    }
                    BlockKind::Move => {
                        self.load(block, planner.tail_exit_sqr());
                        work += if self.cur.profile.is_cruise() {
                            CRUISE_PROFILE_WORK
                        } else {
                            PROFILE_WORK
                        };
                        horizon = self.cur.horizon_to_end(horizon, lead_ticks);
                    }
                }
                continue;
            }
            let cur = &mut self.cur;
            if cur.unset != 0 {
                let i = cur.unset.trailing_zeros() as usize;
                cur.unset &= !(1 << i);
                work += cur.enter_phase(i, tps);
                continue;
            }
            #[cfg(debug_assertions)]
            {
                cur.burst_error = 0.0;
            }
            // The axis whose step comes first. Past the horizon (or none: the block is done),
            // a run of steps would find nothing to do.
            let (i, tick) = cur.first_step();
            if tick < horizon {
                let burst = cur.burst(
                    &mut self.em,
                    tx,
                    horizon,
                    WORK_PER_FILL - work,
                    tps,
                    (i, tick),
                );
                if burst > 0 {
                    #[cfg(debug_assertions)]
                    {
                        self.worst_error = self.worst_error.max(cur.burst_error);
                    }
                    work += burst;
                    continue;
                }
            }
            // A step past the horizon waits for the next top-up while the queue holds half the
            // lead before it (that top-up comes before the queue runs down to it): a top-up ends
            // at the horizon, not with one step past it.
            if tick != u64::MAX
                && tick >= horizon
                && self.em.cursor() + u64::from(lead_ticks / 2) >= horizon
            {
                self.refilling = false;
                break Fill::Pending;
            }
            if tick != u64::MAX {
                let _t = self.em.rise(tx, i, cur.neg & (1 << i), tick);
                #[cfg(debug_assertions)]
                if _t == tick {
                    let exact = cur.exact_time(i, tps).unwrap_or(f64::INFINITY);
                    self.worst_error = self.worst_error.max((tick as f64 - exact).abs());
                }
                work += cur.advance(i, tps);
            } else if cur.done() {
                // Block done: the next one starts where this profile ends.
                self.t_plan = cur.t_end;
                self.v_carry = cur.profile.exit_speed();
                self.loaded = false;
                planner.retire_tail();
                // A top-up that ends a block within a quarter of the lead before its horizon
                // ends there: the next top-up starts with the next block (see
                // `Current::horizon_to_end`).
                if self.em.cursor() + u64::from(lead_ticks / 4) >= horizon {
                    self.refilling = false;
                    break Fill::Pending;
                }
            } else {
                // A hold came to rest inside the block: anchor there, at zero speed.
                cur.s_anchor += cur.profile.length();
                cur.t_anchor = cur.t_end;
                cur.last_axis = NO_AXIS;
                cur.set_profile(Profile::hold(0.0, 0.0, cur.accel), tps);
                self.t_plan = cur.t_anchor;
                self.held = true;
                self.em.finish_rest(tx);
                self.v_carry = 0.0;
                break Fill::Held;
            }
        };
        self.em.publish(tx);
        self.queued_ticks = self.ahead_of(tx, now, running);
        result
    }

    /// Record that the queue holds `ticks` of motion (at least), as a poll that reads no more
    /// of it than that finds.
    #[inline(always)]
    pub(crate) fn note_queued(&mut self, ticks: u32) {
        self.queued_ticks = ticks;
    }

    /// Ticks of motion the queue held ahead of the time of the last [`Prep::fill`], after it:
    /// less than the lead when the queue filled up first (fast steps on several axes).
    pub(crate) fn queued_ticks(&self) -> u32 {
        self.queued_ticks
    }

    /// Re-plan the block in preparation if its exit speed or the hold changed since it was
    /// planned. Returns the work it took.
    fn check_plan<const B: usize>(&mut self, planner: &Planner<N, B>) -> u32 {
        let exit_sqr = planner.tail_exit_sqr();
        let hold = self.hold;
        let cur = &mut self.cur;
        if self.loaded && (cur.exit_used != exit_sqr || cur.hold_used != hold) {
            cur.reanchor(exit_sqr, hold, self.ticks_per_s);
            PROFILE_WORK
        } else {
            0
        }
    }

    /// Start preparing `block`, which ends at `exit_sqr` (its exit speed squared): its
    /// fields written into the `Current` kept in place. Once a block: out of `fill`'s loop.
    #[inline(never)]
    fn load(&mut self, block: &Block<N>, exit_sqr: f32) {
        let mm = f64::from(block.mm);
        let cur = &mut self.cur;
        let mut neg = 0u8;
        let mut moving = 0u8;
        for (i, (a, s)) in cur.axes.iter_mut().zip(block.steps.iter()).enumerate() {
            if *s < 0 {
                neg |= 1 << i;
            }
            let n = s.unsigned_abs();
            *a = AxisSteps {
                n,
                j: 1,
                phase: 0,
                phase_last: 0,
                step_mm: 0.0,
                per_mm: 0.0,
                timing: Timing::Exact,
            };
            if n > 0 {
                moving |= 1 << i;
            }
        }
        // The moving axes' step lengths, in a loop of their own: in the one above, the
        // divisions would be worked out for the axes that stay too (a select, not a branch,
        // to the compiler), at a hundred instructions each in software double precision.
        for_each_axis(moving, |i| {
            if let Some(a) = cur.axes.get_mut(i) {
                a.step_mm = mm / f64::from(a.n);
            }
        });
        cur.next_tick = [u64::MAX; N];
        cur.neg = neg;
        cur.mm = mm;
        cur.accel = f64::from(block.accel);
        cur.ticks_per_speed = 0.0;
        cur.nominal = speed_of(block.nominal_sqr);
        cur.nominal_sqr = block.nominal_sqr;
        cur.s_anchor = 0.0;
        cur.t_anchor = self.t_plan;
        cur.last_axis = NO_AXIS;
        // One axis alone: a single bit.
        cur.only_axis = (moving != 0 && moving & moving.wrapping_sub(1) == 0)
            .then(|| moving.trailing_zeros() as usize);
        cur.exit_used = exit_sqr;
        cur.hold_used = self.hold;
        #[cfg(debug_assertions)]
        {
            cur.burst_error = 0.0;
        }
        cur.set_profile(
            cur.profile_for(self.v_carry, exit_sqr, self.hold),
            self.ticks_per_s,
        );
        cur.unset = moving;
        self.loaded = true;
        self.line = block.line;
        self.rapid = block.speed.rapid;
        self.spindle_rpm = block.spindle_rpm;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::queue::{Consumer, Raw, StepQueue};
    use crate::testing::xorshift;
    extern crate std;
    use std::vec::Vec;

    /// Three axes cruising from `origin` with random intervals, first steps and lengths.
    fn cruises(seed: &mut u64, origin: u64) -> Current<3> {
        let mut cur = Current::<3>::unloaded();
        for (a, next) in cur.axes.iter_mut().zip(cur.next_tick.iter_mut()) {
            let interval = 40.0 + (xorshift(seed) % 4_000) as f64 / 7.0;
            let first = (xorshift(seed) % 200) as f64 + (xorshift(seed) % 1000) as f64 / 997.0;
            let n = 1 + (xorshift(seed) % 300) as u32;
            let Some(clock) = StepClock::cruise(origin, first + 1.0, interval, n) else {
                panic!("a cruise in range");
            };
            // Half the cruises end the axis's steps in the block; the others are followed by
            // another phase.
            let phase_last = if xorshift(seed).is_multiple_of(2) {
                n
            } else {
                1 + (xorshift(seed) % u64::from(n)) as u32
            };
            *a = AxisSteps {
                n,
                j: 1,
                phase: 1,
                phase_last,
                step_mm: 0.0125,
                per_mm: 80.0,
                timing: Timing::Clock(clock),
            };
            *next = clock.tick();
        }
        // Some axes start at the same tick (a diagonal's steps share their events).
        if xorshift(seed).is_multiple_of(2) {
            let (first, rest) = cur.axes.split_at_mut(1);
            if let (Some(a), Some(b)) = (first.first(), rest.first_mut()) {
                b.timing = a.timing;
                b.n = a.n;
                b.phase_last = a.phase_last;
            }
            cur.next_tick[1] = cur.next_tick[0];
        }
        // A third of them have an axis with no step left: two axes walk
        // ([`Current::walk_pair`]).
        if xorshift(seed).is_multiple_of(3) {
            let k = (xorshift(seed) % 3) as usize;
            if let (Some(a), Some(next)) = (cur.axes.get_mut(k), cur.next_tick.get_mut(k)) {
                a.j = a.n + 1;
                a.phase = PHASES;
                *next = u64::MAX;
            }
        }
        cur
    }

    fn emitter(origin: u64) -> Emitter<3> {
        Emitter {
            pulse: 8,
            dir_setup: 8,
            last_tick: origin,
            amendable: false,
            last_rest: false,
            pushed_ticks: 0,
            rose_at: [0; 3],
            room: 256,
            dir_neg: 0,
            dir_known: 0b111,
        }
    }

    /// The steps `walk` takes and the events it writes into a fresh queue (at most its 1,024
    /// slots), from the tick before the axes' first step.
    fn events_of(
        cur: &mut Current<3>,
        walk: impl FnOnce(&mut Current<3>, &mut Emitter<3>, &mut Producer<'_, 3, 1024>) -> Option<u32>,
    ) -> (Option<u32>, [Raw; 1024]) {
        let q = StepQueue::<3, 1024>::new();
        let mut tx = Producer::new(&q);
        let mut em = emitter(cur_origin(cur));
        let steps = walk(cur, &mut em, &mut tx);
        tx.publish();
        let mut rx = Consumer::new(&q);
        let mut events = [Raw::default(); 1024];
        for slot in events.iter_mut() {
            let Some(ev) = rx.peek() else {
                break;
            };
            *slot = ev;
            rx.advance();
        }
        (steps, events)
    }

    /// The steps the walk should take from `cur` at most `max_steps` of them: each axis's
    /// clock ticks before the horizon, within one event's delay of `origin` and before the
    /// last step of each phase that the axis has more steps after, in the order of their ticks
    /// (of two at the same tick, the lower axis first). An axis whose steps in the block end
    /// with its phase takes that last step too. Returns them as the events they make: delay
    /// and rising edges.
    fn reference(cur: &Current<3>, origin: u64, horizon: u64, max_steps: u32) -> Vec<(u32, u8)> {
        let bound = horizon.min(origin + u64::from(MAX_DELTA));
        let mut stop = bound;
        let mut steps = Vec::new();
        for (i, a) in cur.axes.iter().enumerate() {
            let Timing::Clock(mut clock) = a.timing else {
                panic!("a clock");
            };
            if a.j > a.n {
                // No step left.
                continue;
            }
            for _ in a.j..a.phase_last {
                steps.push((clock.tick(), i));
                clock.advance();
            }
            if a.phase_last == a.n {
                if clock.tick() < bound {
                    steps.push((clock.tick(), i));
                }
            } else {
                stop = stop.min(clock.tick());
            }
        }
        steps.retain(|&(tick, _)| tick < stop);
        steps.sort_unstable();
        steps.truncate(max_steps as usize);
        let mut events: Vec<(u32, u8)> = Vec::new();
        let mut last = origin;
        for (tick, i) in steps {
            match events.last_mut() {
                Some((_, rise)) if tick == last => *rise |= 1 << i,
                _ => events.push(((tick - last) as u32, 1 << i)),
            }
            last = tick;
        }
        events
    }

    #[test]
    fn the_cruises_walk_writes_each_clocks_steps_in_order() {
        let mut seed = 0x5eed_cafe_u64;
        let (mut stepped, mut together, mut ended, mut pairs) = (0, 0, 0, 0);
        for round in 0..3_000 {
            let origin = 1_000 + xorshift(&mut seed) % 1_000_000;
            let start = cruises(&mut seed, origin);
            let horizon = origin + 500 + xorshift(&mut seed) % 100_000;
            let max_steps = 1 + (xorshift(&mut seed) % 700) as u32;
            let mut cur = start;
            let (steps, written) = events_of(&mut cur, |cur, em, tx| {
                let first = cur.first_step();
                cur.run_cruises::<1024>(em, tx, horizon, max_steps, 8e6, first)
            });
            let expected = reference(&start, cur_origin(&start), horizon, max_steps);
            let edges: u32 = expected.iter().map(|(_, rise)| rise.count_ones()).sum();
            if start.axes.iter().filter(|a| a.j <= a.n).count() == 2 && edges > 1 {
                pairs += 1;
            }
            assert_eq!(steps, Some(edges), "round {round}");
            let events: Vec<(u32, u8)> = written
                .iter()
                .take_while(|ev| **ev != Raw::default())
                .inspect(|ev| assert!(!ev.rest() && ev.dir_set() == 0 && ev.dir_neg() == 0))
                .map(|ev| (ev.delta(), ev.rise()))
                .collect();
            assert_eq!(events, expected, "round {round}");
            // The last step's axis (of several at its tick, the highest, taken last).
            if let Some((_, rise)) = expected.last() {
                let highest = 7 - rise.leading_zeros() as u8;
                assert_eq!(cur.last_axis, highest, "round {round}");
            }
            // Each axis's clock moved on by the steps it took.
            for (i, (a, b)) in start.axes.iter().zip(cur.axes.iter()).enumerate() {
                let took: u32 = expected
                    .iter()
                    .map(|(_, rise)| u32::from(rise >> i & 1))
                    .sum();
                let Timing::Clock(mut clock) = a.timing else {
                    panic!("a clock");
                };
                for _ in 0..took {
                    clock.advance();
                }
                assert_eq!((b.j, b.timing), (a.j + took, Timing::Clock(clock)));
                if a.j > a.n {
                    // It had no step left, and took none.
                    assert_eq!((took, cur.next_tick.get(i)), (0, Some(&u64::MAX)));
                } else if b.j > b.n {
                    // Its last step in the block taken: the axis is done.
                    assert_eq!((b.phase, cur.next_tick.get(i)), (PHASES, Some(&u64::MAX)));
                    ended += 1;
                } else {
                    assert_eq!(cur.next_tick.get(i), Some(&clock.tick()));
                }
            }
            stepped += edges;
            together += expected
                .iter()
                .filter(|(_, rise)| rise.count_ones() > 1)
                .count();
        }
        // The walks took steps, some of them at the same tick.
        assert!(stepped > 100_000, "{stepped} steps");
        assert!(together > 100, "{together} events of several steps");
        // Axes took their last step in the block and were done, the others walking on.
        assert!(ended > 300, "{ended} axes done");
        // Walks of two axes, the third done.
        assert!(pairs > 500, "{pairs} walks of two axes");
    }

    #[test]
    fn both_lane_forms_step_as_the_clock_does() {
        let mut seed = 0x1a4e_5eed_u64;
        let mut compared = 0u32;
        for _ in 0..500 {
            let origin = 1_000 + xorshift(&mut seed) % 1_000_000;
            let start = cruises(&mut seed, origin);
            for a in &start.axes {
                let Timing::Clock(mut clock) = a.timing else {
                    panic!("a clock");
                };
                let Some((tick, gaps)) = clock.near(origin, 1 << 31) else {
                    panic!("a cruise");
                };
                let (mut packed, mut split) =
                    (PackedLane::new(tick, gaps), SplitLane::new(tick, gaps));
                // The most steps before a stop bound the steps the clock takes before it.
                let stop = tick + (xorshift(&mut seed) % 20_000) as u32;
                let mut ahead = clock;
                let mut before = 0;
                while ahead.tick() - origin < u64::from(stop) {
                    before += 1;
                    ahead.advance();
                }
                let most = packed.most_before(stop);
                assert_eq!(split.most_before(stop), most);
                assert!(
                    most >= before && most <= before + before / 4 + 1,
                    "{most} {before}"
                );
                for _ in 0..200 {
                    let at = clock.tick() - origin;
                    assert_eq!(
                        (u64::from(packed.next()), u64::from(split.next())),
                        (at, at)
                    );
                    packed.step(packed.next());
                    split.step(split.next());
                    // Each finds the tick of the step it moved on from.
                    assert_eq!(
                        (u64::from(packed.previous()), u64::from(split.previous())),
                        (at, at)
                    );
                    clock.advance();
                    compared += 1;
                }
                // The Cortex-M's form counts its steps (RISC-V's are counted beside the lanes),
                // and keeps the count once done.
                assert_eq!(split.taken, 200);
                packed.end();
                split.end();
                assert_eq!((packed.next(), split.next()), (u32::MAX, u32::MAX));
                assert_eq!(split.taken, 200);
            }
        }
        assert_eq!(compared, 500 * 3 * 200);
        // A lane with no step left is never the first.
        assert_eq!(
            (PackedLane::DONE.next(), SplitLane::DONE.next()),
            (u32::MAX, u32::MAX)
        );
    }

    /// The tick the walk from `cur` counts from: the one before the axes' first step.
    fn cur_origin(cur: &Current<3>) -> u64 {
        cur.next_tick.iter().min().copied().unwrap_or(1) - 1
    }
}
