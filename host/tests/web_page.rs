//! The operator's web page (`web/page/`, served by the board's web link) drives the simulator's
//! printer end to end in a real headless Chromium, as a person at the machine would: it loads
//! the page from `forja-sim --http-port`, which talks to the controller over its WebSocket;
//! a second page is told it watches and has its controls disabled; the first uploads a program
//! into the program store through the file picker (and a program that does not fit is refused
//! before anything is sent), sets the hot end's target, starts the program, pauses it (the page
//! shows it paused and the position stays put) and resumes it, sees its progress reach 100 %
//! on both pages, jogs X, and finds the position it shows in the answer to `M114` typed in its
//! console; its keep-alive shows "connection lost" while the simulator is stopped (SIGSTOP),
//! and when it closes the watching page is given control. The steps are `tests/web/drive.js`'s
//! (see there).
//!
//! Chromium is Debian's (`/usr/bin/chromium`, which `.ci/run` installs), driven over the
//! DevTools protocol by `puppeteer-core`, which downloads no browser; it is installed with npm
//! into `target/web-e2e` the first time (`npm install --prefix target/web-e2e
//! puppeteer-core@24`); if that fails the test fails and says why. The driver saves
//! screenshots of the page idle (the program loaded) and in the middle of the job to
//! `target/web-e2e/idle.png` and `target/web-e2e/job.png` (`docs/images/web-page.png` is one).
//!
//! The driver runs in a process group of its own with Chromium in it, which is ended at the
//! time limit; the simulator is stopped whatever happens.

mod common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use common::{Driver, npm_prefix, scratch, sim_binary};

/// The puppeteer-core release line the driver uses (24 runs on Node 18 and later).
const PUPPETEER: &str = "puppeteer-core@24";

/// How long drive.js may take for all its steps (about 20 s of them), and how long past that
/// the driver is given to close Chromium and report before its process group is killed.
const DRIVE_LIMIT: Duration = Duration::from_secs(45);
const STOP_GRACE: Duration = Duration::from_secs(10);

/// The steps drive.js reports `ok` for, in order.
const STEPS: [&str; 12] = [
    "load", "watch", "upload", "refuse", "heat", "start", "pause", "resume", "finish", "jog",
    "lost", "handover",
];

/// Virtual time twice as fast as the wall clock: the program takes 17 s of it, long enough
/// for the page to be seen running, paused and resumed while its polls come every 500 ms.
const TIME_SCALE: &str = "2";

fn manifest_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// `target/web-e2e`: the npm prefix of puppeteer-core, and where the screenshots go.
fn e2e_dir() -> PathBuf {
    manifest_dir().join("../target/web-e2e")
}

/// The `node_modules` that holds puppeteer-core, installed if needed.
fn puppeteer_modules() -> PathBuf {
    npm_prefix(
        "web-e2e",
        PUPPETEER,
        "const [m] = process.argv.slice(1); \
         const v = require(m + '/puppeteer-core/package.json').version; \
         require(m + '/puppeteer-core'); \
         process.exit(v.startsWith('24.') ? 0 : 1)",
    )
    .join("node_modules")
}

/// The system's Chromium: Debian's package, never a browser of npm's.
fn chromium() -> PathBuf {
    let found = ["/usr/bin/chromium", "/usr/bin/chromium-browser"]
        .into_iter()
        .map(PathBuf::from)
        .find(|p| p.exists());
    found.unwrap_or_else(|| {
        panic!(
            "Chromium is not installed (no /usr/bin/chromium): `apt-get install chromium` \
             (.ci/run installs it when it is missing)"
        )
    })
}

/// `forja-sim --listen` on the printer with its web link on a free port.
struct WebSim {
    child: Child,
    /// `http://127.0.0.1:PORT/`, the page.
    url: String,
}

impl WebSim {
    fn start(dir: &Path) -> WebSim {
        let mut child = Command::new(sim_binary())
            .args(["--listen", "--time-scale", TIME_SCALE])
            .args(["--tcp-port", "0", "--http-port", "0"])
            .args(["--machine", "builtin:printer", "--sd-dir"])
            .arg(dir.join("sd"))
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("forja-sim starts");
        let stdout = child.stdout.take().expect("piped");
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut sim = WebSim {
            child,
            url: String::new(),
        };
        while sim.url.is_empty() {
            let line = rx
                .recv_timeout(Duration::from_secs(20))
                .expect("forja-sim prints the address of its web link (`http: ADDR:PORT`)");
            if let Some(addr) = line.strip_prefix("http: ") {
                sim.url = format!("http://{}/", addr.trim());
            }
        }
        sim
    }
}

impl Drop for WebSim {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Whether `path` is a PNG image of a few kilobytes at least (a page, not a blank).
fn is_screenshot(path: &Path) -> bool {
    std::fs::read(path)
        .is_ok_and(|bytes| bytes.starts_with(b"\x89PNG\r\n\x1a\n") && bytes.len() > 20_000)
}

#[test]
fn the_web_page_runs_a_job_in_headless_chromium() {
    let modules = puppeteer_modules();
    let chromium = chromium();
    let dir = scratch("web-page");
    let out = e2e_dir();
    for shot in ["idle.png", "job.png"] {
        let _ = std::fs::remove_file(out.join(shot));
    }
    let sim = WebSim::start(&dir);
    let tests = manifest_dir().join("tests/web");
    let mut command = Command::new("node");
    command
        .arg(tests.join("drive.js"))
        .arg("--modules")
        .arg(&modules)
        .arg("--chromium")
        .arg(&chromium)
        .args(["--url", &sim.url])
        .args(["--sim-pid", &sim.child.id().to_string()])
        .arg("--program")
        .arg(tests.join("part.gcode"))
        .arg("--bad")
        .arg(tests.join("bad.gcode"))
        .arg("--out")
        .arg(&out)
        .arg("--workdir")
        .arg(&dir)
        .args(["--seconds", &DRIVE_LIMIT.as_secs().to_string()]);
    let (success, report) =
        Driver::start(command, dir.join("drive.out"), "drive.js").finish(DRIVE_LIMIT, STOP_GRACE);
    drop(sim);
    println!("{report}");
    assert!(
        success,
        "the web page failed (screenshots of the pages at the failure in {}):\n{report}",
        dir.display()
    );
    for step in STEPS {
        assert!(
            report.contains(&format!("web: {step} ok")),
            "no `{step} ok`:\n{report}"
        );
    }
    for shot in ["idle.png", "job.png"] {
        assert!(
            is_screenshot(&out.join(shot)),
            "{} is not a screenshot of the page",
            out.join(shot).display()
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
