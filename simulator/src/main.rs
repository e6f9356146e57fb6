//! `forja-sim`: the simulator board as a program.
//!
//! Runs a job through the firmware (the controller and the motion kernel on the simulated
//! hardware), streamed in the RepRap dialect or, with `--grbl`, in grbl's, and prints the
//! result; with `--listen`, serves hosts on TCP and a pseudo-terminal instead; with `--check`,
//! only describes the machine file and the job (and, with `--state`, what the state file
//! keeps); with `--plot`, draws the job's toolpath (a printer's extrusion and travel, by layer)
//! and the steps the machine made. The work is in the library (`forja_simulator::run`,
//! `forja_simulator::state`, `forja_simulator::plot`); the clap doc comments below are the
//! `--help`.

use std::io::Write as _;
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use clap::Parser;
use forja_sim_hal::config::{AxisKind, SwitchPolarity, SwitchSide};
use forja_sim_hal::link::FaultConfig;
use forja_sim_hal::{MachineConfig, Pacing};
use forja_simulator::Job;
use forja_simulator::plot::{self, Executed, ImageFormat, LayerRange, Lead, PlotOptions, Toolpath};
use forja_simulator::run::{JobOptions, ListenOptions};

/// Exit code of a job that did not run cleanly (a refused line, lost or badly timed steps, a
/// job that did not finish).
const EXIT_NOT_CLEAN: u8 = 2;

/// Forja's host simulator board: a simulated machine with virtual steppers, limit switches,
/// heaters and clock, running the Forja firmware, reachable over TCP and a pseudo-terminal.
#[derive(Parser, Debug)]
#[command(
    name = "forja-sim",
    version,
    after_help = "Exit status: 0 success, 1 bad input or link failure, 2 the job did not run \
                  cleanly (with --check --plot: the kernel refuses a line of it)."
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

    /// Do not home (G28, or $H with --grbl) before the job: its coordinates are then relative
    /// to where the machine starts.
    #[arg(long)]
    no_home: bool,

    /// Stream the job in the grbl 1.1 dialect, as a CNC sender (CNCjs, UGS) does, instead of
    /// the RepRap one: 0x18 and the banner, $10=3, then character counting against the free
    /// bytes of the receive buffer a `?` reports (Bf:), $H first, a `?` every 200 ms of virtual
    /// time, and `~` (an operator's cycle start, logged) at a tool change's hold. The summary
    /// adds the largest number of bytes in flight, the buffer counted against and the longest
    /// time a `?` waited for its report.
    #[arg(long, conflicts_with = "listen")]
    grbl: bool,

    /// A line to send after homing and before the job, e.g. a work offset: --before "G10 L2 P1
    /// X50 Y50 Z20". Repeat it for several lines; they are sent in order, in either dialect,
    /// and --plot's toolpath follows them too.
    #[arg(long, value_name = "LINE", conflicts_with = "listen")]
    before: Vec<String>,

    /// Wait for hosts on TCP, on a pseudo-terminal and on the web link (the operator's page,
    /// see --http-port) instead of running the job, and print where they are. Paced to the wall clock (see --time-scale). Ends at --time-limit or on
    /// Ctrl-C.
    #[arg(long)]
    listen: bool,

    /// Address the TCP link listens on [default: the machine file's, else 127.0.0.1].
    #[arg(long, value_name = "ADDR")]
    tcp_bind: Option<IpAddr>,

    /// TCP port [default: the machine file's, else 2323]; 0 picks any free port.
    #[arg(long, value_name = "PORT")]
    tcp_port: Option<u16>,

    /// Address the web link listens on: the operator's page at http://ADDR:PORT/, its
    /// WebSocket at /ws [default: the TCP link's address].
    #[arg(long, value_name = "ADDR")]
    http_bind: Option<IpAddr>,

    /// Port of the web link [default: the machine file's http_port, else 8080]; 0 picks any
    /// free port. Printed as `http: ADDR:PORT` at start. When the default port is taken (by
    /// another simulator), any free port is used instead; a port given here must be free.
    #[arg(long, value_name = "PORT")]
    http_port: Option<u16>,

    /// Also make a symbolic link at PATH to the pseudo-terminal, a stable name for host
    /// software (the /dev/pts number changes from run to run).
    #[arg(long, value_name = "PATH")]
    pty_link: Option<PathBuf>,

    /// Hold virtual time to the wall clock when running a job (--listen always does).
    #[arg(long)]
    realtime: bool,

    /// Run virtual time K times faster than the wall clock when paced (--listen, --realtime).
    #[arg(long, value_name = "K", default_value_t = 1.0)]
    time_scale: f64,

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

    /// Draw the job's toolpath, as the firmware's kernel reads it, to OUT (`.png` or `.svg`),
    /// with the path the machine took over it, from the steps it made. When the job runs, the
    /// run's own steps are drawn (recorded as --trace does, to its FILE when given) and the
    /// toolpath starts with the run's G28 (none with --no-home). With --check nothing runs: the
    /// job alone is drawn from the machine's start position, as a host that sends the file to
    /// --listen has it run, with the steps of --plot-trace over it when given.
    ///
    /// On a printer (a machine with an extruder axis) extrusion is drawn solid, coloured by
    /// layer from purple (lowest) through blue and teal to green (highest), travel thin and
    /// dashed; retractions draw nothing. The view frames the part over the bed (the machine's
    /// X/Y travel): extrusion far from the layers above the first, such as a purge line, is
    /// left to an overview beside it. On other machines feeds are solid, rapids dashed, and the
    /// view frames the whole path. A line the kernel refuses is drawn as the machine runs the
    /// job, without it, listed and marked.
    ///
    /// The steps are held to the toolpath: every position the machine passes through (after
    /// each step, in X/Y/Z; a rotary axis and an extruder left out) must be within one step
    /// (the largest mm per step of X, Y and Z) of the moves, whose ends the kernel rounds to
    /// whole steps. The farthest is printed (`trace: farthest from the toolpath 0.0088 mm (one
    /// step: 0.0125 mm)`); steps that stray farther fail the command, the plot drawn with the
    /// place marked, naming how far, where and the line. Homing cycles are not measured: after
    /// a G28 the steps are measured from the last time the machine comes to where homing
    /// leaves it (the start of the program's next move), and before one up to where they
    /// leave the end of the last move.
    #[arg(long, value_name = "OUT", conflicts_with = "listen")]
    plot: Option<PathBuf>,

    /// With --check --plot: a step trace recorded earlier (`--listen --trace FILE`, the job sent
    /// by a host) to draw over the toolpath and hold to it as --plot says: a trace of another
    /// job, or of this one shifted, fails.
    #[arg(long, value_name = "FILE", requires = "plot", requires = "check")]
    plot_trace: Option<PathBuf>,

    /// With --plot, on a printer: draw only these layers, numbered from 1 as slicer previews
    /// number them: one (`3`), or a range with both ends included (`2..5`, `2..` to the top,
    /// `..5` from the first). A layer is a height at which extrusion happens, counted in the
    /// order printed: a purge line drawn before the first layer belongs to layer 1. Cura's
    /// `;LAYER:n` comments count from 0: its layer n is layer n+1 here. The title says the
    /// layers drawn and their heights; the steps the machine made are drawn at those heights.
    #[arg(long, value_name = "LAYERS", requires = "plot")]
    plot_layers: Option<String>,

    /// With --plot: leave travel out (a printer's moves without extrusion; the rapids of other
    /// machines).
    #[arg(long, requires = "plot")]
    plot_hide_travel: bool,

    /// With --listen: a controlling host that sends nothing for this many seconds of virtual
    /// time, while no answer is owed to it, loses control (a TCP client is closed). Any byte
    /// keeps it (`M105`, `?`, a frame 04), and so do reports it asked for every period
    /// (`M155 S`, `M27 S`); any other host that waits on the machine must poll.
    #[arg(
        long,
        value_name = "SECONDS",
        default_value_t = f64::from(forja_simulator::run::DEFAULT_IDLE_TIMEOUT_MS) / 1000.0
    )]
    idle_timeout: f64,

    /// Keep the board's flash (the settings and the uploaded program) in FILE, made erased
    /// when missing, so that they survive a restart as on a board. Each flash erase and write
    /// is in the file when it completes; a simulator killed mid-write leaves the file as a
    /// power cut leaves a flash. With --check: describe what FILE keeps.
    #[arg(long, value_name = "FILE")]
    state: Option<PathBuf>,

    /// Keep the board's SD card (M20–M32: files uploaded with M28/M29, printed with M23/M24)
    /// in DIR, made if missing; by default a fresh temporary directory, removed at exit.
    #[arg(long, value_name = "DIR")]
    sd_dir: Option<PathBuf>,
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
    if !(cli.time_scale.is_finite() && cli.time_scale > 0.0) {
        return Err(format!(
            "--time-scale {}: must be a positive number",
            cli.time_scale
        ));
    }
    let pacing = if cli.time_scale == 1.0 {
        Pacing::Realtime
    } else {
        Pacing::Scaled(cli.time_scale)
    };
    let plot_options = PlotOptions {
        layers: match &cli.plot_layers {
            Some(text) => Some(
                text.parse::<LayerRange>()
                    .map_err(|e| format!("--plot-layers {text}: {e}"))?,
            ),
            None => None,
        },
        hide_travel: cli.plot_hide_travel,
    };

    if cli.check {
        print_machine(&cli.machine, &machine);
        println!("job: {}, {} lines", job.name(), job.line_count());
        if let Some(path) = &cli.state {
            let text = forja_simulator::state::describe(&machine, path)?;
            // A reader that stops early (`| head`) ends the listing, not an error.
            match std::io::stdout().write_all(text.as_bytes()) {
                Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => {
                    return Err(format!("stdout: {e}"));
                }
                _ => {}
            }
        }
        if let Some(out) = &cli.plot {
            let lead = Lead {
                home_first: false,
                grbl: cli.grbl,
                before: &cli.before,
            };
            let path = toolpath(&machine, &job, &lead, &plot_options)?;
            let executed = match &cli.plot_trace {
                Some(trace) => Some(read_trace(trace, &machine)?),
                None => None,
            };
            draw(out, &job, &path, executed.as_ref(), &plot_options)?;
            if !path.refused.is_empty() {
                eprintln!(
                    "forja-sim: the kernel refuses {} of the job's lines (listed above): the \
                     machine would run it without them",
                    path.refused.len()
                );
                return Ok(ExitCode::from(EXIT_NOT_CLEAN));
            }
        }
        return Ok(ExitCode::SUCCESS);
    }
    if cli.listen {
        let options = ListenOptions {
            tcp: SocketAddr::new(
                cli.tcp_bind.unwrap_or(machine.link.tcp_bind),
                cli.tcp_port.unwrap_or(machine.link.tcp_port),
            ),
            http: SocketAddr::new(
                cli.http_bind
                    .or(cli.tcp_bind)
                    .unwrap_or(machine.link.tcp_bind),
                cli.http_port.unwrap_or(machine.link.http_port),
            ),
            http_any_port_if_taken: cli.http_port.is_none(),
            pty_link: cli.pty_link.clone(),
            faults,
            pacing,
            time_limit_ticks,
            trace: cli.trace.clone(),
            state: cli.state.clone(),
            sd_dir: cli.sd_dir.clone(),
            busy_message: forja_simulator::run::busy_message(),
            idle_timeout_ms: Some(idle_timeout_ms(cli.idle_timeout)?),
        };
        let stop = Arc::new(AtomicBool::new(false));
        for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
            signal_hook::flag::register(signal, Arc::clone(&stop))
                .map_err(|e| format!("cannot handle signal {signal}: {e}"))?;
        }
        forja_simulator::run::listen(&machine, &options, stop)?;
        return Ok(ExitCode::SUCCESS);
    }

    // A plot is checked before the job runs, and draws the run's own steps: recorded to
    // --trace's file, or to one of its own that is not kept.
    let plotted = match &cli.plot {
        Some(out) => {
            ImageFormat::of(out).map_err(|e| e.to_string())?;
            let lead = Lead {
                home_first: !cli.no_home,
                grbl: cli.grbl,
                before: &cli.before,
            };
            Some(toolpath(&machine, &job, &lead, &plot_options)?)
        }
        None => None,
    };
    let own_trace = cli.plot.is_some() && cli.trace.is_none();
    let trace = cli.trace.clone().or_else(|| {
        own_trace.then(|| {
            std::env::temp_dir().join(format!("forja-sim-{}-plot.trace", std::process::id()))
        })
    });
    let options = JobOptions {
        home_first: !cli.no_home,
        grbl: cli.grbl,
        before: cli.before.clone(),
        faults,
        time_limit_ticks,
        pacing: if cli.realtime {
            pacing
        } else {
            Pacing::AsFastAsPossible
        },
        trace: trace.clone(),
        state: cli.state.clone(),
        sd_dir: cli.sd_dir.clone(),
    };
    let result = forja_simulator::run::run_job(&machine, &job, &options);
    let executed = match (&cli.plot, &trace, &result) {
        (Some(_), Some(trace), Ok(_)) => Some(read_trace(trace, &machine)),
        _ => None,
    };
    if let (true, Some(trace)) = (own_trace, &trace) {
        let _ = std::fs::remove_file(trace);
    }
    let result = result?;
    println!("{result}");
    if let (Some(out), Some(path), Some(executed)) = (&cli.plot, &plotted, executed) {
        draw(out, &job, path, Some(&executed?), &plot_options)?;
    }
    Ok(exit_code(&result))
}

/// Success for a job that ran cleanly, else [`EXIT_NOT_CLEAN`].
fn exit_code(result: &forja_simulator::run::JobRun) -> ExitCode {
    if result.is_clean() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(EXIT_NOT_CLEAN)
    }
}

/// The steps of the step trace file `path`, replayed on `machine`.
fn read_trace(path: &Path, machine: &MachineConfig) -> Result<Executed, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("cannot read the step trace {}: {e}", path.display()))?;
    Executed::from_trace(&text, Some(machine)).map_err(|e| format!("{}: {e}", path.display()))
}

/// The toolpath of `job` on `machine` (after a `G28` when `home_first`, as the run sends it:
/// a machine that homes no axis is the same either way), with the layers of `options` checked.
fn toolpath(
    machine: &MachineConfig,
    job: &Job,
    lead: &Lead<'_>,
    options: &PlotOptions,
) -> Result<Toolpath, String> {
    let path = Toolpath::from_job(machine, job, lead).map_err(|e| e.to_string())?;
    if let Some(range) = options.layers {
        path.select_layers(range)
            .map_err(|e| format!("--plot-layers {range}: {e}"))?;
    }
    Ok(path)
}

/// Draw `path`, the toolpath of `job`, to `out` as `options` say, with `executed` over it, and
/// say what was drawn and which lines the kernel refuses.
fn draw(
    out: &Path,
    job: &Job,
    path: &Toolpath,
    executed: Option<&Executed>,
    options: &PlotOptions,
) -> Result<(), String> {
    let name = Path::new(job.name()).file_name().map_or_else(
        || job.name().to_string(),
        |n| n.to_string_lossy().into_owned(),
    );
    plot::render(out, &name, path, executed, options).map_err(|e| e.to_string())?;
    if path.printer {
        println!(
            "plotted {} to {}: {}; {:.1} mm of extrusion ({:.1} mm of filament), {:.1} mm of \
             travel, {} retractions",
            job.name(),
            out.display(),
            path.describe_layers(None),
            path.extrusion_mm,
            path.filament_mm,
            path.travel_mm,
            path.retractions
        );
        if let Some(range) = options.layers {
            let span = path.select_layers(range).map_err(|e| e.to_string())?;
            println!("drawn: {}", path.describe_layers(Some(span)));
        }
    } else {
        println!(
            "plotted {} to {}: {:.1} mm at feed, {:.1} mm rapid",
            job.name(),
            out.display(),
            path.feed_mm,
            path.rapid_mm
        );
    }
    for refusal in &path.refused {
        let place = match refusal.line {
            Some(n) => format!("{}, line {n}", job.name()),
            None => "before the job".to_string(),
        };
        println!(
            "refused by the kernel: {place}: {}: {}",
            refusal.text, refusal.reason
        );
    }
    if let Some(ex) = executed {
        println!(
            "executed: {:.1} mm in XY from {} steps over {:.1} s; ends {:.3} mm from the \
             program's end",
            ex.length_mm,
            ex.steps,
            ex.duration_s,
            ex.off_end_mm(path)
        );
    }
    Ok(())
}

/// `--idle-timeout` in milliseconds: at least 1 ms, at most 24 days.
fn idle_timeout_ms(seconds: f64) -> Result<u32, String> {
    let ms = seconds * 1000.0;
    if ms.is_finite() && (1.0..=f64::from(i32::MAX)).contains(&ms) {
        Ok(ms as u32)
    } else {
        Err(format!(
            "--idle-timeout {seconds}: must be from 0.001 to 2000000 seconds"
        ))
    }
}

fn load_machine(arg: &str) -> Result<MachineConfig, String> {
    if let Some(name) = arg.strip_prefix("builtin:") {
        let text = MachineConfig::bundled_toml(name).ok_or_else(|| {
            let names: Vec<&str> = forja_sim_hal::config::BUNDLED
                .iter()
                .map(|(n, _)| *n)
                .collect();
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
    println!(
        "  link: tcp {}:{}, http {}:{}",
        m.link.tcp_bind, m.link.tcp_port, m.link.tcp_bind, m.link.http_port
    );
}
