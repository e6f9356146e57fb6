//! The simulator as the tests run it: the `forja-sim` binary listening on TCP and a
//! pseudo-terminal, its virtual time four times as fast as the wall clock (the moves take less
//! waiting) unless a test asks for another pace, and the `forja` binary run against it; and the
//! Python environments and npm prefixes in which the tests install the hosts and tools they
//! drive (Printrun, OctoPrint, CNCjs, Puppeteer).

#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Mutex, mpsc};
use std::time::{Duration, Instant};

/// The `forja-sim` binary, brought up to date with the firmware's sources once per test
/// binary (`forja-simulator` is no dependency of this crate, so `cargo test -p forja-host`
/// alone would otherwise run a simulator built before the last change).
pub fn sim_binary() -> PathBuf {
    static BUILT: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    BUILT
        .get_or_init(|| {
            let exe = std::env::current_exe().expect("the test's own path");
            // target/<profile>/deps/<test> → target/<profile>/forja-sim
            let profile_dir = exe
                .parent()
                .and_then(Path::parent)
                .expect("the test runs from target/<profile>/deps");
            let bin = profile_dir.join(format!("forja-sim{}", std::env::consts::EXE_SUFFIX));
            let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
            let status = Command::new(cargo)
                .args(["build", "-p", "forja-simulator", "--bin", "forja-sim"])
                .status()
                .expect("cargo runs");
            assert!(status.success(), "building forja-sim failed");
            assert!(bin.exists(), "{} was not built", bin.display());
            bin
        })
        .clone()
}

/// The Python of a virtual environment inside the checkout (`target/<name>`), with
/// `packages` installed by pip (`--no-deps` when `no_deps`) if `ready` (a Python statement
/// that exits non-zero when they are not there) fails. The test fails, saying why, when pip
/// cannot install them. One test at a time makes or fills an environment: the tests of a file
/// run in parallel and share theirs.
pub fn venv_python(name: &str, packages: &[&str], no_deps: bool, ready: &str) -> PathBuf {
    static INSTALLING: Mutex<()> = Mutex::new(());
    let _one = INSTALLING.lock().unwrap_or_else(|e| e.into_inner());
    let venv = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../target")
        .join(name);
    let python = venv.join("bin").join("python");
    let is_ready = |python: &Path| {
        Command::new(python)
            .args(["-c", ready])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if python.exists() && is_ready(&python) {
        return python;
    }
    let made = Command::new("python3")
        .args(["-m", "venv"])
        .arg(&venv)
        .output()
        .unwrap_or_else(|e| panic!("cannot run python3 to make {}: {e}", venv.display()));
    assert!(
        made.status.success(),
        "python3 -m venv {} failed: {}",
        venv.display(),
        String::from_utf8_lossy(&made.stderr)
    );
    let pip = Command::new(&python)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
        ])
        .args(no_deps.then_some("--no-deps"))
        .args(packages)
        .output()
        .expect("the virtual environment's python runs");
    assert!(
        pip.status.success(),
        "pip could not install {} into {}: {}{}",
        packages.join(" "),
        venv.display(),
        String::from_utf8_lossy(&pip.stdout),
        String::from_utf8_lossy(&pip.stderr)
    );
    assert!(
        is_ready(&python),
        "{} was installed into {} but `{ready}` fails",
        packages.join(" "),
        venv.display()
    );
    python
}

/// The npm prefix `target/<name>` inside the checkout, with `package` installed into it by npm
/// if `ready` (a Node script given the prefix's `node_modules` as its argument, which exits
/// non-zero when what the test needs does not load) fails. The test fails, saying why, when
/// npm cannot install it. One test at a time checks or fills a prefix: the tests of a file run
/// in parallel and share theirs.
pub fn npm_prefix(name: &str, package: &str, ready: &str) -> PathBuf {
    static INSTALLING: Mutex<()> = Mutex::new(());
    let _one = INSTALLING.lock().unwrap_or_else(|e| e.into_inner());
    let prefix = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../target")
        .join(name);
    let is_ready = |prefix: &Path| {
        Command::new("node")
            .args(["-e", ready])
            .arg(prefix.join("node_modules"))
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if is_ready(&prefix) {
        return prefix;
    }
    std::fs::create_dir_all(&prefix)
        .unwrap_or_else(|e| panic!("cannot make {}: {e}", prefix.display()));
    let npm = Command::new("npm")
        .args(["install", "--no-audit", "--no-fund", "--prefix"])
        .arg(&prefix)
        .arg(package)
        .stdin(Stdio::null())
        .output()
        .unwrap_or_else(|e| panic!("cannot run npm to install {package}: {e}"));
    assert!(
        npm.status.success(),
        "npm could not install {package} into {}: {}{}",
        prefix.display(),
        String::from_utf8_lossy(&npm.stdout),
        String::from_utf8_lossy(&npm.stderr)
    );
    assert!(
        is_ready(&prefix),
        "{package} was installed into {} but `{ready}` fails with `node`",
        prefix.display()
    );
    prefix
}

/// A scratch directory for one test.
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("forja-host-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A running simulator.
pub struct Sim {
    child: Child,
    /// Its TCP address.
    pub tcp: String,
    /// A stable path to its pseudo-terminal.
    pub pty: PathBuf,
    /// What it printed on standard output after the addresses.
    lines: mpsc::Receiver<String>,
}

impl Sim {
    /// Start `forja-sim --listen` with `extra` arguments, and wait for its addresses.
    pub fn start(dir: &Path, extra: &[&str]) -> Sim {
        Self::start_paced(dir, "4", extra)
    }

    /// [`Sim::start`] with virtual time `time_scale` times as fast as the wall clock.
    pub fn start_paced(dir: &Path, time_scale: &str, extra: &[&str]) -> Sim {
        let pty = dir.join("tty");
        let mut child = Command::new(sim_binary())
            .args([
                "--listen",
                "--time-scale",
                time_scale,
                "--tcp-port",
                "0",
                "--pty-link",
            ])
            .arg(&pty)
            .args(extra)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("forja-sim starts");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut tcp = None;
        while tcp.is_none() || !pty.exists() {
            let line = rx
                .recv_timeout(Duration::from_secs(20))
                .expect("forja-sim prints its addresses");
            if let Some(addr) = line.strip_prefix("tcp: ") {
                tcp = Some(addr.trim().to_string());
            }
        }
        Sim {
            child,
            tcp: tcp.unwrap(),
            pty,
            lines: rx,
        }
    }

    /// `--tcp ADDR`.
    pub fn tcp_args(&self) -> Vec<String> {
        vec!["--tcp".into(), self.tcp.clone()]
    }

    /// `--port PTY`.
    pub fn pty_args(&self) -> Vec<String> {
        vec!["--port".into(), self.pty.display().to_string()]
    }

    /// Stop it as Ctrl-C would (it writes its trace and summary) and return what it printed.
    pub fn stop(mut self) -> Vec<String> {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let _ = self.child.wait();
        let mut out = Vec::new();
        while let Ok(line) = self.lines.recv_timeout(Duration::from_secs(5)) {
            out.push(line);
        }
        out
    }
}

impl Drop for Sim {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Run `forja` with `args`; its output.
pub fn forja<S: AsRef<std::ffi::OsStr>>(args: &[S]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_forja"))
        .args(args)
        .stdin(Stdio::null())
        .output()
        .expect("forja runs")
}

/// Run `forja` with `args` and `input` on its standard input.
pub fn forja_with_input<S: AsRef<std::ffi::OsStr>>(args: &[S], input: &str) -> Output {
    use std::io::Write;
    let mut child = Command::new(env!("CARGO_BIN_EXE_forja"))
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("forja runs");
    child
        .stdin
        .take()
        .unwrap()
        .write_all(input.as_bytes())
        .unwrap();
    child.wait_with_output().unwrap()
}

/// Standard output and error as text, for messages.
pub fn text(out: &Output) -> String {
    format!(
        "status {:?}\n--- stdout\n{}--- stderr\n{}",
        out.status.code(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// `args` followed by `more`.
pub fn with(args: &[String], more: &[&str]) -> Vec<String> {
    args.iter()
        .cloned()
        .chain(more.iter().map(|s| s.to_string()))
        .collect()
}

/// The positions `forja status --once` prints: `[(axis, mm)]`.
pub fn positions(link: &[String]) -> Vec<(char, f64)> {
    let out = forja(&with(link, &["status", "--once"]));
    assert!(out.status.success(), "{}", text(&out));
    let line = String::from_utf8_lossy(&out.stdout).to_string();
    let head = line.split('|').next().unwrap_or_default().to_string();
    let words: Vec<&str> = head.split_whitespace().collect();
    words
        .chunks(2)
        .filter_map(|pair| match pair {
            [axis, value] => Some((axis.chars().next()?, value.parse().ok()?)),
            _ => None,
        })
        .collect()
}

/// The position of `axis` in `positions`.
pub fn axis(positions: &[(char, f64)], axis: char) -> f64 {
    positions
        .iter()
        .find(|p| p.0 == axis)
        .map(|p| p.1)
        .unwrap_or_else(|| panic!("no axis {axis} in {positions:?}"))
}

/// Wait until the positions stop changing (the machine is at rest), at most `limit`.
pub fn settle(link: &[String], limit: Duration) -> Vec<(char, f64)> {
    let end = std::time::Instant::now() + limit;
    let mut last = positions(link);
    loop {
        std::thread::sleep(Duration::from_millis(250));
        let now = positions(link);
        if now == last || std::time::Instant::now() > end {
            return now;
        }
        last = now;
    }
}

/// A program that drives a host (OctoPrint, CNCjs) in a process group of its own, the host's
/// processes in it too, its output kept in a file: however the test ends, the whole group is
/// killed.
pub struct Driver {
    child: Child,
    out: PathBuf,
    name: &'static str,
    /// Whether `child` was waited for: its process group may then no longer be ours.
    reaped: bool,
}

impl Driver {
    /// Start `command` in a new process group, its standard output and error to `out`.
    /// `name` names it in the report.
    pub fn start(mut command: Command, out: PathBuf, name: &'static str) -> Driver {
        let log = std::fs::File::create(&out).expect("the scratch directory is writable");
        let child = command
            .stdin(Stdio::null())
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .process_group(0)
            .spawn()
            .unwrap_or_else(|e| panic!("{name} does not start: {e}"));
        Driver {
            child,
            out,
            name,
            reaped: false,
        }
    }

    /// Signal the whole group; only while the driver is not yet waited for, so that the group
    /// id is still its own.
    fn signal(&self, signal: &str) {
        if !self.reaped {
            let _ = Command::new("kill")
                .args([signal, "--", &format!("-{}", self.child.id())])
                .status();
        }
    }

    /// Wait for the driver to end, at most `limit` (plus 10 s), then `grace` after asking its
    /// group to stop; whether it succeeded and what it printed.
    pub fn finish(mut self, limit: Duration, grace: Duration) -> (bool, String) {
        let started = Instant::now();
        let mut asked_to_stop = false;
        let success = loop {
            if let Some(status) = self.child.try_wait().expect("the driver can be waited for") {
                self.reaped = true;
                break status.success();
            }
            let spent = started.elapsed();
            if !asked_to_stop && spent > limit + Duration::from_secs(10) {
                self.signal("-TERM");
                asked_to_stop = true;
            }
            if spent > limit + grace {
                self.signal("-KILL");
                let _ = self.child.wait();
                self.reaped = true;
                break false;
            }
            std::thread::sleep(Duration::from_millis(200));
        };
        let mut report = std::fs::read_to_string(&self.out).unwrap_or_default();
        if asked_to_stop {
            report.push_str(&format!("({} was stopped at the time limit)\n", self.name));
        }
        (success, report)
    }
}

impl Drop for Driver {
    fn drop(&mut self) {
        if !self.reaped {
            self.signal("-KILL");
            let _ = self.child.wait();
        }
    }
}
