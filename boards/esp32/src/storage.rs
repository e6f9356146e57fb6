//! The settings and program store: [`FlashRecordStorage`] over the `forja` data partition.
//!
//! `partitions.csv` (the table espflash writes at 0x8000) gives the app 3 MiB and the store
//! the 960 KiB after it (0x31_0000..0x40_0000 of a 4 MiB flash). At start the store finds its
//! partition by label in the table on the flash, with esp-bootloader-esp-idf's partition
//! reader, so that a board flashed with another table never erases code: without a `forja`
//! data partition the firmware does not start.
//!
//! The flash is esp-storage's [`FlashStorage`], an `embedded-storage` `NorFlash` over the
//! whole SPI flash: 4-byte words, 4 KiB erase sectors. [`FlashRecordStorage`] only touches the
//! partition's range.
//!
//! # Stalls
//!
//! esp-storage calls the ROM's SPI flash routines inside a critical section, with the flash
//! cache off: every interrupt, the step interrupt included, waits for the operation. A read
//! of a record takes tens of microseconds; a sector erase typically 45 ms and up to 400 ms.
//! The record store is written only while the machine is idle (its contract); the watchdog
//! ([`crate::hardware::WATCHDOG_TIMEOUT_MS`]) allows the longest erase.

use esp_bootloader_esp_idf::partitions::{
    self, DataPartitionSubType, PARTITION_TABLE_MAX_LEN, PartitionType,
};
use esp_hal::peripherals::FLASH;
use esp_storage::FlashStorage;
use forja_drivers::storage::FlashRecordStorage;

use crate::hardware::SetupError;

/// The label of the store's partition in `partitions.csv`.
pub const PARTITION_LABEL: &str = "forja";

/// The flash behind the store.
pub type StoreFlash = FlashStorage<'static>;

/// The settings and program store.
pub type Store = FlashRecordStorage<StoreFlash>;

/// Open the store in the `forja` data partition.
///
/// Context: init. Reads the partition table (3 KiB on the stack). Errors:
/// [`SetupError::PartitionTable`] when the table cannot be read, [`SetupError::NoStore`] when
/// it has no `forja` data partition, [`SetupError::Storage`] when the partition is not a
/// whole number of at least two sectors.
pub fn open(flash: FLASH<'static>) -> Result<Store, SetupError> {
    let mut flash = FlashStorage::new(flash);
    let mut table = [0u8; PARTITION_TABLE_MAX_LEN];
    let region = {
        let table = partitions::read_partition_table(&mut flash, &mut table)
            .map_err(|_| SetupError::PartitionTable)?;
        let entry = table
            .iter()
            .find(|p| {
                p.label_as_str() == PARTITION_LABEL
                    && p.partition_type() == PartitionType::Data(DataPartitionSubType::Undefined)
            })
            .ok_or(SetupError::NoStore)?;
        entry.offset()..entry.offset().saturating_add(entry.len())
    };
    FlashRecordStorage::new(flash, region).map_err(|_| SetupError::Storage)
}
