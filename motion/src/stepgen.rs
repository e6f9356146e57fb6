//! The interrupt side: [`StepGenerator::on_alarm`] turns queued step events into pin edges.
//!
//! Context: the step interrupt (a one-shot timer alarm on the board's clock). Integer-only,
//! allocation-free, panic-free, no blocking; each call lowers the step lines whose pulse is
//! over, then handles at most one event — change directions, check the switches of the axes
//! about to step, raise step lines — and returns when to be called next: the next event or the
//! end of a pulse, whichever comes first. Step times and direction set-up were decided by the
//! thread side; this side keeps the schedule (`next = previous scheduled time + delta`, so
//! interrupt latency never accumulates; the first event after idle is due its delta after the
//! start) and ends every pulse a pulse width after its rising edge was served. A line still
//! high when its axis must step again or change direction (a rising edge served late) delays
//! that event, and the schedule after it, until the line has been low for a pulse width.

#![deny(clippy::indexing_slicing, clippy::arithmetic_side_effects)]

use core::sync::atomic::Ordering;

use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::stepper::{Direction, Stepper};
use forja_hal_abstraction::time::{Duration, Instant};

use crate::config::{HomeDirection, MachineConfig};
use crate::queue::{Consumer, PROBE_CONTACT, PROBE_OFF, Raw, StepQueue, StopCause, SwitchAlert};

/// No switch for this axis.
const NO_SWITCH: u8 = u8::MAX;

/// The lowest set bit of each axis mask: one load, where RV32IMC (the ESP32-C3's core, which
/// has no count-trailing-zeros instruction) would take a dozen instructions to count them.
// Evaluated by the compiler: an index out of range would fail the build, not panic.
#[allow(clippy::indexing_slicing, clippy::arithmetic_side_effects)]
const LOWEST_AXIS: [u8; 256] = {
    let mut t = [0u8; 256];
    let mut m = 1;
    while m < 256 {
        t[m] = (m as u8).trailing_zeros() as u8;
        m += 1;
    }
    t
};

/// The lowest axis in `mask` (0 for an empty mask).
#[inline(always)]
fn lowest_axis(mask: u8) -> usize {
    usize::from(LOWEST_AXIS.get(usize::from(mask)).copied().unwrap_or(0))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    /// No alarm armed; the thread side starts us.
    Idle,
    /// Executing events; `next_at` is armed.
    Running,
    /// Stopped, or at the end of motion: waiting for the last pulses to end.
    WindDown,
}

/// The interrupt side of the kernel. Created by [`crate::split`]; owned by the step interrupt.
pub struct StepGenerator<'q, const N: usize, const Q: usize> {
    rx: Consumer<'q, N, Q>,
    mode: Mode,
    /// Position change of one step of each axis: +1 or -1, by its direction line.
    step_sign: [i32; N],
    dir_neg: u8,
    high: u8,
    /// When the pulse of each raised line ends.
    fall_at: [Instant; N],
    /// The earliest of `fall_at` over the raised lines (meaningless when none is).
    next_fall: Instant,
    next_ev: Raw,
    next_at: Instant,
    /// Scheduled instant of the last consumed event (or of the start after idle).
    last_at: Instant,
    wake_at: Instant,
    discard: bool,
    flush_seen: u32,
    consumed_ticks: u32,
    /// Sample the switches at every rising edge (see [`SwitchAlert`]).
    watch: bool,
    edges_seen: u32,
    switch_of: [u8; N],
    has_switch: u8,
    switch_neg: u8,
    /// The probe's index among the switches ([`NO_SWITCH`]: none).
    probe_of: u8,
    hard_limits: bool,
    pulse: Duration,
    /// The drivers' direction set-up time.
    dir_setup: Duration,
    /// Axes whose direction line changed less than `dir_setup` ago (at the latest), and when
    /// the last of them is ready.
    settling: u8,
    dir_ready_at: Instant,
}

impl<'q, const N: usize, const Q: usize> StepGenerator<'q, N, Q> {
    pub(crate) fn new(
        q: &'q StepQueue<N, Q>,
        config: &MachineConfig<N>,
        pulse: Duration,
        dir_setup: Duration,
    ) -> Self {
        let mut switch_of = [NO_SWITCH; N];
        let mut has_switch = 0u8;
        let mut switch_neg = 0u8;
        for (i, (a, slot)) in config.axes.iter().zip(switch_of.iter_mut()).enumerate() {
            if let Some(h) = a.homing {
                *slot = h.switch;
                has_switch |= 1 << i;
                if h.direction == HomeDirection::Min {
                    switch_neg |= 1 << i;
                }
            }
        }
        Self {
            rx: Consumer::new(q),
            mode: Mode::Idle,
            step_sign: [1; N],
            dir_neg: 0,
            high: 0,
            fall_at: [Instant::from_ticks(0); N],
            next_fall: Instant::from_ticks(0),
            next_ev: Raw::default(),
            next_at: Instant::from_ticks(0),
            last_at: Instant::from_ticks(q.last_event_at.load(Ordering::Relaxed)),
            wake_at: Instant::from_ticks(0),
            discard: false,
            flush_seen: q.flush_req.load(Ordering::Relaxed),
            consumed_ticks: q.consumed_ticks.load(Ordering::Relaxed),
            watch: true,
            edges_seen: q.switch_edges.load(Ordering::Relaxed),
            switch_of,
            has_switch,
            switch_neg,
            probe_of: config.probe_switch.unwrap_or(NO_SWITCH),
            hard_limits: config.hard_limits,
            pulse,
            dir_setup,
            settling: 0,
            dir_ready_at: Instant::from_ticks(0),
        }
    }

    /// Whether no alarm is pending: the thread side will start us when there is motion.
    pub fn is_idle(&self) -> bool {
        self.mode == Mode::Idle
    }

    /// The position of every axis, in steps, counted by this side.
    pub fn positions(&self) -> [i32; N] {
        self.rx.q.positions()
    }

    /// The handle a board's limit switch interrupt reports input edges through.
    pub fn switch_alert(&self) -> SwitchAlert<'q> {
        SwitchAlert::new(self.rx.q)
    }

    /// Handle the step alarm.
    ///
    /// Call it when the alarm fires, with the current time, the `N` steppers (axis `i` is
    /// `steppers[i]`) and the limit switches (indexed by each axis's `homing.switch`). Arm the
    /// alarm at the returned instant, or leave it disarmed on `None` (idle until the thread
    /// side's `poll` asks for a start).
    ///
    /// The switches are sampled only while one may matter (see [`SwitchAlert`]): from the
    /// start of a motion until all read released and settled, during homing, and after the
    /// board reports an edge. Then every switch is sampled at every event that raises a step
    /// line, and a triggered one stops motion before the step of its axis towards it.
    ///
    /// Context: interrupt. Never blocks, never allocates, never panics. A driver or switch
    /// error stops motion with [`crate::Alarm::DriverFault`]; a switch read error counts as
    /// triggered.
    #[inline]
    pub fn on_alarm<S: Stepper, L: LimitSwitch>(
        &mut self,
        now: Instant,
        steppers: &mut [S; N],
        switches: &mut [L],
    ) -> Option<Instant> {
        // An event due (or any alarm out of the running state): the general path, asked
        // first, as most alarms are a step's.
        if now.is_at_or_after(self.wake_at) {
            return self.serve(now, steppers, switches);
        }
        // The end of a pulse before the next event, the call of every other alarm.
        let high = self.high;
        if self.mode == Mode::Running && high != 0 && now.is_at_or_after(self.next_fall) {
            // One line raised (one axis moving, or the others' pulses over): it is the one
            // due, ended here without the general path's registers saved and restored.
            if high & high.wrapping_sub(1) == 0 {
                return match self.end_one_pulse(high, steppers) {
                    Ok(_) => Some(self.wake_at),
                    Err(cause) => self.stop(now, cause, steppers),
                };
            }
            return self.end_of_pulse(now, steppers);
        }
        self.serve(now, steppers, switches)
    }

    /// [`StepGenerator::on_alarm`] between events: end the pulses that are over.
    #[inline(never)]
    fn end_of_pulse<S: Stepper>(&mut self, now: Instant, steppers: &mut [S; N]) -> Option<Instant> {
        match self.end_pulses(now, steppers) {
            Ok(_) => Some(self.soonest()),
            Err(cause) => self.stop(now, cause, steppers),
        }
    }

    /// [`StepGenerator::on_alarm`] at an event, or out of the running state.
    #[inline(never)]
    fn serve<S: Stepper, L: LimitSwitch>(
        &mut self,
        now: Instant,
        steppers: &mut [S; N],
        switches: &mut [L],
    ) -> Option<Instant> {
        let q = self.rx.q;
        // Pulses end first, also in a call that has no event to serve.
        let mut lowered = 0;
        if self.high != 0 && now.is_at_or_after(self.next_fall) {
            lowered = match self.end_pulses(now, steppers) {
                Ok(m) => m,
                Err(cause) => return self.stop(now, cause, steppers),
            };
        }
        let ev = if self.mode == Mode::Running
            && q.flush_req.load(Ordering::Acquire) == self.flush_seen
        {
            if !now.is_at_or_after(self.wake_at) {
                return Some(self.soonest());
            }
            // Peeked by the previous call; only this side removes events.
            self.next_ev
        } else {
            match self.unusual(now, steppers) {
                Ok(ev) => ev,
                Err(next) => return next,
            }
        };
        // A line still high (its rising edge was served late) ends its pulse before its axis
        // changes direction, and stays low a pulse width before it rises again; a direction
        // written late is given its set-up time before the axis steps.
        if (ev.dir_set() & self.high) | (ev.rise() & (self.high | lowered | self.settling)) != 0
            && let Some(at) = self.wait_for_lines(now, ev, lowered)
        {
            return Some(at);
        }
        self.rx.advance();
        self.consumed_ticks = self.consumed_ticks.wrapping_add(ev.delta());
        self.last_at = self.next_at;
        if let Err(cause) = self.execute(ev, now, steppers, switches) {
            return self.stop(now, cause, steppers);
        }
        match self.rx.peek() {
            Some(next) => {
                self.next_ev = next;
                self.next_at = self
                    .next_at
                    .wrapping_add(Duration::from_ticks(next.delta()));
                self.wake_at = self.next_at;
                Some(self.soonest())
            }
            None => self.ran_dry(now, ev.rest(), steppers),
        }
    }

    /// The next instant something is due: the next event, or the end of a pulse before it.
    #[inline(always)]
    fn soonest(&self) -> Instant {
        if self.high != 0 && !self.next_fall.is_at_or_after(self.wake_at) {
            self.next_fall
        } else {
            self.wake_at
        }
    }

    /// Lower the one raised line (`high`, a single bit), whose pulse is due to end; returns
    /// it, or the cause of the stop when its driver failed.
    #[inline(always)]
    fn end_one_pulse<S: Stepper>(
        &mut self,
        high: u8,
        steppers: &mut [S; N],
    ) -> Result<u8, StopCause> {
        let i = lowest_axis(high);
        self.high = 0;
        match steppers.get_mut(i).map(|s| s.step_end()) {
            Some(Err(_)) => Err(StopCause::Fault(i as u8)),
            _ => Ok(high),
        }
    }

    /// Lower the raised lines whose pulse is over at `now`; returns them, or the first axis
    /// whose driver failed (after trying every one).
    #[inline(always)]
    fn end_pulses<S: Stepper>(
        &mut self,
        now: Instant,
        steppers: &mut [S; N],
    ) -> Result<u8, StopCause> {
        let high = self.high;
        // One line raised (one axis moving, or the others' pulses over): it is the one due.
        if high & high.wrapping_sub(1) == 0 {
            return self.end_one_pulse(high, steppers);
        }
        let mut due = 0u8;
        let mut failed = None;
        let mut next: Option<Instant> = None;
        // Only the raised axes, lowest first: the cost follows the axes that step.
        let mut axes = self.high;
        while axes != 0 {
            let i = lowest_axis(axes);
            axes &= axes.wrapping_sub(1);
            let Some(&at) = self.fall_at.get(i) else {
                continue;
            };
            if now.is_at_or_after(at) {
                due |= 1 << i;
                if let Some(s) = steppers.get_mut(i)
                    && s.step_end().is_err()
                {
                    failed = failed.or(Some(StopCause::Fault(i as u8)));
                }
            } else if next.is_none_or(|n| n.is_at_or_after(at)) {
                next = Some(at);
            }
        }
        self.high &= !due;
        if let Some(n) = next {
            self.next_fall = n;
        }
        failed.map_or(Ok(due), Err)
    }

    /// `ev` needs a line low that is high or was lowered just now, or steps an axis whose
    /// direction changed less than the set-up time ago: `Some` instant to serve it at, once
    /// the line has been low a pulse width and the direction set up, or `None` when it may be
    /// served now. The events after it keep their spacing: the schedule moves by the delay.
    #[cold]
    #[inline(never)]
    fn wait_for_lines(&mut self, now: Instant, ev: Raw, lowered: u8) -> Option<Instant> {
        if now.is_at_or_after(self.dir_ready_at) {
            self.settling = 0;
        }
        let mut until = now;
        if ev.rise() & self.settling != 0 {
            until = self.dir_ready_at;
        }
        if ev.rise() & lowered != 0 {
            let low = now.wrapping_add(self.pulse);
            if low.is_at_or_after(until) {
                until = low;
            }
        }
        let mut axes = (ev.dir_set() | ev.rise()) & self.high;
        while axes != 0 {
            let i = lowest_axis(axes);
            axes &= axes.wrapping_sub(1);
            if let Some(&at) = self.fall_at.get(i) {
                let low = at.wrapping_add(self.pulse);
                if low.is_at_or_after(until) {
                    until = low;
                }
            }
        }
        if until == now {
            return None;
        }
        self.next_at = until;
        self.wake_at = until;
        Some(self.soonest())
    }

    /// Everything but an event of a running motion: a flush, a stop, the wind-down, the start
    /// after idle. `Ok` with the event to execute now, or `Err` with what to return.
    #[cold]
    #[inline(never)]
    fn unusual<S: Stepper>(
        &mut self,
        now: Instant,
        steppers: &mut [S; N],
    ) -> Result<Raw, Option<Instant>> {
        let q = self.rx.q;
        let req = q.flush_req.load(Ordering::Acquire);
        if req != self.flush_seen {
            self.flush_seen = req;
            self.rx.clear();
            self.discard = false;
            self.publish();
            q.flush_done.store(req, Ordering::Release);
            return Err(self.wind_down(now, steppers));
        }
        if self.discard {
            self.rx.clear();
            return Err(self.wind_down(now, steppers));
        }
        match self.mode {
            Mode::WindDown => Err(self.wind_down(now, steppers)),
            // Only reached from the fast path's own conditions, never here; kept correct anyway.
            Mode::Running if !now.is_at_or_after(self.wake_at) => Err(Some(self.wake_at)),
            Mode::Running => Ok(self.next_ev),
            Mode::Idle => {
                let Some(ev) = self.rx.peek() else {
                    return Err(self.go_idle());
                };
                // The start is the instant the queued timeline resumes from: the first event is
                // due its delta after it (a dwell at rest, the first half step of a move).
                self.mode = Mode::Running;
                // A switch may have been hit while nothing sampled: sample until all are quiet.
                self.watch = true;
                self.last_at = now;
                self.publish();
                self.next_ev = ev;
                self.next_at = now.wrapping_add(Duration::from_ticks(ev.delta()));
                self.wake_at = self.next_at;
                if !now.is_at_or_after(self.wake_at) {
                    return Err(Some(self.wake_at));
                }
                Ok(ev)
            }
        }
    }

    /// The queue is empty after an event: the end of a motion, or an underrun.
    #[cold]
    #[inline(never)]
    fn ran_dry<S: Stepper>(
        &mut self,
        now: Instant,
        rest: bool,
        steppers: &mut [S; N],
    ) -> Option<Instant> {
        if !rest {
            return self.stop(now, StopCause::Underrun, steppers);
        }
        if self.high == 0 {
            return self.go_idle();
        }
        self.wind_down(now, steppers)
    }

    #[inline(always)]
    fn execute<S: Stepper, L: LimitSwitch>(
        &mut self,
        ev: Raw,
        now: Instant,
        steppers: &mut [S; N],
        switches: &mut [L],
    ) -> Result<(), StopCause> {
        if ev.dir_set() != 0 {
            self.change_directions(ev, now, steppers)?;
        }
        let rise = ev.rise();
        if rise == 0 {
            return Ok(());
        }
        let q = self.rx.q;
        self.publish();
        if self.watch || q.switch_edges.load(Ordering::Relaxed) != self.edges_seen {
            self.check_switches(rise, switches)?;
        }
        let fall = now.wrapping_add(self.pulse);
        let mut axes = rise;
        while axes != 0 {
            let i = lowest_axis(axes);
            axes &= axes.wrapping_sub(1);
            if let (Some(s), Some(p), Some(d), Some(f)) = (
                steppers.get_mut(i),
                q.positions.get(i),
                self.step_sign.get(i),
                self.fall_at.get_mut(i),
            ) {
                if s.step_begin().is_err() {
                    *f = fall;
                    return Err(self.failed_rise(i, rise & !axes, fall));
                }
                p.store(
                    p.load(Ordering::Relaxed).wrapping_add(*d),
                    Ordering::Relaxed,
                );
                *f = fall;
            }
        }
        self.mark_raised(rise, fall);
        Ok(())
    }

    /// The lines of `raised` went high, their pulses to end at `fall`; lines already high end
    /// sooner than these.
    #[inline(always)]
    fn mark_raised(&mut self, raised: u8, fall: Instant) {
        if self.high == 0 {
            self.next_fall = fall;
        }
        self.high |= raised;
    }

    /// Write the direction lines an event changes.
    #[cold]
    #[inline(never)]
    fn change_directions<S: Stepper>(
        &mut self,
        ev: Raw,
        now: Instant,
        steppers: &mut [S; N],
    ) -> Result<(), StopCause> {
        self.dir_ready_at = now.wrapping_add(self.dir_setup);
        for ((i, s), sign) in steppers
            .iter_mut()
            .enumerate()
            .zip(self.step_sign.iter_mut())
        {
            let bit = 1u8 << i;
            if ev.dir_set() & bit == 0 {
                continue;
            }
            let (d, step) = if ev.dir_neg() & bit != 0 {
                (Direction::Negative, -1)
            } else {
                (Direction::Positive, 1)
            };
            s.set_direction(d).map_err(|_| StopCause::Fault(i as u8))?;
            *sign = step;
            self.settling |= bit;
            self.dir_neg = (self.dir_neg & !bit) | (ev.dir_neg() & bit);
        }
        Ok(())
    }

    /// Sample every switch before the axes of `rise` step: a switch triggered towards the
    /// motion of its axis (a homing switch, or any with hard limits on) stops motion, and so
    /// does the probe in the state a probing move waits for. Keeps sampling at the following
    /// steps until every switch reads released and settled and no homing or probing move is
    /// under way.
    #[cold]
    #[inline(never)]
    fn check_switches<L: LimitSwitch>(
        &mut self,
        rise: u8,
        switches: &mut [L],
    ) -> Result<(), StopCause> {
        let q = self.rx.q;
        // Read before sampling: an edge reported after this read is sampled next time.
        self.edges_seen = q.switch_edges.load(Ordering::Acquire);
        let homing = q.homing_mask.load(Ordering::Relaxed) as u8;
        let toward = !(self.dir_neg ^ self.switch_neg);
        let stopping =
            rise & self.has_switch & toward & if self.hard_limits { 0xFF } else { homing };
        let probe = q.probe.load(Ordering::Relaxed);
        let mut quiet = homing == 0 && probe == PROBE_OFF;
        if probe != PROBE_OFF
            && let Some(sw) = switches.get_mut(usize::from(self.probe_of))
        {
            // A read error counts as contact, as a switch's counts as triggered.
            let contact = sw.is_triggered().unwrap_or(true);
            if contact == (probe == PROBE_CONTACT) {
                return Err(StopCause::Probe);
            }
        }
        for (i, idx) in self.switch_of.iter().enumerate() {
            let Some(sw) = switches.get_mut(usize::from(*idx)) else {
                continue;
            };
            let bit = 1u8 << i;
            let triggered = sw.is_triggered().unwrap_or(true);
            if triggered && stopping & bit != 0 {
                return Err(if homing & bit != 0 {
                    StopCause::HomingSwitch(i as u8)
                } else {
                    StopCause::HardLimit(i as u8)
                });
            }
            quiet &= !triggered && !sw.is_changing();
        }
        self.watch = !quiet;
        Ok(())
    }

    /// Stop on our own: tell the thread side why, drop the queue, end the pulse in progress.
    #[cold]
    fn stop<S: Stepper>(
        &mut self,
        now: Instant,
        cause: StopCause,
        steppers: &mut [S; N],
    ) -> Option<Instant> {
        self.discard = true;
        self.rx.clear();
        self.rx.q.set_stop_cause(cause);
        self.wind_down(now, steppers)
    }

    /// Axis `i`'s driver failed its rising edge at an event raising `raised` (the lines raised
    /// so far, `i`'s among them: its line's state is unknown): they end their pulses at `fall`
    /// as the stop winds down, so that no line is left high to swallow a later move's first
    /// step. Returns the stop's cause.
    #[cold]
    fn failed_rise(&mut self, i: usize, raised: u8, fall: Instant) -> StopCause {
        self.mark_raised(raised, fall);
        StopCause::Fault(i as u8)
    }

    /// Lower every raised step line as its pulse ends, then go idle.
    #[cold]
    fn wind_down<S: Stepper>(&mut self, now: Instant, steppers: &mut [S; N]) -> Option<Instant> {
        if self.high != 0 && now.is_at_or_after(self.next_fall) {
            // Nothing better to do with an error here: motion is already stopping.
            let _ = self.end_pulses(now, steppers);
        }
        if self.high != 0 {
            self.mode = Mode::WindDown;
            return Some(self.next_fall);
        }
        self.go_idle()
    }

    /// Tell the thread side how far the timeline has run: the ticks of the consumed events and
    /// the scheduled instant of the last one. Done at every event that raises a step line and
    /// on every change of mode, not at the others: the thread side only needs the two to agree
    /// (the time still queued ahead of now is the same from any consumed event), and they
    /// are exact whenever it resets its timeline (after a flush or at idle).
    #[inline(always)]
    fn publish(&self) {
        let q = self.rx.q;
        q.consumed_ticks
            .store(self.consumed_ticks, Ordering::Relaxed);
        q.last_event_at
            .store(self.last_at.ticks(), Ordering::Relaxed);
    }

    fn go_idle(&mut self) -> Option<Instant> {
        self.mode = Mode::Idle;
        self.publish();
        let q = self.rx.q;
        q.idles
            .store(q.starts.load(Ordering::Acquire), Ordering::Release);
        None
    }
}
