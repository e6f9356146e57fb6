//! `cargo xtask bench`, on the target: instruction counts of the motion kernel as Cortex-M4
//! machine code.
//!
//! The STM32F4 crate's `kernel_bench` example (`boards/stm32f4/examples/kernel_bench.rs`) is
//! built for `thumbv7em-none-eabihf` with the firmware's release profile, for the board's
//! hardware variant. `xtask/scripts/count_insns.py` runs it in the Unicorn emulator (a
//! Cortex-M4 with FPU) and counts the instructions executed inside the image's marker
//! functions; Unicorn is installed with pip into a virtual environment in
//! `target/bench-venv` (Python 3 with `venv` is needed). The count depends only on the
//! image, never on the machine's load: two runs give the same figures. The figures are
//! checked against the kernel's budgets (`docs/performance.md`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::firmware;
use crate::{Step, root};

/// The Unicorn release from PyPI (a manylinux wheel: nothing is compiled).
const UNICORN_VERSION: &str = "2.1.1";

/// The bench image, an example of the STM32F4 firmware crate.
const EXAMPLE: &str = "kernel_bench";

/// The clock the budgets are stated for (an STM32F405/F407).
const CORE_HZ: f64 = 168e6;

/// Most instructions per step event in the step interrupt.
const STEP_EVENT_BUDGET: u64 = 200;

/// Most instructions per planned 1 mm `G1` line (over 5,000 lines/s on a 168 MHz core).
const LINE_BUDGET: u64 = 30_000;

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

/// `cargo xtask bench`'s on-target part: build the image, count, print, check the budgets.
pub fn on_target() -> Result<(), String> {
    let board = firmware::board("stm32f4")?;
    let variant = board.variant(None, |v| v.flasher.is_some())?;
    let target_dir = root().join("target").join("firmware").join(board.name);
    let image = target_dir
        .join(variant.target)
        .join("release")
        .join("examples")
        .join(EXAMPLE);
    let mut build = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    build
        .args(["build", "--release", "--example", EXAMPLE])
        .args(["--target", variant.target])
        .args(["--no-default-features", "--features", variant.feature])
        .current_dir(root().join(board.dir))
        .env("CARGO_TARGET_DIR", &target_dir);
    crate::run_all(vec![
        Step::command(
            format!(
                "{} bench image ({EXAMPLE}, {}, release profile)",
                board.name, variant.feature
            ),
            build,
        ),
        Step::call(
            format!("Unicorn {UNICORN_VERSION} in target/bench-venv"),
            ensure_venv,
        ),
    ])?;
    eprintln!(
        "\n==> instruction count of {} (about a minute)",
        image.display()
    );
    let counts = count(&venv_python(), &image)?;
    report(&counts, variant.feature)
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
fn count(python: &Path, image: &Path) -> Result<Counts, String> {
    let script = root().join("xtask").join("scripts").join("count_insns.py");
    let out = Command::new(python)
        .arg(&script)
        .arg(image)
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
    /// Instructions per unit that the "at 168 MHz" rate is computed from.
    for_rate: f64,
    budget: Option<u64>,
}

/// Print a table of `rows` under `title`, in instructions per `unit` (a column heading, and
/// `unit_name` in messages); returns the rows over their budget.
fn table(title: &str, unit: &str, unit_name: &str, rows: &[Row<'_>]) -> Vec<String> {
    println!(
        "\n{title:<44} {:>9} {:>22} {:>10} {:>8} {:>6} {:>11}",
        "calls", "per call min/avg/max", unit, "budget", "ratio", "at 168 MHz"
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
        let exceeded = r.budget.is_some_and(|b| r.per_unit > b as f64);
        println!(
            "{:<44} {:>9} {per_call:>22} {:>10} {budget:>8} {ratio:>6} {:>9}k/s{}",
            r.what,
            thousands(m.calls),
            format_per_unit(r.per_unit),
            (CORE_HZ / r.for_rate / 1e3).round(),
            if exceeded { "  OVER" } else { "" }
        );
        if exceeded {
            over.push(format!(
                "{title}, {}: {} instructions per {unit_name} (budget {budget})",
                r.what,
                format_per_unit(r.per_unit)
            ));
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

fn report(counts: &Counts, variant: &str) -> Result<(), String> {
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
        "\nMotion kernel as Cortex-M4 machine code: thumbv7em-none-eabihf, release profile, \
         {variant} build,\n{} instructions emulated in all.",
        thousands(counts.total)
    );
    let mut isr = Vec::new();
    let mut prep = Vec::new();
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
        });
        prep.push(Row {
            what,
            calls: p,
            per_unit: p.total as f64 / steps,
            for_rate: (p.total + i.total) as f64 / steps,
            budget: None,
        });
    }
    let line = marker(3, "bench_line")?;
    let per_line = line.total as f64 / result(3)?.lines as f64;
    let mut over = table(
        "step interrupt: StepGenerator::on_alarm",
        "/step ev.",
        "step event",
        &isr,
    );
    over.extend(table(
        "planning: Line::parse + Kernel::execute",
        "/line",
        "line",
        &[Row {
            what: PHASES[2].1,
            calls: line,
            per_unit: per_line,
            for_rate: per_line,
            budget: Some(LINE_BUDGET),
        }],
    ));
    over.extend(table(
        "segment preparation: Kernel::poll",
        "/step ev.",
        "step event",
        &prep,
    ));
    println!(
        "\nPer step event: the instructions of every call during the phase divided by its step \
         events\n(rising edges, all axes), pulse-end and direction calls included. A call counts \
         from the\nmeasured function's first instruction to its return, callees included. \
         \"at 168 MHz\": steps\n(or lines) per second if each instruction took one cycle and \
         the core did nothing else;\nfor segment preparation, the step interrupt's instructions \
         added. Flash wait states and\nmulti-cycle instructions make the cycles more than the \
         instructions."
    );
    if over.is_empty() {
        Ok(())
    } else {
        Err(format!("over budget: {}", over.join("; ")))
    }
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
    fn groups_thousands() {
        assert_eq!(thousands(0), "0");
        assert_eq!(thousands(999), "999");
        assert_eq!(thousands(1000), "1,000");
        assert_eq!(thousands(1_234_567), "1,234,567");
    }
}
