//! Jobs "on the SD card" as a printer host runs them, over the simulator's link: a job of more
//! than a thousand numbered, checksummed lines uploaded with `M28`/`M29` (stored, never run),
//! listed with `M20`, printed with `M23`/`M24` and followed with `M27` to `Done printing
//! file`; every move runs once, as the simulated steppers count them. A refused `M28` lets
//! none of the lines sent after it move the machine.

use std::collections::VecDeque;
use std::time::Duration;

use forja_protocol::gcode::write_numbered;
use forja_sim::board::{BoardConfig, SimBoard};
use forja_sim_hal::link::{MemoryHost, MemoryLink};
use forja_tests::{HostEnd, Replies, Rig};

/// A host that sends one line at a time and the next once the last is answered `ok`, as
/// OctoPrint streams an upload; every line numbered and checksummed.
struct PingPong {
    link: MemoryHost,
    replies: Replies,
    to_send: VecDeque<String>,
    /// The next line number.
    number: u32,
    /// A line is out and not yet answered.
    waiting: bool,
}

impl PingPong {
    fn new(link: MemoryHost) -> Self {
        Self {
            link,
            replies: Replies::default(),
            to_send: VecDeque::new(),
            number: 1,
            waiting: false,
        }
    }

    /// Queue `lines`.
    fn queue<S: AsRef<str>>(&mut self, lines: &[S]) {
        self.to_send
            .extend(lines.iter().map(|l| l.as_ref().to_string()));
    }

    /// Read the firmware's replies, and send the next line when the last was answered.
    fn turn(&mut self) {
        for line in self.replies.feed(&self.link.receive()) {
            assert!(
                !line.starts_with("rs") && !line.starts_with("Error:"),
                "{line}"
            );
            if line.starts_with("ok") {
                self.waiting = false;
            }
        }
        if !self.waiting
            && let Some(body) = self.to_send.pop_front()
        {
            let mut buf = [0u8; 300];
            let n = write_numbered(self.number, body.as_bytes(), &mut buf).unwrap();
            self.number += 1;
            buf[n] = b'\n';
            self.link.send(&buf[..=n]);
            self.waiting = true;
        }
    }

    /// Whether every line queued was sent and answered.
    fn done(&self) -> bool {
        self.to_send.is_empty() && !self.waiting
    }
}

/// The board with a host on an in-memory link.
fn rig() -> (Rig, PingPong) {
    let mut rig = Rig::new("default", BoardConfig::default());
    let (link, host) = MemoryLink::pair();
    rig.board.add_port(link, false);
    (rig, PingPong::new(host))
}

/// Run until the host has sent and seen answered every line queued.
fn exchange(rig: &mut Rig, host: &mut PingPong) {
    let done = rig.run_until(Duration::from_secs(60), |_, _| {
        host.turn();
        host.done()
    });
    assert!(done, "not answered: {:?}", host.replies.lines.last());
}

/// `n` relative moves in X and Y of different lengths: (the lines, the net move of X and Y in
/// steps, the steps each axis makes).
fn job(n: usize) -> (Vec<String>, [i64; 2], [u64; 2]) {
    let mut lines = vec![
        "; a job of relative moves".to_string(),
        "G21 G91".to_string(),
        "G1 F6000".to_string(),
    ];
    let (mut net, mut steps) = ([0i64; 2], [0u64; 2]);
    for i in 0..n {
        let x = ((i % 7) as i64 + 1) * 4 * if i % 2 == 0 { 1 } else { -1 };
        let y = ((i % 5) as i64 + 1) * 4 * if i % 3 == 0 { -1 } else { 1 };
        // Steps of 1/80 mm: 4 steps are 0.05 mm.
        lines.push(format!(
            "G1 X{:.2} Y{:.2}",
            x as f64 / 80.0,
            y as f64 / 80.0
        ));
        if i % 100 == 50 {
            lines.push(format!("; layer {}", i / 100));
        }
        net[0] += x;
        net[1] += y;
        steps[0] += x.unsigned_abs();
        steps[1] += y.unsigned_abs();
    }
    lines.push("G90".to_string());
    (lines, net, steps)
}

fn steps(board: &SimBoard) -> ([i64; 2], [u64; 2]) {
    let m = board.machine();
    (
        [0, 1].map(|a| m.position_steps(a).unwrap()),
        [0, 1].map(|a| m.step_count(a).unwrap()),
    )
}

#[test]
fn a_job_uploaded_to_the_card_prints_every_move_once() {
    let (mut rig, mut host) = rig();
    let (lines, net, made) = job(1200);
    host.queue(&["M21", "M28 /BIG~1.GCO"]);
    host.queue(&lines);
    host.queue(&["M29", "M20"]);
    let (position_before, steps_before) = steps(&rig.board);
    exchange(&mut rig, &mut host);
    let out = &host.replies.lines;
    assert!(out.contains(&"echo:SD card ok".to_string()), "{out:?}");
    assert!(out.contains(&"Writing to file: BIG~1.GCO".to_string()));
    assert!(out.contains(&"Done saving file.".to_string()));
    assert_eq!(
        steps(&rig.board),
        (position_before, steps_before),
        "nothing ran"
    );
    let begin = out.iter().position(|l| l == "Begin file list").unwrap();
    assert_eq!(out[begin + 2], "End file list");
    let (name, size) = out[begin + 1].split_once(' ').unwrap();
    assert_eq!(name, "BIG~1.GCO");
    // Stored without numbers, checksums and comments: one line each.
    let stored: usize = lines
        .iter()
        .filter(|l| !l.starts_with(';'))
        .map(|l| l.len() + 1)
        .sum();
    assert_eq!(size.parse::<usize>().unwrap(), stored);

    host.replies.clear();
    host.queue(&["M23 /big~1.gco", "M24"]);
    exchange(&mut rig, &mut host);
    assert!(
        host.replies.lines[0].starts_with(&format!("File opened: big~1.gco Size: {stored}")),
        "{:?}",
        host.replies.lines
    );
    // Followed as OctoPrint follows it: `M27` every second until it is done.
    let mut positions = Vec::new();
    let mut next_poll_ms = rig.now_ms();
    let mut seen = host.replies.lines.len();
    let done = rig.run_until(Duration::from_secs(120), |_, now_ms| {
        host.turn();
        for l in &host.replies.lines[seen..] {
            if let Some(p) = l.strip_prefix("SD printing byte ") {
                let (at, of) = p.split_once('/').unwrap();
                let at: u32 = at.parse().unwrap();
                assert_eq!(of.parse::<usize>().unwrap(), stored);
                if positions.last() != Some(&at) {
                    positions.push(at);
                }
            }
        }
        seen = host.replies.lines.len();
        if host.done() && now_ms >= next_poll_ms {
            host.queue(&["M27"]);
            next_poll_ms = now_ms + 1000;
        }
        host.replies.lines.iter().any(|l| l == "Done printing file")
    });
    assert!(done, "{:?}", rig.board.status());
    assert!(positions.len() > 2, "{} reports", positions.len());
    assert!(positions.is_sorted(), "{positions:?}");
    let settled = rig.run_until(Duration::from_secs(30), |board, _| {
        host.turn();
        host.done() && board.status().controller.idle
    });
    assert!(settled);
    host.replies.clear();
    host.queue(&["M27"]);
    exchange(&mut rig, &mut host);
    assert_eq!(host.replies.lines, ["Not SD printing", "ok"]);
    let (position, count) = steps(&rig.board);
    for axis in 0..2 {
        assert_eq!(
            position[axis] - position_before[axis],
            net[axis],
            "axis {axis}"
        );
        assert_eq!(count[axis] - steps_before[axis], made[axis], "axis {axis}");
    }
    assert_eq!(rig.machine.violation_count(), 0);
}

#[test]
fn a_refused_upload_moves_nothing() {
    let (mut rig, mut host) = rig();
    let before = steps(&rig.board);
    let (lines, _, _) = job(50);
    host.queue(&["M28 no/such/dir.gco"]);
    host.queue(&lines);
    host.queue(&["M29"]);
    exchange(&mut rig, &mut host);
    let out = &host.replies.lines;
    assert!(
        out.contains(&"open failed, File: no/such/dir.gco.".to_string()),
        "{out:?}"
    );
    let refused = out.iter().filter(|l| l.starts_with("echo:E178")).count();
    assert_eq!(
        refused,
        1 + lines.iter().filter(|l| !l.starts_with(';')).count()
    );
    let end_ms = rig.now_ms() + 1000;
    rig.run_until(Duration::from_secs(10), |_, now_ms| now_ms >= end_ms);
    assert_eq!(steps(&rig.board), before);
    host.replies.clear();
    host.queue(&["M20"]);
    exchange(&mut rig, &mut host);
    assert_eq!(
        host.replies.lines,
        ["Begin file list", "End file list", "ok"]
    );
}
