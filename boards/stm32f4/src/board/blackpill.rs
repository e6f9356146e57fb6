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
//! | SD card SCK / MISO / MOSI (SPI1), CS | PB3 / PB4 / PB5, PA15 | (Spindle Index, –, –, Spindle Pulse) |
//!
//! The SD card (a microSD breakout: 3.3 V, SPI mode) takes the pins grblHAL leaves to the
//! spindle encoder, which Forja does not read; PB3, PB4 and PA15 are JTAG pins after reset
//! and become SPI pins here (SWD on PA13/PA14 stays). SPI1 runs at 400 kHz, the rate every
//! card accepts before and after its initialisation (50 KB/s: far above what a job reads or a
//! 115,200-baud upload writes); TIM5 times the card's waits. The card is initialised and its
//! FAT volume mounted at the first SD-card command, so a board without a card starts as fast
//! and answers those commands with the card's error.
//!
//! Clock: the board's 25 MHz crystal through the PLL to 96 MHz (a multiple of USB's 48 MHz);
//! APB1 runs at 48 MHz, so TIM2 counts at 96 MHz before its prescaler.

use embedded_hal_bus::spi::{ExclusiveDevice, NoDelay};
use forja_drivers::limit::Polarity;
use forja_drivers::sd_card::SdFileStore;
use forja_drivers::sd_card::embedded_sdmmc::SdCard;
use stm32f4xx_hal::gpio::gpioa::{PA9, PA10};
use stm32f4xx_hal::gpio::{ErasedPin, GpioExt, Output, PinState};
use stm32f4xx_hal::hal::spi::MODE_0;
use stm32f4xx_hal::pac::{self, Interrupt};
use stm32f4xx_hal::prelude::_fugit_RateExtU32;
use stm32f4xx_hal::rcc::{self, Rcc};
use stm32f4xx_hal::spi::{Spi, SpiExt};
use stm32f4xx_hal::timer::{DelayUs, TimerExt};

use super::{Pins, Ports};

/// The board's name, as reported to hosts.
pub const NAME: &str = "Black Pill STM32F411CE";

/// The UART wired to the host.
pub type HostUsart = pac::USART1;

/// The host UART's interrupt.
pub const HOST_UART_IRQ: Interrupt = Interrupt::USART1;

/// The host UART's TX and RX pins.
pub type HostUartPins = (PA9, PA10);

/// How far ahead of the steps the kernel prepares them (its `queue_lead_ms`): the kernel's
/// default.
pub const QUEUE_LEAD_MS: u16 = forja_motion::DEFAULT_QUEUE_LEAD_MS;

/// The step clock: TIM2 prescaled to 8 MHz (125 ns resolution, wraps every 537 s).
pub const STEP_TICK_HZ: u32 = 8_000_000;

/// Switches close to ground at the limit, against the input's pull-up.
pub const LIMIT_POLARITY: Polarity = Polarity::NormallyOpen;

/// The SD card: a FAT volume on a card on SPI1, its chip select on PA15, TIM5 for its waits.
pub type Card = SdFileStore<
    SdCard<ExclusiveDevice<Spi<pac::SPI1>, ErasedPin<Output>, NoDelay>, DelayUs<pac::TIM5>>,
>;

/// 25 MHz crystal, PLL to 96 MHz.
pub fn clocks() -> rcc::Config {
    rcc::Config::hse(25.MHz()).sysclk(96.MHz())
}

/// Split the GPIO ports into the board's pins.
pub fn pins(ports: Ports, rcc: &mut Rcc) -> Pins {
    let a = ports.gpioa.split(rcc);
    let b = ports.gpiob.split(rcc);
    let sd_pins = (
        Some(b.pb3.into_alternate()),
        Some(b.pb4.into_alternate()),
        Some(b.pb5.into_alternate()),
    );
    let sd_spi = ports.spi1.spi(sd_pins, MODE_0, 400.kHz(), rcc);
    let sd_cs = a
        .pa15
        .into_push_pull_output_in_state(PinState::High)
        .erase();
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
        card: card(sd_spi, sd_cs, ports.tim5, rcc),
    }
}

/// The SD card on `spi` (pins already in its alternate function), chip select `cs` driven
/// high (released) from the start.
fn card(
    spi: Spi<pac::SPI1>,
    cs: ErasedPin<Output>,
    timer: pac::TIM5,
    rcc: &mut Rcc,
) -> Option<Card> {
    let device = ExclusiveDevice::new_no_delay(spi, cs).ok()?;
    Some(SdFileStore::new(SdCard::new(device, timer.delay_us(rcc))))
}
