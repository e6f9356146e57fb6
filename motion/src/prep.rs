//! Segment preparation: planned blocks → timed step events (thread side).
//!
//! For every axis of a block, step `j` (1-based, of `n` steps) sits at path position
//! `L·(j − ½)/n`, the point where the axis's ideal position crosses the half-step; its time is
//! read off the block's velocity profile in double precision and rounded to the nearest tick.
//! Every axis thus steps at its own exact time (no Bresenham grid, no jitter beyond one tick),
//! and every block emits exactly its integer step count, so positions never drift.
//!
//! The per-axis step times are merged into one time-ordered stream of events for the
//! interrupt. The falling edge of a pulse is due `min_pulse` after the rising one; it rides
//! along with the next event of another axis (one interrupt instead of two) when that keeps a
//! full low time before the axis's own next step — known exactly when it is in the same block,
//! else assumed no nearer than the three pulse widths [`crate::MachineConfig::validate_timing`]
//! guarantees at the maximum rate — and gets an event of its own otherwise. A longer high time
//! is harmless: drivers latch the rising edge. A direction change is written after the axis's
//! last falling edge and at least `dir_setup` before its next rising edge; the step is delayed
//! when there is not room (only ever at a junction where the axis reverses).

use core::sync::atomic::Ordering;

use forja_hal_abstraction::time::Instant;
use libm::sqrt;

use crate::planner::{Block, BlockKind, Planner};
use crate::profile::Profile;
use crate::queue::{Event, MAX_DELTA, Producer};

/// Free slots kept for the events one step can need (falls, direction, rise, bridges).
const SLOTS_PER_STEP: usize = 4;

#[derive(Debug, Clone, Copy)]
struct Open {
    tick: u64,
    ev: Event,
}

/// The block being prepared.
#[derive(Debug, Clone, Copy)]
struct Current<const N: usize> {
    n: [u32; N],
    neg: u8,
    next_j: [u32; N],
    /// Exact time (ticks) of the next step of each axis; infinity when none.
    next_t: [f64; N],
    /// The same rounded to the tick it is emitted at; `u64::MAX` when none.
    next_tick: [u64; N],
    mm: f64,
    accel: f64,
    nominal: f64,
    s_anchor: f64,
    t_anchor: f64,
    last_s: f64,
    last_t: f64,
    profile: Profile,
    exit_used: f32,
    hold_used: bool,
    /// Path length of one step of each axis (0 when it has none).
    step_mm: [f64; N],
    /// The steps of each axis inside the profile's constant-speed phase, timed by a line.
    cruise: [Cruise; N],
}

/// Steps `first..=last` of one axis fall inside the constant-speed phase of the profile: step
/// `j` is due at `base + j·interval` ticks, one multiplication and one addition instead of
/// the profile's division. The range stays two steps clear of the phase's ends, where the
/// profile decides.
#[derive(Debug, Clone, Copy, Default)]
struct Cruise {
    first: u32,
    last: u32,
    base: f64,
    interval: f64,
}

impl<const N: usize> Current<N> {
    fn profile_for(&self, v0: f64, exit_sqr: f32, hold: bool) -> Profile {
        let rest = self.mm - self.s_anchor;
        if hold {
            Profile::hold(rest, v0, self.accel)
        } else {
            Profile::plan(
                rest,
                v0,
                self.nominal,
                sqrt(f64::from(exit_sqr)),
                self.accel,
            )
        }
    }

    /// Find each axis's steps in the constant-speed phase of the current profile.
    fn plan_cruise(&mut self, ticks_per_s: f64) {
        let phase = self.profile.cruise();
        for ((c, &step_mm), &n) in self
            .cruise
            .iter_mut()
            .zip(self.step_mm.iter())
            .zip(self.n.iter())
        {
            *c = Cruise::default();
            let Some((start, end, t_start, v)) = phase else {
                continue;
            };
            if step_mm <= 0.0 {
                continue;
            }
            // Step j is at x = step_mm·(j − ½) − s_anchor along the profile.
            let from = (start + self.s_anchor) / step_mm + 0.5;
            let to = (end + self.s_anchor) / step_mm + 0.5;
            if !(from.is_finite() && to.is_finite()) || to - from < 8.0 {
                continue;
            }
            let first = libm::floor(from) + 2.0;
            let last = (libm::ceil(to) - 2.0).min(f64::from(n));
            if first < 1.0 || last < first {
                continue;
            }
            let interval = ticks_per_s * step_mm / v;
            *c = Cruise {
                first: first as u32,
                last: last as u32,
                base: self.t_anchor
                    + ticks_per_s * (t_start + (-0.5 * step_mm - self.s_anchor - start) / v),
                interval,
            };
        }
    }

    /// Re-plan the rest of the block from the last prepared step.
    fn reanchor(&mut self, exit_sqr: f32, hold: bool, ticks_per_s: f64) {
        let v = self.profile.speed_at(self.last_s - self.s_anchor);
        self.s_anchor = self.last_s;
        self.t_anchor = self.last_t;
        self.exit_used = exit_sqr;
        self.hold_used = hold;
        self.profile = self.profile_for(v, exit_sqr, hold);
        self.plan_cruise(ticks_per_s);
        for i in 0..N {
            self.refresh(i, ticks_per_s);
        }
    }

    /// The exact time (ticks) of the next step of axis `i`, or infinity.
    fn refresh(&mut self, i: usize, ticks_per_s: f64) {
        let (Some(&j), Some(&n)) = (self.next_j.get(i), self.n.get(i)) else {
            return;
        };
        let cruise = self.cruise.get(i).copied().unwrap_or_default();
        let t = if j > n {
            f64::INFINITY
        } else if cruise.first <= j && j <= cruise.last {
            cruise.base + f64::from(j) * cruise.interval
        } else {
            let step_mm = self.step_mm.get(i).copied().unwrap_or(0.0);
            let s = step_mm * (f64::from(j) - 0.5);
            match self.profile.time_at(s - self.s_anchor) {
                Some(dt) => self.t_anchor + dt * ticks_per_s,
                None => f64::INFINITY,
            }
        };
        if let (Some(x), Some(k)) = (self.next_t.get_mut(i), self.next_tick.get_mut(i)) {
            *x = t;
            *k = if t.is_finite() {
                libm::round(t) as u64
            } else {
                u64::MAX
            };
        }
    }

    /// Axis `i` has stepped at exact time `t`.
    fn advance(&mut self, i: usize, t: f64, ticks_per_s: f64) {
        let (Some(j), Some(&step_mm)) = (self.next_j.get_mut(i), self.step_mm.get(i)) else {
            return;
        };
        self.last_s = step_mm * (f64::from(*j) - 0.5);
        self.last_t = t;
        *j += 1;
        self.refresh(i, ticks_per_s);
    }

    fn done(&self) -> bool {
        self.next_j.iter().zip(self.n.iter()).all(|(j, n)| j > n)
    }
}

/// Builds the event stream: merges edges at equal ticks, places falling edges and direction
/// changes, and pushes events with their deltas.
struct Emitter<const N: usize> {
    pulse: u64,
    dir_setup: u64,
    open: Option<Open>,
    last_pushed: u64,
    last_pushed_rest: bool,
    pushed_ticks: u32,
    /// When each pending fall is due.
    fall_at: [u64; N],
    /// When each axis's last fall was emitted.
    fell_at: [u64; N],
    falls: u8,
    dir_neg: u8,
    dir_known: u8,
}

impl<const N: usize> Emitter<N> {
    /// The tick at or after which new events go.
    fn cursor(&self) -> u64 {
        self.open.map_or(self.last_pushed, |o| o.tick)
    }

    /// The rising edge of axis `i` (direction `neg`) at tick `t`; `next_rise` holds the next
    /// step ticks of the block's axes. Returns the tick used.
    fn rise<const Q: usize>(
        &mut self,
        tx: &mut Producer<'_, N, Q>,
        i: usize,
        neg: u8,
        t: u64,
        next_rise: &[u64; N],
    ) -> u64 {
        let bit = 1u8 << i;
        let dir_change = self.dir_known & bit == 0 || self.dir_neg & bit != neg;
        let fell = self.fell_at.get(i).copied().unwrap_or(0);
        let mut t = t.max(self.cursor()).max(fell + self.pulse);
        // This axis's own pulse ends first, a full low time before the new one.
        if self.falls & bit != 0 {
            let f = self.fall_at.get(i).copied().unwrap_or(0);
            let at = self.fall(tx, bit, f);
            t = t.max(at + self.pulse);
        }
        if dir_change {
            // Other pulses end on their own before a direction change (rare: block ends).
            self.flush_falls(tx, t);
            let td = t.saturating_sub(self.dir_setup).max(self.cursor());
            self.add(
                tx,
                td,
                Event {
                    dir_set: bit,
                    dir_neg: neg,
                    ..Event::default()
                },
            );
            t = t.max(td + self.dir_setup);
            self.dir_neg = (self.dir_neg & !bit) | neg;
            self.dir_known |= bit;
        }
        // Other pulses due by `t` ride along when their axis's next step leaves a full low time.
        let mut folded = 0u8;
        while self.falls != 0 {
            let (j, f) = self.earliest_fall();
            if f > t {
                break;
            }
            let jbit = 1u8 << j;
            let next = next_rise.get(j).copied().unwrap_or(0);
            if t - f <= self.pulse || next > t + self.pulse {
                folded |= jbit;
                self.falls &= !jbit;
            } else {
                self.fall(tx, jbit, f);
            }
        }
        self.add(
            tx,
            t,
            Event {
                fall: folded,
                rise: bit,
                ..Event::default()
            },
        );
        for (k, fell) in self.fell_at.iter_mut().enumerate() {
            if folded & (1 << k) != 0 {
                *fell = t;
            }
        }
        if let Some(f) = self.fall_at.get_mut(i) {
            *f = t + self.pulse;
        }
        self.falls |= bit;
        t
    }

    /// Emit the pending fall(s) `mask` at `f` or the cursor, whichever is later.
    fn fall<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>, mask: u8, f: u64) -> u64 {
        let at = f.max(self.cursor());
        self.falls &= !mask;
        self.add(
            tx,
            at,
            Event {
                fall: mask,
                ..Event::default()
            },
        );
        for (k, fell) in self.fell_at.iter_mut().enumerate() {
            if mask & (1 << k) != 0 {
                *fell = at;
            }
        }
        at
    }

    /// The axis with the earliest pending fall, and its deadline.
    fn earliest_fall(&self) -> (usize, u64) {
        let mut best = (0usize, u64::MAX);
        for (k, f) in self.fall_at.iter().enumerate() {
            if self.falls & (1 << k) != 0 && *f < best.1 {
                best = (k, *f);
            }
        }
        best
    }

    /// Emit every pending fall due by `until`, each at its deadline (or the cursor).
    fn flush_falls<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>, until: u64) {
        while self.falls != 0 {
            let (j, f) = self.earliest_fall();
            if f > until {
                break;
            }
            self.fall(tx, 1 << j, f);
        }
    }

    /// End of motion: every pulse ended, and the last event marked as rest.
    fn finish_rest<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>) {
        self.flush_falls(tx, u64::MAX);
        match self.open.take() {
            Some(mut o) => {
                o.ev.rest = true;
                self.push(tx, o);
            }
            None if !self.last_pushed_rest => {
                let tick = self.last_pushed;
                self.push(
                    tx,
                    Open {
                        tick,
                        ev: Event {
                            rest: true,
                            ..Event::default()
                        },
                    },
                );
            }
            None => {}
        }
    }

    /// Put `ev` at `tick` (never before the cursor), merging with the open event when equal.
    fn add<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>, tick: u64, ev: Event) {
        let tick = tick.max(self.cursor());
        match self.open.as_mut() {
            Some(o) if o.tick == tick => {
                o.ev.fall |= ev.fall;
                o.ev.dir_set |= ev.dir_set;
                o.ev.dir_neg = (o.ev.dir_neg & !ev.dir_set) | ev.dir_neg;
                o.ev.rise |= ev.rise;
            }
            _ => {
                if let Some(o) = self.open.take() {
                    self.push(tx, o);
                }
                self.open = Some(Open { tick, ev });
            }
        }
    }

    /// Push the open event, if any.
    fn close<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>) {
        if let Some(o) = self.open.take() {
            self.push(tx, o);
        }
    }

    fn push<const Q: usize>(&mut self, tx: &mut Producer<'_, N, Q>, o: Open) {
        let mut delta = o.tick.saturating_sub(self.last_pushed);
        while delta > u64::from(MAX_DELTA) {
            tx.push(Event {
                delta: MAX_DELTA,
                ..Event::default()
            });
            delta -= u64::from(MAX_DELTA);
            self.pushed_ticks = self.pushed_ticks.wrapping_add(MAX_DELTA);
        }
        let ev = Event {
            delta: delta as u32,
            ..o.ev
        };
        tx.push(ev);
        self.pushed_ticks = self.pushed_ticks.wrapping_add(delta as u32);
        self.last_pushed = o.tick;
        self.last_pushed_rest = ev.rest;
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
}

pub(crate) struct Prep<const N: usize> {
    ticks_per_s: f64,
    em: Emitter<N>,
    cur: Option<Current<N>>,
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
}

impl<const N: usize> Prep<N> {
    pub(crate) fn new(tick_hz: u32, pulse_ticks: u32, dir_setup_ticks: u32) -> Self {
        Self {
            ticks_per_s: f64::from(tick_hz),
            em: Emitter {
                pulse: u64::from(pulse_ticks.max(1)),
                dir_setup: u64::from(dir_setup_ticks),
                open: None,
                last_pushed: 0,
                last_pushed_rest: true,
                pushed_ticks: 0,
                fall_at: [0; N],
                fell_at: [0; N],
                falls: 0,
                dir_neg: 0,
                dir_known: 0,
            },
            cur: None,
            dwell_left: 0,
            t_plan: 0.0,
            v_carry: 0.0,
            hold: false,
            held: false,
            line: 0,
            rapid: false,
            spindle_rpm: 0,
        }
    }

    /// Forget the block in progress and everything not yet pushed (after a flush).
    pub(crate) fn reset(&mut self, consumed_ticks: u32) {
        let em = &mut self.em;
        em.pushed_ticks = consumed_ticks;
        em.open = None;
        em.falls = 0;
        em.dir_known = 0;
        em.last_pushed_rest = true;
        self.cur = None;
        self.dwell_left = 0;
        self.v_carry = 0.0;
        self.hold = false;
        self.held = false;
        // Continue the timeline after everything pushed.
        self.t_plan = self.t_plan.max(self.em.last_pushed as f64);
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
        if let Some(cur) = self.cur.as_mut() {
            cur.nominal = sqrt(f64::from(nominal_sqr));
            // Never equal to the planner's exit: the next fill re-anchors.
            cur.exit_used = f32::NAN;
        }
    }

    /// The motion in preparation: its speed along the path at the last prepared step (mm/s,
    /// 0 at rest: the speed now, `queue_lead_ms` ahead), that speed as a fraction of the
    /// block's nominal speed, whether the block is a rapid, and its spindle speed (rpm).
    pub(crate) fn motion(&self) -> Option<(f64, f64, bool, u32)> {
        let cur = self.cur.as_ref()?;
        let v = cur.profile.speed_at(cur.last_s - cur.s_anchor);
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
        self.cur.is_some() || self.dwell_left > 0
    }

    /// The source line of the block being prepared, or of the last one.
    pub(crate) fn line(&self) -> u32 {
        self.line
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
        let q = tx.shared();
        let consumed = q.consumed_ticks.load(Ordering::Relaxed);
        // Time already spent after the last consumed event (its successors are due sooner).
        let spent = if running {
            let last = Instant::from_ticks(q.last_event_at.load(Ordering::Relaxed));
            now.saturating_duration_since(last).ticks()
        } else {
            0
        };
        let tps = self.ticks_per_s;
        let mut free = tx.free();
        let result = loop {
            if free < SLOTS_PER_STEP + 2 {
                free = tx.free();
                if free < SLOTS_PER_STEP + 2 {
                    break Fill::Pending;
                }
            }
            free -= SLOTS_PER_STEP.min(free);
            let pending = self.em.pushed_ticks.wrapping_sub(consumed);
            let open = self
                .em
                .open
                .map_or(0, |o| (o.tick - self.em.last_pushed) as u32);
            if pending.saturating_sub(spent.min(pending)) + open >= lead_ticks {
                break Fill::Pending;
            }
            if self.dwell_left > 0 {
                let d = self.dwell_left.min(u64::from(MAX_DELTA));
                self.dwell_left -= d;
                let t = self.em.cursor() + d;
                self.em.add(tx, t, Event::default());
                self.t_plan = t as f64;
                continue;
            }
            if self.cur.is_none() {
                let Some(block) = planner.tail().copied() else {
                    self.em.finish_rest(tx);
                    self.v_carry = 0.0;
                    self.t_plan = self.t_plan.max(self.em.last_pushed as f64);
                    break Fill::Drained;
                };
                match block.kind {
                    BlockKind::Dwell(ms) => {
                        self.em.flush_falls(tx, u64::MAX);
                        self.dwell_left = libm::round(f64::from(ms) * tps / 1000.0) as u64;
                        self.t_plan = self.t_plan.max(self.em.cursor() as f64);
                        self.line = block.line;
                        planner.retire_tail();
                        continue;
                    }
                    BlockKind::Move => self.load(&block, planner.tail_exit_sqr()),
                }
            }
            let exit_sqr = planner.tail_exit_sqr();
            let hold = self.hold;
            let Some(cur) = self.cur.as_mut() else {
                continue;
            };
            if cur.exit_used != exit_sqr || cur.hold_used != hold {
                cur.reanchor(exit_sqr, hold, tps);
            }
            // The axis whose step comes first.
            let mut best = (usize::MAX, u64::MAX);
            for (i, t) in cur.next_tick.iter().enumerate() {
                if *t < best.1 {
                    best = (i, *t);
                }
            }
            let (i, tick) = best;
            if tick != u64::MAX {
                let neg = cur.neg & (1 << i);
                let t = cur.next_t.get(i).copied().unwrap_or(0.0);
                self.em.rise(tx, i, neg, tick, &cur.next_tick);
                cur.advance(i, t, tps);
            } else if cur.done() {
                // Block done: the next one starts where this profile ends.
                self.t_plan = cur.t_anchor + cur.profile.duration() * tps;
                self.v_carry = cur.profile.exit_speed();
                self.cur = None;
                planner.retire_tail();
            } else {
                // A hold came to rest inside the block: anchor there, at zero speed.
                cur.last_s = cur.s_anchor + cur.profile.length();
                cur.last_t = cur.t_anchor + cur.profile.duration() * tps;
                self.t_plan = cur.last_t;
                self.held = true;
                self.em.finish_rest(tx);
                self.v_carry = 0.0;
                break Fill::Held;
            }
        };
        self.em.close(tx);
        result
    }

    fn load(&mut self, block: &Block<N>, exit_sqr: f32) {
        let mut n = [0u32; N];
        let mut neg = 0u8;
        for (i, (c, s)) in n.iter_mut().zip(block.steps.iter()).enumerate() {
            *c = s.unsigned_abs();
            if *s < 0 {
                neg |= 1 << i;
            }
        }
        let t0 = self.t_plan;
        let mut cur = Current {
            n,
            neg,
            next_j: [1; N],
            next_t: [f64::INFINITY; N],
            next_tick: [u64::MAX; N],
            mm: f64::from(block.mm),
            accel: f64::from(block.accel),
            nominal: sqrt(f64::from(block.nominal_sqr)),
            s_anchor: 0.0,
            t_anchor: t0,
            last_s: 0.0,
            last_t: t0,
            profile: Profile::plan(0.0, 0.0, 0.0, 0.0, 1.0),
            exit_used: exit_sqr,
            hold_used: self.hold,
            step_mm: core::array::from_fn(|i| {
                if n[i] == 0 {
                    0.0
                } else {
                    f64::from(block.mm) / f64::from(n[i])
                }
            }),
            cruise: [Cruise::default(); N],
        };
        self.line = block.line;
        self.rapid = block.speed.rapid;
        self.spindle_rpm = block.spindle_rpm;
        cur.profile = cur.profile_for(self.v_carry, exit_sqr, self.hold);
        cur.plan_cruise(self.ticks_per_s);
        for i in 0..N {
            cur.refresh(i, self.ticks_per_s);
        }
        self.cur = Some(cur);
    }
}
