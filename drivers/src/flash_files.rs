//! Named files on NOR flash: a board's own flash as its SD card.
//!
//! [`FlashFileStore`] implements [`FileStore`] over a dedicated region of any
//! `embedded-storage` [`NorFlash`]. The region is cut into its erase sectors, and a file is a
//! list of them: a *head* sector that holds its name, its map and, once it is finished, its
//! commit record, and as many *data* sectors as its bytes need, anywhere in the region. A read
//! at any byte offset looks its sector up in the map (one small read) and reads the bytes: its
//! cost does not grow with the file's length, so a job can read a file of several megabytes a
//! few hundred bytes at a time while the machine moves.
//!
//! # Layout
//!
//! Every field lies at a multiple of the flash's *word*, the larger of its read and write
//! sizes and at least 4 bytes; the word must divide 64 bytes ([`FlashFileStore::open`]
//! refuses other flashes). Each field is written once after its sector was erased, in whole
//! words, bytes after the field padded with `0xFF`. Integers are `u32` little-endian; CRCs
//! are CRC-32 (IEEE). Offsets below are for a 4-byte word (the ESP32's, and most NOR parts'):
//!
//! | sector | bytes | field |
//! |---|---|---|
//! | every used sector | 0..16 | header: magic `FjF1`, the file's id, the sector's index in its file (0 for the head), CRC of the 12 bytes before it |
//! | head | 16..80 | the name: its length, then its bytes, as spelled when the file was created |
//! | head | 80..92 | commit record, written last: the size, the number of data sectors, CRC of the header, the name and these 8 bytes |
//! | head | 92.. | the map: one word per data sector, in order: the sector's number in the region |
//! | data | 16.. | the file's bytes: data sector `k` (index `k + 1`) holds bytes `k × D` to `(k + 1) × D`, `D` = sector − 16 |
//!
//! A 4 KiB sector thus holds 4 080 bytes of a file, and a head maps 1 001 data sectors: a file
//! holds at most 4 084 080 bytes ([`FlashFileStore::max_file_len`]), and less when the
//! region is smaller. Each file's head is a sector of its own, so a region of `n` sectors
//! holds at most `n` files, whatever their sizes.
//!
//! Ids are given out in increasing order, one per [`FileStore::create`]: at open the next one
//! is one past the largest of any header in the region, so no sector left by an earlier
//! write ever carries the id of a new one. The finished files are listed in the order of
//! their ids (the order they were created in).
//!
//! # Which files are seen
//!
//! [`FlashFileStore::open`] reads the header of every sector. A head with a valid header and
//! a valid commit record is a finished file if its map checks: it has as many entries as the
//! size needs, and each names a sector of the region whose header carries the file's id and
//! the entry's index. Of the heads of one name (compared without regard to case), the one of
//! the largest id that checks is the file; of more than `FILES` names, the `FILES` files of
//! the largest ids are kept. Every other sector is free: the sectors of removed, replaced and
//! unfinished files, and those no file ever used. Sectors of finished files are recognised by
//! the ids in their headers, so the store keeps no table of sectors: in RAM it keeps, per
//! finished file, its name, id, size, head and number of data sectors, and the state of the
//! file being written.
//!
//! # Writing and erasing
//!
//! - [`FileStore::create`] takes a free sector for the head and writes its header and name.
//! - [`FileStore::append`] writes whole words into the file's last data sector, taking a new
//!   one when it is full (its header, then its map entry); the bytes of an incomplete last
//!   word wait in RAM, in the sector already taken for them.
//! - [`FileStore::finish`] writes the last word, then the commit record; a file it replaces
//!   has its head erased, and its sectors are free.
//! - [`FileStore::remove`] erases the file's head; its data sectors are free from then on.
//!   It first erases any other head of that name with a commit record (an old version whose
//!   head a power cut kept from being erased, which would be found again without the newer
//!   one).
//! - [`FileStore::abandon`] only forgets the write: its sectors are free.
//!
//! A free sector is erased when it is taken, and only then, unless it reads erased throughout
//! already. Sectors are taken in turn from the one after the last taken, wrapping at the end
//! of the region (after a restart, from the one after the sector of the newest header), so
//! that erases spread over the whole region.
//!
//! So [`FileStore::create`] erases at most one sector, [`FileStore::append`] one for each
//! sector its bytes begin (one for a line of G-code), [`FileStore::finish`] and
//! [`FileStore::remove`] one (`remove` more only when older heads of that name were left by a
//! power cut or a failed erase). An erase takes 45 ms on the ESP32's flash, up to 400 ms,
//! during which a single-bank part runs nothing else: write and remove files while the machine
//! is at rest. Reads never erase and never write.
//!
//! # Power loss
//!
//! A head is a finished file only once its commit record is whole (its CRC checks), and the
//! commit record is written after every other byte of the file. A power cut
//! - in `create` or `append`, or in `finish` before the commit record is whole, leaves a head
//!   without a valid commit record: the file is not seen, and the old file of that name, if
//!   any, is untouched;
//! - in `finish` after the commit record is whole leaves both versions with valid commit
//!   records: the newer, of the larger id, is the one seen, whole;
//! - in `remove` leaves the file, or no file: its head is erased last, after any older
//!   version's;
//! - while a free sector is erased to be taken changes no file: the sector belonged to none.
//!
//! A header or map entry torn by a cut belongs to a file without a commit record. A finished
//! file's sectors are never written or erased while it is seen. After any cut, reopening
//! finds each file whole and exact as last finished, or its previous version, or none when it
//! was being removed; the sectors of the interrupted write are free again.
//!
//! # Errors
//!
//! [`FileError::Full`] is found before anything is written: no free sector for a head or for
//! the bytes, no room in the map, or `FILES` files already. A failed flash operation is
//! [`FileError::Device`]. When it fails in [`FileStore::append`] or [`FileStore::finish`],
//! what was written cannot be written again without an erase, so the write cannot go on:
//! `append` and `finish` then answer [`FileError::Device`] until it is abandoned (the
//! application abandons a write after any error).
//!
//! # Costs
//!
//! "Header read": one read of 16 bytes. Reads go through a 256-byte buffer, so no flash read
//! is longer than that.
//! - [`FileStore::read`] of `n` bytes: one map-entry read (one word) per sector the bytes lie
//!   in, and one read per 256 bytes of each.
//! - [`FileStore::file`], [`FileStore::size`], [`FileStore::writing`]: none (RAM).
//! - Taking a sector: one header read per sector looked at (the sectors of files passed over,
//!   and the one taken), then a read of the whole sector (16 reads for 4 KiB) or one erase.
//! - [`FileStore::append`]: one write per 256 bytes and per sector crossed, plus two writes for
//!   each sector taken.
//! - [`FileStore::remove`]: one header read per sector of the region, and one read of 76 bytes
//!   per head that is no file's (left by replaced or unfinished files).
//! - [`FlashFileStore::open`]: one header read per sector of the region; per head, one read of
//!   76 bytes, and per file kept, its map (one read per 64 entries) and one header read per
//!   data sector.
//!
//! # Execution context
//!
//! Thread. Every method blocks for its flash operations.

use core::ops::Range;

use embedded_storage::nor_flash::{NorFlash, NorFlashError};
use forja_hal_abstraction::files::{FileError, FileInfo, FileName, FileStore, MAX_NAME_LEN};
use forja_hal_abstraction::program::crc32_update;

use crate::storage::StorageError;

/// The first bytes of every sector header.
const MAGIC: [u8; 4] = *b"FjF1";
/// Bytes of a sector header: magic, id, index, CRC.
const HEADER_LEN: usize = 16;
/// Bytes of a head's name field: the length, then the name.
const NAME_LEN: usize = 1 + MAX_NAME_LEN;
/// Bytes of a commit record: size, data sectors, CRC.
const COMMIT_LEN: usize = 12;
/// The largest flash word this store handles.
const MAX_WORD: usize = 64;
/// The buffer every read and write of more than a field goes through.
const CHUNK: usize = 256;

/// Put `bytes` at `at` in `buf` (nothing when they do not fit).
fn put(buf: &mut [u8], at: usize, bytes: &[u8]) {
    if let Some(dst) = buf.get_mut(at..at + bytes.len()) {
        dst.copy_from_slice(bytes);
    }
}

/// The `u32` at `at` in `buf`.
fn u32_at(buf: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_le_bytes(buf.get(at..at + 4)?.try_into().ok()?))
}

/// The header of sector `index` of file `id`.
fn encode_header(id: u32, index: u32) -> [u8; HEADER_LEN] {
    let mut h = [0; HEADER_LEN];
    put(&mut h, 0, &MAGIC);
    put(&mut h, 4, &id.to_le_bytes());
    put(&mut h, 8, &index.to_le_bytes());
    let crc = crc32_update(0, h.get(..12).unwrap_or(&[]));
    put(&mut h, 12, &crc.to_le_bytes());
    h
}

/// The file id and index of a valid header.
fn decode_header(h: &[u8]) -> Option<(u32, u32)> {
    if h.get(..4)? != MAGIC || crc32_update(0, h.get(..12)?) != u32_at(h, 12)? {
        return None;
    }
    Some((u32_at(h, 4)?, u32_at(h, 8)?))
}

/// A head's name field.
fn encode_name(name: &FileName) -> [u8; NAME_LEN] {
    let mut field = [0xFF; NAME_LEN];
    let bytes = name.as_bytes();
    put(&mut field, 0, &[bytes.len() as u8]);
    put(&mut field, 1, bytes);
    field
}

/// The CRC of a commit record: over the head's header, its name field, the size and the
/// number of data sectors.
fn commit_crc(id: u32, name: &[u8], size: u32, data: u32) -> u32 {
    let mut crc = crc32_update(0, &encode_header(id, 0));
    crc = crc32_update(crc, name);
    crc = crc32_update(crc, &size.to_le_bytes());
    crc32_update(crc, &data.to_le_bytes())
}

/// Where the fields lie in a sector, for a flash's sizes (see the module's layout table).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Layout {
    /// The erase sector, bytes.
    sector: u32,
    /// The word: every field starts at a multiple of it and is written in whole words.
    word: u32,
    /// The header's bytes, whole words: where the name of a head and the bytes of a data
    /// sector begin.
    header: u32,
    /// Offset of the commit record in a head.
    commit_at: u32,
    /// Offset of the map in a head.
    map_at: u32,
    /// Entries a map holds: the most data sectors of a file.
    entries: u32,
    /// Bytes of a file a data sector holds.
    payload: u32,
}

impl Layout {
    /// The layout for `F`, if this store handles it: its read and write sizes divide
    /// [`MAX_WORD`], and its sector is a whole number of words with room for at least one
    /// map entry.
    fn of<F: NorFlash>() -> Option<Self> {
        let (read, write) = (F::READ_SIZE, F::WRITE_SIZE);
        if read == 0
            || write == 0
            || !MAX_WORD.is_multiple_of(read)
            || !MAX_WORD.is_multiple_of(write)
        {
            return None;
        }
        // Divisors of 64, so powers of two: the word is a multiple of both.
        let word = read.max(write).max(4);
        let round = |n: usize| n.div_ceil(word) * word;
        let header = round(HEADER_LEN);
        let commit_at = header + NAME_LEN;
        let map_at = commit_at + round(COMMIT_LEN);
        let sector = F::ERASE_SIZE;
        if !sector.is_multiple_of(word) || sector < map_at + word {
            return None;
        }
        let sector = u32::try_from(sector).ok()?;
        let payload = sector - header as u32;
        let entries = ((sector - map_at as u32) / word as u32).min(u32::MAX / payload);
        Some(Self {
            sector,
            word: word as u32,
            header: header as u32,
            commit_at: commit_at as u32,
            map_at: map_at as u32,
            entries,
            payload,
        })
    }

    /// Bytes of a commit record, whole words.
    fn commit_len(&self) -> usize {
        (self.map_at - self.commit_at) as usize
    }
}

/// A finished file, as the store keeps it in RAM.
#[derive(Debug, Clone, Copy)]
struct Entry {
    name: FileName,
    id: u32,
    /// Its head sector (from the region's start, in sectors).
    head: u32,
    size: u32,
    /// Its data sectors.
    data: u32,
}

/// The file being written.
#[derive(Debug, Clone, Copy)]
struct Writing {
    name: FileName,
    id: u32,
    head: u32,
    /// Data sectors taken and mapped; the last one is `last`.
    data: u32,
    last: u32,
    /// Sectors counted as the write's: its head, its data sectors, and any it was taking when
    /// a flash operation failed.
    taken: u32,
    /// Bytes on the flash: a whole number of words.
    flushed: u32,
    /// The bytes after them, fewer than a word: written once the word is complete, or by
    /// `finish`.
    tail: [u8; MAX_WORD],
    tail_len: usize,
    /// A flash operation failed: the write cannot go on.
    failed: bool,
}

impl Writing {
    fn size(&self) -> u32 {
        self.flushed + self.tail_len as u32
    }
}

/// Any flash error, as the file store contract has it.
fn device<E>(_: E) -> FileError {
    FileError::Device
}

/// Named files in a dedicated region of a NOR flash, at most `FILES` of them. See the
/// [module documentation](self) for the layout, the power-loss argument and the costs.
///
/// RAM: 84 bytes per file of `FILES` and 168 for the write: 2.9 KiB for 32 files.
///
/// Context: thread. Every method blocks for the flash; `create`, `append`, `finish` and
/// `remove` may erase a sector: write files while the machine is at rest.
#[derive(Debug)]
pub struct FlashFileStore<F, const FILES: usize = 32> {
    flash: F,
    /// Absolute offset of the region.
    base: u32,
    /// Sectors of the region.
    sectors: u32,
    layout: Layout,
    /// The finished files, from slot 0 on, in the order of their ids.
    files: [Option<Entry>; FILES],
    /// Sectors of the finished files.
    used: u32,
    /// The id of the next file; `None` once ids are exhausted.
    next_id: Option<u32>,
    /// Where the search for a free sector begins.
    cursor: u32,
    writing: Option<Writing>,
}

impl<F: NorFlash, const FILES: usize> FlashFileStore<F, FILES> {
    /// Open the files kept in `region` of `flash` (absolute byte offsets): read every sector's
    /// header, and each finished file's map (see the [module documentation](self), "Which
    /// files are seen"). Anything else in the region (an erased flash, another format's data,
    /// the remains of an interrupted write) is free room. Nothing is written.
    ///
    /// Errors: [`StorageError::BadRegion`] when the region is empty, not a whole number of
    /// erase sectors or beyond the flash, or when the flash's read or write size does not
    /// divide 64 bytes, or its erase sector is too small for a head with one map entry;
    /// [`StorageError::Flash`] when a read fails.
    pub fn open(flash: F, region: Range<u32>) -> Result<Self, StorageError> {
        let layout = Layout::of::<F>().ok_or(StorageError::BadRegion)?;
        let len = region.end.saturating_sub(region.start);
        if len == 0
            || !region.start.is_multiple_of(layout.sector)
            || !len.is_multiple_of(layout.sector)
            || region.end as usize > flash.capacity()
        {
            return Err(StorageError::BadRegion);
        }
        let mut store = Self {
            flash,
            base: region.start,
            sectors: len / layout.sector,
            layout,
            files: [None; FILES],
            used: 0,
            next_id: Some(0),
            cursor: 0,
            writing: None,
        };
        let flash_error = |e: F::Error| StorageError::Flash(e.kind());
        // The newest header: its id, index and sector.
        let mut newest: Option<(u32, u32, u32)> = None;
        for sector in 0..store.sectors {
            let Some((id, index)) = store.read_header(sector).map_err(flash_error)? else {
                continue;
            };
            if newest.is_none_or(|(i, k, _)| (id, index) > (i, k)) {
                newest = Some((id, index, sector));
            }
            if index == 0
                && let Some(head) = store.read_head(sector, id).map_err(flash_error)?
            {
                store.consider(head).map_err(flash_error)?;
            }
        }
        store
            .files
            .sort_unstable_by_key(|e| e.map_or(u64::MAX, |e| u64::from(e.id)));
        store.used = store.finished().map(|e| 1 + e.data).sum();
        if let Some((id, _, sector)) = newest {
            store.next_id = id.checked_add(1);
            store.cursor = (sector + 1) % store.sectors;
        }
        Ok(store)
    }

    /// The most bytes one file can hold: what a full map maps, whatever the room left.
    pub fn max_file_len(&self) -> u32 {
        self.layout.entries * self.layout.payload
    }

    /// Bytes of a file each data sector holds.
    pub fn sector_payload(&self) -> u32 {
        self.layout.payload
    }

    /// Sectors free for a new file or for the file being written: a file of `n` bytes takes
    /// one for its head and `n` / [`sector_payload`](Self::sector_payload) (rounded up) for
    /// its bytes.
    pub fn free_sectors(&self) -> u32 {
        let taken = self.writing.map_or(0, |w| w.taken);
        self.sectors.saturating_sub(self.used + taken)
    }

    /// The flash.
    pub fn flash_mut(&mut self) -> &mut F {
        &mut self.flash
    }

    /// Give the flash back.
    pub fn into_inner(self) -> F {
        self.flash
    }

    /// The finished files, in order.
    fn finished(&self) -> impl Iterator<Item = &Entry> {
        self.files.iter().flatten()
    }

    /// The slot of the finished file `name`.
    fn position(&self, name: &FileName) -> Option<usize> {
        self.finished().position(|e| e.name == *name)
    }

    fn entry(&self, name: &FileName) -> Result<Entry, FileError> {
        self.finished()
            .find(|e| e.name == *name)
            .copied()
            .ok_or(FileError::NotFound)
    }

    /// Whether `id` is a finished file's.
    fn is_finished(&self, id: u32) -> bool {
        self.finished().any(|e| e.id == id)
    }

    /// Take the file in slot `pos` out, the later ones moving down.
    fn take(&mut self, pos: usize) -> Option<Entry> {
        let entry = self.files.get_mut(pos)?.take()?;
        if let Some(rest) = self.files.get_mut(pos..) {
            rest.rotate_left(1);
        }
        Some(entry)
    }

    /// Add a file after the others; `false` when every slot is taken.
    fn push(&mut self, entry: Entry) -> bool {
        match self.files.iter_mut().find(|e| e.is_none()) {
            Some(slot) => {
                *slot = Some(entry);
                true
            }
            None => false,
        }
    }

    /// Absolute offset of byte `offset` of `sector`.
    fn address(&self, sector: u32, offset: u32) -> u32 {
        self.base + sector * self.layout.sector + offset
    }

    /// The file id and index in the header of `sector`, if it is valid.
    fn read_header(&mut self, sector: u32) -> Result<Option<(u32, u32)>, F::Error> {
        let mut h = [0; MAX_WORD];
        let len = self.layout.header as usize;
        let at = self.address(sector, 0);
        let buf = h.get_mut(..len).unwrap_or(&mut []);
        self.flash.read(at, buf)?;
        Ok(decode_header(buf))
    }

    /// The finished file whose head is `sector`, of file `id`, if its commit record is valid.
    fn read_head(&mut self, sector: u32, id: u32) -> Result<Option<Entry>, F::Error> {
        let mut buf = [0; NAME_LEN + MAX_WORD];
        let len = NAME_LEN + self.layout.commit_len();
        let at = self.address(sector, self.layout.header);
        let buf = buf.get_mut(..len).unwrap_or(&mut []);
        self.flash.read(at, buf)?;
        let field = buf.get(..NAME_LEN).unwrap_or(&[]);
        let commit = |at: usize| u32_at(buf, NAME_LEN + at);
        let (Some(size), Some(data), Some(crc)) = (commit(0), commit(4), commit(8)) else {
            return Ok(None);
        };
        if commit_crc(id, field, size, data) != crc {
            return Ok(None);
        }
        let len = usize::from(field.first().copied().unwrap_or(0));
        let name = field.get(1..1 + len).and_then(|n| FileName::new(n).ok());
        Ok(name.map(|name| Entry {
            name,
            id,
            head: sector,
            size,
            data,
        }))
    }

    /// At open: keep `head` if it is the newest of its name that checks, and among the
    /// `FILES` newest names.
    fn consider(&mut self, head: Entry) -> Result<(), F::Error> {
        let slot = match self.position(&head.name) {
            Some(pos) if self.files.get(pos).copied().flatten().map(|e| e.id) > Some(head.id) => {
                return Ok(());
            }
            Some(pos) => pos,
            None => match self.files.iter().position(Option::is_none) {
                Some(free) => free,
                None => {
                    // Every slot is taken: the oldest gives way to a newer file.
                    let oldest = self
                        .files
                        .iter()
                        .enumerate()
                        .filter_map(|(i, e)| e.map(|e| (i, e.id)))
                        .min_by_key(|&(_, id)| id);
                    match oldest {
                        Some((pos, id)) if id < head.id => pos,
                        _ => return Ok(()),
                    }
                }
            },
        };
        if self.check(&head)?
            && let Some(dst) = self.files.get_mut(slot)
        {
            *dst = Some(head);
        }
        Ok(())
    }

    /// Whether the map of `head` maps its size, each entry to a sector of its own.
    fn check(&mut self, head: &Entry) -> Result<bool, F::Error> {
        let l = self.layout;
        if head.data > l.entries || head.data != head.size.div_ceil(l.payload) {
            return Ok(false);
        }
        let word = l.word as usize;
        let per_read = (CHUNK / word) as u32;
        let mut buf = [0; CHUNK];
        let mut k = 0;
        while k < head.data {
            let n = (head.data - k).min(per_read);
            let at = self.address(head.head, l.map_at + k * l.word);
            let entries = buf.get_mut(..n as usize * word).unwrap_or(&mut []);
            self.flash.read(at, entries)?;
            for i in 0..n {
                let Some(sector) = u32_at(&buf, i as usize * word) else {
                    return Ok(false);
                };
                if sector >= self.sectors || self.read_header(sector)? != Some((head.id, k + i + 1))
                {
                    return Ok(false);
                }
            }
            k += n;
        }
        Ok(true)
    }

    /// Whether every byte of `sector` reads erased.
    fn is_erased(&mut self, sector: u32) -> Result<bool, F::Error> {
        let mut buf = [0; CHUNK];
        let mut offset = 0;
        while offset < self.layout.sector {
            let n = (self.layout.sector - offset).min(CHUNK as u32);
            let at = self.address(sector, offset);
            let part = buf.get_mut(..n as usize).unwrap_or(&mut []);
            self.flash.read(at, part)?;
            if part.iter().any(|&b| b != 0xFF) {
                return Ok(false);
            }
            offset += n;
        }
        Ok(true)
    }

    fn erase(&mut self, sector: u32) -> Result<(), FileError> {
        let at = self.address(sector, 0);
        self.flash
            .erase(at, at + self.layout.sector)
            .map_err(device)
    }

    fn write(&mut self, sector: u32, offset: u32, bytes: &[u8]) -> Result<(), FileError> {
        let at = self.address(sector, offset);
        self.flash.write(at, bytes).map_err(device)
    }

    /// Take a free sector, erased: the first from the cursor on whose header is not that of a
    /// finished file or of `writing`, erased unless it reads erased already. `None` when
    /// there is none.
    fn allocate(&mut self, writing: Option<u32>) -> Result<Option<u32>, FileError> {
        for i in 0..self.sectors {
            let sector = (self.cursor + i) % self.sectors;
            let header = self.read_header(sector).map_err(device)?;
            if let Some((id, _)) = header
                && (Some(id) == writing || self.is_finished(id))
            {
                continue;
            }
            if header.is_some() || !self.is_erased(sector).map_err(device)? {
                self.erase(sector)?;
            }
            self.cursor = (sector + 1) % self.sectors;
            return Ok(Some(sector));
        }
        Ok(None)
    }

    /// The sector of the written file's data sector `k`: its last one, or a new one (taken,
    /// its header and map entry written) when `k` is the next.
    fn data_sector(&mut self, w: &mut Writing, k: u32) -> Result<u32, FileError> {
        if k < w.data {
            return Ok(w.last);
        }
        let l = self.layout;
        w.taken += 1;
        let sector = self.allocate(Some(w.id))?.ok_or(FileError::Device)?;
        let mut buf = [0xFF; MAX_WORD];
        put(&mut buf, 0, &encode_header(w.id, k + 1));
        self.write(sector, 0, buf.get(..l.header as usize).unwrap_or(&[]))?;
        let mut entry = [0xFF; MAX_WORD];
        put(&mut entry, 0, &sector.to_le_bytes());
        let entry = entry.get(..l.word as usize).unwrap_or(&[]);
        self.write(w.head, l.map_at + k * l.word, entry)?;
        w.data += 1;
        w.last = sector;
        Ok(sector)
    }

    /// Write `bytes` after the written file's, whole words; the rest waits in its tail, in
    /// a sector taken for it.
    fn write_bytes(&mut self, w: &mut Writing, bytes: &[u8]) -> Result<(), FileError> {
        let l = self.layout;
        let word = l.word as usize;
        let mut rest = bytes;
        loop {
            let held = w.tail_len;
            let pending = held + rest.len();
            if pending < word {
                put(&mut w.tail, held, rest);
                w.tail_len = pending;
                break;
            }
            let within = w.flushed % l.payload;
            let sector = self.data_sector(w, w.flushed / l.payload)?;
            let room = (l.payload - within) as usize;
            let whole = pending.min(room).min(CHUNK) / word * word;
            let from_rest = whole - held;
            let mut chunk = [0xFF; CHUNK];
            put(&mut chunk, 0, w.tail.get(..held).unwrap_or(&[]));
            put(&mut chunk, held, rest.get(..from_rest).unwrap_or(&[]));
            self.write(sector, l.header + within, chunk.get(..whole).unwrap_or(&[]))?;
            w.flushed += whole as u32;
            w.tail_len = 0;
            rest = rest.get(from_rest..).unwrap_or(&[]);
        }
        if w.tail_len > 0 {
            self.data_sector(w, w.flushed / l.payload)?;
        }
        Ok(())
    }

    /// Write the written file's last word and its commit record.
    fn commit(&mut self, w: &Writing) -> Result<(), FileError> {
        let l = self.layout;
        if w.tail_len > 0 {
            let mut last = [0xFF; MAX_WORD];
            put(&mut last, 0, w.tail.get(..w.tail_len).unwrap_or(&[]));
            let at = l.header + w.flushed % l.payload;
            self.write(w.last, at, last.get(..l.word as usize).unwrap_or(&[]))?;
        }
        let size = w.size();
        let crc = commit_crc(w.id, &encode_name(&w.name), size, w.data);
        let mut record = [0xFF; MAX_WORD];
        put(&mut record, 0, &size.to_le_bytes());
        put(&mut record, 4, &w.data.to_le_bytes());
        put(&mut record, 8, &crc.to_le_bytes());
        let record = record.get(..l.commit_len()).unwrap_or(&[]);
        self.write(w.head, l.commit_at, record)
    }

    /// The sector of data sector `k` of the file whose head is `head`, from its map.
    fn mapped(&mut self, head: u32, k: u32) -> Result<u32, FileError> {
        let l = self.layout;
        let mut entry = [0; MAX_WORD];
        let entry = entry.get_mut(..l.word as usize).unwrap_or(&mut []);
        let at = self.address(head, l.map_at + k * l.word);
        self.flash.read(at, entry).map_err(device)?;
        u32_at(entry, 0)
            .filter(|&s| s < self.sectors)
            .ok_or(FileError::Device)
    }

    /// Read `out.len()` bytes from byte `offset` of `sector` (within the sector), through
    /// reads of at most [`CHUNK`] bytes aligned to the flash's read size.
    fn read_bytes(&mut self, sector: u32, offset: u32, out: &mut [u8]) -> Result<(), FileError> {
        let align = F::READ_SIZE as u32;
        let mut chunk = [0; CHUNK];
        let mut done = 0;
        while done < out.len() {
            let at = self.address(sector, offset + done as u32);
            let start = at - at % align;
            let skip = (at - start) as usize;
            let want = (out.len() - done + skip).min(CHUNK);
            let len = want.div_ceil(align as usize) * align as usize;
            let buf = chunk.get_mut(..len).unwrap_or(&mut []);
            self.flash.read(start, buf).map_err(device)?;
            let n = want - skip;
            let src = chunk.get(skip..want).ok_or(FileError::Device)?;
            let dst = out.get_mut(done..done + n).ok_or(FileError::Device)?;
            dst.copy_from_slice(src);
            done += n;
        }
        Ok(())
    }
}

impl<F: NorFlash, const FILES: usize> FileStore for FlashFileStore<F, FILES> {
    /// No flash operation.
    fn file(&mut self, index: usize) -> Result<Option<FileInfo>, FileError> {
        Ok(self.finished().nth(index).map(|e| FileInfo {
            name: e.name,
            size: e.size,
        }))
    }

    /// No flash operation.
    fn size(&mut self, name: &FileName) -> Result<u32, FileError> {
        Ok(self.entry(name)?.size)
    }

    /// Per sector the bytes lie in: one map-entry read, and one read per 256 bytes.
    fn read(&mut self, name: &FileName, offset: u32, buf: &mut [u8]) -> Result<usize, FileError> {
        let e = self.entry(name)?;
        let payload = self.layout.payload;
        let from = offset.min(e.size);
        let n = buf.len().min((e.size - from) as usize);
        let mut done = 0;
        while done < n {
            let at = from + done as u32;
            let within = at % payload;
            let sector = self.mapped(e.head, at / payload)?;
            let len = (n - done).min((payload - within) as usize);
            let out = buf.get_mut(done..done + len).ok_or(FileError::Device)?;
            self.read_bytes(sector, self.layout.header + within, out)?;
            done += len;
        }
        Ok(n)
    }

    /// Erases the file's head (and any older head of that name a power cut left), after
    /// reading every sector's header.
    fn remove(&mut self, name: &FileName) -> Result<(), FileError> {
        let pos = self.position(name).ok_or(FileError::NotFound)?;
        let e = self
            .files
            .get(pos)
            .copied()
            .flatten()
            .ok_or(FileError::NotFound)?;
        let writing = self.writing.map(|w| w.id);
        for sector in 0..self.sectors {
            if sector == e.head {
                continue;
            }
            let Some((id, 0)) = self.read_header(sector).map_err(device)? else {
                continue;
            };
            if Some(id) == writing || self.is_finished(id) {
                continue;
            }
            if self
                .read_head(sector, id)
                .map_err(device)?
                .is_some_and(|old| old.name == *name)
            {
                self.erase(sector)?;
            }
        }
        self.erase(e.head)?;
        self.take(pos);
        self.used -= 1 + e.data;
        Ok(())
    }

    /// Takes a sector for the head (at most one erase) and writes its header and name.
    fn create(&mut self, name: &FileName) -> Result<(), FileError> {
        if self.writing.is_some() {
            return Err(FileError::Busy);
        }
        let replaces = self.position(name).is_some();
        if (!replaces && self.finished().count() >= FILES) || self.free_sectors() == 0 {
            return Err(FileError::Full);
        }
        let id = self.next_id.ok_or(FileError::Full)?;
        let head = self.allocate(None)?.ok_or(FileError::Full)?;
        self.next_id = id.checked_add(1);
        let header = self.layout.header as usize;
        let mut buf = [0xFF; MAX_WORD + NAME_LEN];
        put(&mut buf, 0, &encode_header(id, 0));
        put(&mut buf, header, &encode_name(name));
        self.write(head, 0, buf.get(..header + NAME_LEN).unwrap_or(&[]))?;
        self.writing = Some(Writing {
            name: *name,
            id,
            head,
            data: 0,
            last: head,
            taken: 1,
            flushed: 0,
            tail: [0xFF; MAX_WORD],
            tail_len: 0,
            failed: false,
        });
        Ok(())
    }

    /// Writes whole words; takes a sector (at most one erase) for each sector the bytes begin.
    fn append(&mut self, bytes: &[u8]) -> Result<(), FileError> {
        let w = self.writing.ok_or(FileError::NotWriting)?;
        if w.failed {
            return Err(FileError::Device);
        }
        let size = u32::try_from(bytes.len())
            .ok()
            .and_then(|n| w.size().checked_add(n))
            .filter(|&size| size <= self.max_file_len())
            .ok_or(FileError::Full)?;
        let more = size.div_ceil(self.layout.payload).saturating_sub(w.data);
        if more > self.free_sectors() {
            return Err(FileError::Full);
        }
        let mut w = w;
        let written = self.write_bytes(&mut w, bytes);
        w.failed = written.is_err();
        self.writing = Some(w);
        written
    }

    /// Writes the last word and the commit record; erases the head of the file it replaces.
    /// A failure of that erase is not reported (the new file is finished):
    /// [`FileStore::remove`] erases the old head later.
    fn finish(&mut self) -> Result<(), FileError> {
        let w = self.writing.ok_or(FileError::NotWriting)?;
        if w.failed {
            return Err(FileError::Device);
        }
        let replaces = self.position(&w.name);
        if replaces.is_none() && self.finished().count() >= FILES {
            return Err(FileError::Full);
        }
        if let Err(e) = self.commit(&w) {
            self.writing = Some(Writing { failed: true, ..w });
            return Err(e);
        }
        self.writing = None;
        if let Some(old) = replaces.and_then(|pos| self.take(pos)) {
            self.used -= 1 + old.data;
            let _ = self.erase(old.head);
        }
        let entry = Entry {
            name: w.name,
            id: w.id,
            head: w.head,
            size: w.size(),
            data: w.data,
        };
        if !self.push(entry) {
            return Err(FileError::Device);
        }
        self.used += 1 + w.data;
        Ok(())
    }

    /// No flash operation.
    fn abandon(&mut self) -> Result<(), FileError> {
        self.writing = None;
        Ok(())
    }

    fn writing(&self) -> Option<FileName> {
        self.writing.map(|w| w.name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ram_flash::RamNorFlash;
    use forja_hal_abstraction::files::conformance;
    use std::collections::BTreeMap;

    /// 18 sectors of 256 bytes: a file crosses a sector every 240 bytes.
    type Flash = RamNorFlash<{ 18 * 256 }, 4, 256>;
    /// Sectors 2..18 of the flash: 16 sectors.
    const REGION: Range<u32> = 512..18 * 256;
    type Store = FlashFileStore<Flash, 4>;

    fn name(s: &str) -> FileName {
        FileName::new(s.as_bytes()).unwrap()
    }

    fn open(flash: Flash) -> Store {
        FlashFileStore::open(flash, REGION).unwrap()
    }

    fn reopen(store: Store) -> Store {
        open(store.into_inner())
    }

    /// Write `bytes` as `n`, appended 37 bytes at a time (so that words are split).
    fn write<S: FileStore + ?Sized>(store: &mut S, n: &str, bytes: &[u8]) -> Result<(), FileError> {
        store.create(&name(n))?;
        for part in bytes.chunks(37) {
            store.append(part)?;
        }
        store.finish()
    }

    fn contents<S: FileStore + ?Sized>(store: &mut S, n: &str) -> Result<Vec<u8>, FileError> {
        let size = store.size(&name(n))? as usize;
        let mut buf = vec![0; size + 5];
        let len = store.read(&name(n), 0, &mut buf)?;
        buf.truncate(len);
        Ok(buf)
    }

    fn listing<S: FileStore + ?Sized>(store: &mut S) -> Vec<(String, u32)> {
        (0..)
            .map_while(|i| store.file(i).unwrap())
            .map(|f| (f.name.as_str().to_string(), f.size))
            .collect()
    }

    /// `len` bytes that differ from one position to the next and from one `seed` to another.
    fn pattern(seed: u8, len: usize) -> Vec<u8> {
        (0..len)
            .map(|i| (i.wrapping_mul(7) ^ (i >> 8) ^ (i >> 16)) as u8 ^ seed.wrapping_mul(0x35))
            .collect()
    }

    #[test]
    fn the_layout_follows_the_flash_word() {
        assert_eq!(
            Layout::of::<Flash>(),
            Some(Layout {
                sector: 256,
                word: 4,
                header: 16,
                commit_at: 80,
                map_at: 92,
                entries: 41,
                payload: 240,
            })
        );
        let esp = Layout::of::<RamNorFlash<4096, 4, 4096>>().unwrap();
        assert_eq!((esp.entries, esp.payload), (1001, 4080));
        let wide = Layout::of::<RamNorFlash<1024, 64, 256>>().unwrap();
        assert_eq!(
            (wide.header, wide.commit_at, wide.map_at, wide.entries),
            (64, 128, 192, 1)
        );
        // A word that does not divide 64 bytes; a sector too small for a head.
        assert_eq!(Layout::of::<RamNorFlash<960, 48, 480>>(), None);
        assert_eq!(Layout::of::<RamNorFlash<1024, 4, 64>>(), None);
        assert_eq!(
            encode_header(7, 3)[..12],
            [b'F', b'j', b'F', b'1', 7, 0, 0, 0, 3, 0, 0, 0]
        );
        assert_eq!(decode_header(&encode_header(7, 3)), Some((7, 3)));
        let mut torn = encode_header(7, 3);
        torn[5] = 1;
        assert_eq!(decode_header(&torn), None);
        assert_eq!(decode_header(&[0xFF; 16]), None);
    }

    #[test]
    fn bad_regions_are_refused() {
        let open = |r: Range<u32>| FlashFileStore::<Flash>::open(Flash::new(), r).err();
        assert_eq!(open(512..512), Some(StorageError::BadRegion));
        assert_eq!(open(100..612), Some(StorageError::BadRegion));
        assert_eq!(open(512..700), Some(StorageError::BadRegion));
        assert_eq!(open(512..5120), Some(StorageError::BadRegion));
        assert_eq!(
            open(Range {
                start: 1024,
                end: 512
            }),
            Some(StorageError::BadRegion)
        );
        let small = RamNorFlash::<1024, 4, 64>::new();
        assert_eq!(
            FlashFileStore::<_>::open(small, 0..1024).err(),
            Some(StorageError::BadRegion)
        );
        assert_eq!(open(0..256), None, "one sector: room for one empty file");
    }

    #[test]
    fn keeps_the_file_store_contract() {
        conformance::all(|| open(Flash::new()));
        conformance::all_restarting(|| open(Flash::new()), reopen);
    }

    #[test]
    fn files_are_listed_in_the_order_they_were_created_also_after_a_reopen() {
        let mut s = open(Flash::new());
        write(&mut s, "a.g", b"first").unwrap();
        write(&mut s, "b.g", b"bee").unwrap();
        write(&mut s, "A.G", b"second version").unwrap();
        let expected = [("b.g".to_string(), 3), ("A.G".to_string(), 14)];
        assert_eq!(
            listing(&mut s),
            expected,
            "replaced, not added, last spelling"
        );
        let mut s = reopen(s);
        assert_eq!(listing(&mut s), expected);
        write(&mut s, "c.g", &pattern(3, 600)).unwrap();
        s.create(&name("d.g")).unwrap();
        s.append(b"ddd").unwrap();
        s.remove(&name("B.g")).unwrap();
        s.finish().unwrap();
        // A file removed while its new version is written: the new one is created last.
        s.create(&name("a.g")).unwrap();
        s.append(b"new").unwrap();
        s.remove(&name("a.g")).unwrap();
        s.finish().unwrap();
        let expected = [
            ("c.g".to_string(), 600),
            ("d.g".to_string(), 3),
            ("a.g".to_string(), 3),
        ];
        assert_eq!(listing(&mut s), expected);
        let mut s = reopen(s);
        assert_eq!(listing(&mut s), expected);
        assert_eq!(contents(&mut s, "a.g").unwrap(), b"new");
        assert_eq!(contents(&mut s, "c.g").unwrap(), pattern(3, 600));
        assert_eq!(contents(&mut s, "d.g").unwrap(), b"ddd");
    }

    #[test]
    fn room_is_bounded_in_bytes_and_in_files() {
        let mut s = FlashFileStore::<Flash, 2>::open(Flash::new(), REGION).unwrap();
        assert_eq!(s.free_sectors(), 16);
        // 5 sectors: a head and 4 of 240 bytes.
        write(&mut s, "a.g", &[b'a'; 961]).unwrap();
        assert_eq!(s.free_sectors(), 10);
        // The rest: a head and 9 sectors.
        s.create(&name("b.g")).unwrap();
        s.append(&[b'b'; 9 * 240 - 2]).unwrap();
        assert_eq!(s.append(&[b'b'; 3]), Err(FileError::Full));
        // The write is as it was: it goes on and can be finished.
        s.append(&[b'b'; 2]).unwrap();
        assert_eq!(s.append(b"b"), Err(FileError::Full));
        assert_eq!(s.free_sectors(), 0);
        s.finish().unwrap();
        assert_eq!(s.size(&name("b.g")), Ok(9 * 240));
        assert_eq!(s.create(&name("c.g")), Err(FileError::Full));
        // Replacing needs no new slot, but room for both files until the new one is
        // finished; then the old one's sectors are free.
        assert_eq!(
            s.create(&name("a.g")),
            Err(FileError::Full),
            "no sector left"
        );
        s.remove(&name("b.g")).unwrap();
        write(&mut s, "a.g", b"xy").unwrap();
        assert_eq!(s.size(&name("a.g")), Ok(2));
        assert_eq!(s.free_sectors(), 14);
        write(&mut s, "c.g", &[b'c'; 13 * 240]).unwrap();
        assert_eq!(s.create(&name("d.g")), Err(FileError::Full), "no slot");
        assert_eq!(listing(&mut s).len(), 2);
        // A file is at most what its map maps.
        let mut s =
            FlashFileStore::<_, 2>::open(RamNorFlash::<{ 64 * 256 }, 4, 256>::new(), 0..64 * 256)
                .unwrap();
        assert_eq!(s.max_file_len(), 41 * 240);
        s.create(&name("long.g")).unwrap();
        s.append(&vec![b'l'; 41 * 240]).unwrap();
        assert_eq!(s.append(b"l"), Err(FileError::Full));
        s.finish().unwrap();
        assert_eq!(s.free_sectors(), 64 - 42);
    }

    #[test]
    fn reopening_finds_every_finished_file_and_forgets_the_write() {
        let mut s = open(Flash::new());
        let files = [
            ("Part.GCO", pattern(1, 723)),
            ("empty.g", Vec::new()),
            ("long_name_of_a_bracket_v2.gcode", vec![b'1']),
        ];
        for (n, bytes) in &files {
            write(&mut s, n, bytes).unwrap();
        }
        s.create(&name("half.g")).unwrap();
        s.append(&pattern(3, 300)).unwrap();
        let free = s.free_sectors();
        let mut s = reopen(s);
        assert_eq!(s.writing(), None);
        assert_eq!(
            s.free_sectors(),
            free + 3,
            "the write's head and 2 data sectors"
        );
        assert_eq!(s.free_sectors(), 16 - 5 - 1 - 2);
        let names: Vec<_> = files
            .iter()
            .map(|(n, b)| (n.to_string(), b.len() as u32))
            .collect();
        assert_eq!(listing(&mut s), names, "in the order they were created");
        for (n, bytes) in &files {
            assert_eq!(&contents(&mut s, &n.to_lowercase()).unwrap(), bytes, "{n}");
        }
        // New files go after them, also after another reopen.
        write(&mut s, "next.g", b"n").unwrap();
        let mut s = reopen(s);
        assert_eq!(listing(&mut s).last().unwrap().0, "next.g");
    }

    #[test]
    fn reads_at_any_offset_and_across_sectors() {
        let mut s = open(Flash::new());
        let a = pattern(4, 1000);
        let b = pattern(5, 481);
        write(&mut s, "a.g", &a).unwrap();
        write(&mut s, "b.g", &b).unwrap();
        let mut s = reopen(s);
        for (n, bytes) in [("a.g", &a), ("b.g", &b)] {
            for len in [1, 3, 17, 239, 240, 241, 600, 1100] {
                for at in 0..=bytes.len() + 2 {
                    let mut buf = vec![0; len];
                    let got = s.read(&name(n), at as u32, &mut buf).unwrap();
                    let want = bytes.get(at..).unwrap_or(&[]);
                    let want = &want[..want.len().min(len)];
                    assert_eq!(&buf[..got], want, "{n} at {at}, {len} bytes");
                }
            }
        }
    }

    #[test]
    fn several_files_are_written_one_after_the_other_and_read_in_any_order() {
        let mut s = open(Flash::new());
        let sizes = [100, 250, 5, 700];
        for (i, &len) in sizes.iter().enumerate() {
            write(&mut s, &format!("f{i}.g"), &pattern(i as u8, len)).unwrap();
        }
        for round in 0..3 {
            for (i, &len) in sizes.iter().enumerate().rev() {
                let mut buf = [0; 50];
                let at = (round * 37) % len;
                let n = s
                    .read(&name(&format!("F{i}.G")), at as u32, &mut buf)
                    .unwrap();
                assert_eq!(&buf[..n], &pattern(i as u8, len)[at..(at + 50).min(len)]);
            }
        }
    }

    #[test]
    fn removing_or_replacing_frees_room() {
        let mut s = open(Flash::new());
        // Fill with files of 2 sectors each (a head and one of data).
        let mut filled = 0;
        while write(&mut s, &format!("f{filled}.g"), &pattern(filled, 200)).is_ok() {
            filled += 1;
        }
        assert_eq!((filled, s.free_sectors()), (4, 8), "four slots");
        s.abandon().unwrap();
        for round in 0..5u8 {
            for i in 0..4 {
                s.remove(&name(&format!("f{i}.g"))).unwrap();
            }
            let mut s2 = reopen(s);
            assert_eq!(s2.free_sectors(), 16);
            // Fill again with larger files: 4 sectors each.
            for i in 0..4 {
                write(&mut s2, &format!("f{i}.g"), &pattern(round + i, 700)).unwrap();
            }
            assert_eq!(s2.free_sectors(), 0);
            assert_eq!(s2.create(&name("x.g")), Err(FileError::Full));
            s = reopen(s2);
            for i in 0..4 {
                assert_eq!(
                    contents(&mut s, &format!("f{i}.g")).unwrap(),
                    pattern(round + i, 700)
                );
            }
        }
        // Replacing: the old version's sectors are free once the new one is finished.
        s.remove(&name("f0.g")).unwrap();
        s.remove(&name("f1.g")).unwrap();
        assert_eq!(s.free_sectors(), 8);
        for round in 0..6 {
            write(
                &mut s,
                "f2.g",
                &pattern(round, 100 + 100 * usize::from(round)),
            )
            .unwrap();
            assert_eq!(
                s.free_sectors(),
                16 - 4 - 1 - (100 + 100 * u32::from(round)).div_ceil(240)
            );
        }
        let mut s = reopen(s);
        assert_eq!(contents(&mut s, "f2.g").unwrap(), pattern(5, 600));
    }

    #[test]
    fn sectors_are_taken_in_turn_round_the_region() {
        let mut s = open(Flash::new());
        let mut heads = Vec::new();
        for i in 0..10 {
            write(&mut s, "w.g", &pattern(i, 200)).unwrap();
            heads.push(s.files[0].unwrap().head);
            s.remove(&name("w.g")).unwrap();
        }
        assert_eq!(heads, [0, 2, 4, 6, 8, 10, 12, 14, 0, 2]);
        // After a restart, from the sector after the newest header on.
        let mut s = reopen(s);
        write(&mut s, "w.g", b"w").unwrap();
        assert_eq!(s.files[0].unwrap().head, 4);
    }

    #[test]
    fn each_call_erases_at_most_one_sector() {
        let mut s = open(Flash::new());
        // Every sector written, then free: each must be erased before it is used again.
        write(&mut s, "a.g", &pattern(1, 15 * 240)).unwrap();
        s.remove(&name("a.g")).unwrap();
        let erased = |s: &mut Store| s.flash_mut().pages_erased();
        let check = |s: &mut Store, call: &dyn Fn(&mut Store) -> Result<(), FileError>| {
            let before = erased(s);
            call(s).unwrap();
            erased(s) - before
        };
        assert!(check(&mut s, &|s| s.create(&name("b.g"))) <= 1);
        let mut total = 0;
        for part in pattern(2, 1000).chunks(100) {
            let n = check(&mut s, &|s| s.append(part));
            assert!(n <= 1);
            total += n;
        }
        assert_eq!(total, 5, "one for each data sector");
        assert_eq!(check(&mut s, &|s| s.finish()), 0);
        // Replacing erases the old head at finish.
        s.create(&name("b.g")).unwrap();
        for part in pattern(3, 1000).chunks(100) {
            assert!(check(&mut s, &|s| s.append(part)) <= 1);
        }
        assert_eq!(check(&mut s, &|s| s.finish()), 1);
        assert_eq!(check(&mut s, &|s| s.remove(&name("b.g"))), 1);
        // Opening never erases, and neither do reads.
        write(&mut s, "c.g", &pattern(4, 500)).unwrap();
        let before = erased(&mut s);
        let mut s = reopen(s);
        assert_eq!(contents(&mut s, "c.g").unwrap(), pattern(4, 500));
        assert_eq!(erased(&mut s), before);
    }

    #[test]
    fn a_file_of_megabytes_reads_at_any_offset_with_a_few_flash_reads() {
        const BIG: usize = 4 << 20;
        type Big<'a> = RamNorFlash<BIG, 4, 4096, &'a mut [u8; BIG]>;
        let mut mem: Box<[u8; BIG]> = vec![0xFF; BIG].into_boxed_slice().try_into().unwrap();
        let region = 0..BIG as u32;
        let mut s =
            FlashFileStore::<Big, 32>::open(Big::with_memory(&mut mem), region.clone()).unwrap();
        assert_eq!(s.max_file_len(), 1001 * 4080);
        let print = pattern(9, 3_500_000);
        s.create(&name("print.gcode")).unwrap();
        for line in print.chunks(509) {
            s.append(line).unwrap();
        }
        s.finish().unwrap();
        write(&mut s, "cube.g", &pattern(8, 10_000)).unwrap();
        assert_eq!(s.free_sectors(), 1024 - 1 - 858 - 1 - 3);
        let mut buf = [0; 300];
        for at in [
            0, 4079, 4080, 4081, 1_000_000, 2_222_222, 3_499_700, 3_499_999,
        ] {
            let reads = s.flash_mut().reads();
            let n = s.read(&name("print.gcode"), at, &mut buf).unwrap();
            let at = at as usize;
            assert_eq!(
                &buf[..n],
                &print[at..(at + 300).min(print.len())],
                "at {at}"
            );
            // A map entry and two reads of at most 256 bytes, twice across a sector's end.
            let reads = s.flash_mut().reads() - reads;
            assert!(reads <= 5, "{reads} reads at {at}");
        }
        // Opening reads each header once, and each file's map and data headers.
        let flash = s.into_inner();
        let reads = flash.reads();
        let mut s = FlashFileStore::<Big, 32>::open(flash, region.clone()).unwrap();
        let opening = s.flash_mut().reads() - reads;
        assert!(opening < 1024 + 2 * 862 + 40, "{opening} reads to open");
        let mut whole = vec![0; 4096];
        let mut at = 0;
        while at < print.len() {
            let n = s.read(&name("print.gcode"), at as u32, &mut whole).unwrap();
            assert_eq!(&whole[..n], &print[at..at + n]);
            at += n;
        }
        assert_eq!(contents(&mut s, "cube.g").unwrap(), pattern(8, 10_000));
        // Its room serves the next print, as long as a map allows.
        s.remove(&name("print.gcode")).unwrap();
        let longest = s.max_file_len() as usize;
        let next = pattern(10, longest);
        s.create(&name("next.gcode")).unwrap();
        for line in next.chunks(4000) {
            s.append(line).unwrap();
        }
        assert_eq!(s.append(b"x"), Err(FileError::Full));
        s.finish().unwrap();
        let mut s = FlashFileStore::<Big, 32>::open(s.into_inner(), region).unwrap();
        assert_eq!(s.size(&name("next.gcode")), Ok(longest as u32));
        let n = s
            .read(&name("next.gcode"), longest as u32 - 10, &mut buf)
            .unwrap();
        assert_eq!(&buf[..n], &next[longest - 10..]);
    }

    /// A step of the power-cut sequence.
    #[derive(Debug, Clone)]
    enum Op {
        Create(&'static str),
        Append(Vec<u8>),
        Finish,
        Remove(&'static str),
        Abandon,
    }

    /// The finished files by lower-case name: their spelling and bytes.
    type Files = BTreeMap<String, (String, Vec<u8>)>;

    /// Run `ops` until the first error: how many succeeded.
    fn run<S: FileStore>(store: &mut S, ops: &[Op]) -> usize {
        ops.iter()
            .take_while(|op| {
                match op {
                    Op::Create(n) => store.create(&name(n)),
                    Op::Append(bytes) => store.append(bytes),
                    Op::Finish => store.finish(),
                    Op::Remove(n) => store.remove(&name(n)),
                    Op::Abandon => store.abandon(),
                }
                .is_ok()
            })
            .count()
    }

    /// The files seen after each number of `ops` from `base`.
    fn states(base: &Files, ops: &[Op]) -> Vec<Files> {
        let mut files = base.clone();
        let mut writing: Option<(&str, Vec<u8>)> = None;
        let mut out = vec![files.clone()];
        for op in ops {
            match op {
                Op::Create(n) => writing = Some((n, Vec::new())),
                Op::Append(bytes) => writing.as_mut().unwrap().1.extend_from_slice(bytes),
                Op::Finish => {
                    let (n, bytes) = writing.take().unwrap();
                    files.insert(n.to_lowercase(), (n.to_string(), bytes));
                }
                Op::Remove(n) => {
                    files.remove(&n.to_lowercase());
                }
                Op::Abandon => writing = None,
            }
            out.push(files.clone());
        }
        out
    }

    fn seen<S: FileStore>(store: &mut S) -> Files {
        listing(store)
            .into_iter()
            .map(|(n, _)| {
                let bytes = contents(store, &n).unwrap();
                (n.to_lowercase(), (n, bytes))
            })
            .collect()
    }

    /// After a cut: removing every file leaves none behind, and then one file fills the whole
    /// region: no sector was lost.
    fn still_usable(mut s: Store, files: &Files) {
        for (spelled, _) in files.values() {
            s.remove(&name(spelled)).unwrap();
        }
        let mut s = reopen(s);
        assert!(listing(&mut s).is_empty(), "no old version came back");
        assert_eq!(s.free_sectors(), 16);
        let fill = pattern(7, 15 * 240);
        s.create(&name("fill.g")).unwrap();
        for part in fill.chunks(240) {
            s.append(part).unwrap();
        }
        assert_eq!(s.append(b"x"), Err(FileError::Full));
        s.finish().unwrap();
        let mut s = reopen(s);
        assert_eq!(contents(&mut s, "fill.g").unwrap(), fill);
    }

    #[test]
    fn a_power_cut_anywhere_leaves_whole_files() {
        let mut base = open(Flash::new());
        write(&mut base, "a.g", &pattern(1, 700)).unwrap();
        write(&mut base, "b.g", &pattern(2, 300)).unwrap();
        let base_files = seen(&mut base);
        let base = base.into_inner();
        let ops = [
            Op::Create("c.g"),
            Op::Append(pattern(3, 250)),
            Op::Append(pattern(4, 250)),
            Op::Finish,
            Op::Create("A.G"),
            Op::Append(pattern(5, 3)),
            Op::Append(pattern(6, 500)),
            Op::Finish,
            Op::Remove("b.g"),
            Op::Create("d.g"),
            Op::Append(pattern(7, 100)),
            Op::Abandon,
            Op::Remove("c.g"),
            Op::Create("B.G"),
            Op::Append(pattern(8, 10)),
            Op::Finish,
        ];
        let expected = states(&base_files, &ops);
        let total = {
            let mut f = base.clone();
            let before = f.work_done();
            let mut s = FlashFileStore::<&mut Flash, 4>::open(&mut f, REGION).unwrap();
            assert_eq!(run(&mut s, &ops), ops.len());
            f.work_done() - before
        };
        let mut outcomes = vec![0usize; expected.len()];
        for k in 0..=total {
            let mut f = base.clone();
            f.cut_power_after(k);
            let acked = {
                let mut s = FlashFileStore::<&mut Flash, 4>::open(&mut f, REGION).unwrap();
                run(&mut s, &ops)
            };
            f.restore_power();
            let mut s = open(f);
            let got = seen(&mut s);
            // What was acknowledged, or that and the operation the cut interrupted.
            let state = if got == expected[acked] {
                acked
            } else {
                assert_eq!(Some(&got), expected.get(acked + 1), "cut after {k}");
                acked + 1
            };
            outcomes[state] += 1;
            still_usable(s, &got);
        }
        // Each change was seen done, and each finish also not done. (A removal is done by
        // its one erase, which `RamNorFlash` always leaves with the head's header erased.)
        for (i, pair) in expected.windows(2).enumerate() {
            if pair[0] != pair[1] {
                assert!(outcomes[i + 1] > 0, "{i}: {outcomes:?}");
                if matches!(ops[i], Op::Finish) {
                    assert!(outcomes[i] > 0, "{i}: {outcomes:?}");
                }
            }
        }
    }

    #[test]
    fn an_old_head_a_cut_left_behind_never_comes_back() {
        let mut s = open(Flash::new());
        write(&mut s, "a.g", b"old version").unwrap();
        s.create(&name("a.g")).unwrap();
        s.append(b"new version").unwrap();
        // Cut in the erase of the old head, after the commit record (the last unit of work).
        let units = {
            let mut f = s.flash_mut().clone();
            let mut probe = open(f.clone());
            let before = probe.flash_mut().work_done();
            probe.writing = s.writing;
            probe.finish().unwrap();
            f = probe.into_inner();
            f.work_done() - before
        };
        s.flash_mut().cut_power_after(units - 1);
        assert_eq!(
            s.finish(),
            Ok(()),
            "finished: the erase is not the finish's"
        );
        s.flash_mut().restore_power();
        let mut s = reopen(s);
        assert_eq!(listing(&mut s), [("a.g".to_string(), 11)]);
        assert_eq!(contents(&mut s, "a.g").unwrap(), b"new version");
        s.remove(&name("a.g")).unwrap();
        let mut s = reopen(s);
        assert!(listing(&mut s).is_empty());
    }

    #[test]
    fn flash_errors_are_device_errors() {
        let mut s = open(Flash::new());
        write(&mut s, "a.g", &pattern(1, 500)).unwrap();
        // The head's header cannot be written: nothing changes.
        s.flash_mut().cut_power_after(0);
        assert_eq!(s.create(&name("b.g")), Err(FileError::Device));
        assert_eq!(s.writing(), None);
        s.flash_mut().restore_power();
        assert_eq!(contents(&mut s, "a.g").unwrap(), pattern(1, 500));
        // A write that fails cannot go on until it is abandoned.
        s.create(&name("b.g")).unwrap();
        s.append(&pattern(2, 100)).unwrap();
        s.flash_mut().cut_power_after(10);
        assert_eq!(s.append(&pattern(3, 300)), Err(FileError::Device));
        s.flash_mut().restore_power();
        assert_eq!(s.append(b"x"), Err(FileError::Device));
        assert_eq!(s.finish(), Err(FileError::Device));
        assert_eq!(s.writing(), Some(name("b.g")));
        s.abandon().unwrap();
        write(&mut s, "b.g", &pattern(4, 300)).unwrap();
        // A commit record that cannot be written.
        s.create(&name("c.g")).unwrap();
        s.append(b"ccc").unwrap();
        s.flash_mut().cut_power_after(2);
        assert_eq!(s.finish(), Err(FileError::Device));
        s.flash_mut().restore_power();
        assert_eq!(s.size(&name("c.g")), Err(FileError::NotFound));
        s.abandon().unwrap();
        // A removal that fails keeps the file listed; a read of a flash without power fails.
        s.flash_mut().cut_power_after(0);
        assert_eq!(s.remove(&name("a.g")), Err(FileError::Device));
        assert_eq!(s.size(&name("a.g")), Ok(500));
        assert_eq!(s.read(&name("b.g"), 0, &mut [0; 4]), Err(FileError::Device));
        assert_eq!(s.create(&name("d.g")), Err(FileError::Device));
        s.flash_mut().restore_power();
        // The cut came in the erase of its head: the file is gone, the others are whole.
        let mut s = reopen(s);
        assert_eq!(contents(&mut s, "b.g").unwrap(), pattern(4, 300));
        assert_eq!(listing(&mut s), [("b.g".to_string(), 300)]);
        write(&mut s, "a.g", b"again").unwrap();
    }

    #[test]
    fn a_region_of_other_data_opens_empty_and_is_used() {
        let mut mem = [0u8; 18 * 256];
        for (i, b) in mem.iter_mut().enumerate() {
            *b = (i * 13) as u8;
        }
        let mut s = open(Flash::with_memory(mem));
        assert!(listing(&mut s).is_empty());
        assert_eq!(s.free_sectors(), 16);
        write(&mut s, "a.g", &pattern(1, 1000)).unwrap();
        let mut s = reopen(s);
        assert_eq!(contents(&mut s, "a.g").unwrap(), pattern(1, 1000));
    }

    #[test]
    fn with_fewer_slots_than_files_the_newest_are_kept() {
        let mut s = open(Flash::new());
        for n in ["a.g", "b.g", "c.g", "d.g"] {
            write(&mut s, n, n.as_bytes()).unwrap();
        }
        let mut s = FlashFileStore::<Flash, 2>::open(s.into_inner(), REGION).unwrap();
        assert_eq!(
            listing(&mut s),
            [("c.g".to_string(), 3), ("d.g".to_string(), 3)]
        );
        assert_eq!(s.free_sectors(), 12, "the others' sectors are free");
        assert_eq!(s.create(&name("e.g")), Err(FileError::Full));
        s.remove(&name("c.g")).unwrap();
        write(&mut s, "e.g", &pattern(1, 2000)).unwrap();
        assert_eq!(contents(&mut s, "e.g").unwrap(), pattern(1, 2000));
    }
}
