//! Simulated limit switches.
//!
//! A switch sits at a machine position on one side of an axis (machine file `[[axis.switch]]`):
//! a `min` switch is triggered while the axis is at or below its position, a `max` switch at or
//! above it. The position is rounded to the nearest step.
//!
//! Two ways to read one, like the drivers:
//! - [`SimLimitSwitch`] implements [`LimitSwitch`], polarity already applied (`true` = at the
//!   limit);
//! - [`SimSwitchPin`] is the switch's input as an `embedded-hal` [`InputPin`], at the
//!   electrical level its polarity gives (normally open: low when triggered; normally closed:
//!   high when triggered), for the limit input driver of `forja-drivers`.
//!
//! A test can override a switch ([`SimMachine::force_switch`]) to simulate a stuck switch or a
//! cut wire, or move it ([`SimMachine::set_switch_position_steps`]).
//!
//! The touch probe (machine file `[probe]`) is one more switch, read the same two ways
//! ([`SimMachine::probe_switch`], [`SimMachine::probe_pin`]): closed (`true`, touching) while
//! its axis is at or below its position, as a `min` switch. It is a switch of its own, after
//! the axes' switches: never one of an axis's min/max switches, even on the same axis. A test
//! moves the stock's surface ([`SimMachine::set_probe_position_steps`]) or holds the probe
//! open or closed ([`SimMachine::force_probe`]).
//!
//! [`SwitchEdges`] is the pin-change interrupt of the switch inputs, as a board has an EXTI
//! line or a GPIO interrupt on each: the board looks at it after each step interrupt and each
//! poll (a switch changes when a step pushes the axis over it, or when a test forces it) and
//! reports an edge to the step interrupt.

use core::convert::Infallible;
use core::fmt;

use embedded_hal::digital::{self, InputPin};
use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::limit::LimitSwitch;

use crate::config::{AxisConfig, ProbeConfig, SwitchConfig, SwitchPolarity, SwitchSide};
use crate::machine::{NoSuchDevice, SimMachine, State};

/// One switch's configuration and override.
pub(crate) struct SwitchState {
    axis: usize,
    side: SwitchSide,
    /// The touch probe, not one of the axis's min/max switches.
    probe: bool,
    trigger_steps: i64,
    polarity: SwitchPolarity,
    forced: Option<bool>,
}

impl SwitchState {
    pub(crate) fn new(axis: usize, axis_config: &AxisConfig, switch: &SwitchConfig) -> Self {
        Self {
            axis,
            side: switch.side,
            probe: false,
            trigger_steps: axis_config.mm_to_steps(switch.position_mm),
            polarity: switch.polarity,
            forced: None,
        }
    }

    /// The touch probe on `axis_config` (the axis `probe.axis`): closed at or below its
    /// position, as a `min` switch.
    pub(crate) fn probe(axis_config: &AxisConfig, probe: &ProbeConfig) -> Self {
        Self {
            axis: probe.axis,
            side: SwitchSide::Min,
            probe: true,
            trigger_steps: axis_config.mm_to_steps(probe.position_mm),
            polarity: probe.polarity,
            forced: None,
        }
    }
}

impl State {
    fn switch_index(&self, axis: usize, side: SwitchSide) -> Option<usize> {
        self.switches
            .iter()
            .position(|s| !s.probe && s.axis == axis && s.side == side)
    }

    fn probe_index(&self) -> Option<usize> {
        self.switches.iter().position(|s| s.probe)
    }

    fn switch_triggered(&self, index: usize) -> bool {
        let s = &self.switches[index];
        if let Some(forced) = s.forced {
            return forced;
        }
        let position = self.axes[s.axis].position;
        match s.side {
            SwitchSide::Min => position <= s.trigger_steps,
            SwitchSide::Max => position >= s.trigger_steps,
        }
    }
}

impl SimMachine {
    fn switch_handle(&self, axis: usize, side: SwitchSide) -> Result<usize, NoSuchDevice> {
        self.check_axis(axis)?;
        self.state
            .borrow()
            .switch_index(axis, side)
            .ok_or(NoSuchDevice::Switch { axis, side })
    }

    /// The switch on `side` of `axis`, as a [`LimitSwitch`].
    pub fn limit_switch(
        &self,
        axis: usize,
        side: SwitchSide,
    ) -> Result<SimLimitSwitch, NoSuchDevice> {
        Ok(SimLimitSwitch {
            machine: self.clone(),
            index: self.switch_handle(axis, side)?,
        })
    }

    /// The input pin of the switch on `side` of `axis`.
    pub fn switch_pin(&self, axis: usize, side: SwitchSide) -> Result<SimSwitchPin, NoSuchDevice> {
        Ok(SimSwitchPin {
            machine: self.clone(),
            index: self.switch_handle(axis, side)?,
        })
    }

    /// Whether the switch on `side` of `axis` is triggered now.
    pub fn switch_triggered(&self, axis: usize, side: SwitchSide) -> Result<bool, NoSuchDevice> {
        let index = self.switch_handle(axis, side)?;
        Ok(self.state.borrow().switch_triggered(index))
    }

    /// Every switch's state as a bit mask, bit `i` set while switch `i` is triggered (the
    /// axes' switches in machine file order, then the probe): what a pin-change interrupt on
    /// the switch inputs compares.
    pub fn switch_states(&self) -> u64 {
        let s = self.state.borrow();
        (0..s.switches.len().min(64))
            .filter(|&i| s.switch_triggered(i))
            .fold(0, |m, i| m | 1 << i)
    }

    /// Move the switch on `side` of `axis` to `steps` (a machine position, in steps): it trips
    /// there from now on.
    pub fn set_switch_position_steps(
        &self,
        axis: usize,
        side: SwitchSide,
        steps: i64,
    ) -> Result<(), NoSuchDevice> {
        let index = self.switch_handle(axis, side)?;
        self.state.borrow_mut().switches[index].trigger_steps = steps;
        Ok(())
    }

    /// The pin-change interrupt of every switch input, with the switches' states now as the
    /// last seen.
    pub fn switch_edges(&self) -> SwitchEdges {
        SwitchEdges {
            machine: self.clone(),
            seen: self.switch_states(),
        }
    }

    /// Force the switch on `side` of `axis` to read triggered (`Some(true)`) or released
    /// (`Some(false)`) whatever the position; `None` returns it to following the position.
    pub fn force_switch(
        &self,
        axis: usize,
        side: SwitchSide,
        forced: Option<bool>,
    ) -> Result<(), NoSuchDevice> {
        let index = self.switch_handle(axis, side)?;
        self.state.borrow_mut().switches[index].forced = forced;
        Ok(())
    }
}

/// The touch probe.
impl SimMachine {
    fn probe_handle(&self) -> Result<usize, NoSuchDevice> {
        self.state.borrow().probe_index().ok_or(NoSuchDevice::Probe)
    }

    /// The touch probe, as a [`LimitSwitch`] (`true` = touching).
    ///
    /// Errors: [`NoSuchDevice::Probe`] when the machine file has no `[probe]`.
    pub fn probe_switch(&self) -> Result<SimLimitSwitch, NoSuchDevice> {
        Ok(SimLimitSwitch {
            machine: self.clone(),
            index: self.probe_handle()?,
        })
    }

    /// The touch probe's input pin, at the level its polarity gives.
    ///
    /// Errors: [`NoSuchDevice::Probe`] when the machine file has no `[probe]`.
    pub fn probe_pin(&self) -> Result<SimSwitchPin, NoSuchDevice> {
        Ok(SimSwitchPin {
            machine: self.clone(),
            index: self.probe_handle()?,
        })
    }

    /// Whether the probe is touching now; `false` when the machine has none.
    pub fn probe_touching(&self) -> bool {
        let s = self.state.borrow();
        s.probe_index().is_some_and(|i| s.switch_triggered(i))
    }

    /// Move the stock's surface: the probe closes while its axis is at or below `steps` (a
    /// machine position, in steps) from now on.
    ///
    /// Errors: [`NoSuchDevice::Probe`] when the machine file has no `[probe]`.
    pub fn set_probe_position_steps(&self, steps: i64) -> Result<(), NoSuchDevice> {
        let index = self.probe_handle()?;
        self.state.borrow_mut().switches[index].trigger_steps = steps;
        Ok(())
    }

    /// Force the probe to read touching (`Some(true)`) or open (`Some(false)`) whatever the
    /// position; `None` returns it to following the position.
    ///
    /// Errors: [`NoSuchDevice::Probe`] when the machine file has no `[probe]`.
    pub fn force_probe(&self, forced: Option<bool>) -> Result<(), NoSuchDevice> {
        let index = self.probe_handle()?;
        self.state.borrow_mut().switches[index].forced = forced;
        Ok(())
    }
}

/// The pin-change interrupt of a machine's switch inputs ([`SimMachine::switch_edges`]).
#[derive(Clone)]
pub struct SwitchEdges {
    machine: SimMachine,
    /// [`SimMachine::switch_states`] at the last look.
    seen: u64,
}

impl SwitchEdges {
    /// Whether any switch changed since the last look: the interrupt is pending. Looking
    /// clears it.
    ///
    /// Context: either (a board calls it after each step interrupt and each poll).
    pub fn take(&mut self) -> bool {
        let now = self.machine.switch_states();
        core::mem::replace(&mut self.seen, now) != now
    }
}

impl fmt::Debug for SwitchEdges {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SwitchEdges")
            .field("seen", &self.seen)
            .finish()
    }
}

/// A simulated end-stop or the touch probe: implements [`LimitSwitch`] (`true` = at the limit,
/// or touching). Never fails.
#[derive(Clone)]
pub struct SimLimitSwitch {
    machine: SimMachine,
    index: usize,
}

impl fmt::Debug for SimLimitSwitch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimLimitSwitch")
            .field("index", &self.index)
            .finish()
    }
}

impl ErrorType for SimLimitSwitch {
    type Error = Infallible;
}

impl LimitSwitch for SimLimitSwitch {
    fn is_triggered(&mut self) -> Result<bool, Infallible> {
        Ok(self.machine.state.borrow().switch_triggered(self.index))
    }
}

/// A simulated end-stop's or the touch probe's input line, at its electrical level.
#[derive(Clone)]
pub struct SimSwitchPin {
    machine: SimMachine,
    index: usize,
}

impl SimSwitchPin {
    fn level_high(&self) -> bool {
        let s = self.machine.state.borrow();
        let triggered = s.switch_triggered(self.index);
        match s.switches[self.index].polarity {
            SwitchPolarity::NormallyOpen => !triggered,
            SwitchPolarity::NormallyClosed => triggered,
        }
    }
}

impl fmt::Debug for SimSwitchPin {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimSwitchPin")
            .field("index", &self.index)
            .finish()
    }
}

impl digital::ErrorType for SimSwitchPin {
    type Error = Infallible;
}

impl InputPin for SimSwitchPin {
    fn is_high(&mut self) -> Result<bool, Infallible> {
        Ok(self.level_high())
    }

    fn is_low(&mut self) -> Result<bool, Infallible> {
        Ok(!self.level_high())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MachineConfig;
    use forja_hal_abstraction::stepper::{Direction, Stepper, StepperEnable};

    fn step_n(m: &SimMachine, axis: usize, d: Direction, n: u32) {
        let mut s = m.stepper(axis).unwrap();
        s.set_enabled(true).unwrap();
        s.set_direction(d).unwrap();
        for _ in 0..n {
            m.advance_by(5);
            s.step_begin().unwrap();
            m.advance_by(5);
            s.step_end().unwrap();
        }
    }

    #[test]
    fn min_switch_trips_at_its_position() {
        let m = SimMachine::new(&MachineConfig::default_router());
        let mut sw = m.limit_switch(0, SwitchSide::Min).unwrap();
        m.set_position_steps(0, 3).unwrap();
        assert!(!sw.is_triggered().unwrap());
        step_n(&m, 0, Direction::Negative, 2);
        assert!(!sw.is_triggered().unwrap(), "one step above the switch");
        step_n(&m, 0, Direction::Negative, 1);
        assert_eq!(m.position_steps(0), Some(0));
        assert!(sw.is_triggered().unwrap(), "at the switch");
        step_n(&m, 0, Direction::Negative, 1);
        assert!(sw.is_triggered().unwrap(), "beyond it");
        step_n(&m, 0, Direction::Positive, 2);
        assert!(!sw.is_triggered().unwrap(), "backed off");
    }

    #[test]
    fn max_switch_and_polarity() {
        let m = SimMachine::new(&MachineConfig::default_router());
        // The router's X max switch is normally closed at 301 mm = 24080 steps.
        let mut sw = m.limit_switch(0, SwitchSide::Max).unwrap();
        let mut pin = m.switch_pin(0, SwitchSide::Max).unwrap();
        m.set_position_steps(0, 24_079).unwrap();
        assert!(!sw.is_triggered().unwrap());
        assert!(pin.is_low().unwrap(), "normally closed: low while released");
        step_n(&m, 0, Direction::Positive, 1);
        assert!(sw.is_triggered().unwrap());
        assert!(
            pin.is_high().unwrap(),
            "normally closed: high when triggered"
        );
        assert!(m.switch_triggered(0, SwitchSide::Max).unwrap());

        let printer =
            MachineConfig::from_toml_str(MachineConfig::bundled_toml("printer").unwrap()).unwrap();
        let p = SimMachine::new(&printer);
        let mut pin = p.switch_pin(0, SwitchSide::Min).unwrap();
        assert!(pin.is_high().unwrap(), "normally open: high while released");
        p.set_position_steps(0, 0).unwrap();
        assert!(pin.is_low().unwrap(), "normally open: low when triggered");
    }

    #[test]
    fn a_moved_switch_trips_at_its_new_place_and_raises_an_edge() {
        let m = SimMachine::new(&MachineConfig::default_router());
        let mut sw = m.limit_switch(0, SwitchSide::Min).unwrap();
        let mut edges = m.switch_edges();
        m.set_position_steps(0, 0).unwrap();
        assert!(sw.is_triggered().unwrap());
        assert!(edges.take(), "the X min switch closed");
        assert!(!edges.take(), "looking clears the edge");
        m.set_switch_position_steps(0, SwitchSide::Min, -5).unwrap();
        assert!(!sw.is_triggered().unwrap());
        assert!(edges.take(), "and opened");
        step_n(&m, 0, Direction::Negative, 5);
        assert!(sw.is_triggered().unwrap());
        assert_eq!(
            m.set_switch_position_steps(3, SwitchSide::Min, 0),
            Err(NoSuchDevice::Switch {
                axis: 3,
                side: SwitchSide::Min
            })
        );
    }

    #[test]
    fn the_probe_closes_on_the_stock_and_is_not_the_axis_switch() {
        let m = SimMachine::new(&MachineConfig::default_router());
        // The router's probe: Z (axis 2) at or below 20 mm = 8000 steps, normally open.
        let mut probe = m.probe_switch().unwrap();
        let mut pin = m.probe_pin().unwrap();
        let mut z_max = m.limit_switch(2, SwitchSide::Max).unwrap();
        let mut edges = m.switch_edges();
        m.set_position_steps(2, 8_001).unwrap();
        assert!(!probe.is_triggered().unwrap() && !m.probe_touching());
        assert!(pin.is_high().unwrap(), "normally open: high while open");
        step_n(&m, 2, Direction::Negative, 1);
        assert!(probe.is_triggered().unwrap() && m.probe_touching());
        assert!(pin.is_low().unwrap(), "normally open: low when touching");
        assert!(edges.take(), "the probe's closing is an edge");
        assert!(!z_max.is_triggered().unwrap());
        assert_eq!(
            m.limit_switch(2, SwitchSide::Min).unwrap_err(),
            NoSuchDevice::Switch {
                axis: 2,
                side: SwitchSide::Min
            },
            "the probe is not Z's min switch"
        );
        // The probe's bit comes after the axes' five switches.
        assert_eq!(m.switch_states(), 1 << 5);

        // Forced open, it never touches; back to the position, it does.
        m.force_probe(Some(false)).unwrap();
        assert!(!m.probe_touching());
        assert!(edges.take(), "and its opening");
        m.force_probe(None).unwrap();
        assert!(m.probe_touching());
        // The stock's surface moved down: open again until Z reaches it.
        m.set_probe_position_steps(7_990).unwrap();
        assert!(!probe.is_triggered().unwrap());
        step_n(&m, 2, Direction::Negative, 10);
        assert!(probe.is_triggered().unwrap());
        m.force_probe(Some(false)).unwrap();
        assert!(!probe.is_triggered().unwrap());
    }

    #[test]
    fn a_probe_on_the_axis_of_a_min_switch_leaves_that_switch_alone() {
        let file = format!(
            "{}\n[probe]\naxis = \"X\"\nposition_mm = 0.0\npolarity = \"normally_closed\"\n",
            MachineConfig::bundled_toml("printer").unwrap()
        );
        let m = SimMachine::new(&MachineConfig::from_toml_str(&file).unwrap());
        let mut pin = m.probe_pin().unwrap();
        assert!(pin.is_low().unwrap(), "normally closed: low while open");
        m.force_switch(0, SwitchSide::Min, Some(true)).unwrap();
        assert!(
            !m.probe_touching(),
            "forcing X min does not force the probe"
        );
        m.force_switch(0, SwitchSide::Min, None).unwrap();
        m.set_switch_position_steps(0, SwitchSide::Min, -100)
            .unwrap();
        m.set_position_steps(0, 0).unwrap();
        assert!(m.probe_touching());
        assert!(
            pin.is_high().unwrap(),
            "normally closed: high when touching"
        );
        assert!(!m.switch_triggered(0, SwitchSide::Min).unwrap());
    }

    #[test]
    fn a_machine_without_a_probe_says_so() {
        let printer =
            MachineConfig::from_toml_str(MachineConfig::bundled_toml("printer").unwrap()).unwrap();
        let m = SimMachine::new(&printer);
        assert_eq!(m.probe_pin().unwrap_err(), NoSuchDevice::Probe);
        assert_eq!(m.probe_switch().unwrap_err(), NoSuchDevice::Probe);
        assert_eq!(m.force_probe(Some(true)), Err(NoSuchDevice::Probe));
        assert_eq!(m.set_probe_position_steps(0), Err(NoSuchDevice::Probe));
        assert!(!m.probe_touching());
        assert_eq!(NoSuchDevice::Probe.to_string(), "the machine has no probe");
    }

    #[test]
    fn forced_switch_and_missing_switch() {
        let m = SimMachine::new(&MachineConfig::default_router());
        let mut sw = m.limit_switch(2, SwitchSide::Max).unwrap();
        assert!(!sw.is_triggered().unwrap());
        m.force_switch(2, SwitchSide::Max, Some(true)).unwrap();
        assert!(sw.is_triggered().unwrap());
        m.force_switch(2, SwitchSide::Max, None).unwrap();
        assert!(!sw.is_triggered().unwrap());
        assert_eq!(
            m.limit_switch(2, SwitchSide::Min).unwrap_err(),
            NoSuchDevice::Switch {
                axis: 2,
                side: SwitchSide::Min
            }
        );
        assert_eq!(
            m.switch_pin(7, SwitchSide::Min).unwrap_err(),
            NoSuchDevice::Axis(7)
        );
    }
}
