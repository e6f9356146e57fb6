//! # Forja's chip support for the ESP32 family
//!
//! What every ESP32 board shares, whatever its pins: the step clock and alarm, the step and
//! switch interrupts' bodies, the flash stores in the partition table, the WiFi radio and its
//! host link, the watchdog and the fault path, over esp-hal 1.2 and esp-rtos. A board crate
//! (`boards/esp32`) is wiring on top of it: its pin map, which interrupt runs each body at
//! which priority, its tasks, and the one description of its parts it hands to `forja_app`.
//!
//! ```text
//!  board (wiring): pins, handlers, tasks, Parts ──► forja_app::firmware::assemble
//!       │                                             │ StepGenerator   │ Firmware
//!       ▼                                             ▼                 ▼
//!  this crate: StepCell (step + switch interrupts) · controller::run (thread)
//!              timer · limits · storage · wifi · net · link · system · watchdog · fault
//!       │
//!       ▼
//!  esp-hal, esp-rtos, esp-radio, esp-storage · forja-drivers (tcp, flash stores, StepDir)
//! ```
//!
//! ## Layer and contract
//!
//! - Depends on esp-hal, esp-rtos, esp-radio, esp-storage and Forja's portable crates: the
//!   traits, the drivers (`StepDir`, `LimitInput`, `FlashRecordStorage`, `SlotProgramStore`,
//!   `tcp`), the kernel's `StepGenerator`, and the application's `Firmware`, `SetupError`,
//!   `busy_refusal`, session rules (`forja_app::session::LinkSession`) and WiFi credentials
//!   (`forja_app::wifi`). Knows no board: it chooses no
//!   pin, no priority, and binds no interrupt but the step alarm's, to the handler it is given.
//! - Every constructor runs in init, once; errors are `forja_app::firmware::SetupError`, on
//!   which the board resets ([`fault::reset`]).
//! - Nothing here holds motion or protocol logic: the kernel is `forja_motion`'s, the
//!   controller and the link's session rules `forja_app`'s, the link's queues and admission
//!   `forja_drivers::tcp`'s.
//!
//! | module | provides | context |
//! |---|---|---|
//! | [`system`] | [`system::init`] (clock, heap), [`system::start_rtos`] (the scheduler) | init |
//! | [`watchdog`] | TIMG0's [`Watchdog`](watchdog::Watchdog), 2 s | started last at init; fed by the controller task |
//! | [`fault`] | [`fault::reset`] and the panic handler: reset at once | any |
//! | [`timer`] | [`StepTimer`](timer::StepTimer) (the one-shot step [`Alarm`](forja_hal_abstraction::clock::Alarm)) and [`StepClock`](timer::StepClock) (a lock-free [`Clock`](forja_hal_abstraction::clock::Clock)) | alarm: step interrupt and thread, under the step context's lock; clock: any |
//! | [`step`] | [`StepCell`](step::StepCell): the step context and the step and switch interrupts' bodies, the arming of the alarm, the boot self-test | interrupts: integer-only, allocation-free, panic-free, a few µs |
//! | [`limits`] | the switches' readers for the step interrupt (debounced) and the thread (`M119`), the GPIO interrupt's listening and acknowledgement | init, switch interrupt, thread |
//! | [`storage`] | the settings' record store, the program's slot store and the file store of the SD-card commands in the `forja` partition | thread; flash operations stall every interrupt (see there) |
//! | [`wifi`] | the radio ([`wifi::radio`]) and the connection task ([`wifi::run`]): station, reconnection, fallback access point | a task |
//! | [`net`] | the station and access point IP stacks, the access point's DHCP server | tasks |
//! | [`link`] | the host link on TCP port 2323 (`forja_drivers::tcp`) and the operator's web page on port 80 (`forja_drivers::web`: the page, the link over a WebSocket), their listening tasks' bodies | tasks; the controller's end in the controller task |
//! | [`controller`] | the controller task's body ([`controller::run`]) | a task |
//!
//! ## What a board provides
//!
//! - One chip feature (`esp32c3`, `esp32c6`, `esp32s3`, `esp32`), built for that chip's
//!   target.
//! - Its pins, configured (STEP/DIR outputs, the shared ENABLE line released, switch inputs).
//! - Two handlers: the step interrupt at `Priority::max()`, bound to the step alarm by
//!   [`StepTimer::new`](timer::StepTimer::new), calling
//!   [`StepCell::on_step_interrupt`](step::StepCell::on_step_interrupt); the switch interrupt
//!   at `Priority2` (above esp-radio's and esp-rtos's, below the step interrupt), bound with
//!   esp-hal's `Io::set_interrupt_handler`, calling
//!   [`StepCell::on_switch_interrupt`](step::StepCell::on_switch_interrupt).
//! - The one [`StepCell`](step::StepCell) in a `static`, and the tasks: [`wifi::run`],
//!   [`net::run`] for each stack, [`net::serve_dhcp`], [`link::listen`]
//!   ([`link::LISTENERS`] per stack), [`link::listen_web`] ([`link::WEB_LISTENERS`] per
//!   stack) and [`controller::run`].
//! - A `partitions.csv` with a data partition labelled `forja` ([`storage`]).
#![no_std]

pub mod controller;
pub mod fault;
pub mod limits;
pub mod link;
pub mod net;
pub mod step;
pub mod storage;
pub mod system;
pub mod timer;
pub mod watchdog;
pub mod wifi;
