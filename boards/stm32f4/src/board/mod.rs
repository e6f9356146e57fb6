//! Pin maps: the only part of the firmware that differs from one STM32F4 board to another.
//!
//! Each board module names its chip's clock set-up, the host UART and its pins, and the pins of
//! the motor drivers and limit switches, in the same shape:
//!
//! | item | what |
//! |---|---|
//! | `NAME` | the board's name |
//! | `clocks()` | the `rcc::Config` to freeze |
//! | `HostUsart`, `HOST_UART_IRQ`, `HostUartPins` | the UART wired to the host, its interrupt, its pins |
//! | `STEP_TICK_HZ` | the rate of the step clock (the port's `timer` module) |
//! | `LIMIT_POLARITY` | how the limit switch inputs read |
//! | `pins()` | the GPIO ports split into [`Pins`] |
//! | `Card` | the SD card's file store, on its SPI bus (`NoCard` for a board without one) |
//!
//! Exactly one board is compiled in, chosen by a Cargo feature; `build.rs` rejects zero or two.
//! Every pin map drives the same machine before its stored settings: [`machine`].

use forja_drivers::stepper::StepDirConfig;
use forja_hal_abstraction::stepper::StepTiming;
use forja_motion::{AxisConfig, AxisKind, HomeDirection, HomingConfig, MachineConfig};
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

/// The board's GPIO, split and configured, and what hangs on it.
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
    /// The SD card of the SD-card commands, if the board has one ([`Card`]).
    pub card: Option<Card>,
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
    /// SPI1.
    pub spi1: pac::SPI1,
    /// TIM5.
    pub tim5: pac::TIM5,
}

/// Level of the shared enable line that releases every motor (the drivers' ENABLE is active
/// low): the line starts there, before anything else runs.
pub const DRIVERS_RELEASED: stm32f4xx_hal::gpio::PinState = stm32f4xx_hal::gpio::PinState::High;

/// Homing of a linear axis of [`machine`] through limit input `switch`, order `order`.
const fn homing(direction: HomeDirection, switch: u8, order: u8, rates: [f32; 3]) -> HomingConfig {
    let [seek_mm_min, locate_mm_min, pull_off_mm] = rates;
    HomingConfig {
        direction,
        seek_mm_min,
        locate_mm_min,
        pull_off_mm,
        switch,
        order,
    }
}

/// The machine every pin map drives until settings (frame 00) change it: a 300 × 300 mm
/// gantry router with 100 mm of Z and a rotary A, the numbers of the simulator's default
/// machine (`boards/sim-hal/machines/default.toml`), so that a job gives the same positions on
/// both.
///
/// | axis | steps/mm | max rate, mm/min | accel, mm/s² | travel, mm | homes |
/// |---|---|---|---|---|---|
/// | X | 80 (GT2, 20 teeth, 1/16) | 6000 | 500 | 0 – 300 | to min, limit input 0, second |
/// | Y | 80 | 6000 | 500 | 0 – 300 | to min, limit input 1, second |
/// | Z | 400 (T8 screw, 1/16) | 1200 | 200 | 0 – 100 | to max, limit input 2, first |
/// | A | 80 per degree (9:1, 1/16) | 3600 | 720 | unlimited | no |
pub const fn machine() -> MachineConfig<AXES> {
    let x = AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 300.0).with_homing(homing(
        HomeDirection::Min,
        0,
        1,
        [2000.0, 100.0, 2.0],
    ));
    let y = AxisConfig::linear(b'Y', 80.0, 6000.0, 500.0, 300.0).with_homing(homing(
        HomeDirection::Min,
        1,
        1,
        [2000.0, 100.0, 2.0],
    ));
    let z = AxisConfig::linear(b'Z', 400.0, 1200.0, 200.0, 100.0).with_homing(homing(
        HomeDirection::Max,
        2,
        0,
        [600.0, 50.0, 1.0],
    ));
    let mut a = AxisConfig::linear(b'A', 80.0, 3600.0, 720.0, 0.0);
    a.kind = AxisKind::Rotary;
    a.min_mm = -100_000.0;
    a.max_mm = 100_000.0;
    let mut machine = MachineConfig::new([x, y, z, a]);
    machine.queue_lead_ms = QUEUE_LEAD_MS;
    machine
}
