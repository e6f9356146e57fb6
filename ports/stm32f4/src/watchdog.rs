//! The independent watchdog (IWDG): resets the chip when the thread side stops running.
//!
//! A board feeds it from its lowest-priority periodic work, so that a task that never returns
//! (or an interrupt storm that starves the thread side) resets the board. The timeout,
//! [`TIMEOUT_MS`], covers the longest stall the firmware makes on purpose: a 16 KiB flash
//! sector erase (at most 500 ms, [`crate::flash`]). It stops with the core while a debugger
//! halts it.
//!
//! QEMU 7.2 does not emulate the IWDG (its registers read 0): the `qemu` build has a
//! watchdog that does nothing.

/// Milliseconds without feeding after which the chip resets.
pub const TIMEOUT_MS: u32 = 1_000;

#[cfg(not(feature = "qemu"))]
mod imp {
    use stm32f4xx_hal::pac::{DBGMCU, IWDG};
    use stm32f4xx_hal::prelude::_fugit_ExtU32;
    use stm32f4xx_hal::watchdog::IndependentWatchdog;

    /// The running IWDG.
    pub struct Watchdog(IndependentWatchdog);

    impl Watchdog {
        /// Start the watchdog with [`super::TIMEOUT_MS`]; it stops with the core while a
        /// debugger halts it. Once started it cannot be stopped.
        ///
        /// Context: init.
        pub fn start(iwdg: IWDG, dbgmcu: &DBGMCU) -> Self {
            let mut dog = IndependentWatchdog::new(iwdg);
            dog.stop_on_debug(dbgmcu, true);
            dog.start(super::TIMEOUT_MS.millis());
            Self(dog)
        }

        /// Restart the countdown.
        ///
        /// Context: the board's periodic task. One register write.
        pub fn feed(&mut self) {
            self.0.feed();
        }
    }
}

#[cfg(feature = "qemu")]
mod imp {
    use stm32f4xx_hal::pac::{DBGMCU, IWDG};

    /// No watchdog: QEMU does not emulate one.
    pub struct Watchdog(IWDG);

    impl Watchdog {
        /// Keep the (unemulated) peripheral; nothing runs.
        ///
        /// Context: init.
        pub fn start(iwdg: IWDG, _dbgmcu: &DBGMCU) -> Self {
            Self(iwdg)
        }

        /// Nothing to feed.
        pub fn feed(&mut self) {}
    }
}

pub use imp::Watchdog;
