//! Toolpath plots: the path a program asks for and, from a step trace, the path the machine
//! really took, drawn to PNG or SVG.
//!
//! [`Toolpath::from_program`] follows the program as the kernel reads it (`G0`–`G3` with
//! `I`/`J`/`K` or `R` arcs in the `G17`/`G18`/`G19` plane, `G20`/`G21`, `G90`/`G91`, `G92`,
//! `G28`), in machine coordinates from the machine's start position. [`Executed::from_trace`]
//! replays a simulator step trace (`boards/sim-hal/src/trace.rs`) step by step. [`render`] draws
//! both in the XY plane with a millimetre grid; the text is drawn with a built-in 8×8 bitmap
//! font, so no system font is needed.

use std::f64::consts::PI;
use std::fmt;
use std::path::Path;

use forja_protocol::gcode::Line;
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

use crate::machine::MachineInfo;
use crate::program::{Program, describe_line_error};

/// How a stretch of the path is travelled.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MoveKind {
    /// `G0`: positioning, not cutting.
    Rapid,
    /// `G1`–`G3`: at the feed rate.
    Feed,
}

/// Connected points travelled the same way, XY in mm.
#[derive(Clone, Debug, PartialEq)]
pub struct Polyline {
    /// How.
    pub kind: MoveKind,
    /// The points, in order.
    pub points: Vec<[f64; 2]>,
}

/// The path a program asks for.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Toolpath {
    /// The stretches, in program order.
    pub polylines: Vec<Polyline>,
    /// Length travelled at the feed rate, mm (XYZ).
    pub feed_mm: f64,
    /// Length travelled in rapids, mm (XYZ).
    pub rapid_mm: f64,
    /// Where the program ends, machine XYZ mm.
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

#[derive(Clone, Copy, PartialEq, Eq)]
enum Plane {
    Xy,
    Zx,
    Yz,
}

impl Plane {
    /// The plane's two axes and the third one, as indices into XYZ; and the letters of the
    /// centre offsets along the first two.
    fn axes(self) -> ([usize; 3], [u8; 2]) {
        match self {
            Self::Xy => ([0, 1, 2], [b'I', b'J']),
            Self::Zx => ([2, 0, 1], [b'K', b'I']),
            Self::Yz => ([1, 2, 0], [b'J', b'K']),
        }
    }
}

/// Largest angle of one chord of a drawn arc.
const ARC_STEP_RAD: f64 = PI / 90.0;

struct Interpreter {
    pos: [f64; 3],
    offset: [f64; 3],
    absolute: bool,
    inches: bool,
    plane: Plane,
    motion: Option<u8>,
    path: Toolpath,
}

impl Interpreter {
    fn to_mm(&self, value: f64) -> f64 {
        if self.inches { value * 25.4 } else { value }
    }

    fn add(&mut self, kind: MoveKind, points: &[[f64; 3]]) {
        let mut length = 0.0;
        let mut last = self.pos;
        for p in points {
            length += dist3(last, *p);
            last = *p;
        }
        match kind {
            MoveKind::Rapid => self.path.rapid_mm += length,
            MoveKind::Feed => self.path.feed_mm += length,
        }
        let xy = |p: [f64; 3]| [p[0], p[1]];
        match self.path.polylines.last_mut() {
            Some(p) if p.kind == kind && p.points.last() == Some(&xy(self.pos)) => {}
            _ => self.path.polylines.push(Polyline {
                kind,
                points: vec![xy(self.pos)],
            }),
        }
        if let Some(p) = self.path.polylines.last_mut() {
            p.points.extend(points.iter().map(|&q| xy(q)));
        }
        self.pos = last;
    }

    fn line(&mut self, line: &Line<'_>) -> Result<(), String> {
        let mut home = false;
        let mut set = false;
        for w in line.words() {
            if w.letter != b'G' {
                continue;
            }
            match w.value.as_integer() {
                Some(n @ 0..=3) => self.motion = Some(n as u8),
                Some(17) => self.plane = Plane::Xy,
                Some(18) => self.plane = Plane::Zx,
                Some(19) => self.plane = Plane::Yz,
                Some(20) => self.inches = true,
                Some(21) => self.inches = false,
                Some(90) => self.absolute = true,
                Some(91) => self.absolute = false,
                Some(28) => home = true,
                Some(92) => set = true,
                _ => {}
            }
        }
        let value = |letter: u8| line.get(letter).map(|d| d.to_f64());
        let named: Vec<(usize, f64)> = [b'X', b'Y', b'Z']
            .iter()
            .enumerate()
            .filter_map(|(i, &l)| value(l).map(|v| (i, self.to_mm(v))))
            .collect();
        if home {
            // Homing ends at the machine's zero on the axes homed: the path starts afresh.
            let all = named.is_empty();
            for i in 0..3 {
                if all || named.iter().any(|&(k, _)| k == i) {
                    self.pos[i] = 0.0;
                    self.offset[i] = 0.0;
                }
            }
            self.path.polylines.push(Polyline {
                kind: MoveKind::Rapid,
                points: Vec::new(),
            });
            return Ok(());
        }
        if set {
            if named.is_empty() {
                self.offset = self.pos;
            }
            for &(i, v) in &named {
                self.offset[i] = self.pos[i] - v;
            }
            return Ok(());
        }
        if named.is_empty() {
            return Ok(());
        }
        let mut target = self.pos;
        for &(i, v) in &named {
            target[i] = if self.absolute {
                v + self.offset[i]
            } else {
                self.pos[i] + v
            };
        }
        match self.motion {
            Some(0) => self.add(MoveKind::Rapid, &[target]),
            Some(1) | None => self.add(MoveKind::Feed, &[target]),
            Some(m) => {
                let points = self.arc(line, target, m == 2)?;
                self.add(MoveKind::Feed, &points);
            }
        }
        Ok(())
    }

    fn arc(
        &self,
        line: &Line<'_>,
        end: [f64; 3],
        clockwise: bool,
    ) -> Result<Vec<[f64; 3]>, String> {
        let ([a, b, c], [oa, ob]) = self.plane.axes();
        let start = self.pos;
        let (sa, sb, ea, eb) = (start[a], start[b], end[a], end[b]);
        let center = if let Some(r) = line.get(b'R') {
            let r = self.to_mm(r.to_f64());
            let (dx, dy) = (ea - sa, eb - sb);
            let d = (dx * dx + dy * dy).sqrt();
            if d == 0.0 || r == 0.0 {
                return Err("an arc with R needs distinct end points and a radius".into());
            }
            let h = (r * r - d * d / 4.0).max(0.0).sqrt();
            // The centre lies to the right of the chord for a clockwise arc of less than half
            // a turn (R > 0); the other side for counter-clockwise or R < 0.
            let side = if clockwise == (r > 0.0) { -1.0 } else { 1.0 };
            let (mx, my) = ((sa + ea) / 2.0, (sb + eb) / 2.0);
            let (lx, ly) = (-dy / d, dx / d);
            (mx + side * h * lx, my + side * h * ly)
        } else {
            let i = line.get(oa).map_or(0.0, |v| self.to_mm(v.to_f64()));
            let j = line.get(ob).map_or(0.0, |v| self.to_mm(v.to_f64()));
            if i == 0.0 && j == 0.0 {
                return Err("an arc needs a centre (I, J, K) or a radius (R)".into());
            }
            (sa + i, sb + j)
        };
        let radius = ((sa - center.0).powi(2) + (sb - center.1).powi(2)).sqrt();
        let a0 = (sb - center.1).atan2(sa - center.0);
        let a1 = (eb - center.1).atan2(ea - center.0);
        let mut sweep = if clockwise { a0 - a1 } else { a1 - a0 };
        while sweep <= 1e-9 {
            sweep += 2.0 * PI;
        }
        let n = ((sweep / ARC_STEP_RAD).ceil() as usize).clamp(2, 10_000);
        let dir = if clockwise { -1.0 } else { 1.0 };
        let mut points = Vec::with_capacity(n);
        for k in 1..=n {
            let t = k as f64 / n as f64;
            let angle = a0 + dir * sweep * t;
            let mut p = start;
            if k == n {
                p = end;
            } else {
                p[a] = center.0 + radius * angle.cos();
                p[b] = center.1 + radius * angle.sin();
                p[c] = start[c] + (end[c] - start[c]) * t;
            }
            points.push(p);
        }
        Ok(points)
    }
}

fn dist3(p: [f64; 3], q: [f64; 3]) -> f64 {
    ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
}

impl Toolpath {
    /// Follow `program` on a machine that stands at `start` (XYZ mm, machine coordinates)
    /// when it begins.
    ///
    /// Until it homes, a controller counts positions from where it was switched on, so the
    /// program's coordinates are taken relative to `start`; after `G28` they are machine
    /// coordinates (the homed axes at their zero).
    ///
    /// Errors: an arc without centre or radius, with the line number.
    pub fn from_program(program: &Program, start: [f64; 3]) -> Result<Self, PlotError> {
        let mut interp = Interpreter {
            pos: start,
            offset: start,
            absolute: true,
            inches: false,
            plane: Plane::Xy,
            motion: None,
            path: Toolpath::default(),
        };
        let where_ = |n: usize| match &program.path {
            Some(p) => format!("{}, line {n}", p.display()),
            None => format!("line {n}"),
        };
        for l in &program.lines {
            let line = Line::parse(l.text.as_bytes()).map_err(|e| {
                PlotError(format!(
                    "{}: {}",
                    where_(l.source_line),
                    describe_line_error(&e)
                ))
            })?;
            interp
                .line(&line)
                .map_err(|e| PlotError(format!("{}: {e}", where_(l.source_line))))?;
        }
        interp.path.polylines.retain(|p| p.points.len() > 1);
        interp.path.end = interp.pos;
        Ok(interp.path)
    }
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
    /// Replay a trace (`time_ticks,axis,event` rows after `#` header lines). Steps per mm and
    /// start positions come from `machine` when given, else from the trace's optional
    /// `# steps_per_mm X=80 Y=80` and `# start_mm X=150 Y=150` lines.
    ///
    /// Errors: a malformed row or header (with its line number), an X or Y axis whose steps per
    /// mm nobody gives.
    pub fn from_trace(text: &str, machine: Option<&MachineInfo>) -> Result<Self, PlotError> {
        let err = |n: usize, m: &str| PlotError(format!("step trace line {n}: {m}"));
        let mut tick_hz = 0f64;
        let mut letters: Vec<char> = Vec::new();
        let mut header_spm: Vec<(char, f64)> = Vec::new();
        let mut header_start: Vec<(char, f64)> = Vec::new();
        let mut rows_from = None;
        for (i, raw) in text.lines().enumerate() {
            let line = raw.trim();
            let Some(rest) = line.strip_prefix('#') else {
                if line == "time_ticks,axis,event" {
                    rows_from = Some(i + 1);
                    break;
                }
                if line.is_empty() {
                    continue;
                }
                return Err(err(
                    i + 1,
                    "expected \"time_ticks,axis,event\" after the header",
                ));
            };
            let rest = rest.trim();
            if let Some(v) = rest.strip_prefix("tick_hz") {
                tick_hz = v.trim().parse().map_err(|_| err(i + 1, "bad tick_hz"))?;
            } else if let Some(v) = rest.strip_prefix("axes") {
                letters = v
                    .split_whitespace()
                    .filter_map(|a| a.chars().next())
                    .collect();
            } else if let Some(v) = rest.strip_prefix("steps_per_mm") {
                header_spm = pairs(v).map_err(|m| err(i + 1, &m))?;
            } else if let Some(v) = rest.strip_prefix("start_mm") {
                header_start = pairs(v).map_err(|m| err(i + 1, &m))?;
            }
        }
        let Some(rows_from) = rows_from else {
            return Err(PlotError(
                "not a step trace: no \"time_ticks,axis,event\" line".into(),
            ));
        };
        if tick_hz <= 0.0 {
            return Err(PlotError("step trace: missing \"# tick_hz\" header".into()));
        }
        let find = |list: &[(char, f64)], l: char| list.iter().find(|p| p.0 == l).map(|p| p.1);
        let axis = |l: char| -> Result<(f64, f64), PlotError> {
            let from_machine = machine.and_then(|m| m.axis(l));
            let spm = from_machine
                .map(|a| a.steps_per_mm)
                .or_else(|| find(&header_spm, l))
                .ok_or_else(|| {
                    PlotError(format!(
                        "the step trace does not give the steps per mm of axis {l}: give the \
                         machine file with --machine"
                    ))
                })?;
            let start = from_machine
                .map(|a| a.start_mm)
                .or_else(|| find(&header_start, l))
                .unwrap_or(0.0);
            Ok((spm, start))
        };
        let ix = letters.iter().position(|&l| l == 'X');
        let iy = letters.iter().position(|&l| l == 'Y');
        let (sx, x0) = if ix.is_some() { axis('X')? } else { (1.0, 0.0) };
        let (sy, y0) = if iy.is_some() { axis('Y')? } else { (1.0, 0.0) };
        let mut steps = [0i64; 2];
        let mut out = Executed::default();
        let mut last = [x0, y0];
        out.points.push(last);
        let mut last_t = 0u64;
        for (i, raw) in text.lines().enumerate().skip(rows_from) {
            let line = raw.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let mut f = line.split(',');
            let (Some(t), Some(a), Some(ev), None) = (f.next(), f.next(), f.next(), f.next())
            else {
                return Err(err(i + 1, "expected three fields"));
            };
            let t: u64 = t.parse().map_err(|_| err(i + 1, "bad time_ticks"))?;
            last_t = t;
            let delta = match ev {
                "step+" => 1,
                "step-" => -1,
                _ => continue,
            };
            out.steps += 1;
            let k = match a.chars().next() {
                Some('X') if ix.is_some() => 0,
                Some('Y') if iy.is_some() => 1,
                Some(l) if letters.contains(&l) => continue,
                _ => return Err(err(i + 1, &format!("unknown axis \"{a}\""))),
            };
            steps[k] += delta;
            let p = [x0 + steps[0] as f64 / sx, y0 + steps[1] as f64 / sy];
            let d = ((p[0] - last[0]).powi(2) + (p[1] - last[1]).powi(2)).sqrt();
            if d >= MERGE_MM {
                out.length_mm += d;
                out.points.push(p);
                last = p;
            }
        }
        let end = [x0 + steps[0] as f64 / sx, y0 + steps[1] as f64 / sy];
        if end != last {
            out.length_mm += ((end[0] - last[0]).powi(2) + (end[1] - last[1]).powi(2)).sqrt();
            out.points.push(end);
        }
        out.end = end;
        out.duration_s = last_t as f64 / tick_hz;
        Ok(out)
    }
}

/// `X=80 Y=80.5` (also `X:80`).
fn pairs(text: &str) -> Result<Vec<(char, f64)>, String> {
    text.split_whitespace()
        .map(|p| {
            let (l, v) = p
                .split_once('=')
                .or_else(|| p.split_once(':'))
                .ok_or_else(|| format!("expected LETTER=VALUE, not \"{p}\""))?;
            let mut chars = l.chars();
            let (Some(letter), None) = (chars.next(), chars.next()) else {
                return Err(format!("bad axis letter \"{l}\""));
            };
            let v: f64 = v.parse().map_err(|_| format!("bad number \"{v}\""))?;
            Ok((letter.to_ascii_uppercase(), v))
        })
        .collect()
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

/// Draw `path` (and `executed`, if given) to `out`, a `.png` or `.svg` file.
///
/// Errors: another extension, an empty drawing, or the file cannot be written.
pub fn render(
    out: &Path,
    title: &str,
    path: &Toolpath,
    executed: Option<&Executed>,
) -> Result<(), PlotError> {
    let ext = out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    let layout = Layout::new(path, executed)?;
    let size = (WIDTH, layout.height);
    let result = match ext.as_deref() {
        Some("png") => {
            let root = BitMapBackend::new(out, size).into_drawing_area();
            draw(&root, &layout, title, path, executed)
                .and_then(|()| root.present().map_err(|e| e.to_string()))
        }
        Some("svg") => {
            let root = SVGBackend::new(out, size).into_drawing_area();
            draw(&root, &layout, title, path, executed)
                .and_then(|()| root.present().map_err(|e| e.to_string()))
        }
        _ => {
            return Err(PlotError(format!(
                "cannot tell the image format of {}: name it .png or .svg",
                out.display()
            )));
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
        match p.kind {
            MoveKind::Rapid => root
                .draw(&DashedPathElement::new(points, 6, 4, RAPID.stroke_width(1)))
                .map_err(e)?,
            MoveKind::Feed => draw_wide(root, points, FEED).map_err(e)?,
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
    use super::*;

    fn path(text: &str) -> Toolpath {
        Toolpath::from_program(&Program::parse(text.as_bytes()).unwrap(), [0.0; 3]).unwrap()
    }

    #[test]
    fn lines_units_offsets_and_relative_moves() {
        let p = path("G0 X10 Y0\nG1 X10 Y10\nG91 G1 X-10\nG90 G20 G1 X1\nG21 G92 X0\nG1 X5\n");
        assert_eq!(p.rapid_mm, 10.0);
        let feeds: Vec<&Polyline> = p
            .polylines
            .iter()
            .filter(|l| l.kind == MoveKind::Feed)
            .collect();
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
    }

    #[test]
    fn arcs_both_ways_and_by_radius() {
        // A half circle of radius 10 from (0,0) to (20,0) counter-clockwise goes below.
        let p = path("G1 X0 Y0\nG3 X20 Y0 I10 J0\n");
        let pts = &p.polylines[0].points;
        assert!(pts.iter().all(|q| q[1] <= 1e-9));
        assert!((p.feed_mm - PI * 10.0).abs() < 0.05);
        // Clockwise, same ends: above.
        let p = path("G2 X20 Y0 I10 J0\n");
        assert!(p.polylines[0].points.iter().all(|q| q[1] >= -1e-9));
        // By radius: a quarter circle clockwise from (0,0) to (10,10), centre (10,0).
        let p = path("G2 X10 Y10 R10\n");
        for q in &p.polylines[0].points {
            let r = ((q[0] - 10.0).powi(2) + q[1].powi(2)).sqrt();
            assert!((r - 10.0).abs() < 1e-6, "{q:?}");
        }
        // A full circle.
        let p = path("G1 X10 Y0\nG2 X10 Y0 I-10 J0\n");
        assert!((p.feed_mm - (10.0 + 2.0 * PI * 10.0)).abs() < 0.1);
        let e =
            Toolpath::from_program(&Program::parse(b"G2 X1 Y1\n").unwrap(), [0.0; 3]).unwrap_err();
        assert!(e.to_string().starts_with("line 1: an arc needs"), "{e}");
    }

    #[test]
    fn traces_replay_in_machine_millimetres() {
        let trace = "# forja step trace 1\n# tick_hz 1000\n# axes X Y Z\n\
                     # steps_per_mm X=2 Y=4\n# start_mm X=10\ntime_ticks,axis,event\n\
                     0,X,enable\n1,X,step+\n2,X,step+\n3,Y,step-\n4,Z,step+\n5,Y,step-\n";
        let ex = Executed::from_trace(trace, None).unwrap();
        assert_eq!(ex.end, [11.0, -0.5]);
        assert_eq!(ex.steps, 5);
        assert_eq!(ex.duration_s, 0.005);
        let e = Executed::from_trace("# tick_hz 1000\n# axes X\ntime_ticks,axis,event\n", None)
            .unwrap_err();
        assert!(e.to_string().contains("--machine"), "{e}");
        let machine = MachineInfo::parse("[[axis]]\nletter = \"X\"\nsteps_per_mm = 1\n").unwrap();
        let ex = Executed::from_trace(
            "# tick_hz 1000\n# axes X\ntime_ticks,axis,event\n1,X,step-\n",
            Some(&machine),
        )
        .unwrap();
        assert_eq!(ex.end, [-1.0, 0.0]);
        let e = Executed::from_trace(
            "# tick_hz 1000\n# axes X\ntime_ticks,axis,event\n1,Q,step-\n",
            Some(&machine),
        )
        .unwrap_err();
        assert_eq!(e.to_string(), "step trace line 4: unknown axis \"Q\"");
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
