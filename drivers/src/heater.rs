//! PID temperature control with thermal protection: one temperature zone (a hot end, a bed).
//!
//! [`PidHeater`] is the sans-IO core: it is given the time and the measured temperature and
//! answers with a heater power, or with a latched [`HeaterFault`]. [`HeaterChannel`] wires it
//! to a [`TemperatureSensor`] and a [`Heater`], turns the heater off on any fault, and is the
//! zone's [`TemperatureControl`]: the application sets its target (`M104`, `M140`), reads it
//! (`M105`) and decides when it is close enough to its target for a wait (`M109`, `M116`) to
//! end; the channel keeps no G-code rule.
//!
//! # Control
//!
//! A PID on the error `target − measured` in kelvin, with time in seconds and output as a
//! fraction of full power:
//! - the derivative acts on the measurement, not the error, so that a new target does not kick
//!   the output, and is smoothed exponentially (factor [`D_SMOOTHING`] per update);
//! - anti-windup by conditional integration: the integral does not grow while the output is
//!   saturated in the direction of the error, and stays within `0..=max_power`;
//! - further than [`HeaterConfig::full_power_band_mc`] below the target the heater runs at
//!   [`HeaterConfig::max_power`] and the integral is cleared (fast heat-up without wind-up);
//! - the output is clamped to `0..=max_power`.
//!
//! # Protection
//!
//! Every fault turns the heater off, clears the target and latches until
//! [`PidHeater::clear_fault`]:
//! - **over-temperature**: a reading above [`HeaterConfig::max_temp_mc`], whatever the target;
//! - **heating stalled**: while heating towards the target, the temperature must rise by
//!   [`HeaterConfig::watch_increase_mc`] within every [`HeaterConfig::watch_period_ms`]
//!   (a heater cartridge fallen out of its block, a thermistor out of its hole);
//! - **temperature drop**: once the target was reached, the temperature staying more than
//!   [`HeaterConfig::runaway_hysteresis_mc`] below it for [`HeaterConfig::runaway_period_ms`]
//!   (the thermal-runaway check of Marlin and Klipper's `verify_heater`);
//! - **sensor**: the sensor could not be read or reads out of range
//!   ([`PidHeater::trip`], called by [`HeaterChannel`]).
//!
//! # Execution context
//!
//! Thread: the temperature loop, a few times per second. `f32` arithmetic; never panics and
//! never blocks (the sensor read of [`HeaterChannel::poll`] may block for one conversion).

use core::fmt;

use forja_hal_abstraction::device::{DeviceError, TemperatureControl};
use forja_hal_abstraction::thermal::{FULL_POWER, Heater, TemperatureSensor};
use forja_hal_abstraction::{Error, ErrorKind};

/// Smoothing of the derivative term: each update keeps this fraction of the previous value
/// (Marlin's `PID_K1`).
pub const D_SMOOTHING: f32 = 0.95;

/// A target must stay this far below [`HeaterConfig::max_temp_mc`], to leave room for
/// overshoot, in millidegrees.
pub const TARGET_MARGIN_MC: i32 = 15_000;

/// Updates further apart than this (milliseconds) do not integrate or differentiate: the loop
/// was stalled and the elapsed time would only inject a jump.
const MAX_DT_MS: u32 = 5_000;

/// PID gains, in fractions of full power.
///
/// Marlin's `M301`/`M304` values are in PWM counts of 255 with time in seconds: divide each by
/// 255 (Marlin `Kp 22.2, Ki 1.08, Kd 114` is `kp 0.087, ki 0.0042, kd 0.45`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PidGains {
    /// Proportional: power per kelvin of error.
    pub kp: f32,
    /// Integral: power per kelvin-second of accumulated error.
    pub ki: f32,
    /// Derivative: power per kelvin-per-second of temperature change.
    pub kd: f32,
}

/// Gains, limits and protection thresholds of one heater. Temperatures in millidegrees
/// Celsius, times in milliseconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaterConfig {
    /// The PID gains.
    pub gains: PidGains,
    /// Output clamp, 0 to [`FULL_POWER`] (a bed on an undersized supply runs below full).
    pub max_power: u16,
    /// Readings above this are an over-temperature fault.
    pub max_temp_mc: i32,
    /// Further below the target than this, the output is `max_power` and the integral cleared;
    /// `0` keeps the PID in control everywhere.
    pub full_power_band_mc: i32,
    /// Heating stall window.
    pub watch_period_ms: u32,
    /// Rise required within each stall window while heating.
    pub watch_increase_mc: i32,
    /// How long the temperature may stay too far below a reached target.
    pub runaway_period_ms: u32,
    /// How far below a reached target is too far.
    pub runaway_hysteresis_mc: i32,
}

impl HeaterConfig {
    /// A hot end with Marlin's default protection: 275 °C cut-off, 10 °C full-power band,
    /// +2 °C every 20 s while heating, at most 40 s more than 4 °C below target.
    pub const fn hot_end(gains: PidGains) -> Self {
        Self {
            gains,
            max_power: FULL_POWER,
            max_temp_mc: 275_000,
            full_power_band_mc: 10_000,
            watch_period_ms: 20_000,
            watch_increase_mc: 2_000,
            runaway_period_ms: 40_000,
            runaway_hysteresis_mc: 4_000,
        }
    }

    /// A heated bed with Marlin's default protection: 150 °C cut-off, 10 °C full-power band,
    /// +2 °C every 60 s while heating, at most 20 s more than 2 °C below target.
    pub const fn bed(gains: PidGains) -> Self {
        Self {
            gains,
            max_power: FULL_POWER,
            max_temp_mc: 150_000,
            full_power_band_mc: 10_000,
            watch_period_ms: 60_000,
            watch_increase_mc: 2_000,
            runaway_period_ms: 20_000,
            runaway_hysteresis_mc: 2_000,
        }
    }

    /// The highest target accepted: [`TARGET_MARGIN_MC`] below the cut-off.
    pub const fn max_target_mc(&self) -> i32 {
        self.max_temp_mc.saturating_sub(TARGET_MARGIN_MC)
    }
}

/// Why a heater was shut off, or a target refused. The codes go on the wire and are stable.
/// Exhaustive on purpose: every fault has a wire code where it is reported.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum HeaterFault {
    /// The sensor is open, shorted, out of range or unreadable. Code 210.
    Sensor,
    /// Heating towards the target did not raise the temperature enough in time. Code 211.
    HeatingStalled,
    /// The temperature fell and stayed far below a reached target (thermal runaway). Code 212.
    TemperatureDrop,
    /// The temperature exceeded the cut-off. Code 213.
    OverTemperature,
    /// The heater output could not be driven. Code 214.
    Output,
    /// A target above [`HeaterConfig::max_target_mc`] was refused; nothing latched. Code 215.
    TargetTooHigh,
}

impl HeaterFault {
    /// The stable wire code, in 210..=219.
    pub const fn code(&self) -> u16 {
        match self {
            Self::Sensor => 210,
            Self::HeatingStalled => 211,
            Self::TemperatureDrop => 212,
            Self::OverTemperature => 213,
            Self::Output => 214,
            Self::TargetTooHigh => 215,
        }
    }

    /// The stable short name, for the wire (kebab-case).
    pub const fn name(&self) -> &'static str {
        match self {
            Self::Sensor => "sensor-fault",
            Self::HeatingStalled => "heating-stalled",
            Self::TemperatureDrop => "thermal-runaway",
            Self::OverTemperature => "over-temperature",
            Self::Output => "heater-output",
            Self::TargetTooHigh => "target-too-high",
        }
    }
}

/// A refused target is [`DeviceError::OutOfRange`]; every other fault shuts the zone down and
/// is [`DeviceError::Thermal`] with its code and name.
impl From<HeaterFault> for DeviceError {
    fn from(fault: HeaterFault) -> Self {
        match fault {
            HeaterFault::TargetTooHigh => DeviceError::OutOfRange,
            f => DeviceError::Thermal {
                code: f.code(),
                name: f.name(),
            },
        }
    }
}

impl fmt::Display for HeaterFault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Sensor => "temperature sensor fault",
            Self::HeatingStalled => "heating stalled",
            Self::TemperatureDrop => "thermal runaway: temperature dropped below target",
            Self::OverTemperature => "over-temperature",
            Self::Output => "heater output fault",
            Self::TargetTooHigh => "target above the maximum",
        })
    }
}

impl Error for HeaterFault {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Sensor => ErrorKind::SensorFault,
            Self::TargetTooHigh => ErrorKind::OutOfRange,
            Self::HeatingStalled | Self::TemperatureDrop | Self::OverTemperature | Self::Output => {
                ErrorKind::Hardware
            }
        }
    }
}

/// Where the protection state machine stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Watch {
    /// No target.
    Idle,
    /// A new target; the next update decides between heating and holding.
    Start,
    /// Heating towards the target: the temperature must reach `from_mc + increase` before
    /// `since_ms + period`.
    Heating { since_ms: u32, from_mc: i32 },
    /// Target reached; `below_since_ms` is when the temperature last fell too far below it.
    Holding { below_since_ms: Option<u32> },
}

/// The PID controller and thermal protection of one heater (sans-IO).
#[derive(Debug, Clone)]
pub struct PidHeater {
    config: HeaterConfig,
    target_mc: i32,
    integral: f32,
    derivative: f32,
    last: Option<(u32, i32)>,
    watch: Watch,
    fault: Option<HeaterFault>,
}

impl PidHeater {
    /// A controller with no target (heater off).
    pub const fn new(config: HeaterConfig) -> Self {
        Self {
            config,
            target_mc: 0,
            integral: 0.0,
            derivative: 0.0,
            last: None,
            watch: Watch::Idle,
            fault: None,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &HeaterConfig {
        &self.config
    }

    /// Set the target, in millidegrees; `0` or below turns the heater off. A new target
    /// restarts the heating-stall watch.
    ///
    /// Errors: [`HeaterFault::TargetTooHigh`] above [`HeaterConfig::max_target_mc`] (the old
    /// target stays); a latched fault, until [`PidHeater::clear_fault`].
    pub fn set_target(&mut self, target_mc: i32) -> Result<(), HeaterFault> {
        if let Some(fault) = self.fault {
            return Err(fault);
        }
        if target_mc > self.config.max_target_mc() {
            return Err(HeaterFault::TargetTooHigh);
        }
        let target_mc = target_mc.max(0);
        if target_mc != self.target_mc {
            self.target_mc = target_mc;
            self.watch = if target_mc == 0 {
                self.integral = 0.0;
                Watch::Idle
            } else {
                Watch::Start
            };
        }
        Ok(())
    }

    /// The target, in millidegrees; 0 when off.
    pub fn target_mc(&self) -> i32 {
        self.target_mc
    }

    /// The last temperature given to [`PidHeater::update`], in millidegrees.
    pub fn measured_mc(&self) -> Option<i32> {
        self.last.map(|(_, mc)| mc)
    }

    /// The latched fault, if any.
    pub fn fault(&self) -> Option<HeaterFault> {
        self.fault
    }

    /// Latch `fault`: heater off, target cleared. Used for faults found outside the controller
    /// (sensor, output); the first fault is kept.
    pub fn trip(&mut self, fault: HeaterFault) {
        if self.fault.is_none() {
            self.fault = Some(fault);
        }
        self.target_mc = 0;
        self.integral = 0.0;
        self.derivative = 0.0;
        self.watch = Watch::Idle;
    }

    /// Clear a latched fault (an operator's explicit reset); the heater stays off until a new
    /// target is set.
    pub fn clear_fault(&mut self) {
        self.fault = None;
    }

    /// One control step: the temperature `measured_mc` read at `now_ms` (a wrapping
    /// millisecond clock) gives the heater power, 0 to `max_power`.
    ///
    /// Errors: a fault found now or latched before; the caller turns the heater off.
    pub fn update(&mut self, now_ms: u32, measured_mc: i32) -> Result<u16, HeaterFault> {
        let previous = self.last.replace((now_ms, measured_mc));
        if let Some(fault) = self.fault {
            return Err(fault);
        }
        if measured_mc > self.config.max_temp_mc {
            self.trip(HeaterFault::OverTemperature);
            return Err(HeaterFault::OverTemperature);
        }
        if let Err(fault) = self.watch(now_ms, measured_mc) {
            self.trip(fault);
            return Err(fault);
        }
        if self.target_mc == 0 {
            self.derivative = 0.0;
            return Ok(0);
        }

        let max = f32::from(self.config.max_power) / f32::from(FULL_POWER);
        let dt_s = previous
            .map(|(t, _)| now_ms.wrapping_sub(t))
            .filter(|&dt| dt > 0 && dt <= MAX_DT_MS)
            .map_or(0.0, |dt| dt as f32 / 1000.0);
        let error_mc = i64::from(self.target_mc) - i64::from(measured_mc);
        let error_k = error_mc as f32 / 1000.0;

        if self.config.full_power_band_mc > 0
            && error_mc > i64::from(self.config.full_power_band_mc)
        {
            self.integral = 0.0;
            self.derivative = 0.0;
            return Ok(self.config.max_power);
        }

        let g = self.config.gains;
        if dt_s > 0.0
            && let Some((_, previous_mc)) = previous
        {
            let change_mc = i64::from(measured_mc) - i64::from(previous_mc);
            let rate_k_per_s = change_mc as f32 / 1000.0 / dt_s;
            self.derivative =
                D_SMOOTHING * self.derivative - (1.0 - D_SMOOTHING) * g.kd * rate_k_per_s;
        }
        let p = g.kp * error_k;
        let candidate = (self.integral + g.ki * error_k * dt_s).clamp(0.0, max);
        let unclamped = p + candidate + self.derivative;
        let saturated_same_way =
            (unclamped > max && error_k > 0.0) || (unclamped < 0.0 && error_k < 0.0);
        if !saturated_same_way {
            self.integral = candidate;
        }
        let out = (p + self.integral + self.derivative).clamp(0.0, max);
        // `out` is finite and within 0..=1 unless the gains are NaN; `as` saturates either way.
        let power = libm::roundf(out * f32::from(FULL_POWER)) as u16;
        Ok(power.min(self.config.max_power))
    }

    fn watch(&mut self, now_ms: u32, measured_mc: i32) -> Result<(), HeaterFault> {
        let c = &self.config;
        let near_target = measured_mc >= self.target_mc.saturating_sub(c.runaway_hysteresis_mc);
        self.watch = match self.watch {
            Watch::Idle => Watch::Idle,
            Watch::Start | Watch::Heating { .. } if near_target => Watch::Holding {
                below_since_ms: None,
            },
            Watch::Start => Watch::Heating {
                since_ms: now_ms,
                from_mc: measured_mc,
            },
            Watch::Heating { since_ms, from_mc } => {
                if measured_mc >= from_mc.saturating_add(c.watch_increase_mc) {
                    Watch::Heating {
                        since_ms: now_ms,
                        from_mc: measured_mc,
                    }
                } else if now_ms.wrapping_sub(since_ms) >= c.watch_period_ms {
                    return Err(HeaterFault::HeatingStalled);
                } else {
                    Watch::Heating { since_ms, from_mc }
                }
            }
            Watch::Holding { .. } if near_target => Watch::Holding {
                below_since_ms: None,
            },
            Watch::Holding { below_since_ms } => {
                let since = below_since_ms.unwrap_or(now_ms);
                if now_ms.wrapping_sub(since) >= c.runaway_period_ms {
                    return Err(HeaterFault::TemperatureDrop);
                }
                Watch::Holding {
                    below_since_ms: Some(since),
                }
            }
        };
        Ok(())
    }
}

/// What [`HeaterChannel::poll`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeaterReport {
    /// The temperature read, in millidegrees (for M105).
    pub measured_mc: i32,
    /// The power applied, 0 to [`FULL_POWER`].
    pub power: u16,
}

/// A sensor, a heater and their [`PidHeater`]: one call per control period does the lot.
pub struct HeaterChannel<S, H> {
    sensor: S,
    heater: H,
    pid: PidHeater,
    /// The power applied last, 0 to [`FULL_POWER`].
    power: u16,
}

impl<S: TemperatureSensor, H: Heater> HeaterChannel<S, H> {
    /// A channel controlling `heater` from `sensor` as `config` says. Turns the heater off;
    /// if that fails the channel starts latched in [`HeaterFault::Output`], for the board to
    /// report.
    pub fn new(sensor: S, mut heater: H, config: HeaterConfig) -> Self {
        let mut pid = PidHeater::new(config);
        if heater.set_power(0).is_err() {
            pid.trip(HeaterFault::Output);
        }
        Self {
            sensor,
            heater,
            pid,
            power: 0,
        }
    }

    /// Read the sensor, run the controller, drive the heater.
    ///
    /// Context: thread. May block for one sensor conversion.
    /// Errors: a fault (found now or latched); the heater has been turned off (as far as its
    /// output still obeys).
    pub fn poll(&mut self, now_ms: u32) -> Result<HeaterReport, HeaterFault> {
        let measured_mc = match self.sensor.read_millicelsius() {
            Ok(mc) => mc,
            Err(_) => {
                self.pid.trip(HeaterFault::Sensor);
                return Err(self.shut_off());
            }
        };
        let power = match self.pid.update(now_ms, measured_mc) {
            Ok(power) => power,
            Err(_) => return Err(self.shut_off()),
        };
        if self.heater.set_power(power).is_err() {
            self.pid.trip(HeaterFault::Output);
            return Err(self.shut_off());
        }
        self.power = power;
        Ok(HeaterReport { measured_mc, power })
    }

    fn shut_off(&mut self) -> HeaterFault {
        self.power = 0;
        if self.heater.set_power(0).is_err() {
            self.pid.trip(HeaterFault::Output);
        }
        self.pid.fault().unwrap_or(HeaterFault::Output)
    }

    /// The controller: target, last measurement, fault.
    pub fn pid(&self) -> &PidHeater {
        &self.pid
    }

    /// The controller, to set a target or clear a fault.
    pub fn pid_mut(&mut self) -> &mut PidHeater {
        &mut self.pid
    }

    /// Give the sensor and heater back.
    pub fn release(self) -> (S, H) {
        (self.sensor, self.heater)
    }
}

impl<S: TemperatureSensor, H: Heater> TemperatureControl for HeaterChannel<S, H> {
    fn set_target_mc(&mut self, target_mc: i32) -> Result<(), DeviceError> {
        Ok(self.pid.set_target(target_mc)?)
    }

    fn target_mc(&self) -> i32 {
        self.pid.target_mc()
    }

    fn current_mc(&self) -> Option<i32> {
        self.pid.measured_mc()
    }

    fn power(&self) -> u16 {
        self.power
    }

    fn run(&mut self, now_ms: u32) -> Result<(), DeviceError> {
        self.poll(now_ms)?;
        Ok(())
    }

    fn fault(&self) -> Option<DeviceError> {
        self.pid.fault().map(DeviceError::from)
    }

    fn clear_fault(&mut self) {
        self.pid.clear_fault();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use forja_hal_abstraction::ErrorType;

    const GAINS: PidGains = PidGains {
        kp: 0.087,
        ki: 0.0042,
        kd: 0.45,
    };

    /// Whether the last measurement is within `tolerance_mc` of the target.
    fn within(pid: &PidHeater, tolerance_mc: i32) -> bool {
        pid.measured_mc()
            .is_some_and(|mc| (mc - pid.target_mc()).abs() <= tolerance_mc)
    }

    /// A lumped thermal model of a hot end: 20 °C ambient, 40 W heater, heat capacity
    /// `cap_j_per_k`, loss `loss_w_per_k`.
    struct Plant {
        temp_c: f32,
        heater_w: f32,
        cap_j_per_k: f32,
        loss_w_per_k: f32,
    }

    impl Plant {
        fn hot_end() -> Self {
            Self {
                temp_c: 20.0,
                heater_w: 40.0,
                cap_j_per_k: 10.0,
                loss_w_per_k: 0.15,
            }
        }
        fn step(&mut self, power: u16, dt_s: f32) {
            let p = self.heater_w * f32::from(power) / f32::from(FULL_POWER);
            self.temp_c += (p - self.loss_w_per_k * (self.temp_c - 20.0)) * dt_s / self.cap_j_per_k;
        }
        fn mc(&self) -> i32 {
            (self.temp_c * 1000.0) as i32
        }
    }

    #[test]
    fn reaches_and_holds_the_target_without_large_overshoot() {
        let mut pid = PidHeater::new(HeaterConfig::hot_end(GAINS));
        let mut plant = Plant::hot_end();
        pid.set_target(210_000).unwrap();
        let mut peak = 0;
        for i in 0..(600 * 10) {
            let now = i * 100;
            let power = pid.update(now, plant.mc()).unwrap();
            plant.step(power, 0.1);
            peak = peak.max(plant.mc());
        }
        assert!(within(&pid, 1_000), "{} m°C", plant.mc());
        assert!(peak < 210_000 + 8_000, "overshoot to {peak}");
        assert_eq!(pid.fault(), None);
    }

    #[test]
    fn output_is_clamped_and_zero_without_target() {
        let mut cfg = HeaterConfig::bed(GAINS);
        cfg.max_power = FULL_POWER / 2;
        let mut pid = PidHeater::new(cfg);
        assert_eq!(pid.update(0, 20_000), Ok(0));
        assert_eq!(pid.target_mc(), 0, "an idle heater has no target");
        pid.set_target(60_000).unwrap();
        assert_eq!(
            pid.update(100, 20_000),
            Ok(FULL_POWER / 2),
            "full-power band"
        );
        // Inside the band the PID output is clamped too.
        assert!(pid.update(200, 55_000).unwrap() <= FULL_POWER / 2);
        // Well above the target the output is zero, never negative.
        assert_eq!(pid.update(300, 70_000).map(|p| p == 0), Ok(true));
    }

    #[test]
    fn integral_does_not_wind_up_while_saturated() {
        let mut cfg = HeaterConfig::hot_end(GAINS);
        cfg.full_power_band_mc = 0;
        cfg.watch_period_ms = u32::MAX;
        let mut pid = PidHeater::new(cfg);
        pid.set_target(200_000).unwrap();
        // A long time far below the target: saturated, so no integration.
        for i in 0..1_000 {
            assert_eq!(pid.update(i * 100, 150_000), Ok(FULL_POWER));
        }
        assert_eq!(pid.integral, 0.0);
        // At the target, the output drops at once instead of staying high for minutes.
        let p = pid.update(100_100, 200_500).unwrap();
        assert!(p < FULL_POWER / 4, "{p}");
    }

    #[test]
    fn over_temperature_trips_whatever_the_target() {
        let mut pid = PidHeater::new(HeaterConfig::hot_end(GAINS));
        assert_eq!(pid.update(0, 276_000), Err(HeaterFault::OverTemperature));
        assert_eq!(pid.fault(), Some(HeaterFault::OverTemperature));
        // Latched: stays faulted at a normal reading and refuses targets.
        assert_eq!(pid.update(100, 25_000), Err(HeaterFault::OverTemperature));
        assert_eq!(pid.set_target(200_000), Err(HeaterFault::OverTemperature));
        assert_eq!(pid.target_mc(), 0, "a fault clears the target");
        pid.clear_fault();
        assert_eq!(pid.update(200, 25_000), Ok(0));
        pid.set_target(200_000).unwrap();
    }

    #[test]
    fn targets_too_close_to_the_cut_off_are_refused() {
        let mut pid = PidHeater::new(HeaterConfig::hot_end(GAINS));
        assert_eq!(pid.set_target(261_000), Err(HeaterFault::TargetTooHigh));
        assert_eq!(pid.target_mc(), 0);
        pid.set_target(260_000).unwrap();
        pid.set_target(-5).unwrap();
        assert_eq!(pid.target_mc(), 0);
        assert_eq!(pid.fault(), None, "a refused target latches nothing");
    }

    #[test]
    fn stalled_heating_trips() {
        let mut pid = PidHeater::new(HeaterConfig::hot_end(GAINS));
        pid.set_target(200_000).unwrap();
        // A thermistor that fell out of the block: the reading rises only 1 °C in 20 s.
        let mut result = Ok(0);
        for i in 0..=200u32 {
            result = pid.update(i * 100, 25_000 + (i as i32) * 5);
            if result.is_err() {
                break;
            }
        }
        assert_eq!(result, Err(HeaterFault::HeatingStalled));
        assert_eq!(pid.target_mc(), 0);
    }

    #[test]
    fn steady_heating_does_not_trip() {
        let mut pid = PidHeater::new(HeaterConfig::bed(GAINS));
        pid.set_target(100_000).unwrap();
        // +1 °C every 10 s: slow, but more than 2 °C per 60 s.
        for i in 0..=800u32 {
            assert!(
                pid.update(i * 1_000, 20_000 + (i as i32) * 100).is_ok(),
                "{i}"
            );
        }
    }

    #[test]
    fn temperature_dropping_below_a_reached_target_trips() {
        let mut pid = PidHeater::new(HeaterConfig::hot_end(GAINS));
        pid.set_target(200_000).unwrap();
        pid.update(0, 199_000).unwrap();
        // A short dip is tolerated.
        pid.update(1_000, 190_000).unwrap();
        pid.update(30_000, 190_000).unwrap();
        pid.update(31_000, 199_000).unwrap();
        // A lasting one is not.
        pid.update(32_000, 190_000).unwrap();
        pid.update(71_000, 190_000).unwrap();
        assert_eq!(
            pid.update(72_000, 190_000),
            Err(HeaterFault::TemperatureDrop)
        );
    }

    #[test]
    fn lowering_the_target_lets_it_cool() {
        let mut pid = PidHeater::new(HeaterConfig::hot_end(GAINS));
        pid.set_target(200_000).unwrap();
        pid.update(0, 200_000).unwrap();
        pid.set_target(150_000).unwrap();
        for i in 1..=200u32 {
            assert!(pid.update(i * 1_000, 200_000 - (i as i32) * 250).is_ok());
        }
        assert!(within(&pid, 1_000));
    }

    #[test]
    fn codes_are_stable_and_in_the_driver_range() {
        let all = [
            (HeaterFault::Sensor, 210),
            (HeaterFault::HeatingStalled, 211),
            (HeaterFault::TemperatureDrop, 212),
            (HeaterFault::OverTemperature, 213),
            (HeaterFault::Output, 214),
            (HeaterFault::TargetTooHigh, 215),
        ];
        for (f, code) in all {
            assert_eq!(f.code(), code);
            assert!(!f.to_string().is_empty());
        }
        assert_eq!(HeaterFault::Sensor.kind(), ErrorKind::SensorFault);
        assert_eq!(HeaterFault::TargetTooHigh.kind(), ErrorKind::OutOfRange);
    }

    // --- HeaterChannel with fake sensor and heater ---

    #[derive(Debug)]
    struct Fail;
    impl Error for Fail {
        fn kind(&self) -> ErrorKind {
            ErrorKind::SensorFault
        }
    }

    struct FakeSensor(Vec<Result<i32, ()>>);
    impl ErrorType for FakeSensor {
        type Error = Fail;
    }
    impl TemperatureSensor for FakeSensor {
        fn read_millicelsius(&mut self) -> Result<i32, Fail> {
            let r = if self.0.len() > 1 {
                self.0.remove(0)
            } else {
                self.0[0]
            };
            r.map_err(|()| Fail)
        }
    }

    #[derive(Default)]
    struct FakeHeater {
        power: Option<u16>,
        broken: bool,
    }
    impl ErrorType for FakeHeater {
        type Error = Fail;
    }
    impl Heater for FakeHeater {
        fn set_power(&mut self, power: u16) -> Result<(), Fail> {
            if self.broken {
                return Err(Fail);
            }
            self.power = Some(power);
            Ok(())
        }
    }

    #[test]
    fn channel_drives_the_heater_and_reports() {
        let mut ch = HeaterChannel::new(
            FakeSensor(vec![Ok(25_000)]),
            FakeHeater::default(),
            HeaterConfig::hot_end(GAINS),
        );
        ch.pid_mut().set_target(200_000).unwrap();
        let r = ch.poll(0).unwrap();
        assert_eq!(
            r,
            HeaterReport {
                measured_mc: 25_000,
                power: FULL_POWER
            }
        );
        assert!(!within(ch.pid(), 2_000));
        let (_, heater) = ch.release();
        assert_eq!(heater.power, Some(FULL_POWER));
    }

    #[test]
    fn sensor_faults_turn_the_heater_off() {
        let mut ch = HeaterChannel::new(
            FakeSensor(vec![Ok(25_000), Err(())]),
            FakeHeater::default(),
            HeaterConfig::hot_end(GAINS),
        );
        ch.pid_mut().set_target(200_000).unwrap();
        assert!(ch.poll(0).unwrap().power > 0);
        assert_eq!(ch.poll(100), Err(HeaterFault::Sensor));
        assert_eq!(ch.pid().target_mc(), 0);
        let (_, heater) = ch.release();
        assert_eq!(heater.power, Some(0));
    }

    #[test]
    fn output_faults_are_reported() {
        let ch = HeaterChannel::new(
            FakeSensor(vec![Ok(25_000)]),
            FakeHeater {
                power: None,
                broken: true,
            },
            HeaterConfig::hot_end(GAINS),
        );
        assert_eq!(ch.pid().fault(), Some(HeaterFault::Output));
        let mut ch = HeaterChannel::new(
            FakeSensor(vec![Ok(300_000)]),
            FakeHeater::default(),
            HeaterConfig::hot_end(GAINS),
        );
        assert_eq!(ch.poll(0), Err(HeaterFault::OverTemperature));
    }

    #[test]
    fn the_channel_is_a_temperature_zone() {
        let mut ch = HeaterChannel::new(
            FakeSensor(vec![Ok(25_000), Ok(25_000), Err(())]),
            FakeHeater::default(),
            HeaterConfig::hot_end(GAINS),
        );
        let zone: &mut dyn TemperatureControl = &mut ch;
        assert_eq!(zone.current_mc(), None, "nothing measured yet");
        assert_eq!(zone.set_target_mc(261_000), Err(DeviceError::OutOfRange));
        zone.set_target_mc(200_000).unwrap();
        zone.run(0).unwrap();
        assert_eq!(
            (zone.current_mc(), zone.target_mc()),
            (Some(25_000), 200_000)
        );
        zone.run(100).unwrap();
        let sensor = DeviceError::Thermal {
            code: 210,
            name: "sensor-fault",
        };
        assert_eq!(zone.run(200), Err(sensor));
        assert_eq!(zone.fault(), Some(sensor), "latched");
        assert_eq!(zone.target_mc(), 0);
        assert_eq!(zone.set_target_mc(200_000), Err(sensor));
        zone.clear_fault();
        assert_eq!(zone.fault(), None);
        assert_eq!(zone.target_mc(), 0, "off until a new target");
        let (_, heater) = ch.release();
        assert_eq!(heater.power, Some(0));
    }

    #[test]
    fn names_are_stable_and_faults_map_to_device_errors() {
        let all = [
            (HeaterFault::Sensor, "sensor-fault"),
            (HeaterFault::HeatingStalled, "heating-stalled"),
            (HeaterFault::TemperatureDrop, "thermal-runaway"),
            (HeaterFault::OverTemperature, "over-temperature"),
            (HeaterFault::Output, "heater-output"),
        ];
        for (f, name) in all {
            assert_eq!(f.name(), name);
            assert_eq!(
                DeviceError::from(f),
                DeviceError::Thermal {
                    code: f.code(),
                    name
                }
            );
        }
        assert_eq!(HeaterFault::TargetTooHigh.name(), "target-too-high");
        assert_eq!(
            DeviceError::from(HeaterFault::TargetTooHigh),
            DeviceError::OutOfRange
        );
    }
}
