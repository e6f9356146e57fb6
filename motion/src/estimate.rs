//! How long a program takes, worked out before it runs.
//!
//! An [`Estimate`] is a dry run of the kernel's own interpreter and planner (same depth, same
//! configuration, starting from the kernel's position and modal state): lines are planned until
//! the planner is full, then the oldest block is timed with its final entry and exit speeds, as
//! segment preparation will execute it. Homing counts as the seek over the whole travel. The
//! caller feeds the program's lines in order ([`Estimate::line`]) and reads the total
//! ([`Estimate::seconds`]); where the lines come from (a program store, a file) is its concern.
//!
//! Context: thread. Nothing moves and the kernel is not changed.

use forja_protocol::gcode::Line;

use crate::arc::Nm;
use crate::config::MachineConfig;
use crate::coords::Coordinates;
use crate::drill::DrillStep;
use crate::effect::Effect;
use crate::interp::{Action, Interpreter};
use crate::kernel::Kernel;
use crate::planner::{BlockKind, MoveRequest, Planner};
use crate::profile::Profile;

/// A dry run of a program, line by line. See the [module documentation](self).
pub struct Estimate<const N: usize, const B: usize> {
    /// The kernel's configuration, as the program's `M201`/`M203`/`M205 J` change it.
    config: MachineConfig<N>,
    coords: Coordinates<N>,
    interp: Interpreter<N>,
    steps: [i32; N],
    planner: Planner<N, B>,
    total: f64,
    v_carry: f64,
    ended: bool,
}

impl<const N: usize, const B: usize> Estimate<N, B> {
    /// A dry run from where `kernel` stands now: its position, modal state and configuration.
    pub fn new<const Q: usize>(kernel: &Kernel<'_, N, B, Q>) -> Self {
        Self {
            config: *kernel.config(),
            coords: *kernel.coordinates(),
            interp: kernel.interpreter(),
            steps: kernel.commanded_steps(),
            planner: {
                let mut planner = Planner::new();
                planner.set_limits(kernel.planner_settings().path);
                planner
            },
            total: 0.0,
            v_carry: 0.0,
            ended: false,
        }
    }

    /// Plan the program's next line. A line the kernel would refuse changes nothing, as when it
    /// runs. Returns `false` once the program has ended (`M2`/`M30`): later lines do not count.
    pub fn line(&mut self, line: &Line<'_>) -> bool {
        if self.ended {
            return false;
        }
        // A spindle or coolant command beside motion acts first, as the kernel takes it: the
        // whole line, or (refused) nothing of it.
        if let Some((first, then)) = crate::kernel::split_spindle_and_motion(line) {
            let mut next = self.interp;
            let whole = next.interpret(&first, &self.config, &self.coords).is_ok() && {
                let mut after = next;
                after.interpret(&then, &self.config, &self.coords).is_ok()
            };
            if !whole {
                return true;
            }
            self.interp = next;
            return self.line(&then);
        }
        let mut next = self.interp;
        let Ok(action) = next.interpret(line, &self.config, &self.coords) else {
            return true;
        };
        self.interp = next;
        match action {
            Action::Move {
                target,
                feed_mm_min,
                ramp,
            } => self.push(&target, feed_mm_min, ramp),
            Action::Arc {
                mut cutter,
                feed_mm_min,
                ramp,
            } => {
                while let Some(p) = cutter.peek() {
                    let first = cutter.is_first();
                    cutter.advance();
                    self.push(&p, Some(feed_mm_min), ramp && first);
                }
            }
            Action::Dwell { ms } => self.dwell(ms),
            Action::Via { via, target } => {
                self.push(&via, None, false);
                self.push(&target, None, false);
            }
            Action::Probe {
                target,
                feed_mm_min,
                ..
            } => self.push(&target, Some(feed_mm_min), false),
            Action::Drill {
                mut cycle,
                feed_mm_min,
            } => {
                while let Some(step) = cycle.peek() {
                    match step {
                        DrillStep::Rapid(p) => self.push(&p, None, false),
                        DrillStep::Feed(p) => self.push(&p, Some(feed_mm_min), false),
                        DrillStep::Dwell(ms) => self.dwell(ms),
                    }
                    cycle.advance();
                }
            }
            Action::Effect(Effect::ProgramEnd) => self.ended = true,
            Action::SetLimits(change) => {
                // As the kernel takes it: refused (and changing nothing) when the
                // configuration it makes is not valid.
                let mut config = self.config;
                let mut limits = self.planner.limits();
                change.apply(&mut config, &mut limits);
                if config.validate().is_ok() {
                    self.config = config;
                    self.planner.set_limits(limits);
                }
            }
            Action::Home { mask } => {
                while !self.planner.is_empty() {
                    self.retire();
                }
                for (i, a) in self.config.axes.iter().enumerate() {
                    if let (true, Some(h)) = (mask & (1 << i) != 0, a.homing) {
                        self.total += f64::from(a.travel_mm()) / f64::from(h.seek_mm_min / 60.0);
                    }
                }
            }
            _ => {}
        }
        !self.ended
    }

    fn dwell(&mut self, ms: u32) {
        if self.planner.is_full() {
            self.retire();
        }
        let _ = self.planner.push_dwell(ms, 0);
    }

    /// The program's duration so far, seconds: every block planned, timed to a stop at the end.
    pub fn seconds(mut self) -> f32 {
        while !self.planner.is_empty() {
            self.retire();
        }
        self.total as f32
    }

    /// Time the oldest block with its final speeds, and drop it.
    fn retire(&mut self) {
        let exit_sqr = self.planner.tail_exit_sqr();
        if let Some(b) = self.planner.tail().copied() {
            match b.kind {
                BlockKind::Dwell(ms) => {
                    self.total += f64::from(ms) / 1000.0;
                    self.v_carry = 0.0;
                }
                BlockKind::Move => {
                    let p = Profile::plan(
                        f64::from(b.mm),
                        self.v_carry,
                        libm::sqrt(f64::from(b.nominal_sqr)),
                        libm::sqrt(f64::from(exit_sqr)),
                        f64::from(b.accel),
                    );
                    self.total += p.duration();
                    self.v_carry = p.exit_speed();
                }
            }
        }
        self.planner.retire_tail();
    }

    /// Plan a straight move to `target`, timing the oldest block first when the planner is full.
    fn push(&mut self, target: &[Nm; N], feed: Option<f32>, ramp: bool) {
        if self.planner.is_full() {
            self.retire();
        }
        let mut req =
            MoveRequest::to_target(target, &mut self.steps, &self.config, feed, ramp, 0, 0);
        req.feed_scale = self.interp.feed_scale();
        let _ = self.planner.push_move(&req, &self.config);
    }
}
