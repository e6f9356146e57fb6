//! Settings and stored programs: power-loss-safe keyed records on NOR flash.
//!
//! [`FlashRecordStorage`] implements [`RecordStorage`] over any `embedded-storage`
//! [`NorFlash`] (a region of the MCU's internal flash, an external SPI NOR) as a log of
//! records in the region's erase pages. [`Records`] adds typed `save`/`load` on top of any
//! [`RecordStorage`], encoding values with `postcard`.
//!
//! # Layout
//!
//! All offsets and lengths are multiples of the store's word: the flash's read and write
//! sizes, at least 4 bytes, at most 32. Below, `H` is 8 bytes rounded up to the word.
//!
//! | where | what |
//! |---|---|
//! | page, bytes `0..H` | the page's sequence number `s` (`u32` LE), then `s ^ 0x466F_726A` (`u32` LE); the rest `0xFF` |
//! | page, the word at `H` | `0xFF`: the page is live; written `0`: retired, about to be erased |
//! | page, from `H` + one word | records, one after the other, each at a word boundary |
//! | record, bytes `0..H` | the key (`u16` LE), the tag (`u16` LE: the value's length, bit 15 set for a removed key), the CRC-32 of key, tag and value (`u32` LE) |
//! | record, from `H` | the value, `0xFF` up to the next word |
//!
//! A page is *live* when its header checks and its retire word is erased. The live pages, in
//! the order of their sequence numbers, hold the log: a key's value is its last intact record.
//! Every other page is *spare*: erased, or waiting to be (it is erased before its next use).
//!
//! # Writing
//!
//! A write appends a record to the newest live page: its header first, then its value. When it
//! does not fit, the next spare page (in the ring of pages, after the newest) is opened with
//! the next sequence number. When that was the last spare page, the oldest live page is
//! collected into it first: its records that are still their key's value are copied over, then
//! it is retired and erased, and so becomes the spare page. A write that still does not fit
//! once each of the other pages was collected reports [`StorageError::Full`] (a collection
//! never merges pages, so another round would free nothing): on two pages, after one erase.
//!
//! # Power loss
//!
//! No byte is written twice between erases, and each step leaves a state that reads as the
//! old values or the new:
//! - a cut while a record is written leaves a record whose CRC fails, always the last one of
//!   its page: reads skip it, and the next write starts a new page rather than append after it;
//! - a cut while a page is opened leaves a page whose header does not check: a spare page;
//! - a cut while a page is collected leaves every page live (no spare page, which no complete
//!   operation leaves), with the newest page holding copies only; the next write erases it and
//!   collects again;
//! - a cut while a retired page is erased leaves a spare page.
//!
//! The tests cut the power after every single byte of a write, including writes that collect
//! pages, and after every byte of the repair that follows, and check that the key then reads
//! as its old or its new value and that the other keys are untouched.
//!
//! A region in another layout (that of an earlier firmware) has no live page: it reads as an
//! empty store, and its pages are erased as the store needs them.
//!
//! # Cost
//!
//! Stateless in RAM: every operation reads what it needs from the flash, so a new instance over
//! the same region (after a reset) sees exactly what was committed. A read walks the record
//! headers of every live page and checks the CRC of the key's records. A collection looks up
//! each record of the page it collects: quadratic in the records of a page, some hundreds on a
//! 16 KiB page.
//!
//! # Execution context
//!
//! Thread. Reads block for flash reads; writes may block for a page erase (tens of
//! milliseconds on internal flash, during which a single-bank part stalls the core): never
//! write while the machine moves.

use core::fmt;
use core::ops::Range;

use embedded_storage::nor_flash::{NorFlash, NorFlashError, NorFlashErrorKind};
use forja_hal_abstraction::program::crc32_update;
use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::{Error, ErrorKind, ErrorType};
use serde::Serialize;
use serde::de::DeserializeOwned;

/// Largest encoded value handled by [`Records::save`] and [`Records::load`], which encode on
/// the stack.
pub const MAX_RECORD_LEN: usize = 256;

/// The second word of a page header is the sequence number XOR this ("Forj").
const PAGE_MAGIC: u32 = 0x466F_726A;

/// Bit 15 of a record's tag: the key was removed (the record has no value).
const REMOVED: u16 = 0x8000;

/// The two words of an erased record header.
const ERASED_HEADER: (u32, u32) = (u32::MAX, u32::MAX);

/// The largest word the store works with.
const MAX_WORD: usize = 32;

/// Bytes moved per flash operation when a value is read, written, checked or copied.
const CHUNK: usize = 2 * MAX_WORD;

/// A storage operation failed. The codes go on the wire and are stable.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum StorageError {
    /// The flash reported an error. Code 230.
    Flash(NorFlashErrorKind),
    /// No room left, even after reclaiming space; the old value is kept. Code 231.
    Full,
    /// The value is longer than [`FlashRecordStorage::max_value_len`]. Code 233.
    TooLarge,
    /// The caller's buffer cannot hold the value, of `needed` bytes. Code 234.
    BufferTooSmall {
        /// The length of the stored value.
        needed: usize,
    },
    /// The flash region is not a whole number of erase pages, has fewer than two, lies outside
    /// the device, or the flash's word is larger than 32 bytes or its page not a multiple of 64
    /// bytes. Code 235.
    BadRegion,
    /// An internal inconsistency of the storage layer, or a store used by another user at the
    /// same time ([`SharedStore`](crate::shared_store::SharedStore)). Code 236.
    Internal,
}

impl StorageError {
    /// The stable wire code, in 230..=239 (232, "stored data corrupt", is no longer used: the
    /// store repairs every state a power cut leaves).
    pub const fn code(&self) -> u16 {
        match self {
            Self::Flash(_) => 230,
            Self::Full => 231,
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
            Self::TooLarge | Self::BadRegion => ErrorKind::OutOfRange,
            Self::Internal => ErrorKind::Other,
        }
    }
}

fn flash_error<E: NorFlashError>(e: E) -> StorageError {
    StorageError::Flash(e.kind())
}

/// Bytes moved through RAM on their way to or from the flash, aligned for flashes that read
/// and write from aligned RAM.
#[repr(C, align(4))]
struct Chunk([u8; CHUNK]);

impl Chunk {
    const fn erased() -> Self {
        Self([0xFF; CHUNK])
    }

    /// The little-endian `u32` at `at`.
    fn u32_at(&self, at: usize) -> u32 {
        let mut word = [0xFF; 4];
        if let Some(bytes) = self.0.get(at..at + 4) {
            word.copy_from_slice(bytes);
        }
        u32::from_le_bytes(word)
    }
}

/// A record's header.
#[derive(Clone, Copy)]
struct Header {
    key: u16,
    tag: u16,
    crc: u32,
}

impl Header {
    /// The value's length.
    fn len(self) -> usize {
        usize::from(self.tag & !REMOVED)
    }

    /// The key was removed.
    fn removed(self) -> bool {
        self.tag & REMOVED != 0
    }
}

/// A live page: its sequence number above its index, so that ordering these orders the log.
type Live = u64;

fn live_order(seq: u32, page: u32) -> Live {
    (u64::from(seq) << 32) | u64::from(page)
}

fn live_page(order: Live) -> u32 {
    order as u32
}

fn live_sequence(order: Live) -> u32 {
    (order >> 32) as u32
}

/// The live pages, as [`FlashRecordStorage::survey`] found them.
struct Survey {
    /// How many there are.
    count: u32,
    /// The oldest and the newest.
    oldest: Option<Live>,
    newest: Option<Live>,
}

/// Keyed records in a region of a NOR flash (see the [module](self) for the layout).
///
/// Stateless in RAM: every operation reads what it needs from the flash, so a new instance
/// over the same region (after a reset) sees exactly what was committed.
pub struct FlashRecordStorage<F: NorFlash> {
    flash: F,
    /// The region's start in the flash.
    base: u32,
    /// Erase pages in the region.
    pages: u32,
}

impl<F: NorFlash> FlashRecordStorage<F> {
    /// The store's word: the flash's read and write sizes, at least 4 bytes.
    const WORD: usize = max(max(F::READ_SIZE, F::WRITE_SIZE), 4);
    /// Bytes of a page header, and of a record header.
    const HEADER: usize = round_up(8, Self::WORD);
    /// Where a page's first record starts: after its header and its retire word.
    const FIRST: usize = Self::HEADER + Self::WORD;
    /// Bytes of an erase page.
    const PAGE: u32 = F::ERASE_SIZE as u32;

    /// Records in `region` (byte offsets in `flash`) whose bounds are multiples of
    /// `F::ERASE_SIZE` and span at least two pages. Existing records are found where they are;
    /// an erased region is an empty store.
    ///
    /// Context: thread. Does not touch the flash. Errors: [`StorageError::BadRegion`].
    pub fn new(flash: F, region: Range<u32>) -> Result<Self, StorageError> {
        let page = F::ERASE_SIZE;
        let word = Self::WORD;
        let fits = usize::try_from(region.end).is_ok_and(|end| end <= flash.capacity());
        let geometry = word <= MAX_WORD
            && word.is_power_of_two()
            && page.is_multiple_of(CHUNK)
            && page > Self::FIRST + Self::HEADER
            && u32::try_from(page).is_ok();
        let len = region.end.saturating_sub(region.start) as usize;
        if !fits
            || !geometry
            || !(region.start as usize).is_multiple_of(page)
            || !len.is_multiple_of(page)
            || len / page < 2
        {
            return Err(StorageError::BadRegion);
        }
        Ok(Self {
            flash,
            base: region.start,
            pages: (len / page) as u32,
        })
    }

    /// The largest value this store keeps: what fits in one page with its headers.
    pub const fn max_value_len() -> usize {
        let room = F::ERASE_SIZE.saturating_sub(Self::FIRST + Self::HEADER);
        if room < REMOVED as usize {
            room
        } else {
            REMOVED as usize - 1
        }
    }

    /// Erase the whole region: every record is gone.
    ///
    /// Context: thread. Blocks for the erase. Errors: [`StorageError::Flash`].
    pub fn erase_all(&mut self) -> Result<(), StorageError> {
        let end = self.base + self.pages * Self::PAGE;
        self.flash.erase(self.base, end).map_err(flash_error)
    }

    /// The flash, for a board that shares it with other users between operations.
    pub fn flash_mut(&mut self) -> &mut F {
        &mut self.flash
    }

    /// Give the flash back.
    pub fn into_flash(self) -> F {
        self.flash
    }

    fn read_at(&mut self, at: u32, bytes: &mut [u8]) -> Result<(), StorageError> {
        self.flash.read(self.base + at, bytes).map_err(flash_error)
    }

    fn write_at(&mut self, at: u32, bytes: &[u8]) -> Result<(), StorageError> {
        self.flash.write(self.base + at, bytes).map_err(flash_error)
    }

    fn erase_page(&mut self, page: u32) -> Result<(), StorageError> {
        let start = self.base + page * Self::PAGE;
        self.flash
            .erase(start, start + Self::PAGE)
            .map_err(flash_error)
    }

    /// The sequence number of `page` when it is live.
    fn sequence(&mut self, page: u32) -> Result<Option<u32>, StorageError> {
        let mut head = Chunk::erased();
        let bytes = head
            .0
            .get_mut(..Self::FIRST)
            .ok_or(StorageError::Internal)?;
        self.read_at(page * Self::PAGE, bytes)?;
        let (seq, check) = (head.u32_at(0), head.u32_at(4));
        let retired = head
            .0
            .get(Self::HEADER..Self::FIRST)
            .is_none_or(|word| word.iter().any(|&b| b != 0xFF));
        Ok((check == seq ^ PAGE_MAGIC && !retired).then_some(seq))
    }

    /// The first live page after `after` in the log's order.
    fn next_live(&mut self, after: Option<Live>) -> Result<Option<Live>, StorageError> {
        let mut next = None;
        for page in 0..self.pages {
            if let Some(seq) = self.sequence(page)? {
                let order = live_order(seq, page);
                if after.is_none_or(|a| order > a) && next.is_none_or(|n| order < n) {
                    next = Some(order);
                }
            }
        }
        Ok(next)
    }

    /// How many pages are live, and which are the oldest and the newest: one read of each
    /// page's header.
    fn survey(&mut self) -> Result<Survey, StorageError> {
        let mut survey = Survey {
            count: 0,
            oldest: None,
            newest: None,
        };
        for page in 0..self.pages {
            if let Some(seq) = self.sequence(page)? {
                let order = live_order(seq, page);
                survey.count += 1;
                survey.oldest = Some(survey.oldest.map_or(order, |o| o.min(order)));
                survey.newest = Some(survey.newest.map_or(order, |n| n.max(order)));
            }
        }
        Ok(survey)
    }

    /// The two words of the record header at `at`, in the page starting at `page`; `None`
    /// when no header fits there.
    fn header_words(&mut self, page: u32, at: u32) -> Result<Option<(u32, u32)>, StorageError> {
        if at + Self::HEADER as u32 > page + Self::PAGE {
            return Ok(None);
        }
        let mut chunk = Chunk::erased();
        let bytes = chunk
            .0
            .get_mut(..Self::HEADER)
            .ok_or(StorageError::Internal)?;
        self.read_at(at, bytes)?;
        Ok(Some((chunk.u32_at(0), chunk.u32_at(4))))
    }

    /// The record header at `at`, in the page starting at `page`; `None` where the page's
    /// records end: at an erased header, or where a record would not fit in the page.
    fn header(&mut self, page: u32, at: u32) -> Result<Option<Header>, StorageError> {
        let Some((first, crc)) = self.header_words(page, at)? else {
            return Ok(None);
        };
        if (first, crc) == ERASED_HEADER {
            return Ok(None);
        }
        let header = Header {
            key: first as u16,
            tag: (first >> 16) as u16,
            crc,
        };
        Ok((at + Self::size(header.len()) <= page + Self::PAGE).then_some(header))
    }

    /// Bytes of a record of a `len`-byte value: its header and its value, each to a whole
    /// number of words.
    fn size(len: usize) -> u32 {
        (Self::HEADER + round_up(len, Self::WORD)) as u32
    }

    /// The bytes of the value of the record at `at`, a chunk at a time: `visit` gets each
    /// chunk's value bytes.
    fn each_chunk(
        &mut self,
        at: u32,
        header: Header,
        visit: &mut dyn FnMut(&[u8]),
    ) -> Result<(), StorageError> {
        let mut from = at + Self::HEADER as u32;
        let mut left = header.len();
        while left > 0 {
            let take = left.min(CHUNK);
            let mut chunk = Chunk::erased();
            let bytes = chunk
                .0
                .get_mut(..round_up(take, Self::WORD))
                .ok_or(StorageError::Internal)?;
            self.read_at(from, bytes)?;
            visit(bytes.get(..take).unwrap_or(&[]));
            from += CHUNK as u32;
            left -= take;
        }
        Ok(())
    }

    /// The record at `at` was written whole: its CRC checks.
    fn intact(&mut self, at: u32, header: Header) -> Result<bool, StorageError> {
        let mut crc = crc32_update(0, &record_prefix(header.key, header.tag));
        self.each_chunk(at, header, &mut |bytes| crc = crc32_update(crc, bytes))?;
        Ok(crc == header.crc)
    }

    /// The last intact record of `key`, and where it is.
    fn latest(&mut self, key: u16) -> Result<Option<(u32, Header)>, StorageError> {
        let mut found = None;
        let mut after = None;
        while let Some(order) = self.next_live(after)? {
            after = Some(order);
            let page = live_page(order) * Self::PAGE;
            let mut at = page + Self::FIRST as u32;
            while let Some(header) = self.header(page, at)? {
                if header.key == key && self.intact(at, header)? {
                    found = Some((at, header));
                }
                at += Self::size(header.len());
            }
        }
        Ok(found)
    }

    /// Where the next record of the page starting at `page` goes; `None` when the page takes
    /// no more records (its last record is torn, or it is full).
    fn tail(&mut self, page: u32) -> Result<Option<u32>, StorageError> {
        let mut at = page + Self::FIRST as u32;
        let mut last = None;
        while let Some(header) = self.header(page, at)? {
            last = Some((at, header));
            at += Self::size(header.len());
        }
        if let Some((last_at, header)) = last
            && !self.intact(last_at, header)?
        {
            return Ok(None);
        }
        // The records ended at an erased header, not at one that runs past the page.
        let erased = self.header_words(page, at)? == Some(ERASED_HEADER);
        Ok(erased.then_some(at))
    }

    /// Write a record at `at`: its header, then its value.
    fn append(&mut self, at: u32, key: u16, tag: u16, value: &[u8]) -> Result<(), StorageError> {
        let prefix = record_prefix(key, tag);
        let crc = crc32_update(crc32_update(0, &prefix), value);
        let mut chunk = Chunk::erased();
        chunk.0[..4].copy_from_slice(&prefix);
        chunk.0[4..8].copy_from_slice(&crc.to_le_bytes());
        self.write_at(at, chunk.0.get(..Self::HEADER).unwrap_or(&[]))?;
        let mut to = at + Self::HEADER as u32;
        for piece in value.chunks(CHUNK) {
            let mut chunk = Chunk::erased();
            let bytes = chunk
                .0
                .get_mut(..round_up(piece.len(), Self::WORD))
                .ok_or(StorageError::Internal)?;
            bytes
                .get_mut(..piece.len())
                .ok_or(StorageError::Internal)?
                .copy_from_slice(piece);
            self.write_at(to, bytes)?;
            to += CHUNK as u32;
        }
        Ok(())
    }

    /// Make `page` the newest live page, of sequence number `seq`: erased first unless it is.
    fn open(&mut self, page: u32, seq: u32) -> Result<(), StorageError> {
        let start = page * Self::PAGE;
        for at in (start..start + Self::PAGE).step_by(CHUNK) {
            let mut chunk = Chunk::erased();
            self.read_at(at, &mut chunk.0)?;
            if chunk.0.iter().any(|&b| b != 0xFF) {
                self.erase_page(page)?;
                break;
            }
        }
        let mut head = Chunk::erased();
        head.0[..4].copy_from_slice(&seq.to_le_bytes());
        head.0[4..8].copy_from_slice(&(seq ^ PAGE_MAGIC).to_le_bytes());
        self.write_at(start, head.0.get(..Self::HEADER).unwrap_or(&[]))
    }

    /// Retire `page` (it stops being live), then erase it.
    fn retire(&mut self, page: u32) -> Result<(), StorageError> {
        let zeros = [0u8; MAX_WORD];
        let word = zeros.get(..Self::WORD).ok_or(StorageError::Internal)?;
        self.write_at(page * Self::PAGE + Self::HEADER as u32, word)?;
        self.erase_page(page)
    }

    /// Copy into the newly opened page `to` the records of the oldest live page `from` that are
    /// still their key's value, then retire `from`.
    fn collect(&mut self, from: u32, to: u32) -> Result<(), StorageError> {
        let (source, target) = (from * Self::PAGE, to * Self::PAGE);
        let mut at = source + Self::FIRST as u32;
        let mut next = target + Self::FIRST as u32;
        while let Some(header) = self.header(source, at)? {
            let size = Self::size(header.len());
            // A removed key's last record can go: the oldest page holds nothing older.
            if !header.removed() && self.latest(header.key)?.map(|(a, _)| a) == Some(at) {
                if next + size > target + Self::PAGE {
                    return Err(StorageError::Internal);
                }
                let mut done = 0;
                while done < size {
                    let take = (size - done).min(CHUNK as u32);
                    let mut chunk = Chunk::erased();
                    let bytes = chunk
                        .0
                        .get_mut(..take as usize)
                        .ok_or(StorageError::Internal)?;
                    self.read_at(at + done, bytes)?;
                    self.write_at(next + done, bytes)?;
                    done += take;
                }
                next += size;
            }
            at += size;
        }
        self.retire(from)
    }

    /// Append a record of `key` with `tag` and `value`, making room as the module describes.
    fn put(&mut self, key: u16, tag: u16, value: &[u8]) -> Result<(), StorageError> {
        if value.len() > Self::max_value_len() {
            return Err(StorageError::TooLarge);
        }
        let size = Self::size(value.len());
        let mut collections = 0;
        loop {
            let live = self.survey()?;
            if let Some(newest) = live.newest {
                let page = live_page(newest);
                if live.count == self.pages {
                    // A collection was cut short: the newest page holds copies only.
                    self.retire(page)?;
                    continue;
                }
                let start = page * Self::PAGE;
                if let Some(at) = self.tail(start)?
                    && at + size <= start + Self::PAGE
                {
                    return self.append(at, key, tag, value);
                }
            }
            // A collection moves one page's live records into a fresh page and never merges
            // pages, so once each of the others was collected a further one frees nothing.
            if collections + 1 == self.pages {
                return Err(StorageError::Full);
            }
            // The next spare page in the ring after the newest.
            let first = live.newest.map_or(0, |n| live_page(n) + 1);
            let mut spare = None;
            for i in 0..self.pages {
                let page = (first + i) % self.pages;
                if self.sequence(page)?.is_none() {
                    spare = Some(page);
                    break;
                }
            }
            let spare = spare.ok_or(StorageError::Internal)?;
            let seq = live.newest.map_or(0, |n| live_sequence(n).wrapping_add(1));
            self.open(spare, seq)?;
            if live.count + 1 == self.pages
                && let Some(oldest) = live.oldest
            {
                collections += 1;
                self.collect(live_page(oldest), spare)?;
            }
        }
    }
}

/// The first four bytes of a record: its key and its tag, little-endian.
fn record_prefix(key: u16, tag: u16) -> [u8; 4] {
    let (k, t) = (key.to_le_bytes(), tag.to_le_bytes());
    [k[0], k[1], t[0], t[1]]
}

const fn max(a: usize, b: usize) -> usize {
    if a > b { a } else { b }
}

const fn round_up(n: usize, word: usize) -> usize {
    n.div_ceil(word) * word
}

impl<F: NorFlash> ErrorType for FlashRecordStorage<F> {
    type Error = StorageError;
}

impl<F: NorFlash> RecordStorage for FlashRecordStorage<F> {
    fn read(&mut self, key: u16, buf: &mut [u8]) -> Result<Option<usize>, Self::Error> {
        let Some((at, header)) = self.latest(key)? else {
            return Ok(None);
        };
        if header.removed() {
            return Ok(None);
        }
        let needed = header.len();
        let dst = buf
            .get_mut(..needed)
            .ok_or(StorageError::BufferTooSmall { needed })?;
        let mut filled = 0;
        self.each_chunk(at, header, &mut |bytes| {
            if let Some(to) = dst.get_mut(filled..filled + bytes.len()) {
                to.copy_from_slice(bytes);
            }
            filled += bytes.len();
        })?;
        Ok(Some(needed))
    }

    fn write(&mut self, key: u16, value: &[u8]) -> Result<(), Self::Error> {
        self.put(key, value.len() as u16, value)
    }

    fn remove(&mut self, key: u16) -> Result<(), Self::Error> {
        match self.latest(key)? {
            Some((_, header)) if !header.removed() => self.put(key, REMOVED, &[]),
            _ => Ok(()),
        }
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
    type Store = FlashRecordStorage<Flash>;
    /// The longest value of the tests on [`Flash`]: records of up to a quarter of a page.
    const VALUE_LEN: usize = 61;
    const REGION: Range<u32> = 0..1024;

    fn open(flash: Flash) -> Store {
        Store::new(flash, REGION).unwrap()
    }

    fn get(s: &mut Store, key: u16) -> Result<Option<Vec<u8>>, StorageError> {
        let mut buf = [0u8; 256];
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
        // A 256-byte page less its 12-byte header and the record's 8-byte header.
        assert_eq!(Store::max_value_len(), 236);
        let mut s = open(Flash::new());
        assert_eq!(s.write(1, &[7; 237]), Err(StorageError::TooLarge));
        s.write(1, &[7; 236]).unwrap();
        assert_eq!(get(&mut s, 1), Ok(Some(vec![7; 236])));
        let mut small = [0u8; 8];
        assert_eq!(
            s.read(1, &mut small),
            Err(StorageError::BufferTooSmall { needed: 236 })
        );
        assert_eq!(
            StorageError::BufferTooSmall { needed: 236 }.kind(),
            ErrorKind::Full
        );
        // A page-sized value still moves from page to page as others are written.
        for round in 0..6u8 {
            s.write(2, &[round; 100]).unwrap();
            assert_eq!(get(&mut s, 1), Ok(Some(vec![7; 236])));
        }
    }

    #[test]
    fn the_pages_of_real_flashes_hold_any_typed_record() {
        type Wide = RamNorFlash<8192, 32, 4096>;
        type Sector = RamNorFlash<8192, 4, 4096>;
        assert!(FlashRecordStorage::<Wide>::max_value_len() >= MAX_RECORD_LEN);
        assert!(FlashRecordStorage::<Sector>::max_value_len() >= MAX_RECORD_LEN);
        let mut s = FlashRecordStorage::<Wide>::new(Wide::new(), 0..8192).unwrap();
        // Arrays encode without a length prefix: exactly MAX_RECORD_LEN bytes.
        let big = [[0x5Au8; 32]; MAX_RECORD_LEN / 32];
        s.save(1, &big).unwrap();
        assert_eq!(s.load::<[[u8; 32]; MAX_RECORD_LEN / 32]>(1), Ok(Some(big)));
    }

    #[test]
    fn a_region_in_another_layout_reads_empty_and_is_reclaimed() {
        let mut flash = Flash::new();
        // Words of an earlier layout in both pages: no page header checks.
        flash.write(0, &[0, 0, 0, 0, 1, 2, 3, 4]).unwrap();
        flash.write(256, &[0x12, 0x34, 0x56, 0x78]).unwrap();
        let mut s = open(flash);
        assert_eq!(get(&mut s, 1), Ok(None));
        s.write(1, b"new").unwrap();
        assert_eq!(get(&mut s, 1), Ok(Some(b"new".to_vec())));
        let mut s = open(s.into_flash());
        assert_eq!(get(&mut s, 1), Ok(Some(b"new".to_vec())));
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
        assert_eq!(s.write(1, &[0; VALUE_LEN]), Err(StorageError::Full));
        assert_eq!(get(&mut s, 1), Ok(Some(b"precious".to_vec())));
        // Erasing the region is the way out.
        s.erase_all().unwrap();
        assert_eq!(get(&mut s, 1), Ok(None));
        s.write(failed, b"fits now").unwrap();
    }

    #[test]
    fn a_full_two_page_store_says_so_after_one_collection() {
        type Two = RamNorFlash<512, 4, 256>;
        let mut s = FlashRecordStorage::<Two>::new(Two::new(), 0..512).unwrap();
        s.write(1, b"precious").unwrap();
        let mut key = 100;
        let e = loop {
            match s.write(key, &[key as u8; 40]) {
                Ok(()) => key += 1,
                Err(e) => break e,
            }
        };
        assert_eq!(e, StorageError::Full);
        // Another write that does not fit: one collection, one erase, and the same answer.
        let erased = s.flash_mut().pages_erased();
        assert_eq!(s.write(key, &[0; 40]), Err(StorageError::Full));
        assert_eq!(s.flash_mut().pages_erased() - erased, 1);
        let mut buf = [0u8; 64];
        assert_eq!(s.read(1, &mut buf), Ok(Some(8)));
        assert_eq!(&buf[..8], b"precious");
        for k in 100..key {
            assert_eq!(s.read(k, &mut buf), Ok(Some(40)), "key {k}");
            assert_eq!(buf[..40], [k as u8; 40]);
        }
        // A smaller value still fits in what is left.
        s.write(1, b"ok").unwrap();
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
    fn power_cut_sweep<const SIZE: usize, const WORD: usize, const PAGE: usize>(
        rounds: usize,
        max_len: usize,
    ) {
        type S<const SIZE: usize, const WORD: usize, const PAGE: usize> =
            FlashRecordStorage<RamNorFlash<SIZE, WORD, PAGE>>;
        let region = 0..SIZE as u32;
        let open = |f: RamNorFlash<SIZE, WORD, PAGE>| {
            S::<SIZE, WORD, PAGE>::new(f, region.clone()).unwrap()
        };
        let get = |s: &mut S<SIZE, WORD, PAGE>, key: u16| {
            let mut buf = [0u8; PAGE];
            s.read(key, &mut buf).map(|r| r.map(|n| buf[..n].to_vec()))
        };
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
        power_cut_sweep::<1024, 4, 256>(90, VALUE_LEN);
        // ... three 512-byte pages of 8-byte words (wider flash, fewer spare pages) ...
        power_cut_sweep::<1536, 8, 512>(60, 125);
        // ... and two pages, as the STM32F4 boards have: every new page is a collection.
        power_cut_sweep::<512, 4, 256>(60, VALUE_LEN);
    }

    #[test]
    fn a_second_cut_during_recovery_still_leaves_old_or_new() {
        const KEY: u16 = 9;
        let mut flash = Flash::new();
        let mut old: Option<Vec<u8>> = None;
        let mut checks = 0;
        for round in 0..24 {
            let new = value(round, VALUE_LEN);
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
        // Too long for a page of this store.
        assert_eq!(
            s.save(1, &[1u8; 240][..]),
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
