//! Step/direction motor driver over `embedded-hal` output pins.
//!
//! [`StepDir`] implements [`Stepper`] and [`StepperEnable`] for any driver chip with STEP, DIR
//! and (optionally) ENABLE inputs: A4988, DRV8825, the TMC22xx family in step/dir mode, external
//! servo drives. Each line's active level is configurable ([`StepDirConfig`]) and the chip's
//! pulse and set-up times come from a [`DriverChip`] preset or are given directly.
//!
//! # Execution context
//!
//! [`Stepper::set_direction`], [`Stepper::step_begin`] and [`Stepper::step_end`] run in the
//! step interrupt: each is exactly one pin write, with no branch on state and no allocation.
//! [`StepperEnable::set_enabled`] runs in thread context.
//!
//! # Errors
//!
//! A pin write that fails is reported as [`StepperError`], naming the line and carrying the
//! pin's `embedded-hal` error kind; its [`Error::kind`] is always [`ErrorKind::Hardware`], so
//! the kernel stops motion. Most GPIO cannot fail (`Infallible`), and the check then compiles
//! away.
//!
//! # Shutdown
//!
//! Dropping a [`StepDir`] does not touch the pins: a driver normally lives for the whole run of
//! the firmware, and a panicking firmware halts without running destructors. Call
//! [`StepperEnable::set_enabled`]`(false)` to release the motor, or [`StepDir::release`] to get
//! the pins back; the board's panic handler is what makes the outputs safe after a crash.

use core::fmt;

use embedded_hal::digital::{self, OutputPin, PinState};
use forja_hal_abstraction::stepper::{Direction, StepTiming, Stepper, StepperEnable};
use forja_hal_abstraction::{Error, ErrorKind, ErrorType};

use crate::pin::{NoPin, drive, opposite};

/// Timing presets for common step/direction driver chips.
///
/// Each preset gives the chip's minimum STEP high (and low) time and its minimum DIR set-up
/// time before a STEP rising edge, from the manufacturer's datasheet:
///
/// | chip | pulse | DIR set-up | source |
/// |---|---|---|---|
/// | A4988 | 1 µs | 200 ns | Allegro A4988 datasheet, "Timing Requirements" (STEP minimum high and low pulse width; set-up time, input change to STEP) |
/// | DRV8825 | 1.9 µs | 650 ns | TI DRV8825 datasheet (SLVSA73), "Timing Requirements" (pulse duration STEP high and low; set-up time DIR/MODEx to STEP rising) |
/// | TMC2209 | 100 ns | 20 ns | Trinamic TMC2209 datasheet, "STEP/DIR interface timing" (t<sub>SH</sub>, t<sub>SL</sub>: the larger of the input filter time and one clock period + 20 ns, typically 100 ns; t<sub>DSU</sub> DIR to STEP set-up) |
///
/// The TMC2209 figure is the datasheet's typical value; its formula gives 103 ns at the
/// nominal 12 MHz internal clock, which any step timer slower than 9.7 MHz rounds up to
/// anyway. A board that clocks the chip slower, or routes STEP through a slow level shifter,
/// states its own [`StepTiming`]. When in doubt use [`StepTiming::CONSERVATIVE`], which covers
/// all three chips.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum DriverChip {
    /// Allegro A4988.
    A4988,
    /// Texas Instruments DRV8825.
    Drv8825,
    /// Trinamic (Analog Devices) TMC2209, and the TMC2208/TMC2226 with the same timing, in
    /// step/direction mode.
    Tmc2209,
}

impl DriverChip {
    /// The chip's minimum step pulse width and direction set-up time.
    pub const fn timing(self) -> StepTiming {
        match self {
            Self::A4988 => StepTiming {
                min_pulse_ns: 1_000,
                dir_setup_ns: 200,
            },
            Self::Drv8825 => StepTiming {
                min_pulse_ns: 1_900,
                dir_setup_ns: 650,
            },
            Self::Tmc2209 => StepTiming {
                min_pulse_ns: 100,
                dir_setup_ns: 20,
            },
        }
    }
}

/// How a [`StepDir`] drives its lines.
///
/// The common chips take an active-high STEP pulse and an active-low ENABLE input; that is what
/// [`StepDirConfig::new`] and [`StepDirConfig::for_chip`] set. The `invert_*` methods flip one
/// line each, for a board with inverting level shifters or optocouplers, or a motor wired so
/// that it turns the wrong way.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepDirConfig {
    /// Pulse width and direction set-up time handed to the step generator.
    pub timing: StepTiming,
    /// Level of the STEP line during a pulse; the line idles at the other level.
    pub step_active: PinState,
    /// Level of the DIR line for [`Direction::Positive`].
    pub dir_positive: PinState,
    /// Level of the ENABLE line that energises the motor.
    pub enable_active: PinState,
}

impl StepDirConfig {
    /// Active-high STEP, DIR high for positive travel, active-low ENABLE, with `timing`.
    pub const fn new(timing: StepTiming) -> Self {
        Self {
            timing,
            step_active: PinState::High,
            dir_positive: PinState::High,
            enable_active: PinState::Low,
        }
    }

    /// The defaults of [`StepDirConfig::new`] with the timing of `chip`.
    pub const fn for_chip(chip: DriverChip) -> Self {
        Self::new(chip.timing())
    }

    /// STEP pulses go low instead of high (the line idles high).
    #[must_use]
    pub const fn invert_step(mut self) -> Self {
        self.step_active = opposite(self.step_active);
        self
    }

    /// Swap the DIR levels: the motor turns the other way for the same [`Direction`].
    #[must_use]
    pub const fn invert_dir(mut self) -> Self {
        self.dir_positive = opposite(self.dir_positive);
        self
    }

    /// Swap the ENABLE levels (active-high enable input).
    #[must_use]
    pub const fn invert_enable(mut self) -> Self {
        self.enable_active = opposite(self.enable_active);
        self
    }
}

/// The line of a [`StepDir`] whose write failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum StepperLine {
    /// The STEP line.
    Step,
    /// The DIR line.
    Direction,
    /// The ENABLE line.
    Enable,
}

/// A pin write of a [`StepDir`] failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub struct StepperError {
    /// Which line.
    pub line: StepperLine,
    /// The pin's own error kind.
    pub pin_error: digital::ErrorKind,
}

impl StepperError {
    fn on(line: StepperLine) -> impl Fn(digital::ErrorKind) -> Self {
        move |pin_error| Self { line, pin_error }
    }
}

impl fmt::Display for StepperError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let line = match self.line {
            StepperLine::Step => "STEP",
            StepperLine::Direction => "DIR",
            StepperLine::Enable => "ENABLE",
        };
        write!(f, "stepper {line} pin: {}", self.pin_error)
    }
}

impl Error for StepperError {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Hardware
    }
}

/// A step/direction motor driver on two or three output pins.
///
/// `EN` is [`NoPin`] when the board has no enable line (tied to its active level, or shared and
/// driven elsewhere); [`StepperEnable::set_enabled`] then does nothing.
#[derive(Debug)]
pub struct StepDir<STEP, DIR, EN = NoPin> {
    step: STEP,
    dir: DIR,
    enable: EN,
    config: StepDirConfig,
}

impl<STEP: OutputPin, DIR: OutputPin> StepDir<STEP, DIR, NoPin> {
    /// A driver without an enable line. Puts STEP at its idle level.
    ///
    /// Context: thread (board set-up). Errors: the STEP pin could not be written.
    pub fn new(step: STEP, dir: DIR, config: StepDirConfig) -> Result<Self, StepperError> {
        Self::with_enable(step, dir, NoPin, config)
    }
}

impl<STEP: OutputPin, DIR: OutputPin, EN: OutputPin> StepDir<STEP, DIR, EN> {
    /// A driver with an enable line. Puts STEP at its idle level and the motor released
    /// (ENABLE inactive), so that nothing moves until the kernel enables it.
    ///
    /// Context: thread (board set-up). Errors: the STEP or ENABLE pin could not be written.
    pub fn with_enable(
        mut step: STEP,
        dir: DIR,
        mut enable: EN,
        config: StepDirConfig,
    ) -> Result<Self, StepperError> {
        drive(&mut step, opposite(config.step_active))
            .map_err(StepperError::on(StepperLine::Step))?;
        drive(&mut enable, opposite(config.enable_active))
            .map_err(StepperError::on(StepperLine::Enable))?;
        Ok(Self {
            step,
            dir,
            enable,
            config,
        })
    }

    /// The configuration this driver was built with.
    pub fn config(&self) -> &StepDirConfig {
        &self.config
    }

    /// Give the pins back, in the state they were last driven to.
    pub fn release(self) -> (STEP, DIR, EN) {
        (self.step, self.dir, self.enable)
    }
}

impl<STEP: OutputPin, DIR: OutputPin, EN> ErrorType for StepDir<STEP, DIR, EN> {
    type Error = StepperError;
}

impl<STEP: OutputPin, DIR: OutputPin, EN> Stepper for StepDir<STEP, DIR, EN> {
    #[inline]
    fn set_direction(&mut self, direction: Direction) -> Result<(), Self::Error> {
        let level = match direction {
            Direction::Positive => self.config.dir_positive,
            Direction::Negative => opposite(self.config.dir_positive),
        };
        drive(&mut self.dir, level).map_err(StepperError::on(StepperLine::Direction))
    }

    #[inline]
    fn step_begin(&mut self) -> Result<(), Self::Error> {
        drive(&mut self.step, self.config.step_active).map_err(StepperError::on(StepperLine::Step))
    }

    #[inline]
    fn step_end(&mut self) -> Result<(), Self::Error> {
        drive(&mut self.step, opposite(self.config.step_active))
            .map_err(StepperError::on(StepperLine::Step))
    }

    fn timing(&self) -> StepTiming {
        self.config.timing
    }
}

impl<STEP: OutputPin, DIR: OutputPin, EN: OutputPin> StepperEnable for StepDir<STEP, DIR, EN> {
    fn set_enabled(&mut self, enabled: bool) -> Result<(), Self::Error> {
        let level = if enabled {
            self.config.enable_active
        } else {
            opposite(self.config.enable_active)
        };
        drive(&mut self.enable, level).map_err(StepperError::on(StepperLine::Enable))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_fakes::{FailingPin, FakeOutput};

    #[test]
    fn presets_match_the_datasheets() {
        assert_eq!(
            DriverChip::A4988.timing(),
            StepTiming {
                min_pulse_ns: 1_000,
                dir_setup_ns: 200
            }
        );
        assert_eq!(
            DriverChip::Drv8825.timing(),
            StepTiming {
                min_pulse_ns: 1_900,
                dir_setup_ns: 650
            }
        );
        assert_eq!(
            DriverChip::Tmc2209.timing(),
            StepTiming {
                min_pulse_ns: 100,
                dir_setup_ns: 20
            }
        );
        for chip in [DriverChip::A4988, DriverChip::Drv8825, DriverChip::Tmc2209] {
            let t = chip.timing();
            assert!(t.min_pulse_ns <= StepTiming::CONSERVATIVE.min_pulse_ns);
            assert!(t.dir_setup_ns <= StepTiming::CONSERVATIVE.dir_setup_ns);
        }
    }

    #[test]
    fn construction_idles_step_and_releases_the_motor() {
        let (step, dir, en) = (FakeOutput::new(), FakeOutput::new(), FakeOutput::new());
        let cfg = StepDirConfig::for_chip(DriverChip::A4988);
        let d = StepDir::with_enable(step.clone(), dir.clone(), en.clone(), cfg).unwrap();
        assert_eq!(step.level(), Some(PinState::Low));
        assert_eq!(
            en.level(),
            Some(PinState::High),
            "active-low enable starts released"
        );
        assert_eq!(
            dir.level(),
            None,
            "DIR is not written until a direction is set"
        );
        assert_eq!(d.timing(), DriverChip::A4988.timing());
        assert_eq!(d.config(), &cfg);
    }

    #[test]
    fn pulses_and_direction_follow_the_configured_levels() {
        let (step, dir) = (FakeOutput::new(), FakeOutput::new());
        let mut d = StepDir::new(
            step.clone(),
            dir.clone(),
            StepDirConfig::new(StepTiming::CONSERVATIVE),
        )
        .unwrap();
        d.set_direction(Direction::Positive).unwrap();
        assert_eq!(dir.level(), Some(PinState::High));
        d.set_direction(Direction::Negative).unwrap();
        assert_eq!(dir.level(), Some(PinState::Low));
        d.step_begin().unwrap();
        assert_eq!(step.level(), Some(PinState::High));
        d.step_end().unwrap();
        assert_eq!(step.level(), Some(PinState::Low));
        assert_eq!(
            step.writes(),
            3,
            "idle at construction, then one write per edge"
        );
        // Without an enable pin, enabling is a no-op that succeeds.
        d.set_enabled(true).unwrap();
    }

    #[test]
    fn every_line_can_be_inverted() {
        let (step, dir, en) = (FakeOutput::new(), FakeOutput::new(), FakeOutput::new());
        let cfg = StepDirConfig::for_chip(DriverChip::Tmc2209)
            .invert_step()
            .invert_dir()
            .invert_enable();
        let mut d = StepDir::with_enable(step.clone(), dir.clone(), en.clone(), cfg).unwrap();
        assert_eq!(
            step.level(),
            Some(PinState::High),
            "inverted STEP idles high"
        );
        assert_eq!(
            en.level(),
            Some(PinState::Low),
            "active-high enable starts low"
        );
        d.step_begin().unwrap();
        assert_eq!(step.level(), Some(PinState::Low));
        d.step_end().unwrap();
        assert_eq!(step.level(), Some(PinState::High));
        d.set_direction(Direction::Positive).unwrap();
        assert_eq!(dir.level(), Some(PinState::Low));
        d.set_enabled(true).unwrap();
        assert_eq!(en.level(), Some(PinState::High));
        d.set_enabled(false).unwrap();
        assert_eq!(en.level(), Some(PinState::Low));
        let (s, _, _) = d.release();
        assert_eq!(s.level(), Some(PinState::High));
    }

    #[test]
    fn pin_errors_are_hardware_faults_naming_the_line() {
        let cfg = StepDirConfig::new(StepTiming::CONSERVATIVE);
        let e = StepDir::new(FailingPin, FakeOutput::new(), cfg).unwrap_err();
        assert_eq!(e.line, StepperLine::Step);
        assert_eq!(e.kind(), ErrorKind::Hardware);

        let mut d = StepDir::new(FakeOutput::new(), FailingPin, cfg).unwrap();
        let e = d.set_direction(Direction::Positive).unwrap_err();
        assert_eq!(e.line, StepperLine::Direction);
        assert_eq!(e.kind(), ErrorKind::Hardware);
        assert_eq!(e.to_string(), format!("stepper DIR pin: {}", e.pin_error));

        let e = StepDir::with_enable(FakeOutput::new(), FakeOutput::new(), FailingPin, cfg)
            .unwrap_err();
        assert_eq!(e.line, StepperLine::Enable);
    }

    #[test]
    fn works_through_a_mutable_reference() {
        fn pulse<S: Stepper>(mut s: S) -> Result<(), S::Error> {
            s.step_begin()?;
            s.step_end()
        }
        let step = FakeOutput::new();
        let mut d = StepDir::new(
            step.clone(),
            FakeOutput::new(),
            StepDirConfig::new(StepTiming::CONSERVATIVE),
        )
        .unwrap();
        pulse(&mut d).unwrap();
        assert_eq!(step.writes(), 3);
    }
}
