//! The look-ahead planner: a ring of blocks with junction-deviation cornering and a grbl-style
//! reverse/forward pass.
//!
//! Thread side. Each added block gets a nominal speed (its feed, scaled by the feed override of
//! its line and raised to the [`PathLimits`] slowest feed of its kind, then capped by every
//! axis's maximum rate along its direction), an acceleration (capped by every axis's maximum
//! acceleration along its direction and by the [`PathLimits`] acceleration of its kind) and a
//! maximum entry speed (the junction-deviation corner speed with the previous block, capped by
//! both blocks' nominal speeds). The newest block always ends at rest.
//! The reverse pass raises entry speeds from the newest block backwards, and the forward pass
//! lowers them where acceleration from the previous block cannot reach them. `planned` marks
//! the first block whose entry may still change: everything before it is optimal and neither
//! pass visits it again, so the work per added block is amortised constant (grbl's
//! `block_buffer_planned`).
//!
//! The oldest block (`tail`) belongs to segment preparation once it has started on it: the
//! passes never change its entry speed, only its exit (the next block's entry), and
//! preparation caps that exit at what it can still reach from where it is.
//!
//! **Realtime overrides** (grbl's `0x90`–`0x98`, [`Planner::set_overrides`]) scale the
//! nominal speed of every block in the ring at once, the oldest included, and of the blocks
//! added after: feed moves by the feed override, rapids by the rapid override. Each block keeps
//! what its speed is made of (the feed before the overrides, the slowest feed of its kind, the
//! axes' cap, its corner speed), so that a change re-derives its nominal and maximum entry
//! speeds and re-plans the whole ring.

use crate::fpu::sqrtf;

use crate::arc::Nm;
use crate::config::{AxisKind, MachineConfig};
use crate::interp::nm_to_steps;

/// What a block does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum BlockKind {
    /// A straight move.
    Move,
    /// A dwell of this many milliseconds at rest.
    Dwell(u32),
}

/// One planned block.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Block<const N: usize> {
    pub kind: BlockKind,
    /// Signed step counts of every axis.
    pub steps: [i32; N],
    /// Length of the move in mm (all axes).
    pub mm: f32,
    /// Acceleration along the path, mm/s².
    pub accel: f32,
    /// `2 × accel × mm`: the most the speed's square changes over the block, (mm/s)², worked
    /// out once for the planner's passes.
    pub reach_sqr: f32,
    /// Square of the nominal speed, (mm/s)².
    pub nominal_sqr: f32,
    /// Square of the largest entry speed the junction allows.
    pub max_entry_sqr: f32,
    /// Square of the planned entry speed.
    pub entry_sqr: f32,
    /// Source line (program line or G-code line number), for progress reports.
    pub line: u32,
    /// Axes whose switch ends this move (homing).
    pub homing_mask: u8,
    /// What the nominal speed is made of, for the realtime overrides.
    pub speed: SpeedParts,
    /// The spindle speed (`S`) in force for the move, rpm.
    pub spindle_rpm: u32,
}

/// The parts of a block's nominal and maximum entry speeds that the realtime overrides do not
/// change, kept so that an override change can work them out again.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct SpeedParts {
    /// The speed asked for before the realtime overrides, mm/s (a rapid: the axes' cap).
    pub wanted: f32,
    /// The slowest speed of the block's kind ([`PathLimits`]), mm/s; 0 for none.
    pub floor: f32,
    /// The fastest the axes allow along the block, mm/s.
    pub cap: f32,
    /// The junction's corner speed with the block before, squared; 0 when it starts at rest.
    pub junction_sqr: f32,
    /// A rapid: the rapid override scales it, else the feed override.
    pub rapid: bool,
    /// A homing or probing move: no override scales it (grbl's rule).
    pub fixed: bool,
    /// A feed ramp: it may enter above its own nominal speed (up to `cap`).
    pub ramp: bool,
}

impl SpeedParts {
    const NONE: Self = Self {
        wanted: 0.0,
        floor: 0.0,
        cap: 0.0,
        junction_sqr: 0.0,
        rapid: false,
        fixed: false,
        ramp: false,
    };

    /// The nominal speed under the overrides `feed` and `rapid` (factors), mm/s.
    fn nominal(&self, feed: f32, rapid: f32) -> f32 {
        let scale = match (self.fixed, self.rapid) {
            (true, _) => 1.0,
            (false, true) => rapid,
            (false, false) => feed,
        };
        least(most(times(self.wanted, scale), self.floor), self.cap)
    }
}

impl<const N: usize> Block<N> {
    const EMPTY: Self = Self {
        kind: BlockKind::Move,
        steps: [0; N],
        mm: 0.0,
        accel: 1.0,
        reach_sqr: 0.0,
        nominal_sqr: 0.0,
        max_entry_sqr: 0.0,
        entry_sqr: 0.0,
        line: 0,
        homing_mask: 0,
        speed: SpeedParts::NONE,
        spindle_rpm: 0,
    };
}

/// Limits along the path that depend on what a move does, on top of the per-axis limits of the
/// [`MachineConfig`]: Marlin's `M204` accelerations and `M205 S`/`T` slowest feeds, as Marlin's
/// `Planner::_populate_block` applies them.
///
/// A move is of one of three kinds: *printing* (an extruder moves together with another axis),
/// *retracting* (extruders alone: a retraction or its recovery) and *travel* (no extruder
/// moves). Its acceleration is the smallest of the per-axis limits along its direction and the
/// acceleration of its kind here; its junction with the move before it is taken at most at that
/// acceleration too. Unlike Marlin, a retraction is held to the extruder's own maximum
/// acceleration as well: an axis never accelerates beyond its configured limit.
///
/// The slowest feeds raise the feed a move asks for (never above the axes' maximum rates):
/// `min_extruding_feed_mm_s` for printing and retracting moves, `min_travel_feed_mm_s` for
/// travel. They apply to every move, homing and jogs included, as in Marlin.
///
/// The default, [`PathLimits::NONE`], leaves the per-axis limits alone in charge.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathLimits {
    /// `M204 P` (or `S`): acceleration of printing moves, mm/s²; `None`: the per-axis limits
    /// alone.
    pub print_accel_mm_s2: Option<f32>,
    /// `M204 R`: acceleration of retracting moves, mm/s²; `None`: the per-axis limits alone.
    pub retract_accel_mm_s2: Option<f32>,
    /// `M204 T` (or `S`): acceleration of travel moves, mm/s²; `None`: the per-axis limits
    /// alone.
    pub travel_accel_mm_s2: Option<f32>,
    /// `M205 S`: the slowest feed of printing and retracting moves, mm/s (0: no floor).
    pub min_extruding_feed_mm_s: f32,
    /// `M205 T`: the slowest feed of travel moves, mm/s (0: no floor).
    pub min_travel_feed_mm_s: f32,
}

impl PathLimits {
    /// No limit beyond the per-axis ones: no acceleration cap, no slowest feed.
    pub const NONE: Self = Self {
        print_accel_mm_s2: None,
        retract_accel_mm_s2: None,
        travel_accel_mm_s2: None,
        min_extruding_feed_mm_s: 0.0,
        min_travel_feed_mm_s: 0.0,
    };

    /// The acceleration cap of a move of `kind`, mm/s² (infinite when there is none).
    #[inline]
    fn accel_mm_s2(&self, kind: MoveKind) -> f32 {
        let cap = match kind {
            MoveKind::Print => self.print_accel_mm_s2,
            MoveKind::Retract => self.retract_accel_mm_s2,
            MoveKind::Travel => self.travel_accel_mm_s2,
        };
        cap.unwrap_or(f32::INFINITY)
    }

    /// The slowest feed of a move of `kind`, mm/s.
    #[inline]
    fn min_feed_mm_s(&self, kind: MoveKind) -> f32 {
        match kind {
            MoveKind::Print | MoveKind::Retract => self.min_extruding_feed_mm_s,
            MoveKind::Travel => self.min_travel_feed_mm_s,
        }
    }
}

impl Default for PathLimits {
    fn default() -> Self {
        Self::NONE
    }
}

/// What a move does, for the [`PathLimits`] of its kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum MoveKind {
    /// An extruder and another axis.
    Print,
    /// Extruders alone.
    Retract,
    /// No extruder.
    Travel,
}

impl MoveKind {
    /// The kind of a move that moves extruders (`extrudes`) and other axes (`moves_axes`).
    #[inline]
    fn of(extrudes: bool, moves_axes: bool) -> Self {
        match (extrudes, moves_axes) {
            (true, true) => Self::Print,
            (true, false) => Self::Retract,
            (false, _) => Self::Travel,
        }
    }
}

/// What is known of the previous move, for the junction with the next.
#[derive(Debug, Clone, Copy)]
struct Previous<const N: usize> {
    unit: [f32; N],
    /// The axes it moves (their bits): the others' `unit` is 0.
    moving: u8,
    nominal_sqr: f32,
    /// The fastest its axes allow along it ([`SpeedParts::cap`]), mm/s: no override takes its
    /// nominal speed above.
    cap: f32,
}

/// A new move for the planner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct MoveRequest<const N: usize> {
    /// Signed step counts.
    pub steps: [i32; N],
    /// Feed in mm/min along the path, or `None` for the fastest the axes allow (rapid).
    pub feed_mm_min: Option<f32>,
    /// The feed override (`M220`) as a factor: it scales the feed, or the fastest rate of a
    /// rapid, before the axes' maximum rates cap it. 1 for moves that are not G-code lines.
    pub feed_scale: f32,
    /// The feed was given on this line: the move may enter at the previous speed and reach
    /// its own within the move (RepRap's feed ramp).
    pub ramp: bool,
    /// Source line.
    pub line: u32,
    /// Axes whose switch ends this move.
    pub homing_mask: u8,
    /// `G61`: the move starts from rest (the one before it ends at rest).
    pub exact_stop: bool,
    /// A homing or probing move: the realtime overrides do not scale it.
    pub fixed: bool,
    /// The spindle speed (`S`) in force for the move, rpm.
    pub spindle_rpm: u32,
}

impl<const N: usize> MoveRequest<N> {
    /// The move from where the last one ended, `steps` (updated to the end of this one), to
    /// `target` (machine nm), each axis rounded to its nearest step.
    pub(crate) fn to_target(
        target: &[Nm; N],
        steps: &mut [i32; N],
        config: &MachineConfig<N>,
        feed_mm_min: Option<f32>,
        ramp: bool,
        line: u32,
        homing_mask: u8,
    ) -> Self {
        let mut delta = [0i32; N];
        for (i, a) in config.axes.iter().enumerate() {
            let s = nm_to_steps(target[i], a.steps_per_mm);
            delta[i] = s.wrapping_sub(steps[i]);
            steps[i] = s;
        }
        Self {
            steps: delta,
            feed_mm_min,
            feed_scale: 1.0,
            ramp,
            line,
            homing_mask,
            exact_stop: false,
            fixed: homing_mask != 0,
            spindle_rpm: 0,
        }
    }
}

/// The planner ring: `B` blocks.
pub(crate) struct Planner<const N: usize, const B: usize> {
    blocks: [Block<N>; B],
    head: usize,
    tail: usize,
    planned: usize,
    len: usize,
    previous: Option<Previous<N>>,
    limits: PathLimits,
    /// The realtime feed override, as a factor.
    feed_override: f32,
    /// The realtime rapid override, as a factor.
    rapid_override: f32,
    /// The last feed's conversion to mm/s.
    feed_per_s: FeedPerSecond,
}

/// A feed (mm/min, times the line's scale) in mm/s, kept for the next line: the feed is modal,
/// and the conversion, a multiplication and a division, is in software on RISC-V.
#[derive(Debug, Clone, Copy)]
struct FeedPerSecond {
    /// The feed's bits.
    mm_min: u32,
    /// The scale's bits.
    scale: u32,
    /// `feed × scale / 60`.
    mm_s: f32,
}

impl FeedPerSecond {
    /// Feed 0 at scale 0, which is 0 mm/s: a true conversion from the start.
    const ZERO: Self = Self {
        mm_min: 0,
        scale: 0,
        mm_s: 0.0,
    };

    /// `feed_mm_min × scale / 60`, the same to the bit as worked out each time.
    #[inline(always)]
    fn of(&mut self, feed_mm_min: f32, scale: f32) -> f32 {
        if feed_mm_min.to_bits() != self.mm_min || scale.to_bits() != self.scale {
            *self = Self {
                mm_min: feed_mm_min.to_bits(),
                scale: scale.to_bits(),
                mm_s: times(feed_mm_min, scale) / 60.0,
            };
        }
        self.mm_s
    }
}

const fn next(i: usize, b: usize) -> usize {
    if i + 1 == b { 0 } else { i + 1 }
}

const fn prev(i: usize, b: usize) -> usize {
    if i == 0 { b - 1 } else { i - 1 }
}

impl<const N: usize, const B: usize> Planner<N, B> {
    pub(crate) const fn new() -> Self {
        Self {
            blocks: [Block::EMPTY; B],
            head: 0,
            tail: 0,
            planned: 0,
            len: 0,
            previous: None,
            limits: PathLimits::NONE,
            feed_override: 1.0,
            rapid_override: 1.0,
            feed_per_s: FeedPerSecond::ZERO,
        }
    }

    /// Scale feed moves by `feed` and rapids by `rapid` (factors), from now on and for every
    /// block in the ring, the oldest included; re-plan the ring. Returns the oldest block's
    /// new nominal speed squared, for the preparation working on it.
    pub(crate) fn set_overrides(&mut self, feed: f32, rapid: f32) -> Option<f32> {
        self.feed_override = feed;
        self.rapid_override = rapid;
        let mut before: Option<f32> = None;
        for k in 0..self.len {
            let Some(b) = self.blocks.get_mut((self.tail + k) % B) else {
                continue;
            };
            if b.kind != BlockKind::Move {
                before = None;
                continue;
            }
            let nominal = b.speed.nominal(feed, rapid);
            b.nominal_sqr = nominal * nominal;
            // The oldest block has already entered: its entry stays as it is.
            if k > 0 {
                let own = if b.speed.ramp {
                    b.speed.cap * b.speed.cap
                } else {
                    b.nominal_sqr
                };
                b.max_entry_sqr = match before {
                    Some(p) => least(least(b.speed.junction_sqr, p), own),
                    None => 0.0,
                };
            }
            before = Some(b.nominal_sqr);
        }
        if let (Some(p), Some(n)) = (self.previous.as_mut(), before) {
            p.nominal_sqr = n;
        }
        self.planned = self.tail;
        self.recalculate();
        self.tail().map(|b| b.nominal_sqr)
    }

    /// The limits along the path that moves are planned with.
    pub(crate) fn limits(&self) -> PathLimits {
        self.limits
    }

    /// Plan the moves added from now on with `limits`; the blocks already planned keep theirs.
    pub(crate) fn set_limits(&mut self, limits: PathLimits) {
        self.limits = limits;
    }

    pub(crate) fn len(&self) -> usize {
        self.len
    }

    pub(crate) fn is_full(&self) -> bool {
        self.len == B
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Forget every block (stop, alarm). The limits are kept.
    pub(crate) fn clear(&mut self) {
        self.head = 0;
        self.tail = 0;
        self.planned = 0;
        self.len = 0;
        self.previous = None;
    }

    /// The oldest block.
    pub(crate) fn tail(&self) -> Option<&Block<N>> {
        if self.len == 0 {
            None
        } else {
            self.blocks.get(self.tail)
        }
    }

    /// Square of the planned exit speed of the oldest block (the next one's entry, or rest).
    pub(crate) fn tail_exit_sqr(&self) -> f32 {
        if self.len < 2 {
            0.0
        } else {
            self.blocks
                .get(next(self.tail, B))
                .map_or(0.0, |b| b.entry_sqr)
        }
    }

    /// The blocks from oldest to newest.
    #[cfg(test)]
    pub(crate) fn iter(&self) -> impl Iterator<Item = &Block<N>> {
        (0..self.len).filter_map(move |k| self.blocks.get((self.tail + k) % B))
    }

    /// Drop the oldest block: preparation has finished it.
    pub(crate) fn retire_tail(&mut self) {
        if self.len == 0 {
            return;
        }
        if self.planned == self.tail {
            self.planned = next(self.tail, B);
        }
        self.tail = next(self.tail, B);
        self.len -= 1;
        if self.len == 0 {
            self.previous = None;
            self.planned = self.tail;
        }
    }

    /// Add a dwell; `false` when full.
    pub(crate) fn push_dwell(&mut self, ms: u32, line: u32) -> bool {
        if self.is_full() {
            return false;
        }
        let block = Block {
            kind: BlockKind::Dwell(ms),
            line,
            ..Block::EMPTY
        };
        self.insert(block);
        self.previous = None;
        true
    }

    /// Add a move; `false` when full. A move with no steps is not added (and returns `true`).
    pub(crate) fn push_move(&mut self, req: &MoveRequest<N>, config: &MachineConfig<N>) -> bool {
        if self.is_full() {
            return false;
        }
        let mut mm = [0f32; N];
        let mut len_sqr = 0f32;
        let mut extrudes = false;
        let mut moves_axes = false;
        // The axes that move: the others add nothing and cost nothing below.
        let mut moving = 0u8;
        for (i, (m, a)) in mm.iter_mut().zip(config.axes.iter()).enumerate() {
            let s = req.steps.get(i).copied().unwrap_or(0);
            if s == 0 {
                continue;
            }
            *m = s as f32 / a.steps_per_mm;
            len_sqr += *m * *m;
            moving |= 1 << i;
            if a.kind == AxisKind::Extruder {
                extrudes = true;
            } else {
                moves_axes = true;
            }
        }
        if moving == 0 {
            return true;
        }
        let length = sqrtf(len_sqr);
        // Without extrusion the feed's length is the whole length, to the bit: one sum and
        // one square root.
        let feed_len = if extrudes && moves_axes {
            let mut feed_len_sqr = 0f32;
            for (m, a) in mm.iter().zip(config.axes.iter()) {
                if a.kind != AxisKind::Extruder {
                    feed_len_sqr += *m * *m;
                }
            }
            sqrtf(feed_len_sqr)
        } else {
            length
        };
        let kind = MoveKind::of(extrudes, moves_axes);
        let cap = self.limits.accel_mm_s2(kind);
        // The limits along the path: an axis's limit over its share of the length,
        // `limit / (|mm| / length)`, with one division per moving axis and one for the unit.
        let per_length = 1.0 / length;
        let mut unit = [0f32; N];
        let mut accel = cap;
        let mut rate_mm_min = f32::INFINITY;
        for (i, ((u, m), a)) in unit
            .iter_mut()
            .zip(mm.iter())
            .zip(config.axes.iter())
            .enumerate()
        {
            if moving & (1 << i) != 0 {
                *u = *m * per_length;
                let lengths = length / m.abs();
                accel = least(accel, a.accel_mm_s2 * lengths);
                rate_mm_min = least(rate_mm_min, a.max_rate_mm_min * lengths);
            }
        }
        let rate = rate_mm_min / 60.0;
        // A feed is along the axes that are not extruders; the speed is along the whole path.
        // The feed along the whole path: the same unless extruders move with other axes.
        let along_path = |feed: f32| {
            if extrudes && moves_axes {
                feed * length / feed_len
            } else {
                feed
            }
        };
        let wanted = match req.feed_mm_min {
            Some(f) => along_path(self.feed_per_s.of(f, req.feed_scale)),
            None => times(rate, req.feed_scale),
        };
        let floor = self.limits.min_feed_mm_s(kind);
        let junction_sqr = match (self.len, self.previous) {
            (0, _) | (_, None) => 0.0,
            _ if req.exact_stop => 0.0,
            (_, Some(p)) => {
                let fastest = most(p.cap, rate);
                let fastest_sqr = fastest * fastest;
                let moves = p.moving | moving;
                junction_speed_sqr(&p.unit, &unit, moves, config, cap, fastest_sqr)
            }
        };
        let speed = SpeedParts {
            wanted,
            floor: if is_positive(floor) {
                along_path(floor)
            } else {
                0.0
            },
            cap: rate,
            junction_sqr,
            rapid: req.feed_mm_min.is_none(),
            fixed: req.fixed,
            ramp: req.ramp,
        };
        let nominal = speed.nominal(self.feed_override, self.rapid_override);
        let nominal_sqr = nominal * nominal;
        let max_entry_sqr = match (self.len, self.previous) {
            (0, _) | (_, None) => 0.0,
            _ if req.exact_stop => 0.0,
            (_, Some(p)) => {
                // A feed ramp may enter above its own feed, never above what its axes allow.
                let own = if req.ramp { rate * rate } else { nominal_sqr };
                least(least(junction_sqr, p.nominal_sqr), own)
            }
        };
        let block = Block {
            kind: BlockKind::Move,
            steps: req.steps,
            mm: length,
            accel,
            reach_sqr: doubled(accel * length),
            nominal_sqr,
            max_entry_sqr,
            entry_sqr: 0.0,
            line: req.line,
            homing_mask: req.homing_mask,
            speed,
            spindle_rpm: req.spindle_rpm,
        };
        self.insert(block);
        self.previous = Some(Previous {
            unit,
            moving,
            nominal_sqr,
            cap: rate,
        });
        self.recalculate();
        true
    }

    fn insert(&mut self, block: Block<N>) {
        if let Some(slot) = self.blocks.get_mut(self.head) {
            *slot = block;
        }
        self.head = next(self.head, B);
        self.len += 1;
    }

    /// grbl's `planner_recalculate`: reverse pass down to `planned`, forward pass from it.
    /// Works on the blocks in place: a block copied out per step of a pass would cost more
    /// than the pass's arithmetic.
    fn recalculate(&mut self) {
        let mut idx = prev(self.head, B);
        if idx == self.planned {
            return;
        }
        // The newest block ends at rest.
        let Some(newest) = self.blocks.get_mut(idx) else {
            return;
        };
        let mut next_entry = least(newest.max_entry_sqr, newest.reach_sqr);
        newest.entry_sqr = next_entry;
        idx = prev(idx, B);
        while idx != self.planned {
            let Some(cur) = self.blocks.get_mut(idx) else {
                return;
            };
            if !same(cur.entry_sqr, cur.max_entry_sqr) {
                let e = least(next_entry + cur.reach_sqr, cur.max_entry_sqr);
                cur.entry_sqr = e;
                next_entry = e;
            } else {
                next_entry = cur.entry_sqr;
            }
            idx = prev(idx, B);
        }
        // Forward pass: the previous block's entry², acceleration and length.
        let Some(first) = self.blocks.get(self.planned) else {
            return;
        };
        let mut cur = (first.entry_sqr, first.reach_sqr);
        let mut idx = next(self.planned, B);
        while idx != self.head {
            let Some(nxt) = self.blocks.get_mut(idx) else {
                return;
            };
            let (entry_sqr, reach_sqr) = cur;
            if below(entry_sqr, nxt.entry_sqr) {
                let e = entry_sqr + reach_sqr;
                if below(e, nxt.entry_sqr) {
                    nxt.entry_sqr = e;
                    self.planned = idx;
                }
            }
            if same(nxt.entry_sqr, nxt.max_entry_sqr) {
                self.planned = idx;
            }
            cur = (nxt.entry_sqr, nxt.reach_sqr);
            idx = next(idx, B);
        }
    }
}

/// The smaller of two of the planner's values, which are never negative nor NaN (lengths,
/// speeds, their squares, accelerations, infinity for no limit): one integer comparison of
/// their bits, which order such values as their numbers do. `f32::min` calls `fminf` for
/// NaN's rules, and a float comparison is a call of its own on RISC-V, whose floats are
/// software. With `b` NaN (above infinity), `a`.
#[inline(always)]
fn least(a: f32, b: f32) -> f32 {
    debug_assert!(a.is_sign_positive() && b.is_sign_positive(), "{a} {b}");
    if b.to_bits() < a.to_bits() { b } else { a }
}

/// A key that orders floats (not NaN) as their numbers, −0 just below +0, in one integer
/// comparison: the bits, with a negative value's magnitude bits flipped. A float comparison is
/// a call on RISC-V, whose floats are software.
#[inline(always)]
const fn order_key(x: f32) -> i32 {
    let bits = x.to_bits().cast_signed();
    bits ^ ((bits >> 31).cast_unsigned() >> 1).cast_signed()
}

/// `x × factor`, or `x` itself for a factor of exactly 1 (the overrides', scales' and units'
/// usual value): the same to the bit, without the multiplication.
#[inline(always)]
pub(crate) fn times(x: f32, factor: f32) -> f32 {
    if factor.to_bits() == 1f32.to_bits() {
        x
    } else {
        product(x, factor)
    }
}

/// `a × b`, out of line: inlined, the compiler would work it out ahead of the test that
/// skips it and select the result (a multiplication is cheap to it, and a call in software on
/// RISC-V).
#[inline(never)]
fn product(a: f32, b: f32) -> f32 {
    a * b
}

/// `2x` for one of the planner's values, by its exponent when that is exact (a normal value
/// below the largest binade), else by a multiplication (out of line, as in [`times`]).
#[inline(always)]
fn doubled(x: f32) -> f32 {
    let exponent = x.to_bits() >> 23;
    if (1..0xFE).contains(&exponent) {
        f32::from_bits(x.to_bits() + (1 << 23))
    } else {
        product(x, 2.0)
    }
}

/// `x / 2` for one of the planner's values, by its exponent when that is exact (a normal value
/// whose half is normal), else by a multiplication (out of line, as in [`times`]).
#[inline(always)]
fn halved(x: f32) -> f32 {
    let exponent = x.to_bits() >> 23;
    if (2..0xFF).contains(&exponent) {
        f32::from_bits(x.to_bits() - (1 << 23))
    } else {
        product(x, 0.5)
    }
}

/// Whether `x` (not NaN) is above 0, by its bits.
#[inline(always)]
const fn is_positive(x: f32) -> bool {
    x.to_bits().cast_signed() > 0
}

/// Whether `a` is below `b`, two of the planner's values, by their bits as [`least`].
#[inline(always)]
fn below(a: f32, b: f32) -> bool {
    debug_assert!(a.is_sign_positive() && b.is_sign_positive(), "{a} {b}");
    a.to_bits() < b.to_bits()
}

/// Whether `a` equals `b`, two of the planner's values, by their bits as [`least`] (neither is
/// NaN nor −0, where the bits and the numbers disagree).
#[inline(always)]
fn same(a: f32, b: f32) -> bool {
    debug_assert!(a.is_sign_positive() && b.is_sign_positive(), "{a} {b}");
    a.to_bits() == b.to_bits()
}

/// The larger of two of the planner's values, as [`least`].
#[inline(always)]
fn most(a: f32, b: f32) -> f32 {
    debug_assert!(a.is_sign_positive() && b.is_sign_positive(), "{a} {b}");
    if b.to_bits() > a.to_bits() { b } else { a }
}

/// Junction deviation (grbl): the corner speed at which a virtual arc, tangent to both moves and
/// `junction_deviation_mm` from the corner, is taken at the acceleration the axes allow along
/// the change of direction, and at most `cap_mm_s2` (the [`PathLimits`] acceleration of the
/// new move's kind). `moving` has the bits of the axes either move moves: the others' units
/// are 0 and are skipped. Returns the square of the speed, or infinity when it is at least
/// `fastest_sqr`, the square of the fastest either move may be planned at (whatever the
/// overrides), where it could never limit them.
///
/// That case is told from the angle alone, before the change of direction's length, its
/// axes' limits and two square roots. With `c` the cosine below, `w = (1 + c)/2` and
/// `s = √(1 − w)` the half angle's sine, the speed² is `a·δ·s/(1 − s) = a·δ·s(1 + s)/w`, and
/// `s(1 + s) ≥ 2s² = 2(1 − w)` (as `s ≤ 1`); `a` is at least the smallest of the moving axes'
/// accelerations and the cap (an axis's share of the change is at most all of it). The test
/// is `2·a·δ·(1 − w)/w ≥ v²` with `w` raised by 10⁻⁶, above its rounding (that of `c` from
/// rounded unit vectors), and the rest of the rounding within the bound's own slack (the
/// inequality's, at least `w/4` relative).
pub(crate) fn junction_speed_sqr<const N: usize>(
    prev_unit: &[f32; N],
    unit: &[f32; N],
    moving: u8,
    config: &MachineConfig<N>,
    cap_mm_s2: f32,
    fastest_sqr: f32,
) -> f32 {
    let mut cos_theta = 0f32;
    let mut slowest = cap_mm_s2;
    for i in 0..N {
        if moving & (1 << i) == 0 {
            continue;
        }
        cos_theta -= prev_unit[i] * unit[i];
        if let Some(a) = config.axes.get(i) {
            slowest = least(slowest, a.accel_mm_s2);
        }
    }
    if order_key(cos_theta) > order_key(0.999_999) {
        // A reversal: stop.
        return 0.0;
    }
    if order_key(cos_theta) < order_key(-0.999_999) {
        // Straight on: no corner.
        return f32::INFINITY;
    }
    // 2·a·δ·(1 − w)/w ≥ v² as 2·a·δ ≥ w·(v² + 2·a·δ), with no division.
    let w = halved(1.000_002 + cos_theta);
    let least_reach = slowest * doubled(config.junction_deviation_mm);
    if !below(least_reach, w * (fastest_sqr + least_reach)) {
        return f32::INFINITY;
    }
    let mut delta = [0f32; N];
    let mut delta_len_sqr = 0f32;
    for i in 0..N {
        if moving & (1 << i) != 0 {
            let d = unit[i] - prev_unit[i];
            delta[i] = d;
            delta_len_sqr += d * d;
        }
    }
    let delta_len = sqrtf(delta_len_sqr);
    let mut accel = cap_mm_s2;
    for (i, (d, a)) in delta.iter().zip(config.axes.iter()).enumerate() {
        // The axis's limit over its share of the change, `|d| / delta_len`: infinite, and so
        // no limit, for an axis whose share does not change (`delta_len` is not 0: the
        // moves are not in line).
        if moving & (1 << i) != 0 {
            accel = least(accel, a.accel_mm_s2 * (delta_len / d.abs()));
        }
    }
    let sin_half = sqrtf(halved(1.0 - cos_theta));
    accel * config.junction_deviation_mm * sin_half / (1.0 - sin_half)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::AxisConfig;

    fn cfg() -> MachineConfig<2> {
        let mut c = MachineConfig::new([
            AxisConfig::linear(b'X', 100.0, 6000.0, 1000.0, 500.0),
            AxisConfig::linear(b'Y', 100.0, 3000.0, 500.0, 500.0),
        ]);
        c.junction_deviation_mm = 0.05;
        c
    }

    fn mv(x: i32, y: i32, feed: f32) -> MoveRequest<2> {
        MoveRequest {
            steps: [x, y],
            feed_mm_min: Some(feed),
            feed_scale: 1.0,
            ramp: false,
            line: 0,
            homing_mask: 0,
            exact_stop: false,
            fixed: false,
            spindle_rpm: 0,
        }
    }

    #[test]
    fn per_axis_limits_cap_speed_and_acceleration() {
        let c = cfg();
        let mut p = Planner::<2, 8>::new();
        assert!(p.push_move(&mv(0, 1000, 6000.0), &c));
        let b = *p.tail().expect("block");
        assert_eq!(b.nominal_sqr, 50.0 * 50.0);
        assert_eq!(b.accel, 500.0);
        assert_eq!(b.entry_sqr, 0.0);
        p.clear();
        // Diagonal: X and Y each at 1/sqrt2 of the path.
        assert!(p.push_move(&mv(1000, 1000, 1.0e6), &c));
        let b = *p.tail().expect("block");
        let s2 = core::f32::consts::SQRT_2;
        assert!((sqrtf(b.nominal_sqr) - 50.0 * s2).abs() < 1e-3);
        assert!((b.accel - 500.0 * s2).abs() < 1e-2);
    }

    #[test]
    fn collinear_blocks_do_not_stop_and_the_last_ends_at_rest() {
        let c = cfg();
        let mut p = Planner::<2, 8>::new();
        for _ in 0..5 {
            assert!(p.push_move(&mv(1000, 0, 3000.0), &c));
        }
        let entries: [f32; 5] =
            core::array::from_fn(|k| p.iter().nth(k).map_or(-1.0, |b| b.entry_sqr));
        assert_eq!(entries[0], 0.0);
        // 10 mm blocks at 50 mm/s and 1000 mm/s²: full speed at every inner junction.
        for e in &entries[1..] {
            assert!((*e - 2500.0).abs() < 1e-2, "{entries:?}");
        }
        // The last block can stop within its length from its entry.
        let last = p.iter().last().copied().expect("last");
        assert!(last.entry_sqr <= 2.0 * last.accel * last.mm + 1e-3);
    }

    #[test]
    fn right_angle_corner_obeys_junction_deviation() {
        let c = cfg();
        let mut p = Planner::<2, 8>::new();
        assert!(p.push_move(&mv(10_000, 0, 3000.0), &c));
        assert!(p.push_move(&mv(0, 10_000, 3000.0), &c));
        let second = p.iter().nth(1).copied().expect("second");
        // 90 degrees: sin(45) = 0.7071; direction change (−1, 1)/√2 → both axes √2 · limit.
        let sin_half = core::f32::consts::FRAC_1_SQRT_2;
        let accel = 500.0 * core::f32::consts::SQRT_2;
        let expected = accel * 0.05 * sin_half / (1.0 - sin_half);
        assert!((second.max_entry_sqr - expected).abs() < 1e-2);
        assert!((second.entry_sqr - expected).abs() < 1e-2);
    }

    #[test]
    fn reversal_stops() {
        let c = cfg();
        let mut p = Planner::<2, 8>::new();
        assert!(p.push_move(&mv(1000, 0, 3000.0), &c));
        assert!(p.push_move(&mv(-1000, 0, 3000.0), &c));
        assert_eq!(p.iter().nth(1).map(|b| b.entry_sqr), Some(0.0));
    }

    #[test]
    fn feed_on_the_line_ramps_inside_the_move() {
        let c = cfg();
        let mut p = Planner::<2, 8>::new();
        assert!(p.push_move(&mv(1000, 0, 3000.0), &c));
        let mut slow = mv(1000, 0, 1500.0);
        slow.ramp = true;
        assert!(p.push_move(&slow, &c));
        let b = p.iter().nth(1).copied().expect("second");
        // Enters at the previous 50 mm/s and slows to 25 mm/s inside the move.
        assert!((b.max_entry_sqr - 2500.0).abs() < 1e-2);
        assert!((b.nominal_sqr - 625.0).abs() < 1e-2);
        let mut p = Planner::<2, 8>::new();
        assert!(p.push_move(&mv(1000, 0, 3000.0), &c));
        assert!(p.push_move(&mv(1000, 0, 1500.0), &c));
        let b = p.iter().nth(1).copied().expect("second");
        assert!((b.max_entry_sqr - 625.0).abs() < 1e-2);
    }

    /// X and Y as [`cfg`], and an extruder: 100 steps/mm, 50 mm/s, 2000 mm/s².
    fn printer() -> MachineConfig<3> {
        let mut e = AxisConfig::linear(b'E', 100.0, 3000.0, 2000.0, 1000.0);
        e.kind = AxisKind::Extruder;
        let c = cfg();
        let mut p = MachineConfig::new([c.axes[0], c.axes[1], e]);
        p.junction_deviation_mm = 0.05;
        p
    }

    fn mv3(steps: [i32; 3], feed: Option<f32>) -> MoveRequest<3> {
        MoveRequest {
            steps,
            feed_mm_min: feed,
            feed_scale: 1.0,
            ramp: false,
            line: 0,
            homing_mask: 0,
            exact_stop: false,
            fixed: false,
            spindle_rpm: 0,
        }
    }

    /// The acceleration of the single block `req` plans into an empty planner with `limits`.
    fn accel_of(limits: PathLimits, req: &MoveRequest<3>) -> f32 {
        let mut p = Planner::<3, 8>::new();
        p.set_limits(limits);
        assert!(p.push_move(req, &printer()));
        p.tail().expect("block").accel
    }

    #[test]
    fn path_accelerations_cap_each_kind_of_move() {
        let limits = PathLimits {
            print_accel_mm_s2: Some(300.0),
            retract_accel_mm_s2: Some(150.0),
            travel_accel_mm_s2: Some(600.0),
            ..PathLimits::NONE
        };
        let travel = mv3([1000, 0, 0], Some(3000.0));
        let print = mv3([1000, 0, 50], Some(3000.0));
        let retract = mv3([0, 0, -200], Some(2400.0));
        assert_eq!(accel_of(PathLimits::NONE, &travel), 1000.0);
        assert_eq!(accel_of(limits, &travel), 600.0);
        assert_eq!(accel_of(limits, &print), 300.0);
        assert_eq!(accel_of(limits, &retract), 150.0);
        // Without a cap for its kind, the per-axis limits alone.
        let no_print = PathLimits {
            print_accel_mm_s2: None,
            ..limits
        };
        assert!(accel_of(no_print, &print) > 990.0);
        // A cap never lets an axis exceed its own limit: the extruder's 2000 mm/s².
        let fast_retract = PathLimits {
            retract_accel_mm_s2: Some(5000.0),
            ..limits
        };
        assert_eq!(accel_of(fast_retract, &retract), 2000.0);
    }

    #[test]
    fn a_corner_is_taken_at_most_at_the_cap_of_the_new_move() {
        let c = cfg();
        let mut p = Planner::<2, 8>::new();
        p.set_limits(PathLimits {
            travel_accel_mm_s2: Some(100.0),
            ..PathLimits::NONE
        });
        assert!(p.push_move(&mv(10_000, 0, 3000.0), &c));
        assert!(p.push_move(&mv(0, 10_000, 3000.0), &c));
        let second = p.iter().nth(1).copied().expect("second");
        let sin_half = core::f32::consts::FRAC_1_SQRT_2;
        let expected = 100.0 * 0.05 * sin_half / (1.0 - sin_half);
        assert!((second.max_entry_sqr - expected).abs() < 1e-3);
    }

    #[test]
    fn the_feed_override_scales_feeds_and_rapids_within_the_rates() {
        let c = cfg();
        let nominal = |feed: Option<f32>, scale: f32| {
            let mut p = Planner::<2, 8>::new();
            let mut req = mv(1000, 0, 0.0);
            req.feed_mm_min = feed;
            req.feed_scale = scale;
            assert!(p.push_move(&req, &c));
            sqrtf(p.tail().expect("block").nominal_sqr)
        };
        assert!((nominal(Some(3000.0), 0.5) - 25.0).abs() < 1e-4);
        assert!((nominal(Some(2400.0), 2.0) - 80.0).abs() < 1e-4);
        // X's maximum rate, 100 mm/s, caps what the override asks for.
        assert_eq!(nominal(Some(4000.0), 2.0), 100.0);
        assert_eq!(nominal(None, 0.5), 50.0);
        assert_eq!(nominal(None, 1.5), 100.0);
    }

    #[test]
    fn the_slowest_feeds_raise_slow_moves_of_their_kind() {
        let nominal = |limits: PathLimits, req: &MoveRequest<3>| {
            let mut p = Planner::<3, 8>::new();
            p.set_limits(limits);
            assert!(p.push_move(req, &printer()));
            sqrtf(p.tail().expect("block").nominal_sqr)
        };
        let limits = PathLimits {
            min_extruding_feed_mm_s: 20.0,
            min_travel_feed_mm_s: 30.0,
            ..PathLimits::NONE
        };
        let travel = mv3([1000, 0, 0], Some(600.0));
        let retract = mv3([0, 0, -100], Some(600.0));
        assert!((nominal(PathLimits::NONE, &travel) - 10.0).abs() < 1e-4);
        assert!((nominal(limits, &travel) - 30.0).abs() < 1e-4);
        assert!((nominal(limits, &retract) - 20.0).abs() < 1e-4);
        // The floor is a feed along X (the extruder is left out of it) and never passes the
        // axes' maximum rates.
        let print = mv3([1000, 0, 1000], Some(600.0));
        let along_path = core::f32::consts::SQRT_2;
        assert!((nominal(limits, &print) - 20.0 * along_path).abs() < 1e-3);
        let fast = PathLimits {
            min_travel_feed_mm_s: 500.0,
            ..limits
        };
        assert_eq!(nominal(fast, &travel), 100.0);
    }

    #[test]
    fn full_ring_refuses_and_retire_frees() {
        let c = cfg();
        let mut p = Planner::<2, 4>::new();
        for _ in 0..4 {
            assert!(p.push_move(&mv(100, 0, 3000.0), &c));
        }
        assert!(p.is_full());
        assert!(!p.push_move(&mv(100, 0, 3000.0), &c));
        p.retire_tail();
        assert!(p.push_move(&mv(100, 0, 3000.0), &c));
        assert_eq!(p.len(), 4);
    }

    /// The feed's conversion kept from line to line is the conversion worked out each time.
    #[test]
    fn a_kept_feed_conversion_is_the_one_worked_out() {
        let mut kept = FeedPerSecond::ZERO;
        for (feed, scale) in [
            (0.0, 0.0),
            (3000.0, 1.0),
            (3000.0, 1.0),
            (3000.0, 0.5),
            (1234.5, 1.0),
            (1234.5, 0.25),
            (3000.0, 1.0),
        ] {
            let worked_out = feed * scale / 60.0;
            assert_eq!(
                kept.of(feed, scale).to_bits(),
                worked_out.to_bits(),
                "{feed} {scale}"
            );
        }
        assert_eq!(kept.of(3000.0, 1.0), 50.0);
    }

    /// Doubling, halving and scaling by their bits are the multiplications, to the bit, over
    /// the binades of the planner's values, their edges included.
    #[test]
    fn doubling_halving_and_scaling_by_bits_are_exact() {
        let check = |x: f32| {
            assert_eq!(doubled(x).to_bits(), (x * 2.0).to_bits(), "{x}");
            assert_eq!(halved(x).to_bits(), (x * 0.5).to_bits(), "{x}");
            assert_eq!(times(x, 1.0).to_bits(), x.to_bits(), "{x}");
            assert_eq!(times(x, 0.75).to_bits(), (x * 0.75).to_bits(), "{x}");
        };
        let edges = [
            0.0,
            f32::MIN_POSITIVE,
            f32::MIN_POSITIVE / 4.0,
            f32::MIN_POSITIVE * 2.0,
            f32::MAX,
            f32::MAX / 2.0,
            f32::INFINITY,
        ];
        edges.into_iter().for_each(check);
        let mut x = 1.0e-38f32;
        while x < 3.0e38 {
            check(x);
            check(x * 1.618_034);
            x *= 3.0;
        }
    }

    /// A junction the angle alone shows to be faster than either move may go is infinite;
    /// every other is the full computation's, and the full computation is at least the
    /// fastest speed wherever the test says so.
    #[test]
    fn a_junction_told_by_its_angle_alone_is_faster_than_either_move() {
        let mut c = MachineConfig::new([
            AxisConfig::linear(b'X', 80.0, 12_000.0, 3000.0, 500.0),
            AxisConfig::linear(b'Y', 80.0, 12_000.0, 500.0, 500.0),
            AxisConfig::linear(b'Z', 400.0, 900.0, 200.0, 500.0),
        ]);
        c.junction_deviation_mm = 0.01;
        let mut seed = 0x9e37_79b9u64;
        let mut random =
            move || f32::from(crate::testing::xorshift(&mut seed) as u16) / 65_536.0 - 0.5;
        let unit = |v: [f32; 3]| {
            let n = sqrtf(v.iter().map(|x| x * x).sum());
            v.map(|x| x / n)
        };
        let (mut told, mut worked_out) = (0, 0);
        for k in 0..20_000 {
            let p = unit([1.0, random(), random() * 0.1]);
            // Turns from a thousandth of a radian to a reversal.
            let bend = [0.001, 0.01, 0.1, 1.0, 3.0][k % 5] * random();
            let u = unit([1.0 + bend * random(), p[1] + bend, p[2] + bend * random()]);
            let fastest_sqr = [100.0, 10_000.0, 1.0e6][k % 3] * (1.0 + random());
            let exact = junction_speed_sqr(&p, &u, 0b111, &c, f32::INFINITY, f32::INFINITY);
            let quick = junction_speed_sqr(&p, &u, 0b111, &c, f32::INFINITY, fastest_sqr);
            // Just above the full computation's speed, the test never tells.
            if exact.is_finite() && exact > 0.0 {
                let above = exact * 1.000_01;
                let near = junction_speed_sqr(&p, &u, 0b111, &c, f32::INFINITY, above);
                assert_eq!(near.to_bits(), exact.to_bits(), "{exact}");
            }
            if quick.to_bits() == exact.to_bits() {
                worked_out += 1;
            } else {
                assert!(
                    quick.is_infinite() && exact >= fastest_sqr,
                    "{exact} {fastest_sqr}"
                );
                told += 1;
            }
        }
        assert!(told > 1000 && worked_out > 1000, "{told} {worked_out}");
    }
}
