//! The motion kernel and the controller, wired to the board's parts as the simulator board
//! (`boards/sim/src/board.rs`) wires them to its models.
//!
//! | firmware part | on the STM32F4 |
//! |---|---|
//! | step interrupt | [`StepSide::on_alarm`]: `StepGenerator::on_alarm` over the `StepDir` drivers on the STEP/DIR pins and the `LimitInput`s on the limit inputs ([`crate::hardware`]) |
//! | thread side | [`Firmware::poll`]: `forja_app::firmware::Firmware::poll` over the UART ([`HostLink`]); `forja_app::firmware::assemble` builds the kernel and the controller from the parts |
//! | peripherals | `DriverPeripherals` with the shared enable line as each axis's motor power; no heater, fan or spindle output on these pin maps |
//! | storage | the record store ([`crate::storage`]) shared by the settings (`FlashRecordStorage` records) and the uploaded program (`RecordProgramStore`) |
//!
//! The kernel's `MachineConfig` is the pin map's [`board::machine`] with the settings stored
//! in the flash applied over it, as on every board.
//!
//! # Sizes
//!
//! The image must fit an STM32F401 (64 KiB of RAM, `cargo xtask size`). The kernel's planner
//! keeps [`PLANNER_BLOCKS`] moves (about 3.5 KiB) and its step queue [`QUEUE_EVENTS`] events
//! (2 KiB): at the 20 ms `queue_lead_ms` the queue holds the step events of a 20 ms window at
//! up to 12 800 events a second, which is more than a 4-axis move of this machine makes at
//! full rate. The stored program takes at most [`PROGRAM_LINES`] lines (see
//! [`crate::storage`]).

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
use crate::link::HostLink;
use crate::storage::{self, Store, StoreHandle};

/// Planner blocks of the kernel.
pub const PLANNER_BLOCKS: usize = 16;

/// Events of the step queue (a power of two).
pub const QUEUE_EVENTS: usize = 256;

/// Lines the stored program takes at most.
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
    RecordProgramStore<StoreHandle>,
    BoardPeripherals,
    StoreHandle,
>;

/// The step interrupt's part: the step generator, the drivers and the switches.
pub type StepSide = firmware::StepSide<'static, AXES, QUEUE_EVENTS, Stepper, Limit, LIMITS>;

/// The thread side: the firmware on the host link.
pub struct Firmware {
    firmware: BoardFirmware,
    link: HostLink,
}

/// What [`build`] takes: the board's parts for the kernel and the controller.
pub struct MachineParts {
    /// The step queue, for the life of the firmware.
    pub queue: &'static mut Queue,
    /// The step clock's rate.
    pub tick_hz: u32,
    /// The record store.
    pub store: Store,
    /// The motor drivers' STEP/DIR lines.
    pub steppers: [Stepper; AXES],
    /// The motor drivers' enable line.
    pub enables: [MotorEnable; AXES],
    /// The limit switches.
    pub switches: [Limit; LIMITS],
    /// The host link.
    pub link: HostLink,
}

/// Split the kernel over the board's parts: the step interrupt's side and the thread side.
///
/// Context: init. Errors: [`SetupError::Machine`] when the configuration (the board's default
/// with the stored settings) does not suit the step clock; [`SetupError::Storage`] when the
/// stored program cannot be read.
pub fn build(parts: MachineParts) -> Result<(StepSide, Firmware), SetupError> {
    let (settings, program_store) = storage::share(parts.store);
    let program =
        RecordProgramStore::open(program_store, PROGRAM_LINES).map_err(|_| SetupError::Storage)?;
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
        settings,
        queue: parts.queue,
        tick_hz: parts.tick_hz,
        config: ControllerConfig::new("cnc", DRIVERS.timing),
        program,
        peripherals,
    })
    .map_err(|_| SetupError::Machine)?;
    Ok((
        StepSide::new(generator, parts.steppers, parts.switches),
        Firmware {
            firmware,
            link: parts.link,
        },
    ))
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
    /// Context: the controller task, woken by the UART, the limit inputs and the 1 kHz
    /// service tick. Never blocks, except to queue replies on a full transmit queue.
    pub fn poll(&mut self, now: Instant) -> Option<Instant> {
        let news = limits::take_fired() != 0 || self.link.has_input();
        let arm = self.firmware.poll(now, &mut self.link, news);
        crate::link::publish(&self.link, &self.firmware.controller().stats());
        arm
    }
}
