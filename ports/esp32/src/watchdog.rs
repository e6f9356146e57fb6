//! The watchdog: TIMG0's, fed by the controller task, started last at bring-up.

use esp_hal::peripherals::TIMG0;
use esp_hal::time::Duration;
use esp_hal::timer::timg::{MwdtStage, Wdt};

/// Milliseconds without feeding after which the watchdog resets the chip: more than the
/// longest flash erase (see [`crate::storage`]).
pub const WATCHDOG_TIMEOUT_MS: u64 = 2_000;

/// TIMG0's watchdog, from [`crate::system::start_rtos`].
pub struct Watchdog(Wdt<TIMG0<'static>>);

impl Watchdog {
    /// The watchdog of TIMG0, not yet running.
    pub fn new(wdt: Wdt<TIMG0<'static>>) -> Self {
        Self(wdt)
    }

    /// Start it with [`WATCHDOG_TIMEOUT_MS`].
    ///
    /// Context: init, last: from here on the controller task must run at least every
    /// [`WATCHDOG_TIMEOUT_MS`].
    pub fn start(&mut self) {
        self.0.set_timeout(
            MwdtStage::Stage0,
            Duration::from_millis(WATCHDOG_TIMEOUT_MS),
        );
        self.0.enable();
    }

    /// Feed it.
    ///
    /// Context: thread. A few register writes.
    pub fn feed(&mut self) {
        self.0.feed();
    }
}
