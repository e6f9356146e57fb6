//! The kernel on the simulator's virtual hardware (`forja-sim-hal`), wired as a board wires it:
//! the step interrupt ([`StepGenerator::on_alarm`]) over the simulated drivers and switches on
//! the simulation's alarm, the thread side polled every millisecond of virtual time. The
//! drivers check their pulse timing and the machine records every step with its tick.
//!
//! [`Wiring`] is the interrupt side, for whoever owns the kernel (the controller's tests in
//! `forja-app` include this file and wire it under their controller); [`KernelSim`] is the
//! kernel alone on it. Written for a `no_std` crate's tests too: what it takes of `std` is
//! named.

use std::vec;
use std::vec::Vec;

use forja_hal_abstraction::clock::Alarm as _;
use forja_hal_abstraction::stepper::{Direction, StepTiming, StepperEnable as _};
use forja_hal_abstraction::time::Instant;
use forja_motion::{
    AxisKind, CommandError, Kernel, MachineConfig, MachineState, Reply, StepGenerator, SwitchAlert,
};
use forja_protocol::gcode::Line;
use forja_sim_hal::config::{
    AxisConfig as FileAxis, AxisKind as FileAxisKind, LinkConfig, MachineConfig as MachineFile,
    SwitchConfig, SwitchPolarity, SwitchSide,
};
use forja_sim_hal::{
    Firmware, Flow, SimAlarm, SimLimitSwitch, SimMachine, SimStepper, Simulation, SimulationConfig,
    SwitchEdges, TimingViolation,
};

/// How far from 0 the switches of [`machine_file`] wait until a test places one, mm.
const PARKED_MM: f64 = 1e9;

/// The simulated machine of a kernel configuration: its axes at 0 with drivers of `timing`, a
/// switch at each end of every axis, parked out of reach until a test places it
/// ([`Wiring::add_switch`]). Travel is not limited: the kernel's limits are under test.
pub fn machine_file<const N: usize>(
    config: &MachineConfig<N>,
    tick_hz: u32,
    timing: StepTiming,
) -> MachineFile {
    let parked = |side, position_mm| SwitchConfig {
        side,
        position_mm,
        polarity: SwitchPolarity::NormallyOpen,
    };
    MachineFile {
        name: "kernel test bench".into(),
        tick_hz,
        axes: config
            .axes
            .iter()
            .map(|a| FileAxis {
                letter: char::from(a.letter),
                kind: match a.kind {
                    AxisKind::Rotary => FileAxisKind::Rotary,
                    AxisKind::Extruder => FileAxisKind::Extruder,
                    AxisKind::Linear => FileAxisKind::Linear,
                },
                steps_per_mm: f64::from(a.steps_per_mm),
                max_rate_mm_min: f64::from(a.max_rate_mm_min),
                accel_mm_s2: f64::from(a.accel_mm_s2),
                travel: None,
                start_mm: 0.0,
                homing: None,
                switches: vec![
                    parked(SwitchSide::Min, -PARKED_MM),
                    parked(SwitchSide::Max, PARKED_MM),
                ],
                step_timing: timing,
            })
            .collect(),
        heaters: Vec::new(),
        outputs: Vec::new(),
        digital_outputs: Vec::new(),
        beeper: None,
        probe: None,
        link: LinkConfig::default(),
    }
}

/// One rising step edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepRecord {
    /// Virtual time of the edge, ticks since the start of the simulation.
    pub tick: u64,
    /// The axis position after the step, in steps.
    pub position: i32,
}

/// What the simulated machine did.
#[derive(Debug, Clone)]
pub struct Record<const N: usize> {
    /// Where each motor is, in steps.
    pub position: [i32; N],
    /// Every step of every axis while the machine traced them.
    pub steps: Vec<Vec<StepRecord>>,
    /// Timing rules the step interrupt broke (should stay empty).
    pub violations: Vec<TimingViolation>,
}

/// The kernel's step interrupt on a simulated machine, wired as a board wires it.
pub struct Wiring<'q, const N: usize, const Q: usize> {
    /// Where the switch inputs' pin-change interrupt reports edges: the interrupt side's,
    /// unless a test points it elsewhere.
    pub alert: SwitchAlert<'q>,
    /// The simulated machine.
    pub machine: SimMachine,
    isr: Isr<'q, N, Q>,
    sim: Simulation,
}

/// What the step interrupt owns.
struct Isr<'q, const N: usize, const Q: usize> {
    generator: StepGenerator<'q, N, Q>,
    steppers: [SimStepper; N],
    /// The switches the interrupt side samples, in switch-index order.
    switches: Vec<SimLimitSwitch>,
    edges: SwitchEdges,
    alarm: SimAlarm,
}

/// One turn of the loop: the interrupt side, and the thread side `poll`, which returns when to
/// arm the alarm.
struct Turn<'a, 'q, const N: usize, const Q: usize, P> {
    isr: &'a mut Isr<'q, N, Q>,
    alert: &'a SwitchAlert<'q>,
    poll: P,
}

impl<const N: usize, const Q: usize, P> Turn<'_, '_, N, Q, P> {
    /// The pin-change interrupt: report an edge when a switch changed since the last look.
    fn look_at_switches(&mut self) {
        if self.isr.edges.take() {
            self.alert.notify();
        }
    }
}

impl<const N: usize, const Q: usize, P: FnMut(Instant) -> Option<Instant>> Firmware
    for Turn<'_, '_, N, Q, P>
{
    fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        let isr = &mut *self.isr;
        let next = isr
            .generator
            .on_alarm(now, &mut isr.steppers, &mut isr.switches);
        self.look_at_switches();
        next
    }

    fn poll(&mut self, now: Instant) -> Flow {
        self.look_at_switches();
        if let Some(at) = (self.poll)(now) {
            let _ = self.isr.alarm.set_alarm(at);
        }
        Flow::Continue
    }
}

impl<'q, const N: usize, const Q: usize> Wiring<'q, N, Q> {
    /// `isr` on the machine of `config` ([`machine_file`]) at `tick_hz`, its drivers enabled
    /// and checking `timing` (what the kernel was split with), every step traced.
    pub fn new(
        isr: StepGenerator<'q, N, Q>,
        config: &MachineConfig<N>,
        tick_hz: u32,
        timing: StepTiming,
    ) -> Self {
        let machine = SimMachine::new(&machine_file(config, tick_hz, timing));
        machine.set_tracing(true);
        let steppers = core::array::from_fn(|axis| {
            let mut stepper = machine.stepper(axis).expect("an axis of the file");
            let _ = stepper.set_enabled(true);
            stepper
        });
        Self {
            alert: isr.switch_alert(),
            isr: Isr {
                generator: isr,
                steppers,
                switches: Vec::new(),
                edges: machine.switch_edges(),
                alarm: machine.alarm(),
            },
            sim: Simulation::new(machine.clone(), SimulationConfig::new(tick_hz)),
            machine,
        }
    }

    /// Place a switch at switch index `switches.len()`: on `axis`, triggered at `at_steps` and
    /// beyond towards the negative (`negative_end`) or positive end.
    pub fn add_switch(&mut self, axis: usize, at_steps: i32, negative_end: bool) {
        let side = if negative_end {
            SwitchSide::Min
        } else {
            SwitchSide::Max
        };
        self.machine
            .set_switch_position_steps(axis, side, i64::from(at_steps))
            .expect("an axis of the file");
        let switch = self.machine.limit_switch(axis, side);
        self.isr.switches.push(switch.expect("an axis of the file"));
    }

    /// The switches placed so far, in switch-index order.
    pub fn switches(&self) -> &[SimLimitSwitch] {
        &self.isr.switches
    }

    /// The simulation's settings (interrupt latency, poll period).
    pub fn config_mut(&mut self) -> &mut SimulationConfig {
        self.sim.config_mut()
    }

    /// Ticks between two polls of the thread side.
    pub fn poll_period(&self) -> u64 {
        self.sim.config().poll_period_ticks
    }

    /// Virtual time, ticks.
    pub fn now(&self) -> u64 {
        self.machine.now_ticks()
    }

    /// The loop's view of the wiring, `poll` as its thread side; and the simulation.
    fn turn<P>(&mut self, poll: P) -> (Turn<'_, 'q, N, Q, P>, &mut Simulation) {
        let turn = Turn {
            isr: &mut self.isr,
            alert: &self.alert,
            poll,
        };
        (turn, &mut self.sim)
    }

    /// Run virtual time to `until`, the step interrupt on its alarm and `poll` (the thread
    /// side: returns when to arm the alarm) every poll period.
    pub fn advance_to(&mut self, until: u64, poll: impl FnMut(Instant) -> Option<Instant>) {
        let (mut turn, sim) = self.turn(poll);
        sim.run_until(&mut turn, until)
            .expect("the step interrupt lets time move");
    }

    /// Run the thread side once, now.
    pub fn poll_now(&mut self, poll: impl FnMut(Instant) -> Option<Instant>) {
        let now = Instant::from_ticks(self.now() as u32);
        let (mut turn, _) = self.turn(poll);
        turn.poll(now);
    }

    /// Where each motor is, in steps.
    pub fn positions(&self) -> [i32; N] {
        core::array::from_fn(|axis| self.machine.position_steps(axis).unwrap_or(0) as i32)
    }

    /// What the machine did so far.
    pub fn record(&self) -> Record<N> {
        let position = self.positions();
        let steps = self.machine.with_trace(|trace| {
            (0..N)
                .map(|axis| {
                    let mut at = position[axis] - trace.net_steps(axis) as i32;
                    trace
                        .steps(axis)
                        .map(|(tick, direction)| {
                            at += if direction == Direction::Negative {
                                -1
                            } else {
                                1
                            };
                            StepRecord { tick, position: at }
                        })
                        .collect()
                })
                .collect()
        });
        Record {
            position,
            steps,
            violations: self.machine.violations(),
        }
    }
}

/// The thread loop's turn: `Kernel::poll`, again at once while it has steps left to prepare
/// (`Kernel::needs_poll`), as a board's loop does. Returns where to arm the alarm.
fn poll_loop<const N: usize, const B: usize, const Q: usize>(
    kernel: &mut Kernel<'_, N, B, Q>,
    now: Instant,
) -> Option<Instant> {
    let mut arm = kernel.poll(now);
    while kernel.needs_poll() {
        arm = arm.or(kernel.poll(now));
    }
    arm
}

/// A kernel and its interrupt side on a simulated machine.
pub struct KernelSim<'q, const N: usize, const B: usize, const Q: usize> {
    /// The thread side.
    pub kernel: Kernel<'q, N, B, Q>,
    /// The interrupt side and the machine.
    pub wiring: Wiring<'q, N, Q>,
}

impl<'q, const N: usize, const B: usize, const Q: usize> KernelSim<'q, N, B, Q> {
    /// Wire `kernel` and `isr` to the simulated machine of the kernel's configuration, with
    /// the thread side polled every millisecond. `timing` must be what the kernel was split
    /// with.
    pub fn new(
        kernel: Kernel<'q, N, B, Q>,
        isr: StepGenerator<'q, N, Q>,
        timing: StepTiming,
    ) -> Self {
        let wiring = Wiring::new(isr, kernel.config(), kernel.tick_hz(), timing);
        Self { kernel, wiring }
    }

    /// Place a switch at switch index `switches.len()`, on `axis`, triggered at `at_steps` and
    /// beyond towards the negative (`negative_end`) or positive end.
    pub fn add_switch(&mut self, axis: usize, at_steps: i32, negative_end: bool) {
        self.wiring.add_switch(axis, at_steps, negative_end);
    }

    /// Virtual time, ticks.
    pub fn now(&self) -> u64 {
        self.wiring.now()
    }

    /// Ticks between two polls of the thread side.
    pub fn poll_period(&self) -> u64 {
        self.wiring.poll_period()
    }

    /// Where each motor is, in steps.
    pub fn positions(&self) -> [i32; N] {
        self.wiring.positions()
    }

    /// What the machine did so far.
    pub fn record(&self) -> Record<N> {
        self.wiring.record()
    }

    /// Run the thread side once, now.
    pub fn poll(&mut self) {
        let kernel = &mut self.kernel;
        self.wiring.poll_now(|now| poll_loop(kernel, now));
    }

    /// Advance virtual time to `until`, firing alarms and polling on the way.
    pub fn advance_to(&mut self, until: u64) {
        let kernel = &mut self.kernel;
        self.wiring.advance_to(until, |now| poll_loop(kernel, now));
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
            if self.kernel.is_idle() && self.kernel.state() != MachineState::Homing {
                return true;
            }
            if self.now() >= end {
                return false;
            }
            self.advance(self.poll_period());
        }
    }

    /// Offer a G-code line until it is taken (advancing time while the kernel answers
    /// `Busy`), then poll once. Effects are ignored; errors are returned.
    pub fn send(&mut self, text: &str) -> Result<(), CommandError> {
        let line =
            Line::parse(text.as_bytes()).map_err(|_| CommandError::BadValue { letter: b'?' })?;
        for _ in 0..10_000_000u32 {
            match self.kernel.execute(&line)? {
                Reply::Busy => self.advance(self.poll_period()),
                _ => {
                    self.poll();
                    return Ok(());
                }
            }
        }
        Err(CommandError::NotIdle)
    }
}
