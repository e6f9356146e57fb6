//! The simulated board's flash ([`BoardFlash`]: a settings flash and a program flash), and
//! the state file it is kept in, so that what a firmware stores survives a restart of the
//! simulator as it survives a power cycle of a board.
//!
//! # The file
//!
//! | offset | bytes | what |
//! |---|---|---|
//! | 0 | [`HEADER_LEN`] | [`MAGIC`] and the layout in text, then zeros ([`header`]) |
//! | [`HEADER_LEN`] | [`SETTINGS_FLASH_LEN`] | the settings' flash ([`SettingsFlash`]) |
//! | [`HEADER_LEN`] + [`SETTINGS_FLASH_LEN`] | [`PROGRAM_FLASH_LEN`] | the program's flash ([`ProgramFlash`]) |
//!
//! A missing file is made erased (every flash byte `0xFF`): written whole under a temporary
//! name, then renamed, so that a file of the name is always complete. A file of another
//! layout (another header or length) is refused, never reformatted. One simulator at a time
//! uses a file (an exclusive `flock`); a second is refused.
//!
//! # The flash model
//!
//! Each flash is a [`SimFlash`]: the NOR rules of `forja_drivers::ram_flash::RamNorFlash`,
//! every completed erase or write written through to its window of the file before it returns
//! ([`FlashFile`]). The flashes start at page boundaries of the file, so a simulator killed in
//! the middle of an operation leaves the file as a power cut leaves a flash; the limits (no
//! `fsync`, a failed write fails the flash) are in the documentation of [`crate::flash`].

use core::fmt;
use std::fs::{File, OpenOptions};
use std::io::{self, Write as _};
use std::os::unix::fs::FileExt as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nix::fcntl::{Flock, FlockArg};

use crate::flash::{FlashFile, PAGE, SimFlash};

/// Bytes of the flash that keeps the uploaded program (enough for the 9999 lines frame 03
/// allows, with room for the flash to reclaim space).
pub const PROGRAM_FLASH_LEN: usize = 1024 * 1024;

/// Bytes of the flash that keeps the settings.
pub const SETTINGS_FLASH_LEN: usize = 16 * 1024;

/// Erase page of both flashes.
pub const FLASH_PAGE: usize = PAGE;

/// The program's flash.
pub type ProgramFlash = SimFlash<PROGRAM_FLASH_LEN>;

/// The settings' flash.
pub type SettingsFlash = SimFlash<SETTINGS_FLASH_LEN>;

/// The board's two flashes: what survives a restart.
#[derive(Debug)]
pub struct BoardFlash {
    /// Keeps the uploaded program.
    pub program: ProgramFlash,
    /// Keeps the settings.
    pub settings: SettingsFlash,
}

impl BoardFlash {
    /// Both erased: a board fresh from the factory.
    pub fn erased() -> Self {
        Self {
            program: ProgramFlash::erased(),
            settings: SettingsFlash::erased(),
        }
    }

    /// The flash kept in the state file at `path`, made erased when there is none: each
    /// completed erase and write is in the file before it returns. The file stays locked for
    /// this simulator until the flash is dropped.
    ///
    /// Errors: [`StateError`].
    pub fn open(path: &Path) -> Result<Self, StateError> {
        if !path.exists() {
            create(path)?;
        }
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .open(path)
            .map_err(io_error(path))?;
        let file =
            Flock::lock(file, FlockArg::LockExclusiveNonblock).map_err(|_| StateError::InUse {
                path: path.to_path_buf(),
            })?;
        let bytes = read_checked(&file, path)?;
        Ok(Self::from_file_bytes(&bytes, Some(Arc::new(file))))
    }

    /// A copy in memory of the flash in the state file at `path`, as it is now: what a
    /// firmware changes in it stays out of the file.
    ///
    /// Errors: [`StateError`] (a missing file is one).
    pub fn snapshot(path: &Path) -> Result<Self, StateError> {
        let file = File::open(path).map_err(io_error(path))?;
        let bytes = read_checked(&file, path)?;
        Ok(Self::from_file_bytes(&bytes, None))
    }

    /// The two flashes of `bytes` (a whole state file), with their write-through windows.
    fn from_file_bytes(bytes: &[u8], file: Option<Arc<Flock<File>>>) -> Self {
        let window = |base: usize| {
            file.as_ref()
                .map(|f| FlashFile::new(Arc::clone(f), base as u64))
        };
        let part = |at: usize, len: usize| bytes.get(at..at + len).unwrap_or(&[]).to_vec();
        Self {
            settings: SettingsFlash::with_contents(
                part(SETTINGS_AT, SETTINGS_FLASH_LEN),
                window(SETTINGS_AT),
            ),
            program: ProgramFlash::with_contents(
                part(PROGRAM_AT, PROGRAM_FLASH_LEN),
                window(PROGRAM_AT),
            ),
        }
    }
}

/// The first bytes of a state file.
pub const MAGIC: &[u8] = b"forja-sim flash state\n";

/// Bytes before the first flash: the header, one flash page.
pub const HEADER_LEN: usize = FLASH_PAGE;

/// Length of a state file, bytes.
pub const STATE_FILE_LEN: usize = HEADER_LEN + SETTINGS_FLASH_LEN + PROGRAM_FLASH_LEN;

/// Offset of the settings' flash in the file.
pub const SETTINGS_AT: usize = HEADER_LEN;

/// Offset of the program's flash in the file.
pub const PROGRAM_AT: usize = HEADER_LEN + SETTINGS_FLASH_LEN;

/// The header of a state file of this layout: [`MAGIC`], the layout in text, zeros.
pub fn header() -> Vec<u8> {
    let mut h = MAGIC.to_vec();
    h.extend_from_slice(
        format!(
            "layout 1: header {HEADER_LEN}, settings {SETTINGS_FLASH_LEN}, program \
             {PROGRAM_FLASH_LEN}, page {FLASH_PAGE}, word 4\n"
        )
        .as_bytes(),
    );
    h.resize(HEADER_LEN, 0);
    h
}

/// Why a state file cannot be used.
#[derive(Debug)]
#[non_exhaustive]
pub enum StateError {
    /// The file could not be made, opened or read.
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        error: io::Error,
    },
    /// The file is not a state file of this layout (another header or length).
    NotAState {
        /// The file.
        path: PathBuf,
        /// Its length, bytes.
        len: u64,
    },
    /// Another simulator uses the file.
    InUse {
        /// The file.
        path: PathBuf,
    },
}

impl fmt::Display for StateError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io { path, error } => write!(f, "state file {}: {error}", path.display()),
            Self::NotAState { path, len } => write!(
                f,
                "state file {}: not a forja-sim state file of this layout ({len} bytes; one \
                 is {STATE_FILE_LEN} bytes starting with \"forja-sim flash state\")",
                path.display()
            ),
            Self::InUse { path } => write!(
                f,
                "state file {}: in use by another forja-sim",
                path.display()
            ),
        }
    }
}

impl std::error::Error for StateError {}

fn io_error(path: &Path) -> impl Fn(io::Error) -> StateError + '_ {
    move |error| StateError::Io {
        path: path.to_path_buf(),
        error,
    }
}

/// Make an erased state file at `path`: written whole under a temporary name in the same
/// directory, then renamed to `path`.
fn create(path: &Path) -> Result<(), StateError> {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".new-{}", std::process::id()));
    let temp = path.with_file_name(name);
    let result = (|| {
        let mut f = File::create(&temp)?;
        f.write_all(&header())?;
        f.write_all(&vec![0xFF; SETTINGS_FLASH_LEN + PROGRAM_FLASH_LEN])?;
        f.sync_all()?;
        std::fs::rename(&temp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result.map_err(io_error(path))
}

/// The whole contents of the state file `file`, checked against this layout.
fn read_checked(file: &File, path: &Path) -> Result<Vec<u8>, StateError> {
    let len = file.metadata().map_err(io_error(path))?.len();
    let not_a_state = || StateError::NotAState {
        path: path.to_path_buf(),
        len,
    };
    if len != STATE_FILE_LEN as u64 {
        return Err(not_a_state());
    }
    let mut bytes = vec![0; STATE_FILE_LEN];
    file.read_exact_at(&mut bytes, 0).map_err(io_error(path))?;
    if bytes.get(..HEADER_LEN) != Some(&header()[..]) {
        return Err(not_a_state());
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use embedded_storage::nor_flash::{NorFlash as _, ReadNorFlash as _};
    use forja_drivers::ram_flash::RamFlashError;

    use super::*;

    fn temp_path(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("forja-sim-state-{}-{name}", std::process::id()))
    }

    #[test]
    fn every_completed_operation_is_in_the_file_and_survives_a_reopen() {
        let path = temp_path("ops");
        let _ = std::fs::remove_file(&path);
        let mut flash = BoardFlash::open(&path).unwrap();
        assert_eq!(
            std::fs::metadata(&path).unwrap().len(),
            STATE_FILE_LEN as u64
        );
        assert!(matches!(
            BoardFlash::open(&path),
            Err(StateError::InUse { .. })
        ));
        flash.settings.write(8, &[1, 2, 3, 4]).unwrap();
        flash.program.write(4096, &[0x0F; 8]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[SETTINGS_AT + 8..SETTINGS_AT + 12], &[1, 2, 3, 4]);
        assert_eq!(&bytes[PROGRAM_AT + 4096..PROGRAM_AT + 4104], &[0x0F; 8]);
        assert_eq!(bytes[PROGRAM_AT + 4104], 0xFF);
        // A refused operation writes nothing.
        assert_eq!(
            flash.settings.write(8, &[0; 4]),
            Err(RamFlashError::WordWrittenTwice)
        );
        assert_eq!(std::fs::read(&path).unwrap(), bytes);
        flash.program.erase(4096, 8192).unwrap();
        assert_eq!(
            &std::fs::read(&path).unwrap()[PROGRAM_AT + 4096..PROGRAM_AT + 4104],
            &[0xFF; 8]
        );
        drop(flash);

        let mut again = BoardFlash::open(&path).unwrap();
        let mut b = [0; 4];
        again.settings.read(8, &mut b).unwrap();
        assert_eq!(b, [1, 2, 3, 4]);
        let copy = BoardFlash::snapshot(&path).unwrap();
        drop(again);
        // A snapshot's changes stay out of the file.
        let mut copy = copy;
        copy.settings.erase(0, FLASH_PAGE as u32).unwrap();
        assert_eq!(
            &std::fs::read(&path).unwrap()[SETTINGS_AT + 8..SETTINGS_AT + 12],
            &[1, 2, 3, 4]
        );
        std::fs::remove_file(&path).unwrap();
    }

    #[test]
    fn a_file_that_cannot_be_written_fails_the_flash_as_a_power_cut_does() {
        let path = temp_path("readonly");
        let _ = std::fs::remove_file(&path);
        drop(BoardFlash::open(&path).unwrap());
        // A descriptor that cannot write: every write to the file fails, as on a full disk.
        let file = Flock::lock(File::open(&path).unwrap(), FlockArg::LockExclusiveNonblock)
            .map_err(|(_, e)| e)
            .unwrap();
        let window = FlashFile::new(Arc::new(file), SETTINGS_AT as u64);
        let mut flash = SettingsFlash::with_contents(Vec::new(), Some(window));
        assert_eq!(flash.write(0, &[0; 4]), Err(RamFlashError::MediumFailed));
        assert_eq!(flash.read(0, &mut [0; 4]), Err(RamFlashError::MediumFailed));
        assert_eq!(flash.erase(0, 4096), Err(RamFlashError::MediumFailed));
        assert_eq!(
            std::fs::read(&path).unwrap()[SETTINGS_AT..SETTINGS_AT + 4],
            [0xFF; 4]
        );
        std::fs::remove_file(&path).unwrap();
    }

    #[test]
    fn a_file_of_another_layout_is_refused_and_left_alone() {
        let path = temp_path("other");
        std::fs::write(&path, b"not a flash").unwrap();
        let e = BoardFlash::open(&path).unwrap_err();
        assert!(matches!(e, StateError::NotAState { len: 11, .. }), "{e}");
        assert!(e.to_string().contains("not a forja-sim state file"), "{e}");
        let mut wrong = header();
        wrong[0] = b'F';
        wrong.resize(STATE_FILE_LEN, 0xFF);
        std::fs::write(&path, &wrong).unwrap();
        assert!(matches!(
            BoardFlash::open(&path),
            Err(StateError::NotAState { .. })
        ));
        assert_eq!(std::fs::read(&path).unwrap(), wrong);
        std::fs::remove_file(&path).unwrap();
    }
}
