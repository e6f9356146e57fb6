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
use crate::queue::{Consumer, Event, StepQueue, StopCause};

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
    pos: [i32; N],
    dir_neg: u8,
    high: u8,
    high_since: Instant,
    /// Raised lines whose rising edge was served late, and when.
    late: u8,
    late_since: Instant,
    next_ev: Event,
    next_at: Instant,
    wake_at: Instant,
    discard: bool,
    flush_seen: u32,
    consumed_ticks: u32,
    switch_of: [u8; N],
    has_switch: u8,
    switch_neg: u8,
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
            pos: q.positions(),
            dir_neg: 0,
            high: 0,
            high_since: Instant::from_ticks(0),
            late: 0,
            late_since: Instant::from_ticks(0),
            next_ev: Event::default(),
            next_at: Instant::from_ticks(0),
            wake_at: Instant::from_ticks(0),
            discard: false,
            flush_seen: q.flush_req.load(Ordering::Relaxed),
            consumed_ticks: q.consumed_ticks.load(Ordering::Relaxed),
            switch_of,
            has_switch,
            switch_neg,
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
        self.pos
    }

    /// Handle the step alarm.
    ///
    /// Call it when the alarm fires, with the current time, the `N` steppers (axis `i` is
    /// `steppers[i]`) and the limit switches (indexed by each axis's `homing.switch`). Arm the
    /// alarm at the returned instant, or leave it disarmed on `None` (idle until the thread
    /// side's `poll` asks for a start).
    ///
    /// Context: interrupt. Never blocks, never allocates, never panics. A driver or switch
    /// error stops motion with [`crate::Alarm::DriverFault`]; a switch read error counts as
    /// triggered.
    pub fn on_alarm<S: Stepper, L: LimitSwitch>(
        &mut self,
        now: Instant,
        steppers: &mut [S; N],
        switches: &mut [L],
    ) -> Option<Instant> {
        let q = self.rx.q;
        let req = q.flush_req.load(Ordering::Acquire);
        if req != self.flush_seen {
            self.flush_seen = req;
            self.rx.clear();
            self.discard = false;
            q.flush_done.store(req, Ordering::Release);
            return self.wind_down(now, steppers);
        }
        if self.discard {
            self.rx.clear();
            return self.wind_down(now, steppers);
        }
        let ev = match self.mode {
            Mode::WindDown => return self.wind_down(now, steppers),
            Mode::Idle => {
                let Some(ev) = self.rx.peek() else {
                    return self.go_idle();
                };
                // The start is the instant the queued timeline resumes from: the first event is
                // due its delta after it (a dwell at rest, the first half step of a move).
                self.mode = Mode::Running;
                q.last_event_at.store(now.ticks(), Ordering::Relaxed);
                self.next_ev = ev;
                self.next_at = now.wrapping_add(Duration::from_ticks(ev.delta));
                self.wake_at = self.next_at;
                if !now.is_at_or_after(self.wake_at) {
                    return Some(self.wake_at);
                }
                ev
            }
            Mode::Running => {
                if !now.is_at_or_after(self.wake_at) {
                    return Some(self.wake_at);
                }
                // Peeked by the previous call; only this side removes events, and a flush
                // was handled above.
                self.next_ev
            }
        };
        // A rising edge served late must still get its full pulse before the falling edge (the
        // schedule gives it one only when served on time).
        if ev.fall & self.late != 0 {
            let end = self.late_since.wrapping_add(self.pulse);
            if !now.is_at_or_after(end) {
                self.wake_at = end;
                return Some(end);
            }
        }
        self.rx.advance();
        self.consumed_ticks = self.consumed_ticks.wrapping_add(ev.delta);
        q.consumed_ticks
            .store(self.consumed_ticks, Ordering::Relaxed);
        q.last_event_at
            .store(self.next_at.ticks(), Ordering::Relaxed);
        if let Err(cause) = self.execute(&ev, now, steppers, switches) {
            return self.stop(now, cause, steppers);
        }
        match self.rx.peek() {
            Some(next) => {
                self.next_ev = next;
                self.next_at = self.next_at.wrapping_add(Duration::from_ticks(next.delta));
                self.wake_at = self.next_at;
                Some(self.next_at)
            }
            None if ev.rest && self.high == 0 => self.go_idle(),
            None if ev.rest => self.wind_down(now, steppers),
            None => self.stop(now, StopCause::Underrun, steppers),
        }
    }

    #[inline]
    fn execute<S: Stepper, L: LimitSwitch>(
        &mut self,
        ev: &Event,
        now: Instant,
        steppers: &mut [S; N],
        switches: &mut [L],
    ) -> Result<(), StopCause> {
        let mut m = ev.fall & self.high;
        self.high &= !ev.fall;
        self.late &= !ev.fall;
        while m != 0 {
            let i = m.trailing_zeros() as usize;
            m &= m.wrapping_sub(1);
            if let Some(s) = steppers.get_mut(i) {
                s.step_end().map_err(|_| StopCause::Fault(i as u8))?;
            }
        }
        let mut m = ev.dir_set;
        while m != 0 {
            let i = m.trailing_zeros() as usize;
            let bit = m & m.wrapping_neg();
            m &= m.wrapping_sub(1);
            let neg = ev.dir_neg & bit != 0;
            if let Some(s) = steppers.get_mut(i) {
                let d = if neg {
                    Direction::Negative
                } else {
                    Direction::Positive
                };
                s.set_direction(d).map_err(|_| StopCause::Fault(i as u8))?;
            }
            self.dir_neg = (self.dir_neg & !bit) | (ev.dir_neg & bit);
        }
        if ev.rise == 0 {
            return Ok(());
        }
        // Switches first: a tripped switch cancels the whole event.
        let mut m = ev.rise & self.has_switch;
        if m != 0 {
            let homing = self.rx.q.homing_mask.load(Ordering::Relaxed) as u8;
            let toward = !(self.dir_neg ^ self.switch_neg);
            m &= toward & (if self.hard_limits { 0xFF } else { homing });
            while m != 0 {
                let i = m.trailing_zeros() as usize;
                let bit = m & m.wrapping_neg();
                m &= m.wrapping_sub(1);
                let idx = self.switch_of.get(i).copied().unwrap_or(NO_SWITCH) as usize;
                let triggered = match switches.get_mut(idx) {
                    Some(sw) => sw.is_triggered().unwrap_or(true),
                    None => false,
                };
                if triggered {
                    return Err(if homing & bit != 0 {
                        StopCause::HomingSwitch(i as u8)
                    } else {
                        StopCause::HardLimit(i as u8)
                    });
                }
            }
        }
        let mut m = ev.rise;
        while m != 0 {
            let i = m.trailing_zeros() as usize;
            let bit = m & m.wrapping_neg();
            m &= m.wrapping_sub(1);
            if let (Some(s), Some(p)) = (steppers.get_mut(i), self.pos.get_mut(i)) {
                s.step_begin().map_err(|_| StopCause::Fault(i as u8))?;
                *p = if self.dir_neg & bit != 0 {
                    p.wrapping_sub(1)
                } else {
                    p.wrapping_add(1)
                };
                if let Some(a) = self.rx.q.positions.get(i) {
                    a.store(*p, Ordering::Relaxed);
                }
            }
        }
        self.high |= ev.rise;
        self.high_since = now;
        if now != self.next_at {
            self.late |= ev.rise;
            self.late_since = now;
        }
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
            let end = self.high_since.wrapping_add(self.pulse);
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

    fn go_idle(&mut self) -> Option<Instant> {
        self.mode = Mode::Idle;
        let q = self.rx.q;
        q.idles
            .store(q.starts.load(Ordering::Acquire), Ordering::Release);
        None
    }
}
