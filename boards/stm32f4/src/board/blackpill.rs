//! WeAct "Black Pill" V2/V3 with an STM32F411CE, wired as grblHAL's Black Pill breakout.
//!
//! The motor and switch pins follow grblHAL's `boards/blackpill_map.h` (STM32F4xx driver),
//! so that the breakout boards made for it work unchanged. The host link is USART1 on
//! PA9/PA10, the pins that map gives to a fifth motor, which Forja leaves unused; connect a
//! 3.3 V USB-UART adapter there (the on-board USB connector is not used).
//!
//! | function | pin | grblHAL name |
//! |---|---|---|
//! | X step / dir | PA0 / PA1 | X Step, X Direction |
//! | Y step / dir | PA2 / PA3 | Y Step, Y Direction |
//! | Z step / dir | PA4 / PA5 | Z Step, Z Direction |
//! | A step / dir | PA6 / PA7 | M3 Step, M3 Direction |
//! | drivers enable (active low, shared) | PB0 | Steppers enable |
//! | X / Y / Z limit (to ground, pull-up) | PB12 / PB13 / PB14 | X, Y, Z Limit |
//! | host UART TX / RX (USART1) | PA9 / PA10 | (M4 Step / Direction) |
//!
//! Clock: the board's 25 MHz crystal through the PLL to 96 MHz (a multiple of USB's 48 MHz);
//! APB1 runs at 48 MHz, so TIM2 counts at 96 MHz before its prescaler.

use stm32f4xx_hal::gpio::GpioExt;
use stm32f4xx_hal::gpio::gpioa::{PA9, PA10};
use stm32f4xx_hal::pac::{self, Interrupt};
use stm32f4xx_hal::prelude::_fugit_RateExtU32;
use stm32f4xx_hal::rcc::{self, Rcc};

use super::{Pins, Ports};
use forja_drivers::limit::Polarity;

/// The board's name, as reported to hosts.
pub const NAME: &str = "Black Pill STM32F411CE";

/// The UART wired to the host.
pub type HostUsart = pac::USART1;

/// The host UART's interrupt.
pub const HOST_UART_IRQ: Interrupt = Interrupt::USART1;

/// The host UART's TX and RX pins.
pub type HostUartPins = (PA9, PA10);

/// The step clock: TIM2 prescaled to 8 MHz (125 ns resolution, wraps every 537 s).
pub const STEP_TICK_HZ: u32 = 8_000_000;

/// Switches close to ground at the limit, against the input's pull-up.
pub const LIMIT_POLARITY: Polarity = Polarity::NormallyOpen;

/// 25 MHz crystal, PLL to 96 MHz.
pub fn clocks() -> rcc::Config {
    rcc::Config::hse(25.MHz()).sysclk(96.MHz())
}

/// Split the GPIO ports into the board's pins.
pub fn pins(ports: Ports, rcc: &mut Rcc) -> Pins {
    let a = ports.gpioa.split(rcc);
    let b = ports.gpiob.split(rcc);
    Pins {
        step: [
            a.pa0.into_push_pull_output().erase(),
            a.pa2.into_push_pull_output().erase(),
            a.pa4.into_push_pull_output().erase(),
            a.pa6.into_push_pull_output().erase(),
        ],
        dir: [
            a.pa1.into_push_pull_output().erase(),
            a.pa3.into_push_pull_output().erase(),
            a.pa5.into_push_pull_output().erase(),
            a.pa7.into_push_pull_output().erase(),
        ],
        enable: b
            .pb0
            .into_push_pull_output_in_state(super::DRIVERS_RELEASED)
            .erase(),
        limits: [
            b.pb12.into_pull_up_input().erase(),
            b.pb13.into_pull_up_input().erase(),
            b.pb14.into_pull_up_input().erase(),
        ],
        uart: (ports.usart1, (a.pa9, a.pa10)),
    }
}
