//! OctoPrint, a printer host in wide use, drives the simulator's printer over its
//! pseudo-terminal with its default serial settings. The first test connects, heats, prints a
//! sliced job, pauses, resumes and cancels a second print, and sends the job to the printer's
//! SD card and prints it from there: the firmware must give OctoPrint no error and ask for no
//! resend on the way. The second prints the job while the simulator's link damages bytes, and
//! the extruder must end where the job puts it: every move ran exactly once.
//!
//! The real server runs (`octoprint serve`, driven through its REST API by
//! `tests/octoprint/drive.py`); it is installed with its dependencies into a virtual
//! environment inside the checkout (`target/octoprint-venv`, `pip install octoprint==1.11.8`)
//! the first time; if that fails the test fails and says why. The job is PrusaSlicer's from
//! the slicer corpus (`tests/corpus/slicers/prusaslicer.gcode`): its start code with the
//! machine limits, the heating waits and homing, six layers of a 20 x 20 mm plate with
//! relative extrusion, retractions and wipes, `M73` progress, and its end code.
//!
//! Each test prints drive.py's report: one line per step, the firmware's error lines, resend
//! requests and unknown commands as OctoPrint's serial log recorded them, and on failure the
//! tail of that log and OctoPrint's state changes and warnings. OctoPrint and the simulator
//! are stopped whatever happens: drive.py runs in a process group of its own, which is ended
//! at the time limit, and OctoPrint dies with drive.py.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use common::{Driver, Sim, axis, positions, scratch, settle, venv_python, with};
use forja_sim_hal::link::{FaultConfig, FaultyBytes};

/// The OctoPrint release the tests run.
const OCTOPRINT: &str = "octoprint==1.11.8";

/// How long drive.py may take for all its steps, and how long past that it is given to stop
/// OctoPrint and report before its process group is killed.
const DRIVE_LIMIT: Duration = Duration::from_secs(300);
const STOP_GRACE: Duration = Duration::from_secs(30);

fn manifest_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The virtual environment's Python with OctoPrint installed, created and filled if needed.
fn octoprint_python() -> PathBuf {
    let wanted = OCTOPRINT.split("==").nth(1).expect("a pinned version");
    let ready = format!(
        "import importlib.metadata as m, sys; sys.exit(m.version('octoprint') != '{wanted}')"
    );
    venv_python("octoprint-venv", &[OCTOPRINT], false, &ready)
}

/// Start drive.py (OctoPrint in its process group) on `sim` for `steps`.
fn drive(python: &Path, sim: &Sim, dir: &Path, steps: &str) -> Driver {
    let mut command = Command::new(python);
    command
        .arg(manifest_dir().join("tests/octoprint/drive.py"))
        .arg("--pty")
        .arg(&sim.pty)
        .arg("--job")
        .arg(job_file())
        .arg("--basedir")
        .arg(dir.join("octoprint"))
        .args(["--seconds", &DRIVE_LIMIT.as_secs().to_string()])
        .args(["--steps", steps])
        .env("PYTHONUNBUFFERED", "1");
    Driver::start(command, dir.join("drive.out"), "drive.py")
}

/// The sliced job the tests print.
fn job_file() -> PathBuf {
    manifest_dir().join("../tests/corpus/slicers/prusaslicer.gcode")
}

/// How much faster than the wall clock the printer's time runs: the heating waits and the
/// moves of three prints take a minute or two of wall time. `common::Sim` runs at 4.
const TIME_SCALE: &str = "8";

/// The count drive.py reports on its line `octoprint: <what> N`, if it does.
fn reported(report: &str, what: &str) -> Option<u64> {
    let prefix = format!("octoprint: {what} ");
    report
        .lines()
        .find_map(|l| l.strip_prefix(prefix.as_str()))
        .and_then(|n| n.trim().parse().ok())
}

#[test]
fn octoprint_connects_heats_prints_pauses_and_prints_from_the_sd_card() {
    let python = octoprint_python();
    let dir = scratch("octoprint");
    let sim = Sim::start_paced(&dir, TIME_SCALE, &["--machine", "builtin:printer"]);
    let (success, report) = drive(&python, &sim, &dir, "connect,temperatures,print,pause,sd")
        .finish(DRIVE_LIMIT, STOP_GRACE);
    let summary = sim.stop();
    println!("{report}{}", summary.join("\n"));
    assert!(success, "OctoPrint failed:\n{report}");
    for step in [
        "connect",
        "temperatures",
        "print",
        "pause",
        "sd-upload",
        "sd",
    ] {
        assert!(
            report.contains(&format!("octoprint: {step} ok")),
            "no `{step} ok`:\n{report}"
        );
    }
    assert_eq!(
        reported(&report, "firmware errors"),
        Some(0),
        "OctoPrint saw firmware errors:\n{report}"
    );
    // The link damages nothing here: a resend request refused a good line.
    assert_eq!(
        reported(&report, "resend requests"),
        Some(0),
        "the firmware asked OctoPrint to resend lines on an undamaged link:\n{report}"
    );
}

/// How far `job` moves the filament in all, as Marlin reads it: a move's E is a distance
/// under `M83` or `G91`, else a position whose change is the distance; `G92 E` sets the
/// position without moving; `M221 S<percent>` scales the distances that follow (the flow).
/// A move lost or run twice changes where the extruder ends.
fn job_extrusion_mm(job: &str) -> f64 {
    let (mut e_relative, mut all_relative) = (false, false);
    let (mut position, mut travel, mut flow) = (0.0, 0.0, 1.0);
    for line in job.lines() {
        let code = line.split(';').next().unwrap_or_default();
        let Some(command) = code.split_whitespace().next() else {
            continue;
        };
        let word = |letter: char| {
            code.split_whitespace()
                .skip(1)
                .find_map(|w| w.strip_prefix(letter))
                .map(|v| v.parse::<f64>().expect("numbers after the letters"))
        };
        let distance = match (command, word('E')) {
            ("M82", _) => {
                e_relative = false;
                continue;
            }
            ("M83", _) => {
                e_relative = true;
                continue;
            }
            ("G90", _) => {
                all_relative = false;
                continue;
            }
            ("G91", _) => {
                all_relative = true;
                continue;
            }
            ("M221", _) => {
                flow = word('S').map_or(flow, |percent| percent / 100.0);
                continue;
            }
            ("G92", Some(e)) => {
                position = e;
                continue;
            }
            ("G0" | "G1" | "G2" | "G3", Some(e)) if e_relative || all_relative => e,
            ("G0" | "G1" | "G2" | "G3", Some(e)) => e - position,
            _ => continue,
        };
        position += distance;
        travel += distance * flow;
    }
    travel
}

/// The damage of the link in the test below. OctoPrint checks its lines with the RepRap
/// XOR checksum only, which misses two flips of one bit in a line (and a few other pairs):
/// at a rate of 1 % about a line in 150 arrives damaged with a valid checksum, and no
/// firmware can then run every move as written. So the rate is low and the seed one whose
/// flips, as `FaultyBytes` draws them, lie at least `LINE_SPAN` bytes apart over the first
/// `ISOLATED_BYTES` bytes: every damaged line has one flipped bit, which the checksum shows.
const CORRUPT_RATE: f64 = 0.0003;
const SEED: u64 = 55;
const LINE_SPAN: u64 = 256;
const ISOLATED_BYTES: u64 = 100_000;

/// How many bytes of the first `ISOLATED_BYTES` the link damages, or the first two damaged
/// bytes closer than `LINE_SPAN`.
fn isolated_flips() -> Result<u64, (u64, u64)> {
    let config = FaultConfig {
        corrupt_rate: CORRUPT_RATE,
        drop_rate: 0.0,
        seed: SEED,
    };
    let mut faults = FaultyBytes::new(config).expect("a valid fault configuration");
    let (mut last, mut count) = (None::<u64>, 0);
    for at in 0..ISOLATED_BYTES {
        if faults.apply(0) != Some(0) {
            match last {
                Some(before) if at - before < LINE_SPAN => return Err((before, at)),
                _ => {}
            }
            last = Some(at);
            count += 1;
        }
    }
    Ok(count)
}

/// The number before `suffix` in the simulator's summary line for the pseudo-terminal.
fn pty_count(summary: &[String], suffix: &str) -> u64 {
    summary
        .iter()
        .filter(|l| l.starts_with("pty:"))
        .flat_map(|l| l.split([',', '(', ')']))
        .find_map(|part| part.trim().strip_suffix(suffix))
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or(0)
}

#[test]
fn octoprint_prints_through_a_damaging_link_and_every_move_runs_once() {
    let flips = isolated_flips().unwrap_or_else(|(a, b)| {
        panic!(
            "seed {SEED} damages bytes {a} and {b}, which may be one line: choose a seed whose \
             flips are {LINE_SPAN} bytes apart"
        )
    });
    assert!(flips > 10, "seed {SEED} damages only {flips} bytes");
    let python = octoprint_python();
    let dir = scratch("octoprint-damaged");
    let (rate, seed) = (CORRUPT_RATE.to_string(), SEED.to_string());
    let sim = Sim::start_paced(
        &dir,
        TIME_SCALE,
        &[
            "--machine",
            "builtin:printer",
            "--corrupt-rate",
            &rate,
            "--seed",
            &seed,
        ],
    );
    let job = std::fs::read_to_string(job_file()).unwrap();
    let extruded = job_extrusion_mm(&job);
    let link = with(&sim.pty_args(), &[]);
    let before = axis(&positions(&link), 'E');
    let (success, report) =
        drive(&python, &sim, &dir, "connect,print").finish(DRIVE_LIMIT, STOP_GRACE);
    // drive.py has disconnected OctoPrint: the port is free for `forja status`, whose E is
    // the extruder's position as its steps put it, whatever `G92` said.
    let after = if success {
        Some(axis(&settle(&link, Duration::from_secs(30)), 'E'))
    } else {
        None
    };
    let summary = sim.stop();
    println!("{report}{}", summary.join("\n"));
    let received = pty_count(&summary, " bytes received");
    assert!(
        received <= ISOLATED_BYTES,
        "the link carried {received} bytes, past the {ISOLATED_BYTES} whose flips are known \
         to be apart: {summary:?}"
    );
    assert!(success, "OctoPrint failed:\n{report}");
    let after = after.expect("measured after a successful run");
    assert!(
        (after - before - extruded).abs() < 0.03,
        "E moved {:.4} mm, the job extrudes {extruded:.4} mm: a move ran twice or not at \
         all\n{report}",
        after - before
    );
    let corrupted = pty_count(&summary, " corrupted");
    assert!(corrupted > 0, "the link damaged nothing: {summary:?}");
}
