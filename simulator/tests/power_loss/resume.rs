//! The resume turns of the power-loss campaign (`M413`, `M1000`): a stored job cut by a kill
//! and resumed after a restart. See the campaign's description at the top of the test.

use std::path::Path;
use std::time::{Duration, Instant};

use forja_app::controller::store::{RESUME_RECORD, ResumeRecord};
use forja_drivers::storage::FlashRecordStorage;
use forja_hal_abstraction::program::{digest_line, digest_start};
use forja_hal_abstraction::storage::RecordStorage as _;
use forja_protocol::frame::{Action, ClientMessage, Progress};
use forja_sim_hal::state::{SETTINGS_FLASH_LEN, SettingsFlash};
use nix::unistd::Pid;

use super::{Answer, Host, Reply, Rng, Sent, Sim, TIMEOUT, frame, kill_after, start_refused};

/// A machine position: X, Y, Z in tenths of a micrometre (1e-4 mm), as frame 51 gives them.
type Point = [i64; 3];

/// 1 mm in the units of [`Point`].
const MM: i64 = 10_000;

/// Motion lines of a resume program: about a minute of the machine's time, several
/// checkpoints.
const MOVES: usize = 100;

/// A job cut after a checkpoint is cut no sooner than this many seconds (of virtual time)
/// into its run: after the first checkpoint of the run but the one at its start (due 10 s
/// after it), with a few seconds to spare.
const FIRST_CUT_S: u32 = 15;

/// When a run is cut.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Cut {
    /// A random few milliseconds (wall time: at most 1.5 s of the machine's) after the run's
    /// first record is seen in the flash: as a rule before its first periodic checkpoint, so
    /// that the job resumes from the record of the run's start.
    Early,
    /// A random few milliseconds after frame 52 reports this many seconds of the run
    /// (at least [`FIRST_CUT_S`]): after a checkpoint.
    After(u32),
}

impl Cut {
    /// A cut for a run that frame 52 estimates at `estimated_s`: one in four early, the others
    /// after a checkpoint and well before the end (`None` when the run is too short for
    /// that).
    fn draw(estimated_s: u32, rng: &mut Rng) -> Option<Self> {
        let last = estimated_s * 7 / 10;
        if rng.range(0, 3) == 0 {
            Some(Self::Early)
        } else {
            (last > FIRST_CUT_S)
                .then(|| Self::After(rng.range(u64::from(FIRST_CUT_S), u64::from(last)) as u32))
        }
    }
}

/// How far a position frame 51 reports may lie from the program's path: a few steps of X or
/// Y (80 steps/mm), for the axes sampled one after another while they step.
const PATH_TOLERANCE_MM: f64 = 0.05;

/// The record must name every line that had finished this long before the cut (virtual
/// seconds): the checkpoint period (10 s), the settling of the step queue and the one-second
/// resolution of frame 52's elapsed time, with room to spare.
const RECORD_LAG_S: u32 = 14;

/// A stored program whose every motion line moves X forward: where the machine is along X
/// tells which lines have finished.
struct Program {
    /// The lines, line 1 first.
    lines: Vec<String>,
    /// Where the machine is once each line has run: `ends[0]` is the start (home), `ends[k]`
    /// the end of line `k`.
    ends: Vec<Point>,
    /// The digest the firmware keeps of it ([`forja_hal_abstraction::program::digest_line`]).
    digest: u32,
}

/// `v` (a multiple of 0.1 mm) in mm, as G-code.
fn mm(v: i64) -> String {
    format!("{:.1}", v as f64 / MM as f64)
}

impl Program {
    /// A program starting at `home`: units and distance mode, a rapid to X20 Y20 Z90, then
    /// [`MOVES`] feed moves zigzagging in Y while X rises 0.5 or 1 mm a line, in blocks of
    /// relative (`G91`) and absolute (`G90`) lines, with feed changes and, from the middle on,
    /// a work offset (`G92`); the last block is relative, so that a resume that replays the
    /// modal state or the offset wrongly ends elsewhere.
    fn new(home: Point, rng: &mut Rng) -> Self {
        let start = [20 * MM, 20 * MM, 90 * MM];
        let mut lines = vec![
            "G21".to_string(),
            "G90".to_string(),
            format!("G0 X{} Y{} Z{}", mm(start[0]), mm(start[1]), mm(start[2])),
            format!("G1 F{}", rng.range(12, 18) * 100),
        ];
        let mut ends = vec![home, home, home, start, start];
        let mut at = start;
        let mut relative = true;
        let mut up = true;
        let mut moves = 0;
        // Work coordinates are machine coordinates less `shift` (X, Y), once `G92` has set it.
        let mut shift = [0, 0];
        let mut offset = false;
        while moves < MOVES || relative {
            lines.push(if relative { "G91" } else { "G90" }.to_string());
            ends.push(at);
            if !relative && !offset && moves >= MOVES / 3 {
                offset = true;
                let work = [0, 1].map(|_| rng.range(0, 40) as i64 * MM / 2);
                lines.push(format!("G92 X{} Y{}", mm(work[0]), mm(work[1])));
                ends.push(at);
                shift = [at[0] - work[0], at[1] - work[1]];
            }
            for _ in 0..rng.range(4, 12) {
                let dx = rng.range(1, 2) as i64 * MM / 2;
                let y = if up {
                    20 * MM + rng.range(8, 24) as i64 * MM / 2
                } else {
                    20 * MM
                };
                up = !up;
                let to = [at[0] + dx, y, at[2]];
                let mut text = if relative {
                    format!("G1 X{} Y{}", mm(dx), mm(to[1] - at[1]))
                } else {
                    format!("G1 X{} Y{}", mm(to[0] - shift[0]), mm(to[1] - shift[1]))
                };
                if rng.range(0, 4) == 0 {
                    text.push_str(&format!(" F{}", rng.range(9, 18) * 100));
                }
                lines.push(text);
                ends.push(to);
                at = to;
                moves += 1;
            }
            relative = !relative;
        }
        let total = lines.len() as u16;
        let mut digest = digest_start(total);
        for (i, text) in lines.iter().enumerate() {
            digest = digest_line(digest, i as u16 + 1, text.as_bytes());
        }
        Self {
            lines,
            ends,
            digest,
        }
    }

    fn total(&self) -> u16 {
        self.lines.len() as u16
    }

    /// Where the program ends.
    fn end(&self) -> Point {
        self.ends[self.ends.len() - 1]
    }

    /// The lines certainly finished with the machine at `p` on the program's path: every line
    /// that ends at or before `p` along X.
    fn done_at(&self, p: Point) -> u16 {
        (self.ends.partition_point(|e| e[0] <= p[0]) - 1) as u16
    }

    /// The path the machine follows from a start at home (`from == 0`) or from a resume after
    /// line `from`: the program's lines after it, reached from home as `M1000` goes, X and Y
    /// first at the height of home (which is above the program), then Z down.
    fn path(&self, from: u16) -> Vec<Point> {
        let home = self.ends[0];
        let at = self.ends[usize::from(from)];
        let mut path = vec![home];
        if from > 0 {
            path.push([at[0], at[1], home[2]]);
        }
        path.extend_from_slice(&self.ends[usize::from(from)..]);
        path
    }

    /// The record of this program, if `r` is one.
    fn ours(&self, r: Option<ResumeRecord>) -> Option<u16> {
        r.filter(|r| r.digest == self.digest && r.total == self.total())
            .map(|r| r.done)
    }
}

/// How far `p` lies from the segments of `path` whose X range holds it, mm.
fn off_path(path: &[Point], p: Point) -> f64 {
    let tolerance = (PATH_TOLERANCE_MM * MM as f64) as i64;
    let mm = |v: i64| v as f64 / MM as f64;
    path.windows(2)
        .filter(|s| {
            let (lo, hi) = (s[0][0].min(s[1][0]), s[0][0].max(s[1][0]));
            lo - tolerance <= p[0] && p[0] <= hi + tolerance
        })
        .map(|s| {
            let a: [f64; 3] = core::array::from_fn(|i| mm(s[0][i]));
            let d: [f64; 3] = core::array::from_fn(|i| mm(s[1][i]) - a[i]);
            let q: [f64; 3] = core::array::from_fn(|i| mm(p[i]) - a[i]);
            let len2: f64 = d.iter().map(|v| v * v).sum();
            let t = if len2 > 0.0 {
                (q.iter().zip(&d).map(|(q, d)| q * d).sum::<f64>() / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            q.iter()
                .zip(&d)
                .map(|(q, d)| (q - t * d).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .fold(f64::INFINITY, f64::min)
}

/// The resume record the state file holds, read as the firmware reads it; `Err` when the
/// settings' flash cannot be read as a store (a copy caught in the middle of a write).
fn record_in(state: &Path) -> Result<Option<ResumeRecord>, String> {
    use std::os::unix::fs::FileExt as _;
    let file = std::fs::File::open(state).map_err(|e| e.to_string())?;
    let mut bytes = vec![0u8; SETTINGS_FLASH_LEN];
    file.read_exact_at(&mut bytes, forja_sim_hal::state::HEADER_LEN as u64)
        .map_err(|e| e.to_string())?;
    let flash = SettingsFlash::with_contents(bytes, None);
    let mut storage = FlashRecordStorage::<SettingsFlash>::new(flash, 0..SETTINGS_FLASH_LEN as u32)
        .map_err(|e| format!("{e:?}"))?;
    let mut buf = [0u8; 16];
    match storage.read(RESUME_RECORD, &mut buf) {
        Ok(Some(n)) => Ok(ResumeRecord::decode(&buf[..n])),
        Ok(None) => Ok(None),
        Err(e) => Err(format!("{e:?}")),
    }
}

/// What frames 51 and 52 say at one moment.
#[derive(Debug, Clone, Copy)]
struct Look {
    at: Point,
    progress: Progress,
}

/// Ask for frames 51 and 52 and wait for both; `None` once the link is closed.
fn look(host: &mut Host) -> Option<Look> {
    let mut bytes = frame(ClientMessage::Request { message_type: 51 });
    bytes.extend(frame(ClientMessage::Request { message_type: 52 }));
    host.send(&bytes);
    let deadline = Instant::now() + TIMEOUT;
    let (mut at, mut progress) = (None, None);
    while at.is_none() || progress.is_none() {
        match host.next(deadline)? {
            Reply::Positions(p) => at = Some(p),
            Reply::Progress(p) => progress = Some(p),
            _ => {}
        }
    }
    Some(Look {
        at: at?,
        progress: progress?,
    })
}

/// Send a G-code line and return the text lines that answer it, up to and with its `ok`
/// (without the `echo:busy: processing` of a long command); `None` if the link closes or
/// nothing comes in time.
fn command(host: &mut Host, line: &str) -> Option<Vec<String>> {
    host.send(format!("{line}\n").as_bytes());
    collect_until_ok(host)
}

fn collect_until_ok(host: &mut Host) -> Option<Vec<String>> {
    let deadline = Instant::now() + TIMEOUT;
    let mut lines = Vec::new();
    loop {
        if let Reply::Text(t) = host.next(deadline)?
            && t != "echo:busy: processing"
        {
            let ok = t == "ok" || t.starts_with("ok ");
            lines.push(t);
            if ok {
                return Some(lines);
            }
        }
    }
}

/// One resume turn's findings, for the campaign.
#[derive(Default)]
pub struct Turn {
    /// The settings frames the turn amounts to (`M413` stores `power_loss_recovery`).
    pub sent: Sent,
    /// The program uploaded, and whether its upload was confirmed (frame 53).
    pub upload: Option<(Vec<String>, bool)>,
    /// What went wrong.
    pub failures: Vec<String>,
    /// What happened, counted.
    pub counts: Vec<&'static str>,
    /// Records of a job read from the flash during its run and checked against a later
    /// position, that named lines done (more than the run started after).
    pub records_checked: u32,
}

/// How a watched run ended, and what it showed.
struct Watched {
    /// The link closed (the kill).
    killed: bool,
    /// The job reached its last line at the program's end.
    finished: bool,
    /// Each look's elapsed time (frame 52, s) and the lines finished then (by position).
    done_by_time: Vec<(u32, u16)>,
    /// The last record of the program read during the run.
    last_record: Option<u16>,
}

/// A resume turn under way: where it works and what it has found.
struct Resume<'a> {
    state: &'a Path,
    context: &'a str,
    recovery: bool,
    rng: &'a mut Rng,
    found: Turn,
}

/// One resume turn on the state file `state`.
///
/// With `recovery` on: `M413 S1`, `G28`, a new program uploaded and started, the simulator
/// killed at a random moment after the first checkpoint of the run (or early); then, once
/// or twice (a second cut in the resumed run): a restart, `M1000` refused before homing
/// (`E187 not-homed`, nothing moves), `G28`, `M1000` accepted with frame 52 at the line after
/// the record the kill left; the last resumed run is watched to the program's end, after
/// which `M1000` has nothing to resume (`E186`).
///
/// With `recovery` off: `M413 S0`, after which `M1000` has nothing to resume; the same job,
/// cut the same way, leaves no record, and after a restart and `G28`, `M1000` is refused
/// (`E186 no-resume`) and nothing moves.
///
/// `must_refuse`: the program the file holds is incomplete or absent, and `Start` must refuse
/// it (checked first, as in the other turns), `known_lines` long.
pub fn turn(
    state: &Path,
    rng: &mut Rng,
    recovery: bool,
    must_refuse: bool,
    known_lines: usize,
    context: &str,
) -> Turn {
    let mut resume = Resume {
        state,
        context,
        recovery,
        rng,
        found: Turn::default(),
    };
    let sim = Sim::start(state);
    let host = sim.connect();
    resume.run(sim, host, must_refuse, known_lines);
    resume.found
}

impl Resume<'_> {
    fn fail(&mut self, what: String) {
        self.found
            .failures
            .push(format!("{}: {what}", self.context));
    }

    /// The turn, on a simulator just started; every simulator it starts is killed by its end.
    fn run(&mut self, mut sim: Sim, mut host: Host, must_refuse: bool, known_lines: usize) {
        if must_refuse && !start_refused(&mut host) {
            self.fail(format!(
                "Start ran a program of {known_lines} lines that is neither the old complete \
                 one nor the new one"
            ));
        }
        let switch = if self.recovery { "M413 S1" } else { "M413 S0" };
        match command(&mut host, switch) {
            Some(reply) if reply == ["ok"] => {
                let value = if self.recovery { "1" } else { "0" };
                self.found.sent.insert(
                    "power_loss_recovery",
                    vec![(value.to_string(), Answer::Stored)],
                );
            }
            reply => self.fail(format!("{switch} answered {reply:?}")),
        }
        if !self.recovery {
            self.refused_resume(&mut host, "186", "no-resume");
        }
        let Some(home_at) = self.home(&mut host) else {
            return sim.kill();
        };
        let program = Program::new(home_at, self.rng);
        let confirmed = self.upload(&mut host, &program);
        self.found.upload = Some((program.lines.clone(), confirmed));
        if !confirmed {
            return sim.kill();
        }
        host.send(&frame(ClientMessage::Action(Action::Start)));
        let Some(first) = look(&mut host) else {
            self.fail("the link closed after Start".into());
            return sim.kill();
        };
        let Some(first_cut) = Cut::draw(first.progress.estimated_s, self.rng) else {
            self.fail(format!(
                "the job is estimated at {} s, too short to be cut after a checkpoint",
                first.progress.estimated_s
            ));
            return sim.kill();
        };

        let mut base = 0u16;
        let mut cut = Some(first_cut);
        let mut cuts = 0;
        loop {
            let run = self.watch(&mut host, sim.pid(), &program, base, cut);
            if !run.killed {
                if run.finished {
                    self.finish(&mut host);
                }
                return sim.kill();
            }
            sim.kill();
            cuts += 1;
            // The flash as the cut left it: what the restart finds.
            let record = match record_in(self.state) {
                Ok(r) => r,
                Err(e) => return self.fail(format!("the resume record cannot be read: {e}")),
            };
            sim = Sim::start(self.state);
            host = sim.connect();
            if !self.recovery {
                if let Some(r) = record {
                    self.fail(format!(
                        "power-loss recovery is off, yet a resume record is kept: {r:?}"
                    ));
                }
                if self.home(&mut host).is_some() {
                    self.refused_resume(&mut host, "186", "no-resume");
                }
                self.found.counts.push("resume refused (recovery off)");
                return sim.kill();
            }
            let Some(r) = program.ours(record) else {
                self.fail(format!(
                    "no resume record of the job after the cut: {record:?}"
                ));
                return sim.kill();
            };
            self.check_record(&run, r, base, cut);

            // After the restart: refused before homing, then resumed at the record's next line.
            self.refused_resume(&mut host, "187", "not-homed");
            match self.home(&mut host) {
                Some(at) if at == program.ends[0] => {}
                Some(at) => self.fail(format!(
                    "G28 ends at {at:?}, not at {:?} as before",
                    program.ends[0]
                )),
                None => return sim.kill(),
            }
            let Some(progress) = self.resume(&mut host, r) else {
                return sim.kill();
            };
            self.found.counts.push(match (cuts, cut) {
                (1, Some(Cut::Early)) => "resumed after an early cut",
                (1, _) => "resumed",
                (_, Some(Cut::Early)) => "resumed again after an early cut",
                _ => "resumed again",
            });
            base = r;
            cut = if cuts < 2 && self.rng.range(0, 1) == 0 {
                Cut::draw(progress.estimated_s, self.rng)
            } else {
                None
            };
        }
    }

    /// The record `r` a cut left, after a run from line `base + 1`: never back from the run's
    /// start nor from what was read during the run, past the run's start after a checkpoint,
    /// and naming every line that had finished [`RECORD_LAG_S`] before the cut.
    fn check_record(&mut self, run: &Watched, r: u16, base: u16, cut: Option<Cut>) {
        let last_elapsed = run.done_by_time.last().map_or(0, |l| l.0);
        if r < base || run.last_record.is_some_and(|seen| r < seen) {
            self.fail(format!(
                "the record went back to {r} at the cut (run from {base}, {:?} read during \
                 it)",
                run.last_record
            ));
        }
        if matches!(cut, Some(Cut::After(_))) && r <= base {
            self.fail(format!(
                "cut {last_elapsed} s into the run, the record still says {r} (run from {base})"
            ));
        }
        let due = run
            .done_by_time
            .iter()
            .filter(|(e, _)| e + RECORD_LAG_S <= last_elapsed)
            .map(|l| l.1)
            .max()
            .unwrap_or(0);
        if r < due {
            self.fail(format!(
                "the record says {r} lines done, but {due} had finished more than \
                 {RECORD_LAG_S} s before the cut ({last_elapsed} s into the run)"
            ));
        }
    }

    /// `M1000` on a homed machine with the record of `r` lines done: `ok`, and frame 52 (asked
    /// for in the same write) at line `r + 1`. Returns that frame 52.
    fn resume(&mut self, host: &mut Host, r: u16) -> Option<Progress> {
        let mut bytes = b"M1000\n".to_vec();
        bytes.extend(frame(ClientMessage::Request { message_type: 52 }));
        host.send(&bytes);
        let reply = collect_until_ok(host);
        if reply.as_deref() != Some(&["ok".to_string()][..]) {
            self.fail(format!("M1000 answered {reply:?}"));
            return None;
        }
        let deadline = Instant::now() + TIMEOUT;
        let progress = loop {
            match host.next(deadline) {
                Some(Reply::Progress(p)) => break p,
                Some(_) => {}
                None => {
                    self.fail("no frame 52 after M1000".into());
                    return None;
                }
            }
        };
        if progress.current_line != u32::from(r) + 1 {
            self.fail(format!(
                "M1000 resumed at line {} but the record says lines 1..={r} were done",
                progress.current_line
            ));
        }
        Some(progress)
    }

    /// Watch a run of `program` started after line `base` (0: from the start) until the link
    /// closes or, without `cut`, the job reaches the program's end; with `cut`, kill the
    /// simulator (`pid`) when it says. At every look, the resume record is read from the
    /// flash first, then frames 51 and 52 are asked for: a record of the program read before a
    /// position must name only lines finished at that position, never go back, and change at
    /// most once per 10 s of the run. Every position must lie on the run's path, and frame 52
    /// must report the program's lines, from `base + 1` on, never going back. With recovery
    /// off, no record of the program may appear.
    fn watch(
        &mut self,
        host: &mut Host,
        pid: Pid,
        program: &Program,
        base: u16,
        cut: Option<Cut>,
    ) -> Watched {
        let path = program.path(base);
        let total = program.total();
        let mut killer = None;
        let mut done_by_time: Vec<(u32, u16)> = Vec::new();
        let mut last_line = base + 1;
        let mut records: Vec<u16> = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(120);
        let (killed, finished) = loop {
            let record = record_in(self.state).ok().flatten();
            let Some(look) = look(host) else {
                break (true, false);
            };
            let done = base.max(program.done_at(look.at));
            let p = look.progress;
            done_by_time.push((p.elapsed_s, done));
            if let Some(r) = program.ours(record) {
                if !self.recovery {
                    self.fail(format!(
                        "power-loss recovery is off, yet the job recorded line {r} done"
                    ));
                } else if r > done {
                    self.fail(format!(
                        "the resume record names lines 1..={r} done, but the machine, later, \
                         was at {:?} (1e-4 mm), where only lines 1..={done} have finished",
                        look.at
                    ));
                } else if r < base || records.last().is_some_and(|&last| r < last) {
                    self.fail(format!(
                        "the resume record went back to line {r} (run from {base})"
                    ));
                }
                if records.last() != Some(&r) {
                    records.push(r);
                    if self.recovery && r > base {
                        self.found.records_checked += 1;
                    }
                }
            }
            let off = off_path(&path, look.at);
            if off > PATH_TOLERANCE_MM {
                self.fail(format!(
                    "the machine is at {:?} (1e-4 mm), {off:.3} mm off the path of the run \
                     from line {}",
                    look.at,
                    base + 1
                ));
            }
            let line = p.current_line as u16;
            if p.total_lines != u32::from(total) || line < last_line || line > total {
                self.fail(format!(
                    "frame 52 reports line {line} of {} after line {last_line} of {total}",
                    p.total_lines
                ));
            }
            last_line = last_line.max(line);
            let due = match cut {
                Some(Cut::Early) => !self.recovery || !records.is_empty(),
                Some(Cut::After(t)) => p.elapsed_s >= t,
                None => false,
            };
            if due && killer.is_none() {
                let delay = Duration::from_micros(self.rng.range(0, 30_000));
                killer = Some(kill_after(pid, delay));
            }
            if line == total && look.at == program.end() && killer.is_none() {
                break (false, true);
            }
            if Instant::now() > deadline {
                self.fail(format!(
                    "the job did not end: frame 52 at line {line} of {total}"
                ));
                break (false, false);
            }
            if self.found.failures.len() >= 5 {
                break (false, false);
            }
        };
        if let Some(k) = killer {
            k.join().expect("the killer thread");
        }
        // At most one record at the start, then one per 10 s of the run (flash wear); frame
        // 52's elapsed time is whole seconds, rounded down.
        let last_elapsed = done_by_time.last().map_or(0, |l| l.0);
        if records.len() as u32 > 1 + (last_elapsed + 1) / 10 {
            self.fail(format!(
                "{} resume records in {last_elapsed} s of run: {records:?} (one per 10 s)",
                records.len()
            ));
        }
        Watched {
            killed,
            finished,
            done_by_time,
            last_record: records.last().copied(),
        }
    }

    /// `M1000` refused with `code`: the answer is `echo:E<code> <name>` then `ok`, and the
    /// machine has neither moved nor started a job a moment later.
    fn refused_resume(&mut self, host: &mut Host, code: &str, name: &str) {
        let Some(before) = look(host) else {
            return self.fail("the link closed".into());
        };
        let expected = [format!("echo:E{code} {name}"), "ok".to_string()];
        match command(host, "M1000") {
            Some(reply) if reply == expected => {}
            reply => self.fail(format!("M1000 answered {reply:?}, expected {expected:?}")),
        }
        // 20 ms of wall time: a second of the machine's time, had it started to move.
        std::thread::sleep(Duration::from_millis(20));
        match look(host) {
            Some(after) if after.at == before.at && after.progress == before.progress => {}
            after => self.fail(format!(
                "a refused M1000 moved the machine or started the job: before {before:?}, \
                 after {after:?}"
            )),
        }
    }

    /// Home with `G28` and return where the machine ends.
    fn home(&mut self, host: &mut Host) -> Option<Point> {
        match command(host, "G28") {
            Some(reply) if reply == ["ok"] => {}
            reply => {
                self.fail(format!("G28 answered {reply:?}"));
                return None;
            }
        }
        look(host).map(|l| l.at)
    }

    /// Upload `program` (frames 03) and wait for its confirmation (frame 53).
    fn upload(&mut self, host: &mut Host, program: &Program) -> bool {
        let total = program.total();
        let mut bytes = Vec::new();
        for (i, text) in program.lines.iter().enumerate() {
            bytes.extend(frame(ClientMessage::LoadLine {
                index: i as u16 + 1,
                text,
                total,
            }));
        }
        host.send(&bytes);
        let deadline = Instant::now() + TIMEOUT;
        loop {
            match host.next(deadline) {
                Some(Reply::Confirm) => return true,
                Some(Reply::Error(code, detail)) => {
                    self.fail(format!("the upload was refused: E{code} {detail}"));
                    return false;
                }
                Some(_) => {}
                None => {
                    self.fail("the upload was not confirmed".into());
                    return false;
                }
            }
        }
    }

    /// The job has reached its end: `M1000` has nothing left to resume (`job-busy` while the
    /// job winds up, then `E186 no-resume`), and the flash keeps no record.
    fn finish(&mut self, host: &mut Host) {
        let expected = ["echo:E186 no-resume".to_string(), "ok".to_string()];
        let mut reply = None;
        for _ in 0..200 {
            reply = command(host, "M1000");
            match &reply {
                Some(r) if r[0].contains("job-busy") => {
                    std::thread::sleep(Duration::from_millis(2));
                }
                _ => break,
            }
        }
        if reply.as_ref() != Some(&expected.to_vec()) {
            self.fail(format!(
                "at the program's end, M1000 answered {reply:?}, expected {expected:?}"
            ));
        }
        match record_in(self.state) {
            Ok(None) => {}
            r => self.fail(format!(
                "at the program's end, the flash keeps a resume record: {r:?}"
            )),
        }
        self.found.counts.push("job ran to its end");
    }
}
