//! The path a program asks for, as the kernel reads it, without moving: what a plot of the
//! toolpath draws before (or beside) the path a machine really took.
//!
//! A [`Preview`] runs each line through the kernel's interpreter from the power-on modal state
//! and reports the straight pieces the kernel would queue, through a callback
//! ([`Preview::line`]): a `G0` as one [`Travel::Rapid`] piece, a `G1` as one [`Travel::Feed`]
//! piece, and an arc as the chords the kernel cuts it into. Units, distance modes, planes,
//! `G92` offsets and every other modal rule are the interpreter's own, so the preview cannot
//! disagree with what the machine is sent. A homing line leaves the homed axes where the
//! kernel's homing cycle ends: at the switch's end of travel, pulled off by the axis's
//! `pull_off_mm`. A line the kernel refuses changes nothing and is returned as its
//! [`CommandError`], as the kernel would answer it.
//!
//! Travel limits are not checked: a preview shows a program that would leave the machine's
//! travel, so that its plot shows where.
//!
//! Context: thread (or a host tool).

use forja_protocol::gcode::Line;

use crate::config::MachineConfig;
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

/// A program's path, line by line. See the [module documentation](self).
#[derive(Clone)]
pub struct Preview<const N: usize> {
    interp: Interpreter<N>,
    config: MachineConfig<N>,
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
            config: config.clone(),
        }
    }

    /// Take the program's next line: `piece(travel, from, to)` is called for each straight
    /// piece it moves along, in order (machine nanometres). Returns the axes the line homed
    /// (bit `i` for axis `i`; 0 for a line that does not home): the path starts again where
    /// homing left them.
    ///
    /// Errors: the [`CommandError`] the kernel would refuse the line with; nothing changes.
    pub fn line(
        &mut self,
        line: &Line<'_>,
        mut piece: impl FnMut(Travel, [i64; N], [i64; N]),
    ) -> Result<u8, CommandError> {
        let mut next = self.interp;
        let from = self.interp.pos;
        let homed = match next.interpret(line, &self.config)? {
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
                piece(travel, from, target);
                0
            }
            Action::Arc { mut cutter, .. } => {
                let mut at = from;
                while let Some(to) = cutter.peek() {
                    piece(Travel::Feed, at, to);
                    at = to;
                    cutter.advance();
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

    fn pieces(preview: &mut Preview<3>, text: &str) -> Vec<(Travel, [i64; 3], [i64; 3])> {
        let mut out = Vec::new();
        let line = Line::parse(text.as_bytes()).unwrap();
        preview.line(&line, |t, a, b| out.push((t, a, b))).unwrap();
        out
    }

    const MM: i64 = 1_000_000;

    #[test]
    fn rapids_and_feeds_follow_the_modal_state() {
        let mut p = Preview::new(&machine(), [0; 3]);
        assert_eq!(
            pieces(&mut p, "G0 X10"),
            vec![(Travel::Rapid, [0; 3], [10 * MM, 0, 0])]
        );
        assert_eq!(
            pieces(&mut p, "G1 Y5 F600"),
            vec![(Travel::Feed, [10 * MM, 0, 0], [10 * MM, 5 * MM, 0])]
        );
        // Inches and relative distances are the interpreter's.
        pieces(&mut p, "G20 G91");
        assert_eq!(
            pieces(&mut p, "X1"),
            vec![(
                Travel::Feed,
                [10 * MM, 5 * MM, 0],
                [10 * MM + 25_400_000, 5 * MM, 0]
            )]
        );
    }

    #[test]
    fn an_arc_is_the_kernels_chords_ending_on_the_target() {
        let mut p = Preview::new(&machine(), [0; 3]);
        let chords = pieces(&mut p, "G2 X20 Y0 I10 J0 F600");
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
    fn homing_ends_pulled_off_the_switch_and_a_refused_line_changes_nothing() {
        let mut p = Preview::new(&machine(), [5 * MM, 0, 0]);
        let line = Line::parse(b"G28 X0").unwrap();
        assert_eq!(p.line(&line, |_, _, _| panic!("no piece")), Ok(0b001));
        assert_eq!(p.position(), [198 * MM, 0, 0]);
        let bad = Line::parse(b"G2 X1").unwrap();
        assert!(p.line(&bad, |_, _, _| panic!("no piece")).is_err());
        assert_eq!(p.position(), [198 * MM, 0, 0]);
    }
}
