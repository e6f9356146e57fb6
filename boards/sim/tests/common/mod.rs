//! The rig the board's device tests share: the router, its simulator board and a host on an
//! in-memory port, sending G-code lines and reading the replies in virtual time.

#![allow(dead_code)]

use forja_sim::board::{BoardConfig, SimBoard};
use forja_sim_hal::link::{MemoryHost, MemoryLink};
use forja_sim_hal::{Flow, MachineConfig, SimMachine, Simulation, SimulationConfig};

/// The longest a line may take to be answered, in seconds of virtual time.
pub const ANSWER_LIMIT_S: u64 = 60;

/// The router, its board and a host on an in-memory port.
pub struct Rig {
    /// The simulated machine: its devices, for the test to read.
    pub machine: SimMachine,
    /// The firmware on it.
    pub board: SimBoard,
    /// Virtual time.
    pub sim: Simulation,
    /// The host's end of the link.
    pub host: MemoryHost,
}

impl Rig {
    /// The default router, started: what the board says first is read and dropped.
    pub fn router() -> Self {
        let machine = SimMachine::new(&MachineConfig::default_router());
        let mut board = SimBoard::new(&machine, BoardConfig::default()).unwrap();
        let (link, host) = MemoryLink::pair();
        board.add_port(link, false);
        let hz = u64::from(machine.tick_hz());
        let mut config = SimulationConfig::new(machine.tick_hz());
        // Start-up: whatever the board says first, in its first 100 ms.
        config.time_limit_ticks = Some(hz / 10);
        let sim = Simulation::new(machine.clone(), config);
        let mut rig = Self {
            machine,
            board,
            sim,
            host,
        };
        rig.run_until(|_| false);
        rig.sim.config_mut().time_limit_ticks = Some(ANSWER_LIMIT_S * hz);
        rig
    }

    /// Run until `done` holds for the lines received, or for the time limit; the lines.
    pub fn run_until(&mut self, mut done: impl FnMut(&[&str]) -> bool) -> Vec<String> {
        let host = &self.host;
        let mut text = String::new();
        self.board
            .run(&mut self.sim, |_, _| {
                text.push_str(&String::from_utf8_lossy(&host.take_received()));
                if done(&text.lines().collect::<Vec<_>>()) {
                    Flow::Stop
                } else {
                    Flow::Continue
                }
            })
            .unwrap();
        text.lines().map(str::to_string).collect()
    }

    /// Send `line`; the lines received until its `ok` (or `ok` with a report after it),
    /// Marlin's keep-alives left out.
    pub fn ask(&mut self, line: &str) -> Vec<String> {
        let is_ok = |l: &str| l == "ok" || l.starts_with("ok ");
        self.host.send(format!("{line}\n").as_bytes());
        let out = self.run_until(|lines| lines.iter().any(|l| is_ok(l)));
        assert!(
            out.iter().any(|l| is_ok(l)),
            "{line}: no ok within {ANSWER_LIMIT_S} s: {out:?}"
        );
        out.into_iter()
            .filter(|l| !l.starts_with("echo:busy:"))
            .collect()
    }

    /// `line` answered `ok` and nothing else.
    pub fn ok(&mut self, line: &str) {
        assert_eq!(self.ask(line), ["ok"], "{line}");
    }
}
