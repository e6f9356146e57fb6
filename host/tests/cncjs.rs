//! CNCjs, the web-based controller for CNC machines and printers, drives the simulator over the
//! pseudo-terminal in two of its modes.
//!
//! In its Marlin mode it drives the printer: it connects and becomes ready on the `M115`
//! answer, shows the position from its `M114` polls after a move, pauses its job on the
//! `Error:` line of a hard limit, runs a sliced job to its last line with no error, and ends a
//! job only once the machine is at rest. The job is Cura's from the slicer corpus
//! (`tests/corpus/slicers/cura.gcode`): its heating waits, homing, six layers of a 20 x 20 mm
//! plate with absolute extrusion and retractions, and its end code.
//!
//! In its Grbl mode it drives the router (the link speaks grbl 1.1, `docs/protocol.md` §9): it
//! polls with `?` when it sees no banner and becomes ready on the status report, shows the
//! machine state and position of the reports, jogs with `$J=`, runs a CAM program
//! (`tests/corpus/cam/cncjs-smoke.nc`) to its end through a feed hold and resume (`!`, `~`) and
//! a feed override change (0x91) that a later `Ov:` shows, and resets it mid-way (0x18): the
//! banner comes again, the machine is in `ALARM:3`, `$X` unlocks it and the program runs again
//! to its end, where `forja status` then finds the machine.
//!
//! The real server runs (the `cncjs` command of the npm package, driven through its socket.io
//! API by `tests/cncjs/drive.js` and `tests/cncjs/drive_grbl.js` with the system `node`); it is
//! installed with its dependencies into `target/cncjs` (`npm install --prefix target/cncjs
//! cncjs@1`) the first time; if that fails the test fails and says why.
//!
//! The tests print the driver's report: one line per step and what the firmware sent that
//! CNCjs took for an error or did not understand; on failure the last lines CNCjs logged, the
//! last serial lines (and, in the Grbl mode, CNCjs's last states). CNCjs and the simulator are
//! stopped whatever happens: the driver runs in a process group of its own, which is ended at
//! the time limit, and the CNCjs server exits when the driver is gone.

mod common;

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use common::{Driver, Sim, axis, npm_prefix, positions, scratch, settle};

/// The CNCjs release line the test runs.
const CNCJS: &str = "cncjs@1";

/// How long drive.js may take for all its steps, and how long past that a driver is given to
/// stop CNCjs and report before its process group is killed.
const DRIVE_LIMIT: Duration = Duration::from_secs(170);
const STOP_GRACE: Duration = Duration::from_secs(20);

/// The steps drive.js reports `ok` for, in order.
const STEPS: [&str; 6] = ["server", "connect", "position", "fault", "job", "finish"];

/// How long drive_grbl.js may take for all its steps (about 30 s of them).
const GRBL_DRIVE_LIMIT: Duration = Duration::from_secs(120);

/// The steps drive_grbl.js reports `ok` for, in order.
const GRBL_STEPS: [&str; 6] = ["server", "connect", "jog", "job", "reset", "again"];

/// Virtual time 4 times as fast as the wall clock for the router: the CAM program takes 35 s
/// of it, about 9 s, while CNCjs polls the status every 250 ms of the wall clock and must see
/// the program run, hold, resume and change its override before it ends.
const GRBL_TIME_SCALE: &str = "4";

/// The positions of the simulator and of a program agree when closer than this, mm: less than
/// a step of the router's X and Y (1/80 mm).
const TOLERANCE_MM: f64 = 0.01;

fn manifest_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The npm prefix CNCjs is installed into (`target/cncjs`), installed if needed.
fn cncjs_prefix() -> PathBuf {
    npm_prefix(
        "cncjs",
        CNCJS,
        "const [m] = process.argv.slice(1); \
         const v = require(m + '/cncjs/package.json').version; \
         require.resolve(m + '/socket.io-client'); \
         require.resolve(m + '/jsonwebtoken'); \
         process.exit(v.startsWith('1.') ? 0 : 1)",
    )
}

/// Start `script` of tests/cncjs (the CNCjs server in its process group) on `sim`, with `args`
/// after the ones every driver takes, its steps given `limit`.
fn drive(
    script: &'static str,
    prefix: &Path,
    sim: &Sim,
    dir: &Path,
    limit: Duration,
    args: &[&OsStr],
) -> Driver {
    let mut command = Command::new("node");
    command
        .arg(manifest_dir().join("tests/cncjs").join(script))
        .arg("--cncjs")
        .arg(prefix)
        .arg("--pty")
        .arg(&sim.pty)
        .arg("--workdir")
        .arg(dir.join("cncjs"))
        .args(["--seconds", &limit.as_secs().to_string()])
        .args(args);
    Driver::start(command, dir.join("drive.out"), script)
}

/// Where a program that moves only in absolute coordinates leaves X, Y and Z: the last value
/// each of them takes. Comments (in parentheses, after `;`) are left out; a program with a
/// word that makes that rule wrong (`G91` relative moves, `G92` offsets, `G28`/`G30`
/// returns, `G53` machine moves, `G10` offsets) is refused, and so is one that does not set
/// all three.
fn program_end(text: &str) -> [(char, f64); 3] {
    let mut end = [('X', None), ('Y', None), ('Z', None)];
    for raw in text.lines() {
        let mut code = String::new();
        let mut depth = 0usize;
        for c in raw.split(';').next().unwrap_or_default().chars() {
            match c {
                '(' => depth += 1,
                ')' => depth = depth.saturating_sub(1),
                _ if depth == 0 => code.push(c.to_ascii_uppercase()),
                _ => {}
            }
        }
        let mut words = Vec::new();
        let mut rest = code.as_str();
        while let Some(start) = rest.find(|c: char| c.is_ascii_uppercase()) {
            let letter = rest[start..].chars().next().unwrap_or_default();
            let tail = &rest[start + 1..];
            let len = tail
                .find(|c: char| !(c.is_ascii_digit() || matches!(c, '.' | '-' | '+' | ' ')))
                .unwrap_or(tail.len());
            let number: String = tail[..len].chars().filter(|c| *c != ' ').collect();
            words.push((letter, number.parse::<f64>().ok()));
            rest = &tail[len..];
        }
        for (letter, value) in &words {
            let refused = *letter == 'G'
                && value.is_some_and(|v| [91.0, 92.0, 28.0, 30.0, 53.0, 10.0].contains(&v));
            assert!(
                !refused,
                "the program has `{raw}`: where it ends is not its last X, Y and Z words"
            );
            if let Some(slot) = end.iter_mut().find(|slot| slot.0 == *letter) {
                slot.1 = *value;
            }
        }
    }
    end.map(|(axis, value)| {
        (
            axis,
            value.unwrap_or_else(|| panic!("the program never sets {axis}")),
        )
    })
}

#[test]
fn cncjs_connects_shows_positions_pauses_on_a_fault_and_runs_a_sliced_job() {
    let prefix = cncjs_prefix();
    let dir = scratch("cncjs");
    // Virtual time 8 times as fast as the wall clock: the sliced job takes 7 minutes of it.
    let sim = Sim::start_paced(&dir, "8", &["--machine", "builtin:printer"]);
    let job = manifest_dir().join("../tests/corpus/slicers/cura.gcode");
    let args = [OsStr::new("--job"), job.as_os_str()];
    let (success, report) =
        drive("drive.js", &prefix, &sim, &dir, DRIVE_LIMIT, &args).finish(DRIVE_LIMIT, STOP_GRACE);
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

#[test]
fn cncjs_drives_a_router_as_a_grbl_controller() {
    let prefix = cncjs_prefix();
    let dir = scratch("cncjs-grbl");
    let sim = Sim::start_paced(&dir, GRBL_TIME_SCALE, &["--machine", "builtin:default"]);
    let program = manifest_dir().join("../tests/corpus/cam/cncjs-smoke.nc");
    let text = std::fs::read_to_string(&program)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", program.display()));
    let end = program_end(&text);
    let link = sim.pty_args();
    let start = positions(&link);
    let args = [OsStr::new("--program"), program.as_os_str()];
    let driver = drive(
        "drive_grbl.js",
        &prefix,
        &sim,
        &dir,
        GRBL_DRIVE_LIMIT,
        &args,
    );
    let (success, report) = driver.finish(GRBL_DRIVE_LIMIT, STOP_GRACE);
    // drive_grbl.js has closed the port: it is free for `forja status`, whose positions are
    // where the simulator's steps put the axes.
    let at = success.then(|| settle(&link, Duration::from_secs(30)));
    let summary = sim.stop();
    println!("{report}{}", summary.join("\n"));
    assert!(success, "CNCjs failed:\n{report}");
    for step in GRBL_STEPS {
        assert!(
            report.contains(&format!("cncjs: {step} ok")),
            "no `{step} ok`:\n{report}"
        );
    }
    assert!(
        report.contains("cncjs: firmware errors 0\n"),
        "the firmware refused lines:\n{report}"
    );
    // The reset that cut the motion raised the one alarm.
    assert!(
        report.contains("cncjs: alarms 1\n  ALARM:3\n"),
        "the firmware raised other alarms than the reset's ALARM:3:\n{report}"
    );
    assert!(
        report.contains("cncjs: lines CNCjs's Grbl parser does not know 0\n"),
        "the firmware sent lines in the grbl dialect that are none of grbl's:\n{report}"
    );
    let at = at.expect("measured after a successful run");
    for (letter, mm) in end {
        assert!(
            (axis(&at, letter) - mm).abs() < TOLERANCE_MM,
            "after the program ran again from where the reset left the machine, \
             `forja status` finds {letter} at {} mm; the program ends at {mm} mm \
             ({at:?})\n{report}",
            axis(&at, letter)
        );
    }
    assert!(
        (axis(&at, 'A') - axis(&start, 'A')).abs() < TOLERANCE_MM,
        "A moved from {} to {} mm; the program never names it",
        axis(&start, 'A'),
        axis(&at, 'A')
    );
}
