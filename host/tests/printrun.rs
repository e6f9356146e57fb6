//! A RepRap host that this project did not write drives the simulator: Printrun's `printcore`
//! streams a job over the simulator's pseudo-terminal while the simulator's link damages the
//! bytes it receives, and every move must run exactly once.
//!
//! Printrun is installed into a virtual environment inside the checkout
//! (`target/printrun-venv`) with `pip install --no-deps printrun pyserial platformdirs
//! puremagic psutil`; if that fails the test fails and says why.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use common::{Sim, axis, positions, scratch, settle, venv_python, with};

/// The packages `from printrun.printcore import printcore` needs.
const PACKAGES: [&str; 5] = [
    "printrun",
    "pyserial",
    "platformdirs",
    "puremagic",
    "psutil",
];

/// The virtual environment's Python with Printrun, created and filled if needed.
fn printrun_python() -> PathBuf {
    venv_python(
        "printrun-venv",
        &PACKAGES,
        true,
        "from printrun.printcore import printcore",
    )
}

/// Stream `file` to the pseudo-terminal `pty` with Printrun's `printcore`, within `seconds`;
/// what it printed. The test fails if printcore does not finish the job.
fn stream(python: &Path, pty: &Path, file: &Path, seconds: u32) -> String {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/printrun/stream.py");
    let out = Command::new(python)
        .arg(&script)
        .arg(pty)
        .arg(file)
        .arg(seconds.to_string())
        .output()
        .expect("the Printrun script runs");
    let report = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "Printrun failed:\n{report}");
    assert!(report.contains("printrun: done"), "{report}");
    report
}

#[test]
fn printrun_streams_a_job_through_a_damaging_link_and_every_move_runs_once() {
    let python = printrun_python();
    let dir = scratch("printrun");
    let sim = Sim::start(&dir, &["--corrupt-rate", "0.002", "--seed", "5"]);
    // Relative moves of different lengths: one run twice or not at all moves the end.
    let mut job = String::from("G21\nG91\nG1 F6000\n");
    let (mut dx, mut dy) = (0.0f64, 0.0f64);
    for i in 0..150 {
        let x = f64::from(i % 9 + 1) * if i % 2 == 0 { 0.05 } else { -0.04 };
        let y = f64::from(i % 4 + 1) * if i % 3 == 0 { -0.05 } else { 0.04 };
        job.push_str(&format!("G1 X{x:.2} Y{y:.2} ; move {i}\n"));
        dx += x;
        dy += y;
    }
    job.push_str("G90\n");
    let file = dir.join("job.gcode");
    std::fs::write(&file, job).unwrap();
    let link = with(&sim.pty_args(), &[]);
    let before = positions(&link);
    let (x0, y0) = (axis(&before, 'X'), axis(&before, 'Y'));
    let report = stream(&python, &sim.pty, &file, 120);
    let at = settle(&link, Duration::from_secs(30));
    let (x, y) = (axis(&at, 'X'), axis(&at, 'Y'));
    assert!(
        (x - (x0 + dx)).abs() < 0.007 && (y - (y0 + dy)).abs() < 0.007,
        "the machine is at X{x} Y{y}, the job ends at X{} Y{}: a move ran twice or not at \
         all\n{report}",
        x0 + dx,
        y0 + dy
    );
    let summary = sim.stop();
    let damage = summary
        .iter()
        .find(|l| l.starts_with("pty:") && l.contains("corrupted"))
        .cloned()
        .unwrap_or_default();
    println!("{report}{damage}");
    let corrupted: u64 = damage
        .split(", ")
        .find_map(|part| part.strip_suffix(" corrupted)"))
        .and_then(|n| n.parse().ok())
        .unwrap_or(0);
    assert!(corrupted > 0, "the link damaged nothing: {summary:?}");
}

#[test]
fn printrun_streams_a_sliced_job_with_no_line_refused() {
    let python = printrun_python();
    let dir = scratch("printrun-sliced");
    let sim = Sim::start_paced(&dir, "8", &["--machine", "builtin:printer"]);
    let job = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/corpus/slicers/cura.gcode");
    let report = stream(&python, &sim.pty, &job, 240);
    let summary = sim.stop();
    let controller = summary
        .iter()
        .find(|l| l.starts_with("controller:"))
        .unwrap_or_else(|| panic!("no controller summary: {summary:?}"));
    println!("{report}{controller}");
    assert!(
        controller.contains(" 0 refused"),
        "a line of the sliced job was refused: {controller}\n{report}"
    );
}
