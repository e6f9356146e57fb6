//! Simulated step/direction drivers.
//!
//! Each axis has a simulated driver chip with three input lines, modelled at the electrical
//! level:
//!
//! | line | active level | effect |
//! |---|---|---|
//! | STEP | high | a rising edge of an enabled driver moves the axis one step in the DIR direction |
//! | DIR | high = positive | selects the direction of the following steps |
//! | ENABLE | **low** = enabled | energises the motor (as on the A4988, DRV8825 and TMC22xx) |
//!
//! Two ways in, to the same lines:
//! - [`SimStepper`] implements [`Stepper`] and [`StepperEnable`] directly;
//! - [`SimStepDirPins`] gives the three lines as `embedded-hal` [`OutputPin`]s, so that a board
//!   can wire the generic step/dir driver of `forja-drivers` over them, exactly as a firmware
//!   board wires it over GPIO (configure that driver with the levels of the table above).
//!
//! # Timing checks
//!
//! The driver enforces the [`StepTiming`] it reports (the machine file's `min_pulse_ns` and
//! `dir_setup_ns`), against the virtual clock: a STEP rising edge sooner than `dir_setup_ns`
//! after a DIR change, a STEP high time shorter than `min_pulse_ns`, or a low time between two
//! pulses shorter than `min_pulse_ns`, is recorded as a [`TimingViolation`] (see
//! [`crate::SimMachine::violations`]). The step still happens: a real chip may or may not miss
//! it, and the violation is the finding. Times are compared in whole ticks: a minimum of
//! `ns` needs `ceil(ns × tick_hz / 10⁹)` ticks.
//!
//! Two rules of order are checked as well: DIR must not change while STEP is high (drivers
//! that step on both edges, such as the TMC22xx with `dedge`, read DIR at the falling edge
//! too), and through [`SimStepper`] a `step_begin` must be followed by a `step_end` before the
//! next `step_begin` (on the pins, driving a line to the level it has is no edge and no fault).

use core::convert::Infallible;
use core::fmt;

use embedded_hal::digital::{self, OutputPin};
use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::stepper::{Direction, StepTiming, Stepper, StepperEnable};
use forja_hal_abstraction::time::Duration;

use crate::config::AxisConfig;
use crate::machine::{NoSuchDevice, SimMachine, State};
use crate::trace::{TraceEvent, TraceEventKind};

/// Which timing rule a step edge broke.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ViolationKind {
    /// A STEP rising edge came sooner than `dir_setup_ns` after a DIR change.
    DirSetup,
    /// A STEP pulse was high for less than `min_pulse_ns`.
    PulseHigh,
    /// STEP was low for less than `min_pulse_ns` between two pulses.
    PulseLow,
    /// DIR changed while STEP was high.
    DirDuringPulse,
    /// [`SimStepper`] was told to begin a pulse while STEP was high, or to end one while it
    /// was low.
    UnpairedEdge,
}

impl ViolationKind {
    /// Whether the rule is a minimum time (with ticks to compare), not a rule of order.
    pub fn is_timed(self) -> bool {
        matches!(self, Self::DirSetup | Self::PulseHigh | Self::PulseLow)
    }
}

impl fmt::Display for ViolationKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::DirSetup => "DIR set-up time",
            Self::PulseHigh => "STEP high time",
            Self::PulseLow => "STEP low time",
            Self::DirDuringPulse => "DIR change during a STEP pulse",
            Self::UnpairedEdge => "STEP edge without its pair",
        })
    }
}

/// A step edge that broke the driver's timing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct TimingViolation {
    /// Virtual time of the offending edge, in ticks since start.
    pub time_ticks: u64,
    /// Axis index.
    pub axis: usize,
    /// The rule broken.
    pub kind: ViolationKind,
    /// Ticks between the edges concerned (0 for a rule of order).
    pub actual_ticks: u64,
    /// Ticks the rule needs (0 for a rule of order).
    pub required_ticks: u64,
}

impl fmt::Display for TimingViolation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "tick {}: axis {}: {}",
            self.time_ticks, self.axis, self.kind
        )?;
        if self.kind.is_timed() {
            write!(
                f,
                " of {} ticks, needs {}",
                self.actual_ticks, self.required_ticks
            )?;
        }
        Ok(())
    }
}

/// One axis's driver and mechanics.
pub(crate) struct AxisState {
    pub(crate) position: i64,
    pub(crate) lowest: i64,
    pub(crate) highest: i64,
    pub(crate) steps: u64,
    pub(crate) lost_steps: u64,
    pub(crate) enabled: bool,
    pub(crate) direction: Direction,
    step_high: bool,
    dir_changed_at: Option<u64>,
    rose_at: Option<u64>,
    fell_at: Option<u64>,
    pub(crate) timing: StepTiming,
    pulse_ticks: u64,
    dir_setup_ticks: u64,
}

impl AxisState {
    pub(crate) fn new(config: &AxisConfig, tick_hz: u32) -> Self {
        let start = config.mm_to_steps(config.start_mm);
        let timing = config.step_timing;
        Self {
            position: start,
            lowest: start,
            highest: start,
            steps: 0,
            lost_steps: 0,
            enabled: false,
            direction: Direction::Negative,
            step_high: false,
            dir_changed_at: None,
            rose_at: None,
            fell_at: None,
            timing,
            pulse_ticks: u64::from(Duration::from_nanos_ceil(timing.min_pulse_ns, tick_hz).ticks()),
            dir_setup_ticks: u64::from(
                Duration::from_nanos_ceil(timing.dir_setup_ns, tick_hz).ticks(),
            ),
        }
    }
}

impl State {
    fn trace_event(&mut self, axis: usize, kind: TraceEventKind) {
        if self.tracing {
            self.trace.push(TraceEvent {
                time_ticks: self.now,
                axis,
                kind,
            });
        }
    }

    /// Drive the STEP line of `axis` to `high`.
    pub(crate) fn drive_step(&mut self, axis: usize, high: bool) {
        let now = self.now;
        let Some(a) = self.axes.get_mut(axis) else {
            return;
        };
        if a.step_high == high {
            return;
        }
        a.step_high = high;
        let mut found = [None, None];
        if high {
            if let Some(fell) = a.fell_at
                && now - fell < a.pulse_ticks
            {
                found[0] = Some((ViolationKind::PulseLow, now - fell, a.pulse_ticks));
            }
            if let Some(changed) = a.dir_changed_at
                && now - changed < a.dir_setup_ticks
            {
                found[1] = Some((ViolationKind::DirSetup, now - changed, a.dir_setup_ticks));
            }
            a.rose_at = Some(now);
            let moved = if a.enabled {
                a.position += match a.direction {
                    Direction::Positive => 1,
                    Direction::Negative => -1,
                };
                a.lowest = a.lowest.min(a.position);
                a.highest = a.highest.max(a.position);
                a.steps += 1;
                Some(a.direction)
            } else {
                a.lost_steps += 1;
                None
            };
            if let Some(d) = moved {
                self.trace_event(axis, TraceEventKind::Step(d));
            }
        } else {
            if let Some(rose) = a.rose_at
                && now - rose < a.pulse_ticks
            {
                found[0] = Some((ViolationKind::PulseHigh, now - rose, a.pulse_ticks));
            }
            a.fell_at = Some(now);
        }
        for (kind, actual_ticks, required_ticks) in found.into_iter().flatten() {
            self.record_violation(TimingViolation {
                time_ticks: now,
                axis,
                kind,
                actual_ticks,
                required_ticks,
            });
        }
    }

    /// Drive the DIR line of `axis` to select `direction`.
    pub(crate) fn drive_dir(&mut self, axis: usize, direction: Direction) {
        let now = self.now;
        let Some(a) = self.axes.get_mut(axis) else {
            return;
        };
        if a.direction != direction {
            a.direction = direction;
            a.dir_changed_at = Some(now);
            let during_pulse = a.step_high;
            self.trace_event(axis, TraceEventKind::Dir(direction));
            if during_pulse {
                self.record_order_violation(axis, ViolationKind::DirDuringPulse);
            }
        }
    }

    /// Drive the STEP line of `axis` to `high` for a [`SimStepper`], which must pair its
    /// edges: a line already at `high` is an [`ViolationKind::UnpairedEdge`].
    fn drive_step_paired(&mut self, axis: usize, high: bool) {
        if self.axes.get(axis).is_some_and(|a| a.step_high == high) {
            self.record_order_violation(axis, ViolationKind::UnpairedEdge);
        }
        self.drive_step(axis, high);
    }

    fn record_order_violation(&mut self, axis: usize, kind: ViolationKind) {
        self.record_violation(TimingViolation {
            time_ticks: self.now,
            axis,
            kind,
            actual_ticks: 0,
            required_ticks: 0,
        });
    }

    /// Drive the ENABLE line of `axis` to enable (`true`) or release the motor.
    pub(crate) fn drive_enable(&mut self, axis: usize, enabled: bool) {
        let Some(a) = self.axes.get_mut(axis) else {
            return;
        };
        if a.enabled != enabled {
            a.enabled = enabled;
            self.trace_event(axis, TraceEventKind::Enable(enabled));
        }
    }
}

impl SimMachine {
    /// The driver of `axis`, as a [`Stepper`] + [`StepperEnable`].
    pub fn stepper(&self, axis: usize) -> Result<SimStepper, NoSuchDevice> {
        self.check_axis(axis)?;
        Ok(SimStepper {
            machine: self.clone(),
            axis,
        })
    }

    /// The STEP, DIR and ENABLE lines of the driver of `axis`, as output pins.
    pub fn step_dir_pins(&self, axis: usize) -> Result<SimStepDirPins, NoSuchDevice> {
        self.check_axis(axis)?;
        let pin = |line| SimDriverPin {
            machine: self.clone(),
            axis,
            line,
        };
        Ok(SimStepDirPins {
            step: pin(DriverLine::Step),
            dir: pin(DriverLine::Dir),
            enable: pin(DriverLine::Enable),
        })
    }
}

/// The simulated driver of one axis: implements [`Stepper`] and [`StepperEnable`].
///
/// Every method is one state update and never fails ([`Infallible`]).
#[derive(Clone)]
pub struct SimStepper {
    machine: SimMachine,
    axis: usize,
}

impl SimStepper {
    /// The axis this driver moves.
    pub fn axis(&self) -> usize {
        self.axis
    }

    /// Drive this driver's lines: `f` on the machine's state and the axis.
    fn drive(&self, f: impl FnOnce(&mut State, usize)) {
        f(&mut self.machine.state.borrow_mut(), self.axis);
    }
}

impl fmt::Debug for SimStepper {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimStepper")
            .field("axis", &self.axis)
            .finish()
    }
}

impl ErrorType for SimStepper {
    type Error = Infallible;
}

impl Stepper for SimStepper {
    fn set_direction(&mut self, direction: Direction) -> Result<(), Infallible> {
        self.drive(|s, axis| s.drive_dir(axis, direction));
        Ok(())
    }

    fn step_begin(&mut self) -> Result<(), Infallible> {
        self.drive(|s, axis| s.drive_step_paired(axis, true));
        Ok(())
    }

    fn step_end(&mut self) -> Result<(), Infallible> {
        self.drive(|s, axis| s.drive_step_paired(axis, false));
        Ok(())
    }

    fn timing(&self) -> StepTiming {
        self.machine.state.borrow().axes[self.axis].timing
    }
}

impl StepperEnable for SimStepper {
    fn set_enabled(&mut self, enabled: bool) -> Result<(), Infallible> {
        self.drive(|s, axis| s.drive_enable(axis, enabled));
        Ok(())
    }
}

/// Which input of the simulated driver chip a [`SimDriverPin`] drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DriverLine {
    /// STEP, active high.
    Step,
    /// DIR, high = positive.
    Dir,
    /// ENABLE, active low.
    Enable,
}

/// One input line of a simulated driver chip, as an `embedded-hal` output pin.
#[derive(Clone)]
pub struct SimDriverPin {
    machine: SimMachine,
    axis: usize,
    line: DriverLine,
}

impl SimDriverPin {
    /// The line this pin drives.
    pub fn line(&self) -> DriverLine {
        self.line
    }

    fn drive(&mut self, high: bool) {
        let mut s = self.machine.state.borrow_mut();
        match self.line {
            DriverLine::Step => s.drive_step(self.axis, high),
            DriverLine::Dir => s.drive_dir(
                self.axis,
                if high {
                    Direction::Positive
                } else {
                    Direction::Negative
                },
            ),
            DriverLine::Enable => s.drive_enable(self.axis, !high),
        }
    }
}

impl fmt::Debug for SimDriverPin {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimDriverPin")
            .field("axis", &self.axis)
            .field("line", &self.line)
            .finish()
    }
}

impl digital::ErrorType for SimDriverPin {
    type Error = Infallible;
}

impl OutputPin for SimDriverPin {
    fn set_low(&mut self) -> Result<(), Infallible> {
        self.drive(false);
        Ok(())
    }

    fn set_high(&mut self) -> Result<(), Infallible> {
        self.drive(true);
        Ok(())
    }
}

/// The three input lines of one axis's simulated driver chip.
#[derive(Debug, Clone)]
pub struct SimStepDirPins {
    /// STEP, active high.
    pub step: SimDriverPin,
    /// DIR, high = positive.
    pub dir: SimDriverPin,
    /// ENABLE, active low.
    pub enable: SimDriverPin,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MachineConfig;

    /// The router: 1 MHz ticks, conservative timing (2 µs pulse = 2 ticks, 1 µs set-up = 1).
    fn machine() -> SimMachine {
        let m = SimMachine::new(&MachineConfig::default_router());
        m.set_tracing(true);
        m
    }

    /// The rules broken so far, in time order.
    fn violation_kinds(m: &SimMachine) -> Vec<ViolationKind> {
        m.violations().iter().map(|v| v.kind).collect()
    }

    /// A well-timed step: DIR already set, high for `high` ticks, then low.
    fn pulse(m: &SimMachine, s: &mut SimStepper, high: u64, low: u64) {
        s.step_begin().unwrap();
        m.advance_by(high);
        s.step_end().unwrap();
        m.advance_by(low);
    }

    #[test]
    fn steps_move_the_axis_in_the_current_direction() {
        let m = machine();
        let mut x = m.stepper(0).unwrap();
        let start = m.position_steps(0).unwrap();
        assert_eq!(x.timing(), StepTiming::CONSERVATIVE);
        x.set_enabled(true).unwrap();
        x.set_direction(Direction::Positive).unwrap();
        m.advance_by(10);
        for _ in 0..5 {
            pulse(&m, &mut x, 2, 8);
        }
        x.set_direction(Direction::Negative).unwrap();
        m.advance_by(1);
        for _ in 0..2 {
            pulse(&m, &mut x, 2, 8);
        }
        assert_eq!(m.position_steps(0), Some(start + 3));
        assert_eq!(m.step_count(0), Some(7));
        assert_eq!(m.position_range_steps(0), Some((start, start + 5)));
        assert_eq!(m.step_times(0), vec![10, 20, 30, 40, 50, 61, 71]);
        assert_eq!(m.violation_count(), 0, "{:?}", m.violations());
        m.with_trace(|t| {
            let kinds: Vec<_> = t.events().iter().map(|e| e.kind.name()).collect();
            assert_eq!(&kinds[..3], ["enable", "dir+", "step+"]);
            assert_eq!(t.net_steps(0), 3);
        });
        assert_eq!(m.position_steps(1), Some(150 * 80), "other axes untouched");
    }

    #[test]
    fn a_disabled_driver_loses_its_steps() {
        let m = machine();
        let mut y = m.stepper(1).unwrap();
        let start = m.position_steps(1).unwrap();
        pulse(&m, &mut y, 2, 2);
        assert_eq!(m.position_steps(1), Some(start));
        assert_eq!(m.lost_steps(1), Some(1));
        y.set_enabled(true).unwrap();
        pulse(&m, &mut y, 2, 2);
        y.set_enabled(false).unwrap();
        assert_eq!(
            m.position_steps(1),
            Some(start - 1),
            "DIR starts low: negative"
        );
        assert_eq!(m.is_enabled(1), Some(false));
        assert_eq!(m.step_times(1), vec![4]);
    }

    #[test]
    fn timing_violations_are_caught() {
        let m = machine();
        let mut x = m.stepper(0).unwrap();
        x.set_enabled(true).unwrap();

        // Step edge in the same tick as the direction change: set-up 0 < 1 tick.
        x.set_direction(Direction::Positive).unwrap();
        x.step_begin().unwrap();
        // Pulse of one tick: high 1 < 2.
        m.advance_by(1);
        x.step_end().unwrap();
        // Next rising edge one tick later: low 1 < 2.
        m.advance_by(1);
        x.step_begin().unwrap();
        m.advance_by(2);
        x.step_end().unwrap();

        let v = m.violations();
        assert_eq!(
            violation_kinds(&m),
            [
                ViolationKind::DirSetup,
                ViolationKind::PulseHigh,
                ViolationKind::PulseLow
            ]
        );
        assert_eq!(
            (v[0].time_ticks, v[0].actual_ticks, v[0].required_ticks),
            (0, 0, 1)
        );
        assert_eq!(
            (v[1].time_ticks, v[1].actual_ticks, v[1].required_ticks),
            (1, 1, 2)
        );
        assert_eq!(
            (v[2].time_ticks, v[2].actual_ticks, v[2].required_ticks),
            (2, 1, 2)
        );
        assert_eq!(
            v[1].to_string(),
            "tick 1: axis 0: STEP high time of 1 ticks, needs 2"
        );
        // The steps still happened.
        assert_eq!(m.step_count(0), Some(2));
        // A zero-width pulse (begin and end in one interrupt) is caught as well.
        m.advance_by(10);
        x.step_begin().unwrap();
        x.step_end().unwrap();
        assert_eq!(m.violation_count(), 4);
    }

    #[test]
    fn rules_of_order_are_caught() {
        let m = machine();
        let mut x = m.stepper(0).unwrap();
        x.set_enabled(true).unwrap();
        m.advance_by(10);
        x.step_begin().unwrap();
        m.advance_by(2);
        // DIR changes under a high STEP.
        x.set_direction(Direction::Positive).unwrap();
        // A second begin without an end.
        x.step_begin().unwrap();
        m.advance_by(2);
        x.step_end().unwrap();
        m.advance_by(2);
        // An end without a begin.
        x.step_end().unwrap();
        assert_eq!(
            violation_kinds(&m),
            [
                ViolationKind::DirDuringPulse,
                ViolationKind::UnpairedEdge,
                ViolationKind::UnpairedEdge
            ]
        );
        let v = m.violations();
        assert_eq!(
            v[0].to_string(),
            "tick 12: axis 0: DIR change during a STEP pulse"
        );
        assert_eq!((v[1].time_ticks, v[2].time_ticks), (12, 16));
        assert_eq!(m.step_count(0), Some(1), "a second begin is no second step");
        // On the pins, a line driven to its level is no edge and no fault.
        let mut pins = m.step_dir_pins(1).unwrap();
        pins.step.set_low().unwrap();
        assert_eq!(m.violation_count(), 3);
    }

    #[test]
    fn timing_follows_the_machine_file_and_tick_rate() {
        let text = "tick_hz = 20_000_000\n[[axis]]\nletter = \"X\"\nsteps_per_mm = 80\n\
                    max_rate_mm_min = 6000\naccel_mm_s2 = 500\ntravel_min_mm = 0\n\
                    travel_max_mm = 300\nmin_pulse_ns = 1900\ndir_setup_ns = 650\n";
        let m = SimMachine::new(&MachineConfig::from_toml_str(text).unwrap());
        let mut x = m.stepper(0).unwrap();
        assert_eq!(
            x.timing(),
            StepTiming {
                min_pulse_ns: 1900,
                dir_setup_ns: 650
            }
        );
        x.set_enabled(true).unwrap();
        x.set_direction(Direction::Positive).unwrap();
        m.advance_by(13); // 650 ns = 13 ticks at 20 MHz: just enough.
        x.step_begin().unwrap();
        m.advance_by(37); // 1900 ns = 38 ticks: one short.
        x.step_end().unwrap();
        let v = m.violations();
        assert_eq!(v.len(), 1);
        assert_eq!(
            (v[0].kind, v[0].required_ticks),
            (ViolationKind::PulseHigh, 38)
        );
    }

    #[test]
    fn pins_drive_the_same_driver() {
        let m = machine();
        let mut pins = m.step_dir_pins(2).unwrap();
        let start = m.position_steps(2).unwrap();
        pins.enable.set_low().unwrap();
        pins.dir.set_high().unwrap();
        m.advance_by(5);
        for _ in 0..4 {
            pins.step.set_high().unwrap();
            m.advance_by(3);
            pins.step.set_low().unwrap();
            m.advance_by(3);
        }
        assert_eq!(m.is_enabled(2), Some(true));
        assert_eq!(m.direction(2), Some(Direction::Positive));
        assert_eq!(m.position_steps(2), Some(start + 4));
        // Setting a line to the level it has is no edge.
        pins.step.set_low().unwrap();
        assert_eq!(m.step_count(2), Some(4));
        pins.enable.set_high().unwrap();
        assert_eq!(m.is_enabled(2), Some(false));
        assert_eq!(pins.step.line(), DriverLine::Step);
        assert_eq!(m.violation_count(), 0);
    }
}
