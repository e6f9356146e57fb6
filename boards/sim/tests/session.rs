//! The board's TCP port: who controls it is the `LinkSession`'s decision, and the same
//! session greets the controller (frame 54) and keeps it alive (frame 55).

use std::io::{ErrorKind, Read as _};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use forja_sim::board::{BoardConfig, PortId, SimBoard};
use forja_sim_hal::link::{PortLink, TcpLink};
use forja_sim_hal::{Flow, MachineConfig, SimMachine, Simulation, SimulationConfig};

const WALL: Duration = Duration::from_secs(10);

/// A host's end: the lines it has received so far.
struct Host {
    stream: TcpStream,
    text: String,
}

impl Host {
    fn connect(board: &SimBoard, port: PortId) -> Self {
        let addr = board.port::<TcpLink>(port).unwrap().local_addr().unwrap();
        let stream = TcpStream::connect(addr).unwrap();
        stream.set_nonblocking(true).unwrap();
        Self {
            stream,
            text: String::new(),
        }
    }

    /// Take what has arrived, without waiting.
    fn receive(&mut self) {
        let mut buf = [0u8; 1024];
        loop {
            match self.stream.read(&mut buf) {
                Ok(0) => return,
                Ok(n) => self.text.push_str(&String::from_utf8_lossy(&buf[..n])),
                Err(e) if e.kind() == ErrorKind::WouldBlock => return,
                Err(e) => panic!("{e}"),
            }
        }
    }

    fn count(&self, prefix: &str) -> usize {
        self.text.lines().filter(|l| l.starts_with(prefix)).count()
    }
}

/// Run `board` until `done` holds, for at most [`WALL`] of real time.
fn run_until(board: &mut SimBoard, sim: &mut Simulation, mut done: impl FnMut(&SimBoard) -> bool) {
    let deadline = Instant::now() + WALL;
    board
        .run(sim, |board, _| {
            if done(board) {
                return Flow::Stop;
            }
            assert!(Instant::now() < deadline, "timed out");
            Flow::Continue
        })
        .unwrap();
}

#[test]
fn a_second_client_is_refused_by_the_session_and_the_next_one_greeted() {
    let machine = SimMachine::new(&MachineConfig::default_router());
    let mut board = SimBoard::new(&machine, BoardConfig::default()).unwrap();
    let tcp = TcpLink::bind("127.0.0.1:0".parse().unwrap(), &b"error: busy\n"[..]).unwrap();
    let port = board.add_port(tcp, true);
    let mut sim = Simulation::new(machine.clone(), SimulationConfig::new(machine.tick_hz()));
    let refused = |b: &SimBoard| b.port::<TcpLink>(port).unwrap().refused();

    let mut first = Host::connect(&board, port);
    run_until(&mut board, &mut sim, |_| {
        first.receive();
        first.count("N54") == 1
    });

    // A second client while the first is in control: the busy message, then closed.
    let mut second = TcpStream::connect(first.stream.peer_addr().unwrap()).unwrap();
    run_until(&mut board, &mut sim, |b| refused(b) == 1);
    second.set_read_timeout(Some(WALL)).unwrap();
    let mut text = String::new();
    second.read_to_string(&mut text).unwrap();
    assert_eq!(text, "error: busy\n");

    // The first keeps control: keep-alives go on, no second greeting.
    let keep_alives = first.count("N55");
    run_until(&mut board, &mut sim, |_| {
        first.receive();
        first.count("N55") > keep_alives
    });
    assert_eq!(first.count("N54"), 1, "{}", first.text);
    assert_eq!(board.status().active_port, Some(port));

    // Once it has closed, the next client is admitted and greeted.
    drop(first);
    let mut third = Host::connect(&board, port);
    run_until(&mut board, &mut sim, |_| {
        third.receive();
        third.count("N54") == 1
    });
    assert_eq!(refused(&board), 1);
    assert_eq!(board.port::<TcpLink>(port).unwrap().connections(), 2);
}
