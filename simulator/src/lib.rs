//! # The Forja simulator program
//!
//! `forja-sim` runs the host simulator board (`forja-sim`, `boards/sim/`: the firmware wired
//! to the virtual hardware of `forja-sim-hal`) as a program: it streams a job through the
//! firmware as `forja send` does (in the RepRap dialect, or with `--grbl` in grbl's, as CNC
//! senders stream) and prints the result, or serves hosts on TCP and a pseudo-terminal, with
//! the board's flash kept in a state file across restarts; and it draws a job's toolpath, as
//! the firmware's kernel reads it, with the steps the machine made over it. It is a tool that
//! runs the board, as a flasher or a debugger runs a firmware board: nothing here is part of
//! the firmware.
//!
//! | module | what |
//! |---|---|
//! | [`run`] | [`run::run_job`] streams a job to the board as `forja send` does (or `forja send --grbl`, in the grbl dialect); [`run::listen`] serves hosts on TCP and a pseudo-terminal |
//! | [`host`] | [`host::StreamHost`] and [`host::GrblHost`]: the client's own senders, driven from the simulation loop |
//! | [`job`] | [`Job`]: a G-code file to stream, and the bundled sample |
//! | [`plot`] | a job's toolpath as the kernel reads it ([`plot::Toolpath`]), the path a step trace took ([`plot::Executed`]), drawn to PNG or SVG (`--plot`) |
//! | [`state`] | the board started on the flash of a state file (`--state`), and what the file keeps (`--check --state`) |
//!
//! The `forja-sim` binary (`cargo xtask sim`) is the command line over [`run`] and [`plot`].
#![deny(unsafe_code)]

pub mod host;
pub mod job;
pub mod plot;
pub mod run;
pub mod state;

pub use job::{Job, JobError};
