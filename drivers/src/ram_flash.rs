//! A NOR flash in RAM that enforces NOR rules and can lose power on cue.
//!
//! [`RamNorFlash`] implements `embedded-storage`'s `NorFlash` the way a real part behaves, and
//! is strict where a real part is forgiving, so that a storage layer tested on it does not rely
//! on luck:
//! - erase sets whole pages to `0xFF`; a write can only clear bits;
//! - reads, writes and erases must be aligned to their sizes and within the device;
//! - a word may be written once per erase (the `NorFlash` contract; a second write is an
//!   error here, where real parts would silently AND the data);
//! - [`RamNorFlash::cut_power_after`] makes the device stop after a number of units of work
//!   (one unit per byte programmed, one per page erased). The interrupted byte is torn (only
//!   some of its bits programmed), an interrupted erase leaves the page half erased, and every
//!   later operation fails until [`RamNorFlash::restore_power`].
//!
//! It is `no_std` and allocation-free. Its bytes are its own array by default, or memory it is
//! lent ([`FlashMemory`]): a `&'static mut` array (the STM32 board's QEMU build keeps its store
//! in a RAM region so), or a board's own buffer (the host simulator's, on the heap). One model
//! serves the tests of the storage layer and every board that keeps a flash in RAM.

use core::fmt;

use embedded_storage::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};

/// An error of [`RamNorFlash`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum RamFlashError {
    /// Offset or length not a multiple of the read, write or erase size.
    NotAligned,
    /// Beyond the end of the device.
    OutOfBounds,
    /// The power was cut (see [`RamNorFlash::cut_power_after`]).
    PowerLost,
    /// A word was written twice without an erase in between.
    WordWrittenTwice,
    /// The medium that keeps a board's flash failed (the host simulator's state file could
    /// not be written); the flash refuses every later operation, as after a power cut.
    MediumFailed,
}

impl fmt::Display for RamFlashError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::NotAligned => "flash access not aligned",
            Self::OutOfBounds => "flash access out of bounds",
            Self::PowerLost => "flash lost power",
            Self::WordWrittenTwice => "flash word written twice without erase",
            Self::MediumFailed => "flash medium failed",
        })
    }
}

impl NorFlashError for RamFlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            Self::NotAligned => NorFlashErrorKind::NotAligned,
            Self::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            Self::PowerLost | Self::WordWrittenTwice | Self::MediumFailed => {
                NorFlashErrorKind::Other
            }
        }
    }
}

/// The memory a [`RamNorFlash`] keeps its `SIZE` bytes in: its own array, or memory it is lent
/// for its life.
pub trait FlashMemory<const SIZE: usize> {
    /// The bytes.
    fn bytes(&self) -> &[u8; SIZE];
    /// The bytes, to change.
    fn bytes_mut(&mut self) -> &mut [u8; SIZE];
}

impl<const SIZE: usize> FlashMemory<SIZE> for [u8; SIZE] {
    fn bytes(&self) -> &[u8; SIZE] {
        self
    }

    fn bytes_mut(&mut self) -> &mut [u8; SIZE] {
        self
    }
}

impl<const SIZE: usize> FlashMemory<SIZE> for &mut [u8; SIZE] {
    fn bytes(&self) -> &[u8; SIZE] {
        self
    }

    fn bytes_mut(&mut self) -> &mut [u8; SIZE] {
        self
    }
}

/// `SIZE` bytes of NOR flash in pages of `PAGE` bytes, read and written in words of `WORD`
/// bytes, kept in `M` (by default its own array). `SIZE` must be a multiple of `PAGE`, and
/// `PAGE` of `WORD`.
#[derive(Clone)]
pub struct RamNorFlash<
    const SIZE: usize,
    const WORD: usize = 4,
    const PAGE: usize = 4096,
    M = [u8; SIZE],
> {
    mem: M,
    /// Units of work left before the power goes; `None`: no cut planned.
    budget: Option<usize>,
    powered: bool,
    work_done: usize,
    pages_erased: usize,
    reads: usize,
    bytes_read: usize,
}

impl<const SIZE: usize, const WORD: usize, const PAGE: usize, M> fmt::Debug
    for RamNorFlash<SIZE, WORD, PAGE, M>
{
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RamNorFlash")
            .field("size", &SIZE)
            .field("word", &WORD)
            .field("page", &PAGE)
            .field("powered", &self.powered)
            .field("work_done", &self.work_done)
            .finish_non_exhaustive()
    }
}

impl<const SIZE: usize, const WORD: usize, const PAGE: usize> Default
    for RamNorFlash<SIZE, WORD, PAGE>
{
    fn default() -> Self {
        Self::new()
    }
}

impl<const SIZE: usize, const WORD: usize, const PAGE: usize> RamNorFlash<SIZE, WORD, PAGE> {
    /// A fully erased device in its own array.
    pub const fn new() -> Self {
        Self::with_memory([0xFF; SIZE])
    }
}

impl<const SIZE: usize, const WORD: usize, const PAGE: usize, M: FlashMemory<SIZE>>
    RamNorFlash<SIZE, WORD, PAGE, M>
{
    /// A device over `mem`, holding what `mem` holds (erased where it is `0xFF`): a flash
    /// that kept its contents.
    pub const fn with_memory(mem: M) -> Self {
        Self {
            mem,
            budget: None,
            powered: true,
            work_done: 0,
            pages_erased: 0,
            reads: 0,
            bytes_read: 0,
        }
    }

    /// The memory back, as the device left it.
    pub fn into_memory(self) -> M {
        self.mem
    }

    /// Let the next `units` units of work complete (one per byte programmed, one per page
    /// erased), then lose power in the middle of the following one.
    pub fn cut_power_after(&mut self, units: usize) {
        self.budget = Some(units);
    }

    /// Power up again after a cut; the contents stay as the cut left them.
    pub fn restore_power(&mut self) {
        self.budget = None;
        self.powered = true;
    }

    /// Whether the device has power.
    pub fn is_powered(&self) -> bool {
        self.powered
    }

    /// Units of work completed since creation (to size a power-cut sweep).
    pub fn work_done(&self) -> usize {
        self.work_done
    }

    /// Pages fully erased since creation.
    pub fn pages_erased(&self) -> usize {
        self.pages_erased
    }

    /// Successful `read` calls since creation (to count the reads a storage layer makes).
    pub fn reads(&self) -> usize {
        self.reads
    }

    /// Bytes returned by successful `read` calls since creation.
    pub fn bytes_read(&self) -> usize {
        self.bytes_read
    }

    /// The raw contents.
    pub fn as_bytes(&self) -> &[u8; SIZE] {
        self.mem.bytes()
    }

    /// Take one unit of work from the budget; `false` when the power goes now.
    fn spend(&mut self) -> bool {
        match self.budget {
            Some(0) => {
                self.powered = false;
                false
            }
            Some(n) => {
                self.budget = Some(n - 1);
                self.work_done += 1;
                true
            }
            None => {
                self.work_done += 1;
                true
            }
        }
    }

    fn check(&self, offset: u32, len: usize, align: usize) -> Result<usize, RamFlashError> {
        if !self.powered {
            return Err(RamFlashError::PowerLost);
        }
        let start = offset as usize;
        if align == 0 || !start.is_multiple_of(align) || !len.is_multiple_of(align) {
            return Err(RamFlashError::NotAligned);
        }
        match start.checked_add(len) {
            Some(end) if end <= SIZE => Ok(start),
            _ => Err(RamFlashError::OutOfBounds),
        }
    }
}

impl<const SIZE: usize, const WORD: usize, const PAGE: usize, M: FlashMemory<SIZE>> ErrorType
    for RamNorFlash<SIZE, WORD, PAGE, M>
{
    type Error = RamFlashError;
}

impl<const SIZE: usize, const WORD: usize, const PAGE: usize, M: FlashMemory<SIZE>> ReadNorFlash
    for RamNorFlash<SIZE, WORD, PAGE, M>
{
    const READ_SIZE: usize = WORD;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        let start = self.check(offset, bytes.len(), WORD)?;
        let src = self
            .mem
            .bytes()
            .get(start..start + bytes.len())
            .ok_or(RamFlashError::OutOfBounds)?;
        bytes.copy_from_slice(src);
        self.reads += 1;
        self.bytes_read += bytes.len();
        Ok(())
    }

    fn capacity(&self) -> usize {
        SIZE
    }
}

impl<const SIZE: usize, const WORD: usize, const PAGE: usize, M: FlashMemory<SIZE>> NorFlash
    for RamNorFlash<SIZE, WORD, PAGE, M>
{
    const WRITE_SIZE: usize = WORD;
    const ERASE_SIZE: usize = PAGE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        let len = (to as usize)
            .checked_sub(from as usize)
            .ok_or(RamFlashError::OutOfBounds)?;
        let start = self.check(from, len, PAGE)?;
        for page in (start..start + len).step_by(PAGE.max(1)) {
            let powered = self.spend();
            let bytes = self
                .mem
                .bytes_mut()
                .get_mut(page..page + PAGE)
                .ok_or(RamFlashError::OutOfBounds)?;
            if !powered {
                // Interrupted: the first half of the page is erased, the rest is not.
                bytes.iter_mut().take(PAGE / 2).for_each(|b| *b = 0xFF);
                return Err(RamFlashError::PowerLost);
            }
            bytes.fill(0xFF);
            self.pages_erased += 1;
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let start = self.check(offset, bytes.len(), WORD)?;
        let target = self
            .mem
            .bytes()
            .get(start..start + bytes.len())
            .ok_or(RamFlashError::OutOfBounds)?;
        if target.iter().any(|&b| b != 0xFF) {
            return Err(RamFlashError::WordWrittenTwice);
        }
        for (i, &b) in bytes.iter().enumerate() {
            let powered = self.spend();
            let Some(cell) = self.mem.bytes_mut().get_mut(start + i) else {
                return Err(RamFlashError::OutOfBounds);
            };
            if !powered {
                // Torn: only the low nibble's cleared bits made it.
                *cell &= b | 0xF0;
                return Err(RamFlashError::PowerLost);
            }
            *cell &= b;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    type Flash = RamNorFlash<1024, 4, 256>;

    #[test]
    fn nor_rules_are_enforced() {
        let mut f = Flash::new();
        let mut buf = [0u8; 8];
        f.read(0, &mut buf).unwrap();
        assert_eq!(buf, [0xFF; 8]);
        f.write(4, &[1, 2, 3, 4]).unwrap();
        assert_eq!(
            f.write(4, &[0, 0, 0, 0]),
            Err(RamFlashError::WordWrittenTwice)
        );
        assert_eq!(f.write(2, &[0, 0, 0, 0]), Err(RamFlashError::NotAligned));
        assert_eq!(f.write(0, &[0, 0]), Err(RamFlashError::NotAligned));
        assert_eq!(f.read(1, &mut buf), Err(RamFlashError::NotAligned));
        assert_eq!(f.write(1024, &[0; 4]), Err(RamFlashError::OutOfBounds));
        assert_eq!(f.erase(0, 100), Err(RamFlashError::NotAligned));
        assert_eq!(f.erase(256, 0), Err(RamFlashError::OutOfBounds));
        assert_eq!(f.erase(0, 2048), Err(RamFlashError::OutOfBounds));
        f.read(0, &mut buf).unwrap();
        assert_eq!(buf, [0xFF, 0xFF, 0xFF, 0xFF, 1, 2, 3, 4]);
        f.erase(0, 256).unwrap();
        f.read(0, &mut buf).unwrap();
        assert_eq!(buf, [0xFF; 8]);
        assert_eq!(f.capacity(), 1024);
        assert_eq!(RamFlashError::PowerLost.kind(), NorFlashErrorKind::Other);
        assert_eq!(RamFlashError::MediumFailed.kind(), NorFlashErrorKind::Other);
        assert_eq!(
            format!("{}", RamFlashError::MediumFailed),
            "flash medium failed"
        );
    }

    #[test]
    fn lent_memory_keeps_its_contents_and_the_rules() {
        let mut mem = [0xFF; 1024];
        mem[..4].copy_from_slice(&[1, 2, 3, 4]);
        let mut f = RamNorFlash::<1024, 4, 256, &mut [u8; 1024]>::with_memory(&mut mem);
        let mut buf = [0u8; 4];
        f.read(0, &mut buf).unwrap();
        assert_eq!(buf, [1, 2, 3, 4], "what the memory held");
        assert_eq!(f.write(0, &[0; 4]), Err(RamFlashError::WordWrittenTwice));
        f.write(256, &[5, 6, 7, 8]).unwrap();
        f.erase(0, 256).unwrap();
        assert_eq!(f.as_bytes()[..4], [0xFF; 4]);
        f.into_memory();
        assert_eq!(mem[256..260], [5, 6, 7, 8], "written to the memory lent");
        assert_eq!(mem[..4], [0xFF; 4]);
    }

    #[test]
    fn power_cut_tears_the_current_byte_and_stops_everything() {
        let mut f = Flash::new();
        f.cut_power_after(2);
        assert_eq!(f.write(0, &[0x00; 4]), Err(RamFlashError::PowerLost));
        assert!(!f.is_powered());
        assert_eq!(&f.as_bytes()[..4], &[0x00, 0x00, 0xF0, 0xFF]);
        assert_eq!(f.read(0, &mut [0; 4]), Err(RamFlashError::PowerLost));
        f.restore_power();
        assert_eq!(f.work_done(), 2);
        assert!(f.read(0, &mut [0; 4]).is_ok());
    }

    #[test]
    fn power_cut_during_erase_leaves_a_half_erased_page() {
        let mut f = Flash::new();
        f.write(0, &[0; 256]).unwrap();
        f.write(256, &[0; 4]).unwrap();
        f.write(400, &[0; 4]).unwrap();
        f.cut_power_after(1);
        assert_eq!(f.erase(0, 512), Err(RamFlashError::PowerLost));
        assert!(f.as_bytes()[..256].iter().all(|&b| b == 0xFF));
        assert_eq!(&f.as_bytes()[256..260], &[0xFF; 4], "first half erased");
        assert_eq!(&f.as_bytes()[400..404], &[0; 4], "second half not");
    }
}
