//! Pin maps: the only part of the firmware that differs from one STM32F4 board to another.
//!
//! Each board module names its chip's clock set-up, the host UART and its pins, and the pins of
//! the motor drivers and limit switches, in the same shape:
//!
//! | item | what |
//! |---|---|
//! | `NAME` | the board's name |
//! | `clocks()` | the `rcc::Config` to freeze |
//! | `HostUsart`, `HOST_UART_IRQ`, `HOST_UART_PINS` | the UART wired to the host, its interrupt, its pins |
//! | `STEP_TICK_HZ` | the rate of the step clock (see [`crate::timer`]) |
//! | `LIMIT_POLARITY` | how the limit switch inputs read |
//! | `pins()` | the GPIO ports split into [`Pins`] |
//!
//! Exactly one board is compiled in, chosen by a Cargo feature; `build.rs` rejects zero or two.

use forja_drivers::stepper::StepDirConfig;
use forja_hal_abstraction::stepper::StepTiming;
use stm32f4xx_hal::gpio::{ErasedPin, Input, Output};
use stm32f4xx_hal::pac;

#[cfg(feature = "blackpill")]
mod blackpill;
#[cfg(feature = "blackpill")]
pub use blackpill::*;

#[cfg(feature = "qemu")]
mod netduinoplus2;
#[cfg(feature = "qemu")]
pub use netduinoplus2::*;

/// Motor outputs (step/dir pairs) on every board: X, Y, Z and a fourth (A, or a printer's E).
pub const AXES: usize = 4;

/// Limit switch inputs on every board: X, Y and Z.
pub const LIMITS: usize = 3;

/// Baud rate of the host UART (8N1).
pub const HOST_BAUD: u32 = 115_200;

/// How the motor driver lines are driven: active-high STEP, active-low ENABLE, and a timing
/// that covers the A4988, DRV8825 and TMC2209 sticks of the usual carrier boards.
pub const DRIVERS: StepDirConfig = StepDirConfig::new(StepTiming::CONSERVATIVE);

/// The board's GPIO, split and configured.
pub struct Pins {
    /// STEP output of each motor, in axis order.
    pub step: [ErasedPin<Output>; AXES],
    /// DIR output of each motor, in axis order.
    pub dir: [ErasedPin<Output>; AXES],
    /// The enable line shared by every motor driver (active low).
    pub enable: ErasedPin<Output>,
    /// Limit switch inputs, with pull-ups, in axis order.
    pub limits: [ErasedPin<Input>; LIMITS],
    /// The host UART and its transmit and receive pins.
    pub uart: (HostUsart, HostUartPins),
}

/// The peripherals a pin map chooses from.
pub struct Ports {
    /// GPIO port A.
    pub gpioa: pac::GPIOA,
    /// GPIO port B.
    pub gpiob: pac::GPIOB,
    /// GPIO port C.
    pub gpioc: pac::GPIOC,
    /// USART1.
    pub usart1: pac::USART1,
    /// USART6.
    pub usart6: pac::USART6,
}

/// Level of the shared enable line that releases every motor (the drivers' ENABLE is active
/// low): the line starts there, before anything else runs.
pub const DRIVERS_RELEASED: stm32f4xx_hal::gpio::PinState = stm32f4xx_hal::gpio::PinState::High;
