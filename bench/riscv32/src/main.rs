//! # Kernel bench image, RISC-V (the ESP32-C3's core)
//!
//! The STM32F4 crate's bench program (`boards/stm32f4/examples/kernel_bench/program.rs`),
//! unchanged, built for `riscv32imc-unknown-none-elf` (the ESP32-C3's core) with the ESP32
//! firmware's release profile: `cargo xtask bench` counts its instructions in the Unicorn
//! emulator as it does the Cortex-M images, so that the cores' figures come from the same
//! program.
//!
//! No emulator of the ESP32-C3 is at hand, and the program needs none of its peripherals, so
//! the image has no chip HAL and no boot loader: its start-up is the few instructions below
//! (stack pointer, trap vector, `.bss` cleared, then the program), and `link.x` puts the
//! whole image in one RAM region that the counter maps. It would not start on the chip.
#![no_std]
#![no_main]

use core::ptr::addr_of_mut;

// The start-up: the stack at the top of RAM, every trap to `_start_trap` (an exception is a
// failure: the image enables no interrupt), `.bss` cleared, then `start`. The loader has
// written `.data` at its place already (one region: the load address is the run address).
core::arch::global_asm!(
    r#"
    .section .text.start, "ax"
    .globl _start
_start:
    .option push
    .option norelax
    la sp, __stack_top
    .option pop
    la t0, _start_trap
    csrw mtvec, t0
    la t0, __sbss
    la t1, __ebss
1:
    bgeu t0, t1, 2f
    sw zero, 0(t0)
    addi t0, t0, 4
    j 1b
2:
    call start

    .balign 4
    .globl _start_trap
_start_trap:
    j _start_trap
"#
);

/// The bench program.
#[path = "../../../boards/stm32f4/examples/kernel_bench/program.rs"]
mod program;

/// The entry point, called once by the start-up.
#[unsafe(no_mangle)]
extern "C" fn start() -> ! {
    static mut QUEUE_MEM: program::Queue = program::Queue::new();
    // SAFETY: `start` runs once, so this is the only reference to the static.
    let queue = unsafe { &mut *addr_of_mut!(QUEUE_MEM) };
    program::run(queue)
}
