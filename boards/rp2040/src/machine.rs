//! The firmware over the board's parts, assembled by the application layer
//! (`forja_app::firmware::assemble`) as on every board: the stored settings over
//! [`board::machine`], the kernel split around the step queue, the controller over the program
//! store and the motor power.
//!
//! | firmware part | on the RP2040 |
//! |---|---|
//! | step interrupt | [`StepSide::on_alarm`]: `StepGenerator::on_alarm` over the STEP/DIR drivers and the limit switches |
//! | thread side | [`Firmware::poll`]: `Controller::poll` over the host UART ([`HostLink`]) |
//! | peripherals | `DriverPeripherals` with each driver's ENABLE line as its motor power; the heaters and fans are not driven |
//! | storage | the settings store (`FlashRecordStorage` records) and the program store (`RecordProgramStore`), [`crate::storage`] |
//!
//! # Sizes
//!
//! RAM is not scarce (264 KiB): the planner keeps the kernel's default [`PLANNER_BLOCKS`]
//! moves and the step queue [`QUEUE_EVENTS`] events, 20 ms of steps at up to 12 800 events a
//! second, as on the STM32F4.

use forja_app::controller::{ControllerConfig, RecordProgramStore};
use forja_app::firmware::{self, Parts as FirmwareParts};
use forja_app::peripherals::{
    DriverPeripherals, MotorEnables, NoHeater, NoLimit, NoPwm, NoSpindle, Parts,
};
use forja_hal_abstraction::time::Instant;
use forja_motion::StepQueue;

use crate::board::{self, AXES, DRIVERS, LIMITS};
use crate::hardware::{MotorEnable, SetupError, Stepper};
use crate::limits::{self, Limit};
use crate::storage::Store;
use crate::uart::HostLink;

/// Planner blocks of the kernel (its default).
pub const PLANNER_BLOCKS: usize = 32;

/// Events of the step queue (a power of two).
pub const QUEUE_EVENTS: usize = 256;

/// Lines the stored program takes at most: a line is a record of at most 56 bytes, so 200
/// take under half of the program store's seven live sectors.
pub const PROGRAM_LINES: u16 = 200;

/// The step queue between the kernel and the step interrupt.
pub type Queue = StepQueue<AXES, QUEUE_EVENTS>;

/// The board's peripherals: motor power only.
pub type BoardPeripherals = DriverPeripherals<
    NoHeater,
    NoHeater,
    NoPwm,
    NoSpindle,
    MotorEnables<MotorEnable, AXES>,
    NoLimit,
    AXES,
    0,
>;

/// The board's firmware, as the application layer assembles it.
pub type BoardFirmware = firmware::Firmware<
    'static,
    AXES,
    PLANNER_BLOCKS,
    QUEUE_EVENTS,
    RecordProgramStore<Store>,
    BoardPeripherals,
    Store,
>;

/// The step interrupt's part: the step generator, the drivers and the switches.
pub type StepSide = firmware::StepSide<'static, AXES, QUEUE_EVENTS, Stepper, Limit, LIMITS>;

/// The thread side: the firmware on the host link.
pub struct Firmware {
    firmware: BoardFirmware,
    link: HostLink,
    edges_seen: u32,
}

/// The board's parts for the kernel and the controller, from [`crate::hardware::init`].
pub struct MachineParts {
    /// The motor drivers' STEP and DIR lines, in axis order.
    pub steppers: [Stepper; AXES],
    /// The motor drivers' ENABLE lines, in axis order, released.
    pub enables: [MotorEnable; AXES],
    /// The limit switches, in limit input order.
    pub switches: [Limit; LIMITS],
    /// The settings store.
    pub settings: Store,
    /// The program store.
    pub program: Store,
    /// The host link.
    pub link: HostLink,
}

/// Split the kernel over the board's parts, at the step clock's `tick_hz`: the step
/// interrupt's side and the thread side.
///
/// Context: init. Errors: [`SetupError::Machine`] when the configuration (the board's default
/// with the stored settings) does not suit the step clock; [`SetupError::Storage`] when the
/// stored program cannot be read.
pub fn build(
    queue: &'static mut Queue,
    tick_hz: u32,
    parts: MachineParts,
) -> Result<(StepSide, Firmware), SetupError> {
    let program =
        RecordProgramStore::open(parts.program, PROGRAM_LINES).map_err(|_| SetupError::Storage)?;
    let peripherals = DriverPeripherals::new(Parts {
        hot_end: None,
        bed: None,
        fans: [],
        spindle: None,
        motors: MotorEnables(parts.enables),
        limits: [None; AXES],
        tolerance_mc: 2_000,
    });
    let (generator, firmware, _) = firmware::assemble(FirmwareParts {
        machine: board::machine(),
        settings: parts.settings,
        queue,
        tick_hz,
        config: ControllerConfig::new("cnc", DRIVERS.timing),
        program,
        peripherals,
    })
    .map_err(|_| SetupError::Machine)?;
    let step = StepSide::new(generator, parts.steppers, parts.switches);
    let firmware = Firmware {
        firmware,
        link: parts.link,
        edges_seen: limits::edges(),
    };
    Ok((step, firmware))
}

impl Firmware {
    /// Announce the start (`start`). Call once the host UART is enabled.
    ///
    /// Context: init or the controller task.
    pub fn boot(&mut self) {
        self.firmware.boot(&mut self.link);
    }

    /// Poll the controller at `now` when there is something to do: bytes on the link, a limit
    /// switch that changed, or the instant it asked to be woken at. Returns where to arm the
    /// step alarm.
    ///
    /// Context: the controller task. Never blocks, except to queue replies on a full transmit
    /// queue.
    pub fn poll(&mut self, now: Instant) -> Option<Instant> {
        let edges = limits::edges();
        let news = edges != self.edges_seen || self.link.has_input();
        self.edges_seen = edges;
        self.firmware.poll(now, &mut self.link, news)
    }

    /// The latest instant to poll again at (sooner when there is news); `None` when nothing
    /// is timed.
    pub fn wake_at(&self) -> Option<Instant> {
        self.firmware.wake_at()
    }
}
