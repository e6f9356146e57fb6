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

/// Unicorn from PyPI (a manylinux wheel: nothing is compiled).
const UNICORN: &str = "unicorn==2.1.1";

/// The bench image, an example of the STM32F4 firmware crate.
const EXAMPLE: &str = "kernel_bench";

/// The clock the budgets are stated for (an STM32F405/F407).
const CORE_HZ: f64 = 168e6;

/// Most instructions per step event in the step interrupt.
const STEP_EVENT_BUDGET: u64 = 200;

/// Most instructions per planned 1 mm `G1` line (5,000 lines/s at 168 MHz with 10 % of the
/// core, rounded down).
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
        Step::call("Unicorn in target/bench-venv".to_string(), || {
            ensure_venv().map(drop)
        }),
    ])?;
    let python = ensure_venv()?;
    eprintln!("\n==> instruction count of {}", image.display());
    let counts = count(&python, &image)?;
    report(&counts, variant.feature)
}

/// The virtual environment's Python, with Unicorn; created and filled when missing.
fn ensure_venv() -> Result<PathBuf, String> {
    let venv = root().join("target").join("bench-venv");
    let python = venv.join("bin").join("python");
    let ready = Command::new(&python)
        .args(["-c", "import unicorn"])
        .output()
        .is_ok_and(|o| o.status.success());
    if ready {
        return Ok(python);
    }
    eprintln!("installing {UNICORN} into {}", venv.display());
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
            UNICORN,
        ])
        .status()
        .map_err(|e| format!("{}: {e}", python.display()))?;
    if status.success() {
        Ok(python)
    } else {
        Err(format!("pip install {UNICORN} failed"))
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

/// A rate at 168 MHz with one instruction per cycle, e.g. `672k/s`.
fn rate(per_unit: f64) -> String {
    format!("{:.0}k/s", CORE_HZ / per_unit / 1e3)
}

fn report(counts: &Counts, variant: &str) -> Result<(), String> {
    let marker = |phase: u32, name: &str| -> Result<Marker, String> {
        counts
            .markers
            .get(&(phase, name.to_string()))
            .copied()
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
    let mut over = Vec::new();
    println!(
        "\nMotion kernel on the Cortex-M4 (thumbv7em-none-eabihf, release profile, {variant} \
         build; Unicorn; {} instructions executed in all)",
        thousands(counts.total)
    );
    println!(
        "\n{:<42} {:>9} {:>19} {:>12} {:>8} {:>7} {:>13}",
        "step interrupt (StepGenerator::on_alarm)",
        "calls",
        "per call min/avg/max",
        "per step ev.",
        "budget",
        "ratio",
        "at 168 MHz"
    );
    for &(phase, what) in PHASES {
        let m = marker(phase, "bench_isr")?;
        let r = result(phase)?;
        let per_event = m.total as f64 / r.step_events as f64;
        let ratio = per_event / STEP_EVENT_BUDGET as f64;
        println!(
            "{what:<42} {:>9} {:>19} {per_event:>12.1} {STEP_EVENT_BUDGET:>8} {ratio:>7.2} {:>13}{}",
            thousands(m.calls),
            format!("{}/{:.0}/{}", m.min, m.total as f64 / m.calls as f64, m.max),
            rate(per_event),
            if ratio > 1.0 { "  OVER" } else { "" }
        );
        if ratio > 1.0 {
            over.push(format!(
                "step interrupt, {what}: {per_event:.1} instructions per step event \
                 (budget {STEP_EVENT_BUDGET})"
            ));
        }
    }
    let m = marker(3, "bench_line")?;
    let r = result(3)?;
    let per_line = m.total as f64 / r.lines as f64;
    let ratio = per_line / LINE_BUDGET as f64;
    println!(
        "\n{:<42} {:>9} {:>19} {:>12} {:>8} {:>7} {:>13}",
        "planning (Line::parse + Kernel::execute)",
        "calls",
        "per call min/avg/max",
        "per line",
        "budget",
        "ratio",
        "at 168 MHz"
    );
    println!(
        "{:<42} {:>9} {:>19} {per_line:>12.0} {:>8} {ratio:>7.2} {:>13}{}",
        PHASES[2].1,
        thousands(m.calls),
        format!("{}/{per_line:.0}/{}", thousands(m.min), thousands(m.max)),
        thousands(LINE_BUDGET),
        rate(per_line),
        if ratio > 1.0 { "  OVER" } else { "" }
    );
    if ratio > 1.0 {
        over.push(format!(
            "planning: {per_line:.0} instructions per 1 mm line (budget {LINE_BUDGET})"
        ));
    }
    println!(
        "\n{:<42} {:>9} {:>19} {:>12} {:>8} {:>7} {:>13}",
        "segment preparation (Kernel::poll)",
        "calls",
        "per call min/avg/max",
        "per step ev.",
        "+ isr",
        "",
        "at 168 MHz"
    );
    for &(phase, what) in PHASES {
        let m = marker(phase, "bench_prep")?;
        let isr = marker(phase, "bench_isr")?;
        let r = result(phase)?;
        let per_event = m.total as f64 / r.step_events as f64;
        let both = (m.total + isr.total) as f64 / r.step_events as f64;
        println!(
            "{what:<42} {:>9} {:>19} {per_event:>12.1} {both:>8.0} {:>7} {:>13}",
            thousands(m.calls),
            format!(
                "{}/{:.0}/{}",
                m.min,
                m.total as f64 / m.calls as f64,
                thousands(m.max)
            ),
            "",
            rate(both)
        );
    }
    println!(
        "\nper step event: all instructions of the calls during the phase divided by its step \
         events (rising edges, all axes), pulse-end and direction calls included; a call counts \
         from the measured function's first instruction to its return, callees included. \
         \"at 168 MHz\": step events per second if every instruction took one cycle and the \
         core did nothing else (flash wait states and multi-cycle instructions make cycles \
         more); for segment preparation, with the interrupt's instructions added (\"+ isr\")."
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
