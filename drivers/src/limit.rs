//! Limit switch (end-stop) over an `embedded-hal` input pin, with polarity and debounce.
//!
//! [`LimitInput`] implements [`LimitSwitch`]: it applies the switch's [`Polarity`] and a
//! sample-count debounce, so that `true` always means "at the limit".
//!
//! # Debounce
//!
//! Every call to [`LimitSwitch::is_triggered`] takes one sample. The reported state changes
//! when, and only when, [`LimitConfig::debounce_samples`] consecutive samples disagree with it:
//! with `N` samples, a bounce shorter than `N` polls is ignored, and a real change is reported
//! on the `N`-th poll after it (at the step rate, a few tens of microseconds). `N = 1` reports
//! every sample as it is. A sample that agrees with the reported state resets the count. The
//! filter is integer-only and deterministic: the same samples always give the same answers.
//!
//! # Failure
//!
//! A read error is fail-safe: the switch is reported triggered at once, without waiting for the
//! debounce, and the call returns the error (the kernel treats an error as triggered too, so a
//! caller that ignores the detail still stops). After an error, `N` clean released samples are
//! needed before the switch reads released again.
//!
//! # Execution context
//!
//! Either: the step interrupt polls it during homing and for hard limits. One pin read and a few
//! integer operations, no blocking, no allocation.

use core::fmt;

use embedded_hal::digital::{self, InputPin};
use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::{Error, ErrorKind, ErrorType};

/// Which input level means "triggered".
///
/// Named after the usual wiring: the switch between the input and ground, with a pull-up.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Polarity {
    /// A normally-open switch closes to ground at the limit: triggered when the input is
    /// **low**. Also any sensor whose output is active-low.
    NormallyOpen,
    /// A normally-closed switch opens at the limit, letting the pull-up win: triggered when the
    /// input is **high**. The fail-safe wiring: a cut wire reads as triggered. Also any sensor
    /// whose output is active-high.
    NormallyClosed,
}

/// How a [`LimitInput`] interprets its pin.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct LimitConfig {
    /// Which level means triggered.
    pub polarity: Polarity,
    /// Consecutive disagreeing samples needed to change the reported state; `1` disables the
    /// debounce, `0` is treated as `1`.
    pub debounce_samples: u8,
}

impl LimitConfig {
    /// A switch of `polarity` with a debounce of `debounce_samples` samples.
    pub const fn new(polarity: Polarity, debounce_samples: u8) -> Self {
        Self {
            polarity,
            debounce_samples,
        }
    }
}

/// The input of a [`LimitInput`] could not be read; the switch reads as triggered.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub struct LimitError {
    /// The pin's own error kind.
    pub pin_error: digital::ErrorKind,
}

impl fmt::Display for LimitError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "limit switch input unreadable ({})", self.pin_error)
    }
}

impl Error for LimitError {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Hardware
    }
}

/// A debounced limit switch on one input pin.
#[derive(Debug)]
pub struct LimitInput<P> {
    pin: P,
    config: LimitConfig,
    triggered: bool,
    disagreeing: u8,
}

impl<P: InputPin> LimitInput<P> {
    /// A switch on `pin`. The first sample is taken now and becomes the reported state without
    /// debounce; if it cannot be read, the switch starts triggered.
    ///
    /// Context: thread (board set-up).
    pub fn new(mut pin: P, config: LimitConfig) -> Self {
        let triggered = Self::sample(&mut pin, config.polarity).unwrap_or(true);
        Self {
            pin,
            config,
            triggered,
            disagreeing: 0,
        }
    }

    /// The reported state, without taking a sample.
    pub fn last_state(&self) -> bool {
        self.triggered
    }

    /// The pin, to configure or acknowledge its pin-change interrupt (reads through it take no
    /// sample of the switch).
    pub fn pin_mut(&mut self) -> &mut P {
        &mut self.pin
    }

    /// Give the pin back.
    pub fn release(self) -> P {
        self.pin
    }

    fn sample(pin: &mut P, polarity: Polarity) -> Result<bool, digital::ErrorKind> {
        let high = pin.is_high().map_err(|e| digital::Error::kind(&e))?;
        Ok(match polarity {
            Polarity::NormallyOpen => !high,
            Polarity::NormallyClosed => high,
        })
    }
}

impl<P: InputPin> ErrorType for LimitInput<P> {
    type Error = LimitError;
}

impl<P: InputPin> LimitSwitch for LimitInput<P> {
    fn is_triggered(&mut self) -> Result<bool, Self::Error> {
        match Self::sample(&mut self.pin, self.config.polarity) {
            Err(pin_error) => {
                self.triggered = true;
                self.disagreeing = 0;
                Err(LimitError { pin_error })
            }
            Ok(now) if now == self.triggered => {
                self.disagreeing = 0;
                Ok(self.triggered)
            }
            Ok(now) => {
                self.disagreeing = self.disagreeing.saturating_add(1);
                if self.disagreeing >= self.config.debounce_samples.max(1) {
                    self.triggered = now;
                    self.disagreeing = 0;
                }
                Ok(self.triggered)
            }
        }
    }

    fn is_changing(&self) -> bool {
        self.disagreeing != 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_fakes::{FailingPin, FakeInput, Sample};
    use Sample::{Fault, High, Low};

    fn poll_n<P: InputPin>(s: &mut LimitInput<P>, n: usize) -> Vec<Result<bool, LimitError>> {
        (0..n).map(|_| s.is_triggered()).collect()
    }

    #[test]
    fn polarity_decides_which_level_is_triggered() {
        let cfg = |p| LimitConfig::new(p, 1);
        let mut no = LimitInput::new(FakeInput::at(Low), cfg(Polarity::NormallyOpen));
        assert_eq!(no.is_triggered(), Ok(true));
        let mut no = LimitInput::new(FakeInput::at(High), cfg(Polarity::NormallyOpen));
        assert_eq!(no.is_triggered(), Ok(false));
        let mut nc = LimitInput::new(FakeInput::at(High), cfg(Polarity::NormallyClosed));
        assert_eq!(nc.is_triggered(), Ok(true));
        let mut nc = LimitInput::new(FakeInput::at(Low), cfg(Polarity::NormallyClosed));
        assert_eq!(nc.is_triggered(), Ok(false));
    }

    #[test]
    fn state_changes_on_the_nth_consecutive_sample() {
        let pin = FakeInput::at(High); // NO switch released
        let mut s = LimitInput::new(pin.clone(), LimitConfig::new(Polarity::NormallyOpen, 3));
        assert!(!s.last_state());
        pin.push(&[Low, Low, Low, Low]);
        let got: Vec<bool> = poll_n(&mut s, 4).into_iter().map(Result::unwrap).collect();
        assert_eq!(got, [false, false, true, true]);
        pin.push(&[High, High, High]);
        let got: Vec<bool> = poll_n(&mut s, 3).into_iter().map(Result::unwrap).collect();
        assert_eq!(got, [true, true, false]);
    }

    #[test]
    fn is_changing_while_the_debounce_counts() {
        let pin = FakeInput::at(High);
        let mut s = LimitInput::new(pin.clone(), LimitConfig::new(Polarity::NormallyOpen, 3));
        assert!(!s.is_changing());
        pin.push(&[Low, Low, Low, High]);
        assert_eq!(s.is_triggered(), Ok(false));
        assert!(s.is_changing(), "one disagreeing sample");
        assert_eq!(s.is_triggered(), Ok(false));
        assert!(s.is_changing());
        assert_eq!(s.is_triggered(), Ok(true));
        assert!(!s.is_changing(), "the change is reported");
        assert_eq!(s.is_triggered(), Ok(true));
        assert!(s.is_changing(), "a release starts counting");
    }

    #[test]
    fn bounces_shorter_than_the_window_are_ignored() {
        let pin = FakeInput::at(High);
        let mut s = LimitInput::new(pin.clone(), LimitConfig::new(Polarity::NormallyOpen, 3));
        pin.push(&[Low, Low, High, Low, Low, High, Low, High, High]);
        assert!(poll_n(&mut s, 9).into_iter().all(|r| r == Ok(false)));
    }

    #[test]
    fn zero_or_one_sample_means_no_debounce() {
        for n in [0, 1] {
            let pin = FakeInput::at(High);
            let mut s = LimitInput::new(pin.clone(), LimitConfig::new(Polarity::NormallyOpen, n));
            pin.push(&[Low, High, Low]);
            let got: Vec<bool> = poll_n(&mut s, 3).into_iter().map(Result::unwrap).collect();
            assert_eq!(got, [true, false, true]);
        }
    }

    #[test]
    fn read_errors_trigger_at_once_and_release_only_after_clean_samples() {
        let pin = FakeInput::at(High);
        let mut s = LimitInput::new(pin.clone(), LimitConfig::new(Polarity::NormallyOpen, 2));
        pin.push(&[Fault]);
        let e = s.is_triggered().unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Hardware);
        assert!(s.last_state(), "an unreadable switch is at the limit");
        pin.push(&[High, High, High]);
        let got: Vec<bool> = poll_n(&mut s, 3).into_iter().map(Result::unwrap).collect();
        assert_eq!(got, [true, false, false]);
    }

    #[test]
    fn an_unreadable_switch_starts_triggered() {
        let mut s = LimitInput::new(FailingPin, LimitConfig::new(Polarity::NormallyClosed, 4));
        assert!(s.last_state());
        assert!(s.is_triggered().is_err());
        assert!(s.last_state());
        let _pin: FailingPin = s.release();
    }

    #[test]
    fn same_samples_same_answers() {
        let script = [
            High, Low, Low, High, Low, Low, Low, Fault, High, High, Low, High,
        ];
        let run = || {
            let pin = FakeInput::at(High);
            pin.push(&script);
            let mut s = LimitInput::new(pin, LimitConfig::new(Polarity::NormallyOpen, 2));
            poll_n(&mut s, script.len())
        };
        assert_eq!(run(), run());
    }
}
