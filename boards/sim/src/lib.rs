//! # Forja's host simulator board
//!
//! The simulator is a Forja board like the STM32F4 and ESP32 ones, whose hardware is a model
//! running on the host: `forja-sim-hal`, to this board what `stm32f4xx-hal` is to the STM32
//! one (virtual steppers, switches, heaters, PWM outputs, clock and alarm, flash, host links,
//! the machine file and the simulation loop). This crate is the wiring: the motion kernel and
//! the controller on that hardware exactly as a firmware board wires them, through the
//! `forja-hal-abstraction` traits, over a clock and an alarm, with the same protocol code on
//! the links. It is the default board when no hardware is attached, and the test bed of
//! everything else.
//!
//! | module | what |
//! |---|---|
//! | [`board`] | [`board::SimBoard`]: the firmware on a `forja_sim_hal::SimMachine`, wired as a firmware board wires it: the kernel's step interrupt on `Firmware::on_alarm` with the `forja-drivers` step/dir driver and limit inputs on the simulated pins, and `forja_app::controller` on `Firmware::poll`, serving the links |
//! | [`state`] | the board's two flashes laid out in one state file (`--state`), so that settings and the uploaded program survive a restart |
//! | [`run`] | [`run::run_job`] streams a job to the board as `forja send` does; [`run::listen`] serves hosts on TCP and a pseudo-terminal |
//! | [`host`] | [`host::StreamHost`]: the client's own streamer, driven from the simulation loop |
//! | [`job`] | [`Job`]: a G-code file to stream, and the bundled sample |
//!
//! The `forja-sim` binary (`cargo xtask sim`) is the command line over [`run`].
#![deny(unsafe_code)]

pub mod board;
pub mod host;
pub mod job;
pub mod run;
pub mod state;

pub use job::{Job, JobError};
