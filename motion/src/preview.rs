//! The path a program asks for, as the kernel reads it, without moving: what a plot of the
//! toolpath draws before (or beside) the path a machine really took.
//!
//! A [`Preview`] runs each line through the kernel's interpreter from the power-on modal state
//! and reports the straight [`Piece`]s the kernel would queue, through a callback
//! ([`Preview::line`]): a `G0` as one [`Travel::Rapid`] piece, a `G1` as one [`Travel::Feed`]
//! piece, and an arc as the chords the kernel cuts it into. Units, distance modes, planes,
//! `G92` offsets, extrusion modes (`M82`, `M83`), the flow override (`M221`) and every other
//! modal rule are the interpreter's own, so the preview cannot disagree with what the machine
//! is sent. A homing line leaves the homed axes where the kernel's homing cycle ends: at the
//! switch's end of travel, pulled off by the axis's `pull_off_mm`. A line the kernel refuses
//! changes nothing and is returned as its [`CommandError`], as the kernel would answer it.
//!
//! On a machine with an extruder (an axis of [`AxisKind::Extruder`]) each piece also says what
//! it does with the filament: [`Piece::extruded_nm`] is how far the extruders advance along it
//! and [`Piece::moves_tool`] whether any other axis moves. A piece that [`extrudes`] lays
//! material along its way; one that moves the tool without extruding is a travel move (or a
//! wipe, when the extruders draw back as it goes); one that moves only the extruders is a
//! retraction, its undoing or a prime, in place.
//!
//! Travel limits are not checked: a preview shows a program that would leave the machine's
//! travel, so that its plot shows where.
//!
//! Context: thread (or a host tool).
//!
//! [`extrudes`]: Piece::extrudes

use forja_protocol::gcode::Line;

use crate::config::{AxisKind, MachineConfig};
use crate::coords::Coordinates;
use crate::drill::DrillStep;
use crate::error::CommandError;
use crate::interp::{Action, Interpreter, mm_to_nm};

/// How a piece of the path is travelled.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Travel {
    /// `G0`: positioning at the axes' maximum rates, not cutting.
    Rapid,
    /// `G1`, `G2`, `G3`: at the programmed feed rate.
    Feed,
}

/// One straight piece of a program's path: a `G0` or `G1` move, or one chord of an arc.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Piece<const N: usize> {
    /// How it is travelled.
    pub travel: Travel,
    /// Where it starts, machine nanometres per axis.
    pub from: [i64; N],
    /// Where it ends, machine nanometres per axis.
    pub to: [i64; N],
    /// How far the extruder axes advance along it, nanometres of filament (their sum, in
    /// machine positions: the flow override included): negative when they draw filament
    /// back, 0 when they stand still and on a machine without an extruder.
    pub extruded_nm: i64,
    /// Whether an axis that is not an extruder moves along it: `false` for a piece that only
    /// turns the extruders.
    pub moves_tool: bool,
}

impl<const N: usize> Piece<N> {
    /// Whether material is laid along the piece: the tool moves while the extruders advance.
    pub fn extrudes(&self) -> bool {
        self.moves_tool && self.extruded_nm > 0
    }
}

/// A program's path, line by line. See the [module documentation](self).
#[derive(Clone)]
pub struct Preview<const N: usize> {
    interp: Interpreter<N>,
    config: MachineConfig<N>,
    coords: Coordinates<N>,
}

impl<const N: usize> Preview<N> {
    /// The power-on modal state of a machine of `config` whose position counts from `start_nm`
    /// (machine nanometres per axis). A controller that has not homed counts from zero where
    /// it was switched on, so a preview of what the firmware does starts at zero.
    pub fn new(config: &MachineConfig<N>, start_nm: [i64; N]) -> Self {
        let mut interp = Interpreter::new(config);
        interp.pos = start_nm;
        Self {
            interp,
            config: *config,
            coords: Coordinates::ZERO,
        }
    }

    /// [`Preview::new`] with the work coordinate systems of `coords` (a machine's table; `G54`
    /// active).
    pub fn with_coordinates(
        config: &MachineConfig<N>,
        start_nm: [i64; N],
        coords: &Coordinates<N>,
    ) -> Self {
        let mut preview = Self::new(config, start_nm);
        preview.coords = *coords;
        preview.interp.use_coordinates(coords);
        preview
    }

    /// Read the lines after this in the grbl dialect's meanings (`G28`/`G30` to the stored
    /// positions), as a link in the grbl dialect runs them, or in the RepRap dialect's.
    pub fn set_grbl_dialect(&mut self, grbl: bool) {
        self.interp.grbl = grbl;
    }

    /// Take the program's next line: `piece` is called for each straight [`Piece`] it moves
    /// along, in order. Returns the axes the line homed (bit `i` for axis `i`; 0 for a line
    /// that does not home): the path starts again where homing left them.
    ///
    /// Errors: the [`CommandError`] the kernel would refuse the line with; nothing changes.
    pub fn line(
        &mut self,
        line: &Line<'_>,
        mut piece: impl FnMut(Piece<N>),
    ) -> Result<u8, CommandError> {
        // A spindle or coolant command beside motion acts first, as the kernel takes it.
        if let Some((first, then)) = crate::kernel::split_spindle_and_motion(line) {
            let mut next = self.interp;
            next.interpret(&first, &self.config, &self.coords)?;
            let saved = core::mem::replace(&mut self.interp, next);
            return self.line(&then, piece).inspect_err(|_| self.interp = saved);
        }
        let mut next = self.interp;
        let from = self.interp.pos;
        let homed = match next.interpret(line, &self.config, &self.coords)? {
            Action::Move {
                target,
                feed_mm_min,
                ..
            } => {
                let travel = if feed_mm_min.is_some() {
                    Travel::Feed
                } else {
                    Travel::Rapid
                };
                piece(self.piece(travel, from, target));
                0
            }
            Action::Arc { mut cutter, .. } => {
                let mut at = from;
                while let Some(to) = cutter.peek() {
                    piece(self.piece(Travel::Feed, at, to));
                    at = to;
                    cutter.advance();
                }
                0
            }
            Action::SetCoordinates { slot, values } => {
                self.coords.set(slot, values);
                0
            }
            Action::Via { via, target } => {
                piece(self.piece(Travel::Rapid, from, via));
                piece(self.piece(Travel::Rapid, via, target));
                0
            }
            // The whole way to the target: where the probe stops is the machine's to find.
            Action::Probe { target, .. } => {
                piece(self.piece(Travel::Feed, from, target));
                0
            }
            Action::Drill { mut cycle, .. } => {
                let mut at = from;
                while let Some(step) = cycle.peek() {
                    let (travel, to) = match step {
                        DrillStep::Rapid(to) => (Travel::Rapid, to),
                        DrillStep::Feed(to) => (Travel::Feed, to),
                        DrillStep::Dwell(_) => (Travel::Feed, at),
                    };
                    if to != at {
                        piece(self.piece(travel, at, to));
                    }
                    at = to;
                    cycle.advance();
                }
                0
            }
            Action::Home { mask } => {
                let mut homed = 0;
                for (i, axis) in self.config.axes.iter().enumerate() {
                    // No axis named: all of them (`G28`).
                    if mask != 0 && mask & (1 << i) == 0 {
                        continue;
                    }
                    if let Some(homing) = axis.homing {
                        // Where the kernel's cycle ends: the switch's end of travel, pulled off.
                        let d = homing.direction;
                        next.pos[i] = mm_to_nm(axis.end_mm(d) - d.sign() * homing.pull_off_mm);
                        homed |= 1 << i;
                    }
                }
                homed
            }
            _ => 0,
        };
        self.interp = next;
        Ok(homed)
    }

    /// Where the lines taken so far leave the machine, in machine nanometres per axis.
    pub fn position(&self) -> [i64; N] {
        self.interp.pos
    }

    /// The piece from `from` to `to`, with what it does with the extruders.
    fn piece(&self, travel: Travel, from: [i64; N], to: [i64; N]) -> Piece<N> {
        let mut extruded_nm = 0;
        let mut moves_tool = false;
        for (i, axis) in self.config.axes.iter().enumerate() {
            if axis.kind == AxisKind::Extruder {
                extruded_nm += to[i] - from[i];
            } else if to[i] != from[i] {
                moves_tool = true;
            }
        }
        Piece {
            travel,
            from,
            to,
            extruded_nm,
            moves_tool,
        }
    }
}

#[cfg(test)]
mod tests {
    use std::vec;
    use std::vec::Vec;

    use super::*;
    use crate::config::{AxisConfig, HomeDirection, HomingConfig};

    fn machine() -> MachineConfig<3> {
        let axis = |letter: u8| AxisConfig::linear(letter, 80.0, 6000.0, 500.0, 200.0);
        let mut config = MachineConfig::new([axis(b'X'), axis(b'Y'), axis(b'Z')]);
        config.axes[0].min_mm = 0.0;
        config.axes[0].max_mm = 200.0;
        config.axes[0].homing = Some(HomingConfig {
            direction: HomeDirection::Max,
            seek_mm_min: 1000.0,
            locate_mm_min: 100.0,
            pull_off_mm: 2.0,
            switch: 0,
            order: 0,
        });
        config
    }

    /// A printer: X, Y, Z and an extruder E; X homes to its minimum.
    fn printer() -> MachineConfig<4> {
        let axis = |letter: u8| AxisConfig::linear(letter, 80.0, 6000.0, 500.0, 200.0);
        let mut config = MachineConfig::new([axis(b'X'), axis(b'Y'), axis(b'Z'), axis(b'E')]);
        config.axes[3].kind = AxisKind::Extruder;
        config.axes[0].homing = Some(HomingConfig {
            direction: HomeDirection::Min,
            seek_mm_min: 1000.0,
            locate_mm_min: 100.0,
            pull_off_mm: 5.0,
            switch: 0,
            order: 0,
        });
        config
    }

    fn pieces<const N: usize>(preview: &mut Preview<N>, text: &str) -> Vec<Piece<N>> {
        let mut out = Vec::new();
        let line = Line::parse(text.as_bytes()).unwrap();
        preview.line(&line, |p| out.push(p)).unwrap();
        out
    }

    /// How, from where and to where each piece goes.
    fn ends<const N: usize>(pieces: &[Piece<N>]) -> Vec<(Travel, [i64; N], [i64; N])> {
        pieces.iter().map(|p| (p.travel, p.from, p.to)).collect()
    }

    /// The one piece of a line, with what it does with the extruder.
    fn filament(preview: &mut Preview<4>, text: &str) -> (i64, bool, bool) {
        let pieces = pieces(preview, text);
        assert_eq!(pieces.len(), 1, "{text}: {pieces:?}");
        let p = pieces[0];
        (p.extruded_nm, p.moves_tool, p.extrudes())
    }

    const MM: i64 = 1_000_000;

    #[test]
    fn rapids_and_feeds_follow_the_modal_state() {
        let mut p = Preview::new(&machine(), [0; 3]);
        assert_eq!(
            ends(&pieces(&mut p, "G0 X10")),
            vec![(Travel::Rapid, [0; 3], [10 * MM, 0, 0])]
        );
        assert_eq!(
            ends(&pieces(&mut p, "G1 Y5 F600")),
            vec![(Travel::Feed, [10 * MM, 0, 0], [10 * MM, 5 * MM, 0])]
        );
        // Inches and relative distances are the interpreter's.
        pieces(&mut p, "G20 G91");
        assert_eq!(
            ends(&pieces(&mut p, "X1")),
            vec![(
                Travel::Feed,
                [10 * MM, 5 * MM, 0],
                [10 * MM + 25_400_000, 5 * MM, 0]
            )]
        );
        // No extruder: nothing is ever extruded.
        let all = pieces(&mut p, "G1 X1 Y1 Z1");
        assert!(
            all.iter()
                .all(|p| p.extruded_nm == 0 && p.moves_tool && !p.extrudes())
        );
    }

    #[test]
    fn an_arc_is_the_kernels_chords_ending_on_the_target() {
        let mut p = Preview::new(&machine(), [0; 3]);
        let chords = ends(&pieces(&mut p, "G2 X20 Y0 I10 J0 F600"));
        assert!(chords.len() > 4, "{chords:?}");
        assert!(chords.iter().all(|c| c.0 == Travel::Feed));
        for pair in chords.windows(2) {
            assert_eq!(pair[0].2, pair[1].1, "the chords join");
        }
        assert_eq!(chords.last().unwrap().2, [20 * MM, 0, 0]);
        // Clockwise from (0,0) around (10,0): the chords pass above the X axis.
        assert!(chords.iter().all(|c| c.2[1] >= 0));
        assert_eq!(p.position(), [20 * MM, 0, 0]);
    }

    #[test]
    fn extrusion_travel_and_retraction_are_told_apart() {
        let mut p = Preview::new(&printer(), [0; 4]);
        pieces(&mut p, "M83");
        // Material laid while the tool moves.
        assert_eq!(
            filament(&mut p, "G1 X10 E1.5 F1200"),
            (1_500_000, true, true)
        );
        // A retraction, its undoing and a prime only turn the extruder.
        assert_eq!(filament(&mut p, "G1 E-.8 F2100"), (-800_000, false, false));
        assert_eq!(filament(&mut p, "G1 E.8"), (800_000, false, false));
        // Travel, in rapids or at the feed rate, and a Z move.
        assert_eq!(filament(&mut p, "G0 X20 Y5"), (0, true, false));
        assert_eq!(filament(&mut p, "G1 Z.4 F600"), (0, true, false));
        // A wipe draws filament back as the tool moves: not an extrusion.
        assert_eq!(filament(&mut p, "G1 X25 E-.2"), (-200_000, true, false));
        // Absolute extrusion: the advance is the difference of positions.
        pieces(&mut p, "M82");
        pieces(&mut p, "G92 E0");
        assert_eq!(filament(&mut p, "G1 X30 E2"), (2 * MM, true, true));
        assert_eq!(filament(&mut p, "G1 X31 E1"), (-MM, true, false));
        // An arc's chords share its extrusion: each extrudes, together the whole of it.
        pieces(&mut p, "G92 E0");
        let chords = pieces(&mut p, "G3 X41 Y5 I5 J0 E3");
        assert!(chords.len() > 4, "{chords:?}");
        assert!(chords.iter().all(Piece::extrudes), "{chords:?}");
        assert_eq!(chords.iter().map(|c| c.extruded_nm).sum::<i64>(), 3 * MM);
    }

    #[test]
    fn homing_ends_pulled_off_the_switch_and_a_refused_line_changes_nothing() {
        let mut p = Preview::new(&machine(), [5 * MM, 0, 0]);
        let line = Line::parse(b"G28 X0").unwrap();
        assert_eq!(p.line(&line, |_| panic!("no piece")), Ok(0b001));
        assert_eq!(p.position(), [198 * MM, 0, 0]);
        let bad = Line::parse(b"G2 X1").unwrap();
        assert!(p.line(&bad, |_| panic!("no piece")).is_err());
        assert_eq!(p.position(), [198 * MM, 0, 0]);
        // `G28` homes every axis that homes, to its minimum here, and leaves the others.
        let mut p = Preview::new(&printer(), [50 * MM, 60 * MM, 7 * MM, 3 * MM]);
        let line = Line::parse(b"G28").unwrap();
        assert_eq!(p.line(&line, |_| panic!("no piece")), Ok(0b0001));
        assert_eq!(p.position(), [5 * MM, 60 * MM, 7 * MM, 3 * MM]);
    }
}
