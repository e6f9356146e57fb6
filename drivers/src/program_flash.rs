//! A stored program on NOR flash, one fixed-size slot per line: reading a line is one flash
//! read.
//!
//! [`SlotProgramStore`] implements [`ProgramStore`] over a dedicated region of any
//! `embedded-storage` [`NorFlash`]. Line `k` (1-based) lives in slot `k - 1`, at
//! `region.start + (k - 1) * SLOT_LEN`, so [`ProgramStore::read`] is a single read of
//! [`SLOT_LEN`] bytes whatever the program's length (the record map of
//! [`FlashRecordStorage`](crate::storage::FlashRecordStorage) searches its pages instead).
//!
//! # Layout
//!
//! | bytes | field |
//! |---|---|
//! | 0..2 | the line's index, `u16` little-endian, 1-based |
//! | 2 | the text's length, 0..=[`MAX_LINE_LEN`] |
//! | 3..3+len | the text; the rest up to byte 42 is 0 |
//! | 42..44 | the program's total number of lines, `u16` little-endian |
//! | 44..48 | the program's digest through this line ([`digest_line`](forja_hal_abstraction::program::digest_line)), `u32` little-endian |
//! | 48..60 | 0 |
//! | 60..64 | CRC-32 (IEEE) of bytes 0..60, little-endian |
//!
//! A slot is valid when its CRC, index and length check. [`SLOT_LEN`] (64) divides the erase
//! sector of every common flash and is a multiple of its read and write sizes, so no slot
//! straddles a sector; [`SlotProgramStore::open`] refuses a flash for which it is not.
//! There is no header: the program is the run of valid slots from slot 0 that carry the total
//! of slot 0 and whose digests chain (each is the digest of the one before continued over its
//! own line), up to the total. It is complete when that run reaches the total: the "complete"
//! mark is the last line itself, written last, so a power cut in the middle of an upload
//! leaves an incomplete program (never a complete one), and a slot of another upload can
//! never extend a program (its digest does not chain). Slots of the earlier layout (no total)
//! open as no program.
//!
//! # Writing and erasing
//!
//! Each slot is written once after its sector was erased. The region is erased sector by
//! sector as the program grows, never all at once:
//! - [`ProgramStore::begin`] (the controller calls it when line 1 of a new program arrives)
//!   and [`ProgramStore::clear`] erase sector 0, which removes the old program's first line and
//!   so the whole old program;
//! - [`ProgramStore::store`] makes sure that the slot it writes *and the slot after it* lie in
//!   sectors erased for this program, erasing the next sector ahead when the line is the last
//!   of its sector, then writes the slot.
//!
//! So a call erases at most one sector (4 KiB on the ESP32: typically 45 ms, at most about
//! 400 ms, during which a single-bank part runs nothing else): load a program while the
//! machine is at rest, as the controller does. The old program's later sectors keep their
//! slots until the new program reaches them; they are never read, because the run of valid
//! slots always ends at an erased slot of the new program (below).
//!
//! # Power loss
//!
//! Invariant: with `n` lines stored, slots `0..n` are valid, and slot `n` and the rest of its
//! sector are erased, except that slot `n` may hold a torn write. A power cut
//! - while sector 0 is erased by `clear`: slot 0 is either untouched (the old program, whole,
//!   since nothing else changed) or no longer valid (an empty store);
//! - while the sector ahead is erased by `store`: slot `n` is not written yet and erased, so
//!   the program ends at line `n` (the half-erased sector lies beyond it);
//! - while slot `n` is written: its CRC does not check, so the program ends at line `n`
//!   without the interrupted line, or, if the write had completed, with it.
//!
//! Reopening finds the same program by scanning from slot 0 to the first slot that is not
//! valid, never a corrupt line, and a stored line always reads. After a cut in the middle of a
//! write, slot `n` is torn and cannot be written again without erasing its sector: storing
//! line `n + 1` is refused with [`StoreError::Device`] until the program is loaded again from
//! line 1 (the controller requires that after a restart anyway).
//!
//! # Costs
//!
//! - [`ProgramStore::read`]: one flash read of [`SLOT_LEN`] bytes.
//! - [`ProgramStore::store`]: one write of [`SLOT_LEN`] bytes, plus one sector erase for the
//!   first line and then once every `ERASE_SIZE / SLOT_LEN` lines (64 lines for 4 KiB).
//! - [`ProgramStore::clear`]: one sector erase (none when the store is already empty).
//! - [`SlotProgramStore::open`]: one slot read per stored line, plus one when the program is
//!   incomplete: at most [`SlotProgramStore::capacity`] reads (9 999 for a 9999-line program).
//!
//! # Execution context
//!
//! Thread. Every method blocks for its flash operations.

use core::ops::Range;

use embedded_storage::nor_flash::{NorFlash, NorFlashError};
use forja_hal_abstraction::program::{
    MAX_LINE_LEN, MAX_LINES, ProgramState, ProgramStore, StoreError, crc32_update,
};

use crate::storage::StorageError;

/// Bytes of flash per line.
pub const SLOT_LEN: usize = 64;

/// Offset of the text's length in a slot.
const LEN_AT: usize = 2;
/// Offset of the text in a slot.
const TEXT_AT: usize = 3;
/// Offset of the program's total in a slot.
const TOTAL_AT: usize = TEXT_AT + MAX_LINE_LEN;
/// Offset of the digest in a slot.
const DIGEST_AT: usize = TOTAL_AT + 2;
/// Offset of the CRC in a slot: the bytes before it are checked.
const CRC_AT: usize = SLOT_LEN - 4;

/// CRC-32 of a slot's bytes.
fn crc32(bytes: &[u8]) -> u32 {
    crc32_update(0, bytes)
}

/// What a slot holds besides its index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Slot<'a> {
    text: &'a [u8],
    total: u16,
    digest: u32,
}

/// Encode line `index` (1-based) of a program of `total` lines, with `text` (at most
/// [`MAX_LINE_LEN`] bytes) and the program's `digest` through it, into a slot.
fn encode(index: u16, total: u16, digest: u32, text: &[u8]) -> [u8; SLOT_LEN] {
    let mut slot = [0u8; SLOT_LEN];
    let len = text.len().min(MAX_LINE_LEN);
    if let Some(dst) = slot.get_mut(..LEN_AT) {
        dst.copy_from_slice(&index.to_le_bytes());
    }
    if let Some(dst) = slot.get_mut(LEN_AT) {
        *dst = len as u8;
    }
    if let (Some(dst), Some(src)) = (slot.get_mut(TEXT_AT..TEXT_AT + len), text.get(..len)) {
        dst.copy_from_slice(src);
    }
    if let Some(dst) = slot.get_mut(TOTAL_AT..DIGEST_AT) {
        dst.copy_from_slice(&total.to_le_bytes());
    }
    if let Some(dst) = slot.get_mut(DIGEST_AT..DIGEST_AT + 4) {
        dst.copy_from_slice(&digest.to_le_bytes());
    }
    let crc = crc32(slot.get(..CRC_AT).unwrap_or(&[]));
    if let Some(dst) = slot.get_mut(CRC_AT..) {
        dst.copy_from_slice(&crc.to_le_bytes());
    }
    slot
}

/// The contents of `slot` if it is a valid slot of line `index`.
fn decode(index: u16, slot: &[u8; SLOT_LEN]) -> Option<Slot<'_>> {
    let (body, crc) = slot.split_at_checked(CRC_AT)?;
    let crc = u32::from_le_bytes(crc.try_into().ok()?);
    if crc32(body) != crc {
        return None;
    }
    let stored = u16::from_le_bytes(body.get(..LEN_AT)?.try_into().ok()?);
    let len = usize::from(*body.get(LEN_AT)?);
    if stored != index || len > MAX_LINE_LEN {
        return None;
    }
    let total = u16::from_le_bytes(body.get(TOTAL_AT..DIGEST_AT)?.try_into().ok()?);
    let digest = u32::from_le_bytes(body.get(DIGEST_AT..DIGEST_AT + 4)?.try_into().ok()?);
    Some(Slot {
        text: body.get(TEXT_AT..TEXT_AT + len)?,
        total,
        digest,
    })
}

fn is_erased(slot: &[u8; SLOT_LEN]) -> bool {
    slot.iter().all(|&b| b == 0xFF)
}

/// A program kept in a dedicated flash region, one [`SLOT_LEN`]-byte slot per line (see the
/// [module documentation](self) for the layout and the power-loss argument).
///
/// Context: thread. Every operation blocks for the flash; `store` and `clear` may erase one
/// sector: load a program while the machine is at rest.
#[derive(Debug)]
pub struct SlotProgramStore<F> {
    flash: F,
    /// Absolute offset of slot 0.
    base: u32,
    /// Bytes of the region (a whole number of sectors).
    region_len: u32,
    capacity: u16,
    /// Lines stored, the program's total and digest.
    state: ProgramState,
    /// Bytes from the start of the region erased for the current program: every slot from
    /// slot `state.count` up to here is erased (except that one when `tail_dirty`).
    erased_end: u32,
    /// Slot `state.count` holds a torn or failed write and cannot be written before an erase.
    tail_dirty: bool,
}

impl<F: NorFlash> SlotProgramStore<F> {
    /// Open the program kept in `region` of `flash` (absolute byte offsets): the run of valid
    /// slots from slot 0 that carry the same total and whose digests chain, up to the total,
    /// found by reading them in turn (one read per stored line, plus one when the program is
    /// incomplete). Anything else in the region (an empty flash, another format's data) is an
    /// empty store.
    ///
    /// Errors: [`StorageError::BadRegion`] when the region is empty, not a whole number of
    /// erase sectors, or beyond the flash, or when [`SLOT_LEN`] is not a multiple of the
    /// flash's read and write sizes or does not divide its erase size;
    /// [`StorageError::Flash`] when a read fails.
    pub fn open(flash: F, region: Range<u32>) -> Result<Self, StorageError> {
        let sector = F::ERASE_SIZE;
        let region_len = region.end.saturating_sub(region.start);
        let aligned = |x: u32| sector != 0 && (x as usize).is_multiple_of(sector);
        if region_len == 0
            || !aligned(region.start)
            || !aligned(region_len)
            || region.end as usize > flash.capacity()
            || F::READ_SIZE == 0
            || !SLOT_LEN.is_multiple_of(F::READ_SIZE)
            || F::WRITE_SIZE == 0
            || !SLOT_LEN.is_multiple_of(F::WRITE_SIZE)
            || !sector.is_multiple_of(SLOT_LEN)
        {
            return Err(StorageError::BadRegion);
        }
        let slots = region_len as usize / SLOT_LEN;
        let capacity = u16::try_from(slots).unwrap_or(MAX_LINES).min(MAX_LINES);
        let mut store = Self {
            flash,
            base: region.start,
            region_len,
            capacity,
            state: ProgramState::NONE,
            erased_end: 0,
            tail_dirty: false,
        };
        let mut slot = [0u8; SLOT_LEN];
        while store.state.count < capacity
            && (store.state.count == 0 || store.state.count < store.state.total)
        {
            let index = store.state.count + 1;
            store.read_slot(store.state.count, &mut slot)?;
            // Slot 1 begins the program of its total; each slot after it carries that total
            // and the digest chained over its own line.
            let next = decode(index, &slot).and_then(|s| {
                let before = match index {
                    1 => ProgramState::begin(s.total, capacity).ok()?,
                    _ => store.state,
                };
                let next = before.next(capacity, index, s.text).ok()?;
                (s.total == before.total && s.digest == next.digest).then_some(next)
            });
            let Some(next) = next else {
                store.tail_dirty = !is_erased(&slot);
                break;
            };
            store.state = next;
        }
        if store.state.count > 0 {
            // The sector of slot `count` was erased before line `count` was written.
            let sector = sector as u32;
            let next = store.slot_offset(store.state.count);
            store.erased_end = (next / sector)
                .saturating_add(1)
                .saturating_mul(sector)
                .min(region_len);
        } else {
            store.tail_dirty = false;
            store.state = ProgramState::NONE;
        }
        Ok(store)
    }

    /// The most lines this store holds: the region's slots, at most [`MAX_LINES`].
    pub fn capacity(&self) -> u16 {
        self.capacity
    }

    /// The flash.
    pub fn flash_mut(&mut self) -> &mut F {
        &mut self.flash
    }

    /// Give the flash back.
    pub fn into_inner(self) -> F {
        self.flash
    }

    /// Offset of slot `slot` (0-based) from the region's start.
    fn slot_offset(&self, slot: u16) -> u32 {
        u32::from(slot) * SLOT_LEN as u32
    }

    fn read_slot(&mut self, slot: u16, buf: &mut [u8; SLOT_LEN]) -> Result<(), StorageError> {
        let at = self.base + self.slot_offset(slot);
        self.flash
            .read(at, buf)
            .map_err(|e| StorageError::Flash(e.kind()))
    }

    /// Erase sectors from `erased_end` until `end` (region-relative) is covered.
    fn erase_to(&mut self, end: u32) -> Result<(), StoreError> {
        let sector = F::ERASE_SIZE as u32;
        while self.erased_end < end {
            let from = self.base + self.erased_end;
            self.flash
                .erase(from, from + sector)
                .map_err(|_| StoreError::Device)?;
            self.erased_end += sector;
        }
        Ok(())
    }

    /// Erase sector 0 (unless the store is empty with sector 0 erased already): the old
    /// program goes, and no program is left. Nothing changes when the erase fails.
    fn erase_first(&mut self) -> Result<(), StoreError> {
        if self.state.count == 0 && !self.tail_dirty && self.erased_end > 0 {
            self.state = ProgramState::NONE;
            return Ok(());
        }
        let erased_end = self.erased_end;
        self.erased_end = 0;
        let sector = F::ERASE_SIZE as u32;
        if let Err(e) = self.erase_to(sector.min(self.region_len)) {
            // Erasing only sets bits: what was erased before still is.
            self.erased_end = erased_end;
            return Err(e);
        }
        self.tail_dirty = false;
        self.state = ProgramState::NONE;
        Ok(())
    }
}

impl<F: NorFlash> ProgramStore for SlotProgramStore<F> {
    fn state(&self) -> ProgramState {
        self.state
    }

    /// Erases sector 0, as [`clear`](ProgramStore::clear); the total is written with each line.
    fn begin(&mut self, total: u16) -> Result<(), StoreError> {
        let begun = ProgramState::begin(total, self.capacity)?;
        self.erase_first()?;
        self.state = begun;
        Ok(())
    }

    /// One flash read of [`SLOT_LEN`] bytes.
    fn read(&mut self, index: u16, buf: &mut [u8; MAX_LINE_LEN]) -> Result<usize, StoreError> {
        if index == 0 || index > self.state.count {
            return Err(StoreError::NoSuchLine);
        }
        let mut slot = [0u8; SLOT_LEN];
        self.read_slot(index - 1, &mut slot)
            .map_err(|_| StoreError::Device)?;
        let text = decode(index, &slot).ok_or(StoreError::Device)?.text;
        let dst = buf.get_mut(..text.len()).ok_or(StoreError::Device)?;
        dst.copy_from_slice(text);
        Ok(text.len())
    }

    /// Line 1 erases sector 0 unless [`begin`](ProgramStore::begin) just did; the last line
    /// of each sector erases the next one first.
    fn store(&mut self, index: u16, text: &[u8]) -> Result<(), StoreError> {
        let next = self.state.next(self.capacity, index, text)?;
        let slot = index - 1;
        if self.tail_dirty {
            if slot != 0 {
                return Err(StoreError::Device);
            }
            // Slot 0 holds a failed write: start over with sector 0.
            self.erased_end = 0;
        }
        let start = self.slot_offset(slot);
        // This slot, and the next one when there is one.
        let ahead = if index < self.capacity { 2 } else { 1 };
        let end = (start + ahead * SLOT_LEN as u32).min(self.region_len);
        self.erase_to(end)?;
        self.tail_dirty = false;
        let bytes = encode(index, next.total, next.digest, text);
        if self.flash.write(self.base + start, &bytes).is_err() {
            self.tail_dirty = true;
            return Err(StoreError::Device);
        }
        self.state = next;
        Ok(())
    }

    /// Erases sector 0: the old program's first line goes, and with it the whole program.
    fn clear(&mut self) -> Result<(), StoreError> {
        self.erase_first()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ram_flash::RamNorFlash;
    use forja_hal_abstraction::program::{RamStore, digest_line, digest_start};

    /// Four slots per 256-byte sector, so that short programs cross sectors.
    type Flash = RamNorFlash<2048, 4, 256>;
    /// Sectors 1..8 of the flash: 28 slots.
    const REGION: Range<u32> = 256..2048;

    fn line(tag: &str, k: u16) -> Vec<u8> {
        format!("G1 X{k}.{tag} Y{}", k * 3).into_bytes()
    }

    fn load(s: &mut SlotProgramStore<Flash>, tag: &str, lines: u16) {
        if lines == 0 {
            s.clear().unwrap();
        } else {
            s.begin(lines).unwrap();
        }
        for k in 1..=lines {
            s.store(k, &line(tag, k)).unwrap();
        }
    }

    fn read_all(s: &mut SlotProgramStore<Flash>) -> Vec<Vec<u8>> {
        let mut buf = [0; MAX_LINE_LEN];
        (1..=s.len())
            .map(|k| {
                let n = s.read(k, &mut buf).unwrap();
                buf[..n].to_vec()
            })
            .collect()
    }

    fn program(tag: &str, lines: u16) -> Vec<Vec<u8>> {
        (1..=lines).map(|k| line(tag, k)).collect()
    }

    #[test]
    fn slot_layout_and_crc() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        let slot = encode(7, 9, 0x1234_5678, b"G0 X1");
        assert_eq!(&slot[..8], &[7, 0, 5, b'G', b'0', b' ', b'X', b'1']);
        assert_eq!(&slot[42..48], &[9, 0, 0x78, 0x56, 0x34, 0x12]);
        assert_eq!(
            decode(7, &slot),
            Some(Slot {
                text: b"G0 X1",
                total: 9,
                digest: 0x1234_5678
            })
        );
        assert_eq!(decode(8, &slot), None, "another line's slot");
        let mut torn = slot;
        torn[4] ^= 1;
        assert_eq!(decode(7, &torn), None);
        assert_eq!(decode(0xFFFF, &[0xFF; SLOT_LEN]), None);
    }

    #[test]
    fn lines_round_trip_and_survive_a_reopen() {
        let mut s = SlotProgramStore::open(Flash::new(), REGION).unwrap();
        assert_eq!(s.capacity(), 28);
        assert!(s.is_empty());
        s.begin(13).unwrap();
        for k in 1..=10 {
            s.store(k, &line("a", k)).unwrap();
        }
        s.store(11, b"").unwrap();
        s.store(12, &[b'Z'; MAX_LINE_LEN]).unwrap();
        let mut expected = program("a", 10);
        expected.push(Vec::new());
        expected.push(vec![b'Z'; MAX_LINE_LEN]);
        assert_eq!(read_all(&mut s), expected);
        let digest = s.digest();
        let mut s = SlotProgramStore::open(s.into_inner(), REGION).unwrap();
        assert_eq!((s.len(), s.total(), s.is_complete()), (12, 13, false));
        assert_eq!(s.digest(), digest);
        assert_eq!(read_all(&mut s), expected);
        let mut buf = [0; MAX_LINE_LEN];
        assert_eq!(s.read(0, &mut buf), Err(StoreError::NoSuchLine));
        assert_eq!(s.read(13, &mut buf), Err(StoreError::NoSuchLine));
        // Lines go on after a reopen; the last one completes the program.
        s.store(13, b"M2").unwrap();
        let mut s = SlotProgramStore::open(s.into_inner(), REGION).unwrap();
        assert_eq!((s.len(), s.is_complete()), (13, true));
        assert_eq!(s.read(13, &mut buf), Ok(2));
    }

    #[test]
    fn a_shorter_program_hides_the_longer_one_it_replaces() {
        let mut s = SlotProgramStore::open(Flash::new(), REGION).unwrap();
        load(&mut s, "old", 20);
        // Ends at a sector boundary, then in the middle of a sector, then empty.
        for lines in [8, 5, 0] {
            load(&mut s, "new", lines);
            let mut s2 = SlotProgramStore::open(s.into_inner(), REGION).unwrap();
            assert_eq!(read_all(&mut s2), program("new", lines), "{lines} lines");
            s = s2;
        }
    }

    #[test]
    fn errors_leave_the_store_unchanged() {
        let mut s = SlotProgramStore::open(Flash::new(), REGION).unwrap();
        assert_eq!(s.store(1, b"G1 X1"), Err(StoreError::NoUpload));
        assert_eq!(s.begin(29), Err(StoreError::Full));
        assert_eq!(s.begin(0), Err(StoreError::Full));
        s.begin(28).unwrap();
        assert_eq!(
            s.store(2, b"G1 X1"),
            Err(StoreError::OutOfOrder {
                expected: 1,
                got: 2
            })
        );
        for k in 1..=27 {
            s.store(k, &line("a", k)).unwrap();
        }
        let before = *s.flash_mut().as_bytes();
        assert_eq!(
            s.store(27, b"G1"),
            Err(StoreError::OutOfOrder {
                expected: 28,
                got: 27
            })
        );
        assert_eq!(s.store(28, &[b'X'; 40]), Err(StoreError::TooLong));
        s.store(28, b"last").unwrap();
        let full = *s.flash_mut().as_bytes();
        assert_ne!(before, full);
        assert_eq!(s.store(29, b"G1"), Err(StoreError::NoUpload));
        assert_eq!(s.len(), 28);
        assert_eq!(s.flash_mut().as_bytes(), &full);
        let mut s = SlotProgramStore::open(s.into_inner(), REGION).unwrap();
        assert_eq!(s.len(), 28);
        assert_eq!(s.store(29, b"G1"), Err(StoreError::NoUpload));
        // A failing device: clear reports it and keeps the program.
        s.flash_mut().cut_power_after(0);
        assert_eq!(s.clear(), Err(StoreError::Device));
        assert_eq!(s.len(), 28);
    }

    #[test]
    fn behaves_as_the_ram_store() {
        let mut flash = SlotProgramStore::open(Flash::new(), REGION).unwrap();
        let mut ram = RamStore::<28>::new();
        let mut seed = 0x1234_5678u32;
        let mut buf = [0; MAX_LINE_LEN];
        let mut buf2 = [0; MAX_LINE_LEN];
        for _ in 0..3000 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let r = seed >> 8;
            let len = ram.len();
            match r % 16 {
                0 if r & 0x10 == 0 => assert_eq!(flash.clear(), ram.clear()),
                0 => {
                    let total = (r >> 5) as u16 % 31;
                    assert_eq!(flash.begin(total), ram.begin(total));
                }
                1 => {
                    let index = (r >> 4) as u16 % 32;
                    assert_eq!(flash.store(index, b"G0"), ram.store(index, b"G0"));
                }
                2 => {
                    let text = vec![b'Y'; 38 + (r >> 4) as usize % 3];
                    assert_eq!(flash.store(len + 1, &text), ram.store(len + 1, &text));
                }
                3..=9 => {
                    let text = line("r", (r >> 4) as u16 % 1000);
                    assert_eq!(flash.store(len + 1, &text), ram.store(len + 1, &text));
                }
                _ => {
                    let index = (r >> 4) as u16 % 32;
                    let a = flash.read(index, &mut buf);
                    assert_eq!(a, ram.read(index, &mut buf2));
                    if let Ok(n) = a {
                        assert_eq!(buf[..n], buf2[..n]);
                    }
                }
            }
            assert_eq!(flash.len(), ram.len());
            assert_eq!(flash.total(), ram.total());
            assert_eq!(flash.digest(), ram.digest());
        }
    }

    #[test]
    fn reading_a_line_is_one_read_of_one_slot() {
        // A 704 KiB flash in RAM does not fit the test thread's stack.
        std::thread::Builder::new()
            .stack_size(16 << 20)
            .spawn(one_read_per_line)
            .unwrap()
            .join()
            .unwrap();
    }

    fn one_read_per_line() {
        type Big = RamNorFlash<{ 704 * 1024 }, 4, 4096>;
        let mut s = SlotProgramStore::open(Big::new(), 0..704 * 1024).unwrap();
        assert_eq!(s.capacity(), MAX_LINES);
        s.begin(MAX_LINES).unwrap();
        for k in 1..=MAX_LINES {
            s.store(k, b"G1 X12.300 Y6.150 F3000").unwrap();
        }
        let mut buf = [0; MAX_LINE_LEN];
        for k in [1, 2, 5000, MAX_LINES - 1, MAX_LINES] {
            let (reads, bytes) = (s.flash_mut().reads(), s.flash_mut().bytes_read());
            assert_eq!(s.read(k, &mut buf), Ok(23));
            assert_eq!(s.flash_mut().reads() - reads, 1, "line {k}");
            assert_eq!(s.flash_mut().bytes_read() - bytes, SLOT_LEN);
        }
        let reads = s.flash_mut().reads();
        for k in 1..=MAX_LINES {
            s.read(k, &mut buf).unwrap();
        }
        assert_eq!(s.flash_mut().reads() - reads, usize::from(MAX_LINES));
        // Opening scans the stored lines once (the program fills the capacity: no extra read).
        let mut flash = s.into_inner();
        let reads = flash.reads();
        let s = SlotProgramStore::open(&mut flash, 0..704 * 1024).unwrap();
        assert_eq!(s.len(), MAX_LINES);
        assert_eq!(flash.reads() - reads, usize::from(MAX_LINES));
        // Storing erases one sector per 64 lines, the first line included.
        assert_eq!(flash.pages_erased(), usize::from(MAX_LINES).div_ceil(64));
    }

    #[test]
    fn bad_regions_are_refused() {
        let open = |r: Range<u32>| SlotProgramStore::open(Flash::new(), r).err();
        assert_eq!(open(256..256), Some(StorageError::BadRegion));
        assert_eq!(
            open(Range {
                start: 512,
                end: 256
            }),
            Some(StorageError::BadRegion)
        );
        assert_eq!(open(100..356), Some(StorageError::BadRegion));
        assert_eq!(open(256..400), Some(StorageError::BadRegion));
        assert_eq!(open(256..4096), Some(StorageError::BadRegion));
        // Sectors smaller than a slot.
        let small = RamNorFlash::<1024, 4, 32>::new();
        assert_eq!(
            SlotProgramStore::open(small, 0..1024).err(),
            Some(StorageError::BadRegion)
        );
        assert_eq!(open(0..256), None);
    }

    #[test]
    fn a_power_cut_anywhere_leaves_a_consistent_program() {
        const OLD: u16 = 11;
        const NEW: u16 = 9;
        let mut base = SlotProgramStore::open(Flash::new(), REGION).unwrap();
        load(&mut base, "old", OLD);
        let base = base.into_inner();
        let total = {
            let mut f = base.clone();
            let before = f.work_done();
            let mut s = SlotProgramStore::open(&mut f, REGION).unwrap();
            assert_eq!(upload_ref(&mut s, NEW), Some(NEW));
            f.work_done() - before
        };
        // Three erases (sector 0, then ahead at lines 4 and 8) and NEW slots.
        assert_eq!(total, 3 + usize::from(NEW) * SLOT_LEN);
        // How often each length of the new program was found (an interrupted erase of
        // sector 0 always empties the store here: `RamNorFlash` erases its first half).
        let mut new_seen = [0usize; NEW as usize + 1];
        for k in 0..=total {
            let mut f = base.clone();
            f.cut_power_after(k);
            let acked = {
                let mut s = SlotProgramStore::open(&mut f, REGION).unwrap();
                upload_ref(&mut s, NEW)
            };
            f.restore_power();
            let mut s = SlotProgramStore::open(f, REGION).unwrap();
            let got = read_all(&mut s);
            let n = s.len();
            if acked.is_none() && got == program("old", OLD) {
                assert_eq!(n, OLD);
            } else {
                assert_eq!(got, program("new", n), "cut after {k}");
                let acked = acked.unwrap_or(0);
                assert!(
                    n == acked || n == acked + 1,
                    "cut after {k}: {n} vs {acked}"
                );
                new_seen[usize::from(n)] += 1;
                // Complete exactly when every line is there.
                assert_eq!(s.is_complete(), n == NEW, "cut after {k}");
                // Going on from the next line works unless that slot was torn.
                match s.store(n + 1, &line("new", n + 1)) {
                    Ok(()) => assert_eq!(read_all(&mut s), program("new", n + 1)),
                    // Nothing to go on with: complete, or no line 1 (no upload).
                    Err(e) if n == NEW || n == 0 => assert_eq!(e, StoreError::NoUpload),
                    Err(e) => assert_eq!(e, StoreError::Device, "cut after {k}"),
                }
            }
            // Loading the program again from line 1 always works.
            load(&mut s, "again", NEW);
            let mut s = SlotProgramStore::open(s.into_inner(), REGION).unwrap();
            assert_eq!(read_all(&mut s), program("again", NEW), "cut after {k}");
        }
        assert!(new_seen.iter().all(|&c| c > 0), "{new_seen:?}");
    }

    /// Begin, then store lines 1..=`lines` of program "new" until the first error; `None`
    /// when the begin failed, else how many lines were acknowledged.
    fn upload_ref(s: &mut SlotProgramStore<&mut Flash>, lines: u16) -> Option<u16> {
        s.begin(lines).ok()?;
        let mut done = 0;
        for k in 1..=lines {
            if s.store(k, &line("new", k)).is_err() {
                return Some(done);
            }
            done = k;
        }
        Some(done)
    }

    /// An upload cut after 4 of 10 lines reopens incomplete; a line 5 written by another
    /// upload of the same total (its digest chains from other lines) never extends it.
    #[test]
    fn an_interrupted_upload_stays_incomplete_and_takes_no_foreign_line() {
        let mut s = SlotProgramStore::open(Flash::new(), REGION).unwrap();
        s.begin(10).unwrap();
        for k in 1..=4 {
            s.store(k, &line("a", k)).unwrap();
        }
        // Program "b", same total: its line 5 in slot 4, as a splice would put it.
        let mut other = digest_start(10);
        for k in 1..=5 {
            other = digest_line(other, k, &line("b", k));
        }
        let foreign = encode(5, 10, other, &line("b", 5));
        let at = REGION.start + 4 * SLOT_LEN as u32;
        s.flash_mut().write(at, &foreign).unwrap();
        let s = SlotProgramStore::open(s.into_inner(), REGION).unwrap();
        assert_eq!((s.len(), s.total(), s.is_complete()), (4, 10, false));
    }
}
