//! The [`FileStore`] contract as checks that any store runs in its tests (feature
//! `conformance`).
//!
//! Each public function checks one behaviour of the [contract](super) and panics when the
//! store breaks it, at the line of the check, with a message that names the operation and the
//! file. [`all`] runs every check on a fresh store; [`all_restarting`] runs the checks of a
//! store that keeps its files when it restarts (every store but one in RAM), given how to
//! restart it:
//!
//! ```
//! use forja_hal_abstraction::files::{RamFileStore, conformance};
//!
//! conformance::all(RamFileStore::<2048, 4>::new);
//! ```
//!
//! What a store needs to run them:
//! - it is empty when a check begins;
//! - it has room for 4 finished files, and for a new version of one of them while it is
//!   written: 2 KiB in all, in files of up to 1500 bytes;
//! - every check writes 8.3 names (`job.gco`, `A.G`), each part in one case, as a FAT card
//!   without long names keeps them; only
//!   [`long_names_are_written_only_where_the_store_says_so`] writes long names, and only to a
//!   store whose [`FileStore::writes_long_names`] is `true`.
//!
//! What the checks cannot bring about is left to each store's own tests: a full store, a
//! failing medium, a power cut in the middle of an operation, and which order the files are
//! listed in.
//!
//! The checks are `no_std` and allocate nothing: less than 4 KiB of stack. They call the
//! store through `&mut dyn FileStore`, as the application does, except the restart checks,
//! which own it.

use super::{FileError, FileInfo, FileName, FileStore, MAX_NAME_LEN};

/// The checks that [`all`] runs, each on a fresh store.
const CHECKS: [fn(&mut dyn FileStore); 12] = [
    a_file_is_seen_only_once_finished,
    reads_take_any_offset_and_any_buffer,
    finishing_replaces_the_old_file_and_abandoning_keeps_it,
    names_are_one_file_whatever_their_case,
    one_file_is_written_at_a_time,
    empty_files_are_files,
    removing_leaves_the_others_and_a_write_goes_on,
    the_listing_keeps_its_order,
    refused_operations_change_nothing,
    long_names_are_written_only_where_the_store_says_so,
    mount_and_release_keep_the_files,
    a_lent_store_is_the_same_store,
];

/// Runs every check of this module but the restart checks, each on a store fresh from
/// `make`.
pub fn all<S: FileStore>(mut make: impl FnMut() -> S) {
    for check in CHECKS {
        check(&mut make());
    }
}

/// Runs the restart checks, each on a store fresh from `make`. `restart` takes the store as
/// a power cut finds it (nothing is finished, abandoned or released first) and gives back
/// the store opened again over the same medium.
pub fn all_restarting<S: FileStore>(mut make: impl FnMut() -> S, mut restart: impl FnMut(S) -> S) {
    a_restart_keeps_the_finished_files(make(), &mut restart);
    a_restart_forgets_the_write_in_progress(make(), &mut restart);
}

/// A file being written is not seen by [`FileStore::file`], [`FileStore::size`] or
/// [`FileStore::read`], and [`FileStore::writing`] names it; once finished it is seen whole.
pub fn a_file_is_seen_only_once_finished(store: &mut dyn FileStore) {
    assert_eq!(store.writing(), None, "a fresh store writes nothing");
    assert_listed(store, &[]);
    let job = name("job.gco");
    assert_eq!(store.create(&job), Ok(()), "create job.gco");
    assert_eq!(store.append(b"G1 X1\n"), Ok(()), "append to job.gco");
    assert_eq!(store.writing(), Some(job), "job.gco is being written");
    assert_unseen(store, "job.gco");
    assert_listed(store, &[]);
    assert_eq!(store.append(b"G1 X2\n"), Ok(()), "append to job.gco");
    assert_unseen(store, "job.gco");
    assert_eq!(store.finish(), Ok(()), "finish job.gco");
    assert_eq!(
        store.writing(),
        None,
        "nothing is written once job.gco is finished"
    );
    assert_listed(store, &[("job.gco", 12)]);
    assert_holds(store, "job.gco", b"G1 X1\nG1 X2\n");
    assert_holds(store, "JOB.GCO", b"G1 X1\nG1 X2\n");
}

/// [`FileStore::read`] copies as many bytes as fit in the buffer and are left from the
/// offset: from any offset, into buffers of any length (none included), 0 at and past the
/// end, with reads of another file in between.
pub fn reads_take_any_offset_and_any_buffer(store: &mut dyn FileStore) {
    write(store, "job.gco", b"G1 X1\nG1 X2\n");
    let job = name("job.gco");
    let mut small = [0; 4];
    assert_eq!(store.read(&job, 3, &mut small), Ok(4), "4 bytes at 3");
    assert_eq!(&small, b"X1\nG", "4 bytes at 3");
    assert_eq!(store.read(&job, 9, &mut small), Ok(3), "the last 3 bytes");
    assert_eq!(&small[..3], b"X2\n", "the last 3 bytes");
    assert_eq!(store.read(&job, 10, &mut small), Ok(2), "the last 2 bytes");
    assert_eq!(&small[..2], b"2\n", "the last 2 bytes");
    for past in [12, 13, 99, u32::MAX] {
        assert_eq!(
            store.read(&job, past, &mut small),
            Ok(0),
            "a read at {past}"
        );
    }
    assert_eq!(store.read(&job, 0, &mut []), Ok(0), "a read into no buffer");

    let long: [u8; 1500] = pattern(1);
    write(store, "long.g", &long);
    write(store, "other.g", b"other");
    let mut buf = [0; 600];
    for len in [1, 3, 17, 256, 511, 512, 513, 600] {
        let mut at = 0;
        while at <= long.len() + 2 {
            let got = store.read(&name("long.g"), at as u32, &mut buf[..len]);
            let want = long.get(at..).unwrap_or(&[]);
            let want = &want[..want.len().min(len)];
            assert_eq!(got, Ok(want.len()), "{len} bytes of long.g at {at}");
            assert!(buf[..want.len()] == *want, "{len} bytes of long.g at {at}");
            at += 1 + len / 2 + at % 7;
        }
        assert_holds(store, "other.g", b"other");
    }
    // Backwards, and across the file.
    for at in [1499, 1024, 1023, 512, 511, 0, 700] {
        let got = store.read(&name("long.g"), at as u32, &mut buf[..4]);
        let want = &long[at..(at + 4).min(long.len())];
        assert_eq!(got, Ok(want.len()), "4 bytes of long.g at {at}");
        assert!(buf[..want.len()] == *want, "4 bytes of long.g at {at}");
    }
    assert_holds(store, "long.g", &long);
}

/// Until it is finished, a new version of a file leaves the old one seen, unchanged; abandoned,
/// it leaves the old one; finished, it takes the old one's place (one file, not two) with the
/// new bytes, also for reads that went on in the old one.
pub fn finishing_replaces_the_old_file_and_abandoning_keeps_it(store: &mut dyn FileStore) {
    let second: [u8; 1500] = pattern(2);
    write(store, "a.g", b"first");
    write(store, "b.g", b"bee");
    let begin = |store: &mut dyn FileStore| {
        assert_eq!(store.create(&name("A.G")), Ok(()), "create A.G");
        for piece in second.chunks(100) {
            assert_eq!(store.append(piece), Ok(()), "append to A.G");
            assert_holds(store, "a.g", b"first");
        }
        assert_listed(store, &[("a.g", 5), ("b.g", 3)]);
    };
    begin(store);
    assert_eq!(store.abandon(), Ok(()), "abandon A.G");
    assert_eq!(
        store.writing(),
        None,
        "nothing is written once A.G is abandoned"
    );
    assert_holds(store, "a.g", b"first");
    assert_listed(store, &[("a.g", 5), ("b.g", 3)]);
    begin(store);
    assert_eq!(store.finish(), Ok(()), "finish A.G");
    assert_listed(store, &[("A.G", 1500), ("b.g", 3)]);
    assert_holds(store, "a.g", &second);
    assert_holds(store, "b.g", b"bee");
    // A read in the middle of the file, then a shorter version: the next read is of it.
    let mut buf = [0; 4];
    assert_eq!(
        store.read(&name("a.g"), 1000, &mut buf),
        Ok(4),
        "a.g at 1000"
    );
    write(store, "a.g", b"short now");
    assert_eq!(
        store.read(&name("a.g"), 6, &mut buf),
        Ok(3),
        "a.g at 6, replaced"
    );
    assert_eq!(&buf[..3], b"now", "a.g at 6, replaced");
    assert_listed(store, &[("a.g", 9), ("b.g", 3)]);
}

/// Names that differ only in the case of letters are one file, found by any spelling, which
/// keeps the spelling of its last write; [`FileStore::remove`] takes any spelling too.
pub fn names_are_one_file_whatever_their_case(store: &mut dyn FileStore) {
    write(store, "part.gco", b"old");
    for spelling in ["part.gco", "PART.GCO", "Part.Gco", "pArT.gCo"] {
        assert_eq!(store.size(&name(spelling)), Ok(3), "size of {spelling}");
        assert_holds(store, spelling, b"old");
    }
    write(store, "b.g", b"bee");
    write(store, "PART.GCO", b"new and longer");
    assert_listed(store, &[("PART.GCO", 14), ("b.g", 3)]);
    assert_holds(store, "part.gco", b"new and longer");
    write(store, "part.GCO", b"again");
    assert_listed(store, &[("part.GCO", 5), ("b.g", 3)]);
    assert_eq!(store.remove(&name("Part.gco")), Ok(()), "remove Part.gco");
    assert_eq!(
        store.remove(&name("part.gco")),
        Err(FileError::NotFound),
        "remove part.gco once it is removed"
    );
    assert_unseen(store, "PART.GCO");
    assert_listed(store, &[("b.g", 3)]);
}

/// [`FileStore::append`] and [`FileStore::finish`] without a write are
/// [`FileError::NotWriting`], [`FileStore::abandon`] is `Ok`; [`FileStore::create`] during a
/// write is [`FileError::Busy`], whatever the name, and the write goes on.
pub fn one_file_is_written_at_a_time(store: &mut dyn FileStore) {
    assert_not_writing(store, "on a fresh store");
    assert_eq!(store.abandon(), Ok(()), "abandon on a fresh store");
    assert_not_writing(store, "after abandoning nothing");
    assert_eq!(store.create(&name("a.g")), Ok(()), "create a.g");
    assert_eq!(store.append(b"aa"), Ok(()), "append to a.g");
    for other in ["b.g", "a.g", "A.G"] {
        assert_eq!(
            store.create(&name(other)),
            Err(FileError::Busy),
            "create {other} while a.g is written"
        );
        assert_eq!(
            store.writing().as_ref().map(FileName::as_str),
            Some("a.g"),
            "a.g is written after create {other}"
        );
    }
    assert_eq!(store.append(b"a"), Ok(()), "append to a.g after Busy");
    assert_eq!(store.finish(), Ok(()), "finish a.g");
    assert_listed(store, &[("a.g", 3)]);
    assert_holds(store, "a.g", b"aaa");
    assert_unseen(store, "b.g");
    assert_not_writing(store, "after finishing a.g");
    assert_eq!(store.create(&name("b.g")), Ok(()), "create b.g");
    assert_eq!(store.abandon(), Ok(()), "abandon b.g");
    assert_not_writing(store, "after abandoning b.g");
    assert_eq!(store.abandon(), Ok(()), "abandon twice");
    assert_eq!(
        store.create(&name("b.g")),
        Ok(()),
        "create b.g after abandoning it"
    );
    assert_eq!(store.finish(), Ok(()), "finish b.g");
    assert_listed(store, &[("a.g", 3), ("b.g", 0)]);
}

/// A file of no bytes is a file: listed, of size 0, read as nothing; it replaces and is
/// replaced like any other.
pub fn empty_files_are_files(store: &mut dyn FileStore) {
    write(store, "e.g", b"");
    assert_listed(store, &[("e.g", 0)]);
    assert_holds(store, "e.g", b"");
    assert_eq!(
        store.read(&name("e.g"), 0, &mut [0; 4]),
        Ok(0),
        "a read of e.g"
    );
    write(store, "e.g", b"full");
    assert_holds(store, "e.g", b"full");
    write(store, "e.g", b"");
    assert_holds(store, "e.g", b"");
    assert_listed(store, &[("e.g", 0)]);
    assert_eq!(store.remove(&name("e.g")), Ok(()), "remove e.g");
    assert_listed(store, &[]);
}

/// [`FileStore::remove`] takes one finished file away and leaves the others whole; a write
/// in progress goes on, also when the file removed is the finished version of the one being
/// written.
pub fn removing_leaves_the_others_and_a_write_goes_on(store: &mut dyn FileStore) {
    let a: [u8; 400] = pattern(3);
    let c: [u8; 600] = pattern(4);
    write(store, "a.g", &a);
    write(store, "b.g", &pattern::<20>(5));
    write(store, "c.g", &c);
    // Writing `written`, remove `removed`; the write goes on.
    let remove_while_writing = |store: &mut dyn FileStore, written: &str, removed: &str| {
        assert_eq!(store.create(&name(written)), Ok(()), "create {written}");
        assert_eq!(store.append(b"dd"), Ok(()), "append to {written}");
        let once = store.remove(&name(removed));
        assert_eq!(once, Ok(()), "remove {removed} while {written} is written");
        let twice = store.remove(&name(removed));
        assert_eq!(twice, Err(FileError::NotFound), "remove {removed} twice");
        assert_unseen(store, removed);
        let writing = store.writing();
        assert_eq!(
            writing,
            Some(name(written)),
            "writing after removing {removed}"
        );
        let appended = store.append(b"d");
        assert_eq!(
            appended,
            Ok(()),
            "append to {written} after removing {removed}"
        );
        assert_eq!(store.finish(), Ok(()), "finish {written}");
        assert_holds(store, written, b"ddd");
    };
    remove_while_writing(store, "d.g", "B.g");
    assert_listed(store, &[("a.g", 400), ("c.g", 600), ("d.g", 3)]);
    assert_holds(store, "a.g", &a);
    assert_holds(store, "c.g", &c);
    // The finished version of the file being written.
    remove_while_writing(store, "a.g", "a.g");
    assert_listed(store, &[("a.g", 3), ("c.g", 600), ("d.g", 3)]);
    assert_holds(store, "c.g", &c);
    assert_holds(store, "d.g", b"ddd");
}

/// [`FileStore::file`] lists every finished file once, then answers `None`; its order stays
/// the same while no file is finished or removed, whatever is asked in between, a write in
/// progress included.
pub fn the_listing_keeps_its_order(store: &mut dyn FileStore) {
    write(store, "one.g", b"1");
    write(store, "two.g", b"22");
    write(store, "three.g", b"333");
    assert_listed(store, &[("one.g", 1), ("two.g", 2), ("three.g", 3)]);
    let first = listing(store);
    for i in [2, 0, 1, 1, 3, 2, 50, 0] {
        assert_eq!(
            store.file(i),
            Ok(first.files.get(i).copied().flatten()),
            "file({i}) out of order"
        );
    }
    assert_eq!(store.size(&name("two.g")), Ok(2), "size of two.g");
    assert_holds(store, "three.g", b"333");
    assert_eq!(store.file(1), Ok(first.files[1]), "file(1) after reads");
    assert_eq!(store.create(&name("four.g")), Ok(()), "create four.g");
    assert_eq!(store.append(b"4444"), Ok(()), "append to four.g");
    assert_eq!(listing(store), first, "the listing during a write");
    assert_eq!(store.abandon(), Ok(()), "abandon four.g");
    assert_eq!(
        listing(store),
        first,
        "the listing after abandoning a write"
    );
    assert_eq!(
        store.remove(&name("four.g")),
        Err(FileError::NotFound),
        "remove four.g, never finished"
    );
    assert_eq!(listing(store), first, "the listing after a refused remove");
}

/// An operation refused with [`FileError::NotFound`], [`FileError::NotWriting`] or
/// [`FileError::Busy`] changes nothing: neither the finished files nor the write in progress.
pub fn refused_operations_change_nothing(store: &mut dyn FileStore) {
    write(store, "kept.g", b"kept");
    let before = listing(store);
    let refused = |store: &mut dyn FileStore, when: &str| {
        let missing = name("gone.g");
        let size = store.size(&missing);
        assert_eq!(size, Err(FileError::NotFound), "size of gone.g {when}");
        let read = store.read(&missing, 0, &mut [0; 8]);
        assert_eq!(read, Err(FileError::NotFound), "read gone.g {when}");
        let removed = store.remove(&missing);
        assert_eq!(removed, Err(FileError::NotFound), "remove gone.g {when}");
        assert_eq!(listing(store), before, "the listing after refusals {when}");
        assert_holds(store, "kept.g", b"kept");
    };
    refused(store, "without a write");
    assert_not_writing(store, "without a write");
    refused(store, "after NotWriting");
    assert_eq!(store.create(&name("new.g")), Ok(()), "create new.g");
    assert_eq!(store.append(b"new "), Ok(()), "append to new.g");
    for busy in ["kept.g", "gone.g"] {
        let created = store.create(&name(busy));
        assert_eq!(
            created,
            Err(FileError::Busy),
            "create {busy} during a write"
        );
    }
    refused(store, "during a write");
    assert_eq!(store.writing(), Some(name("new.g")), "new.g after refusals");
    let appended = store.append(b"bytes");
    assert_eq!(appended, Ok(()), "append to new.g after refusals");
    assert_eq!(store.finish(), Ok(()), "finish new.g");
    assert_holds(store, "new.g", b"new bytes");
    assert_holds(store, "kept.g", b"kept");
    assert_unseen(store, "gone.g");
}

/// A store whose [`FileStore::writes_long_names`] is `true` writes every [`FileName`], up to
/// [`MAX_NAME_LEN`] bytes, and tells long names apart by every byte; one whose answer is
/// `false` refuses a name that is not 8.3 with [`FileError::BadName`] and changes nothing.
/// Both write 8.3 names.
pub fn long_names_are_written_only_where_the_store_says_so(store: &mut dyn FileStore) {
    let mut longest = [b'x'; MAX_NAME_LEN];
    longest[MAX_NAME_LEN - 4..].copy_from_slice(b".gco");
    let longest = FileName::new(&longest).unwrap_or_else(|e| panic!("the longest name: {e}"));
    write(store, "short.g", b"short");
    let long: [u8; 300] = pattern(6);
    if store.writes_long_names() {
        write(store, "bracket_v2.gcode", &long);
        write(store, "bracket_v3.gcode", b"v3");
        write(store, longest.as_str(), b"longest");
        assert_listed(
            store,
            &[
                ("short.g", 5),
                ("bracket_v2.gcode", 300),
                ("bracket_v3.gcode", 2),
                (longest.as_str(), 7),
            ],
        );
        assert_holds(store, "BRACKET_V2.GCODE", &long);
        assert_holds(store, "bracket_v3.gcode", b"v3");
        assert_holds(store, longest.as_str(), b"longest");
        write(store, "Bracket_V2.gcode", b"v2");
        assert_listed(
            store,
            &[
                ("short.g", 5),
                ("Bracket_V2.gcode", 2),
                ("bracket_v3.gcode", 2),
                (longest.as_str(), 7),
            ],
        );
        assert_holds(store, "bracket_v2.gcode", b"v2");
    } else {
        for long_name in [
            "bracket_v2.gcode",
            longest.as_str(),
            "abcdefghi.g",
            "a.gcod",
        ] {
            assert_eq!(
                store.create(&name(long_name)),
                Err(FileError::BadName),
                "create {long_name} on a store without long names"
            );
            assert_eq!(store.writing(), None, "writing after refusing {long_name}");
            assert_eq!(
                store.append(b"x"),
                Err(FileError::NotWriting),
                "after {long_name}"
            );
        }
        assert_listed(store, &[("short.g", 5)]);
        write(store, "abcdefgh.gco", &long);
        assert_listed(store, &[("short.g", 5), ("abcdefgh.gco", 300)]);
        assert_holds(store, "ABCDEFGH.GCO", &long);
    }
    assert_holds(store, "short.g", b"short");
}

/// [`FileStore::mount`] answers `Ok` on a working store, as often as it is called;
/// [`FileStore::release`] keeps every finished file, and the store goes on after it, mounted
/// again or not. A write in progress when it is released is abandoned, or goes on: either way
/// [`FileStore::abandon`] ends it and it is never seen.
pub fn mount_and_release_keep_the_files(store: &mut dyn FileStore) {
    assert_eq!(store.mount(), Ok(()), "mount a fresh store");
    assert_eq!(store.mount(), Ok(()), "mount a mounted store");
    write(store, "a.g", b"kept");
    store.release();
    assert_listed(store, &[("a.g", 4)]);
    assert_holds(store, "a.g", b"kept");
    store.release();
    assert_eq!(store.mount(), Ok(()), "mount a released store");
    assert_holds(store, "a.g", b"kept");
    assert_eq!(store.create(&name("b.g")), Ok(()), "create b.g");
    assert_eq!(store.append(b"half"), Ok(()), "append to b.g");
    store.release();
    let writing = store.writing();
    assert!(
        writing.is_none() || writing == Some(name("b.g")),
        "after a release, b.g or nothing is being written, not {writing:?}"
    );
    assert_eq!(store.abandon(), Ok(()), "abandon after a release");
    assert_unseen(store, "b.g");
    assert_eq!(store.mount(), Ok(()), "mount after a released write");
    write(store, "c.g", b"after");
    assert_listed(store, &[("a.g", 4), ("c.g", 5)]);
    assert_holds(store, "a.g", b"kept");
}

/// The store lent (`&mut dyn FileStore` as a [`FileStore`] itself) is the store: what is
/// written through one is seen through the other.
pub fn a_lent_store_is_the_same_store(store: &mut dyn FileStore) {
    let long_names = store.writes_long_names();
    let mut lent = &mut *store;
    write(&mut lent, "a.g", b"lent");
    assert_eq!(
        FileStore::size(&mut lent, &name("a.g")),
        Ok(4),
        "size of a.g, lent"
    );
    assert_eq!(
        FileStore::writes_long_names(&lent),
        long_names,
        "long names, lent"
    );
    assert_eq!(
        FileStore::create(&mut lent, &name("b.g")),
        Ok(()),
        "create b.g, lent"
    );
    assert_eq!(
        FileStore::writing(&lent),
        Some(name("b.g")),
        "writing, lent"
    );
    assert_eq!(store.writing(), Some(name("b.g")), "writing");
    assert_eq!(store.abandon(), Ok(()), "abandon b.g");
    assert_holds(store, "a.g", b"lent");
    assert_listed(store, &[("a.g", 4)]);
}

/// Every finished file is found after a restart as it was last finished, removed files
/// stay removed, and a write abandoned before it leaves the old file.
pub fn a_restart_keeps_the_finished_files<S: FileStore>(
    mut store: S,
    mut restart: impl FnMut(S) -> S,
) {
    let b: [u8; 300] = pattern(7);
    let new: [u8; 1500] = pattern(8);
    write(&mut store, "a.g", b"first");
    write(&mut store, "b.g", &b);
    write(&mut store, "e.g", b"");
    assert_eq!(store.create(&name("A.G")), Ok(()), "create A.G");
    assert_eq!(store.append(&new), Ok(()), "append to A.G");
    assert_eq!(store.abandon(), Ok(()), "abandon A.G");
    let mut store = restart(store);
    assert_eq!(store.writing(), None, "writing after a restart");
    assert_listed(&mut store, &[("a.g", 5), ("b.g", 300), ("e.g", 0)]);
    assert_holds(&mut store, "a.g", b"first");
    assert_holds(&mut store, "b.g", &b);
    assert_holds(&mut store, "e.g", b"");
    write(&mut store, "A.G", &new);
    assert_eq!(store.remove(&name("b.g")), Ok(()), "remove b.g");
    assert_eq!(store.create(&name("c.g")), Ok(()), "create c.g");
    assert_eq!(store.append(b"new"), Ok(()), "append to c.g");
    assert_eq!(store.finish(), Ok(()), "finish c.g");
    assert_eq!(store.create(&name("c.g")), Ok(()), "create c.g again");
    assert_eq!(store.append(b"newer"), Ok(()), "append to the new c.g");
    assert_eq!(
        store.remove(&name("c.g")),
        Ok(()),
        "remove c.g while it is written"
    );
    assert_eq!(store.finish(), Ok(()), "finish the new c.g");
    let mut store = restart(store);
    assert_listed(&mut store, &[("A.G", 1500), ("e.g", 0), ("c.g", 5)]);
    assert_holds(&mut store, "a.g", &new);
    assert_holds(&mut store, "c.g", b"newer");
    assert_holds(&mut store, "e.g", b"");
    assert_unseen(&mut store, "b.g");
    let mut store = restart(store);
    assert_listed(&mut store, &[("A.G", 1500), ("e.g", 0), ("c.g", 5)]);
    assert_holds(&mut store, "a.g", &new);
}

/// A restart forgets a write in progress: neither a new file nor a new version of a file is
/// seen, the old version is whole, and the store takes new writes.
pub fn a_restart_forgets_the_write_in_progress<S: FileStore>(
    mut store: S,
    mut restart: impl FnMut(S) -> S,
) {
    let half: [u8; 700] = pattern(9);
    write(&mut store, "kept.g", b"whole");
    assert_eq!(store.create(&name("kept.g")), Ok(()), "create kept.g again");
    assert_eq!(store.append(&half), Ok(()), "append to the new kept.g");
    let mut store = restart(store);
    assert_not_writing(&mut store, "after a restart");
    assert_listed(&mut store, &[("kept.g", 5)]);
    assert_holds(&mut store, "kept.g", b"whole");
    assert_eq!(store.create(&name("gone.g")), Ok(()), "create gone.g");
    assert_eq!(store.append(&half), Ok(()), "append to gone.g");
    let mut store = restart(store);
    assert_eq!(store.writing(), None, "gone.g after a restart");
    assert_unseen(&mut store, "gone.g");
    assert_listed(&mut store, &[("kept.g", 5)]);
    write(&mut store, "gone.g", b"back");
    write(&mut store, "kept.g", &half);
    let mut store = restart(store);
    assert_listed(&mut store, &[("kept.g", 700), ("gone.g", 4)]);
    assert_holds(&mut store, "kept.g", &half);
    assert_holds(&mut store, "gone.g", b"back");
}

/// The most files a check lists.
const LISTED: usize = 8;

/// What [`FileStore::file`] answers from index 0 to its first `None`.
#[derive(Debug, PartialEq)]
struct Listing {
    files: [Option<FileInfo>; LISTED],
    len: usize,
}

#[track_caller]
fn listing<S: FileStore + ?Sized>(store: &mut S) -> Listing {
    let mut files = [None; LISTED];
    let mut len = 0;
    loop {
        match store.file(len) {
            Ok(Some(info)) => {
                let slot = files
                    .get_mut(len)
                    .unwrap_or_else(|| panic!("more than {LISTED} files listed"));
                *slot = Some(info);
                len += 1;
            }
            Ok(None) => break,
            Err(e) => panic!("file({len}): {e}"),
        }
    }
    assert_eq!(
        store.file(len + 1),
        Ok(None),
        "file({}) past the last",
        len + 1
    );
    Listing { files, len }
}

/// `name` as a [`FileName`]; the checks name only valid names.
#[track_caller]
fn name(name: &str) -> FileName {
    FileName::new(name.as_bytes()).unwrap_or_else(|e| panic!("{name:?}: {e}"))
}

/// Write `bytes` as `file`, 37 bytes an append: pieces that fill no block, sector or word.
#[track_caller]
fn write<S: FileStore + ?Sized>(store: &mut S, file: &str, bytes: &[u8]) {
    assert_eq!(store.create(&name(file)), Ok(()), "create {file}");
    for piece in bytes.chunks(37) {
        assert_eq!(store.append(piece), Ok(()), "append to {file}");
    }
    assert_eq!(store.finish(), Ok(()), "finish {file}");
}

/// The store lists exactly `files`, in any order: each under this spelling, of this size,
/// and each answers [`FileStore::size`] with it.
#[track_caller]
fn assert_listed<S: FileStore + ?Sized>(store: &mut S, files: &[(&str, u32)]) {
    let listed = listing(store);
    let seen = listed.files.get(..listed.len).unwrap_or(&[]);
    assert_eq!(listed.len, files.len(), "listed {seen:?}, not {files:?}");
    for &(file, size) in files {
        let found = seen.iter().flatten().filter(|info| info.name == name(file));
        let mut found = found.map(|info| (info.name.as_str(), info.size));
        assert_eq!(found.next(), Some((file, size)), "{file} in {seen:?}");
        assert_eq!(found.next(), None, "{file} once in {seen:?}");
        assert_eq!(store.size(&name(file)), Ok(size), "size of {file}");
    }
}

/// `file` holds `bytes`: its size, and reads from its start on, 259 bytes at a time (across
/// any block), up to a read that answers 0.
#[track_caller]
fn assert_holds<S: FileStore + ?Sized>(store: &mut S, file: &str, bytes: &[u8]) {
    let n = name(file);
    assert_eq!(store.size(&n), Ok(bytes.len() as u32), "size of {file}");
    let mut buf = [0; 259];
    let mut at = 0;
    loop {
        let want = bytes.get(at..).unwrap_or(&[]);
        let want = want.get(..buf.len()).unwrap_or(want);
        let got = store.read(&n, at as u32, &mut buf);
        assert_eq!(got, Ok(want.len()), "bytes of {file} read at {at}");
        assert!(
            buf.get(..want.len()) == Some(want),
            "the bytes of {file} from {at} differ"
        );
        if want.is_empty() {
            break;
        }
        at += want.len();
    }
}

/// No file is being written: [`FileStore::append`] and [`FileStore::finish`] are
/// [`FileError::NotWriting`].
#[track_caller]
fn assert_not_writing<S: FileStore + ?Sized>(store: &mut S, when: &str) {
    assert_eq!(store.writing(), None, "writing {when}");
    let appended = store.append(b"x");
    assert_eq!(appended, Err(FileError::NotWriting), "append {when}");
    assert_eq!(store.finish(), Err(FileError::NotWriting), "finish {when}");
}

/// No finished file answers to `file`.
#[track_caller]
fn assert_unseen<S: FileStore + ?Sized>(store: &mut S, file: &str) {
    let n = name(file);
    assert_eq!(store.size(&n), Err(FileError::NotFound), "size of {file}");
    let read = store.read(&n, 0, &mut [0; 4]);
    assert_eq!(read, Err(FileError::NotFound), "read {file}");
    let listed = listing(store);
    let seen = listed.files.get(..listed.len).unwrap_or(&[]);
    assert!(
        !seen.iter().flatten().any(|info| info.name == n),
        "{file} is listed: {seen:?}"
    );
}

/// `N` bytes that differ from one position to the next and from one `seed` to another, so
/// that a misplaced block shows.
fn pattern<const N: usize>(seed: u32) -> [u8; N] {
    let mut x = seed.wrapping_mul(0x9E37_79B9) | 1;
    core::array::from_fn(|_| {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        x as u8
    })
}
