//! Netduino Plus 2 (STM32F405RG) with an Arduino CNC Shield V3, as QEMU's `netduinoplus2`.
//!
//! The Netduino Plus 2 has Arduino headers; its digital pins map to the STM32 as in
//! MicroPython's `boards/NETDUINO_PLUS_2/pins.csv`. The CNC Shield V3 takes GRBL's Arduino
//! pin-out (GRBL 0.9 `cpu_map`: limits on D9–D11, the A axis on the shield's D12/D13 jumpers).
//! The host link is the Arduino serial pair D0/D1, USART6 on this board.
//!
//! | function | Arduino pin | STM32 pin |
//! |---|---|---|
//! | X / Y / Z step | D2 / D3 / D4 | PA3 / PA2 / PB12 |
//! | X / Y / Z dir | D5 / D6 / D7 | PB8 / PB9 / PA1 |
//! | A step / dir | D12 / D13 | PB14 / PB13 |
//! | drivers enable (active low, shared) | D8 | PA0 |
//! | X / Y / Z limit | D9 / D10 / D11 | PA6 / PB10 / PB15 |
//! | host UART TX / RX (USART6) | D1 / D0 | PC6 / PC7 |
//!
//! # What QEMU 7.2 emulates
//!
//! The CPU, SysTick, NVIC, USARTs, EXTI and SYSCFG; TIM2–5 exist but fire erratically.
//! RCC, GPIO, DMA, the flash controller and the IWDG are not emulated: their registers read 0
//! and ignore writes, and the flash is read-only memory. Hence, in this build only:
//! - the clock stays on HSI without the PLL (waiting for a PLL or HSE to lock would hang);
//! - the step clock is SysTick, which QEMU counts at the 168 MHz its board model declares;
//! - GPIO inputs read low, which is what a normally-closed switch reads at rest, so the limit
//!   inputs use that polarity and never trip;
//! - settings are kept in RAM (the port's `flash` module) and there is no watchdog.
//!
//! The QEMU machine connects its first serial port to USART1 and its sixth to USART6:
//! `cargo xtask qemu stm32f4` puts the host link on the sixth.

use stm32f4xx_hal::gpio::GpioExt;
use stm32f4xx_hal::gpio::gpioc::{PC6, PC7};
use stm32f4xx_hal::pac::{self, Interrupt};
use stm32f4xx_hal::rcc::{self, Rcc};

use super::{Pins, Ports};
use forja_drivers::limit::Polarity;

/// No SD card: the SD-card commands are answered as Marlin without a card answers them (QEMU
/// emulates no card on this machine).
pub type Card = forja_app::peripherals::NoCard;

/// The board's name, as reported to hosts.
pub const NAME: &str = "Netduino Plus 2 (QEMU)";

/// The UART wired to the host.
pub type HostUsart = pac::USART6;

/// The host UART's interrupt.
pub const HOST_UART_IRQ: Interrupt = Interrupt::USART6;

/// The host UART's TX and RX pins.
pub type HostUartPins = (PC6, PC7);

/// How far ahead of the steps the kernel prepares them (its `queue_lead_ms`): 100 ms. QEMU
/// pauses the emulated core now and then for tens of milliseconds of the host's time (code it
/// translates for the first time, the host's scheduling), which SysTick counts all the same; a
/// board's core never pauses, and keeps the kernel's default of 20 ms.
pub const QUEUE_LEAD_MS: u16 = 100;

/// The step clock: SysTick at QEMU's 168 MHz core clock (wraps every 25.6 s).
pub const STEP_TICK_HZ: u32 = 168_000_000;

/// Inputs read low in QEMU: the rest state of a normally-closed switch.
pub const LIMIT_POLARITY: Polarity = Polarity::NormallyClosed;

/// The internal 16 MHz oscillator, no PLL.
pub fn clocks() -> rcc::Config {
    rcc::Config::hsi()
}

/// Split the GPIO ports into the board's pins.
pub fn pins(ports: Ports, rcc: &mut Rcc) -> Pins {
    let a = ports.gpioa.split(rcc);
    let b = ports.gpiob.split(rcc);
    let c = ports.gpioc.split(rcc);
    Pins {
        step: [
            a.pa3.into_push_pull_output().erase(),
            a.pa2.into_push_pull_output().erase(),
            b.pb12.into_push_pull_output().erase(),
            b.pb14.into_push_pull_output().erase(),
        ],
        dir: [
            b.pb8.into_push_pull_output().erase(),
            b.pb9.into_push_pull_output().erase(),
            a.pa1.into_push_pull_output().erase(),
            b.pb13.into_push_pull_output().erase(),
        ],
        enable: a
            .pa0
            .into_push_pull_output_in_state(super::DRIVERS_RELEASED)
            .erase(),
        limits: [
            a.pa6.into_pull_up_input().erase(),
            b.pb10.into_pull_up_input().erase(),
            b.pb15.into_pull_up_input().erase(),
        ],
        uart: (ports.usart6, (c.pc6, c.pc7)),
        card: None,
    }
}
