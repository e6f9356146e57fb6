//! Board bring-up: pins, clocks, the step timer, the host UART, the switches, the stores and
//! the watchdog, from the pin map of [`crate::board`] and the chip support of
//! `forja-port-rp2040`; then the firmware, assembled by the application layer from these
//! parts. The `#[app]` module calls [`init`] and hands the parts to its tasks.

use cortex_m::peripheral::NVIC;
use forja_app::controller::{ControllerConfig, RecordProgramStore};
use forja_app::firmware::{MotionParts, SetupError, assemble_motion};
use forja_app::peripherals::MotorEnables;
use forja_drivers::pin::NoPin;
use forja_drivers::stepper::StepDir;
use forja_port_rp2040::timer::{TICK_HZ, TimerAlarm};
use forja_port_rp2040::uart::HostUart;
use forja_port_rp2040::{flash, limits, watchdog};
use rp2040_hal::clocks::{Clock as _, init_clocks_and_plls};
use rp2040_hal::fugit::RateExtU32;
use rp2040_hal::pac::{self, Interrupt, UART0};
use rp2040_hal::uart::{DataBits, StopBits, UartConfig, UartPeripheral};
use rp2040_hal::{Sio, Timer, Watchdog, gpio};

use crate::board::{self, DRIVERS, HOST_BAUD, HostUartPins};
use crate::machine::{Firmware, PROGRAM_LINES, Queue, StepSide};

/// Everything [`init`] sets up.
pub struct Board {
    /// The step alarm (TIMER alarm 0).
    pub step_alarm: TimerAlarm<0>,
    /// The controller task's wake-up (TIMER alarm 1).
    pub wake_alarm: TimerAlarm<1>,
    /// The host UART with the interrupt ends of its queues.
    pub uart: HostUart<UART0, HostUartPins>,
    /// The step interrupt's part.
    pub step: StepSide,
    /// The thread side, not yet booted.
    pub firmware: Firmware,
    /// The running watchdog.
    pub watchdog: Watchdog,
}

/// Bring the board up from reset, with `queue` as the step queue.
///
/// Context: init (interrupts disabled). Errors: see [`SetupError`].
pub fn init(mut dp: pac::Peripherals, queue: &'static mut Queue) -> Result<Board, SetupError> {
    let sio = Sio::new(dp.SIO);
    let gpio = gpio::Pins::new(dp.IO_BANK0, dp.PADS_BANK0, sio.gpio_bank0, &mut dp.RESETS);
    let pins = board::pins(gpio);

    let mut watchdog = Watchdog::new(dp.WATCHDOG);
    let clocks = init_clocks_and_plls(
        board::XTAL_HZ,
        dp.XOSC,
        dp.CLOCKS,
        dp.PLL_SYS,
        dp.PLL_USB,
        &mut dp.RESETS,
        &mut watchdog,
    )
    .map_err(|_| SetupError::Clocks)?;

    let timer = Timer::new(dp.TIMER, &mut dp.RESETS, &clocks);
    let step_alarm = TimerAlarm::new(&timer);
    let wake_alarm = TimerAlarm::new(&timer);

    let config = UartConfig::new(HOST_BAUD.Hz(), DataBits::Eight, None, StopBits::One);
    let serial = UartPeripheral::new(dp.UART0, pins.uart, &mut dp.RESETS)
        .enable(config, clocks.peripheral_clock.freq())
        .map_err(|_| SetupError::Link)?;
    let (uart, link) = HostUart::start(serial, || NVIC::pend(Interrupt::UART0_IRQ))?;

    let [s0, s1, s2, s3] = pins.step;
    let [d0, d1, d2, d3] = pins.dir;
    let drive = |s, d| StepDir::new(s, d, DRIVERS).map_err(|_| SetupError::Stepper);
    let steppers = [
        drive(s0, d0)?,
        drive(s1, d1)?,
        drive(s2, d2)?,
        drive(s3, d3)?,
    ];
    let [e0, e1, e2, e3] = pins.enable;
    let power = |e| StepDir::with_enable(NoPin, NoPin, e, DRIVERS).map_err(|_| SetupError::Stepper);
    let motors = MotorEnables([power(e0)?, power(e1)?, power(e2)?, power(e3)?]);

    let settings = flash::store(board::SETTINGS_REGION)?;
    let program = RecordProgramStore::open(flash::store(board::PROGRAM_REGION)?, PROGRAM_LINES)
        .map_err(|_| SetupError::Storage)?;
    let (step, firmware) = assemble_motion(MotionParts {
        machine: board::machine(),
        config: ControllerConfig::new("cnc", DRIVERS.timing),
        queue,
        tick_hz: TICK_HZ,
        steppers,
        motors,
        switches: limits::switches(pins.limits, board::LIMIT_POLARITY),
        settings,
        program,
        link,
        // The SKR Pico has no SD card slot.
        files: None,
    })?;
    // The stores are open (opening may repair, erasing sectors): the watchdog may start.
    watchdog::start(&mut watchdog);

    Ok(Board {
        step_alarm,
        wake_alarm,
        uart,
        step,
        firmware,
        watchdog,
    })
}
