//! What happens when the firmware cannot go on: a panic, a hard fault, or a board that fails
//! to set up ([`reset`]). In every case the core resets at once. This crate defines the
//! firmware's panic handler and `HardFault` handler: a board links no other.
//!
//! A reset is the safe state: every GPIO returns to a floating input, so the STEP lines stop
//! and the drivers' ENABLE input is pulled to "released" by the carrier board; heaters and
//! spindles stop the same way. The host sees the link restart with `start`. Nothing is printed:
//! the UART belongs to the protocol. Under QEMU run with `-no-reboot` (as `cargo xtask qemu`
//! does), the reset ends QEMU, which is how a test sees it.

use core::panic::PanicInfo;

use cortex_m::peripheral::SCB;
use cortex_m_rt::{ExceptionFrame, exception};

/// Reset the core now.
pub fn reset() -> ! {
    cortex_m::interrupt::disable();
    SCB::sys_reset()
}

#[panic_handler]
fn panic(_info: &PanicInfo) -> ! {
    reset()
}

#[exception]
unsafe fn HardFault(_frame: &ExceptionFrame) -> ! {
    reset()
}
