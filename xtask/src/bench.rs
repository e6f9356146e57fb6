//! `cargo xtask bench`, on the target: instruction counts of the motion kernel as Cortex-M4,
//! Cortex-M0+ and RISC-V (the ESP32-C3's core) machine code.
//!
//! One bench program (`boards/stm32f4/examples/kernel_bench/program.rs`) is built into three
//! images: the STM32F4 crate's `kernel_bench` example for `thumbv7em-none-eabihf` with the
//! firmware's release profile, for the board's hardware variant; the RP2040 crate's for
//! `thumbv6m-none-eabi` (`boards/rp2040/examples/kernel_bench.rs`); and `bench/riscv32`, a
//! crate of its own with no chip HAL, for `riscv32imc-unknown-none-elf` with the ESP32
//! firmware's release profile. `xtask/scripts/count_insns.py` runs each in the Unicorn
//! emulator (a Cortex-M4 with FPU; a Cortex-M0, whose ARMv6-M instruction set is the M0+'s; a
//! 32-bit RISC-V core) and counts the instructions executed inside the image's marker
//! functions; Unicorn is installed with pip into a virtual environment in `target/bench-venv`
//! (Python 3 with `venv` is needed). The count depends only on the image, never on the
//! machine's load: two runs give the same figures. The Cortex-M4 and RISC-V figures are checked
//! against the kernel's budgets (`docs/performance.md`); the Cortex-M0+ figures are reported
//! beside the same budgets, which they are not held to.
//!
//! The emulator has neither the RP2040's boot ROM nor its SIO, so the M0+ image is built with
//! `rp2040-hal`'s `disable-intrinsics`: floating point and integer division run as the
//! compiler's software routines, where the firmware calls the boot ROM's float routines and
//! the SIO's hardware divider. The step interrupt is integer-only and calls neither; the
//! planning and segment preparation figures count the compiler's routines where the firmware
//! runs the ROM's and the divider.
//!
//! No emulator of the ESP32-C3 is at hand (Unicorn has a RISC-V core but none of the chip's
//! peripherals, ROM or boot chain), so the RISC-V image is the program alone: a start-up of a
//! few instructions and one RAM region (`bench/riscv32/link.x`), no `esp-hal`. RV32IMC has no
//! floating-point unit: single and double precision run as the compiler's software routines
//! (in the ESP32-C3 firmware too); integer multiplication and division are the M extension's
//! instructions.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::firmware;
use crate::{Step, root};

/// The Unicorn release from PyPI (a manylinux wheel: nothing is compiled).
const UNICORN_VERSION: &str = "2.1.1";

/// The bench image: an example of each firmware crate that runs it, the binary of a bench crate.
const EXAMPLE: &str = "kernel_bench";

/// Where a core's bench image is built.
enum Image {
    /// The [`EXAMPLE`] of a firmware board's crate, for its first hardware variant.
    Board {
        /// The firmware board.
        board: &'static str,
        /// Features added to the variant's for the bench build.
        features: &'static [&'static str],
    },
    /// The [`EXAMPLE`] binary of a bench crate with no chip HAL, excluded from the root
    /// workspace.
    Crate {
        /// The crate's directory, from the workspace root; its target directory is
        /// `target/firmware/<name>`.
        dir: &'static str,
        /// The name of its target directory, and in the report.
        name: &'static str,
        /// The target it is built for.
        target: &'static str,
    },
}

/// A core the bench image is counted on.
struct Core {
    /// The core's name, for the report.
    name: &'static str,
    /// Where its image is built.
    image: Image,
    /// The counter's `--core`.
    counter: &'static str,
    /// The core's clock on that board, for the "steps per second" column.
    clock_hz: f64,
    /// Whether the budgets hold here (a figure over one fails the bench).
    budgets: bool,
    /// Whether planning is held to [`LINE_TARGET`] here; elsewhere the target is reported and
    /// [`LINE_CEILING`] held.
    line_target_held: bool,
    /// The bench moves ([`PHASES`]) whose whole kernel is held to [`WHOLE_KERNEL_TARGET`]
    /// here (those where it is met); on the others the target is reported.
    whole_target_held: &'static [u32],
    /// Printed under the core's tables.
    note: &'static str,
}

impl Core {
    /// The heading of the rate column: "at 168 MHz".
    fn at_clock(&self) -> String {
        format!("at {} MHz", (self.clock_hz / 1e6).round())
    }
}

/// The cores, in report order. The budgets are stated for the first, at its clock (an
/// STM32F405/F407 at 168 MHz), and held on the cores of the boards with budgets of their own
/// to meet (the STM32F4's and the ESP32-C3's); the RP2040's Cortex-M0+ is reported beside
/// them.
const CORES: &[Core] = &[
    Core {
        name: "Cortex-M4",
        image: Image::Board {
            board: "stm32f4",
            features: &[],
        },
        counter: "m4",
        clock_hz: 168e6,
        budgets: true,
        line_target_held: true,
        whole_target_held: &[1, 2, 3],
        note: "",
    },
    Core {
        name: "Cortex-M0+",
        image: Image::Board {
            board: "rp2040",
            features: &["rp2040-hal/disable-intrinsics"],
        },
        counter: "m0plus",
        clock_hz: 125e6,
        budgets: false,
        line_target_held: false,
        whole_target_held: &[],
        note: "The budgets are the Cortex-M4's, shown for comparison. The image is built with \
               rp2040-hal's\ndisable-intrinsics (the emulator has no boot ROM and no SIO): \
               floating point and division are the\ncompiler's software routines, where the \
               firmware calls the ROM's float routines and the SIO's\ndivider; the step \
               interrupt calls neither.",
    },
    Core {
        name: "RISC-V",
        image: Image::Crate {
            dir: "bench/riscv32",
            name: "bench-riscv32",
            target: "riscv32imc-unknown-none-elf",
        },
        counter: "riscv32",
        clock_hz: 160e6,
        budgets: true,
        line_target_held: true,
        whole_target_held: &[1, 2, 3],
        note: "The budgets are the Cortex-M4's, held here too; the rate is at the \
               ESP32-C3's 160 MHz. The image\nhas no chip HAL (no ESP32-C3 emulator): the \
               program alone, in one RAM region, with the ESP32\nfirmware's release profile. \
               RV32IMC has no FPU: floating point is the compiler's software routines\n(the \
               firmware's too); division is the M extension's instruction.",
    },
];

/// Most instructions per step event in the step interrupt.
const STEP_EVENT_BUDGET: u64 = 200;

/// The target for the whole kernel, interrupt and preparation, per step event (670k steps/s
/// at 168 MHz): held on the moves where the kernel meets it ([`Core::whole_target_held`]),
/// reported beside the figures on the others.
const WHOLE_KERNEL_TARGET: u64 = 250;

/// Most instructions per planned 1 mm `G1` line (28,000 lines/s on a 168 MHz core), held on
/// the cores whose [`Core::line_target_held`] is set and reported on the others.
const LINE_TARGET: u64 = 6_000;

/// Most instructions per planned 1 mm `G1` line on a core not held to [`LINE_TARGET`] yet
/// (over 5,000 lines/s on a 168 MHz core).
const LINE_CEILING: u64 = 30_000;

/// Most instructions of one `Kernel::poll` call while the machine moves: the link, the heaters
/// and the reports wait behind it (about 120 µs on a 168 MHz core).
const POLL_BUDGET: u64 = 20_000;

/// The phases of the bench image, in its order (see the example's documentation).
const PHASES: &[(u32, &str)] = &[
    (1, "1 axis, G1 X200 (16,000 steps)"),
    (2, "3 axes, G1 X300 Y80 Z10 (18,400 steps)"),
    (3, "1,000 lines of 1 mm G1 (2 axes)"),
];

/// One measured function within one phase: calls, and instructions in total and per call.
#[derive(Debug, Clone, Copy, Default)]
struct Marker {
    calls: u64,
    total: u64,
    min: u64,
    max: u64,
}

/// What one phase did: its step events (rising edges, all axes) and lines taken.
#[derive(Debug, Clone, Copy, Default)]
struct PhaseResult {
    step_events: u64,
    lines: u64,
}

/// The counter's records.
#[derive(Debug, Default)]
struct Counts {
    markers: BTreeMap<(u32, String), Marker>,
    results: BTreeMap<u32, PhaseResult>,
    total: u64,
}

/// `cargo xtask bench`'s on-target part: for each core, build the image, count and print;
/// then check the budgets where they hold.
pub fn on_target() -> Result<(), String> {
    let mut over = Vec::new();
    for core in CORES {
        over.extend(on_core(core)?);
    }
    if over.is_empty() {
        Ok(())
    } else {
        Err(format!("over budget: {}", over.join("; ")))
    }
}

/// Build the image for `core`, count it and print its tables; the figures over their budget
/// where the budgets hold.
fn on_core(core: &Core) -> Result<Vec<String>, String> {
    let (build, command) = build(&core.image)?;
    let target = build.target;
    crate::run_all(vec![
        Step::call(format!("Rust target {target}"), move || {
            firmware::ensure_target(target)
        }),
        Step::command(
            format!(
                "{} bench image ({EXAMPLE}, {}, release profile)",
                build.name, build.features
            ),
            command,
        ),
        Step::call(
            format!("Unicorn {UNICORN_VERSION} in target/bench-venv"),
            ensure_venv,
        ),
    ])?;
    eprintln!(
        "\n==> instruction count of {} (about a minute)",
        build.image.display()
    );
    let counts = count(&venv_python(), &build.image, core.counter)?;
    report(&counts, core, &build)
}

/// How a bench image is built, and where it lands.
struct Build {
    /// The board or bench crate, for the report.
    name: &'static str,
    /// The features of the build, or what stands for them, for the report.
    features: String,
    target: &'static str,
    image: PathBuf,
}

/// The build of `image`, with the release profile, in `target/firmware/<name>`, and the
/// command that makes it.
fn build(image: &Image) -> Result<(Build, Command), String> {
    let mut command = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    command.args(["build", "--release"]);
    let (name, dir, target, features) = match *image {
        Image::Board { board, features } => {
            let board = firmware::board(board)?;
            let variant = board.variant(None, |v| v.flasher.is_some())?;
            let mut all = vec![variant.feature];
            all.extend(features);
            let all = all.join(",");
            command.args(["--example", EXAMPLE]).args([
                "--no-default-features",
                "--features",
                &all,
            ]);
            (board.name, board.dir, variant.target, all)
        }
        Image::Crate { dir, name, target } => {
            command.args(["--bin", EXAMPLE]);
            (name, dir, target, "no chip HAL".to_string())
        }
    };
    let target_dir = root().join("target").join("firmware").join(name);
    let mut path = target_dir.join(target).join("release");
    if matches!(image, Image::Board { .. }) {
        path.push("examples");
    }
    command
        .args(["--target", target])
        .current_dir(root().join(dir))
        .env("CARGO_TARGET_DIR", &target_dir);
    let build = Build {
        name,
        features,
        target,
        image: path.join(EXAMPLE),
    };
    Ok((build, command))
}

/// The virtual environment's Python.
fn venv_python() -> PathBuf {
    root()
        .join("target")
        .join("bench-venv")
        .join("bin")
        .join("python")
}

/// Create the virtual environment and install Unicorn into it, unless it has the right one.
fn ensure_venv() -> Result<(), String> {
    let venv = root().join("target").join("bench-venv");
    let python = venv_python();
    let check = format!(
        "import importlib.metadata as m, sys; sys.exit(m.version('unicorn') != '{UNICORN_VERSION}')"
    );
    let ready = Command::new(&python)
        .args(["-c", &check])
        .output()
        .is_ok_and(|o| o.status.success());
    if ready {
        return Ok(());
    }
    let unicorn = format!("unicorn=={UNICORN_VERSION}");
    eprintln!("installing {unicorn} into {}", venv.display());
    let status = Command::new("python3")
        .args(["-m", "venv"])
        .arg(&venv)
        .status()
        .map_err(|e| format!("python3: {e} (Python 3 with venv is needed)"))?;
    if !status.success() {
        return Err(format!(
            "python3 -m venv {} failed (Debian/Ubuntu: apt-get install python3-venv)",
            venv.display()
        ));
    }
    let status = Command::new(&python)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            &unicorn,
        ])
        .status()
        .map_err(|e| format!("{}: {e}", python.display()))?;
    if status.success() {
        Ok(())
    } else {
        Err(format!("pip install {unicorn} failed"))
    }
}

/// Run the counter on `image` and read its records.
fn count(python: &Path, image: &Path, core: &str) -> Result<Counts, String> {
    let script = root().join("xtask").join("scripts").join("count_insns.py");
    let out = Command::new(python)
        .arg(&script)
        .arg(image)
        .arg(format!("--core={core}"))
        .output()
        .map_err(|e| format!("{}: {e}", script.display()))?;
    eprint!("{}", String::from_utf8_lossy(&out.stderr));
    if !out.status.success() {
        return Err(format!("{} failed ({})", script.display(), out.status));
    }
    parse(&String::from_utf8_lossy(&out.stdout))
}

fn parse(text: &str) -> Result<Counts, String> {
    let mut counts = Counts::default();
    for line in text.lines() {
        let fields: Vec<&str> = line.split_whitespace().collect();
        let num = |i: usize| -> Result<u64, String> {
            fields
                .get(i)
                .and_then(|f| f.parse().ok())
                .ok_or_else(|| format!("bad record from the counter: {line:?}"))
        };
        match fields.first() {
            Some(&"marker") => {
                let name = fields.get(2).copied().unwrap_or_default().to_string();
                let phase = u32::try_from(num(1)?).map_err(|e| e.to_string())?;
                let marker = Marker {
                    calls: num(3)?,
                    total: num(4)?,
                    min: num(5)?,
                    max: num(6)?,
                };
                counts.markers.insert((phase, name), marker);
            }
            Some(&"result") => {
                let phase = u32::try_from(num(1)?).map_err(|e| e.to_string())?;
                let result = PhaseResult {
                    step_events: num(2)?,
                    lines: num(3)?,
                };
                counts.results.insert(phase, result);
            }
            Some(&"total") => counts.total = num(1)?,
            _ => return Err(format!("bad record from the counter: {line:?}")),
        }
    }
    Ok(counts)
}

/// `n` with thousands separators.
fn thousands(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// One row of a table: a measured function in one phase.
struct Row<'a> {
    what: &'a str,
    calls: &'a Marker,
    /// Instructions per unit (step event or line).
    per_unit: f64,
    /// Instructions per unit that the "at <clock>" rate is computed from.
    for_rate: f64,
    budget: Option<u64>,
    /// Whether `budget` is held (a figure over it fails the bench), or a target reported.
    held: bool,
    /// Most instructions of one call, where that is held.
    call_budget: Option<u64>,
}

/// Print a table of `rows` under `title`, in instructions per `unit` (a column heading, and
/// `unit_name` in messages), with rates at `core`'s clock; returns the rows over their budget
/// where `core`'s budgets hold.
fn table(core: &Core, title: &str, unit: &str, unit_name: &str, rows: &[Row<'_>]) -> Vec<String> {
    let at_clock = core.at_clock();
    println!(
        "\n{title:<44} {:>9} {:>22} {:>10} {:>8} {:>6} {at_clock:>11}",
        "calls", "per call min/avg/max", unit, "budget", "ratio"
    );
    let mut over = Vec::new();
    for r in rows {
        let m = r.calls;
        let per_call = format!(
            "{}/{}/{}",
            thousands(m.min),
            thousands((m.total as f64 / m.calls as f64).round() as u64),
            thousands(m.max)
        );
        let (budget, ratio) = match r.budget {
            Some(b) => (thousands(b), format!("{:.2}", r.per_unit / b as f64)),
            None => ("-".to_string(), "-".to_string()),
        };
        let call_over = r.call_budget.filter(|&b| m.max > b);
        let over_unit = r.budget.is_some_and(|b| r.per_unit > b as f64);
        // A target not held yet is only reported.
        let missed_target = over_unit && !r.held && call_over.is_none();
        let exceeded = !missed_target && (over_unit || call_over.is_some());
        println!(
            "{:<44} {:>9} {per_call:>22} {:>10} {budget:>8} {ratio:>6} {:>9}k/s{}",
            r.what,
            thousands(m.calls),
            format_per_unit(r.per_unit),
            (core.clock_hz / r.for_rate / 1e3).round(),
            match (missed_target, exceeded, core.budgets) {
                (true, _, _) => "  (target: not met)",
                (false, false, _) => "",
                (false, true, true) => "  OVER",
                (false, true, false) => "  (over; not held here)",
            }
        );
        if exceeded && core.budgets {
            over.push(match call_over {
                Some(b) => format!(
                    "{title}, {}: a call of {} instructions (budget {})",
                    r.what,
                    thousands(m.max),
                    thousands(b)
                ),
                None => format!(
                    "{title}, {}: {} instructions per {unit_name} (budget {budget})",
                    r.what,
                    format_per_unit(r.per_unit)
                ),
            });
        }
    }
    over
}

/// Instructions per unit: one decimal below 1,000, whole numbers above.
fn format_per_unit(x: f64) -> String {
    if x < 1000.0 {
        format!("{x:.1}")
    } else {
        thousands(x.round() as u64)
    }
}

fn report(counts: &Counts, core: &Core, build: &Build) -> Result<Vec<String>, String> {
    let marker = |phase: u32, name: &str| -> Result<&Marker, String> {
        counts
            .markers
            .get(&(phase, name.to_string()))
            .filter(|m| m.calls > 0)
            .ok_or_else(|| format!("the counter saw no call of {name} in phase {phase}"))
    };
    let result = |phase: u32| -> Result<PhaseResult, String> {
        counts
            .results
            .get(&phase)
            .copied()
            .filter(|r| r.step_events > 0 && r.lines > 0)
            .ok_or_else(|| format!("phase {phase} reported no step events or no lines"))
    };
    println!(
        "\nMotion kernel as {} machine code: {}, release profile, {} build ({}),\n\
         {} instructions emulated in all.",
        core.name,
        build.target,
        build.name,
        build.features,
        thousands(counts.total)
    );
    let mut isr = Vec::new();
    let mut prep = Vec::new();
    let mut whole = Vec::new();
    for &(phase, what) in PHASES {
        let steps = result(phase)?.step_events as f64;
        let i = marker(phase, "bench_isr")?;
        let p = marker(phase, "bench_prep")?;
        isr.push(Row {
            what,
            calls: i,
            per_unit: i.total as f64 / steps,
            for_rate: i.total as f64 / steps,
            budget: Some(STEP_EVENT_BUDGET),
            held: true,
            call_budget: None,
        });
        prep.push(Row {
            what,
            calls: p,
            per_unit: p.total as f64 / steps,
            for_rate: (p.total + i.total) as f64 / steps,
            budget: None,
            held: true,
            call_budget: Some(POLL_BUDGET),
        });
        whole.push(Row {
            what,
            calls: p,
            per_unit: (p.total + i.total) as f64 / steps,
            for_rate: (p.total + i.total) as f64 / steps,
            budget: Some(WHOLE_KERNEL_TARGET),
            held: core.whole_target_held.contains(&phase),
            call_budget: None,
        });
    }
    let line = marker(3, "bench_line")?;
    let per_line = line.total as f64 / result(3)?.lines as f64;
    let mut over = table(
        core,
        "step interrupt: StepGenerator::on_alarm",
        "/step ev.",
        "step event",
        &isr,
    );
    over.extend(table(
        core,
        "planning: Line::parse_in + Kernel::execute",
        "/line",
        "line",
        &[Row {
            what: PHASES[2].1,
            calls: line,
            per_unit: per_line,
            for_rate: per_line,
            budget: Some(LINE_TARGET),
            held: core.line_target_held,
            call_budget: None,
        }],
    ));
    if core.budgets && per_line > LINE_CEILING as f64 {
        over.push(format!(
            "planning: {} instructions per line (ceiling {})",
            format_per_unit(per_line),
            thousands(LINE_CEILING)
        ));
    }
    over.extend(table(
        core,
        "segment preparation: Kernel::poll",
        "/step ev.",
        "step event",
        &prep,
    ));
    over.extend(table(
        core,
        "whole kernel: interrupt + preparation",
        "/step ev.",
        "step event",
        &whole,
    ));
    println!(
        "\nPer step event: the instructions of every call during the phase divided by its step \
         events\n(rising edges, all axes), pulse-end and direction calls included. A call counts \
         from the\nmeasured function's first instruction to its return, callees included. \
         \"{at_clock}\": steps\n(or lines) per second if each instruction took one cycle and \
         the core did nothing else;\nfor segment preparation, the step interrupt's instructions \
         added. Flash wait states and\nmulti-cycle instructions make the cycles more than the \
         instructions. Segment preparation's budget\nis for one call: {} instructions at most \
         (the largest call is the \"max\" column).\nThe whole kernel's \
         figure is against its target ({} instructions per step event), held on the moves\nwhere \
         it is met and reported on the others; its calls are the preparation's. Planning's target ({} instructions per line) is held where\n\
         it is met, and reported elsewhere beside a ceiling of {} that is held.",
        thousands(POLL_BUDGET),
        WHOLE_KERNEL_TARGET,
        thousands(LINE_TARGET),
        thousands(LINE_CEILING),
        at_clock = core.at_clock(),
    );
    if !core.note.is_empty() {
        println!("{}", core.note);
    }
    Ok(over)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_counter_records() {
        let c = parse(
            "marker 1 bench_isr 3 300 90 120\nresult 1 2 1\nmarker 3 bench_line 2 40 20 20\n\
             total 1000\n",
        )
        .expect("parses");
        let m = c.markers[&(1, "bench_isr".to_string())];
        assert_eq!((m.calls, m.total, m.min, m.max), (3, 300, 90, 120));
        assert_eq!(c.results[&1].step_events, 2);
        assert_eq!(c.total, 1000);
        assert!(parse("marker x").is_err());
        assert!(parse("something else").is_err());
    }

    #[test]
    fn every_image_is_built_by_a_board_that_runs_on_hardware_or_a_bench_crate() {
        for core in CORES {
            match core.image {
                Image::Board { board, .. } => {
                    let board = firmware::board(board).expect("a firmware board");
                    assert!(board.variant(None, |v| v.flasher.is_some()).is_ok());
                }
                Image::Crate { dir, .. } => {
                    assert!(root().join(dir).join("Cargo.toml").is_file(), "{dir}");
                }
            }
        }
        assert!(
            CORES[0].budgets,
            "the budgets are stated for the first core"
        );
    }

    #[test]
    fn groups_thousands() {
        assert_eq!(thousands(0), "0");
        assert_eq!(thousands(999), "999");
        assert_eq!(thousands(1000), "1,000");
        assert_eq!(thousands(1_234_567), "1,234,567");
    }
}
