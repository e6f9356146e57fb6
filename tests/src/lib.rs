//! End-to-end tests of Forja through the simulator.
//!
//! The firmware runs in the test's own process: a [`forja_sim::board::SimBoard`] (the
//! controller and the motion kernel on the simulated machine) under a
//! [`forja_sim_hal::Simulation`], served on real links — a pseudo-terminal, a TCP socket — or an
//! in-memory one, while the test plays the host through the helpers here. The tests are in
//! `tests/`:
//!
//! | file | what |
//! |---|---|
//! | `stream.rs` | a printer job of several hundred numbered, checksummed lines over the pseudo-terminal: homing, heating, moves, every report |
//! | `frames.rs` | the operator's client over TCP: settings, homing, jog, program upload and run, pause, resume, stop, progress, a restart |
//! | `faults.rs` | 1 % of the bytes from the host corrupted or dropped: every move of a 1,000-line job runs exactly once |
//! | `limits.rs` | limit switches through the board's pin-change interrupt: a hard limit stops motion at the switch and locks the machine |
//! | `invariants.rs` | arbitrary interleavings of lines, realtime frames, `M112`, jogs, homing, refused and damaged lines ([`invariants`]): acknowledged moves run once, positions stay true |
//! | `bad_input.rs` | garbage, over-long lines, wrong numbers, broken frames, bad program lines, a full store: always an error reply, nothing changed |
//!
//! Virtual time runs as fast as the computer does; waits on the host side are bounded by the
//! wall clock ([`Rig::run_until`]), so that a broken firmware fails a test rather than hanging
//! it.

pub mod invariants;

use std::fs::{File, OpenOptions};
use std::io::ErrorKind;
use std::net::{SocketAddr, TcpStream};
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::time::{Duration, Instant};

use forja_protocol::frame::{ClientMessage, ControllerMessage, FRAME_LEN};
use forja_sim::board::{BoardConfig, SimBoard};
use forja_sim_hal::link::MemoryHost;
use forja_sim_hal::{Flow, MachineConfig, SimMachine, Simulation, SimulationConfig};

/// The host's end of a link.
pub trait HostEnd {
    /// Send bytes to the firmware (all of them, or panic: a test link does not fail).
    fn send(&mut self, bytes: &[u8]);
    /// Take what the firmware has sent so far, without waiting.
    fn receive(&mut self) -> Vec<u8>;
}

impl HostEnd for MemoryHost {
    fn send(&mut self, bytes: &[u8]) {
        MemoryHost::send(self, bytes);
    }
    fn receive(&mut self) -> Vec<u8> {
        self.take_received()
    }
}

fn read_nonblocking(r: &mut impl std::io::Read) -> Vec<u8> {
    let mut out = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        match r.read(&mut buf) {
            Ok(0) => return out,
            Ok(n) => out.extend_from_slice(&buf[..n]),
            Err(e) if e.kind() == ErrorKind::WouldBlock => return out,
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => panic!("host link failed: {e}"),
        }
    }
}

fn write_all_nonblocking(w: &mut impl std::io::Write, mut bytes: &[u8]) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while !bytes.is_empty() {
        match w.write(bytes) {
            Ok(n) => bytes = &bytes[n..],
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::Interrupted) => {
                assert!(Instant::now() < deadline, "the host could not write");
                std::thread::sleep(Duration::from_micros(100));
            }
            Err(e) => panic!("host link failed: {e}"),
        }
    }
}

/// A host on the simulator's pseudo-terminal, opened by path as serial software opens a port
/// (the simulator has set the terminal to raw mode).
#[derive(Debug)]
pub struct PtyHost(File);

impl PtyHost {
    /// Open the terminal at `path`, non-blocking.
    pub fn open(path: &Path) -> Self {
        let flags = nix::fcntl::OFlag::O_NOCTTY | nix::fcntl::OFlag::O_NONBLOCK;
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(flags.bits())
            .open(path)
            .expect("the pseudo-terminal opens");
        Self(file)
    }
}

impl HostEnd for PtyHost {
    fn send(&mut self, bytes: &[u8]) {
        write_all_nonblocking(&mut self.0, bytes);
    }
    fn receive(&mut self) -> Vec<u8> {
        read_nonblocking(&mut self.0)
    }
}

/// A host on the simulator's TCP link.
#[derive(Debug)]
pub struct TcpHost(TcpStream);

impl TcpHost {
    /// Connect to `addr`, non-blocking, without Nagle's delay.
    pub fn connect(addr: SocketAddr) -> Self {
        let stream = TcpStream::connect(addr).expect("the TCP link accepts");
        stream.set_nonblocking(true).expect("non-blocking");
        stream.set_nodelay(true).expect("no delay");
        Self(stream)
    }
}

impl HostEnd for TcpHost {
    fn send(&mut self, bytes: &[u8]) {
        write_all_nonblocking(&mut self.0, bytes);
    }
    fn receive(&mut self) -> Vec<u8> {
        read_nonblocking(&mut self.0)
    }
}

/// Reply lines as they come, cut at `\n`.
#[derive(Debug, Default, Clone)]
pub struct Replies {
    partial: Vec<u8>,
    /// Every complete line so far, without its `\n`.
    pub lines: Vec<String>,
}

impl Replies {
    /// Take `bytes`; returns the lines they completed.
    pub fn feed(&mut self, bytes: &[u8]) -> Vec<String> {
        self.partial.extend_from_slice(bytes);
        let mut new = Vec::new();
        while let Some(end) = self.partial.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = self.partial.drain(..=end).collect();
            let text = String::from_utf8_lossy(&line).trim_end().to_string();
            if !text.is_empty() {
                new.push(text);
            }
        }
        self.lines.extend(new.iter().cloned());
        new
    }

    /// The frames among the lines, decoded.
    pub fn frames(&self) -> Vec<ControllerMessage<'_>> {
        frames(&self.lines)
    }

    /// The codes of the 56 frames among the lines.
    pub fn error_codes(&self) -> Vec<u16> {
        error_codes(&self.lines)
    }

    /// Forget the lines so far.
    pub fn clear(&mut self) {
        self.lines.clear();
    }
}

/// The frames among `lines`, decoded (a line that is not a well-formed frame is skipped).
pub fn frames(lines: &[String]) -> Vec<ControllerMessage<'_>> {
    lines
        .iter()
        .filter(|l| l.len() == FRAME_LEN && l.starts_with('N') && l.ends_with('F'))
        .filter_map(|l| ControllerMessage::decode(l.as_bytes()).ok())
        .collect()
}

/// The codes of the 56 frames among `lines`.
pub fn error_codes(lines: &[String]) -> Vec<u16> {
    frames(lines)
        .iter()
        .filter_map(|m| match m {
            ControllerMessage::Error { code, .. } => Some(*code),
            _ => None,
        })
        .collect()
}

/// A client frame, with its `\n`.
pub fn frame(msg: &ClientMessage<'_>) -> Vec<u8> {
    let mut f = [0u8; FRAME_LEN];
    msg.encode(&mut f).expect("the test's frame encodes");
    let mut v = f.to_vec();
    v.push(b'\n');
    v
}

/// A bundled machine, the board on it, and a simulation as fast as possible.
pub struct Rig {
    /// The simulated machine.
    pub machine: SimMachine,
    /// The firmware.
    pub board: SimBoard,
    /// The simulation loop (virtual time goes on from one run to the next).
    pub sim: Simulation,
}

impl Rig {
    /// The bundled machine `name` (`default` or `printer`) with a board of `config`.
    pub fn new(name: &str, config: BoardConfig) -> Self {
        let text = MachineConfig::bundled_toml(name).expect("a bundled machine");
        let file = MachineConfig::from_toml_str(text).expect("the bundled file is valid");
        let machine = SimMachine::new(&file);
        Self::on(machine, config)
    }

    /// The board of `config` on `machine`.
    pub fn on(machine: SimMachine, config: BoardConfig) -> Self {
        let board = SimBoard::new(&machine, config).expect("the board builds");
        let sim = Simulation::new(machine.clone(), SimulationConfig::new(machine.tick_hz()));
        Self {
            machine,
            board,
            sim,
        }
    }

    /// Virtual time now, ms.
    pub fn now_ms(&self) -> u64 {
        self.machine.now_ticks() * 1000 / u64::from(self.machine.tick_hz())
    }

    /// Run until `done` says so (it is called after every thread-side poll, with the virtual
    /// time in ms), at most `wall` of real time. Returns whether `done` was reached.
    pub fn run_until(
        &mut self,
        wall: Duration,
        mut done: impl FnMut(&mut SimBoard, u64) -> bool,
    ) -> bool {
        let deadline = Instant::now() + wall;
        let machine = self.machine.clone();
        let tick_hz = u64::from(machine.tick_hz());
        let mut reached = false;
        let mut polls = 0u32;
        self.board
            .run(&mut self.sim, |board, _| {
                let now_ms = machine.now_ticks() * 1000 / tick_hz;
                if done(board, now_ms) {
                    reached = true;
                    return Flow::Stop;
                }
                polls = polls.wrapping_add(1);
                if polls.is_multiple_of(256) && Instant::now() > deadline {
                    return Flow::Stop;
                }
                Flow::Continue
            })
            .expect("the simulation runs");
        reached
    }

    /// Run `ms` milliseconds of virtual time, passing bytes between `host` and the firmware
    /// into `replies`.
    pub fn exchange(&mut self, host: &mut impl HostEnd, replies: &mut Replies, ms: u64) {
        let end = self.now_ms() + ms;
        self.run_until(Duration::from_secs(30), |_, now| {
            replies.feed(&host.receive());
            now >= end
        });
    }

    /// Run until the machine is at rest (moves done, not homing, no line held).
    pub fn settle(&mut self, host: &mut impl HostEnd, replies: &mut Replies) {
        let settled = self.run_until(Duration::from_secs(60), |board, _| {
            replies.feed(&host.receive());
            let s = board.status();
            s.controller.idle && !s.controller.holding
        });
        assert!(
            settled,
            "the machine did not come to rest: {:?}",
            self.board.status()
        );
    }
}

/// Wall-clock milliseconds since `start` (the host's clock for its time-outs on OS links).
pub fn wall_ms(start: Instant) -> u64 {
    start.elapsed().as_millis() as u64
}

/// `a` and `b` within 1 µm.
pub fn same_mm(a: f64, b: f64) -> bool {
    (a - b).abs() < 0.001
}
