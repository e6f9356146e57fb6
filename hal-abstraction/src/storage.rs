//! Persistent storage of keyed records (settings, the stored program).
//!
//! Boards implement [`RecordStorage`] over an `embedded-storage` `NorFlash` (see the
//! `forja-drivers` crate); the kernel serialises its records with `postcard`.

use crate::ErrorType;

/// A store of small records by key that survives power loss: after a power cut during
/// [`RecordStorage::write`], a later read returns either the old or the new value, never a mix.
pub trait RecordStorage: ErrorType {
    /// Read the newest value of `key` into `buf`; `Ok(None)` when the key was never written
    /// or was removed, `Ok(Some(len))` with the value in `buf[..len]` otherwise.
    ///
    /// Context: thread. May block (flash reads). Errors: [`crate::ErrorKind::Full`] when `buf`
    /// is too small, [`crate::ErrorKind::Corrupt`] when the stored data fails its check.
    fn read(&mut self, key: u16, buf: &mut [u8]) -> Result<Option<usize>, Self::Error>;

    /// Replace the value of `key`.
    ///
    /// Context: thread. May block for a flash erase (tens of milliseconds): never call it while
    /// the machine moves on a single-bank flash that stalls the core.
    /// Errors: [`crate::ErrorKind::Full`] when the store has no room; the old value is kept.
    fn write(&mut self, key: u16, value: &[u8]) -> Result<(), Self::Error>;

    /// Remove `key`; removing an absent key is not an error.
    ///
    /// Context: thread. May block. Errors: as [`RecordStorage::write`].
    fn remove(&mut self, key: u16) -> Result<(), Self::Error>;
}

impl<T: RecordStorage + ?Sized> RecordStorage for &mut T {
    fn read(&mut self, key: u16, buf: &mut [u8]) -> Result<Option<usize>, Self::Error> {
        T::read(self, key, buf)
    }
    fn write(&mut self, key: u16, value: &[u8]) -> Result<(), Self::Error> {
        T::write(self, key, value)
    }
    fn remove(&mut self, key: u16) -> Result<(), Self::Error> {
        T::remove(self, key)
    }
}
