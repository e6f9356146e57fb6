//! Drilling canned cycles (`G81`, `G82`, `G83`): one hole's moves, produced one at a time.
//!
//! Thread side. The interpreter works out where a hole is and what its cycle does
//! ([`DrillCycle::new`]); the kernel plans the moves as the planner has room, as it plans an
//! arc's chords. The moves are those of grblHAL and LinuxCNC for the XY plane (`G17`):
//!
//! 1. when the tool is below the retract plane `R`, a rapid up to it;
//! 2. a rapid in X and Y to the hole;
//! 3. a rapid down to `R`;
//! 4. `G81`: a feed to the bottom `Z`. `G82`: the same, then a dwell of `P` seconds.
//!    `G83`: pecks of `Q` each, every one followed by a rapid out to `R` and a rapid back down
//!    to [`PECK_CLEARANCE_NM`] above the depth reached, until the bottom;
//! 5. a rapid up to the clearance height: the retract plane (`G99`), or the higher of it and
//!    where Z was when the cycle began (`G98`).

use crate::arc::Nm;

/// How far above the depth already drilled a `G83` peck's rapid return stops, nm: the feed
/// takes over there (LinuxCNC's 0.010 in).
pub(crate) const PECK_CLEARANCE_NM: Nm = 254_000;

/// Which cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum DrillKind {
    /// `G81`: drill to the bottom, retract.
    Drill,
    /// `G82`: drill to the bottom, dwell, retract.
    Dwell,
    /// `G83`: drill in pecks, leaving the hole after each.
    Peck,
}

/// One move of a cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum DrillStep<const N: usize> {
    /// A rapid to this machine position.
    Rapid([Nm; N]),
    /// A move at the cycle's feed to this machine position.
    Feed([Nm; N]),
    /// A dwell at the bottom, ms.
    Dwell(u32),
}

/// Where the cycle is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Up to the retract plane when below it.
    Clear,
    /// Over to the hole.
    Over,
    /// Down to the retract plane.
    Down,
    /// Feeding down (`G83`: the next peck).
    Cut,
    /// `G83`: out to the retract plane after a peck.
    PeckOut,
    /// `G83`: back down to just above the depth reached.
    PeckIn,
    /// `G82`: the dwell at the bottom.
    Wait,
    /// Up to the clearance height.
    Retract,
    /// Done.
    Done,
}

/// One hole's cycle. Machine positions in nm; Z is axis `z`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct DrillCycle<const N: usize> {
    kind: DrillKind,
    z: usize,
    /// Where the tool is before the next step.
    at: [Nm; N],
    /// The hole, at the height the tool is when it gets there.
    hole: [Nm; N],
    retract_nm: Nm,
    bottom_nm: Nm,
    clearance_nm: Nm,
    /// `G83`: the depth of one peck.
    peck_nm: Nm,
    /// `G82`: the dwell.
    dwell_ms: u32,
    /// The deepest point drilled so far.
    reached_nm: Nm,
    phase: Phase,
}

impl<const N: usize> DrillCycle<N> {
    /// The cycle from `from` (machine nm) for the hole at `hole` (its X and Y; its Z is not
    /// used), drilling from `retract_nm` down to `bottom_nm` and ending at `clearance_nm` (all
    /// machine Z). The interpreter checks that the bottom is below the retract plane, the
    /// clearance not below it, and `peck_nm` positive for `G83`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        kind: DrillKind,
        z: usize,
        from: [Nm; N],
        hole: [Nm; N],
        retract_nm: Nm,
        bottom_nm: Nm,
        clearance_nm: Nm,
        peck_nm: Nm,
        dwell_ms: u32,
    ) -> Self {
        let mut hole = hole;
        if let Some(h) = hole.get_mut(z) {
            *h = from.get(z).copied().unwrap_or(0).max(retract_nm);
        }
        Self {
            kind,
            z,
            at: from,
            hole,
            retract_nm,
            bottom_nm,
            clearance_nm,
            peck_nm,
            dwell_ms,
            reached_nm: retract_nm,
            phase: Phase::Clear,
        }
    }

    /// Where the cycle ends: over the hole at the clearance height.
    pub(crate) fn end(&self) -> [Nm; N] {
        self.with_z(self.hole, self.clearance_nm)
    }

    /// The lowest and highest position of each axis over the whole cycle, for the travel
    /// checks.
    pub(crate) fn bounds(&self) -> ([Nm; N], [Nm; N]) {
        let points = [
            self.at,
            self.hole,
            self.with_z(self.hole, self.bottom_nm),
            self.with_z(self.hole, self.retract_nm),
            self.end(),
        ];
        let lo = core::array::from_fn(|i| points.iter().map(|p| p[i]).min().unwrap_or(0));
        let hi = core::array::from_fn(|i| points.iter().map(|p| p[i]).max().unwrap_or(0));
        (lo, hi)
    }

    fn with_z(&self, mut p: [Nm; N], z_nm: Nm) -> [Nm; N] {
        if let Some(z) = p.get_mut(self.z) {
            *z = z_nm;
        }
        p
    }

    fn z_now(&self) -> Nm {
        self.at.get(self.z).copied().unwrap_or(0)
    }

    /// The next move, without consuming it; `None` when the cycle is over.
    pub(crate) fn peek(&self) -> Option<DrillStep<N>> {
        self.next_of(self.phase).map(|(step, _)| step)
    }

    /// Consume the move [`DrillCycle::peek`] returned.
    pub(crate) fn advance(&mut self) {
        if let Some((step, phase)) = self.next_of(self.phase) {
            match step {
                DrillStep::Rapid(p) | DrillStep::Feed(p) => self.at = p,
                DrillStep::Dwell(_) => {}
            }
            if let DrillStep::Feed(p) = step {
                self.reached_nm = self.reached_nm.min(p.get(self.z).copied().unwrap_or(0));
            }
            self.phase = phase;
        } else {
            self.phase = Phase::Done;
        }
    }

    /// The move of `phase` and the phase after it, skipping the phases with nothing to do.
    fn next_of(&self, mut phase: Phase) -> Option<(DrillStep<N>, Phase)> {
        loop {
            let (step, next) = match phase {
                Phase::Clear if self.z_now() < self.retract_nm => (
                    Some(DrillStep::Rapid(self.with_z(self.at, self.retract_nm))),
                    Phase::Over,
                ),
                Phase::Clear => (None, Phase::Over),
                Phase::Over => (
                    Some(DrillStep::Rapid(self.with_z(self.hole, self.z_now()))),
                    Phase::Down,
                ),
                Phase::Down if self.z_now() != self.retract_nm => (
                    Some(DrillStep::Rapid(self.with_z(self.hole, self.retract_nm))),
                    Phase::Cut,
                ),
                Phase::Down => (None, Phase::Cut),
                Phase::Cut => {
                    let depth = match self.kind {
                        DrillKind::Peck => self
                            .reached_nm
                            .saturating_sub(self.peck_nm)
                            .max(self.bottom_nm),
                        DrillKind::Drill | DrillKind::Dwell => self.bottom_nm,
                    };
                    let next = match self.kind {
                        DrillKind::Peck if depth > self.bottom_nm => Phase::PeckOut,
                        DrillKind::Dwell => Phase::Wait,
                        _ => Phase::Retract,
                    };
                    (Some(DrillStep::Feed(self.with_z(self.hole, depth))), next)
                }
                Phase::PeckOut => (
                    Some(DrillStep::Rapid(self.with_z(self.hole, self.retract_nm))),
                    Phase::PeckIn,
                ),
                Phase::PeckIn => {
                    let above = self
                        .reached_nm
                        .saturating_add(PECK_CLEARANCE_NM)
                        .min(self.retract_nm);
                    (
                        Some(DrillStep::Rapid(self.with_z(self.hole, above))),
                        Phase::Cut,
                    )
                }
                Phase::Wait => (Some(DrillStep::Dwell(self.dwell_ms)), Phase::Retract),
                Phase::Retract => (Some(DrillStep::Rapid(self.end())), Phase::Done),
                Phase::Done => return None,
            };
            match step {
                // A rapid to where the tool already is: nothing to do.
                Some(DrillStep::Rapid(p)) if p == self.at => phase = next,
                Some(s) => return Some((s, next)),
                None => phase = next,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use super::*;

    const MM: Nm = 1_000_000;

    fn steps(mut c: DrillCycle<3>) -> Vec<DrillStep<3>> {
        let mut out = Vec::new();
        while let Some(s) = c.peek() {
            out.push(s);
            c.advance();
        }
        out
    }

    #[test]
    fn g81_from_above_goes_over_down_to_r_feeds_to_the_bottom_and_retracts() {
        let c = DrillCycle::new(
            DrillKind::Drill,
            2,
            [0, 0, 30 * MM],
            [10 * MM, 5 * MM, 0],
            22 * MM,
            15 * MM,
            30 * MM,
            0,
            0,
        );
        assert_eq!(
            steps(c),
            [
                DrillStep::Rapid([10 * MM, 5 * MM, 30 * MM]),
                DrillStep::Rapid([10 * MM, 5 * MM, 22 * MM]),
                DrillStep::Feed([10 * MM, 5 * MM, 15 * MM]),
                DrillStep::Rapid([10 * MM, 5 * MM, 30 * MM]),
            ]
        );
        assert_eq!(c.end(), [10 * MM, 5 * MM, 30 * MM]);
        assert_eq!(c.bounds(), ([0, 0, 15 * MM], [10 * MM, 5 * MM, 30 * MM]));
    }

    #[test]
    fn a_tool_below_the_retract_plane_rises_to_it_before_moving_over() {
        let c = DrillCycle::new(
            DrillKind::Dwell,
            2,
            [0, 0, 20 * MM],
            [10 * MM, 0, 0],
            22 * MM,
            15 * MM,
            22 * MM,
            0,
            500,
        );
        assert_eq!(
            steps(c),
            [
                DrillStep::Rapid([0, 0, 22 * MM]),
                DrillStep::Rapid([10 * MM, 0, 22 * MM]),
                DrillStep::Feed([10 * MM, 0, 15 * MM]),
                DrillStep::Dwell(500),
                DrillStep::Rapid([10 * MM, 0, 22 * MM]),
            ]
        );
    }

    #[test]
    fn g83_pecks_leave_the_hole_and_come_back_just_above_the_depth_reached() {
        let c = DrillCycle::new(
            DrillKind::Peck,
            2,
            [0, 0, 22 * MM],
            [0, 0, 0],
            22 * MM,
            17 * MM,
            22 * MM,
            2 * MM,
            0,
        );
        let z = |nm: Nm| [0, 0, nm];
        assert_eq!(
            steps(c),
            [
                DrillStep::Feed(z(20 * MM)),
                DrillStep::Rapid(z(22 * MM)),
                DrillStep::Rapid(z(20 * MM + PECK_CLEARANCE_NM)),
                DrillStep::Feed(z(18 * MM)),
                DrillStep::Rapid(z(22 * MM)),
                DrillStep::Rapid(z(18 * MM + PECK_CLEARANCE_NM)),
                DrillStep::Feed(z(17 * MM)),
                DrillStep::Rapid(z(22 * MM)),
            ]
        );
    }
}
