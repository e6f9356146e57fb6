//! Fans, spindles and heaters on `embedded-hal` PWM channels.
//!
//! Every driver here takes any [`SetDutyCycle`] channel, scales its command to the channel's
//! [`SetDutyCycle::max_duty_cycle`] with integer arithmetic, and writes the duty once per
//! command. [`Fan`] is a [`FanControl`] and [`Spindle`] a [`SpindleControl`], the devices the
//! application commands (`M106`/`M107`, `M3`/`M4`/`M5`); [`PwmHeater`] is the [`Heater`] of a
//! temperature loop. Each applies exactly what it is told: the G-code rules (an `M3` without `S`
//! runs at the last speed) are the application's.
//!
//! # Execution context
//!
//! Thread: the application applies fan and spindle commands in order with motion (when the
//! moves before them are done), the temperature loop drives [`PwmHeater`]. No method blocks.
//!
//! # Errors
//!
//! A channel or pin that refuses a write gives [`PwmError`] or [`SpindleError`], with the
//! `embedded-hal` error kind; their [`Error::kind`] is [`ErrorKind::Hardware`]. Through the
//! device traits they are [`DeviceError::Hardware`]; a reversal asked of a spindle that cannot
//! reverse is [`DeviceError::OutOfRange`].
//!
//! # Turning off
//!
//! These drivers do not switch their output off when dropped. A `Drop` impl could call
//! `set_duty_cycle_fully_off`, but it would not make the machine safe: a driver lives for the
//! whole run of the firmware (in a `static` or an RTIC resource), and a panicking firmware
//! halts without running destructors, leaving the timer running at its last duty. Safety comes
//! from the board instead: its panic handler (or a watchdog reset) returns the pins to their
//! reset state, and hardware pull-downs keep heater, spindle and laser MOSFETs off while the
//! pins float. A `Drop` impl would also forbid handing the pins back with `release`. Call
//! [`Fan::off`], [`Spindle::stop`] or `set_power(0)` to turn an output off.

use core::fmt;

use embedded_hal::digital::{self, OutputPin, PinState};
use embedded_hal::pwm::{self, SetDutyCycle};
use forja_hal_abstraction::device::{DeviceError, FanControl, Rotation, SpindleControl};
use forja_hal_abstraction::thermal::{FULL_POWER, Heater};
use forja_hal_abstraction::{Error, ErrorKind, ErrorType};

use crate::pin::{NoPin, drive, opposite};

/// `value / scale` of `max`, rounded to nearest; `value` is at most `scale`.
fn scale_duty(value: u32, scale: u32, max: u16) -> u16 {
    if scale == 0 {
        return 0;
    }
    let duty =
        (u64::from(value.min(scale)) * u64::from(max) + u64::from(scale / 2)) / u64::from(scale);
    u16::try_from(duty).unwrap_or(max)
}

fn set_duty<P: SetDutyCycle>(pwm: &mut P, duty: u16) -> Result<(), pwm::ErrorKind> {
    pwm.set_duty_cycle(duty).map_err(|e| pwm::Error::kind(&e))
}

/// A PWM channel refused a duty cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub struct PwmError {
    /// The channel's own error kind.
    pub pwm_error: pwm::ErrorKind,
}

impl fmt::Display for PwmError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "PWM output: {}", self.pwm_error)
    }
}

impl Error for PwmError {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Hardware
    }
}

impl From<pwm::ErrorKind> for PwmError {
    fn from(pwm_error: pwm::ErrorKind) -> Self {
        Self { pwm_error }
    }
}

/// How a [`Fan`] maps its 0–255 speed to a duty cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct FanConfig {
    /// Lowest speed at which the fan still turns: speeds 1–255 map linearly onto
    /// `min_speed`–255 (Marlin's `FAN_MIN_PWM`). `0` maps speeds unchanged.
    pub min_speed: u8,
    /// The output is active-low (a P-channel switch, an inverting driver): full speed is duty 0.
    pub inverted: bool,
}

impl FanConfig {
    /// Speeds map unchanged, active-high output.
    pub const DIRECT: FanConfig = FanConfig {
        min_speed: 0,
        inverted: false,
    };
}

/// A PWM fan, commanded on the RepRap 0–255 scale (`M106 S…`, `M107`).
#[derive(Debug)]
pub struct Fan<P> {
    pwm: P,
    config: FanConfig,
    speed: u8,
}

impl<P: SetDutyCycle> Fan<P> {
    /// A fan on `pwm`, switched off.
    ///
    /// Context: thread. Errors: the channel refused the duty cycle.
    pub fn new(pwm: P, config: FanConfig) -> Result<Self, PwmError> {
        let mut fan = Self {
            pwm,
            config,
            speed: 0,
        };
        fan.set_speed(0)?;
        Ok(fan)
    }

    /// Run at `speed` out of 255 (`M106 S<speed>`); 0 stops the fan.
    ///
    /// Context: thread. Errors: the channel refused the duty cycle (the recorded speed is
    /// unchanged).
    pub fn set_speed(&mut self, speed: u8) -> Result<(), PwmError> {
        let min = u32::from(self.config.min_speed);
        let effective = match u32::from(speed) {
            s if s == 0 || min <= 1 => s,
            // 1 ↦ min, 255 ↦ 255.
            s => min + (s - 1) * (255 - min) / 254,
        };
        let max = self.pwm.max_duty_cycle();
        let duty = scale_duty(effective, 255, max);
        let duty = if self.config.inverted {
            max - duty
        } else {
            duty
        };
        set_duty(&mut self.pwm, duty)?;
        self.speed = speed;
        Ok(())
    }

    /// Stop the fan (`M107`).
    ///
    /// Context: thread. Errors: as [`Fan::set_speed`].
    pub fn off(&mut self) -> Result<(), PwmError> {
        self.set_speed(0)
    }

    /// The commanded speed, 0–255 (for status reports).
    pub fn speed(&self) -> u8 {
        self.speed
    }

    /// Give the channel back, at its last duty cycle.
    pub fn release(self) -> P {
        self.pwm
    }
}

impl<P: SetDutyCycle> FanControl for Fan<P> {
    fn set_duty(&mut self, duty: u8) -> Result<(), DeviceError> {
        self.set_speed(duty).map_err(|_| DeviceError::Hardware)
    }
}

/// A heater switched by a PWM channel (a MOSFET gate): implements [`Heater`].
///
/// Use a slow PWM (a few Hz to a few hundred Hz) for beds on mechanical or solid-state relays.
#[derive(Debug)]
pub struct PwmHeater<P> {
    pwm: P,
}

impl<P: SetDutyCycle> PwmHeater<P> {
    /// A heater on `pwm`, switched off.
    ///
    /// Context: thread. Errors: the channel refused the duty cycle.
    pub fn new(mut pwm: P) -> Result<Self, PwmError> {
        set_duty(&mut pwm, 0)?;
        Ok(Self { pwm })
    }

    /// Give the channel back, at its last duty cycle.
    pub fn release(self) -> P {
        self.pwm
    }
}

impl<P: SetDutyCycle> ErrorType for PwmHeater<P> {
    type Error = PwmError;
}

impl<P: SetDutyCycle> Heater for PwmHeater<P> {
    fn set_power(&mut self, power: u16) -> Result<(), Self::Error> {
        let max = self.pwm.max_duty_cycle();
        let duty = scale_duty(u32::from(power), u32::from(FULL_POWER), max);
        Ok(set_duty(&mut self.pwm, duty)?)
    }
}

/// What a [`Spindle`] is told to do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SpindleState {
    /// Stopped (`M5`).
    Off,
    /// Clockwise at `rpm` (`M3 S<rpm>`).
    Clockwise {
        /// Speed, revolutions per minute.
        rpm: u32,
    },
    /// Counter-clockwise at `rpm` (`M4 S<rpm>`); needs a direction pin.
    CounterClockwise {
        /// Speed, revolutions per minute.
        rpm: u32,
    },
}

/// Speed range and line levels of a [`Spindle`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpindleConfig {
    /// The speed at full duty; faster commands are clamped to it.
    pub max_rpm: u32,
    /// The slowest speed the spindle holds; slower non-zero commands run at it.
    pub min_rpm: u32,
    /// Level of the direction pin for clockwise rotation.
    pub clockwise: PinState,
    /// Level of the enable pin that runs the spindle.
    pub enable_active: PinState,
}

impl SpindleConfig {
    /// Up to `max_rpm`, no minimum, direction high for clockwise, active-high enable.
    pub const fn new(max_rpm: u32) -> Self {
        Self {
            max_rpm,
            min_rpm: 0,
            clockwise: PinState::High,
            enable_active: PinState::High,
        }
    }
}

/// A [`Spindle`] command failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum SpindleError {
    /// The PWM channel refused the duty cycle.
    Pwm(pwm::ErrorKind),
    /// The direction or enable pin could not be written.
    Pin(digital::ErrorKind),
    /// Counter-clockwise rotation was asked of a spindle without a direction pin; nothing
    /// changed.
    NotReversible,
}

impl fmt::Display for SpindleError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Pwm(k) => write!(f, "spindle PWM output: {k}"),
            Self::Pin(k) => write!(f, "spindle control pin: {k}"),
            Self::NotReversible => f.write_str("spindle has no direction control"),
        }
    }
}

impl Error for SpindleError {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Pwm(_) | Self::Pin(_) => ErrorKind::Hardware,
            Self::NotReversible => ErrorKind::OutOfRange,
        }
    }
}

impl From<SpindleError> for DeviceError {
    fn from(e: SpindleError) -> Self {
        match e {
            SpindleError::NotReversible => DeviceError::OutOfRange,
            SpindleError::Pwm(_) | SpindleError::Pin(_) => DeviceError::Hardware,
        }
    }
}

/// A spindle (or a laser, a plasma torch's motion-synchronised output) with a PWM speed
/// input and optional direction and enable pins.
///
/// Starting sets the direction first, then the enable, then the speed; stopping removes the
/// speed first, then the enable. A reversal while running drops the speed to zero before it
/// flips the direction; waiting for the spindle to slow down (a `G4` dwell) is the G-code's
/// business, not the driver's.
#[derive(Debug)]
pub struct Spindle<P, DIR = NoPin, EN = NoPin> {
    pwm: P,
    dir: Option<DIR>,
    enable: Option<EN>,
    config: SpindleConfig,
    state: SpindleState,
}

impl<P: SetDutyCycle> Spindle<P, NoPin, NoPin> {
    /// A clockwise-only spindle with no enable pin, stopped.
    ///
    /// Context: thread. Errors: the channel refused the duty cycle.
    pub fn new(pwm: P, config: SpindleConfig) -> Result<Self, SpindleError> {
        Self::build(pwm, None, None, config)
    }
}

impl<P: SetDutyCycle, DIR: OutputPin> Spindle<P, DIR, NoPin> {
    /// A reversible spindle with no enable pin, stopped.
    ///
    /// Context: thread. Errors: the channel refused the duty cycle.
    pub fn with_direction(pwm: P, dir: DIR, config: SpindleConfig) -> Result<Self, SpindleError> {
        Self::build(pwm, Some(dir), None, config)
    }
}

impl<P: SetDutyCycle, EN: OutputPin> Spindle<P, NoPin, EN> {
    /// A clockwise-only spindle with an enable pin, stopped.
    ///
    /// Context: thread. Errors: the channel or the enable pin refused the write.
    pub fn with_enable(pwm: P, enable: EN, config: SpindleConfig) -> Result<Self, SpindleError> {
        Self::build(pwm, None, Some(enable), config)
    }
}

impl<P: SetDutyCycle, DIR: OutputPin, EN: OutputPin> Spindle<P, DIR, EN> {
    /// A reversible spindle with an enable pin, stopped.
    ///
    /// Context: thread. Errors: the channel or the enable pin refused the write.
    pub fn with_direction_and_enable(
        pwm: P,
        dir: DIR,
        enable: EN,
        config: SpindleConfig,
    ) -> Result<Self, SpindleError> {
        Self::build(pwm, Some(dir), Some(enable), config)
    }

    fn build(
        pwm: P,
        dir: Option<DIR>,
        enable: Option<EN>,
        config: SpindleConfig,
    ) -> Result<Self, SpindleError> {
        let mut spindle = Self {
            pwm,
            dir,
            enable,
            config,
            state: SpindleState::Off,
        };
        spindle.stop()?;
        Ok(spindle)
    }

    /// Whether counter-clockwise rotation is available (a direction pin is wired).
    pub fn is_reversible(&self) -> bool {
        self.dir.is_some()
    }

    /// Apply `state`; returns the speed actually commanded after clamping to
    /// [`SpindleConfig::min_rpm`]..=[`SpindleConfig::max_rpm`] (0 when off).
    ///
    /// Context: thread. Errors: [`SpindleError::NotReversible`] (nothing changed); a write
    /// failure, after which the spindle is in an unknown state and the caller stops the
    /// machine.
    pub fn set(&mut self, state: SpindleState) -> Result<u32, SpindleError> {
        let (clockwise, rpm) = match state {
            SpindleState::Off => {
                self.stop()?;
                return Ok(0);
            }
            SpindleState::Clockwise { rpm } => (true, rpm),
            SpindleState::CounterClockwise { rpm } => (false, rpm),
        };
        if !clockwise && self.dir.is_none() {
            return Err(SpindleError::NotReversible);
        }
        let rpm = match rpm {
            0 => 0,
            r => r.clamp(
                self.config.min_rpm.min(self.config.max_rpm),
                self.config.max_rpm,
            ),
        };
        let reversing = matches!(
            (self.state, clockwise),
            (SpindleState::Clockwise { .. }, false) | (SpindleState::CounterClockwise { .. }, true)
        );
        if reversing {
            set_duty(&mut self.pwm, 0).map_err(SpindleError::Pwm)?;
        }
        if let Some(dir) = self.dir.as_mut() {
            let level = if clockwise {
                self.config.clockwise
            } else {
                opposite(self.config.clockwise)
            };
            drive(dir, level).map_err(SpindleError::Pin)?;
        }
        if let Some(enable) = self.enable.as_mut() {
            drive(enable, self.config.enable_active).map_err(SpindleError::Pin)?;
        }
        let duty = scale_duty(rpm, self.config.max_rpm, self.pwm.max_duty_cycle());
        set_duty(&mut self.pwm, duty).map_err(SpindleError::Pwm)?;
        self.state = if clockwise {
            SpindleState::Clockwise { rpm }
        } else {
            SpindleState::CounterClockwise { rpm }
        };
        Ok(rpm)
    }

    /// Stop the spindle (`M5`): speed to zero, then enable off.
    ///
    /// Context: thread. Errors: a write failure.
    pub fn stop(&mut self) -> Result<(), SpindleError> {
        set_duty(&mut self.pwm, 0).map_err(SpindleError::Pwm)?;
        if let Some(enable) = self.enable.as_mut() {
            drive(enable, opposite(self.config.enable_active)).map_err(SpindleError::Pin)?;
        }
        self.state = SpindleState::Off;
        Ok(())
    }

    /// The state last applied successfully, with the clamped speed.
    pub fn state(&self) -> SpindleState {
        self.state
    }

    /// Give the channel and pins back, as last driven.
    pub fn release(self) -> (P, Option<DIR>, Option<EN>) {
        (self.pwm, self.dir, self.enable)
    }
}

impl<P: SetDutyCycle, DIR: OutputPin, EN: OutputPin> SpindleControl for Spindle<P, DIR, EN> {
    fn run(&mut self, rotation: Rotation, rpm: u32) -> Result<(), DeviceError> {
        let state = match rotation {
            Rotation::Clockwise => SpindleState::Clockwise { rpm },
            Rotation::CounterClockwise => SpindleState::CounterClockwise { rpm },
        };
        self.set(state)?;
        Ok(())
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        Ok(Spindle::stop(self)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_fakes::{FailingPin, FakeOutput};
    use std::cell::RefCell;
    use std::rc::Rc;

    /// A PWM channel of 1000 steps that records every duty written.
    #[derive(Debug, Clone, Default)]
    struct FakePwm {
        log: Rc<RefCell<Vec<u16>>>,
        broken: bool,
    }
    impl FakePwm {
        fn duty(&self) -> Option<u16> {
            self.log.borrow().last().copied()
        }
    }
    #[derive(Debug)]
    struct PwmFault;
    impl pwm::Error for PwmFault {
        fn kind(&self) -> pwm::ErrorKind {
            pwm::ErrorKind::Other
        }
    }
    impl pwm::ErrorType for FakePwm {
        type Error = PwmFault;
    }
    impl SetDutyCycle for FakePwm {
        fn max_duty_cycle(&self) -> u16 {
            1000
        }
        fn set_duty_cycle(&mut self, duty: u16) -> Result<(), PwmFault> {
            assert!(duty <= 1000, "duty {duty} above max");
            if self.broken {
                return Err(PwmFault);
            }
            self.log.borrow_mut().push(duty);
            Ok(())
        }
    }

    #[test]
    fn fan_maps_0_to_255_onto_the_duty_range() {
        let pwm = FakePwm::default();
        let mut fan = Fan::new(pwm.clone(), FanConfig::DIRECT).unwrap();
        assert_eq!(pwm.duty(), Some(0));
        fan.set_speed(255).unwrap();
        assert_eq!(pwm.duty(), Some(1000));
        fan.set_speed(128).unwrap();
        assert_eq!(pwm.duty(), Some(502));
        assert_eq!(fan.speed(), 128);
        fan.off().unwrap();
        assert_eq!(pwm.duty(), Some(0));
        assert_eq!(fan.speed(), 0);
        let _pwm: FakePwm = fan.release();
    }

    #[test]
    fn fan_minimum_speed_and_inversion() {
        let pwm = FakePwm::default();
        let cfg = FanConfig {
            min_speed: 51,
            inverted: true,
        };
        let mut fan = Fan::new(pwm.clone(), cfg).unwrap();
        assert_eq!(pwm.duty(), Some(1000), "inverted off is full duty");
        fan.set_speed(1).unwrap();
        assert_eq!(
            pwm.duty(),
            Some(1000 - 200),
            "speed 1 runs at the minimum (51/255)"
        );
        fan.set_speed(255).unwrap();
        assert_eq!(pwm.duty(), Some(0));
        let mut last = 1001;
        for s in 1..=255u8 {
            fan.set_speed(s).unwrap();
            let d = pwm.duty().unwrap();
            assert!(d <= last, "monotonic");
            last = d;
        }
    }

    #[test]
    fn fan_errors_keep_the_recorded_speed() {
        let pwm = FakePwm {
            broken: true,
            ..FakePwm::default()
        };
        assert_eq!(
            Fan::new(pwm, FanConfig::DIRECT).unwrap_err().kind(),
            ErrorKind::Hardware
        );
    }

    #[test]
    fn heater_power_scales_to_duty() {
        let pwm = FakePwm::default();
        let mut h = PwmHeater::new(pwm.clone()).unwrap();
        assert_eq!(pwm.duty(), Some(0));
        h.set_power(FULL_POWER).unwrap();
        assert_eq!(pwm.duty(), Some(1000));
        h.set_power(FULL_POWER / 4).unwrap();
        assert_eq!(pwm.duty(), Some(250));
        let _ = h.release();
    }

    #[test]
    fn spindle_speed_direction_and_enable() {
        let (pwm, dir, en) = (FakePwm::default(), FakeOutput::new(), FakeOutput::new());
        let mut s = Spindle::with_direction_and_enable(
            pwm.clone(),
            dir.clone(),
            en.clone(),
            SpindleConfig {
                min_rpm: 1_000,
                ..SpindleConfig::new(24_000)
            },
        )
        .unwrap();
        assert_eq!(pwm.duty(), Some(0));
        assert_eq!(en.level(), Some(PinState::Low));
        assert!(s.is_reversible());

        assert_eq!(s.set(SpindleState::Clockwise { rpm: 12_000 }), Ok(12_000));
        assert_eq!(pwm.duty(), Some(500));
        assert_eq!(dir.level(), Some(PinState::High));
        assert_eq!(en.level(), Some(PinState::High));

        // Above the maximum: clamped. Below the minimum: raised.
        assert_eq!(s.set(SpindleState::Clockwise { rpm: 30_000 }), Ok(24_000));
        assert_eq!(pwm.duty(), Some(1000));
        assert_eq!(s.set(SpindleState::Clockwise { rpm: 10 }), Ok(1_000));

        // Reversal passes through zero speed before the direction flips.
        pwm.log.borrow_mut().clear();
        assert_eq!(
            s.set(SpindleState::CounterClockwise { rpm: 6_000 }),
            Ok(6_000)
        );
        assert_eq!(*pwm.log.borrow(), [0, 250]);
        assert_eq!(dir.level(), Some(PinState::Low));
        assert_eq!(s.state(), SpindleState::CounterClockwise { rpm: 6_000 });

        assert_eq!(s.set(SpindleState::Off), Ok(0));
        assert_eq!(pwm.duty(), Some(0));
        assert_eq!(en.level(), Some(PinState::Low));
        assert_eq!(s.state(), SpindleState::Off);
        let (_, d, e) = s.release();
        assert!(d.is_some() && e.is_some());
    }

    #[test]
    fn a_spindle_without_direction_pin_refuses_reverse() {
        let pwm = FakePwm::default();
        let mut s = Spindle::new(pwm.clone(), SpindleConfig::new(10_000)).unwrap();
        assert!(!s.is_reversible());
        s.set(SpindleState::Clockwise { rpm: 5_000 }).unwrap();
        let e = s
            .set(SpindleState::CounterClockwise { rpm: 5_000 })
            .unwrap_err();
        assert_eq!(e, SpindleError::NotReversible);
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert_eq!(pwm.duty(), Some(500), "nothing changed");
        assert_eq!(s.state(), SpindleState::Clockwise { rpm: 5_000 });
    }

    #[test]
    fn fan_and_spindle_are_devices() {
        let (fan_pwm, spindle_pwm) = (FakePwm::default(), FakePwm::default());
        let mut fan = Fan::new(fan_pwm.clone(), FanConfig::DIRECT).unwrap();
        let mut spindle = Spindle::new(spindle_pwm.clone(), SpindleConfig::new(10_000)).unwrap();
        let f: &mut dyn FanControl = &mut fan;
        f.set_duty(255).unwrap();
        assert_eq!(fan_pwm.duty(), Some(1000));
        let s: &mut dyn SpindleControl = &mut spindle;
        s.run(Rotation::Clockwise, 20_000).unwrap();
        assert_eq!(spindle_pwm.duty(), Some(1000), "capped at the maximum");
        assert_eq!(
            s.run(Rotation::CounterClockwise, 5_000),
            Err(DeviceError::OutOfRange)
        );
        assert_eq!(spindle_pwm.duty(), Some(1000), "nothing changed");
        s.stop().unwrap();
        assert_eq!(spindle.state(), SpindleState::Off);
        let broken = FakePwm {
            broken: true,
            ..FakePwm::default()
        };
        let mut fan = Fan {
            pwm: broken,
            config: FanConfig::DIRECT,
            speed: 0,
        };
        assert_eq!(
            FanControl::set_duty(&mut fan, 1),
            Err(DeviceError::Hardware)
        );
    }

    #[test]
    fn spindle_pin_failures_are_hardware_errors() {
        let e = Spindle::with_enable(FakePwm::default(), FailingPin, SpindleConfig::new(1))
            .unwrap_err();
        assert!(matches!(e, SpindleError::Pin(_)));
        assert_eq!(e.kind(), ErrorKind::Hardware);
        let mut s =
            Spindle::with_direction(FakePwm::default(), FailingPin, SpindleConfig::new(1_000))
                .unwrap();
        assert!(matches!(
            s.set(SpindleState::Clockwise { rpm: 1 }),
            Err(SpindleError::Pin(_))
        ));
        assert!(!e.to_string().is_empty());
    }
}
