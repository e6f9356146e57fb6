//! The settings, the stored program and the files of the SD-card commands, in the `forja`
//! data partition: the settings in a [`FlashRecordStorage`] (keyed records), the program in a
//! [`SlotProgramStore`] (one 64-byte slot per line), the files in a [`FlashFileStore`] (named
//! files, `M20`–`M32`), as the simulator keeps them in two flashes and a directory.
//!
//! The board's `partitions.csv` (the table espflash writes at 0x8000) gives the stores a data
//! partition labelled [`PARTITION_LABEL`] (the ESP32 boards: the 2 752 KiB after a 1.25 MiB
//! app, 0x15_0000..0x40_0000 of a 4 MiB flash). At start the stores find their partition by
//! label in the table on the flash, with esp-bootloader-esp-idf's partition reader, so that a
//! board flashed with another table never erases code: without a `forja` data partition the
//! firmware does not start. The partition is cut in three:
//!
//! | part | size | keeps | used by |
//! |---|---|---|---|
//! | settings | [`SETTINGS_LEN`] (4 sectors) | frame 00 values, WiFi credentials | `Controller::with_settings` |
//! | program | [`PROGRAM_LEN`] (157 sectors) | the uploaded program, line `k` in slot `k - 1` (9 999 lines) | the controller's program store |
//! | files | the rest (527 sectors on the ESP32 boards) | up to 32 named files: 4 080 bytes per sector beyond one for each file's head, a file of at most 2 146 080 bytes here (526 sectors) | the SD-card commands, and jobs run from a file |
//!
//! The flash is esp-storage's [`FlashStorage`], an `embedded-storage` `NorFlash` over the
//! whole SPI flash: 4-byte words, 4 KiB erase sectors. The stores reach it through
//! [`SharedFlash`] handles; each only touches its own range.
//!
//! # Stalls
//!
//! esp-storage calls the ROM's SPI flash routines inside a critical section, with the flash
//! cache off: every interrupt, the step interrupt included, waits for the operation. One read
//! takes a few to tens of microseconds; a sector erase typically 45 ms and up to 400 ms.
//! Each write erases at most one sector (a file's `append` one for each sector its bytes
//! begin: one for a line), and the watchdog ([`crate::watchdog::WATCHDOG_TIMEOUT_MS`]) allows
//! the longest erase. The settings and the program are written only while the machine is idle
//! (their contract); a file written or removed while the machine moves (`M28`–`M30` of
//! another file during a job) delays its steps by as much as an erase: upload files while the
//! machine is at rest.
//!
//! Reads happen while the machine moves: the controller reads the stored program line by line
//! as the planner frees room, each line one flash read of 64 bytes ([`SlotProgramStore`]), and
//! a job run from a file reads it a few hundred bytes at a time, each time one read of a map
//! entry (4 bytes) and reads of at most 256 bytes ([`FlashFileStore`]). Opening the stores at
//! start reads the stored lines once (at most 9 999 slot reads) and every file sector's
//! header once (527 reads), plus each file's map. See the ESP32 board's README ("Running a
//! stored program", "Files").

use core::cell::RefCell;
use core::ops::Range;

use critical_section::Mutex;
use embedded_storage::nor_flash::{ErrorType, NorFlash, ReadNorFlash};
use esp_bootloader_esp_idf::partitions::{
    self, DataPartitionSubType, PARTITION_TABLE_MAX_LEN, PartitionType,
};
use esp_hal::peripherals::FLASH;
use esp_storage::{FlashStorage, FlashStorageError};
use forja_drivers::flash_files::FlashFileStore;
use forja_drivers::program_flash::{SLOT_LEN, SlotProgramStore};
use forja_drivers::storage::FlashRecordStorage;
use forja_hal_abstraction::program::MAX_LINES;

use forja_app::firmware::SetupError;

/// The label of the store's partition in `partitions.csv`.
pub const PARTITION_LABEL: &str = "forja";

/// Bytes of the partition that keep the settings, at its start: four 4 KiB sectors (the
/// simulator's settings flash is as large).
pub const SETTINGS_LEN: u32 = 4 * SECTOR;

/// Bytes of the partition that keep the program, after the settings: the sectors of
/// [`MAX_LINES`] slots (157 sectors, 628 KiB).
pub const PROGRAM_LEN: u32 = (MAX_LINES as u32 * SLOT_LEN as u32).div_ceil(SECTOR) * SECTOR;

/// The flash's erase sector.
const SECTOR: u32 = 4096;

/// The SPI flash, once [`open`] has taken it.
static FLASH_STORAGE: Mutex<RefCell<Option<FlashStorage<'static>>>> =
    Mutex::new(RefCell::new(None));

/// A handle on the SPI flash, for one of the stores. Every operation runs in a critical
/// section, as esp-storage runs each of its ROM calls anyway.
#[derive(Debug)]
pub struct SharedFlash {
    capacity: usize,
}

impl SharedFlash {
    fn with<R>(
        f: impl FnOnce(&mut FlashStorage<'static>) -> Result<R, FlashStorageError>,
    ) -> Result<R, FlashStorageError> {
        critical_section::with(|cs| match FLASH_STORAGE.borrow(cs).borrow_mut().as_mut() {
            Some(flash) => f(flash),
            None => Err(FlashStorageError::Other(0)),
        })
    }
}

impl ErrorType for SharedFlash {
    type Error = FlashStorageError;
}

impl ReadNorFlash for SharedFlash {
    const READ_SIZE: usize = <FlashStorage<'static> as ReadNorFlash>::READ_SIZE;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        Self::with(|flash| flash.read(offset, bytes))
    }

    fn capacity(&self) -> usize {
        self.capacity
    }
}

impl NorFlash for SharedFlash {
    const WRITE_SIZE: usize = <FlashStorage<'static> as NorFlash>::WRITE_SIZE;
    const ERASE_SIZE: usize = <FlashStorage<'static> as NorFlash>::ERASE_SIZE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        Self::with(|flash| flash.erase(from, to))
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        Self::with(|flash| flash.write(offset, bytes))
    }
}

/// The settings' record store in the `forja` partition.
pub type Store = FlashRecordStorage<SharedFlash>;

/// The uploaded program's store in the `forja` partition.
pub type ProgramFlash = SlotProgramStore<SharedFlash>;

/// The files of the SD-card commands in the `forja` partition: at most 32.
pub type FileFlash = FlashFileStore<SharedFlash>;

/// The three stores.
pub struct Stores {
    /// The settings.
    pub settings: Store,
    /// The uploaded program.
    pub program: ProgramFlash,
    /// The files.
    pub files: FileFlash,
}

/// Open the settings, program and file stores in the `forja` data partition.
///
/// Context: init; call once. Reads the partition table (3 KiB on the stack), then every
/// stored program line once (at most 9 999 reads of 64 bytes), then the header of every
/// sector of the files (527 reads of 16 bytes on the ESP32 boards) and each file's map.
/// Errors: [`SetupError::StorageLayout`] when the table cannot be read, [`SetupError::NoStore`]
/// when it has no `forja` data partition, [`SetupError::Storage`] when the partition is not a
/// whole number of sectors with at least two for the settings, the program's and one for the
/// files, when the flash cannot be read, or when the flash was already taken.
pub fn open(flash: FLASH<'static>) -> Result<Stores, SetupError> {
    let mut flash = FlashStorage::new(flash);
    let mut table = [0u8; PARTITION_TABLE_MAX_LEN];
    let region: Range<u32> = {
        let table = partitions::read_partition_table(&mut flash, &mut table)
            .map_err(|_| SetupError::StorageLayout)?;
        let entry = table
            .iter()
            .find(|p| {
                p.label_as_str() == PARTITION_LABEL
                    && p.partition_type() == PartitionType::Data(DataPartitionSubType::Undefined)
            })
            .ok_or(SetupError::NoStore)?;
        entry.offset()..entry.offset().saturating_add(entry.len())
    };
    let capacity = ReadNorFlash::capacity(&flash);
    let taken = critical_section::with(|cs| {
        FLASH_STORAGE
            .borrow(cs)
            .borrow_mut()
            .replace(flash)
            .is_some()
    });
    if taken {
        return Err(SetupError::Storage);
    }
    let program_at = region.start.saturating_add(SETTINGS_LEN);
    let files_at = program_at.saturating_add(PROGRAM_LEN);
    let settings = FlashRecordStorage::new(SharedFlash { capacity }, region.start..program_at)
        .map_err(|_| SetupError::Storage)?;
    let program = SlotProgramStore::open(SharedFlash { capacity }, program_at..files_at)
        .map_err(|_| SetupError::Storage)?;
    let files = FlashFileStore::open(SharedFlash { capacity }, files_at..region.end)
        .map_err(|_| SetupError::Storage)?;
    Ok(Stores {
        settings,
        program,
        files,
    })
}
