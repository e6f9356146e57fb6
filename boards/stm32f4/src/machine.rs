//! The firmware's parts on these boards, as the application layer takes them
//! (`forja_app::firmware::assemble_motion`, [`crate::hardware::init`]), and their sizes.
//!
//! | firmware part | on the STM32F4 |
//! |---|---|
//! | step interrupt | [`StepSide`]: `StepGenerator::on_alarm` over the `StepDir` drivers on the STEP/DIR pins and the `LimitInput`s on the limit inputs |
//! | thread side | [`Firmware`]: the controller on the host UART (the port's `HostLink`) |
//! | peripherals | motor power: the enable line shared by every driver ([`Motors`]); the pin map's SD card ([`Card`]) for the SD-card commands; no heater, fan or spindle output on these pin maps |
//! | storage | the port's record store in flash sectors 1–2, shared by the settings and the uploaded program (`RecordProgramStore`) |
//!
//! The kernel's `MachineConfig` is the pin map's [`crate::board::machine`] with the settings
//! stored in the flash applied over it, as on every board.
//!
//! # Sizes
//!
//! The image must fit an STM32F401 (64 KiB of RAM, `cargo xtask size`). The kernel's planner
//! keeps [`PLANNER_BLOCKS`] moves (about 3.5 KiB) and its step queue [`QUEUE_EVENTS`] events
//! (2 KiB): at the 20 ms `queue_lead_ms` the queue holds the step events of a 20 ms window at
//! up to 12 800 events a second, which is more than a 4-axis move of this machine makes at
//! full rate. The stored program takes at most [`PROGRAM_LINES`] lines: settings and program
//! share one 16 KiB page of the store.

use forja_app::controller::RecordProgramStore;
use forja_app::firmware::{self, MotionFirmware};
use forja_app::peripherals::MotorEnables;
use forja_drivers::pin::NoPin;
use forja_drivers::stepper::StepDir;
use forja_motion::StepQueue;
use forja_port_stm32f4::flash::StoreHandle;
use forja_port_stm32f4::limits::Limit;
use forja_port_stm32f4::uart::HostLink;
use stm32f4xx_hal::gpio::{ErasedPin, Output};

use crate::board::{AXES, Card, LIMITS};

/// Planner blocks of the kernel.
pub const PLANNER_BLOCKS: usize = 16;

/// Events of the step queue (a power of two).
pub const QUEUE_EVENTS: usize = 256;

/// Lines the stored program takes at most.
pub const PROGRAM_LINES: u16 = 200;

/// The step queue between the kernel and the step interrupt.
pub type Queue = StepQueue<AXES, QUEUE_EVENTS>;

/// One motor driver as the step interrupt drives it: STEP and DIR pins.
pub type Stepper = StepDir<ErasedPin<Output>, ErasedPin<Output>>;

/// The motors' power: the one enable line that every driver shares, switched for all of them.
pub type Motors = MotorEnables<StepDir<NoPin, NoPin, ErasedPin<Output>>, 1>;

/// The step interrupt's part: the step generator, the drivers and the switches.
pub type StepSide = firmware::StepSide<'static, AXES, QUEUE_EVENTS, Stepper, Limit, LIMITS>;

/// The thread side: the firmware on the host link.
pub type Firmware = MotionFirmware<
    'static,
    AXES,
    PLANNER_BLOCKS,
    QUEUE_EVENTS,
    RecordProgramStore<StoreHandle>,
    Motors,
    StoreHandle,
    HostLink,
    Card,
>;
