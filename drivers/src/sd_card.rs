//! Files on a FAT16 or FAT32 SD card, as a [`FileStore`].
//!
//! [`SdFileStore`] keeps the store's files in the root directory of the card's first
//! partition, where Marlin keeps them and where a PC puts them: a print copied onto the card
//! is listed and runs, and a file uploaded with `M28` is read by the PC. It is generic over an
//! [`embedded_sdmmc::BlockDevice`]: on a board, embedded-sdmmc's [`SdCard`] over an
//! `embedded-hal` `SpiDevice` and a delay; in tests, a disk image in memory.
//!
//! ```
//! use embedded_hal::{delay::DelayNs, spi::SpiDevice};
//! use forja_drivers::sd_card::SdFileStore;
//! use forja_drivers::sd_card::embedded_sdmmc::SdCard;
//!
//! /// The board's card: nothing is read until the first file operation.
//! fn card<S: SpiDevice, D: DelayNs>(spi: S, delay: D) -> SdFileStore<SdCard<S, D>> {
//!     SdFileStore::new(SdCard::new(spi, delay))
//! }
//! ```
//!
//! The store reads and writes the card's FAT structures itself, through the block device:
//! the boot block, the root directory (short and long names), the FAT chains, the files'
//! data. From embedded-sdmmc (re-exported as [`embedded_sdmmc`]) it takes the block device:
//! its [`SdCard`] speaks to the card over SPI.
//!
//! # Names
//!
//! The store writes no long file names ([`FileStore::writes_long_names`] is `false`), so
//! [`FileStore::create`] takes 8.3 names only ([`is_short_name`]): 1 to 8 characters, an
//! optional `.` and 1 to 3 more, of letters, digits and ``! # $ % & ' ( ) - @ ^ _ ` { } ~``;
//! not a DOS device name (`CON`, `PRN`, `AUX`, `NUL`, `COM1`–`COM9`, `LPT1`–`LPT9`), not one of
//! the store's own temporaries ([`WRITING`], [`REMOVING`]), and not the name of a directory,
//! the volume label or a hidden or system file of the root directory. Any other name is
//! [`FileError::BadName`], before anything is written. The case of letters is kept the way
//! FAT keeps it without a long name: an all-small base or extension is marked as such
//! (`part.gco` is listed, and shown by a PC, as `part.gco`); one that mixes capitals and small
//! letters is stored in capitals (`Part.gco` is listed as `PART.gco`). It is the same file
//! either way, since names are compared without regard to case.
//!
//! Files on the card are listed under their long name when they have one that is a
//! [`FileName`] (printable ASCII, no spaces, up to [`MAX_NAME_LEN`] characters):
//! `bracket_v2.gcode` is listed as `bracket_v2.gcode`. Otherwise they are listed under their
//! 8.3 short name: a PC's `my part.gcode` is listed as `MYPART~1.GCO`. A file answers to both
//! names. Not listed: directories (files in them are not seen), the volume label, hidden and
//! system files, files whose long name starts with `.` (macOS's `._name`), files whose short
//! name is not plain ASCII, and the store's temporaries. Listing follows the directory's order.
//!
//! A finished file replaces the file that answers to its name. It takes the spelling written,
//! and the old long name goes, when the name written is the old file's short name and its
//! long name, if it has one, is the same name (`bracket.gco` replacing a PC's `Bracket.gco`,
//! whose short name is `BRACKET.GCO`, leaves `bracket.gco`). Written under the short name of a
//! file listed under another long name, the file keeps that long name (`BRACKE~1.GCO`
//! replacing `bracket_v2.gcode` leaves `bracket_v2.gcode`, with the new contents).
//!
//! # Writing, and power cuts
//!
//! A file being written is the root directory's [`WRITING`] file, unseen. Finishing it is one
//! 512-byte directory block write (the commit), which a power cut leaves done or not done:
//! - a new name: the temporary's entry is renamed to the name;
//! - an existing file: its entry is pointed at the new data (the old file's clusters are first
//!   recorded in a [`REMOVING`] entry, so that they are freed, not leaked, whatever happens
//!   next); then the temporary's entry is deleted and the old clusters are freed.
//!
//! [`FileStore::remove`] renames the file's entry to [`REMOVING`] (the commit), then frees
//! its clusters and deletes the entry. So after a power cut, a restart or a card taken out,
//! the card holds each file's old contents or its new ones, never a part, and the next mount
//! ([`SdFileStore::mount`], which every operation does first) finishes the cleanup: a
//! temporary whose clusters another entry now owns is deleted alone, any other temporary is
//! deleted with its clusters, and long-name entries that belong to no file (a removal's, or
//! those that other implementations leave: embedded-sdmmc's delete does) are deleted. A
//! write in progress is forgotten.
//!
//! What a power cut can leave is at most one cluster allocated but unused (a "lost cluster",
//! which a PC's disk check frees) when it strikes while a cluster is added to a file being
//! written, or some of the clusters of a file being freed when it strikes in the middle of
//! freeing them (they are freed in the order of the file, one FAT block at a time, so a file
//! whose FAT entries share one block loses none); a replaced file keeping its old long name
//! when it strikes between the commit and that name's deletion; and the two copies of the FAT
//! differing in one block when it strikes between their writes (PCs read the first; a disk
//! check reports it). A PC that reads the card between a cut and the next mount sees
//! [`WRITING`] or [`REMOVING`] in the root directory. Never a file with the wrong contents, a
//! file under two names, or a cluster in two files once the next mount is done.
//!
//! If the root directory has no free entry for [`REMOVING`] when an existing file is replaced
//! (a full FAT16 root directory), the old clusters are freed right after the commit instead,
//! and a power cut between the two leaves them lost.
//!
//! # Reading
//!
//! The file last read stays open: [`FileStore::read`] of the same name at the next offset
//! goes on from where the last read stopped, following the FAT from the cluster it had
//! reached, so a job is read through once. A read before the last one's position follows the
//! FAT from the start of the file. Finishing, removing and unmounting close it.
//!
//! # Costs
//!
//! - Listing ([`FileStore::file`]): reading the root directory on from the file last listed
//!   (one block per 16 entries): listing all files in order costs about one block read per
//!   file, never a walk from the start for each.
//! - [`FileStore::size`], [`FileStore::remove`], [`FileStore::create`], [`FileStore::finish`],
//!   a read of another file than the last, and mounting: reading the root directory once or a
//!   few times.
//! - [`FileStore::append`]: the blocks written (and read first, the block the last append
//!   ended in, unless it is the block last read or written), two FAT blocks (both copies)
//!   read and written per cluster added, and once per file the directory entry.
//! - [`FileStore::finish`] and [`FileStore::remove`]: a few directory blocks written, and the
//!   FAT blocks (both copies) that hold the freed clusters' entries: 128 entries a block on
//!   FAT32, 256 on FAT16.
//!
//! # Execution context
//!
//! Thread. Every method blocks for its card transfers (an SD card over SPI: about a
//! millisecond per block, and up to a few hundred milliseconds when the card is busy).
//!
//! # Errors
//!
//! A failed transfer and a card that cannot be mounted are [`FileError::Device`]
//! ([`SdFileStore::mount`] tells which: [`MountError`]); a full card or a full FAT16 root
//! directory is [`FileError::Full`] (a FAT32 root directory grows by a cluster); names are
//! checked before anything is written. A failed operation changes nothing that is seen, and a
//! write in progress goes on as it was (when the card has lost what was appended, the write
//! can only be abandoned: [`FileError::Device`] until then). Once a commit is done, the
//! operation succeeds: a cleanup that fails after it is finished by the next mount, create,
//! finish or removal. The store's own code does not panic on any card contents: a FAT chain
//! that ends before its file's length is [`FileError::Device`].
//!
//! # Card changes
//!
//! The store mounts the card at its first operation and stays mounted. A board that sees the
//! card taken out (a card-detect switch) calls [`SdFileStore::unmount`], then
//! re-initialises the card before it is used again ([`SdCard::mark_card_uninit`] through
//! [`SdFileStore::device`]); the next operation mounts the new card. A card swapped without
//! an unmount fails its transfers until then.
//!
//! [`SdCard`]: embedded_sdmmc::SdCard
//! [`SdCard::mark_card_uninit`]: embedded_sdmmc::SdCard::mark_card_uninit

use core::fmt;
use core::ops::ControlFlow;

pub use embedded_sdmmc;
use embedded_sdmmc::{Block, BlockDevice, BlockIdx, TimeSource, Timestamp};
use forja_hal_abstraction::files::{FileError, FileInfo, FileName, FileStore, MAX_NAME_LEN};
use forja_hal_abstraction::{Error, ErrorKind};

/// The name of the file being written, in the root directory.
pub const WRITING: &str = "~FORJA.NEW";

/// The name of the entry that holds a removed or replaced file's clusters while they are
/// freed, in the root directory.
pub const REMOVING: &str = "~FORJA.OLD";

/// [`WRITING`] as stored in a directory entry.
const WRITING_SFN: [u8; 11] = *b"~FORJA  NEW";
/// [`REMOVING`] as stored in a directory entry.
const REMOVING_SFN: [u8; 11] = *b"~FORJA  OLD";

/// Bytes of a block.
const BLOCK: usize = Block::LEN;
/// Bytes of a directory entry.
const SLOT: usize = 32;
/// The first byte of a deleted directory entry.
const DELETED: u8 = 0xE5;
/// Directory entry attributes.
const HIDDEN: u8 = 0x02;
const SYSTEM: u8 = 0x04;
const VOLUME: u8 = 0x08;
const DIRECTORY: u8 = 0x10;
const ARCHIVE: u8 = 0x20;
/// The attributes of a long-name entry (under the mask 0x3F).
const LONG_NAME: u8 = 0x0F;
/// Byte 12 of an entry: its base name, its extension, is in small letters.
const SMALL_BASE: u8 = 0x08;
const SMALL_EXT: u8 = 0x10;
/// Where the 13 UTF-16 characters of a long-name entry are.
const LONG_CHARS: [usize; 13] = [1, 3, 5, 7, 9, 14, 16, 18, 20, 22, 24, 28, 30];
/// The largest file on FAT: 4 GiB less one byte.
const MAX_FILE: u64 = u32::MAX as u64;

/// A clock that always reads the same time, for the dates of files written by a board
/// without a calendar clock. The default is FAT's first day, 1980-01-01 00:00:00, which PCs
/// show as "no date".
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct FixedTime(pub Timestamp);

impl Default for FixedTime {
    fn default() -> Self {
        Self(Timestamp {
            year_since_1970: 10,
            zero_indexed_month: 0,
            zero_indexed_day: 0,
            hours: 0,
            minutes: 0,
            seconds: 0,
        })
    }
}

impl TimeSource for FixedTime {
    fn get_timestamp(&self) -> Timestamp {
        self.0
    }
}

/// The card could not be mounted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum MountError {
    /// A transfer failed (no card, a card not initialised, a bus fault).
    Device,
    /// The card's first partition is not FAT16 or FAT32 (exFAT, as SDXC cards come formatted;
    /// FAT12; a card without a partition table or with a GPT one).
    NotFat,
}

impl fmt::Display for MountError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Device => "the SD card does not answer",
            Self::NotFat => "the SD card's first partition is not FAT16 or FAT32",
        })
    }
}

impl Error for MountError {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Device => ErrorKind::Hardware,
            Self::NotFat => ErrorKind::Other,
        }
    }
}

/// Whether [`SdFileStore`] can create a file named `name`: an 8.3 name, not a DOS device
/// name nor one of the store's temporaries (see the [module documentation](self)). A name on
/// the card can still clash with a directory or a hidden file, which only `create` finds.
pub fn is_short_name(name: &FileName) -> bool {
    short_name(name).is_some()
}

/// `name` as a directory entry stores it, and its small-letter flags (byte 12), if it is an
/// 8.3 name the store may create.
fn short_name(name: &FileName) -> Option<([u8; 11], u8)> {
    let bytes = name.as_bytes();
    let (base, ext) = match bytes.iter().position(|&b| b == b'.') {
        Some(dot) => (bytes.get(..dot)?, bytes.get(dot + 1..)?),
        None => (bytes, &[][..]),
    };
    let fits = |part: &[u8], max| {
        part.len() <= max && part.iter().all(|b| short_char(b.to_ascii_uppercase()))
    };
    let bare_dot = ext.is_empty() && bytes.last() == Some(&b'.');
    if base.is_empty() || bare_dot || !fits(base, 8) || !fits(ext, 3) {
        return None;
    }
    let mut sfn = [b' '; 11];
    for (dst, b) in sfn.iter_mut().zip(base) {
        *dst = b.to_ascii_uppercase();
    }
    for (dst, b) in sfn.iter_mut().skip(8).zip(ext) {
        *dst = b.to_ascii_uppercase();
    }
    let small = |part: &[u8]| {
        part.iter().any(u8::is_ascii_lowercase) && !part.iter().any(u8::is_ascii_uppercase)
    };
    let mut case = 0;
    if small(base) {
        case |= SMALL_BASE;
    }
    if small(ext) {
        case |= SMALL_EXT;
    }
    let device = matches!(
        sfn.get(..8),
        Some(b"CON     " | b"PRN     " | b"AUX     " | b"NUL     ")
    ) || (matches!(sfn.get(..3), Some(b"COM" | b"LPT"))
        && matches!(sfn.get(3), Some(b'1'..=b'9'))
        && sfn.get(4..8) == Some(&b"    "[..]));
    if device || sfn == WRITING_SFN || sfn == REMOVING_SFN {
        return None;
    }
    Some((sfn, case))
}

/// A byte a short name may hold (in capitals).
fn short_char(b: u8) -> bool {
    b.is_ascii_uppercase() || b.is_ascii_digit() || b"!#$%&'()-@^_`{}~".contains(&b)
}

fn le16(b: &[u8], at: usize) -> u16 {
    b.get(at..at + 2)
        .and_then(|s| s.try_into().ok())
        .map_or(0, u16::from_le_bytes)
}

fn le32(b: &[u8], at: usize) -> u32 {
    b.get(at..at + 4)
        .and_then(|s| s.try_into().ok())
        .map_or(0, u32::from_le_bytes)
}

fn put16(b: &mut [u8], at: usize, v: u16) {
    if let Some(s) = b.get_mut(at..at + 2) {
        s.copy_from_slice(&v.to_le_bytes());
    }
}

fn put32(b: &mut [u8], at: usize, v: u32) {
    if let Some(s) = b.get_mut(at..at + 4) {
        s.copy_from_slice(&v.to_le_bytes());
    }
}

fn read_block<D: BlockDevice>(d: &D, buf: &mut [Block; 1], at: u32) -> Result<(), FileError> {
    d.read(buf, BlockIdx(at)).map_err(|_| FileError::Device)
}

fn write_block<D: BlockDevice>(d: &D, buf: &[Block; 1], at: u32) -> Result<(), FileError> {
    d.write(buf, BlockIdx(at)).map_err(|_| FileError::Device)
}

/// `t` as a directory entry stores a time and a date (bytes 22..26 of an entry). Each field
/// is kept to its bits, whatever a clock gives.
fn fat_stamp(t: &Timestamp) -> [u8; 4] {
    #[inline(always)]
    fn field(v: u8, bits: u32, at: u32) -> u16 {
        (u16::from(v) & ((1 << bits) - 1)) << at
    }
    let time = field(t.hours, 5, 11) | field(t.minutes, 6, 5) | field(t.seconds / 2, 5, 0);
    let date = field(t.year_since_1970.saturating_sub(10), 7, 9)
        | field(t.zero_indexed_month.saturating_add(1), 4, 5)
        | field(t.zero_indexed_day.saturating_add(1), 5, 0);
    let [t0, t1] = time.to_le_bytes();
    let [d0, d1] = date.to_le_bytes();
    [t0, t1, d0, d1]
}

/// A new directory entry: the short name `sfn`, an archive, created and written at `stamp`,
/// holding the chain from `cluster` and `size` bytes.
fn new_entry(sfn: &[u8; 11], stamp: [u8; 4], fat32: bool, cluster: u32, size: u32) -> [u8; SLOT] {
    let mut raw = [0u8; SLOT];
    let (name, rest) = raw.split_at_mut(11);
    name.copy_from_slice(sfn);
    if let Some(attr) = rest.first_mut() {
        *attr = ARCHIVE;
    }
    // Created (14..18), last read (18..20) and last written (22..26) at `stamp`.
    for (at, bytes) in [(14, &stamp[..]), (18, &stamp[2..]), (22, &stamp[..])] {
        if let Some(dst) = raw.get_mut(at..at + bytes.len()) {
            dst.copy_from_slice(bytes);
        }
    }
    set_cluster(&mut raw, fat32, cluster);
    put32(&mut raw, 28, size);
    raw
}

/// Where the volume's structures are, in absolute blocks.
#[derive(Clone, Copy, Debug)]
struct Geometry {
    fat32: bool,
    fat_start: u32,
    fat_blocks: u32,
    fats: u32,
    /// FAT16: the root directory's fixed region.
    root_start: u32,
    root_blocks: u32,
    /// FAT32: the root directory's first cluster.
    root_cluster: u32,
    /// The first block of cluster 2.
    data_start: u32,
    cluster_blocks: u32,
    /// Data clusters: numbers 2..clusters + 2.
    clusters: u32,
    /// FAT32: the FSInfo block.
    info: u32,
}

impl Geometry {
    /// Read the partition table and the first partition's boot block, checked as far as the
    /// store relies on them.
    fn read<D: BlockDevice>(d: &D) -> Result<Self, MountError> {
        let mut buf = [Block::new()];
        read_block(d, &mut buf, 0).map_err(|_| MountError::Device)?;
        let [block] = &buf;
        let mbr = &block.contents;
        let kind = mbr.get(450).copied().unwrap_or(0);
        let status = mbr.get(446).copied().unwrap_or(0xFF);
        if le16(mbr, 510) != 0xAA55
            || status & 0x7F != 0
            || !matches!(kind, 0x04 | 0x06 | 0x0B | 0x0C | 0x0E)
        {
            return Err(MountError::NotFat);
        }
        let start = le32(mbr, 454);
        read_block(d, &mut buf, start).map_err(|_| MountError::Device)?;
        let [block] = &buf;
        Self::parse(&block.contents, start).ok_or(MountError::NotFat)
    }

    /// The geometry of the FAT16 or FAT32 boot block `bpb`, at block `start`.
    fn parse(bpb: &[u8], start: u32) -> Option<Self> {
        let cluster_blocks = u32::from(bpb.get(13).copied()?);
        let reserved = u32::from(le16(bpb, 14));
        let fats = u32::from(bpb.get(16).copied()?);
        let root_entries = u32::from(le16(bpb, 17));
        let total = match le16(bpb, 19) {
            0 => le32(bpb, 32),
            n => u32::from(n),
        };
        let fat_blocks = match le16(bpb, 22) {
            0 => le32(bpb, 36),
            n => u32::from(n),
        };
        let sane = le16(bpb, 510) == 0xAA55
            && usize::from(le16(bpb, 11)) == BLOCK
            && cluster_blocks.is_power_of_two()
            && cluster_blocks <= 128
            && reserved >= 1
            && (1..=2).contains(&fats)
            && fat_blocks > 0;
        if !sane {
            return None;
        }
        let root_blocks = (root_entries * SLOT as u32).div_ceil(BLOCK as u32);
        let fat_start = start.checked_add(reserved)?;
        let root_start = fat_start.checked_add(fats.checked_mul(fat_blocks)?)?;
        let data_start = root_start.checked_add(root_blocks)?;
        let data_blocks = start.checked_add(total)?.checked_sub(data_start)?;
        let clusters = data_blocks / cluster_blocks;
        let fat32 = clusters >= 65525;
        let entry_bytes = if fat32 { 4 } else { 2 };
        let fat_covers =
            u64::from(fat_blocks) * BLOCK as u64 / entry_bytes >= u64::from(clusters) + 2;
        if clusters < 4085 || !fat_covers {
            return None;
        }
        let (root_cluster, info) = if fat32 {
            let root = le32(bpb, 44);
            let info = u32::from(le16(bpb, 48));
            let ok = le16(bpb, 42) == 0
                && root >= 2
                && root - 2 < clusters
                && (1..reserved).contains(&info);
            if !ok {
                return None;
            }
            (root, start.checked_add(info)?)
        } else {
            if root_entries == 0 {
                return None;
            }
            (0, 0)
        };
        Some(Self {
            fat32,
            fat_start,
            fat_blocks,
            fats,
            root_start,
            root_blocks,
            root_cluster,
            data_start,
            cluster_blocks,
            clusters,
            info,
        })
    }

    /// Mark the FAT32 count of free clusters unknown (PCs count them when they need it): the
    /// store keeps no count as it takes and frees clusters.
    fn forget_free_count<D: BlockDevice>(&self, d: &D) -> Result<(), MountError> {
        if !self.fat32 {
            return Ok(());
        }
        let mut buf = [Block::new()];
        read_block(d, &mut buf, self.info).map_err(|_| MountError::Device)?;
        let [block] = &mut buf;
        let signed = le32(&block.contents, 0) == 0x4161_5252
            && le32(&block.contents, 484) == 0x6141_7272
            && le32(&block.contents, 508) == 0xAA55_0000;
        if !signed {
            return Err(MountError::NotFat);
        }
        if le32(&block.contents, 488) != u32::MAX {
            put32(&mut block.contents, 488, u32::MAX);
            write_block(d, &buf, self.info).map_err(|_| MountError::Device)?;
        }
        Ok(())
    }

    /// Whether `c` is a data cluster of the volume.
    fn is_cluster(&self, c: u32) -> bool {
        c >= 2 && c - 2 < self.clusters
    }

    /// The first block of data cluster `c`.
    fn cluster_block(&self, c: u32) -> u32 {
        self.data_start + (c - 2) * self.cluster_blocks
    }

    /// Bytes of a cluster.
    fn cluster_bytes(&self) -> u32 {
        self.cluster_blocks * BLOCK as u32
    }

    /// The block (of the first FAT) and the byte in it of cluster `c`'s FAT entry.
    fn fat_place(&self, c: u32) -> (u32, usize) {
        let at = if self.fat32 { c * 4 } else { c * 2 };
        (
            self.fat_start + at / BLOCK as u32,
            (at % BLOCK as u32) as usize,
        )
    }

    fn fat_entry(&self, block: &[u8], at: usize) -> u32 {
        if self.fat32 {
            le32(block, at) & 0x0FFF_FFFF
        } else {
            u32::from(le16(block, at))
        }
    }

    fn set_fat_entry(&self, block: &mut [u8], at: usize, v: u32) {
        if self.fat32 {
            let kept = le32(block, at) & 0xF000_0000;
            put32(block, at, kept | (v & 0x0FFF_FFFF));
        } else {
            put16(block, at, v as u16);
        }
    }

    /// The FAT entry of the last cluster of a chain.
    fn end_of_chain(&self) -> u32 {
        if self.fat32 { 0x0FFF_FFFF } else { 0xFFFF }
    }

    /// The position of the root directory's first entry.
    fn root(&self) -> Pos {
        Pos {
            cluster: if self.fat32 { self.root_cluster } else { 0 },
            block: 0,
            slot: 0,
        }
    }

    /// The absolute block of the directory entry at `p`.
    fn slot_block(&self, p: Pos) -> u32 {
        if p.cluster == 0 {
            self.root_start + p.block
        } else {
            self.cluster_block(p.cluster) + p.block
        }
    }
}

/// Cluster `c`'s FAT entry.
fn fat_get<D: BlockDevice>(d: &D, g: &Geometry, c: u32) -> Result<u32, FileError> {
    let mut buf = [Block::new()];
    let (block, at) = g.fat_place(c);
    read_block(d, &mut buf, block)?;
    let [b] = &buf;
    Ok(g.fat_entry(&b.contents, at))
}

/// Write the FAT block `buf`, read from the first FAT's block `block`, to every FAT.
fn write_fat<D: BlockDevice>(
    d: &D,
    g: &Geometry,
    buf: &[Block; 1],
    block: u32,
) -> Result<(), FileError> {
    for copy in 0..g.fats {
        write_block(d, buf, block + copy * g.fat_blocks)?;
    }
    Ok(())
}

/// Free the chain of clusters from `head`, in its order, one FAT block at a time. Stops at the
/// chain's end, at a cluster already free (a chain partly freed before) and after as many
/// clusters as the volume has (a FAT with a loop).
fn free_chain<D: BlockDevice>(d: &D, g: &Geometry, head: u32) -> Result<(), FileError> {
    let mut buf = [Block::new()];
    let mut loaded: Option<u32> = None;
    let mut dirty = false;
    let mut c = head;
    let mut left = g.clusters;
    while g.is_cluster(c) && left > 0 {
        left -= 1;
        let (block, at) = g.fat_place(c);
        if loaded != Some(block) {
            if let (Some(previous), true) = (loaded, dirty) {
                write_fat(d, g, &buf, previous)?;
            }
            read_block(d, &mut buf, block)?;
            loaded = Some(block);
            dirty = false;
        }
        let [b] = &mut buf;
        let next = g.fat_entry(&b.contents, at);
        if next == 0 {
            break;
        }
        g.set_fat_entry(&mut b.contents, at, 0);
        dirty = true;
        c = next;
    }
    if let (Some(block), true) = (loaded, dirty) {
        write_fat(d, g, &buf, block)?;
    }
    Ok(())
}

/// Set cluster `c`'s FAT entry to `v`, in every FAT.
fn fat_set<D: BlockDevice>(d: &D, g: &Geometry, c: u32, v: u32) -> Result<(), FileError> {
    let mut buf = [Block::new()];
    let (block, at) = g.fat_place(c);
    read_block(d, &mut buf, block)?;
    let [b] = &mut buf;
    g.set_fat_entry(&mut b.contents, at, v);
    write_fat(d, g, &buf, block)
}

/// Take a free cluster, the first from `hint` on (round the volume), marked as a chain's last.
/// Errors: [`FileError::Full`], the volume has none.
fn allocate<D: BlockDevice>(d: &D, g: &Geometry, hint: u32) -> Result<u32, FileError> {
    let mut buf = [Block::new()];
    let mut loaded = None;
    let first = if g.is_cluster(hint) { hint - 2 } else { 0 };
    for k in 0..g.clusters {
        let c = 2 + (first + k) % g.clusters;
        let (block, at) = g.fat_place(c);
        if loaded != Some(block) {
            read_block(d, &mut buf, block)?;
            loaded = Some(block);
        }
        let [b] = &mut buf;
        if g.fat_entry(&b.contents, at) == 0 {
            g.set_fat_entry(&mut b.contents, at, g.end_of_chain());
            write_fat(d, g, &buf, block)?;
            return Ok(c);
        }
    }
    Err(FileError::Full)
}

/// Make `last` the end of its chain and free the clusters after it, if any.
fn cut_after<D: BlockDevice>(d: &D, g: &Geometry, last: u32) -> Result<(), FileError> {
    let rest = fat_get(d, g, last)?;
    if !g.is_cluster(rest) {
        return Ok(());
    }
    fat_set(d, g, last, g.end_of_chain())?;
    free_chain(d, g, rest)
}

/// A directory entry's place: the cluster of the root directory's chain (0 for FAT16's fixed
/// root region), the block in it, the entry in the block.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
struct Pos {
    cluster: u32,
    block: u32,
    slot: u8,
}

/// Call `f` with each entry of the root directory from `from` on, until it breaks or the
/// directory ends (past its end mark, whose first byte is 0, every entry is free).
fn walk<D: BlockDevice>(
    d: &D,
    g: &Geometry,
    from: Pos,
    f: &mut dyn FnMut(Pos, &[u8]) -> ControlFlow<()>,
) -> Result<(), FileError> {
    let mut buf = [Block::new()];
    let mut pos = from;
    let mut hops = 0;
    loop {
        read_block(d, &mut buf, g.slot_block(pos))?;
        let [block] = &buf;
        for (i, raw) in block
            .contents
            .chunks_exact(SLOT)
            .enumerate()
            .skip(usize::from(pos.slot))
        {
            let here = Pos {
                slot: i as u8,
                ..pos
            };
            if f(here, raw).is_break() {
                return Ok(());
            }
        }
        pos.slot = 0;
        pos.block += 1;
        if pos.cluster == 0 {
            if pos.block >= g.root_blocks {
                return Ok(());
            }
        } else if pos.block >= g.cluster_blocks {
            let next = fat_get(d, g, pos.cluster)?;
            hops += 1;
            if !g.is_cluster(next) || hops > g.clusters {
                return Ok(());
            }
            pos = Pos {
                cluster: next,
                block: 0,
                slot: 0,
            };
        }
    }
}

/// Change the directory entry at `p`.
fn patch<D: BlockDevice>(
    d: &D,
    g: &Geometry,
    p: Pos,
    f: &dyn Fn(&mut [u8]),
) -> Result<(), FileError> {
    let mut buf = [Block::new()];
    let at = g.slot_block(p);
    read_block(d, &mut buf, at)?;
    let [block] = &mut buf;
    let start = usize::from(p.slot) * SLOT;
    if let Some(slot) = block.contents.get_mut(start..start + SLOT) {
        f(slot);
    }
    write_block(d, &buf, at)
}

/// Mark `count` consecutive directory entries from `from` deleted.
fn delete_slots<D: BlockDevice>(
    d: &D,
    g: &Geometry,
    from: Pos,
    count: usize,
) -> Result<(), FileError> {
    let mut left = count;
    let mut result = Ok(());
    walk(d, g, from, &mut |p, _| {
        if left == 0 {
            return ControlFlow::Break(());
        }
        left -= 1;
        result = patch(d, g, p, &|slot| {
            if let Some(first) = slot.first_mut() {
                *first = DELETED;
            }
        });
        if result.is_err() || left == 0 {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    })?;
    result
}

/// Write the new root directory entry `raw` in the first free one, and return its place. A
/// FAT32 root directory without a free entry grows by a cluster. Errors:
/// [`FileError::Full`], a FAT16 root directory (or the volume) has no room.
fn add_entry<D: BlockDevice>(d: &D, g: &Geometry, raw: &[u8; SLOT]) -> Result<Pos, FileError> {
    let mut free = None;
    let mut last = g.root();
    walk(d, g, g.root(), &mut |p, slot| {
        last = p;
        if matches!(slot.first(), Some(&(0 | DELETED))) {
            free = Some(p);
            return ControlFlow::Break(());
        }
        ControlFlow::Continue(())
    })?;
    let pos = match free {
        Some(p) => p,
        None if g.fat32 => {
            // A cluster of free entries, zeroed before the directory's chain takes it in.
            let c = allocate(d, g, last.cluster)?;
            let zero = [Block::new()];
            for block in 0..g.cluster_blocks {
                write_block(d, &zero, g.cluster_block(c) + block)?;
            }
            fat_set(d, g, last.cluster, c)?;
            Pos {
                cluster: c,
                block: 0,
                slot: 0,
            }
        }
        None => return Err(FileError::Full),
    };
    patch(d, g, pos, &|slot| slot.copy_from_slice(raw))?;
    Ok(pos)
}

/// The checksum of a short name that its long-name entries carry.
fn checksum(sfn: &[u8; 11]) -> u8 {
    sfn.iter()
        .fold(0u8, |sum, &b| sum.rotate_right(1).wrapping_add(b))
}

/// The long-name entries read before a short entry.
#[derive(Clone, Copy)]
struct LongRun {
    /// The first of them, and how many.
    first: Pos,
    slots: u8,
    /// The sequence number the next one must carry (0: the run is complete).
    next: u8,
    sum: u8,
    /// The name's ASCII characters, as far as they fit.
    chars: [u8; MAX_NAME_LEN],
    /// The name's length: up to its terminator, or 13 characters a slot.
    len: usize,
    /// The position of the first character outside ASCII (`usize::MAX`: none).
    foreign: usize,
    /// The name's first character.
    lead: u16,
}

impl LongRun {
    /// Take in the long-name entry `raw` at `at`: a run starts at its last part and goes on in
    /// descending order.
    fn step(run: &mut Option<Self>, at: Pos, raw: &[u8]) {
        let order = raw.first().copied().unwrap_or(0);
        let seq = order & 0x1F;
        let sum = raw.get(13).copied().unwrap_or(0);
        if order & 0x40 != 0 {
            *run = (1..=20).contains(&seq).then_some(Self {
                first: at,
                slots: 1,
                next: seq - 1,
                sum,
                chars: [0; MAX_NAME_LEN],
                len: usize::from(seq) * 13,
                foreign: usize::MAX,
                lead: 0,
            });
        } else if let Some(r) = run.as_mut()
            && r.next != 0
            && seq == r.next
            && sum == r.sum
        {
            r.slots += 1;
            r.next = seq - 1;
        } else {
            *run = None;
        }
        let Some(run) = run.as_mut() else {
            return;
        };
        let base = usize::from(seq - 1) * 13;
        for (k, &offset) in LONG_CHARS.iter().enumerate() {
            let p = base + k;
            match le16(raw, offset) {
                0x0000 => run.len = run.len.min(p),
                0xFFFF => {}
                unit => {
                    if p == 0 {
                        run.lead = unit;
                    }
                    match (run.chars.get_mut(p), u8::try_from(unit)) {
                        (Some(c), Ok(b)) if b.is_ascii() => *c = b,
                        (None, Ok(b)) if b.is_ascii() => {}
                        _ => run.foreign = run.foreign.min(p),
                    }
                }
            }
        }
    }

    /// The long name, if it is a [`FileName`].
    fn name(&self) -> Option<FileName> {
        if self.foreign < self.len {
            return None;
        }
        FileName::new(self.chars.get(..self.len)?).ok()
    }
}

/// A short directory entry, with the long name before it.
#[derive(Clone, Copy)]
struct Entry {
    pos: Pos,
    sfn: [u8; 11],
    attr: u8,
    case: u8,
    cluster: u32,
    size: u32,
    /// The last write's time and date (bytes 22..26).
    stamp: [u8; 4],
    long: Option<LongRun>,
}

impl Entry {
    fn new(pos: Pos, raw: &[u8], fat32: bool, long: Option<LongRun>) -> Self {
        let mut sfn = [b' '; 11];
        if let Some(name) = raw.get(..11) {
            sfn.copy_from_slice(name);
        }
        let high = if fat32 { u32::from(le16(raw, 20)) } else { 0 };
        let long = long.filter(|run| run.next == 0 && run.sum == checksum(&sfn));
        Self {
            pos,
            sfn,
            attr: raw.get(11).copied().unwrap_or(0),
            case: raw.get(12).copied().unwrap_or(0),
            cluster: (high << 16) | u32::from(le16(raw, 26)),
            size: le32(raw, 28),
            stamp: raw
                .get(22..26)
                .and_then(|s| s.try_into().ok())
                .unwrap_or([0; 4]),
            long,
        }
    }

    fn is_temporary(&self) -> bool {
        self.sfn == WRITING_SFN || self.sfn == REMOVING_SFN
    }

    /// The short name as a name, with the small-letter flags applied, if it is plain ASCII.
    fn short_name(&self) -> Option<FileName> {
        let part = |bytes: &[u8], small: bool, out: &mut [u8], at: &mut usize| -> Option<()> {
            for &b in bytes.iter().take_while(|&&b| b != b' ') {
                if !short_char(b) {
                    return None;
                }
                *out.get_mut(*at)? = if small { b.to_ascii_lowercase() } else { b };
                *at += 1;
            }
            Some(())
        };
        let mut text = [0u8; 12];
        let mut len = 0;
        let (base, ext) = self.sfn.split_at(8);
        part(base, self.case & SMALL_BASE != 0, &mut text, &mut len)?;
        if ext.first().is_some_and(|&b| b != b' ') {
            *text.get_mut(len)? = b'.';
            len += 1;
            part(ext, self.case & SMALL_EXT != 0, &mut text, &mut len)?;
        }
        FileName::new(text.get(..len)?).ok()
    }

    /// The name the file is listed under, if it is listed.
    fn listed(&self) -> Option<FileName> {
        let hidden = self.attr & (DIRECTORY | VOLUME | HIDDEN | SYSTEM) != 0
            || self.is_temporary()
            || self.long.is_some_and(|run| run.lead == u16::from(b'.'));
        if hidden {
            return None;
        }
        let short = self.short_name()?;
        Some(self.long.and_then(|run| run.name()).unwrap_or(short))
    }

    /// Whether the file is listed and answers to `name`, by its long or its short name.
    fn answers_to(&self, name: &FileName) -> bool {
        self.listed().is_some()
            && (self.long.and_then(|run| run.name()) == Some(*name)
                || self.short_name() == Some(*name))
    }
}

/// Call `f` with each short entry of the root directory from `from` on (after it, with
/// `after`), with its long name.
fn entries<D: BlockDevice>(
    d: &D,
    g: &Geometry,
    from: Pos,
    after: bool,
    f: &mut dyn FnMut(&Entry) -> ControlFlow<()>,
) -> Result<(), FileError> {
    scan_root(d, g, from, after, f, &mut |_, _| {})
}

/// [`entries`], and `orphans` with each run of long-name entries that belongs to no short
/// entry (its first entry and how many), as a power cut or another implementation leaves
/// them.
fn scan_root<D: BlockDevice>(
    d: &D,
    g: &Geometry,
    from: Pos,
    after: bool,
    f: &mut dyn FnMut(&Entry) -> ControlFlow<()>,
    orphans: &mut dyn FnMut(Pos, usize),
) -> Result<(), FileError> {
    let mut run: Option<LongRun> = None;
    // The long-name entries since the last other entry.
    let mut pending: Option<(Pos, usize)> = None;
    let mut skip = after;
    let mut stopped = false;
    walk(d, g, from, &mut |pos, raw| {
        let first = raw.first().copied().unwrap_or(0);
        if first == 0 {
            return ControlFlow::Break(());
        }
        if core::mem::take(&mut skip) {
            return ControlFlow::Continue(());
        }
        let attr = raw.get(11).copied().unwrap_or(0);
        if first != DELETED && attr & 0x3F == LONG_NAME {
            LongRun::step(&mut run, pos, raw);
            match &mut pending {
                Some((_, n)) => *n += 1,
                None => pending = Some((pos, 1)),
            }
            return ControlFlow::Continue(());
        }
        let entry = (first != DELETED).then(|| Entry::new(pos, raw, g.fat32, run.take()));
        run = None;
        if let Some((p, n)) = pending.take() {
            let owned = entry
                .and_then(|e| e.long)
                .map_or(0, |run| usize::from(run.slots));
            if n > owned {
                orphans(p, n - owned);
            }
        }
        match entry {
            Some(e) => {
                stopped = f(&e).is_break();
                if stopped {
                    ControlFlow::Break(())
                } else {
                    ControlFlow::Continue(())
                }
            }
            None => ControlFlow::Continue(()),
        }
    })?;
    if let (Some((p, n)), false) = (pending, stopped) {
        orphans(p, n);
    }
    Ok(())
}

/// Clean up after a power cut: delete the temporaries (see [`discard`]) and the long-name
/// entries that belong to no file.
fn tidy<D: BlockDevice>(d: &D, g: &Geometry) -> Result<(), FileError> {
    let found = survey(d, g, None, None)?;
    for t in [found.writing, found.removing].iter().flatten() {
        discard(d, g, t)?;
    }
    // A few runs a pass; a directory littered with more takes more passes.
    for _ in 0..64 {
        let mut runs = [(g.root(), 0); 8];
        let mut count = 0;
        scan_root(
            d,
            g,
            g.root(),
            false,
            &mut |_| ControlFlow::Continue(()),
            &mut |p, n| {
                if let Some(run) = runs.get_mut(count) {
                    *run = (p, n);
                }
                count += 1;
            },
        )?;
        for &(p, n) in runs.iter().take(count) {
            delete_slots(d, g, p, n)?;
        }
        if count <= runs.len() {
            break;
        }
    }
    Ok(())
}

/// What the root directory holds about a name.
#[derive(Default)]
struct Survey {
    /// The first listed file that answers to the name.
    file: Option<Entry>,
    /// An unlisted entry (a directory, the volume label, a hidden or system file) with the
    /// short name.
    clash: bool,
    writing: Option<Entry>,
    removing: Option<Entry>,
}

fn survey<D: BlockDevice>(
    d: &D,
    g: &Geometry,
    name: Option<&FileName>,
    sfn: Option<[u8; 11]>,
) -> Result<Survey, FileError> {
    let mut found = Survey::default();
    entries(d, g, g.root(), false, &mut |e| {
        if e.sfn == WRITING_SFN {
            found.writing = Some(*e);
        } else if e.sfn == REMOVING_SFN {
            found.removing = Some(*e);
        } else if found.file.is_none() && name.is_some_and(|n| e.answers_to(n)) {
            found.file = Some(*e);
        } else if Some(e.sfn) == sfn && e.listed().is_none() {
            found.clash = true;
        }
        ControlFlow::Continue(())
    })?;
    Ok(found)
}

/// Delete the temporary `t`, with its clusters unless another entry owns them (a commit made
/// them that entry's).
fn discard<D: BlockDevice>(d: &D, g: &Geometry, t: &Entry) -> Result<(), FileError> {
    if g.is_cluster(t.cluster) {
        let mut owned = false;
        entries(d, g, g.root(), false, &mut |e| {
            owned = !e.is_temporary() && e.cluster == t.cluster;
            if owned {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        })?;
        if !owned {
            free_chain(d, g, t.cluster)?;
        }
    }
    delete_slots(d, g, t.pos, 1)
}

/// Set the first cluster of the directory entry `slot`.
fn set_cluster(slot: &mut [u8], fat32: bool, c: u32) {
    if fat32 {
        put16(slot, 20, (c >> 16) as u16);
    }
    put16(slot, 26, c as u16);
}

/// The file being written.
#[derive(Clone, Copy)]
struct Writing {
    name: FileName,
    sfn: [u8; 11],
    case: u8,
    /// The place of its [`WRITING`] entry.
    pos: Pos,
    /// The chain's first cluster (0: none yet).
    head: u32,
    /// The cluster that holds the last byte appended (0: none appended).
    last: u32,
    /// Bytes appended.
    len: u32,
    /// The directory entry holds the first cluster, so that a cleanup finds the clusters.
    anchored: bool,
    /// A failed append may have left clusters past `last` in the chain.
    spare: bool,
    /// The temporary is gone from the card: the write can only be abandoned.
    lost: bool,
}

/// The file last read, and how far into its chain the reading got.
#[derive(Clone, Copy)]
struct Reading {
    name: FileName,
    size: u32,
    head: u32,
    /// The cluster reached, and the file's byte at its start.
    cluster: u32,
    start: u32,
}

/// A [`FileStore`] on a FAT16 or FAT32 SD card. See the [module documentation](self).
///
/// `D` is the card ([`SdCard`](embedded_sdmmc::SdCard) over SPI), `T` the clock that dates the
/// files written.
pub struct SdFileStore<D: BlockDevice, T: TimeSource = FixedTime> {
    card: D,
    time: T,
    mounted: Option<Geometry>,
    writing: Option<Writing>,
    reading: Option<Reading>,
    /// The file last listed: its index and its entry's place.
    listed: Option<(usize, Pos)>,
    /// A block of file data, as the card holds it, and its number: the next read or append in
    /// the same block needs no transfer. Appends write through it.
    cache: [Block; 1],
    cached: Option<u32>,
}

impl<D: BlockDevice> SdFileStore<D, FixedTime> {
    /// The store on `card`, dating files 1980-01-01 ([`FixedTime`]). Nothing is read until
    /// the first operation.
    pub fn new(card: D) -> Self {
        Self::with_time(card, FixedTime::default())
    }
}

impl<D: BlockDevice, T: TimeSource> SdFileStore<D, T> {
    /// The store on `card`, dating the files it writes by `time`. Nothing is read until the
    /// first operation.
    pub fn with_time(card: D, time: T) -> Self {
        Self {
            card,
            time,
            mounted: None,
            writing: None,
            reading: None,
            listed: None,
            cache: [Block::new()],
            cached: None,
        }
    }

    /// Mount the card, if it is not mounted: read its partition table and boot block, mark
    /// its count of free clusters unknown (FAT32), and clean up after a power cut (see the
    /// [module documentation](self)). Every file operation mounts first, so a board calls this
    /// only to tell the user early what is wrong with a card.
    ///
    /// Thread; blocks for a few block reads and writes. Errors: [`MountError`]; the store is
    /// then not mounted, and the next operation tries again.
    pub fn mount(&mut self) -> Result<(), MountError> {
        if self.mounted.is_some() {
            return Ok(());
        }
        self.cached = None;
        let g = Geometry::read(&self.card)?;
        g.forget_free_count(&self.card)?;
        tidy(&self.card, &g).map_err(|_| MountError::Device)?;
        self.mounted = Some(g);
        self.listed = None;
        Ok(())
    }

    /// Whether the card is mounted.
    pub fn is_mounted(&self) -> bool {
        self.mounted.is_some()
    }

    /// Let go of the card: abandon a write in progress (as far as the card still answers),
    /// close the file being read, forget the volume. The next operation mounts again. For a
    /// board that sees the card taken out, or is about to cut its power.
    ///
    /// Thread; blocks for the abandoned write's cleanup. Errors are ignored: a card taken
    /// out is cleaned up at its next mount.
    pub fn unmount(&mut self) {
        let _ = self.abandon();
        self.close_reading();
        self.mounted = None;
        self.listed = None;
    }

    /// Run `f` on the card's block device, for what only the device does (re-initialising an
    /// [`SdCard`](embedded_sdmmc::SdCard), changing its SPI clock). The store keeps no copy of
    /// a block across it.
    ///
    /// Thread; blocks for what `f` does.
    pub fn device<R>(&mut self, f: impl FnOnce(&mut D) -> R) -> R {
        self.cached = None;
        f(&mut self.card)
    }

    /// The geometry of the mounted card, mounting it first.
    fn geometry(&mut self) -> Result<Geometry, FileError> {
        self.mount().map_err(|_| FileError::Device)?;
        self.mounted.ok_or(FileError::Device)
    }

    fn close_reading(&mut self) {
        self.reading = None;
        self.cached = None;
    }

    /// The file `name` being read, found (and another forgotten) if needed.
    fn reader(&mut self, g: &Geometry, name: &FileName) -> Result<Reading, FileError> {
        if let Some(r) = self.reading.filter(|r| r.name == *name) {
            return Ok(r);
        }
        self.close_reading();
        let entry = survey(&self.card, g, Some(name), None)?
            .file
            .ok_or(FileError::NotFound)?;
        if entry.size > 0 && !g.is_cluster(entry.cluster) {
            return Err(FileError::Device);
        }
        let r = Reading {
            name: *name,
            size: entry.size,
            head: entry.cluster,
            cluster: entry.cluster,
            start: 0,
        };
        self.reading = Some(r);
        Ok(r)
    }

    /// Block `block` of file data into the cache, read unless it is there.
    fn load(&mut self, block: u32) -> Result<&mut Block, FileError> {
        if self.cached != Some(block) {
            self.cached = None;
            read_block(&self.card, &mut self.cache, block)?;
            self.cached = Some(block);
        }
        let [b] = &mut self.cache;
        Ok(b)
    }

    /// Copy the bytes of the file `r` from `offset` (inside it) into `buf`, as many as fit and
    /// the file has, following its chain from the cluster reached.
    fn read_from(
        &mut self,
        g: &Geometry,
        r: &mut Reading,
        offset: u32,
        buf: &mut [u8],
    ) -> Result<usize, FileError> {
        if offset < r.start {
            (r.cluster, r.start) = (r.head, 0);
        }
        let want = buf.len().min((r.size - offset) as usize);
        let mut done = 0;
        while done < want {
            let at = offset + done as u32;
            while at - r.start >= g.cluster_bytes() {
                let next = fat_get(&self.card, g, r.cluster)?;
                if !g.is_cluster(next) {
                    return Err(FileError::Device);
                }
                r.cluster = next;
                r.start += g.cluster_bytes();
            }
            let block = g.cluster_block(r.cluster) + (at - r.start) / BLOCK as u32;
            let from = at as usize % BLOCK;
            let n = (BLOCK - from).min(want - done);
            let data = self.load(block)?;
            if let (Some(dst), Some(src)) = (
                buf.get_mut(done..done + n),
                data.contents.get(from..from + n),
            ) {
                dst.copy_from_slice(src);
            }
            done += n;
        }
        Ok(done)
    }

    /// Write `bytes` after the `w.len` bytes of the file `w`, taking the clusters it needs
    /// (those a failed append left first), and write each block through the cache.
    fn put(&mut self, g: &Geometry, w: &mut Writing, bytes: &[u8]) -> Result<(), FileError> {
        let mut done = 0;
        while done < bytes.len() {
            if w.len.is_multiple_of(g.cluster_bytes()) {
                let spare = match w.last {
                    0 => w.head,
                    last => Some(fat_get(&self.card, g, last)?)
                        .filter(|&c| g.is_cluster(c))
                        .unwrap_or(0),
                };
                w.last = match spare {
                    // The first free cluster after the chain's last (from the volume's start
                    // for its first).
                    0 => {
                        let c = allocate(&self.card, g, w.last)?;
                        match w.last {
                            0 => w.head = c,
                            last => fat_set(&self.card, g, last, c)?,
                        }
                        c
                    }
                    c => c,
                };
            }
            let at = w.len % g.cluster_bytes();
            let block = g.cluster_block(w.last) + at / BLOCK as u32;
            let from = at as usize % BLOCK;
            let n = (BLOCK - from).min(bytes.len() - done);
            let data = if from == 0 {
                self.cached = Some(block);
                let [b] = &mut self.cache;
                b.contents.fill(0);
                b
            } else {
                self.load(block)?
            };
            if let (Some(dst), Some(src)) = (
                data.contents.get_mut(from..from + n),
                bytes.get(done..done + n),
            ) {
                dst.copy_from_slice(src);
            }
            let written = write_block(&self.card, &self.cache, block);
            if written.is_err() {
                self.cached = None;
            }
            written?;
            done += n;
            w.len += n as u32;
        }
        Ok(())
    }

    /// Create the [`REMOVING`] entry holding `old`'s clusters. `Ok(false)`: the root
    /// directory has no room for it.
    fn hold_clusters(&mut self, g: &Geometry, old: &Entry) -> Result<bool, FileError> {
        let raw = new_entry(&REMOVING_SFN, old.stamp, g.fat32, old.cluster, old.size);
        match add_entry(&self.card, g, &raw) {
            Ok(_) => Ok(true),
            Err(FileError::Full) => Ok(false),
            Err(e) => Err(e),
        }
    }
}

impl<D: BlockDevice, T: TimeSource> FileStore for SdFileStore<D, T> {
    fn file(&mut self, index: usize) -> Result<Option<FileInfo>, FileError> {
        let g = self.geometry()?;
        let (mut at, from, after) = match self.listed {
            Some((last, pos)) if last < index => (last + 1, pos, true),
            _ => (0, g.root(), false),
        };
        let mut found = None;
        entries(&self.card, &g, from, after, &mut |e| match e.listed() {
            Some(name) if at == index => {
                found = Some((FileInfo { name, size: e.size }, e.pos));
                ControlFlow::Break(())
            }
            Some(_) => {
                at += 1;
                ControlFlow::Continue(())
            }
            None => ControlFlow::Continue(()),
        })?;
        self.listed = found.map(|(_, pos)| (index, pos));
        Ok(found.map(|(info, _)| info))
    }

    fn size(&mut self, name: &FileName) -> Result<u32, FileError> {
        if let Some(r) = self.reading.filter(|r| r.name == *name) {
            return Ok(r.size);
        }
        let g = self.geometry()?;
        let found = survey(&self.card, &g, Some(name), None)?;
        found.file.map(|e| e.size).ok_or(FileError::NotFound)
    }

    fn read(&mut self, name: &FileName, offset: u32, buf: &mut [u8]) -> Result<usize, FileError> {
        let g = self.geometry()?;
        let mut r = self.reader(&g, name)?;
        if offset >= r.size || buf.is_empty() {
            return Ok(0);
        }
        match self.read_from(&g, &mut r, offset, buf) {
            Ok(n) => {
                self.reading = Some(r);
                Ok(n)
            }
            Err(e) => {
                self.close_reading();
                Err(e)
            }
        }
    }

    fn remove(&mut self, name: &FileName) -> Result<(), FileError> {
        let g = self.geometry()?;
        self.close_reading();
        self.listed = None;
        let d = &self.card;
        let found = survey(d, &g, Some(name), None)?;
        let file = found.file.ok_or(FileError::NotFound)?;
        if let Some(t) = found.removing {
            discard(d, &g, &t)?;
        }
        // The commit: the file is no longer seen, its clusters are held by the entry.
        patch(d, &g, file.pos, &|slot| {
            if let Some(sfn) = slot.get_mut(..11) {
                sfn.copy_from_slice(&REMOVING_SFN);
            }
            if let Some(case) = slot.get_mut(12) {
                *case &= !(SMALL_BASE | SMALL_EXT);
            }
        })?;
        // Cleanup: a failure here is finished at the next mount or removal.
        if let Some(run) = file.long {
            let _ = delete_slots(d, &g, run.first, usize::from(run.slots));
        }
        let _ = discard(
            d,
            &g,
            &Entry {
                sfn: REMOVING_SFN,
                long: None,
                ..file
            },
        );
        Ok(())
    }

    fn create(&mut self, name: &FileName) -> Result<(), FileError> {
        if self.writing.is_some() {
            return Err(FileError::Busy);
        }
        let (sfn, case) = short_name(name).ok_or(FileError::BadName)?;
        let g = self.geometry()?;
        let d = &self.card;
        let found = survey(d, &g, None, Some(sfn))?;
        if found.clash {
            return Err(FileError::BadName);
        }
        for t in [found.writing, found.removing].iter().flatten() {
            discard(d, &g, t)?;
        }
        let stamp = fat_stamp(&self.time.get_timestamp());
        let pos = add_entry(d, &g, &new_entry(&WRITING_SFN, stamp, g.fat32, 0, 0))?;
        self.writing = Some(Writing {
            name: *name,
            sfn,
            case,
            pos,
            head: 0,
            last: 0,
            len: 0,
            anchored: false,
            spare: false,
            lost: false,
        });
        Ok(())
    }

    fn append(&mut self, bytes: &[u8]) -> Result<(), FileError> {
        let w = self.writing.ok_or(FileError::NotWriting)?;
        if w.lost {
            return Err(FileError::Device);
        }
        if u64::from(w.len) + bytes.len() as u64 > MAX_FILE {
            return Err(FileError::Full);
        }
        if bytes.is_empty() {
            return Ok(());
        }
        let g = self.geometry()?;
        let mut next = w;
        let mut written = self.put(&g, &mut next, bytes);
        if written.is_ok() && !w.anchored {
            // The first append: the entry takes the chain, for a cleanup to find.
            written = patch(&self.card, &g, w.pos, &|slot| {
                set_cluster(slot, g.fat32, next.head);
                put32(slot, 28, next.len);
            });
            next.anchored = written.is_ok();
        }
        if let Some(kept) = self.writing.as_mut() {
            match written {
                Ok(()) => *kept = next,
                // As it was: the next append writes over what this one left, in the
                // clusters it took.
                Err(_) => {
                    kept.head = next.head;
                    kept.spare = true;
                    // Clusters that no entry holds yet go back at once.
                    if !w.anchored
                        && g.is_cluster(next.head)
                        && free_chain(&self.card, &g, next.head).is_ok()
                    {
                        kept.head = 0;
                    }
                }
            }
        }
        written
    }

    fn finish(&mut self) -> Result<(), FileError> {
        let w = self.writing.ok_or(FileError::NotWriting)?;
        if w.lost {
            return Err(FileError::Device);
        }
        let (name, sfn, case, len) = (w.name, w.sfn, w.case, w.len);
        let g = self.geometry()?;
        self.close_reading();
        self.listed = None;
        let d = &self.card;
        // Clusters that failed appends left past the end go first.
        let head = match (w.spare, w.last) {
            (false, _) => w.head,
            (true, 0) => {
                if g.is_cluster(w.head) {
                    free_chain(d, &g, w.head)?;
                }
                0
            }
            (true, last) => {
                cut_after(d, &g, last)?;
                w.head
            }
        };
        if let Some(kept) = self.writing.as_mut() {
            (kept.head, kept.spare) = (head, false);
        }
        // The entry takes the chain, the length and the time of writing.
        let stamp = fat_stamp(&self.time.get_timestamp());
        patch(d, &g, w.pos, &|slot| {
            set_cluster(slot, g.fat32, head);
            put32(slot, 28, len);
            if let Some(dst) = slot.get_mut(22..26) {
                dst.copy_from_slice(&stamp);
            }
        })?;
        let found = survey(d, &g, Some(&name), Some(sfn))?;
        if let Some(t) = found.removing {
            discard(d, &g, &t)?;
        }
        let Some(new) = found
            .writing
            .filter(|e| e.pos == w.pos && e.size == len && e.cluster == head)
        else {
            if let Some(kept) = self.writing.as_mut() {
                kept.lost = true;
            }
            return Err(FileError::Device);
        };
        if found.clash {
            return Err(FileError::Device);
        }
        match found.file {
            None => {
                // The commit: the temporary takes the name.
                patch(d, &g, new.pos, &|slot| {
                    if let Some(dst) = slot.get_mut(..11) {
                        dst.copy_from_slice(&sfn);
                    }
                    if let Some(flags) = slot.get_mut(12) {
                        *flags = (*flags & !(SMALL_BASE | SMALL_EXT)) | case;
                    }
                })?;
                self.writing = None;
            }
            Some(old) => {
                let moved = g.is_cluster(old.cluster) && old.cluster != new.cluster;
                let held = moved && self.hold_clusters(&g, &old)?;
                let d = &self.card;
                // The name written is the file's own short name, or its long name: the file
                // takes the spelling written (its long name goes). A short name written for a
                // file listed under another long name keeps that long name.
                let respell = old.sfn == sfn && old.long.is_none_or(|run| run.name() == Some(name));
                // The commit: the file's entry takes the new data.
                patch(d, &g, old.pos, &|slot| {
                    set_cluster(slot, g.fat32, new.cluster);
                    put32(slot, 28, new.size);
                    if let Some(stamp) = slot.get_mut(22..26) {
                        stamp.copy_from_slice(&new.stamp);
                    }
                    if let Some(attr) = slot.get_mut(11) {
                        *attr |= ARCHIVE;
                    }
                    if let (true, Some(flags)) = (respell, slot.get_mut(12)) {
                        *flags = (*flags & !(SMALL_BASE | SMALL_EXT)) | case;
                    }
                })?;
                self.writing = None;
                // Cleanup: a failure here is finished at the next mount, create or finish.
                let _ = (|| -> Result<(), FileError> {
                    discard(d, &g, &new)?;
                    if held {
                        let found = survey(d, &g, None, None)?;
                        if let Some(t) = found.removing {
                            discard(d, &g, &t)?;
                        }
                    } else if moved {
                        free_chain(d, &g, old.cluster)?;
                    }
                    if let (true, Some(run)) = (respell, old.long) {
                        delete_slots(d, &g, run.first, usize::from(run.slots))?;
                    }
                    Ok(())
                })();
            }
        }
        Ok(())
    }

    fn abandon(&mut self) -> Result<(), FileError> {
        let Some(w) = self.writing.take() else {
            return Ok(());
        };
        self.cached = None;
        let g = self.geometry()?;
        if !w.anchored && g.is_cluster(w.head) {
            // Clusters a failed first append took, that no entry holds.
            free_chain(&self.card, &g, w.head)?;
        }
        match survey(&self.card, &g, None, None)?.writing {
            Some(t) => discard(&self.card, &g, &t),
            None => Ok(()),
        }
    }

    fn writing(&self) -> Option<FileName> {
        self.writing.as_ref().map(|w| w.name)
    }

    /// `false`: the store writes 8.3 names only.
    fn writes_long_names(&self) -> bool {
        false
    }

    /// [`SdFileStore::mount`], its error as [`FileError::Device`].
    fn mount(&mut self) -> Result<(), FileError> {
        SdFileStore::mount(self).map_err(|_| FileError::Device)
    }

    /// [`SdFileStore::unmount`].
    fn release(&mut self) {
        self.unmount();
    }
}

impl<D: BlockDevice, T: TimeSource> fmt::Debug for SdFileStore<D, T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SdFileStore")
            .field("mounted", &self.mounted.is_some())
            .field("writing", &self.writing.as_ref().map(|w| w.name))
            .field("reading", &self.reading.as_ref().map(|r| r.name))
            .finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use forja_hal_abstraction::files::conformance;
    use std::cell::{Cell, RefCell};
    use std::io::{Cursor, Read as _, Write as _};
    use std::rc::Rc;

    /// The first block of the card's partition.
    const PART: usize = 64;

    #[derive(Debug)]
    struct CardFault;

    impl fmt::Display for CardFault {
        fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.write_str("card fault")
        }
    }

    impl core::error::Error for CardFault {}

    /// A card image in memory, shared with the test, that counts its transfers and fails on
    /// demand: every transfer, or every write after a budget (a power cut).
    #[derive(Clone, Default)]
    struct Card {
        image: Rc<RefCell<Vec<u8>>>,
        failing: Rc<Cell<bool>>,
        writes_left: Rc<Cell<Option<usize>>>,
        reads: Rc<Cell<usize>>,
        writes: Rc<Cell<usize>>,
    }

    impl Card {
        fn with_image(image: Vec<u8>) -> Self {
            Self {
                image: Rc::new(RefCell::new(image)),
                ..Self::default()
            }
        }

        /// Another card holding a copy of this one's image.
        fn copy(&self) -> Self {
            Self::with_image(self.image.borrow().clone())
        }
    }

    impl BlockDevice for Card {
        type Error = CardFault;

        fn read(&self, blocks: &mut [Block], start: BlockIdx) -> Result<(), CardFault> {
            if self.failing.get() {
                return Err(CardFault);
            }
            let image = self.image.borrow();
            for (i, block) in blocks.iter_mut().enumerate() {
                let at = (start.0 as usize + i) * BLOCK;
                block
                    .contents
                    .copy_from_slice(image.get(at..at + BLOCK).ok_or(CardFault)?);
            }
            self.reads.set(self.reads.get() + blocks.len());
            Ok(())
        }

        fn write(&self, blocks: &[Block], start: BlockIdx) -> Result<(), CardFault> {
            if self.failing.get() {
                return Err(CardFault);
            }
            if let Some(left) = self.writes_left.get() {
                if left == 0 {
                    return Err(CardFault);
                }
                self.writes_left.set(Some(left - 1));
            }
            let mut image = self.image.borrow_mut();
            for (i, block) in blocks.iter().enumerate() {
                let at = (start.0 as usize + i) * BLOCK;
                image
                    .get_mut(at..at + BLOCK)
                    .ok_or(CardFault)?
                    .copy_from_slice(&block.contents);
            }
            self.writes.set(self.writes.get() + blocks.len());
            Ok(())
        }

        fn num_blocks(&self) -> Result<embedded_sdmmc::BlockCount, CardFault> {
            Ok(embedded_sdmmc::BlockCount(
                (self.image.borrow().len() / BLOCK) as u32,
            ))
        }
    }

    #[derive(Clone, Copy, Debug)]
    enum Format {
        /// 8 MiB, 1 KiB clusters.
        Fat16,
        /// 34 MiB, 512-byte clusters.
        Fat32,
        /// FAT16 on 2.5 MiB, 512-byte clusters, 16 root directory entries.
        Small,
    }

    /// A card with a partition table and a volume formatted by fatfs, as a PC formats it.
    fn card(format: Format) -> Card {
        let (bytes, fat, cluster, root) = match format {
            Format::Fat16 => (8 << 20, fatfs::FatType::Fat16, 1024, 512),
            Format::Fat32 => (34 << 20, fatfs::FatType::Fat32, 512, 0),
            Format::Small => (5 << 19, fatfs::FatType::Fat16, 512, 16),
        };
        let mut image = vec![0u8; bytes];
        let kind = if matches!(fat, fatfs::FatType::Fat32) {
            0x0C
        } else {
            0x0E
        };
        image[450] = kind;
        image[454..458].copy_from_slice(&(PART as u32).to_le_bytes());
        image[458..462].copy_from_slice(&((bytes / BLOCK - PART) as u32).to_le_bytes());
        image[510] = 0x55;
        image[511] = 0xAA;
        let mut options = fatfs::FormatVolumeOptions::new()
            .fat_type(fat)
            .bytes_per_cluster(cluster);
        if root > 0 {
            options = options.max_root_dir_entries(root);
        }
        fatfs::format_volume(Cursor::new(&mut image[PART * BLOCK..]), options).unwrap();
        Card::with_image(image)
    }

    /// Run `f` on the card as a PC sees it (fatfs, an independent FAT implementation).
    fn pc<R>(card: &Card, f: impl FnOnce(&fatfs::FileSystem<Cursor<&mut [u8]>>) -> R) -> R {
        let mut image = card.image.borrow_mut();
        let fs = fatfs::FileSystem::new(
            Cursor::new(&mut image[PART * BLOCK..]),
            fatfs::FsOptions::new(),
        )
        .unwrap();
        let result = f(&fs);
        fs.unmount().unwrap();
        result
    }

    /// The root directory's files and directories as a PC lists them: names and sizes.
    fn pc_listing(card: &Card) -> Vec<(String, u64)> {
        pc(card, |fs| {
            fs.root_dir()
                .iter()
                .map(|e| e.unwrap())
                .map(|e| (e.file_name(), e.len()))
                .collect()
        })
    }

    fn pc_contents(card: &Card, name: &str) -> Vec<u8> {
        pc(card, |fs| {
            let mut bytes = Vec::new();
            fs.root_dir()
                .open_file(name)
                .unwrap()
                .read_to_end(&mut bytes)
                .unwrap();
            bytes
        })
    }

    fn pc_write(card: &Card, name: &str, bytes: &[u8]) {
        pc(card, |fs| {
            let mut file = fs.root_dir().create_file(name).unwrap();
            file.truncate().unwrap();
            file.write_all(bytes).unwrap();
        });
    }

    /// Free clusters, counted in the FAT (the store leaves the FAT32 count unknown).
    fn free_clusters(card: &Card) -> u32 {
        pc(card, |fs| fs.stats().unwrap().free_clusters())
    }

    fn name(s: &str) -> FileName {
        FileName::new(s.as_bytes()).unwrap()
    }

    /// Bytes that differ from one position to the next, so that a misplaced block shows.
    fn pattern(len: usize, seed: u32) -> Vec<u8> {
        let mut x = seed | 1;
        (0..len)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                x as u8
            })
            .collect()
    }

    fn write<S: FileStore + ?Sized>(store: &mut S, n: &str, bytes: &[u8]) {
        store.create(&name(n)).unwrap();
        for chunk in bytes.chunks(97) {
            store.append(chunk).unwrap();
        }
        store.finish().unwrap();
    }

    fn contents<S: FileStore + ?Sized>(store: &mut S, n: &str) -> Result<Vec<u8>, FileError> {
        let size = store.size(&name(n))? as usize;
        let mut buf = vec![0; size + 10];
        let mut at = 0;
        while at < buf.len() {
            let got = store.read(&name(n), at as u32, &mut buf[at..(at + 300).min(size + 10)])?;
            if got == 0 {
                break;
            }
            at += got;
        }
        buf.truncate(at);
        Ok(buf)
    }

    fn listing<S: FileStore + ?Sized>(store: &mut S) -> Vec<(String, u32)> {
        (0..)
            .map_while(|i| store.file(i).unwrap())
            .map(|f| (f.name.as_str().to_string(), f.size))
            .collect()
    }

    fn strs(list: &[(&str, u32)]) -> Vec<(String, u32)> {
        list.iter().map(|&(n, s)| (n.to_string(), s)).collect()
    }

    #[test]
    fn stamps_keep_each_field_to_its_bits() {
        // FAT's first day, 1980-01-01 00:00:00: date 0x0021, time 0.
        assert_eq!(fat_stamp(&FixedTime::default().0), [0, 0, 0x21, 0]);
        let stamp = |hours, minutes, seconds, month, day| {
            fat_stamp(&Timestamp {
                year_since_1970: 56,
                zero_indexed_month: month,
                zero_indexed_day: day,
                hours,
                minutes,
                seconds,
            })
        };
        // 2026-12-03 21:58:40.
        assert_eq!(stamp(21, 58, 40, 11, 2), [0x54, 0xAF, 0x83, 0x5D]);
        // Out-of-range fields do not spill into their neighbours, nor panic.
        let wild = stamp(255, 255, 255, 255, 255);
        assert_eq!(u16::from_le_bytes([wild[2], wild[3]]) >> 9, 46);
        assert_eq!(u16::from_le_bytes([wild[0], wild[1]]) >> 11, 31);
    }

    #[test]
    fn short_names_are_checked_and_keep_their_case_flags() {
        for good in [
            "a",
            "CUBE~1.GCO",
            "part.gco",
            "Part.g",
            "12345678.abc",
            "a-b_(1).{x}",
        ] {
            assert!(is_short_name(&name(good)), "{good}");
        }
        for bad in [
            "bracket_v2.gcode",
            "123456789.g",
            "a.gcod",
            "a.b.c",
            "abc.",
            "a+b.g",
            "a,b",
            "a=b",
            "a[1].g",
            "CON",
            "con.gco",
            "com1.txt",
            "LPT9",
            "~forja.new",
            "~FORJA.OLD",
        ] {
            assert!(!is_short_name(&name(bad)), "{bad}");
        }
        assert!(is_short_name(&name("COM0")) && is_short_name(&name("CONS.g")));
        assert_eq!(
            short_name(&name("part.GCO")),
            Some((*b"PART    GCO", SMALL_BASE))
        );
        assert_eq!(
            short_name(&name("Part.gco")),
            Some((*b"PART    GCO", SMALL_EXT))
        );
        assert_eq!(
            short_name(&name("a1.g")),
            Some((*b"A1      G  ", SMALL_BASE | SMALL_EXT))
        );
        assert_eq!(short_name(&name("A1")), Some((*b"A1         ", 0)));
    }

    #[test]
    fn files_written_read_back_byte_exact_on_a_pc() {
        for format in [Format::Fat16, Format::Fat32] {
            let card = card(format);
            let mut store = SdFileStore::new(card.clone());
            let cluster = if matches!(format, Format::Fat16) {
                1024
            } else {
                512
            };
            let files = [
                ("job.gco", pattern(12, 1)),
                ("EXACT.BIN", pattern(cluster * 3, 2)),
                ("Mixed.Gco", pattern(cluster * 5 + 1, 3)),
                ("EMPTY.G", Vec::new()),
                ("big.gco", pattern(200_000, 4)),
            ];
            for (n, bytes) in &files {
                write(&mut store, n, bytes);
            }
            assert_eq!(
                listing(&mut store),
                strs(&[
                    ("job.gco", 12),
                    ("EXACT.BIN", cluster as u32 * 3),
                    ("MIXED.GCO", cluster as u32 * 5 + 1),
                    ("EMPTY.G", 0),
                    ("big.gco", 200_000),
                ]),
                "{format:?}"
            );
            for (n, bytes) in &files {
                assert_eq!(&contents(&mut store, n).unwrap(), bytes, "{format:?} {n}");
            }
            store.unmount();
            // A PC sees the same names (small letters kept where FAT can), sizes and bytes.
            assert_eq!(
                pc_listing(&card),
                [
                    ("job.gco", 12),
                    ("EXACT.BIN", cluster as u64 * 3),
                    ("MIXED.GCO", cluster as u64 * 5 + 1),
                    ("EMPTY.G", 0),
                    ("big.gco", 200_000),
                ]
                .map(|(n, s)| (n.to_string(), s)),
                "{format:?}"
            );
            for (n, bytes) in &files {
                assert_eq!(&pc_contents(&card, n), bytes, "{format:?} {n}");
            }
        }
    }

    #[test]
    fn files_a_pc_puts_on_the_card_are_listed_and_read() {
        for format in [Format::Fat16, Format::Fat32] {
            let card = card(format);
            let bracket = pattern(5000, 7);
            pc_write(&card, "bracket_v2.gcode", &bracket);
            pc_write(&card, "CUBE.GCO", b"G1 X1\n");
            pc_write(&card, "my part.gcode", b"G1 Y2\n");
            pc_write(&card, "._bracket_v2.gcode", b"mac");
            pc_write(&card, "Été.gco", b"G1 Z3\n");
            pc(&card, |fs| {
                let dir = fs.root_dir().create_dir("jobs").unwrap();
                dir.create_file("inner.gco")
                    .unwrap()
                    .write_all(b"x")
                    .unwrap();
            });
            let shorts: Vec<String> = pc(&card, |fs| {
                fs.root_dir()
                    .iter()
                    .map(|e| e.unwrap().short_file_name())
                    .collect()
            });
            let mut store = SdFileStore::new(card.clone());
            let listed = listing(&mut store);
            let names: Vec<&str> = listed.iter().map(|(n, _)| n.as_str()).collect();
            // Long names when they are names, short names otherwise; no metadata file, no
            // directory, no file inside one, no name outside ASCII.
            assert_eq!(names[0], "bracket_v2.gcode", "{format:?} {shorts:?}");
            assert_eq!(names[1], "CUBE.GCO");
            assert_eq!(names[2], "MYPART~1.GCO");
            assert!(!names.iter().any(|n| n.starts_with('.') || *n == "jobs"));
            assert!(
                !names
                    .iter()
                    .any(|n| n.contains("inner") || n.contains("INNER"))
            );
            assert_eq!(listed[0].1, 5000);
            // By either name, without regard to case.
            assert_eq!(contents(&mut store, "BRACKET_V2.GCODE").unwrap(), bracket);
            assert_eq!(contents(&mut store, "bracke~1.gco").unwrap(), bracket);
            assert_eq!(contents(&mut store, "cube.gco").unwrap(), b"G1 X1\n");
            assert_eq!(contents(&mut store, "MyPart~1.gco").unwrap(), b"G1 Y2\n");
            assert_eq!(store.size(&name("jobs")), Err(FileError::NotFound));
            assert_eq!(store.size(&name("inner.gco")), Err(FileError::NotFound));
            // A long name cannot be written; a directory's name is taken.
            assert_eq!(
                store.create(&name("bracket_v3.gcode")),
                Err(FileError::BadName)
            );
            assert_eq!(store.create(&name("JOBS")), Err(FileError::BadName));
            assert_eq!(store.writing(), None);
        }
    }

    /// The store as a power cut leaves its card, mounted again.
    fn restart(mut store: SdFileStore<Card>) -> SdFileStore<Card> {
        SdFileStore::new(store.device(|card| card.clone()))
    }

    /// The store, mounted again, and a PC list the same files, in the same order, with the
    /// same bytes, and nothing else: no temporary, no long-name entries without their file.
    fn assert_a_pc_sees_the_same(card: &Card) {
        let mut store = SdFileStore::new(card.clone());
        let listed = listing(&mut store);
        let bytes: Vec<Vec<u8>> = listed
            .iter()
            .map(|(n, _)| contents(&mut store, n).unwrap())
            .collect();
        store.unmount();
        assert_eq!(orphans(card), 0);
        let sizes = listed.iter().map(|(n, size)| (n.clone(), u64::from(*size)));
        assert_eq!(pc_listing(card), sizes.collect::<Vec<_>>());
        for ((n, _), bytes) in listed.iter().zip(&bytes) {
            assert_eq!(&pc_contents(card, n), bytes, "{n}");
        }
    }

    #[test]
    fn keeps_the_file_store_contract_and_a_pc_sees_what_it_wrote() {
        for format in [Format::Fat16, Format::Fat32] {
            // Each check's card is looked at by a PC once the check is over: when the next
            // card is made, and after the last.
            let mut last: Option<Card> = None;
            let mut make = || {
                let fresh = card(format);
                if let Some(done) = last.replace(fresh.clone()) {
                    assert_a_pc_sees_the_same(&done);
                }
                SdFileStore::new(fresh)
            };
            conformance::all(&mut make);
            conformance::all_restarting(&mut make, restart);
            assert_a_pc_sees_the_same(&last.unwrap());
        }
    }

    #[test]
    fn a_replaced_file_keeps_its_entry_and_a_new_one_takes_the_first_free_one() {
        for format in [Format::Fat16, Format::Fat32] {
            let card = card(format);
            let mut store = SdFileStore::new(card.clone());
            write(&mut store, "job.gco", b"G1 X1\nG1 X2\n");
            write(&mut store, "b.g", b"bee");
            store.create(&name("JOB.gco")).unwrap();
            store.append(&pattern(3000, 5)).unwrap();
            store.abandon().unwrap();
            // Finished, the new version replaces the old one in place, with the new spelling.
            write(&mut store, "JOB.gco", &pattern(3000, 5));
            assert_eq!(listing(&mut store), strs(&[("JOB.gco", 3000), ("b.g", 3)]));
            store.create(&name("b.g")).unwrap();
            store.append(b"new").unwrap();
            store.remove(&name("B.G")).unwrap();
            store.append(b" bee").unwrap();
            store.finish().unwrap();
            write(&mut store, "e.g", b"");
            write(&mut store, "e.g", b"full");
            write(&mut store, "e.g", b"");
            store.unmount();
            // The new `b.g` is where its temporary was; `e.g` took the entry the old `b.g` left.
            let order = [("JOB.gco", 3000), ("e.g", 0), ("b.g", 7)];
            assert_eq!(pc_listing(&card), order.map(|(n, s)| (n.to_string(), s)));
            assert_eq!(pc_contents(&card, "job.gco"), pattern(3000, 5));
            assert_eq!(pc_contents(&card, "b.g"), b"new bee");
        }
    }

    #[test]
    fn replacing_and_removing_free_every_cluster() {
        for format in [Format::Fat16, Format::Fat32] {
            let card = card(format);
            pc_write(&card, "bracket_v2.gcode", &pattern(40_000, 1));
            let free = free_clusters(&card);
            let mut store = SdFileStore::new(card.clone());
            for round in 0..3 {
                write(&mut store, "a.g", &pattern(70_000 + round * 1000, 2));
                write(&mut store, "b.g", &pattern(9000, 3));
                write(&mut store, "a.g", &pattern(30_000, 4));
                store.create(&name("c.g")).unwrap();
                store.append(&pattern(50_000, 5)).unwrap();
                store.abandon().unwrap();
                write(&mut store, "b.g", b"");
                store.remove(&name("a.g")).unwrap();
                store.remove(&name("b.g")).unwrap();
            }
            // A PC's file replaced under its short name keeps its long name.
            write(&mut store, "BRACKE~1.GCO", &pattern(100, 6));
            assert_eq!(listing(&mut store), strs(&[("bracket_v2.gcode", 100)]));
            write(&mut store, "bracke~1.gco", &pattern(40_000, 1));
            store.unmount();
            assert_eq!(free_clusters(&card), free, "{format:?}");
            assert_eq!(
                pc_listing(&card),
                [("bracket_v2.gcode".to_string(), 40_000)]
            );
            let mut store = SdFileStore::new(card.clone());
            store.remove(&name("bracket_v2.gcode")).unwrap();
            store.unmount();
            assert!(pc_listing(&card).is_empty(), "the long name goes too");
            let cluster = if matches!(format, Format::Fat16) {
                1024
            } else {
                512
            };
            assert_eq!(free_clusters(&card), free + 40_000_u32.div_ceil(cluster));
        }
    }

    #[test]
    fn a_pc_file_replaced_under_its_own_short_name_takes_the_new_spelling() {
        let card = card(Format::Fat16);
        pc_write(&card, "Bracket.gco", b"old");
        let mut store = SdFileStore::new(card.clone());
        assert_eq!(listing(&mut store), strs(&[("Bracket.gco", 3)]));
        write(&mut store, "bracket.gco", b"new!");
        assert_eq!(listing(&mut store), strs(&[("bracket.gco", 4)]));
        store.unmount();
        assert_eq!(pc_listing(&card), [("bracket.gco".to_string(), 4)]);
        assert_eq!(pc_contents(&card, "BRACKET.GCO"), b"new!");
    }

    #[test]
    fn reads_go_on_from_the_last_one_across_clusters_through_a_multi_megabyte_file() {
        for format in [Format::Fat16, Format::Fat32] {
            let card = card(format);
            let job = pattern(3 << 20, 9);
            pc_write(&card, "big.gco", &job);
            pc_write(&card, "other.gco", b"other");
            let mut store = SdFileStore::new(card.clone());
            assert_eq!(store.size(&name("big.gco")), Ok(3 << 20));
            // A job's reads: 256 bytes at a time from the start. They cost about one block
            // read per block of the file, and one FAT read per cluster, never a walk from the
            // start of the file.
            let before = card.reads.get();
            let mut buf = [0u8; 256];
            let mut at = 0usize;
            while at < job.len() {
                let n = store.read(&name("big.gco"), at as u32, &mut buf).unwrap();
                assert_eq!(&buf[..n], &job[at..at + n], "{format:?} at {at}");
                at += n;
            }
            let blocks = job.len() / BLOCK;
            let reads = card.reads.get() - before;
            assert!(
                reads <= 2 * blocks + 64,
                "{format:?}: {reads} reads for {blocks} blocks"
            );
            // Across cluster boundaries, backwards, at the end, and for another file between.
            let cluster = if matches!(format, Format::Fat16) {
                1024
            } else {
                512
            };
            for offset in [
                cluster - 1,
                7 * cluster - 3,
                5,
                40 * cluster + 511,
                job.len() - 2,
            ] {
                let mut two = [0u8; 4];
                let n = store
                    .read(&name("big.gco"), offset as u32, &mut two)
                    .unwrap();
                assert_eq!(&two[..n], &job[offset..(offset + 4).min(job.len())]);
                assert_eq!(contents(&mut store, "other.gco").unwrap(), b"other");
            }
            let mut big = vec![0u8; 100_000];
            let n = store.read(&name("big.gco"), 1_000_001, &mut big).unwrap();
            assert_eq!(n, 100_000);
            assert_eq!(&big[..], &job[1_000_001..1_100_001]);
            // Replaced while it is read: the next read is of the new file.
            write(&mut store, "big.gco", b"short now");
            assert_eq!(store.read(&name("big.gco"), 6, &mut buf), Ok(3));
            assert_eq!(&buf[..3], b"now");
        }
    }

    #[test]
    fn a_multi_megabyte_upload_reads_back_on_a_pc() {
        let card = card(Format::Fat32);
        let mut store = SdFileStore::new(card.clone());
        let job = pattern(5 << 20, 11);
        store.create(&name("upload.gco")).unwrap();
        for chunk in job.chunks(1500) {
            store.append(chunk).unwrap();
        }
        store.finish().unwrap();
        assert_eq!(store.size(&name("UPLOAD.GCO")), Ok(5 << 20));
        store.unmount();
        assert_eq!(pc_contents(&card, "upload.gco"), job);
    }

    #[test]
    fn a_failing_card_is_a_device_error_and_the_store_goes_on_when_it_answers_again() {
        let card = card(Format::Fat16);
        let mut store = SdFileStore::new(card.clone());
        card.failing.set(true);
        assert_eq!(store.mount(), Err(MountError::Device));
        assert_eq!(store.file(0), Err(FileError::Device));
        assert_eq!(store.create(&name("a.g")), Err(FileError::Device));
        assert_eq!(store.writing(), None);
        card.failing.set(false);
        write(&mut store, "a.g", b"kept");
        store.create(&name("b.g")).unwrap();
        store.append(b"first ").unwrap();
        card.failing.set(true);
        for result in [
            store.file(0).map(|_| ()),
            store.size(&name("a.g")).map(|_| ()),
            store.read(&name("a.g"), 0, &mut [0; 4]).map(|_| ()),
            store.remove(&name("a.g")),
            store.append(b"lost"),
            store.finish(),
        ] {
            assert_eq!(result, Err(FileError::Device));
        }
        assert_eq!(store.writing(), Some(name("b.g")));
        card.failing.set(false);
        // Nothing changed: the write goes on where it was, the other file is whole.
        store.append(b"second").unwrap();
        store.finish().unwrap();
        assert_eq!(contents(&mut store, "b.g").unwrap(), b"first second");
        assert_eq!(contents(&mut store, "a.g").unwrap(), b"kept");
        // Only writes fail: the same.
        store.create(&name("c.g")).unwrap();
        store.append(&pattern(5000, 1)).unwrap();
        card.writes_left.set(Some(0));
        assert_eq!(store.append(&pattern(5000, 2)), Err(FileError::Device));
        assert_eq!(store.finish(), Err(FileError::Device));
        assert_eq!(store.remove(&name("a.g")), Err(FileError::Device));
        card.writes_left.set(None);
        store.append(b"end").unwrap();
        store.finish().unwrap();
        let mut want = pattern(5000, 1);
        want.extend_from_slice(b"end");
        assert_eq!(contents(&mut store, "c.g").unwrap(), want);
        // A finish that fails after many appends: the write is as it was.
        store.create(&name("e.g")).unwrap();
        let long = pattern(20_000, 8);
        for chunk in long.chunks(1000) {
            store.append(chunk).unwrap();
        }
        card.writes_left.set(Some(0));
        assert_eq!(store.finish(), Err(FileError::Device));
        card.writes_left.set(Some(1));
        assert_eq!(store.finish(), Err(FileError::Device));
        card.writes_left.set(None);
        store.append(b"!").unwrap();
        store.finish().unwrap();
        let mut want = long.clone();
        want.push(b'!');
        assert_eq!(contents(&mut store, "e.g").unwrap(), want);
        store.remove(&name("e.g")).unwrap();
        // An abandon that fails is finished at the next create.
        store.create(&name("d.g")).unwrap();
        store.append(b"dropped").unwrap();
        card.failing.set(true);
        assert_eq!(store.abandon(), Err(FileError::Device));
        assert_eq!(store.writing(), None);
        card.failing.set(false);
        write(&mut store, "d.g", b"d");
        store.unmount();
        assert_eq!(
            pc_listing(&card),
            [("a.g", 4), ("b.g", 12), ("c.g", 5003), ("d.g", 1)].map(|(n, s)| (n.to_string(), s))
        );
    }

    #[test]
    fn bad_names_are_refused_before_anything_is_written() {
        let card = card(Format::Fat16);
        pc(&card, |fs| {
            fs.root_dir().create_dir("JOBS").unwrap();
        });
        let mut store = SdFileStore::new(card.clone());
        store.mount().unwrap();
        let writes = card.writes.get();
        for bad in ["long_name.gcode", "a.b.c", "CON.gco", "~FORJA.NEW", "jobs"] {
            assert_eq!(store.create(&name(bad)), Err(FileError::BadName), "{bad}");
            assert_eq!(store.writing(), None);
        }
        assert_eq!(card.writes.get(), writes);
        assert_eq!(store.remove(&name("~FORJA.NEW")), Err(FileError::NotFound));
    }

    #[test]
    fn a_full_card_is_full_and_the_write_is_kept_as_it_was() {
        let card = card(Format::Small);
        let free = free_clusters(&card);
        let mut store = SdFileStore::new(card.clone());
        store.create(&name("huge.g")).unwrap();
        let chunk = pattern(7000, 3);
        let mut stored = Vec::new();
        let error = loop {
            match store.append(&chunk) {
                Ok(()) => stored.extend_from_slice(&chunk),
                Err(e) => break e,
            }
        };
        assert_eq!(error, FileError::Full);
        assert!(stored.len() > 2_000_000, "{}", stored.len());
        assert_eq!(store.append(&chunk), Err(FileError::Full));
        // What was appended before is kept, and more fits when it fits.
        store.append(b"tail").unwrap();
        stored.extend_from_slice(b"tail");
        store.finish().unwrap();
        assert_eq!(contents(&mut store, "huge.g").unwrap(), stored);
        store.create(&name("more.g")).unwrap();
        assert_eq!(store.append(&chunk), Err(FileError::Full));
        store.abandon().unwrap();
        store.unmount();
        assert_eq!(pc_contents(&card, "huge.g"), stored);
        let cluster = 512;
        assert_eq!(
            free_clusters(&card),
            free - (stored.len() as u32).div_ceil(cluster),
            "the clusters of the failed appends are free again"
        );
        let mut store = SdFileStore::new(card.clone());
        store.remove(&name("huge.g")).unwrap();
        store.unmount();
        assert_eq!(free_clusters(&card), free);
    }

    #[test]
    fn a_full_root_directory_is_full_and_files_can_still_be_replaced() {
        let card = card(Format::Small);
        let mut store = SdFileStore::new(card.clone());
        // 16 entries: 15 files and the temporary of a write.
        for i in 0..15 {
            write(&mut store, &format!("f{i}.g"), &pattern(1500, i));
        }
        store.unmount();
        let free = free_clusters(&card);
        // No room for the entry that holds the old clusters: they are freed after the commit.
        let mut store = SdFileStore::new(card.clone());
        write(&mut store, "f0.g", b"replaced");
        store.create(&name("g.g")).unwrap();
        store.abandon().unwrap();
        store.remove(&name("f2.g")).unwrap();
        write(&mut store, "f2.g", &pattern(600, 2));
        store.unmount();
        assert_eq!(free_clusters(&card), free + 3 - 1 + 3 - 2);
        // The temporary takes the last entry and becomes the 16th file; then there is no room.
        let mut store = SdFileStore::new(card.clone());
        write(&mut store, "g.g", b"16th");
        assert_eq!(store.create(&name("h.g")), Err(FileError::Full));
        assert_eq!(store.writing(), None);
        store.remove(&name("g.g")).unwrap();
        store.create(&name("h.g")).unwrap();
        store.abandon().unwrap();
        store.unmount();
        assert_eq!(pc_contents(&card, "f0.g"), b"replaced");
        assert_eq!(pc_contents(&card, "f2.g"), pattern(600, 2));
        assert_eq!(pc_contents(&card, "f3.g"), pattern(1500, 3));
        assert_eq!(pc_listing(&card).len(), 15);
        assert_eq!(free_clusters(&card), free + 3 - 1 + 3 - 2);
    }

    #[test]
    fn a_full_fat32_root_directory_grows_by_a_cluster() {
        // 512-byte clusters: 16 entries a cluster, and the formatted root has one cluster.
        let card = card(Format::Fat32);
        let free = free_clusters(&card);
        let mut store = SdFileStore::new(card.clone());
        let files: Vec<(String, Vec<u8>)> = (0..40)
            .map(|i| (format!("f{i}.g"), pattern(100 + 37 * i, i as u32)))
            .collect();
        for (n, bytes) in &files {
            write(&mut store, n, bytes);
        }
        let listed = listing(&mut store);
        assert_eq!(listed.len(), 40);
        for (n, bytes) in &files {
            assert_eq!(&contents(&mut store, n).unwrap(), bytes);
        }
        store.unmount();
        assert_eq!(pc_listing(&card).len(), 40);
        for (n, bytes) in &files {
            assert_eq!(&pc_contents(&card, n), bytes, "{n}");
        }
        // The files' clusters, and two more clusters of directory.
        let data: u32 = files
            .iter()
            .map(|(_, b)| b.len().div_ceil(512) as u32)
            .sum();
        assert_eq!(free_clusters(&card), free - data - 2);
        pc_write(&card, "pc.g", b"from a PC");
        let mut store = SdFileStore::new(card.clone());
        assert_eq!(contents(&mut store, "pc.g").unwrap(), b"from a PC");
    }

    /// Runs of long-name entries in the root directory that belong to no file.
    fn orphans(card: &Card) -> usize {
        let g = Geometry::read(card).unwrap();
        let mut runs = 0;
        scan_root(
            card,
            &g,
            g.root(),
            false,
            &mut |_| ControlFlow::Continue(()),
            &mut |_, _| runs += 1,
        )
        .unwrap();
        runs
    }

    /// The finished file `name` and the temporaries, as the store and a PC see the card after
    /// it is mounted again.
    fn after_restart(card: &Card, n: &str) -> Option<Vec<u8>> {
        let mut store = SdFileStore::new(card.clone());
        store.mount().unwrap();
        let seen = contents(&mut store, n).ok();
        store.unmount();
        assert_eq!(orphans(card), 0);
        let listed = pc_listing(card);
        assert!(
            !listed.iter().any(|(n, _)| n.starts_with("~FORJA")),
            "{listed:?}"
        );
        match &seen {
            Some(bytes) => assert_eq!(&pc_contents(card, n), bytes),
            None => assert!(!listed.iter().any(|(l, _)| l.eq_ignore_ascii_case(n))),
        }
        seen
    }

    #[test]
    fn a_power_cut_at_any_write_of_finish_or_remove_leaves_the_old_file_or_the_new_one() {
        for format in [Format::Fat16, Format::Fat32] {
            let base = card(format);
            pc_write(&base, "Job.gco", &pattern(9000, 1));
            pc_write(&base, "other.g", b"other");
            let old = pattern(9000, 1);
            let new = pattern(14_000, 2);
            let cluster = if matches!(format, Format::Fat16) {
                1024
            } else {
                512
            };
            let free_old = free_clusters(&base);
            let free_new = free_old + 9000_u32.div_ceil(cluster) - 14_000_u32.div_ceil(cluster);
            let mut outcomes = (0, 0);
            for cut in 0.. {
                let card = base.copy();
                let mut store = SdFileStore::new(card.clone());
                store.create(&name("job.gco")).unwrap();
                store.append(&new).unwrap();
                card.writes_left.set(Some(cut));
                let finished = store.finish().is_ok();
                card.writes_left.set(None);
                std::mem::forget(store);
                let seen = after_restart(&card, "job.gco").unwrap();
                if seen == old {
                    outcomes.0 += 1;
                    assert_eq!(free_clusters(&card), free_old, "{format:?} cut {cut}");
                } else {
                    assert_eq!(seen, new, "{format:?} cut {cut}");
                    outcomes.1 += 1;
                    assert_eq!(free_clusters(&card), free_new, "{format:?} cut {cut}");
                }
                assert_eq!(pc_contents(&card, "other.g"), b"other");
                if finished {
                    assert_eq!(seen, new);
                    break;
                }
            }
            assert!(outcomes.0 > 0 && outcomes.1 > 0, "{outcomes:?}");
            // Removing.
            let free_none = free_old + 9000_u32.div_ceil(cluster);
            for cut in 0.. {
                let card = base.copy();
                let mut store = SdFileStore::new(card.clone());
                store.mount().unwrap();
                card.writes_left.set(Some(cut));
                let removed = store.remove(&name("JOB.GCO")).is_ok();
                card.writes_left.set(None);
                std::mem::forget(store);
                match after_restart(&card, "job.gco") {
                    Some(seen) => {
                        assert_eq!(seen, old, "{format:?} cut {cut}");
                        assert!(!removed);
                        assert_eq!(free_clusters(&card), free_old);
                    }
                    None => {
                        assert_eq!(free_clusters(&card), free_none, "{format:?} cut {cut}");
                    }
                }
                if removed {
                    break;
                }
            }
        }
    }

    #[test]
    fn a_power_cut_during_an_upload_leaves_the_old_file_and_at_most_one_lost_cluster() {
        let base = card(Format::Fat16);
        pc_write(&base, "job.gco", b"old");
        let free = free_clusters(&base);
        let new = pattern(5000, 3);
        for cut in 0.. {
            let card = base.copy();
            let mut store = SdFileStore::new(card.clone());
            store.mount().unwrap();
            card.writes_left.set(Some(cut));
            let done = (|| {
                store.create(&name("job.gco"))?;
                for chunk in new.chunks(700) {
                    store.append(chunk)?;
                }
                store.finish()
            })()
            .is_ok();
            card.writes_left.set(None);
            std::mem::forget(store);
            let seen = after_restart(&card, "job.gco").unwrap();
            let lost = if seen == b"old" {
                free - free_clusters(&card)
            } else {
                assert_eq!(seen, new, "cut {cut}");
                (free + 1 - 5).saturating_sub(free_clusters(&card))
            };
            assert!(lost <= 1, "cut {cut}: {lost} clusters lost");
            if done {
                assert_eq!(seen, new);
                break;
            }
        }
    }

    #[test]
    fn cards_that_are_not_fat16_or_fat32_are_refused() {
        let blank = Card::with_image(vec![0; 4 << 20]);
        let mut store = SdFileStore::new(blank.clone());
        assert_eq!(store.mount(), Err(MountError::NotFat));
        assert_eq!(store.file(0), Err(FileError::Device));
        assert!(!store.is_mounted());
        let exfat = card(Format::Fat16);
        exfat.image.borrow_mut()[450] = 0x07;
        assert_eq!(SdFileStore::new(exfat).mount(), Err(MountError::NotFat));
        let garbled = card(Format::Fat16);
        garbled.image.borrow_mut()[PART * BLOCK + 13] = 0;
        assert_eq!(SdFileStore::new(garbled).mount(), Err(MountError::NotFat));
        assert_eq!(MountError::Device.kind(), ErrorKind::Hardware);
        let fine = card(Format::Fat32);
        let mut store = SdFileStore::new(fine);
        store.mount().unwrap();
        assert!(store.is_mounted());
    }

    #[test]
    fn a_card_taken_out_and_put_back_is_mounted_again() {
        let card = card(Format::Fat16);
        let mut store = SdFileStore::new(card.clone());
        write(&mut store, "a.g", b"a");
        store.create(&name("b.g")).unwrap();
        store.append(b"half").unwrap();
        card.failing.set(true);
        store.unmount();
        assert_eq!(store.writing(), None);
        card.failing.set(false);
        // Meanwhile a PC adds a file.
        pc_write(&card, "pc.g", b"from the pc");
        assert_eq!(
            listing(&mut store),
            strs(&[("a.g", 1), ("pc.g", 11)]),
            "the abandoned temporary is cleaned up"
        );
        assert_eq!(store.device(|c| c.image.borrow().len()), 8 << 20);
    }

    #[test]
    fn listing_in_order_goes_on_from_the_file_last_listed() {
        let card = card(Format::Fat32);
        let mut store = SdFileStore::new(card.clone());
        for i in 0..40 {
            write(&mut store, &format!("f{i}.g"), &[b'x'; 3]);
        }
        store.remove(&name("f7.g")).unwrap();
        let all = listing(&mut store);
        assert_eq!(all.len(), 39);
        // One block read per file (the block of the entry after the last one listed), and
        // the FAT for each of the directory's clusters: never from the start again.
        let before = card.reads.get();
        assert_eq!(listing(&mut store), all);
        let reads = card.reads.get() - before;
        assert!(reads <= all.len() + 1 + 2 * 4, "{reads}");
        // Out of order, the same answers.
        for i in [20, 3, 38, 0, 39] {
            let got = store.file(i).unwrap().map(|f| f.name.as_str().to_string());
            assert_eq!(got, all.get(i).map(|(n, _)| n.clone()));
        }
    }

    #[test]
    fn long_name_entries_left_without_their_file_are_removed_at_mount() {
        let card = card(Format::Fat32);
        pc_write(&card, "first_long_name.gcode", b"1");
        pc_write(&card, "second_long_name.gcode", b"2");
        pc_write(&card, "third_long_name.gcode", b"3");
        // Another implementation (embedded-sdmmc's delete) removes the second file's short
        // entry only.
        let g = Geometry::read(&card).unwrap();
        let mut second = None;
        entries(&card, &g, g.root(), false, &mut |e| {
            if e.long.and_then(|run| run.name()) == Some(name("second_long_name.gcode")) {
                second = Some(e.pos);
            }
            ControlFlow::Continue(())
        })
        .unwrap();
        delete_slots(&card, &g, second.unwrap(), 1).unwrap();
        assert_eq!(orphans(&card), 1);
        let mut store = SdFileStore::new(card.clone());
        assert_eq!(
            listing(&mut store),
            strs(&[("first_long_name.gcode", 1), ("third_long_name.gcode", 1)])
        );
        store.unmount();
        assert_eq!(orphans(&card), 0);
        assert_eq!(
            pc_listing(&card),
            [("first_long_name.gcode", 1), ("third_long_name.gcode", 1)]
                .map(|(n, s)| (n.to_string(), s))
        );
    }
}
