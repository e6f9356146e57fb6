//! The simulated NOR flash, and the file it can be kept in.
//!
//! [`SimFlash`] is `forja_drivers::ram_flash::RamNorFlash` (the one model of a NOR flash in
//! RAM, which the storage layer is tested on) with its bytes on the heap, in words of [`WORD`]
//! bytes and erase pages of [`PAGE`] bytes: an erase sets whole pages to `0xFF`, a write may
//! only clear bits of erased words, every access is aligned and within the device.
//!
//! # Kept in a file
//!
//! Given a window of a file ([`FlashFile`]), every completed erase or write is written to the
//! file (one positioned write of exactly the bytes it changed, no buffer in between) before it
//! returns: the file is the flash after the last completed operation. A board lays its flashes
//! out in one file and reopens them after a restart, as a board's flash survives a power cycle.
//!
//! A process killed in the middle of an operation (SIGKILL, a crash) leaves the file as a flash
//! is left by a power cut in the middle of one. The operation is one `pwrite` of its bytes in
//! ascending order, which Linux stops, if at all, only between the 4 KiB pages of the file
//! cache it copies; a flash that starts at a page boundary of the file never has a word
//! straddle two of them. The file then holds a prefix of the operation, in whole words, and the
//! old contents after it: some words written and the rest still erased, or some pages of an
//! erase done and the rest as before. Bits are only ever cleared by a write and set by an
//! erase, so nothing a real part could not hold is ever there. (A real part may also leave a
//! word half-programmed, some of its bits cleared; `RamNorFlash::cut_power_after` models that
//! finer case for the storage layer's own tests.) A kill between operations leaves the file at
//! that boundary exactly.
//!
//! The limit: the file is written, not synced (`fsync`). A kill of the process leaves the
//! written data in the operating system's cache, which the next process reads; a power cut of
//! the computer itself may lose operations the file system had not yet stored.
//!
//! A write to the file that fails (a full disk) makes the flash fail every later operation with
//! [`RamFlashError::MediumFailed`], as a flash that lost its power does: the storage layer
//! reports a flash error instead of carrying on with a file that no longer follows the flash.

use core::fmt;
use std::fs::File;
use std::os::unix::fs::FileExt as _;
use std::sync::Arc;

use embedded_storage::nor_flash::{ErrorType, NorFlash, ReadNorFlash};
use forja_drivers::ram_flash::{FlashMemory, RamFlashError, RamNorFlash};
use nix::fcntl::Flock;

/// Read and write unit of a [`SimFlash`], bytes.
pub const WORD: usize = 4;

/// Erase page of a [`SimFlash`], bytes.
pub const PAGE: usize = 4096;

/// A flash's bytes on the heap: a megabyte does not belong on a stack.
struct Heap<const SIZE: usize>(Box<[u8; SIZE]>);

impl<const SIZE: usize> FlashMemory<SIZE> for Heap<SIZE> {
    fn bytes(&self) -> &[u8; SIZE] {
        &self.0
    }

    fn bytes_mut(&mut self) -> &mut [u8; SIZE] {
        &mut self.0
    }
}

/// One flash's window of a file: where its completed operations are written.
#[derive(Debug)]
pub struct FlashFile {
    file: Arc<Flock<File>>,
    /// Offset of the flash's byte 0 in the file.
    base: u64,
    /// A write to the file failed: the file no longer follows the flash.
    failed: bool,
}

impl FlashFile {
    /// The window of `file` (locked by its owner) from byte `base` on.
    pub fn new(file: Arc<Flock<File>>, base: u64) -> Self {
        Self {
            file,
            base,
            failed: false,
        }
    }

    /// Whether the flash may be used: [`RamFlashError::MediumFailed`] once a write to the file
    /// failed.
    pub fn usable(&self) -> Result<(), RamFlashError> {
        if self.failed {
            Err(RamFlashError::MediumFailed)
        } else {
            Ok(())
        }
    }

    /// Write `bytes`, the flash's contents from byte `offset` after an operation, to the file
    /// (one positioned write, retried only for what a short write left).
    pub fn write(&mut self, offset: usize, bytes: &[u8]) -> Result<(), RamFlashError> {
        self.usable()?;
        let at = self.base + offset as u64;
        if self.file.write_all_at(bytes, at).is_err() {
            self.failed = true;
            return Err(RamFlashError::MediumFailed);
        }
        Ok(())
    }
}

/// `SIZE` bytes of simulated NOR flash (see the [module documentation](self)).
pub struct SimFlash<const SIZE: usize> {
    flash: RamNorFlash<SIZE, WORD, PAGE, Heap<SIZE>>,
    file: Option<FlashFile>,
}

impl<const SIZE: usize> SimFlash<SIZE> {
    /// A fully erased flash, in memory only.
    pub fn erased() -> Self {
        Self::with_contents(Vec::new(), None)
    }

    /// A flash holding `bytes` (cut or padded with erased bytes to `SIZE`), each completed
    /// operation written through to `file` when there is one.
    pub fn with_contents(mut bytes: Vec<u8>, file: Option<FlashFile>) -> Self {
        bytes.resize(SIZE, 0xFF);
        let boxed: Box<[u8; SIZE]> = bytes
            .into_boxed_slice()
            .try_into()
            .unwrap_or_else(|_| unreachable!("resized to SIZE"));
        Self {
            flash: RamNorFlash::with_memory(Heap(boxed)),
            file,
        }
    }

    /// The raw contents.
    pub fn as_bytes(&self) -> &[u8; SIZE] {
        self.flash.as_bytes()
    }

    fn usable(&self) -> Result<(), RamFlashError> {
        self.file.as_ref().map_or(Ok(()), FlashFile::usable)
    }

    /// Write the bytes `start..start + len` of a completed operation through to the file.
    fn write_through(&mut self, start: usize, len: usize) -> Result<(), RamFlashError> {
        let Some(file) = &mut self.file else {
            return Ok(());
        };
        let bytes = self
            .flash
            .as_bytes()
            .get(start..start + len)
            .ok_or(RamFlashError::OutOfBounds)?;
        file.write(start, bytes)
    }
}

impl<const SIZE: usize> fmt::Debug for SimFlash<SIZE> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimFlash")
            .field("size", &SIZE)
            .field("file", &self.file.is_some())
            .finish()
    }
}

impl<const SIZE: usize> ErrorType for SimFlash<SIZE> {
    type Error = RamFlashError;
}

impl<const SIZE: usize> ReadNorFlash for SimFlash<SIZE> {
    const READ_SIZE: usize = WORD;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.usable()?;
        self.flash.read(offset, bytes)
    }

    fn capacity(&self) -> usize {
        SIZE
    }
}

impl<const SIZE: usize> NorFlash for SimFlash<SIZE> {
    const WRITE_SIZE: usize = WORD;
    const ERASE_SIZE: usize = PAGE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        self.usable()?;
        self.flash.erase(from, to)?;
        self.write_through(from as usize, to.saturating_sub(from) as usize)
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.usable()?;
        self.flash.write(offset, bytes)?;
        self.write_through(offset as usize, bytes.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn it_keeps_the_nor_rules() {
        let mut f = SimFlash::<{ 4 * PAGE }>::erased();
        assert_eq!(f.capacity(), 4 * PAGE);
        assert_eq!(f.write(2, &[0; 4]), Err(RamFlashError::NotAligned));
        f.write(4, &[1, 2, 3, 4]).unwrap();
        assert_eq!(
            f.write(4, &[1, 2, 3, 4]),
            Err(RamFlashError::WordWrittenTwice)
        );
        let mut b = [0; 4];
        f.read(4, &mut b).unwrap();
        assert_eq!(b, [1, 2, 3, 4]);
        f.erase(0, PAGE as u32).unwrap();
        f.read(4, &mut b).unwrap();
        assert_eq!(b, [0xFF; 4]);
        assert_eq!(f.erase(0, 5 * PAGE as u32), Err(RamFlashError::OutOfBounds));
    }

    #[test]
    fn contents_are_cut_or_padded_to_the_size() {
        let f = SimFlash::<8>::with_contents(vec![0, 1, 2], None);
        assert_eq!(f.as_bytes(), &[0, 1, 2, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF]);
        let f = SimFlash::<4>::with_contents(vec![7; 9], None);
        assert_eq!(f.as_bytes(), &[7; 4]);
    }
}
