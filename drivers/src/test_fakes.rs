//! Fake pins and peripherals for the host tests of this crate.

use std::cell::RefCell;
use std::collections::VecDeque;
use std::rc::Rc;

use embedded_hal::digital::{self, InputPin, OutputPin, PinState};

/// The error of [`FailingPin`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PinFault;

impl digital::Error for PinFault {
    fn kind(&self) -> digital::ErrorKind {
        digital::ErrorKind::Other
    }
}

/// A pin whose every read and write fails.
#[derive(Debug, Clone, Copy)]
pub struct FailingPin;

impl digital::ErrorType for FailingPin {
    type Error = PinFault;
}

impl OutputPin for FailingPin {
    fn set_low(&mut self) -> Result<(), PinFault> {
        Err(PinFault)
    }
    fn set_high(&mut self) -> Result<(), PinFault> {
        Err(PinFault)
    }
}

impl InputPin for FailingPin {
    fn is_high(&mut self) -> Result<bool, PinFault> {
        Err(PinFault)
    }
    fn is_low(&mut self) -> Result<bool, PinFault> {
        Err(PinFault)
    }
}

#[derive(Debug, Default)]
struct OutputState {
    level: Option<PinState>,
    writes: usize,
}

/// An output pin that records its level; clones share the record, so a test keeps one clone
/// and hands the other to the driver.
#[derive(Debug, Clone, Default)]
pub struct FakeOutput(Rc<RefCell<OutputState>>);

impl FakeOutput {
    pub fn new() -> Self {
        Self::default()
    }
    /// The last level written, `None` before the first write.
    pub fn level(&self) -> Option<PinState> {
        self.0.borrow().level
    }
    /// How many writes the pin has seen.
    pub fn writes(&self) -> usize {
        self.0.borrow().writes
    }
}

impl digital::ErrorType for FakeOutput {
    type Error = core::convert::Infallible;
}

impl OutputPin for FakeOutput {
    fn set_low(&mut self) -> Result<(), Self::Error> {
        let mut s = self.0.borrow_mut();
        s.level = Some(PinState::Low);
        s.writes += 1;
        Ok(())
    }
    fn set_high(&mut self) -> Result<(), Self::Error> {
        let mut s = self.0.borrow_mut();
        s.level = Some(PinState::High);
        s.writes += 1;
        Ok(())
    }
}

/// One scripted input sample: a level or a read error.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sample {
    Low,
    High,
    Fault,
}

#[derive(Debug, Default)]
struct InputState {
    script: VecDeque<Sample>,
    last: Option<Sample>,
}

/// An input pin that plays a script of samples, then repeats the last one forever.
#[derive(Debug, Clone, Default)]
pub struct FakeInput(Rc<RefCell<InputState>>);

impl FakeInput {
    /// A pin that reads `level` until told otherwise.
    pub fn at(level: Sample) -> Self {
        let p = Self::default();
        p.0.borrow_mut().last = Some(level);
        p
    }
    /// Queue samples to be read, one per read.
    pub fn push(&self, samples: &[Sample]) {
        self.0.borrow_mut().script.extend(samples.iter().copied());
    }
    fn next(&self) -> Sample {
        let mut s = self.0.borrow_mut();
        if let Some(x) = s.script.pop_front() {
            s.last = Some(x);
        }
        s.last.unwrap_or(Sample::Low)
    }
}

impl digital::ErrorType for FakeInput {
    type Error = PinFault;
}

impl InputPin for FakeInput {
    fn is_high(&mut self) -> Result<bool, PinFault> {
        match self.next() {
            Sample::High => Ok(true),
            Sample::Low => Ok(false),
            Sample::Fault => Err(PinFault),
        }
    }
    fn is_low(&mut self) -> Result<bool, PinFault> {
        self.is_high().map(|h| !h)
    }
}
