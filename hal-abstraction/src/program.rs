//! Where programs are kept: the contract a program store fulfils, and the format rules every
//! store shares.
//!
//! A program arrives line by line (frame message 03: one line of at most [`MAX_LINE_LEN`]
//! bytes, indexed from 1, at most [`MAX_LINES`] lines) and is kept by a [`ProgramStore`]: a
//! driver over NOR flash (`forja-drivers`' `FlashProgramStore`), a store in RAM
//! ([`RamStore`]), or anything else that keeps the rules below. The application layer
//! (`forja-app`) runs the stored lines as a job.
//!
//! Context: thread. Flash-backed stores may block while they write.

use core::fmt;

/// The longest program line, bytes (frame message 03).
pub const MAX_LINE_LEN: usize = 39;

/// The most lines of a program (four digits in frame message 03).
pub const MAX_LINES: u16 = 9999;

/// What a [`ProgramStore`] knows of its program besides the lines: how many are stored, the
/// program's total, and the digest of the lines stored. Every store changes it by the same
/// rules: [`ProgramState::begin`], then [`ProgramState::next`] for each line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ProgramState {
    /// Lines stored.
    pub count: u16,
    /// The program's number of lines; 0 with no program.
    pub total: u16,
    /// The digest of the lines stored ([`digest_line`]): [`digest_start`] of the total before
    /// the first line, 0 with no program.
    pub digest: u32,
}

impl ProgramState {
    /// No program.
    pub const NONE: Self = Self {
        count: 0,
        total: 0,
        digest: 0,
    };

    /// A program of `total` lines begun, no line stored yet, in a store with room for
    /// `capacity` lines. Error: [`StoreError::Full`] when `total` is 0 or beyond the room (or
    /// [`MAX_LINES`]).
    pub fn begin(total: u16, capacity: u16) -> Result<Self, StoreError> {
        if total == 0 || total > capacity.min(MAX_LINES) {
            return Err(StoreError::Full);
        }
        Ok(Self {
            count: 0,
            total,
            digest: digest_start(total),
        })
    }

    /// The state once line `index` with `text` is stored, if a store with room for `capacity`
    /// lines may store it: a program is being stored (begun and not complete,
    /// [`StoreError::NoUpload`]), lines come strictly in order ([`StoreError::OutOfOrder`]),
    /// are at most [`MAX_LINE_LEN`] bytes ([`StoreError::TooLong`]) and fit
    /// ([`StoreError::Full`]); the errors come in that order. A store takes the new state once
    /// the line is written, so that a line refused or not written leaves it as it was.
    pub fn next(&self, capacity: u16, index: u16, text: &[u8]) -> Result<Self, StoreError> {
        if self.count >= self.total {
            return Err(StoreError::NoUpload);
        }
        let expected = self.count.saturating_add(1);
        if index != expected {
            return Err(StoreError::OutOfOrder {
                expected,
                got: index,
            });
        }
        if text.len() > MAX_LINE_LEN {
            return Err(StoreError::TooLong);
        }
        if index > capacity {
            return Err(StoreError::Full);
        }
        Ok(Self {
            count: index,
            total: self.total,
            digest: digest_line(self.digest, index, text),
        })
    }
}

/// Where programs are kept.
///
/// A program is uploaded as a whole: [`begin`] starts a program of `total` lines (removing the
/// old one), then lines are stored strictly in order: storing line `k` is accepted only when
/// `k` is one more than the number of lines stored and at most the total. The program is
/// *complete* ([`is_complete`]) once its last line is stored; only a complete program runs.
/// Stores that keep the program across a restart record completeness durably: after a power
/// cut in the middle of an upload the store reopens incomplete (or empty), never complete.
/// Every error leaves the store as it was.
///
/// Each store also keeps the program's [`digest`], a CRC-32 chained over the total and every
/// stored line ([`digest_start`], [`digest_line`]): two programs with the same digest are, for
/// any practical purpose, the same program (a resumed job checks it).
///
/// Context: thread. Flash-backed stores may block while they write.
///
/// [`begin`]: ProgramStore::begin
/// [`is_complete`]: ProgramStore::is_complete
/// [`digest`]: ProgramStore::digest
pub trait ProgramStore {
    /// The lines stored, the program's total and its digest.
    fn state(&self) -> ProgramState;

    /// The number of lines stored.
    fn len(&self) -> u16 {
        self.state().count
    }

    /// The number of lines of the program being stored or stored (as [`ProgramStore::begin`]
    /// gave it); 0 with no program.
    fn total(&self) -> u16 {
        self.state().total
    }

    /// The digest of the lines stored so far (see [`digest_line`]); [`digest_start`] of the
    /// total before the first line, 0 with no program.
    fn digest(&self) -> u32 {
        self.state().digest
    }

    /// Whether no line is stored.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether a program is stored whole: every line of its total.
    fn is_complete(&self) -> bool {
        !self.is_empty() && self.len() == self.total()
    }

    /// Remove the program and start one of `total` lines (1..=[`MAX_LINES`]).
    /// Errors: [`StoreError::Full`] when `total` is 0 or beyond the store's room,
    /// [`StoreError::Device`].
    fn begin(&mut self, total: u16) -> Result<(), StoreError>;

    /// Copy line `index` (1-based) into `buf`; returns its length.
    /// Errors: [`StoreError::NoSuchLine`], [`StoreError::Device`].
    fn read(&mut self, index: u16, buf: &mut [u8; MAX_LINE_LEN]) -> Result<usize, StoreError>;

    /// Store line `index`, which must be `len() + 1` and at most `total()`.
    /// Errors: [`StoreError::NoUpload`] when no program is being stored (none begun, or the
    /// program is complete), [`StoreError::OutOfOrder`], [`StoreError::TooLong`],
    /// [`StoreError::Full`], [`StoreError::Device`].
    fn store(&mut self, index: u16, text: &[u8]) -> Result<(), StoreError>;

    /// Remove every line. Errors: [`StoreError::Device`].
    fn clear(&mut self) -> Result<(), StoreError>;
}

impl<T: ProgramStore + ?Sized> ProgramStore for &mut T {
    fn state(&self) -> ProgramState {
        T::state(self)
    }
    fn begin(&mut self, total: u16) -> Result<(), StoreError> {
        T::begin(self, total)
    }
    fn read(&mut self, index: u16, buf: &mut [u8; MAX_LINE_LEN]) -> Result<usize, StoreError> {
        T::read(self, index, buf)
    }
    fn store(&mut self, index: u16, text: &[u8]) -> Result<(), StoreError> {
        T::store(self, index, text)
    }
    fn clear(&mut self) -> Result<(), StoreError> {
        T::clear(self)
    }
}

/// CRC-32 (IEEE 802.3, reflected, as zlib's `crc32`) continued from `crc` over `bytes`;
/// `crc32_update(0, bytes)` is the CRC-32 of `bytes`. Bitwise: the stores check lines of at
/// most a few hundred bytes, which do not need a table.
pub fn crc32_update(crc: u32, bytes: &[u8]) -> u32 {
    let mut crc = !crc;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            let mask = (crc & 1).wrapping_neg();
            crc = (crc >> 1) ^ (0xEDB8_8320 & mask);
        }
    }
    !crc
}

/// The digest of a program of `total` lines before its first line.
pub fn digest_start(total: u16) -> u32 {
    crc32_update(0, &total.to_le_bytes())
}

/// The digest after line `index` with `text`, from the digest `prev` of the lines before it:
/// a CRC-32 continued over the index (little-endian), the length and the text.
pub fn digest_line(prev: u32, index: u16, text: &[u8]) -> u32 {
    let len = text.len().min(MAX_LINE_LEN) as u8;
    let crc = crc32_update(prev, &index.to_le_bytes());
    let crc = crc32_update(crc, &[len]);
    crc32_update(crc, text.get(..usize::from(len)).unwrap_or(&[]))
}

/// A program store in RAM with room for `L` lines (at most [`MAX_LINES`] are ever accepted).
pub struct RamStore<const L: usize> {
    lines: [[u8; MAX_LINE_LEN]; L],
    lens: [u8; L],
    state: ProgramState,
}

impl<const L: usize> Default for RamStore<L> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const L: usize> RamStore<L> {
    /// An empty store.
    pub const fn new() -> Self {
        Self {
            lines: [[0; MAX_LINE_LEN]; L],
            lens: [0; L],
            state: ProgramState::NONE,
        }
    }
}

impl<const L: usize> ProgramStore for RamStore<L> {
    fn state(&self) -> ProgramState {
        self.state
    }

    fn begin(&mut self, total: u16) -> Result<(), StoreError> {
        self.state = ProgramState::begin(total, Self::capacity())?;
        Ok(())
    }

    fn read(&mut self, index: u16, buf: &mut [u8; MAX_LINE_LEN]) -> Result<usize, StoreError> {
        if index == 0 || index > self.state.count {
            return Err(StoreError::NoSuchLine);
        }
        let k = usize::from(index - 1);
        let (Some(line), Some(&len)) = (self.lines.get(k), self.lens.get(k)) else {
            return Err(StoreError::NoSuchLine);
        };
        *buf = *line;
        Ok(usize::from(len))
    }

    fn store(&mut self, index: u16, text: &[u8]) -> Result<(), StoreError> {
        let next = self.state.next(Self::capacity(), index, text)?;
        let k = usize::from(self.state.count);
        let (Some(line), Some(len)) = (self.lines.get_mut(k), self.lens.get_mut(k)) else {
            return Err(StoreError::Full);
        };
        line.fill(0);
        if let Some(dst) = line.get_mut(..text.len()) {
            dst.copy_from_slice(text);
        }
        *len = text.len() as u8;
        self.state = next;
        Ok(())
    }

    fn clear(&mut self) -> Result<(), StoreError> {
        self.state = ProgramState::NONE;
        Ok(())
    }
}

impl<const L: usize> RamStore<L> {
    fn capacity() -> u16 {
        u16::try_from(L).unwrap_or(MAX_LINES).min(MAX_LINES)
    }
}

/// A program store refused an operation; the store is left as it was.
/// Exhaustive on purpose: every error has a wire code in the application layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StoreError {
    /// Line `got` was offered but line `expected` (the one after the last stored) is next.
    OutOfOrder {
        /// The index the store expects.
        expected: u16,
        /// The index offered.
        got: u16,
    },
    /// The store is full.
    Full,
    /// The line is longer than [`MAX_LINE_LEN`] bytes.
    TooLong,
    /// No line with this index is stored.
    NoSuchLine,
    /// The storage device failed.
    Device,
    /// A line other than line 1 while no upload is in progress: the store holds a complete
    /// program or none, or the upload was interrupted (a restart, another host): a new upload
    /// starts with line 1.
    NoUpload,
}

impl fmt::Display for StoreError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::OutOfOrder { expected, got } => {
                write!(f, "line-order {got:04} (expected {expected:04})")
            }
            Self::Full => f.write_str("store-full"),
            Self::TooLong => f.write_str("line-too-long"),
            Self::NoSuchLine => f.write_str("no-such-line"),
            Self::Device => f.write_str("store-device"),
            Self::NoUpload => f.write_str("no-upload"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn ram_store_is_strictly_ordered_and_bounded() {
        let mut s = RamStore::<3>::new();
        s.begin(3).expect("begin");
        assert_eq!(
            s.store(2, b"G1 X1"),
            Err(StoreError::OutOfOrder {
                expected: 1,
                got: 2
            })
        );
        assert_eq!(s.len(), 0);
        s.store(1, b"G1 X1").expect("1");
        s.store(2, b"G1 X2").expect("2");
        assert_eq!(
            s.store(2, b"G1 X9"),
            Err(StoreError::OutOfOrder {
                expected: 3,
                got: 2
            })
        );
        assert_eq!(s.store(3, &[b'X'; 40]), Err(StoreError::TooLong));
        s.store(3, &[b'X'; 39]).expect("39 bytes fit");
        assert!(s.is_complete());
        assert_eq!(s.store(4, b"G1"), Err(StoreError::NoUpload));
        assert_eq!(s.len(), 3);
        let mut buf = [0; MAX_LINE_LEN];
        assert_eq!(s.read(2, &mut buf), Ok(5));
        assert_eq!(&buf[..5], b"G1 X2");
        assert_eq!(s.read(4, &mut buf), Err(StoreError::NoSuchLine));
        assert_eq!(s.read(0, &mut buf), Err(StoreError::NoSuchLine));
        s.clear().expect("clear");
        assert!(s.is_empty());
    }
}
