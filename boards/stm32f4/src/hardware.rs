//! Board bring-up: clocks, pins, the step timer, the host UART, the limit inputs, the store and
//! the watchdog, from the pin map of [`crate::board`] and the chip support of
//! `forja-port-stm32f4`; then the firmware, assembled by the application layer from these
//! parts. The `#[app]` module calls [`init`] and hands the parts to its tasks.

use cortex_m::peripheral::NVIC;
use forja_app::controller::{ControllerConfig, RecordProgramStore};
use forja_app::firmware::{MotionParts, SetupError, assemble_motion};
use forja_app::peripherals::MotorEnables;
use forja_drivers::pin::NoPin;
use forja_drivers::stepper::StepDir;
use forja_hal_abstraction::clock::Clock as _;
use forja_port_stm32f4::flash;
use forja_port_stm32f4::limits::Limits;
use forja_port_stm32f4::timer::{self, StepTimer};
use forja_port_stm32f4::uart::HostUart;
use forja_port_stm32f4::watchdog::Watchdog;
use stm32f4xx_hal::pac;
use stm32f4xx_hal::prelude::*;
use stm32f4xx_hal::serial::{Serial, config::Config as SerialConfig};

use crate::board::{self, DRIVERS, HOST_BAUD, HostUsart, LIMIT_POLARITY};
use crate::machine::{Firmware, PROGRAM_LINES, Queue, StepSide};

/// Everything [`init`] sets up.
pub struct Board {
    /// The step clock and alarm.
    pub timer: StepTimer,
    /// The host UART with the interrupt ends of its queues.
    pub uart: HostUart<HostUsart>,
    /// The EXTI lines of the limit switches, reporting to the step side.
    pub limits: Limits,
    /// The running watchdog.
    pub watchdog: Watchdog,
    /// The step interrupt's part.
    pub step: StepSide,
    /// The thread side, not yet booted.
    pub firmware: Firmware,
}

/// Bring the board up from reset, with `queue` as the step queue.
///
/// Context: init (interrupts disabled). Errors: see [`SetupError`].
pub fn init(
    dp: pac::Peripherals,
    cp: cortex_m::Peripherals,
    queue: &'static mut Queue,
) -> Result<Board, SetupError> {
    let mut rcc = dp.RCC.freeze(board::clocks());
    let mut syscfg = dp.SYSCFG.constrain(&mut rcc);
    let mut exti = dp.EXTI;
    let ports = board::Ports {
        gpioa: dp.GPIOA,
        gpiob: dp.GPIOB,
        gpioc: dp.GPIOC,
        usart1: dp.USART1,
        usart6: dp.USART6,
        spi1: dp.SPI1,
        tim5: dp.TIM5,
    };
    let pins = board::pins(ports, &mut rcc);

    let (usart, uart_pins) = pins.uart;
    let config = SerialConfig::default().baudrate(HOST_BAUD.bps());
    let serial: Serial<HostUsart> =
        Serial::new(usart, uart_pins, config, &mut rcc).map_err(|_| SetupError::Link)?;
    let (uart, link) = HostUart::start(serial, || NVIC::pend(board::HOST_UART_IRQ))?;

    let timer = timer::start(dp.TIM2, cp.SYST, board::STEP_TICK_HZ, &mut rcc)?;

    let [s0, s1, s2, s3] = pins.step;
    let [d0, d1, d2, d3] = pins.dir;
    let drive = |s, d| StepDir::new(s, d, DRIVERS).map_err(|_| SetupError::Stepper);
    let steppers = [
        drive(s0, d0)?,
        drive(s1, d1)?,
        drive(s2, d2)?,
        drive(s3, d3)?,
    ];
    let enable = StepDir::with_enable(NoPin, NoPin, pins.enable, DRIVERS);
    let motors = MotorEnables([enable.map_err(|_| SetupError::Stepper)?]);

    let (mut limits, switches) = Limits::new(pins.limits, LIMIT_POLARITY, &mut syscfg, &mut exti);

    let (settings, program) = flash::stores(dp.FLASH)?;
    let watchdog = Watchdog::start(dp.IWDG, &dp.DBGMCU);
    let program =
        RecordProgramStore::open(program, PROGRAM_LINES).map_err(|_| SetupError::Storage)?;
    let (step, firmware) = assemble_motion(MotionParts {
        machine: board::machine(),
        config: ControllerConfig::new("cnc", DRIVERS.timing),
        queue,
        tick_hz: timer.clock().tick_hz(),
        steppers,
        motors,
        switches,
        settings,
        program,
        link,
        files: pins.card,
    })?;
    limits.attach(step.switch_alert());

    Ok(Board {
        timer,
        uart,
        limits,
        watchdog,
        step,
        firmware,
    })
}
