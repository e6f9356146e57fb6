//! # Kernel bench image, Cortex-M0+
//!
//! The STM32F4 crate's bench program (`boards/stm32f4/examples/kernel_bench/program.rs`),
//! unchanged, built for the RP2040's core (`thumbv6m-none-eabi`) with this crate's release
//! profile: `cargo xtask bench` counts its instructions in the Unicorn emulator as it does the
//! Cortex-M4 image, so that the two cores' figures come from the same program. It runs no
//! peripheral and needs no boot loader under the emulator; the boot loader is linked all the
//! same, so that the image would also start on the board.
#![no_std]
#![no_main]

use cortex_m_rt::entry;
// The vector table of the chip (the PAC's interrupt vectors).
use rp2040_hal as _;

/// The second-stage boot loader (see the firmware's `main.rs`).
#[unsafe(link_section = ".boot2")]
#[unsafe(no_mangle)]
#[used]
pub static BOOT2_FIRMWARE: [u8; 256] = rp2040_boot2::BOOT_LOADER_W25Q080;

/// The bench program.
#[path = "../../stm32f4/examples/kernel_bench/program.rs"]
mod program;

#[entry]
fn main() -> ! {
    // `#[entry]` hands the function's `static mut`s over as `&'static mut`.
    static mut QUEUE_MEM: program::Queue = program::Queue::new();
    program::run(QUEUE_MEM)
}
