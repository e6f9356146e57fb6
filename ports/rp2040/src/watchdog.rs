//! The watchdog: resets the chip when the thread side stops running.

use rp2040_hal::Watchdog;
use rp2040_hal::fugit::ExtU32;

/// Milliseconds without feeding after which the watchdog resets the chip: more than the
/// longest stall made on purpose, a sector erase (at most 400 ms, see [`crate::flash`]).
pub const TIMEOUT_MS: u32 = 1_000;

/// Start `watchdog` with [`TIMEOUT_MS`]; it stops with the core while a debugger halts it.
/// Call it once the stores are open: opening them may repair (erase) sectors. The board feeds
/// it (`Watchdog::feed`) from its controller task.
///
/// Context: init.
pub fn start(watchdog: &mut Watchdog) {
    watchdog.pause_on_debug(true);
    watchdog.start(TIMEOUT_MS.millis());
}
