//! Toolpath plots: the path a job asks for, as the firmware's kernel reads it, and, from a step
//! trace, the path the simulated machine really took, drawn to PNG or SVG (`forja-sim --plot`).
//!
//! [`Toolpath::from_job`] runs the job through the kernel's own reading of G-code
//! ([`forja_motion::Preview`], on the kernel configuration the simulator board builds from the
//! machine file, [`forja_sim::board::parts::machine`]): units, distance modes, planes, `G92`
//! offsets, arcs (cut into the kernel's chords) and homing are the firmware's, and a line the
//! kernel refuses is an error naming the job and the line. Positions are the machine's
//! physical ones, those of a step trace: the firmware counts from zero when it starts while the
//! machine stands at each axis's `start_mm`, so an axis is drawn shifted by its start position
//! until a homing line homes it, and from then on where the kernel's homing cycle left it.
//! [`Executed::from_trace`] replays a step trace (`forja_sim_hal::trace`) step by step.
//! [`render`] draws both in the XY plane with a millimetre grid; the text is drawn with a
//! built-in 8×8 bitmap font, so no system font is needed.
//!
//! A tool of the simulator program, on the host: nothing here is part of the firmware.

use std::fmt;
use std::path::Path;

use forja_hal_abstraction::stepper::Direction;
use forja_host::codes::explain;
use forja_host::program::{Program, ProgramError, describe_line_error};
use forja_motion::{NM_PER_MM, Preview, Travel};
use forja_protocol::gcode::Line;
use forja_sim::board::BoardError;
use forja_sim::board::parts;
use forja_sim_hal::{MachineConfig, StepTrace, TraceEventKind};
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

use crate::job::Job;

/// Connected points travelled the same way, XY in mm.
#[derive(Clone, Debug, PartialEq)]
pub struct Polyline {
    /// How: in rapids or at the feed rate.
    pub travel: Travel,
    /// The points, in order.
    pub points: Vec<[f64; 2]>,
}

/// The path a job asks for, in the machine's physical coordinates.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Toolpath {
    /// The stretches, in program order; a homing line starts a new one.
    pub polylines: Vec<Polyline>,
    /// Length travelled at the feed rate, mm (XYZ).
    pub feed_mm: f64,
    /// Length travelled in rapids, mm (XYZ).
    pub rapid_mm: f64,
    /// Where the job ends, XYZ mm (0 on an axis the machine does not have).
    pub end: [f64; 3],
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

impl Toolpath {
    /// Follow `job` on a machine of `machine` standing at its start position; `home_first`:
    /// a `G28` comes before the job, as [`crate::run::run_job`] sends it.
    ///
    /// Errors: a machine the kernel cannot take, a job line that does not parse or that the
    /// kernel refuses (with the job's name and the line's number).
    pub fn from_job(
        machine: &MachineConfig,
        job: &Job,
        home_first: bool,
    ) -> Result<Self, PlotError> {
        match machine.axes.len() {
            1 => follow::<1>(machine, job, home_first),
            2 => follow::<2>(machine, job, home_first),
            3 => follow::<3>(machine, job, home_first),
            4 => follow::<4>(machine, job, home_first),
            5 => follow::<5>(machine, job, home_first),
            6 => follow::<6>(machine, job, home_first),
            7 => follow::<7>(machine, job, home_first),
            8 => follow::<8>(machine, job, home_first),
            n => Err(PlotError(BoardError::AxisCount(n).to_string())),
        }
    }

    /// Add a straight piece from `from` to `to` (XYZ mm).
    fn add(&mut self, travel: Travel, from: [f64; 3], to: [f64; 3]) {
        let length =
            ((to[0] - from[0]).powi(2) + (to[1] - from[1]).powi(2) + (to[2] - from[2]).powi(2))
                .sqrt();
        match travel {
            Travel::Rapid => self.rapid_mm += length,
            Travel::Feed => self.feed_mm += length,
        }
        let (from, to) = ([from[0], from[1]], [to[0], to[1]]);
        match self.polylines.last_mut() {
            Some(p) if p.travel == travel && p.points.last() == Some(&from) => p.points.push(to),
            _ => self.polylines.push(Polyline {
                travel,
                points: vec![from, to],
            }),
        }
    }
}

/// [`Toolpath::from_job`] on a machine of `N` axes.
fn follow<const N: usize>(
    machine: &MachineConfig,
    job: &Job,
    home_first: bool,
) -> Result<Toolpath, PlotError> {
    let config = parts::machine::<N>(machine).map_err(|e| PlotError(e.to_string()))?;
    let program = Program::parse(job.text().as_bytes()).map_err(|e| match e {
        ProgramError::Line { line, reason, .. } => {
            PlotError(format!("{}, line {line}: {reason}", job.name()))
        }
        e => PlotError(format!("{}: {e}", job.name())),
    })?;
    let xyz = [b'X', b'Y', b'Z'].map(|l| config.axis_index(l));
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
    // The firmware counts from zero when it starts.
    let mut preview = Preview::new(&config, [0; N]);
    let mut path = Toolpath::default();
    let lines = home_first.then_some((None, "G28")).into_iter().chain(
        program
            .lines
            .iter()
            .map(|l| (Some(l.source_line), l.text.as_str())),
    );
    for (number, text) in lines {
        let place = || match number {
            Some(n) => format!("{}, line {n}", job.name()),
            None => "G28 (before the job)".to_string(),
        };
        let line = Line::parse(text.as_bytes())
            .map_err(|e| PlotError(format!("{}: {}", place(), describe_line_error(&e))))?;
        let homed = preview
            .line(&line, |travel, from, to| {
                path.add(travel, at(from, &shift), at(to, &shift));
            })
            .map_err(|e| {
                PlotError(format!(
                    "{}: {}",
                    place(),
                    explain(e.code(), &e.to_string())
                ))
            })?;
        if homed != 0 {
            for (i, s) in shift.iter_mut().enumerate() {
                if homed & (1 << i) != 0 {
                    *s = 0;
                }
            }
            path.polylines.push(Polyline {
                travel: Travel::Rapid,
                points: Vec::new(),
            });
        }
    }
    path.polylines.retain(|p| p.points.len() > 1);
    path.end = at(preview.position(), &shift);
    Ok(path)
}

/// The path the machine took, replayed from a step trace.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Executed {
    /// XY points in mm, machine coordinates, in time order (close points merged).
    pub points: Vec<[f64; 2]>,
    /// Steps in the trace, all axes.
    pub steps: u64,
    /// Length of the XY path, mm.
    pub length_mm: f64,
    /// Where the trace ends, XY mm.
    pub end: [f64; 2],
    /// Time of the last event, s.
    pub duration_s: f64,
}

/// Points of the executed path closer than this to the previous one are merged.
const MERGE_MM: f64 = 0.02;

impl Executed {
    /// Replay a step trace (the text of a `--trace` file). Steps per mm and start positions
    /// come from `machine` when given, else from the trace's `# steps_per_mm` and `# start_mm`
    /// header lines.
    ///
    /// Errors: a trace that does not read (naming the line), an X or Y axis whose steps per mm
    /// nobody gives.
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
        let xy = [axis('X')?, axis('Y')?];
        let place = |steps: [i64; 2]| -> [f64; 2] {
            core::array::from_fn(|k| {
                xy[k].map_or(0.0, |(_, per_mm, start)| start + steps[k] as f64 / per_mm)
            })
        };
        let mut steps = [0i64; 2];
        let mut out = Executed::default();
        let mut last = place(steps);
        out.points.push(last);
        let mut last_ticks = 0u64;
        for event in trace.events() {
            last_ticks = event.time_ticks;
            let TraceEventKind::Step(direction) = event.kind else {
                continue;
            };
            out.steps += 1;
            let Some(k) = (0..2).find(|&k| xy[k].is_some_and(|(i, _, _)| i == event.axis)) else {
                continue;
            };
            steps[k] += if direction == Direction::Positive {
                1
            } else {
                -1
            };
            let p = place(steps);
            let d = ((p[0] - last[0]).powi(2) + (p[1] - last[1]).powi(2)).sqrt();
            if d >= MERGE_MM {
                out.length_mm += d;
                out.points.push(p);
                last = p;
            }
        }
        let end = place(steps);
        if end != last {
            out.length_mm += ((end[0] - last[0]).powi(2) + (end[1] - last[1]).powi(2)).sqrt();
            out.points.push(end);
        }
        out.end = end;
        out.duration_s = last_ticks as f64 / f64::from(trace.tick_hz());
        Ok(out)
    }

    /// How far from the end of `path` the trace ends, in XY, mm.
    pub fn off_end_mm(&self, path: &Toolpath) -> f64 {
        ((self.end[0] - path.end[0]).powi(2) + (self.end[1] - path.end[1]).powi(2)).sqrt()
    }
}

const FEED: RGBColor = RGBColor(120, 170, 235);
const RAPID: RGBColor = RGBColor(150, 150, 150);
const EXECUTED: RGBColor = RGBColor(220, 40, 40);
const GRID: RGBColor = RGBColor(228, 228, 228);
const INK: RGBColor = RGBColor(40, 40, 40);

/// Pixels per font pixel.
const TEXT_SCALE: i32 = 2;
/// Width of the image, pixels.
const WIDTH: u32 = 1200;

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

/// Draw `path` (and `executed`, if given) to `out`, a `.png` or `.svg` file.
///
/// Errors: another extension, an empty drawing, or the file cannot be written.
pub fn render(
    out: &Path,
    title: &str,
    path: &Toolpath,
    executed: Option<&Executed>,
) -> Result<(), PlotError> {
    let format = ImageFormat::of(out)?;
    let layout = Layout::new(path, executed)?;
    let size = (WIDTH, layout.height);
    let result = match format {
        ImageFormat::Png => {
            let root = BitMapBackend::new(out, size).into_drawing_area();
            draw(&root, &layout, title, path, executed)
                .and_then(|()| root.present().map_err(|e| e.to_string()))
        }
        ImageFormat::Svg => {
            let root = SVGBackend::new(out, size).into_drawing_area();
            draw(&root, &layout, title, path, executed)
                .and_then(|()| root.present().map_err(|e| e.to_string()))
        }
    };
    result.map_err(|e| PlotError(format!("cannot write {}: {e}", out.display())))
}

struct Layout {
    height: u32,
    /// Data bounds, mm: x0, y0, x1, y1.
    bounds: [f64; 4],
    scale: f64,
    origin: (f64, f64),
}

const MARGIN_LEFT: f64 = 110.0;
const MARGIN_RIGHT: f64 = 30.0;
const MARGIN_TOP: f64 = 90.0;
const MARGIN_BOTTOM: f64 = 50.0;

impl Layout {
    fn new(path: &Toolpath, executed: Option<&Executed>) -> Result<Self, PlotError> {
        let mut b = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        let points = path
            .polylines
            .iter()
            .flat_map(|p| p.points.iter())
            .chain(executed.into_iter().flat_map(|e| e.points.iter()));
        for p in points {
            b = [
                b[0].min(p[0]),
                b[1].min(p[1]),
                b[2].max(p[0]),
                b[3].max(p[1]),
            ];
        }
        if !b.iter().all(|v| v.is_finite()) {
            return Err(PlotError(
                "nothing to draw: the program makes no move in X or Y".into(),
            ));
        }
        let (mut dx, mut dy) = (b[2] - b[0], b[3] - b[1]);
        let pad = 0.04 * dx.max(dy).max(1.0);
        b = [b[0] - pad, b[1] - pad, b[2] + pad, b[3] + pad];
        dx += 2.0 * pad;
        dy += 2.0 * pad;
        let inner_w = f64::from(WIDTH) - MARGIN_LEFT - MARGIN_RIGHT;
        let scale = inner_w / dx;
        let height = (dy * scale + MARGIN_TOP + MARGIN_BOTTOM).clamp(360.0, 1600.0);
        let inner_h = height - MARGIN_TOP - MARGIN_BOTTOM;
        let scale = scale.min(inner_h / dy);
        let origin = (
            MARGIN_LEFT + (inner_w - dx * scale) / 2.0,
            MARGIN_TOP + inner_h - (inner_h - dy * scale) / 2.0,
        );
        Ok(Self {
            height: height as u32,
            bounds: b,
            scale,
            origin,
        })
    }

    fn px(&self, p: [f64; 2]) -> (i32, i32) {
        (
            (self.origin.0 + (p[0] - self.bounds[0]) * self.scale).round() as i32,
            (self.origin.1 - (p[1] - self.bounds[1]) * self.scale).round() as i32,
        )
    }
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

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    layout: &Layout,
    title: &str,
    path: &Toolpath,
    executed: Option<&Executed>,
) -> DrawResult {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    root.fill(&WHITE).map_err(e)?;
    let [x0, y0, x1, y1] = layout.bounds;
    let step = grid_step((x1 - x0).max(y1 - y0));
    let (left, top) = layout.px([x0, y1]);
    let (right, bottom) = layout.px([x1, y0]);
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
    root.draw(&Rectangle::new([(left, top), (right, bottom)], INK))
        .map_err(e)?;
    draw_text(root, right - text_width("mm"), bottom + 30, "mm", INK).map_err(e)?;

    for p in &path.polylines {
        let points = pixels(layout, &p.points);
        match p.travel {
            Travel::Rapid => root
                .draw(&DashedPathElement::new(points, 6, 4, RAPID.stroke_width(1)))
                .map_err(e)?,
            Travel::Feed => draw_wide(root, points, FEED).map_err(e)?,
        }
    }
    if let Some(ex) = executed {
        let points = pixels(layout, &ex.points);
        root.draw(&PathElement::new(
            points,
            EXECUTED.mix(0.85).stroke_width(1),
        ))
        .map_err(e)?;
    }

    draw_text(root, 20, 16, title, INK).map_err(e)?;
    let mut x = 20;
    let y = 52;
    let mut legend: Vec<(&str, RGBColor, bool)> =
        vec![("feed", FEED, false), ("rapid", RAPID, true)];
    if executed.is_some() {
        legend.push(("executed (step trace)", EXECUTED, false));
    }
    for (name, color, dashed) in legend {
        let sample = vec![(x, y + 8), (x + 30, y + 8)];
        if dashed {
            root.draw(&DashedPathElement::new(sample, 6, 4, color.stroke_width(2)))
                .map_err(e)?;
        } else {
            root.draw(&PathElement::new(sample, color.stroke_width(2)))
                .map_err(e)?;
        }
        draw_text(root, x + 38, y, name, INK).map_err(e)?;
        x += 38 + text_width(name) + 30;
    }
    Ok(())
}

/// A polyline two pixels wide, drawn segment by segment: the bitmap backend's wide strokes
/// lose whole segments of long paths that run over themselves.
fn draw_wide<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    points: Vec<(i32, i32)>,
    color: RGBColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    for pair in points.windows(2) {
        root.draw(&PathElement::new(pair.to_vec(), color.stroke_width(3)))?;
    }
    Ok(())
}

/// The points in pixels, without repeats: a wide stroke through a repeated point (a Z-only
/// move in the XY plane) is drawn wrongly by the backends.
fn pixels(layout: &Layout, points: &[[f64; 2]]) -> Vec<(i32, i32)> {
    let mut out: Vec<(i32, i32)> = Vec::with_capacity(points.len());
    for &q in points {
        let p = layout.px(q);
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
        Toolpath::from_job(machine, &Job::from_text("job.gcode", text), home_first).unwrap()
    }

    fn path(text: &str) -> Toolpath {
        follow_on(&plain(), text, false)
    }

    fn feeds(p: &Toolpath) -> Vec<&Polyline> {
        p.polylines
            .iter()
            .filter(|l| l.travel == Travel::Feed)
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
    fn a_line_the_kernel_refuses_is_an_error_naming_the_job_and_line() {
        let job = Job::from_text("job.gcode", "G0 X1\n\n(an arc without centre)\nG2 X1 Y1\n");
        let e = Toolpath::from_job(&plain(), &job, false).unwrap_err();
        assert!(e.to_string().starts_with("job.gcode, line 4: "), "{e}");
        assert!(e.to_string().contains("(E12"), "{e}");
        let job = Job::from_text("job.gcode", "G0 X1\nG1 X(\n");
        let e = Toolpath::from_job(&plain(), &job, false).unwrap_err();
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

    #[test]
    fn renders_png_and_svg_and_refuses_other_names() {
        let dir = std::env::temp_dir().join(format!("forja-sim-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = path("G0 X10 Y10\nG1 X30 F6000\nG2 X40 Y20 I0 J10\nG1 Y30\nG0 X0 Y0\n");
        let ex = Executed {
            points: vec![[0.0, 0.0], [10.0, 10.0], [30.0, 10.0]],
            ..Executed::default()
        };
        for name in ["plot.png", "plot.SVG"] {
            let out = dir.join(name);
            render(&out, "job.gcode", &p, Some(&ex)).unwrap();
            assert!(std::fs::metadata(&out).unwrap().len() > 1000, "{name}");
        }
        let e = render(&dir.join("plot.jpg"), "job.gcode", &p, None).unwrap_err();
        assert!(e.to_string().contains("name it .png or .svg"), "{e}");
        let e = render(&dir.join("none.svg"), "none", &path("G21\n"), None).unwrap_err();
        assert!(e.to_string().starts_with("nothing to draw"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
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
