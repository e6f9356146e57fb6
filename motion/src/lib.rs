//! # Forja's motion kernel
//!
//! The board-agnostic heart of the firmware: parsed G-code lines in, step pulses out. It never
//! names a chip, a HAL or an executor; it reaches hardware only through the traits of
//! `forja-hal-abstraction` (steppers, limit switches) and reads no clock: every entry point
//! takes the current [`Instant`](forja_hal_abstraction::time::Instant).
//!
//! ## Two sides, one queue
//!
//! ```text
//!  thread side (task / main loop)                         interrupt side (step alarm)
//!  ┌───────────────────────────────────────────────┐      ┌──────────────────────────────┐
//!  │ Kernel::execute(&Line) ─► interpreter ─► planner│      │ StepGenerator::on_alarm(now, │
//!  │ Kernel::poll(now) ─► segment preparation ──────┼─────►│   &mut [S; N], &mut [L])     │
//!  │   (float, exact per-axis step times)           │ Step │   → Option<Instant>          │
//!  │ Kernel::{jog, home, hold, resume, stop, reset} │ Queue│ (integer only, no panics)    │
//!  └───────────────────────────────────────────────┘      └──────────────────────────────┘
//! ```
//!
//! [`split`] creates both halves around a [`StepQueue`] that outlives them (a `static`, or a
//! local in tests). The [`Kernel`] lives in a thread context; [`Kernel::poll`] must run again
//! within [`Kernel::poll_within_ms`] while the machine moves (at most half of
//! `queue_lead_ms`, less when fast steps fill the queue first), and again at once while
//! [`Kernel::needs_poll`] (one call prepares a bounded share of steps); it returns the instant
//! to arm the step alarm at when the interrupt side is idle and has work. The
//! [`StepGenerator`] lives in the step interrupt: each alarm, call
//! [`StepGenerator::on_alarm`] and re-arm at what it returns.
//!
//! ## Contract
//!
//! - Floats stay on the thread side. The interrupt side is integer-only, allocation-free and
//!   panic-free; one call ends the pulses that are over and handles at most one event
//!   (direction changes, switch checks, rising edges) in a bounded number of instructions
//!   (see `docs/performance.md`).
//! - Every step is emitted within one tick of its exact time on the planned profile (0.6 tick
//!   by construction; measured in debug builds by `Kernel::worst_step_error_ticks`).
//! - The interrupt samples the limit switches only while one may matter: from the start of a
//!   motion until all are released and settled, during homing, and after the board reports an
//!   input edge through [`SwitchAlert`] (its pin-change interrupt). A board calls
//!   [`SwitchAlert::notify`] on every switch edge.
//! - Every axis steps at its own exact time (rounded to the nearest tick), not on a shared
//!   Bresenham grid; every move emits exactly its integer step count, so there is no drift.
//! - A refused G-code line changes nothing; unsupported commands are named in the error.
//! - The queue uses load/store atomics only (no compare-and-swap, no `unsafe`): it works on
//!   `thumbv7em` and `riscv32imc` alike.
//! - No `unsafe` code but one declaration: on hard-float Arm, single precision's square root
//!   is the FPU's instruction, written in assembly (`fpu.rs`), where `libm` would run a
//!   software routine for the same correctly rounded result.
//!
//! ## Modules
//!
//! | module | what |
//! |---|---|
//! | [`config`] | [`MachineConfig`], [`AxisConfig`], validation, `postcard` storage |
//! | [`coords`] | [`coords::Coordinates`]: the work coordinate systems (`G54`–`G59.3`) and stored positions (`G28.1`, `G30.1`) |
//! | [`effect`] | [`Effect`]: commands for other subsystems, returned in stream order |
//! | [`error`] | the error enums and the table of their wire codes |
//! | [`estimate`] | [`Estimate`]: how long a program takes, by a dry run of the interpreter and planner |
//! | [`preview`] | [`Preview`]: the path a program asks for, as the kernel cuts it into straight pieces (a toolpath plot) |
//! | [`replay`] | [`Replay`]: the modal state a program leaves after some of its lines (a resumed job) |
#![no_std]
#![deny(unsafe_code)]
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::panic))]

#[cfg(test)]
extern crate std;

mod arc;
mod bound;
pub mod config;
pub mod coords;
mod drill;
pub mod effect;
pub mod error;
pub mod estimate;
mod fpu;
mod interp;
mod kernel;
mod planner;
mod prep;
pub mod preview;
mod profile;
mod queue;
pub mod replay;
mod step_clock;
mod stepgen;
#[cfg(test)]
mod testing;
mod trig;
mod whole;

pub use config::{
    AxisConfig, AxisKind, DEFAULT_QUEUE_LEAD_MS, HomeDirection, HomingConfig, MachineConfig,
    SoftLimits,
};
pub use effect::{Effect, Sync};
pub use error::{Alarm, CommandError, ConfigError};
pub use estimate::Estimate;
pub use interp::NM_PER_MM;
pub use kernel::{
    Kernel, MachineState, ModalReport, MotionNow, PlannerSettings, PositionReport, ProbeReport,
    Reply, split,
};
pub use planner::PathLimits;
pub use preview::{Piece, Preview, Travel};
pub use queue::{StepQueue, SwitchAlert};
pub use replay::Replay;
pub use stepgen::StepGenerator;

/// The most axes a machine can have (step masks are 8 bits wide).
pub const MAX_AXES: usize = 8;
