//! Simulated switched (on/off) outputs: coolant valves, relays.
//!
//! Each `[[digital_output]]` of the machine file is a device on one line: on while the line is
//! at the device's active level ([`DigitalOutputConfig::active`]), off otherwise. At power-up
//! every line is at its inactive level (a pull resistor holds the device off until the
//! firmware drives the line).
//!
//! [`SimOutputPin`] is the line as the firmware drives it, an `embedded-hal` [`OutputPin`] (and
//! [`StatefulOutputPin`]). A test reads the device ([`SimMachine::output_on`],
//! [`SimMachine::digital_output_level`]) and every change of it with its virtual time
//! ([`SimMachine::digital_output_history`]).
//!
//! The changes are not in the step trace ([`crate::trace`]): its events belong to an axis and
//! its file names one in each row, which an output has not.

use core::convert::Infallible;
use core::fmt;

use embedded_hal::digital::{self, OutputPin, PinState, StatefulOutputPin};

use crate::config::DigitalOutputConfig;
use crate::machine::{NoSuchDevice, SimMachine};

/// One output's line and its changes.
pub(crate) struct DigitalOutputState {
    active: PinState,
    level: PinState,
    history: Vec<OutputChange>,
}

impl DigitalOutputState {
    /// The output of `config`, off: its line at the inactive level.
    pub(crate) fn new(config: &DigitalOutputConfig) -> Self {
        Self {
            active: config.active,
            level: !config.active,
            history: Vec::new(),
        }
    }

    fn is_on(&self) -> bool {
        self.level == self.active
    }
}

/// A digital output switched on or off.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct OutputChange {
    /// Virtual time of the change, in ticks since start.
    pub time_ticks: u64,
    /// `true`: switched on.
    pub on: bool,
}

impl SimMachine {
    fn check_digital_output(&self, index: usize) -> Result<(), NoSuchDevice> {
        if index < self.config().digital_outputs.len() {
            Ok(())
        } else {
            Err(NoSuchDevice::DigitalOutput(index))
        }
    }

    /// The index of the digital output called `name`.
    pub fn digital_output_index(&self, name: &str) -> Option<usize> {
        self.config().digital_output_index(name)
    }

    /// The line of digital output `index` (machine file order), for the firmware to drive.
    pub fn digital_output(&self, index: usize) -> Result<SimOutputPin, NoSuchDevice> {
        self.check_digital_output(index)?;
        Ok(SimOutputPin {
            machine: self.clone(),
            index,
        })
    }

    /// The level of the line of digital output `index`.
    pub fn digital_output_level(&self, index: usize) -> Result<PinState, NoSuchDevice> {
        self.check_digital_output(index)?;
        Ok(self.state.borrow().digital_outputs[index].level)
    }

    /// Whether the digital output called `name` is on (its line at its active level); `None`
    /// when the machine has no such output.
    pub fn output_on(&self, name: &str) -> Option<bool> {
        let index = self.digital_output_index(name)?;
        Some(self.state.borrow().digital_outputs[index].is_on())
    }

    /// Every time digital output `index` was switched on or off, in time order.
    pub fn digital_output_history(&self, index: usize) -> Result<Vec<OutputChange>, NoSuchDevice> {
        self.check_digital_output(index)?;
        Ok(self.state.borrow().digital_outputs[index].history.clone())
    }
}

/// The line of a simulated digital output: implements [`OutputPin`] and
/// [`StatefulOutputPin`]. Never fails ([`Infallible`]).
#[derive(Clone)]
pub struct SimOutputPin {
    machine: SimMachine,
    index: usize,
}

impl SimOutputPin {
    /// The output this line switches (machine file order).
    pub fn index(&self) -> usize {
        self.index
    }

    fn drive(&mut self, level: PinState) {
        let mut s = self.machine.state.borrow_mut();
        let now = s.now;
        let out = &mut s.digital_outputs[self.index];
        let was_on = out.is_on();
        out.level = level;
        if out.is_on() != was_on {
            let on = out.is_on();
            out.history.push(OutputChange {
                time_ticks: now,
                on,
            });
        }
    }

    fn level(&self) -> PinState {
        self.machine.state.borrow().digital_outputs[self.index].level
    }
}

impl fmt::Debug for SimOutputPin {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimOutputPin")
            .field("index", &self.index)
            .finish()
    }
}

impl digital::ErrorType for SimOutputPin {
    type Error = Infallible;
}

impl OutputPin for SimOutputPin {
    fn set_low(&mut self) -> Result<(), Infallible> {
        self.drive(PinState::Low);
        Ok(())
    }

    fn set_high(&mut self) -> Result<(), Infallible> {
        self.drive(PinState::High);
        Ok(())
    }
}

impl StatefulOutputPin for SimOutputPin {
    fn is_set_high(&mut self) -> Result<bool, Infallible> {
        Ok(self.level() == PinState::High)
    }

    fn is_set_low(&mut self) -> Result<bool, Infallible> {
        Ok(self.level() == PinState::Low)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{FLOOD, MIST, MachineConfig};

    #[test]
    fn the_routers_coolant_lines_start_off_and_record_their_changes() {
        let m = SimMachine::new(&MachineConfig::default_router());
        assert_eq!(
            (m.output_on(FLOOD), m.output_on(MIST)),
            (Some(false), Some(false))
        );
        assert_eq!(m.output_on("vacuum"), None);
        let flood = m.digital_output_index(FLOOD).unwrap();
        let mut pin = m.digital_output(flood).unwrap();
        assert_eq!(pin.index(), flood);
        assert_eq!(m.digital_output_level(flood), Ok(PinState::Low));
        assert_eq!(pin.is_set_low(), Ok(true));

        m.advance_to(100);
        pin.set_high().unwrap();
        assert_eq!(m.output_on(FLOOD), Some(true));
        assert_eq!(m.output_on(MIST), Some(false), "the other line is its own");
        assert_eq!(pin.is_set_high(), Ok(true));
        m.advance_to(150);
        pin.set_high().unwrap();
        m.advance_to(200);
        pin.toggle().unwrap();
        assert_eq!(m.output_on(FLOOD), Some(false));
        assert_eq!(
            m.digital_output_history(flood).unwrap(),
            [
                OutputChange {
                    time_ticks: 100,
                    on: true
                },
                OutputChange {
                    time_ticks: 200,
                    on: false
                }
            ],
            "changes only, each at its time"
        );
        assert_eq!(
            m.digital_output(2).unwrap_err(),
            NoSuchDevice::DigitalOutput(2)
        );
        assert_eq!(
            m.digital_output_history(2).unwrap_err().to_string(),
            "the machine has no digital output 2"
        );
    }

    #[test]
    fn an_active_low_output_is_on_while_its_line_is_low() {
        let text = "[[axis]]\nletter = \"X\"\nsteps_per_mm = 80\nmax_rate_mm_min = 6000\n\
                    accel_mm_s2 = 500\ntravel_min_mm = 0\ntravel_max_mm = 300\n\
                    [[digital_output]]\nname = \"vacuum\"\nactive = \"low\"\n";
        let m = SimMachine::new(&MachineConfig::from_toml_str(text).unwrap());
        let mut pin = m.digital_output(0).unwrap();
        assert_eq!(
            m.digital_output_level(0),
            Ok(PinState::High),
            "off at power-up"
        );
        assert_eq!(m.output_on("vacuum"), Some(false));
        pin.set_low().unwrap();
        assert_eq!(m.output_on("vacuum"), Some(true));
        assert_eq!(
            m.digital_output_history(0).unwrap(),
            [OutputChange {
                time_ticks: 0,
                on: true
            }]
        );
    }
}
