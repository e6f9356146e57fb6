//! Power cuts of the whole firmware: the simulator, keeping its flash in a state file
//! (`--state`), is killed with SIGKILL at random moments while a host uploads programs
//! (frames 03), writes settings (frames 00) and runs a stored program (frame 02 `Start`), and
//! while a stored job runs that the firmware is to resume after the restart (Marlin's `M413`
//! and `M1000`). After every kill, the firmware starts again on the file (`--check --state`,
//! which prints every setting and the stored program as the firmware finds them), and:
//!
//! - each setting is the last value the firmware acknowledged (frame 50, or `ok` to `M413`;
//!   before any, the old value) or a value sent after it and not yet answered; never a refused
//!   one (frame 56): acknowledged means stored, refused changes nothing;
//! - the program is the old complete one, the new complete one (the new one if its upload was
//!   confirmed with frame 53), or else it is refused by `Start` (incomplete or absent): never a
//!   program with wrong lines that runs;
//! - the firmware starts, whatever the kill left in the file.
//!
//! Settings are first written without a kill until their 16 KiB flash is nearly full, so that
//! pages are erased and records copied forward during the campaign (checked: some turn sets
//! bits again in the file's settings flash, which only an erase does).
//!
//! # Resume after a power cut
//!
//! In the resume turns, the machine is homed (`G28`) and runs a stored job of about a minute
//! of its own time (the simulator runs 50 times faster than the wall clock; frame 52's elapsed
//! time is the machine's): 100 feed moves zigzagging in Y while X rises, in blocks of relative
//! (`G91`) and absolute (`G90`) lines with feed changes and, from a third of the way on, a work
//! offset (`G92`), the last block relative. Every motion line moves X forward, so where the
//! machine is along X tells which lines have finished. At every look during a run, the test
//! first reads the resume record (key 0x0300 of the settings' flash) from the state file as
//! the firmware reads it, then asks for frames 51 and 52. Three turns in four, with power-loss
//! recovery on (`M413 S1`):
//!
//! - the job is killed at a random moment after the first periodic checkpoint of its run (at
//!   least 15 s into it), or, one cut in four, within its first seconds (to resume from the
//!   record the run wrote at its start);
//! - a record read before a position names no line that had not finished at that position
//!   (a record ahead of the steps by less than the time a look takes, about 25 ms of the
//!   machine's time, goes unseen: the controller's unit tests hold that bound); it never goes
//!   back, changes at most once per 10 s of the run (flash wear), and at the cut names every
//!   line that had finished more than 14 s before (the 10 s checkpoint period, the step
//!   queue's settling and frame 52's whole seconds, with room to spare), so past the run's
//!   start after a checkpoint;
//! - after the restart, `M1000` is refused before homing (`echo:E187 not-homed`) and nothing
//!   moves (frames 51 and 52 the same 20 ms later); after `G28` (back at the same home),
//!   `M1000` answers `ok` and frame 52 reports the line after the record the cut left: the
//!   job resumes after the last checkpoint, which is no later than the last line finished;
//! - every position of a run lies on its path (within 0.05 mm): the program's lines and, for
//!   a resumed run, the return from home, X and Y at home's height first, then Z down to the
//!   start of the resumed line; frame 52 counts the lines up from there, never back;
//! - a resumed run is, one time in two, cut and resumed again; the last one runs to the
//!   program's end (frame 51 at its final position, which a wrongly replayed distance mode or
//!   offset would miss, frame 52 at its last line), after which `M1000` has nothing to resume
//!   (`echo:E186 no-resume`) and the flash keeps no record.
//!
//! One turn in four, with recovery off (`M413 S0`): `M1000` at once has nothing to resume
//! (`E186`) and moves nothing; the job, cut the same way, leaves no record in the flash; after
//! the restart and `G28`, `M1000` is refused with `E186` and nothing moves.
//!
//! Seeded: `FORJA_POWER_LOSS_SEED` (default 1), `FORJA_POWER_LOSS_KILLS` (default 200, about
//! 20 s) and `FORJA_POWER_LOSS_RESUMES` (default 8, placed at random among the kills, about
//! 20 s more) set the campaign; a longer one is the same test with more kills. A failure names
//! the seed and the turn. The kill moments are drawn from how long the operations take on this
//! computer (wall time, a random delay of a few milliseconds; nothing is asserted about wall
//! time), so that they fall before, inside and just after them; a job to resume is cut at a
//! moment of its own time.

mod common;
#[path = "power_loss/resume.rs"]
mod resume;

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, ErrorKind, Read as _, Write as _};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use forja_protocol::frame::{Action, ClientMessage, ControllerMessage, FRAME_LEN, Progress};
use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;

use common::{Running, sim};

/// The settings the test changes, with the values it picks from (whole numbers, which frame 50
/// shows as sent).
/// A few values are refused (a maximum rate below the homing seek rate): a refused value must
/// never be found stored.
const SETTINGS: [(&str, u32, u32); 8] = [
    ("x.max_rate", 1800, 6000),
    ("y.max_rate", 1800, 6000),
    ("z.max_rate", 550, 1200),
    ("x.accel", 100, 500),
    ("y.accel", 100, 500),
    ("jog_feed", 100, 2000),
    ("default_feed", 100, 2000),
    ("keep_alive_ms", 500, 5000),
];

/// Settings written before the campaign, without a kill: most of the settings' flash.
const PREFILL_SETTINGS: u64 = 740;

/// How long to wait for the simulator's answers before calling it stuck.
const TIMEOUT: Duration = Duration::from_secs(20);

/// SplitMix64: small, seeded, good enough to pick kill moments and values.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `lo..=hi`.
    fn range(&mut self, lo: u64, hi: u64) -> u64 {
        lo + self.next() % (hi - lo + 1)
    }
}

fn env_number(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// A simulator serving TCP on a state file.
struct Sim {
    child: Running,
    tcp: SocketAddr,
    /// Where its standard error goes, for the failure messages.
    stderr: PathBuf,
    /// Kept open: the simulator prints a few more lines, which must not find the pipe closed.
    _stdout: BufReader<std::process::ChildStdout>,
}

impl Sim {
    fn start(state: &Path) -> Sim {
        let stderr = state.with_extension("stderr");
        let mut child = sim()
            .args([
                "--listen",
                "--tcp-port",
                "0",
                "--time-scale",
                "50",
                "--time-limit",
                "100000",
                "--state",
            ])
            .arg(state)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&stderr).expect("stderr file"))
            .spawn()
            .expect("forja-sim starts");
        let mut stdout = BufReader::new(child.stdout.take().expect("stdout"));
        let tcp = loop {
            let mut line = String::new();
            let n = stdout.read_line(&mut line).expect("stdout readable");
            assert!(
                n > 0,
                "forja-sim ended before printing its TCP address: {}",
                std::fs::read_to_string(&stderr).unwrap_or_default()
            );
            if let Some(addr) = line.trim_end().strip_prefix("tcp: ") {
                break addr.parse().expect("a socket address");
            }
        };
        // The rest of stdout is not read: it is a few lines, within the pipe's buffer.
        Sim {
            child: Running(child),
            tcp,
            stderr,
            _stdout: stdout,
        }
    }

    fn pid(&self) -> Pid {
        Pid::from_raw(self.child.0.id() as i32)
    }

    /// Connect as the controlling host, and wait for the greeting (frame 54).
    fn connect(&self) -> Host {
        let stream = TcpStream::connect(self.tcp).expect("connect");
        stream
            .set_read_timeout(Some(Duration::from_millis(50)))
            .expect("timeout");
        let mut host = Host {
            stream,
            pending: Vec::new(),
            closed: false,
        };
        let deadline = Instant::now() + TIMEOUT;
        loop {
            match host.next(deadline) {
                Some(Reply::Connected) => return host,
                Some(_) => {}
                None => panic!(
                    "no greeting from forja-sim: {}",
                    std::fs::read_to_string(&self.stderr).unwrap_or_default()
                ),
            }
        }
    }

    /// Kill with SIGKILL and reap.
    fn kill(mut self) {
        let _ = kill(self.pid(), Signal::SIGKILL);
        let _ = self.child.0.wait();
    }
}

/// What the firmware sent, as far as the test cares.
#[derive(Debug, Clone, PartialEq)]
enum Reply {
    Setting(String, String),
    Progress(Progress),
    /// Frame 51: X, Y and Z, in tenths of a micrometre.
    Positions([i64; 3]),
    Confirm,
    Connected,
    Error(u16, String),
    /// A line that is not a frame: the answer to a G-code line (`ok`, `echo:E186 no-resume`).
    Text(String),
    Other,
}

/// The host side of a TCP connection.
struct Host {
    stream: TcpStream,
    pending: Vec<u8>,
    closed: bool,
}

fn frame(message: ClientMessage<'_>) -> Vec<u8> {
    let mut out = [0u8; FRAME_LEN];
    message.encode(&mut out).expect("encodable");
    let mut v = out.to_vec();
    v.push(b'\n');
    v
}

impl Host {
    /// Send, ignoring a connection the kill closed.
    fn send(&mut self, bytes: &[u8]) {
        if self.stream.write_all(bytes).is_err() {
            self.closed = true;
        }
    }

    /// The next reply, or `None` once the connection is closed or at `deadline`.
    fn next(&mut self, deadline: Instant) -> Option<Reply> {
        loop {
            if let Some(end) = self.pending.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.pending.drain(..=end).collect();
                let line = &line[..line.len() - 1];
                let Ok(message) = ControllerMessage::decode(line) else {
                    return Some(Reply::Text(String::from_utf8_lossy(line).into_owned()));
                };
                return Some(match message {
                    ControllerMessage::Setting { key, value } => {
                        Reply::Setting(key.to_string(), value.to_string())
                    }
                    ControllerMessage::Progress(p) => Reply::Progress(p),
                    ControllerMessage::Positions(p) => Reply::Positions(
                        [b'X', b'Y', b'Z'].map(|a| i64::from(p.get(a).unwrap_or(i32::MIN))),
                    ),
                    ControllerMessage::Confirm { .. } => Reply::Confirm,
                    ControllerMessage::Connected => Reply::Connected,
                    ControllerMessage::Error { code, detail } => {
                        Reply::Error(code, detail.to_string())
                    }
                    _ => Reply::Other,
                });
            }
            if self.closed || Instant::now() >= deadline {
                return None;
            }
            let mut buf = [0u8; 4096];
            match self.stream.read(&mut buf) {
                Ok(0) => self.closed = true,
                Ok(n) => self.pending.extend_from_slice(&buf[..n]),
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                Err(_) => self.closed = true,
            }
        }
    }
}

/// What the firmware keeps, as `--check --state` prints it.
#[derive(Debug, Clone, PartialEq, Default)]
struct Stored {
    settings: BTreeMap<String, String>,
    program: Vec<String>,
    /// Whether the firmware reports the program complete (it runs).
    complete: bool,
}

/// Start the firmware on `state` (a copy of it) and read what it keeps.
fn stored(state: &Path) -> Result<Stored, String> {
    let out = sim()
        .args(["--check", "--state"])
        .arg(state)
        .output()
        .map_err(|e| e.to_string())?;
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    if !out.status.success() {
        return Err(format!(
            "the firmware does not start on the file ({}): {}{text}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    let mut s = Stored::default();
    let mut in_program = false;
    for line in text.lines() {
        if line.starts_with("  program: ") {
            in_program = true;
            s.complete = line.ends_with(" lines, complete");
        } else if let Some(entry) = line.strip_prefix("    ") {
            if in_program {
                let (_, text) = entry.split_at(entry.len().min(5));
                s.program.push(text.to_string());
            } else if let Some((k, v)) = entry.split_once('=') {
                s.settings.insert(k.to_string(), v.to_string());
            }
        }
    }
    if s.settings.is_empty() {
        return Err(format!("no settings in --check's output: {text}"));
    }
    Ok(s)
}

/// Removes the state file and the simulator's standard error when the test ends, passed or
/// failed.
struct Cleanup(PathBuf);

impl Drop for Cleanup {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
        let _ = std::fs::remove_file(self.0.with_extension("stderr"));
    }
}

/// The settings' flash as the state file holds it (see `forja_sim_hal::state`).
fn settings_flash_of(state: &Path) -> Vec<u8> {
    let bytes = std::fs::read(state).expect("the state file");
    let at = forja_sim_hal::state::HEADER_LEN;
    bytes[at..at + forja_sim_hal::state::SETTINGS_FLASH_LEN].to_vec()
}

/// A program of `lines` lines that no other upload of the campaign has (its feed rate is the
/// upload's number), moving within the default machine's travel from where it starts.
fn program(id: u64, lines: usize, rng: &mut Rng) -> Vec<String> {
    (0..lines)
        .map(|_| {
            format!(
                "G1 X{}.{} Y{}.{} F{}",
                rng.range(140, 160),
                rng.range(0, 9),
                rng.range(140, 160),
                rng.range(0, 9),
                1000 + id
            )
        })
        .collect()
}

/// The operation killed in one turn.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Op {
    /// Killed while starting up, before a host connects.
    Boot,
    Settings,
    Upload,
    Job,
    /// A stored job cut and resumed (`M1000`), power-loss recovery on or off (`M413`).
    Resume {
        recovery: bool,
    },
}

/// Mean wall time of an operation, to draw kill moments from (microseconds).
struct Durations(BTreeMap<&'static str, f64>);

impl Durations {
    fn get(&self, op: &'static str) -> f64 {
        self.0.get(op).copied().unwrap_or(20_000.0)
    }

    fn record(&mut self, op: &'static str, us: f64) {
        let mean = self.get(op);
        self.0.insert(op, mean * 0.8 + us * 0.2);
    }
}

/// Kill the simulator of `pid` after `delay`, from another thread.
fn kill_after(pid: Pid, delay: Duration) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        std::thread::sleep(delay);
        let _ = kill(pid, Signal::SIGKILL);
    })
}

/// Whether the firmware refuses `Start` (a 56 before the 52 that follows the request).
fn start_refused(host: &mut Host) -> bool {
    host.send(&frame(ClientMessage::Action(Action::Start)));
    host.send(&frame(ClientMessage::Request { message_type: 52 }));
    let deadline = Instant::now() + TIMEOUT;
    let mut refused = false;
    loop {
        match host.next(deadline) {
            Some(Reply::Error(..)) => refused = true,
            Some(Reply::Progress(_)) => break,
            Some(_) => {}
            None => panic!("no answer to Start and 04 52"),
        }
    }
    if !refused {
        host.send(&frame(ClientMessage::Action(Action::Stop)));
    }
    refused
}

/// What became of one settings frame (00).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Answer {
    /// Frame 50: stored.
    Stored,
    /// Frame 56: refused, nothing changed.
    Refused,
    /// No answer before the kill.
    None,
}

/// The values a setting may have after the kill, given its value before and the frames sent
/// for it in order: the last stored value (or the old one), or any value sent after it and not
/// answered; never a refused one.
fn allowed_values(old: &str, frames: &[(String, Answer)]) -> Vec<String> {
    let last_stored = frames.iter().rposition(|f| f.1 == Answer::Stored);
    let base = match last_stored {
        Some(i) => frames[i].0.clone(),
        None => old.to_string(),
    };
    std::iter::once(base)
        .chain(
            frames
                .iter()
                .skip(last_stored.map_or(0, |i| i + 1))
                .filter(|f| f.1 == Answer::None)
                .map(|f| f.0.clone()),
        )
        .collect()
}

/// The settings frames sent in one turn: each key's values in order, with their answers.
type Sent = BTreeMap<&'static str, Vec<(String, Answer)>>;

/// Send `frames` settings frames (random keys and values) and read their answers: 50 or 56,
/// one per frame, in order, until the link closes (or, without `killed`, until every frame
/// is answered).
fn write_settings(
    host: &mut Host,
    rng: &mut Rng,
    frames: u64,
    killed: bool,
    on_first_byte: impl FnOnce(),
) -> (Sent, Option<Duration>) {
    let mut order: Vec<(&'static str, usize)> = Vec::new();
    let mut sent = Sent::new();
    let mut bytes = Vec::new();
    for _ in 0..frames {
        let (key, lo, hi) = SETTINGS[rng.range(0, SETTINGS.len() as u64 - 1) as usize];
        let value = rng.range(u64::from(lo), u64::from(hi)).to_string();
        bytes.extend(frame(ClientMessage::SetSetting { key, value: &value }));
        let values = sent.entry(key).or_default();
        order.push((key, values.len()));
        values.push((value, Answer::None));
    }
    let started = Instant::now();
    on_first_byte();
    host.send(&bytes);
    let mut answered = 0;
    let mut all_answered = None;
    while let Some(reply) = host.next(Instant::now() + TIMEOUT) {
        let answer = match reply {
            Reply::Setting(..) => Answer::Stored,
            Reply::Error(..) => Answer::Refused,
            _ => continue,
        };
        if let Some(&(key, i)) = order.get(answered)
            && let Some(v) = sent.get_mut(key).and_then(|v| v.get_mut(i))
        {
            v.1 = answer;
        }
        answered += 1;
        if answered == order.len() {
            all_answered = Some(started.elapsed());
            if !killed {
                break;
            }
        }
    }
    (sent, all_answered)
}

#[test]
fn killed_at_random_moments_the_firmware_keeps_old_or_new_never_a_mix() {
    let seed = env_number("FORJA_POWER_LOSS_SEED", 1);
    let kills = env_number("FORJA_POWER_LOSS_KILLS", 200);
    let resumes = env_number("FORJA_POWER_LOSS_RESUMES", 8);
    let mut rng = Rng(seed);
    let state: PathBuf = std::env::temp_dir().join(format!(
        "forja-sim-power-loss-{}-{seed}.flash",
        std::process::id()
    ));
    let _ = std::fs::remove_file(&state);
    let _cleanup = Cleanup(state.clone());
    let started = Instant::now();

    // A fresh file: the machine file's settings, no program. Then settings written without a
    // kill until the settings' flash (16 KiB, about 16 bytes a record) is nearly full, so that
    // the campaign's writes make it erase pages and copy records forward under the kills.
    let sim = Sim::start(&state);
    let mut host = sim.connect();
    let (prefill, _) = write_settings(&mut host, &mut rng, PREFILL_SETTINGS, false, || {});
    drop(host);
    sim.kill();
    // Turns in which a page of the settings' flash was erased (bits set again).
    let mut erasing_turns = 0;
    let mut settings_flash = settings_flash_of(&state);
    let mut known = stored(&state).expect("the firmware starts on a new file");
    assert!(known.program.is_empty());
    for (key, frames) in &prefill {
        if let Some((last, _)) = frames.iter().rev().find(|f| f.1 == Answer::Stored) {
            assert_eq!(
                known.settings.get(*key),
                Some(last),
                "{key} after the writes without a kill"
            );
        }
    }
    // The program last seen complete, if any.
    let mut complete: Option<Vec<String>> = None;
    // The program last seen is incomplete or absent: `Start` must refuse it.
    let mut must_refuse = true;
    let mut durations = Durations(BTreeMap::new());
    let mut failures: Vec<String> = Vec::new();
    let mut counts: BTreeMap<String, u32> = BTreeMap::new();
    // The resume turns, among the others: every fourth with power-loss recovery off.
    let mut resume_turns: BTreeMap<u64, bool> = BTreeMap::new();
    while (resume_turns.len() as u64) < resumes {
        resume_turns.insert(rng.range(0, kills + resumes - 1), true);
    }
    for (j, recovery) in resume_turns.values_mut().enumerate() {
        *recovery = j % 4 != 3;
    }
    // Resume records read from the flash during a job and checked against a later position.
    let mut records_checked = 0;

    for turn in 0..kills + resumes {
        let op = match rng.range(0, 9) {
            _ if resume_turns.contains_key(&turn) => Op::Resume {
                recovery: resume_turns[&turn],
            },
            0 => Op::Boot,
            1..=3 => Op::Settings,
            4..=7 => Op::Upload,
            _ if complete.is_some() => Op::Job,
            _ => Op::Upload,
        };
        let context = format!("seed {seed}, turn {turn}, {op:?}");
        let boot_started = Instant::now();
        let mut sent = BTreeMap::new();
        let mut upload: Option<(Vec<String>, bool)> = None;
        if let Op::Resume { recovery } = op {
            let t = resume::turn(
                &state,
                &mut rng,
                recovery,
                must_refuse,
                known.program.len(),
                &context,
            );
            failures.extend(t.failures);
            sent = t.sent;
            upload = t.upload;
            records_checked += t.records_checked;
            for c in t.counts {
                *counts.entry(c.into()).or_default() += 1;
            }
        } else if op == Op::Boot {
            let sim = Sim::start(&state);
            let delay = Duration::from_micros(rng.range(0, durations.get("boot") as u64));
            std::thread::sleep(delay);
            sim.kill();
            *counts.entry("boot".into()).or_default() += 1;
        } else {
            let sim = Sim::start(&state);
            let mut host = sim.connect();
            durations.record("boot", boot_started.elapsed().as_micros() as f64);
            if must_refuse && !start_refused(&mut host) {
                failures.push(format!(
                    "{context}: Start ran a program of {} lines that is neither the old \
                     complete one nor the new one",
                    known.program.len()
                ));
            }
            let name: &'static str = match op {
                Op::Settings => "settings",
                Op::Upload => "upload",
                _ => "job",
            };
            let delay = Duration::from_micros(rng.range(0, (durations.get(name) * 1.3) as u64));
            let pid = sim.pid();
            let mut killer = None;
            let (whole, took) = match op {
                Op::Settings => {
                    let frames = rng.range(20, 120);
                    let (s, took) = write_settings(&mut host, &mut rng, frames, true, || {
                        killer = Some(kill_after(pid, delay));
                    });
                    let none_answered = s.values().flatten().all(|f| f.1 == Answer::None);
                    sent = s;
                    // The first write after a cut may repair the flash first, and take
                    // longer: a kill that came before any answer moves the next ones later.
                    (
                        took.is_some(),
                        took.or((none_answered).then_some(delay * 2)),
                    )
                }
                Op::Upload => {
                    let lines = if rng.range(0, 9) == 0 {
                        rng.range(100, 300)
                    } else {
                        rng.range(1, 40)
                    } as usize;
                    let p = program(turn, lines, &mut rng);
                    let mut bytes = Vec::new();
                    for (i, text) in p.iter().enumerate() {
                        bytes.extend(frame(ClientMessage::LoadLine {
                            index: i as u16 + 1,
                            text,
                            total: lines as u16,
                        }));
                    }
                    let op_started = Instant::now();
                    killer = Some(kill_after(pid, delay));
                    host.send(&bytes);
                    let mut took = None;
                    while let Some(reply) = host.next(Instant::now() + TIMEOUT) {
                        if reply == Reply::Confirm {
                            took = Some(op_started.elapsed());
                        }
                    }
                    upload = Some((p, took.is_some()));
                    (took.is_some(), took)
                }
                _ => {
                    // A job: let it run a few milliseconds of wall time.
                    killer = Some(kill_after(pid, delay));
                    host.send(&frame(ClientMessage::Action(Action::Start)));
                    while host.next(Instant::now() + TIMEOUT).is_some() {}
                    (false, Some(Duration::from_millis(30)))
                }
            };
            if let Some(k) = killer {
                k.join().expect("the killer thread");
            }
            sim.kill();
            if let Some(t) = took {
                durations.record(name, t.as_micros() as f64);
            }
            *counts
                .entry(format!("{name} {}", if whole { "done" } else { "cut" }))
                .or_default() += 1;
        }

        let now = match stored(&state) {
            Ok(s) => s,
            Err(e) => {
                failures.push(format!("{context}: {e}"));
                break;
            }
        };
        // Settings: the last stored value or a value sent after it, never a refused one.
        for (key, old) in &known.settings {
            let got = now.settings.get(key).cloned().unwrap_or_default();
            let allowed = match sent.get(key.as_str()) {
                Some(frames) => allowed_values(old, frames),
                None => vec![old.clone()],
            };
            if !allowed.contains(&got) {
                failures.push(format!(
                    "{context}: setting {key} is {got:?}, expected one of {allowed:?}"
                ));
            }
        }
        let after = settings_flash_of(&state);
        if after.iter().zip(&settings_flash).any(|(a, b)| a & !b != 0) {
            erasing_turns += 1;
        }
        settings_flash = after;
        // The program: old complete, new complete (if confirmed), or refused by Start.
        let old = complete.clone().unwrap_or_default();
        let (new, confirmed) = upload.unwrap_or_default();
        if confirmed && now.program != new {
            failures.push(format!(
                "{context}: the upload was confirmed (53) but the program is {} lines, not the \
                 {} uploaded",
                now.program.len(),
                new.len()
            ));
        }
        let old_or_new = !now.program.is_empty() && (now.program == new || now.program == old);
        if now.complete && !old_or_new {
            failures.push(format!(
                "{context}: a program of {} lines is reported complete but is neither the old \
                 complete one nor the new one",
                now.program.len()
            ));
        }
        if now.complete && old_or_new {
            complete = Some(now.program.clone());
            must_refuse = false;
        } else {
            complete = None;
            must_refuse = true;
        }
        known = now;
        if failures.len() >= 10 {
            break;
        }
    }
    assert!(
        failures.is_empty(),
        "{} failures (seed {seed}; {counts:?} after {:.1} s):\n{}",
        failures.len(),
        started.elapsed().as_secs_f64(),
        failures.join("\n")
    );
    let cut: u32 = counts
        .iter()
        .filter(|(k, _)| k.ends_with("cut") || k.as_str() == "boot")
        .map(|(_, n)| n)
        .sum();
    assert!(
        u64::from(cut) * 4 >= kills,
        "too few kills fell inside an operation: {counts:?}"
    );
    assert!(
        erasing_turns >= 1,
        "the settings' flash never reclaimed a page under the kills: {counts:?}"
    );
    let on = resume_turns.values().filter(|&&r| r).count() as u32;
    let off = resume_turns.len() as u32 - on;
    let count = |k: &str| counts.get(k).copied().unwrap_or(0);
    assert!(
        count("resumed") + count("resumed after an early cut") == on
            && count("job ran to its end") >= on
            && count("resume refused (recovery off)") == off,
        "not every resume turn was cut, resumed (or refused) and ran to its end: {counts:?}"
    );
    assert!(
        on == 0 || records_checked >= 1,
        "no resume record was read during a job and checked against the machine's position"
    );
}
