//! A [`ProgramStore`] over any [`RecordStorage`]: the uploaded program survives a restart.
//!
//! One record per line, the line's text as it is (at most 39 bytes), under record key
//! [`LINE_RECORDS`]` + index`; one header record under [`HEADER_RECORD`], 8 bytes
//! little-endian: the number of lines stored (`u16`), the program's total (`u16`) and the
//! digest of the lines stored ([`forja_hal_abstraction::program::digest_line`], `u32`). The program is complete
//! when the two counts are equal.
//!
//! Storing line `k` writes the line, then the header: a power cut between the two leaves the
//! program as it was before line `k`. So the header says "complete" only once the last line is
//! in storage, and a cut in the middle of an upload leaves an incomplete program, which never
//! runs. [`ProgramStore::begin`] writes a header of 0 lines of the new total,
//! [`ProgramStore::clear`] one of 0 of 0; the old line records are overwritten by the next
//! program. A header of another length (the one-count header of earlier versions) opens as no
//! program: whether that program was complete cannot be known.

use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::{Error as _, ErrorKind};

use forja_hal_abstraction::program::StoreError;
use forja_hal_abstraction::program::{MAX_LINE_LEN, MAX_LINES, ProgramState, ProgramStore};

/// The record key of the header (lines stored, total, digest).
pub const HEADER_RECORD: u16 = 0x1000;

/// Bytes of the header record.
const HEADER_LEN: usize = 8;

/// Line `k` (1-based) is stored under `LINE_RECORDS + k`, up to `0x1000 + 9999`.
pub const LINE_RECORDS: u16 = 0x1000;

fn store_error(kind: ErrorKind) -> StoreError {
    match kind {
        ErrorKind::Full => StoreError::Full,
        _ => StoreError::Device,
    }
}

/// A program kept in a [`RecordStorage`], with room for at most `capacity` lines.
///
/// Context: thread. Every operation blocks as the storage does (a flash write may erase a
/// page): load a program while the machine is at rest.
#[derive(Debug)]
pub struct RecordProgramStore<S> {
    storage: S,
    state: ProgramState,
    capacity: u16,
}

impl<S: RecordStorage> RecordProgramStore<S> {
    /// Open the program kept in `storage` (none when it has no header, or a header of
    /// another format), with room for `capacity` lines (at most 9999). A program whose header
    /// does not fit `capacity` opens as none.
    ///
    /// Errors: [`StoreError::Device`] when the header cannot be read.
    pub fn open(mut storage: S, capacity: u16) -> Result<Self, StoreError> {
        let mut buf = [0u8; 16];
        let header = match storage
            .read(HEADER_RECORD, &mut buf)
            .map_err(|e| store_error(e.kind()))?
        {
            Some(HEADER_LEN) => decode_header(&buf),
            _ => None,
        };
        let capacity = capacity.min(MAX_LINES);
        let state = header
            .filter(|h| h.count <= h.total && h.total <= capacity)
            .unwrap_or(ProgramState::NONE);
        Ok(Self {
            storage,
            state,
            capacity,
        })
    }

    /// The storage.
    pub fn storage_mut(&mut self) -> &mut S {
        &mut self.storage
    }

    /// Give the storage back.
    pub fn into_inner(self) -> S {
        self.storage
    }

    /// Write `state` as the header, then take it.
    fn write_header(&mut self, state: ProgramState) -> Result<(), StoreError> {
        let mut buf = [0u8; HEADER_LEN];
        buf[..2].copy_from_slice(&state.count.to_le_bytes());
        buf[2..4].copy_from_slice(&state.total.to_le_bytes());
        buf[4..].copy_from_slice(&state.digest.to_le_bytes());
        self.storage
            .write(HEADER_RECORD, &buf)
            .map_err(|e| store_error(e.kind()))?;
        self.state = state;
        Ok(())
    }
}

/// The state an 8-byte header holds: lines stored, total and digest.
fn decode_header(buf: &[u8]) -> Option<ProgramState> {
    Some(ProgramState {
        count: u16::from_le_bytes(buf.get(..2)?.try_into().ok()?),
        total: u16::from_le_bytes(buf.get(2..4)?.try_into().ok()?),
        digest: u32::from_le_bytes(buf.get(4..HEADER_LEN)?.try_into().ok()?),
    })
}

impl<S: RecordStorage> ProgramStore for RecordProgramStore<S> {
    fn state(&self) -> ProgramState {
        self.state
    }

    fn begin(&mut self, total: u16) -> Result<(), StoreError> {
        self.write_header(ProgramState::begin(total, self.capacity)?)
    }

    fn read(&mut self, index: u16, buf: &mut [u8; MAX_LINE_LEN]) -> Result<usize, StoreError> {
        if index == 0 || index > self.state.count {
            return Err(StoreError::NoSuchLine);
        }
        match self.storage.read(LINE_RECORDS + index, buf) {
            Ok(Some(len)) => Ok(len),
            Ok(None) => Err(StoreError::NoSuchLine),
            Err(e) => Err(store_error(e.kind())),
        }
    }

    fn store(&mut self, index: u16, text: &[u8]) -> Result<(), StoreError> {
        let next = self.state.next(self.capacity, index, text)?;
        self.storage
            .write(LINE_RECORDS + index, text)
            .map_err(|e| store_error(e.kind()))?;
        self.write_header(next)
    }

    fn clear(&mut self) -> Result<(), StoreError> {
        if self.state == ProgramState::NONE {
            return Ok(());
        }
        self.write_header(ProgramState::NONE)
    }
}

/// The record key, in the controller's settings storage, of the resume record: the progress
/// of the last job, for power-loss recovery (`M1000`). See [`ResumeRecord`].
pub const RESUME_RECORD: u16 = 0x0300;

/// The progress of a job, kept for power-loss recovery: which program ran (its digest and
/// total) and how many of its lines had certainly finished. 8 bytes little-endian: digest
/// (`u32`), total (`u16`), lines done (`u16`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ResumeRecord {
    /// The program's digest ([`ProgramStore::digest`]).
    pub digest: u32,
    /// The program's total number of lines.
    pub total: u16,
    /// Lines `1..=done` had run, their motion finished; 0 when none had.
    pub done: u16,
}

impl ResumeRecord {
    /// Bytes of the record.
    pub const LEN: usize = 8;

    /// The record's bytes.
    pub fn encode(&self) -> [u8; Self::LEN] {
        let mut buf = [0u8; Self::LEN];
        buf[..4].copy_from_slice(&self.digest.to_le_bytes());
        buf[4..6].copy_from_slice(&self.total.to_le_bytes());
        buf[6..].copy_from_slice(&self.done.to_le_bytes());
        buf
    }

    /// A record from its bytes; `None` for bytes of another length or a record that cannot
    /// be one (more lines done than the program has).
    pub fn decode(bytes: &[u8]) -> Option<Self> {
        if bytes.len() != Self::LEN {
            return None;
        }
        let r = Self {
            digest: u32::from_le_bytes(bytes.get(..4)?.try_into().ok()?),
            total: u16::from_le_bytes(bytes.get(4..6)?.try_into().ok()?),
            done: u16::from_le_bytes(bytes.get(6..8)?.try_into().ok()?),
        };
        (r.done <= r.total).then_some(r)
    }
}

#[cfg(test)]
mod tests {
    use super::super::settings::tests::VecStorage;
    use super::*;

    #[test]
    fn lines_survive_a_reopen_and_errors_change_nothing() {
        let mut s = RecordProgramStore::open(VecStorage::default(), 3).unwrap();
        assert_eq!(s.store(1, b"G1 X1"), Err(StoreError::NoUpload));
        assert_eq!(s.begin(4), Err(StoreError::Full));
        s.begin(3).unwrap();
        assert_eq!(
            s.store(2, b"G1 X1"),
            Err(StoreError::OutOfOrder {
                expected: 1,
                got: 2
            })
        );
        s.store(1, b"G1 X1").unwrap();
        s.store(2, b"G1 X2").unwrap();
        assert_eq!(s.store(3, &[b'X'; 40]), Err(StoreError::TooLong));
        s.store(3, b"G1 X3").unwrap();
        assert_eq!(s.store(4, b"G1 X4"), Err(StoreError::NoUpload));
        let digest = s.digest();
        let mut s = RecordProgramStore::open(s.into_inner(), 3).unwrap();
        assert_eq!(s.len(), 3);
        assert!(s.is_complete());
        assert_eq!(s.digest(), digest);
        let mut buf = [0; MAX_LINE_LEN];
        assert_eq!(s.read(2, &mut buf), Ok(5));
        assert_eq!(&buf[..5], b"G1 X2");
        assert_eq!(s.read(4, &mut buf), Err(StoreError::NoSuchLine));
        s.storage_mut().fail = true;
        assert_eq!(s.clear(), Err(StoreError::Device));
        assert_eq!(s.len(), 3);
        s.storage_mut().fail = false;
        s.clear().unwrap();
        let s = RecordProgramStore::open(s.into_inner(), 3).unwrap();
        assert!(s.is_empty());
    }
}

#[cfg(test)]
mod completeness {
    use super::super::settings::tests::VecStorage;
    use super::*;

    /// A power cut in the middle of an upload (the storage refuses every write from then on,
    /// and the store is reopened) leaves an incomplete program, never a complete one; a header
    /// of the earlier format opens as no program.
    #[test]
    fn an_interrupted_upload_reopens_incomplete() {
        let mut s = RecordProgramStore::open(VecStorage::default(), 10).unwrap();
        s.begin(10).unwrap();
        for k in 1..=4u16 {
            s.store(k, b"G1 X1").unwrap();
        }
        s.storage_mut().fail = true;
        assert_eq!(s.store(5, b"G1 X5"), Err(StoreError::Device));
        let mut storage = s.into_inner();
        storage.fail = false;
        let mut s = RecordProgramStore::open(storage, 10).unwrap();
        assert_eq!((s.len(), s.total(), s.is_complete()), (4, 10, false));
        // Only line 5 continues it; nothing completes it but its last line.
        assert_eq!(
            s.store(6, b"G1 X6"),
            Err(StoreError::OutOfOrder {
                expected: 5,
                got: 6
            })
        );
        for k in 5..=9u16 {
            s.store(k, b"G1 X1").unwrap();
            assert!(!s.is_complete());
        }
        s.store(10, b"G1 X1").unwrap();
        assert!(s.is_complete());

        let mut legacy = VecStorage::default();
        legacy.records.push((HEADER_RECORD, [3u8].to_vec()));
        legacy.records.push((LINE_RECORDS + 1, b"G1 X1".to_vec()));
        let s = RecordProgramStore::open(legacy, 10).unwrap();
        assert!(s.is_empty() && !s.is_complete());
    }
}
