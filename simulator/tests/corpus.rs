//! The slicer corpus (`tests/corpus/slicers/`: what PrusaSlicer, Cura, OrcaSlicer and
//! SuperSlicer emit for a Marlin printer) runs on the simulator's printer machine with no line
//! refused, no timing violation, and every line run.

mod common;

use std::path::PathBuf;

use common::sim;

/// The sliced files of the corpus.
fn corpus() -> Vec<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/corpus/slicers");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|entry| entry.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "gcode"))
        .collect();
    files.sort();
    files
}

/// The number after `label` in the run's summary (`refused 0`).
fn count(summary: &str, label: &str) -> Option<u64> {
    let at = summary.find(label)? + label.len();
    summary[at..]
        .trim_start()
        .split(|c: char| !c.is_ascii_digit())
        .next()?
        .parse()
        .ok()
}

#[test]
fn every_sliced_file_runs_on_the_printer_with_no_line_refused() {
    let files = corpus();
    assert!(files.len() >= 4, "the corpus: {files:?}");
    for file in files {
        let out = sim()
            .args(["--machine", "builtin:printer", "--job"])
            .arg(&file)
            .output()
            .unwrap();
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        let name = file.display();
        assert!(out.status.success(), "{name}:\n{text}");
        assert!(text.contains("result: finished"), "{name}:\n{text}");
        assert_eq!(count(&text, "refused"), Some(0), "{name}:\n{text}");
        assert_eq!(
            count(&text, "timing violations:"),
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
}
