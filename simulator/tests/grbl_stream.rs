//! Streaming in the grbl dialect with character counting (`forja-sim --grbl`): a long program
//! runs through the firmware with every line answered once and in order, the bytes in flight
//! never above the receive buffer the firmware reports (`Bf:`), and `?` answered at once while
//! that buffer is full.

mod common;

use std::fmt::Write as _;
use std::path::PathBuf;

use common::sim;

/// The work offset the runs set before the job (`G54`), machine mm.
const OFFSET: [f64; 3] = [50.0, 50.0, 20.0];

/// The `--before` lines that set it, as an operator touching off would.
const BEFORE: [&str; 2] = ["G10 L2 P1 X50 Y50 Z20", "G28.1"];

/// A generated program: its text, how many of its lines are G-code (not blank, not only a
/// comment), and where it ends, work mm.
struct Program {
    text: String,
    code_lines: usize,
    end: [f64; 3],
}

/// A writer of program lines that numbers every tenth G-code line (`N10`, `N20`, …) and keeps
/// the position.
struct Writer {
    lines: Vec<String>,
    code_lines: usize,
    at: [f64; 3],
}

impl Writer {
    fn comment(&mut self, text: &str) {
        self.lines.push(text.to_string());
    }

    /// A G-code line; `to` is where it leaves the tool (work mm), `None` for no motion.
    fn code(&mut self, text: String, to: Option<[f64; 3]>) {
        self.code_lines += 1;
        let mut line = if self.code_lines.is_multiple_of(10) {
            format!("N{} {text}", self.code_lines)
        } else {
            text
        };
        // Comments of both kinds and stray blanks, as CAM posts and people leave them.
        match self.code_lines % 13 {
            0 => line.push_str(" ; next segment"),
            5 => line = line.replacen(' ', " (cut) ", 1),
            9 => line = format!("  {line}\t"),
            _ => {}
        }
        self.lines.push(line);
        if let Some(to) = to {
            self.at = to;
        }
    }
}

/// A square zig-zag of `total` source lines within work X 0..200, Y 0..190 (machine 50..250
/// after [`OFFSET`]): rows of short `G1` moves of 1 to 3 mm at F3000 joined by half-circle
/// arcs (`G2`/`G3`), a tool change (`M6`) half-way, comments and blank lines among them, and
/// a new pass from the corner whenever the rows reach the top.
fn zigzag(total: usize) -> Program {
    const SEGMENTS_MM: [f64; 5] = [2.0, 1.5, 2.5, 3.0, 1.0];
    const FOOTER: usize = 3;
    let mut w = Writer {
        lines: Vec::new(),
        code_lines: 0,
        at: [0.0; 3],
    };
    w.comment("(forja grbl streaming test: a square zig-zag in G54)");
    w.comment("; short moves and arcs at realistic feeds");
    w.comment("");
    w.code("G21 G90 G17 G54".into(), None);
    w.code("G0 Z5".into(), Some([0.0, 0.0, 5.0]));
    w.code("G0 X0 Y0".into(), Some([0.0, 0.0, 5.0]));
    w.code("M3 S12000".into(), None);
    w.code("G1 Z-1 F300".into(), Some([0.0, 0.0, -1.0]));
    w.code("F3000".into(), None);
    let mut row = 0u32;
    let mut segment = 0;
    let mut tool_changed = false;
    while w.lines.len() < total - FOOTER {
        let [x, y, z] = w.at;
        let forward = row.is_multiple_of(2);
        let row_end = if forward { 200.0 } else { 0.0 };
        if x == row_end {
            // The row is done: the next one, up by 2 mm, through a half circle outside it.
            if y + 2.0 > 190.0 {
                w.comment("(back to the corner for another pass)");
                w.code("G0 Z5".into(), Some([x, y, 5.0]));
                w.code("G0 X0 Y0".into(), Some([0.0, 0.0, 5.0]));
                w.code("G1 Z-1 F300".into(), Some([0.0, 0.0, -1.0]));
                w.code("F3000".into(), None);
                row = 0;
                continue;
            }
            if !tool_changed && w.lines.len() > total / 2 {
                tool_changed = true;
                w.comment("");
                w.comment("(tool change: 3 mm end mill)");
                w.code("G0 Z5".into(), Some([x, y, 5.0]));
                w.code("M5".into(), None);
                w.code("M6 T2".into(), None);
                w.code("M3 S10000".into(), None);
                w.code("G1 Z-1 F300".into(), Some([x, y, -1.0]));
                w.code("F3000".into(), None);
            }
            let arc = if forward { "G3" } else { "G2" };
            w.code(
                format!("{arc} X{x:.3} Y{:.3} I0 J1", y + 2.0),
                Some([x, y + 2.0, z]),
            );
            row += 1;
            if w.lines.len().is_multiple_of(50) {
                w.comment("");
            }
            w.comment(&format!("(row {row})"));
            continue;
        }
        let step = SEGMENTS_MM[segment % SEGMENTS_MM.len()];
        segment += 1;
        let next_x = if forward {
            (x + step).min(row_end)
        } else {
            (x - step).max(row_end)
        };
        w.code(format!("G1 X{next_x:.3} Y{y:.3}"), Some([next_x, y, z]));
        if w.lines.len().is_multiple_of(97) {
            w.comment("");
        }
    }
    let [x, y, _] = w.at;
    w.code("G0 Z5".into(), Some([x, y, 5.0]));
    w.code("M5".into(), None);
    w.code("M30".into(), None);
    assert_eq!(w.lines.len(), total);
    assert!(tool_changed);
    let mut text = String::new();
    for line in &w.lines {
        writeln!(text, "{line}").unwrap();
    }
    Program {
        text,
        code_lines: w.code_lines,
        end: w.at,
    }
}

fn temp_path(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("forja-grbl-stream-{}-{name}", std::process::id()))
}

/// Run `forja-sim --machine builtin:default --grbl --before … --job <text>`; its summary.
fn run_grbl(name: &str, text: &str) -> String {
    let path = temp_path(name);
    std::fs::write(&path, text).unwrap();
    let mut command = sim();
    command.args(["--machine", "builtin:default", "--grbl"]);
    for line in BEFORE {
        command.args(["--before", line]);
    }
    let out = command.arg("--job").arg(&path).output().unwrap();
    std::fs::remove_file(&path).unwrap();
    let summary = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{summary}");
    // Shown with `--nocapture`: the figures of the run.
    println!("{summary}");
    summary
}

/// The number right after `label` in `text` (`refused 0`, `latency 1.000`).
fn number_after(text: &str, label: &str) -> f64 {
    let at = text
        .find(label)
        .unwrap_or_else(|| panic!("no `{label}` in:\n{text}"))
        + label.len();
    let digits: String = text[at..]
        .trim_start()
        .chars()
        .take_while(|c| c.is_ascii_digit() || *c == '.' || *c == '-')
        .collect();
    digits
        .parse()
        .unwrap_or_else(|_| panic!("`{label}` is not followed by a number in:\n{text}"))
}

/// The line of the summary that starts with `prefix`, without it.
fn summary_line<'a>(text: &'a str, prefix: &str) -> &'a str {
    text.lines()
        .find_map(|l| l.strip_prefix(prefix))
        .unwrap_or_else(|| panic!("no `{prefix}` line in:\n{text}"))
}

/// `(largest bytes in flight, buffer counted against)` from the character-counting line.
fn in_flight(summary: &str) -> (f64, f64) {
    let counting = summary_line(summary, "character counting: ");
    (
        number_after(counting, "largest in flight"),
        number_after(counting, " of "),
    )
}

#[test]
fn a_ten_thousand_line_program_streams_with_every_line_answered_once_in_order() {
    let program = zigzag(10_000);
    let summary = run_grbl("zigzag.nc", &program.text);
    assert!(summary.contains("result: finished"), "{summary}");
    // `$H`, the two `--before` lines and the program's G-code lines, each answered `ok`
    // exactly once: none refused, none left unanswered, no answer without its line.
    let lines = program.code_lines + 1 + BEFORE.len();
    let run = summary_line(&summary, "lines run: ");
    assert_eq!(number_after(run, ""), lines as f64, "{summary}");
    assert_eq!(number_after(run, " of "), lines as f64, "{summary}");
    assert_eq!(number_after(run, "refused"), 0.0, "{summary}");
    assert_eq!(number_after(run, "unanswered"), 0.0, "{summary}");
    assert_eq!(number_after(run, "stray answers"), 0.0, "{summary}");
    // The controller ran every G-code line once (`$H` is a `$` command, not one of them) …
    assert_eq!(
        number_after(run, "executed"),
        (lines - 1) as f64,
        "{summary}"
    );
    // … and in order: the line numbers its status reports give (`Ln:`) never went back.
    let counting = summary_line(&summary, "character counting: ");
    assert_eq!(number_after(counting, "Ln went back"), 0.0, "{summary}");
    // Counted against the firmware's read-ahead window, which it reports in `Bf:`, and never
    // above it; the sender used it.
    let (largest, buffer) = in_flight(&summary);
    assert_eq!(buffer, 768.0, "{summary}");
    assert!(largest <= buffer, "{summary}");
    assert!(largest > buffer - 40.0, "{summary}");
    assert!(
        number_after(counting, "largest ? latency") < 50.0,
        "{summary}"
    );
    // The operator answered the tool change.
    assert!(
        summary.contains("[MSG:Change to tool T2, then cycle start]: operator: cycle start (~)"),
        "{summary}"
    );
    assert!(summary.contains("[MSG:Pgm End]"), "{summary}");
    // The machine ended where the program does, in machine coordinates.
    let end = summary_line(&summary, "final position: ");
    for (i, letter) in ["X", "Y", "Z"].into_iter().enumerate() {
        let at = number_after(end, letter);
        let expected = program.end[i] + OFFSET[i];
        assert!(
            (at - expected).abs() < 0.013,
            "{letter}: {at} mm, the program ends at {expected} mm:\n{summary}"
        );
    }
    assert_eq!(
        number_after(&summary, "timing violations:"),
        0.0,
        "{summary}"
    );
}

#[test]
fn a_status_request_is_answered_at_once_while_the_receive_buffer_is_full() {
    // Slow short moves: the planner fills, the lines behind wait in the controller's receive
    // buffer, and the sender keeps it as full as the count allows while it polls `?`.
    let mut text = String::from("G21 G90 G54\nG0 X0 Y0 Z5\nG1 Z-1 F300\n");
    for i in 1..=600u32 {
        let x = f64::from(i % 100) * 0.8;
        let y = f64::from(i / 100) * 2.0 + if i.is_multiple_of(2) { 0.4 } else { 0.0 };
        writeln!(text, "N{i} G1 X{x:.3} Y{y:.3} F600 (slow)").unwrap();
    }
    text.push_str("G0 Z5\nM30\n");
    let summary = run_grbl("slow.nc", &text);
    assert!(summary.contains("result: finished"), "{summary}");
    let counting = summary_line(&summary, "character counting: ");
    let (largest, buffer) = in_flight(&summary);
    assert_eq!(buffer, 768.0, "{summary}");
    assert!(largest <= buffer && largest > buffer - 40.0, "{summary}");
    // Most polls went with the buffer full; each was answered within a few polls of the
    // firmware's loop (1 ms of virtual time each), never behind the lines that wait.
    let reports = number_after(counting, "status reports:");
    let when_full = &counting[counting.find("with the buffer full:").unwrap()..];
    let full = number_after(when_full, "with the buffer full:");
    assert!(full >= 100.0 && full <= reports, "{summary}");
    assert!(
        number_after(when_full, "largest ? latency") < 50.0,
        "{summary}"
    );
}
