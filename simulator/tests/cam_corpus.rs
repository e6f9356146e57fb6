//! The CAM corpus (`tests/corpus/cam/`: what Fusion 360, CamBam, Estlcam, Carbide Create,
//! FreeCAD and VCarve write for a grbl router) runs on the simulator's router through a link in
//! the grbl dialect, streamed by character counting as CNC senders stream it, with no line
//! refused, every line run, and the machine's steps within one step of the program's path.

mod common;

use common::{assert_ran_whole, corpus, count, sim};

/// The work offsets an operator sets before the corpus's programs (the corpus README): `G54`
/// at the top front left corner of a 20 mm stock, `G55` for Fusion's second setup, and the
/// homed position as the one `G28` goes to.
const SETUP: [&str; 3] = ["G10 L2 P1 X50 Y50 Z20", "G10 L2 P2 X150 Y50 Z20", "G28.1"];

#[test]
fn every_cam_program_runs_on_the_router_with_no_line_refused_and_on_its_path() {
    let files = corpus("cam", "nc");
    assert!(files.len() >= 7, "the corpus: {files:?}");
    let out_dir = std::env::temp_dir().join(format!("forja-cam-corpus-{}", std::process::id()));
    std::fs::create_dir_all(&out_dir).unwrap();
    for file in files {
        let name = file.display().to_string();
        let plot = out_dir.join(format!(
            "{}.svg",
            file.file_stem().unwrap().to_string_lossy()
        ));
        let mut command = sim();
        command.args(["--machine", "builtin:default", "--grbl"]);
        for line in SETUP {
            command.args(["--before", line]);
        }
        let out = command
            .arg("--job")
            .arg(&file)
            .arg("--plot")
            .arg(&plot)
            .output()
            .unwrap();
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(out.status.success(), "{name}:\n{text}");
        assert_ran_whole(&name, &text);
        assert_eq!(count(&text, "unanswered"), Some(0), "{name}:\n{text}");
        // The steps follow the program: the plot checks every position the machine passed
        // through against the kernel's moves and fails the run beyond one step.
        let trace = text
            .lines()
            .find(|l| l.starts_with("trace: farthest from the toolpath"))
            .unwrap_or_else(|| panic!("{name}: no trace check:\n{text}"));
        let mm: f64 = trace
            .trim_start_matches("trace: farthest from the toolpath ")
            .split(' ')
            .next()
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("{name}: {trace}"));
        assert!(mm <= 0.0125, "{name}: {trace}");
    }
    let _ = std::fs::remove_dir_all(&out_dir);
}
