//! Toolpath plots: the path a job asks for, as the firmware's kernel reads it, and, from a step
//! trace, the path the simulated machine really took, drawn to PNG or SVG (`forja-sim --plot`).
//!
//! [`Toolpath::from_job`] runs the job through the kernel's own reading of G-code
//! ([`forja_motion::Preview`], on the kernel configuration the simulator board builds from the
//! machine file, [`forja_sim::board::parts::machine`]): units, distance modes, planes, `G92`
//! offsets, extrusion modes, arcs (cut into the kernel's chords) and homing are the
//! firmware's. Positions are the machine's physical ones, those of a step trace: the firmware
//! counts from zero when it starts while the machine stands at each axis's `start_mm`, so an
//! axis is drawn shifted by its start position until a homing line homes it, and from then on
//! where the kernel's homing cycle left it; nothing is drawn between the two. A line the kernel
//! refuses changes nothing, as when the machine runs the job (which goes on to its end): it is
//! kept in [`Toolpath::refused`], said on the plot and marked where the tool stood.
//!
//! On a machine with an extruder (a printer) the path is told apart as the preview's
//! [`Piece`]s are: **extrusion**, where an extruder advances as the tool moves, and **travel**,
//! where the tool moves without extruding (wipes included); a piece that only turns the
//! extruder (a retraction, its undoing, a prime) draws nothing and is counted. The part's
//! **layers** are the heights at which extrusion happens, numbered from 1 in the order they are
//! printed: a layer starts at the first extrusion above every extrusion before it, and an
//! extrusion at or below the height of the layer being printed belongs to that layer (a purge
//! line a start G-code draws at 0.3 mm before the first layer at 0.2 mm belongs to layer 1,
//! whose heights are then 0.2 to 0.3 mm). A travel move belongs to the layer of the next
//! extrusion, the one it leads to; the travel after the last extrusion to the last layer. On a
//! machine without an extruder the path is told apart by how it is travelled: rapids (`G0`)
//! and feeds.
//!
//! [`Executed::from_trace`] replays a step trace (`forja_sim_hal::trace`) step by step.
//! [`render`] draws both in the XY plane with a millimetre grid and the machine's X/Y travel
//! (the bed of a printer), [`PlotOptions`] choosing the layers drawn and whether travel is;
//! the view frames the extrusion drawn (the whole path on a machine without an extruder). The
//! text is drawn with a built-in 8×8 bitmap font, so no system font is needed.
//!
//! A tool of the simulator program, on the host: nothing here is part of the firmware.

use std::fmt;
use std::ops::RangeInclusive;
use std::path::Path;
use std::str::FromStr;

use forja_hal_abstraction::stepper::Direction;
use forja_host::codes::explain;
use forja_host::grbl_sender::clean_line;
use forja_host::program::{Program, ProgramError, describe_line_error};
use forja_motion::{AxisKind, NM_PER_MM, Piece, Preview, Travel};
use forja_protocol::gcode::Line;
use forja_sim::board::BoardError;
use forja_sim::board::parts;
use forja_sim_hal::{MachineConfig, StepTrace, TraceEventKind};
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

use crate::job::Job;

/// What a stretch of the path does, which decides how it is drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PathKind {
    /// On a machine without an extruder: positioning in rapids (`G0`).
    Rapid,
    /// On a machine without an extruder: at the feed rate (`G1`, `G2`, `G3`).
    Feed,
    /// On a printer: material laid, an extruder advancing as the tool moves.
    Extrusion,
    /// On a printer: the tool moving without extruding (in rapids or not, wipes included).
    Travel,
}

/// Connected points of the same kind and layer, XY in mm.
#[derive(Clone, Debug, PartialEq)]
pub struct Polyline {
    /// What the stretch does.
    pub kind: PathKind,
    /// The layer it belongs to, an index into [`Toolpath::layers`]; `None` on a machine without
    /// an extruder, and for travel of a printer job that extrudes nothing.
    pub layer: Option<usize>,
    /// The points, in order.
    pub points: Vec<[f64; 2]>,
}

/// One layer of a printed part. See the [module documentation](self).
#[derive(Clone, Debug, PartialEq)]
pub struct Layer {
    /// The lowest and highest height of its extrusion, mm.
    pub z_mm: [f64; 2],
    /// Length of its extrusion, mm (XYZ).
    pub extrusion_mm: f64,
}

/// A line of the job the kernel refuses: the machine runs the job without it.
#[derive(Clone, Debug, PartialEq)]
pub struct Refusal {
    /// The line's number in the job; `None` for the `G28` sent before the job.
    pub line: Option<usize>,
    /// The line as sent (comments and spaces left out).
    pub text: String,
    /// Why the kernel refuses it, with its error code.
    pub reason: String,
    /// Where the tool stands when the line comes, XY mm.
    pub at: [f64; 2],
}

/// The path a job asks for, in the machine's physical coordinates.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Toolpath {
    /// The stretches, in program order; a homing line starts a new one.
    pub polylines: Vec<Polyline>,
    /// Whether the machine has an extruder: the path is then extrusion and travel, in layers.
    pub printer: bool,
    /// The layers of a printer job, from the first printed; empty when nothing is extruded.
    pub layers: Vec<Layer>,
    /// Length travelled at the feed rate, mm (XYZ).
    pub feed_mm: f64,
    /// Length travelled in rapids, mm (XYZ).
    pub rapid_mm: f64,
    /// On a printer: length of the extrusion, mm (XYZ).
    pub extrusion_mm: f64,
    /// On a printer: length travelled without extruding, mm (XYZ).
    pub travel_mm: f64,
    /// On a printer: filament fed along the extrusion, mm (the extruders' advance).
    pub filament_mm: f64,
    /// On a printer: moves of the extruders alone that draw filament back.
    pub retractions: usize,
    /// The lines the kernel refuses, in order.
    pub refused: Vec<Refusal>,
    /// The machine's X/Y travel (the bed of a printer), mm: x0, y0, x1, y1; `None` when X or Y
    /// has no limits.
    pub bed: Option<[f64; 4]>,
    /// Where the job ends, XYZ mm (0 on an axis the machine does not have).
    pub end: [f64; 3],
    /// Every straight move of the tool in X, Y and Z, in program order (an arc as the kernel's
    /// chords), from end to end on the step grid as the kernel steps it: the geometry
    /// [`Executed::check`] holds a step trace to. Moves of other axes alone (an extruder's, a
    /// rotary axis's), and moves shorter than a step on every axis, are left out.
    pub moves: Vec<Move>,
    /// Where homing lines come among [`Toolpath::moves`]: the index of the move each comes
    /// before (the number of moves for one after the last), in order, once each. The homing
    /// cycle's own moves are not the program's: [`Executed::check`] leaves them out.
    pub homings: Vec<usize>,
}

/// A straight move of the program, as the kernel queues it: a `G0` or `G1`, or a chord of an
/// arc. Its ends are on the step grid: each axis's target rounded to a whole step, as the
/// kernel steps to it (within half a step an axis of the program's exact position).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Move {
    /// Where it starts, physical XYZ mm.
    pub from: [f64; 3],
    /// Where it ends, physical XYZ mm.
    pub to: [f64; 3],
    /// The number of the job's line it comes from; `None` only for a line sent before the job.
    pub line: Option<usize>,
}

/// A plot that cannot be made.
#[derive(Debug)]
pub struct PlotError(String);

impl fmt::Display for PlotError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for PlotError {}

/// Layers of a printed part (`--plot-layers`), numbered from 1 as slicer previews number them:
/// one (`3`) or a range with both ends included (`2..5`; `2..` up to the top, `..5` from the
/// first).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LayerRange {
    /// The first layer, from 1.
    pub first: usize,
    /// The last layer; `None`: the top one.
    pub last: Option<usize>,
}

impl FromStr for LayerRange {
    type Err = PlotError;

    /// Errors: not a number or a range of them, a layer 0, a range that ends before it starts.
    fn from_str(text: &str) -> Result<Self, PlotError> {
        let number = |s: &str| -> Result<usize, PlotError> {
            match s.trim().parse::<usize>() {
                Ok(0) => Err(PlotError("layers are numbered from 1".into())),
                Ok(n) => Ok(n),
                Err(_) => Err(PlotError(
                    "give a layer (3) or a range of layers, both ends included (2..5, 2.., ..5)"
                        .into(),
                )),
            }
        };
        let range = match text.split_once("..") {
            None => {
                let n = number(text)?;
                Self {
                    first: n,
                    last: Some(n),
                }
            }
            Some((first, last)) => Self {
                first: if first.trim().is_empty() {
                    1
                } else {
                    number(first)?
                },
                last: if last.trim().is_empty() {
                    None
                } else {
                    Some(number(last)?)
                },
            },
        };
        match range.last {
            Some(last) if last < range.first => {
                Err(PlotError("the range ends before it starts".into()))
            }
            _ => Ok(range),
        }
    }
}

impl fmt::Display for LayerRange {
    /// As [`LayerRange::from_str`] reads it: `3`, `2..5`, `2..`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.last {
            Some(last) if last == self.first => write!(f, "{last}"),
            Some(last) => write!(f, "{}..{last}", self.first),
            None => write!(f, "{}..", self.first),
        }
    }
}

/// What a plot shows of a toolpath.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PlotOptions {
    /// The layers drawn, on a printer; all when `None`.
    pub layers: Option<LayerRange>,
    /// Leave travel out (a printer's; on a machine without an extruder, the rapids).
    pub hide_travel: bool,
}

/// What a run sends before its job ([`crate::run::JobOptions`]), for [`Toolpath::from_job`].
#[derive(Debug, Clone, Copy, Default)]
pub struct Lead<'a> {
    /// A homing cycle first.
    pub home_first: bool,
    /// The job goes in the grbl dialect (`G28`/`G30` to the stored positions).
    pub grbl: bool,
    /// Lines after homing and before the job (work offsets).
    pub before: &'a [String],
}

/// Heights closer than this are one, mm.
const Z_TOLERANCE_MM: f64 = 0.001;

impl Toolpath {
    /// Follow `job` on a machine of `machine` standing at its start position, after the lines
    /// [`crate::run::run_job`] sends before it (`lead`: homing and the `--before` lines), in
    /// the dialect it streams the job in.
    ///
    /// Errors: a machine the kernel cannot take, a job line that does not parse (with the
    /// job's name and the line's number). A line the kernel refuses is not an error: it is
    /// kept in [`Toolpath::refused`].
    pub fn from_job(
        machine: &MachineConfig,
        job: &Job,
        lead: &Lead<'_>,
    ) -> Result<Self, PlotError> {
        match machine.axes.len() {
            1 => follow::<1>(machine, job, lead),
            2 => follow::<2>(machine, job, lead),
            3 => follow::<3>(machine, job, lead),
            4 => follow::<4>(machine, job, lead),
            5 => follow::<5>(machine, job, lead),
            6 => follow::<6>(machine, job, lead),
            7 => follow::<7>(machine, job, lead),
            8 => follow::<8>(machine, job, lead),
            n => Err(PlotError(BoardError::AxisCount(n).to_string())),
        }
    }

    /// The layers `range` names, as indices into [`Toolpath::layers`].
    ///
    /// Errors: a machine without an extruder, a job that extrudes nothing, a layer the job does
    /// not have (saying how many it has).
    pub fn select_layers(&self, range: LayerRange) -> Result<RangeInclusive<usize>, PlotError> {
        if !self.printer {
            return Err(PlotError(
                "layers are the heights at which an extruder lays material, and the machine has \
                 no extruder"
                    .into(),
            ));
        }
        let count = self.layers.len();
        if count == 0 {
            return Err(PlotError(
                "the job extrudes nothing: it has no layers".into(),
            ));
        }
        let last = range.last.unwrap_or(count);
        if range.first > count || last > count {
            return Err(PlotError(format!(
                "the job has {}",
                self.describe_layers(None)
            )));
        }
        Ok(range.first - 1..=last - 1)
    }

    /// The layers of `span` (all when `None`) in words, with their heights: `6 layers, Z 0.2 to
    /// 1.2 mm`, `layer 2 of 6, Z 0.4 mm`, `layers 2 to 4 of 6, Z 0.4 to 0.8 mm`.
    pub fn describe_layers(&self, span: Option<RangeInclusive<usize>>) -> String {
        let count = self.layers.len();
        if count == 0 {
            return "no layers (nothing extruded)".into();
        }
        let (first, last) = span.map_or((0, count - 1), |s| (*s.start(), *s.end()));
        let (low, high) = (self.layers[first].z_mm[0], self.layers[last].z_mm[1]);
        let z = if high - low < Z_TOLERANCE_MM {
            format!("Z {} mm", label(low))
        } else {
            format!("Z {} to {} mm", label(low), label(high))
        };
        let plural = if count == 1 { "" } else { "s" };
        if first == 0 && last == count - 1 {
            format!("{count} layer{plural}, {z}")
        } else if first == last {
            format!("layer {} of {count}, {z}", first + 1)
        } else {
            format!("layers {} to {} of {count}, {z}", first + 1, last + 1)
        }
    }
}

/// A straight piece of the path in physical XYZ mm, before it joins a polyline.
struct Stroke {
    kind: PathKind,
    from: [f64; 3],
    to: [f64; 3],
    /// The first piece after a homing line: it starts a new polyline.
    after_homing: bool,
}

impl Stroke {
    fn length_mm(&self) -> f64 {
        let d = |k: usize| self.to[k] - self.from[k];
        (d(0).powi(2) + d(1).powi(2) + d(2).powi(2)).sqrt()
    }
}

/// The lines of `job` as a grbl sender sends them and the grbl dialect reads them: comments
/// and blanks dropped ([`clean_line`]), a leading `N` number (the dialect's line number, not
/// checked) and `%` lines (a program's start and end markers) left out. With their numbers in
/// the file.
fn grbl_lines(job: &Job) -> Vec<(usize, String)> {
    job.lines()
        .enumerate()
        .filter_map(|(i, raw)| {
            let text = clean_line(raw);
            let text = text.trim();
            let unnumbered = match text.strip_prefix(['N', 'n']) {
                Some(rest) => rest.trim_start_matches(|c: char| c.is_ascii_digit()).trim(),
                None => text,
            };
            (!unnumbered.is_empty() && unnumbered != "%").then(|| (i + 1, unnumbered.to_string()))
        })
        .collect()
}

/// [`Toolpath::from_job`] on a machine of `N` axes.
fn follow<const N: usize>(
    machine: &MachineConfig,
    job: &Job,
    lead: &Lead<'_>,
) -> Result<Toolpath, PlotError> {
    let config = parts::machine::<N>(machine).map_err(|e| PlotError(e.to_string()))?;
    let program: Vec<(usize, String)> = if lead.grbl {
        grbl_lines(job)
    } else {
        Program::parse(job.text().as_bytes())
            .map_err(|e| match e {
                ProgramError::Line { line, reason, .. } => {
                    PlotError(format!("{}, line {line}: {reason}", job.name()))
                }
                e => PlotError(format!("{}: {e}", job.name())),
            })?
            .lines
            .into_iter()
            .map(|l| (l.source_line, l.text))
            .collect()
    };
    let xyz = [b'X', b'Y', b'Z'].map(|l| config.axis_index(l));
    let printer = config.axes.iter().any(|a| a.kind == AxisKind::Extruder);
    // Physical position = the kernel's count + the shift: the start position until homed.
    let mut shift: [i64; N] = core::array::from_fn(|i| {
        machine
            .axes
            .get(i)
            .map_or(0, |a| (a.start_mm * NM_PER_MM).round() as i64)
    });
    let at = |nm: [i64; N], shift: &[i64; N]| {
        xyz.map(|i| i.map_or(0.0, |i| (nm[i] + shift[i]) as f64 / NM_PER_MM))
    };
    // The same on the step grid: the kernel steps to each target rounded to whole steps.
    let stepped = |nm: [i64; N], shift: &[i64; N]| {
        xyz.map(|i| {
            i.map_or(0.0, |i| {
                let per_mm = f64::from(config.axes[i].steps_per_mm);
                (nm[i] as f64 * per_mm / NM_PER_MM).round() / per_mm + shift[i] as f64 / NM_PER_MM
            })
        })
    };
    let travel_of = |letter: char| {
        machine
            .axes
            .iter()
            .find(|a| a.letter == letter)
            .and_then(|a| a.travel)
    };
    let mut path = Toolpath {
        printer,
        bed: travel_of('X')
            .zip(travel_of('Y'))
            .map(|(x, y)| [x.min_mm, y.min_mm, x.max_mm, y.max_mm]),
        ..Toolpath::default()
    };
    // The firmware counts from zero when it starts.
    let mut preview = Preview::new(&config, [0; N]);
    let mut strokes: Vec<Stroke> = Vec::new();
    let mut after_homing = false;
    let homing = lead.home_first.then_some((None, "G28"));
    let lines = homing
        .into_iter()
        .chain(lead.before.iter().map(|l| (None, l.as_str())))
        .chain(program.iter().map(|(n, text)| (Some(*n), text.as_str())));
    for (k, (number, text)) in lines.enumerate() {
        // The homing line is RepRap's `G28` (grbl's `$H`); the rest in the job's dialect.
        if k == usize::from(homing.is_some()) {
            preview.set_grbl_dialect(lead.grbl);
        }
        let line = Line::parse(text.as_bytes()).map_err(|e| {
            let place = match number {
                Some(n) => format!("{}, line {n}", job.name()),
                None => format!("{text} (before the job)"),
            };
            PlotError(format!("{place}: {}", describe_line_error(&e)))
        })?;
        let outcome = preview.line(&line, |piece: Piece<N>| {
            let (from, to) = (at(piece.from, &shift), at(piece.to, &shift));
            match piece.travel {
                Travel::Rapid => path.rapid_mm += distance(from, to),
                Travel::Feed => path.feed_mm += distance(from, to),
            }
            if !piece.moves_tool {
                if piece.extruded_nm < 0 {
                    path.retractions += 1;
                }
                return;
            }
            let kind = match (printer, piece.travel) {
                (true, _) if piece.extrudes() => {
                    path.filament_mm += piece.extruded_nm as f64 / NM_PER_MM;
                    PathKind::Extrusion
                }
                (true, _) => PathKind::Travel,
                (false, Travel::Rapid) => PathKind::Rapid,
                (false, Travel::Feed) => PathKind::Feed,
            };
            let (from_steps, to_steps) = (stepped(piece.from, &shift), stepped(piece.to, &shift));
            if from_steps != to_steps {
                path.moves.push(Move {
                    from: from_steps,
                    to: to_steps,
                    line: number,
                });
            }
            strokes.push(Stroke {
                kind,
                from,
                to,
                after_homing: core::mem::take(&mut after_homing),
            });
        });
        match outcome {
            Ok(0) => {}
            Ok(homed) => {
                for (i, s) in shift.iter_mut().enumerate() {
                    if homed & (1 << i) != 0 {
                        *s = 0;
                    }
                }
                after_homing = true;
                if path.homings.last() != Some(&path.moves.len()) {
                    path.homings.push(path.moves.len());
                }
            }
            Err(e) => {
                let here = at(preview.position(), &shift);
                path.refused.push(Refusal {
                    line: number,
                    text: text.to_string(),
                    reason: explain(e.code(), &e.to_string()),
                    at: [here[0], here[1]],
                });
            }
        }
    }
    let layer_of = assign_layers(&mut path, &strokes);
    for (stroke, layer) in strokes.iter().zip(layer_of) {
        path.add(stroke, layer);
    }
    path.end = at(preview.position(), &shift);
    Ok(path)
}

/// Find the layers of a printer job's extrusion (into `path.layers`) and the layer of each
/// stroke. See the [module documentation](self).
fn assign_layers(path: &mut Toolpath, strokes: &[Stroke]) -> Vec<Option<usize>> {
    let mut layer_of = vec![None; strokes.len()];
    let mut top = f64::NEG_INFINITY;
    for (k, s) in strokes.iter().enumerate() {
        if s.kind != PathKind::Extrusion {
            continue;
        }
        let z = s.to[2];
        if z > top + Z_TOLERANCE_MM {
            top = z;
            path.layers.push(Layer {
                z_mm: [z, z],
                extrusion_mm: 0.0,
            });
        }
        let layer = path.layers.len() - 1;
        let l = &mut path.layers[layer];
        l.z_mm = [l.z_mm[0].min(z), l.z_mm[1].max(z)];
        l.extrusion_mm += s.length_mm();
        layer_of[k] = Some(layer);
    }
    // Travel: the layer it leads to; after the last extrusion, the last layer.
    let mut next = path.layers.len().checked_sub(1);
    for (k, s) in strokes.iter().enumerate().rev() {
        match s.kind {
            PathKind::Extrusion => next = layer_of[k],
            PathKind::Travel => layer_of[k] = next,
            PathKind::Rapid | PathKind::Feed => {}
        }
    }
    layer_of
}

fn distance(from: [f64; 3], to: [f64; 3]) -> f64 {
    ((to[0] - from[0]).powi(2) + (to[1] - from[1]).powi(2) + (to[2] - from[2]).powi(2)).sqrt()
}

impl Toolpath {
    /// Add a stroke of `layer`, joining the polyline before when it goes on from its end.
    fn add(&mut self, stroke: &Stroke, layer: Option<usize>) {
        match stroke.kind {
            PathKind::Extrusion => self.extrusion_mm += stroke.length_mm(),
            PathKind::Travel => self.travel_mm += stroke.length_mm(),
            PathKind::Rapid | PathKind::Feed => {}
        }
        let (from, to) = (
            [stroke.from[0], stroke.from[1]],
            [stroke.to[0], stroke.to[1]],
        );
        match self.polylines.last_mut() {
            Some(p)
                if !stroke.after_homing
                    && p.kind == stroke.kind
                    && p.layer == layer
                    && p.points.last() == Some(&from) =>
            {
                p.points.push(to);
            }
            _ => self.polylines.push(Polyline {
                kind: stroke.kind,
                layer,
                points: vec![from, to],
            }),
        }
    }
}

/// The path the machine took, replayed from a step trace.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Executed {
    /// XYZ points in mm, machine coordinates (0 on an axis the trace does not have), in time
    /// order (points closer than 0.02 mm to the one before merged).
    pub points: Vec<[f64; 3]>,
    /// Steps in the trace, all axes.
    pub steps: u64,
    /// Length of the XY path, mm.
    pub length_mm: f64,
    /// Where the trace ends, XY mm.
    pub end: [f64; 2],
    /// Time of the last event, s.
    pub duration_s: f64,
    /// Every step of X, Y and Z, for [`Executed::check`]; `None` for a path not replayed from
    /// a trace.
    replay: Option<Replay>,
}

/// Points of the executed path closer than this to the previous one are merged.
const MERGE_MM: f64 = 0.02;

impl Executed {
    /// Replay a step trace (the text of a `--trace` file). Steps per mm and start positions
    /// come from `machine` when given, else from the trace's `# steps_per_mm` and `# start_mm`
    /// header lines.
    ///
    /// Errors: a trace that does not read (naming the line), an X, Y or Z axis whose steps per
    /// mm nobody gives.
    pub fn from_trace(text: &str, machine: Option<&MachineConfig>) -> Result<Self, PlotError> {
        let trace = StepTrace::read_csv(text.as_bytes()).map_err(|e| PlotError(e.to_string()))?;
        // The axis's index in the trace, its steps per mm and its start position.
        let axis = |letter: char| -> Result<Option<(usize, f64, f64)>, PlotError> {
            let Some(i) = trace.axes().iter().position(|&l| l == letter) else {
                return Ok(None);
            };
            let from_machine = machine.and_then(|m| m.axes.iter().find(|a| a.letter == letter));
            let steps_per_mm = from_machine
                .map(|a| a.steps_per_mm)
                .or_else(|| trace.steps_per_mm().get(i).copied())
                .ok_or_else(|| {
                    PlotError(format!(
                        "the step trace does not give the steps per mm of axis {letter}: give \
                         the machine file with --machine"
                    ))
                })?;
            let start_mm = from_machine
                .map(|a| a.start_mm)
                .or_else(|| trace.start_mm().get(i).copied())
                .unwrap_or(0.0);
            Ok(Some((i, steps_per_mm, start_mm)))
        };
        let xyz = [axis('X')?, axis('Y')?, axis('Z')?];
        let place = |steps: [i64; 3]| -> [f64; 3] {
            core::array::from_fn(|k| {
                xyz[k].map_or(0.0, |(_, per_mm, start)| start + steps[k] as f64 / per_mm)
            })
        };
        let mut steps = [0i64; 3];
        let mut out = Executed::default();
        let mut last = place(steps);
        out.points.push(last);
        let mut last_ticks = 0u64;
        let mut replay = Replay {
            axes: xyz.map(|a| a.map(|(_, per_mm, start)| (per_mm, start))),
            steps: Vec::new(),
        };
        // The time of the last step of X, Y or Z.
        let mut last_step_ticks = None;
        for event in trace.events() {
            last_ticks = event.time_ticks;
            let TraceEventKind::Step(direction) = event.kind else {
                continue;
            };
            out.steps += 1;
            let Some(k) = (0..3).find(|&k| xyz[k].is_some_and(|(i, _, _)| i == event.axis)) else {
                continue;
            };
            steps[k] += if direction == Direction::Positive {
                1
            } else {
                -1
            };
            if last_step_ticks == Some(event.time_ticks)
                && let Some(before) = replay.steps.last_mut()
            {
                *before |= SAME_INSTANT;
            }
            last_step_ticks = Some(event.time_ticks);
            let negative = if direction == Direction::Negative {
                NEGATIVE
            } else {
                0
            };
            replay.steps.push(k as u8 | negative);
            let p = place(steps);
            if distance(p, last) >= MERGE_MM {
                out.length_mm += xy_distance(p, last);
                out.points.push(p);
                last = p;
            }
        }
        let end = place(steps);
        if end != last {
            out.length_mm += xy_distance(end, last);
            out.points.push(end);
        }
        out.end = [end[0], end[1]];
        out.duration_s = last_ticks as f64 / f64::from(trace.tick_hz());
        out.replay = Some(replay);
        Ok(out)
    }

    /// How far from the end of `path` the trace ends, in XY, mm.
    pub fn off_end_mm(&self, path: &Toolpath) -> f64 {
        ((self.end[0] - path.end[0]).powi(2) + (self.end[1] - path.end[1]).powi(2)).sqrt()
    }

    /// The stretches of the path whose height is within `z_mm` (both ends included), XY mm.
    fn within(&self, z_mm: [f64; 2]) -> Vec<Vec<[f64; 2]>> {
        let inside = |p: &[f64; 3]| {
            (z_mm[0] - EXECUTED_Z_TOLERANCE_MM..=z_mm[1] + EXECUTED_Z_TOLERANCE_MM).contains(&p[2])
        };
        self.points
            .chunk_by(|a, b| inside(a) == inside(b))
            .filter(|run| inside(&run[0]))
            .map(|run| run.iter().map(|p| [p[0], p[1]]).collect())
            .collect()
    }
}

/// How far from a layer's height the executed path still counts as at that layer, mm: a few Z
/// steps.
const EXECUTED_Z_TOLERANCE_MM: f64 = 0.01;

fn xy_distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

/// How a trace's steps follow a toolpath, as [`Executed::check`] finds it.
#[derive(Clone, Debug, PartialEq)]
pub struct TraceCheck {
    /// One step, mm: the largest of the millimetres per step of X, Y and Z (those the trace
    /// has), `1 / min(steps_per_mm)`.
    pub step_mm: f64,
    /// The measured position farthest from the toolpath; `None` when none was measured.
    pub farthest: Option<Deviation>,
    /// How many positions were measured.
    pub measured: u64,
    /// The first move after a homing line, when the steps never come to its start (the
    /// trace is not this job's, or ends during the homing cycle); measuring stopped there.
    pub missed: Option<Move>,
}

/// A position of the trace and the toolpath near it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Deviation {
    /// How far the position is from the nearest move of the toolpath, mm (XYZ).
    pub distance_mm: f64,
    /// The position, physical XYZ mm.
    pub at: [f64; 3],
    /// The job's line of the nearest move; `None` for a line sent before the job.
    pub line: Option<usize>,
}

impl TraceCheck {
    /// Whether the steps stray farther than one step from the toolpath, or never come to a
    /// stretch of it.
    pub fn fails(&self) -> bool {
        self.missed.is_some() || self.farthest.is_some_and(|f| f.distance_mm > self.step_mm)
    }

    /// The error a failed check is: the steps strayed more than a step from the toolpath
    /// (how far, where, near which line), or never came to where the program goes on after a
    /// homing line. `None` for a check that passes.
    pub fn error(&self) -> Option<PlotError> {
        if let Some(m) = self.missed {
            return Some(PlotError(format!(
                "the steps never come to {}, where the program goes on after homing{}: the \
                 step trace is not this job's, or ends before",
                position(m.from),
                m.line.map_or_else(String::new, |n| format!(" (line {n})"))
            )));
        }
        let f = self.farthest.filter(|f| f.distance_mm > self.step_mm)?;
        Some(PlotError(format!(
            "the steps strayed {:.4} mm from the toolpath at {}{}, more than one step ({:.4} mm)",
            f.distance_mm,
            position(f.at),
            f.line.map_or_else(String::new, |n| format!(" (line {n})")),
            self.step_mm
        )))
    }
}

impl fmt::Display for TraceCheck {
    /// The line of the plot's summary: `trace: farthest from the toolpath 0.0089 mm (one step:
    /// 0.0125 mm), at 612000 positions in X/Y/Z`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.farthest {
            Some(d) => write!(
                f,
                "trace: farthest from the toolpath {:.4} mm (one step: {:.4} mm), at {} \
                 positions in X/Y/Z",
                d.distance_mm, self.step_mm, self.measured
            ),
            None => write!(
                f,
                "trace: no position measured against the toolpath (one step: {:.4} mm)",
                self.step_mm
            ),
        }
    }
}

/// `X10.000 Y20.000 Z5.000`.
fn position(p: [f64; 3]) -> String {
    format!("X{:.3} Y{:.3} Z{:.3}", p[0], p[1], p[2])
}

/// A step of [`Replay::steps`] in the negative direction.
const NEGATIVE: u8 = 4;
/// A step of [`Replay::steps`] made at the same tick as the next one.
const SAME_INSTANT: u8 = 8;

/// The steps of X, Y and Z of a trace, one byte each: what [`Executed::check`] walks.
#[derive(Clone, Default, PartialEq)]
struct Replay {
    /// The steps per mm and start position (mm) of X, Y and Z; `None` for an axis the trace
    /// does not have.
    axes: [Option<(f64, f64)>; 3],
    /// Each step of X, Y or Z in time order: the axis (0, 1, 2), with [`NEGATIVE`] for a step
    /// in the negative direction and [`SAME_INSTANT`] when the next step comes at the same
    /// tick.
    steps: Vec<u8>,
}

impl fmt::Debug for Replay {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Replay")
            .field("axes", &self.axes)
            .field("steps", &self.steps.len())
            .finish()
    }
}

/// A place in a [`Replay`]: how many of its steps are made, and the step counts they add up
/// to.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct At {
    made: usize,
    steps: [i64; 3],
}

impl Replay {
    /// One step, mm: the largest mm per step of the axes; `None` without X, Y or Z.
    fn step_mm(&self) -> Option<f64> {
        self.axes
            .iter()
            .flatten()
            .map(|&(per_mm, _)| 1.0 / per_mm)
            .max_by(f64::total_cmp)
    }

    /// The physical position of `at`, XYZ mm.
    fn position(&self, at: At) -> [f64; 3] {
        core::array::from_fn(|k| {
            self.axes[k].map_or(0.0, |(per_mm, start)| start + at.steps[k] as f64 / per_mm)
        })
    }

    /// Move `at` on to the next instant of the trace (its next step and any other at the same
    /// tick) and give the position there; `None` at the trace's end.
    fn next(&self, at: &mut At) -> Option<[f64; 3]> {
        if at.made >= self.steps.len() {
            return None;
        }
        while let Some(&code) = self.steps.get(at.made) {
            at.made += 1;
            let k = usize::from(code & 3);
            at.steps[k] += if code & NEGATIVE != 0 { -1 } else { 1 };
            if code & SAME_INSTANT == 0 {
                break;
            }
        }
        Some(self.position(*at))
    }
}

/// How many moves after the cursor's the trace is looked for on when it leaves the cursor's
/// move: more than an instant can pass (chords of an arc shorter than a step), or the cursor
/// can lag behind (on a line run back and forth over itself, it stays on the first move).
const AHEAD: usize = 64;
/// Moves before the cursor the trace may still be on (at a corner).
const BEHIND: usize = 2;
/// Moves before and after the cursor looked at once the trace strayed (a failure's report):
/// off the toolpath the trace may be nearest to a later move that crosses its way, and the
/// move it is really beside must stay in sight; fewer than [`AHEAD`], so that a trace far off
/// all along costs little.
const ASTRAY_REACH: usize = 16;

/// Moves of a toolpath between homing lines.
struct Stretch<'a> {
    moves: &'a [Move],
    /// A homing line comes before it: the trace comes to its start by the homing cycle.
    after_homing: bool,
    /// A homing line comes after it: the trace leaves its end for the homing cycle.
    homing_after: bool,
}

/// What the positions measured on a stretch came to.
#[derive(Clone, Copy, Debug, Default)]
struct Tally {
    farthest: Option<Deviation>,
    measured: u64,
}

impl Tally {
    fn farthest_mm(&self) -> f64 {
        self.farthest.map_or(-1.0, |f| f.distance_mm)
    }

    fn raise(&mut self, d: Deviation) {
        if d.distance_mm > self.farthest_mm() {
            self.farthest = Some(d);
        }
    }

    fn add(&mut self, other: Tally) {
        if let Some(f) = other.farthest {
            self.raise(f);
        }
        self.measured += other.measured;
    }
}

/// How following a stretch from a place of the trace ends.
enum Followed {
    /// Followed to the stretch's end: the trace ends, or leaves the end for the homing cycle
    /// after it at `at`.
    Done(At),
    /// More than a step from every move near the cursor, at `at`; `settled`: after the trace
    /// left the line through the stretch's start along a single axis (see [`Checker::follow`]).
    Strayed {
        at: At,
        cursor: usize,
        settled: bool,
    },
    /// The trace ends before the stretch does, not settled.
    Unfinished,
}

/// Whether the trace came to the end of a stretch's moves: within a step of the last move's
/// start with the last move in sight of the cursor, then of its end; and whether it leaves
/// the end again.
struct EndWatch {
    last: usize,
    last_from: [f64; 3],
    end: [f64; 3],
    /// 0: not yet; 1: at the last move's start; 2: then at its end.
    phase: u8,
    /// In phase 2: the nearest the trace came to the end, mm.
    nearest_mm: f64,
}

impl EndWatch {
    fn new(moves: &[Move]) -> Self {
        let last = moves.len() - 1;
        Self {
            last,
            last_from: moves[last].from,
            end: moves[last].to,
            phase: 0,
            nearest_mm: f64::INFINITY,
        }
    }

    /// Whether the trace, at `p`, came to the end and now goes away from it: on the last move
    /// each instant takes it nearer the end, so a step away is the next move's (a homing
    /// cycle's).
    fn leaving(&mut self, p: [f64; 3]) -> bool {
        if self.phase < 2 {
            return false;
        }
        let d = distance(p, self.end);
        if d > self.nearest_mm {
            return true;
        }
        self.nearest_mm = d;
        false
    }

    /// The trace at `p`, with the moves up to `sight` in view of the cursor; it comes to a
    /// point within `reach_mm` of it.
    fn see(&mut self, p: [f64; 3], sight: usize, reach_mm: f64) {
        if sight < self.last {
            return;
        }
        if self.phase == 0 && distance(p, self.last_from) <= reach_mm {
            self.phase = 1;
        }
        if self.phase == 1 && distance(p, self.end) <= reach_mm {
            self.phase = 2;
            self.nearest_mm = distance(p, self.end);
        }
    }

    fn reached(&self) -> bool {
        self.phase == 2
    }
}

/// A check of a trace against a toolpath, stretch by stretch.
struct Checker<'a> {
    replay: &'a Replay,
    /// One step, mm: how far the trace may be from the moves.
    step_mm: f64,
}

/// The distance from `p` to the segment `m`, mm.
fn segment_distance(p: [f64; 3], m: &Move) -> f64 {
    let d: [f64; 3] = core::array::from_fn(|k| m.to[k] - m.from[k]);
    let w: [f64; 3] = core::array::from_fn(|k| p[k] - m.from[k]);
    let dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    let t = if dd > 0.0 {
        ((w[0] * d[0] + w[1] * d[1] + w[2] * d[2]) / dd).clamp(0.0, 1.0)
    } else {
        0.0
    };
    distance(p, core::array::from_fn(|k| m.from[k] + t * d[k]))
}

impl Checker<'_> {
    /// The nearest to `p` of the moves from `behind` before `cursor` to `ahead` after it: its
    /// distance and index.
    fn nearest(
        &self,
        moves: &[Move],
        cursor: usize,
        behind: usize,
        ahead: usize,
        p: [f64; 3],
    ) -> (f64, usize) {
        let last = (cursor + ahead).min(moves.len() - 1);
        (cursor.saturating_sub(behind)..=last)
            .map(|k| (segment_distance(p, &moves[k]), k))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .unwrap_or((f64::INFINITY, cursor))
    }

    /// Whether `p` is within a step of the move at `cursor`, else of the first of the
    /// `ahead` after it that is (the cursor moved on to it), else of one just before it; the
    /// distance to it.
    fn on(&self, moves: &[Move], cursor: &mut usize, ahead: usize, p: [f64; 3]) -> Option<f64> {
        let d = segment_distance(p, &moves[*cursor]);
        if d <= self.step_mm {
            return Some(d);
        }
        let last = (*cursor + ahead).min(moves.len() - 1);
        let first = *cursor + 1;
        let next = moves[first..=last]
            .iter()
            .map(|m| segment_distance(p, m))
            .enumerate()
            .find(|&(_, d)| d <= self.step_mm);
        if let Some((k, d)) = next {
            *cursor = first + k;
            return Some(d);
        }
        (cursor.saturating_sub(BEHIND)..*cursor)
            .map(|k| segment_distance(p, &moves[k]))
            .find(|&d| d <= self.step_mm)
    }

    /// Follow `stretch` from `at`, where the trace stands at its start. The trace may be on
    /// the stretch's start by chance during a homing cycle, which moves one axis at a time:
    /// unless `settled`, the following is settled only once the trace stands off the start in
    /// two axes, or comes to the stretch's end; until then a stray means the lock was wrong.
    fn follow(&self, stretch: &Stretch<'_>, mut at: At, mut settled: bool) -> (Followed, Tally) {
        let moves = stretch.moves;
        let start = moves[0].from;
        let mut cursor = 0;
        let mut end = EndWatch::new(moves);
        let mut tally = Tally::default();
        let mut p = self.replay.position(at);
        loop {
            if stretch.homing_after && end.leaving(p) {
                return (Followed::Done(at), tally);
            }
            let Some(d) = self.on(moves, &mut cursor, AHEAD, p) else {
                if stretch.homing_after && end.reached() {
                    return (Followed::Done(at), tally);
                }
                return (
                    Followed::Strayed {
                        at,
                        cursor,
                        settled,
                    },
                    tally,
                );
            };
            tally.measured += 1;
            if d > tally.farthest_mm() {
                let (d, k) = self.nearest(moves, cursor, BEHIND, AHEAD, p);
                tally.raise(Deviation {
                    distance_mm: d,
                    at: p,
                    line: moves[k].line,
                });
            }
            end.see(p, cursor + AHEAD, self.step_mm);
            if !settled {
                let off = (0..3)
                    .filter(|&k| (p[k] - start[k]).abs() > self.step_mm)
                    .count();
                settled = off >= 2 || end.reached();
            }
            match self.replay.next(&mut at) {
                Some(q) => p = q,
                None if settled => return (Followed::Done(at), tally),
                None => return (Followed::Unfinished, tally),
            }
        }
    }

    /// The farthest point from `stretch` of the trace from `at`, where it strays at `cursor`,
    /// to the stretch's end (where the trace leaves it for a homing cycle, the end within as
    /// far as the trace strayed; or the trace's end): the distance to the nearest of the
    /// moves up to [`ASTRAY_REACH`] before or after the cursor, which goes on to that move.
    fn astray(&self, stretch: &Stretch<'_>, mut at: At, mut cursor: usize) -> (Deviation, u64) {
        let moves = stretch.moves;
        let mut end = EndWatch::new(moves);
        let mut p = self.replay.position(at);
        let mut worst: Option<Deviation> = None;
        let mut measured = 0;
        loop {
            if stretch.homing_after && end.leaving(p) {
                break;
            }
            let (d, k) = self.nearest(moves, cursor, ASTRAY_REACH, ASTRAY_REACH, p);
            if d > self.step_mm && stretch.homing_after && end.reached() {
                break;
            }
            measured += 1;
            if worst.is_none_or(|w| d > w.distance_mm) {
                worst = Some(Deviation {
                    distance_mm: d,
                    at: p,
                    line: moves[k].line,
                });
            }
            cursor = cursor.max(k);
            // Off by as much as the trace strayed.
            let reach = worst.map_or(self.step_mm, |w| w.distance_mm.max(self.step_mm));
            end.see(p, cursor + ASTRAY_REACH, reach);
            match self.replay.next(&mut at) {
                Some(q) => p = q,
                None => break,
            }
        }
        let worst = worst.unwrap_or(Deviation {
            distance_mm: f64::INFINITY,
            at: p,
            line: moves[cursor].line,
        });
        (worst, measured)
    }

    /// Check the trace from `at` against `stretch`: where the trace goes on from (its end, or
    /// where it leaves the stretch's end for a homing cycle) and what was measured, or the
    /// failure.
    fn stretch(&self, stretch: &Stretch<'_>, at: At) -> Result<(At, Tally), Failure> {
        if !stretch.after_homing {
            return match self.follow(stretch, at, true) {
                (Followed::Done(at), tally) => Ok((at, tally)),
                (Followed::Strayed { at, cursor, .. }, tally) => Err(Failure {
                    stray: Some(self.astray(stretch, at, cursor)),
                    tally,
                }),
                // Not when settled from the start: the trace's end is the stretch's.
                (Followed::Unfinished, tally) => Ok((at, tally)),
            };
        }
        // The trace comes to the stretch's start at the end of the homing cycle, and may pass
        // it before: each arrival there is tried, the first the trace follows to the end (or
        // settles on) is taken. When none is, the one followed longest is the failure.
        let start = stretch.moves[0].from;
        let mut at = at;
        let mut p = self.replay.position(at);
        let mut there = false;
        let mut best: Option<(usize, At, usize, Tally)> = None;
        loop {
            let arrived = distance(p, start) <= self.step_mm;
            if arrived && !there {
                // The lock starts where the trace comes nearest the start.
                let mut next = at;
                while let Some(q) = self.replay.next(&mut next)
                    && distance(q, start) < distance(p, start)
                {
                    (at, p) = (next, q);
                }
                match self.follow(stretch, at, false) {
                    (Followed::Done(next), tally) => return Ok((next, tally)),
                    (
                        Followed::Strayed {
                            at: off,
                            cursor,
                            settled: true,
                        },
                        tally,
                    ) => {
                        return Err(Failure {
                            stray: Some(self.astray(stretch, off, cursor)),
                            tally,
                        });
                    }
                    (
                        Followed::Strayed {
                            at: off, cursor, ..
                        },
                        tally,
                    ) => {
                        let lasted = off.made - at.made;
                        if best.is_none_or(|(l, ..)| lasted >= l) {
                            best = Some((lasted, off, cursor, tally));
                        }
                    }
                    (Followed::Unfinished, _) => {}
                }
            }
            there = arrived;
            match self.replay.next(&mut at) {
                Some(q) => p = q,
                None => break,
            }
        }
        Err(match best {
            Some((_, off, cursor, tally)) => Failure {
                stray: Some(self.astray(stretch, off, cursor)),
                tally,
            },
            None => Failure {
                stray: None,
                tally: Tally::default(),
            },
        })
    }
}

/// A stretch the trace does not follow: where it strays the farthest and how many positions
/// were measured from where it strayed ([`Checker::astray`]), or `None` when it never comes to
/// the stretch's start; what was measured before.
struct Failure {
    stray: Option<(Deviation, u64)>,
    tally: Tally,
}

impl Executed {
    /// Hold the steps to `path`'s geometry: the largest distance from any position the trace
    /// passes through (after each step, all axes at that instant) to the nearest point of
    /// `path`'s [moves](Toolpath::moves), in X, Y and Z (a rotary axis and an extruder left
    /// out). A correct run stays within one step ([`TraceCheck::step_mm`]): the kernel follows
    /// its straight moves and arc chords without cutting corners, from end to end on the step
    /// grid (the moves' ends are rounded to whole steps as the kernel rounds its targets), and
    /// each axis steps where its ideal position crosses a half step, so it is within half a
    /// step an axis of the line between them.
    ///
    /// The trace and the moves are walked together, in order: a cursor on the move the trace
    /// follows goes on to the next one within a step when the trace leaves it (up to 64 moves
    /// on), so a trace of millions of steps costs a few distances a step. The homing cycle's
    /// moves are not the program's and are not measured: at a homing line the trace leaves
    /// the program's path where it goes away from the end of the moves before it, and comes
    /// back where it comes to the start of the moves after it and follows them. The cycle
    /// may pass that point before, but moving one axis only: an arrival counts once the
    /// trace, following the moves, stands off it in two axes (or comes to their end), and one
    /// that strays before is dropped for the next.
    ///
    /// From the first position farther than a step from the moves near the cursor on, the
    /// cursor goes on to the nearest of the moves 16 around it, to the end of the stretch of
    /// moves between homing lines, and measuring stops there: [`TraceCheck::farthest`] is the
    /// farthest point of that stretch from the moves around where the program was.
    ///
    /// `None` for a path not replayed from a trace, or from a trace without X, Y or Z.
    pub fn check(&self, path: &Toolpath) -> Option<TraceCheck> {
        let replay = self.replay.as_ref()?;
        let step_mm = replay.step_mm()?;
        let checker = Checker { replay, step_mm };
        let mut check = TraceCheck {
            step_mm,
            farthest: None,
            measured: 0,
            missed: None,
        };
        let mut tally = Tally::default();
        let mut at = At::default();
        for (i, stretch) in stretches(path).iter().enumerate() {
            if i > 0 && at.made >= replay.steps.len() {
                // The trace ends before the homing line: nothing more to hold it to.
                break;
            }
            match checker.stretch(stretch, at) {
                Ok((next, t)) => {
                    tally.add(t);
                    at = next;
                }
                Err(failure) => {
                    tally.add(failure.tally);
                    match failure.stray {
                        Some((stray, measured)) => {
                            tally.raise(stray);
                            tally.measured += measured;
                        }
                        None => check.missed = Some(stretch.moves[0]),
                    }
                    break;
                }
            }
        }
        check.farthest = tally.farthest;
        check.measured = tally.measured;
        Some(check)
    }
}

/// The stretches of `path`'s moves between its homing lines, those with moves.
fn stretches(path: &Toolpath) -> Vec<Stretch<'_>> {
    let mut bounds = vec![0];
    bounds.extend(path.homings.iter().copied());
    bounds.push(path.moves.len());
    bounds
        .windows(2)
        .filter(|w| w[0] < w[1])
        .map(|w| Stretch {
            moves: &path.moves[w[0]..w[1]],
            after_homing: path.homings.contains(&w[0]),
            homing_after: path.homings.contains(&w[1]),
        })
        .collect()
}

const FEED: RGBColor = RGBColor(120, 170, 235);
/// Moves that neither cut nor lay material: rapids, and a printer's travel.
const TRAVEL: RGBColor = RGBColor(150, 150, 150);
/// The extrusion of a single layer.
const EXTRUSION: RGBColor = RGBColor(30, 100, 200);
/// The extrusion of layers, from the lowest drawn to the highest (none of them red, the
/// executed path's colour).
const LAYER_RAMP: [RGBColor; 4] = [
    RGBColor(70, 40, 150),
    RGBColor(30, 100, 200),
    RGBColor(10, 155, 150),
    RGBColor(80, 170, 40),
];
const EXECUTED: RGBColor = RGBColor(220, 40, 40);
const REFUSED: RGBColor = RGBColor(200, 0, 140);
const BED: RGBColor = RGBColor(246, 242, 232);
const BED_EDGE: RGBColor = RGBColor(185, 170, 140);
const GRID: RGBColor = RGBColor(228, 228, 228);
const INK: RGBColor = RGBColor(40, 40, 40);

/// Pixels per font pixel.
const TEXT_SCALE: i32 = 2;
/// Width of the image, pixels.
const WIDTH: u32 = 1200;
/// Layers named one by one in the legend; more are shown as a colour ramp.
const LEGEND_LAYERS: usize = 16;

/// The image formats [`render`] writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    /// A PNG bitmap.
    Png,
    /// An SVG drawing.
    Svg,
}

impl ImageFormat {
    /// The format of `out`, told by its extension (`.png` or `.svg`, in any case).
    ///
    /// Errors: another extension, or none.
    pub fn of(out: &Path) -> Result<Self, PlotError> {
        let ext = out
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("png") => Ok(Self::Png),
            Some("svg") => Ok(Self::Svg),
            _ => Err(PlotError(format!(
                "cannot tell the image format of {}: name it .png or .svg",
                out.display()
            ))),
        }
    }
}

/// Draw `path` (and `executed`, if given) to `out`, a `.png` or `.svg` file, as `options`
/// say, under a title that starts with `name` and says which layers are drawn.
///
/// A trace's steps are held to the toolpath ([`Executed::check`]) and the result printed on
/// stdout, a line of the plot's summary (`trace: farthest from the toolpath 0.0089 mm (one
/// step: 0.0125 mm), …`); where they strayed farther than a step is marked on the plot.
///
/// Errors: another extension, layers the job does not have ([`Toolpath::select_layers`]),
/// nothing to draw, or the file cannot be written; after the plot is drawn, steps that stray
/// farther than one step from the toolpath or never come to it ([`TraceCheck::error`]).
pub fn render(
    out: &Path,
    name: &str,
    path: &Toolpath,
    executed: Option<&Executed>,
    options: &PlotOptions,
) -> Result<(), PlotError> {
    let format = ImageFormat::of(out)?;
    let check = executed.and_then(|ex| ex.check(path));
    let mut scene = Scene::new(name, path, executed, options)?;
    if let Some(check) = &check {
        let mark = match (check.missed, check.farthest) {
            (Some(m), _) => Some((m.from, "the steps never come here".to_string())),
            (None, Some(f)) if check.fails() => {
                Some((f.at, format!("the steps strayed {:.3} mm", f.distance_mm)))
            }
            _ => None,
        };
        if let Some((at, label)) = mark {
            scene.strays.push(([at[0], at[1]], label));
        }
    }
    let size = (WIDTH, scene.layout.height);
    let result = match format {
        ImageFormat::Png => {
            let root = BitMapBackend::new(out, size).into_drawing_area();
            draw(&root, &scene).and_then(|()| root.present().map_err(|e| e.to_string()))
        }
        ImageFormat::Svg => {
            let root = SVGBackend::new(out, size).into_drawing_area();
            draw(&root, &scene).and_then(|()| root.present().map_err(|e| e.to_string()))
        }
    };
    result.map_err(|e| PlotError(format!("cannot write {}: {e}", out.display())))?;
    if let Some(check) = &check {
        println!("{check}");
        if let Some(e) = check.error() {
            return Err(PlotError(format!(
                "{e} (the plot, drawn to {}, marks where)",
                out.display()
            )));
        }
    }
    Ok(())
}

/// How a polyline is drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Pen {
    /// Solid, `width` pixels wide.
    Solid(RGBColor, u32),
    /// Thin and dashed.
    Dashed(RGBColor),
}

/// An entry of the legend: a sample of how a thing is drawn, and its name.
struct Entry {
    sample: Option<Sample>,
    name: String,
}

enum Sample {
    Line(Pen),
    Area(RGBColor, RGBColor),
    Cross(RGBColor),
}

/// What is drawn, where, and with what words.
struct Scene {
    title: String,
    /// The legend, a row of entries a line.
    rows: Vec<Vec<Entry>>,
    /// What the plot warns of, under the legend.
    warning: Option<String>,
    /// The polylines, XY mm, in drawing order.
    strokes: Vec<(Vec<[f64; 2]>, Pen)>,
    /// The extrusion drawn, for the overview: points and colour.
    extrusion: Vec<(Vec<[f64; 2]>, RGBColor)>,
    bed: Option<[f64; 4]>,
    /// The refused lines: where the tool stood, and which line it is.
    refused: Vec<([f64; 2], String)>,
    /// Where the steps strayed from the toolpath, and how far.
    strays: Vec<([f64; 2], String)>,
    layout: Layout,
}

impl Scene {
    /// What a plot of `path` (and `executed`) as `options` say shows, under a title that
    /// starts with `name`.
    ///
    /// Errors: layers the job does not have, nothing to draw.
    fn new(
        name: &str,
        path: &Toolpath,
        executed: Option<&Executed>,
        options: &PlotOptions,
    ) -> Result<Self, PlotError> {
        let span = match options.layers {
            Some(range) => Some(path.select_layers(range)?),
            None => None,
        };
        let drawn_layers = span
            .clone()
            .or_else(|| (!path.layers.is_empty()).then(|| 0..=path.layers.len() - 1));
        let colour_of = |layer: Option<usize>| match (&drawn_layers, layer) {
            (Some(s), Some(l)) if s.start() != s.end() => {
                layer_colour((l - s.start()) as f64 / (s.end() - s.start()) as f64)
            }
            _ => EXTRUSION,
        };

        // Extrusion, lower layers first so that each lies over the one below; then feeds and
        // rapids in program order, then travel over them.
        let chosen = path.polylines.iter().filter(|p| match &span {
            None => true,
            Some(s) => p.layer.is_some_and(|l| s.contains(&l)),
        });
        let mut extrusion: Vec<&Polyline> = Vec::new();
        let mut others: Vec<(Vec<[f64; 2]>, Pen)> = Vec::new();
        let mut travel: Vec<(Vec<[f64; 2]>, Pen)> = Vec::new();
        for p in chosen {
            match p.kind {
                PathKind::Extrusion => extrusion.push(p),
                PathKind::Feed => others.push((p.points.clone(), Pen::Solid(FEED, 3))),
                PathKind::Rapid if !options.hide_travel => {
                    others.push((p.points.clone(), Pen::Dashed(TRAVEL)));
                }
                PathKind::Travel if !options.hide_travel => {
                    travel.push((p.points.clone(), Pen::Dashed(TRAVEL)));
                }
                PathKind::Travel | PathKind::Rapid => {}
            }
        }
        extrusion.sort_by_key(|p| p.layer);
        let executed_runs: Vec<Vec<[f64; 2]>> = match (executed, &span) {
            (Some(ex), Some(s)) => ex.within([
                path.layers[*s.start()].z_mm[0],
                path.layers[*s.end()].z_mm[1],
            ]),
            (Some(ex), None) => vec![ex.points.iter().map(|p| [p[0], p[1]]).collect()],
            (None, _) => Vec::new(),
        };

        // The view: the part, from the extrusion drawn; without extrusion, all that is drawn.
        let mut view = part_bounds(path, &extrusion);
        if view.is_empty() {
            for (points, _) in others.iter().chain(&travel) {
                view.take(points);
            }
            for run in &executed_runs {
                view.take(run);
            }
        }
        let Some(view) = view.get() else {
            return Err(PlotError(if span.is_some() {
                "nothing to draw: the layers chosen make no move in X or Y".into()
            } else {
                "nothing to draw: the program makes no move in X or Y".into()
            }));
        };

        let title = if path.printer {
            format!("{name}: {}", path.describe_layers(span.clone()))
        } else {
            name.to_string()
        };
        let rows = legend(path, executed, options, drawn_layers.clone(), &colour_of);
        let warning = match path.refused.as_slice() {
            [] => None,
            [one] => Some(format!(
                "the kernel refuses {}: the machine runs the job without it",
                line_name(one)
            )),
            [first, ..] => Some(format!(
                "the kernel refuses {} lines ({} first): the machine runs the job without them",
                path.refused.len(),
                line_name(first)
            )),
        };
        let text_rows = rows.len() + usize::from(warning.is_some());
        let mut layout = Layout::new(view, text_rows, false);
        // Extrusion outside the view (a purge line), or a refused line: an overview beside
        // shows the whole of it.
        let mut whole = Bounds::default();
        for p in &extrusion {
            whole.take(&p.points);
        }
        for r in &path.refused {
            whole.take(&[r.at]);
        }
        if whole.get().is_some_and(|w| !contains(layout.bounds, w)) {
            layout = Layout::new(view, text_rows, true);
            let b = layout.bounds;
            whole.take(&[[b[0], b[1]], [b[2], b[3]]]);
            if let Some(bed) = path.bed {
                whole.take(&[[bed[0], bed[1]], [bed[2], bed[3]]]);
            }
            layout.overview = whole.get();
        }

        let width = extrusion_width_px(layout.scale);
        let mut strokes: Vec<(Vec<[f64; 2]>, Pen)> = extrusion
            .iter()
            .map(|p| (p.points.clone(), Pen::Solid(colour_of(p.layer), width)))
            .collect();
        strokes.extend(others);
        strokes.extend(travel);
        strokes.extend(
            executed_runs
                .into_iter()
                .map(|run| (run, Pen::Solid(EXECUTED, 1))),
        );
        Ok(Self {
            title,
            rows,
            warning,
            strokes,
            extrusion: extrusion
                .iter()
                .map(|p| (p.points.clone(), colour_of(p.layer)))
                .collect(),
            bed: path.bed,
            strays: Vec::new(),
            refused: path
                .refused
                .iter()
                .map(|r| {
                    let name = r.line.map_or_else(|| "G28".into(), |n| format!("line {n}"));
                    (r.at, name)
                })
                .collect(),
            layout,
        })
    }
}

/// About the width of a 0.45 mm extrusion drawn at `scale` pixels per mm, halved so that the
/// lines stay apart, 2 to 6 pixels.
fn extrusion_width_px(scale: f64) -> u32 {
    (0.45 * scale * 0.5).round().clamp(2.0, 6.0) as u32
}

/// The legend of a plot of `path`: the extrusion's layers (`drawn`) on a row of their own,
/// then how the rest is drawn.
fn legend(
    path: &Toolpath,
    executed: Option<&Executed>,
    options: &PlotOptions,
    drawn: Option<RangeInclusive<usize>>,
    colour_of: &dyn Fn(Option<usize>) -> RGBColor,
) -> Vec<Vec<Entry>> {
    let entry = |sample: Sample, name: &str| Entry {
        sample: Some(sample),
        name: name.into(),
    };
    let hidden = |name: &str| {
        if options.hide_travel {
            format!("{name} (hidden)")
        } else {
            name.to_string()
        }
    };
    let mut rows = Vec::new();
    let mut row = Vec::new();
    if path.printer {
        rows.push(layer_legend(path, drawn, colour_of));
        row.push(entry(Sample::Line(Pen::Dashed(TRAVEL)), &hidden("travel")));
    } else {
        row.push(entry(Sample::Line(Pen::Solid(FEED, 2)), "feed"));
        row.push(entry(Sample::Line(Pen::Dashed(TRAVEL)), &hidden("rapid")));
    }
    if path.bed.is_some() {
        let name = if path.printer { "bed" } else { "X/Y travel" };
        row.push(entry(Sample::Area(BED, BED_EDGE), name));
    }
    if executed.is_some() {
        row.push(entry(
            Sample::Line(Pen::Solid(EXECUTED, 2)),
            "executed (step trace)",
        ));
    }
    if !path.refused.is_empty() {
        row.push(entry(Sample::Cross(REFUSED), "refused line"));
    }
    rows.push(row);
    rows
}

/// `line 26 (G28W)`, or the `G28` before the job.
fn line_name(r: &Refusal) -> String {
    match r.line {
        Some(n) => format!("line {n} ({})", r.text),
        None => format!("the {} before the job", r.text),
    }
}

/// The legend of the extrusion: each layer drawn with its colour, or the ramp's ends when
/// there are many.
fn layer_legend(
    path: &Toolpath,
    drawn: Option<RangeInclusive<usize>>,
    colour_of: &dyn Fn(Option<usize>) -> RGBColor,
) -> Vec<Entry> {
    let Some(drawn) = drawn else {
        return vec![Entry {
            sample: None,
            name: "extrusion: none".into(),
        }];
    };
    let line = |layer: usize, name: String| Entry {
        sample: Some(Sample::Line(Pen::Solid(colour_of(Some(layer)), 3))),
        name,
    };
    if drawn.start() == drawn.end() {
        return vec![line(*drawn.start(), "extrusion".into())];
    }
    let z = |l: usize| label(path.layers[l].z_mm[0]);
    if drawn.clone().count() <= LEGEND_LAYERS {
        let mut row = vec![Entry {
            sample: None,
            name: "extrusion by layer:".into(),
        }];
        row.extend(drawn.map(|l| line(l, format!("{}", l + 1))));
        row
    } else {
        let (first, last) = (*drawn.start(), *drawn.end());
        vec![
            line(
                first,
                format!("extrusion, layer {} (Z {})", first + 1, z(first)),
            ),
            line((first + last) / 2, "to".into()),
            line(last, format!("layer {} (Z {})", last + 1, z(last))),
        ]
    }
}

/// How far from the extrusion of the layers above the first the extrusion drawn still frames
/// the part, at least, mm: a skirt or a brim is in the view, a purge line along the bed's edge
/// is not.
const PART_REACH_MM: f64 = 15.0;

/// The view of a printer's extrusion `drawn`: the part. The part is the extrusion of the job's
/// layers above the first (whose extrusion holds what a start G-code purges); the extrusion
/// drawn within [`PART_REACH_MM`] of it, or half its size, is framed. All of `drawn` when the
/// job has one layer, or when none of `drawn` is near the part.
fn part_bounds(path: &Toolpath, drawn: &[&Polyline]) -> Bounds {
    let mut part = Bounds::default();
    for p in &path.polylines {
        if p.kind == PathKind::Extrusion && p.layer.is_some_and(|l| l > 0) {
            part.take(&p.points);
        }
    }
    let mut view = Bounds::default();
    if let Some(core) = part.get() {
        let reach = (0.5 * (core[2] - core[0]).max(core[3] - core[1])).max(PART_REACH_MM);
        let near = [
            core[0] - reach,
            core[1] - reach,
            core[2] + reach,
            core[3] + reach,
        ];
        for q in drawn.iter().flat_map(|p| &p.points) {
            if contains(near, [q[0], q[1], q[0], q[1]]) {
                view.take(&[*q]);
            }
        }
    }
    if view.is_empty() {
        for p in drawn {
            view.take(&p.points);
        }
    }
    view
}

/// Whether the rectangle `outer` (x0, y0, x1, y1) holds the rectangle `inner`.
fn contains(outer: [f64; 4], inner: [f64; 4]) -> bool {
    outer[0] <= inner[0] && outer[1] <= inner[1] && inner[2] <= outer[2] && inner[3] <= outer[3]
}

/// The colour of the layer at `t` from the lowest drawn (0) to the highest (1).
fn layer_colour(t: f64) -> RGBColor {
    let t = t.clamp(0.0, 1.0) * (LAYER_RAMP.len() - 1) as f64;
    let k = (t.floor() as usize).min(LAYER_RAMP.len() - 2);
    let f = t - k as f64;
    let (a, b) = (LAYER_RAMP[k], LAYER_RAMP[k + 1]);
    let mix = |x: u8, y: u8| (f64::from(x) + (f64::from(y) - f64::from(x)) * f).round() as u8;
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

/// The smallest rectangle around some points, mm.
#[derive(Clone, Copy, Debug)]
struct Bounds([f64; 4]);

impl Default for Bounds {
    fn default() -> Self {
        Self([
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ])
    }
}

impl Bounds {
    fn take(&mut self, points: &[[f64; 2]]) {
        for p in points {
            let b = &mut self.0;
            *b = [
                b[0].min(p[0]),
                b[1].min(p[1]),
                b[2].max(p[0]),
                b[3].max(p[1]),
            ];
        }
    }

    fn is_empty(&self) -> bool {
        self.get().is_none()
    }

    /// x0, y0, x1, y1; `None` before any point.
    fn get(&self) -> Option<[f64; 4]> {
        self.0.iter().all(|v| v.is_finite()).then_some(self.0)
    }
}

struct Layout {
    height: u32,
    /// What the overview beside the plot shows, mm: x0, y0, x1, y1; `None`: no overview.
    overview: Option<[f64; 4]>,
    /// The view, mm: x0, y0, x1, y1.
    bounds: [f64; 4],
    /// Pixels per mm.
    scale: f64,
    origin: (f64, f64),
}

const MARGIN_LEFT: f64 = 110.0;
const MARGIN_RIGHT: f64 = 30.0;
/// Width of the overview beside the plot, pixels.
const OVERVIEW_WIDTH: f64 = 270.0;
const MARGIN_BOTTOM: f64 = 50.0;
/// Where the title is, and the height of a line of text under it, pixels.
const TITLE_Y: i32 = 16;
const ROW_HEIGHT: i32 = 30;

impl Layout {
    /// A view of `b` (mm) with a margin around it, under `rows` lines of text, with room for an
    /// overview on its right when `beside`.
    fn new(b: [f64; 4], rows: usize, beside: bool) -> Self {
        let top = f64::from(TITLE_Y + 20 + ROW_HEIGHT * rows as i32 + 20);
        let (mut dx, mut dy) = (b[2] - b[0], b[3] - b[1]);
        let pad = (0.05 * dx.max(dy)).max(1.0);
        let b = [b[0] - pad, b[1] - pad, b[2] + pad, b[3] + pad];
        dx += 2.0 * pad;
        dy += 2.0 * pad;
        let right = if beside {
            MARGIN_RIGHT + OVERVIEW_WIDTH + MARGIN_RIGHT
        } else {
            MARGIN_RIGHT
        };
        let inner_w = f64::from(WIDTH) - MARGIN_LEFT - right;
        let scale = inner_w / dx;
        let least = if beside {
            top + OVERVIEW_WIDTH + 2.0 * f64::from(ROW_HEIGHT) + MARGIN_BOTTOM
        } else {
            360.0
        };
        let height = (dy * scale + top + MARGIN_BOTTOM).clamp(least, 1600.0);
        let inner_h = height - top - MARGIN_BOTTOM;
        let scale = scale.min(inner_h / dy);
        let origin = (
            MARGIN_LEFT + (inner_w - dx * scale) / 2.0,
            top + inner_h - (inner_h - dy * scale) / 2.0,
        );
        Self {
            height: height as u32,
            overview: None,
            bounds: b,
            scale,
            origin,
        }
    }

    fn px(&self, p: [f64; 2]) -> (i32, i32) {
        (
            (self.origin.0 + (p[0] - self.bounds[0]) * self.scale).round() as i32,
            (self.origin.1 - (p[1] - self.bounds[1]) * self.scale).round() as i32,
        )
    }
}

/// The part of the segment `a`–`b` inside `rect` (x0, y0, x1, y1), if any (Liang–Barsky).
fn clip(a: [f64; 2], b: [f64; 2], rect: [f64; 4]) -> Option<([f64; 2], [f64; 2])> {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-dx, a[0] - rect[0]),
        (dx, rect[2] - a[0]),
        (-dy, a[1] - rect[1]),
        (dy, rect[3] - a[1]),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else if p < 0.0 {
            t0 = t0.max(q / p);
        } else {
            t1 = t1.min(q / p);
        }
        if t0 > t1 {
            return None;
        }
    }
    Some((
        [a[0] + t0 * dx, a[1] + t0 * dy],
        [a[0] + t1 * dx, a[1] + t1 * dy],
    ))
}

/// The stretches of the polyline `points` inside `rect`.
fn clip_polyline(points: &[[f64; 2]], rect: [f64; 4]) -> Vec<Vec<[f64; 2]>> {
    let mut runs = Vec::new();
    let mut run: Vec<[f64; 2]> = Vec::new();
    for pair in points.windows(2) {
        match clip(pair[0], pair[1], rect) {
            Some((a, b)) => {
                if run.last() != Some(&a) {
                    if run.len() > 1 {
                        runs.push(core::mem::take(&mut run));
                    }
                    run = vec![a];
                }
                run.push(b);
            }
            None => {
                if run.len() > 1 {
                    runs.push(core::mem::take(&mut run));
                }
                run.clear();
            }
        }
    }
    if run.len() > 1 {
        runs.push(run);
    }
    runs
}

/// 1, 2 or 5 times a power of ten, about `range / 8`.
fn grid_step(range: f64) -> f64 {
    let raw = (range / 8.0).max(1e-6);
    let power = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * power)
        .find(|&s| s >= raw)
        .unwrap_or(10.0 * power)
}

fn label(v: f64) -> String {
    let text = format!("{v:.3}");
    let text = text.trim_end_matches('0').trim_end_matches('.');
    if text == "-0" {
        "0".into()
    } else {
        text.into()
    }
}

type DrawResult = Result<(), String>;

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, scene: &Scene) -> DrawResult {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    let layout = &scene.layout;
    let view = layout.bounds;
    root.fill(&WHITE).map_err(e)?;
    let [x0, y0, x1, y1] = view;
    let (left, top) = layout.px([x0, y1]);
    let (right, bottom) = layout.px([x1, y0]);

    // The bed, under everything.
    if let Some(bed) = scene.bed {
        let inside = [
            bed[0].max(x0),
            bed[1].max(y0),
            bed[2].min(x1),
            bed[3].min(y1),
        ];
        if inside[0] < inside[2] && inside[1] < inside[3] {
            root.draw(&Rectangle::new(
                [
                    layout.px([inside[0], inside[3]]),
                    layout.px([inside[2], inside[1]]),
                ],
                BED.filled(),
            ))
            .map_err(e)?;
        }
    }
    let step = grid_step((x1 - x0).max(y1 - y0));
    let mut gx = (x0 / step).ceil() * step;
    while gx <= x1 {
        let (x, _) = layout.px([gx, y0]);
        root.draw(&PathElement::new(vec![(x, top), (x, bottom)], GRID))
            .map_err(e)?;
        let text = label(gx);
        let w = text_width(&text);
        draw_text(root, x - w / 2, bottom + 10, &text, INK).map_err(e)?;
        gx += step;
    }
    let mut gy = (y0 / step).ceil() * step;
    while gy <= y1 {
        let (_, y) = layout.px([x0, gy]);
        root.draw(&PathElement::new(vec![(left, y), (right, y)], GRID))
            .map_err(e)?;
        let text = label(gy);
        draw_text(root, left - 12 - text_width(&text), y - 8, &text, INK).map_err(e)?;
        gy += step;
    }
    if let Some(bed) = scene.bed {
        let outline = [
            [bed[0], bed[1]],
            [bed[2], bed[1]],
            [bed[2], bed[3]],
            [bed[0], bed[3]],
            [bed[0], bed[1]],
        ];
        for run in clip_polyline(&outline, view) {
            let points = pixels(layout, &run);
            root.draw(&PathElement::new(points, BED_EDGE.stroke_width(2)))
                .map_err(e)?;
        }
    }
    root.draw(&Rectangle::new([(left, top), (right, bottom)], INK))
        .map_err(e)?;
    draw_text(root, right - text_width("mm"), bottom + 30, "mm", INK).map_err(e)?;

    for (points, pen) in &scene.strokes {
        for run in clip_polyline(points, view) {
            draw_polyline(root, pixels(layout, &run), *pen).map_err(e)?;
        }
    }
    let marks = scene.refused.iter().map(|(at, name)| (at, name, REFUSED));
    let strays = scene.strays.iter().map(|(at, name)| (at, name, EXECUTED));
    for (at, name, colour) in marks.chain(strays) {
        if !(x0..=x1).contains(&at[0]) || !(y0..=y1).contains(&at[1]) {
            continue;
        }
        let (x, y) = layout.px(*at);
        draw_cross(root, x, y, colour).map_err(e)?;
        draw_text(root, x + 10, y + 6, name, colour).map_err(e)?;
    }

    if let Some(whole) = layout.overview {
        draw_overview(root, scene, whole, top).map_err(e)?;
    }

    draw_text(root, 20, TITLE_Y, &scene.title, INK).map_err(e)?;
    let mut y = TITLE_Y + 20 + 12;
    for row in &scene.rows {
        let mut x = 20;
        for entry in row {
            match &entry.sample {
                None => {}
                Some(Sample::Line(pen)) => {
                    let sample = vec![(x, y + 8), (x + 30, y + 8)];
                    let pen = match *pen {
                        Pen::Solid(c, w) => Pen::Solid(c, w.max(2)),
                        dashed => dashed,
                    };
                    draw_polyline(root, sample, pen).map_err(e)?;
                    x += 38;
                }
                Some(Sample::Area(fill, edge)) => {
                    root.draw(&Rectangle::new([(x, y), (x + 30, y + 16)], fill.filled()))
                        .map_err(e)?;
                    root.draw(&Rectangle::new([(x, y), (x + 30, y + 16)], *edge))
                        .map_err(e)?;
                    x += 38;
                }
                Some(Sample::Cross(colour)) => {
                    draw_cross(root, x + 15, y + 8, *colour).map_err(e)?;
                    x += 38;
                }
            }
            draw_text(root, x, y, &entry.name, INK).map_err(e)?;
            x += text_width(&entry.name) + 24;
        }
        y += ROW_HEIGHT;
    }
    if let Some(warning) = &scene.warning {
        draw_text(root, 20, y, warning, REFUSED).map_err(e)?;
    }
    Ok(())
}

/// Draw the overview of `whole` (mm) beside the plot, its top at `top` pixels: the bed, the
/// extrusion drawn, the plot's view and the refused lines.
fn draw_overview<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    scene: &Scene,
    whole: [f64; 4],
    top: i32,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let side = OVERVIEW_WIDTH;
    let left = f64::from(WIDTH) - MARGIN_RIGHT - side;
    draw_text(root, left as i32, top, "overview", INK)?;
    let top = f64::from(top + ROW_HEIGHT);
    let (w, h) = (
        (whole[2] - whole[0]).max(1e-3),
        (whole[3] - whole[1]).max(1e-3),
    );
    let scale = (side / w).min(side / h);
    let px = |p: [f64; 2]| {
        (
            (left + (p[0] - whole[0]) * scale).round() as i32,
            (top + (whole[3] - p[1]) * scale).round() as i32,
        )
    };
    let rect = |r: [f64; 4]| [px([r[0], r[3]]), px([r[2], r[1]])];
    if let Some(bed) = scene.bed {
        root.draw(&Rectangle::new(rect(bed), BED.filled()))?;
        root.draw(&Rectangle::new(rect(bed), BED_EDGE))?;
    }
    for (points, colour) in &scene.extrusion {
        draw_polyline(root, pixels_by(px, points), Pen::Solid(*colour, 2))?;
    }
    root.draw(&Rectangle::new(rect(scene.layout.bounds), INK))?;
    for (at, _) in &scene.refused {
        if contains(whole, [at[0], at[1], at[0], at[1]]) {
            let (x, y) = px(*at);
            draw_cross(root, x, y, REFUSED)?;
        }
    }
    let bottom = px([whole[0], whole[1]]).1;
    draw_text(root, left as i32, bottom + 8, "box: the view", INK)
}

/// Draw a polyline (pixels) with `pen`. A solid one is drawn segment by segment: the bitmap
/// backend's wide strokes lose whole segments of long paths that run over themselves.
fn draw_polyline<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    points: Vec<(i32, i32)>,
    pen: Pen,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    match pen {
        Pen::Solid(colour, 1) => root.draw(&PathElement::new(points, colour.stroke_width(1))),
        Pen::Solid(colour, width) => {
            for pair in points.windows(2) {
                root.draw(&PathElement::new(pair.to_vec(), colour.stroke_width(width)))?;
            }
            Ok(())
        }
        Pen::Dashed(colour) => root.draw(&DashedPathElement::new(
            points,
            6,
            4,
            colour.stroke_width(1),
        )),
    }
}

/// A cross 12 pixels wide centred on `(x, y)`.
fn draw_cross<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    x: i32,
    y: i32,
    colour: RGBColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    root.draw(&PathElement::new(
        vec![(x - 6, y - 6), (x + 6, y + 6)],
        colour.stroke_width(3),
    ))?;
    root.draw(&PathElement::new(
        vec![(x - 6, y + 6), (x + 6, y - 6)],
        colour.stroke_width(3),
    ))
}

/// The points in pixels, without repeats: a wide stroke through a repeated point (a Z-only
/// move in the XY plane) is drawn wrongly by the backends.
fn pixels(layout: &Layout, points: &[[f64; 2]]) -> Vec<(i32, i32)> {
    pixels_by(|q| layout.px(q), points)
}

/// The points in pixels by `px`, without repeats.
fn pixels_by(px: impl Fn([f64; 2]) -> (i32, i32), points: &[[f64; 2]]) -> Vec<(i32, i32)> {
    let mut out: Vec<(i32, i32)> = Vec::with_capacity(points.len());
    for &q in points {
        let p = px(q);
        if out.last() != Some(&p) {
            out.push(p);
        }
    }
    out
}

fn text_width(text: &str) -> i32 {
    text.chars().count() as i32 * 8 * TEXT_SCALE
}

/// Draw `text` with its top-left corner at `(x, y)` in the built-in 8×8 font (ASCII; other
/// characters as `?`), each font pixel a `TEXT_SCALE`-pixel square, runs merged into bars.
fn draw_text<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    x: i32,
    y: i32,
    text: &str,
    color: RGBColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let s = TEXT_SCALE;
    for (k, ch) in text.chars().enumerate() {
        let code = if ch.is_ascii() {
            ch as usize
        } else {
            '?' as usize
        };
        let glyph = font8x8::legacy::BASIC_LEGACY
            .get(code)
            .copied()
            .unwrap_or_default();
        let gx = x + k as i32 * 8 * s;
        for (row, bits) in glyph.iter().enumerate() {
            let mut col = 0;
            while col < 8 {
                if bits >> col & 1 == 1 {
                    let start = col;
                    while col < 8 && bits >> col & 1 == 1 {
                        col += 1;
                    }
                    let (px, py) = (gx + start * s, y + row as i32 * s);
                    root.draw(&Rectangle::new(
                        [(px, py), (px + (col - start) * s, py + s)],
                        color.filled(),
                    ))?;
                } else {
                    col += 1;
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::f64::consts::PI;

    use super::*;

    /// Three axes at 0, without homing.
    const PLAIN: &str = "tick_hz = 1_000_000\n\
        [[axis]]\nletter = \"X\"\nsteps_per_mm = 80\nmax_rate_mm_min = 6000\naccel_mm_s2 = 500\n\
        travel_min_mm = -500\ntravel_max_mm = 500\nstart_mm = 0\n\
        [[axis]]\nletter = \"Y\"\nsteps_per_mm = 80\nmax_rate_mm_min = 6000\naccel_mm_s2 = 500\n\
        travel_min_mm = -500\ntravel_max_mm = 500\nstart_mm = 0\n\
        [[axis]]\nletter = \"Z\"\nsteps_per_mm = 400\nmax_rate_mm_min = 1200\n\
        accel_mm_s2 = 200\ntravel_min_mm = -500\ntravel_max_mm = 500\nstart_mm = 0\n";

    fn plain() -> MachineConfig {
        MachineConfig::from_toml_str(PLAIN).unwrap()
    }

    fn follow_on(machine: &MachineConfig, text: &str, home_first: bool) -> Toolpath {
        let lead = Lead {
            home_first,
            ..Lead::default()
        };
        Toolpath::from_job(machine, &Job::from_text("job.gcode", text), &lead).unwrap()
    }

    fn path(text: &str) -> Toolpath {
        follow_on(&plain(), text, false)
    }

    fn feeds(p: &Toolpath) -> Vec<&Polyline> {
        p.polylines
            .iter()
            .filter(|l| l.kind == PathKind::Feed)
            .collect()
    }

    #[test]
    fn lines_units_offsets_and_relative_moves() {
        let p = path("G0 X10 Y0\nG1 X10 Y10\nG91 G1 X-10\nG90 G20 G1 X1\nG21 G92 X0\nG1 X5\n");
        assert_eq!(p.rapid_mm, 10.0);
        let feeds = feeds(&p);
        assert_eq!(feeds.len(), 1);
        assert_eq!(
            feeds[0].points,
            [
                [10.0, 0.0],
                [10.0, 10.0],
                [0.0, 10.0],
                [25.4, 10.0],
                [30.4, 10.0]
            ]
        );
        assert!((p.feed_mm - 50.4).abs() < 1e-9);
        assert_eq!(p.end, [30.4, 10.0, 0.0]);
    }

    #[test]
    fn arcs_both_ways_and_by_radius_end_on_their_target() {
        // A half circle of radius 10 from (0,0) to (20,0) counter-clockwise goes below.
        let p = path("G1 X0 Y0\nG3 X20 Y0 I10 J0\n");
        let pts = &feeds(&p)[0].points;
        assert!(pts.len() > 4, "{pts:?}");
        assert!(pts.iter().all(|q| q[1] <= 1e-9));
        assert_eq!(pts.last(), Some(&[20.0, 0.0]));
        assert!((p.feed_mm - PI * 10.0).abs() < 0.05);
        // Clockwise, same ends: above.
        let p = path("G2 X20 Y0 I10 J0\n");
        assert!(p.polylines[0].points.iter().all(|q| q[1] >= -1e-9));
        assert_eq!(p.end, [20.0, 0.0, 0.0]);
        // By radius: a quarter circle clockwise from (0,0) to (10,10), centre (10,0).
        let p = path("G2 X10 Y10 R10\n");
        for q in &p.polylines[0].points {
            let r = ((q[0] - 10.0).powi(2) + q[1].powi(2)).sqrt();
            assert!((r - 10.0).abs() < 1e-5, "{q:?}");
        }
        assert_eq!(p.polylines[0].points.last(), Some(&[10.0, 10.0]));
        // A full circle.
        let p = path("G1 X10 Y0\nG2 X10 Y0 I-10 J0\n");
        assert!((p.feed_mm - (10.0 + 2.0 * PI * 10.0)).abs() < 0.1);
        assert_eq!(p.end, [10.0, 0.0, 0.0]);
    }

    #[test]
    fn a_line_the_kernel_refuses_is_kept_and_the_path_goes_on_without_it() {
        let p = path("G0 X1\n\n(an arc without centre)\nG2 X1 Y1\nG0 X3\n");
        assert_eq!(p.refused.len(), 1, "{:?}", p.refused);
        let r = &p.refused[0];
        assert_eq!(
            (r.line, r.text.as_str(), r.at),
            (Some(4), "G2X1Y1", [1.0, 0.0])
        );
        assert!(r.reason.contains("(E12"), "{}", r.reason);
        assert_eq!(p.polylines[0].points, [[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]]);
        // A line that does not parse is not the kernel's to refuse: the job cannot be sent.
        let job = Job::from_text("job.gcode", "G0 X1\nG1 X(\n");
        let e = Toolpath::from_job(&plain(), &job, &Lead::default()).unwrap_err();
        assert!(e.to_string().starts_with("job.gcode, line 2: "), "{e}");
    }

    #[test]
    fn axes_count_from_their_start_until_homed_and_homing_starts_a_new_polyline() {
        // The router starts at X150 Y150 Z50 and homes X and Y to their minimum pulled off by
        // 2 mm, Z to its maximum (100) pulled off by 1 mm.
        let router = MachineConfig::default_router();
        let p = follow_on(&router, "G0 X10 Y10\nG28 X0\nG0 X10 Y10\n", false);
        let rapids: Vec<&Vec<[f64; 2]>> = p.polylines.iter().map(|l| &l.points).collect();
        // Y is not homed by `G28 X0`: it still counts from its start.
        assert_eq!(
            rapids,
            [
                &vec![[150.0, 150.0], [160.0, 160.0]],
                &vec![[2.0, 160.0], [10.0, 160.0]]
            ]
        );
        let p = follow_on(&router, "G0 X10 Y10 Z20\n", true);
        assert_eq!(p.polylines[0].points, [[2.0, 2.0], [10.0, 10.0]]);
        assert_eq!(p.end, [10.0, 10.0, 20.0]);
        assert!((p.rapid_mm - (128.0f64 + 79.0 * 79.0).sqrt()).abs() < 1e-9);
    }

    #[test]
    fn traces_replay_in_machine_millimetres() {
        let trace = "# forja step trace 1\n# tick_hz 1000\n# axes X Y Z\n\
                     # steps_per_mm X=2 Y=4 Z=1\n# start_mm X=10 Y=0 Z=0\n\
                     time_ticks,axis,event\n\
                     0,X,enable\n1,X,step+\n2,X,step+\n3,Y,step-\n4,Z,step+\n5,Y,step-\n";
        let ex = Executed::from_trace(trace, None).unwrap();
        assert_eq!(ex.end, [11.0, -0.5]);
        assert_eq!(ex.points.last(), Some(&[11.0, -0.5, 1.0]));
        assert_eq!(ex.steps, 5);
        assert_eq!(ex.duration_s, 0.005);
        let e = Executed::from_trace("# tick_hz 1000\n# axes X\ntime_ticks,axis,event\n", None)
            .unwrap_err();
        assert!(e.to_string().contains("--machine"), "{e}");
        let machine = MachineConfig::from_toml_str(&PLAIN.replacen(
            "steps_per_mm = 80",
            "steps_per_mm = 1",
            1,
        ))
        .unwrap();
        let ex = Executed::from_trace(
            "# tick_hz 1000\n# axes X\ntime_ticks,axis,event\n1,X,step-\n",
            Some(&machine),
        )
        .unwrap();
        assert_eq!(ex.end, [-1.0, 0.0]);
        let path = Toolpath {
            end: [2.0, 4.0, 0.0],
            ..Toolpath::default()
        };
        assert_eq!(ex.off_end_mm(&path), 5.0);
        let e = Executed::from_trace(
            "# tick_hz 1000\n# axes X\ntime_ticks,axis,event\n1,Q,step-\n",
            Some(&machine),
        )
        .unwrap_err();
        assert_eq!(e.to_string(), "step trace line 4: unknown axis \"Q\"");
    }

    /// A step trace of a machine of X, Y and Z (`per_mm` steps per mm, standing at `start`)
    /// going straight from point to point (mm): at each instant every axis at its position
    /// rounded to the nearest step, as the kernel steps, the steps of an instant at one tick.
    fn trace_through(per_mm: [f64; 3], start: [f64; 3], points: &[[f64; 3]]) -> String {
        let mut text = format!(
            "# forja step trace 1\n# tick_hz 1000000\n# axes X Y Z\n\
             # steps_per_mm X={} Y={} Z={}\n# start_mm X={} Y={} Z={}\ntime_ticks,axis,event\n",
            per_mm[0], per_mm[1], per_mm[2], start[0], start[1], start[2]
        );
        let mut steps = [0i64; 3];
        let mut tick = 0u64;
        for pair in points.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            let span = (0..3)
                .map(|k| ((b[k] - a[k]) * per_mm[k]).abs())
                .fold(0.0, f64::max);
            // A quarter of a step at most per instant: one step an axis at most.
            let n = (span * 4.0).ceil().max(1.0) as usize;
            for i in 1..=n {
                let t = i as f64 / n as f64;
                tick += 1;
                for k in 0..3 {
                    let want = ((a[k] + t * (b[k] - a[k]) - start[k]) * per_mm[k]).round() as i64;
                    while steps[k] != want {
                        let sign = if want > steps[k] { 1 } else { -1 };
                        steps[k] += sign;
                        let event = if sign > 0 { "step+" } else { "step-" };
                        text += &format!("{tick},{},{event}\n", ['X', 'Y', 'Z'][k]);
                    }
                }
            }
        }
        text
    }

    /// The start of `path`'s moves and the end of each.
    fn corners(path: &[Move]) -> Vec<[f64; 3]> {
        let mut points = vec![path[0].from];
        points.extend(path.iter().map(|m| m.to));
        points
    }

    /// Half a step on each axis of [`PLAIN`] and the router, mm: how far a correct trace is
    /// from the moves at most.
    fn half_steps() -> f64 {
        (2.0 * 0.00625f64.powi(2) + 0.00125f64.powi(2)).sqrt()
    }

    #[test]
    fn moves_end_on_the_step_grid_and_homings_are_placed_among_them() {
        let p = path("G1 X10.004 Y0.003 F600\nG1 X10.006\nG1 Z1\n");
        // 800.32 steps: 800; 0.24: 0; 800.48 steps: 800 again, no move on the grid.
        assert_eq!(
            p.moves,
            [
                Move {
                    from: [0.0; 3],
                    to: [10.0, 0.0, 0.0],
                    line: Some(1)
                },
                Move {
                    from: [10.0, 0.0, 0.0],
                    to: [10.0, 0.0, 1.0],
                    line: Some(3)
                },
            ]
        );
        assert!(p.homings.is_empty());
        // On the router, the G28 before the job, the job's own right after it (one homing),
        // one in the middle and one at the end.
        let router = MachineConfig::default_router();
        let p = follow_on(&router, "G28\nG0 X10 Y10\nG28 Z0\nG0 Z50\nG28\n", true);
        assert_eq!(p.homings, [0, 1, 2]);
        assert_eq!(p.moves[0].from, [2.0, 2.0, 99.0]);
        assert_eq!(p.moves[1].from, [10.0, 10.0, 99.0]);
        let stretches = stretches(&p);
        let flags: Vec<(usize, bool, bool)> = stretches
            .iter()
            .map(|s| (s.moves.len(), s.after_homing, s.homing_after))
            .collect();
        assert_eq!(flags, [(1, true, true), (1, true, true)]);
    }

    #[test]
    fn a_trace_that_follows_the_moves_passes_and_one_that_strays_is_named() {
        let p = path("G1 X10 F600\nG2 X20 Y10 I0 J10\nG1 Z-2\nG1 X0 Y0 Z0\n");
        let points = corners(&p.moves);
        let check = |points: &[[f64; 3]]| {
            let trace = trace_through([80.0, 80.0, 400.0], [0.0; 3], points);
            let ex = Executed::from_trace(&trace, Some(&plain())).unwrap();
            ex.check(&p).unwrap()
        };
        let ok = check(&points);
        assert_eq!(ok.step_mm, 0.0125);
        let f = ok.farthest.unwrap();
        assert!(
            f.distance_mm > 0.0 && f.distance_mm <= half_steps() + 1e-9,
            "{f:?}"
        );
        assert!(!ok.fails() && ok.error().is_none() && ok.missed.is_none());
        assert!(ok.measured > 4000, "{}", ok.measured);
        assert!(
            ok.to_string()
                .starts_with("trace: farthest from the toolpath 0.00"),
            "{ok}"
        );
        assert!(ok.to_string().contains(" mm (one step: 0.0125 mm), at "));
        // A detour 0.1 mm off the first line, at X5.
        let mut off = points.clone();
        off.insert(1, [5.0, 0.1, 0.0]);
        let bad = check(&off);
        assert!(bad.fails());
        let f = bad.farthest.unwrap();
        assert!((f.distance_mm - 0.1).abs() < 1e-9, "{f:?}");
        // Where the trace first comes 0.1 mm off, Y a round 8 steps.
        assert_eq!((f.at, f.line), ([4.6875, 0.1, 0.0], Some(1)));
        assert_eq!(
            bad.error().unwrap().to_string(),
            "the steps strayed 0.1000 mm from the toolpath at X4.688 Y0.100 Z0.000 (line 1), \
             more than one step (0.0125 mm)"
        );
        // A path not replayed from a trace is not checked.
        assert_eq!(Executed::default().check(&p), None);
    }

    #[test]
    fn the_positions_measured_are_those_after_each_instant() {
        let p = path("G1 X0.0125 Y0.0125 F600\n");
        let check = |events: &str| {
            let trace = format!("# tick_hz 1000\n# axes X Y Z\ntime_ticks,axis,event\n{events}");
            let ex = Executed::from_trace(&trace, Some(&plain())).unwrap();
            ex.check(&p).unwrap()
        };
        // X and Y at the same tick: the machine goes from one corner to the other.
        let together = check("1,X,step+\n1,Y,step+\n");
        assert_eq!(together.measured, 2);
        assert_eq!(together.farthest.unwrap().distance_mm, 0.0);
        // One tick apart: it stands at (0.0125, 0) in between, half a diagonal step off.
        let apart = check("1,X,step+\n2,Y,step+\n");
        assert_eq!(apart.measured, 3);
        let f = apart.farthest.unwrap();
        assert!(
            (f.distance_mm - 0.0125 / 2f64.sqrt()).abs() < 1e-12,
            "{f:?}"
        );
        assert_eq!(f.at, [0.0125, 0.0, 0.0]);
    }

    /// The waypoints of the router's homing cycle from `from` (Z up, then X, then Y, each to
    /// its switch, backed off, to the switch again and pulled off), ending at X2 Y2 Z99: the
    /// cycle passes that point on its way to Y's switch and again when it backs off.
    fn router_homing(from: [f64; 3]) -> Vec<[f64; 3]> {
        let [x, y, _] = from;
        vec![
            [x, y, 100.0],
            [x, y, 98.0],
            [x, y, 100.0],
            [x, y, 99.0],
            [0.0, y, 99.0],
            [2.0, y, 99.0],
            [0.0, y, 99.0],
            [2.0, y, 99.0],
            [2.0, 0.0, 99.0],
            [2.0, 2.0, 99.0],
            [2.0, 0.0, 99.0],
            [2.0, 2.0, 99.0],
        ]
    }

    #[test]
    fn the_homing_cycles_are_left_out_and_a_trace_of_another_job_fails() {
        let router = MachineConfig::default_router();
        let job = "G0 X10 Y10 Z20\nG1 X40 F3000\nG2 X30 Y20 I-10 J0\nG28\nG0 X5 Y5 Z90\nG1 Y20\n";
        let p = follow_on(&router, job, true);
        let stretches = stretches(&p);
        let [first, second] = stretches.as_slice() else {
            panic!("{}", stretches.len())
        };
        // Homing from where the router starts, the first stretch, homing from its end, the
        // second stretch.
        let mut points = vec![[150.0, 150.0, 50.0]];
        points.extend(router_homing(points[0]));
        points.extend(corners(first.moves));
        points.extend(router_homing(*points.last().unwrap()));
        points.extend(corners(second.moves));
        let trace = trace_through([80.0, 80.0, 400.0], [150.0, 150.0, 50.0], &points);
        let ex = Executed::from_trace(&trace, Some(&router)).unwrap();
        let check = ex.check(&p).unwrap();
        assert!(!check.fails(), "{check:?}");
        let f = check.farthest.unwrap();
        assert!(f.distance_mm <= half_steps() + 1e-9, "{f:?}");
        // The same trace over the job 1 mm to the right: the steps stray on line 1.
        let shifted = "G0 X11 Y10 Z20\nG1 X41 F3000\nG2 X31 Y20 I-10 J0\nG28\nG0 X6 Y5 Z90\n\
                       G1 Y20\n";
        let check = ex.check(&follow_on(&router, shifted, true)).unwrap();
        assert!(check.fails());
        let f = check.farthest.unwrap();
        assert!((0.9..1.02).contains(&f.distance_mm), "{f:?}");
        let e = check.error().unwrap().to_string();
        assert!(e.starts_with("the steps strayed 1.0"), "{e}");
        assert!(e.ends_with("more than one step (0.0125 mm)"), "{e}");
        // A trace that never homes never comes to where the job goes on after homing.
        let trace = trace_through(
            [80.0, 80.0, 400.0],
            [150.0, 150.0, 50.0],
            &[[150.0, 150.0, 50.0], [10.0, 10.0, 20.0]],
        );
        let ex = Executed::from_trace(&trace, Some(&router)).unwrap();
        let check = ex.check(&p).unwrap();
        assert_eq!(check.missed, Some(p.moves[0]));
        assert_eq!(check.farthest, None);
        assert_eq!(
            check.error().unwrap().to_string(),
            "the steps never come to X2.000 Y2.000 Z99.000, where the program goes on after \
             homing (line 1): the step trace is not this job's, or ends before"
        );
    }

    #[test]
    fn renders_png_and_svg_and_refuses_other_names() {
        let dir = std::env::temp_dir().join(format!("forja-sim-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = path("G0 X10 Y10\nG1 X30 F6000\nG2 X40 Y20 I0 J10\nG1 Y30\nG0 X0 Y0\n");
        let ex = Executed {
            points: vec![[0.0, 0.0, 0.0], [10.0, 10.0, 0.0], [30.0, 10.0, 0.0]],
            ..Executed::default()
        };
        let options = PlotOptions::default();
        for name in ["plot.png", "plot.SVG"] {
            let out = dir.join(name);
            render(&out, "job.gcode", &p, Some(&ex), &options).unwrap();
            assert!(std::fs::metadata(&out).unwrap().len() > 1000, "{name}");
        }
        let e = render(&dir.join("plot.jpg"), "job.gcode", &p, None, &options).unwrap_err();
        assert!(e.to_string().contains("name it .png or .svg"), "{e}");
        let e = render(
            &dir.join("none.svg"),
            "none",
            &path("G21\n"),
            None,
            &options,
        )
        .unwrap_err();
        assert!(e.to_string().starts_with("nothing to draw"), "{e}");
        // A printer job, all layers and one, with travel and without.
        let job = printer_path(PRINTER_JOB);
        for (name, layers, hide_travel) in [
            ("all.png", None, false),
            ("one.svg", Some(LayerRange::from_str("2").unwrap()), true),
        ] {
            let out = dir.join(name);
            let options = PlotOptions {
                layers,
                hide_travel,
            };
            render(&out, "part.gcode", &job, None, &options).unwrap();
            assert!(std::fs::metadata(&out).unwrap().len() > 1000, "{name}");
        }
        let options = PlotOptions {
            layers: Some(LayerRange::from_str("4..").unwrap()),
            ..PlotOptions::default()
        };
        let e = render(&dir.join("none.png"), "part", &job, None, &options).unwrap_err();
        assert!(e.to_string().starts_with("the job has 3 layers"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A printer job: homing, a purge line at 0.3 mm near the bed's edge, then three layers of
    /// a 20 mm part at 0.2, 0.4 and 0.6 mm, with retractions, a wipe, and a park at the end.
    const PRINTER_JOB: &str = "G28\nM83\nG1 Z0.3 F600\n\
        G1 X5 Y60 E5 F1200\nG1 E-0.8 F2100\n\
        G0 Z0.2\nG0 X100 Y100\nG1 E0.8\nG1 X120 Y100 E1\nG1 X120 Y120 E1\n\
        G1 Z0.4\nG0 X100 Y100\nG1 X120 Y100 E1\nG1 X118 Y100 E-0.2\n\
        G1 Z0.6\nG0 X105 Y105\nG1 X115 Y105 E1\nG1 E-0.8\n\
        G0 Z10\nG0 X0 Y200\n";

    fn printer() -> MachineConfig {
        MachineConfig::from_toml_str(MachineConfig::bundled_toml("printer").unwrap()).unwrap()
    }

    fn printer_path(text: &str) -> Toolpath {
        follow_on(&printer(), text, false)
    }

    /// A polyline's kind, layer, first and last point.
    type Outline = (PathKind, Option<usize>, [f64; 2], [f64; 2]);

    /// The outline of each polyline.
    fn outline(p: &Toolpath) -> Vec<Outline> {
        p.polylines
            .iter()
            .map(|l| (l.kind, l.layer, l.points[0], *l.points.last().unwrap()))
            .collect()
    }

    #[test]
    fn a_printer_path_is_extrusion_and_travel_in_layers() {
        use PathKind::{Extrusion, Travel};
        let p = printer_path(PRINTER_JOB);
        assert!(p.printer);
        // Homing leaves X and Y 5 mm off their switches, Z 2 mm: the path starts there.
        assert_eq!(
            outline(&p),
            [
                (Travel, Some(0), [5.0, 5.0], [5.0, 5.0]),
                (Extrusion, Some(0), [5.0, 5.0], [5.0, 60.0]),
                (Travel, Some(0), [5.0, 60.0], [100.0, 100.0]),
                (Extrusion, Some(0), [100.0, 100.0], [120.0, 120.0]),
                (Travel, Some(1), [120.0, 120.0], [100.0, 100.0]),
                (Extrusion, Some(1), [100.0, 100.0], [120.0, 100.0]),
                (Travel, Some(2), [120.0, 100.0], [105.0, 105.0]),
                (Extrusion, Some(2), [105.0, 105.0], [115.0, 105.0]),
                (Travel, Some(2), [115.0, 105.0], [0.0, 200.0]),
            ]
        );
        // The purge line at 0.3 mm comes before the first layer at 0.2 mm: it is layer 1's.
        assert_eq!(
            p.layers,
            [
                Layer {
                    z_mm: [0.2, 0.3],
                    extrusion_mm: 55.0 + 40.0
                },
                Layer {
                    z_mm: [0.4, 0.4],
                    extrusion_mm: 20.0
                },
                Layer {
                    z_mm: [0.6, 0.6],
                    extrusion_mm: 10.0
                },
            ]
        );
        assert_eq!(p.retractions, 2, "the wipe moves the tool: it is travel");
        assert!((p.filament_mm - 9.0).abs() < 1e-9, "{}", p.filament_mm);
        assert!((p.extrusion_mm - 125.0).abs() < 1e-9, "{}", p.extrusion_mm);
        assert_eq!(p.bed, Some([0.0, 0.0, 235.0, 235.0]));
        assert_eq!(p.end, [0.0, 200.0, 10.0]);
        // The same moves on a machine without an extruder are feeds and rapids, in no layer.
        let cnc = path("G0 X100 Y100\nG1 X120 F600\n");
        assert!(!cnc.printer && cnc.layers.is_empty());
        assert_eq!(
            outline(&cnc),
            [
                (PathKind::Rapid, None, [0.0, 0.0], [100.0, 100.0]),
                (PathKind::Feed, None, [100.0, 100.0], [120.0, 100.0]),
            ]
        );
    }

    #[test]
    fn layer_ranges_read_check_and_describe() {
        let range = |text: &str| LayerRange::from_str(text);
        for text in ["3", "2..5", "2.."] {
            assert_eq!(range(text).unwrap().to_string(), text);
        }
        assert_eq!(range("..4").unwrap().to_string(), "1..4");
        let ok = |first, last| Ok::<_, String>(LayerRange { first, last });
        for (text, want) in [
            ("3", ok(3, Some(3))),
            ("2..5", ok(2, Some(5))),
            (" 2 .. 5 ", ok(2, Some(5))),
            ("2..", ok(2, None)),
            ("..4", ok(1, Some(4))),
            ("..", ok(1, None)),
            ("4..4", ok(4, Some(4))),
        ] {
            assert_eq!(range(text).map_err(|e| e.to_string()), want, "{text}");
        }
        for (text, why) in [
            ("0", "numbered from 1"),
            ("0..3", "numbered from 1"),
            ("5..2", "ends before it starts"),
            ("x", "give a layer (3) or a range"),
            ("", "give a layer"),
            ("-1", "give a layer"),
            ("2..=5", "give a layer"),
            ("1.5", "give a layer"),
        ] {
            let e = range(text).unwrap_err().to_string();
            assert!(e.contains(why), "{text}: {e}");
        }

        let p = printer_path(PRINTER_JOB);
        let select = |text: &str| p.select_layers(range(text).unwrap());
        assert_eq!(select("2").unwrap(), 1..=1);
        assert_eq!(select("2..").unwrap(), 1..=2);
        assert_eq!(select("..3").unwrap(), 0..=2);
        for text in ["4", "3..4", "4.."] {
            assert_eq!(
                select(text).unwrap_err().to_string(),
                "the job has 3 layers, Z 0.2 to 0.6 mm"
            );
        }
        assert_eq!(p.describe_layers(None), "3 layers, Z 0.2 to 0.6 mm");
        assert_eq!(
            p.describe_layers(Some(0..=0)),
            "layer 1 of 3, Z 0.2 to 0.3 mm"
        );
        assert_eq!(p.describe_layers(Some(1..=1)), "layer 2 of 3, Z 0.4 mm");
        assert_eq!(
            p.describe_layers(Some(1..=2)),
            "layers 2 to 3 of 3, Z 0.4 to 0.6 mm"
        );
        let e = path("G1 X1\n")
            .select_layers(range("1").unwrap())
            .unwrap_err();
        assert!(e.to_string().contains("the machine has no extruder"), "{e}");
        let e = printer_path("G0 X10\n")
            .select_layers(range("1").unwrap())
            .unwrap_err();
        assert_eq!(e.to_string(), "the job extrudes nothing: it has no layers");
    }

    #[test]
    fn the_view_frames_the_part_and_an_overview_shows_the_rest() {
        let p = printer_path(PRINTER_JOB);
        let scene = |layers: Option<&str>| {
            let options = PlotOptions {
                layers: layers.map(|t| LayerRange::from_str(t).unwrap()),
                hide_travel: false,
            };
            Scene::new("part", &p, None, &options).unwrap()
        };
        // All layers: the part (100..120 x 100..120) with a margin, not the purge line at X5,
        // the park at (0, 200) or the bed; the overview holds the bed and the purge line.
        let all = scene(None);
        let [x0, y0, x1, y1] = all.layout.bounds;
        assert!(
            (98.0..100.0).contains(&x0) && (98.0..100.0).contains(&y0),
            "{x0} {y0}"
        );
        assert!(
            (120.0..122.0).contains(&x1) && (120.0..122.0).contains(&y1),
            "{x1} {y1}"
        );
        assert_eq!(all.layout.overview, Some([0.0, 0.0, 235.0, 235.0]));
        assert_eq!(all.title, "part: 3 layers, Z 0.2 to 0.6 mm");
        // Layer 3 alone: its extrusion, 105..115 along Y 105; nothing outside, no overview.
        let top = scene(Some("3"));
        let [x0, y0, x1, y1] = top.layout.bounds;
        assert!(
            (104.0..105.0).contains(&x0) && (115.0..=116.0).contains(&x1),
            "{x0} {x1}"
        );
        assert!(y0 < 105.0 && 105.0 < y1, "{y0} {y1}");
        assert_eq!(top.layout.overview, None);
        assert_eq!(top.title, "part: layer 3 of 3, Z 0.6 mm");
        // Its travel is drawn (the move to its start, the park), no other layer's extrusion.
        let solid: Vec<&Vec<[f64; 2]>> = top
            .strokes
            .iter()
            .filter(|(_, pen)| matches!(pen, Pen::Solid(..)))
            .map(|(points, _)| points)
            .collect();
        assert_eq!(solid, [&vec![[105.0, 105.0], [115.0, 105.0]]]);
        assert_eq!(top.strokes.len(), 3);
        // Layer 1 holds the purge line: the view is still the part, the purge in the overview.
        let first = scene(Some("1"));
        assert!(first.layout.bounds[0] > 90.0, "{:?}", first.layout.bounds);
        assert!(first.layout.overview.is_some());
    }

    #[test]
    fn executed_paths_are_cut_to_the_layers_heights() {
        let ex = Executed {
            points: vec![
                [0.0, 0.0, 0.2],
                [1.0, 0.0, 0.2],
                [1.0, 0.0, 0.4],
                [2.0, 0.0, 0.4],
                [2.0, 0.0, 0.6],
                [3.0, 0.0, 0.2],
            ],
            ..Executed::default()
        };
        assert_eq!(
            ex.within([0.2, 0.2]),
            [vec![[0.0, 0.0], [1.0, 0.0]], vec![[3.0, 0.0]]]
        );
        assert_eq!(
            ex.within([0.4, 0.6]),
            [vec![[1.0, 0.0], [2.0, 0.0], [2.0, 0.0]]]
        );
    }

    #[test]
    fn clipping_keeps_what_is_inside_the_view() {
        let view = [0.0, 0.0, 10.0, 10.0];
        assert_eq!(
            clip([-5.0, 5.0], [15.0, 5.0], view),
            Some(([0.0, 5.0], [10.0, 5.0]))
        );
        assert_eq!(clip([-5.0, -5.0], [-1.0, 20.0], view), None);
        assert_eq!(
            clip([2.0, 2.0], [3.0, 3.0], view),
            Some(([2.0, 2.0], [3.0, 3.0]))
        );
        // In, out and in again: two stretches.
        assert_eq!(
            clip_polyline(&[[5.0, 5.0], [5.0, 20.0], [6.0, 20.0], [6.0, 5.0]], view),
            [vec![[5.0, 5.0], [5.0, 10.0]], vec![[6.0, 10.0], [6.0, 5.0]]]
        );
    }

    #[test]
    fn layer_colours_run_from_the_ramps_start_to_its_end() {
        assert_eq!(layer_colour(0.0), LAYER_RAMP[0]);
        assert_eq!(layer_colour(1.0), LAYER_RAMP[3]);
        assert_eq!(layer_colour(2.0), LAYER_RAMP[3]);
        assert_ne!(layer_colour(0.5), layer_colour(0.6));
    }

    #[test]
    fn grid_steps_are_round() {
        assert_eq!(grid_step(80.0), 10.0);
        assert_eq!(grid_step(300.0), 50.0);
        assert_eq!(grid_step(3.0), 0.5);
        assert_eq!(label(12.5), "12.5");
        assert_eq!(label(-0.0), "0");
    }
}
