//! The step trace: every step, direction change and enable change, with its virtual time.
//!
//! [`crate::SimMachine`] records a trace while tracing is on
//! ([`crate::SimMachine::set_tracing`]); tests query it ([`StepTrace::step_times`]) and the
//! simulator writes it to a file (`--trace FILE`) for `forja-sim --plot` to overlay on the toolpath.
//!
//! # File format
//!
//! Plain text, one event a line, comma-separated, after a few `#` header lines:
//!
//! ```text
//! # forja step trace 1
//! # tick_hz 1000000
//! # axes X Y Z A
//! # steps_per_mm X=80 Y=80 Z=400 A=8.888888888888889
//! # start_mm X=150 Y=150 Z=0 A=0
//! time_ticks,axis,event
//! 0,X,enable
//! 10,X,dir+
//! 12,X,step+
//! 512,X,step+
//! ```
//!
//! - `steps_per_mm`: steps per millimetre (per degree for a rotary axis) of each axis, and
//!   `start_mm`: where each axis was when the trace began, mm (degrees), so that a reader can
//!   replay the path without the machine file (`forja-sim --plot` does). Both are written when the
//!   trace knows them (the simulator's traces always do); `LETTER=VALUE` pairs in axis order.
//! - `time_ticks`: virtual time in ticks of the simulator's clock since it started (`tick_hz`
//!   ticks a second), a 64-bit count that does not wrap.
//! - `axis`: the axis letter.
//! - `event`: `step+` / `step-`, one step in the positive / negative direction, at the STEP
//!   line's active (rising) edge of an enabled driver; `dir+` / `dir-`, the DIR line changed to
//!   positive / negative; `enable` / `disable`, the driver's enable line changed.
//!
//! A step of a disabled driver moves nothing and is not traced (see
//! [`crate::SimMachine::lost_steps`]). Lines starting with `#` other than those above are
//! comments; readers ignore unknown `#` lines and must ignore unknown event names, so that the
//! format can grow.

use core::fmt;
use std::io::{self, BufRead, Write};
use std::path::Path;

use forja_hal_abstraction::stepper::Direction;

/// What happened on an axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TraceEventKind {
    /// One step of an enabled driver, in this direction.
    Step(Direction),
    /// The direction line changed to this direction.
    Dir(Direction),
    /// The enable line changed: `true` energised, `false` released.
    Enable(bool),
}

impl TraceEventKind {
    /// The event's name in the trace file.
    pub fn name(self) -> &'static str {
        match self {
            Self::Step(Direction::Positive) => "step+",
            Self::Step(Direction::Negative) => "step-",
            Self::Dir(Direction::Positive) => "dir+",
            Self::Dir(Direction::Negative) => "dir-",
            Self::Enable(true) => "enable",
            Self::Enable(false) => "disable",
        }
    }

    fn from_name(name: &str) -> Option<Self> {
        Some(match name {
            "step+" => Self::Step(Direction::Positive),
            "step-" => Self::Step(Direction::Negative),
            "dir+" => Self::Dir(Direction::Positive),
            "dir-" => Self::Dir(Direction::Negative),
            "enable" => Self::Enable(true),
            "disable" => Self::Enable(false),
            _ => return None,
        })
    }
}

/// One traced event.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct TraceEvent {
    /// Virtual time since the simulator started, in ticks.
    pub time_ticks: u64,
    /// Axis index (into the machine file's axes).
    pub axis: usize,
    /// What happened.
    pub kind: TraceEventKind,
}

/// A recorded step trace.
#[derive(Debug, Clone)]
pub struct StepTrace {
    tick_hz: u32,
    axes: Vec<char>,
    /// Steps per mm of each axis; empty when not known.
    steps_per_mm: Vec<f64>,
    /// Where each axis was when the trace began, mm; empty when not known.
    start_mm: Vec<f64>,
    events: Vec<TraceEvent>,
}

impl StepTrace {
    /// An empty trace of a machine with these axis letters and clock rate.
    pub fn new(tick_hz: u32, axes: Vec<char>) -> Self {
        Self {
            tick_hz,
            axes,
            steps_per_mm: Vec::new(),
            start_mm: Vec::new(),
            events: Vec::new(),
        }
    }

    /// The same trace with the steps per mm of each axis and where each was when the trace
    /// began, mm (both in axis order, one value per axis; other lengths are ignored).
    pub fn with_scale(mut self, steps_per_mm: Vec<f64>, start_mm: Vec<f64>) -> Self {
        if steps_per_mm.len() == self.axes.len() {
            self.steps_per_mm = steps_per_mm;
        }
        self.set_start_mm(start_mm);
        self
    }

    /// Where each axis was when the trace began, mm (one value per axis, in axis order).
    pub(crate) fn set_start_mm(&mut self, start_mm: Vec<f64>) {
        if start_mm.len() == self.axes.len() {
            self.start_mm = start_mm;
        }
    }

    /// Steps per mm of each axis, in axis order; empty when the trace does not know them.
    pub fn steps_per_mm(&self) -> &[f64] {
        &self.steps_per_mm
    }

    /// Where each axis was when the trace began, mm, in axis order; empty when not known.
    pub fn start_mm(&self) -> &[f64] {
        &self.start_mm
    }

    /// Ticks per second of the event times.
    pub fn tick_hz(&self) -> u32 {
        self.tick_hz
    }

    /// The axis letters, by index.
    pub fn axes(&self) -> &[char] {
        &self.axes
    }

    /// Every event, in time order.
    pub fn events(&self) -> &[TraceEvent] {
        &self.events
    }

    /// Append an event. Events must be pushed in time order.
    pub fn push(&mut self, event: TraceEvent) {
        self.events.push(event);
    }

    /// Forget every event.
    pub fn clear(&mut self) {
        self.events.clear();
    }

    /// The times of the steps of `axis`, in order.
    pub fn step_times(&self, axis: usize) -> Vec<u64> {
        self.steps(axis).map(|(t, _)| t).collect()
    }

    /// The steps of `axis` with their direction, in order.
    pub fn steps(&self, axis: usize) -> impl Iterator<Item = (u64, Direction)> + '_ {
        self.events.iter().filter_map(move |e| match e.kind {
            TraceEventKind::Step(d) if e.axis == axis => Some((e.time_ticks, d)),
            _ => None,
        })
    }

    /// Positive minus negative steps of `axis`: its displacement over the trace.
    pub fn net_steps(&self, axis: usize) -> i64 {
        self.steps(axis)
            .map(|(_, d)| if d == Direction::Positive { 1 } else { -1 })
            .sum()
    }

    /// Write the trace in the file format of this module.
    pub fn write_csv<W: Write>(&self, mut w: W) -> io::Result<()> {
        writeln!(w, "# forja step trace 1")?;
        writeln!(w, "# tick_hz {}", self.tick_hz)?;
        let letters: Vec<String> = self.axes.iter().map(char::to_string).collect();
        writeln!(w, "# axes {}", letters.join(" "))?;
        for (name, values) in [
            ("steps_per_mm", &self.steps_per_mm),
            ("start_mm", &self.start_mm),
        ] {
            if values.is_empty() {
                continue;
            }
            let pairs: Vec<String> = self
                .axes
                .iter()
                .zip(values.iter())
                .map(|(l, v)| format!("{l}={v}"))
                .collect();
            writeln!(w, "# {name} {}", pairs.join(" "))?;
        }
        writeln!(w, "time_ticks,axis,event")?;
        for e in &self.events {
            let letter = self.axes.get(e.axis).copied().unwrap_or('?');
            writeln!(w, "{},{},{}", e.time_ticks, letter, e.kind.name())?;
        }
        w.flush()
    }

    /// Write the trace to a file, replacing it.
    pub fn save(&self, path: &Path) -> io::Result<()> {
        let file = std::fs::File::create(path)?;
        self.write_csv(io::BufWriter::new(file))
    }

    /// Read a trace written by [`StepTrace::write_csv`]. Unknown event names are skipped.
    ///
    /// Errors: [`TraceParseError`] naming the line of a malformed row or header, or an I/O error.
    pub fn read_csv<R: BufRead>(r: R) -> Result<Self, TraceParseError> {
        let mut trace = StepTrace::new(0, Vec::new());
        let mut saw_columns = false;
        for (i, line) in r.lines().enumerate() {
            let n = i + 1;
            let line = line.map_err(|e| TraceParseError::new(n, format!("read error: {e}")))?;
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            if let Some(rest) = line.strip_prefix('#') {
                let rest = rest.trim();
                if let Some(hz) = rest.strip_prefix("tick_hz ") {
                    trace.tick_hz = hz
                        .trim()
                        .parse()
                        .map_err(|_| TraceParseError::new(n, "bad tick_hz"))?;
                } else if let Some(axes) = rest.strip_prefix("axes") {
                    trace.axes = axes
                        .split_whitespace()
                        .map(|a| {
                            let mut c = a.chars();
                            match (c.next(), c.next()) {
                                (Some(l), None) => Ok(l),
                                _ => Err(TraceParseError::new(n, "bad axis letter")),
                            }
                        })
                        .collect::<Result<_, _>>()?;
                } else if let Some(v) = rest.strip_prefix("steps_per_mm ") {
                    trace.steps_per_mm = per_axis(&trace.axes, v, n)?;
                } else if let Some(v) = rest.strip_prefix("start_mm ") {
                    trace.start_mm = per_axis(&trace.axes, v, n)?;
                }
                continue;
            }
            if !saw_columns {
                if line != "time_ticks,axis,event" {
                    return Err(TraceParseError::new(
                        n,
                        "expected \"time_ticks,axis,event\"",
                    ));
                }
                saw_columns = true;
                continue;
            }
            let mut fields = line.split(',');
            let (Some(t), Some(a), Some(ev), None) =
                (fields.next(), fields.next(), fields.next(), fields.next())
            else {
                return Err(TraceParseError::new(n, "expected three fields"));
            };
            let time_ticks = t
                .parse()
                .map_err(|_| TraceParseError::new(n, "bad time_ticks"))?;
            let axis = trace
                .axes
                .iter()
                .position(|&l| a.len() == l.len_utf8() && a.starts_with(l))
                .ok_or_else(|| TraceParseError::new(n, format!("unknown axis \"{a}\"")))?;
            if let Some(kind) = TraceEventKind::from_name(ev) {
                trace.events.push(TraceEvent {
                    time_ticks,
                    axis,
                    kind,
                });
            }
        }
        if trace.tick_hz == 0 {
            return Err(TraceParseError::new(0, "missing \"# tick_hz\" header"));
        }
        Ok(trace)
    }
}

/// Equal when every field is; the header numbers compare bit for bit (so that equality is an
/// equivalence, `NaN` included).
impl PartialEq for StepTrace {
    fn eq(&self, other: &Self) -> bool {
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        self.tick_hz == other.tick_hz
            && self.axes == other.axes
            && bits(&self.steps_per_mm) == bits(&other.steps_per_mm)
            && bits(&self.start_mm) == bits(&other.start_mm)
            && self.events == other.events
    }
}

impl Eq for StepTrace {}

/// The values of `LETTER=VALUE` pairs (header line `n`), in the order of `axes`; every axis
/// must have one.
fn per_axis(axes: &[char], text: &str, n: usize) -> Result<Vec<f64>, TraceParseError> {
    let mut values = vec![None; axes.len()];
    for pair in text.split_whitespace() {
        let (letter, value) = pair.split_once('=').ok_or_else(|| {
            TraceParseError::new(n, format!("expected LETTER=VALUE, not \"{pair}\""))
        })?;
        let i = axes
            .iter()
            .position(|&l| letter.len() == l.len_utf8() && letter.starts_with(l))
            .ok_or_else(|| TraceParseError::new(n, format!("unknown axis \"{letter}\"")))?;
        let v: f64 = value
            .parse()
            .map_err(|_| TraceParseError::new(n, format!("bad number \"{value}\"")))?;
        if let Some(slot) = values.get_mut(i) {
            *slot = Some(v);
        }
    }
    values
        .into_iter()
        .zip(axes)
        .map(|(v, l)| v.ok_or_else(|| TraceParseError::new(n, format!("no value for axis {l}"))))
        .collect()
}

/// A trace file that could not be read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TraceParseError {
    /// 1-based line (0 for a missing header).
    pub line: usize,
    /// What is wrong.
    pub message: String,
}

impl TraceParseError {
    fn new(line: usize, message: impl Into<String>) -> Self {
        Self {
            line,
            message: message.into(),
        }
    }
}

impl fmt::Display for TraceParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "step trace line {}: {}", self.line, self.message)
    }
}

impl std::error::Error for TraceParseError {}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> StepTrace {
        let mut t = StepTrace::new(1_000_000, vec!['X', 'Y']);
        let ev = |time_ticks, axis, kind| TraceEvent {
            time_ticks,
            axis,
            kind,
        };
        t.push(ev(0, 0, TraceEventKind::Enable(true)));
        t.push(ev(5, 0, TraceEventKind::Dir(Direction::Positive)));
        t.push(ev(7, 0, TraceEventKind::Step(Direction::Positive)));
        t.push(ev(9, 1, TraceEventKind::Step(Direction::Negative)));
        t.push(ev(12, 0, TraceEventKind::Step(Direction::Positive)));
        t.push(ev(20, 0, TraceEventKind::Enable(false)));
        t
    }

    #[test]
    fn queries() {
        let t = sample();
        assert_eq!(t.step_times(0), vec![7, 12]);
        assert_eq!(t.step_times(1), vec![9]);
        assert_eq!(t.net_steps(0), 2);
        assert_eq!(t.net_steps(1), -1);
    }

    #[test]
    fn file_format_round_trips() {
        let t = sample();
        let mut out = Vec::new();
        t.write_csv(&mut out).unwrap();
        let text = String::from_utf8(out.clone()).unwrap();
        assert!(text.starts_with(
            "# forja step trace 1\n# tick_hz 1000000\n# axes X Y\ntime_ticks,axis,event\n\
             0,X,enable\n5,X,dir+\n7,X,step+\n9,Y,step-\n"
        ));
        assert_eq!(StepTrace::read_csv(&out[..]).unwrap(), t);
    }

    #[test]
    fn the_header_gives_steps_per_mm_and_the_start_position() {
        use forja_hal_abstraction::stepper::{Stepper, StepperEnable};

        use crate::{MachineConfig, SimMachine};

        let text = "tick_hz = 1_000_000\n\
                    [[axis]]\nletter = \"X\"\nsteps_per_mm = 80\nmax_rate_mm_min = 6000\n\
                    accel_mm_s2 = 500\ntravel_min_mm = 0\ntravel_max_mm = 300\nstart_mm = 150\n\
                    [[axis]]\nletter = \"Z\"\nsteps_per_mm = 400.5\nmax_rate_mm_min = 600\n\
                    accel_mm_s2 = 100\ntravel_min_mm = 0\ntravel_max_mm = 100\nstart_mm = 0\n";
        let m = SimMachine::new(&MachineConfig::from_toml_str(text).unwrap());
        m.set_tracing(true);
        let mut x = m.stepper(0).unwrap();
        x.set_enabled(true).unwrap();
        x.set_direction(Direction::Positive).unwrap();
        m.advance_by(10);
        x.step_begin().unwrap();
        m.advance_by(10);
        x.step_end().unwrap();
        let mut out = Vec::new();
        m.take_trace().write_csv(&mut out).unwrap();
        let text = String::from_utf8(out.clone()).unwrap();
        // The lines `forja-sim --plot` reads (`simulator/src/plot.rs`: `Executed::from_trace`).
        assert!(
            text.starts_with(
                "# forja step trace 1\n# tick_hz 1000000\n# axes X Z\n\
                 # steps_per_mm X=80 Z=400.5\n# start_mm X=150 Z=0\ntime_ticks,axis,event\n"
            ),
            "{text}"
        );
        let back = StepTrace::read_csv(&out[..]).unwrap();
        assert_eq!(back.steps_per_mm(), [80.0, 400.5]);
        assert_eq!(back.start_mm(), [150.0, 0.0]);
        assert_eq!(back.net_steps(0), 1);
        // The next trace begins where the last one ended.
        assert_eq!(m.take_trace().start_mm(), [150.0125, 0.0]);
        // A header without a value for every axis is refused, naming its line.
        let bad = "# tick_hz 1000\n# axes X Y\n# steps_per_mm X=80\ntime_ticks,axis,event\n";
        assert_eq!(StepTrace::read_csv(bad.as_bytes()).unwrap_err().line, 3);
    }

    #[test]
    fn reader_skips_unknown_events_and_names_bad_lines() {
        let text = "# tick_hz 1000\n# axes X\ntime_ticks,axis,event\n1,X,step+\n2,X,glow\n";
        let t = StepTrace::read_csv(text.as_bytes()).unwrap();
        assert_eq!(t.events().len(), 1);
        let bad = "# tick_hz 1000\n# axes X\ntime_ticks,axis,event\n1,Q,step+\n";
        assert_eq!(StepTrace::read_csv(bad.as_bytes()).unwrap_err().line, 4);
        let bad = "# tick_hz 1000\n# axes X\ntime_ticks,axis,event\nx,X,step+\n";
        assert_eq!(StepTrace::read_csv(bad.as_bytes()).unwrap_err().line, 4);
    }
}
