//! Simulated heaters and temperature sensors over a first-order thermal model.
//!
//! # Model
//!
//! One lumped mass per heater (machine file `[[heater]]`): heat capacity `C` (J/K), heater
//! power `P` (W) at full duty, loss to ambient `k` (W/K), ambient temperature `T_a`. With a
//! power fraction `u` (0..=1):
//!
//! ```text
//! C · dT/dt = u · P − k · (T − T_a)
//! ```
//!
//! For a constant `u` over an interval `dt` the solution is exact:
//!
//! ```text
//! T(t + dt) = T_ss + (T(t) − T_ss) · exp(−dt · k / C),   T_ss = T_a + u · P / k
//! ```
//!
//! Power changes only when the firmware sets it, so the simulator evaluates the model lazily,
//! from the last change (or read) to the current virtual time, whatever the step: the result
//! does not depend on how often it is read. Full power settles at `T_a + P / k` (what a
//! thermal-runaway check must catch) with time constant `C / k`.
//!
//! # Devices
//!
//! [`SimHeater`] implements [`Heater`] and, for boards that drive heaters through a PWM
//! channel, `embedded-hal`'s [`SetDutyCycle`] (full scale [`FULL_POWER`]); both set the same
//! power. [`SimTemperatureSensor`] implements [`TemperatureSensor`]. Faults for tests of the
//! thermal protection: a sensor can be made to read open or shorted
//! ([`SimMachine::set_sensor_fault`]) and a heater can be disconnected from its mass
//! ([`SimMachine::set_heater_connected`]), so that power no longer heats anything.

use core::convert::Infallible;
use core::fmt;

use embedded_hal::pwm::{self, SetDutyCycle};
use forja_hal_abstraction::thermal::{FULL_POWER, Heater, TemperatureSensor};
use forja_hal_abstraction::{Error, ErrorKind, ErrorType};

use crate::config::HeaterConfig;
use crate::machine::{NoSuchDevice, SimMachine};

/// A first-order thermal model (see the module documentation).
#[derive(Debug, Clone, PartialEq)]
pub struct ThermalModel {
    power_w: f64,
    heat_capacity_j_per_k: f64,
    loss_w_per_k: f64,
    ambient_c: f64,
    temperature_c: f64,
    /// Power fraction, 0..=1.
    duty: f64,
    connected: bool,
    fault: Option<SensorFault>,
}

impl ThermalModel {
    /// A model with the constants of `config`, at `start_c`, heater off.
    pub fn new(config: &HeaterConfig) -> Self {
        Self {
            power_w: config.power_w,
            heat_capacity_j_per_k: config.heat_capacity_j_per_k,
            loss_w_per_k: config.loss_w_per_k,
            ambient_c: config.ambient_c,
            temperature_c: config.start_c,
            duty: 0.0,
            connected: true,
            fault: None,
        }
    }

    /// Current temperature, in degrees Celsius.
    pub fn temperature_c(&self) -> f64 {
        self.temperature_c
    }

    /// Current power fraction, 0..=1.
    pub fn duty(&self) -> f64 {
        self.duty
    }

    /// Set the power fraction; clamped to 0..=1.
    pub fn set_duty(&mut self, duty: f64) {
        self.duty = duty.clamp(0.0, 1.0);
    }

    /// The temperature the model settles at with the current power.
    pub fn steady_state_c(&self) -> f64 {
        let heat = if self.connected {
            self.duty * self.power_w
        } else {
            0.0
        };
        self.ambient_c + heat / self.loss_w_per_k
    }

    /// Time constant `C / k`, in seconds.
    pub fn time_constant_s(&self) -> f64 {
        self.heat_capacity_j_per_k / self.loss_w_per_k
    }

    /// Advance the model by `dt_s` seconds at the current power.
    pub fn advance(&mut self, dt_s: f64) {
        if dt_s <= 0.0 {
            return;
        }
        let ss = self.steady_state_c();
        let decay = (-dt_s / self.time_constant_s()).exp();
        self.temperature_c = ss + (self.temperature_c - ss) * decay;
    }
}

/// A simulated sensor fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SensorFault {
    /// The sensor circuit is open (a thermistor's wire came off).
    Open,
    /// The sensor is shorted.
    Short,
}

/// The error of a faulty [`SimTemperatureSensor`]; its kind is [`ErrorKind::SensorFault`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SimSensorError(pub SensorFault);

impl Error for SimSensorError {
    fn kind(&self) -> ErrorKind {
        ErrorKind::SensorFault
    }
}

impl fmt::Display for SimSensorError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            SensorFault::Open => f.write_str("temperature sensor open"),
            SensorFault::Short => f.write_str("temperature sensor shorted"),
        }
    }
}

impl std::error::Error for SimSensorError {}

impl SimMachine {
    fn check_heater(&self, index: usize) -> Result<(), NoSuchDevice> {
        if index < self.config().heaters.len() {
            Ok(())
        } else {
            Err(NoSuchDevice::Heater(index))
        }
    }

    fn with_heater<R>(
        &self,
        index: usize,
        f: impl FnOnce(&mut ThermalModel) -> R,
    ) -> Result<R, NoSuchDevice> {
        self.check_heater(index)?;
        let mut s = self.state.borrow_mut();
        s.sync_thermal();
        Ok(f(&mut s.heaters[index]))
    }

    /// Heater `index` (machine file order), as a [`Heater`].
    pub fn heater(&self, index: usize) -> Result<SimHeater, NoSuchDevice> {
        self.check_heater(index)?;
        Ok(SimHeater {
            machine: self.clone(),
            index,
        })
    }

    /// The temperature sensor of heater `index`, as a [`TemperatureSensor`].
    pub fn temperature_sensor(&self, index: usize) -> Result<SimTemperatureSensor, NoSuchDevice> {
        self.check_heater(index)?;
        Ok(SimTemperatureSensor {
            machine: self.clone(),
            index,
        })
    }

    /// The thermal model of heater `index`, brought up to the current virtual time.
    pub fn thermal_model(&self, index: usize) -> Result<ThermalModel, NoSuchDevice> {
        self.with_heater(index, |h| h.clone())
    }

    /// The true temperature of heater `index` now, in degrees Celsius (whatever its sensor
    /// reads).
    pub fn temperature_c(&self, index: usize) -> Result<f64, NoSuchDevice> {
        self.with_heater(index, |h| h.temperature_c())
    }

    /// Make the sensor of heater `index` fail (`Some`) or work again (`None`).
    pub fn set_sensor_fault(
        &self,
        index: usize,
        fault: Option<SensorFault>,
    ) -> Result<(), NoSuchDevice> {
        self.with_heater(index, |h| h.fault = fault)
    }

    /// Connect (`true`) or disconnect heater `index` from its mass: disconnected, its power
    /// heats nothing (a cartridge fallen out of its block).
    pub fn set_heater_connected(&self, index: usize, connected: bool) -> Result<(), NoSuchDevice> {
        self.with_heater(index, |h| h.connected = connected)
    }
}

/// A simulated heater: implements [`Heater`] and [`SetDutyCycle`]. Never fails.
#[derive(Clone)]
pub struct SimHeater {
    machine: SimMachine,
    index: usize,
}

impl SimHeater {
    fn set_fraction(&mut self, duty: f64) {
        // The index was checked when the handle was made.
        let _ = self.machine.with_heater(self.index, |h| h.set_duty(duty));
    }

    /// The current power fraction, 0..=1.
    pub fn duty_fraction(&self) -> f64 {
        self.machine
            .with_heater(self.index, |h| h.duty())
            .unwrap_or(0.0)
    }
}

impl fmt::Debug for SimHeater {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimHeater")
            .field("index", &self.index)
            .finish()
    }
}

impl ErrorType for SimHeater {
    type Error = Infallible;
}

impl Heater for SimHeater {
    fn set_power(&mut self, power: u16) -> Result<(), Infallible> {
        self.set_fraction(f64::from(power) / f64::from(FULL_POWER));
        Ok(())
    }
}

impl pwm::ErrorType for SimHeater {
    type Error = Infallible;
}

impl SetDutyCycle for SimHeater {
    fn max_duty_cycle(&self) -> u16 {
        FULL_POWER
    }

    fn set_duty_cycle(&mut self, duty: u16) -> Result<(), Infallible> {
        self.set_fraction(f64::from(duty) / f64::from(FULL_POWER));
        Ok(())
    }
}

/// A simulated temperature sensor: implements [`TemperatureSensor`], reading the true
/// temperature of its heater's mass, or [`SimSensorError`] while a fault is set.
#[derive(Clone)]
pub struct SimTemperatureSensor {
    machine: SimMachine,
    index: usize,
}

impl fmt::Debug for SimTemperatureSensor {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimTemperatureSensor")
            .field("index", &self.index)
            .finish()
    }
}

impl ErrorType for SimTemperatureSensor {
    type Error = SimSensorError;
}

impl TemperatureSensor for SimTemperatureSensor {
    fn read_millicelsius(&mut self) -> Result<i32, SimSensorError> {
        let (t, fault) = self
            .machine
            .with_heater(self.index, |h| (h.temperature_c(), h.fault))
            .unwrap_or((0.0, Some(SensorFault::Open)));
        match fault {
            Some(f) => Err(SimSensorError(f)),
            None => Ok((t * 1000.0).round() as i32),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MachineConfig;

    fn printer() -> SimMachine {
        let text = MachineConfig::bundled_toml("printer").unwrap();
        SimMachine::new(&MachineConfig::from_toml_str(text).unwrap())
    }

    const HZ: u64 = 1_000_000;

    #[test]
    fn full_power_converges_to_the_steady_state() {
        let m = printer();
        let hotend = m.heater_index("hotend").unwrap();
        let mut heater = m.heater(hotend).unwrap();
        let mut sensor = m.temperature_sensor(hotend).unwrap();
        assert_eq!(sensor.read_millicelsius().unwrap(), 25_000);
        heater.set_power(FULL_POWER).unwrap();
        assert_eq!(heater.duty_fraction(), 1.0);
        // Ten time constants (100 s each), read every 100 ms virtual.
        let mut last = 25_000;
        for _ in 0..10_000 {
            m.advance_by(HZ / 10);
            let t = sensor.read_millicelsius().unwrap();
            assert!(t >= last, "heating is monotonic");
            last = t;
        }
        let ss = 25.0 + 40.0 / 0.1;
        assert!(
            (f64::from(last) / 1000.0 - ss).abs() < 0.05,
            "{last} vs {ss}"
        );
        assert_eq!(m.thermal_model(hotend).unwrap().steady_state_c(), ss);
    }

    #[test]
    fn matches_the_analytic_curve_whatever_the_read_rate() {
        // Read once after 60 s, and on another machine every millisecond: same answer,
        // and both match T_ss + (T0 - T_ss) e^(-t/tau).
        let coarse = printer();
        let fine = printer();
        for m in [&coarse, &fine] {
            m.heater(0).unwrap().set_power(FULL_POWER / 2).unwrap();
        }
        coarse.advance_by(60 * HZ);
        for _ in 0..60_000 {
            fine.advance_by(HZ / 1000);
            let _ = fine.temperature_c(0).unwrap();
        }
        let u = f64::from(FULL_POWER / 2) / f64::from(FULL_POWER);
        let ss = 25.0 + u * 40.0 / 0.1;
        let expected = ss + (25.0 - ss) * (-60.0f64 / 100.0).exp();
        let a = coarse.temperature_c(0).unwrap();
        let b = fine.temperature_c(0).unwrap();
        assert!((a - expected).abs() < 1e-9, "{a} vs {expected}");
        assert!((b - expected).abs() < 1e-6, "{b} vs {expected}");
    }

    #[test]
    fn cools_to_ambient_when_off() {
        let text = MachineConfig::bundled_toml("printer").unwrap().replacen(
            "heat_capacity_j_per_k = 10.0\n",
            "heat_capacity_j_per_k = 10.0\nstart_c = 210.0\n",
            1,
        );
        let m = SimMachine::new(&MachineConfig::from_toml_str(&text).unwrap());
        assert_eq!(m.temperature_c(0).unwrap(), 210.0);
        m.advance_by(1_000 * HZ);
        assert!((m.temperature_c(0).unwrap() - 25.0).abs() < 0.01);
    }

    #[test]
    fn pwm_interface_sets_the_same_power() {
        let m = printer();
        let bed = m.heater_index("bed").unwrap();
        let mut heater = m.heater(bed).unwrap();
        assert_eq!(heater.max_duty_cycle(), FULL_POWER);
        heater.set_duty_cycle_percent(50).unwrap();
        assert!((heater.duty_fraction() - 0.5).abs() < 1e-4);
        heater.set_duty_cycle_fully_off().unwrap();
        assert_eq!(heater.duty_fraction(), 0.0);
    }

    #[test]
    fn faults() {
        let m = printer();
        let mut sensor = m.temperature_sensor(0).unwrap();
        m.set_sensor_fault(0, Some(SensorFault::Open)).unwrap();
        let e = sensor.read_millicelsius().unwrap_err();
        assert_eq!(e.kind(), ErrorKind::SensorFault);
        assert_eq!(e.to_string(), "temperature sensor open");
        m.set_sensor_fault(0, None).unwrap();
        assert!(sensor.read_millicelsius().is_ok());

        // A disconnected heater heats nothing however long it is on.
        m.set_heater_connected(0, false).unwrap();
        m.heater(0).unwrap().set_power(FULL_POWER).unwrap();
        m.advance_by(300 * HZ);
        assert_eq!(sensor.read_millicelsius().unwrap(), 25_000);

        assert_eq!(m.heater(5).unwrap_err(), NoSuchDevice::Heater(5));
        assert!(m.temperature_sensor(2).is_err());
    }
}
