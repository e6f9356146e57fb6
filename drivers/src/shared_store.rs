//! One record store shared by two users: the settings and the uploaded program in one flash
//! region, where the chip has only room (or erase pages) for one [`FlashRecordStorage`].
//!
//! The controller keeps the settings and the program each in its own [`RecordStorage`]; their
//! keys do not overlap (settings `0x0100…0x02FF`, program lines `0x1000…`).
//! [`StoreSlot::share`] parks the one store in a `static` slot and gives out a [`SharedStore`]
//! for each user. An operation takes the store out of its slot (a critical section of a few
//! instructions), runs with interrupts enabled, and puts it back: a long operation (a page
//! erase) never holds an interrupt off for longer than the flash itself does.
//!
//! Both handles are meant for one context (the controller's thread), so an operation never
//! finds the slot empty; one that did (a handle used from an interrupt in the middle of the
//! other's operation) fails with [`StorageError::Internal`] and changes nothing.
//!
//! ```
//! use forja_drivers::ram_flash::RamNorFlash;
//! use forja_drivers::shared_store::StoreSlot;
//! use forja_drivers::storage::FlashRecordStorage;
//! use forja_hal_abstraction::storage::RecordStorage;
//!
//! type Store = FlashRecordStorage<RamNorFlash<8192>>;
//! static SLOT: StoreSlot<Store> = StoreSlot::new();
//!
//! let store = Store::new(RamNorFlash::new(), 0..8192).unwrap();
//! let (mut settings, mut program) = SLOT.share(store);
//! settings.write(0x0100, b"80.0").unwrap();
//! program.write(0x1000, b"G1 X10").unwrap();
//! let mut buf = [0; 16];
//! assert_eq!(program.read(0x0100, &mut buf).unwrap(), Some(4));
//! ```
//!
//! Context: init for [`StoreSlot::share`], thread for the handles (they may block as the store
//! does).
//!
//! [`FlashRecordStorage`]: crate::storage::FlashRecordStorage

use core::cell::RefCell;

use critical_section::Mutex;
use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::storage::RecordStorage;

use crate::storage::StorageError;

/// The slot a shared store is parked in between operations: a `static` of the board or port.
pub struct StoreSlot<S> {
    store: Mutex<RefCell<Option<S>>>,
}

impl<S> Default for StoreSlot<S> {
    fn default() -> Self {
        Self::new()
    }
}

impl<S> StoreSlot<S> {
    /// An empty slot.
    pub const fn new() -> Self {
        Self {
            store: Mutex::new(RefCell::new(None)),
        }
    }

    /// Park `store` here and make the handles of its two users (the settings and the
    /// program). A store parked before is replaced (and dropped).
    ///
    /// Context: init.
    pub fn share(&self, store: S) -> (SharedStore<'_, S>, SharedStore<'_, S>) {
        critical_section::with(|cs| self.store.borrow(cs).replace(Some(store)));
        (SharedStore { slot: self }, SharedStore { slot: self })
    }

    fn take(&self) -> Option<S> {
        critical_section::with(|cs| self.store.borrow(cs).take())
    }

    fn put_back(&self, store: S) {
        critical_section::with(|cs| self.store.borrow(cs).replace(Some(store)));
    }
}

/// One user's view of a store parked in a [`StoreSlot`]: a [`RecordStorage`] that runs each
/// operation on the store, taken out of its slot for the time of the operation.
pub struct SharedStore<'a, S> {
    slot: &'a StoreSlot<S>,
}

impl<S> core::fmt::Debug for SharedStore<'_, S> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("SharedStore")
    }
}

impl<S: RecordStorage<Error = StorageError>> SharedStore<'_, S> {
    /// Run `op` on the store, taken out of its slot.
    fn with<R>(
        &mut self,
        op: impl FnOnce(&mut S) -> Result<R, StorageError>,
    ) -> Result<R, StorageError> {
        let mut store = self.slot.take().ok_or(StorageError::Internal)?;
        let result = op(&mut store);
        self.slot.put_back(store);
        result
    }
}

impl<S: RecordStorage<Error = StorageError>> ErrorType for SharedStore<'_, S> {
    type Error = StorageError;
}

impl<S: RecordStorage<Error = StorageError>> RecordStorage for SharedStore<'_, S> {
    fn read(&mut self, key: u16, buf: &mut [u8]) -> Result<Option<usize>, StorageError> {
        self.with(|s| s.read(key, buf))
    }

    fn write(&mut self, key: u16, value: &[u8]) -> Result<(), StorageError> {
        self.with(|s| s.write(key, value))
    }

    fn remove(&mut self, key: u16) -> Result<(), StorageError> {
        self.with(|s| s.remove(key))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ram_flash::RamNorFlash;
    use crate::storage::FlashRecordStorage;

    type Store = FlashRecordStorage<RamNorFlash<8192>>;

    #[test]
    fn both_users_see_one_store() {
        static SLOT: StoreSlot<Store> = StoreSlot::new();
        let (mut settings, mut program) =
            SLOT.share(Store::new(RamNorFlash::new(), 0..8192).unwrap());
        settings.write(0x0100, b"80.0").unwrap();
        program.write(0x1000, b"G1 X10").unwrap();
        let mut buf = [0; 16];
        assert_eq!(settings.read(0x1000, &mut buf).unwrap(), Some(6));
        assert_eq!(&buf[..6], b"G1 X10");
        assert_eq!(program.read(0x0100, &mut buf).unwrap(), Some(4));
        program.remove(0x0100).unwrap();
        assert_eq!(settings.read(0x0100, &mut buf).unwrap(), None);
    }

    /// A store whose reads use the other handle of its own slot, as an interrupt that broke
    /// into an operation would.
    struct Reentrant(&'static StoreSlot<Reentrant>);

    impl ErrorType for Reentrant {
        type Error = StorageError;
    }

    impl RecordStorage for Reentrant {
        fn read(&mut self, key: u16, buf: &mut [u8]) -> Result<Option<usize>, StorageError> {
            SharedStore { slot: self.0 }.read(key, buf)
        }
        fn write(&mut self, _: u16, _: &[u8]) -> Result<(), StorageError> {
            Ok(())
        }
        fn remove(&mut self, _: u16) -> Result<(), StorageError> {
            Ok(())
        }
    }

    #[test]
    fn an_operation_that_finds_the_slot_empty_fails_and_the_store_stays() {
        static SLOT: StoreSlot<Reentrant> = StoreSlot::new();
        let (mut a, mut b) = SLOT.share(Reentrant(&SLOT));
        assert_eq!(a.read(1, &mut [0; 4]), Err(StorageError::Internal));
        // The store went back to its slot: the other handle still reaches it.
        assert_eq!(b.write(1, b"x"), Ok(()));
    }
}
