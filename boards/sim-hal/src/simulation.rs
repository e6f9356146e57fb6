//! The simulation loop: virtual time, the step interrupt and the thread side.
//!
//! A firmware board has two execution contexts: the step **interrupt**, raised by the alarm,
//! and the **thread** (main loop or tasks) that reads the links, plans and runs the heaters.
//! [`Simulation`] reproduces both over virtual time, for whatever implements [`Firmware`]:
//!
//! 1. It looks at the armed alarm ([`crate::SimAlarm`]) and at the next thread poll (every
//!    [`SimulationConfig::poll_period_ticks`]) and moves virtual time to the earlier of the two;
//!    when both fall on the same tick the interrupt goes first, as it would preempt the thread.
//! 2. An alarm calls [`Firmware::on_alarm`] with the current instant, after disarming the
//!    alarm; the instant it returns, if any, re-arms it (the interrupt may also re-arm through
//!    its own [`crate::SimAlarm`] handle and return `None`). Interrupt code takes no virtual
//!    time: a pulse's falling edge must be scheduled, as on hardware.
//! 3. A poll calls [`Firmware::poll`], which returns [`Flow::Stop`] when the firmware is done.
//! 4. The thermal models follow virtual time exactly ([`crate::thermal`]).
//!
//! It stops when the firmware says so, at the time limit, or when a stop flag is raised
//! (Ctrl-C). [`Simulation::run`] starts with a poll at the current virtual time;
//! [`Simulation::run_until`] runs up to a given tick and keeps the poll schedule of the run
//! before it, so that a test can advance the firmware in slices, looking at it in between, on
//! the schedule of one long run.
//!
//! A busy board serves its step interrupt a little late: with
//! [`SimulationConfig::max_latency_ticks`] set, each alarm is served up to that many ticks
//! after its instant (a pseudo-random, reproducible delay), and the interrupt sees the time it
//! runs at. [`Pacing::AsFastAsPossible`] runs virtual time as fast as the host computes;
//! [`Pacing::Realtime`] holds virtual time to the wall clock (sleeping whenever it is more than
//! [`PACING_SLACK`] ahead), for links to real host software; [`Pacing::Scaled`] holds it to a
//! multiple of the wall clock, so that long jobs run quickly and still in step with a host.
//!
//! The loop never touches a device itself: the kernel wiring owns the steppers, switches,
//! heaters and links and hands them to the firmware object, so the hardware types do not
//! change when the kernel is plugged in.

use core::fmt;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use forja_hal_abstraction::time::Instant;

use crate::machine::SimMachine;

/// How far virtual time may run ahead of the wall clock in [`Pacing::Realtime`] before the
/// loop sleeps.
pub const PACING_SLACK: std::time::Duration = std::time::Duration::from_micros(500);

/// What the thread side wants after a poll.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Flow {
    /// Keep running.
    Continue,
    /// Keep running, and poll again at once (after the alarms due now): the thread side
    /// stopped with work left, as a board's thread loop polls again when its firmware asks.
    Again,
    /// Stop the simulation: the job is done or the firmware gave up.
    Stop,
}

impl Flow {
    /// [`Flow::Again`] when `again` (the firmware has work left for its next turn, e.g. steps
    /// to prepare), else [`Flow::Continue`].
    pub fn again_if(again: bool) -> Self {
        if again { Self::Again } else { Self::Continue }
    }
}

/// The firmware under simulation: its step interrupt and its thread side.
pub trait Firmware {
    /// The step alarm fired at `now`. Returns the instant to fire next, or `None` to leave the
    /// alarm as the handler left it (disarmed, unless it armed it through a
    /// [`crate::SimAlarm`]).
    ///
    /// Context: interrupt. Takes no virtual time.
    fn on_alarm(&mut self, now: Instant) -> Option<Instant>;

    /// One turn of the thread side (read links, plan, control heaters) at `now`.
    ///
    /// Context: thread. Takes no virtual time.
    fn poll(&mut self, now: Instant) -> Flow;
}

impl<T: Firmware + ?Sized> Firmware for &mut T {
    fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        T::on_alarm(self, now)
    }
    fn poll(&mut self, now: Instant) -> Flow {
        T::poll(self, now)
    }
}

/// A [`Firmware`] made of two closures: the interrupt and the thread side.
pub struct FnFirmware<A, P> {
    /// The step interrupt.
    pub on_alarm: A,
    /// The thread side.
    pub poll: P,
}

impl<A, P> Firmware for FnFirmware<A, P>
where
    A: FnMut(Instant) -> Option<Instant>,
    P: FnMut(Instant) -> Flow,
{
    fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        (self.on_alarm)(now)
    }
    fn poll(&mut self, now: Instant) -> Flow {
        (self.poll)(now)
    }
}

/// A firmware with a hook after each of its polls ([`Simulation::run_hooked`]).
struct Hooked<'a, F: ?Sized, H> {
    firmware: &'a mut F,
    hook: H,
}

impl<F: Firmware + ?Sized, H: FnMut(&mut F, Instant) -> Flow> Firmware for Hooked<'_, F, H> {
    fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        self.firmware.on_alarm(now)
    }
    fn poll(&mut self, now: Instant) -> Flow {
        let firmware = self.firmware.poll(now);
        if firmware == Flow::Stop {
            return Flow::Stop;
        }
        match (self.hook)(self.firmware, now) {
            Flow::Continue => firmware,
            hook => hook,
        }
    }
}

/// How virtual time relates to the wall clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pacing {
    /// As fast as the host computes.
    AsFastAsPossible,
    /// Held to the wall clock: one virtual second takes one second.
    Realtime,
    /// Held to the wall clock `K` times faster: one virtual second takes `1/K` second (at
    /// most; the host may not keep up). `K` must be finite and positive.
    Scaled(f64),
}

impl Pacing {
    /// Virtual seconds per wall second, `None` when unpaced.
    pub fn speed(self) -> Option<f64> {
        match self {
            Self::AsFastAsPossible => None,
            Self::Realtime => Some(1.0),
            Self::Scaled(k) if k.is_finite() && k > 0.0 => Some(k),
            Self::Scaled(_) => None,
        }
    }
}

/// Settings of a [`Simulation`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimulationConfig {
    /// Fast or paced.
    pub pacing: Pacing,
    /// Stop after this much virtual time (from the start of [`Simulation::run`]).
    pub time_limit_ticks: Option<u64>,
    /// Virtual time between two thread polls; at least 1.
    pub poll_period_ticks: u64,
    /// Alarms allowed at a single tick before the run fails with [`RunError::AlarmStorm`].
    pub max_alarms_per_tick: u32,
    /// Polls in a row at a single tick ([`Flow::Again`]) before the run fails with
    /// [`RunError::PollStorm`].
    pub max_polls_per_tick: u32,
    /// Largest delay of the step interrupt after its alarm's instant, in ticks: each alarm is
    /// served up to this late (pseudo-random, the same in every run). 0: on time.
    pub max_latency_ticks: u64,
}

impl SimulationConfig {
    /// As fast as possible, no time limit, a thread poll every millisecond, at most 10 000
    /// alarms and 10 000 polls in a row per tick, interrupts on time.
    pub fn new(tick_hz: u32) -> Self {
        Self {
            pacing: Pacing::AsFastAsPossible,
            time_limit_ticks: None,
            poll_period_ticks: u64::from(tick_hz / 1000).max(1),
            max_alarms_per_tick: 10_000,
            max_polls_per_tick: 10_000,
            max_latency_ticks: 0,
        }
    }
}

/// Why a run ended normally.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum StopReason {
    /// [`Firmware::poll`] returned [`Flow::Stop`].
    Firmware,
    /// The time limit was reached.
    TimeLimit,
    /// The stop flag was raised.
    Interrupted,
}

/// What a run did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RunReport {
    /// Why it ended.
    pub stop: StopReason,
    /// Virtual time at the start, in ticks.
    pub start_ticks: u64,
    /// Virtual time at the end, in ticks.
    pub end_ticks: u64,
    /// Alarms fired.
    pub alarms: u64,
    /// Thread polls made.
    pub polls: u64,
    /// Wall-clock time taken.
    pub wall: std::time::Duration,
}

impl RunReport {
    /// Virtual time the run took, in ticks.
    pub fn virtual_ticks(&self) -> u64 {
        self.end_ticks - self.start_ticks
    }
}

/// A run that went wrong.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum RunError {
    /// The alarm kept firing without virtual time moving: the interrupt re-arms itself at or
    /// before now, and the thread side would never run again.
    AlarmStorm {
        /// The tick it happened at.
        at_ticks: u64,
        /// Alarms fired at that tick.
        alarms: u32,
    },
    /// The thread side kept asking to be polled again ([`Flow::Again`]) without virtual time
    /// moving: it never finishes the work it says it has left.
    PollStorm {
        /// The tick it happened at.
        at_ticks: u64,
        /// Polls in a row at that tick.
        polls: u32,
    },
}

/// How many times in a row something happened at one tick (an alarm, a poll again at once):
/// what [`RunError::AlarmStorm`] and [`RunError::PollStorm`] count.
struct InARow {
    at: u64,
    count: u32,
}

impl InARow {
    /// None yet, at tick `at`.
    fn at(at: u64) -> Self {
        Self { at, count: 0 }
    }

    /// It happened at tick `t`: the count in a row at `t`, this one included.
    fn count(&mut self, t: u64) -> u32 {
        if self.at == t {
            self.count += 1;
        } else {
            *self = Self { at: t, count: 1 };
        }
        self.count
    }
}

impl fmt::Display for RunError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::AlarmStorm { at_ticks, alarms } => write!(
                f,
                "the step alarm fired {alarms} times at tick {at_ticks} without time moving"
            ),
            Self::PollStorm { at_ticks, polls } => write!(
                f,
                "the thread side asked {polls} times in a row at tick {at_ticks} to be polled \
                 again without time moving"
            ),
        }
    }
}

impl std::error::Error for RunError {}

/// First state of the generator of interrupt latencies.
const LATENCY_SEED: u64 = 0x2545_f491_4f6c_dd1d;

/// The simulation loop of one machine.
#[derive(Debug)]
pub struct Simulation {
    machine: SimMachine,
    config: SimulationConfig,
    stop: Option<Arc<AtomicBool>>,
    /// When the thread side is due next, as the last run left it.
    next_poll: Option<u64>,
    /// The generator of interrupt latencies (xorshift).
    latency: u64,
}

impl Simulation {
    /// A loop over `machine` with `config`.
    pub fn new(machine: SimMachine, config: SimulationConfig) -> Self {
        Self {
            machine,
            config,
            stop: None,
            next_poll: None,
            latency: LATENCY_SEED,
        }
    }

    /// Stop the run (with [`StopReason::Interrupted`]) once `flag` is raised; checked before
    /// every event.
    pub fn set_stop_flag(&mut self, flag: Arc<AtomicBool>) {
        self.stop = Some(flag);
    }

    /// The machine.
    pub fn machine(&self) -> &SimMachine {
        &self.machine
    }

    /// The settings.
    pub fn config(&self) -> &SimulationConfig {
        &self.config
    }

    /// Change the settings for the next run.
    pub fn config_mut(&mut self) -> &mut SimulationConfig {
        &mut self.config
    }

    /// Run `firmware` until it stops, the time limit passes or the stop flag is raised. The
    /// first poll happens at the current virtual time.
    ///
    /// Errors: [`RunError::AlarmStorm`], [`RunError::PollStorm`].
    pub fn run<F: Firmware + ?Sized>(&mut self, firmware: &mut F) -> Result<RunReport, RunError> {
        let now = self.machine.now_ticks();
        self.run_from(firmware, now, None)
    }

    /// Run `firmware` until virtual time `until_ticks` (or the time limit, if sooner), unless
    /// it stops or the stop flag is raised first. Events due at `until_ticks` run; the run then
    /// ends there ([`StopReason::TimeLimit`]). The polls go on where the previous run left
    /// them (the first at the current virtual time, when none ran), so that runs in slices
    /// poll as one long run does.
    ///
    /// Errors: [`RunError::AlarmStorm`], [`RunError::PollStorm`].
    pub fn run_until<F: Firmware + ?Sized>(
        &mut self,
        firmware: &mut F,
        until_ticks: u64,
    ) -> Result<RunReport, RunError> {
        let first_poll = self.next_poll.unwrap_or_else(|| self.machine.now_ticks());
        self.run_from(firmware, first_poll, Some(until_ticks))
    }

    /// The delay of the next interrupt, ticks.
    fn latency(&mut self) -> u64 {
        let max = self.config.max_latency_ticks;
        if max == 0 {
            return 0;
        }
        self.latency ^= self.latency << 13;
        self.latency ^= self.latency >> 7;
        self.latency ^= self.latency << 17;
        self.latency % (max + 1)
    }

    /// The loop: the first poll at `first_poll`, ending at `until` or the time limit.
    fn run_from<F: Firmware + ?Sized>(
        &mut self,
        firmware: &mut F,
        first_poll: u64,
        until: Option<u64>,
    ) -> Result<RunReport, RunError> {
        let m = self.machine.clone();
        let wall_start = std::time::Instant::now();
        let start_ticks = m.now_ticks();
        let limit = self
            .config
            .time_limit_ticks
            .map(|l| start_ticks.saturating_add(l));
        let deadline = match (limit, until) {
            (Some(l), Some(u)) => Some(l.min(u)),
            (l, u) => l.or(u),
        };
        let period = self.config.poll_period_ticks.max(1);
        let tick_hz = f64::from(m.tick_hz());
        let mut next_poll = first_poll;
        let mut report = RunReport {
            stop: StopReason::Firmware,
            start_ticks,
            end_ticks: start_ticks,
            alarms: 0,
            polls: 0,
            wall: std::time::Duration::ZERO,
        };
        let mut alarms_here = InARow::at(start_ticks);
        let mut polls_here = InARow::at(start_ticks);
        let finish = |mut report: RunReport, stop| {
            report.stop = stop;
            report.end_ticks = m.now_ticks();
            report.wall = wall_start.elapsed();
            report
        };

        let result = loop {
            if self
                .stop
                .as_ref()
                .is_some_and(|f| f.load(Ordering::Relaxed))
            {
                break Ok(finish(report, StopReason::Interrupted));
            }
            let alarm = m.alarm_at_ticks().filter(|&a| a <= next_poll);
            let t = alarm.unwrap_or(next_poll).max(m.now_ticks());
            if let Some(d) = deadline
                && t > d
            {
                m.advance_to(d);
                break Ok(finish(report, StopReason::TimeLimit));
            }
            if let Some(speed) = self.config.pacing.speed() {
                let target = wall_start
                    + std::time::Duration::from_secs_f64(
                        (t - start_ticks) as f64 / tick_hz / speed,
                    );
                let ahead = target.saturating_duration_since(std::time::Instant::now());
                if ahead > PACING_SLACK {
                    std::thread::sleep(ahead);
                }
            }
            m.advance_to(t);
            if alarm.is_some() {
                m.take_alarm();
                let alarms = alarms_here.count(t);
                if alarms > self.config.max_alarms_per_tick {
                    break Err(RunError::AlarmStorm {
                        at_ticks: t,
                        alarms,
                    });
                }
                report.alarms += 1;
                let late = self.latency();
                m.advance_by(late);
                if let Some(next) = firmware.on_alarm(Instant::from_ticks(m.now_ticks() as u32)) {
                    m.set_alarm_ticks(m.instant_to_ticks(next));
                }
            } else {
                report.polls += 1;
                match firmware.poll(Instant::from_ticks(t as u32)) {
                    Flow::Stop => break Ok(finish(report, StopReason::Firmware)),
                    Flow::Again => {
                        let polls = polls_here.count(t);
                        if polls > self.config.max_polls_per_tick {
                            break Err(RunError::PollStorm { at_ticks: t, polls });
                        }
                        next_poll = t;
                    }
                    Flow::Continue => next_poll = t + period,
                }
            }
        };
        self.next_poll = Some(next_poll);
        result
    }

    /// [`Simulation::run`], calling `hook` with the firmware after each of its thread-side
    /// polls that did not stop it: the turn of what stands outside the firmware (a host that
    /// reads replies and sends lines, a test that watches). The run also ends when `hook`
    /// returns [`Flow::Stop`].
    ///
    /// Errors: [`RunError::AlarmStorm`], [`RunError::PollStorm`].
    pub fn run_hooked<F, H>(&mut self, firmware: &mut F, hook: H) -> Result<RunReport, RunError>
    where
        F: Firmware + ?Sized,
        H: FnMut(&mut F, Instant) -> Flow,
    {
        self.run(&mut Hooked { firmware, hook })
    }

    /// [`Simulation::run`] with two closures: the interrupt and the thread side.
    pub fn run_with<A, P>(&mut self, on_alarm: A, poll: P) -> Result<RunReport, RunError>
    where
        A: FnMut(Instant) -> Option<Instant>,
        P: FnMut(Instant) -> Flow,
    {
        self.run(&mut FnFirmware { on_alarm, poll })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MachineConfig;
    use forja_hal_abstraction::clock::{Alarm, Clock};
    use forja_hal_abstraction::stepper::{Direction, Stepper, StepperEnable};
    use forja_hal_abstraction::time::Duration;

    fn machine() -> SimMachine {
        let m = SimMachine::new(&MachineConfig::default_router());
        m.set_tracing(true);
        m
    }

    /// A minimal step generator: `n` steps on X every `period` ticks, pulse 2 ticks wide,
    /// scheduled edge by edge like the kernel's step interrupt.
    struct Stepping {
        x: crate::SimStepper,
        left: u32,
        high: bool,
        period: u32,
    }

    impl Firmware for Stepping {
        fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
            if self.high {
                self.x.step_end().unwrap();
                self.high = false;
                self.left -= 1;
                (self.left > 0).then(|| now.wrapping_add(Duration::from_ticks(self.period - 2)))
            } else {
                self.x.step_begin().unwrap();
                self.high = true;
                Some(now.wrapping_add(Duration::from_ticks(2)))
            }
        }
        fn poll(&mut self, _now: Instant) -> Flow {
            if self.left == 0 {
                Flow::Stop
            } else {
                Flow::Continue
            }
        }
    }

    #[test]
    fn interrupt_runs_at_the_scheduled_times() {
        let m = machine();
        let mut x = m.stepper(0).unwrap();
        x.set_enabled(true).unwrap();
        x.set_direction(Direction::Positive).unwrap();
        let start = m.position_steps(0).unwrap();
        let mut alarm = m.alarm();
        alarm.set_alarm(Instant::from_ticks(100)).unwrap();
        let mut fw = Stepping {
            x,
            left: 1000,
            high: false,
            period: 125, // 8 kHz: 6000 mm/min at 80 steps/mm
        };
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        let report = sim.run(&mut fw).unwrap();
        assert_eq!(report.stop, StopReason::Firmware);
        assert_eq!(report.alarms, 2000);
        assert_eq!(m.position_steps(0), Some(start + 1000));
        let times = m.step_times(0);
        assert_eq!(times.len(), 1000);
        assert!(
            times
                .iter()
                .enumerate()
                .all(|(i, &t)| t == 100 + 125 * i as u64)
        );
        assert_eq!(m.violation_count(), 0);
        // The last falling edge is at 100 + 999 * 125 + 2; the poll after it stops the run.
        assert_eq!(report.end_ticks, 125_000);
        assert_eq!(report.polls, 126);
    }

    #[test]
    fn time_limit_and_poll_period() {
        let m = machine();
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        sim.config_mut().time_limit_ticks = Some(10_500);
        let mut polls = Vec::new();
        let report = sim
            .run_with(
                |_| None,
                |now| {
                    polls.push(now.ticks());
                    Flow::Continue
                },
            )
            .unwrap();
        assert_eq!(report.stop, StopReason::TimeLimit);
        assert_eq!(report.end_ticks, 10_500);
        assert_eq!(polls, (0..=10).map(|i| i * 1000).collect::<Vec<_>>());
        // A second run continues from there.
        sim.config_mut().time_limit_ticks = Some(1000);
        let report = sim.run_with(|_| None, |_| Flow::Continue).unwrap();
        assert_eq!((report.start_ticks, report.end_ticks), (10_500, 11_500));
    }

    #[test]
    fn the_hook_runs_after_each_poll_until_either_stops() {
        let m = machine();
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        let mut turns = Vec::new();
        let mut firmware = FnFirmware {
            on_alarm: |_| None,
            poll: |now: Instant| {
                if now.ticks() < 5_000 {
                    Flow::Continue
                } else {
                    Flow::Stop
                }
            },
        };
        let report = sim
            .run_hooked(&mut firmware, |_, now| {
                turns.push(now.ticks());
                if now.ticks() < 2_000 {
                    Flow::Continue
                } else {
                    Flow::Stop
                }
            })
            .unwrap();
        assert_eq!(report.stop, StopReason::Firmware);
        assert_eq!(turns, [0, 1000, 2000]);
        // The next run polls again at once; the firmware's own stop ends it without a turn of
        // the hook.
        turns.clear();
        sim.run_hooked(&mut firmware, |_, now| {
            turns.push(now.ticks());
            Flow::Continue
        })
        .unwrap();
        assert_eq!(turns, [2000, 3000, 4000]);
    }

    #[test]
    fn runs_in_slices_keep_the_poll_schedule() {
        let m = machine();
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        let mut polls = Vec::new();
        for until in [1_500, 1_600, 3_000] {
            let mut firmware = FnFirmware {
                on_alarm: |_| None,
                poll: |now: Instant| {
                    polls.push(now.ticks());
                    Flow::Continue
                },
            };
            let report = sim.run_until(&mut firmware, until).unwrap();
            assert_eq!(report.stop, StopReason::TimeLimit);
            assert_eq!(report.end_ticks, until);
        }
        // One poll a millisecond, as in one run to 3000; the poll due at the end runs.
        assert_eq!(polls, [0, 1000, 2000, 3000]);
        // A run with a time limit ends at the sooner of the two.
        sim.config_mut().time_limit_ticks = Some(100);
        let report = sim
            .run_until(
                &mut FnFirmware {
                    on_alarm: |_| None,
                    poll: |_| Flow::Continue,
                },
                10_000,
            )
            .unwrap();
        assert_eq!(report.end_ticks, 3_100);
    }

    /// The instants the alarm fires at, re-armed 10 ticks after each, 50 times from tick 100,
    /// with interrupts up to `max_latency` ticks late.
    fn served_at(max_latency: u64) -> Vec<u32> {
        let m = machine();
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        sim.config_mut().max_latency_ticks = max_latency;
        m.set_alarm_ticks(100);
        let mut fired = Vec::new();
        sim.run_until(
            &mut FnFirmware {
                on_alarm: |now: Instant| {
                    fired.push(now.ticks());
                    (fired.len() < 50).then(|| now.wrapping_add(Duration::from_ticks(10)))
                },
                poll: |_| Flow::Continue,
            },
            10_000,
        )
        .unwrap();
        fired
    }

    #[test]
    fn late_interrupts_run_at_their_late_time_the_same_in_every_run() {
        assert_eq!(
            served_at(0),
            (0..50).map(|k| 100 + 10 * k).collect::<Vec<_>>()
        );
        let late = served_at(5);
        assert_eq!(late.len(), 50);
        let delays: Vec<u32> = core::iter::once(late[0] - 100)
            .chain(late.windows(2).map(|w| w[1] - w[0] - 10))
            .collect();
        assert!(delays.iter().all(|&d| d <= 5), "{delays:?}");
        assert!(delays.iter().filter(|&&d| d > 0).count() > 25, "{delays:?}");
        assert_eq!(served_at(5), late, "reproducible");
    }

    #[test]
    fn interrupt_preempts_a_poll_due_at_the_same_tick_and_can_rearm_itself() {
        let m = machine();
        let mut alarm = m.alarm();
        alarm.set_alarm(Instant::from_ticks(1000)).unwrap();
        let log = core::cell::RefCell::new(Vec::new());
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        sim.config_mut().time_limit_ticks = Some(2000);
        let mut own = m.alarm();
        let mut fired = 0;
        sim.run_with(
            |now| {
                log.borrow_mut().push(("isr", now.ticks()));
                fired += 1;
                if fired == 1 {
                    // Re-arm through the handle instead of the return value.
                    own.set_alarm(now.wrapping_add(Duration::from_ticks(500)))
                        .unwrap();
                }
                None
            },
            |now| {
                log.borrow_mut().push(("poll", now.ticks()));
                Flow::Continue
            },
        )
        .unwrap();
        assert_eq!(
            log.into_inner(),
            [
                ("poll", 0),
                ("isr", 1000),
                ("poll", 1000),
                ("isr", 1500),
                ("poll", 2000)
            ]
        );
        assert_eq!(m.alarm_at_ticks(), None);
    }

    #[test]
    fn an_alarm_storm_is_an_error() {
        let m = machine();
        m.set_alarm_ticks(10);
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        let e = sim.run_with(Some, |_| Flow::Continue).unwrap_err();
        assert_eq!(
            e,
            RunError::AlarmStorm {
                at_ticks: 10,
                alarms: 10_001
            }
        );
        assert!(e.to_string().contains("10001 times at tick 10"));
    }

    #[test]
    fn a_poll_storm_is_an_error() {
        let m = machine();
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        let e = sim.run_with(|_| None, |_| Flow::Again).unwrap_err();
        assert_eq!(
            e,
            RunError::PollStorm {
                at_ticks: 0,
                polls: 10_001
            }
        );
        assert!(e.to_string().contains("10001 times in a row at tick 0"));
    }

    #[test]
    fn stop_flag_interrupts() {
        let m = machine();
        let flag = Arc::new(AtomicBool::new(false));
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        sim.set_stop_flag(Arc::clone(&flag));
        let mut n = 0;
        let report = sim
            .run_with(
                |_| None,
                |_| {
                    n += 1;
                    if n == 5 {
                        flag.store(true, Ordering::Relaxed);
                    }
                    Flow::Continue
                },
            )
            .unwrap();
        assert_eq!(report.stop, StopReason::Interrupted);
        assert_eq!(report.polls, 5);
    }

    #[test]
    fn realtime_pacing_follows_the_wall_clock() {
        let m = machine();
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        sim.config_mut().pacing = Pacing::Realtime;
        sim.config_mut().time_limit_ticks = Some(150_000); // 150 ms
        let report = sim.run_with(|_| None, |_| Flow::Continue).unwrap();
        let wall = report.wall.as_secs_f64();
        assert!(wall >= 0.148, "{wall} s is faster than real time");
        assert!(wall < 1.0, "{wall} s");

        // The same span unpaced takes a fraction of it.
        let mut fast = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        fast.config_mut().time_limit_ticks = Some(150_000);
        let report = fast.run_with(|_| None, |_| Flow::Continue).unwrap();
        assert!(report.wall.as_secs_f64() < 0.1);
        assert_eq!(m.clock().now().ticks(), 300_000);
    }

    #[test]
    fn scaled_pacing_runs_faster_than_the_wall_clock() {
        let m = machine();
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        sim.config_mut().pacing = Pacing::Scaled(10.0);
        sim.config_mut().time_limit_ticks = Some(1_000_000); // 1 s of virtual time
        let report = sim.run_with(|_| None, |_| Flow::Continue).unwrap();
        let wall = report.wall.as_secs_f64();
        assert!(wall >= 0.098, "{wall} s is faster than 10x");
        assert!(wall < 0.9, "{wall} s");
        assert_eq!(Pacing::Scaled(-1.0).speed(), None);
        assert_eq!(Pacing::Realtime.speed(), Some(1.0));
    }

    #[test]
    fn heaters_follow_virtual_time_during_a_run() {
        let text = MachineConfig::bundled_toml("printer").unwrap();
        let m = SimMachine::new(&MachineConfig::from_toml_str(text).unwrap());
        let mut sim = Simulation::new(m.clone(), SimulationConfig::new(m.tick_hz()));
        sim.config_mut().time_limit_ticks = Some(600 * 1_000_000);
        let mut heater = m.heater(0).unwrap();
        let mut sensor = m.temperature_sensor(0).unwrap();
        // A bang-bang controller on the thread side holds 200 °C.
        use forja_hal_abstraction::thermal::{FULL_POWER, Heater, TemperatureSensor};
        sim.run_with(
            |_| None,
            |_| {
                let t = sensor.read_millicelsius().unwrap();
                heater
                    .set_power(if t < 200_000 { FULL_POWER } else { 0 })
                    .unwrap();
                Flow::Continue
            },
        )
        .unwrap();
        let t = m.temperature_c(0).unwrap();
        assert!((t - 200.0).abs() < 0.5, "{t}");
    }
}
