//! `forja`: the command the person at the machine runs. Parsing and printing only; the work is
//! in the `forja_host` library. The clap doc comments below are the `--help`.

use std::io::{self, BufRead, IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, Parser, Subcommand};
use forja_host::client::{self, Observer};
use forja_host::frames::{self, FrameClient, UploadOptions};
use forja_host::grbl_sender::{self, GrblSender};
use forja_host::link::{Connection, Incoming, LinkSpec};
use forja_host::program::Program;
use forja_host::streamer::{self, Window};
use forja_protocol::frame::{Action, Decimal};
use forja_protocol::grbl::Realtime;
use indicatif::{ProgressBar, ProgressStyle};

/// Forja's client: stream G-code to a controller, store and run programs, jog and watch the
/// machine.
#[derive(Parser, Debug)]
#[command(
    name = "forja",
    version,
    after_help = "The controller is reached with --port (a serial port) or --tcp (a network \
                  address).\nExit status: 0 success, 1 failure, 2 bad command line."
)]
struct Cli {
    #[command(flatten)]
    link: LinkArgs,

    #[command(subcommand)]
    command: Command,
}

#[derive(Args, Debug)]
struct LinkArgs {
    /// Serial port of the controller, e.g. /dev/ttyUSB0, /dev/ttyACM0 or COM3.
    #[arg(long, global = true, value_name = "PATH", conflicts_with = "tcp")]
    port: Option<String>,

    /// Baud rate of the serial port.
    #[arg(long, global = true, value_name = "N", default_value_t = 115_200)]
    baud: u32,

    /// Network address of the controller, HOST:PORT (e.g. 192.168.1.50:2323).
    #[arg(long, global = true, value_name = "HOST:PORT")]
    tcp: Option<String>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Stream a G-code file: numbered, checksummed lines, resent when damaged, several in
    /// flight at once; a progress bar, and a summary at the end. With --grbl, in the grbl 1.1
    /// dialect with character counting, as CNC senders stream.
    Send(SendArgs),
    /// Store a G-code file in the controller (frame protocol) to run it later with `run`.
    Upload {
        /// The G-code file.
        file: PathBuf,
        /// Lines sent between two checks of what the controller stored.
        #[arg(long, value_name = "N", default_value_t = 3)]
        batch: usize,
    },
    /// Run the stored program from its current line, or resume after `pause`.
    Run,
    /// Hold the motion (decelerating, without losing steps); `run` resumes.
    Pause,
    /// Abort the motion and the program (the position is kept).
    Stop,
    /// Set the stored program back to its first line.
    Rewind,
    /// Soft reset: clear alarms and modal state; the stored program is kept.
    Reset,
    /// Home every axis, or only AXIS.
    Home {
        /// The axis to home (X, Y, Z, A, …).
        axis: Option<char>,
    },
    /// Move axes by relative distances in mm at the jog feed rate, e.g. `forja jog X+0.1 Y-2`.
    Jog {
        /// Moves: an axis letter and a signed distance in mm.
        #[arg(required = true, value_name = "AXIS±MM")]
        moves: Vec<String>,
    },
    /// Show the positions and the program's progress, live.
    Status {
        /// Show once and exit.
        #[arg(long)]
        once: bool,
        /// Time between two updates, in milliseconds.
        #[arg(long, value_name = "MS", default_value_t = 250)]
        interval: u64,
        /// Stop after this many updates.
        #[arg(long, value_name = "N")]
        count: Option<u64>,
    },
    /// An interactive terminal: type G-code, read the controller's replies. Ctrl-D ends.
    Console {
        /// Show every line sent and received, resend requests included.
        #[arg(long)]
        verbose: bool,
    },
}

#[derive(Args, Debug)]
struct SendArgs {
    /// The G-code file.
    file: PathBuf,
    /// Most bytes in flight (the controller's receive buffer) [default: 256 on a serial
    /// port, 2048 over TCP].
    #[arg(long, value_name = "BYTES", conflicts_with = "grbl")]
    window: Option<usize>,
    /// Most lines in flight [default: 32 on a serial port, 128 over TCP].
    #[arg(long, value_name = "N", conflicts_with = "grbl")]
    window_lines: Option<usize>,
    /// Seconds without an answer before lines are sent again.
    #[arg(
        long,
        value_name = "S",
        default_value_t = 10.0,
        conflicts_with = "grbl"
    )]
    reply_timeout: f64,
    /// No progress bar (the summary is still printed).
    #[arg(long)]
    quiet: bool,
    /// Speak grbl 1.1, as CNC senders do: a soft reset (ctrl-x) and the banner first, then
    /// lines without numbers, comments and blanks stripped, each answered `ok` or `error:N`,
    /// as many in flight as the controller's receive buffer holds (character counting), and a
    /// `?` status poll four times a second. Ends when the machine is idle again.
    #[arg(long)]
    grbl: bool,
    /// With --grbl: the receive buffer to count against, bytes [default: the free bytes of the
    /// `Bf:` a `?` reports once connected (see --report-buffer), else 128, grbl's].
    #[arg(long, value_name = "BYTES", requires = "grbl")]
    rx_buffer: Option<usize>,
    /// With --grbl: send `$10=3` first so that status reports carry `Bf:` (a Forja link's own
    /// setting; grbl itself stores it).
    #[arg(long, requires = "grbl")]
    report_buffer: bool,
    /// With --grbl: at a hold that asks for a cycle start (an `M6` tool change), send `~` at
    /// once instead of waiting for Enter.
    #[arg(long, requires = "grbl")]
    auto_cycle_start: bool,
}

/// `println!` that does not fail when standard output is closed (`forja … | head`).
macro_rules! say {
    ($($arg:tt)*) => {{
        let _ = writeln!(io::stdout(), $($arg)*);
    }};
}

/// `print!` that does not fail when standard output is closed.
macro_rules! say_part {
    ($($arg:tt)*) => {{
        let _ = write!(io::stdout(), $($arg)*);
    }};
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("forja: {e:#}");
            ExitCode::FAILURE
        }
    }
}

impl LinkArgs {
    fn spec(&self) -> Result<LinkSpec> {
        match (&self.port, &self.tcp) {
            (Some(path), None) => Ok(LinkSpec::Serial {
                path: path.clone(),
                baud: self.baud,
            }),
            (None, Some(address)) => Ok(LinkSpec::Tcp {
                address: address.clone(),
            }),
            _ => bail!(
                "say where the controller is: --port /dev/ttyUSB0 (a serial port) or --tcp \
                 HOST:PORT (a network address)"
            ),
        }
    }

    fn connect(&self) -> Result<(LinkSpec, Connection)> {
        let spec = self.spec()?;
        let conn = Connection::open(&spec)?;
        Ok((spec, conn))
    }
}

fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Send(args) if args.grbl => send_grbl(&cli.link, &args),
        Command::Send(args) => send(&cli.link, &args),
        Command::Upload { file, batch } => upload(&cli.link, &file, batch),
        Command::Run => action(&cli.link, Action::Start, "running the stored program"),
        Command::Pause => action(&cli.link, Action::Pause, "paused"),
        Command::Stop => action(&cli.link, Action::Stop, "stopped"),
        Command::Rewind => action(&cli.link, Action::Rewind, "the program is back at line 1"),
        Command::Reset => action(&cli.link, Action::Reset, "reset"),
        Command::Home { axis: None } => action(&cli.link, Action::HomeAll, "homing all axes"),
        Command::Home { axis: Some(a) } => {
            let a = a.to_ascii_uppercase();
            if !a.is_ascii_uppercase() {
                bail!("'{a}' is not an axis letter");
            }
            action(&cli.link, Action::Home(a as u8), &format!("homing {a}"))
        }
        Command::Jog { moves } => jog(&cli.link, &moves),
        Command::Status {
            once,
            interval,
            count,
        } => status(&cli.link, if once { Some(1) } else { count }, interval),
        Command::Console { verbose } => console(&cli.link, verbose),
    }
}

/// The progress bar of `send`, and the notices above it.
struct Progress {
    bar: ProgressBar,
}

impl Observer for Progress {
    fn progress(&mut self, accepted: u32, total: u32) {
        self.bar.set_length(u64::from(total));
        self.bar.set_position(u64::from(accepted));
    }

    fn notice(&mut self, text: &str) {
        self.bar.println(text);
    }
}

fn send(link: &LinkArgs, args: &SendArgs) -> Result<ExitCode> {
    let program = Program::load(&args.file)?;
    let (spec, mut conn) = link.connect()?;
    let base = if spec.is_tcp() {
        Window::TCP
    } else {
        Window::UART
    };
    if !(args.reply_timeout.is_finite() && args.reply_timeout > 0.0) {
        bail!("--reply-timeout must be a positive number of seconds");
    }
    let config = streamer::Config {
        window: Window {
            bytes: args.window.unwrap_or(base.bytes).max(1),
            lines: args.window_lines.unwrap_or(base.lines).max(1),
        },
        reply_timeout: Duration::from_secs_f64(args.reply_timeout),
        ..streamer::Config::default()
    };
    let bar = progress_bar(args.quiet, program.lines.len())?;
    client::drain(&mut conn, Duration::from_millis(500))
        .with_context(|| format!("reading from {spec}"))?;
    let mut observer = Progress { bar: bar.clone() };
    let result = client::send_program(&mut conn, &program, config, &mut observer);
    bar.finish_and_clear();
    let report = result?;
    let name = args.file.display();
    let kb = report.stats.bytes_sent as f64 / 1000.0;
    say!(
        "sent {name}: {} lines in {:.1} s ({:.0} lines/s, {kb:.1} kB)",
        report.lines,
        report.elapsed.as_secs_f64(),
        report.lines_per_second()
    );
    let s = report.stats;
    say!(
        "resends: {} ({} lines sent again), time-outs: {}, refused: {}",
        s.rewinds,
        s.lines_resent,
        s.stalls,
        report.refused.len()
    );
    match (report.link_use(), report.bit_rate) {
        (Some(share), Some(rate)) if share <= 1.05 => {
            say!("link use: {:.0} % of {rate} baud", share * 100.0);
        }
        (Some(share), Some(rate)) => say!(
            "link: {:.0} bits/s, faster than its nominal {rate} baud (a USB or virtual port)",
            share * f64::from(rate)
        ),
        _ => {}
    }
    if report.refused.is_empty() {
        Ok(ExitCode::SUCCESS)
    } else {
        for r in &report.refused {
            eprintln!("forja: {r}");
        }
        eprintln!(
            "forja: the job ran, but {} line(s) of it were refused and had no effect",
            report.refused.len()
        );
        Ok(ExitCode::FAILURE)
    }
}

/// Show `text` above the progress bar, or on standard error when there is no bar.
fn tell(bar: &ProgressBar, text: impl AsRef<str>) {
    if bar.is_hidden() {
        eprintln!("{}", text.as_ref());
    } else {
        bar.println(text);
    }
}

/// `send --grbl`: stream `args.file` with the grbl sender until every line is answered and
/// the machine is idle.
fn send_grbl(link: &LinkArgs, args: &SendArgs) -> Result<ExitCode> {
    let name = args.file.display();
    let text =
        std::fs::read_to_string(&args.file).with_context(|| format!("cannot read {name}"))?;
    let config = grbl_sender::Config {
        rx_buffer_bytes: args.rx_buffer.unwrap_or(grbl_sender::GRBL_RX_BUFFER),
        report_buffer: args.report_buffer,
        size_from_report: args.rx_buffer.is_none(),
        ..grbl_sender::Config::default()
    };
    let mut sender = GrblSender::new(config);
    // The source line of each line sent, for messages.
    let mut source = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if sender
            .push(line)
            .with_context(|| format!("{name}, line {}", i + 1))?
            .is_some()
        {
            source.push(i + 1);
        }
    }
    sender.finish();
    let (spec, mut conn) = link.connect()?;
    let bar = progress_bar(args.quiet, source.len())?;
    client::drain(&mut conn, Duration::from_millis(500))
        .with_context(|| format!("reading from {spec}"))?;
    // Enter at the terminal is the operator's cycle start.
    let enter = (!args.auto_cycle_start && io::stdin().is_terminal()).then(|| {
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in io::stdin().lock().lines() {
                if line.is_err() || tx.send(()).is_err() {
                    break;
                }
            }
        });
        rx
    });
    let started = Instant::now();
    let mut out = Vec::new();
    // The status reports counted when the last line was answered: the machine is done at the
    // first `Idle` reported after it.
    let mut reports_at_done = None;
    loop {
        out.clear();
        sender.transmit(Instant::now(), &mut out);
        conn.send(&out)?;
        while let Some(event) = sender.next_event() {
            let line = |number: u32| source.get(number as usize - 1).copied().unwrap_or(0);
            match event {
                grbl_sender::Event::Ready { rx_buffer_bytes } => {
                    tell(
                        &bar,
                        format!("connected: counting against {rx_buffer_bytes} bytes"),
                    );
                }
                grbl_sender::Event::Refused { number, code, text } => {
                    tell(
                        &bar,
                        format!("{name}, line {}: error:{code}: {text}", line(number)),
                    );
                }
                grbl_sender::Event::Alarm { code } => {
                    bar.finish_and_clear();
                    bail!(
                        "ALARM:{code}: the machine stopped; {} of {} lines were sent",
                        sender.sent(),
                        source.len()
                    );
                }
                grbl_sender::Event::Message(text) => tell(&bar, format!("controller: {text}")),
                grbl_sender::Event::AwaitingCycleStart(text) => {
                    tell(&bar, format!("controller: {text}"));
                    if args.auto_cycle_start {
                        sender.realtime(Realtime::CycleStart);
                        tell(&bar, "cycle start sent (~)");
                    } else if let Some(enter) = &enter {
                        while enter.try_recv().is_ok() {}
                        tell(&bar, "press Enter for cycle start (~)");
                    } else {
                        tell(&bar, "waiting for cycle start on the machine");
                    }
                }
                grbl_sender::Event::Restarted => {
                    bar.finish_and_clear();
                    bail!("the controller restarted during the job (a banner came unasked)");
                }
                grbl_sender::Event::NoBanner => {
                    bar.finish_and_clear();
                    bail!("no grbl banner from {spec} after ctrl-x: is it a grbl controller?");
                }
                _ => {}
            }
        }
        if enter.as_ref().is_some_and(|e| e.try_recv().is_ok()) {
            sender.realtime(Realtime::CycleStart);
            tell(&bar, "cycle start sent (~)");
        }
        let answered = sender.answers().iter().filter(|a| a.is_some()).count();
        bar.set_position(answered as u64);
        let stats = sender.stats();
        if sender.phase() == grbl_sender::Phase::Done {
            let since = *reports_at_done.get_or_insert(stats.status_reports);
            let idle = sender.last_status().is_some_and(|s| s.starts_with("Idle"));
            if stats.status_reports > since && idle {
                break;
            }
        }
        let wait = sender
            .poll_at()
            .map_or(Duration::from_millis(100), |t| {
                t.saturating_duration_since(Instant::now())
            })
            .min(Duration::from_millis(100));
        if let Some(Incoming::Line(line)) = conn.receive(wait)? {
            sender.receive(Instant::now(), &line);
        }
    }
    bar.finish_and_clear();
    let s = sender.stats();
    say!(
        "sent {name}: {} lines in {:.1} s, {} refused (error:N); counted against {} bytes, \
         largest in flight {} bytes ({} lines)",
        source.len(),
        started.elapsed().as_secs_f64(),
        s.errors,
        sender.rx_buffer_bytes(),
        s.max_in_flight_bytes,
        s.max_in_flight_lines
    );
    if s.errors == 0 {
        Ok(ExitCode::SUCCESS)
    } else {
        eprintln!(
            "forja: the job ran, but {} line(s) of it were refused and had no effect",
            s.errors
        );
        Ok(ExitCode::FAILURE)
    }
}

fn upload(link: &LinkArgs, file: &Path, batch: usize) -> Result<ExitCode> {
    let program = Program::load(file)?;
    let texts = program.frame_texts()?;
    let shortened = program
        .lines
        .iter()
        .zip(&texts)
        .filter(|(l, t)| l.text != **t)
        .count();
    let (spec, mut conn) = link.connect()?;
    client::drain(&mut conn, Duration::from_millis(300))
        .with_context(|| format!("reading from {spec}"))?;
    let bar = if io::stderr().is_terminal() {
        ProgressBar::new(texts.len() as u64)
    } else {
        ProgressBar::hidden()
    };
    let mut frames = FrameClient::new(&mut conn, Duration::from_secs(2));
    let options = UploadOptions {
        batch: batch.max(1),
        ..UploadOptions::default()
    };
    let report = frames.upload(&texts, options, |n| bar.set_position(n as u64));
    bar.finish_and_clear();
    let report = report?;
    say_part!("uploaded {}: {} lines stored", file.display(), report.lines);
    if shortened > 0 {
        say_part!(", {shortened} shortened to fit 39 bytes (same meaning)");
    }
    if report.resent > 0 {
        say_part!(", {} sent again", report.resent);
    }
    say!();
    if !report.confirmed {
        bail!("every line is stored, but the controller did not confirm the program");
    }
    say!("the controller confirmed the program: 'forja run' starts it");
    Ok(ExitCode::SUCCESS)
}

fn action(link: &LinkArgs, action: Action, done: &str) -> Result<ExitCode> {
    let (spec, mut conn) = link.connect()?;
    client::drain(&mut conn, Duration::from_millis(200))
        .with_context(|| format!("reading from {spec}"))?;
    let mut frames = FrameClient::new(&mut conn, Duration::from_secs(2));
    let progress = frames.action(action)?;
    say_part!("{done}");
    if matches!(
        action,
        Action::Start | Action::Rewind | Action::Pause | Action::Stop
    ) && progress.total_lines > 0
    {
        say_part!(
            " (line {} of {})",
            progress.current_line,
            progress.total_lines
        );
    }
    say!();
    Ok(ExitCode::SUCCESS)
}

fn parse_jog(text: &str) -> Result<(u8, Decimal)> {
    let mut chars = text.chars();
    let axis = chars
        .next()
        .filter(char::is_ascii_alphabetic)
        .ok_or_else(|| anyhow!("\"{text}\": a jog is an axis letter and a distance, e.g. X+0.1"))?;
    let rest = chars.as_str();
    let distance = Decimal::parse(rest.as_bytes())
        .filter(|_| !rest.is_empty())
        .ok_or_else(|| {
            anyhow!("\"{text}\": \"{rest}\" is not a distance in mm (e.g. X+0.1, Y-2, Z5)")
        })?;
    Ok((axis.to_ascii_uppercase() as u8, distance))
}

fn jog(link: &LinkArgs, moves: &[String]) -> Result<ExitCode> {
    let moves = moves
        .iter()
        .map(|m| parse_jog(m))
        .collect::<Result<Vec<_>>>()?;
    let (spec, mut conn) = link.connect()?;
    client::drain(&mut conn, Duration::from_millis(200))
        .with_context(|| format!("reading from {spec}"))?;
    let mut frames = FrameClient::new(&mut conn, Duration::from_secs(2));
    for (axis, distance) in moves {
        frames.jog(axis, distance)?;
        say!("jogging {} by {distance} mm", char::from(axis));
    }
    Ok(ExitCode::SUCCESS)
}

fn status(link: &LinkArgs, count: Option<u64>, interval_ms: u64) -> Result<ExitCode> {
    let (spec, mut conn) = link.connect()?;
    client::drain(&mut conn, Duration::from_millis(200))
        .with_context(|| format!("reading from {spec}"))?;
    let live = io::stdout().is_terminal() && count != Some(1);
    let mut frames = FrameClient::new(&mut conn, Duration::from_secs(2));
    let mut shown = 0u64;
    let mut stdout = io::stdout();
    loop {
        let positions = frames.positions()?;
        let progress = frames.progress()?;
        for notice in frames.take_notices() {
            if live {
                writeln!(stdout)?;
            }
            writeln!(stdout, "controller: {notice}")?;
        }
        let line = frames::status_line(&positions, &progress);
        if live {
            write!(stdout, "\r\x1b[2K{line}")?;
        } else {
            writeln!(stdout, "{line}")?;
        }
        stdout.flush()?;
        shown += 1;
        if count.is_some_and(|c| shown >= c) {
            break;
        }
        // A long interval must not let the board's idle time-out end the session.
        let next = Instant::now() + Duration::from_millis(interval_ms);
        while let Some(left) = next.checked_duration_since(Instant::now()) {
            std::thread::sleep(left.min(Duration::from_secs(1)));
            frames.keep_alive()?;
        }
    }
    if live {
        writeln!(stdout)?;
    }
    Ok(ExitCode::SUCCESS)
}

fn console(link: &LinkArgs, verbose: bool) -> Result<ExitCode> {
    let (spec, mut conn) = link.connect()?;
    if io::stdin().is_terminal() {
        eprintln!("connected to {spec}; type G-code, Ctrl-D ends");
    }
    client::drain(&mut conn, Duration::from_millis(300))
        .with_context(|| format!("reading from {spec}"))?;
    if verbose {
        conn.record();
    }
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in io::stdin().lock().lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let mut stdout = io::stdout();
    let result = client::console(&mut conn, &rx, &mut stdout, streamer::Config::default());
    if verbose {
        for (sent, bytes) in conn.transcript() {
            let arrow = if *sent { ">" } else { "<" };
            for l in String::from_utf8_lossy(bytes).split(['\r', '\n']) {
                if !l.is_empty() {
                    eprintln!("{arrow} {l}");
                }
            }
        }
    }
    result?;
    Ok(ExitCode::SUCCESS)
}

/// The progress bar of a stream of `lines` lines on the terminal (hidden when `quiet` or when
/// standard error is not a terminal).
fn progress_bar(quiet: bool, lines: usize) -> Result<ProgressBar> {
    let bar = if quiet || !io::stderr().is_terminal() {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(lines as u64)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{bar:40}] {pos}/{len} lines {percent:>3}% {elapsed_precise} ETA {eta}",
        )
        .map_err(|e| anyhow!("{e}"))?
        .progress_chars("=> "),
    );
    Ok(bar)
}
