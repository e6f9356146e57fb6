//! The settings and program store: a [`FlashRecordStorage`] over two 16 KiB flash sectors,
//! shared by the settings and the uploaded program through two [`StoreHandle`]s ([`stores`]).
//!
//! The board's linker script reserves sectors 1 and 2 (0x0800_4000..0x0800_C000, the symbols
//! `_storage_start` and `_storage_end`) and starts the code after them, so erasing a store page
//! never touches code. `SectorFlash` is the `embedded-storage` `NorFlash` over those two
//! sectors: offsets are relative to the region, the erase page is one 16 KiB sector, words are
//! programmed 32 bits at a time (parallelism x32, for a 2.7–3.6 V supply).
//!
//! `stm32f4xx-hal`'s own `NorFlash` (`flash::UnlockedFlash`) does not fit this use: its erase
//! page is the largest sector (128 KiB) where the store's pages are the 16 KiB sectors, it
//! erases and programs at parallelism x8 (a 16 KiB sector erase takes up to 800 ms instead of
//! 500 ms, near the watchdog's second), it leaves the data cache holding words of an erased
//! sector, and it does not clear the controller's error flags before an operation.
//!
//! # Stalls
//!
//! The F4's flash has one bank: while a sector is erased (typically 250 ms, at most 500 ms per
//! 16 KiB sector at x32, RM0383 Table 27 / DS10314 Table 41) every fetch from flash waits, so
//! every interrupt stalls. The record store is written only while the machine is idle (its
//! contract), and the watchdog allows 1 s.
//!
//! # Sharing
//!
//! The settings (record keys `0x0100…0x02FF`) and the program (`0x1000…`) live in the same
//! region, shared through the drivers' [`StoreSlot`]: both handles belong to the controller's
//! context. The store's one free page is its spare for reclaiming space, so settings and
//! program together must fit in one 16 KiB page: a program line is a record of at most 48
//! bytes (an 8-byte header and the line's 39 bytes, to a whole word), which bounds the lines a
//! board's program store may take (200 on the boards here).
//!
//! # QEMU
//!
//! QEMU 7.2 emulates the flash as read-only memory and not its controller, so the `qemu` build
//! keeps the same two pages in main RAM (`RamFlash`, in `.uninit`; QEMU 7.2 does not map the
//! F405's core-coupled RAM, whose writes fault): settings and programs then last until QEMU
//! exits.

#[cfg(not(feature = "qemu"))]
pub use sector::{FlashError, SectorFlash};

#[cfg(feature = "qemu")]
pub use ram::RamFlash;

use forja_app::firmware::SetupError;
use forja_drivers::shared_store::{SharedStore, StoreSlot};
use forja_drivers::storage::FlashRecordStorage;
use stm32f4xx_hal::pac;

/// Bytes of one erase page: one 16 KiB sector.
pub const PAGE: usize = 16 * 1024;

/// Bytes of the store: two pages.
pub const STORE_LEN: usize = 2 * PAGE;

/// The flash behind the store in this build.
#[cfg(not(feature = "qemu"))]
pub type StoreFlash = SectorFlash;
/// The flash behind the store in this build.
#[cfg(feature = "qemu")]
pub type StoreFlash = RamFlash;

/// The settings and program store.
pub type Store = FlashRecordStorage<StoreFlash>;

/// One user's view of the store (the settings', the program's).
pub type StoreHandle = SharedStore<'static, Store>;

/// The store, parked between the operations of its handles.
static SLOT: StoreSlot<Store> = StoreSlot::new();

/// Open the store over its region and make the handles of its two users: the settings and
/// the program. The `qemu` build keeps the flash controller `flash` untouched.
///
/// Context: init, once. Errors: [`SetupError::StorageLayout`] when the linker script puts the
/// region elsewhere (or, under `qemu`, on a second call); [`SetupError::Storage`] when the
/// store refuses the region.
pub fn stores(flash: pac::FLASH) -> Result<(StoreHandle, StoreHandle), SetupError> {
    #[cfg(not(feature = "qemu"))]
    let flash = SectorFlash::new(flash)?;
    #[cfg(feature = "qemu")]
    let flash = {
        let _ = flash;
        ram::take()?
    };
    let store = Store::new(flash, 0..STORE_LEN as u32).map_err(|_| SetupError::Storage)?;
    Ok(SLOT.share(store))
}

#[cfg(not(feature = "qemu"))]
mod sector {
    use embedded_storage::nor_flash::{ErrorType, NorFlash, NorFlashError, ReadNorFlash};
    use forja_app::firmware::SetupError;
    use stm32f4xx_hal::pac;

    use super::{PAGE, STORE_LEN};

    /// Address of the store in the memory map (sector 1).
    const BASE: usize = 0x0800_4000;
    /// Number of the first sector of the store.
    const FIRST_SECTOR: u8 = 1;

    /// Flash unlock keys (RM0383 §3.5.1).
    const KEY1: u32 = 0x4567_0123;
    const KEY2: u32 = 0xCDEF_89AB;

    /// Error bits of FLASH_SR: PGSERR, PGPERR, PGAERR, WRPERR, OPERR.
    const SR_ERRORS: u32 = (1 << 7) | (1 << 6) | (1 << 5) | (1 << 4) | (1 << 1);

    unsafe extern "C" {
        static _storage_start: u8;
        static _storage_end: u8;
    }

    /// An access outside the region or not aligned to the word or page size, or an error of
    /// the flash controller.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub enum FlashError {
        /// Offset or length not a multiple of the write or erase size.
        NotAligned,
        /// Beyond the end of the region.
        OutOfBounds,
        /// The flash controller reported an error (programming sequence, parallelism,
        /// alignment, write protection); its status bits.
        Controller(u32),
    }

    impl NorFlashError for FlashError {
        fn kind(&self) -> embedded_storage::nor_flash::NorFlashErrorKind {
            use embedded_storage::nor_flash::NorFlashErrorKind as K;
            match self {
                Self::NotAligned => K::NotAligned,
                Self::OutOfBounds => K::OutOfBounds,
                Self::Controller(_) => K::Other,
            }
        }
    }

    /// Check an access of `len` bytes at `offset` against the region and the alignment
    /// `align`.
    fn check(offset: u32, len: usize, align: usize) -> Result<core::ops::Range<usize>, FlashError> {
        let start = offset as usize;
        let end = start.checked_add(len).ok_or(FlashError::OutOfBounds)?;
        if end > STORE_LEN {
            return Err(FlashError::OutOfBounds);
        }
        if !start.is_multiple_of(align) || !len.is_multiple_of(align) {
            return Err(FlashError::NotAligned);
        }
        Ok(start..end)
    }

    /// Sectors 1 and 2 of the internal flash, as a `NorFlash`.
    pub struct SectorFlash {
        flash: pac::FLASH,
    }

    impl SectorFlash {
        /// The store region, checked against the linker script's `_storage_start` and
        /// `_storage_end`.
        ///
        /// Context: init. Errors: [`SetupError::StorageLayout`] when they disagree.
        pub fn new(flash: pac::FLASH) -> Result<Self, SetupError> {
            // Only the addresses of the linker symbols are taken, never their contents.
            let start = core::ptr::addr_of!(_storage_start) as usize;
            let end = core::ptr::addr_of!(_storage_end) as usize;
            if start != BASE || end != BASE + STORE_LEN {
                return Err(SetupError::StorageLayout);
            }
            Ok(Self { flash })
        }

        fn wait_ready(&self) {
            while self.flash.sr().read().bsy().bit_is_set() {}
        }

        /// Run `op` with the controller unlocked and idle; relock and report its errors.
        fn unlocked(&mut self, op: impl FnOnce(&pac::FLASH)) -> Result<(), FlashError> {
            self.wait_ready();
            // SAFETY (register writes): the documented unlock sequence and error clearing.
            self.flash.sr().write(|w| unsafe { w.bits(SR_ERRORS) });
            if self.flash.cr().read().lock().bit_is_set() {
                self.flash.keyr().write(|w| unsafe { w.bits(KEY1) });
                self.flash.keyr().write(|w| unsafe { w.bits(KEY2) });
            }
            op(&self.flash);
            self.wait_ready();
            let errors = self.flash.sr().read().bits() & SR_ERRORS;
            self.flash.sr().write(|w| unsafe { w.bits(SR_ERRORS) });
            // Back to idle: no programming, no erase, locked.
            self.flash.cr().write(|w| unsafe { w.bits(1 << 31) });
            if errors != 0 {
                return Err(FlashError::Controller(errors));
            }
            Ok(())
        }

        /// Reset the data cache, which may hold words of a sector just erased or programmed.
        fn flush_data_cache(&mut self) {
            self.flash.acr().modify(|_, w| w.dcen().clear_bit());
            self.flash.acr().modify(|_, w| w.dcrst().set_bit());
            self.flash.acr().modify(|_, w| w.dcrst().clear_bit());
            self.flash.acr().modify(|_, w| w.dcen().set_bit());
        }
    }

    impl ErrorType for SectorFlash {
        type Error = FlashError;
    }

    impl ReadNorFlash for SectorFlash {
        const READ_SIZE: usize = 1;

        fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
            let range = check(offset, bytes.len(), 1)?;
            // SAFETY: the range lies inside the store region of the memory-mapped flash
            // (checked above), which is always readable and is changed only through
            // `&mut self`.
            let src = unsafe {
                core::slice::from_raw_parts((BASE + range.start) as *const u8, range.len())
            };
            bytes.copy_from_slice(src);
            Ok(())
        }

        fn capacity(&self) -> usize {
            STORE_LEN
        }
    }

    impl NorFlash for SectorFlash {
        const WRITE_SIZE: usize = 4;
        const ERASE_SIZE: usize = PAGE;

        fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
            let range = check(from, to.saturating_sub(from) as usize, PAGE)?;
            for page in range.step_by(PAGE) {
                let sector = FIRST_SECTOR + (page / PAGE) as u8;
                self.unlocked(|flash| {
                    // SAFETY: sector erase of a store sector, x32 parallelism (PSIZE = 0b10).
                    flash.cr().write(|w| unsafe {
                        w.bits((0b10 << 8) | (u32::from(sector) << 3) | (1 << 1))
                    });
                    flash
                        .cr()
                        .modify(|r, w| unsafe { w.bits(r.bits() | (1 << 16)) });
                })?;
            }
            self.flush_data_cache();
            Ok(())
        }

        fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
            let range = check(offset, bytes.len(), 4)?;
            let result = self.unlocked(|flash| {
                // SAFETY: programming mode, x32 parallelism (PG = 1, PSIZE = 0b10).
                flash.cr().write(|w| unsafe { w.bits((0b10 << 8) | 1) });
                for (i, word) in bytes.chunks_exact(4).enumerate() {
                    let value = u32::from_le_bytes([word[0], word[1], word[2], word[3]]);
                    let address = (BASE + range.start + 4 * i) as *mut u32;
                    // SAFETY: an aligned word of the store region, programmed with PG set; the
                    // controller is waited for before the next one.
                    unsafe { core::ptr::write_volatile(address, value) };
                    while flash.sr().read().bsy().bit_is_set() {}
                }
            });
            self.flush_data_cache();
            result
        }
    }
}

#[cfg(feature = "qemu")]
mod ram {
    use core::mem::MaybeUninit;
    use core::sync::atomic::{AtomicBool, Ordering};

    use forja_app::firmware::SetupError;
    use forja_drivers::ram_flash::RamNorFlash;

    use super::{PAGE, STORE_LEN};

    /// The RAM behind the store: main RAM, not initialised at reset.
    #[unsafe(link_section = ".uninit.forja_store")]
    static mut STORE: MaybeUninit<[u8; STORE_LEN]> = MaybeUninit::uninit();

    /// Two 16 KiB "sectors" of RAM that behave like NOR flash: the drivers' in-RAM model over
    /// the RAM region, with the sector flash's geometry: 32-bit words, erased to 0xFF a 16 KiB
    /// page at a time, each written once per erase.
    pub type RamFlash = RamNorFlash<STORE_LEN, 4, PAGE, &'static mut [u8; STORE_LEN]>;

    /// Whether the RAM region was handed out.
    static TAKEN: AtomicBool = AtomicBool::new(false);

    /// The RAM region as a [`RamFlash`], erased.
    ///
    /// Context: init; call once. Errors: [`SetupError::StorageLayout`] on a second call.
    pub fn take() -> Result<RamFlash, SetupError> {
        if TAKEN.swap(true, Ordering::Relaxed) {
            return Err(SetupError::StorageLayout);
        }
        // SAFETY: the flag above lets this run once, so this is the only reference to STORE;
        // every byte is written before the array is read.
        let mem = unsafe {
            let store = &mut *core::ptr::addr_of_mut!(STORE);
            store.as_mut_ptr().write_bytes(0xFF, 1);
            store.assume_init_mut()
        };
        Ok(RamNorFlash::with_memory(mem))
    }
}
