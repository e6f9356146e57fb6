//! `cargo xtask`: Forja's one entry point for building, testing and running the firmware.
//!
//! Each subcommand is a list of steps run in order; the first failing step stops the run and
//! names itself. The help text below is the documentation of every command.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};

use clap::{Parser, Subcommand};

mod bench;
mod firmware;
mod graph;
mod lines;
mod qemu;

/// Forja's build, test and run tasks.
#[derive(Parser)]
#[command(name = "cargo xtask", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    task: Task,
}

#[derive(Subcommand)]
enum Task {
    /// Run every check CI runs: formatting, clippy with -D warnings, all host tests, the
    /// portable crates checked for both firmware targets, and the firmware builds.
    Test,
    /// Run the simulator with the bundled sample job and print the result; with `--listen`,
    /// wait for clients on TCP and a pseudo-terminal instead. Extra arguments go to the simulator.
    Sim {
        /// Arguments passed to the simulator (see `cargo xtask sim -- --help`).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Run every fuzz target for the given time each, or for a number of executions each
    /// (needs the nightly toolchain; installs cargo-fuzz when it is missing). A target's
    /// corpus grows in fuzz/corpus/<target>, its failing inputs land in
    /// fuzz/artifacts/<target>; the first failure stops the run.
    Fuzz {
        /// Seconds per target.
        #[arg(long, default_value_t = 60)]
        seconds: u64,
        /// Stop each target after this many executions instead of after `--seconds`
        /// (libFuzzer's `-runs`; with `--workers`, executions of all workers together).
        #[arg(long, conflicts_with = "seconds")]
        runs: Option<u64>,
        /// Run only this target.
        #[arg(long)]
        target: Option<String>,
        /// Fuzzing processes per target (libFuzzer's `-fork`); 1 fuzzes in one process.
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
        workers: u32,
        /// The sanitizer the targets are built with: address (cargo-fuzz's default), leak,
        /// memory, thread, or none (fastest: the safe-Rust checks, debug assertions and
        /// overflow checks stay on).
        #[arg(long, default_value = "address")]
        sanitizer: String,
    },
    /// Run the criterion benchmarks of the portable crates on the host, then count the motion
    /// kernel's instructions as machine code in the Unicorn emulator (installed into
    /// target/bench-venv): on the Cortex-M4 (an STM32F4 bench image), checked against the
    /// kernel's budgets (fails when one is exceeded), and on the RP2040's Cortex-M0+, reported.
    Bench {
        /// Only the host benchmarks.
        #[arg(long, conflicts_with = "target_only")]
        host_only: bool,
        /// Only the on-target instruction count.
        #[arg(long)]
        target_only: bool,
        /// Extra arguments passed to criterion (for example a benchmark name filter).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Build a firmware board's release images (its default variants, or one) into
    /// target/firmware/<board>-<variant>.elf; an ESP32 image also as a merged
    /// <board>-<variant>.bin to write at flash offset 0 (installs espflash when it is missing).
    Build {
        /// The board: stm32f4, esp32 or rp2040.
        board: String,
        /// Only this variant (Cargo feature), e.g. blackpill, qemu, esp32c3 or esp32c6.
        #[arg(long)]
        variant: Option<String>,
    },
    /// Build a board's hardware image and write it: with probe-rs through a debug probe
    /// (STM32, RP2040), or with espflash over USB (ESP32); installs the tool when it is
    /// missing.
    Flash {
        /// The board: stm32f4, esp32 or rp2040.
        board: String,
        /// The variant (default: the board's first hardware one).
        #[arg(long)]
        variant: Option<String>,
    },
    /// Build a board's QEMU image and run it in qemu-system-arm, its host UART on a local TCP
    /// port; QEMU starts the firmware when a client connects.
    Qemu {
        /// The board: stm32f4.
        board: String,
        /// TCP port of the host link on 127.0.0.1 (0: pick a free one).
        #[arg(long, default_value_t = 2324)]
        port: u16,
        /// Instead of running interactively, run the end-to-end test that `test` runs: boot,
        /// stream a G-code job (with a resend), upload and run a program with frames, and
        /// compare the final positions with the simulator's.
        #[arg(long)]
        check: bool,
    },
    /// Build every default firmware release image and print its flash and RAM use against
    /// the smallest chip it must fit, and each board crate's lines of code outside its pin
    /// maps against the 300-line budget (fails when an image does not fit or a board is over).
    Size,
    /// Check the crate graph's rules (the layers point one way; part of `test`).
    Graph,
}

/// Portable crates that must build for every firmware target.
const PORTABLE: &[&str] = &[
    "forja-hal-abstraction",
    "forja-protocol",
    "forja-motion",
    "forja-app",
    "forja-drivers",
];

/// The firmware targets of the boards.
const FIRMWARE_TARGETS: &[&str] = &[
    "thumbv7em-none-eabihf",
    "thumbv6m-none-eabi",
    "riscv32imc-unknown-none-elf",
];

/// Benchmarked crates.
const BENCHED: &[&str] = &["forja-protocol", "forja-motion"];

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.task {
        Task::Test => test(),
        Task::Sim { args } => sim(&args),
        Task::Fuzz {
            seconds,
            runs,
            target,
            workers,
            sanitizer,
        } => fuzz(&Campaign {
            length: runs.map_or(Length::Seconds(seconds), Length::Runs),
            only: target,
            workers,
            sanitizer,
        }),
        Task::Bench {
            host_only,
            target_only,
            args,
        } => (if target_only { Ok(()) } else { bench(&args) }).and_then(|()| {
            if host_only {
                Ok(())
            } else {
                bench::on_target()
            }
        }),
        Task::Build { board, variant } => firmware::build(&board, variant.as_deref()),
        Task::Flash { board, variant } => firmware::flash(&board, variant.as_deref()),
        Task::Qemu { board, port, check } => firmware::run_qemu(&board, port, check),
        Task::Size => firmware::size().and_then(|()| lines::report()),
        Task::Graph => graph::check(),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("xtask: {e}");
            ExitCode::FAILURE
        }
    }
}

/// The workspace root (the parent of this crate's directory).
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

/// A command, or a check run in this process, described by `what` when it fails.
struct Step {
    what: String,
    action: Action,
}

enum Action {
    Command(Command),
    Call(Box<dyn FnOnce() -> Result<(), String>>),
}

impl Step {
    fn cargo(what: impl Into<String>, args: &[&str]) -> Self {
        let mut cmd = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
        cmd.args(args).current_dir(root());
        Self::command(what.into(), cmd)
    }

    /// `cargo +<toolchain> …` through the rustup proxy: the `cargo` that runs xtask (`$CARGO`)
    /// is a toolchain's own binary and does not understand `+toolchain`.
    fn cargo_on(toolchain: &str, what: impl Into<String>, args: &[&str]) -> Self {
        let mut cmd = Command::new("cargo");
        cmd.arg(format!("+{toolchain}"))
            .args(args)
            .current_dir(root());
        Self::command(what.into(), cmd)
    }

    fn command(what: String, cmd: Command) -> Self {
        Self {
            what,
            action: Action::Command(cmd),
        }
    }

    fn call(what: String, check: impl FnOnce() -> Result<(), String> + 'static) -> Self {
        Self {
            what,
            action: Action::Call(Box::new(check)),
        }
    }

    fn run(self) -> Result<(), String> {
        eprintln!("\n==> {}", self.what);
        match self.action {
            Action::Command(mut cmd) => {
                let status = cmd
                    .status()
                    .map_err(|e| format!("{}: could not start: {e}", self.what))?;
                if status.success() {
                    Ok(())
                } else {
                    Err(format!("{} failed ({status})", self.what))
                }
            }
            Action::Call(check) => check().map_err(|e| format!("{}: {e}", self.what)),
        }
    }
}

fn run_all(steps: Vec<Step>) -> Result<(), String> {
    steps.into_iter().try_for_each(Step::run)
}

fn test() -> Result<(), String> {
    let mut steps = vec![
        Step::cargo("format check", &["fmt", "--all", "--check"]),
        Step::call("crate graph".to_string(), graph::check),
        Step::call("board lines".to_string(), lines::report),
        Step::cargo(
            "clippy (all targets, -D warnings)",
            &[
                "clippy",
                "--workspace",
                "--all-targets",
                "--",
                "-D",
                "warnings",
            ],
        ),
        // The TCP host link of the embassy-net boards and the SD card are features of the
        // drivers.
        Step::cargo(
            "clippy of the drivers' embassy-net link and SD card (-D warnings)",
            &[
                "clippy",
                "-p",
                "forja-drivers",
                "--features",
                "embassy-net,sd-card",
                "--all-targets",
                "--",
                "-D",
                "warnings",
            ],
        ),
        Step::cargo("host tests", &["test", "--workspace", "--all-targets"]),
        Step::cargo(
            "host tests of the drivers' embassy-net link and SD card",
            &[
                "test",
                "-p",
                "forja-drivers",
                "--features",
                "embassy-net,sd-card",
                "--lib",
                "--",
                "tcp",
                "sd_card",
            ],
        ),
        Step::cargo("doc tests", &["test", "--workspace", "--doc"]),
        rustdoc_step(),
    ];
    for target in FIRMWARE_TARGETS {
        let mut args = vec!["check", "--target", target];
        for krate in PORTABLE {
            args.extend(["-p", krate]);
        }
        steps.push(Step::cargo(format!("portable crates on {target}"), &args));
    }
    steps.extend(firmware::test_steps());
    run_all(steps)
}

/// The crates' documentation, built with every rustdoc warning an error (broken and private
/// links, bad HTML): xtask's own comments are its `--help` and left out.
fn rustdoc_step() -> Step {
    let mut cmd = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    cmd.args(["doc", "--no-deps", "--workspace", "--exclude", "xtask"])
        .env("RUSTDOCFLAGS", "-D warnings")
        .current_dir(root());
    Step::command("documentation (rustdoc -D warnings)".to_string(), cmd)
}

fn sim(args: &[String]) -> Result<(), String> {
    let mut all = vec!["run", "--quiet", "--release", "-p", "forja-simulator", "--"];
    all.extend(args.iter().map(String::as_str));
    Step::cargo("simulator", &all).run()
}

/// The fuzz targets, as listed in `fuzz/Cargo.toml`.
fn fuzz_targets() -> Result<Vec<String>, String> {
    let manifest = root().join("fuzz").join("Cargo.toml");
    let text = std::fs::read_to_string(&manifest)
        .map_err(|e| format!("cannot read {}: {e}", manifest.display()))?;
    let mut targets = Vec::new();
    let mut in_bin = false;
    for line in text.lines().map(str::trim) {
        if line.starts_with('[') {
            in_bin = line == "[[bin]]";
        } else if in_bin && let Some(rest) = line.strip_prefix("name") {
            let name = rest
                .trim_start()
                .trim_start_matches('=')
                .trim()
                .trim_matches('"');
            targets.push(name.to_string());
        }
    }
    if targets.is_empty() {
        return Err(format!("no [[bin]] targets in {}", manifest.display()));
    }
    Ok(targets)
}

fn ensure_cargo_tool(probe: &[&str], install: &[&str], what: &str) -> Result<(), String> {
    let present = Command::new("cargo")
        .args(probe)
        .current_dir(root())
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if present {
        return Ok(());
    }
    eprintln!("{what} is not installed; installing it (one time, a few minutes)");
    let mut args = vec!["install", "--locked"];
    args.extend(install);
    Step::cargo(format!("install {what}"), &args).run()
}

/// How long each fuzz target runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Length {
    /// Wall-clock seconds.
    Seconds(u64),
    /// Executions of the target, all workers together.
    Runs(u64),
}

/// A `cargo xtask fuzz` run.
#[derive(Debug)]
struct Campaign {
    length: Length,
    /// Only this target, or every one.
    only: Option<String>,
    /// Fuzzing processes per target.
    workers: u32,
    /// `cargo fuzz --sanitizer`.
    sanitizer: String,
}

/// Sanitizers `cargo fuzz` builds with.
const SANITIZERS: &[&str] = &["address", "leak", "memory", "thread", "none"];

/// What a fuzz target needs beyond the defaults: `cargo fuzz` build options, then libFuzzer
/// options.
///
/// `controller` runs the whole firmware on the simulator for every input, so its inputs are
/// capped at 80 bytes (40 operations, the length of its proptest's scripts), and it is built
/// without the instrumentation of every integer comparison, which makes an execution about
/// three times slower and helps little: its input is decoded by remainders, not compared.
fn fuzz_target_options(target: &str) -> (&'static [&'static str], &'static [&'static str]) {
    match target {
        "controller" => (&["--no-trace-compares"], &["-max_len=80"]),
        _ => (&[], &[]),
    }
}

fn fuzz(campaign: &Campaign) -> Result<(), String> {
    if !SANITIZERS.contains(&campaign.sanitizer.as_str()) {
        return Err(format!(
            "no sanitizer named {}; the sanitizers are: {}",
            campaign.sanitizer,
            SANITIZERS.join(", ")
        ));
    }
    ensure_cargo_tool(
        &["+nightly", "fuzz", "--version"],
        &["cargo-fuzz"],
        "cargo-fuzz",
    )?;
    let targets = fuzz_targets()?;
    let chosen: Vec<&String> = match &campaign.only {
        Some(t) => {
            let found: Vec<&String> = targets.iter().filter(|n| *n == t).collect();
            if found.is_empty() {
                return Err(format!(
                    "no fuzz target named {t}; the targets are: {}",
                    targets.join(", ")
                ));
            }
            found
        }
        None => targets.iter().collect(),
    };
    let (length, what) = match campaign.length {
        Length::Seconds(s) => (format!("-max_total_time={s}"), format!("{s} s")),
        Length::Runs(n) => (format!("-runs={n}"), format!("{n} executions")),
    };
    let fork = format!("-fork={}", campaign.workers);
    for target in chosen {
        let (build, options) = fuzz_target_options(target);
        let mut args = vec!["fuzz", "run", "--sanitizer", &campaign.sanitizer];
        args.extend(build);
        args.extend([target.as_str(), "--", &length, "-print_final_stats=1"]);
        args.extend(options);
        if campaign.workers > 1 {
            args.push(&fork);
        }
        Step::cargo_on(
            "nightly",
            format!(
                "fuzz {target} for {what} ({} worker{}, sanitizer {})",
                campaign.workers,
                if campaign.workers == 1 { "" } else { "s" },
                campaign.sanitizer
            ),
            &args,
        )
        .run()?;
    }
    Ok(())
}

fn bench(args: &[String]) -> Result<(), String> {
    let mut all = vec!["bench"];
    for krate in BENCHED {
        all.extend(["-p", krate]);
    }
    all.push("--");
    all.extend(args.iter().map(String::as_str));
    Step::cargo("benchmarks", &all).run()
}
