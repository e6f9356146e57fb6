//! Board bring-up: pins, clocks, the step timer, the host UART, the switches, the stores and
//! the watchdog, from the pin map of [`crate::board`]. The `#[app]` module calls [`init`] and
//! hands the parts to its tasks.

use forja_drivers::pin::NoPin;
use forja_drivers::stepper::StepDir;
use rp2040_hal::clocks::{Clock as _, init_clocks_and_plls};
use rp2040_hal::fugit::{ExtU32, RateExtU32};
use rp2040_hal::uart::{DataBits, StopBits, UartConfig, UartPeripheral};
use rp2040_hal::{Sio, Timer, Watchdog, gpio, pac};

use crate::board::{self, DRIVERS, HOST_BAUD, Output};
use crate::limits;
use crate::machine::MachineParts;
use crate::storage;
use crate::timer::TimerAlarm;
use crate::uart::{self, HostUart};

/// One motor driver as the step interrupt drives it: STEP and DIR.
pub type Stepper = StepDir<Output, Output>;

/// One motor driver as the thread side powers it: its ENABLE line.
pub type MotorEnable = StepDir<NoPin, NoPin, Output>;

/// Milliseconds without feeding after which the watchdog resets the chip: more than the
/// longest stall made on purpose, a sector erase (at most 400 ms, see [`crate::storage`]).
pub const WATCHDOG_MS: u32 = 1_000;

pub use forja_app::firmware::SetupError;

/// Everything [`init`] sets up.
pub struct Hardware {
    /// The step alarm (TIMER alarm 0).
    pub step_alarm: TimerAlarm<0>,
    /// The controller task's wake-up (TIMER alarm 1).
    pub wake_alarm: TimerAlarm<1>,
    /// The host UART with the interrupt ends of its queues.
    pub uart: HostUart,
    /// The parts of the kernel and the controller.
    pub machine: MachineParts,
    /// The watchdog, not yet started ([`start_watchdog`]).
    pub watchdog: Watchdog,
}

/// Bring the board up from reset.
///
/// Context: init (interrupts disabled). Errors: see [`SetupError`].
pub fn init(mut dp: pac::Peripherals) -> Result<Hardware, SetupError> {
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
    let parts = uart::QUEUES.split().ok_or(SetupError::LinkQueues)?;

    let [s0, s1, s2, s3] = pins.step;
    let [d0, d1, d2, d3] = pins.dir;
    let [e0, e1, e2, e3] = pins.enable;
    let stepper = |s, d| StepDir::new(s, d, DRIVERS).map_err(|_| SetupError::Stepper);
    let enable =
        |e| StepDir::with_enable(NoPin, NoPin, e, DRIVERS).map_err(|_| SetupError::Stepper);

    let (settings, program) = storage::stores()?;

    Ok(Hardware {
        step_alarm,
        wake_alarm,
        uart: HostUart::new(serial, parts.rx_irq, parts.tx_irq),
        machine: MachineParts {
            steppers: [
                stepper(s0, d0)?,
                stepper(s1, d1)?,
                stepper(s2, d2)?,
                stepper(s3, d3)?,
            ],
            enables: [enable(e0)?, enable(e1)?, enable(e2)?, enable(e3)?],
            switches: limits::switches(pins.limits),
            settings,
            program,
            link: uart::link(parts.reader, parts.writer),
        },
        watchdog,
    })
}

/// Start the watchdog with [`WATCHDOG_MS`]; it stops with the core while a debugger halts it.
/// Call it once the stores are open: opening them may repair (erase) sectors.
///
/// Context: init.
pub fn start_watchdog(watchdog: &mut Watchdog) {
    watchdog.pause_on_debug(true);
    watchdog.start(WATCHDOG_MS.millis());
}
