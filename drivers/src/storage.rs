//! Settings and stored programs: power-loss-safe keyed records on NOR flash.
//!
//! [`FlashRecordStorage`] implements [`RecordStorage`] over any `embedded-storage`
//! [`NorFlash`] (a region of the MCU's internal flash, an external SPI NOR) with the
//! `sequential-storage` crate's map. [`Records`] adds typed `save`/`load` on top of any
//! [`RecordStorage`], encoding values with `postcard`.
//!
//! # Power loss
//!
//! Records are appended, never rewritten in place: each carries a CRC over its header and its
//! data, and a record that was being written when the power went fails its check and is
//! ignored, so a read returns the previous value. Pages are erased only after their live
//! records were copied forward, and an interrupted erase or copy is repaired on the next
//! operation. The tests cut the power after every single byte of a write, including writes
//! that move records between pages, and check that the key then reads as its old or its new
//! value, never as an error or a mix.
//!
//! Removal writes a tombstone record (an empty marker) rather than erasing, so plain
//! write-once NOR flash suffices.
//!
//! # Sizes
//!
//! `BUF` bytes on the stack of each operation hold one record while it is written or read: the
//! 2-byte key, a 1-byte marker and the value, rounded up to the flash's word size.
//! [`FlashRecordStorage::max_value_len`] is the largest value; a record must also fit in one
//! erase page with its header. The region needs at least two pages: one is always kept erased
//! for copying live records forward.
//!
//! # Execution context
//!
//! Thread. Reads block for flash reads; writes may block for a page erase (tens of
//! milliseconds on internal flash, during which a single-bank part stalls the core): never
//! write while the machine moves.

use core::fmt;
use core::future::Future;
use core::ops::Range;
use core::pin::pin;
use core::task::{Context, Poll, Waker};

use embedded_storage::nor_flash::{NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash};
use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::{Error, ErrorKind, ErrorType};
use sequential_storage::cache::{Cache, Uncached};
use sequential_storage::map::{MapConfig, MapStorage};
use serde::Serialize;
use serde::de::DeserializeOwned;

/// Largest encoded value handled by [`Records::save`] and [`Records::load`], which encode on
/// the stack.
pub const MAX_RECORD_LEN: usize = 256;

/// Record overhead in the data buffer: the `u16` key and the present/removed marker.
const KEY_AND_MARKER: usize = 3;

/// Run a future to completion on the spot. The futures of `sequential-storage` only wait for
/// the flash, and the flash here is blocking ([`Blocking`]), so they complete in one poll; the
/// loop is a formality that keeps this correct whatever they do.
fn block_on<F: Future>(future: F) -> F::Output {
    let mut future = pin!(future);
    let mut cx = Context::from_waker(Waker::noop());
    loop {
        if let Poll::Ready(output) = future.as_mut().poll(&mut cx) {
            return output;
        }
        core::hint::spin_loop();
    }
}

/// A blocking `NorFlash` seen through the async traits that `sequential-storage` takes.
struct Blocking<F>(F);

impl<F: embedded_storage::nor_flash::ErrorType> embedded_storage::nor_flash::ErrorType
    for Blocking<F>
{
    type Error = F::Error;
}

impl<F: ReadNorFlash> embedded_storage_async::nor_flash::ReadNorFlash for Blocking<F> {
    const READ_SIZE: usize = F::READ_SIZE;

    async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.0.read(offset, bytes)
    }

    fn capacity(&self) -> usize {
        self.0.capacity()
    }
}

impl<F: NorFlash> embedded_storage_async::nor_flash::NorFlash for Blocking<F> {
    const WRITE_SIZE: usize = F::WRITE_SIZE;
    const ERASE_SIZE: usize = F::ERASE_SIZE;

    async fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        self.0.erase(from, to)
    }

    async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.0.write(offset, bytes)
    }
}

/// A storage operation failed. The codes go on the wire and are stable.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum StorageError {
    /// The flash reported an error. Code 230.
    Flash(NorFlashErrorKind),
    /// No room left, even after reclaiming space; the old value is kept. Code 231.
    Full,
    /// The stored data is damaged beyond the automatic repair. Code 232.
    Corrupt,
    /// The value is larger than [`FlashRecordStorage::max_value_len`] or than a page. Code 233.
    TooLarge,
    /// The caller's buffer cannot hold the value, of `needed` bytes. Code 234.
    BufferTooSmall {
        /// The length of the stored value.
        needed: usize,
    },
    /// The flash region is not a whole number of erase pages, has fewer than two, or lies
    /// outside the device. Code 235.
    BadRegion,
    /// An internal inconsistency of the storage layer. Code 236.
    Internal,
}

impl StorageError {
    /// The stable wire code, in 230..=239.
    pub const fn code(&self) -> u16 {
        match self {
            Self::Flash(_) => 230,
            Self::Full => 231,
            Self::Corrupt => 232,
            Self::TooLarge => 233,
            Self::BufferTooSmall { .. } => 234,
            Self::BadRegion => 235,
            Self::Internal => 236,
        }
    }
}

impl fmt::Display for StorageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Flash(kind) => write!(f, "flash error: {kind}"),
            Self::Full => f.write_str("storage full"),
            Self::Corrupt => f.write_str("stored data corrupt"),
            Self::TooLarge => f.write_str("record too large"),
            Self::BufferTooSmall { needed } => {
                write!(f, "buffer too small ({needed} bytes needed)")
            }
            Self::BadRegion => f.write_str("bad flash region"),
            Self::Internal => f.write_str("storage internal error"),
        }
    }
}

impl Error for StorageError {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Flash(_) => ErrorKind::Hardware,
            Self::Full | Self::BufferTooSmall { .. } => ErrorKind::Full,
            Self::Corrupt => ErrorKind::Corrupt,
            Self::TooLarge | Self::BadRegion => ErrorKind::OutOfRange,
            Self::Internal => ErrorKind::Other,
        }
    }
}

impl<E: NorFlashError> From<sequential_storage::Error<E>> for StorageError {
    fn from(e: sequential_storage::Error<E>) -> Self {
        use sequential_storage::Error as S;
        match e {
            S::Storage { value, .. } => Self::Flash(value.kind()),
            S::FullStorage => Self::Full,
            S::Corrupted { .. } => Self::Corrupt,
            S::ItemTooBig | S::BufferTooBig => Self::TooLarge,
            S::BufferTooSmall(_) | S::SerializationError(_) => Self::TooLarge,
            _ => Self::Internal,
        }
    }
}

/// A data buffer aligned for flashes that read and write from aligned RAM.
#[repr(C, align(4))]
struct AlignedBuf<const N: usize>([u8; N]);

/// The map of `sequential-storage`, keyed by `u16`, without RAM cache.
type Map<F> = MapStorage<u16, Blocking<F>, Cache<Uncached, Uncached, Uncached, u16>>;

/// Keyed records in a region of a NOR flash, each operation with a `BUF`-byte record buffer on
/// its stack.
///
/// The default `BUF` of 288 bytes holds any value of [`Records`] ([`MAX_RECORD_LEN`] bytes)
/// on flashes with words of up to 32 bytes.
///
/// Stateless in RAM: every operation reads what it needs from the flash, so a new instance
/// over the same region (after a reset) sees exactly what was committed. (The buffer is not
/// kept in the store: a board parks the store in a `static`, whose initial value would then
/// take the buffer's bytes of flash.)
pub struct FlashRecordStorage<F: NorFlash, const BUF: usize = 288> {
    map: Map<F>,
}

impl<F: NorFlash, const BUF: usize> FlashRecordStorage<F, BUF> {
    /// Records in `region` (byte offsets in `flash`) whose bounds are multiples of
    /// `F::ERASE_SIZE` and span at least two pages. Existing records are found where they are;
    /// an erased region is an empty store.
    ///
    /// Context: thread. Does not touch the flash. Errors: [`StorageError::BadRegion`].
    pub fn new(flash: F, region: Range<u32>) -> Result<Self, StorageError> {
        if usize::try_from(region.end).map_or(true, |end| end > flash.capacity()) {
            return Err(StorageError::BadRegion);
        }
        let config = MapConfig::try_new(region).map_err(|_| StorageError::BadRegion)?;
        Ok(Self {
            map: MapStorage::new(Blocking(flash), config, Cache::new_uncached()),
        })
    }

    /// The largest value this instance stores: `BUF` rounded down to the flash word, less the
    /// key and marker. (A record must also fit in one page with its header.)
    pub const fn max_value_len() -> usize {
        let word = if F::READ_SIZE > F::WRITE_SIZE {
            F::READ_SIZE
        } else {
            F::WRITE_SIZE
        };
        let word = if word == 0 { 1 } else { word };
        (BUF / word * word).saturating_sub(KEY_AND_MARKER)
    }

    /// Erase the whole region: every record is gone.
    ///
    /// Context: thread. Blocks for the erase. Errors: [`StorageError::Flash`].
    pub fn erase_all(&mut self) -> Result<(), StorageError> {
        Ok(block_on(self.map.erase_all())?)
    }

    /// The flash, for a board that shares it with other users between operations.
    pub fn flash_mut(&mut self) -> &mut F {
        &mut self.map.flash().0
    }

    /// Give the flash back.
    pub fn into_flash(self) -> F {
        self.map.destroy().0.0
    }
}

impl<F: NorFlash, const BUF: usize> ErrorType for FlashRecordStorage<F, BUF> {
    type Error = StorageError;
}

impl<F: NorFlash, const BUF: usize> RecordStorage for FlashRecordStorage<F, BUF> {
    fn read(&mut self, key: u16, buf: &mut [u8]) -> Result<Option<usize>, Self::Error> {
        let mut record = AlignedBuf([0; BUF]);
        let item = block_on(self.map.fetch_item::<Option<&[u8]>>(&mut record.0, &key))?;
        match item {
            None | Some(None) => Ok(None),
            Some(Some(value)) => {
                let needed = value.len();
                let dst = buf
                    .get_mut(..needed)
                    .ok_or(StorageError::BufferTooSmall { needed })?;
                dst.copy_from_slice(value);
                Ok(Some(needed))
            }
        }
    }

    fn write(&mut self, key: u16, value: &[u8]) -> Result<(), Self::Error> {
        if value.len() > Self::max_value_len() {
            return Err(StorageError::TooLarge);
        }
        let mut record = AlignedBuf([0; BUF]);
        Ok(block_on(self.map.store_item(
            &mut record.0,
            &key,
            &Some(value),
        ))?)
    }

    fn remove(&mut self, key: u16) -> Result<(), Self::Error> {
        let mut record = AlignedBuf([0; BUF]);
        let present = block_on(self.map.fetch_item::<Option<&[u8]>>(&mut record.0, &key))?
            .flatten()
            .is_some();
        if !present {
            return Ok(());
        }
        Ok(block_on(self.map.store_item(
            &mut record.0,
            &key,
            &None::<&[u8]>,
        ))?)
    }
}

/// A typed [`Records`] operation failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum RecordError<E> {
    /// The store failed.
    Storage(E),
    /// The value does not encode into [`MAX_RECORD_LEN`] bytes. Code 237.
    Encode,
    /// The stored bytes are not a valid value of the type asked for (a record written by an
    /// older firmware with another layout, or under another key). Code 238.
    Decode,
}

impl RecordError<StorageError> {
    /// The stable wire code: the storage error's, or 237/238.
    pub const fn code(&self) -> u16 {
        match self {
            Self::Storage(e) => e.code(),
            Self::Encode => 237,
            Self::Decode => 238,
        }
    }
}

impl<E: fmt::Display> fmt::Display for RecordError<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Storage(e) => e.fmt(f),
            Self::Encode => write!(f, "record does not encode into {MAX_RECORD_LEN} bytes"),
            Self::Decode => f.write_str("stored record does not decode"),
        }
    }
}

impl<E: Error> Error for RecordError<E> {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Storage(e) => e.kind(),
            Self::Encode => ErrorKind::OutOfRange,
            Self::Decode => ErrorKind::Corrupt,
        }
    }
}

/// Typed records on any [`RecordStorage`], encoded with `postcard`.
///
/// Implemented for every [`RecordStorage`]; values encode on the stack into
/// [`MAX_RECORD_LEN`] bytes.
///
/// Context: thread; blocks as the underlying store does.
pub trait Records: RecordStorage {
    /// Encode `value` and store it under `key`.
    ///
    /// Errors: [`RecordError::Encode`] when it encodes to more than [`MAX_RECORD_LEN`] bytes;
    /// the store's errors (the old value is kept).
    fn save<T: Serialize + ?Sized>(
        &mut self,
        key: u16,
        value: &T,
    ) -> Result<(), RecordError<Self::Error>> {
        let mut buf = [0u8; MAX_RECORD_LEN];
        let bytes = postcard::to_slice(value, &mut buf).map_err(|_| RecordError::Encode)?;
        self.write(key, bytes).map_err(RecordError::Storage)
    }

    /// The value stored under `key`, `None` when there is none.
    ///
    /// Errors: [`RecordError::Decode`] when the stored bytes are not a `T`; the store's errors.
    fn load<T: DeserializeOwned>(
        &mut self,
        key: u16,
    ) -> Result<Option<T>, RecordError<Self::Error>> {
        let mut buf = [0u8; MAX_RECORD_LEN];
        let Some(len) = self.read(key, &mut buf).map_err(RecordError::Storage)? else {
            return Ok(None);
        };
        let bytes = buf.get(..len).ok_or(RecordError::Decode)?;
        postcard::from_bytes(bytes)
            .map(Some)
            .map_err(|_| RecordError::Decode)
    }
}

impl<S: RecordStorage + ?Sized> Records for S {}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ram_flash::{RamFlashError, RamNorFlash};
    use serde::Deserialize;

    /// Four 256-byte pages of 4-byte words.
    type Flash = RamNorFlash<1024, 4, 256>;
    type Store = FlashRecordStorage<Flash, 64>;
    const REGION: Range<u32> = 0..1024;

    fn open(flash: Flash) -> Store {
        Store::new(flash, REGION).unwrap()
    }

    fn get(s: &mut Store, key: u16) -> Result<Option<Vec<u8>>, StorageError> {
        let mut buf = [0u8; 64];
        Ok(s.read(key, &mut buf)?.map(|n| buf[..n].to_vec()))
    }

    #[test]
    fn write_read_overwrite_remove() {
        let mut s = open(Flash::new());
        assert_eq!(get(&mut s, 1), Ok(None));
        s.write(1, b"first").unwrap();
        s.write(2, b"").unwrap();
        assert_eq!(get(&mut s, 1), Ok(Some(b"first".to_vec())));
        assert_eq!(
            get(&mut s, 2),
            Ok(Some(Vec::new())),
            "empty is a value, not absence"
        );
        s.write(1, b"second").unwrap();
        assert_eq!(get(&mut s, 1), Ok(Some(b"second".to_vec())));
        s.remove(1).unwrap();
        assert_eq!(get(&mut s, 1), Ok(None));
        s.remove(1).unwrap();
        s.remove(99).unwrap();
        // Survives a re-open: the state is all in flash.
        let mut s = open(s.into_flash());
        assert_eq!(get(&mut s, 1), Ok(None));
        assert_eq!(get(&mut s, 2), Ok(Some(Vec::new())));
    }

    #[test]
    fn size_limits() {
        assert_eq!(Store::max_value_len(), 61);
        let mut s = open(Flash::new());
        assert_eq!(s.write(1, &[7; 62]), Err(StorageError::TooLarge));
        s.write(1, &[7; 61]).unwrap();
        let mut small = [0u8; 8];
        assert_eq!(
            s.read(1, &mut small),
            Err(StorageError::BufferTooSmall { needed: 61 })
        );
        assert_eq!(
            StorageError::BufferTooSmall { needed: 61 }.kind(),
            ErrorKind::Full
        );
    }

    #[test]
    fn the_default_buffer_holds_any_typed_record() {
        type Wide = RamNorFlash<8192, 32, 4096>;
        assert!(FlashRecordStorage::<Wide>::max_value_len() >= MAX_RECORD_LEN);
        assert!(FlashRecordStorage::<Flash>::max_value_len() >= MAX_RECORD_LEN);
        let mut s = FlashRecordStorage::<Wide>::new(Wide::new(), 0..8192).unwrap();
        // Arrays encode without a length prefix: exactly MAX_RECORD_LEN bytes.
        let big = [[0x5Au8; 32]; MAX_RECORD_LEN / 32];
        s.save(1, &big).unwrap();
        assert_eq!(s.load::<[[u8; 32]; MAX_RECORD_LEN / 32]>(1), Ok(Some(big)));
    }

    #[test]
    fn bad_regions_are_refused() {
        assert!(matches!(
            Store::new(Flash::new(), 0..256),
            Err(StorageError::BadRegion)
        ));
        assert!(matches!(
            Store::new(Flash::new(), 0..1000),
            Err(StorageError::BadRegion)
        ));
        assert!(matches!(
            Store::new(Flash::new(), 0..2048),
            Err(StorageError::BadRegion)
        ));
        assert!(Store::new(Flash::new(), 512..1024).is_ok());
    }

    #[test]
    fn filling_the_store_reports_full_and_keeps_old_values() {
        let mut s = open(Flash::new());
        s.write(1, b"precious").unwrap();
        let mut written = Vec::new();
        let mut err = None;
        for key in 100..200u16 {
            match s.write(key, &[key as u8; 40]) {
                Ok(()) => written.push(key),
                Err(e) => {
                    err = Some((key, e));
                    break;
                }
            }
        }
        let (failed, e) = err.expect("a 1 KiB store cannot hold 100 records of 40 bytes");
        assert_eq!(e, StorageError::Full);
        assert_eq!(e.kind(), ErrorKind::Full);
        assert!(written.len() >= 3, "{written:?}");
        // Nothing was lost, the failed key is absent.
        let mut s = open(s.into_flash());
        assert_eq!(get(&mut s, 1), Ok(Some(b"precious".to_vec())));
        for &key in &written {
            assert_eq!(get(&mut s, key), Ok(Some(vec![key as u8; 40])));
        }
        assert_eq!(get(&mut s, failed), Ok(None));
        // Growing an existing record fails the same way and keeps the old value.
        assert_eq!(s.write(1, &[0; 61]), Err(StorageError::Full));
        assert_eq!(get(&mut s, 1), Ok(Some(b"precious".to_vec())));
        // Erasing the region is the way out.
        s.erase_all().unwrap();
        assert_eq!(get(&mut s, 1), Ok(None));
        s.write(failed, b"fits now").unwrap();
    }

    /// The value of round `i` of the power-cut sweep: lengths vary so that records straddle
    /// page ends and trigger page moves.
    fn value(round: usize, max_len: usize) -> Vec<u8> {
        let len = 1 + (round * 7) % max_len;
        (0..len).map(|i| (round * 31 + i) as u8).collect()
    }

    /// Write `rounds` successive values to one key (and now and then to a second one), cutting
    /// the power after every unit of work of every write; after each cut, re-open the store as
    /// after a reset and check that it reads the old or the new value and still works.
    fn power_cut_sweep<
        const SIZE: usize,
        const WORD: usize,
        const PAGE: usize,
        const BUF: usize,
    >(
        rounds: usize,
    ) {
        type S<const SIZE: usize, const WORD: usize, const PAGE: usize, const BUF: usize> =
            FlashRecordStorage<RamNorFlash<SIZE, WORD, PAGE>, BUF>;
        let region = 0..SIZE as u32;
        let open = |f: RamNorFlash<SIZE, WORD, PAGE>| {
            S::<SIZE, WORD, PAGE, BUF>::new(f, region.clone()).unwrap()
        };
        let get = |s: &mut S<SIZE, WORD, PAGE, BUF>, key: u16| {
            let mut buf = [0u8; BUF];
            s.read(key, &mut buf).map(|r| r.map(|n| buf[..n].to_vec()))
        };
        let max_len = S::<SIZE, WORD, PAGE, BUF>::max_value_len();
        let (mut old_a, mut old_b): (Option<Vec<u8>>, Option<Vec<u8>>) = (None, None);
        let mut flash = RamNorFlash::<SIZE, WORD, PAGE>::new();
        let (mut cuts, mut rounds_with_erase) = (0usize, 0usize);
        for round in 0..rounds {
            // Mostly key A; every third round key B, so that page moves carry live records of
            // another key.
            let (key, other) = if round % 3 == 2 { (2u16, 1u16) } else { (1, 2) };
            let new = value(round, max_len);
            let (old, old_other) = if key == 1 {
                (old_a.clone(), old_b.clone())
            } else {
                (old_b.clone(), old_a.clone())
            };

            let mut probe = open(flash.clone());
            let (work0, erased0) = (
                probe.flash_mut().work_done(),
                probe.flash_mut().pages_erased(),
            );
            probe.write(key, &new).unwrap();
            let units = probe.flash_mut().work_done() - work0;
            if probe.flash_mut().pages_erased() > erased0 {
                rounds_with_erase += 1;
            }

            for k in 0..units {
                let mut f = flash.clone();
                f.cut_power_after(k);
                let mut s = open(f);
                assert!(s.write(key, &new).is_err(), "round {round}, cut after {k}");
                let mut f = s.into_flash();
                assert!(!f.is_powered(), "round {round}, cut after {k}");
                f.restore_power();

                let mut s = open(f);
                let got = get(&mut s, key);
                assert!(
                    got == Ok(old.clone()) || got == Ok(Some(new.clone())),
                    "round {round}, cut after {k} of {units}: read {got:?}, old {old:?}, new {new:?}"
                );
                assert_eq!(
                    get(&mut s, other),
                    Ok(old_other.clone()),
                    "round {round}, cut after {k}: the other record was disturbed"
                );
                s.write(key, &new)
                    .unwrap_or_else(|e| panic!("round {round}, cut after {k}: rewrite {e:?}"));
                assert_eq!(get(&mut s, key), Ok(Some(new.clone())));
                assert_eq!(get(&mut s, other), Ok(old_other.clone()));
                cuts += 1;
            }

            let mut s = open(flash);
            s.write(key, &new).unwrap();
            flash = s.into_flash();
            if key == 1 {
                old_a = Some(new);
            } else {
                old_b = Some(new);
            }
        }
        assert!(cuts > rounds * 8, "{cuts} cuts");
        assert!(rounds_with_erase >= 3, "the sweep must include page moves");
    }

    #[test]
    fn a_power_cut_at_any_byte_of_a_write_leaves_old_or_new() {
        // Four 256-byte pages of 4-byte words (internal flash of a small MCU) ...
        power_cut_sweep::<1024, 4, 256, 64>(90);
        // ... and three 512-byte pages of 8-byte words (wider flash, fewer spare pages).
        power_cut_sweep::<1536, 8, 512, 128>(60);
    }

    #[test]
    fn a_second_cut_during_recovery_still_leaves_old_or_new() {
        const KEY: u16 = 9;
        let mut flash = Flash::new();
        let mut old: Option<Vec<u8>> = None;
        let mut checks = 0;
        for round in 0..24 {
            let new = value(round, Store::max_value_len());
            let mut probe = open(flash.clone());
            let w0 = probe.flash_mut().work_done();
            probe.write(KEY, &new).unwrap();
            let units = probe.flash_mut().work_done() - w0;
            for k in (0..units).step_by(5) {
                // First cut, during the write.
                let mut f = flash.clone();
                f.cut_power_after(k);
                let mut s = open(f);
                assert!(s.write(KEY, &new).is_err());
                let mut torn = s.into_flash();
                torn.restore_power();
                // Second cut, at every unit of the first operation after the reset (a read
                // that may repair, then the rewrite).
                let mut probe = open(torn.clone());
                let r0 = probe.flash_mut().work_done();
                let _ = get(&mut probe, KEY);
                probe.write(KEY, &new).unwrap();
                let recovery_units = probe.flash_mut().work_done() - r0;
                for j in 0..recovery_units {
                    let mut f = torn.clone();
                    f.cut_power_after(j);
                    let mut s = open(f);
                    let _ = get(&mut s, KEY);
                    let _ = s.write(KEY, &new);
                    let mut f = s.into_flash();
                    f.restore_power();
                    let mut s = open(f);
                    let got = get(&mut s, KEY);
                    assert!(
                        got == Ok(old.clone()) || got == Ok(Some(new.clone())),
                        "round {round}, cuts after {k} then {j}: {got:?}"
                    );
                    s.write(KEY, &new).unwrap();
                    checks += 1;
                }
            }
            let mut s = open(flash);
            s.write(KEY, &new).unwrap();
            flash = s.into_flash();
            old = Some(new);
        }
        assert!(checks > 500, "{checks}");
    }

    #[test]
    fn a_power_cut_during_remove_leaves_old_or_absent() {
        let mut s = open(Flash::new());
        s.write(5, b"to be removed").unwrap();
        let flash = s.into_flash();
        let mut probe = open(flash.clone());
        let before = probe.flash_mut().work_done();
        probe.remove(5).unwrap();
        let units = probe.flash_mut().work_done() - before;
        assert!(units > 0);
        for k in 0..units {
            let mut f = flash.clone();
            f.cut_power_after(k);
            let mut s = open(f);
            assert!(s.remove(5).is_err());
            let mut f = s.into_flash();
            f.restore_power();
            let mut s = open(f);
            let got = get(&mut s, 5);
            assert!(
                got == Ok(None) || got == Ok(Some(b"to be removed".to_vec())),
                "cut after {k}: {got:?}"
            );
        }
    }

    #[test]
    fn flash_errors_map_to_hardware() {
        let mut f = Flash::new();
        f.cut_power_after(0);
        let mut s = open(f);
        let e = s.write(1, b"x").unwrap_err();
        assert_eq!(e, StorageError::Flash(RamFlashError::PowerLost.kind()));
        assert_eq!(e.kind(), ErrorKind::Hardware);
        assert_eq!(e.code(), 230);
    }

    #[test]
    fn codes_are_stable() {
        let all = [
            (StorageError::Flash(NorFlashErrorKind::Other), 230),
            (StorageError::Full, 231),
            (StorageError::Corrupt, 232),
            (StorageError::TooLarge, 233),
            (StorageError::BufferTooSmall { needed: 1 }, 234),
            (StorageError::BadRegion, 235),
            (StorageError::Internal, 236),
        ];
        for (e, code) in all {
            assert_eq!(e.code(), code);
            assert_eq!(RecordError::Storage(e).code(), code);
            assert!(!e.to_string().is_empty());
        }
        assert_eq!(RecordError::<StorageError>::Encode.code(), 237);
        assert_eq!(RecordError::<StorageError>::Decode.code(), 238);
    }

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct Settings {
        steps_per_mm: [f32; 3],
        max_feed_mm_min: u32,
        invert_axes: (bool, bool, bool),
        probe_offset_um: Option<[i32; 3]>,
    }

    #[test]
    fn typed_records_round_trip() {
        let mut s = open(Flash::new());
        let settings = Settings {
            steps_per_mm: [80.0, 80.0, 400.0],
            max_feed_mm_min: 12_000,
            invert_axes: (false, true, false),
            probe_offset_um: Some([-40_000, 12_500, -1_200]),
        };
        assert_eq!(s.load::<Settings>(10), Ok(None));
        s.save(10, &settings).unwrap();
        assert_eq!(s.load::<Settings>(10), Ok(Some(settings)));
        // Through a `&mut` borrow, as the kernel holds it.
        let r = &mut s;
        r.save(11, &42u32).unwrap();
        assert_eq!(r.load::<u32>(11), Ok(Some(42)));
    }

    #[test]
    fn typed_records_report_encode_and_decode_failures() {
        let mut s = open(Flash::new());
        // Too big for the stack buffer.
        let big = [0u8; MAX_RECORD_LEN + 1];
        assert_eq!(s.save(1, &big[..]), Err(RecordError::Encode));
        // Too big for this store's record buffer.
        assert_eq!(
            s.save(1, &[1u8; 100][..]),
            Err(RecordError::Storage(StorageError::TooLarge))
        );
        // A record of another type.
        s.write(2, &[0xFF]).unwrap();
        let e = s.load::<u32>(2).unwrap_err();
        assert_eq!(e, RecordError::Decode);
        assert_eq!(e.kind(), ErrorKind::Corrupt);
        assert!(!e.to_string().is_empty());
    }
}
