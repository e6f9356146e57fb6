//! `forja-sim`: the simulator board as a program.
//!
//! Loads and checks a machine file and a job, and with `--listen` opens the TCP and
//! pseudo-terminal links and serves them in real time. The clap doc comments below are its
//! `--help`.

use std::io::Write as _;
use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use clap::Parser;
use embedded_io::{Read, ReadReady};
use forja_hal_abstraction::link::{LinkState, LinkStatus};
use forja_sim::config::{AxisKind, SwitchPolarity, SwitchSide};
use forja_sim::link::{FaultConfig, FaultInjector, HostLink, PtyLink, TcpLink};
use forja_sim::{
    Flow, Job, MachineConfig, Pacing, SimMachine, Simulation, SimulationConfig, StopReason,
};

/// The line sent to a TCP client that connects while another one is in control.
const BUSY_MESSAGE: &[u8] = b"error: busy: another host is in control of this machine\n";

/// Exit code of a run that could not happen because the motion kernel is not wired in.
const EXIT_NOT_WIRED: u8 = 2;

/// Forja's host simulator board: a simulated machine with virtual steppers, limit switches,
/// heaters and clock, reachable over TCP and a pseudo-terminal.
#[derive(Parser, Debug)]
#[command(
    name = "forja-sim",
    version,
    after_help = "Exit status: 0 success, 1 bad input or link failure, 2 the job could not be run."
)]
struct Cli {
    /// Machine file (TOML), or `builtin:NAME` for a bundled one: `builtin:default` (the 4-axis
    /// router) or `builtin:printer`.
    #[arg(long, value_name = "FILE", default_value = "builtin:default")]
    machine: String,

    /// G-code job to run [default: the bundled sample job].
    #[arg(long, value_name = "FILE")]
    job: Option<PathBuf>,

    /// Check the machine file and the job, print what they describe, and exit.
    #[arg(long)]
    check: bool,

    /// Wait for hosts on TCP and on a pseudo-terminal instead of running the job, and print
    /// where they are. Implies --realtime. Ends at --time-limit or on Ctrl-C.
    #[arg(long)]
    listen: bool,

    /// Address the TCP link listens on [default: the machine file's, else 127.0.0.1].
    #[arg(long, value_name = "ADDR")]
    tcp_bind: Option<IpAddr>,

    /// TCP port [default: the machine file's, else 2323]; 0 picks any free port.
    #[arg(long, value_name = "PORT")]
    tcp_port: Option<u16>,

    /// Also make a symbolic link at PATH to the pseudo-terminal, a stable name for host
    /// software (the /dev/pts number changes from run to run).
    #[arg(long, value_name = "PATH")]
    pty_link: Option<PathBuf>,

    /// Hold virtual time to the wall clock instead of running as fast as possible.
    #[arg(long)]
    realtime: bool,

    /// Stop after this many seconds of virtual time.
    #[arg(long, value_name = "SECONDS")]
    time_limit: Option<f64>,

    /// Record every step, direction and enable change to FILE (`time_ticks,axis,event`).
    #[arg(long, value_name = "FILE")]
    trace: Option<PathBuf>,

    /// Corrupt this fraction of the bytes received from hosts (one bit flipped), e.g. 0.01.
    #[arg(long, value_name = "RATE", default_value_t = 0.0)]
    corrupt_rate: f64,

    /// Drop this fraction of the bytes received from hosts, e.g. 0.005.
    #[arg(long, value_name = "RATE", default_value_t = 0.0)]
    drop_rate: f64,

    /// Seed of the fault injector: the same seed gives the same faults.
    #[arg(long, value_name = "N", default_value_t = 0)]
    seed: u64,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(&cli) {
        Ok(code) => code,
        Err(message) => {
            eprintln!("forja-sim: {message}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: &Cli) -> Result<ExitCode, String> {
    let machine = load_machine(&cli.machine)?;
    let job = match &cli.job {
        Some(path) => Job::load(path).map_err(|e| e.to_string())?,
        None => Job::sample(),
    };
    let faults = FaultConfig {
        corrupt_rate: cli.corrupt_rate,
        drop_rate: cli.drop_rate,
        seed: cli.seed,
    };
    faults.validate().map_err(|e| e.to_string())?;
    let time_limit_ticks = match cli.time_limit {
        Some(s) if s.is_finite() && s > 0.0 => Some((s * f64::from(machine.tick_hz)) as u64),
        Some(s) => {
            return Err(format!(
                "--time-limit {s}: must be a positive number of seconds"
            ));
        }
        None => None,
    };

    if cli.check {
        print_machine(&cli.machine, &machine);
        println!("job: {}, {} lines", job.name(), job.line_count());
        return Ok(ExitCode::SUCCESS);
    }
    if cli.listen {
        return listen(cli, &machine, faults, time_limit_ticks);
    }

    println!(
        "machine: {} ({} axes), job: {}, {} lines",
        machine.name,
        machine.axes.len(),
        job.name(),
        job.line_count()
    );
    eprintln!(
        "forja-sim: the motion kernel is not wired into the simulator board yet: the job was \
         not run, and there is no result to report"
    );
    Ok(ExitCode::from(EXIT_NOT_WIRED))
}

fn load_machine(arg: &str) -> Result<MachineConfig, String> {
    if let Some(name) = arg.strip_prefix("builtin:") {
        let text = MachineConfig::bundled_toml(name).ok_or_else(|| {
            let names: Vec<&str> = forja_sim::config::BUNDLED.iter().map(|(n, _)| *n).collect();
            format!(
                "no bundled machine \"{name}\" (bundled: {})",
                names.join(", ")
            )
        })?;
        return MachineConfig::from_toml_str(text).map_err(|e| format!("{arg}: {e}"));
    }
    let text = std::fs::read_to_string(arg).map_err(|e| format!("{arg}: {e}"))?;
    MachineConfig::from_toml_str(&text).map_err(|e| format!("{arg}: {e}"))
}

fn print_machine(source: &str, m: &MachineConfig) {
    println!("machine: {} ({source})", m.name);
    println!("  clock: {} Hz", m.tick_hz);
    for a in &m.axes {
        let (unit, kind) = match a.kind {
            AxisKind::Linear => ("mm", "linear"),
            AxisKind::Rotary => ("deg", "rotary"),
            AxisKind::Extruder => ("mm", "extruder"),
        };
        let travel = a.travel.map_or_else(
            || "no limits".to_string(),
            |t| format!("{}..{} {unit}", t.min_mm, t.max_mm),
        );
        let homing = a.homing.map_or_else(
            || "does not home".to_string(),
            |h| format!("homes {:?}", h.direction).to_lowercase(),
        );
        let switches: Vec<String> = a
            .switches
            .iter()
            .map(|s| {
                format!(
                    "{}@{} {}",
                    match s.side {
                        SwitchSide::Min => "min",
                        SwitchSide::Max => "max",
                    },
                    s.position_mm,
                    match s.polarity {
                        SwitchPolarity::NormallyOpen => "NO",
                        SwitchPolarity::NormallyClosed => "NC",
                    }
                )
            })
            .collect();
        println!(
            "  {}: {kind}, {} steps/{unit}, {travel}, max {} {unit}/min, accel {} {unit}/s², \
             {homing}, switches: {}",
            a.letter,
            a.steps_per_mm,
            a.max_rate_mm_min,
            a.accel_mm_s2,
            if switches.is_empty() {
                "none".to_string()
            } else {
                switches.join(", ")
            }
        );
    }
    for h in &m.heaters {
        println!(
            "  heater {}: {} W, {} J/K, {} W/K to {} °C ambient",
            h.name, h.power_w, h.heat_capacity_j_per_k, h.loss_w_per_k, h.ambient_c
        );
    }
    for o in &m.outputs {
        println!("  output {}: duty 0..{}", o.name, o.max_duty);
    }
    println!("  link: tcp {}:{}", m.link.tcp_bind, m.link.tcp_port);
}

/// One served link and what it has seen.
struct Served<L> {
    name: &'static str,
    link: FaultInjector<L>,
    state: LinkState,
    received: u64,
}

impl<L: HostLink<Error = std::io::Error>> Served<L> {
    fn new(name: &'static str, link: L, faults: FaultConfig) -> Result<Self, String> {
        Ok(Self {
            name,
            link: FaultInjector::new(link, faults).map_err(|e| e.to_string())?,
            state: LinkState::Disconnected,
            received: 0,
        })
    }

    /// One thread-side turn: service the link, report connection changes, take the bytes.
    fn turn(&mut self, now_s: f64) -> Result<(), String> {
        self.link
            .poll()
            .map_err(|e| format!("{} link failed: {e}", self.name))?;
        let state = self.link.state();
        if state != self.state {
            let what = match state {
                LinkState::Connected => "host connected",
                LinkState::Disconnected => "host disconnected",
            };
            eprintln!("forja-sim: [{now_s:.3} s] {}: {what}", self.name);
            self.state = state;
        }
        let mut buf = [0u8; 1024];
        while self.link.read_ready().map_err(|e| e.to_string())? {
            let n = self.link.read(&mut buf).map_err(|e| e.to_string())?;
            self.received += n as u64;
        }
        Ok(())
    }

    fn summary(&self, faults: FaultConfig) {
        let s = self.link.stats();
        print!(
            "{}: {} connections, {} bytes received",
            self.name,
            self.link.connections(),
            self.received
        );
        if faults.is_active() {
            print!(
                " ({} from the host, {} dropped, {} corrupted)",
                s.bytes, s.dropped, s.corrupted
            );
        }
        println!();
    }
}

fn listen(
    cli: &Cli,
    config: &MachineConfig,
    faults: FaultConfig,
    time_limit_ticks: Option<u64>,
) -> Result<ExitCode, String> {
    let addr = SocketAddr::new(
        cli.tcp_bind.unwrap_or(config.link.tcp_bind),
        cli.tcp_port.unwrap_or(config.link.tcp_port),
    );
    let tcp = TcpLink::bind(addr, BUSY_MESSAGE).map_err(|e| format!("tcp {addr}: {e}"))?;
    let tcp_addr = tcp.local_addr().map_err(|e| format!("tcp {addr}: {e}"))?;
    let pty = PtyLink::open(cli.pty_link.as_deref()).map_err(|e| match &cli.pty_link {
        Some(p) => format!("pseudo-terminal (link {}): {e}", p.display()),
        None => format!("pseudo-terminal: {e}"),
    })?;

    println!("machine: {}", config.name);
    println!("tcp: {tcp_addr}");
    println!("pty: {}", pty.slave_path().display());
    if let Some(link) = pty.symlink_path() {
        println!(
            "pty-link: {} -> {}",
            link.display(),
            pty.slave_path().display()
        );
    }
    if faults.is_active() {
        println!(
            "faults: corrupt {} drop {} seed {} (bytes from hosts only)",
            faults.corrupt_rate, faults.drop_rate, faults.seed
        );
    }
    let _ = std::io::stdout().flush();
    eprintln!(
        "forja-sim: the motion kernel is not wired into the simulator board yet: bytes from \
         hosts are received and counted, not answered. Ctrl-C ends."
    );

    let machine = SimMachine::new(config);
    machine.set_tracing(cli.trace.is_some());
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, Arc::clone(&stop))
            .map_err(|e| format!("cannot handle signal {signal}: {e}"))?;
    }

    let mut sim_config = SimulationConfig::new(config.tick_hz);
    sim_config.pacing = Pacing::Realtime;
    sim_config.time_limit_ticks = time_limit_ticks;
    let mut sim = Simulation::new(machine.clone(), sim_config);
    sim.set_stop_flag(stop);

    let mut tcp = Served::new("tcp", tcp, faults)?;
    let mut pty = Served::new("pty", pty, faults)?;
    let mut failure = None;
    let tick_hz = f64::from(config.tick_hz);
    let clock = machine.clock();
    let report = sim
        .run_with(
            |_| None,
            |_| {
                let now_s = clock.now_ticks() as f64 / tick_hz;
                match tcp.turn(now_s).and_then(|()| pty.turn(now_s)) {
                    Ok(()) => Flow::Continue,
                    Err(e) => {
                        failure = Some(e);
                        Flow::Stop
                    }
                }
            },
        )
        .map_err(|e| e.to_string())?;
    if let Some(e) = failure {
        return Err(e);
    }

    let why = match report.stop {
        StopReason::TimeLimit => "time limit",
        StopReason::Interrupted => "interrupted",
        StopReason::Firmware => "stopped",
    };
    println!(
        "ended ({why}) after {:.3} s of virtual time",
        report.virtual_ticks() as f64 / tick_hz
    );
    tcp.summary(faults);
    pty.summary(faults);
    if let Some(path) = &cli.trace {
        machine
            .take_trace()
            .save(path)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        println!("trace: {}", path.display());
    }
    Ok(ExitCode::SUCCESS)
}
