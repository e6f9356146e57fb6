//! The interrupt side: [`StepGenerator::on_alarm`] turns queued step events into pin edges.
//!
//! Context: the step interrupt (a one-shot timer alarm on the board's clock). Integer-only,
//! allocation-free, panic-free, no blocking; each call handles exactly one event — lower the
//! step lines whose pulse is over, change directions, check the switches of the axes about to
//! step, raise step lines — and returns when to be called next. All timing decisions (step
//! times, pulse width, direction set-up) were taken by the thread side; this side only keeps
//! the schedule (`next = previous scheduled time + delta`, so interrupt latency never
//! accumulates; the first event after idle is due its delta after the start) and guards the
//! minimum pulse width against a late rising edge.

#![deny(clippy::indexing_slicing, clippy::arithmetic_side_effects)]

use core::sync::atomic::Ordering;

use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::stepper::{Direction, Stepper};
use forja_hal_abstraction::time::{Duration, Instant};

use crate::config::{HomeDirection, MachineConfig};
use crate::queue::{Consumer, PROBE_CONTACT, PROBE_OFF, Raw, StepQueue, StopCause, SwitchAlert};

/// No switch for this axis.
const NO_SWITCH: u8 = u8::MAX;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    /// No alarm armed; the thread side starts us.
    Idle,
    /// Executing events; `next_at` is armed.
    Running,
    /// Stopped: waiting for the last pulse to be long enough before lowering it.
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
    /// Raised lines whose rising edge was served late, and when.
    late: u8,
    late_since: Instant,
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
}

impl<'q, const N: usize, const Q: usize> StepGenerator<'q, N, Q> {
    pub(crate) fn new(q: &'q StepQueue<N, Q>, config: &MachineConfig<N>, pulse: Duration) -> Self {
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
            late: 0,
            late_since: Instant::from_ticks(0),
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
        let q = self.rx.q;
        let ev = if self.mode == Mode::Running
            && q.flush_req.load(Ordering::Acquire) == self.flush_seen
        {
            if !now.is_at_or_after(self.wake_at) {
                return Some(self.wake_at);
            }
            // Peeked by the previous call; only this side removes events.
            self.next_ev
        } else {
            match self.unusual(now, steppers) {
                Ok(ev) => ev,
                Err(next) => return next,
            }
        };
        // A rising edge served late must still get its full pulse before the falling edge (the
        // schedule gives it one only when served on time).
        if ev.fall() & self.late != 0 {
            let end = self.late_since.wrapping_add(self.pulse);
            if !now.is_at_or_after(end) {
                self.wake_at = end;
                return Some(end);
            }
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
                Some(self.next_at)
            }
            None => self.ran_dry(now, ev.rest(), steppers),
        }
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
        let fall = ev.fall() & self.high;
        if fall != 0 {
            self.high &= !fall;
            self.late &= !fall;
            // Only the axes whose bit is set, lowest first: the cost follows the axes that
            // step, not the machine's axis count.
            let mut axes = fall;
            while axes != 0 {
                let i = axes.trailing_zeros() as usize;
                axes &= axes.wrapping_sub(1);
                if let Some(s) = steppers.get_mut(i) {
                    s.step_end().map_err(|_| StopCause::Fault(i as u8))?;
                }
            }
        }
        if ev.dir_set() != 0 {
            self.change_directions(ev, steppers)?;
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
        let mut axes = rise;
        while axes != 0 {
            let i = axes.trailing_zeros() as usize;
            axes &= axes.wrapping_sub(1);
            if let (Some(s), Some(p), Some(d)) = (
                steppers.get_mut(i),
                q.positions.get(i),
                self.step_sign.get(i),
            ) {
                s.step_begin().map_err(|_| StopCause::Fault(i as u8))?;
                p.store(
                    p.load(Ordering::Relaxed).wrapping_add(*d),
                    Ordering::Relaxed,
                );
            }
        }
        self.high |= rise;
        if now != self.next_at {
            self.late |= rise;
            self.late_since = now;
        }
        Ok(())
    }

    /// Write the direction lines an event changes.
    #[cold]
    #[inline(never)]
    fn change_directions<S: Stepper>(
        &mut self,
        ev: Raw,
        steppers: &mut [S; N],
    ) -> Result<(), StopCause> {
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

    /// Lower any raised step line once its pulse is long enough, then go idle.
    #[cold]
    fn wind_down<S: Stepper>(&mut self, now: Instant, steppers: &mut [S; N]) -> Option<Instant> {
        if self.high != 0 {
            // Raised at or before the last consumed event: at its scheduled instant, or when it
            // was served if that was late.
            let since = if self.late != 0 && self.late_since.is_at_or_after(self.last_at) {
                self.late_since
            } else {
                self.last_at
            };
            let end = since.wrapping_add(self.pulse);
            if !now.is_at_or_after(end) {
                self.mode = Mode::WindDown;
                return Some(end);
            }
            let mut m = self.high;
            self.high = 0;
            while m != 0 {
                let i = m.trailing_zeros() as usize;
                m &= m.wrapping_sub(1);
                if let Some(s) = steppers.get_mut(i) {
                    // Nothing better to do with an error here: motion is already stopping.
                    let _ = s.step_end();
                }
            }
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
