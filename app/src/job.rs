//! Jobs: a stored program, run line by line through the kernel, with progress and an
//! estimate of its duration.
//!
//! Thread side. Programs arrive as frame message 03 (one line of at most 39 bytes, indexed
//! from 1, at most 9999 lines) and live in a [`ProgramStore`]; boards provide flash-backed
//! stores, [`RamStore`](forja_hal_abstraction::program::RamStore) keeps them in RAM. A [`Job`] feeds the stored lines to the
//! [`Kernel`] as fast as it takes them, and answers the frame actions (start, pause, resume,
//! stop, rewind, reset) and the progress request (message 52).

use forja_hal_abstraction::time::Instant;
use forja_protocol::gcode::Line;

use crate::error::JobError;
use forja_hal_abstraction::program::{MAX_LINE_LEN, ProgramStore};
use forja_motion::effect::Effect;
use forja_motion::{Estimate, Kernel, MachineState, Reply};

/// Where a job stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobState {
    /// Not started (or stopped, or reset): [`Job::start`] runs from the current line.
    Idle,
    /// Feeding lines and moving.
    Running,
    /// Held by [`Job::pause`] or a program `M226`; [`Job::start`] resumes.
    Paused,
    /// Every line has run and the motion has finished.
    Finished,
}

/// The figures of frame message 52.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Progress {
    /// Seconds since the job started (frozen when it finished).
    pub elapsed_s: u32,
    /// Estimated duration of the whole job, seconds, from the plan.
    pub estimated_s: u32,
    /// Lines stored: the program's lines once it is complete; the lines stored so far while
    /// its upload is incomplete.
    pub total_lines: u16,
    /// The line whose motion runs now while the job runs or is paused; the next line to run
    /// when it is idle (after a stop, a rewind, or before the first start); the last line once
    /// the program has finished. 1-based; 0 with no program stored or an incomplete one (so
    /// `total_lines > 0` with `current_line == 0` reads "upload incomplete, nothing to run").
    pub current_line: u16,
}

impl From<Progress> for forja_protocol::frame::Progress {
    fn from(p: Progress) -> Self {
        Self {
            elapsed_s: p.elapsed_s,
            estimated_s: p.estimated_s,
            total_lines: u32::from(p.total_lines),
            current_line: u32::from(p.current_line),
        }
    }
}

/// What the resume record should say now (see [`Job::checkpoint`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Checkpoint {
    /// Lines `1..=line` have run, their motion finished (0: none yet).
    Done(u16),
    /// The program has finished: nothing is left to resume.
    Finished,
}

/// The progress the job has recorded, for [`Job::checkpoint`].
#[derive(Debug, Clone, Copy)]
struct Tracking {
    /// Whether the running job records its progress (from a start until it finishes or an
    /// alarm cuts its motion).
    on: bool,
    recorded: Option<u16>,
    /// A line seen done while running, and when (ms): it is recorded once it has been done
    /// for the settle time.
    pending: Option<(u16, u32)>,
    /// The last line that has been done for the settle time, not yet recorded.
    settled: Option<u16>,
    last_write_ms: Option<u32>,
}

impl Tracking {
    const OFF: Self = Self {
        on: false,
        recorded: None,
        pending: None,
        settled: None,
        last_write_ms: None,
    };
}

/// Runs a stored program through the kernel.
pub struct Job {
    state: JobState,
    next_line: u16,
    buf: [u8; MAX_LINE_LEN],
    started: Option<Instant>,
    elapsed_s: u32,
    estimated_s: f32,
    tick_hz: u32,
    /// The line the run started from (at a start, not a resume), and the last line fed since
    /// (the start line until one is).
    first_fed: u16,
    last_fed: u16,
    tracking: Tracking,
}

impl Default for Job {
    fn default() -> Self {
        Self::new()
    }
}

impl Job {
    /// A job at line 1, not started.
    pub const fn new() -> Self {
        Self {
            state: JobState::Idle,
            next_line: 1,
            buf: [0; MAX_LINE_LEN],
            started: None,
            elapsed_s: 0,
            estimated_s: 0.0,
            tick_hz: 1,
            first_fed: 1,
            last_fed: 0,
            tracking: Tracking::OFF,
        }
    }

    /// Where the job stands.
    pub fn state(&self) -> JobState {
        self.state
    }

    /// The duration estimated at the last start, seconds.
    pub fn estimate_s(&self) -> f32 {
        self.estimated_s
    }

    /// The next line to be fed (1-based).
    pub fn next_line(&self) -> u16 {
        self.next_line
    }

    /// Action `Start`: run the program from the current line, or resume a paused job. The
    /// duration is estimated here (a dry run of the planner over the remaining lines).
    pub fn start<P: ProgramStore, const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
        store: &mut P,
        now: Instant,
    ) -> Result<(), JobError> {
        match self.state {
            JobState::Paused => {
                kernel.resume();
                self.state = JobState::Running;
                return Ok(());
            }
            JobState::Running => return Ok(()),
            JobState::Idle | JobState::Finished => {}
        }
        if store.is_empty() {
            return Err(JobError::Empty);
        }
        if !store.is_complete() {
            return Err(JobError::Incomplete {
                stored: store.len(),
                total: store.total(),
            });
        }
        if self.next_line > store.len() {
            self.next_line = 1;
        }
        if !kernel.is_idle() {
            return Err(JobError::Busy);
        }
        self.run_from_here(kernel, store, now)
    }

    /// Start a resumed job at `line` (1-based) of the complete program in `store`, the
    /// kernel's modal state and position having been restored for it (the moves to the
    /// resumed line's start may still be running: they come first).
    pub fn start_resumed<P: ProgramStore, const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
        store: &mut P,
        line: u16,
        now: Instant,
    ) -> Result<(), JobError> {
        if matches!(self.state, JobState::Running | JobState::Paused) {
            return Err(JobError::Busy);
        }
        if !store.is_complete() {
            return Err(JobError::Incomplete {
                stored: store.len(),
                total: store.total(),
            });
        }
        self.next_line = line.max(1);
        self.run_from_here(kernel, store, now)
    }

    fn run_from_here<P: ProgramStore, const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
        store: &mut P,
        now: Instant,
    ) -> Result<(), JobError> {
        self.estimated_s = estimate_seconds(kernel, store, self.next_line)?;
        self.tick_hz = kernel.tick_hz().max(1);
        self.started = Some(now);
        self.elapsed_s = 0;
        // The kernel's line is that of an earlier run until this run's first block is prepared.
        self.first_fed = self.next_line;
        self.last_fed = self.next_line;
        self.state = JobState::Running;
        self.tracking = Tracking {
            on: true,
            ..Tracking::OFF
        };
        Ok(())
    }

    /// What to write to the resume record now, if anything; call it at every poll with the
    /// time in ms. A line is recorded as done only when it certainly is:
    /// - while the job runs, the lines before the one whose motion is being prepared, once
    ///   they have been so for `settle_ms` (more than the step queue holds: their last steps
    ///   have been executed), and at most once per `period_ms` (flash wear);
    /// - at once when the job is paused or stopped with the machine at rest;
    /// - never after an alarm cut the motion (steps may be lost): the record keeps the last
    ///   settled line, and the job records nothing more until it is started again.
    ///
    /// The first call after a start reports the lines before the start line at once, so that
    /// the record of an earlier run never outlives the start. A finished program reports
    /// [`Checkpoint::Finished`] once. Nothing is reported while no job was started since
    /// [`Job::new`].
    pub fn checkpoint<const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &Kernel<'_, N, B, Q>,
        now_ms: u32,
        settle_ms: u32,
        period_ms: u32,
    ) -> Option<Checkpoint> {
        if !self.tracking.on {
            return None;
        }
        let machine = kernel.state();
        if matches!(machine, MachineState::Alarm(_) | MachineState::Halted) {
            self.tracking = Tracking::OFF;
            return None;
        }
        let Some(done) = self.done_line(kernel) else {
            self.tracking = Tracking::OFF;
            return Some(Checkpoint::Finished);
        };
        let at_rest = matches!(
            machine,
            MachineState::Idle | MachineState::Paused | MachineState::Hold { stopped: true }
        );
        let t = &mut self.tracking;
        if t.recorded.is_none() {
            // A start: the lines before the first one of this run are done; an older record
            // (of a run that went further) must not survive it.
            let first = self.first_fed.saturating_sub(1);
            t.recorded = Some(first);
            t.last_write_ms = Some(now_ms);
            return Some(Checkpoint::Done(first));
        }
        if self.state != JobState::Running && at_rest {
            t.pending = None;
            if t.recorded == Some(done) {
                return None;
            }
            t.recorded = Some(done);
            t.last_write_ms = Some(now_ms);
            return Some(Checkpoint::Done(done));
        }
        if let Some((line, seen)) = t.pending
            && now_ms.wrapping_sub(seen) >= settle_ms
        {
            t.settled = Some(line);
            t.pending = None;
        }
        let known = t.settled.max(t.recorded).unwrap_or(0);
        if t.pending.is_none() && done > known {
            t.pending = Some((done, now_ms));
        }
        let due = t
            .last_write_ms
            .is_none_or(|w| now_ms.wrapping_sub(w) >= period_ms);
        match t.settled {
            Some(line) if due && t.recorded.is_none_or(|r| line > r) => {
                t.settled = None;
                t.recorded = Some(line);
                t.last_write_ms = Some(now_ms);
                Some(Checkpoint::Done(line))
            }
            _ => None,
        }
    }

    /// Action `Pause`: feed hold (decelerate on the path, no step lost).
    pub fn pause<const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
    ) -> Result<(), JobError> {
        if self.state != JobState::Running {
            return Err(JobError::NotRunning);
        }
        kernel.hold();
        self.state = JobState::Paused;
        Ok(())
    }

    /// Action `Stop`: stop motion (decelerating) and the program, keeping the position and the
    /// current line. The line that was being fed runs again on the next start.
    pub fn stop<const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
    ) {
        if matches!(self.state, JobState::Running | JobState::Paused) {
            kernel.stop();
            let current = self.running_line(kernel);
            if current >= 1 && current < self.next_line {
                self.next_line = current;
            }
        }
        self.state = JobState::Idle;
    }

    /// The last line whose motion is finished, as far as the job can tell now: the lines
    /// before the one whose motion is being prepared while the job runs or is paused (the
    /// step queue may still hold the end of that line's motion: see the controller's
    /// checkpoints), the lines before the next one when it is idle; `None` once the program
    /// has finished. 0 when no line is done.
    pub fn done_line<const N: usize, const B: usize, const Q: usize>(
        &self,
        kernel: &Kernel<'_, N, B, Q>,
    ) -> Option<u16> {
        match self.state {
            JobState::Finished => None,
            JobState::Idle => Some(self.next_line.saturating_sub(1)),
            JobState::Running | JobState::Paused => {
                Some(self.running_line(kernel).saturating_sub(1))
            }
        }
    }

    /// Action `Rewind`: back to line 1. Only while not running.
    pub fn rewind(&mut self) -> Result<(), JobError> {
        if matches!(self.state, JobState::Running | JobState::Paused) {
            return Err(JobError::Busy);
        }
        self.next_line = 1;
        self.state = JobState::Idle;
        Ok(())
    }

    /// Action `Reset`: soft reset of the kernel (alarms cleared, modal defaults); the job
    /// stops, the program and the current line are kept.
    pub fn reset<const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
    ) {
        kernel.reset();
        self.state = JobState::Idle;
    }

    /// Feed lines while the kernel takes them. Returns an [`Effect`] a line produced (the
    /// controller carries it out, then calls `poll` again), `Ok(None)` when nothing is to be
    /// done now, or the error of a line that failed (the job stops at that line).
    pub fn poll<P: ProgramStore, const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
        store: &mut P,
        now: Instant,
    ) -> Result<Option<Effect<'_>>, JobError> {
        if let Some(t0) = self.started
            && matches!(self.state, JobState::Running | JobState::Paused)
        {
            let ticks = now.saturating_duration_since(t0).ticks();
            self.elapsed_s = ticks / self.tick_hz;
        }
        if self.state != JobState::Running {
            return Ok(None);
        }
        if let MachineState::Alarm(_) | MachineState::Halted = kernel.state() {
            self.state = JobState::Idle;
            return Ok(None);
        }
        if kernel.state() == MachineState::Paused {
            self.state = JobState::Paused;
            return Ok(None);
        }
        loop {
            if self.next_line > store.len() {
                if kernel.is_idle() {
                    self.state = JobState::Finished;
                }
                return Ok(None);
            }
            if !kernel.can_accept() {
                return Ok(None);
            }
            let index = self.next_line;
            let mut local = [0u8; MAX_LINE_LEN];
            let len = store
                .read(index, &mut local)
                .map_err(|_| JobError::Syntax { line: index })?;
            let text = local.get(..len).unwrap_or(&[]);
            let line = match Line::parse(text) {
                Ok(l) => l,
                Err(_) => {
                    self.state = JobState::Idle;
                    return Err(JobError::Syntax { line: index });
                }
            };
            kernel.set_line_tag(u32::from(index));
            match kernel.execute(&line) {
                Ok(Reply::Busy) => return Ok(None),
                Ok(Reply::Ok) | Ok(Reply::Position(_)) => {
                    self.last_fed = index;
                    self.next_line += 1;
                }
                Ok(Reply::Effect(e)) => {
                    self.last_fed = index;
                    self.next_line += 1;
                    if e == Effect::Paused {
                        self.state = JobState::Paused;
                    }
                    if e == Effect::ProgramEnd {
                        // `M2`/`M30`: the motion before it is done (the effect waits for it);
                        // the lines after it do not run, and the next start is from line 1.
                        self.state = JobState::Finished;
                        self.next_line = 1;
                    }
                    self.buf = local;
                    return Ok(Some(e.rebase(&local, &self.buf)));
                }
                Err(error) => {
                    self.state = JobState::Idle;
                    return Err(JobError::Line { line: index, error });
                }
            }
        }
    }

    /// The line whose motion runs now: the kernel's, within the lines of this run fed so far.
    fn running_line<const N: usize, const B: usize, const Q: usize>(
        &self,
        kernel: &Kernel<'_, N, B, Q>,
    ) -> u16 {
        u16::try_from(kernel.current_line())
            .unwrap_or(0)
            .clamp(self.first_fed, self.last_fed.max(self.first_fed))
    }

    /// The figures of frame message 52.
    pub fn progress<P: ProgramStore, const N: usize, const B: usize, const Q: usize>(
        &self,
        kernel: &Kernel<'_, N, B, Q>,
        store: &P,
    ) -> Progress {
        let current = match self.state {
            // Nothing runs: no program, or an upload not complete (`NL` then counts the lines
            // stored so far).
            _ if !store.is_complete() => 0,
            JobState::Finished => store.len(),
            // What `start` will run first.
            JobState::Idle if self.next_line > store.len() => 1,
            JobState::Idle => self.next_line,
            JobState::Running | JobState::Paused => self.running_line(kernel),
        };
        Progress {
            elapsed_s: self.elapsed_s,
            estimated_s: libm::roundf(self.estimated_s) as u32,
            total_lines: store.len(),
            current_line: current,
        }
    }
}

/// Estimate how long the stored program takes from line `from` to its end, seconds: the
/// kernel's dry run ([`Estimate`]) over the stored lines, from where the kernel stands.
/// Errors: [`JobError::Syntax`] for a line that cannot be read or parsed.
pub fn estimate_seconds<P: ProgramStore, const N: usize, const B: usize, const Q: usize>(
    kernel: &Kernel<'_, N, B, Q>,
    store: &mut P,
    from: u16,
) -> Result<f32, JobError> {
    let mut estimate = Estimate::new(kernel);
    let mut buf = [0u8; MAX_LINE_LEN];
    for index in from.max(1)..=store.len() {
        let len = store
            .read(index, &mut buf)
            .map_err(|_| JobError::Syntax { line: index })?;
        let line = Line::parse(buf.get(..len).unwrap_or(&[]))
            .map_err(|_| JobError::Syntax { line: index })?;
        if !estimate.line(&line) {
            break;
        }
    }
    Ok(estimate.seconds())
}
