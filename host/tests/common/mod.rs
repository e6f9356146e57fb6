//! The simulator as the tests run it: the `forja-sim` binary listening on TCP and a
//! pseudo-terminal, its virtual time four times as fast as the wall clock (the moves take less
//! waiting), and the `forja` binary run against it.

#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// The `forja-sim` binary, built if the workspace build did not build it yet.
pub fn sim_binary() -> PathBuf {
    let exe = std::env::current_exe().expect("the test's own path");
    // target/<profile>/deps/<test> → target/<profile>/forja-sim
    let profile_dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("the test runs from target/<profile>/deps");
    let bin = profile_dir.join(format!("forja-sim{}", std::env::consts::EXE_SUFFIX));
    if !bin.exists() {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let status = Command::new(cargo)
            .args(["build", "-p", "forja-simulator", "--bin", "forja-sim"])
            .status()
            .expect("cargo runs");
        assert!(status.success(), "building forja-sim failed");
    }
    assert!(bin.exists(), "{} was not built", bin.display());
    bin
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
        let pty = dir.join("tty");
        let mut child = Command::new(sim_binary())
            .args([
                "--listen",
                "--time-scale",
                "4",
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
