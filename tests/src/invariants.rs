//! The controller's safety invariants, checked under arbitrary interleavings of host input.
//!
//! A [`Session`] is the simulator's router board on an in-memory link, played by a host that
//! behaves as Printrun does (numbered, checksummed lines, one in flight, `rs` answered by a
//! resend) while an operator interleaves the frames' realtime actions, `M112`, jogs, homing,
//! refused lines, damaged lines and waits. [`Op::decode`] turns any bytes into such a script,
//! so the same [`run`] serves a proptest (`tests/invariants.rs`) and a `cargo fuzz` target.
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
use std::time::Duration;

use forja_motion::MachineState;
use forja_protocol::frame::{Action, ClientMessage, ControllerMessage};
use forja_protocol::gcode::{Decimal, MAX_LINE_LEN, write_numbered};
use forja_sim::board::BoardConfig;
use forja_sim::link::{MemoryHost, MemoryLink};

use crate::{Replies, Rig, frame};

/// The longest a realtime command may take to act, virtual ms.
pub const REALTIME_MS: u64 = 10;

/// One relative move unit, mm (four steps on the router's 80 steps/mm axes).
const UNIT_MM: f64 = 0.05;

/// Axes the script moves: X, Y, Z (A is rotary).
const AXES: usize = 3;

/// The modal state of every script: mm, relative moves, 3000 mm/min.
const PREAMBLE: &str = "G21 G91 G1 F3000";

/// How long [`run`] waits for the machine to come to rest, wall clock: a hang guard only.
const SETTLE_WALL: Duration = Duration::from_secs(20);

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

/// The host, the board and what the invariants expect.
struct Session {
    rig: Rig,
    host: MemoryHost,
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
    log: Vec<String>,
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

impl Session {
    fn new() -> Self {
        let mut rig = Rig::new("default", BoardConfig::default());
        let (link, host) = MemoryLink::pair();
        rig.board.add_port(link, false);
        let expected = core::array::from_fn(|a| rig.machine.positions_mm()[a]);
        let firmware = rig.board.status().machine_mm;
        let zero = core::array::from_fn(|a| expected[a] - firmware[a]);
        let mut s = Self {
            rig,
            host,
            replies: Replies::default(),
            seen: 0,
            next_number: 1,
            in_flight: None,
            to_send: VecDeque::new(),
            corrupt_next: None,
            expected,
            zero,
            homed: 0,
            log: Vec::new(),
        };
        s.queue(PREAMBLE, Kind::Other);
        s.drain();
        s
    }

    fn queue(&mut self, body: &str, kind: Kind) {
        self.to_send.push_back((body.to_string(), kind));
    }

    fn send_raw(&mut self, bytes: &[u8]) {
        self.log
            .push(format!("> {}", String::from_utf8_lossy(bytes).trim_end()));
        self.host.send(bytes);
    }

    /// Read the replies, act on them as the host does; send the next line when none is in
    /// flight.
    fn pump(&mut self) {
        self.replies.feed(&self.host.take_received());
        while self.seen < self.replies.lines.len() {
            let line = self.replies.lines[self.seen].clone();
            self.seen += 1;
            self.log.push(format!("< {line}"));
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
            if let Some(sent) = self.in_flight.take()
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
            let sent = self
                .in_flight
                .as_ref()
                .expect("a resend with no line in flight");
            assert_eq!(n, sent.number, "resend of a line not in flight");
            let bytes = sent.bytes.clone();
            self.send_raw(&bytes);
        } else if (line.starts_with("!!") || line.starts_with("Error:"))
            && let Some(sent) = self.in_flight.as_mut()
        {
            sent.refused = true;
        }
    }

    /// Run `ms` of virtual time, pumping the host; `check` is called at every poll.
    fn run_for(&mut self, ms: u64) {
        let end = self.rig.now_ms() + ms;
        self.run_while(|_, now| now < end);
    }

    /// Run while `go` says so (bounded by the wall clock), pumping the host and checking the
    /// travel at every poll. Returns whether `go` ended it.
    fn run_while(&mut self, mut go: impl FnMut(&mut Self, u64) -> bool) -> bool {
        let deadline = std::time::Instant::now() + SETTLE_WALL;
        loop {
            let now = self.rig.now_ms();
            self.pump();
            self.check_travel();
            self.check_no_alarm();
            if !go(self, now) {
                return true;
            }
            if std::time::Instant::now() > deadline {
                return false;
            }
            let target = now + 1;
            let machine = self.rig.machine.clone();
            let tick_hz = u64::from(machine.tick_hz());
            self.rig.run_until(Duration::from_secs(5), |_, _| {
                machine.now_ticks() * 1000 / tick_hz >= target
            });
        }
    }

    /// `mm` on `axis`, or `-mm` when `mm` would take the machine (as far as the moves sent so
    /// far go) within 1 mm of the end of its travel: the operator keeps clear of the switches,
    /// whose alarm would drop acknowledged moves on purpose.
    fn within_travel(&self, axis: usize, mm: f64) -> f64 {
        let Some(travel) = self.rig.machine.config().axes[axis].travel else {
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
        if end < travel.min_mm + 1.0 || end > travel.max_mm - 1.0 {
            -mm
        } else {
            mm
        }
    }

    fn check_travel(&self) {
        let status = self.rig.board.status();
        if matches!(status.state, MachineState::Homing) {
            return;
        }
        let homed = status.homed;
        for axis in 0..AXES {
            if homed & (1 << axis) == 0 {
                continue;
            }
            let Some(travel) = self.rig.machine.config().axes[axis].travel else {
                continue;
            };
            let (min, max) = (travel.min_mm, travel.max_mm);
            let at = status.machine_mm[axis];
            assert!(
                at >= min - 1e-6 && at <= max + 1e-6,
                "homed axis {axis} at {at} mm, outside its travel {min}..{max}\n{}",
                self.tail()
            );
        }
    }

    /// The script keeps clear of the switches: the only alarm is the one `M112` raises.
    fn check_no_alarm(&self) {
        let state = self.rig.board.status().state;
        if let MachineState::Alarm(a) = state {
            assert_eq!(
                a,
                forja_motion::Alarm::EmergencyStop,
                "unexpected alarm\n{}",
                self.tail()
            );
        }
    }

    fn tail(&self) -> String {
        let from = self.log.len().saturating_sub(40);
        self.log[from..].join("\n")
    }

    /// Send every queued line and wait for the answers and for rest.
    fn drain(&mut self) {
        let done = self.run_while(|s, _| {
            let st = s.rig.board.status();
            !(s.in_flight.is_none() && s.to_send.is_empty() && st.idle && !st.holding)
        });
        assert!(
            done,
            "the machine did not come to rest: {:?}\n{}",
            self.rig.board.status(),
            self.tail()
        );
    }

    /// At rest: the steps reached equal the acknowledged moves, and `M114` says so.
    fn check_position(&mut self) {
        let at = self.rig.machine.positions_mm();
        for (axis, (reached, expected)) in at.iter().zip(self.expected).enumerate() {
            assert!(
                (reached - expected).abs() < 1e-3,
                "axis {axis} at {reached} mm, the acknowledged moves end at {expected} mm\n{}",
                self.tail()
            );
        }
        let before = self.replies.lines.len();
        self.queue("M114", Kind::Other);
        self.drain();
        let report = self.replies.lines[before..]
            .iter()
            .find(|l| l.starts_with("ok C:"))
            .cloned()
            .unwrap_or_else(|| panic!("no M114 report\n{}", self.tail()));
        for (axis, letter) in ["X:", "Y:", "Z:"].iter().enumerate() {
            let value: f64 = report
                .split_whitespace()
                .find_map(|w| w.strip_prefix(letter))
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("M114 without {letter}: {report}"));
            let steps_reached = at[axis] - self.zero[axis];
            assert!(
                (value - steps_reached).abs() < 1e-3,
                "M114 says {report}, the steps reached {steps_reached} on axis {axis}\n{}",
                self.tail()
            );
        }
    }

    /// Bring the machine to rest after an operation that drops motion on purpose, and take
    /// where it is as the new reference.
    fn rest_and_rebase(&mut self) {
        if matches!(self.rig.board.status().state, MachineState::Hold { .. }) {
            self.send_frame(&ClientMessage::Action(Action::Start));
        }
        self.drain();
        let at = self.rig.machine.positions_mm();
        self.expected = core::array::from_fn(|a| at[a]);
        let status = self.rig.board.status();
        if status.homed != self.homed {
            self.zero = core::array::from_fn(|a| at[a] - status.machine_mm[a]);
        }
        self.homed = status.homed;
    }

    fn send_frame(&mut self, msg: &ClientMessage<'_>) {
        let f = frame(msg);
        self.send_raw(&f);
    }

    fn apply(&mut self, op: Op) {
        self.log.push(format!("# {op:?}"));
        match op {
            Op::Move { axis, units } => {
                let mm = self.within_travel(axis, f64::from(units) * UNIT_MM);
                let letter = ["X", "Y", "Z"][axis];
                self.queue(&format!("G1 {letter}{mm:.2}"), Kind::Move { axis, mm });
                self.run_for(1);
            }
            Op::Bad(bad) => {
                self.queue(bad.text(), Kind::Other);
                self.run_for(1);
            }
            Op::Pause => {
                self.send_frame(&ClientMessage::Action(Action::Pause));
                self.run_for(1);
            }
            Op::Start => {
                self.send_frame(&ClientMessage::Action(Action::Start));
                self.run_for(1);
            }
            Op::Stop => {
                self.send_frame(&ClientMessage::Action(Action::Stop));
                self.rest_and_rebase();
                self.check_position();
            }
            Op::Reset => {
                self.send_frame(&ClientMessage::Action(Action::Reset));
                self.rest_and_rebase();
                self.check_position();
                // A reset brings the modal state back to its defaults (absolute moves).
                self.queue(PREAMBLE, Kind::Other);
            }
            Op::Status => self.status_within_realtime(),
            Op::Jog { axis, count } => self.jog(axis, count),
            Op::Emergency => self.emergency(),
            Op::Home => {
                self.queue("G28", Kind::Other);
                self.rest_and_rebase();
                // G28 leaves relative mode as it was; the reference is the homed position.
                self.check_position();
            }
            Op::Corrupt { at } => self.corrupt_next = Some(at),
            Op::Wait { ms } => self.run_for(u64::from(ms)),
        }
    }

    fn status_within_realtime(&mut self) {
        let before = self.replies.lines.len();
        let sent_at = self.rig.now_ms();
        self.send_frame(&ClientMessage::Request { message_type: 51 });
        let answered = |s: &Self| {
            crate::frames(&s.replies.lines[before..])
                .iter()
                .any(|m| matches!(m, ControllerMessage::Positions(_)))
        };
        self.run_while(|s, now| !answered(s) && now <= sent_at + REALTIME_MS);
        assert!(
            answered(self),
            "frame 04 not answered within {REALTIME_MS} ms ({:?})\n{}",
            self.rig.board.status(),
            self.tail()
        );
    }

    fn emergency(&mut self) {
        let sent_at = self.rig.now_ms();
        self.send_raw(b"M112\n");
        let locked = |s: &Self| {
            matches!(
                s.rig.board.status().state,
                MachineState::Alarm(forja_motion::Alarm::EmergencyStop)
            )
        };
        self.run_while(|s, now| !locked(s) && now <= sent_at + REALTIME_MS);
        assert!(
            locked(self),
            "M112 did not act within {REALTIME_MS} ms ({:?})\n{}",
            self.rig.board.status(),
            self.tail()
        );
        // Every line still queued is refused while locked: the host waits for the answers,
        // then resets.
        self.to_send.clear();
        self.run_while(|s, _| s.in_flight.is_some());
        self.queue("M999", Kind::Other);
        self.rest_and_rebase();
        self.check_position();
        self.queue(PREAMBLE, Kind::Other);
    }

    fn jog(&mut self, axis: usize, count: i8) {
        let count = if self.within_travel(axis, f64::from(count)) == f64::from(count) {
            count
        } else {
            count.saturating_neg()
        };
        let before = self.replies.lines.len();
        let axis_letter = [b'X', b'Y', b'Z'][axis];
        self.send_frame(&ClientMessage::Jog {
            step: Decimal::new(5, 2),
            axis: axis_letter,
            count: i32::from(count),
        });
        self.run_for(REALTIME_MS);
        let refused = crate::frames(&self.replies.lines[before..])
            .iter()
            .any(|m| matches!(m, ControllerMessage::Error { .. }));
        if !refused {
            self.expected[axis] += f64::from(count) * UNIT_MM;
        }
    }

    fn finish(&mut self) {
        if matches!(self.rig.board.status().state, MachineState::Hold { .. }) {
            self.send_frame(&ClientMessage::Action(Action::Start));
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

/// Run `script` on a fresh router and check every invariant of the module; panics with the
/// last exchanges on the link when one fails.
pub fn run(script: &[Op]) {
    let mut s = Session::new();
    for &op in script {
        s.apply(op);
    }
    s.finish();
}
