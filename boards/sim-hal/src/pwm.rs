//! Simulated PWM outputs (fans, spindles).
//!
//! [`SimPwm`] implements `embedded-hal`'s [`SetDutyCycle`] (Forja's `PwmOutput`) with the
//! machine file's `max_duty`, and records every change of duty with its virtual time
//! ([`SimMachine::pwm_history`]).

use core::fmt;

use embedded_hal::pwm::{self, SetDutyCycle};

use crate::config::OutputConfig;
use crate::machine::{NoSuchDevice, SimMachine};

/// One output's duty and its changes.
pub(crate) struct PwmState {
    max_duty: u16,
    duty: u16,
    history: Vec<DutyChange>,
}

impl PwmState {
    pub(crate) fn new(config: &OutputConfig) -> Self {
        Self {
            max_duty: config.max_duty,
            duty: 0,
            history: Vec::new(),
        }
    }
}

/// A change of an output's duty.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct DutyChange {
    /// Virtual time of the change, in ticks since start.
    pub time_ticks: u64,
    /// The new duty, out of the output's `max_duty`.
    pub duty: u16,
}

/// A duty above the output's maximum; nothing was changed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct DutyOutOfRange {
    /// The duty asked for.
    pub duty: u16,
    /// The output's maximum.
    pub max_duty: u16,
}

impl pwm::Error for DutyOutOfRange {
    fn kind(&self) -> pwm::ErrorKind {
        pwm::ErrorKind::Other
    }
}

impl fmt::Display for DutyOutOfRange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "duty {} above the maximum {}", self.duty, self.max_duty)
    }
}

impl std::error::Error for DutyOutOfRange {}

impl SimMachine {
    fn check_output(&self, index: usize) -> Result<(), NoSuchDevice> {
        if index < self.config().outputs.len() {
            Ok(())
        } else {
            Err(NoSuchDevice::Output(index))
        }
    }

    /// PWM output `index` (machine file order).
    pub fn pwm(&self, index: usize) -> Result<SimPwm, NoSuchDevice> {
        self.check_output(index)?;
        Ok(SimPwm {
            machine: self.clone(),
            index,
        })
    }

    /// The current duty of output `index`, out of its `max_duty`.
    pub fn pwm_duty(&self, index: usize) -> Result<u16, NoSuchDevice> {
        self.check_output(index)?;
        Ok(self.state.borrow().outputs[index].duty)
    }

    /// Every change of duty of output `index`, in time order.
    pub fn pwm_history(&self, index: usize) -> Result<Vec<DutyChange>, NoSuchDevice> {
        self.check_output(index)?;
        Ok(self.state.borrow().outputs[index].history.clone())
    }
}

/// A simulated PWM output: implements [`SetDutyCycle`].
///
/// Errors: a duty above [`SetDutyCycle::max_duty_cycle`] is refused with [`DutyOutOfRange`]
/// and changes nothing.
#[derive(Clone)]
pub struct SimPwm {
    machine: SimMachine,
    index: usize,
}

impl fmt::Debug for SimPwm {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimPwm")
            .field("index", &self.index)
            .finish()
    }
}

impl pwm::ErrorType for SimPwm {
    type Error = DutyOutOfRange;
}

impl SetDutyCycle for SimPwm {
    fn max_duty_cycle(&self) -> u16 {
        self.machine.state.borrow().outputs[self.index].max_duty
    }

    fn set_duty_cycle(&mut self, duty: u16) -> Result<(), DutyOutOfRange> {
        let mut s = self.machine.state.borrow_mut();
        let now = s.now;
        let out = &mut s.outputs[self.index];
        if duty > out.max_duty {
            return Err(DutyOutOfRange {
                duty,
                max_duty: out.max_duty,
            });
        }
        if duty != out.duty {
            out.duty = duty;
            out.history.push(DutyChange {
                time_ticks: now,
                duty,
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MachineConfig;

    #[test]
    fn records_duty_changes() {
        let m = SimMachine::new(&MachineConfig::default_router());
        let spindle = m.output_index("spindle").unwrap();
        let mut pwm = m.pwm(spindle).unwrap();
        assert_eq!(pwm.max_duty_cycle(), 1000);
        m.advance_to(100);
        pwm.set_duty_cycle(600).unwrap();
        m.advance_to(250);
        pwm.set_duty_cycle(600).unwrap();
        pwm.set_duty_cycle_fully_on().unwrap();
        assert_eq!(
            pwm.set_duty_cycle(1001).unwrap_err(),
            DutyOutOfRange {
                duty: 1001,
                max_duty: 1000
            }
        );
        assert_eq!(m.pwm_duty(spindle), Ok(1000));
        assert_eq!(
            m.pwm_history(spindle).unwrap(),
            vec![
                DutyChange {
                    time_ticks: 100,
                    duty: 600
                },
                DutyChange {
                    time_ticks: 250,
                    duty: 1000
                }
            ]
        );
        assert_eq!(m.pwm(1).unwrap_err(), NoSuchDevice::Output(1));
    }
}
