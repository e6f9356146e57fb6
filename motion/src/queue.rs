//! The step queue: the one channel between the thread side and the step interrupt.
//!
//! A bounded single-producer/single-consumer ring of step events, plus the handful of flags the
//! two sides exchange (positions, start/idle handshake, flush and stop notices). It is built
//! from load/store atomics only — no compare-and-swap and no `unsafe` — so it works unchanged
//! on Cortex-M4 and on `riscv32imc`, which has no atomic read-modify-write instructions. Every
//! atomic has exactly one writer; the comments on each field name it.
//!
//! An event is two 32-bit words: the delay since the previous event in ticks (at most
//! [`MAX_DELTA`], the whole word: the interrupt reads it without masking), and three 8-bit axis
//! masks (directions to change, the new directions, step lines to raise) with a "rest" flag.
//! The interrupt applies them in that order; it ends each pulse itself, a pulse width after
//! the rising edge, so falling edges never travel through the queue.

#![deny(clippy::indexing_slicing)]

use core::sync::atomic::{AtomicI32, AtomicU32, Ordering};

/// Largest delay one event can carry; longer waits are split into empty events.
pub(crate) const MAX_DELTA: u32 = (1 << 30) - 1;
/// In an event's second word, above its three masks.
const REST_FLAG: u32 = 1 << 24;

/// One step event.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct Event {
    /// Ticks since the previous event; for the first event after an idle interrupt, ticks since
    /// the interrupt was started.
    pub delta: u32,
    /// After this event the machine is at rest: the interrupt may go idle if nothing follows.
    pub rest: bool,
    /// Axes whose direction line changes.
    pub dir_set: u8,
    /// New directions of those axes: bit set = negative.
    pub dir_neg: u8,
    /// Step lines to raise (one step each).
    pub rise: u8,
}

/// An event's second word but its rest flag: the axes whose direction changes, their new
/// directions, the step lines to raise.
#[inline(always)]
fn masks_word(dir_set: u8, dir_neg: u8, rise: u8) -> u32 {
    u32::from(dir_set) | u32::from(dir_neg) << 8 | u32::from(rise) << 16
}

impl Event {
    fn encode(&self) -> [u32; 2] {
        [
            self.delta & MAX_DELTA,
            masks_word(self.dir_set, self.dir_neg, self.rise)
                | if self.rest { REST_FLAG } else { 0 },
        ]
    }

    #[cfg(test)]
    fn decode(w: Raw) -> Self {
        Self {
            delta: w.delta(),
            rest: w.rest(),
            dir_set: w.dir_set(),
            dir_neg: w.dir_neg(),
            rise: w.rise(),
        }
    }
}

/// One step event as the queue holds it: the interrupt side reads its fields straight from
/// the two words.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct Raw {
    time: u32,
    masks: u32,
}

impl Raw {
    /// See [`Event::delta`].
    #[inline(always)]
    pub(crate) fn delta(self) -> u32 {
        self.time
    }

    /// See [`Event::rest`].
    #[inline(always)]
    pub(crate) fn rest(self) -> bool {
        self.masks & REST_FLAG != 0
    }

    /// See [`Event::dir_set`].
    #[inline(always)]
    pub(crate) fn dir_set(self) -> u8 {
        self.masks as u8
    }

    /// See [`Event::dir_neg`].
    #[inline(always)]
    pub(crate) fn dir_neg(self) -> u8 {
        (self.masks >> 8) as u8
    }

    /// See [`Event::rise`].
    #[inline(always)]
    pub(crate) fn rise(self) -> u8 {
        (self.masks >> 16) as u8
    }
}

/// [`StepQueue::probe`]: no probing move.
pub(crate) const PROBE_OFF: u32 = 0;
/// [`StepQueue::probe`]: the move stops when the probe touches (`G38.2`, `G38.3`).
pub(crate) const PROBE_CONTACT: u32 = 1;
/// [`StepQueue::probe`]: the move stops when the probe loses contact (`G38.4`, `G38.5`).
pub(crate) const PROBE_RELEASE: u32 = 2;

/// Why the interrupt stopped motion on its own (published in [`StepQueue`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum StopCause {
    /// A hard limit tripped on this axis.
    HardLimit(u8),
    /// The homing switch of this axis triggered.
    HomingSwitch(u8),
    /// A driver or switch error on this axis.
    Fault(u8),
    /// The queue ran dry while moving.
    Underrun,
    /// The probe reached the state a probing move waits for.
    Probe,
}

impl StopCause {
    fn encode(self) -> u32 {
        match self {
            Self::HardLimit(a) => 0x100 | u32::from(a),
            Self::HomingSwitch(a) => 0x200 | u32::from(a),
            Self::Fault(a) => 0x300 | u32::from(a),
            Self::Underrun => 0x400,
            Self::Probe => 0x500,
        }
    }

    fn decode(w: u32) -> Option<Self> {
        let a = w as u8;
        match w >> 8 {
            1 => Some(Self::HardLimit(a)),
            2 => Some(Self::HomingSwitch(a)),
            3 => Some(Self::Fault(a)),
            4 => Some(Self::Underrun),
            5 => Some(Self::Probe),
            _ => None,
        }
    }
}

/// The storage shared by the thread side ([`crate::Kernel`]) and the step interrupt
/// ([`crate::StepGenerator`]): `N` axes, `Q` event slots (a power of two).
///
/// Create it where it can outlive both sides — a `static` (through the executor's
/// `&'static mut` resources, e.g. RTIC `#[init(local = [...])]`) or a stack variable in tests —
/// and hand it to [`crate::split`].
pub struct StepQueue<const N: usize, const Q: usize> {
    /// Event words. Written by the producer before it publishes `head`.
    slots: [[AtomicU32; 2]; Q],
    /// Events pushed (free-running). Writer: thread.
    head: AtomicU32,
    /// Events consumed (free-running). Writer: interrupt.
    tail: AtomicU32,
    /// Machine position of each axis in steps. Writer: interrupt (thread only while idle).
    pub(crate) positions: [AtomicI32; N],
    /// Sum of the deltas of consumed events, wrapping. Writer: interrupt.
    pub(crate) consumed_ticks: AtomicU32,
    /// Scheduled instant (ticks) of the last consumed event, or of the start after idle.
    /// Writer: interrupt.
    pub(crate) last_event_at: AtomicU32,
    /// Times the thread started an idle interrupt. Writer: thread.
    pub(crate) starts: AtomicU32,
    /// Times the interrupt went idle. Writer: interrupt.
    pub(crate) idles: AtomicU32,
    /// Flush requests. Writer: thread.
    pub(crate) flush_req: AtomicU32,
    /// Flushes done. Writer: interrupt.
    pub(crate) flush_done: AtomicU32,
    /// Stops on the interrupt's own initiative. Writer: interrupt.
    pub(crate) stops: AtomicU32,
    /// Cause of the last stop. Writer: interrupt.
    stop_cause: AtomicU32,
    /// Axes whose switch ends the current (homing) move. Writer: thread.
    pub(crate) homing_mask: AtomicU32,
    /// What ends the current (probing) move: [`PROBE_OFF`], [`PROBE_CONTACT`] or
    /// [`PROBE_RELEASE`]. Writer: thread.
    pub(crate) probe: AtomicU32,
    /// Limit switch input edges reported (wrapping count). Writers: the contexts that hold a
    /// [`SwitchAlert`]; see there why more than one is safe.
    pub(crate) switch_edges: AtomicU32,
}

impl<const N: usize, const Q: usize> Default for StepQueue<N, Q> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize, const Q: usize> StepQueue<N, Q> {
    const CHECK: () = {
        assert!(
            Q.is_power_of_two() && Q >= 8,
            "Q must be a power of two >= 8"
        );
        assert!(N >= 1 && N <= crate::MAX_AXES, "1 to 8 axes");
    };

    /// An empty queue with every axis at step 0.
    pub const fn new() -> Self {
        #[allow(clippy::let_unit_value)]
        let () = Self::CHECK;
        Self {
            slots: [const { [const { AtomicU32::new(0) }; 2] }; Q],
            head: AtomicU32::new(0),
            tail: AtomicU32::new(0),
            positions: [const { AtomicI32::new(0) }; N],
            consumed_ticks: AtomicU32::new(0),
            last_event_at: AtomicU32::new(0),
            starts: AtomicU32::new(0),
            idles: AtomicU32::new(0),
            flush_req: AtomicU32::new(0),
            flush_done: AtomicU32::new(0),
            stops: AtomicU32::new(0),
            stop_cause: AtomicU32::new(0),
            homing_mask: AtomicU32::new(0),
            probe: AtomicU32::new(PROBE_OFF),
            switch_edges: AtomicU32::new(0),
        }
    }

    /// Number of event slots.
    pub const fn capacity(&self) -> usize {
        Q
    }

    /// The machine position of every axis, in steps, as the interrupt last published it.
    pub fn positions(&self) -> [i32; N] {
        let mut out = [0; N];
        for (o, p) in out.iter_mut().zip(self.positions.iter()) {
            *o = p.load(Ordering::Relaxed);
        }
        out
    }

    #[inline(always)]
    fn slot(&self, counter: u32) -> Option<&[AtomicU32; 2]> {
        // `Q` is a power of two, so the mask keeps the index in range.
        self.slots.get(counter as usize & (Q - 1))
    }

    pub(crate) fn set_stop_cause(&self, cause: StopCause) {
        self.stop_cause.store(cause.encode(), Ordering::Relaxed);
        let n = self.stops.load(Ordering::Relaxed);
        self.stops.store(n.wrapping_add(1), Ordering::Release);
    }

    pub(crate) fn stop_cause(&self) -> Option<StopCause> {
        StopCause::decode(self.stop_cause.load(Ordering::Relaxed))
    }
}

/// Reports limit switch input edges to the step interrupt.
///
/// Outside homing, the step interrupt samples the limit switches only while one may matter:
/// from the start of each motion until every switch reads released and settled, and again
/// after an edge is reported here, until they are all released and settled once more. A board
/// calls [`SwitchAlert::notify`] on every edge of every switch input, from the pin-change
/// interrupt of the inputs (EXTI on an STM32, the GPIO interrupt on an ESP32); the next step
/// of an axis towards a triggered switch then stops motion. A board with no pin-change
/// interrupt calls it from a periodic timer instead, and gets hard limits within that period.
///
/// Get one from [`crate::StepGenerator::switch_alert`]. It is `Copy` and may live in a
/// `static`: it only holds a reference to the [`StepQueue`].
///
/// Context: any, including interrupts of any priority. One load and one store; no
/// read-modify-write atomics. Two contexts notifying at once may count one edge instead of
/// two, which loses nothing: the step interrupt reads the count before it samples, so any
/// count it has not seen makes it sample, and an edge whose count it has seen happened before
/// that sample.
#[derive(Debug, Clone, Copy)]
pub struct SwitchAlert<'q> {
    edges: &'q AtomicU32,
}

impl<'q> SwitchAlert<'q> {
    pub(crate) fn new<const N: usize, const Q: usize>(q: &'q StepQueue<N, Q>) -> Self {
        Self {
            edges: &q.switch_edges,
        }
    }

    /// A limit switch input changed level.
    #[inline]
    pub fn notify(&self) {
        let n = self.edges.load(Ordering::Relaxed);
        self.edges.store(n.wrapping_add(1), Ordering::Release);
    }
}

/// The thread's end of the queue. Events are written ahead of what the interrupt sees and
/// made visible together ([`Producer::publish`]); until then the last one written can still
/// change ([`Producer::amend_last`]).
pub(crate) struct Producer<'q, const N: usize, const Q: usize> {
    q: &'q StepQueue<N, Q>,
    /// Events published (free-running): the interrupt sees those before it.
    head: u32,
    /// Events written (free-running), published or not.
    next: u32,
}

impl<'q, const N: usize, const Q: usize> Producer<'q, N, Q> {
    pub(crate) fn new(q: &'q StepQueue<N, Q>) -> Self {
        let head = q.head.load(Ordering::Relaxed);
        Self {
            q,
            head,
            next: head,
        }
    }

    pub(crate) fn shared(&self) -> &'q StepQueue<N, Q> {
        self.q
    }

    /// Slots free now.
    pub(crate) fn free(&self) -> usize {
        let tail = self.q.tail.load(Ordering::Acquire);
        Q - self.next.wrapping_sub(tail) as usize
    }

    /// Events written so far (free-running, published or not): the difference of two
    /// readings is the events written between them.
    #[inline(always)]
    pub(crate) fn written(&self) -> u32 {
        self.next
    }

    /// Run `writes` on a copy of this producer, and take its writes back: a loop of writes
    /// keeps the copy's write position in a register, where this producer's, behind a
    /// reference, would be stored at every write.
    #[inline(always)]
    pub(crate) fn in_run<R>(&mut self, writes: impl FnOnce(&mut Self) -> R) -> R {
        let mut run = Self {
            q: self.q,
            head: self.head,
            next: self.next,
        };
        let result = writes(&mut run);
        self.next = run.next;
        result
    }

    /// Events written and not yet taken by the interrupt.
    pub(crate) fn len(&self) -> usize {
        Q - self.free()
    }

    /// Push one event and publish it; `false` when full.
    #[cfg(test)]
    pub(crate) fn push(&mut self, ev: Event) -> bool {
        if self.free() == 0 {
            return false;
        }
        let written = self.write(&ev);
        self.publish();
        written
    }

    /// Write one event, unpublished, into a slot the caller knows is free (from
    /// [`Producer::free`] since its last writes); `false`, and nothing written, when there is
    /// none after all.
    #[inline(always)]
    pub(crate) fn write(&mut self, ev: &Event) -> bool {
        let [w0, w1] = ev.encode();
        let Some([s0, s1]) = self.q.slot(self.next) else {
            return false;
        };
        s0.store(w0, Ordering::Relaxed);
        s1.store(w1, Ordering::Relaxed);
        self.next = self.next.wrapping_add(1);
        true
    }

    /// [`Producer::write`] of the rising edges of `rise` alone, `delta` (at most
    /// [`MAX_DELTA`]) after the last event: the walks' one kind of event, with nothing to
    /// mask.
    #[inline(always)]
    pub(crate) fn write_rise(&mut self, delta: u32, rise: u8) -> bool {
        debug_assert!(delta <= MAX_DELTA);
        let Some([s0, s1]) = self.q.slot(self.next) else {
            return false;
        };
        s0.store(delta, Ordering::Relaxed);
        s1.store(masks_word(0, 0, rise), Ordering::Relaxed);
        self.next = self.next.wrapping_add(1);
        true
    }

    /// Merge `ev`'s edges and flags into the last event written, if it is not published yet
    /// (its delta stays); `false` when there is none such.
    #[inline(always)]
    pub(crate) fn amend_last(&mut self, ev: &Event) -> bool {
        if self.next == self.head {
            return false;
        }
        let Some([s0, s1]) = self.q.slot(self.next.wrapping_sub(1)) else {
            return false;
        };
        let last = Raw {
            time: s0.load(Ordering::Relaxed),
            masks: s1.load(Ordering::Relaxed),
        };
        let merged = Event {
            delta: last.delta(),
            rest: last.rest() || ev.rest,
            dir_set: last.dir_set() | ev.dir_set,
            dir_neg: (last.dir_neg() & !ev.dir_set) | ev.dir_neg,
            rise: last.rise() | ev.rise,
        };
        let [w0, w1] = merged.encode();
        s0.store(w0, Ordering::Relaxed);
        s1.store(w1, Ordering::Relaxed);
        true
    }

    /// Make every event written visible to the interrupt.
    #[inline(always)]
    pub(crate) fn publish(&mut self) {
        if self.head != self.next {
            self.head = self.next;
            self.q.head.store(self.head, Ordering::Release);
        }
    }
}

/// The interrupt's end of the queue.
pub(crate) struct Consumer<'q, const N: usize, const Q: usize> {
    pub(crate) q: &'q StepQueue<N, Q>,
    tail: u32,
}

impl<'q, const N: usize, const Q: usize> Consumer<'q, N, Q> {
    pub(crate) fn new(q: &'q StepQueue<N, Q>) -> Self {
        Self {
            q,
            tail: q.tail.load(Ordering::Relaxed),
        }
    }

    /// The oldest event, without removing it.
    #[inline(always)]
    pub(crate) fn peek(&self) -> Option<Raw> {
        let head = self.q.head.load(Ordering::Acquire);
        if head == self.tail {
            return None;
        }
        let [s0, s1] = self.q.slot(self.tail)?;
        Some(Raw {
            time: s0.load(Ordering::Relaxed),
            masks: s1.load(Ordering::Relaxed),
        })
    }

    /// Remove the oldest event (after a successful [`Consumer::peek`]).
    #[inline(always)]
    pub(crate) fn advance(&mut self) {
        self.tail = self.tail.wrapping_add(1);
        self.q.tail.store(self.tail, Ordering::Release);
    }

    /// Drop every event pushed so far.
    pub(crate) fn clear(&mut self) {
        self.tail = self.q.head.load(Ordering::Acquire);
        self.q.tail.store(self.tail, Ordering::Release);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_round_trip_through_the_ring() {
        let q = StepQueue::<3, 8>::new();
        let mut p = Producer::new(&q);
        let mut c = Consumer::new(&q);
        assert_eq!(c.peek(), None);
        for k in 0..20u32 {
            let ev = Event {
                delta: k * 1000 + 7,
                rest: k % 3 == 0,
                dir_set: k as u8,
                dir_neg: 2,
                rise: 0x80 | k as u8,
            };
            assert!(p.push(ev));
            assert_eq!(c.peek().map(Event::decode), Some(ev));
            c.advance();
        }
        for _ in 0..8 {
            assert!(p.push(Event::default()));
        }
        assert!(!p.push(Event::default()));
        assert_eq!(p.len(), 8);
        c.clear();
        assert_eq!(p.free(), 8);
    }

    #[test]
    fn stop_causes_round_trip() {
        for c in [
            StopCause::HardLimit(3),
            StopCause::HomingSwitch(0),
            StopCause::Fault(7),
            StopCause::Underrun,
            StopCause::Probe,
        ] {
            assert_eq!(StopCause::decode(c.encode()), Some(c));
        }
    }
}
