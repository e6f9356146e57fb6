//! One controlling host across the board's ports (TCP and the pseudo-terminal): a host that is
//! not in control never has a byte run, a new session starts with nothing of the previous one,
//! and a silent host loses control after the idle time-out.
//!
//! The board runs in virtual time as fast as it can; the wall clock only guards against a hang.

use std::fs::{File, OpenOptions};
use std::io::ErrorKind;
use std::net::TcpStream;
use std::os::unix::fs::OpenOptionsExt;
use std::time::{Duration, Instant};

use forja_sim::board::{BoardConfig, PortId, SimBoard};
use forja_sim_hal::link::{MemoryLink, PortLink, PtyLink, TcpLink};
use forja_sim_hal::{Flow, MachineConfig, SimMachine, Simulation, SimulationConfig};

/// Hang guard of every wait.
const WALL: Duration = Duration::from_secs(20);

const BUSY: &[u8] = b"error: busy\n";

/// The router, with a TCP port (frames) and a pseudo-terminal port, as `forja-sim --listen`.
struct Rig {
    machine: SimMachine,
    board: SimBoard,
    sim: Simulation,
    tcp: PortId,
    pty: PortId,
    pty_path: std::path::PathBuf,
}

impl Rig {
    fn new(idle_timeout_ms: Option<u32>) -> Self {
        let machine = SimMachine::new(&MachineConfig::default_router());
        let mut board = SimBoard::new(&machine, BoardConfig::default()).unwrap();
        let tcp = board.add_port(
            TcpLink::bind("127.0.0.1:0".parse().unwrap(), BUSY).unwrap(),
            true,
        );
        let pty_link = PtyLink::open(None).unwrap();
        let pty_path = pty_link.slave_path().to_path_buf();
        let pty = board.add_port(pty_link, false);
        for port in [tcp, pty] {
            board.set_idle_timeout(port, idle_timeout_ms);
        }
        board.set_busy_message(BUSY);
        let sim = Simulation::new(machine.clone(), SimulationConfig::new(machine.tick_hz()));
        Self {
            machine,
            board,
            sim,
            tcp,
            pty,
            pty_path,
        }
    }

    fn now_ms(&self) -> u64 {
        self.machine.now_ticks() * 1000 / u64::from(self.machine.tick_hz())
    }

    /// Run until `done` holds (checked after every turn); fails after [`WALL`].
    fn run_until(&mut self, what: &str, mut done: impl FnMut(&mut SimBoard) -> bool) {
        let deadline = Instant::now() + WALL;
        let mut reached = false;
        self.board
            .run(&mut self.sim, |board, _| {
                if done(board) {
                    reached = true;
                    return Flow::Stop;
                }
                if Instant::now() > deadline {
                    return Flow::Stop;
                }
                Flow::Continue
            })
            .unwrap();
        assert!(reached, "timed out waiting for {what}");
    }

    /// Run `ms` of virtual time, `each` called after every turn.
    fn run_for(&mut self, ms: u64, mut each: impl FnMut(&mut SimBoard)) {
        let end = self.now_ms() + ms;
        let machine = self.machine.clone();
        let tick_hz = u64::from(machine.tick_hz());
        self.run_until("virtual time", |board| {
            each(board);
            machine.now_ticks() * 1000 / tick_hz >= end
        });
    }

    fn tcp_client(&self) -> Host<TcpStream> {
        let addr = self
            .board
            .port::<TcpLink>(self.tcp)
            .unwrap()
            .local_addr()
            .unwrap();
        let stream = TcpStream::connect(addr).unwrap();
        stream.set_nonblocking(true).unwrap();
        Host::new(stream)
    }

    fn pty_host(&self) -> Host<File> {
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags((nix::fcntl::OFlag::O_NOCTTY | nix::fcntl::OFlag::O_NONBLOCK).bits())
            .open(&self.pty_path)
            .unwrap();
        Host::new(file)
    }

    fn x_mm(&self) -> f64 {
        self.machine.position_mm(0).unwrap()
    }
}

/// A host's end: what it has received so far, and whether its peer closed.
struct Host<S> {
    io: S,
    text: String,
    closed: bool,
}

impl<S: std::io::Read + std::io::Write> Host<S> {
    fn new(io: S) -> Self {
        Self {
            io,
            text: String::new(),
            closed: false,
        }
    }

    /// Take what has arrived, without waiting.
    fn receive(&mut self) {
        let mut buf = [0u8; 4096];
        loop {
            match self.io.read(&mut buf) {
                Ok(0) => {
                    self.closed = true;
                    return;
                }
                Ok(n) => self.text.push_str(&String::from_utf8_lossy(&buf[..n])),
                Err(e) if e.kind() == ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                // A reset connection, or a terminal whose master is gone.
                Err(_) => {
                    self.closed = true;
                    return;
                }
            }
        }
    }

    fn send(&mut self, bytes: &[u8]) {
        self.io.write_all(bytes).unwrap();
    }

    fn count(&self, prefix: &str) -> usize {
        self.text.lines().filter(|l| l.starts_with(prefix)).count()
    }
}

/// Item 5: a TCP client's `G1 X50`, sent while the terminal's host was in control, ran after
/// that host left. Now the client is refused (busy message, closed) and its line never runs.
#[test]
fn a_tcp_line_sent_while_the_pty_controls_never_runs() {
    let mut rig = Rig::new(None);
    let x0 = rig.x_mm();
    let mut pty = rig.pty_host();
    pty.send(b"M115\n");
    rig.run_until("the pty host's answer", |_| {
        pty.receive();
        pty.count("ok") == 1
    });
    assert_eq!(rig.board.status().active_port, Some(rig.pty));

    let mut tcp = rig.tcp_client();
    tcp.send(b"G1 X50 F6000\n");
    rig.run_until("the TCP client's refusal", |_| {
        tcp.receive();
        tcp.closed
    });
    assert_eq!(tcp.text, "error: busy\n");

    // The pty's host leaves; nothing of the refused client runs, then or later.
    drop(pty);
    rig.run_for(3_000, |_| {});
    assert_eq!(rig.board.status().active_port, None);
    assert_eq!(rig.x_mm(), x0, "the refused client's move ran");
    assert_eq!(
        rig.board.status().controller.stats.executed,
        1,
        "only the M115"
    );
}

/// Item 5: the terminal's input while a TCP client is in control is refused with the busy
/// message and discarded, not buffered to run once the client has gone.
#[test]
fn pty_input_while_tcp_controls_is_refused_and_discarded() {
    let mut rig = Rig::new(None);
    let x0 = rig.x_mm();
    let mut tcp = rig.tcp_client();
    rig.run_until("the greeting", |_| {
        tcp.receive();
        tcp.count("N54") == 1
    });
    let mut pty = rig.pty_host();
    pty.send(b"G1 X50 F6000\n");
    rig.run_until("the busy message on the pty", |_| {
        pty.receive();
        pty.text.contains("error: busy")
    });
    assert_eq!(pty.count("ok"), 0, "{}", pty.text);
    let stats = rig.board.port_stats(rig.pty).unwrap();
    assert_eq!(stats.refused_bytes, 13);

    // The client leaves; the terminal's host takes control with its next line, and only that
    // line runs.
    drop(tcp);
    rig.run_for(500, |_| {});
    pty.send(b"M114\n");
    rig.run_until("the pty host's answer", |_| {
        pty.receive();
        pty.count("ok") == 1
    });
    rig.run_for(3_000, |_| {});
    assert_eq!(rig.board.status().active_port, Some(rig.pty));
    assert_eq!(rig.x_mm(), x0, "the refused move ran");
    assert_eq!(rig.board.status().controller.stats.executed, 1);
    assert_eq!(pty.count("ok"), 1, "{}", pty.text);
}

/// Item 5: client B received 138 of client A's `ok`s: A's unread lines ran in B's session.
/// Now a client that takes control starts with nothing of the previous one.
#[test]
fn a_new_client_never_receives_the_previous_clients_replies() {
    let mut rig = Rig::new(None);
    let mut a = rig.tcp_client();
    rig.run_until("A's greeting", |_| {
        a.receive();
        a.count("N54") == 1
    });
    // A sends 200 lines and leaves; B connects at once, before the board reads any of them.
    let mut lines = String::new();
    for i in 0..200 {
        lines.push_str(&format!("G1 X{} F30000\n", i % 2));
    }
    a.send(lines.as_bytes());
    drop(a);
    let mut b = rig.tcp_client();
    std::thread::sleep(Duration::from_millis(50));

    rig.run_until("B's greeting", |_| {
        b.receive();
        b.count("N54") == 1
    });
    rig.run_for(2_000, |_| b.receive());
    assert_eq!(b.count("ok"), 0, "B received A's replies: {}", b.text);
    assert_eq!(
        rig.board.status().controller.stats.executed,
        0,
        "A's lines ran in B's session"
    );
    assert_eq!(rig.board.port::<TcpLink>(rig.tcp).unwrap().connections(), 2);

    // B's own lines are answered, numbered from the start.
    b.send(b"M114\n");
    rig.run_until("B's answer", |_| {
        b.receive();
        b.count("ok") == 1
    });
}

/// Item 6: a silent, never-closing TCP client locked out every other host forever. Now it is
/// closed after the idle time-out and the terminal's host gets control.
#[test]
fn a_silent_tcp_client_times_out_and_the_pty_gets_control() {
    let mut rig = Rig::new(Some(2_000));
    let mut tcp = rig.tcp_client();
    rig.run_until("the greeting", |_| {
        tcp.receive();
        tcp.count("N54") == 1
    });
    let greeted_ms = rig.now_ms();
    let mut pty = rig.pty_host();
    pty.send(b"M115\n");
    rig.run_until("the busy message", |_| {
        pty.receive();
        pty.text.contains("error: busy")
    });

    rig.run_until("the silent client's close", |_| {
        tcp.receive();
        tcp.closed
    });
    let closed_ms = rig.now_ms();
    assert!(
        (greeted_ms + 1_900..=greeted_ms + 2_100).contains(&closed_ms),
        "closed after {} ms of silence",
        closed_ms - greeted_ms
    );
    assert!(tcp.count("N55") >= 1, "keep-alives went out: {}", tcp.text);
    assert_eq!(rig.board.port_stats(rig.tcp).unwrap().idle_timeouts, 1);

    pty.send(b"M115\n");
    rig.run_until("the pty host's answer", |_| {
        pty.receive();
        pty.count("ok") == 1
    });
    assert_eq!(rig.board.status().active_port, Some(rig.pty));
}

/// Item 6, the other way: a terminal host that holds the port open and says nothing gives up
/// control after the time-out, and a TCP client is admitted; a client refused before that is
/// told so.
#[test]
fn a_silent_pty_host_gives_up_control_to_a_tcp_client() {
    let mut rig = Rig::new(Some(2_000));
    let mut pty = rig.pty_host();
    pty.send(b"M115\n");
    rig.run_until("the pty host's answer", |_| {
        pty.receive();
        pty.count("ok") == 1
    });

    let mut early = rig.tcp_client();
    rig.run_until("the early client's refusal", |_| {
        early.receive();
        early.closed
    });
    assert_eq!(early.text, "error: busy\n");

    rig.run_for(2_500, |_| {});
    assert_eq!(rig.board.status().active_port, None, "control given up");
    assert_eq!(rig.board.port_stats(rig.pty).unwrap().idle_timeouts, 1);
    let mut tcp = rig.tcp_client();
    rig.run_until("the greeting", |_| {
        tcp.receive();
        tcp.count("N54") == 1
    });
    assert_eq!(rig.board.status().active_port, Some(rig.tcp));
    pty.send(b"M114\n");
    rig.run_until("the busy message", |_| {
        pty.receive();
        pty.text.contains("error: busy")
    });
}

/// A silent terminal host that no one else wanted keeps its session: its next line is
/// answered in the same session (no `start` again).
#[test]
fn a_silent_pty_host_keeps_its_session_when_no_one_else_came() {
    let mut rig = Rig::new(Some(1_000));
    let mut pty = rig.pty_host();
    pty.send(b"M115\n");
    rig.run_until("the pty host's answer", |_| {
        pty.receive();
        pty.count("ok") == 1
    });
    rig.run_for(3_000, |_| {});
    assert_eq!(rig.board.status().active_port, None);
    pty.send(b"M114\n");
    rig.run_until("the pty host's answer", |_| {
        pty.receive();
        pty.count("ok") == 2
    });
    assert_eq!(pty.count("start"), 1, "{}", pty.text);
    assert_eq!(rig.board.port_stats(rig.pty).unwrap().sessions, 1);
}

/// A client that waits for an answer the controller owes it (the `ok` of `G28` comes when the
/// homing cycle ends) is not timed out for its silence.
#[test]
fn a_client_waiting_for_its_answer_is_not_timed_out() {
    let mut rig = Rig::new(Some(500));
    let mut tcp = rig.tcp_client();
    rig.run_until("the greeting", |_| {
        tcp.receive();
        tcp.count("N54") == 1
    });
    let start_ms = rig.now_ms();
    tcp.send(b"G28\n");
    rig.run_until("the end of homing", |_| {
        tcp.receive();
        tcp.count("ok") == 1 || tcp.closed
    });
    assert!(!tcp.closed, "dropped while homing: {}", tcp.text);
    assert!(
        rig.now_ms() - start_ms > 2_000,
        "homing took longer than the time-out"
    );
    assert_eq!(rig.board.port_stats(rig.tcp).unwrap().idle_timeouts, 0);
}

/// Item 6: the controller read a flood with no bound in one turn. Now it reads at most
/// `READ_BUDGET` bytes a turn and the rest waits on the link.
#[test]
fn a_flood_is_read_a_bounded_amount_per_turn() {
    let machine = SimMachine::new(&MachineConfig::default_router());
    let mut board = SimBoard::new(&machine, BoardConfig::default()).unwrap();
    let (link, host) = MemoryLink::pair();
    board.add_port(link, false);
    let flood: Vec<u8> = b"M114\n".repeat(200_000);
    host.send(&flood);
    let mut sim = Simulation::new(machine.clone(), SimulationConfig::new(machine.tick_hz()));
    let mut turns = 0;
    let mut most = 0;
    let mut last = flood.len();
    board
        .run(&mut sim, |_, _| {
            let left = host.pending_to_firmware();
            most = most.max(last - left);
            last = left;
            host.take_received();
            turns += 1;
            if turns == 20 {
                Flow::Stop
            } else {
                Flow::Continue
            }
        })
        .unwrap();
    assert!(
        most <= forja_sim::board::READ_BUDGET,
        "{most} bytes read in one turn"
    );
    assert!(most > 0);
    assert!(host.pending_to_firmware() > flood.len() - 20 * forja_sim::board::READ_BUDGET - 1);
}

/// Follow-up of item 5: an `M112` from a host that was not in control was refused like any
/// other line, and the machine went on moving. An emergency stop now acts from any host —
/// numbered or not, whatever its checksum, even split across writes — and nothing else of
/// that host runs; the controlling host is told of the fault.
#[test]
fn m112_from_a_host_not_in_control_stops_the_machine() {
    let mut rig = Rig::new(None);
    let x0 = rig.x_mm();
    let y0 = rig.machine.position_mm(1).unwrap();
    let mut tcp = rig.tcp_client();
    rig.run_until("the greeting", |_| {
        tcp.receive();
        tcp.count("N54") == 1
    });
    tcp.send(b"G1 X50 F600\n");
    let machine = rig.machine.clone();
    rig.run_until("the move under way", |_| {
        machine.position_mm(0).unwrap() > x0 + 1.0
    });
    assert_eq!(rig.board.status().active_port, Some(rig.tcp));

    // The terminal's host: a move (refused, never run), then an `M112` cut in two.
    let mut pty = rig.pty_host();
    pty.send(b"G1 Y40 F6000\nN7 M1");
    rig.run_for(50, |_| pty.receive());
    assert!(pty.text.contains("error: busy"), "{}", pty.text);
    assert!(
        !matches!(
            rig.board.status().controller.state,
            forja_motion::MachineState::Alarm(_)
        ),
        "half an M112 stopped the machine"
    );
    pty.send(b"12*0\n");
    rig.run_until("the emergency stop", |board| {
        matches!(
            board.status().controller.state,
            forja_motion::MachineState::Alarm(forja_motion::Alarm::EmergencyStop)
        )
    });
    rig.run_until("the fault at the controlling host", |_| {
        tcp.receive();
        tcp.text.contains("Error:E153 emergency-stop")
    });
    let stopped = rig.x_mm();
    assert!(stopped < x0 + 49.0, "{x0} {stopped}");
    rig.run_for(1_000, |_| {});
    assert_eq!(rig.x_mm(), stopped, "the machine moved after the stop");
    assert_eq!(
        rig.machine.position_mm(1).unwrap(),
        y0,
        "the refused move ran"
    );
    assert_eq!(rig.board.port_stats(rig.pty).unwrap().emergency_stops, 1);
    assert_eq!(rig.board.status().active_port, Some(rig.tcp));
    assert_eq!(
        rig.board.status().controller.stats.executed,
        1,
        "only the TCP client's G1"
    );
    // The controlling host resets and goes on.
    tcp.send(b"M999\n");
    rig.run_until("the reset's answer", |_| {
        tcp.receive();
        tcp.count("ok") == 2
    });
    assert_eq!(
        rig.board.status().controller.state,
        forja_motion::MachineState::Idle
    );
}
