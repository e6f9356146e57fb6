//! The simulator's two ways of running: a job streamed through the controller over an
//! in-memory link ([`run_job`]), in the RepRap dialect or in grbl's, and serving hosts on TCP,
//! a pseudo-terminal and the operator's web page ([`listen`]).

use core::fmt;
use std::io::Write as _;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use embedded_io::{Read, ReadReady, Write, WriteReady};
use forja_app::controller::Stats as ControllerStats;
use forja_drivers::port_link::Admission;
use forja_hal_abstraction::link::{LinkState, LinkStatus};
use forja_host::grbl_sender::{self, GrblSender};
use forja_host::program::Program;
use forja_host::streamer::{Config, Stats};

use forja_sim_hal::link::{
    FaultConfig, FaultInjector, MemoryLink, PortLink, PtyLink, Tapped, TcpLink, WebLink,
};
use forja_sim_hal::{
    Flow, MachineConfig, Pacing, SimClock, SimMachine, Simulation, SimulationConfig, StopReason,
};

use crate::host::{GrblHost, StreamHost};
use crate::job::Job;
use forja_sim::board::{PortId, SimBoard};

/// How [`run_job`] runs.
#[derive(Debug, Clone, PartialEq)]
pub struct JobOptions {
    /// Home before the job when the machine has axes that home (`G28`, or `$H` in the grbl
    /// dialect): the job's coordinates are machine coordinates, or work coordinates set by
    /// [`JobOptions::before`], which the controller knows only once homed.
    pub home_first: bool,
    /// Stream in the grbl dialect, as a CNC sender does ([`GRBL_SENDER`]), instead of the
    /// RepRap one.
    pub grbl: bool,
    /// Lines sent after homing and before the job (a work offset: `G10 L2 P1 X50 Y50 Z20`).
    pub before: Vec<String>,
    /// Faults on the bytes from the host.
    pub faults: FaultConfig,
    /// Give up after this much virtual time.
    pub time_limit_ticks: Option<u64>,
    /// As fast as possible, or held to the wall clock.
    pub pacing: Pacing,
    /// Record every step to this file.
    pub trace: Option<PathBuf>,
    /// Keep the board's flash in this state file ([`crate::state`]).
    pub state: Option<PathBuf>,
    /// Keep the board's SD card in this directory (`None`: a fresh temporary one).
    pub sd_dir: Option<PathBuf>,
}

impl Default for JobOptions {
    fn default() -> Self {
        Self {
            home_first: true,
            grbl: false,
            before: Vec::new(),
            faults: FaultConfig {
                corrupt_rate: 0.0,
                drop_rate: 0.0,
                seed: 0,
            },
            time_limit_ticks: None,
            pacing: Pacing::AsFastAsPossible,
            trace: None,
            state: None,
            sd_dir: None,
        }
    }
}

/// The reply time-out of [`run_job`]'s streamer ([`Config::reply_timeout`]; its other settings
/// are `forja send`'s for a serial link, [`Config::default`]). The controller answers a line
/// only when it can take it, so a line held by homing, a heater wait or a full planner goes
/// unanswered for as long as that lasts (homing the default router takes over 20 s of virtual
/// time), and the in-memory link loses no reply: copies sent after a shorter time-out would
/// only be refused as out of order.
pub const JOB_REPLY_TIMEOUT: Duration = Duration::from_secs(600);

/// How [`run_job`] streams in the grbl dialect, as CNC senders connect: `0x18` and the banner,
/// `$10=3`, then the buffer counted against read from a `?`'s `Bf:` (768 bytes on Forja), and
/// a `?` every 200 ms of virtual time.
pub const GRBL_SENDER: grbl_sender::Config = grbl_sender::Config {
    rx_buffer_bytes: grbl_sender::GRBL_RX_BUFFER,
    report_buffer: true,
    size_from_report: true,
    status_interval: Some(Duration::from_millis(200)),
    status_timeout: Duration::from_secs(1),
    banner_timeout: Duration::from_millis(2500),
    reset_attempts: 3,
};

/// What a grbl run ([`JobOptions::grbl`]) measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GrblFigures {
    /// The receive buffer counted against, bytes (from `Bf:`).
    pub rx_buffer_bytes: usize,
    /// The sender's counters: the most bytes and lines in flight, the status reports and the
    /// longest time from a `?` to its report.
    pub sender: grbl_sender::Stats,
    /// Lines sent and never answered (dropped by a reset, or in flight at the end).
    pub unanswered: usize,
    /// Status reports whose `Ln:` was smaller than the report's before (0: lines ran in order).
    pub line_number_regressions: u32,
}

/// What [`run_job`] did.
#[derive(Debug, Clone)]
pub struct JobRun {
    /// The machine's name.
    pub machine: String,
    /// The job's name.
    pub job: String,
    /// Whether the machine was homed first (`G28`, or `$H` in the grbl dialect).
    pub homed_first: bool,
    /// The lines sent after homing and before the job ([`JobOptions::before`]).
    pub before: usize,
    /// Whether the controller took every line and the machine came to rest.
    pub finished: bool,
    /// Lines of the job streamed (the homing and [`JobOptions::before`] lines included; blank
    /// and comment lines, the handshake's `M110`, the closing line and `$10=3` not counted).
    pub lines: usize,
    /// How many of them the controller took (answered `ok`).
    pub accepted: usize,
    /// The RepRap streamer's counters (all zero in the grbl dialect).
    pub sender: Stats,
    /// In the grbl dialect, what the character-counting sender measured.
    pub grbl: Option<GrblFigures>,
    /// The refusals (`echo:E…`, `echo:Unknown command`; `error:N` in the grbl dialect) and
    /// faults (`Error:`; `ALARM:N`) received, in order.
    pub faults: Vec<String>,
    /// The operator's log of a grbl run: each `[MSG:…]` and the cycle starts sent.
    pub log: Vec<String>,
    /// The controller's view.
    pub controller: ControllerStats,
    /// Virtual time the run took, seconds.
    pub virtual_s: f64,
    /// Wall-clock time the run took.
    pub wall: Duration,
    /// Each axis: its letter, its physical position at the end (mm, or degrees), the steps it
    /// made, and the steps lost to a disabled driver.
    pub axes: Vec<(char, f64, u64, u64)>,
    /// Driver timing rules broken (pulse width, direction set-up).
    pub violations: u64,
}

impl JobRun {
    /// Whether the job ran through, with every line taken and nothing wrong with the steps.
    pub fn is_clean(&self) -> bool {
        self.finished
            && self.faults.is_empty()
            && self.violations == 0
            && self.axes.iter().all(|a| a.3 == 0)
    }
}

impl JobRun {
    /// What came before the job, for the summary: `G28`, `$H`, the `--before` lines.
    fn preamble(&self) -> Option<String> {
        let home = if self.grbl.is_some() { "$H" } else { "G28" };
        let before = match self.before {
            0 => None,
            1 => Some("1 --before line".to_string()),
            n => Some(format!("{n} --before lines")),
        };
        match (self.homed_first, before) {
            (true, Some(b)) => Some(format!("{home} and {b}")),
            (true, None) => Some(home.to_string()),
            (false, b) => b,
        }
    }
}

impl fmt::Display for JobRun {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let preamble = self.preamble();
        writeln!(f, "machine: {}", self.machine)?;
        write!(f, "job: {}", self.job)?;
        match (&self.grbl, &preamble) {
            (Some(_), Some(p)) => writeln!(f, " (grbl dialect, after {p})")?,
            (Some(_), None) => writeln!(f, " (grbl dialect)")?,
            (None, Some(p)) => writeln!(f, " (after {p})")?,
            (None, None) => writeln!(f)?,
        }
        writeln!(
            f,
            "result: {}",
            if self.finished {
                "finished"
            } else {
                "did not finish"
            }
        )?;
        let included = preamble.map_or_else(String::new, |p| format!(" ({p} included)"));
        match &self.grbl {
            None => writeln!(
                f,
                "lines run: {} of {}{included}; executed {} (with M110 and the closing line), \
                 refused {}, resends {}",
                self.accepted,
                self.lines,
                self.controller.executed,
                self.controller.refused,
                self.controller.resends
            )?,
            Some(g) => {
                writeln!(
                    f,
                    "lines run: {} of {}{included}; refused {} (error:N), unanswered {}, stray \
                     answers {}; executed {}",
                    self.accepted,
                    self.lines,
                    g.sender.errors,
                    g.unanswered,
                    g.sender.stray_answers,
                    self.controller.executed
                )?;
                writeln!(
                    f,
                    "character counting: largest in flight {} of {} bytes ({} lines); status \
                     reports: {}, largest ? latency {:.3} ms; with the buffer full: {}, largest \
                     ? latency {:.3} ms; Ln went back {} times",
                    g.sender.max_in_flight_bytes,
                    g.rx_buffer_bytes,
                    g.sender.max_in_flight_lines,
                    g.sender.status_reports,
                    g.sender.max_status_latency.as_secs_f64() * 1000.0,
                    g.sender.full_status_reports,
                    g.sender.max_full_status_latency.as_secs_f64() * 1000.0,
                    g.line_number_regressions
                )?;
            }
        }
        for fault in &self.faults {
            writeln!(f, "  {fault}")?;
        }
        for entry in &self.log {
            writeln!(f, "{entry}")?;
        }
        writeln!(
            f,
            "virtual time: {:.3} s (wall {:.3} s)",
            self.virtual_s,
            self.wall.as_secs_f64()
        )?;
        write!(f, "final position:")?;
        for (letter, mm, _, _) in &self.axes {
            write!(f, " {letter} {mm:.3}")?;
        }
        writeln!(f)?;
        write!(f, "steps:")?;
        for (letter, _, steps, lost) in &self.axes {
            write!(f, " {letter} {steps}")?;
            if *lost > 0 {
                write!(f, " ({lost} lost)")?;
            }
        }
        writeln!(f)?;
        write!(f, "timing violations: {}", self.violations)
    }
}

/// The sender of a run, in either dialect.
enum Sender {
    RepRap(StreamHost),
    Grbl(GrblHost),
}

impl Sender {
    /// Hand the sender what the controller sent at `now_us`; what to write back.
    fn exchange(&mut self, received: &[u8], now_us: u64) -> Vec<u8> {
        match self {
            Self::RepRap(h) => h.exchange(received, now_us / 1000),
            Self::Grbl(h) => h.exchange(received, now_us),
        }
    }

    fn is_over(&self) -> bool {
        match self {
            Self::RepRap(h) => h.is_over(),
            Self::Grbl(h) => h.is_over(),
        }
    }
}

/// Stream `job` to the firmware on a new machine as `config` describes it, over an in-memory
/// link, as fast as the computer runs, until the controller has taken every line and the
/// machine is at rest, or the sender stops (an alarm).
///
/// In the RepRap dialect it streams as `forja send` does: its program check, then its streamer
/// with the window of a serial link and [`JOB_REPLY_TIMEOUT`], after `G28`. With
/// [`JobOptions::grbl`] it streams as `forja send --grbl` and CNC senders do: `0x18`, the
/// banner, `$10=3`, character counting against the `Bf:` of a `?` ([`GRBL_SENDER`]), `$H`
/// first, a `?` every 200 ms, and `~` at a hold that asks for a cycle start (an operator at an
/// `M6` tool change, in [`JobRun::log`]).
///
/// Errors: a job line that does not parse or cannot be sent, a board that cannot be built, a
/// simulation error.
pub fn run_job(config: &MachineConfig, job: &Job, options: &JobOptions) -> Result<JobRun, String> {
    let home = options.home_first && config.axes.iter().any(|a| a.homing.is_some());
    let before = options.before.iter().map(String::as_str);
    // Where the `place`-th line sent in the grbl dialect comes from (1-based: `$H`, the
    // `--before` lines, then each line of the job).
    let preamble = usize::from(home && options.grbl) + options.before.len();
    let grbl_place = |place: usize| match place.checked_sub(preamble + 1) {
        Some(k) => format!("{}, line {}", job.name(), k + 1),
        None if home && place == 1 => "$H".to_string(),
        None => format!("--before line {}", place - usize::from(home)),
    };
    let mut sender = if options.grbl {
        let lines = home
            .then_some("$H")
            .into_iter()
            .chain(before)
            .chain(job.lines());
        let host = GrblHost::new(GRBL_SENDER, lines)
            .map_err(|(place, e)| format!("{}: {e}", grbl_place(place)))?;
        Sender::Grbl(host)
    } else {
        let program =
            Program::parse(job.text().as_bytes()).map_err(|e| format!("{}: {e}", job.name()))?;
        let lines = home
            .then_some("G28")
            .into_iter()
            .chain(before)
            .chain(program.texts());
        let streamer = Config {
            reply_timeout: JOB_REPLY_TIMEOUT,
            ..Config::default()
        };
        let host = StreamHost::new(streamer, lines).map_err(|(i, e)| {
            let preamble = usize::from(home) + options.before.len();
            match i.checked_sub(preamble + 1) {
                Some(k) => {
                    let at = program.lines.get(k).map_or(0, |l| l.source_line);
                    format!("{}, line {at}: {e}", job.name())
                }
                None if home && i == 1 => format!("G28: {e}"),
                None => format!("--before line {}: {e}", i - usize::from(home)),
            }
        })?;
        Sender::RepRap(host)
    };
    let machine = SimMachine::new(config);
    machine.set_tracing(options.trace.is_some());
    let mut board_config = crate::state::board_config(options.state.as_deref())?;
    board_config.sd_dir = options.sd_dir.clone();
    let mut board = SimBoard::new(&machine, board_config).map_err(|e| e.to_string())?;
    let (link, host) = MemoryLink::pair();
    let link = FaultInjector::new(link, options.faults).map_err(|e| e.to_string())?;
    board.add_port(link, false);
    let mut sim_config = SimulationConfig::new(config.tick_hz);
    sim_config.time_limit_ticks = options.time_limit_ticks;
    sim_config.pacing = options.pacing;
    let mut sim = Simulation::new(machine.clone(), sim_config);
    let tick_hz = u64::from(config.tick_hz);
    let report = board
        .run(&mut sim, |board, _| {
            let now_us = board.machine().now_ticks() * 1_000_000 / tick_hz;
            let out = sender.exchange(&host.take_received(), now_us);
            if !out.is_empty() {
                host.send(&out);
            }
            let status = board.status();
            if sender.is_over() && status.controller.idle && !status.controller.holding {
                Flow::Stop
            } else {
                Flow::Continue
            }
        })
        .map_err(|e| e.to_string())?;
    let axes = config
        .axes
        .iter()
        .enumerate()
        .map(|(i, a)| {
            (
                a.letter,
                machine.position_mm(i).unwrap_or(0.0),
                machine.step_count(i).unwrap_or(0),
                machine.lost_steps(i).unwrap_or(0),
            )
        })
        .collect();
    if let Some(path) = &options.trace {
        machine
            .take_trace()
            .save(path)
            .map_err(|e| format!("{}: {e}", path.display()))?;
    }
    let stopped = report.stop == StopReason::Firmware;
    let mut run = JobRun {
        machine: config.name.clone(),
        job: job.name().to_string(),
        homed_first: home,
        before: options.before.len(),
        finished: false,
        lines: 0,
        accepted: 0,
        sender: Stats::default(),
        grbl: None,
        faults: Vec::new(),
        log: Vec::new(),
        controller: board.status().controller.stats,
        virtual_s: report.virtual_ticks() as f64 / config.tick_hz as f64,
        wall: report.wall,
        axes,
        violations: machine.violation_count(),
    };
    match &sender {
        Sender::RepRap(h) => {
            run.finished = stopped && h.is_done();
            run.lines = h.streamer().pushed() as usize;
            run.accepted = h.streamer().accepted() as usize;
            run.sender = h.stats();
            run.faults = h.faults().map(str::to_string).collect();
        }
        Sender::Grbl(h) => {
            let s: &GrblSender = h.sender();
            run.finished = stopped && h.is_done();
            run.lines = s.pushed();
            run.accepted = s
                .answers()
                .iter()
                .filter(|a| **a == Some(grbl_sender::Answer::Ok))
                .count();
            run.grbl = Some(GrblFigures {
                rx_buffer_bytes: s.rx_buffer_bytes(),
                sender: s.stats(),
                unanswered: s.sent()
                    - s.answers()
                        .iter()
                        .filter(|a| {
                            matches!(
                                a,
                                Some(grbl_sender::Answer::Ok | grbl_sender::Answer::Error(_))
                            )
                        })
                        .count(),
                line_number_regressions: h.line_number_regressions(),
            });
            run.faults = h
                .faults()
                .iter()
                .map(|f| match &f.line {
                    Some((place, text)) => format!("{} ({}: {text})", f.what, grbl_place(*place)),
                    None => f.what.clone(),
                })
                .collect();
            run.log = h.log().to_vec();
        }
    }
    Ok(run)
}

/// A served link that counts what it received and reports its host coming and going.
#[derive(Debug)]
pub struct Watched<L> {
    name: &'static str,
    link: L,
    clock: SimClock,
    tick_hz: f64,
    state: LinkState,
    received: u64,
}

impl<L: PortLink> Watched<L> {
    /// Watch `link`, reporting on stderr as `name` at the times of `clock`.
    pub fn new(name: &'static str, link: L, clock: SimClock, tick_hz: u32) -> Self {
        Self {
            name,
            link,
            clock,
            tick_hz: f64::from(tick_hz),
            state: LinkState::Disconnected,
            received: 0,
        }
    }

    /// Bytes the firmware has read.
    pub fn received(&self) -> u64 {
        self.received
    }

    /// The watched link.
    pub fn inner(&self) -> &L {
        &self.link
    }
}

impl<L: PortLink> embedded_io::ErrorType for Watched<L> {
    type Error = L::Error;
}

impl<L: PortLink> Read for Watched<L> {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = self.link.read(buf)?;
        self.received += n as u64;
        Ok(n)
    }
}

impl<L: PortLink> ReadReady for Watched<L> {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        self.link.read_ready()
    }
}

impl<L: PortLink> Write for Watched<L> {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.link.write(buf)
    }
    fn flush(&mut self) -> Result<(), Self::Error> {
        self.link.flush()
    }
}

impl<L: PortLink + WriteReady> WriteReady for Watched<L> {
    fn write_ready(&mut self) -> Result<bool, Self::Error> {
        self.link.write_ready()
    }
}

impl<L: PortLink> LinkStatus for Watched<L> {
    fn state(&self) -> LinkState {
        self.link.state()
    }
}

impl<L: PortLink> Watched<L> {
    /// Report a change of the link's state.
    fn watch(&mut self) {
        let state = self.link.state();
        if state != self.state {
            self.state = state;
            let what = match state {
                LinkState::Connected => "host connected",
                LinkState::Disconnected => "host disconnected",
            };
            let now_s = self.clock.now_ticks() as f64 / self.tick_hz;
            eprintln!("forja-sim: [{now_s:.3} s] {}: {what}", self.name);
        }
    }
}

impl<L: PortLink> PortLink for Watched<L> {
    fn poll(&mut self) -> Result<(), Self::Error> {
        self.link.poll()?;
        self.watch();
        Ok(())
    }

    fn connections(&self) -> u64 {
        self.link.connections()
    }

    fn admit(&mut self, gate: &mut dyn Admission, now_ms: u32) -> Result<bool, Self::Error> {
        let admitted = self.link.admit(gate, now_ms)?;
        self.watch();
        Ok(admitted)
    }

    fn discard_input(&mut self) -> Result<usize, Self::Error> {
        self.link.discard_input()
    }

    fn hang_up(&mut self) {
        self.link.hang_up();
        self.watch();
    }
}

/// How [`listen`] serves.
#[derive(Debug, Clone)]
pub struct ListenOptions {
    /// Where the TCP link listens (port 0: any free port).
    pub tcp: SocketAddr,
    /// Where the web link listens: the operator's page at `/`, its WebSocket at `/ws` (port
    /// 0: any free port).
    pub http: SocketAddr,
    /// When the port of [`ListenOptions::http`] is taken, listen on any free port instead,
    /// and say so on stderr: for a default port, not one the operator asked for.
    pub http_any_port_if_taken: bool,
    /// A symbolic link to make to the pseudo-terminal.
    pub pty_link: Option<PathBuf>,
    /// Faults on the bytes from hosts.
    pub faults: FaultConfig,
    /// Real time, or faster.
    pub pacing: Pacing,
    /// Stop after this much virtual time.
    pub time_limit_ticks: Option<u64>,
    /// Record every step to this file.
    pub trace: Option<PathBuf>,
    /// Keep the board's flash in this state file ([`crate::state`]).
    pub state: Option<PathBuf>,
    /// Keep the board's SD card in this directory (`None`: a fresh temporary one).
    pub sd_dir: Option<PathBuf>,
    /// What a host that is not in control is sent: a TCP client that connects while another
    /// host is in control (it is then closed), a terminal host whose input is refused, and a
    /// web page that watches and sends.
    /// Every board sends [`busy_message`].
    pub busy_message: Vec<u8>,
    /// Virtual time after which a silent controlling host loses control (a TCP client is
    /// closed), ms; `None`: never. See [`SimBoard::set_idle_timeout`].
    pub idle_timeout_ms: Option<u32>,
}

/// The idle time-out [`listen`] is given by default: a minute of silence.
pub const DEFAULT_IDLE_TIMEOUT_MS: u32 = 60_000;

type Served<L> = Watched<FaultInjector<L>>;

fn watched<L: PortLink>(
    name: &'static str,
    link: L,
    machine: &SimMachine,
    faults: FaultConfig,
) -> Result<Served<L>, String> {
    Ok(Watched::new(
        name,
        FaultInjector::new(link, faults).map_err(|e| e.to_string())?,
        machine.clock(),
        machine.tick_hz(),
    ))
}

/// Serve hosts on TCP (with frames 54 and 55), on a pseudo-terminal and on the web link (the
/// operator's page and its WebSocket, with frames 54 and 55 too), through the controller, one
/// controlling host across the three, paced to the wall clock, until the time limit or until
/// `stop` is raised. The web link's watchers see what the TCP client is sent as well as what
/// a page in control is. Prints where the links are, then a summary.
///
/// Errors: a link that cannot be opened or fails, a board that cannot be built.
pub fn listen(
    config: &MachineConfig,
    options: &ListenOptions,
    stop: Arc<AtomicBool>,
) -> Result<(), String> {
    let tcp_addr = options.tcp;
    let tcp = TcpLink::bind(tcp_addr, options.busy_message.clone())
        .map_err(|e| format!("tcp {tcp_addr}: {e}"))?;
    let tcp_addr = tcp
        .local_addr()
        .map_err(|e| format!("tcp {tcp_addr}: {e}"))?;
    let http_addr = options.http;
    let web = match WebLink::bind(http_addr, options.busy_message.clone()) {
        Err(e) if e.kind() == std::io::ErrorKind::AddrInUse && options.http_any_port_if_taken => {
            let any = SocketAddr::new(http_addr.ip(), 0);
            let web = WebLink::bind(any, options.busy_message.clone());
            eprintln!(
                "forja-sim: http port {} is taken: any free port instead",
                http_addr.port()
            );
            web
        }
        bound => bound,
    }
    .map_err(|e| format!("http {http_addr}: {e}"))?;
    let http_addr = web
        .local_addr()
        .map_err(|e| format!("http {http_addr}: {e}"))?;
    let tcp = Tapped::new(tcp, web.tap());
    let pty = PtyLink::open(options.pty_link.as_deref()).map_err(|e| match &options.pty_link {
        Some(p) => format!("pseudo-terminal (link {}): {e}", p.display()),
        None => format!("pseudo-terminal: {e}"),
    })?;
    println!("machine: {}", config.name);
    println!("tcp: {tcp_addr}");
    println!("pty: {}", pty.slave_path().display());
    println!("http: {http_addr}");
    if let Some(link) = pty.symlink_path() {
        println!(
            "pty-link: {} -> {}",
            link.display(),
            pty.slave_path().display()
        );
    }
    if options.faults.is_active() {
        println!(
            "faults: corrupt {} drop {} seed {} (bytes from hosts only)",
            options.faults.corrupt_rate, options.faults.drop_rate, options.faults.seed
        );
    }
    let _ = std::io::stdout().flush();

    let machine = SimMachine::new(config);
    machine.set_tracing(options.trace.is_some());
    let mut board_config = crate::state::board_config(options.state.as_deref())?;
    board_config.sd_dir = options.sd_dir.clone();
    let mut board = SimBoard::new(&machine, board_config).map_err(|e| e.to_string())?;
    let tcp_port = board.add_port(watched("tcp", tcp, &machine, options.faults)?, true);
    let pty_port = board.add_port(watched("pty", pty, &machine, options.faults)?, false);
    let web_port = board.add_port(watched("http", web, &machine, options.faults)?, true);
    for port in [tcp_port, pty_port, web_port] {
        board.set_idle_timeout(port, options.idle_timeout_ms);
    }
    board.set_busy_message(options.busy_message.clone());

    let mut sim_config = SimulationConfig::new(config.tick_hz);
    sim_config.pacing = options.pacing;
    sim_config.time_limit_ticks = options.time_limit_ticks;
    let mut sim = Simulation::new(machine.clone(), sim_config);
    sim.set_stop_flag(stop);
    let mut failure = None;
    let report = board
        .run(&mut sim, |board, _| {
            for id in [tcp_port, pty_port, web_port] {
                if let Some(e) = board.port_failure(id) {
                    failure = Some(e.to_string());
                    return Flow::Stop;
                }
            }
            Flow::Continue
        })
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
        report.virtual_ticks() as f64 / f64::from(config.tick_hz)
    );
    summary::<Tapped<TcpLink>>(&board, tcp_port, "tcp", options.faults);
    summary::<PtyLink>(&board, pty_port, "pty", options.faults);
    summary::<WebLink>(&board, web_port, "http", options.faults);
    let stats = board.status().controller.stats;
    println!(
        "controller: {} lines executed, {} refused, {} resends, {} frames, {} errors",
        stats.executed, stats.refused, stats.resends, stats.frames, stats.errors
    );
    if let Some(path) = &options.trace {
        machine
            .take_trace()
            .save(path)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        println!("trace: {}", path.display());
    }
    Ok(())
}

fn summary<L: PortLink<Error = std::io::Error> + 'static>(
    board: &SimBoard,
    id: PortId,
    name: &str,
    faults: FaultConfig,
) {
    let Some(port) = board.port::<Served<L>>(id) else {
        return;
    };
    print!(
        "{name}: {} connections, {} bytes received",
        port.connections(),
        port.received()
    );
    if let Some(s) = board.port_stats(id) {
        print!(
            ", {} sessions, {} idle time-outs, {} bytes refused",
            s.sessions, s.idle_timeouts, s.refused_bytes
        );
    }
    let link: &dyn std::any::Any = port.inner().inner();
    if let Some(tcp) = link.downcast_ref::<Tapped<TcpLink>>() {
        print!(", {} dropped for not reading", tcp.inner().overflows());
    } else if let Some(web) = link.downcast_ref::<WebLink>() {
        let s = web.stats();
        print!(
            ", {} assets served, {} requests refused, {} watchers, {} protocol errors, {} \
             dropped for not reading",
            s.served, s.refused_requests, s.watchers, s.protocol_errors, s.overflows
        );
    } else if let Some(pty) = link.downcast_ref::<PtyLink>() {
        print!(", {} reply bytes discarded", pty.tx_discarded());
    }
    if faults.is_active() {
        let s = port.inner().stats();
        print!(
            " ({} from the host, {} dropped, {} corrupted)",
            s.bytes, s.dropped, s.corrupted
        );
    }
    println!();
}

/// The refusal of a host while another is in control, as every board sends it: the
/// controller's `busy_refusal` (frame 56 `Error:E300 link-busy` for a frame client, then the
/// notice line `// E300 link-busy` for a G-code host).
pub fn busy_message() -> Vec<u8> {
    let mut out = [0; forja_app::controller::BUSY_REFUSAL_LEN];
    let len = forja_app::controller::busy_refusal(&mut out);
    out.get(..len).unwrap_or_default().to_vec()
}
