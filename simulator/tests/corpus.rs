//! The slicer corpus (`tests/corpus/slicers/`: what PrusaSlicer, Cura, OrcaSlicer and
//! SuperSlicer emit for a Marlin printer) runs on the simulator's printer machine with no line
//! refused, no timing violation, and every line run.

mod common;

use common::{assert_ran_whole, corpus, sim};

#[test]
fn every_sliced_file_runs_on_the_printer_with_no_line_refused() {
    let files = corpus("slicers", "gcode");
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
        assert_ran_whole(&name.to_string(), &text);
    }
}
