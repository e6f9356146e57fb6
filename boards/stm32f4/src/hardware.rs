//! Board bring-up: clocks, pins, the step timer, the host UART, the limit inputs, the store and
//! the watchdog, from the pin map of [`crate::board`]. The `#[app]` module calls [`init`] and
//! hands the parts to its tasks.

use forja_drivers::pin::NoPin;
use forja_drivers::stepper::StepDir;
use forja_drivers::uart::{UartReader, UartWriter};
use stm32f4xx_hal::gpio::{ErasedPin, Output};
use stm32f4xx_hal::pac;
use stm32f4xx_hal::prelude::*;
use stm32f4xx_hal::serial::{Serial, config::Config as SerialConfig};

use crate::board::{self, AXES, DRIVERS, HOST_BAUD, LIMITS};
use crate::enable::{self, SharedEnable};
use crate::limits::{Limit, Limits};
use crate::storage::{STORE_LEN, Store, StoreFlash};
use crate::timer::StepTimer;
use crate::uart::{self, HostUart, RX_LEN, TX_LEN};
use crate::watchdog::Watchdog;

/// One motor driver as the step interrupt drives it: STEP and DIR pins.
pub type Stepper = StepDir<ErasedPin<Output>, ErasedPin<Output>>;

/// One motor driver as the thread side powers it: its share of the enable line.
pub type MotorEnable = StepDir<NoPin, NoPin, SharedEnable>;

pub use forja_app::firmware::SetupError;

/// Everything [`init`] sets up.
pub struct Hardware {
    /// The step clock and alarm.
    pub timer: StepTimer,
    /// The host UART with the interrupt ends of its queues.
    pub uart: HostUart,
    /// The controller's end of the receive queue.
    pub reader: UartReader<'static, RX_LEN>,
    /// The controller's end of the transmit queue (kicks the UART interrupt).
    pub writer: UartWriter<'static, TX_LEN>,
    /// The motor drivers' STEP and DIR lines, in axis order.
    pub steppers: [Stepper; AXES],
    /// The motor drivers' enable line, one handle per axis, released.
    pub enables: [MotorEnable; AXES],
    /// The EXTI lines of the limit switches.
    pub limits: Limits,
    /// The limit switches, in limit input order.
    pub switches: [Limit; LIMITS],
    /// The settings and program store.
    pub store: Store,
    /// The running watchdog.
    pub watchdog: Watchdog,
}

/// Bring the board up from reset.
///
/// Context: init (interrupts disabled). Errors: see [`SetupError`].
pub fn init(dp: pac::Peripherals, cp: cortex_m::Peripherals) -> Result<Hardware, SetupError> {
    let mut rcc = dp.RCC.freeze(board::clocks());
    let mut syscfg = dp.SYSCFG.constrain(&mut rcc);
    let mut exti = dp.EXTI;

    let pins = board::pins(
        board::Ports {
            gpioa: dp.GPIOA,
            gpiob: dp.GPIOB,
            gpioc: dp.GPIOC,
            usart1: dp.USART1,
            usart6: dp.USART6,
        },
        &mut rcc,
    );

    let (usart, uart_pins) = pins.uart;
    let serial: Serial<board::HostUsart> = Serial::new(
        usart,
        uart_pins,
        SerialConfig::default().baudrate(HOST_BAUD.bps()),
        &mut rcc,
    )
    .map_err(|_| SetupError::Link)?;
    let parts = uart::QUEUES.split().ok_or(SetupError::LinkQueues)?;
    let uart = HostUart::new(serial, parts.rx_irq, parts.tx_irq);
    let writer = parts.writer.with_kick(uart::kick);

    #[cfg(not(feature = "qemu"))]
    let timer = {
        let _ = cp.SYST;
        StepTimer::new(dp.TIM2, board::STEP_TICK_HZ, &mut rcc)?
    };
    #[cfg(feature = "qemu")]
    let timer = StepTimer::new(cp.SYST, board::STEP_TICK_HZ)?;

    let [e0, e1, e2, e3] = enable::split(pins.enable, DRIVERS.enable_active);
    let [s0, s1, s2, s3] = pins.step;
    let [d0, d1, d2, d3] = pins.dir;
    let steppers = [
        stepper(s0, d0)?,
        stepper(s1, d1)?,
        stepper(s2, d2)?,
        stepper(s3, d3)?,
    ];
    let enables = [
        enable_line(e0)?,
        enable_line(e1)?,
        enable_line(e2)?,
        enable_line(e3)?,
    ];

    let (limits, switches) = Limits::new(pins.limits, &mut syscfg, &mut exti);

    #[cfg(not(feature = "qemu"))]
    let flash = StoreFlash::new(dp.FLASH)?;
    #[cfg(feature = "qemu")]
    let flash = StoreFlash::new()?;
    let store = Store::new(flash, 0..STORE_LEN as u32).map_err(|_| SetupError::Storage)?;

    let watchdog = Watchdog::start(dp.IWDG, &dp.DBGMCU);

    Ok(Hardware {
        timer,
        uart,
        reader: parts.reader,
        writer,
        steppers,
        enables,
        limits,
        switches,
        store,
        watchdog,
    })
}

/// One motor driver's STEP and DIR lines, STEP idle.
fn stepper(step: ErasedPin<Output>, dir: ErasedPin<Output>) -> Result<Stepper, SetupError> {
    StepDir::new(step, dir, DRIVERS).map_err(|_| SetupError::Stepper)
}

/// One motor driver's share of the enable line, released.
fn enable_line(enable: SharedEnable) -> Result<MotorEnable, SetupError> {
    StepDir::with_enable(NoPin, NoPin, enable, DRIVERS).map_err(|_| SetupError::Stepper)
}
