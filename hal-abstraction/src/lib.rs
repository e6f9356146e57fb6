//! # Forja hardware traits
//!
//! The motion kernel and the application layer never touch a register. They talk to the machine
//! only through the small traits of this crate, one capability each, shaped like `embedded-hal`
//! 1.0:
//!
//! | module | trait | what it is |
//! |---|---|---|
//! | [`time`] | [`time::Instant`], [`time::Duration`] | the one time type, 32-bit ticks with wrapping comparison |
//! | [`clock`] | [`clock::Clock`], [`clock::Alarm`] | a monotonic tick counter and the one-shot step alarm |
//! | [`stepper`] | [`stepper::Stepper`], [`stepper::StepperEnable`] | one step/direction motor driver |
//! | [`limit`] | [`limit::LimitSwitch`] | one end-stop, polarity already applied |
//! | [`link`] | [`link::LinkStatus`] | whether a host is connected (bytes move over `embedded-io`) |
//! | [`thermal`] | [`thermal::Heater`], [`thermal::TemperatureSensor`] | heater power and temperature reading |
//! | [`pwm`] | [`pwm::PwmOutput`] | fans and spindles (the `embedded-hal` PWM trait) |
//! | [`device`] | [`device::TemperatureControl`], [`device::FanControl`], [`device::SpindleControl`], [`device::CoolantControl`], [`device::DigitalOutput`], [`device::Beeper`] | the machine's devices as the application commands them, with one [`device::DeviceError`] |
//! | [`storage`] | [`storage::RecordStorage`] | power-loss-safe keyed records (over `embedded-storage`) |
//! | [`program`] | [`program::ProgramStore`] | where a program's lines are kept, stored whole or not at all |
//! | [`files`] | [`files::FileStore`] | named files (an SD card, a directory), each stored whole or not at all |
//!
//! ## Contract
//!
//! Every method states three things:
//! - **Context**: `interrupt` (called from the step or another interrupt handler, with a budget of
//!   a few hundred nanoseconds and no blocking of any kind), `thread` (called from a task or the
//!   main loop; may take longer) or `either`.
//! - **Blocking**: whether the call may wait for the hardware.
//! - **Errors**: what an `Err` means and what the caller does with it.
//!
//! Errors implement [`Error`], whose [`Error::kind`] maps any driver error onto the small,
//! `#[non_exhaustive]` [`ErrorKind`]. Drivers whose operations cannot fail (most GPIO) use
//! [`core::convert::Infallible`]. The traits the kernel calls name their driver's error type
//! ([`ErrorType`]); the [`device`] traits, which the application holds as trait objects
//! (`&mut dyn FanControl`), share one error, [`device::DeviceError`], instead. Every trait is
//! implemented for `&mut T` so that a driver can be lent without giving it away.
//!
//! ## Features
//!
//! | feature | adds |
//! |---|---|
//! | `defmt` | `defmt::Format` for the small value types: time, step direction and timing, link state, spindle rotation, errors |
//! | `alloc` | [`link::LinkStatus`] for `Box<T>`, for a board that serves links of several types |
//! | `conformance` | `files::conformance`: the [`files::FileStore`] contract as checks that a store's tests run (`no_std`, allocation-free) |
#![no_std]
#![deny(unsafe_code)]

pub mod clock;
pub mod device;
pub mod files;
pub mod limit;
pub mod link;
pub mod program;
pub mod pwm;
pub mod stepper;
pub mod storage;
pub mod thermal;
pub mod time;

use core::fmt::Debug;

/// The error of a driver, seen through its [`ErrorKind`].
pub trait Error: Debug {
    /// What kind of failure this is, for the caller to react to without knowing the driver.
    fn kind(&self) -> ErrorKind;
}

impl Error for core::convert::Infallible {
    fn kind(&self) -> ErrorKind {
        match *self {}
    }
}

/// Kinds of driver failure.
///
/// The kernel maps these to machine alarms: any error from a motion driver stops motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum ErrorKind {
    /// The peripheral reported a fault (driver over-temperature, bus error, stuck pin).
    Hardware,
    /// A sensor reads outside its physical range: open or shorted wiring.
    SensorFault,
    /// The operation did not complete in time.
    Timeout,
    /// The resource is full (storage) or busy (a transfer already running).
    Full,
    /// Stored data failed its integrity check.
    Corrupt,
    /// An argument outside what the hardware supports.
    OutOfRange,
    /// Anything else; see the driver's own error for detail.
    Other,
}

impl core::fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Hardware => "hardware fault",
            Self::SensorFault => "sensor fault",
            Self::Timeout => "timeout",
            Self::Full => "full",
            Self::Corrupt => "corrupt data",
            Self::OutOfRange => "out of range",
            Self::Other => "driver error",
        })
    }
}

/// Names the error type of a driver.
pub trait ErrorType {
    /// The driver's error.
    type Error: Error;
}

impl<T: ErrorType + ?Sized> ErrorType for &mut T {
    type Error = T::Error;
}
