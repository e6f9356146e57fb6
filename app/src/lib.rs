//! # Forja's application layer
//!
//! Everything between a host link and the motion kernel, once for every board: the
//! [`controller`] (RepRap G-code lines and the 53-byte frames on the same link, their replies,
//! the receive queue and the realtime path), [`job`]s run from a program store, the settings
//! and their records, and the dispatch of G- and M-codes to the machine's [`peripherals`]
//! (heaters, fans, spindle, coolant, motor power, end-stops), with the G-code rules that are the
//! application's, not the drivers' (an `M3` without `S` runs at the last speed, how close to
//! its target a heater must be for `M109` to go on, what is turned off on a stop).
//!
//! ```text
//!  board (wiring)  ──link bytes──►  forja-app: controller ──lines──► forja-motion: kernel
//!                                     │  jobs, settings            (interpreter, planner,
//!                                     ▼                             steps, homing)
//!                               devices (forja_hal_abstraction::device traits,
//!                                        implemented by forja-drivers)
//! ```
//!
//! ## Contract
//!
//! - `no_std`, no allocation, no panics, no clock: every entry point takes the time, and the
//!   link is any `embedded-io` `Read + ReadReady + Write`.
//! - Thread context only (a task or the main loop); nothing here runs in an interrupt. The step
//!   interrupt belongs to the kernel's `StepGenerator`.
//! - What the board provides is reached through traits: the program store
//!   ([`ProgramStore`](forja_hal_abstraction::program::ProgramStore)) and the settings' record
//!   storage from `forja-hal-abstraction`, the devices through [`controller::Peripherals`], the
//!   board's description of which it has (its [`peripherals::Parts`]: each device a trait
//!   object of `forja_hal_abstraction::device`).
//! - Acknowledged means done: a line answered `ok` runs exactly once, a refused line changes
//!   nothing, and the emergency path (`M112`, the frames) never waits behind a queue
//!   (`docs/protocol.md` §7.6 states each guarantee and its limit).
//!
//! ## Modules
//!
//! | module | what |
//! |---|---|
//! | [`controller`] | [`controller::Controller`]: the link, both protocols' replies, jobs, settings and peripherals around the kernel |
//! | [`firmware`] | [`firmware::assemble`]: the firmware built from a board's parts, and its thread side |
//! | [`hosts`] | [`hosts::Arbiter`]: one controlling host across a board's ports (sessions, the busy refusal, the read budget) |
//! | [`session`] | [`session::LinkSession`]: the session rules of a connection-oriented link (one controlling client, refusal of the others, keep-alives, the idle time-out), which the drivers' links ask ([`session::Admission`]) |
//! | [`job`] | the job runner over a program store: start, pause, stop, rewind, progress, checkpoints |
//! | [`peripherals`] | [`peripherals::Parts`]: a board's list of its devices for the controller; [`peripherals::MotorPeripherals`] for a board whose parts are motion alone |
//! | [`wifi`] | the network a WiFi board joins: credentials from the settings, and the watch on them |
//! | [`error`] | the errors of jobs, program stores and file stores, and their wire codes (170–199, 220) |
#![no_std]
#![forbid(unsafe_code)]
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::panic))]

#[cfg(test)]
extern crate std;

mod bytes;
pub mod controller;
pub mod error;
pub mod firmware;
pub mod hosts;
pub mod job;
pub mod peripherals;
pub mod session;
pub mod wifi;
