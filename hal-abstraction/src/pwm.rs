//! PWM outputs: fans and spindles.
//!
//! This is `embedded-hal`'s own trait, re-exported so that every HAL's PWM channel works as a
//! Forja fan or spindle output with no adapter. Context: thread. Never blocks.

pub use embedded_hal::pwm::{Error, ErrorKind, ErrorType, SetDutyCycle as PwmOutput};
