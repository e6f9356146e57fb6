//! The firmware's parts on this board, as the application layer takes them
//! (`forja_app::firmware::assemble_motion`, [`crate::hardware::init`]), and their sizes.
//!
//! | firmware part | on the RP2040 |
//! |---|---|
//! | step interrupt | [`StepSide`]: `StepGenerator::on_alarm` over the STEP/DIR drivers and the limit switches |
//! | thread side | [`Firmware`]: the controller on the host UART (the port's `HostLink`) |
//! | peripherals | motor power only: each driver's ENABLE line ([`Motors`]); the heaters and fans are not driven |
//! | storage | the settings store and the program store (`RecordProgramStore`), each on its own flash region (the pin map's) |
//!
//! # Sizes
//!
//! RAM is not scarce (264 KiB): the planner keeps the kernel's default [`PLANNER_BLOCKS`]
//! moves and the step queue [`QUEUE_EVENTS`] events, 20 ms of steps at up to 12 800 events a
//! second, as on the STM32F4.

use forja_app::controller::RecordProgramStore;
use forja_app::firmware::{self, MotionFirmware};
use forja_app::peripherals::MotorEnables;
use forja_drivers::pin::NoPin;
use forja_drivers::stepper::StepDir;
use forja_motion::StepQueue;
use forja_port_rp2040::flash::Store;
use forja_port_rp2040::limits::Limit;
use forja_port_rp2040::uart::HostLink;
use rp2040_hal::gpio::PullUp;

use crate::board::{AXES, LIMITS, Output};

/// Planner blocks of the kernel (its default).
pub const PLANNER_BLOCKS: usize = 32;

/// Events of the step queue (a power of two).
pub const QUEUE_EVENTS: usize = 256;

/// Lines the stored program takes at most: a line is a record of at most 48 bytes, so 200
/// take under half of the program store's seven live sectors.
pub const PROGRAM_LINES: u16 = 200;

/// The step queue between the kernel and the step interrupt.
pub type Queue = StepQueue<AXES, QUEUE_EVENTS>;

/// One motor driver as the step interrupt drives it: STEP and DIR.
pub type Stepper = StepDir<Output, Output>;

/// The motors' power: each driver's ENABLE line, switched together.
pub type Motors = MotorEnables<StepDir<NoPin, NoPin, Output>, AXES>;

/// The step interrupt's part: the step generator, the drivers and the switches.
pub type StepSide = firmware::StepSide<'static, AXES, QUEUE_EVENTS, Stepper, Limit<PullUp>, LIMITS>;

/// The thread side: the firmware on the host link.
pub type Firmware = MotionFirmware<
    'static,
    AXES,
    PLANNER_BLOCKS,
    QUEUE_EVENTS,
    RecordProgramStore<Store>,
    Motors,
    Store,
    HostLink,
>;
