//! # Kernel bench image
//!
//! The motion kernel on the Cortex-M4, for instruction counting: `cargo xtask bench` builds
//! this example for `thumbv7em-none-eabihf` with the firmware's release profile and runs it in
//! an instruction-counting emulator (`xtask/scripts/count_insns.py`). The program, its
//! machine, phases and marker functions are chip-independent (`kernel_bench/program.rs`,
//! shared with the RP2040's and the RISC-V bench images); this file is the chip's part: the
//! vector table, the port's memory helpers and the entry point.
#![no_std]
#![no_main]

use cortex_m_rt::entry;
// The vector table of the chip (the PAC's interrupt vectors).
use stm32f4xx_hal as _;

/// The bench program.
#[path = "kernel_bench/program.rs"]
mod program;

/// The port's memory helpers, which the firmware links in place of `compiler-builtins'` (the
/// planner copies lines through them), so that the bench counts the same copies. (The port
/// crate itself brings a panic handler of its own.)
#[path = "../../../ports/stm32f4/src/memory.rs"]
mod memory;

#[entry]
fn main() -> ! {
    // `#[entry]` hands the function's `static mut`s over as `&'static mut`.
    static mut QUEUE_MEM: program::Queue = program::Queue::new();
    program::run(QUEUE_MEM)
}
