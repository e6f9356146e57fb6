//! The simulated board's stores as its firmware uses them: the settings and the uploaded
//! program as records in the board's two flashes ([`BoardFlash`], through
//! `forja_drivers::storage::FlashRecordStorage`, as a firmware board keeps them in its flash
//! sectors), and files on its SD card ([`DirFileStore`]).
//!
//! The board opens them at start-up ([`BoardStores::open`]) and gives the flashes back when it
//! stops ([`BoardStores::into_flash`]), to start another board on them (a restart).

use core::fmt;
use std::io;
use std::path::PathBuf;

use forja_drivers::storage::{FlashRecordStorage, StorageError};

use crate::files::DirFileStore;
use crate::state::{
    BoardFlash, PROGRAM_FLASH_LEN, ProgramFlash, SETTINGS_FLASH_LEN, SettingsFlash,
};

/// The settings' records, in the whole settings flash.
pub type SettingsRecords = FlashRecordStorage<SettingsFlash>;

/// The uploaded program's records, in the whole program flash.
pub type ProgramRecords = FlashRecordStorage<ProgramFlash>;

/// The board's stores. See the [module documentation](self).
pub struct BoardStores {
    /// The settings' records.
    pub settings: SettingsRecords,
    /// The program's records.
    pub program: ProgramRecords,
    /// The SD card.
    pub card: DirFileStore,
}

impl fmt::Debug for BoardStores {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("BoardStores")
            .field("card", &self.card)
            .finish_non_exhaustive()
    }
}

/// A store could not be opened.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum StoresError {
    /// A flash's records.
    Flash(StorageError),
    /// The SD card's directory, with the host's error as text.
    Card(String),
}

impl fmt::Display for StoresError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Flash(e) => write!(f, "flash: {e:?}"),
            Self::Card(e) => write!(f, "SD card directory: {e}"),
        }
    }
}

impl std::error::Error for StoresError {}

impl BoardStores {
    /// The records of `flash` and the SD card in `sd_dir` (a fresh temporary directory with
    /// `None`: [`DirFileStore::open_or_temporary`]).
    ///
    /// Errors: [`StoresError`].
    pub fn open(flash: BoardFlash, sd_dir: Option<PathBuf>) -> Result<Self, StoresError> {
        let BoardFlash { program, settings } = flash;
        let records = |e| StoresError::Flash(e);
        Ok(Self {
            settings: FlashRecordStorage::new(settings, 0..SETTINGS_FLASH_LEN as u32)
                .map_err(records)?,
            program: FlashRecordStorage::new(program, 0..PROGRAM_FLASH_LEN as u32)
                .map_err(records)?,
            card: DirFileStore::open_or_temporary(sd_dir)
                .map_err(|e: io::Error| StoresError::Card(e.to_string()))?,
        })
    }

    /// The flashes of the records `program` and `settings`, to start a board on.
    pub fn into_flash(program: ProgramRecords, settings: SettingsRecords) -> BoardFlash {
        BoardFlash {
            program: program.into_flash(),
            settings: settings.into_flash(),
        }
    }
}

#[cfg(test)]
mod tests {
    use forja_hal_abstraction::files::{FileName, FileStore as _};
    use forja_hal_abstraction::storage::RecordStorage as _;

    use super::*;

    #[test]
    fn the_records_survive_a_restart_and_the_card_is_fresh() {
        let mut stores = BoardStores::open(BoardFlash::erased(), None).unwrap();
        stores.settings.write(7, b"seven").unwrap();
        let name = FileName::new(b"a.g").unwrap();
        stores.card.create(&name).unwrap();
        stores.card.finish().unwrap();
        let BoardStores {
            settings, program, ..
        } = stores;
        let flash = BoardStores::into_flash(program, settings);
        let mut again = BoardStores::open(flash, None).unwrap();
        let mut buf = [0; 8];
        assert_eq!(again.settings.read(7, &mut buf), Ok(Some(5)));
        assert_eq!(again.card.file(0), Ok(None), "a new temporary card");
    }
}
