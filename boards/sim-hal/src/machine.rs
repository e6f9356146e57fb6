//! The simulated machine: shared state, the virtual clock and the step alarm.
//!
//! [`SimMachine`] is a cheap, cloneable handle to one machine's state: the virtual time, the
//! armed alarm, every axis (position in steps, driver lines, timing checks), every switch,
//! heater, PWM output and digital output, the beeper, the step trace and the timing
//! violations. The device handles it gives out ([`SimClock`], [`SimAlarm`],
//! [`crate::SimStepper`], [`crate::SimLimitSwitch`], [`crate::SimHeater`],
//! [`crate::SimOutputPin`], [`crate::SimBeeper`], …) implement the `forja-hal-abstraction` and
//! `embedded-hal` traits over that state; the test or the simulation loop inspects it through
//! the same handle.
//!
//! Single-threaded: the handles share the state through `Rc<RefCell<…>>`, each method borrows
//! it for the duration of the call only, so handles can be used in any order, including from
//! inside the simulation's callbacks.

use core::cell::RefCell;
use core::convert::Infallible;
use core::fmt;
use std::rc::Rc;

use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::clock::{Alarm, Clock};
use forja_hal_abstraction::stepper::Direction;
use forja_hal_abstraction::time::{Duration, Instant};

use crate::beeper::BeeperState;
use crate::config::{MachineConfig, SwitchSide};
use crate::digital::DigitalOutputState;
use crate::limit::SwitchState;
use crate::pwm::PwmState;
use crate::stepper::{AxisState, TimingViolation};
use crate::thermal::ThermalModel;
use crate::trace::StepTrace;

/// How many timing violations are kept for inspection; later ones are only counted.
pub const MAX_KEPT_VIOLATIONS: usize = 1000;

/// The state behind every handle of one machine.
pub(crate) struct State {
    pub(crate) tick_hz: u32,
    /// Virtual time since start, in ticks; never wraps.
    pub(crate) now: u64,
    /// The armed alarm, as an absolute tick count.
    pub(crate) alarm_at: Option<u64>,
    pub(crate) axes: Vec<AxisState>,
    pub(crate) switches: Vec<SwitchState>,
    pub(crate) heaters: Vec<ThermalModel>,
    /// The virtual time up to which the thermal models have been advanced.
    pub(crate) thermal_at: u64,
    pub(crate) outputs: Vec<PwmState>,
    pub(crate) digital_outputs: Vec<DigitalOutputState>,
    pub(crate) beeper: Option<BeeperState>,
    pub(crate) tracing: bool,
    pub(crate) trace: StepTrace,
    pub(crate) violations: Vec<TimingViolation>,
    pub(crate) violation_count: u64,
}

impl State {
    /// Bring the thermal models up to the current virtual time.
    pub(crate) fn sync_thermal(&mut self) {
        if self.now > self.thermal_at {
            let dt_s = (self.now - self.thermal_at) as f64 / f64::from(self.tick_hz);
            for h in &mut self.heaters {
                h.advance(dt_s);
            }
            self.thermal_at = self.now;
        }
    }

    pub(crate) fn record_violation(&mut self, v: TimingViolation) {
        self.violation_count += 1;
        if self.violations.len() < MAX_KEPT_VIOLATIONS {
            self.violations.push(v);
        }
    }
}

/// A device asked of a [`SimMachine`] that its machine file does not have.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum NoSuchDevice {
    /// No axis with this index.
    Axis(usize),
    /// The axis has no switch on this side.
    Switch {
        /// Axis index.
        axis: usize,
        /// The side asked for.
        side: SwitchSide,
    },
    /// No heater with this index.
    Heater(usize),
    /// No PWM output with this index.
    Output(usize),
    /// No digital (on/off) output with this index.
    DigitalOutput(usize),
    /// No beeper.
    Beeper,
    /// No touch probe (the machine file has no `[probe]`).
    Probe,
}

impl fmt::Display for NoSuchDevice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Axis(i) => write!(f, "the machine has no axis {i}"),
            Self::Switch { axis, side } => {
                write!(f, "axis {axis} has no switch on its {side:?} side")
            }
            Self::Heater(i) => write!(f, "the machine has no heater {i}"),
            Self::Output(i) => write!(f, "the machine has no output {i}"),
            Self::DigitalOutput(i) => write!(f, "the machine has no digital output {i}"),
            Self::Beeper => f.write_str("the machine has no beeper"),
            Self::Probe => f.write_str("the machine has no probe"),
        }
    }
}

impl std::error::Error for NoSuchDevice {}

/// A handle to one simulated machine. Clones share the machine.
#[derive(Clone)]
pub struct SimMachine {
    pub(crate) state: Rc<RefCell<State>>,
    config: Rc<MachineConfig>,
}

impl fmt::Debug for SimMachine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimMachine")
            .field("name", &self.config.name)
            .field("now_ticks", &self.now_ticks())
            .finish_non_exhaustive()
    }
}

impl SimMachine {
    /// A machine as `config` describes it, at virtual time 0, every axis at its `start_mm`,
    /// every driver disabled with its DIR line low (negative), every switch and the probe
    /// following the positions, every heater at `start_c` and off, every PWM output at duty 0,
    /// every digital output off, the beeper silent, no alarm armed, tracing off. A probe on an
    /// axis `config` does not have is left out.
    pub fn new(config: &MachineConfig) -> Self {
        let axes = config
            .axes
            .iter()
            .map(|a| AxisState::new(a, config.tick_hz))
            .collect();
        let probe = config
            .probe
            .as_ref()
            .and_then(|p| Some(SwitchState::probe(config.axes.get(p.axis)?, p)));
        let switches = config
            .axes
            .iter()
            .enumerate()
            .flat_map(|(i, a)| a.switches.iter().map(move |s| SwitchState::new(i, a, s)))
            .chain(probe)
            .collect();
        let state = State {
            tick_hz: config.tick_hz,
            now: 0,
            alarm_at: None,
            axes,
            switches,
            heaters: config.heaters.iter().map(ThermalModel::new).collect(),
            thermal_at: 0,
            outputs: config.outputs.iter().map(PwmState::new).collect(),
            digital_outputs: config
                .digital_outputs
                .iter()
                .map(DigitalOutputState::new)
                .collect(),
            beeper: config.beeper.as_ref().map(BeeperState::new),
            tracing: false,
            trace: StepTrace::new(
                config.tick_hz,
                config.axes.iter().map(|a| a.letter).collect(),
            )
            .with_scale(
                config.axes.iter().map(|a| a.steps_per_mm).collect(),
                config.axes.iter().map(|a| a.start_mm).collect(),
            ),
            violations: Vec::new(),
            violation_count: 0,
        };
        Self {
            state: Rc::new(RefCell::new(state)),
            config: Rc::new(config.clone()),
        }
    }

    /// The machine file this machine was built from.
    pub fn config(&self) -> &MachineConfig {
        &self.config
    }

    /// Ticks per second of the virtual clock.
    pub fn tick_hz(&self) -> u32 {
        self.config.tick_hz
    }

    // ---- virtual time -------------------------------------------------------------------

    /// Virtual time since start, in ticks (64 bits: never wraps).
    pub fn now_ticks(&self) -> u64 {
        self.state.borrow().now
    }

    /// Virtual time since start, in whole milliseconds: the clock of link sessions and hosts.
    pub fn now_ms(&self) -> u64 {
        (u128::from(self.now_ticks()) * 1000 / u128::from(self.tick_hz())) as u64
    }

    /// Virtual time since start, in seconds.
    pub fn now_secs(&self) -> f64 {
        self.now_ticks() as f64 / f64::from(self.tick_hz())
    }

    /// Move virtual time forward to `ticks`. A time at or before now changes nothing: virtual
    /// time never goes back. The thermal models follow lazily, exactly (see
    /// [`crate::thermal`]).
    pub fn advance_to(&self, ticks: u64) {
        let mut s = self.state.borrow_mut();
        if ticks > s.now {
            s.now = ticks;
        }
    }

    /// Move virtual time forward by `ticks`.
    pub fn advance_by(&self, ticks: u64) {
        let now = self.now_ticks();
        self.advance_to(now.saturating_add(ticks));
    }

    /// The full 64-bit tick count of `at`, a 32-bit instant within 2³¹ ticks of now.
    pub fn instant_to_ticks(&self, at: Instant) -> u64 {
        let now = self.now_ticks();
        let delta = i64::from(at.signed_ticks_since(Instant::from_ticks(now as u32)));
        now.saturating_add_signed(delta)
    }

    /// The virtual clock, for the kernel.
    pub fn clock(&self) -> SimClock {
        SimClock {
            state: Rc::clone(&self.state),
        }
    }

    /// The step alarm, for the kernel.
    pub fn alarm(&self) -> SimAlarm {
        SimAlarm {
            state: Rc::clone(&self.state),
        }
    }

    /// When the alarm is armed for, as an absolute tick count.
    pub fn alarm_at_ticks(&self) -> Option<u64> {
        self.state.borrow().alarm_at
    }

    /// Arm the alarm for absolute tick `ticks`; a time in the past fires at the current time.
    pub fn set_alarm_ticks(&self, ticks: u64) {
        let mut s = self.state.borrow_mut();
        s.alarm_at = Some(ticks.max(s.now));
    }

    /// Disarm the alarm and return when it was armed for.
    pub fn take_alarm(&self) -> Option<u64> {
        self.state.borrow_mut().alarm_at.take()
    }

    // ---- axes ---------------------------------------------------------------------------

    /// Number of axes.
    pub fn axis_count(&self) -> usize {
        self.config.axes.len()
    }

    /// The index of the axis named `letter` (either case).
    pub fn axis_index(&self, letter: char) -> Option<usize> {
        self.config.axis_index(letter)
    }

    pub(crate) fn check_axis(&self, axis: usize) -> Result<(), NoSuchDevice> {
        if axis < self.axis_count() {
            Ok(())
        } else {
            Err(NoSuchDevice::Axis(axis))
        }
    }

    fn with_axis<R>(&self, axis: usize, f: impl FnOnce(&AxisState) -> R) -> Option<R> {
        self.state.borrow().axes.get(axis).map(f)
    }

    /// Physical position of `axis`, in steps from machine zero.
    pub fn position_steps(&self, axis: usize) -> Option<i64> {
        self.with_axis(axis, |a| a.position)
    }

    /// Physical position of `axis`, in millimetres (degrees for a rotary axis).
    pub fn position_mm(&self, axis: usize) -> Option<f64> {
        let steps = self.position_steps(axis)?;
        Some(self.config.axes[axis].steps_to_mm(steps))
    }

    /// Physical positions of every axis, in millimetres (degrees for rotary axes), in axis
    /// order.
    pub fn positions_mm(&self) -> Vec<f64> {
        let s = self.state.borrow();
        self.config
            .axes
            .iter()
            .zip(&s.axes)
            .map(|(c, a)| c.steps_to_mm(a.position))
            .collect()
    }

    /// Move `axis` by hand to `steps` (as an operator would with the motors off). Not traced;
    /// resets the axis's lowest/highest seen positions to it.
    pub fn set_position_steps(&self, axis: usize, steps: i64) -> Result<(), NoSuchDevice> {
        let mut s = self.state.borrow_mut();
        let a = s.axes.get_mut(axis).ok_or(NoSuchDevice::Axis(axis))?;
        a.position = steps;
        a.lowest = steps;
        a.highest = steps;
        Ok(())
    }

    /// The lowest and highest positions of `axis` since start (or the last hand move), in steps:
    /// a test checks from them that a job stayed within travel.
    pub fn position_range_steps(&self, axis: usize) -> Option<(i64, i64)> {
        self.with_axis(axis, |a| (a.lowest, a.highest))
    }

    /// Steps `axis` has made (both directions).
    pub fn step_count(&self, axis: usize) -> Option<u64> {
        self.with_axis(axis, |a| a.steps)
    }

    /// Step pulses `axis` received while its driver was disabled: they moved nothing.
    pub fn lost_steps(&self, axis: usize) -> Option<u64> {
        self.with_axis(axis, |a| a.lost_steps)
    }

    /// Whether the driver of `axis` is enabled.
    pub fn is_enabled(&self, axis: usize) -> Option<bool> {
        self.with_axis(axis, |a| a.enabled)
    }

    /// The direction the DIR line of `axis` selects.
    pub fn direction(&self, axis: usize) -> Option<Direction> {
        self.with_axis(axis, |a| a.direction)
    }

    /// The first [`MAX_KEPT_VIOLATIONS`] step timing violations, in time order.
    pub fn violations(&self) -> Vec<TimingViolation> {
        self.state.borrow().violations.clone()
    }

    /// How many step timing violations happened in all.
    pub fn violation_count(&self) -> u64 {
        self.state.borrow().violation_count
    }

    // ---- trace --------------------------------------------------------------------------

    /// Start (`true`) or stop recording the step trace. Off by default: a long job makes
    /// millions of steps.
    pub fn set_tracing(&self, on: bool) {
        let start = self.positions_mm();
        let mut s = self.state.borrow_mut();
        if on && !s.tracing && s.trace.events().is_empty() {
            // A fresh trace begins where the axes are now.
            s.trace.set_start_mm(start);
        }
        s.tracing = on;
    }

    /// Whether the step trace is being recorded.
    pub fn is_tracing(&self) -> bool {
        self.state.borrow().tracing
    }

    /// Run `f` on the trace recorded so far.
    pub fn with_trace<R>(&self, f: impl FnOnce(&StepTrace) -> R) -> R {
        f(&self.state.borrow().trace)
    }

    /// The times of the traced steps of `axis`.
    pub fn step_times(&self, axis: usize) -> Vec<u64> {
        self.with_trace(|t| t.step_times(axis))
    }

    /// Take the trace recorded so far, leaving an empty one.
    pub fn take_trace(&self) -> StepTrace {
        let start = self.positions_mm();
        let mut s = self.state.borrow_mut();
        // The next trace begins where the axes are now.
        let empty = StepTrace::new(s.trace.tick_hz(), s.trace.axes().to_vec())
            .with_scale(s.trace.steps_per_mm().to_vec(), start);
        core::mem::replace(&mut s.trace, empty)
    }

    // ---- heaters and outputs ------------------------------------------------------------

    /// The index of the heater called `name`.
    pub fn heater_index(&self, name: &str) -> Option<usize> {
        self.config.heaters.iter().position(|h| h.name == name)
    }

    /// The index of the PWM output called `name`.
    pub fn output_index(&self, name: &str) -> Option<usize> {
        self.config.outputs.iter().position(|o| o.name == name)
    }
}

/// The virtual clock: implements [`Clock`].
///
/// Its [`Clock::now`] is the low 32 bits of the machine's virtual tick count. Virtual time moves
/// only when the simulation loop (or a test) advances it; in paced mode the loop keeps it in
/// step with the wall clock.
#[derive(Clone)]
pub struct SimClock {
    state: Rc<RefCell<State>>,
}

impl SimClock {
    /// Virtual time since start in ticks, not truncated.
    pub fn now_ticks(&self) -> u64 {
        self.state.borrow().now
    }
}

impl fmt::Debug for SimClock {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimClock")
            .field("now_ticks", &self.now_ticks())
            .finish()
    }
}

impl Clock for SimClock {
    fn now(&self) -> Instant {
        Instant::from_ticks(self.state.borrow().now as u32)
    }

    fn tick_hz(&self) -> u32 {
        self.state.borrow().tick_hz
    }
}

/// The step alarm: implements [`Alarm`]. The simulation loop fires it
/// ([`crate::Simulation`]).
#[derive(Clone)]
pub struct SimAlarm {
    state: Rc<RefCell<State>>,
}

impl SimAlarm {
    /// When the alarm is armed for, as an absolute tick count.
    pub fn armed_at_ticks(&self) -> Option<u64> {
        self.state.borrow().alarm_at
    }

    /// Arm the alarm `after` ticks from now.
    pub fn set_alarm_in(&mut self, after: Duration) {
        let mut s = self.state.borrow_mut();
        s.alarm_at = Some(s.now + u64::from(after.ticks()));
    }
}

impl fmt::Debug for SimAlarm {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimAlarm")
            .field("armed_at_ticks", &self.armed_at_ticks())
            .finish()
    }
}

impl ErrorType for SimAlarm {
    type Error = Infallible;
}

impl Alarm for SimAlarm {
    /// Arms the alarm at `at`, read as within 2³¹ ticks of now: an instant at or before now
    /// fires at the current virtual time, on the loop's next turn.
    fn set_alarm(&mut self, at: Instant) -> Result<(), Infallible> {
        let mut s = self.state.borrow_mut();
        let delta = at.signed_ticks_since(Instant::from_ticks(s.now as u32));
        s.alarm_at = Some(s.now + u64::from(delta.max(0).unsigned_abs()));
        Ok(())
    }

    fn clear_alarm(&mut self) {
        self.state.borrow_mut().alarm_at = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn machine() -> SimMachine {
        SimMachine::new(&MachineConfig::default_router())
    }

    #[test]
    fn clock_is_virtual_and_wraps_at_32_bits() {
        let m = machine();
        let clock = m.clock();
        assert_eq!(clock.tick_hz(), 1_000_000);
        assert_eq!(clock.now(), Instant::from_ticks(0));
        m.advance_to(1_500);
        assert_eq!(clock.now().ticks(), 1_500);
        m.advance_to(1_000);
        assert_eq!(m.now_ticks(), 1_500, "time never goes back");
        m.advance_to((1 << 32) + 7);
        assert_eq!(clock.now().ticks(), 7);
        assert_eq!(clock.now_ticks(), (1 << 32) + 7);
        assert!((m.now_secs() - 4294.967303).abs() < 1e-6);
    }

    #[test]
    fn alarm_converts_wrapping_instants_to_absolute_time() {
        let m = machine();
        let mut alarm = m.alarm();
        m.advance_to((1 << 32) - 10);
        // 20 ticks ahead, across the 32-bit wrap.
        alarm.set_alarm(Instant::from_ticks(10)).unwrap();
        assert_eq!(m.alarm_at_ticks(), Some((1 << 32) + 10));
        assert_eq!(m.instant_to_ticks(Instant::from_ticks(10)), (1 << 32) + 10);
        // An instant in the past fires now, never 2^32 ticks later.
        alarm
            .set_alarm(Instant::from_ticks(((1u64 << 32) - 50) as u32))
            .unwrap();
        assert_eq!(m.alarm_at_ticks(), Some((1 << 32) - 10));
        alarm.set_alarm_in(Duration::from_ticks(5));
        assert_eq!(alarm.armed_at_ticks(), Some((1 << 32) - 5));
        alarm.clear_alarm();
        assert_eq!(m.alarm_at_ticks(), None);
        m.set_alarm_ticks(3);
        assert_eq!(m.take_alarm(), Some((1 << 32) - 10));
        assert_eq!(m.take_alarm(), None);
    }

    #[test]
    fn lookups() {
        let m = machine();
        assert_eq!(m.axis_count(), 4);
        assert_eq!(m.axis_index('z'), Some(2));
        assert_eq!(m.output_index("spindle"), Some(0));
        assert_eq!(m.heater_index("bed"), None);
        assert_eq!(m.position_mm(0), Some(150.0));
        assert_eq!(m.positions_mm(), vec![150.0, 150.0, 50.0, 0.0]);
        assert_eq!(m.position_steps(2), Some(50 * 400));
        assert_eq!(m.position_steps(9), None);
        assert_eq!(m.stepper(9).unwrap_err(), NoSuchDevice::Axis(9));
        assert!(m.stepper(9).unwrap_err().to_string().contains("no axis 9"));
        m.set_position_steps(0, -3).unwrap();
        assert_eq!(m.position_range_steps(0), Some((-3, -3)));
    }
}
