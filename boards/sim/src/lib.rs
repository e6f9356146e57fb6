//! # Forja's host simulator board
//!
//! The simulator is a Forja board like the STM32F4 and ESP32 ones, whose hardware is a model
//! running on the host: `forja-sim-hal`, to this board what `stm32f4xx-hal` is to the STM32
//! one (virtual steppers, switches, heaters, PWM outputs, clock and alarm, flash and the state
//! file it is kept in, host links, the machine file and the simulation loop). This crate is
//! the wiring: the motion kernel and the controller on that hardware exactly as a firmware
//! board wires them, through the `forja-hal-abstraction` traits, over a clock and an alarm,
//! with the same protocol code on the links, and one controlling host across its ports as
//! `forja_app::hosts` decides. It is the default board when no hardware is attached, and the
//! test bed of everything else.
//!
//! | module | what |
//! |---|---|
//! | [`board`] | [`board::SimBoard`]: the firmware on a `forja_sim_hal::SimMachine`, wired as a firmware board wires it: the kernel's step interrupt on `Firmware::on_alarm` with the `forja-drivers` step/dir driver and limit inputs on the simulated pins, and `forja_app::controller` on `Firmware::poll`, serving the links |
//! | [`board::parts`] | the board's description of its parts (its pin map and its machine), read from the machine file |
//!
//! The `forja-sim` program that runs the board (jobs, `--listen`, the state file) is the
//! `forja-simulator` crate (`simulator/`).
#![deny(unsafe_code)]

pub mod board;
