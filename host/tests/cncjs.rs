//! CNCjs, the web-based controller for CNC machines and printers, drives the simulator's printer
//! in its Marlin mode over the pseudo-terminal: it connects and becomes ready on the `M115`
//! answer, shows the position from its `M114` polls after a move, pauses its job on the
//! `Error:` line of a hard limit, runs a sliced job to its last line with no error, and ends a
//! job only once the machine is at rest.
//!
//! The real server runs (the `cncjs` command of the npm package, driven through its socket.io
//! API by `tests/cncjs/drive.js` with the system `node`); it is installed with its dependencies
//! into `target/cncjs` (`npm install --prefix target/cncjs cncjs@1`) the first time; if that
//! fails the test fails and says why. The job is Cura's from the slicer corpus
//! (`tests/corpus/slicers/cura.gcode`): its heating waits, homing, six layers of a 20 x 20 mm
//! plate with absolute extrusion and retractions, and its end code.
//!
//! The test prints drive.js's report: one line per step, the firmware's `Error:` lines, the
//! commands it said it does not have and the lines it refused, as CNCjs passed them on; on
//! failure the last lines CNCjs logged and the last serial lines. CNCjs and the simulator are
//! stopped whatever happens: drive.js runs in a process group of its own, which is ended at the
//! time limit, and the CNCjs server exits when drive.js is gone.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use common::{Driver, Sim, scratch};

/// The CNCjs release line the test runs.
const CNCJS: &str = "cncjs@1";

/// How long drive.js may take for all its steps, and how long past that it is given to stop
/// CNCjs and report before its process group is killed.
const DRIVE_LIMIT: Duration = Duration::from_secs(170);
const STOP_GRACE: Duration = Duration::from_secs(20);

/// The steps drive.js reports `ok` for, in order.
const STEPS: [&str; 6] = ["server", "connect", "position", "fault", "job", "finish"];

fn manifest_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The npm prefix CNCjs is installed into, installed if needed.
fn cncjs_prefix() -> PathBuf {
    let prefix = manifest_dir().join("../target/cncjs");
    let ready = |prefix: &Path| {
        let modules = prefix.join("node_modules");
        Command::new("node")
            .arg("-e")
            .arg(
                "const [m] = process.argv.slice(1); \
                 const v = require(m + '/cncjs/package.json').version; \
                 require.resolve(m + '/socket.io-client'); \
                 require.resolve(m + '/jsonwebtoken'); \
                 process.exit(v.startsWith('1.') ? 0 : 1)",
            )
            .arg(&modules)
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if ready(&prefix) {
        return prefix;
    }
    std::fs::create_dir_all(&prefix)
        .unwrap_or_else(|e| panic!("cannot make {}: {e}", prefix.display()));
    let npm = Command::new("npm")
        .args(["install", "--no-audit", "--no-fund", "--prefix"])
        .arg(&prefix)
        .arg(CNCJS)
        .stdin(Stdio::null())
        .output()
        .unwrap_or_else(|e| panic!("cannot run npm to install {CNCJS}: {e}"));
    assert!(
        npm.status.success(),
        "npm could not install {CNCJS} into {}: {}{}",
        prefix.display(),
        String::from_utf8_lossy(&npm.stdout),
        String::from_utf8_lossy(&npm.stderr)
    );
    assert!(
        ready(&prefix),
        "{CNCJS} was installed into {} but its package, socket.io-client or jsonwebtoken \
         does not load with `node`",
        prefix.display()
    );
    prefix
}

/// Start drive.js (the CNCjs server in its process group) on `sim`.
fn drive(prefix: &Path, sim: &Sim, dir: &Path) -> Driver {
    let mut command = Command::new("node");
    command
        .arg(manifest_dir().join("tests/cncjs/drive.js"))
        .arg("--cncjs")
        .arg(prefix)
        .arg("--pty")
        .arg(&sim.pty)
        .arg("--job")
        .arg(manifest_dir().join("../tests/corpus/slicers/cura.gcode"))
        .arg("--workdir")
        .arg(dir.join("cncjs"))
        .args(["--seconds", &DRIVE_LIMIT.as_secs().to_string()]);
    Driver::start(command, dir.join("drive.out"), "drive.js")
}

#[test]
fn cncjs_connects_shows_positions_pauses_on_a_fault_and_runs_a_sliced_job() {
    let prefix = cncjs_prefix();
    let dir = scratch("cncjs");
    // Virtual time 8 times as fast as the wall clock: the sliced job takes 7 minutes of it.
    let sim = Sim::start_paced(&dir, "8", &["--machine", "builtin:printer"]);
    let (success, report) = drive(&prefix, &sim, &dir).finish(DRIVE_LIMIT, STOP_GRACE);
    let summary = sim.stop();
    println!("{report}{}", summary.join("\n"));
    assert!(success, "CNCjs failed:\n{report}");
    for step in STEPS {
        assert!(
            report.contains(&format!("cncjs: {step} ok")),
            "no `{step} ok`:\n{report}"
        );
    }
    // The hard limit of the fault step is the one error; the job itself has none.
    assert!(
        report.contains("cncjs: firmware errors 1\n  Error:E150 hard-limit X\n"),
        "the firmware sent other errors than the hard limit:\n{report}"
    );
}
