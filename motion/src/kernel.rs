//! The thread side: [`Kernel`] takes G-code lines, jogs and actions, plans, prepares steps
//! and runs homing; [`split`] creates it together with its interrupt side.

use core::sync::atomic::Ordering;

use forja_hal_abstraction::stepper::StepTiming;
use forja_hal_abstraction::time::{Duration, Instant};
use forja_protocol::gcode::{Decimal, Line, MAX_WORDS, Word};

use crate::arc::{ArcCutter, Nm};
use crate::config::{AxisKind, MachineConfig, SoftLimits};
use crate::coords::Coordinates;
use crate::drill::{DrillCycle, DrillStep};
use crate::effect::{Effect, StopKind};
use crate::error::{Alarm, CommandError, ConfigError};
use crate::interp::{
    Action, Interpreter, LimitChange, NM_PER_MM, Staged, mm_to_nm, nm_to_steps, steps_to_nm, to_nm,
};
use crate::planner::{MoveRequest, PathLimits, Planner};
use crate::prep::{Fill, Prep};
use crate::queue::{
    MAX_DELTA, PROBE_CONTACT, PROBE_OFF, PROBE_RELEASE, Producer, StepQueue, StopCause,
};
use crate::stepgen::StepGenerator;

/// The largest machine position magnitude a move may reach, mm: ±99999.9999 mm, the widest
/// value a frame 51 position field holds. Axes whose steps/mm would overflow `i32` steps
/// before that have a smaller bound. An extruder is bound by its `i32` steps only: its
/// position grows with every millimetre of filament fed, and a long print feeds more.
pub(crate) const MAX_POSITION_MM: f64 = 99_999.999_9;

/// The answer to one G-code line.
#[derive(Debug, Clone, Copy, PartialEq)]
#[must_use]
pub enum Reply<'l, const N: usize> {
    /// Taken: done, or its motion queued. Acknowledge it (`ok`).
    Ok,
    /// Not taken, nothing changed: the planner is full, or the line must wait for the motion
    /// before it. Offer the same line again after the next [`Kernel::poll`].
    Busy,
    /// Taken (`M114`): the position to report.
    Position(PositionReport<N>),
    /// Taken: a command for another subsystem, to carry out now, in stream order.
    Effect(Effect<'l>),
}

/// Positions for `M114` and the status frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionReport<const N: usize> {
    /// The axis letters.
    pub letters: [u8; N],
    /// The commanded position in work coordinates (after `G92`), mm: where the last queued
    /// move ends.
    pub work_mm: [f64; N],
    /// The machine position, mm: where the steppers are now.
    pub machine_mm: [f64; N],
}

/// The settings the planner works with now, for a report of them (Marlin's `M503`): what
/// `M92`, `M201`, `M203`, `M204`, `M205`, `M220` and `M221` set, in the units Marlin reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlannerSettings<const N: usize> {
    /// The axis letters.
    pub letters: [u8; N],
    /// `M92`: steps per mm (per degree on a rotary axis).
    pub steps_per_mm: [f32; N],
    /// `M201`: the maximum acceleration of each axis, mm/s².
    pub max_accel_mm_s2: [f32; N],
    /// `M203`: the maximum rate of each axis, mm/s (the configuration's
    /// [`AxisConfig::max_rate_mm_min`](crate::AxisConfig::max_rate_mm_min) / 60).
    pub max_rate_mm_s: [f32; N],
    /// `M204` and `M205 S`/`T`: the limits along the path by kind of move.
    pub path: PathLimits,
    /// `M205 J`: the junction deviation, mm.
    pub junction_deviation_mm: f32,
    /// `M220`: the feed-rate override, percent.
    pub feed_percent: u16,
    /// `M221`: the flow override of each extruder axis, percent; `None` for the other axes.
    pub flow_percent: [Option<u16>; N],
}

/// The interpreter's modal state, for a parser-state report (grbl's `$G`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModalReport<const N: usize> {
    /// The motion mode as its G code: `G0`–`G3`, `G38.2`–`G38.5`, `G80`–`G83`.
    pub motion: &'static str,
    /// The plane: 17, 18 or 19.
    pub plane: u8,
    /// `G20` (inches) rather than `G21`.
    pub inches: bool,
    /// `G90` (absolute) rather than `G91`.
    pub absolute: bool,
    /// The programmed feed rate, mm/min.
    pub feed_mm_min: f32,
    /// The work coordinate system, 0 for `G54` (6–8: `G59.1`–`G59.3`).
    pub coordinate_system: u8,
    /// `G61`: every move ends at rest (else `G64`).
    pub exact_stop: bool,
    /// The tool length offset (`G43.1`), nm.
    pub tool_length_nm: i64,
    /// The `G92` offset of each axis, nm (grbl's sign: work = machine − origin − this).
    pub g92_nm: [i64; N],
}

/// The motion now ([`Kernel::motion_now`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionNow {
    /// The speed along the path, mm/min; 0 at rest.
    pub speed_mm_min: f32,
    /// That speed as a fraction of the move's programmed speed (after the overrides): 0 at
    /// rest, 1 at the programmed speed, below it while accelerating, decelerating or cornering.
    pub fraction: f32,
    /// The move is a rapid (`G0`).
    pub rapid: bool,
    /// The spindle speed (`S`) in force for the move, rpm; at rest, the one the lines taken so
    /// far set.
    pub spindle_rpm: u32,
}

/// The machine's state, as the controller reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MachineState {
    /// At rest, ready.
    Idle,
    /// Moving (or dwelling).
    Running,
    /// A feed hold: decelerating (`stopped == false`) or at rest on the path.
    Hold {
        /// Whether the machine has come to rest.
        stopped: bool,
    },
    /// Paused by `M226`, at rest; [`Kernel::resume`] continues.
    Paused,
    /// Running the homing cycle.
    Homing,
    /// Locked by an alarm: [`Kernel::reset`] or a homing clears it.
    Alarm(Alarm),
    /// Stopped by `M0`: [`Kernel::reset`] clears it.
    Halted,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum HomePhase {
    Next,
    Seek,
    BackOff,
    Locate,
    PullOff,
}

#[derive(Debug, Clone, Copy)]
struct Homing {
    pending: u8,
    axis: usize,
    phase: HomePhase,
    start_steps: i32,
    triggered: Option<i32>,
}

/// A probing move under way (`G38.2`–`G38.5`).
#[derive(Debug, Clone, Copy)]
struct Probing<const N: usize> {
    /// `G38.2`/`G38.4`: a move that ends without the probe changing is an alarm.
    must_trip: bool,
    /// The step interrupt's counts when the move started.
    start: [i32; N],
    /// Its counts where the probe tripped.
    tripped: Option<[i32; N]>,
}

/// The outcome of the last probing move, for a report (grbl's `[PRB:…]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeReport<const N: usize> {
    /// The machine position where the probe tripped, or where the move ended without it, nm.
    pub machine_nm: [Nm; N],
    /// Whether the probe tripped.
    pub tripped: bool,
}

/// An axis's bounds in machine nm, worked out from the configuration when it is set (at
/// [`split`] and by `M92`), not at every move: its travel, and how far from 0 a position may
/// be counted and reported ([`MAX_POSITION_MM`], `i32` steps).
#[derive(Debug, Clone, Copy)]
struct AxisBounds {
    min: Nm,
    max: Nm,
    reach: Nm,
}

fn axis_bounds<const N: usize>(config: &MachineConfig<N>) -> [AxisBounds; N] {
    core::array::from_fn(|i| {
        let a = &config.axes[i];
        let counted = f64::from(i32::MAX) / f64::from(a.steps_per_mm);
        let reach_mm = match a.kind {
            AxisKind::Extruder => counted,
            _ => MAX_POSITION_MM.min(counted),
        };
        AxisBounds {
            min: mm_to_nm(a.min_mm),
            max: mm_to_nm(a.max_mm),
            reach: libm::floor(reach_mm * NM_PER_MM) as Nm,
        }
    })
}

/// A pending arc: chords still to be planned.
#[derive(Debug, Clone, Copy)]
struct PendingArc<const N: usize> {
    cutter: ArcCutter<N>,
    feed_mm_min: f32,
    /// The feed override of the arc's line, as a factor.
    feed_scale: f32,
    ramp: bool,
    /// `G61`: the arc starts from rest.
    exact_stop: bool,
}

/// A pending drilling cycle: moves still to be planned.
#[derive(Debug, Clone, Copy)]
struct PendingDrill<const N: usize> {
    cycle: DrillCycle<N>,
    feed_mm_min: f32,
    /// The feed override of the cycle's line, as a factor.
    feed_scale: f32,
}

/// The thread side of the motion kernel.
///
/// `N` axes, a planner of `B` blocks (default 32) and a step queue of `Q` events (default 256,
/// a power of two). Context: thread (a task or the main loop), never the step interrupt. None
/// of its methods block; none allocate.
pub struct Kernel<'q, const N: usize, const B: usize = 32, const Q: usize = 256> {
    config: MachineConfig<N>,
    bounds: [AxisBounds; N],
    tick_hz: u32,
    /// The work coordinate systems and stored positions.
    coords: Coordinates<N>,
    /// The slots of `coords` changed since the application last took them.
    coords_changed: u16,
    /// The drivers' timing the configuration is checked against (`M203`).
    timing: StepTiming,
    tx: Producer<'q, N, Q>,
    planner: Planner<N, B>,
    prep: Prep<N>,
    /// The last [`Kernel::poll`] stopped preparing with work left.
    prep_more: bool,
    /// The interpreter's state, and the spare a line is interpreted into.
    interp: Staged<N>,
    /// Commanded machine position in steps (where the last queued move ends).
    steps: [i32; N],
    /// Interrupt step count of machine step 0.
    origin: [i32; N],
    homed: u8,
    alarm: Option<Alarm>,
    halted: bool,
    paused: bool,
    hold: bool,
    stop_requested: bool,
    arc: Option<PendingArc<N>>,
    drill: Option<PendingDrill<N>>,
    homing: Option<Homing>,
    probing: Option<Probing<N>>,
    /// The last probing move's outcome, and whether it was reported since.
    probe: Option<(ProbeReport<N>, bool)>,
    flush: Option<u32>,
    /// The realtime feed and rapid overrides, percent.
    overrides: (u16, u16),
    /// The spindle speed the moves queued now carry, rpm.
    block_rpm: u32,
    stops_seen: u32,
    /// Until when a [`Kernel::poll`] has nothing to do unless the interrupt stops: set by one
    /// that found nothing, cleared by any call that gives the thread side work of its own (a
    /// cycle, a flush, a stop) and by every poll that does work.
    quiet_until: Option<Instant>,
    lead_ticks: u32,
    line_tag: u32,
}

/// Create the two halves of the kernel around `queue`.
///
/// `tick_hz` is the rate of the board's clock ([`forja_hal_abstraction::clock::Clock::tick_hz`]),
/// `timing` the slowest of the drivers' [`forja_hal_abstraction::stepper::Stepper::timing`]
/// values (the largest pulse width and set-up time). The [`Kernel`] goes to the thread side,
/// the [`StepGenerator`] to the step interrupt; the queue must outlive both.
///
/// ```
/// use forja_hal_abstraction::stepper::StepTiming;
/// use forja_motion::{AxisConfig, Kernel, MachineConfig, StepQueue, split};
///
/// let config = MachineConfig::new([
///     AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 200.0),
///     AxisConfig::linear(b'Y', 80.0, 6000.0, 500.0, 200.0),
/// ]);
/// let mut queue = StepQueue::<2, 256>::new();
/// let (kernel, isr): (Kernel<'_, 2>, _) =
///     split(&mut queue, config, 1_000_000, StepTiming::CONSERVATIVE).unwrap();
/// assert!(isr.is_idle());
/// # let _ = kernel;
/// ```
pub fn split<'q, const N: usize, const B: usize, const Q: usize>(
    queue: &'q mut StepQueue<N, Q>,
    config: MachineConfig<N>,
    tick_hz: u32,
    timing: StepTiming,
) -> Result<(Kernel<'q, N, B, Q>, StepGenerator<'q, N, Q>), ConfigError> {
    config.validate()?;
    config.validate_timing(tick_hz, timing)?;
    let queue: &'q StepQueue<N, Q> = queue;
    let pulse = Duration::from_nanos_ceil(timing.min_pulse_ns, tick_hz)
        .ticks()
        .max(1);
    let dir_setup = Duration::from_nanos_ceil(timing.dir_setup_ns, tick_hz).ticks();
    let isr = StepGenerator::new(
        queue,
        &config,
        Duration::from_ticks(pulse),
        Duration::from_ticks(dir_setup),
    );
    let lead = (u64::from(config.queue_lead_ms) * u64::from(tick_hz) / 1000)
        .clamp(1, u64::from(MAX_DELTA)) as u32;
    let origin = queue.positions();
    let kernel = Kernel {
        interp: Staged::new(Interpreter::new(&config)),
        coords: Coordinates::ZERO,
        coords_changed: 0,
        tick_hz,
        timing,
        tx: Producer::new(queue),
        planner: Planner::new(),
        prep: Prep::new(tick_hz, pulse, dir_setup),
        prep_more: false,
        steps: [0; N],
        origin,
        homed: 0,
        alarm: None,
        halted: false,
        paused: false,
        hold: false,
        stop_requested: false,
        arc: None,
        drill: None,
        homing: None,
        probing: None,
        probe: None,
        flush: None,
        overrides: (100, 100),
        block_rpm: 0,
        stops_seen: queue.stops.load(Ordering::Relaxed),
        quiet_until: None,
        lead_ticks: lead,
        line_tag: 0,
        bounds: axis_bounds(&config),
        config,
    };
    Ok((kernel, isr))
}

impl<'q, const N: usize, const B: usize, const Q: usize> Kernel<'q, N, B, Q> {
    /// The configuration in use.
    pub fn config(&self) -> &MachineConfig<N> {
        &self.config
    }

    /// The planner's settings now (what `M503` reports): the configuration's per-axis limits
    /// and junction deviation, the limits along the path, and the feed and flow overrides of
    /// the lines executed so far.
    pub fn planner_settings(&self) -> PlannerSettings<N> {
        let axes = &self.config.axes;
        let flow = self.interp.live().flow_percent();
        PlannerSettings {
            letters: core::array::from_fn(|i| axes[i].letter),
            steps_per_mm: core::array::from_fn(|i| axes[i].steps_per_mm),
            max_accel_mm_s2: core::array::from_fn(|i| axes[i].accel_mm_s2),
            max_rate_mm_s: core::array::from_fn(|i| axes[i].max_rate_mm_s()),
            path: self.planner.limits(),
            junction_deviation_mm: self.config.junction_deviation_mm,
            feed_percent: self.interp.live().feed_percent(),
            flow_percent: core::array::from_fn(|i| {
                (axes[i].kind == AxisKind::Extruder).then_some(flow[i])
            }),
        }
    }

    /// The clock rate given at construction.
    pub fn tick_hz(&self) -> u32 {
        self.tick_hz
    }

    /// The machine's state.
    pub fn state(&self) -> MachineState {
        if let Some(a) = self.alarm {
            return MachineState::Alarm(a);
        }
        if self.halted {
            return MachineState::Halted;
        }
        if self.homing.is_some() {
            return MachineState::Homing;
        }
        if self.hold {
            return MachineState::Hold {
                stopped: self.at_rest(),
            };
        }
        if self.paused {
            return MachineState::Paused;
        }
        if self.is_idle() {
            MachineState::Idle
        } else {
            MachineState::Running
        }
    }

    /// The largest distance, in ticks, of a prepared step's tick from its exact time on the
    /// planned profile since the start (steps moved later by a direction change or by their
    /// axis's last pulse not counted). Measured in debug builds only, for the property tests.
    #[doc(hidden)]
    #[cfg(debug_assertions)]
    pub fn worst_step_error_ticks(&self) -> f64 {
        self.prep.worst_error_ticks()
    }

    /// Whether every queued move has finished and the steppers are at rest. A feed hold with
    /// motion behind it is not idle: that motion runs on [`Kernel::resume`].
    pub fn is_idle(&self) -> bool {
        !self.moving_planned()
            && self.arc.is_none()
            && self.drill.is_none()
            && self.flush.is_none()
            && self.tx.len() == 0
            && self.isr_idle()
    }

    fn moving_planned(&self) -> bool {
        !self.planner.is_empty() || self.prep.is_busy()
    }

    /// Whether the steppers are at rest with nothing queued for the interrupt: idle, or a feed
    /// hold that has come to rest on the path.
    fn at_rest(&self) -> bool {
        let prepared_rest = self.prep.is_held() || !self.moving_planned();
        prepared_rest && self.flush.is_none() && self.tx.len() == 0 && self.isr_idle()
    }

    fn isr_idle(&self) -> bool {
        let q = self.tx.shared();
        q.starts.load(Ordering::Relaxed) == q.idles.load(Ordering::Acquire)
    }

    /// Axes homed since power-on or the last alarm (bit `i` = axis `i`).
    pub fn homed_axes(&self) -> u8 {
        self.homed
    }

    /// The machine position in steps, as the step interrupt has counted it.
    pub fn machine_steps(&self) -> [i32; N] {
        let isr = self.tx.shared().positions();
        core::array::from_fn(|i| isr[i].wrapping_sub(self.origin[i]))
    }

    /// Positions for a report.
    pub fn position(&self) -> PositionReport<N> {
        let m = self.machine_steps();
        let w = self
            .interp
            .live()
            .work_position(self.config.axis_index(b'Z'));
        PositionReport {
            letters: core::array::from_fn(|i| self.config.axes[i].letter),
            work_mm: core::array::from_fn(|i| w[i] as f64 / NM_PER_MM),
            machine_mm: core::array::from_fn(|i| {
                f64::from(m[i]) / f64::from(self.config.axes[i].steps_per_mm)
            }),
        }
    }

    /// The source line of the motion being prepared (the tag set by [`Kernel::set_line_tag`]
    /// when its line was executed).
    pub fn current_line(&self) -> u32 {
        self.prep.line()
    }

    /// Tag the blocks of the following lines with `tag` (a program line), for progress reports.
    pub fn set_line_tag(&mut self, tag: u32) {
        self.line_tag = tag;
    }

    /// A copy of the interpreter's state (for dry runs).
    pub(crate) fn interpreter(&self) -> Interpreter<N> {
        *self.interp.live()
    }

    /// Where the last queued move ends, in machine nanometres per axis.
    pub fn commanded_position_nm(&self) -> [Nm; N] {
        self.interp.live().pos
    }

    /// Take the power-on modal state (mm, absolute, no offsets) where the last queued move
    /// ends: the state a resumed job's return moves are made in (see [`crate::Replay`]).
    pub fn reset_modal_state(&mut self) {
        self.interp
            .live_mut()
            .reset_modal(&self.config, &self.coords);
    }

    /// Take a program's modal state ([`crate::Replay`]) to go on with it, the last queued move
    /// ending at `at` (machine nm): the program's own position there, but for the extruders,
    /// which are not moved back and keep their place (their work position is rebased, as `G92`
    /// does).
    pub fn take_modal_state(&mut self, replay: &crate::Replay<N>, at: [Nm; N]) {
        let mut state = replay.interp;
        for (i, a) in self.config.axes.iter().enumerate() {
            if a.kind == AxisKind::Extruder {
                state.rebase_axis(i, at[i]);
            }
        }
        state.pos = at;
        *self.interp.live_mut() = state;
    }

    /// Where the last queued move ends, in machine steps.
    pub(crate) fn commanded_steps(&self) -> [i32; N] {
        self.steps
    }

    /// Whether a motion line would be taken now (the planner has room and nothing is pending).
    /// A controller checks this before parsing the next line, instead of offering lines that
    /// come back `Busy`; lines that wait for the machine at rest may still answer `Busy`.
    pub fn can_accept(&self) -> bool {
        !self.planner.is_full()
            && self.arc.is_none()
            && self.drill.is_none()
            && self.homing.is_none()
            && self.probing.is_none()
            && self.flush.is_none()
            && !self.paused
            && !self.stop_requested
    }

    /// Blocks waiting in the planner.
    pub fn planned_blocks(&self) -> usize {
        self.planner.len()
    }

    /// Execute one parsed G-code line. See [`Reply`] for what to do with the answer.
    ///
    /// Context: thread. A refused line (`Err`) changes nothing.
    pub fn execute<'l>(&mut self, line: &Line<'l>) -> Result<Reply<'l, N>, CommandError> {
        if line.is_empty() {
            return Ok(Reply::Ok);
        }
        if let Some((first, then)) = split_spindle_and_motion(line) {
            return self.execute_in_order(first, &then);
        }
        // The action is read where `interpret` left it: moved out, it would be copied whole.
        match self
            .interp
            .stage()
            .interpret(line, &self.config, &self.coords)
        {
            Ok(ref action) => self.act(action),
            Err(e) => Err(e),
        }
    }

    /// A line with both a spindle or coolant command and motion (`G0 X0 Y0 S16000 M3`, as CAM
    /// posts write them): the command first, at rest after the motion before it, then the
    /// motion (RS274's order of execution). Both are checked before either acts: a refused
    /// line changes nothing.
    fn execute_in_order<'l>(
        &mut self,
        first: Line<'l>,
        then: &Line<'l>,
    ) -> Result<Reply<'l, N>, CommandError> {
        let command = self
            .interp
            .stage()
            .interpret(&first, &self.config, &self.coords)?;
        let mut after = *self.interp.staged();
        let motion = after.interpret(then, &self.config, &self.coords)?;
        let Action::Effect(effect) = command else {
            return Err(CommandError::ModalConflict);
        };
        // The rest of the line is its motion: nothing that acts on its own.
        let moves = matches!(
            motion,
            Action::None
                | Action::Dwell { .. }
                | Action::Move { .. }
                | Action::Arc { .. }
                | Action::Drill { .. }
                | Action::Via { .. }
                | Action::Probe { .. }
        );
        if !moves {
            return Err(CommandError::ModalConflict);
        }
        self.check_travel(&motion)?;
        match self.act(&Action::Effect(effect))? {
            Reply::Effect(e) => {
                // At rest: the motion is taken (checked above, the planner empty).
                self.interp.stage_as(&after);
                let _ = self.act(&motion)?;
                Ok(Reply::Effect(e))
            }
            other => Ok(other),
        }
    }

    /// Refuse an `action` that moves where the machine may not go (or probes without a probe),
    /// before anything acts: [`Kernel::act`]'s checks of the place.
    fn check_travel(&self, action: &Action<'_, N>) -> Result<(), CommandError> {
        match *action {
            Action::Probe { .. } if self.config.probe_switch.is_none() => {
                Err(CommandError::NoProbe)
            }
            Action::Move { target, .. } | Action::Probe { target, .. } => {
                self.check_move(&target, &target)
            }
            Action::Arc { cutter, .. } => {
                let (lo, hi) = cutter.bounds();
                self.check_move(&lo, &hi)
            }
            Action::Drill { cycle, .. } => {
                let (lo, hi) = cycle.bounds();
                self.check_move(&lo, &hi)
            }
            Action::Via { via, target } => {
                self.check_move(&via, &via)?;
                self.check_move(&target, &target)
            }
            _ => Ok(()),
        }
    }

    /// A rapid move to `target` (machine nm), as a `G0` naming every axis would be taken:
    /// refused, `Busy` or queued by the same rules. For a resumed job's return to its line.
    pub fn rapid_to(&mut self, target: [Nm; N]) -> Result<Reply<'static, N>, CommandError> {
        self.interp.stage().pos = target;
        let action = Action::Move {
            target,
            feed_mm_min: None,
            ramp: false,
        };
        self.act(&action)
    }

    /// Carry out `action`, interpreted from a line into the staged interpreter state
    /// ([`Staged::stage`]), which is committed when the action is taken. A refused action
    /// changes nothing.
    fn act<'l>(&mut self, action: &Action<'l, N>) -> Result<Reply<'l, N>, CommandError> {
        // Always accepted: emergency stop, reports and immediate effects.
        match *action {
            Action::Stop(StopKind::Emergency) => {
                self.interp.commit();
                self.emergency_stop();
                return Ok(Reply::Effect(Effect::Stopped(StopKind::Emergency)));
            }
            Action::Report => {
                self.interp.commit();
                return Ok(Reply::Position(self.position()));
            }
            Action::Effect(e) if e.sync() == crate::Sync::Now => {
                self.interp.commit();
                return Ok(Reply::Effect(e));
            }
            _ => {}
        }
        if let Some(a) = self.alarm
            && (!matches!(action, Action::Home { .. }) || a == Alarm::EmergencyStop)
        {
            return Err(CommandError::Locked);
        }
        if self.halted {
            return Err(CommandError::Halted);
        }
        // Lines after a stop wait for it to complete (it drops only what came before it).
        if self.arc.is_some()
            || self.drill.is_some()
            || self.homing.is_some()
            || self.probing.is_some()
            || self.flush.is_some()
            || self.paused
            || self.stop_requested
        {
            self.drain_arc();
            return Ok(Reply::Busy);
        }
        self.check_travel(action)?;
        let idle = self.is_idle();
        self.block_rpm = self.interp.staged().spindle_rpm();
        // What the action answers besides `ok`: an effect for the caller to carry out. Only that is
        // kept until the state is committed (a whole reply would be copied on the way out).
        let effect = match *action {
            Action::None => None,
            Action::SetCoordinates { slot, values } => {
                self.coords.set(slot, values);
                self.coords_changed |= 1 << slot.index();
                None
            }
            Action::Move {
                target,
                feed_mm_min,
                ramp,
            } => {
                if self.planner.is_full() {
                    return Ok(Reply::Busy);
                }
                self.queue_move(
                    &target,
                    feed_mm_min,
                    self.interp.staged().feed_scale(),
                    ramp,
                    0,
                    self.interp.staged().exact_stop,
                );
                // The most common line, answered here: the answer below moves the optional
                // effect into the reply whatever it holds (a copy of 21 bytes, byte by byte).
                self.interp.commit();
                return Ok(Reply::Ok);
            }
            Action::Arc {
                cutter,
                feed_mm_min,
                ramp,
            } => {
                self.quiet_until = None;
                self.arc = Some(PendingArc {
                    cutter,
                    feed_mm_min,
                    feed_scale: self.interp.staged().feed_scale(),
                    ramp,
                    exact_stop: self.interp.staged().exact_stop,
                });
                self.drain_arc();
                None
            }
            Action::Drill { cycle, feed_mm_min } => {
                self.quiet_until = None;
                self.drill = Some(PendingDrill {
                    cycle,
                    feed_mm_min,
                    feed_scale: self.interp.staged().feed_scale(),
                });
                self.drain_arc();
                None
            }
            Action::Dwell { ms } => {
                if self.planner.is_full() {
                    return Ok(Reply::Busy);
                }
                let _ = self.planner.push_dwell(ms, self.line_tag);
                None
            }
            Action::Home { mask } => {
                if !idle {
                    return Ok(Reply::Busy);
                }
                self.start_homing(mask);
                None
            }
            Action::SetStepsPerMm(values) => {
                if !idle {
                    return Ok(Reply::Busy);
                }
                self.set_steps_per_mm(&values)?;
                None
            }
            Action::SetLimits(change) => {
                self.set_limits(&change)?;
                None
            }
            Action::Effect(e) => {
                if !idle {
                    return Ok(Reply::Busy);
                }
                if let Effect::Motors {
                    enabled: false,
                    axes,
                } = e
                {
                    self.homed &= !axes;
                }
                Some(e)
            }
            Action::Stop(kind) => {
                if !idle {
                    return Ok(Reply::Busy);
                }
                self.halted = true;
                Some(Effect::Stopped(kind))
            }
            Action::Pause => {
                if !idle {
                    return Ok(Reply::Busy);
                }
                self.paused = true;
                Some(Effect::Paused)
            }
            Action::ToolChange(tool) => {
                if !idle {
                    return Ok(Reply::Busy);
                }
                self.paused = true;
                Some(Effect::ToolChange(tool))
            }
            Action::Probe {
                target,
                feed_mm_min,
                away,
                must_trip,
            } => {
                if !idle {
                    return Ok(Reply::Busy);
                }
                self.start_probe(&target, feed_mm_min, away, must_trip);
                None
            }
            Action::Via { via, target } => {
                if B.saturating_sub(self.planner.len()) < 2 {
                    return Ok(Reply::Busy);
                }
                self.queue_move(
                    &via,
                    None,
                    self.interp.staged().feed_scale(),
                    false,
                    0,
                    false,
                );
                self.queue_move(
                    &target,
                    None,
                    self.interp.staged().feed_scale(),
                    false,
                    0,
                    false,
                );
                None
            }
            // Taken before these checks (see the top); answered the same way here.
            Action::Report => {
                self.interp.commit();
                return Ok(Reply::Position(self.position()));
            }
        };
        // Keep the modal state the line set (a move's target is its new position).
        self.interp.commit();
        Ok(effect.map_or(Reply::Ok, Reply::Effect))
    }

    /// Jog (frame message 01): move axis `letter` by `count` steps of `step_mm` (rounded to the
    /// nanometre, as every position), relative, at the jog feed rate. Soft limits apply as to
    /// any move.
    pub fn jog(
        &mut self,
        letter: u8,
        step_mm: Decimal,
        count: i32,
    ) -> Result<Reply<'static, N>, CommandError> {
        let axis = self
            .config
            .axis_index(letter)
            .ok_or(CommandError::UnknownAxis { letter })?;
        if self.alarm.is_some() {
            return Err(CommandError::Locked);
        }
        if self.halted {
            return Err(CommandError::Halted);
        }
        // A jog during a feed hold would wait for the resume behind the held motion: refused.
        if self.homing.is_some() || self.arc.is_some() || self.flush.is_some() || self.hold {
            return Err(CommandError::NotIdle);
        }
        // The step to the nanometre, as every position, then `count` of them.
        let nm = to_nm(step_mm, false, b'S')?
            .checked_mul(i64::from(count))
            .ok_or(CommandError::BadValue { letter: b'S' })?;
        let mut target = self.interp.live().pos;
        target[axis] = target[axis].saturating_add(nm);
        self.check_move(&target, &target)?;
        if self.planner.is_full() {
            return Ok(Reply::Busy);
        }
        let feed = self.config.jog_feed_mm_min;
        self.queue_move(&target, Some(feed), 1.0, false, 0, false);
        self.interp.live_mut().pos = target;
        Ok(Reply::Ok)
    }

    /// Home the axes in `mask` (frame message 02 `Zero`/`ZeroX`…, or `G28`): seek the switch,
    /// back off, approach slowly, pull off, set the position. Needs the machine at rest.
    /// Clears an alarm (other than an emergency stop).
    pub fn home(&mut self, mask: u8) -> Result<(), CommandError> {
        if self.alarm == Some(Alarm::EmergencyStop) {
            return Err(CommandError::Locked);
        }
        if self.halted {
            return Err(CommandError::Halted);
        }
        for (i, a) in self.config.axes.iter().enumerate() {
            if mask & (1 << i) != 0 && a.homing.is_none() {
                return Err(CommandError::BadValue { letter: a.letter });
            }
        }
        if !self.is_idle() || self.homing.is_some() {
            return Err(CommandError::NotIdle);
        }
        self.start_homing(mask);
        Ok(())
    }

    /// Jog with one G-code line (grbl's `$J=`): a `G0`/`G1`-like move whose `G90`/`G91` and
    /// `G20`/`G21` hold for this move only; the modal state is the one before it, the position
    /// the jog's target. Soft limits apply as to any move.
    pub fn jog_line<'l>(&mut self, line: &Line<'l>) -> Result<Reply<'l, N>, CommandError> {
        let before = *self.interp.live();
        let reply = self.execute(line)?;
        let target = self.interp.live().pos;
        *self.interp.live_mut() = before;
        self.interp.live_mut().pos = target;
        Ok(reply)
    }

    /// The work coordinate systems and stored positions.
    pub fn coordinates(&self) -> &Coordinates<N> {
        &self.coords
    }

    /// Take `coords` (the stored table, at start-up): the active system's origin follows.
    pub fn set_coordinates(&mut self, coords: Coordinates<N>) {
        self.coords = coords;
        self.interp.live_mut().use_coordinates(&coords);
    }

    /// The slots of the table that lines changed since the last call (bit
    /// [`Slot::index`](crate::coords::Slot::index)),
    /// for the application to store; cleared.
    pub fn take_changed_coordinates(&mut self) -> u16 {
        core::mem::take(&mut self.coords_changed)
    }

    /// The modal state of the interpreter (grbl's `$G`).
    pub fn modal_report(&self) -> ModalReport<N> {
        self.interp.live().modal()
    }

    /// The realtime feed and rapid overrides (grbl's `0x90`–`0x98`), percent.
    pub fn realtime_overrides(&self) -> (u16, u16) {
        self.overrides
    }

    /// Set the realtime overrides, percent: `feed` scales every feed move and `rapid` every
    /// rapid, those queued and the one under way included, at once (grbl's overrides; homing
    /// and probing are not scaled). Back to 100 % at [`Kernel::reset`].
    pub fn set_realtime_overrides(&mut self, feed: u16, rapid: u16) {
        self.overrides = (feed, rapid);
        let tail = self
            .planner
            .set_overrides(f32::from(feed) / 100.0, f32::from(rapid) / 100.0);
        if let Some(nominal_sqr) = tail {
            self.prep.set_nominal(nominal_sqr);
        }
    }

    /// The motion now, as prepared (`queue_lead_ms` ahead of the steps): grbl's realtime feed
    /// rate (`FS:`), and what a laser's power follows.
    pub fn motion_now(&self) -> MotionNow {
        match self.prep.motion() {
            Some((v, fraction, rapid, spindle_rpm)) if !self.at_rest() => MotionNow {
                speed_mm_min: (v * 60.0) as f32,
                fraction: fraction as f32,
                rapid,
                spindle_rpm,
            },
            _ => MotionNow {
                speed_mm_min: 0.0,
                fraction: 0.0,
                rapid: false,
                spindle_rpm: self.interp.live().spindle_rpm(),
            },
        }
    }

    /// The speed along the path now, mm/min (0 at rest): grbl's realtime feed rate (`FS:`).
    pub fn speed_mm_min(&self) -> f32 {
        self.motion_now().speed_mm_min
    }

    /// The feed-rate override, percent (`M220`).
    pub fn feed_override_percent(&self) -> u16 {
        self.interp.live().feed_percent()
    }

    /// After a [`Kernel::reset`] that cut the motion: lock the machine in
    /// [`Alarm::ResetDuringMotion`] (grbl's `ALARM:3`) until [`Kernel::unlock`] or a homing.
    pub fn lock_after_reset(&mut self) {
        self.alarm = Some(Alarm::ResetDuringMotion);
    }

    /// Take grbl's meanings where the dialects differ (`G28`/`G30` to the stored positions,
    /// `G4 P` in seconds, `M0` paused until cycle start), or RepRap's (a link in the grbl
    /// dialect, or one that left it).
    pub fn set_grbl_dialect(&mut self, grbl: bool) {
        self.interp.live_mut().grbl = grbl;
    }

    /// Leave an alarm without homing (grbl's `$X`), the position kept as the steps counted it.
    /// An emergency stop is left only by [`Kernel::reset`].
    pub fn unlock(&mut self) {
        if self.alarm != Some(Alarm::EmergencyStop) {
            self.alarm = None;
        }
    }

    /// Feed hold: decelerate to rest on the planned path, keeping every step. Lines can still be
    /// queued; nothing moves until [`Kernel::resume`].
    pub fn hold(&mut self) {
        if self.homing.is_none() {
            self.hold = true;
            self.prep.set_hold(true);
        }
    }

    /// End a feed hold or an `M226` pause.
    pub fn resume(&mut self) {
        self.paused = false;
        if self.hold && !self.stop_requested {
            self.hold = false;
            self.prep.set_hold(false);
        }
    }

    /// Stop motion and drop everything queued, keeping the position: a feed hold, then the
    /// planner, the block in preparation and the step queue are flushed once at rest. The
    /// commanded position becomes where the steppers stopped; a later [`Kernel::resume`]
    /// revives nothing. During a hold already at rest this happens at once.
    pub fn stop(&mut self) {
        self.arc = None;
        self.drill = None;
        self.paused = false;
        if self.homing.is_some() {
            // Homing moves are slow: cut them at once.
            self.abort(true, false);
            return;
        }
        if self.at_rest() {
            self.abort(false, false);
            return;
        }
        self.hold = true;
        self.prep.set_hold(true);
        self.stop_requested = true;
        self.quiet_until = None;
    }

    /// `M112`: cut motion at once and lock the machine until a reset.
    pub fn emergency_stop(&mut self) {
        self.abort(true, false);
        self.alarm = Some(Alarm::EmergencyStop);
    }

    /// Soft reset: stop at once, clear alarms and `M0`, modal state back to defaults
    /// (position kept, `G92` offsets cleared). When motion was cut, the axes lose their homed
    /// state (steps may have been lost).
    pub fn reset(&mut self) {
        // A hold at rest lost no step: the homed axes stay homed.
        let moving = !self.at_rest();
        self.abort(moving, false);
        self.alarm = None;
        self.halted = false;
        self.paused = false;
        self.interp
            .live_mut()
            .reset_modal(&self.config, &self.coords);
        self.set_realtime_overrides(100, 100);
    }

    /// Stop the interrupt side at once and drop everything; `lose_homing` forgets the homed axes.
    fn abort(&mut self, lose_homing: bool, force_flush: bool) {
        self.arc = None;
        self.drill = None;
        self.homing = None;
        self.probing = None;
        self.tx.shared().probe.store(PROBE_OFF, Ordering::Relaxed);
        self.hold = false;
        self.stop_requested = false;
        self.prep.set_hold(false);
        self.planner.clear();
        let idle = !force_flush && self.tx.len() == 0 && self.isr_idle() && self.flush.is_none();
        self.prep
            .reset(self.tx.shared().consumed_ticks.load(Ordering::Relaxed));
        if lose_homing {
            self.homed = 0;
        }
        if idle {
            self.tx.shared().homing_mask.store(0, Ordering::Relaxed);
            self.resync();
        } else {
            self.request_flush();
        }
    }

    fn request_flush(&mut self) {
        let q = self.tx.shared();
        let req = q.flush_req.load(Ordering::Relaxed).wrapping_add(1);
        q.homing_mask.store(0, Ordering::Relaxed);
        q.flush_req.store(req, Ordering::Release);
        self.flush = Some(req);
        self.quiet_until = None;
    }

    /// Change steps per unit (`M92`), keeping the machine where it is.
    fn set_steps_per_mm(&mut self, values: &[Option<f32>; N]) -> Result<(), CommandError> {
        let mut c = self.config;
        for (a, v) in c.axes.iter_mut().zip(values.iter()) {
            if let Some(v) = v {
                a.steps_per_mm = *v;
            }
        }
        c.validate()
            .map_err(|_| CommandError::BadValue { letter: b'M' })?;
        self.bounds = axis_bounds(&c);
        self.config = c;
        self.rescale_steps();
        Ok(())
    }

    /// After a change of steps per unit, while idle: Marlin's rule, the machine stays at the
    /// same millimetres, which are now other step counts (the motors do not move). Idle, so the
    /// interrupt's count is the planner's.
    fn rescale_steps(&mut self) {
        let isr = self.tx.shared().positions();
        for (i, a) in self.config.axes.iter().enumerate() {
            let steps = nm_to_steps(self.interp.live().pos[i], a.steps_per_mm);
            self.origin[i] = isr[i].wrapping_sub(steps);
            self.steps[i] = steps;
        }
    }

    /// Take a whole set of planner settings at once: the steps per unit, maximum accelerations
    /// and rates and the junction deviation of `machine` (its other fields are not read), and
    /// the path limits `path`. What a controller's `M501` (the stored settings) and `M502`
    /// (the defaults) do, and a board's start with stored path limits. Steps per unit change
    /// by `M92`'s rule (the machine keeps its millimetres); a rate below an axis's homing
    /// speeds lowers them, as `M203` does.
    ///
    /// Returns [`Reply::Busy`] until the machine is idle (nothing changes meanwhile), like
    /// `M92`. Errors: the configuration it makes is not valid, or cannot be stepped
    /// ([`MachineConfig::validate_timing`]), or a path limit is not a finite positive number
    /// (a slowest feed not negative): [`CommandError::BadValue`] naming the axis or `M`;
    /// nothing changes.
    pub fn set_planner_settings(
        &mut self,
        machine: &MachineConfig<N>,
        path: PathLimits,
    ) -> Result<Reply<'static, N>, CommandError> {
        if !self.is_idle() || self.homing.is_some() {
            return Ok(Reply::Busy);
        }
        let mut c = self.config;
        let change = [
            LimitChange::AxisAccel(core::array::from_fn(|i| Some(machine.axes[i].accel_mm_s2))),
            LimitChange::AxisRate(core::array::from_fn(|i| {
                Some(machine.axes[i].max_rate_mm_min)
            })),
        ];
        let mut limits = path;
        for ch in &change {
            ch.apply(&mut c, &mut limits);
        }
        for (a, from) in c.axes.iter_mut().zip(&machine.axes) {
            a.steps_per_mm = from.steps_per_mm;
        }
        c.junction_deviation_mm = machine.junction_deviation_mm;
        let accel_ok = |v: Option<f32>| v.is_none_or(|v| v.is_finite() && v > 0.0);
        let feed_ok = |v: f32| v.is_finite() && v >= 0.0;
        if !(accel_ok(path.print_accel_mm_s2)
            && accel_ok(path.retract_accel_mm_s2)
            && accel_ok(path.travel_accel_mm_s2)
            && feed_ok(path.min_extruding_feed_mm_s)
            && feed_ok(path.min_travel_feed_mm_s))
        {
            return Err(CommandError::BadValue { letter: b'M' });
        }
        c.validate()
            .and_then(|()| c.validate_timing(self.tick_hz, self.timing))
            .map_err(|e| refusal(&c, e))?;
        self.bounds = axis_bounds(&c);
        self.config = c;
        self.planner.set_limits(path);
        self.rescale_steps();
        Ok(Reply::Ok)
    }

    /// Change the planner's limits (`M201`, `M203`, `M204`, `M205`) for the moves planned from
    /// now on. The blocks already planned keep the limits they were planned with, as in Marlin,
    /// so the line needs no wait for the motion before it.
    ///
    /// The configuration must stay valid: an `M203` rate the drivers or the clock cannot step
    /// ([`MachineConfig::validate_timing`]) is refused, naming the axis. An `M203` rate below an
    /// axis's homing speeds lowers them to it (Marlin's planner caps homing moves the same way).
    fn set_limits(&mut self, change: &LimitChange<N>) -> Result<(), CommandError> {
        let mut c = self.config;
        let mut limits = self.planner.limits();
        change.apply(&mut c, &mut limits);
        c.validate()
            .and_then(|()| c.validate_timing(self.tick_hz, self.timing))
            .map_err(|e| refusal(&c, e))?;
        self.config = c;
        self.planner.set_limits(limits);
        Ok(())
    }

    /// Machine nm limits of axis `i`.
    fn travel_nm(&self, i: usize) -> (Nm, Nm) {
        let b = &self.bounds[i];
        (b.min, b.max)
    }

    /// Refuse a move from the commanded position over `lo..=hi` (machine nm) that leaves the
    /// travel of a homed axis ([`CommandError::SoftLimit`]) or that no machine can make
    /// ([`CommandError::OutOfReach`], see [`Kernel::check_reach`]), in that order.
    fn check_move(&self, lo: &[Nm; N], hi: &[Nm; N]) -> Result<(), CommandError> {
        self.check_soft_limits(lo, hi)?;
        self.check_reach(lo, hi)
    }

    fn check_soft_limits(&self, lo: &[Nm; N], hi: &[Nm; N]) -> Result<(), CommandError> {
        for i in 0..N {
            let checked = match self.config.soft_limits {
                SoftLimits::Off => false,
                SoftLimits::WhenHomed => self.homed & (1 << i) != 0,
                SoftLimits::Always => true,
            };
            let (min, max) = self.travel_nm(i);
            if checked && (lo[i] < min || hi[i] > max) {
                return Err(CommandError::SoftLimit { axis: i as u8 });
            }
        }
        Ok(())
    }

    /// Refuse a move from the commanded position over `lo..=hi` (machine nm) that cannot be
    /// right whether homed or not: longer on an axis than that axis's whole travel, or ending
    /// beyond what is counted in `i32` steps and reported ([`MAX_POSITION_MM`]).
    fn check_reach(&self, lo: &[Nm; N], hi: &[Nm; N]) -> Result<(), CommandError> {
        let from = &self.interp.live().pos;
        for (i, b) in self.bounds.iter().enumerate() {
            let low = lo[i].min(from[i]);
            let high = hi[i].max(from[i]);
            let longer_than_travel = high.saturating_sub(low) > b.max.saturating_sub(b.min);
            if longer_than_travel || low < -b.reach || high > b.reach {
                return Err(CommandError::OutOfReach { axis: i as u8 });
            }
        }
        Ok(())
    }

    /// Plan a move to `target` (machine nm). The planner must have room.
    fn queue_move(
        &mut self,
        target: &[Nm; N],
        feed_mm_min: Option<f32>,
        feed_scale: f32,
        ramp: bool,
        homing_mask: u8,
        exact_stop: bool,
    ) {
        let mut req = MoveRequest::to_target(
            target,
            &mut self.steps,
            &self.config,
            feed_mm_min,
            ramp,
            self.line_tag,
            homing_mask,
        );
        req.feed_scale = feed_scale;
        req.exact_stop = exact_stop;
        // Homing and probing run at their own feeds whatever the overrides.
        req.fixed = homing_mask != 0 || self.homing.is_some() || self.probing.is_some();
        req.spindle_rpm = self.block_rpm;
        let _ = self.planner.push_move(&req, &self.config);
    }

    /// Plan the chords of the pending arc, or the moves of the pending drilling cycle, while the
    /// planner has room.
    fn drain_arc(&mut self) {
        while let Some(mut d) = self.drill {
            if self.planner.is_full() {
                return;
            }
            match d.cycle.peek() {
                Some(DrillStep::Rapid(p)) => {
                    self.queue_move(&p, None, d.feed_scale, false, 0, false)
                }
                Some(DrillStep::Feed(p)) => {
                    self.queue_move(&p, Some(d.feed_mm_min), d.feed_scale, false, 0, false);
                }
                Some(DrillStep::Dwell(ms)) => {
                    let _ = self.planner.push_dwell(ms, self.line_tag);
                }
                None => {
                    self.drill = None;
                    continue;
                }
            }
            d.cycle.advance();
            self.drill = Some(d);
        }
        while let Some(mut p) = self.arc {
            if self.planner.is_full() {
                return;
            }
            match p.cutter.peek() {
                Some(point) => {
                    let ramp = p.ramp && p.cutter.is_first();
                    let exact = p.exact_stop && p.cutter.is_first();
                    self.queue_move(&point, Some(p.feed_mm_min), p.feed_scale, ramp, 0, exact);
                    p.cutter.advance();
                    self.arc = Some(p);
                }
                None => self.arc = None,
            }
        }
    }

    /// Where the steppers are becomes the commanded position.
    fn resync(&mut self) {
        let m = self.machine_steps();
        let mut pos = self.interp.live().pos;
        for (i, a) in self.config.axes.iter().enumerate() {
            self.steps[i] = m[i];
            pos[i] = steps_to_nm(m[i], a.steps_per_mm);
        }
        self.interp.live_mut().set_machine_position(pos);
    }

    /// Run the thread side: take the interrupt's news, advance homing, plan arc chords, and
    /// prepare steps. Returns the instant to arm the step alarm at when the step interrupt is
    /// idle and has work (the board arms it; an instant already past fires at once), `None`
    /// otherwise.
    ///
    /// Context: thread. Call it again within [`Kernel::poll_within_ms`] while the machine
    /// moves, after each [`Kernel::execute`] that was taken, and again at once while
    /// [`Kernel::needs_poll`] says so. Its cost is bounded: one call prepares at most a few
    /// dozen step events (under 20,000 instructions on a Cortex-M4, `docs/performance.md`),
    /// and a motion starts once its lead is prepared.
    pub fn poll(&mut self, now: Instant) -> Option<Instant> {
        // A quiet poll follows one that found nothing to do, which left `prep_more` false.
        if self.is_quiet(now) {
            return None;
        }
        if self.has_nothing_to_do(now) {
            self.prep_more = false;
            return None;
        }
        self.quiet_until = None;
        self.poll_fully(now)
    }

    /// Whether this poll comes before the instant the last one found it would have nothing to
    /// do until, with no stop of the interrupt since. Nothing has given the thread side work
    /// meanwhile (that clears the instant), and the queue runs down by no more than the time
    /// that passes, so the answer still holds: most polls while the machine moves read a clock
    /// and a counter, not the whole state.
    #[inline(always)]
    fn is_quiet(&mut self, now: Instant) -> bool {
        let Some(until) = self.quiet_until else {
            return false;
        };
        // Before `until`, and by no more than the lead: an instant left from long ago (the
        // clock wraps) is not taken for one to come.
        let left = until.ticks().wrapping_sub(now.ticks());
        if left == 0 || left > self.lead_ticks || self.interrupt_stopped() {
            return false;
        }
        debug_assert!(
            !self.has_thread_side_work() && !self.prep_more,
            "work left behind a quiet poll"
        );
        // What the queue holds at the least: it holds half the lead at `until`.
        self.prep.note_queued(left + self.lead_ticks / 2);
        true
    }

    /// Whether the interrupt has stopped motion on its own since the thread side last saw it
    /// (`Kernel::poll_fully` reports it).
    #[inline(always)]
    fn interrupt_stopped(&self) -> bool {
        self.tx.shared().stops.load(Ordering::Acquire) != self.stops_seen
    }

    /// Whether a cycle (homing, probing, an arc or drilling cycle being cut), a flush or a stop
    /// waits on the thread side.
    #[inline(always)]
    fn has_thread_side_work(&self) -> bool {
        self.flush.is_some()
            || self.homing.is_some()
            || self.probing.is_some()
            || self.arc.is_some()
            || self.drill.is_some()
            || self.stop_requested
    }

    /// Whether this poll has nothing to do: the interrupt runs with no stop to report, no
    /// cycle, flush or stop waits on the thread side, and the step queue holds enough motion
    /// (most polls while the machine moves). The checks come ahead of the full call, whose
    /// set-up alone would cost more than they do; the full call would find the same and
    /// return `None`, the interrupt being under way. When the queue holds enough, the polls
    /// until it may not are quiet ([`Kernel::is_quiet`]).
    #[inline(always)]
    fn has_nothing_to_do(&mut self, now: Instant) -> bool {
        if self.interrupt_stopped() || self.has_thread_side_work() || self.isr_idle() {
            return false;
        }
        let ahead = self.prep.ahead_of(&self.tx, now, true);
        if !self.prep.holds_enough(ahead, self.lead_ticks, true) {
            return false;
        }
        let margin = ahead
            .saturating_sub(self.lead_ticks / 2)
            .min(self.lead_ticks);
        self.quiet_until = Some(now.wrapping_add(Duration::from_ticks(margin)));
        true
    }

    /// [`Kernel::poll`] when there may be something to do.
    #[inline(never)]
    fn poll_fully(&mut self, now: Instant) -> Option<Instant> {
        // Only a preparation this call stops short asks for another at once: a call that
        // returns before preparing (a flush under way) leaves the interrupt to run first.
        self.prep_more = false;
        let q = self.tx.shared();
        let stops = q.stops.load(Ordering::Acquire);
        if stops != self.stops_seen {
            self.stops_seen = stops;
            self.on_interrupt_stop(q.stop_cause());
        }
        if let Some(req) = self.flush {
            if q.flush_done.load(Ordering::Acquire) != req {
                return self.start_interrupt(now, true);
            }
            self.flush = None;
            self.prep.reset(q.consumed_ticks.load(Ordering::Relaxed));
            self.resync();
        }
        if self.homing.is_some() {
            self.homing_step();
        }
        if self.probing.is_some() {
            self.probe_step();
        }
        // Tested here: the call alone would cost every poll more than the test.
        if self.arc.is_some() || self.drill.is_some() {
            self.drain_arc();
        }
        if self.stop_requested && self.at_rest() {
            self.stop_requested = false;
            self.abort(false, false);
            return self.start_interrupt(now, true);
        }
        let running = !self.isr_idle();
        let fill = self.prep.fill(
            &mut self.planner,
            &mut self.tx,
            self.lead_ticks,
            now,
            running,
        );
        self.prep_more = fill == Fill::More;
        if self.prep_more && !running {
            // The motion starts with its lead prepared, a few calls from now.
            return None;
        }
        self.start_interrupt(now, false)
    }

    /// The longest the thread side may wait before the next [`Kernel::poll`] while the
    /// machine moves, ms: half of the motion the step queue held after the last one, and at
    /// most half of `queue_lead_ms` (the queue fills up before the lead when the steps are
    /// fast, so that the motion it holds is shorter).
    pub fn poll_within_ms(&self) -> u32 {
        let lead_ms = u32::from(self.config().queue_lead_ms);
        let queued_ms = u64::from(self.prep.queued_ticks()) * 1000 / u64::from(self.tick_hz);
        (queued_ms.min(u64::from(lead_ms)) as u32 / 2).max(1)
    }

    /// Whether the last [`Kernel::poll`] stopped with steps left to prepare before the queue
    /// holds its lead: call it again at once (after the board's other work of the moment).
    pub fn needs_poll(&self) -> bool {
        self.prep_more
    }

    fn start_interrupt(&mut self, now: Instant, force: bool) -> Option<Instant> {
        let q = self.tx.shared();
        let starts = q.starts.load(Ordering::Relaxed);
        if starts != q.idles.load(Ordering::Acquire) {
            return None;
        }
        if self.tx.len() == 0 && !force {
            return None;
        }
        q.starts.store(starts.wrapping_add(1), Ordering::Release);
        Some(now)
    }

    fn on_interrupt_stop(&mut self, cause: Option<StopCause>) {
        match cause {
            Some(StopCause::HomingSwitch(i)) => {
                let isr = self.tx.shared().positions();
                if let Some(h) = self.homing.as_mut()
                    && h.axis == usize::from(i)
                {
                    h.triggered = isr.get(h.axis).copied();
                }
                self.planner.clear();
                self.prep
                    .reset(self.tx.shared().consumed_ticks.load(Ordering::Relaxed));
                self.request_flush();
                // Keep the cycle going (abort() would end it).
                return;
            }
            Some(StopCause::Probe) => {
                let isr = self.tx.shared().positions();
                if let Some(p) = self.probing.as_mut() {
                    p.tripped = Some(isr);
                }
                self.planner.clear();
                self.prep
                    .reset(self.tx.shared().consumed_ticks.load(Ordering::Relaxed));
                self.request_flush();
                return;
            }
            Some(StopCause::HardLimit(i)) => self.alarm = Some(Alarm::HardLimit { axis: i }),
            Some(StopCause::Fault(i)) => self.alarm = Some(Alarm::DriverFault { axis: i }),
            Some(StopCause::Underrun) | None => self.alarm = Some(Alarm::StepUnderrun),
        }
        // The interrupt side discards everything until it sees a flush.
        self.abort(true, true);
    }

    fn start_homing(&mut self, mask: u8) {
        self.alarm = None;
        self.hold = false;
        self.prep.set_hold(false);
        if mask == 0 {
            return;
        }
        self.homed &= !mask;
        self.quiet_until = None;
        self.homing = Some(Homing {
            pending: mask,
            axis: 0,
            phase: HomePhase::Next,
            start_steps: 0,
            triggered: None,
        });
    }

    /// Advance the homing cycle once the previous homing move has ended.
    fn homing_step(&mut self) {
        let Some(mut h) = self.homing else { return };
        if !self.is_idle() {
            return;
        }
        let isr = self.tx.shared().positions();
        let here = isr.get(h.axis).copied().unwrap_or(0);
        let Some(cfg) = self.config.axes.get(h.axis).and_then(|a| a.homing) else {
            if h.phase != HomePhase::Next {
                self.homing = None;
                return;
            }
            h.axis = 0;
            return self.homing_next(h);
        };
        let axis = h.axis;
        let toward = cfg.direction.sign();
        match h.phase {
            HomePhase::Next => return self.homing_next(h),
            HomePhase::Seek => match h.triggered.take() {
                Some(_) => {
                    h.phase = HomePhase::BackOff;
                    self.homing_move(
                        axis,
                        -toward * cfg.pull_off_mm.max(0.5),
                        cfg.locate_mm_min,
                        0,
                    );
                }
                None => return self.homing_alarm(Alarm::HomingSwitchNotFound { axis: axis as u8 }),
            },
            HomePhase::BackOff => {
                h.phase = HomePhase::Locate;
                h.start_steps = here;
                let dist = 2.0 * cfg.pull_off_mm.max(0.5) + 1.0;
                self.homing_move(axis, toward * dist, cfg.locate_mm_min, 1 << axis);
            }
            HomePhase::Locate => match h.triggered.take() {
                Some(at) if at == h.start_steps => {
                    return self.homing_alarm(Alarm::HomingSwitchStuck { axis: axis as u8 });
                }
                Some(at) => {
                    let a = &self.config.axes[axis];
                    let home_steps = nm_to_steps(mm_to_nm(a.end_mm(cfg.direction)), a.steps_per_mm);
                    self.origin[axis] = at.wrapping_sub(home_steps);
                    self.resync();
                    h.phase = HomePhase::PullOff;
                    if cfg.pull_off_mm > 0.0 {
                        self.homing_move(axis, -toward * cfg.pull_off_mm, cfg.seek_mm_min, 0);
                    }
                }
                None => return self.homing_alarm(Alarm::HomingSwitchNotFound { axis: axis as u8 }),
            },
            HomePhase::PullOff => {
                self.homed |= 1 << axis;
                h.pending &= !(1 << axis);
                h.phase = HomePhase::Next;
                self.homing = Some(h);
                return self.homing_step();
            }
        }
        self.homing = Some(h);
    }

    fn homing_next(&mut self, mut h: Homing) {
        // Lowest `order` first, then axis index.
        let next = self
            .config
            .axes
            .iter()
            .enumerate()
            .filter(|(i, a)| h.pending & (1 << i) != 0 && a.homing.is_some())
            .min_by_key(|(i, a)| (a.homing.map_or(0, |c| c.order), *i))
            .map(|(i, _)| i);
        let Some(axis) = next else {
            self.homing = None;
            self.tx.shared().homing_mask.store(0, Ordering::Relaxed);
            self.resync();
            return;
        };
        let Some(cfg) = self.config.axes[axis].homing else {
            self.homing = None;
            return;
        };
        h.axis = axis;
        h.phase = HomePhase::Seek;
        h.triggered = None;
        let toward = cfg.direction.sign();
        let dist = self.config.axes[axis].travel_mm() + 2.0 * cfg.pull_off_mm;
        self.homing = Some(h);
        self.homing_move(axis, toward * dist, cfg.seek_mm_min, 1 << axis);
    }

    fn homing_move(&mut self, axis: usize, mm: f32, feed_mm_min: f32, switch_mask: u8) {
        self.tx
            .shared()
            .homing_mask
            .store(u32::from(switch_mask), Ordering::Relaxed);
        let mut target = self.interp.live().pos;
        target[axis] += mm_to_nm(mm);
        self.queue_move(&target, Some(feed_mm_min), 1.0, false, switch_mask, false);
        self.interp.live_mut().pos = target;
    }

    /// Start a probing move to `target`: the step interrupt stops it when the probe touches
    /// (or, `away`, loses contact). At the probing feed, not scaled by the feed override (as
    /// grbl's), and ending at rest: the kernel takes no other line until it is over.
    fn start_probe(&mut self, target: &[Nm; N], feed_mm_min: f32, away: bool, must_trip: bool) {
        let q = self.tx.shared();
        let mode = if away { PROBE_RELEASE } else { PROBE_CONTACT };
        q.probe.store(mode, Ordering::Relaxed);
        self.quiet_until = None;
        self.probing = Some(Probing {
            must_trip,
            start: q.positions(),
            tripped: None,
        });
        self.queue_move(target, Some(feed_mm_min), 1.0, false, 0, true);
    }

    /// End the probing move once the machine is at rest: record where the probe tripped (the
    /// position the kernel goes on from), or lock the machine as grbl does when the probe was
    /// already tripped at the start ([`Alarm::ProbeFailInitial`]) or, for `G38.2`/`G38.4`,
    /// never tripped ([`Alarm::ProbeFailContact`]).
    fn probe_step(&mut self) {
        let Some(p) = self.probing else { return };
        if !self.is_idle() {
            return;
        }
        self.probing = None;
        self.tx.shared().probe.store(PROBE_OFF, Ordering::Relaxed);
        let machine = self.machine_steps();
        let machine_nm =
            core::array::from_fn(|i| steps_to_nm(machine[i], self.config.axes[i].steps_per_mm));
        let tripped = p.tripped.is_some();
        self.probe = Some((
            ProbeReport {
                machine_nm,
                tripped,
            },
            false,
        ));
        if p.tripped == Some(p.start) {
            self.alarm = Some(Alarm::ProbeFailInitial);
        } else if !tripped && p.must_trip {
            self.alarm = Some(Alarm::ProbeFailContact);
        }
    }

    /// Whether a probing move (`G38.2`–`G38.5`) is under way: the kernel takes no other line
    /// until it is over.
    pub fn is_probing(&self) -> bool {
        self.probing.is_some()
    }

    /// The last probing move's outcome (`None` before the first): grbl's `$#` reports it.
    pub fn probe_report(&self) -> Option<ProbeReport<N>> {
        self.probe.map(|(r, _)| r)
    }

    /// The outcome of a probing move that ended since the last call, once.
    pub fn take_probe_report(&mut self) -> Option<ProbeReport<N>> {
        match self.probe.as_mut() {
            Some((r, reported)) if !*reported => {
                *reported = true;
                Some(*r)
            }
            _ => None,
        }
    }

    fn homing_alarm(&mut self, alarm: Alarm) {
        self.abort(true, false);
        self.alarm = Some(alarm);
    }
}

/// The spindle and coolant commands that may share a line with motion.
fn is_spindle_or_coolant(w: &Word) -> bool {
    w.letter == b'M' && matches!(w.value.as_integer(), Some(3 | 4 | 5 | 7 | 8 | 9))
}

/// A line with one spindle or coolant `M` word (with its `S`) and motion, as two lines in the
/// order they act: the command, then the rest. `None` for any other line.
pub(crate) fn split_spindle_and_motion<'l>(line: &Line<'l>) -> Option<(Line<'l>, Line<'l>)> {
    let words = line.words();
    if words.iter().filter(|w| is_spindle_or_coolant(w)).count() != 1
        || words
            .iter()
            .any(|w| w.letter == b'M' && !is_spindle_or_coolant(w))
    {
        return None;
    }
    let mut first = [Word::bare(b'S'); MAX_WORDS];
    let mut rest = [Word::bare(b'S'); MAX_WORDS];
    let (mut n_first, mut n_rest) = (0, 0);
    for w in words {
        let (slot, n) = if is_spindle_or_coolant(w) || w.letter == b'S' {
            (&mut first, &mut n_first)
        } else {
            (&mut rest, &mut n_rest)
        };
        if let Some(s) = slot.get_mut(*n) {
            *s = *w;
            *n += 1;
        }
    }
    let (first, rest) = (first.get(..n_first)?, rest.get(..n_rest)?);
    // Only `F` or nothing besides the command: a line of its own.
    if rest.iter().all(|w| w.letter == b'F') {
        return None;
    }
    Some((
        Line::from_parts(None, first, None).ok()?,
        Line::from_parts(None, rest, None).ok()?,
    ))
}

/// The refusal of a setting that leaves `config` invalid: a bad value of the axis the error
/// names (its letter), of `J` for the junction deviation, else of the command (`M`).
fn refusal<const N: usize>(config: &MachineConfig<N>, error: ConfigError) -> CommandError {
    let letter = match (error.axis(), error) {
        (Some(i), _) => config.axes.get(usize::from(i)).map_or(b'M', |a| a.letter),
        (None, ConfigError::JunctionDeviation) => b'J',
        (None, _) => b'M',
    };
    CommandError::BadValue { letter }
}
