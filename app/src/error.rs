//! Errors of the application layer and their stable wire codes: the program store's, the file
//! store's and the job's. The kernel's own errors (`100..=155`) are in `forja_motion::error`.
//!
//! | code | error | meaning |
//! |---|---|---|
//! | 170 | [`StoreError::OutOfOrder`] | a program line is not the one after the last stored |
//! | 171 | [`StoreError::Full`] | the program store has no room |
//! | 172 | [`StoreError::TooLong`] | a program line is longer than 39 bytes |
//! | 173 | [`StoreError::NoSuchLine`] | a line index outside the stored program |
//! | 174 | [`StoreError::Device`] | the storage device failed |
//! | 175 | [`StoreError::NoUpload`] | a program line that continues no upload in progress (send line 1 first) |
//! | 176 | [`FileError::NotFound`] | no file of that name |
//! | 177 | [`FileError::Full`] | the file store has no room for the bytes, or for one more file |
//! | 178 | [`FileError::BadName`] | a file name outside the rules of [`FileName`](forja_hal_abstraction::files::FileName) |
//! | 179 | [`FileError::Busy`] | a file is being written already |
//! | 180 | [`JobError::Empty`] | start asked with no program stored |
//! | 181 | [`JobError::NotRunning`] | pause or resume with no job running |
//! | 182 | [`JobError::Busy`] | the action needs the job stopped (load, rewind, jog) |
//! | 183 | [`JobError::Line`] | a stored line failed: the job stopped at it (see the inner error) |
//! | 184 | [`JobError::Syntax`] | a stored line does not parse as G-code, or cannot be read |
//! | 185 | [`JobError::Incomplete`] | start asked while the program's upload is not complete |
//! | 186 | [`JobError::NothingToResume`] | resume (`M1000`) with no interrupted job recorded |
//! | 187 | [`JobError::NotHomed`] | resume (`M1000`) before the machine is homed |
//! | 188 | [`JobError::ProgramChanged`] | resume (`M1000`) of a job whose program has changed since |
//! | 189 | [`JobError::NoFileSelected`] | a file command (`M24`, `M26`) with no file selected (`M23`) |
//! | 199 | [`FileError::NotWriting`] | no file is being written |
//! | 220 | [`FileError::Device`] | the file store's device (the SD card) failed |
//!
//! Codes not listed are reserved. A code is never reused for a different meaning. The program
//! store's and the file store's errors are contracts of `forja-hal-abstraction`
//! ([`StoreError`], [`FileError`]), which knows no wire: [`StoreRefusal`] and [`FileRefusal`]
//! give them their codes (a device's failure in the drivers' range, 200–299).

use core::fmt;

use forja_hal_abstraction::files::FileError;
use forja_hal_abstraction::program::StoreError;
use forja_motion::CommandError;
use forja_protocol::error::WireError;

/// A program store's error as it goes on the wire, with its code and name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StoreRefusal(pub StoreError);

impl WireError for StoreRefusal {
    fn code(&self) -> u16 {
        match self.0 {
            StoreError::OutOfOrder { .. } => 170,
            StoreError::Full => 171,
            StoreError::TooLong => 172,
            StoreError::NoSuchLine => 173,
            StoreError::Device => 174,
            StoreError::NoUpload => 175,
        }
    }
    fn name(&self) -> &'static str {
        match self.0 {
            StoreError::OutOfOrder { .. } => "line-order",
            StoreError::Full => "store-full",
            StoreError::TooLong => "line-too-long",
            StoreError::NoSuchLine => "no-such-line",
            StoreError::Device => "store-device",
            StoreError::NoUpload => "no-upload",
        }
    }
}

/// A file store's error as it goes on the wire, with its code and name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FileRefusal(pub FileError);

impl WireError for FileRefusal {
    fn code(&self) -> u16 {
        match self.0 {
            FileError::NotFound => 176,
            FileError::Full => 177,
            FileError::BadName => 178,
            FileError::Busy => 179,
            FileError::NotWriting => 199,
            FileError::Device => 220,
        }
    }
    fn name(&self) -> &'static str {
        match self.0 {
            FileError::NotFound => "no-such-file",
            FileError::Full => "files-full",
            FileError::BadName => "bad-file-name",
            FileError::Busy => "file-busy",
            FileError::NotWriting => "not-writing",
            FileError::Device => "file-device",
        }
    }
}

/// A job action that cannot be done now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum JobError {
    /// No program is stored.
    Empty,
    /// Pause or resume with no job running.
    NotRunning,
    /// The action needs the job stopped.
    Busy,
    /// A stored line does not parse (or cannot be read); the job stopped at it.
    Syntax {
        /// The 1-based program line.
        line: u16,
    },
    /// A stored line failed; the job stopped at `line`.
    Line {
        /// The 1-based program line.
        line: u16,
        /// What was wrong with it.
        error: CommandError,
    },
    /// The stored program's upload is not complete: `stored` of its `total` lines arrived.
    Incomplete {
        /// Lines stored.
        stored: u16,
        /// Lines the program has.
        total: u16,
    },
    /// Resume (`M1000`) with no interrupted job recorded.
    NothingToResume,
    /// Resume (`M1000`) before every axis with a homing cycle is homed.
    NotHomed,
    /// Resume (`M1000`) of a job whose program is no longer the stored one.
    ProgramChanged,
    /// A file command (`M24`, `M26`) with no file selected.
    NoFileSelected,
}

impl JobError {
    /// The stable wire code (see the module table).
    pub const fn code(&self) -> u16 {
        match self {
            Self::Empty => 180,
            Self::NotRunning => 181,
            Self::Busy => 182,
            Self::Line { .. } => 183,
            Self::Syntax { .. } => 184,
            Self::Incomplete { .. } => 185,
            Self::NothingToResume => 186,
            Self::NotHomed => 187,
            Self::ProgramChanged => 188,
            Self::NoFileSelected => 189,
        }
    }
}

impl fmt::Display for JobError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Empty => f.write_str("job: no program stored"),
            Self::NotRunning => f.write_str("job: not running"),
            Self::Busy => f.write_str("job: stop it first"),
            Self::Line { line, error } => write!(f, "job: line {line:04}: {error}"),
            Self::Syntax { line } => write!(f, "job: line {line:04}: not G-code"),
            Self::Incomplete { stored, total } => {
                write!(
                    f,
                    "job: program incomplete ({stored} of {total} lines stored)"
                )
            }
            Self::NothingToResume => f.write_str("job: nothing to resume"),
            Self::NotHomed => f.write_str("job: home the machine first"),
            Self::ProgramChanged => f.write_str("job: the program changed since it ran"),
            Self::NoFileSelected => f.write_str("job: no file selected"),
        }
    }
}

impl WireError for JobError {
    fn code(&self) -> u16 {
        JobError::code(self)
    }
    fn name(&self) -> &'static str {
        match self {
            Self::Empty => "job-empty",
            Self::NotRunning => "job-not-running",
            Self::Busy => "job-busy",
            Self::Line { .. } => "job-line",
            Self::Syntax { .. } => "job-syntax",
            Self::Incomplete { .. } => "program-incomplete",
            Self::NothingToResume => "no-resume",
            Self::NotHomed => "not-homed",
            Self::ProgramChanged => "program-changed",
            Self::NoFileSelected => "no-file-selected",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_in_range_and_distinct() {
        let codes = [
            StoreRefusal(StoreError::OutOfOrder {
                expected: 1,
                got: 2,
            })
            .code(),
            StoreRefusal(StoreError::Full).code(),
            StoreRefusal(StoreError::TooLong).code(),
            StoreRefusal(StoreError::NoSuchLine).code(),
            StoreRefusal(StoreError::Device).code(),
            StoreRefusal(StoreError::NoUpload).code(),
            JobError::Empty.code(),
            JobError::NotRunning.code(),
            JobError::Busy.code(),
            JobError::Line {
                line: 1,
                error: CommandError::Locked,
            }
            .code(),
            JobError::Syntax { line: 1 }.code(),
            JobError::Incomplete {
                stored: 1,
                total: 2,
            }
            .code(),
            JobError::NothingToResume.code(),
            JobError::NotHomed.code(),
            JobError::ProgramChanged.code(),
            JobError::NoFileSelected.code(),
            FileRefusal(FileError::NotFound).code(),
            FileRefusal(FileError::Full).code(),
            FileRefusal(FileError::BadName).code(),
            FileRefusal(FileError::Busy).code(),
            FileRefusal(FileError::NotWriting).code(),
        ];
        for (i, c) in codes.iter().enumerate() {
            assert!((170..=199).contains(c), "{c}");
            assert!(!codes[..i].contains(c), "duplicate {c}");
        }
        // A device's failure is in the drivers' range, apart from their own codes.
        let device = FileRefusal(FileError::Device).code();
        assert!((200..=299).contains(&device) && !(210..=215).contains(&device));
        assert!(!(230..=238).contains(&device));
    }
}
