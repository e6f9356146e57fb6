//! A [`ProgramStore`] over any [`RecordStorage`]: the uploaded program survives a restart.
//!
//! One record per line, the line's text as it is (at most 39 bytes), under record key
//! [`LINE_RECORDS`]` + index`; one header record under [`HEADER_RECORD`] with the number of
//! lines, a `postcard` `u16`. Storing line `k` writes the line, then the header: a power cut
//! between the two leaves the program as it was before line `k`. [`ProgramStore::clear`]
//! only writes a header of 0; the old line records are overwritten by the next program.

use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::{Error as _, ErrorKind};

use crate::error::StoreError;
use crate::job::{MAX_LINE_LEN, MAX_LINES, ProgramStore, check_next_line};

/// The record key of the header (the number of lines).
pub const HEADER_RECORD: u16 = 0x1000;

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
    count: u16,
    capacity: u16,
}

impl<S: RecordStorage> RecordProgramStore<S> {
    /// Open the program kept in `storage` (none when it has no header), with room for
    /// `capacity` lines (at most 9999).
    ///
    /// Errors: [`StoreError::Device`] when the header cannot be read or decoded.
    pub fn open(mut storage: S, capacity: u16) -> Result<Self, StoreError> {
        let mut buf = [0u8; 4];
        let count = match storage
            .read(HEADER_RECORD, &mut buf)
            .map_err(|e| store_error(e.kind()))?
        {
            Some(len) => postcard::from_bytes::<u16>(buf.get(..len).unwrap_or(&[]))
                .map_err(|_| StoreError::Device)?,
            None => 0,
        };
        let capacity = capacity.min(MAX_LINES);
        Ok(Self {
            storage,
            count: count.min(capacity),
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

    fn write_header(&mut self, count: u16) -> Result<(), StoreError> {
        let mut buf = [0u8; 4];
        let bytes = postcard::to_slice(&count, &mut buf).map_err(|_| StoreError::Device)?;
        self.storage
            .write(HEADER_RECORD, bytes)
            .map_err(|e| store_error(e.kind()))
    }
}

impl<S: RecordStorage> ProgramStore for RecordProgramStore<S> {
    fn len(&self) -> u16 {
        self.count
    }

    fn read(&mut self, index: u16, buf: &mut [u8; MAX_LINE_LEN]) -> Result<usize, StoreError> {
        if index == 0 || index > self.count {
            return Err(StoreError::NoSuchLine);
        }
        match self.storage.read(LINE_RECORDS + index, buf) {
            Ok(Some(len)) => Ok(len),
            Ok(None) => Err(StoreError::NoSuchLine),
            Err(e) => Err(store_error(e.kind())),
        }
    }

    fn store(&mut self, index: u16, text: &[u8]) -> Result<(), StoreError> {
        check_next_line(self.count, self.capacity, index, text.len())?;
        self.storage
            .write(LINE_RECORDS + index, text)
            .map_err(|e| store_error(e.kind()))?;
        self.write_header(index)?;
        self.count = index;
        Ok(())
    }

    fn clear(&mut self) -> Result<(), StoreError> {
        if self.count == 0 {
            return Ok(());
        }
        self.write_header(0)?;
        self.count = 0;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::settings::tests::VecStorage;
    use super::*;

    #[test]
    fn lines_survive_a_reopen_and_errors_change_nothing() {
        let mut s = RecordProgramStore::open(VecStorage::default(), 3).unwrap();
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
        assert_eq!(s.store(4, b"G1 X4"), Err(StoreError::Full));
        let mut s = RecordProgramStore::open(s.into_inner(), 3).unwrap();
        assert_eq!(s.len(), 3);
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
