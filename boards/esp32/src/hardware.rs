//! The board's parts: bring-up from the pin map of [`crate::board`] ([`init`]), and the one
//! description of the parts handed to the application layer ([`firmware()`]).
//!
//! | firmware part | on this board |
//! |---|---|
//! | step interrupt | `StepDir` drivers on the STEP/DIR outputs and debounced `LimitInput`s on the switch inputs, in the port's `StepContext` |
//! | peripherals | `Parts`: the shared enable line (released until the controller energises the motors), the switches read again for `M119`, the file store of the SD-card commands; no heater, fan, spindle or coolant |
//! | stores | the `forja` partition: the settings in a `FlashRecordStorage`, the uploaded program in a `SlotProgramStore`, the files in a `FlashFileStore` |
//! | kernel | [`board::MACHINE`] with the stored settings over it, [`PLANNER_BLOCKS`] blocks, a step queue of [`QUEUE_EVENTS`] events |
//! | host link | the WiFi link (`forja_port_esp32::link`) |

use esp_hal::gpio::{Io, Output};
use esp_hal::interrupt::InterruptHandler;
use forja_app::controller::ControllerConfig;
use forja_app::firmware::{self, Firmware, SetupError};
use forja_app::peripherals::{MotorEnables, Parts};
use forja_drivers::pin::NoPin;
use forja_drivers::stepper::StepDir;
use forja_hal_abstraction::clock::Clock;
use forja_motion::StepQueue;
use forja_port_esp32::limits::{self, ThreadLimit};
use forja_port_esp32::link::{LINK, WifiLink};
use forja_port_esp32::step::{StepCell, StepContext, Stepper};
use forja_port_esp32::storage::{self, FileFlash, ProgramFlash, Store, Stores};
use forja_port_esp32::system;
use forja_port_esp32::timer::{StepClock, StepTimer};
use forja_port_esp32::watchdog::Watchdog;
use forja_port_esp32::wifi::{self, Radio};
use static_cell::StaticCell;

use crate::board::{self, AXES, DRIVERS, LIMIT_POLARITY, LIMITS};

/// Events of the step queue between the kernel and the step interrupt (a power of two; 8 KiB,
/// the simulator's size).
pub const QUEUE_EVENTS: usize = 1024;

/// Planner blocks of the kernel (the simulator's).
pub const PLANNER_BLOCKS: usize = 32;

/// The drivers' shared enable line as the controller drives it (`M17`/`M18`, before motion):
/// a driver with no STEP or DIR line, as the simulator's enables.
pub type EnableLine = StepDir<NoPin, NoPin, Output<'static>>;

/// The board's peripherals: motor power, the switches for `M119` and the files.
pub type BoardPeripherals = Parts<'static, MotorEnables<EnableLine, 1>, ThreadLimit, AXES>;

/// The firmware of this board, as the application layer assembles it.
pub type BoardFirmware =
    Firmware<'static, AXES, PLANNER_BLOCKS, QUEUE_EVENTS, ProgramFlash, BoardPeripherals, Store>;

/// The step context of this board.
pub type BoardStep = StepCell<AXES, QUEUE_EVENTS, LIMITS>;

/// Everything [`init`] sets up.
pub struct Hardware {
    /// What the step interrupt owns: the step alarm, the STEP/DIR lines and the limit
    /// switches; no step generator yet.
    pub step: StepContext<AXES, QUEUE_EVENTS, LIMITS>,
    /// The step clock, for any context.
    pub clock: StepClock,
    /// The drivers' enable line (released), for the controller.
    pub enable: EnableLine,
    /// The limit switches as the controller reads them, in axis order.
    pub limits: [ThreadLimit; LIMITS],
    /// The settings, program and file stores.
    pub stores: Stores,
    /// The WiFi driver and its interfaces.
    pub radio: Radio,
    /// The controller's end of the host link.
    pub link: WifiLink,
    /// The running watchdog.
    pub watchdog: Watchdog,
}

/// Bring the board up from reset; `step_interrupt` is bound to the step alarm and
/// `switch_interrupt` to the GPIO interrupt, which the limit switch inputs raise once the step
/// generator is attached.
///
/// Context: the start of `main`, before any task runs. Errors: see [`SetupError`].
pub fn init(
    step_interrupt: InterruptHandler,
    switch_interrupt: InterruptHandler,
) -> Result<Hardware, SetupError> {
    let p = system::init();
    let pins = board::pins!(p);
    let mut watchdog = system::start_rtos(p.TIMG0, p.FROM_CPU_INTR0);

    #[cfg(feature = "esp32")]
    let timer = StepTimer::new(p.TIMG1, step_interrupt);
    #[cfg(not(feature = "esp32"))]
    let timer = StepTimer::new(p.SYSTIMER, step_interrupt);
    let clock = timer.clock();

    // The GPIO interrupt, at `switch_interrupt`'s priority. No pin listens yet.
    Io::new(p.IO_MUX).set_interrupt_handler(switch_interrupt);

    let enable = StepDir::with_enable(NoPin, NoPin, pins.enable, DRIVERS)
        .map_err(|_| SetupError::Stepper)?;
    let mut steppers = pins.step.into_iter().zip(pins.dir);
    let mut stepper = || {
        let (step, dir) = steppers.next().ok_or(SetupError::Stepper)?;
        StepDir::new(step, dir, DRIVERS).map_err(|_| SetupError::Stepper)
    };
    let steppers: [Stepper; AXES] = [stepper()?, stepper()?, stepper()?];

    let thread_limits = pins
        .limits
        .each_ref()
        .map(|pin| limits::thread_side(pin, LIMIT_POLARITY));
    let step_limits = pins
        .limits
        .map(|pin| limits::step_side(pin, LIMIT_POLARITY));

    let stores = storage::open(p.FLASH)?;
    let radio = wifi::radio(p.WIFI)?;

    // Last: from here on the controller task must feed the watchdog.
    watchdog.start();

    Ok(Hardware {
        step: StepContext::new(timer, steppers, step_limits),
        clock,
        enable,
        limits: thread_limits,
        stores,
        radio,
        link: LINK.take().ok_or(SetupError::Link)?,
        watchdog,
    })
}

static QUEUE: StaticCell<StepQueue<AXES, QUEUE_EVENTS>> = StaticCell::new();
static FILES: StaticCell<FileFlash> = StaticCell::new();

/// The board's parts handed to the application layer: the firmware from [`board::MACHINE`]
/// and the stored settings, its step generator attached to `step`, the file store lent to
/// its peripherals for good.
///
/// Context: init, after the step context is installed and its alarm passed the self-test;
/// call once. Errors: [`SetupError::Machine`] when the stored settings make a machine the
/// kernel refuses at this clock rate, [`SetupError::Storage`] when this was called before.
pub fn firmware(
    clock: StepClock,
    stores: Stores,
    enable: EnableLine,
    limits: [ThreadLimit; LIMITS],
    step: &'static BoardStep,
) -> Result<BoardFirmware, SetupError> {
    let queue = QUEUE
        .try_init(StepQueue::new())
        .ok_or(SetupError::Storage)?;
    let files = FILES.try_init(stores.files).ok_or(SetupError::Storage)?;
    let peripherals = BoardPeripherals {
        files: Some(files),
        ..Parts::new(MotorEnables([enable]), limits.map(Some))
    };
    let (generator, firmware, _) = firmware::assemble(firmware::Parts {
        machine: board::MACHINE,
        settings: stores.settings,
        queue,
        tick_hz: clock.tick_hz(),
        config: ControllerConfig::new("cnc", DRIVERS.timing),
        program: stores.program,
        peripherals,
    })
    .map_err(|_| SetupError::Machine)?;
    step.attach(generator);
    Ok(firmware)
}
