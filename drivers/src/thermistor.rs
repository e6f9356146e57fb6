//! NTC thermistor temperature sensor on an ADC channel.
//!
//! `embedded-hal` 1.0 has no ADC trait, so this module defines the smallest one that a board's
//! HAL can implement in a few lines: [`AdcChannel`], or a closure wrapped in [`AdcFn`].
//! [`Thermistor`] turns its readings into millidegrees Celsius and implements
//! [`TemperatureSensor`].
//!
//! # Circuit
//!
//! The usual printer-board divider: a pull-up resistor from the ADC reference to the input, the
//! thermistor from the input to ground, and the ADC referenced to the same voltage (so the
//! supply cancels out). A reading `raw` of full scale `max` gives the thermistor resistance
//!
//! ```text
//! R = R_pullup · raw / (max − raw)
//! ```
//!
//! and the [`NtcModel`] (Beta equation or Steinhart–Hart) gives the temperature.
//!
//! # Faults
//!
//! A reading of 0 (thermistor shorted) or full scale (thermistor open, unplugged), or a
//! temperature outside [`ThermistorConfig::valid_mc`], is [`ErrorKind::SensorFault`]: the
//! temperature controller turns the heater off.
//!
//! # Execution context
//!
//! Thread (the temperature loop). One ADC conversion and a few dozen `f32` operations including
//! one logarithm; never panics.

use core::fmt;
use core::ops::RangeInclusive;

use forja_hal_abstraction::thermal::TemperatureSensor;
use forja_hal_abstraction::{Error, ErrorKind, ErrorType};

/// 0 °C in kelvin.
const ZERO_CELSIUS_K: f32 = 273.15;

/// One ADC input, read in raw counts.
pub trait AdcChannel {
    /// The HAL's conversion error.
    type Error: fmt::Debug;

    /// One conversion, in counts from 0 to [`AdcChannel::max_raw`].
    ///
    /// Context: thread. May block for one conversion. Errors: the conversion failed.
    fn read_raw(&mut self) -> Result<u16, Self::Error>;

    /// The full-scale reading: `2^bits − 1` for an ADC of `bits` bits (4095 for 12 bits).
    fn max_raw(&self) -> u16;
}

impl<T: AdcChannel + ?Sized> AdcChannel for &mut T {
    type Error = T::Error;
    fn read_raw(&mut self) -> Result<u16, Self::Error> {
        T::read_raw(self)
    }
    fn max_raw(&self) -> u16 {
        T::max_raw(self)
    }
}

/// An [`AdcChannel`] made of a closure that performs one conversion.
pub struct AdcFn<F> {
    read: F,
    max_raw: u16,
}

impl<F> AdcFn<F> {
    /// A channel of full scale `max_raw` (4095 for 12 bits) read by `read`.
    pub const fn new(max_raw: u16, read: F) -> Self {
        Self { read, max_raw }
    }

    /// The full scale of an ADC of `bits` bits (1 to 16).
    pub const fn max_raw_for_bits(bits: u8) -> u16 {
        if bits >= 16 {
            u16::MAX
        } else {
            (1u16 << bits) - 1
        }
    }
}

impl<F: FnMut() -> Result<u16, E>, E: fmt::Debug> AdcChannel for AdcFn<F> {
    type Error = E;
    fn read_raw(&mut self) -> Result<u16, E> {
        (self.read)()
    }
    fn max_raw(&self) -> u16 {
        self.max_raw
    }
}

/// The resistance–temperature law of an NTC thermistor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NtcModel {
    /// The Beta equation: `1/T = 1/T0 + ln(R/R0)/β`, exact at `T0` and good to about a degree
    /// over 0–250 °C for the usual printer thermistors.
    Beta {
        /// Resistance at `t0_c`, in ohms.
        r0_ohms: f32,
        /// Reference temperature, °C (25 for datasheet "R25" values).
        t0_c: f32,
        /// β, in kelvin.
        beta_k: f32,
    },
    /// Steinhart–Hart: `1/T = A + B·ln R + C·(ln R)³`, with `R` in ohms and `T` in kelvin;
    /// fit it to three points with [`NtcModel::steinhart_hart_from_points`].
    SteinhartHart {
        /// A coefficient.
        a: f32,
        /// B coefficient.
        b: f32,
        /// C coefficient.
        c: f32,
    },
}

impl NtcModel {
    /// 100 kΩ at 25 °C, β = 4066 K: EPCOS/TDK B57560G104F, the classic RepRap hot-end
    /// thermistor (Marlin's and Klipper's "EPCOS 100K B57560G104F").
    pub const EPCOS_100K: NtcModel = NtcModel::Beta {
        r0_ohms: 100_000.0,
        t0_c: 25.0,
        beta_k: 4066.0,
    };

    /// 100 kΩ at 25 °C, β = 3950 K: the generic "3950" thermistor of most beds and clone hot
    /// ends.
    pub const GENERIC_3950_100K: NtcModel = NtcModel::Beta {
        r0_ohms: 100_000.0,
        t0_c: 25.0,
        beta_k: 3950.0,
    };

    /// The Steinhart–Hart coefficients through three `(°C, ohms)` points, ideally spread over
    /// the working range (for example 25, 150 and 250 °C). `None` when the points do not give
    /// a usable fit (equal or non-positive values).
    pub fn steinhart_hart_from_points(points: [(f32, f32); 3]) -> Option<NtcModel> {
        let [(t1, r1), (t2, r2), (t3, r3)] = points;
        if !(r1 > 0.0 && r2 > 0.0 && r3 > 0.0) {
            return None;
        }
        let (l1, l2, l3) = (libm::logf(r1), libm::logf(r2), libm::logf(r3));
        let y1 = 1.0 / (t1 + ZERO_CELSIUS_K);
        let y2 = 1.0 / (t2 + ZERO_CELSIUS_K);
        let y3 = 1.0 / (t3 + ZERO_CELSIUS_K);
        let g2 = (y2 - y1) / (l2 - l1);
        let g3 = (y3 - y1) / (l3 - l1);
        let c = (g3 - g2) / (l3 - l2) / (l1 + l2 + l3);
        let b = g2 - c * (l1 * l1 + l1 * l2 + l2 * l2);
        let a = y1 - (b + l1 * l1 * c) * l1;
        [a, b, c]
            .iter()
            .all(|x| x.is_finite())
            .then_some(NtcModel::SteinhartHart { a, b, c })
    }

    /// The temperature, in °C, of a thermistor of resistance `r_ohms` (not finite for a
    /// non-positive resistance).
    pub fn celsius(&self, r_ohms: f32) -> f32 {
        let inv_t = match *self {
            NtcModel::Beta {
                r0_ohms,
                t0_c,
                beta_k,
            } => 1.0 / (t0_c + ZERO_CELSIUS_K) + libm::logf(r_ohms / r0_ohms) / beta_k,
            NtcModel::SteinhartHart { a, b, c } => {
                let l = libm::logf(r_ohms);
                a + b * l + c * l * l * l
            }
        };
        1.0 / inv_t - ZERO_CELSIUS_K
    }

    /// The resistance, in ohms, at `celsius` (the inverse of [`NtcModel::celsius`]; for the
    /// Steinhart–Hart model, by bisection over 1 Ω–100 MΩ).
    pub fn resistance(&self, celsius: f32) -> f32 {
        match *self {
            NtcModel::Beta {
                r0_ohms,
                t0_c,
                beta_k,
            } => {
                let t = celsius + ZERO_CELSIUS_K;
                let t0 = t0_c + ZERO_CELSIUS_K;
                r0_ohms * libm::expf(beta_k * (1.0 / t - 1.0 / t0))
            }
            NtcModel::SteinhartHart { .. } => {
                // Temperature falls as resistance rises; bisect on ln R.
                let (mut lo, mut hi) = (0.0f32, libm::logf(1.0e8));
                for _ in 0..60 {
                    let mid = 0.5 * (lo + hi);
                    if self.celsius(libm::expf(mid)) > celsius {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                libm::expf(0.5 * (lo + hi))
            }
        }
    }
}

/// How a [`Thermistor`] is wired and which readings are believable.
#[derive(Debug, Clone, PartialEq)]
pub struct ThermistorConfig {
    /// The thermistor's law.
    pub model: NtcModel,
    /// The pull-up resistor, in ohms (4.7 kΩ on most printer boards).
    pub pullup_ohms: f32,
    /// Temperatures outside this range, in millidegrees Celsius, are sensor faults.
    pub valid_mc: RangeInclusive<i32>,
}

impl ThermistorConfig {
    /// `model` behind a `pullup_ohms` pull-up, believable from −20 °C to 350 °C.
    pub const fn new(model: NtcModel, pullup_ohms: f32) -> Self {
        Self {
            model,
            pullup_ohms,
            valid_mc: -20_000..=350_000,
        }
    }
}

/// A [`Thermistor`] reading failed.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum ThermistorError<E> {
    /// The ADC conversion failed.
    Adc(E),
    /// Full-scale reading: the thermistor is open or unplugged.
    Open,
    /// Zero reading: the thermistor or its wiring is shorted.
    Shorted,
    /// The reading converts to a temperature outside [`ThermistorConfig::valid_mc`], in
    /// millidegrees (saturated to `i32`).
    Implausible(i32),
}

impl<E: fmt::Debug> fmt::Display for ThermistorError<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Adc(e) => write!(f, "thermistor ADC conversion failed: {e:?}"),
            Self::Open => f.write_str("thermistor open"),
            Self::Shorted => f.write_str("thermistor shorted"),
            Self::Implausible(mc) => write!(f, "thermistor reads an implausible {mc} m°C"),
        }
    }
}

impl<E: fmt::Debug> Error for ThermistorError<E> {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Adc(_) => ErrorKind::Hardware,
            Self::Open | Self::Shorted | Self::Implausible(_) => ErrorKind::SensorFault,
        }
    }
}

/// An NTC thermistor behind a pull-up, read through an [`AdcChannel`].
pub struct Thermistor<A> {
    adc: A,
    config: ThermistorConfig,
}

impl<A: AdcChannel> Thermistor<A> {
    /// A sensor on `adc` wired as `config` says.
    pub fn new(adc: A, config: ThermistorConfig) -> Self {
        Self { adc, config }
    }

    /// The temperature, in millidegrees Celsius, that a reading of `raw` stands for.
    ///
    /// Context: either. Never blocks. Errors: as [`TemperatureSensor::read_millicelsius`],
    /// except [`ThermistorError::Adc`].
    pub fn convert(&self, raw: u16) -> Result<i32, ThermistorError<A::Error>> {
        let max = self.adc.max_raw();
        if raw >= max {
            return Err(ThermistorError::Open);
        }
        if raw == 0 {
            return Err(ThermistorError::Shorted);
        }
        let r_ohms = self.config.pullup_ohms * f32::from(raw) / f32::from(max - raw);
        let celsius = self.config.model.celsius(r_ohms);
        if !celsius.is_finite() {
            return Err(ThermistorError::Implausible(if celsius > 0.0 {
                i32::MAX
            } else {
                i32::MIN
            }));
        }
        // `as` saturates: a wild value stays wild and fails the range check below.
        let mc = libm::roundf(celsius * 1000.0) as i32;
        if self.config.valid_mc.contains(&mc) {
            Ok(mc)
        } else {
            Err(ThermistorError::Implausible(mc))
        }
    }

    /// The configuration this sensor was built with.
    pub fn config(&self) -> &ThermistorConfig {
        &self.config
    }

    /// Give the ADC channel back.
    pub fn release(self) -> A {
        self.adc
    }
}

impl<A: AdcChannel> ErrorType for Thermistor<A> {
    type Error = ThermistorError<A::Error>;
}

impl<A: AdcChannel> TemperatureSensor for Thermistor<A> {
    fn read_millicelsius(&mut self) -> Result<i32, Self::Error> {
        let raw = self.adc.read_raw().map_err(ThermistorError::Adc)?;
        self.convert(raw)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MAX12: u16 = 4095;

    /// The reading the divider gives at `celsius`.
    fn raw_at(model: NtcModel, pullup: f32, celsius: f32) -> u16 {
        let r = model.resistance(celsius);
        (f32::from(MAX12) * r / (r + pullup)).round() as u16
    }

    fn sensor(model: NtcModel, raw: u16) -> Thermistor<AdcFn<impl FnMut() -> Result<u16, ()>>> {
        Thermistor::new(
            AdcFn::new(MAX12, move || Ok(raw)),
            ThermistorConfig::new(model, 4_700.0),
        )
    }

    #[test]
    fn full_scale_helper() {
        assert_eq!(AdcFn::<()>::max_raw_for_bits(12), 4095);
        assert_eq!(AdcFn::<()>::max_raw_for_bits(10), 1023);
        assert_eq!(AdcFn::<()>::max_raw_for_bits(16), u16::MAX);
    }

    #[test]
    fn beta_model_round_trips_over_the_printing_range() {
        for model in [NtcModel::EPCOS_100K, NtcModel::GENERIC_3950_100K] {
            for c in [0.0f32, 25.0, 60.0, 110.0, 200.0, 250.0, 300.0] {
                let mc = sensor(model, raw_at(model, 4_700.0, c))
                    .read_millicelsius()
                    .unwrap();
                // 12-bit quantisation: well under 1 °C from 0 to 300 °C with a 4.7 kΩ pull-up.
                assert!(
                    (mc - (c * 1000.0) as i32).abs() < 1_000,
                    "{model:?} at {c} °C read {mc}"
                );
            }
        }
    }

    #[test]
    fn known_points_of_the_epcos_thermistor() {
        let m = NtcModel::EPCOS_100K;
        assert!((m.celsius(100_000.0) - 25.0).abs() < 0.01);
        // β = 4066 K gives about 645 Ω at 200 °C.
        assert!((m.resistance(200.0) - 645.0).abs() < 5.0);
    }

    #[test]
    fn steinhart_hart_fit_reproduces_its_points() {
        let beta = NtcModel::EPCOS_100K;
        let pts = [25.0f32, 150.0, 250.0].map(|t| (t, beta.resistance(t)));
        let sh = NtcModel::steinhart_hart_from_points(pts).unwrap();
        for (t, r) in pts {
            assert!((sh.celsius(r) - t).abs() < 0.2, "{t} °C: {}", sh.celsius(r));
            assert!(((sh.resistance(t) - r) / r).abs() < 0.01);
        }
        let mc = sensor(sh, raw_at(sh, 4_700.0, 200.0))
            .read_millicelsius()
            .unwrap();
        assert!((mc - 200_000).abs() < 1_000, "{mc}");
        assert_eq!(
            NtcModel::steinhart_hart_from_points([(25.0, 1.0), (25.0, 1.0), (25.0, 1.0)]),
            None
        );
        assert_eq!(
            NtcModel::steinhart_hart_from_points([(25.0, 0.0), (50.0, 1.0), (75.0, 2.0)]),
            None
        );
    }

    #[test]
    fn open_shorted_and_implausible_readings_are_sensor_faults() {
        let m = NtcModel::EPCOS_100K;
        let e = sensor(m, MAX12).read_millicelsius().unwrap_err();
        assert_eq!(e, ThermistorError::Open);
        assert_eq!(e.kind(), ErrorKind::SensorFault);
        let e = sensor(m, 0).read_millicelsius().unwrap_err();
        assert_eq!(e, ThermistorError::Shorted);
        assert_eq!(e.kind(), ErrorKind::SensorFault);
        // One count from full scale: about −60 °C, colder than any workshop.
        let e = sensor(m, MAX12 - 1).read_millicelsius().unwrap_err();
        assert!(
            matches!(e, ThermistorError::Implausible(mc) if mc < -20_000),
            "{e:?}"
        );
        assert_eq!(e.kind(), ErrorKind::SensorFault);
        // One count above zero: far above 350 °C.
        let e = sensor(m, 1).read_millicelsius().unwrap_err();
        assert!(
            matches!(e, ThermistorError::Implausible(mc) if mc > 350_000),
            "{e:?}"
        );
        assert!(e.to_string().starts_with("thermistor reads an implausible"));
    }

    #[test]
    fn adc_errors_are_hardware_faults() {
        let mut t = Thermistor::new(
            AdcFn::new(MAX12, || Err("bus")),
            ThermistorConfig::new(NtcModel::EPCOS_100K, 4_700.0),
        );
        let e = t.read_millicelsius().unwrap_err();
        assert_eq!(e, ThermistorError::Adc("bus"));
        assert_eq!(e.kind(), ErrorKind::Hardware);
        assert_eq!(t.config().pullup_ohms, 4_700.0);
    }

    #[test]
    fn every_reading_converts_without_panicking() {
        let t = sensor(NtcModel::GENERIC_3950_100K, 0);
        let mut last = i32::MAX;
        for raw in 0..=MAX12 {
            if let Ok(mc) = t.convert(raw) {
                assert!(mc < last, "temperature falls as the reading rises");
                last = mc;
            }
        }
        assert!(last < 0);
    }
}
