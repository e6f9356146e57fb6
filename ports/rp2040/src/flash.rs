//! The settings and program stores on the QSPI flash that the RP2040 runs from: a
//! [`FlashRecordStorage`] over each region the board reserves ([`store`]), written through the
//! boot ROM's flash routines.
//!
//! The board's linker script ends its FLASH region where the stores start and defines
//! `_storage_start` and `_storage_end` around them; a store's region must lie between the two
//! (checked at start), so that erasing a store never touches code.
//!
//! Reads are plain reads of the memory-mapped flash. The RP2040 runs its code from that same
//! flash (XIP), which cannot be read while a sector is erased or a page programmed, so
//! [`QspiFlash`] calls the ROM routines from a function placed in RAM (`.data`), with
//! interrupts off and XIP restored afterwards by a copy of the second-stage boot loader in RAM
//! (fast quad reads again), as the Pico SDK does. The second core is never started and no DMA
//! channel reads the flash, so nothing else touches it meanwhile. `rp2040-hal` has no flash
//! driver of its own (only the ROM's function table, `rom_data`, used here).
//!
//! # Stalls
//!
//! Every interrupt waits while the flash is busy: a 4 KiB sector erase takes 45 ms, at most
//! 400 ms, a 256-byte page program at most 3 ms (W25Q16JV datasheet). The stores are written
//! only while the machine is idle (the controller refuses frame 00 sets and 03 uploads
//! otherwise), one sector or page per interrupt-free stretch, and the watchdog allows 1 s.

use core::ops::Range;

use embedded_storage::nor_flash::{
    ErrorType, NorFlash, NorFlashErrorKind, ReadNorFlash, check_erase, check_read, check_write,
};
use forja_app::firmware::SetupError;
use forja_drivers::storage::FlashRecordStorage;
use rp2040_hal::rom_data;

/// The flash as the core sees it.
const XIP_BASE: u32 = 0x1000_0000;
/// Bytes of a sector, the smallest erase.
pub const SECTOR: u32 = 4096;
/// Bytes of a page, the unit of programming.
const PAGE: usize = 256;

unsafe extern "C" {
    /// The first byte of the stores (the board's linker script).
    static _storage_start: u8;
    /// The byte after the last of the stores.
    static _storage_end: u8;
}

/// A store.
pub type Store = FlashRecordStorage<QspiFlash>;

/// A store over `region` of the flash (offsets from the flash's first byte), whole sectors.
///
/// Context: init, once for each region (two stores over one region would corrupt each other).
/// Errors: [`SetupError::StorageLayout`] when the region is not whole sectors between the
/// linker script's `_storage_start` and `_storage_end`; [`SetupError::Storage`] when the
/// store refuses the region.
pub fn store(region: Range<u32>) -> Result<Store, SetupError> {
    // Only the symbols' addresses are taken, never their contents.
    let first = core::ptr::addr_of!(_storage_start) as u32;
    let end = core::ptr::addr_of!(_storage_end) as u32;
    let placed = first <= XIP_BASE + region.start && XIP_BASE + region.end <= end;
    let whole = region.start.is_multiple_of(SECTOR) && region.end.is_multiple_of(SECTOR);
    if !placed || !whole || region.is_empty() {
        return Err(SetupError::StorageLayout);
    }
    let len = region.end - region.start;
    Store::new(QspiFlash { region }, 0..len).map_err(|_| SetupError::Storage)
}

/// One region of the QSPI flash as a `NorFlash`; offsets are from the region's start.
#[derive(Debug)]
pub struct QspiFlash {
    region: Range<u32>,
}

impl ErrorType for QspiFlash {
    type Error = NorFlashErrorKind;
}

impl ReadNorFlash for QspiFlash {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        check_read(self, offset, bytes.len())?;
        let at = (XIP_BASE + self.region.start + offset) as *const u8;
        // SAFETY: inside the region (checked), memory-mapped flash that is always readable
        // and changes only through `&mut self`.
        bytes.copy_from_slice(unsafe { core::slice::from_raw_parts(at, bytes.len()) });
        Ok(())
    }

    fn capacity(&self) -> usize {
        (self.region.end - self.region.start) as usize
    }
}

impl NorFlash for QspiFlash {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = SECTOR as usize;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        check_erase(self, from, to)?;
        for sector in (from..to).step_by(SECTOR as usize) {
            rom_op(self.region.start + sector, SECTOR, core::ptr::null());
        }
        Ok(())
    }

    /// Program `bytes` a flash page at a time: each page is sent whole, `0xFF` (which leaves a
    /// byte as it is) around the new bytes, from a buffer in RAM.
    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        check_write(self, offset, bytes.len())?;
        let mut at = (self.region.start + offset) as usize;
        let mut rest = bytes;
        while !rest.is_empty() {
            let in_page = at % PAGE;
            let n = rest.len().min(PAGE - in_page);
            let mut page = [0xFFu8; PAGE];
            page[in_page..in_page + n].copy_from_slice(&rest[..n]);
            rom_op((at - in_page) as u32, PAGE as u32, page.as_ptr());
            at += n;
            rest = &rest[n..];
        }
        Ok(())
    }
}

/// What [`in_ram`] runs: the ROM routines, the boot loader copy, and the operation. The
/// assembly reads the fields at their offsets.
#[repr(C)]
struct RomOp {
    connect_internal_flash: usize,
    flash_exit_xip: usize,
    flash_range_erase: usize,
    flash_range_program: usize,
    flash_flush_cache: usize,
    enter_xip: usize,
    offset: u32,
    len: u32,
    /// The bytes to program (in RAM); null to erase.
    data: *const u8,
}

/// Erase (`data` null) or program `len` bytes at flash `offset`, with interrupts off. The ROM
/// routines are looked up and the boot loader copied to the stack while XIP still works.
fn rom_op(offset: u32, len: u32, data: *const u8) {
    let mut boot2 = [0u32; 64];
    // SAFETY: the second-stage boot loader is the flash's first 256 bytes, mapped at XIP_BASE.
    unsafe { core::ptr::copy_nonoverlapping(XIP_BASE as *const u32, boot2.as_mut_ptr(), 64) };
    let op = RomOp {
        connect_internal_flash: rom_data::connect_internal_flash::ptr() as usize,
        flash_exit_xip: rom_data::flash_exit_xip::ptr() as usize,
        flash_range_erase: rom_data::flash_range_erase::ptr() as usize,
        flash_range_program: rom_data::flash_range_program::ptr() as usize,
        flash_flush_cache: rom_data::flash_flush_cache::ptr() as usize,
        // A Thumb function: the address with bit 0 set.
        enter_xip: boot2.as_ptr() as usize | 1,
        offset,
        len,
        data,
    };
    // SAFETY: the callers pass a whole sector or page of a store region (checked), never
    // code; interrupts are off, the other core is not running and no DMA reads the flash, so
    // nothing is fetched from the flash until `in_ram` has restored XIP.
    critical_section::with(|_| unsafe { in_ram(&op) });
}

/// The flash operation itself, in RAM: connect the flash, leave XIP, erase (with 64 KiB block
/// erases where whole blocks are asked for, D8h) or program, flush the XIP cache, and run the
/// boot loader copy to enter fast XIP again. `r4` keeps `op` across the calls (AAPCS preserves
/// it).
///
/// # Safety
///
/// Nothing may read the flash until it returns (see [`rom_op`]).
#[inline(never)]
#[unsafe(link_section = ".data.ram_func")]
unsafe fn in_ram(op: &RomOp) {
    // SAFETY: by the caller.
    unsafe {
        core::arch::asm!(
            "ldr r0, [r4, #0]",
            "blx r0",
            "ldr r0, [r4, #4]",
            "blx r0",
            "ldr r0, [r4, #24]",
            "ldr r1, [r4, #32]",
            "cmp r1, #0",
            "beq 1f",
            "ldr r2, [r4, #28]",
            "ldr r3, [r4, #12]",
            "blx r3",
            "b 2f",
            "1:",
            "ldr r1, [r4, #28]",
            "movs r2, #1",
            "lsls r2, r2, #16",
            "movs r3, #0xd8",
            "ldr r5, [r4, #8]",
            "blx r5",
            "2:",
            "ldr r0, [r4, #16]",
            "blx r0",
            "ldr r0, [r4, #20]",
            "blx r0",
            in("r4") op,
            out("r5") _,
            clobber_abi("C"),
        );
    }
}
