//! A deterministic host simulation of the interrupt side (feature `std`).
//!
//! [`Simulation`] wires a [`Kernel`] and its [`StepGenerator`] exactly as a board does, on a
//! virtual clock: the step alarm fires at the instant the interrupt side asked for, and the
//! thread side is polled every `poll_period` ticks. [`SimStepper`]s record every step with its
//! tick and check the driver timing (pulse width, low time, direction set-up) as a real driver
//! would need it; [`SimSwitch`]es trigger at a machine position. The simulator board and the
//! tests use it.

use std::cell::RefCell;
use std::format;
use std::rc::Rc;
use std::string::String;
use std::vec::Vec;

use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::stepper::{Direction, StepTiming, Stepper};
use forja_hal_abstraction::time::{Duration, Instant};
use forja_protocol::gcode::Line;

use crate::error::CommandError;
use crate::kernel::{Kernel, Reply};
use crate::queue::SwitchAlert;
use crate::stepgen::StepGenerator;

/// One rising step edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepRecord {
    /// Virtual time of the edge, ticks since the start of the simulation.
    pub tick: u64,
    /// The axis position after the step (interrupt step count).
    pub position: i32,
}

/// What the simulated machine did, shared by its steppers and switches.
#[derive(Debug)]
pub struct Recorder<const N: usize> {
    /// Virtual time, ticks.
    pub now: u64,
    /// Step count of each axis (the motor's real position).
    pub position: [i32; N],
    /// Every step of every axis, when `record` is set.
    pub steps: Vec<Vec<StepRecord>>,
    /// Timing rules broken (should stay empty).
    pub violations: Vec<String>,
    /// Whether to keep every step in `steps` (off for very long runs).
    pub record: bool,
    /// Total steps of each axis.
    pub step_count: [u64; N],
    pulse: u64,
    dir_setup: u64,
    dir_neg: [bool; N],
    dir_set_at: [u64; N],
    high: [bool; N],
    rose_at: [u64; N],
    fell_at: [u64; N],
}

impl<const N: usize> Recorder<N> {
    fn violation(&mut self, what: String) {
        if self.violations.len() < 100 {
            self.violations.push(what);
        }
    }
}

/// A stepper driver that records its steps.
#[derive(Debug, Clone)]
pub struct SimStepper<const N: usize> {
    axis: usize,
    rec: Rc<RefCell<Recorder<N>>>,
}

impl<const N: usize> ErrorType for SimStepper<N> {
    type Error = core::convert::Infallible;
}

impl<const N: usize> Stepper for SimStepper<N> {
    fn set_direction(&mut self, direction: Direction) -> Result<(), Self::Error> {
        let mut r = self.rec.borrow_mut();
        let a = self.axis;
        let neg = direction == Direction::Negative;
        if r.high[a] {
            let now = r.now;
            r.violation(format!(
                "axis {a}: direction change during a pulse at {now}"
            ));
        }
        if r.dir_neg[a] != neg {
            r.dir_neg[a] = neg;
            r.dir_set_at[a] = r.now;
        }
        Ok(())
    }

    fn step_begin(&mut self) -> Result<(), Self::Error> {
        let mut r = self.rec.borrow_mut();
        let a = self.axis;
        let now = r.now;
        if r.high[a] {
            r.violation(format!("axis {a}: rise while high at {now}"));
        }
        if r.step_count[a] > 0 && now - r.fell_at[a] < r.pulse {
            r.violation(format!("axis {a}: low time too short at {now}"));
        }
        if now - r.dir_set_at[a] < r.dir_setup && r.step_count[a] > 0 {
            r.violation(format!("axis {a}: direction set-up too short at {now}"));
        }
        r.high[a] = true;
        r.rose_at[a] = now;
        r.position[a] += if r.dir_neg[a] { -1 } else { 1 };
        r.step_count[a] += 1;
        if r.record {
            let position = r.position[a];
            if let Some(v) = r.steps.get_mut(a) {
                v.push(StepRecord {
                    tick: now,
                    position,
                });
            }
        }
        Ok(())
    }

    fn step_end(&mut self) -> Result<(), Self::Error> {
        let mut r = self.rec.borrow_mut();
        let a = self.axis;
        let now = r.now;
        if !r.high[a] {
            r.violation(format!("axis {a}: fall while low at {now}"));
        }
        if now - r.rose_at[a] < r.pulse {
            r.violation(format!("axis {a}: pulse too short at {now}"));
        }
        r.high[a] = false;
        r.fell_at[a] = now;
        Ok(())
    }

    fn timing(&self) -> StepTiming {
        StepTiming::CONSERVATIVE
    }
}

/// A limit switch triggered at and beyond a step position of one axis.
#[derive(Debug, Clone)]
pub struct SimSwitch<const N: usize> {
    axis: usize,
    at_steps: i32,
    negative_end: bool,
    rec: Rc<RefCell<Recorder<N>>>,
}

impl<const N: usize> SimSwitch<N> {
    /// Move the switch.
    pub fn set_position(&mut self, at_steps: i32) {
        self.at_steps = at_steps;
    }
}

impl<const N: usize> ErrorType for SimSwitch<N> {
    type Error = core::convert::Infallible;
}

impl<const N: usize> LimitSwitch for SimSwitch<N> {
    fn is_triggered(&mut self) -> Result<bool, Self::Error> {
        let p = self.rec.borrow().position[self.axis];
        Ok(if self.negative_end {
            p <= self.at_steps
        } else {
            p >= self.at_steps
        })
    }
}

/// A pin-change interrupt for simulated switches: [`EdgeWatch::look`] reports an edge to the
/// step interrupt when any switch changed since the last look. Looking after every step
/// interrupt is what an EXTI line does for a switch that a step pushed over its point.
#[derive(Debug, Clone, Copy)]
pub struct EdgeWatch<'q> {
    alert: SwitchAlert<'q>,
    levels: u64,
}

impl<'q> EdgeWatch<'q> {
    /// Watch for `alert`, with every switch seen released.
    pub fn new(alert: SwitchAlert<'q>) -> Self {
        Self { alert, levels: 0 }
    }

    /// Compare the switches' levels with the last look; report an edge if any differs.
    pub fn look<const N: usize>(&mut self, switches: &mut [SimSwitch<N>]) {
        let mut levels = 0u64;
        for (i, sw) in switches.iter_mut().enumerate().take(64) {
            if sw.is_triggered() == Ok(true) {
                levels |= 1 << i;
            }
        }
        if levels != self.levels {
            self.levels = levels;
            self.alert.notify();
        }
    }
}

/// A kernel, its interrupt side, steppers and switches on a virtual clock.
pub struct Simulation<'q, const N: usize, const B: usize, const Q: usize> {
    /// The thread side.
    pub kernel: Kernel<'q, N, B, Q>,
    /// The interrupt side.
    pub isr: StepGenerator<'q, N, Q>,
    /// The steppers (axis `i` is `steppers[i]`).
    pub steppers: [SimStepper<N>; N],
    /// The limit switches, by switch index.
    pub switches: Vec<SimSwitch<N>>,
    /// Their pin-change interrupt, looked at after each step interrupt and poll.
    pub edges: EdgeWatch<'q>,
    /// The record of everything that moved.
    pub rec: Rc<RefCell<Recorder<N>>>,
    /// Ticks between two polls of the thread side.
    pub poll_period: u64,
    /// Interrupt calls made.
    pub interrupts: u64,
    /// Largest interrupt latency, ticks: each alarm is served up to this late (pseudo-random,
    /// deterministic), as a busy board would.
    pub max_latency: u64,
    latency_seed: u64,
    alarm: Option<u64>,
    next_poll: u64,
}

impl<'q, const N: usize, const B: usize, const Q: usize> Simulation<'q, N, B, Q> {
    /// Wire `kernel` and `isr` to recording steppers, with the thread side polled every
    /// millisecond. `timing` must be what the kernel was split with.
    pub fn new(
        kernel: Kernel<'q, N, B, Q>,
        isr: StepGenerator<'q, N, Q>,
        timing: StepTiming,
    ) -> Self {
        let tick_hz = kernel.tick_hz();
        let rec = Rc::new(RefCell::new(Recorder {
            now: 0,
            position: [0; N],
            steps: (0..N).map(|_| Vec::new()).collect(),
            violations: Vec::new(),
            record: true,
            step_count: [0; N],
            pulse: u64::from(Duration::from_nanos_ceil(timing.min_pulse_ns, tick_hz).ticks()),
            dir_setup: u64::from(Duration::from_nanos_ceil(timing.dir_setup_ns, tick_hz).ticks()),
            dir_neg: [false; N],
            dir_set_at: [0; N],
            high: [false; N],
            rose_at: [0; N],
            fell_at: [0; N],
        }));
        let steppers = core::array::from_fn(|axis| SimStepper {
            axis,
            rec: rec.clone(),
        });
        let edges = EdgeWatch::new(isr.switch_alert());
        Self {
            kernel,
            isr,
            steppers,
            switches: Vec::new(),
            edges,
            rec,
            poll_period: (u64::from(tick_hz) / 1000).max(1),
            interrupts: 0,
            max_latency: 0,
            latency_seed: 0x2545_f491_4f6c_dd1d,
            alarm: None,
            next_poll: 0,
        }
    }

    /// Add a switch at switch index `switches.len()`, on `axis`, triggered at `at_steps` and
    /// beyond towards the negative (`negative_end`) or positive end.
    pub fn add_switch(&mut self, axis: usize, at_steps: i32, negative_end: bool) {
        self.switches.push(SimSwitch {
            axis,
            at_steps,
            negative_end,
            rec: self.rec.clone(),
        });
    }

    /// Virtual time, ticks.
    pub fn now(&self) -> u64 {
        self.rec.borrow().now
    }

    fn instant(&self) -> Instant {
        Instant::from_ticks(self.now() as u32)
    }

    /// Run the step interrupt once, now.
    fn fire(&mut self) {
        let now = self.now();
        let at = self
            .isr
            .on_alarm(self.instant(), &mut self.steppers, &mut self.switches);
        self.interrupts += 1;
        self.edges.look(&mut self.switches);
        self.alarm =
            at.map(|i| now + i.signed_ticks_since(Instant::from_ticks(now as u32)).max(0) as u64);
    }

    /// Run the thread side once, now.
    pub fn poll(&mut self) {
        self.edges.look(&mut self.switches);
        if let Some(at) = self.kernel.poll(self.instant()) {
            let now = self.now();
            let t = now
                + at.signed_ticks_since(Instant::from_ticks(now as u32))
                    .max(0) as u64;
            self.alarm = Some(self.alarm.map_or(t, |a| a.min(t)));
        }
    }

    /// Advance virtual time to `until`, firing alarms and polling on the way.
    pub fn advance_to(&mut self, until: u64) {
        loop {
            let t_alarm = self.alarm.unwrap_or(u64::MAX);
            let t = t_alarm.min(self.next_poll);
            if t > until {
                let mut r = self.rec.borrow_mut();
                r.now = r.now.max(until);
                return;
            }
            {
                let mut r = self.rec.borrow_mut();
                r.now = r.now.max(t);
            }
            if t_alarm <= self.next_poll {
                self.alarm = None;
                if self.max_latency > 0 {
                    self.latency_seed ^= self.latency_seed << 13;
                    self.latency_seed ^= self.latency_seed >> 7;
                    self.latency_seed ^= self.latency_seed << 17;
                    let late = self.latency_seed % (self.max_latency + 1);
                    let mut r = self.rec.borrow_mut();
                    r.now += late;
                }
                self.fire();
            } else {
                self.next_poll = t + self.poll_period;
                self.poll();
            }
        }
    }

    /// Advance by `ticks`.
    pub fn advance(&mut self, ticks: u64) {
        let until = self.now() + ticks;
        self.advance_to(until);
    }

    /// Run until the kernel is idle (and not homing), at most `max_ticks`; whether it got there.
    pub fn run_until_idle(&mut self, max_ticks: u64) -> bool {
        let end = self.now() + max_ticks;
        loop {
            self.poll();
            if self.kernel.is_idle() && self.kernel.state() != crate::MachineState::Homing {
                return true;
            }
            if self.now() >= end {
                return false;
            }
            let step = self.poll_period;
            self.advance(step);
        }
    }

    /// Offer a G-code line until it is taken (advancing time while the kernel answers
    /// `Busy`), then poll once. Effects are ignored; errors are returned.
    pub fn send(&mut self, text: &str) -> Result<(), CommandError> {
        let line =
            Line::parse(text.as_bytes()).map_err(|_| CommandError::BadValue { letter: b'?' })?;
        for _ in 0..10_000_000u32 {
            match self.kernel.execute(&line)? {
                Reply::Busy => {
                    let step = self.poll_period;
                    self.advance(step);
                }
                _ => {
                    self.poll();
                    return Ok(());
                }
            }
        }
        Err(CommandError::NotIdle)
    }
}
