//! What the tests that run the `forja-sim` binary share. Each test uses what it needs.

#![allow(dead_code)]

use std::path::PathBuf;
use std::process::{Child, Command};

/// The `forja-sim` binary of this build.
pub fn sim() -> Command {
    Command::new(env!("CARGO_BIN_EXE_forja-sim"))
}

/// A running `forja-sim`, killed and reaped when dropped: a test that fails before it ends
/// leaves no simulator behind.
pub struct Running(pub Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The files of the corpus `tests/corpus/<dir>` whose extension is `ext`, sorted.
pub fn corpus(dir: &str, ext: &str) -> Vec<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/corpus")
        .join(dir);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|entry| entry.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .collect();
    files.sort();
    files
}

/// The number after `label` in a run's summary (`refused 0`).
pub fn count(summary: &str, label: &str) -> Option<u64> {
    let at = summary.find(label)? + label.len();
    summary[at..]
        .trim_start()
        .split(|c: char| !c.is_ascii_digit())
        .next()?
        .parse()
        .ok()
}

/// Check a job run's summary `text` (of `name`): it finished, with no line refused, no timing
/// violation, and every line run.
pub fn assert_ran_whole(name: &str, text: &str) {
    assert!(text.contains("result: finished"), "{name}:\n{text}");
    assert_eq!(count(text, "refused"), Some(0), "{name}:\n{text}");
    assert_eq!(
        count(text, "timing violations:"),
        Some(0),
        "{name}:\n{text}"
    );
    let run = text
        .lines()
        .find_map(|l| l.strip_prefix("lines run: "))
        .unwrap_or_else(|| panic!("{name}: no lines-run summary:\n{text}"));
    let (done, of) = run.split_once(" of ").expect("`N of M`");
    let of: String = of.chars().take_while(char::is_ascii_digit).collect();
    assert_eq!(done, of, "{name}: every line runs:\n{text}");
}
