//! The controller's safety invariants, checked under arbitrary interleavings of host input.
//!
//! A `Session` is the simulator's board on a small router ([`MACHINE`]) and an in-memory
//! link, played by a host that behaves as Printrun does (numbered, checksummed lines, one in
//! flight, `rs` answered by a resend) while an operator interleaves the frames' realtime
//! actions, `M112` (sent out of turn, its own `ok` awaited), jogs, homing, refused lines,
//! damaged lines and waits. [`Op::decode`] turns any bytes into such a script, so the same
//! [`run`] serves a proptest (`tests/invariants.rs`) and a `cargo fuzz` target.
//!
//! The firmware is polled every millisecond of virtual time while anything moves or is on its
//! way, and the host looks after every poll. When nothing can happen until the host sends
//! something (the machine stands still, no byte is in transit, the host waits), a wait jumps
//! to its end with a single poll; the realtime checks always poll every millisecond.
//!
//! What [`run`] checks, and panics on:
//!
//! - **Acknowledged means done.** Every relative move answered with `ok` runs exactly once:
//!   between two points where the machine was brought to rest on purpose (a stop, a reset,
//!   `M112`, homing), the steps reached equal the sum of the acknowledged moves. A refused
//!   line (`!!` before its `ok`) moves nothing and changes no modal state: the moves after it
//!   are still relative.
//! - **The position is true.** Whenever the machine is at rest, `M114` reports the position the
//!   steps reached.
//! - **The travel is kept.** Once an axis is homed, no step takes it out of its travel.
//! - **The realtime path is never blocked.** `M112` locks the machine, and frame 04 is answered,
//!   within [`REALTIME_MS`] of virtual time, whatever the host has sent before.

use std::collections::VecDeque;
use std::sync::OnceLock;
use std::time::Duration;

use forja_motion::MachineState;
use forja_protocol::frame::{Action, ClientMessage, ControllerMessage};
use forja_protocol::gcode::{Decimal, MAX_LINE_LEN, write_numbered};
use forja_protocol::reply::Reply;
use forja_sim::board::{BoardConfig, BoardStatus, SimBoard};
use forja_sim_hal::link::{MemoryHost, MemoryLink};
use forja_sim_hal::{MachineConfig, SimMachine};

use crate::{Replies, Rig, frame};

/// The longest a realtime command may take to act, virtual ms.
pub const REALTIME_MS: u64 = 10;

/// The machine every [`run`] starts on: the bundled router (`machines/default.toml`) cut down
/// to what a script reaches, so that a whole script takes a fraction of a second of virtual
/// time. X, Y and Z keep the router's normally-closed homing switches and homing directions
/// (X and Y to the minimum, Z up to the maximum), and X and Y its 80 steps/mm; Z has 200. X and
/// Y have 12 mm of travel (room for a 5 mm move either way), Z 6 mm, each starting in the
/// middle. Accelerations of 10 000 mm/s² (X, Y) and 5 000 mm/s² (Z) make a move of a few
/// tenths of a millimetre last tens of milliseconds, and a homing cycle at the axes' top rates,
/// with a 1 mm pull-off, under half a second. The A axis and the spindle, which no script
/// uses, are left out.
pub const MACHINE: &str = r#"
name = "Forja reference router, cut down for the invariants"
tick_hz = 1_000_000

[[axis]]
letter = "X"
steps_per_mm = 80.0
max_rate_mm_min = 6000.0
accel_mm_s2 = 10000.0
travel_min_mm = 0.0
travel_max_mm = 12.0
start_mm = 6.0

[axis.homing]
direction = "negative"
seek_mm_min = 6000.0
locate_mm_min = 4000.0
pull_off_mm = 1.0

[[axis.switch]]
side = "min"
position_mm = 0.0
polarity = "normally_closed"

[[axis]]
letter = "Y"
steps_per_mm = 80.0
max_rate_mm_min = 6000.0
accel_mm_s2 = 10000.0
travel_min_mm = 0.0
travel_max_mm = 12.0
start_mm = 6.0

[axis.homing]
direction = "negative"
seek_mm_min = 6000.0
locate_mm_min = 4000.0
pull_off_mm = 1.0

[[axis.switch]]
side = "min"
position_mm = 0.0
polarity = "normally_closed"

[[axis]]
letter = "Z"
steps_per_mm = 200.0
max_rate_mm_min = 3000.0
accel_mm_s2 = 5000.0
travel_min_mm = 0.0
travel_max_mm = 6.0
start_mm = 3.0

[axis.homing]
direction = "positive"
seek_mm_min = 3000.0
locate_mm_min = 3000.0
pull_off_mm = 1.0

[[axis.switch]]
side = "max"
position_mm = 6.0
polarity = "normally_closed"
"#;

/// One relative move unit, mm (four steps on X and Y, ten on Z).
const UNIT_MM: f64 = 0.05;

/// Axes the script moves: X, Y, Z.
const AXES: usize = 3;

/// The modal state of every script: mm, relative moves, 3000 mm/min.
const PREAMBLE: &str = "G21 G91 G1 F3000";

/// How long [`run`] waits for the machine to come to rest, wall clock: a hang guard only.
const SETTLE_WALL: Duration = Duration::from_secs(20);

/// Exchanges on the link a failure's message shows.
const LOG_LEN: usize = 40;

/// A line the firmware must refuse, whatever the machine's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BadLine {
    /// An axis the router lacks.
    UnknownAxis,
    /// A G-code the firmware does not implement.
    UnknownCommand,
    /// A modal change on a line that is refused: it must not take effect.
    ModalThenBad,
}

impl BadLine {
    fn text(self) -> &'static str {
        match self {
            Self::UnknownAxis => "G1 Q5",
            Self::UnknownCommand => "G5 X1",
            Self::ModalThenBad => "G90 G1 Q1",
        }
    }
}

/// One step of a script.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Op {
    /// `G1` relative move of `units` × 0.05 mm on axis `axis` (0 = X, 1 = Y, 2 = Z).
    Move {
        /// The axis.
        axis: usize,
        /// Signed length in 0.05 mm units, never 0.
        units: i8,
    },
    /// A line the firmware must refuse.
    Bad(BadLine),
    /// Frame 02 `Pause`.
    Pause,
    /// Frame 02 `Start` (resume).
    Start,
    /// Frame 02 `Stop`, then the machine is brought to rest.
    Stop,
    /// Frame 02 `Reset`, then the machine is brought to rest.
    Reset,
    /// Frame 04 asking for 51: answered within [`REALTIME_MS`].
    Status,
    /// Frame 01 jog of `count` × 0.05 mm on `axis`.
    Jog {
        /// The axis.
        axis: usize,
        /// Signed count of 0.05 mm steps.
        count: i8,
    },
    /// `M112`: the machine locks within [`REALTIME_MS`]; then `M999`.
    Emergency,
    /// `G28`: home every axis, then the machine is brought to rest.
    Home,
    /// The next line is damaged on its first sending: byte `at` of its body replaced.
    Corrupt {
        /// Where in the body (modulo its length).
        at: u8,
    },
    /// Let virtual time pass.
    Wait {
        /// How long, ms.
        ms: u16,
    },
}

impl Op {
    /// The script `bytes` describe: two bytes an operation, any bytes valid.
    pub fn decode(bytes: &[u8]) -> Vec<Op> {
        bytes
            .chunks_exact(2)
            .map(|c| {
                let (k, v) = (c[0], c[1]);
                let axis = usize::from(v % AXES as u8);
                let signed = (v as i8) / 4;
                match k % 16 {
                    0..=5 => Op::Move {
                        axis,
                        units: if signed == 0 { 1 } else { signed },
                    },
                    6 => Op::Bad(match v % 3 {
                        0 => BadLine::UnknownAxis,
                        1 => BadLine::UnknownCommand,
                        _ => BadLine::ModalThenBad,
                    }),
                    7 => Op::Pause,
                    8 => Op::Start,
                    9 => Op::Stop,
                    10 => Op::Status,
                    11 => Op::Jog {
                        axis,
                        count: if signed == 0 { -1 } else { signed },
                    },
                    12 => match v % 8 {
                        0 => Op::Emergency,
                        1 => Op::Reset,
                        2 => Op::Home,
                        _ => Op::Status,
                    },
                    13 => Op::Corrupt { at: v },
                    _ => Op::Wait {
                        ms: u16::from(v) * 2,
                    },
                }
            })
            .collect()
    }
}

/// What a line in flight is.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    Move { axis: usize, mm: f64 },
    Other,
}

#[derive(Debug, Clone)]
struct Sent {
    number: u32,
    bytes: Vec<u8>,
    kind: Kind,
    refused: bool,
}

/// One exchange on the link, kept for a failure's message.
#[derive(Debug)]
enum Entry {
    Op(Op),
    Sent(Vec<u8>),
    Received(String),
}

/// The last [`LOG_LEN`] exchanges, written out only when an invariant fails.
#[derive(Debug, Default)]
struct Log(VecDeque<Entry>);

impl Log {
    fn push(&mut self, entry: Entry) {
        if self.0.len() == LOG_LEN {
            self.0.pop_front();
        }
        self.0.push_back(entry);
    }

    fn tail(&self) -> String {
        let lines: Vec<String> = self
            .0
            .iter()
            .map(|e| match e {
                Entry::Op(op) => format!("# {op:?}"),
                Entry::Sent(bytes) => format!("> {}", String::from_utf8_lossy(bytes).trim_end()),
                Entry::Received(line) => format!("< {line}"),
            })
            .collect();
        lines.join("\n")
    }
}

/// What the host sees after a poll of the firmware.
struct Poll {
    status: BoardStatus,
    /// Virtual time, ms.
    now_ms: u64,
    /// Whether the step alarm is armed.
    stepping: bool,
}

/// The host side of a [`Session`]: what it sent, what it expects, and the checks made at
/// every poll of the firmware.
struct Host {
    link: MemoryHost,
    replies: Replies,
    seen: usize,
    next_number: u32,
    in_flight: Option<Sent>,
    to_send: VecDeque<(String, Kind)>,
    corrupt_next: Option<u8>,
    /// Machine position (mm) at the last point of rest, plus every acknowledged move since.
    expected: [f64; AXES],
    /// Where the firmware's machine zero is on the simulated machine, mm: set at power-on
    /// (the firmware counts from where the axes stand) and by homing.
    zero: [f64; AXES],
    homed: u8,
    /// Answers (`ok`) still owed for the unnumbered `M112` lines sent out of turn.
    owed_oks: u32,
    /// Each axis's travel on the simulated machine, mm.
    travel: [Option<(f64, f64)>; AXES],
    log: Log,
}

/// The board and its host.
struct Session {
    rig: Rig,
    host: Host,
}

fn numbered(number: u32, body: &str) -> Vec<u8> {
    let mut buf = [0u8; MAX_LINE_LEN];
    let n = write_numbered(number, body.as_bytes(), &mut buf).expect("a valid test line");
    let mut v = buf[..n].to_vec();
    v.push(b'\n');
    v
}

/// `bytes` with byte `at` of the body (between the number and `*`) changed.
fn damaged(bytes: &[u8], at: u8) -> Vec<u8> {
    let mut v = bytes.to_vec();
    let start = v.iter().position(|&b| b == b' ').map_or(1, |p| p + 1);
    let end = v.iter().position(|&b| b == b'*').unwrap_or(v.len());
    if end > start {
        let i = start + usize::from(at) % (end - start);
        v[i] = if v[i] == b'7' { b'3' } else { b'7' };
    }
    v
}

/// [`MACHINE`], parsed once.
fn machine_file() -> &'static MachineConfig {
    static FILE: OnceLock<MachineConfig> = OnceLock::new();
    FILE.get_or_init(|| {
        MachineConfig::from_toml_str(MACHINE).expect("the session's machine is valid")
    })
}

impl Host {
    fn send_raw(&mut self, bytes: &[u8]) {
        self.log.push(Entry::Sent(bytes.to_vec()));
        self.link.send(bytes);
    }

    fn send_frame(&mut self, msg: &ClientMessage<'_>) {
        let f = frame(msg);
        self.send_raw(&f);
    }

    fn queue(&mut self, body: &str, kind: Kind) {
        self.to_send.push_back((body.to_string(), kind));
    }

    /// Read the replies, act on them as the host does; send the next line when none is in
    /// flight.
    fn pump(&mut self) {
        self.replies.feed(&self.link.take_received());
        while self.seen < self.replies.lines.len() {
            let line = self.replies.lines[self.seen].clone();
            self.seen += 1;
            self.log.push(Entry::Received(line.clone()));
            self.on_reply(&line);
        }
        if self.in_flight.is_none()
            && let Some((body, kind)) = self.to_send.pop_front()
        {
            let number = self.next_number;
            self.next_number += 1;
            let bytes = numbered(number, &body);
            let first = match self.corrupt_next.take() {
                Some(at) => damaged(&bytes, at),
                None => bytes.clone(),
            };
            self.send_raw(&first);
            self.in_flight = Some(Sent {
                number,
                bytes,
                kind,
                refused: false,
            });
        }
    }

    fn on_reply(&mut self, line: &str) {
        if line == "ok" || line.starts_with("ok ") {
            if self.owed_oks > 0 {
                // Answers come in the order the firmware reads the lines, and `M112` may be
                // read before or after the line in flight: either way the first `ok` settles
                // it, and the line in flight has its own still to come.
                self.owed_oks -= 1;
            } else if let Some(sent) = self.in_flight.take()
                && !sent.refused
                && let Kind::Move { axis, mm } = sent.kind
            {
                self.expected[axis] += mm;
            }
        } else if let Some(n) = line
            .strip_prefix("rs ")
            .or_else(|| line.strip_prefix("Resend: "))
        {
            let n: u32 = n.trim().parse().expect("a resend names a line");
            let Some(sent) = self.in_flight.as_ref() else {
                panic!("a resend with no line in flight\n{}", self.log.tail());
            };
            assert_eq!(
                n,
                sent.number,
                "resend of a line not in flight\n{}",
                self.log.tail()
            );
            let bytes = sent.bytes.clone();
            self.send_raw(&bytes);
            // The `ok` that follows an `rs` is the `rs`'s, not the line's.
            self.owed_oks += 1;
        } else if matches!(
            Reply::parse(line.as_bytes()),
            Ok(Reply::Refused { .. } | Reply::Unknown(_) | Reply::Fault { .. })
        ) && let Some(sent) = self.in_flight.as_mut()
        {
            sent.refused = true;
        }
    }

    /// The operator stopped the job: the moves not sent yet are dropped (they were turned
    /// within the travel from where the moves before them were to end, which the stop makes
    /// untrue); the other lines, such as the modal preamble, still go.
    fn drop_unsent_moves(&mut self) {
        self.to_send
            .retain(|(_, kind)| !matches!(kind, Kind::Move { .. }));
        // The move in flight, if the firmware asks for it again (it was damaged, and the `rs`
        // was sent before the stop arrived), is not sent again: the operator's host does not
        // send a move written before the stop to run after it. Its number goes as an empty line.
        if let Some(sent) = self.in_flight.as_mut()
            && matches!(sent.kind, Kind::Move { .. })
        {
            sent.bytes = numbered(sent.number, "");
            sent.kind = Kind::Other;
        }
    }

    /// Nothing can happen before something is sent: no step is under way (the step alarm is
    /// not armed), the machine is at rest or stopped in a feed hold, no byte is unread by the
    /// firmware, and the host waits — with nothing to send, or for the answer to a line the
    /// firmware holds.
    fn settled(&self, poll: &Poll) -> bool {
        let st = &poll.status;
        let standing = match st.controller.state {
            MachineState::Hold { stopped } => stopped,
            _ => st.controller.idle && !st.controller.holding,
        };
        let waiting = match self.in_flight {
            None => self.to_send.is_empty(),
            Some(_) => st.controller.holding,
        };
        !poll.stepping && standing && waiting && self.link.pending_to_firmware() == 0
    }

    /// The jog of `mm` on `axis`, or of `-mm`, that keeps the machine 1 mm clear of the ends of
    /// its travel wherever it falls among the moves not yet run (a jog acts at once, before or
    /// after the move in flight and the queued ones, as the firmware reads them); `None` when
    /// neither does.
    fn jog_within_travel(&self, axis: usize, mm: f64) -> Option<f64> {
        let Some((min_mm, max_mm)) = self.travel[axis] else {
            return Some(mm);
        };
        let in_flight = self.in_flight.iter().map(|sent| sent.kind);
        let queued = self.to_send.iter().map(|(_, kind)| *kind);
        let mut stops = vec![self.expected[axis]];
        for kind in in_flight.chain(queued) {
            if let Kind::Move { axis: a, mm } = kind
                && a == axis
            {
                let last = *stops.last().unwrap_or(&self.expected[axis]);
                stops.push(last + mm);
            }
        }
        let clear = |jog: f64| {
            stops
                .iter()
                .all(|p| p + jog >= min_mm + 1.0 && p + jog <= max_mm - 1.0)
        };
        [mm, -mm].into_iter().find(|&j| clear(j))
    }

    /// `mm` on `axis`, or `-mm` when `mm` would take the machine (as far as the moves sent so
    /// far go) within 1 mm of the end of its travel: the operator keeps clear of the switches,
    /// whose alarm would drop acknowledged moves on purpose.
    fn within_travel(&self, axis: usize, mm: f64) -> f64 {
        let Some((min_mm, max_mm)) = self.travel[axis] else {
            return mm;
        };
        let queued = self.to_send.iter().map(|(_, kind)| *kind);
        let in_flight = self.in_flight.iter().map(|sent| sent.kind);
        let pending: f64 = queued
            .chain(in_flight)
            .filter_map(|kind| match kind {
                Kind::Move { axis: a, mm } if a == axis => Some(mm),
                _ => None,
            })
            .sum();
        let end = self.expected[axis] + pending + mm;
        if end < min_mm + 1.0 || end > max_mm - 1.0 {
            -mm
        } else {
            mm
        }
    }

    /// The checks made at every poll: the travel is kept, and the only alarm is `M112`'s.
    fn check(&self, status: &BoardStatus) {
        self.check_travel(status);
        self.check_no_alarm(status);
    }

    fn check_travel(&self, status: &BoardStatus) {
        if matches!(status.controller.state, MachineState::Homing) {
            return;
        }
        for axis in 0..AXES {
            if status.controller.homed & (1 << axis) == 0 {
                continue;
            }
            let Some((min, max)) = self.travel[axis] else {
                continue;
            };
            let at = status.machine_mm[axis];
            assert!(
                at >= min - 1e-6 && at <= max + 1e-6,
                "homed axis {axis} at {at} mm, outside its travel {min}..{max}\n{}",
                self.log.tail()
            );
        }
    }

    /// The script keeps clear of the switches: the only alarm is the one `M112` raises.
    fn check_no_alarm(&self, status: &BoardStatus) {
        if let MachineState::Alarm(a) = status.controller.state {
            assert_eq!(
                a,
                forja_motion::Alarm::EmergencyStop,
                "unexpected alarm\n{}",
                self.log.tail()
            );
        }
    }
}

impl Session {
    fn new() -> Self {
        let file = machine_file();
        let mut rig = Rig::on(SimMachine::new(file), BoardConfig::default());
        let (link, host) = MemoryLink::pair();
        rig.board.add_port(link, false);
        let expected = core::array::from_fn(|a| rig.machine.positions_mm()[a]);
        let firmware = rig.board.status().machine_mm;
        let zero = core::array::from_fn(|a| expected[a] - firmware[a]);
        let travel = core::array::from_fn(|a| file.axes[a].travel.map(|t| (t.min_mm, t.max_mm)));
        let mut s = Self {
            rig,
            host: Host {
                link: host,
                replies: Replies::default(),
                seen: 0,
                next_number: 1,
                in_flight: None,
                to_send: VecDeque::new(),
                corrupt_next: None,
                expected,
                zero,
                homed: 0,
                owed_oks: 0,
                travel,
                log: Log::default(),
            },
        };
        s.host.queue(PREAMBLE, Kind::Other);
        s.drain();
        s
    }

    fn status(&self) -> BoardStatus {
        self.rig.board.status()
    }

    /// Run `ms` of virtual time, pumping the host. While the machine stands still and neither
    /// side has anything to say ([`Host::settled`]), the firmware is polled at the end only
    /// (and again every millisecond as soon as a poll finds it otherwise); every poll is
    /// checked.
    fn run_for(&mut self, ms: u64) {
        let end = self.rig.now_ms() + ms;
        loop {
            self.run_while(|h, p| p.now_ms < end && !h.settled(p));
            let now = self.rig.now_ms();
            if now >= end {
                return;
            }
            let tick_hz = u64::from(self.rig.machine.tick_hz());
            let config = self.rig.sim.config_mut();
            let period = config.poll_period_ticks;
            config.poll_period_ticks = (end - now) * tick_hz / 1000;
            self.run_while(|h, p| p.now_ms < end && h.settled(p));
            self.rig.sim.config_mut().poll_period_ticks = period;
        }
    }

    /// Run while `go` says so (bounded by the wall clock), pumping the host and making the
    /// checks of [`Host::check`] at every poll of the firmware. Returns whether `go` ended it.
    fn run_while(&mut self, mut go: impl FnMut(&mut Host, &Poll) -> bool) -> bool {
        let Self { rig, host } = self;
        let mut turn = |host: &mut Host, board: &SimBoard, now_ms: u64| {
            host.pump();
            let poll = Poll {
                status: board.status(),
                now_ms,
                stepping: board.machine().alarm_at_ticks().is_some(),
            };
            host.check(&poll.status);
            go(host, &poll)
        };
        if !turn(host, &rig.board, rig.now_ms()) {
            return true;
        }
        rig.run_until(SETTLE_WALL, |board, now| !turn(host, board, now))
    }

    /// Send every queued line and wait for the answers and for rest.
    fn drain(&mut self) {
        let done = self.run_while(|h, p| {
            let st = &p.status;
            !(h.in_flight.is_none()
                && h.to_send.is_empty()
                && st.controller.idle
                && !st.controller.holding)
        });
        assert!(
            done,
            "the machine did not come to rest: {:?}\n{}",
            self.status(),
            self.host.log.tail()
        );
    }

    /// At rest: the steps reached equal the acknowledged moves, and `M114` says so.
    fn check_position(&mut self) {
        let at = self.rig.machine.positions_mm();
        for (axis, (reached, expected)) in at.iter().zip(self.host.expected).enumerate() {
            assert!(
                (reached - expected).abs() < 1e-3,
                "axis {axis} at {reached} mm, the acknowledged moves end at {expected} mm\n{}",
                self.host.log.tail()
            );
        }
        let before = self.host.replies.lines.len();
        self.host.queue("M114", Kind::Other);
        self.drain();
        let report = self.host.replies.lines[before..]
            .iter()
            .find(|l| l.starts_with("X:"))
            .cloned()
            .unwrap_or_else(|| panic!("no M114 report\n{}", self.host.log.tail()));
        for (axis, letter) in ["X:", "Y:", "Z:"].iter().enumerate() {
            let value: f64 = report
                .split_whitespace()
                .find_map(|w| w.strip_prefix(letter))
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("M114 without {letter}: {report}"));
            let steps_reached = at[axis] - self.host.zero[axis];
            assert!(
                (value - steps_reached).abs() < 1e-3,
                "M114 says {report}, the steps reached {steps_reached} on axis {axis}\n{}",
                self.host.log.tail()
            );
        }
    }

    /// Bring the machine to rest after an operation that drops motion on purpose, and take
    /// where it is as the new reference.
    fn rest_and_rebase(&mut self) {
        if matches!(self.status().controller.state, MachineState::Hold { .. }) {
            self.host.send_frame(&ClientMessage::Action(Action::Start));
        }
        self.drain();
        let at = self.rig.machine.positions_mm();
        self.host.expected = core::array::from_fn(|a| at[a]);
        let status = self.status();
        if status.controller.homed != self.host.homed {
            self.host.zero = core::array::from_fn(|a| at[a] - status.machine_mm[a]);
        }
        self.host.homed = status.controller.homed;
    }

    fn apply(&mut self, op: Op) {
        self.host.log.push(Entry::Op(op));
        match op {
            Op::Move { axis, units } => {
                let mm = self.host.within_travel(axis, f64::from(units) * UNIT_MM);
                let letter = ["X", "Y", "Z"][axis];
                self.host
                    .queue(&format!("G1 {letter}{mm:.2}"), Kind::Move { axis, mm });
                self.run_for(1);
            }
            Op::Bad(bad) => {
                self.host.queue(bad.text(), Kind::Other);
                self.run_for(1);
            }
            Op::Pause => {
                self.host.send_frame(&ClientMessage::Action(Action::Pause));
                self.run_for(1);
            }
            Op::Start => {
                self.host.send_frame(&ClientMessage::Action(Action::Start));
                self.run_for(1);
            }
            Op::Stop => {
                self.host.send_frame(&ClientMessage::Action(Action::Stop));
                self.host.drop_unsent_moves();
                self.rest_and_rebase();
                self.check_position();
            }
            Op::Reset => {
                self.host.send_frame(&ClientMessage::Action(Action::Reset));
                self.host.drop_unsent_moves();
                self.rest_and_rebase();
                self.check_position();
                // A reset brings the modal state back to its defaults (absolute moves).
                self.host.queue(PREAMBLE, Kind::Other);
            }
            Op::Status => self.status_within_realtime(),
            Op::Jog { axis, count } => self.jog(axis, count),
            Op::Emergency => self.emergency(),
            Op::Home => {
                self.host.queue("G28", Kind::Other);
                self.rest_and_rebase();
                // G28 leaves relative mode as it was; the reference is the homed position.
                self.check_position();
            }
            Op::Corrupt { at } => self.host.corrupt_next = Some(at),
            Op::Wait { ms } => self.run_for(u64::from(ms)),
        }
    }

    fn status_within_realtime(&mut self) {
        let before = self.host.replies.lines.len();
        let sent_at = self.rig.now_ms();
        self.host
            .send_frame(&ClientMessage::Request { message_type: 51 });
        let answered = |h: &Host| {
            crate::frames(&h.replies.lines[before..])
                .iter()
                .any(|m| matches!(m, ControllerMessage::Positions(_)))
        };
        self.run_while(|h, p| !answered(h) && p.now_ms <= sent_at + REALTIME_MS);
        assert!(
            answered(&self.host),
            "frame 04 not answered within {REALTIME_MS} ms ({:?})\n{}",
            self.status(),
            self.host.log.tail()
        );
    }

    fn emergency(&mut self) {
        let sent_at = self.rig.now_ms();
        self.host.send_raw(b"M112\n");
        self.host.owed_oks += 1;
        let locked = |st: &BoardStatus| {
            matches!(
                st.controller.state,
                MachineState::Alarm(forja_motion::Alarm::EmergencyStop)
            )
        };
        self.run_while(|_, p| !locked(&p.status) && p.now_ms <= sent_at + REALTIME_MS);
        assert!(
            locked(&self.status()),
            "M112 did not act within {REALTIME_MS} ms ({:?})\n{}",
            self.status(),
            self.host.log.tail()
        );
        // Every line still queued is refused while locked: the host waits for the answers
        // (to `M112` too), then resets.
        self.host.to_send.clear();
        let answered = self.run_while(|h, _| h.in_flight.is_some() || h.owed_oks > 0);
        assert!(
            answered,
            "M112 or the line in flight was not answered ({:?})\n{}",
            self.status(),
            self.host.log.tail()
        );
        self.host.queue("M999", Kind::Other);
        self.rest_and_rebase();
        self.check_position();
        self.host.queue(PREAMBLE, Kind::Other);
    }

    fn jog(&mut self, axis: usize, count: i8) {
        let mm = f64::from(count) * UNIT_MM;
        let count = match self.host.jog_within_travel(axis, mm) {
            Some(j) if j == mm => count,
            Some(_) => count.saturating_neg(),
            // No room either way among the moves not yet run: the operator does not jog.
            None => return,
        };
        let before = self.host.replies.lines.len();
        let axis_letter = [b'X', b'Y', b'Z'][axis];
        self.host.send_frame(&ClientMessage::Jog {
            step: Decimal::new(5, 2),
            axis: axis_letter,
            count: i32::from(count),
        });
        self.run_for(REALTIME_MS);
        let refused = crate::frames(&self.host.replies.lines[before..])
            .iter()
            .any(|m| matches!(m, ControllerMessage::Error { .. }));
        if !refused {
            self.host.expected[axis] += f64::from(count) * UNIT_MM;
        }
    }

    fn finish(&mut self) {
        if matches!(self.status().controller.state, MachineState::Hold { .. }) {
            self.host.send_frame(&ClientMessage::Action(Action::Start));
        }
        self.drain();
        self.check_position();
        assert_eq!(
            self.rig.machine.violation_count(),
            0,
            "step timing violated"
        );
    }
}

/// Run `script` on a fresh [`MACHINE`] and check every invariant of the module; panics with
/// the last exchanges on the link when one fails.
pub fn run(script: &[Op]) {
    let mut s = Session::new();
    for &op in script {
        s.apply(op);
    }
    s.finish();
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `M112` sent while a damaged line is on its way: the firmware answers `M112` first and
    /// then asks for the line again, which the host still has in flight.
    #[test]
    fn a_resend_after_m112_is_for_the_line_in_flight() {
        run(&[Op::Emergency, Op::Corrupt { at: 16 }, Op::Emergency]);
    }

    /// A stop behind moves that were acknowledged and not yet run, with more moves queued
    /// that those would have kept within the travel: the queued moves are dropped, not sent
    /// into the switch (found by the fuzz target).
    #[test]
    fn a_stop_drops_the_moves_not_sent() {
        let mut bytes = vec![
            187, 60, 49, 116, 116, 116, 116, 116, 116, 116, 0, 0, 0, 65, 65,
        ];
        bytes.extend([0, 0, 116, 116]);
        bytes.extend([0; 50]);
        bytes.extend([65, 65, 65, 65, 41, 41, 0]);
        run(&Op::decode(&bytes));
    }

    /// A wait at rest ends exactly at its time, and one behind a move lets the move run: the
    /// acknowledged move is where the machine stands.
    #[test]
    fn waits_end_on_time_and_let_moves_run() {
        let mut s = Session::new();
        let start = s.rig.now_ms();
        s.apply(Op::Wait { ms: 500 });
        assert_eq!(s.rig.now_ms(), start + 500);
        s.apply(Op::Move { axis: 0, units: 20 });
        s.apply(Op::Wait { ms: 500 });
        s.finish();
        assert!((s.host.expected[0] - (6.0 + 1.0)).abs() < 1e-9);
    }
}
