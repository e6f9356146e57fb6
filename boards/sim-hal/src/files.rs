//! The simulated board's SD card: a directory of the host computer, behind the firmware's
//! [`FileStore`] contract.
//!
//! [`DirFileStore`] keeps each finished file as a file of the directory under its own name
//! (`forja-sim --sd-dir DIR` names the directory, so the files can be put there or looked at
//! from outside; by default each board gets a fresh temporary directory, removed with it). A
//! file being written is the directory's temporary [`WRITING`]: finishing flushes it to the
//! disk and renames it over the name, which replaces a file of that name at once (a rename is
//! atomic), so a simulator killed at any moment leaves the old file or the new one, never
//! part of it. Listing shows only entries whose names are [`FileName`]s (never the temporary,
//! whose name starts with `.`), in the order of their names; a temporary left by a killed
//! simulator is removed when the directory is opened again.
//!
//! Names are matched without regard to the case of letters, as the contract says, whatever
//! the host's file system does: a file finished under `PART.GCO` replaces `part.gco` and
//! takes the new spelling (a second rename).
//!
//! Errors of the host's file system are [`FileError::Device`], a full disk [`FileError::Full`].

use std::fs::{self, File, OpenOptions};
use std::io::{self, Read as _, Seek as _, SeekFrom, Write as _};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};

use forja_hal_abstraction::files::{FileError, FileInfo, FileName, FileStore};

/// The name of the file being written, in the directory.
pub const WRITING: &str = ".forja-writing";

/// A file store over a directory. See the [module documentation](self).
#[derive(Debug)]
pub struct DirFileStore {
    dir: PathBuf,
    /// The directory was made for this store, and is removed with it.
    temporary: bool,
    /// The file being written: its name, and the temporary it grows in.
    writing: Option<(FileName, File)>,
}

/// A host file system error as the contract has it.
fn device(e: io::Error) -> FileError {
    match e.kind() {
        io::ErrorKind::StorageFull | io::ErrorKind::QuotaExceeded => FileError::Full,
        _ => FileError::Device,
    }
}

impl DirFileStore {
    /// The store in `dir`, made if it does not exist; a file being written when a previous
    /// simulator stopped is removed.
    ///
    /// Errors: the directory cannot be made, read, or cleared of the temporary.
    pub fn open(dir: impl Into<PathBuf>) -> io::Result<Self> {
        let dir = dir.into();
        fs::create_dir_all(&dir)?;
        match fs::remove_file(dir.join(WRITING)) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e),
            _ => {}
        }
        Ok(Self {
            dir,
            temporary: false,
            writing: None,
        })
    }

    /// The store in a fresh directory of the host's temporary directory, removed when the
    /// store is dropped: an empty card for each board.
    ///
    /// Errors: the directory cannot be made.
    pub fn temporary() -> io::Result<Self> {
        static BOARDS: AtomicU32 = AtomicU32::new(0);
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let board = BOARDS.fetch_add(1, Ordering::Relaxed);
        let name = format!("forja-sd-{}-{board}-{nanos}", std::process::id());
        let dir = std::env::temp_dir().join(name);
        fs::create_dir(&dir)?;
        Ok(Self {
            dir,
            temporary: true,
            writing: None,
        })
    }

    /// The store in `dir`, or in a fresh temporary directory with `None`.
    ///
    /// Errors: as [`DirFileStore::open`] and [`DirFileStore::temporary`].
    pub fn open_or_temporary(dir: Option<PathBuf>) -> io::Result<Self> {
        match dir {
            Some(dir) => Self::open(dir),
            None => Self::temporary(),
        }
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// The finished files, in the order of their names: each name and its path.
    fn entries(&self) -> Result<Vec<(FileName, PathBuf)>, FileError> {
        let mut found = Vec::new();
        for entry in fs::read_dir(&self.dir).map_err(device)? {
            let entry = entry.map_err(device)?;
            if !entry.file_type().map_err(device)?.is_file() {
                continue;
            }
            let os_name = entry.file_name();
            let Some(name) = os_name
                .to_str()
                .and_then(|n| FileName::new(n.as_bytes()).ok())
            else {
                continue;
            };
            found.push((name, entry.path()));
        }
        found.sort_by(|(a, _), (b, _)| a.as_bytes().cmp(b.as_bytes()));
        Ok(found)
    }

    /// The path of the finished file `name`, as it is spelled in the directory.
    fn find(&self, name: &FileName) -> Result<PathBuf, FileError> {
        self.entries()?
            .into_iter()
            .find(|(n, _)| n == name)
            .map(|(_, path)| path)
            .ok_or(FileError::NotFound)
    }

    /// Make the directory's last changes (a rename, a removal) durable, as far as the host
    /// allows: they are done whether or not it does.
    fn sync_dir(&self) {
        let _ = File::open(&self.dir).and_then(|d| d.sync_all());
    }
}

impl Drop for DirFileStore {
    fn drop(&mut self) {
        if self.temporary {
            let _ = fs::remove_dir_all(&self.dir);
        }
    }
}

impl FileStore for DirFileStore {
    fn file(&mut self, index: usize) -> Result<Option<FileInfo>, FileError> {
        let Some((name, path)) = self.entries()?.into_iter().nth(index) else {
            return Ok(None);
        };
        let len = fs::metadata(path).map_err(device)?.len();
        Ok(Some(FileInfo {
            name,
            size: u32::try_from(len).unwrap_or(u32::MAX),
        }))
    }

    fn size(&mut self, name: &FileName) -> Result<u32, FileError> {
        let len = fs::metadata(self.find(name)?).map_err(device)?.len();
        Ok(u32::try_from(len).unwrap_or(u32::MAX))
    }

    fn read(&mut self, name: &FileName, offset: u32, buf: &mut [u8]) -> Result<usize, FileError> {
        let mut file = File::open(self.find(name)?).map_err(device)?;
        file.seek(SeekFrom::Start(u64::from(offset)))
            .map_err(device)?;
        let mut read = 0;
        while read < buf.len() {
            match file.read(&mut buf[read..]) {
                Ok(0) => break,
                Ok(n) => read += n,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(device(e)),
            }
        }
        Ok(read)
    }

    fn remove(&mut self, name: &FileName) -> Result<(), FileError> {
        fs::remove_file(self.find(name)?).map_err(device)?;
        self.sync_dir();
        Ok(())
    }

    fn create(&mut self, name: &FileName) -> Result<(), FileError> {
        if self.writing.is_some() {
            return Err(FileError::Busy);
        }
        let file = OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .open(self.dir.join(WRITING))
            .map_err(device)?;
        self.writing = Some((*name, file));
        Ok(())
    }

    fn append(&mut self, bytes: &[u8]) -> Result<(), FileError> {
        let (_, file) = self.writing.as_mut().ok_or(FileError::NotWriting)?;
        let before = file.stream_position().map_err(device)?;
        if let Err(e) = file.write_all(bytes) {
            // As it was before the call.
            let _ = file.set_len(before);
            let _ = file.seek(SeekFrom::Start(before));
            return Err(device(e));
        }
        Ok(())
    }

    fn finish(&mut self) -> Result<(), FileError> {
        let (name, file) = self.writing.as_mut().ok_or(FileError::NotWriting)?;
        let name = *name;
        file.sync_all().map_err(device)?;
        let temporary = self.dir.join(WRITING);
        let spelled = self.dir.join(name.as_str());
        // Over the file of that name as the directory spells it (one rename: atomic), then
        // under the new spelling.
        let target = match self.find(&name) {
            Ok(existing) => existing,
            Err(FileError::NotFound) => spelled.clone(),
            Err(e) => return Err(e),
        };
        fs::rename(&temporary, &target).map_err(device)?;
        self.writing = None;
        // The file is finished now: the new spelling and the flush of the directory are
        // done as far as the host allows.
        if target != spelled {
            let _ = fs::rename(&target, &spelled);
        }
        self.sync_dir();
        Ok(())
    }

    fn abandon(&mut self) -> Result<(), FileError> {
        if self.writing.take().is_none() {
            return Ok(());
        }
        match fs::remove_file(self.dir.join(WRITING)) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(device(e)),
            _ => Ok(()),
        }
    }

    fn writing(&self) -> Option<FileName> {
        self.writing.as_ref().map(|(name, _)| *name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use forja_hal_abstraction::files::conformance;

    fn name(s: &str) -> FileName {
        FileName::new(s.as_bytes()).unwrap()
    }

    fn write(store: &mut DirFileStore, n: &str, bytes: &[u8]) {
        store.create(&name(n)).unwrap();
        store.append(bytes).unwrap();
        store.finish().unwrap();
    }

    fn listing(store: &mut DirFileStore) -> Vec<(String, u32)> {
        (0..)
            .map_while(|i| store.file(i).unwrap())
            .map(|f| (f.name.as_str().to_string(), f.size))
            .collect()
    }

    /// What the directory holds, as the host sees it.
    fn on_disk(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        names.sort();
        names
    }

    /// The store as a simulator killed at this moment leaves it, opened again: the
    /// directory keeps what was written to it, the temporary of a write included, and still
    /// goes with the store.
    fn restart(mut store: DirFileStore) -> DirFileStore {
        let dir = store.path().to_path_buf();
        store.temporary = false;
        drop(store);
        let mut store = DirFileStore::open(dir).unwrap();
        store.temporary = true;
        store
    }

    #[test]
    fn keeps_the_file_store_contract() {
        conformance::all(|| DirFileStore::temporary().unwrap());
        conformance::all_restarting(|| DirFileStore::temporary().unwrap(), restart);
    }

    #[test]
    fn files_are_kept_in_the_directory_under_their_last_spelling_in_the_order_of_names() {
        let mut store = DirFileStore::temporary().unwrap();
        let dir = store.path().to_path_buf();
        store.create(&name("part.gco")).unwrap();
        store.append(b"old").unwrap();
        assert_eq!(on_disk(&dir), [WRITING]);
        store.finish().unwrap();
        assert_eq!(on_disk(&dir), ["part.gco"]);
        write(&mut store, "b.g", b"bee");
        write(&mut store, "PART.GCO", b"new and longer");
        assert_eq!(
            listing(&mut store),
            [("PART.GCO".to_string(), 14), ("b.g".to_string(), 3)]
        );
        assert_eq!(on_disk(&dir), ["PART.GCO", "b.g"]);
        store.create(&name("a.g")).unwrap();
        store.append(b"a").unwrap();
        store.abandon().unwrap();
        assert_eq!(on_disk(&dir), ["PART.GCO", "b.g"]);
        store.remove(&name("Part.gco")).unwrap();
        assert_eq!(on_disk(&dir), ["b.g"]);
        drop(store);
        assert!(!dir.exists(), "a temporary card goes with its board");
    }

    #[test]
    fn a_write_cut_midway_leaves_its_temporary_until_the_directory_is_opened_again() {
        let dir = std::env::temp_dir().join(format!("forja-sd-test-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        let mut store = DirFileStore::open(&dir).unwrap();
        write(&mut store, "kept.g", b"whole");
        // A simulator killed midway through a new version of `kept.g`: what was written is
        // in the temporary, never under a name.
        store.create(&name("kept.g")).unwrap();
        store.append(b"half of a new vers").unwrap();
        assert_eq!(on_disk(&dir), [WRITING, "kept.g"]);
        std::mem::forget(store);
        let mut store = DirFileStore::open(&dir).unwrap();
        assert_eq!(on_disk(&dir), ["kept.g"], "the temporary is cleared");
        assert_eq!(listing(&mut store), [("kept.g".to_string(), 5)]);
        drop(store);
        assert!(dir.exists(), "a named directory is kept");
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn names_outside_the_rules_are_not_listed() {
        let store_dir = DirFileStore::temporary().unwrap();
        let dir = store_dir.path().to_path_buf();
        let mut store = store_dir;
        fs::write(dir.join("has space.g"), b"x").unwrap();
        fs::write(dir.join(".hidden"), b"x").unwrap();
        fs::create_dir(dir.join("sub")).unwrap();
        fs::write(dir.join("ok.g"), b"xy").unwrap();
        assert_eq!(listing(&mut store), [("ok.g".to_string(), 2)]);
    }
}
