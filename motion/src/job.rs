//! Jobs: a stored program, run line by line through the kernel, with progress and an
//! estimate of its duration.
//!
//! Thread side. Programs arrive as frame message 03 (one line of at most 39 bytes, indexed
//! from 1, at most 9999 lines) and live in a [`ProgramStore`]; boards provide flash-backed
//! stores, [`RamStore`] keeps them in RAM. A [`Job`] feeds the stored lines to the
//! [`Kernel`] as fast as it takes them, and answers the frame actions (start, pause, resume,
//! stop, rewind, reset) and the progress request (message 52).

use forja_hal_abstraction::time::Instant;
use forja_protocol::gcode::Line;

use crate::arc::Nm;
use crate::effect::Effect;
use crate::error::{JobError, StoreError};
use crate::interp::{Action, nm_to_steps};
use crate::kernel::{Kernel, MachineState, Reply};
use crate::planner::{BlockKind, MoveRequest, Planner};
use crate::profile::Profile;

/// The longest program line, bytes (frame message 03).
pub const MAX_LINE_LEN: usize = 39;

/// The most lines of a program (four digits in frame message 03).
pub const MAX_LINES: u16 = 9999;

/// Where programs are kept.
///
/// Lines are numbered from 1 and stored strictly in order: storing line `k` is accepted only
/// when `k` is one more than the number of lines stored. To load a new program, [`clear`]
/// first (a controller does so when a line 1 arrives). Every error leaves the store as it was.
///
/// Context: thread. Flash-backed stores may block while they write.
///
/// [`clear`]: ProgramStore::clear
pub trait ProgramStore {
    /// The number of lines stored.
    fn len(&self) -> u16;

    /// Whether no line is stored.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Copy line `index` (1-based) into `buf`; returns its length.
    /// Errors: [`StoreError::NoSuchLine`], [`StoreError::Device`].
    fn read(&mut self, index: u16, buf: &mut [u8; MAX_LINE_LEN]) -> Result<usize, StoreError>;

    /// Store line `index`, which must be `len() + 1`.
    /// Errors: [`StoreError::OutOfOrder`], [`StoreError::Full`], [`StoreError::TooLong`],
    /// [`StoreError::Device`].
    fn store(&mut self, index: u16, text: &[u8]) -> Result<(), StoreError>;

    /// Remove every line. Errors: [`StoreError::Device`].
    fn clear(&mut self) -> Result<(), StoreError>;
}

impl<T: ProgramStore + ?Sized> ProgramStore for &mut T {
    fn len(&self) -> u16 {
        T::len(self)
    }
    fn read(&mut self, index: u16, buf: &mut [u8; MAX_LINE_LEN]) -> Result<usize, StoreError> {
        T::read(self, index, buf)
    }
    fn store(&mut self, index: u16, text: &[u8]) -> Result<(), StoreError> {
        T::store(self, index, text)
    }
    fn clear(&mut self) -> Result<(), StoreError> {
        T::clear(self)
    }
}

/// The rule every [`ProgramStore`] applies before it stores line `index` of `len` bytes, holding
/// `count` lines with room for `capacity`: lines come strictly in order (1, 2, …), are at most
/// [`MAX_LINE_LEN`] bytes, and fit. The errors come in that order, and a refused line leaves the
/// store as it was.
pub fn check_next_line(
    count: u16,
    capacity: u16,
    index: u16,
    len: usize,
) -> Result<(), StoreError> {
    let expected = count.saturating_add(1);
    if index != expected {
        return Err(StoreError::OutOfOrder {
            expected,
            got: index,
        });
    }
    if len > MAX_LINE_LEN {
        return Err(StoreError::TooLong);
    }
    if index > capacity {
        return Err(StoreError::Full);
    }
    Ok(())
}

/// A program store in RAM with room for `L` lines (at most [`MAX_LINES`] are ever accepted).
pub struct RamStore<const L: usize> {
    lines: [[u8; MAX_LINE_LEN]; L],
    lens: [u8; L],
    count: u16,
}

impl<const L: usize> Default for RamStore<L> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const L: usize> RamStore<L> {
    /// An empty store.
    pub const fn new() -> Self {
        Self {
            lines: [[0; MAX_LINE_LEN]; L],
            lens: [0; L],
            count: 0,
        }
    }
}

impl<const L: usize> ProgramStore for RamStore<L> {
    fn len(&self) -> u16 {
        self.count
    }

    fn read(&mut self, index: u16, buf: &mut [u8; MAX_LINE_LEN]) -> Result<usize, StoreError> {
        if index == 0 || index > self.count {
            return Err(StoreError::NoSuchLine);
        }
        let k = usize::from(index - 1);
        let (Some(line), Some(&len)) = (self.lines.get(k), self.lens.get(k)) else {
            return Err(StoreError::NoSuchLine);
        };
        *buf = *line;
        Ok(usize::from(len))
    }

    fn store(&mut self, index: u16, text: &[u8]) -> Result<(), StoreError> {
        let capacity = u16::try_from(L).unwrap_or(MAX_LINES).min(MAX_LINES);
        check_next_line(self.count, capacity, index, text.len())?;
        let k = usize::from(self.count);
        let (Some(line), Some(len)) = (self.lines.get_mut(k), self.lens.get_mut(k)) else {
            return Err(StoreError::Full);
        };
        line.fill(0);
        if let Some(dst) = line.get_mut(..text.len()) {
            dst.copy_from_slice(text);
        }
        *len = text.len() as u8;
        self.count = index;
        Ok(())
    }

    fn clear(&mut self) -> Result<(), StoreError> {
        self.count = 0;
        Ok(())
    }
}

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
    /// Lines in the program.
    pub total_lines: u16,
    /// The line whose motion runs now while the job runs or is paused; the next line to run
    /// when it is idle (after a stop, a rewind, or before the first start); the last line once
    /// the program has finished. 1-based; 0 with no program stored.
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
        if self.next_line > store.len() {
            self.next_line = 1;
        }
        if !kernel.is_idle() {
            return Err(JobError::Busy);
        }
        self.estimated_s = estimate_seconds(kernel, store, self.next_line)?;
        self.tick_hz = kernel.tick_hz().max(1);
        self.started = Some(now);
        self.elapsed_s = 0;
        // The kernel's line is that of an earlier run until this run's first block is prepared.
        self.first_fed = self.next_line;
        self.last_fed = self.next_line;
        self.state = JobState::Running;
        Ok(())
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
            _ if store.is_empty() => 0,
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

/// Estimate how long the program takes from line `from` to its end, seconds.
///
/// A dry run of the same interpreter and planner (same depth, same configuration, starting
/// from the kernel's position and modal state): lines are planned until the planner is full,
/// then the oldest block is timed with its final entry and exit speeds, as segment
/// preparation will execute it. Homing counts as the seek over the whole travel and back.
pub fn estimate_seconds<P: ProgramStore, const N: usize, const B: usize, const Q: usize>(
    kernel: &Kernel<'_, N, B, Q>,
    store: &mut P,
    from: u16,
) -> Result<f32, JobError> {
    let config = kernel.config();
    let mut interp = kernel.interpreter();
    let mut steps = kernel.commanded_steps();
    let mut planner = Planner::<N, B>::new();
    let mut total = 0f64;
    let mut v_carry = 0f64;
    let mut buf = [0u8; MAX_LINE_LEN];
    let retire = |planner: &mut Planner<N, B>, total: &mut f64, v_carry: &mut f64| {
        let exit_sqr = planner.tail_exit_sqr();
        if let Some(b) = planner.tail().copied() {
            match b.kind {
                BlockKind::Dwell(ms) => {
                    *total += f64::from(ms) / 1000.0;
                    *v_carry = 0.0;
                }
                BlockKind::Move => {
                    let p = Profile::plan(
                        f64::from(b.mm),
                        *v_carry,
                        libm::sqrt(f64::from(b.nominal_sqr)),
                        libm::sqrt(f64::from(exit_sqr)),
                        f64::from(b.accel),
                    );
                    *total += p.duration();
                    *v_carry = p.exit_speed();
                }
            }
        }
        planner.retire_tail();
    };
    let mut push = |planner: &mut Planner<N, B>,
                    target: &[Nm; N],
                    feed: Option<f32>,
                    ramp: bool,
                    total: &mut f64,
                    v_carry: &mut f64| {
        if planner.is_full() {
            retire(planner, total, v_carry);
        }
        let mut delta = [0i32; N];
        for (i, a) in config.axes.iter().enumerate() {
            let s = nm_to_steps(target[i], a.steps_per_mm);
            delta[i] = s.wrapping_sub(steps[i]);
            steps[i] = s;
        }
        let req = MoveRequest {
            steps: delta,
            feed_mm_min: feed,
            ramp,
            line: 0,
            homing_mask: 0,
        };
        let _ = planner.push_move(&req, config);
    };
    for index in from.max(1)..=store.len() {
        let len = store
            .read(index, &mut buf)
            .map_err(|_| JobError::Syntax { line: index })?;
        let line = Line::parse(buf.get(..len).unwrap_or(&[]))
            .map_err(|_| JobError::Syntax { line: index })?;
        let mut next = interp;
        let Ok(action) = next.interpret(&line, config) else {
            continue;
        };
        interp = next;
        match action {
            Action::Move {
                target,
                feed_mm_min,
                ramp,
            } => push(
                &mut planner,
                &target,
                feed_mm_min,
                ramp,
                &mut total,
                &mut v_carry,
            ),
            Action::Arc {
                mut cutter,
                feed_mm_min,
                ramp,
            } => {
                while let Some(p) = cutter.peek() {
                    let first = cutter.is_first();
                    cutter.advance();
                    push(
                        &mut planner,
                        &p,
                        Some(feed_mm_min),
                        ramp && first,
                        &mut total,
                        &mut v_carry,
                    );
                }
            }
            Action::Dwell { ms } => {
                if planner.is_full() {
                    retire(&mut planner, &mut total, &mut v_carry);
                }
                let _ = planner.push_dwell(ms, 0);
            }
            Action::Effect(Effect::ProgramEnd) => break,
            Action::Home { mask } => {
                while !planner.is_empty() {
                    retire(&mut planner, &mut total, &mut v_carry);
                }
                for (i, a) in config.axes.iter().enumerate() {
                    if let (true, Some(h)) = (mask & (1 << i) != 0, a.homing) {
                        total += f64::from(a.travel_mm()) / f64::from(h.seek_mm_min / 60.0);
                    }
                }
            }
            _ => {}
        }
    }
    while !planner.is_empty() {
        retire(&mut planner, &mut total, &mut v_carry);
    }
    Ok(total as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ram_store_is_strictly_ordered_and_bounded() {
        let mut s = RamStore::<3>::new();
        assert_eq!(
            s.store(2, b"G1 X1"),
            Err(StoreError::OutOfOrder {
                expected: 1,
                got: 2
            })
        );
        assert_eq!(s.len(), 0);
        s.store(1, b"G1 X1").expect("1");
        s.store(2, b"G1 X2").expect("2");
        assert_eq!(
            s.store(2, b"G1 X9"),
            Err(StoreError::OutOfOrder {
                expected: 3,
                got: 2
            })
        );
        assert_eq!(s.store(3, &[b'X'; 40]), Err(StoreError::TooLong));
        s.store(3, &[b'X'; 39]).expect("39 bytes fit");
        assert_eq!(s.store(4, b"G1"), Err(StoreError::Full));
        assert_eq!(s.len(), 3);
        let mut buf = [0; MAX_LINE_LEN];
        assert_eq!(s.read(2, &mut buf), Ok(5));
        assert_eq!(&buf[..5], b"G1 X2");
        assert_eq!(s.read(4, &mut buf), Err(StoreError::NoSuchLine));
        assert_eq!(s.read(0, &mut buf), Err(StoreError::NoSuchLine));
        s.clear().expect("clear");
        assert!(s.is_empty());
    }
}
