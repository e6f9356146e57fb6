//! What happens when the firmware cannot go on: a panic, a CPU exception (esp-hal turns those
//! into a panic), or a board that fails to set up ([`reset`]). In every case the chip resets
//! at once. This crate defines the firmware's panic handler: a board links no other.
//!
//! A reset is the safe state: every GPIO returns to an input, so the STEP lines stop and the
//! drivers' ENABLE input is pulled to "released" by the carrier board. The host sees the TCP
//! connection drop and, after the reconnection, the link greet it again with 54. Nothing is
//! printed: the link belongs to the protocol.

use core::panic::PanicInfo;

/// Reset the chip now.
pub fn reset() -> ! {
    esp_hal::system::software_reset()
}

#[panic_handler]
fn panic(_info: &PanicInfo) -> ! {
    reset()
}
