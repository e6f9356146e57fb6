//! Board bring-up: clocks, the heap, esp-rtos, pins, the step timer, the store, the WiFi
//! driver and the watchdog, from the pin map of [`crate::board`]. `main` calls [`init`] and
//! hands the parts to its tasks.

use esp_hal::clock::CpuClock;
use esp_hal::gpio::{Input, Io, Output};
use esp_hal::interrupt::InterruptHandler;
use esp_hal::peripherals::{Peripherals, TIMG0};
use esp_hal::rng::Rng;
use esp_hal::time::Duration;
use esp_hal::timer::timg::{MwdtStage, TimerGroup, Wdt};
use esp_radio::wifi::{ControllerConfig, Interface, WifiController};
use forja_drivers::limit::{LimitConfig, LimitInput};
use forja_drivers::pin::NoPin;
use forja_drivers::stepper::StepDir;

use crate::board::{self, AXES, DRIVERS, LIMIT_POLARITY, LIMITS};
use crate::limits::{self, ThreadLimit};
use crate::link::WifiLink;
use crate::step::StepContext;
use crate::storage::{self, Stores};
use crate::timer::{StepClock, StepTimer};

/// One motor driver as the step interrupt drives it: its STEP and DIR lines.
pub type Stepper = StepDir<Output<'static>, Output<'static>>;

/// The drivers' shared enable line as the controller drives it (`M17`/`M18`, before motion):
/// a driver with no STEP or DIR line, as the simulator's enables.
pub type EnableLine = StepDir<NoPin, NoPin, Output<'static>>;

/// One limit switch as the step interrupt reads it, debounced.
pub type Limit = LimitInput<Input<'static>>;

/// Samples that must agree before a switch changes state.
pub const DEBOUNCE_SAMPLES: u8 = 3;

/// Milliseconds without feeding after which the watchdog resets the chip: more than the
/// longest flash erase (see [`crate::storage`]).
pub const WATCHDOG_TIMEOUT_MS: u64 = 2_000;

/// Heap for the WiFi driver: in the RAM the ROM bootloader used (free once the app runs),
/// and in main RAM.
const HEAP_RECLAIMED: usize = 64 * 1024;
const HEAP_MAIN: usize = 48 * 1024;

pub use forja_app::firmware::SetupError;

/// The watchdog, fed by the controller task.
pub type Watchdog = Wdt<TIMG0<'static>>;

/// Everything [`init`] sets up.
pub struct Hardware {
    /// What the step interrupt owns: the step alarm, the STEP/DIR lines and the limit
    /// switches; no step generator yet.
    pub step: StepContext,
    /// The step clock, for any context.
    pub clock: StepClock,
    /// The drivers' enable line (released), for the controller.
    pub enable: EnableLine,
    /// The limit switches as the controller reads them, in axis order.
    pub limits: [ThreadLimit; LIMITS],
    /// The settings and program stores.
    pub stores: Stores,
    /// The WiFi driver.
    pub wifi: WifiController<'static>,
    /// The station interface.
    pub station: Interface,
    /// The access point interface.
    pub access_point: Interface,
    /// A random seed for the network stacks.
    pub seed: u64,
    /// The controller's end of the host link.
    pub link: WifiLink,
    /// The running watchdog.
    pub watchdog: Watchdog,
}

/// Bring the board up from reset; `step_interrupt` is bound to the step alarm and
/// `switch_interrupt` to the GPIO interrupt, which the limit switch inputs raise once the step
/// generator is attached (see [`crate::limits`]).
///
/// Context: the start of `main`, before any task runs. Errors: see [`SetupError`].
pub fn init(
    step_interrupt: InterruptHandler,
    switch_interrupt: InterruptHandler,
) -> Result<Hardware, SetupError> {
    let p: Peripherals = esp_hal::init(esp_hal::Config::default().with_cpu_clock(CpuClock::max()));

    esp_alloc::heap_allocator!(#[esp_hal::ram(reclaimed)] size: HEAP_RECLAIMED);
    esp_alloc::heap_allocator!(size: HEAP_MAIN);

    let pins = board::pins!(p);

    let timg0 = TimerGroup::new(p.TIMG0);
    esp_rtos::start(timg0.timer0, p.FROM_CPU_INTR0);
    let mut watchdog = timg0.wdt;

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

    let thread_limits = pins.limits.each_ref().map(limits::thread_side);
    let limit_config = LimitConfig::new(LIMIT_POLARITY, DEBOUNCE_SAMPLES);
    let step_limits = pins.limits.map(|pin| LimitInput::new(pin, limit_config));

    let stores = storage::open(p.FLASH)?;

    let wifi =
        WifiController::new(p.WIFI, ControllerConfig::default()).map_err(|_| SetupError::Link)?;
    let station = Interface::station();
    let access_point = Interface::access_point();

    let rng = Rng::new();
    let seed = (u64::from(rng.random()) << 32) | u64::from(rng.random());

    // Last: from here on the controller task must run at least every WATCHDOG_TIMEOUT_MS.
    watchdog.set_timeout(
        MwdtStage::Stage0,
        Duration::from_millis(WATCHDOG_TIMEOUT_MS),
    );
    watchdog.enable();

    Ok(Hardware {
        step: StepContext {
            timer,
            steppers,
            limits: step_limits,
            generator: None,
        },
        clock,
        enable,
        limits: thread_limits,
        stores,
        wifi,
        station,
        access_point,
        seed,
        link: WifiLink::take().ok_or(SetupError::Link)?,
        watchdog,
    })
}
