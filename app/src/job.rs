//! Jobs: a stored program or a file, run line by line through the kernel, with progress and
//! an estimate of its duration.
//!
//! Thread side. Programs arrive as frame message 03 (one line of at most 39 bytes, indexed
//! from 1, at most 9999 lines) and live in a [`ProgramStore`]; boards provide flash-backed
//! stores, [`RamStore`](forja_hal_abstraction::program::RamStore) keeps them in RAM. Files
//! arrive with Marlin's `M28`/`M29` and live in the board's [`FileStore`]: lines of up to
//! [`MAX_LINE_LEN`] bytes (256, the G-code line's limit), as many as the file holds. A [`Job`]
//! runs the program, or the file selected with [`Job::select_file`]: it feeds the lines to the
//! [`Kernel`] as fast as it takes them, and answers the frame actions (start, pause, resume,
//! stop, rewind, reset) and the progress request (message 52) for whichever it runs.
//!
//! A file is read in order, a few hundred bytes ahead of the line being fed: the controller
//! hands the job its file store at each poll ([`Job::read_ahead`]). Blank lines and comments
//! are skipped as a printer host skips them when it streams a file; a line longer than
//! [`MAX_LINE_LEN`] is cut at its `;` comment when that comes within the limit, and stops the
//! job otherwise. Positions in a file are byte offsets (Marlin's `M26`/`M27`); its lines are
//! counted as they are read, from the count of the whole file made when it was selected.

use forja_hal_abstraction::files::{FileError, FileName, FileStore};
use forja_hal_abstraction::time::Instant;
use forja_protocol::gcode::{Line, MAX_LINE_LEN};

use crate::error::JobError;
use forja_hal_abstraction::program::{self, ProgramStore};
use forja_motion::effect::{Effect, Storage};
use forja_motion::error::CommandError;
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
    /// Estimated duration of the whole job, seconds, from the plan; 0 for a file (a dry run
    /// of a whole file is not made).
    pub estimated_s: u32,
    /// Lines stored: the program's lines once it is complete; the lines stored so far while
    /// its upload is incomplete; a file's lines (at most 65535 reported).
    pub total_lines: u16,
    /// The line whose motion runs now while the job runs or is paused; the next line to run
    /// when it is idle (after a stop, a rewind, or before the first start); the last line once
    /// the program has finished. 1-based; 0 with no program stored or an incomplete one (so
    /// `total_lines > 0` with `current_line == 0` reads "upload incomplete, nothing to run").
    /// A file's lines are counted as they are read.
    pub current_line: u16,
}

/// The file a job runs, as `M27` and the file commands see it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SelectedFile {
    /// The file's name.
    pub name: FileName,
    /// Its size, bytes.
    pub size: u32,
    /// Where reading has got to: the byte the next line starts at (Marlin's `M27` position).
    pub byte: u32,
    /// Whether it is being printed, as Marlin's `M27` tells: from its selection or its start
    /// until it finishes, or is stopped (a stop, an alarm, a line that failed). A job paused
    /// by `M25` ([`Job::suspend`]) is still being printed.
    pub printing: bool,
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

/// Bytes of a file read ahead of the line being fed: a longest line and its terminator fit,
/// with room for the lines after it.
const READ_AHEAD: usize = 512;

/// Lines of a file whose byte offset and number the job remembers after feeding them, to
/// name the line whose motion runs.
const RECENT_LINES: usize = 16;

/// A file being run: where reading has got to, and the bytes read ahead.
#[derive(Clone, Copy)]
struct FileRun {
    name: FileName,
    size: u32,
    /// The file's lines, counted when it was selected.
    lines: u32,
    /// Where the next line starts, and its number (from 1).
    next_byte: u32,
    next_line: u32,
    /// The file's bytes from `next_byte` on: `ahead[..ahead_len]`.
    ahead: [u8; READ_AHEAD],
    ahead_len: usize,
    /// The rest of a line cut at its comment is being skipped.
    skipping: bool,
    /// The byte offset and number of the last lines fed, oldest overwritten first.
    recent: [(u32, u32); RECENT_LINES],
    recent_next: usize,
    /// Being printed (see [`SelectedFile::printing`]).
    printing: bool,
    /// Finished, and not yet told ([`Job::take_file_done`]).
    done: bool,
}

/// What comes next in a file.
enum Next {
    /// A line of `len` bytes at the start of the read-ahead; `used` bytes (its terminator
    /// included) go with it, `lines` lines end there, and the rest of the line is skipped
    /// after it when `skip_rest`.
    Line {
        len: usize,
        used: usize,
        lines: u32,
        skip_rest: bool,
    },
    /// More bytes must be read first.
    Bytes,
    /// Nothing is left.
    End,
    /// A line longer than [`MAX_LINE_LEN`] before any comment.
    TooLong,
}

impl FileRun {
    fn new(name: FileName, size: u32, lines: u32) -> Self {
        Self {
            name,
            size,
            lines,
            next_byte: 0,
            next_line: 1,
            ahead: [0; READ_AHEAD],
            ahead_len: 0,
            skipping: false,
            recent: [(0, 0); RECENT_LINES],
            recent_next: 0,
            printing: true,
            done: false,
        }
    }

    /// Read again from byte `byte`, line `line`.
    fn seek(&mut self, byte: u32, line: u32) {
        self.next_byte = byte.min(self.size);
        self.next_line = line.max(1);
        self.ahead_len = 0;
        self.skipping = false;
        self.recent = [(0, 0); RECENT_LINES];
    }

    fn ahead(&self) -> &[u8] {
        self.ahead.get(..self.ahead_len).unwrap_or(&[])
    }

    /// Whether the read-ahead holds the file up to its end.
    fn holds_the_end(&self) -> bool {
        u64::from(self.next_byte) + self.ahead_len as u64 >= u64::from(self.size)
    }

    /// Drop `used` bytes from the read-ahead, which end `lines` lines.
    fn consume(&mut self, used: usize, lines: u32) {
        let used = used.min(self.ahead_len);
        crate::bytes::shift_to_front(&mut self.ahead, used, self.ahead_len);
        self.ahead_len -= used;
        self.next_byte = self.next_byte.saturating_add(used as u32);
        self.next_line = self.next_line.saturating_add(lines);
    }

    /// The next line in the read-ahead, after the rest of a cut line is skipped.
    fn next(&mut self) -> Next {
        if self.skipping {
            match self.ahead().iter().position(|&b| b == b'\n') {
                Some(i) => {
                    self.consume(i + 1, 1);
                    self.skipping = false;
                }
                None => {
                    let at_end = self.holds_the_end();
                    self.consume(self.ahead_len, u32::from(at_end));
                    if !at_end {
                        return Next::Bytes;
                    }
                    self.skipping = false;
                }
            }
        }
        if self.ahead_len == 0 {
            return if self.next_byte >= self.size {
                Next::End
            } else {
                Next::Bytes
            };
        }
        let ahead = self.ahead();
        let (len, used, lines) = match ahead.iter().position(|&b| b == b'\n') {
            Some(i) => (i, i + 1, 1),
            None if self.holds_the_end() => (ahead.len(), ahead.len(), 1),
            None if ahead.len() < READ_AHEAD => return Next::Bytes,
            // A line longer than the read-ahead: its comment is cut off, the rest skipped.
            None => {
                return match comment_start(ahead) {
                    Some(len) => Next::Line {
                        len,
                        used: ahead.len(),
                        lines: 0,
                        skip_rest: true,
                    },
                    None => Next::TooLong,
                };
            }
        };
        if len <= MAX_LINE_LEN {
            return Next::Line {
                len,
                used,
                lines,
                skip_rest: false,
            };
        }
        match comment_start(ahead.get(..len).unwrap_or(&[])) {
            Some(len) => Next::Line {
                len,
                used,
                lines,
                skip_rest: false,
            },
            None => Next::TooLong,
        }
    }

    /// Line `line` starting at byte `byte` was fed.
    fn fed(&mut self, byte: u32, line: u32) {
        if let Some(slot) = self.recent.get_mut(self.recent_next) {
            *slot = (byte, line);
        }
        self.recent_next = (self.recent_next + 1) % RECENT_LINES;
    }

    /// The number of the line fed at byte `byte`: the one remembered, or, when that has been
    /// forgotten, the oldest remembered after it.
    fn line_at(&self, byte: u32) -> u32 {
        let known = self.recent.iter().filter(|(_, line)| *line > 0);
        let exact = known.clone().find(|(b, _)| *b == byte).map(|(_, l)| *l);
        exact
            .or_else(|| known.filter(|(b, _)| *b > byte).map(|(_, l)| *l).min())
            .unwrap_or(self.next_line)
    }
}

/// Where a `;` comment starts within the first [`MAX_LINE_LEN`] bytes of `line`.
fn comment_start(line: &[u8]) -> Option<usize> {
    line.iter().take(MAX_LINE_LEN + 1).position(|&b| b == b';')
}

/// The `M` number of a storage command (`M20`–`M32`).
fn storage_number(s: &Storage<'_>) -> u32 {
    match s {
        Storage::List => 20,
        Storage::Init => 21,
        Storage::Release => 22,
        Storage::Select(_) => 23,
        Storage::Start => 24,
        Storage::Pause => 25,
        Storage::SetPosition(_) => 26,
        Storage::Report | Storage::ReportEvery(_) => 27,
        Storage::BeginWrite(_) => 28,
        Storage::EndWrite(_) => 29,
        Storage::Delete(_) => 30,
        Storage::SelectAndStart(_) => 32,
    }
}

/// A stored line that is a file command (`M20`–`M32`): file commands are the host's, and a
/// job stops at one, as at any line it cannot run.
fn file_command_in_job(line: u32, s: &Storage<'_>) -> JobError {
    JobError::Line {
        line: u16::try_from(line).unwrap_or(u16::MAX),
        error: CommandError::Unsupported {
            letter: b'M',
            number: Some(storage_number(s)),
        },
    }
}

/// Runs a stored program, or a file, through the kernel.
pub struct Job {
    state: JobState,
    /// The program's next line.
    next_line: u16,
    /// The file the job runs instead of the program, when one is selected.
    file: Option<FileRun>,
    buf: [u8; MAX_LINE_LEN],
    started: Option<Instant>,
    elapsed_s: u32,
    estimated_s: f32,
    tick_hz: u32,
    /// The kernel's line tag the run started from (at a start, not a resume), and the last
    /// one fed since (the first until a line is): a program's line numbers, a file's byte
    /// offsets.
    first_fed: u32,
    last_fed: u32,
    tracking: Tracking,
}

impl Default for Job {
    fn default() -> Self {
        Self::new()
    }
}

impl Job {
    /// A job at line 1 of the program, not started.
    pub const fn new() -> Self {
        Self {
            state: JobState::Idle,
            next_line: 1,
            file: None,
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

    /// The next line to be fed (1-based): the program's, or the selected file's.
    pub fn next_line(&self) -> u32 {
        match &self.file {
            Some(run) => run.next_line,
            None => u32::from(self.next_line),
        }
    }

    /// The file the job runs, when one is selected.
    pub fn file(&self) -> Option<SelectedFile> {
        self.file.as_ref().map(|run| SelectedFile {
            name: run.name,
            size: run.size,
            byte: run.next_byte,
            printing: run.printing,
        })
    }

    /// Run the file `name` of `size` bytes and `lines` lines from now on, from its start,
    /// instead of the program or the file selected before (Marlin's `M23`). The job is idle;
    /// the file counts as being printed until it finishes or is stopped.
    /// Error: [`JobError::Busy`] while a job runs or is paused.
    pub fn select_file(&mut self, name: FileName, size: u32, lines: u32) -> Result<(), JobError> {
        if matches!(self.state, JobState::Running | JobState::Paused) {
            return Err(JobError::Busy);
        }
        self.file = Some(FileRun::new(name, size, lines));
        self.state = JobState::Idle;
        Ok(())
    }

    /// Run the program again, from line 1, rather than the selected file (none selected:
    /// nothing changes). Error: [`JobError::Busy`] while the file runs or is paused.
    pub fn select_program(&mut self) -> Result<(), JobError> {
        if self.file.is_none() {
            return Ok(());
        }
        if matches!(self.state, JobState::Running | JobState::Paused) {
            return Err(JobError::Busy);
        }
        self.file = None;
        self.next_line = 1;
        self.state = JobState::Idle;
        Ok(())
    }

    /// Go on from byte `byte` of the selected file, line `line` starting there (Marlin's
    /// `M26`; past the end: the end). The job is idle.
    /// Errors: [`JobError::NoFileSelected`], [`JobError::Busy`] while the file runs or is
    /// paused.
    pub fn set_file_position(&mut self, byte: u32, line: u32) -> Result<(), JobError> {
        let active = matches!(self.state, JobState::Running | JobState::Paused);
        let run = self.file.as_mut().ok_or(JobError::NoFileSelected)?;
        if active {
            return Err(JobError::Busy);
        }
        run.seek(byte, line);
        self.state = JobState::Idle;
        Ok(())
    }

    /// Stop feeding the running file's lines and let the motion already queued finish
    /// (Marlin's `M25`): the job is idle, the file still being printed, and [`Job::start`]
    /// goes on from the next line. Error: [`JobError::NotRunning`] unless a file runs.
    pub fn suspend(&mut self) -> Result<(), JobError> {
        if self.state != JobState::Running || self.file.is_none() {
            return Err(JobError::NotRunning);
        }
        self.state = JobState::Idle;
        Ok(())
    }

    /// Whether the selected file has finished since the last call (Marlin's `Done printing
    /// file` is due).
    pub fn take_file_done(&mut self) -> bool {
        self.file
            .as_mut()
            .is_some_and(|run| core::mem::take(&mut run.done))
    }

    /// Read the running file ahead of the line being fed, from `files`; call it at every poll
    /// while a file runs (nothing is read otherwise).
    ///
    /// Errors: the store's ([`FileError::NotFound`] when the file is gone), and
    /// [`FileError::Device`] for a file shorter than when it was selected; the caller stops
    /// the job.
    pub fn read_ahead(&mut self, files: &mut dyn FileStore) -> Result<(), FileError> {
        let Some(run) = self.file.as_mut() else {
            return Ok(());
        };
        if self.state != JobState::Running || run.holds_the_end() {
            return Ok(());
        }
        let at = run.next_byte.saturating_add(run.ahead_len as u32);
        let room = run.ahead.get_mut(run.ahead_len..).unwrap_or(&mut []);
        if room.is_empty() {
            return Ok(());
        }
        let n = files.read(&run.name, at, room)?;
        if n == 0 {
            return Err(FileError::Device);
        }
        run.ahead_len = (run.ahead_len + n).min(READ_AHEAD);
        Ok(())
    }

    /// Action `Start`: run the program (or the selected file) from the current line, or resume
    /// a paused job. A program's duration is estimated here (a dry run of the planner over the
    /// remaining lines); a file starts without an estimate, also while the motion before it
    /// still runs, and from its start again once it has finished.
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
        if let Some(run) = self.file.as_mut() {
            if self.state == JobState::Finished {
                run.seek(0, 1);
            }
            run.printing = true;
            self.estimated_s = 0.0;
            let first = run.next_byte;
            self.begin_run(kernel, first, now);
            return Ok(());
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
        self.file = None;
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
        self.begin_run(kernel, u32::from(self.next_line), now);
        Ok(())
    }

    /// Run from the line tagged `first`.
    fn begin_run<const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &Kernel<'_, N, B, Q>,
        first: u32,
        now: Instant,
    ) {
        self.tick_hz = kernel.tick_hz().max(1);
        self.started = Some(now);
        self.elapsed_s = 0;
        // The kernel's line is that of an earlier run until this run's first block is prepared.
        self.first_fed = first;
        self.last_fed = first;
        self.state = JobState::Running;
        self.tracking = Tracking {
            on: true,
            ..Tracking::OFF
        };
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
    /// [`Job::new`]. A file is not recorded: its start reports [`Checkpoint::Finished`] once,
    /// so that the record of the program run before it does not outlive it.
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
        if self.file.is_some() {
            self.tracking = Tracking::OFF;
            return Some(Checkpoint::Finished);
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
            let first = program_line(self.first_fed).saturating_sub(1);
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
    /// current line. The line that was being fed runs again on the next start. A file is no
    /// longer being printed.
    pub fn stop<const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
    ) {
        if matches!(self.state, JobState::Running | JobState::Paused) {
            kernel.stop();
            let current = self.running_tag(kernel);
            match self.file.as_mut() {
                Some(run) if current < run.next_byte => {
                    let line = run.line_at(current);
                    run.seek(current, line);
                }
                Some(_) => {}
                None => {
                    let current = program_line(current);
                    if current >= 1 && current < self.next_line {
                        self.next_line = current;
                    }
                }
            }
        }
        self.state = JobState::Idle;
        self.end_printing();
    }

    /// The last line whose motion is finished, as far as the job can tell now: the lines
    /// before the one whose motion is being prepared while the job runs or is paused (the
    /// step queue may still hold the end of that line's motion: see the controller's
    /// checkpoints), the lines before the next one when it is idle; `None` once the program
    /// has finished, and for a file. 0 when no line is done.
    pub fn done_line<const N: usize, const B: usize, const Q: usize>(
        &self,
        kernel: &Kernel<'_, N, B, Q>,
    ) -> Option<u16> {
        if self.file.is_some() {
            return None;
        }
        match self.state {
            JobState::Finished => None,
            JobState::Idle => Some(self.next_line.saturating_sub(1)),
            JobState::Running | JobState::Paused => {
                Some(program_line(self.running_tag(kernel)).saturating_sub(1))
            }
        }
    }

    /// Action `Rewind`: back to line 1 (of the program, or of the selected file). Only while
    /// not running.
    pub fn rewind(&mut self) -> Result<(), JobError> {
        if matches!(self.state, JobState::Running | JobState::Paused) {
            return Err(JobError::Busy);
        }
        self.next_line = 1;
        if let Some(run) = self.file.as_mut() {
            run.seek(0, 1);
        }
        self.state = JobState::Idle;
        Ok(())
    }

    /// Action `Reset`: soft reset of the kernel (alarms cleared, modal defaults); the job
    /// stops, the program (or file) and the current line are kept.
    pub fn reset<const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
    ) {
        kernel.reset();
        self.state = JobState::Idle;
        self.end_printing();
    }

    /// The selected file is no longer being printed.
    fn end_printing(&mut self) {
        if let Some(run) = self.file.as_mut() {
            run.printing = false;
        }
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
            self.end_printing();
            return Ok(None);
        }
        if kernel.state() == MachineState::Paused {
            self.state = JobState::Paused;
            return Ok(None);
        }
        if self.file.is_some() {
            return self.poll_file(kernel);
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
            let mut local = [0u8; program::MAX_LINE_LEN];
            let len = store
                .read(index, &mut local)
                .map_err(|_| JobError::Syntax { line: index })?;
            let text = local.get(..len).unwrap_or(&[]);
            let mut line = Line::empty();
            if line.parse_in(text).is_err() {
                self.state = JobState::Idle;
                return Err(JobError::Syntax { line: index });
            }
            kernel.set_line_tag(u32::from(index));
            match kernel.execute(&line) {
                Ok(Reply::Busy) => return Ok(None),
                Ok(Reply::Ok) | Ok(Reply::Position(_)) => {
                    self.last_fed = u32::from(index);
                    self.next_line += 1;
                }
                Ok(Reply::Effect(Effect::Storage(s))) => {
                    self.state = JobState::Idle;
                    return Err(file_command_in_job(u32::from(index), &s));
                }
                Ok(Reply::Effect(e)) => {
                    self.last_fed = u32::from(index);
                    self.next_line += 1;
                    if matches!(e, Effect::Paused) {
                        self.state = JobState::Paused;
                    }
                    if matches!(e, Effect::ProgramEnd) {
                        // `M2`/`M30`: the motion before it is done (the effect waits for it);
                        // the lines after it do not run, and the next start is from line 1.
                        self.state = JobState::Finished;
                        self.next_line = 1;
                    }
                    return Ok(Some(self.keep(&local, e)));
                }
                Err(error) => {
                    self.state = JobState::Idle;
                    return Err(JobError::Line { line: index, error });
                }
            }
        }
    }

    /// Feed the selected file's lines while the kernel takes them (see [`Job::poll`]).
    fn poll_file<const N: usize, const B: usize, const Q: usize>(
        &mut self,
        kernel: &mut Kernel<'_, N, B, Q>,
    ) -> Result<Option<Effect<'_>>, JobError> {
        loop {
            let Some(run) = self.file.as_mut() else {
                return Ok(None);
            };
            let number = run.next_line;
            let line_no = u16::try_from(number).unwrap_or(u16::MAX);
            let (len, used, lines, skip_rest) = match run.next() {
                Next::Line {
                    len,
                    used,
                    lines,
                    skip_rest,
                } => (len, used, lines, skip_rest),
                Next::Bytes => return Ok(None),
                Next::End => {
                    if kernel.is_idle() {
                        self.finish_file();
                    }
                    return Ok(None);
                }
                Next::TooLong => {
                    self.state = JobState::Idle;
                    self.end_printing();
                    return Err(JobError::Syntax { line: line_no });
                }
            };
            let mut local = [0u8; MAX_LINE_LEN];
            let text = run.ahead.get(..len).unwrap_or(&[]);
            if let Some(dst) = local.get_mut(..text.len()) {
                dst.copy_from_slice(text);
            }
            let byte = run.next_byte;
            let mut line = Line::empty();
            if line.parse_in(local.get(..len).unwrap_or(&[])).is_err() {
                self.state = JobState::Idle;
                self.end_printing();
                return Err(JobError::Syntax { line: line_no });
            }
            let take = |run: &mut FileRun| {
                run.consume(used, lines);
                run.skipping = skip_rest;
            };
            if line.is_empty() {
                take(run);
                continue;
            }
            if !kernel.can_accept() {
                return Ok(None);
            }
            kernel.set_line_tag(byte);
            match kernel.execute(&line) {
                Ok(Reply::Busy) => return Ok(None),
                Ok(Reply::Effect(Effect::Storage(s))) => {
                    self.state = JobState::Idle;
                    self.end_printing();
                    return Err(file_command_in_job(number, &s));
                }
                Ok(reply) => {
                    take(run);
                    run.fed(byte, number);
                    self.last_fed = byte;
                    let Reply::Effect(e) = reply else { continue };
                    if matches!(e, Effect::Paused) {
                        self.state = JobState::Paused;
                    }
                    if matches!(e, Effect::ProgramEnd) {
                        // As in a program: the lines after it do not run.
                        self.finish_file();
                    }
                    return Ok(Some(self.keep(&local, e)));
                }
                Err(error) => {
                    self.state = JobState::Idle;
                    self.end_printing();
                    return Err(JobError::Line {
                        line: line_no,
                        error,
                    });
                }
            }
        }
    }

    /// The selected file has finished: the next start runs it from its start.
    fn finish_file(&mut self) {
        self.state = JobState::Finished;
        if let Some(run) = self.file.as_mut() {
            run.printing = false;
            run.done = true;
        }
    }

    /// Keep the line `local` that produced `e`, and the effect with its texts in the copy.
    fn keep<'a>(&'a mut self, local: &[u8], e: Effect<'_>) -> Effect<'a> {
        self.buf = [0; MAX_LINE_LEN];
        if let Some(dst) = self.buf.get_mut(..local.len()) {
            dst.copy_from_slice(local);
        }
        e.rebase(local, &self.buf)
    }

    /// The kernel's tag of the line whose motion runs now, within those of this run fed so
    /// far.
    fn running_tag<const N: usize, const B: usize, const Q: usize>(
        &self,
        kernel: &Kernel<'_, N, B, Q>,
    ) -> u32 {
        kernel
            .current_line()
            .clamp(self.first_fed, self.last_fed.max(self.first_fed))
    }

    /// The figures of frame message 52.
    pub fn progress<P: ProgramStore, const N: usize, const B: usize, const Q: usize>(
        &self,
        kernel: &Kernel<'_, N, B, Q>,
        store: &P,
    ) -> Progress {
        let lines = |n: u32| u16::try_from(n).unwrap_or(u16::MAX);
        let (total, current) = match &self.file {
            Some(run) => {
                let current = match self.state {
                    JobState::Finished => run.lines,
                    JobState::Idle => run.next_line.min(run.lines),
                    JobState::Running | JobState::Paused => run.line_at(self.running_tag(kernel)),
                };
                (lines(run.lines), lines(current))
            }
            None => {
                let current = match self.state {
                    // Nothing runs: no program, or an upload not complete (`NL` then counts
                    // the lines stored so far).
                    _ if !store.is_complete() => 0,
                    JobState::Finished => store.len(),
                    // What `start` will run first.
                    JobState::Idle if self.next_line > store.len() => 1,
                    JobState::Idle => self.next_line,
                    JobState::Running | JobState::Paused => program_line(self.running_tag(kernel)),
                };
                (store.len(), current)
            }
        };
        Progress {
            elapsed_s: self.elapsed_s,
            estimated_s: libm::roundf(self.estimated_s) as u32,
            total_lines: total,
            current_line: current,
        }
    }
}

/// A program line from a kernel tag (program lines are at most [`program::MAX_LINES`]).
fn program_line(tag: u32) -> u16 {
    u16::try_from(tag).unwrap_or(u16::MAX)
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
    let mut buf = [0u8; program::MAX_LINE_LEN];
    for index in from.max(1)..=store.len() {
        let len = store
            .read(index, &mut buf)
            .map_err(|_| JobError::Syntax { line: index })?;
        let mut line = Line::empty();
        line.parse_in(buf.get(..len).unwrap_or(&[]))
            .map_err(|_| JobError::Syntax { line: index })?;
        if !estimate.line(&line) {
            break;
        }
    }
    Ok(estimate.seconds())
}
