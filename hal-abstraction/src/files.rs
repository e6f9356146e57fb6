//! Named files: the contract of a file store (an SD card, a directory, a region of RAM), and a
//! store in RAM.
//!
//! A [`FileStore`] keeps files by [`FileName`], several at once, and writes one at a time: a
//! file is [created](FileStore::create), [appended](FileStore::append) to and
//! [finished](FileStore::finish), and only a finished file is seen. The application layer
//! (`forja-app`) serves Marlin's SD-card commands (`M20`–`M32`) from it: printer hosts upload
//! jobs "to the SD card" and print them from there.
//!
//! # Contract
//!
//! - **Context**: thread, never an interrupt. Every method may block on its medium (a flash
//!   erase, an SD card's busy time); reads should take about as long as the bytes asked for,
//!   since a running job reads its file a few hundred bytes at a time while the machine moves.
//!   Writes ([`FileStore::create`], [`FileStore::append`], [`FileStore::finish`],
//!   [`FileStore::remove`]) may hold the whole chip up (a NOR flash erase runs with interrupts
//!   off on some parts): the application writes only while the machine is at rest.
//! - **A stored thing is complete, or it is absent.** A file being written is not seen by
//!   [`FileStore::file`], [`FileStore::size`] or [`FileStore::read`] until it is finished;
//!   finishing makes it seen whole, replacing a file of the same name at once. A power cut, a
//!   restart or [`FileStore::abandon`] at any point leaves the old file (or none), never part
//!   of the new one.
//! - **One write at a time.** [`FileStore::create`] while a file is being written is
//!   [`FileError::Busy`]; the caller finishes or abandons it first. A store forgets a write in
//!   progress when it restarts.
//! - **Names** follow [`FileName`]'s rules, the same for every store, and are compared
//!   without regard to the case of letters, as on a FAT card: `part.gco` and `PART.GCO` are
//!   one file, which keeps the spelling of its last write.
//! - **Lines** are the caller's business: a store keeps bytes, of any content and any length
//!   its room allows.
//! - **Errors** are one [`FileError`] for every store. An operation that fails changes
//!   nothing, except where its documentation says otherwise.
//!
//! The module `conformance` (feature `conformance`) checks a store against this contract in
//! its tests.

use core::fmt;

#[cfg(any(test, feature = "conformance"))]
pub mod conformance;

/// The longest file name, bytes.
pub const MAX_NAME_LEN: usize = 63;

/// Bytes a name may not hold besides spaces and control bytes: path separators, the
/// characters a FAT card refuses, and the G-code comment mark (a name with `;` could not be
/// named on a G-code line).
const FORBIDDEN: &[u8] = b"/\\\"*:<>?|;";

/// A file's name: 1 to [`MAX_NAME_LEN`] bytes of printable ASCII, without spaces, without
/// `/ \ " * : < > ? | ;`, not starting with `.`. Marlin's 8.3 names (`CUBE~1.GCO`) are names,
/// and so are long ones (`bracket_v2.gcode`).
///
/// Two names are equal when they differ only in the case of letters (as on a FAT card); a
/// name keeps its spelling.
#[derive(Clone, Copy)]
pub struct FileName {
    bytes: [u8; MAX_NAME_LEN],
    len: u8,
}

impl FileName {
    /// `name` if it follows the rules. Error: [`FileError::BadName`].
    pub fn new(name: &[u8]) -> Result<Self, FileError> {
        let allowed = |b: &u8| b.is_ascii_graphic() && !FORBIDDEN.contains(b);
        let valid = !name.is_empty()
            && name.len() <= MAX_NAME_LEN
            && name.first() != Some(&b'.')
            && name.iter().all(allowed);
        if !valid {
            return Err(FileError::BadName);
        }
        let mut bytes = [0; MAX_NAME_LEN];
        if let Some(dst) = bytes.get_mut(..name.len()) {
            dst.copy_from_slice(name);
        }
        Ok(Self {
            bytes,
            len: name.len() as u8,
        })
    }

    /// The name's bytes, as spelled.
    pub fn as_bytes(&self) -> &[u8] {
        self.bytes.get(..usize::from(self.len)).unwrap_or(&[])
    }

    /// The name, as spelled.
    pub fn as_str(&self) -> &str {
        core::str::from_utf8(self.as_bytes()).unwrap_or("")
    }
}

impl PartialEq for FileName {
    fn eq(&self, other: &Self) -> bool {
        self.as_bytes().eq_ignore_ascii_case(other.as_bytes())
    }
}

impl Eq for FileName {}

impl fmt::Debug for FileName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self.as_str(), f)
    }
}

impl fmt::Display for FileName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A finished file: its name and its size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FileInfo {
    /// The file's name.
    pub name: FileName,
    /// Its size, bytes.
    pub size: u32,
}

/// Where named files are kept. See the [module documentation](self) for the contract every
/// method keeps.
///
/// Object-safe: the application holds a board's store as `&mut dyn FileStore`.
pub trait FileStore {
    /// The finished file at `index` (from 0) in the store's order, `None` past the last. The
    /// order stays the same while no file is finished or removed.
    ///
    /// Errors: [`FileError::Device`].
    fn file(&mut self, index: usize) -> Result<Option<FileInfo>, FileError>;

    /// The size of the finished file `name`, bytes.
    ///
    /// Errors: [`FileError::NotFound`], [`FileError::Device`].
    fn size(&mut self, name: &FileName) -> Result<u32, FileError>;

    /// Copy the bytes of the finished file `name` from byte `offset` on into `buf`, as many as
    /// fit and are left; returns how many (0 at or past the end).
    ///
    /// Errors: [`FileError::NotFound`], [`FileError::Device`].
    fn read(&mut self, name: &FileName, offset: u32, buf: &mut [u8]) -> Result<usize, FileError>;

    /// Remove the finished file `name`. A write in progress under that name goes on.
    ///
    /// Errors: [`FileError::NotFound`], [`FileError::Device`].
    fn remove(&mut self, name: &FileName) -> Result<(), FileError>;

    /// Begin writing the file `name`, empty. It is not seen until [`FileStore::finish`]; a
    /// finished file of the same name is seen, unchanged, until then.
    ///
    /// Errors: [`FileError::Busy`] while another file is being written, [`FileError::Full`]
    /// when the store cannot hold one more file, [`FileError::Device`].
    fn create(&mut self, name: &FileName) -> Result<(), FileError>;

    /// Add `bytes` at the end of the file being written.
    ///
    /// Errors: [`FileError::NotWriting`], [`FileError::Full`], [`FileError::Device`]; the write
    /// is then as it was before the call (the caller may [abandon](FileStore::abandon) it).
    fn append(&mut self, bytes: &[u8]) -> Result<(), FileError>;

    /// Finish the file being written: it is seen from now on, whole, in place of a file of the
    /// same name. Atomic: a power cut leaves the old file or the new one.
    ///
    /// Errors: [`FileError::NotWriting`], [`FileError::Full`], [`FileError::Device`]; the write
    /// is then as it was before the call.
    fn finish(&mut self) -> Result<(), FileError>;

    /// Drop the file being written, if any: the store is as it was before
    /// [`FileStore::create`].
    ///
    /// Errors: [`FileError::Device`] (what was written is not seen, and is forgotten at the
    /// next start at the latest).
    fn abandon(&mut self) -> Result<(), FileError>;

    /// The name of the file being written, if one is.
    fn writing(&self) -> Option<FileName>;

    /// Whether [`FileStore::create`] takes every [`FileName`] (`true`, the default), or only
    /// the 8.3 ones (`PART.GCO`), refusing the others with [`FileError::BadName`]: a FAT card
    /// whose driver writes no long names. Hosts learn it from `Cap:LFN_WRITE`.
    fn writes_long_names(&self) -> bool {
        true
    }

    /// Make the medium ready (`M21`): an SD card initialised and its volume mounted. A store
    /// that is always ready (the default) answers `Ok`; one that mounts lazily mounts here, so
    /// that a missing card is told at once.
    ///
    /// Errors: [`FileError::Device`] (no card, a volume it cannot read).
    fn mount(&mut self) -> Result<(), FileError> {
        Ok(())
    }

    /// Let the medium go (`M22`): a write in progress is abandoned, nothing is held open, and
    /// the card may be taken out; the next operation, or [`FileStore::mount`], mounts it again.
    /// The default abandons the write in progress.
    fn release(&mut self) {
        let _ = self.abandon();
    }
}

impl<T: FileStore + ?Sized> FileStore for &mut T {
    fn file(&mut self, index: usize) -> Result<Option<FileInfo>, FileError> {
        T::file(self, index)
    }
    fn size(&mut self, name: &FileName) -> Result<u32, FileError> {
        T::size(self, name)
    }
    fn read(&mut self, name: &FileName, offset: u32, buf: &mut [u8]) -> Result<usize, FileError> {
        T::read(self, name, offset, buf)
    }
    fn remove(&mut self, name: &FileName) -> Result<(), FileError> {
        T::remove(self, name)
    }
    fn create(&mut self, name: &FileName) -> Result<(), FileError> {
        T::create(self, name)
    }
    fn append(&mut self, bytes: &[u8]) -> Result<(), FileError> {
        T::append(self, bytes)
    }
    fn finish(&mut self) -> Result<(), FileError> {
        T::finish(self)
    }
    fn abandon(&mut self) -> Result<(), FileError> {
        T::abandon(self)
    }
    fn writing(&self) -> Option<FileName> {
        T::writing(self)
    }
    fn writes_long_names(&self) -> bool {
        T::writes_long_names(self)
    }
    fn mount(&mut self) -> Result<(), FileError> {
        T::mount(self)
    }
    fn release(&mut self) {
        T::release(self)
    }
}

/// A file store refused an operation.
/// Exhaustive on purpose: every error has a wire code in the application layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FileError {
    /// No finished file has this name.
    NotFound,
    /// No room: for the bytes, or for one more file.
    Full,
    /// The name breaks [`FileName`]'s rules.
    BadName,
    /// Another file is being written: finish or abandon it first.
    Busy,
    /// No file is being written (none was created, or it was finished or abandoned).
    NotWriting,
    /// The storage device failed.
    Device,
}

impl fmt::Display for FileError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::NotFound => "no-such-file",
            Self::Full => "files-full",
            Self::BadName => "bad-file-name",
            Self::Busy => "file-busy",
            Self::NotWriting => "not-writing",
            Self::Device => "file-device",
        })
    }
}

/// One finished file of a [`RamFileStore`]: its bytes are `data[start..start + len]`.
#[derive(Clone, Copy)]
struct Entry {
    name: FileName,
    start: usize,
    len: usize,
}

/// A file store in RAM: `BYTES` bytes for the files' contents, at most `FILES` finished files.
/// For tests, and for small boards that keep a job only until they restart.
///
/// The finished files lie one after the other from the start of the buffer, in the order they
/// were finished; the file being written grows after them. Removing or replacing a file moves
/// the ones after it down, so the whole room is always in one piece. Replacing a file needs
/// room for both until the new one is finished.
pub struct RamFileStore<const BYTES: usize, const FILES: usize> {
    data: [u8; BYTES],
    entries: [Option<Entry>; FILES],
    /// Bytes of finished files, from the start of `data`.
    used: usize,
    /// The file being written and its length so far (its bytes follow `used`).
    writing: Option<(FileName, usize)>,
}

impl<const BYTES: usize, const FILES: usize> Default for RamFileStore<BYTES, FILES> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const BYTES: usize, const FILES: usize> RamFileStore<BYTES, FILES> {
    /// An empty store.
    pub const fn new() -> Self {
        Self {
            data: [0; BYTES],
            entries: [None; FILES],
            used: 0,
            writing: None,
        }
    }

    /// The finished entries, in order.
    fn finished(&self) -> impl Iterator<Item = &Entry> {
        self.entries.iter().flatten()
    }

    fn entry(&self, name: &FileName) -> Result<Entry, FileError> {
        self.finished()
            .find(|e| e.name == *name)
            .copied()
            .ok_or(FileError::NotFound)
    }

    /// Remove the finished file `name` and move what follows it down (the file being written
    /// included).
    fn take_out(&mut self, name: &FileName) -> Result<(), FileError> {
        let gone = self.entry(name)?;
        let end = self.used + self.writing.map_or(0, |(_, len)| len);
        self.data
            .copy_within(gone.start + gone.len..end, gone.start);
        self.used -= gone.len;
        let mut kept = [None; FILES];
        for (slot, e) in kept
            .iter_mut()
            .zip(self.entries.iter().flatten().filter(|e| e.name != *name))
        {
            let start = if e.start > gone.start {
                e.start - gone.len
            } else {
                e.start
            };
            *slot = Some(Entry { start, ..*e });
        }
        self.entries = kept;
        Ok(())
    }
}

impl<const BYTES: usize, const FILES: usize> FileStore for RamFileStore<BYTES, FILES> {
    fn file(&mut self, index: usize) -> Result<Option<FileInfo>, FileError> {
        Ok(self.finished().nth(index).map(|e| FileInfo {
            name: e.name,
            size: e.len as u32,
        }))
    }

    fn size(&mut self, name: &FileName) -> Result<u32, FileError> {
        Ok(self.entry(name)?.len as u32)
    }

    fn read(&mut self, name: &FileName, offset: u32, buf: &mut [u8]) -> Result<usize, FileError> {
        let e = self.entry(name)?;
        let from = (offset as usize).min(e.len);
        let n = buf.len().min(e.len - from);
        let src = self
            .data
            .get(e.start + from..e.start + from + n)
            .ok_or(FileError::Device)?;
        if let Some(dst) = buf.get_mut(..n) {
            dst.copy_from_slice(src);
        }
        Ok(n)
    }

    fn remove(&mut self, name: &FileName) -> Result<(), FileError> {
        self.take_out(name)
    }

    fn create(&mut self, name: &FileName) -> Result<(), FileError> {
        if self.writing.is_some() {
            return Err(FileError::Busy);
        }
        let replaces = self.finished().any(|e| e.name == *name);
        if !replaces && self.finished().count() >= FILES {
            return Err(FileError::Full);
        }
        self.writing = Some((*name, 0));
        Ok(())
    }

    fn append(&mut self, bytes: &[u8]) -> Result<(), FileError> {
        let (name, len) = self.writing.ok_or(FileError::NotWriting)?;
        let at = self.used + len;
        let dst = self
            .data
            .get_mut(at..at + bytes.len())
            .ok_or(FileError::Full)?;
        dst.copy_from_slice(bytes);
        self.writing = Some((name, len + bytes.len()));
        Ok(())
    }

    fn finish(&mut self) -> Result<(), FileError> {
        let (name, _) = self.writing.ok_or(FileError::NotWriting)?;
        let replaces = self.finished().any(|e| e.name == name);
        if !replaces && self.entries.iter().all(Option::is_some) {
            return Err(FileError::Full);
        }
        if replaces {
            self.take_out(&name)?;
        }
        let (_, len) = self.writing.take().ok_or(FileError::NotWriting)?;
        let slot = self
            .entries
            .iter_mut()
            .find(|e| e.is_none())
            .ok_or(FileError::Full)?;
        *slot = Some(Entry {
            name,
            start: self.used,
            len,
        });
        self.used += len;
        Ok(())
    }

    fn abandon(&mut self) -> Result<(), FileError> {
        self.writing = None;
        Ok(())
    }

    fn writing(&self) -> Option<FileName> {
        self.writing.map(|(name, _)| name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn name(s: &str) -> FileName {
        FileName::new(s.as_bytes()).unwrap()
    }

    fn write<S: FileStore + ?Sized>(store: &mut S, n: &str, bytes: &[u8]) -> Result<(), FileError> {
        store.create(&name(n))?;
        store.append(bytes)?;
        store.finish()
    }

    fn contents<S: FileStore + ?Sized>(
        store: &mut S,
        n: &str,
    ) -> Result<([u8; 64], usize), FileError> {
        let mut buf = [0; 64];
        let len = store.read(&name(n), 0, &mut buf)?;
        Ok((buf, len))
    }

    fn listed<S: FileStore + ?Sized>(store: &mut S) -> ([Option<FileInfo>; 4], usize) {
        let mut out = [None; 4];
        let mut count = 0;
        while let Some(info) = store.file(count).unwrap() {
            out[count] = Some(info);
            count += 1;
        }
        (out, count)
    }

    #[test]
    fn names_follow_the_rules() {
        for good in ["CUBE~1.GCO", "a", "bracket_v2.gcode", "part(1)-b+c.g"] {
            assert!(FileName::new(good.as_bytes()).is_ok(), "{good}");
        }
        let long = [b'x'; MAX_NAME_LEN];
        assert!(FileName::new(&long).is_ok());
        assert_eq!(FileName::new(&[b'x'; 64]).unwrap_err(), FileError::BadName);
        for bad in [
            "",
            "a b",
            "dir/part.g",
            "a\\b",
            ".hidden",
            "a*b",
            "a;b",
            "a:b",
            "a?b",
            "é.g",
            "a\tb",
        ] {
            assert_eq!(
                FileName::new(bad.as_bytes()).unwrap_err(),
                FileError::BadName,
                "{bad}"
            );
        }
        assert_eq!(name("Part.GCO"), name("part.gco"));
        assert_ne!(name("part.gco"), name("part.g"));
        assert_eq!(name("Part.GCO").as_str(), "Part.GCO");
    }

    #[test]
    fn keeps_the_file_store_contract() {
        conformance::all(RamFileStore::<2048, 4>::new);
    }

    /// The store lists `names`, in this order and spelling.
    fn assert_order<S: FileStore>(store: &mut S, names: &[&str]) {
        let (files, count) = listed(store);
        assert_eq!(count, names.len(), "{files:?}");
        for (file, want) in files.iter().zip(names) {
            assert_eq!(
                file.map(|f| f.name).as_ref().map(FileName::as_str),
                Some(*want)
            );
        }
    }

    #[test]
    fn files_are_listed_in_the_order_they_were_finished() {
        let mut s = RamFileStore::<64, 4>::new();
        write(&mut s, "a.g", b"aaaa").unwrap();
        write(&mut s, "b.g", b"bb").unwrap();
        write(&mut s, "c.g", b"cccccc").unwrap();
        s.create(&name("d.g")).unwrap();
        s.append(b"dd").unwrap();
        s.remove(&name("b.g")).unwrap();
        s.finish().unwrap();
        assert_order(&mut s, &["a.g", "c.g", "d.g"]);
        write(&mut s, "A.G", b"second").unwrap();
        assert_order(&mut s, &["c.g", "d.g", "A.G"]);
        s.create(&name("c.g")).unwrap();
        s.append(b"new").unwrap();
        s.remove(&name("c.g")).unwrap();
        s.finish().unwrap();
        assert_order(&mut s, &["d.g", "A.G", "c.g"]);
        for (n, want) in [("d.g", &b"dd"[..]), ("a.g", b"second"), ("c.g", b"new")] {
            let (buf, len) = contents(&mut s, n).unwrap();
            assert_eq!(&buf[..len], want, "{n}");
        }
    }

    #[test]
    fn room_is_bounded_in_bytes_and_in_files() {
        let mut s = RamFileStore::<8, 2>::new();
        write(&mut s, "a.g", b"12345").unwrap();
        s.create(&name("b.g")).unwrap();
        s.append(b"123").unwrap();
        assert_eq!(s.append(b"4"), Err(FileError::Full));
        // The write is as it was: it can still be finished.
        s.finish().unwrap();
        assert_eq!(s.size(&name("b.g")), Ok(3));
        assert_eq!(s.create(&name("c.g")), Err(FileError::Full));
        // Replacing needs no new entry, but room for both files until the new one is finished;
        // then the old one's bytes are free.
        s.create(&name("a.g")).unwrap();
        assert_eq!(s.append(b"x"), Err(FileError::Full));
        s.abandon().unwrap();
        s.remove(&name("b.g")).unwrap();
        write(&mut s, "a.g", b"xy").unwrap();
        assert_eq!(s.size(&name("a.g")), Ok(2));
        write(&mut s, "c.g", b"123456").unwrap();
        assert_eq!(listed(&mut s).1, 2);
    }
}
