//! The grbl sender: character counting, a sans-IO state machine (smoltcp's shape).
//!
//! The sender streams G-code to a controller that speaks grbl 1.1 (`docs/protocol.md` §9) the
//! way grbl's own `stream.py -s` and CNCjs do. Like [`crate::streamer::Streamer`] it never reads
//! a clock or touches a link; the caller moves bytes:
//!
//! ```text
//! loop {
//!     sender.transmit(now, &mut out);        // 0x18, `?`, lines, as the count allows
//!     link.write_all(&out);
//!     for each line received:
//!         sender.receive(now, line);         // `ok`, `error:N`, `ALARM:N`, `<…>`, `[MSG:…]`
//!     while let Some(event) = sender.next_event() { … }
//!     // call again when a line arrives, or at `poll_at()` at the latest
//! }
//! ```
//!
//! # The algorithm
//!
//! **Reset.** The sender first sends `0x18` (grbl's soft reset, which also takes a Forja link
//! into the grbl dialect) and sends nothing else until the banner `Grbl 1.1h ['$' for help]`
//! comes; without one within [`Config::banner_timeout`] it resets again, and gives up after
//! [`Config::reset_attempts`]. Answers that arrive before the banner belong to lines of an
//! earlier session and are dropped.
//!
//! **Sizing.** With [`Config::report_buffer`], `$10=3` goes next (status reports then carry
//! `Bf:`); with [`Config::size_from_report`], once that is answered, one `?`: the second number
//! of the report's `Bf:`, the free bytes of an empty receive buffer, becomes the buffer size
//! counted against (768 on Forja, the read-ahead window). Without `Bf:` in the report, or
//! without a report within [`Config::status_timeout`], [`Config::rx_buffer_bytes`] stays
//! (grbl's 128).
//!
//! **Character counting.** Each line is sent with one `\n`; the sender keeps the lengths of the
//! lines sent and not yet answered, and sends the next line only while their sum with it stays
//! within the buffer size. Every `ok` or `error:N` answers the oldest line in flight: grbl
//! answers every line, in order, exactly once. The controller's receive buffer can then never
//! overflow, and it always has room for the realtime bytes. A line longer than the whole buffer
//! is sent alone, when nothing else is in flight ([`Stats::oversized`]).
//!
//! **Lines.** [`GrblSender::push`] cleans a line as grbl senders do (CNCjs, UGS): `(…)` and
//! `;` comments and the blanks around the rest are dropped, and a line left empty is not sent
//! (the Forja decoder drops empty lines without an answer, which would break the count).
//!
//! **Answers.** Each line's answer is kept ([`GrblSender::answers`]). An `error:N` is counted
//! and reported ([`Event::Refused`]); the stream goes on, the caller decides whether to stop.
//! An `ALARM:N` stops the stream ([`Phase::Alarm`]): no line is sent after it, the answers of
//! the lines in flight are still recorded.
//!
//! **Realtime bytes** ([`GrblSender::realtime`]: `?`, `!`, `~`, the overrides) go out at the
//! next [`GrblSender::transmit`], ahead of any line, whatever the count: they never enter the
//! receive buffer, so they are never counted. With [`Config::status_interval`] the sender
//! polls `?` itself, one at a time (another only after the report, or after
//! [`Config::status_timeout`]), behind the lines of the same transmit, when the buffer is as
//! full as the count allows. The time from each `?` to its report is measured
//! ([`Stats::max_status_latency`]), and apart for a `?` sent while the buffer was full
//! ([`Stats::max_full_status_latency`]): the controller's promise that realtime bytes act at
//! once however many lines wait.
//!
//! **Soft reset** ([`GrblSender::soft_reset`]) drops the lines in flight, which the controller
//! discards without an answer ([`Answer::Dropped`]), and clears the count. A job that had begun
//! ends there ([`Phase::Stopped`] once the banner comes). A banner the sender did not ask for
//! (the controller restarted) while lines were unanswered ends the job too
//! ([`Event::Restarted`]).
//!
//! **Holds.** A `[MSG:…]` that asks for a cycle start (`[MSG:Change to tool T1, then cycle
//! start]`, a Forja `M6`) is [`Event::AwaitingCycleStart`]; the caller tells the operator and
//! sends `~` when told to ([`Realtime::CycleStart`]).

use std::borrow::Cow;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

use forja_protocol::gcode::MAX_LINE_LEN;
use forja_protocol::grbl::{Realtime, StatusText};

/// grbl's receive buffer, bytes: what a sender counts against unless told otherwise.
pub const GRBL_RX_BUFFER: usize = 128;

/// The line that makes status reports carry `Bf:` (bit 0: `MPos`, bit 1: the buffer state).
pub const BUFFER_REPORT_LINE: &str = "$10=3";

/// The sender's settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Config {
    /// Bytes of the controller's receive buffer counted against, until a report's `Bf:` says
    /// otherwise ([`Config::size_from_report`]).
    pub rx_buffer_bytes: usize,
    /// After the banner, send [`BUFFER_REPORT_LINE`] so that status reports carry `Bf:`. On
    /// grbl the setting is stored; on Forja it is the link's.
    pub report_buffer: bool,
    /// After the banner (and `$10=3`), ask `?` once and count against the free bytes its `Bf:`
    /// reports.
    pub size_from_report: bool,
    /// Poll `?` this often once the banner came (`None`: only when the caller asks).
    pub status_interval: Option<Duration>,
    /// A `?` not answered with a report within this long is taken as lost: another may go.
    pub status_timeout: Duration,
    /// `0x18` is sent again after this long without the banner.
    pub banner_timeout: Duration,
    /// The sender gives up after this many `0x18` without a banner.
    pub reset_attempts: u32,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            rx_buffer_bytes: GRBL_RX_BUFFER,
            report_buffer: false,
            size_from_report: true,
            status_interval: Some(Duration::from_millis(250)),
            status_timeout: Duration::from_secs(1),
            banner_timeout: Duration::from_millis(2500),
            reset_attempts: 3,
        }
    }
}

/// Where the sender is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// `0x18` sent; waiting for the banner.
    Resetting,
    /// Sending `$10=3` and reading `Bf:` from a `?`.
    Sizing,
    /// Sending lines as the count allows.
    Streaming,
    /// [`GrblSender::finish`] was called and every line was answered.
    Done,
    /// An `ALARM:N` came: no more lines are sent.
    Alarm,
    /// The caller reset the controller during the job: no more lines are sent.
    Stopped,
    /// No banner came, or the controller restarted during the job: no more lines are sent.
    Failed,
}

/// How the controller answered a line.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Answer {
    /// `ok`.
    Ok,
    /// `error:N`: the line was refused and had no effect.
    Error(u8),
    /// The line was in the controller's buffer at a soft reset, which discards it unanswered.
    Dropped,
}

/// Something the caller should know about.
#[derive(Clone, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Event {
    /// The banner came (and the buffer was sized): lines are being sent.
    Ready {
        /// The buffer size counted against.
        rx_buffer_bytes: usize,
    },
    /// The controller refused a line (`error:N`); the stream goes on.
    Refused {
        /// The line's number: 1 is the first line pushed and sent.
        number: u32,
        /// grbl's error number.
        code: u8,
        /// The line as sent.
        text: String,
    },
    /// `ALARM:N`: the machine stopped; no more lines are sent.
    Alarm {
        /// grbl's alarm number.
        code: u8,
    },
    /// A `[MSG:…]` for the operator (its text).
    Message(String),
    /// A `[MSG:…]` that asks for a cycle start (an `M6` tool change): the machine holds until
    /// `~` comes. Its text.
    AwaitingCycleStart(String),
    /// The controller restarted (a banner not asked for) with lines unanswered.
    Restarted,
    /// No banner after [`Config::reset_attempts`] resets.
    NoBanner,
    /// Every line was answered.
    Done,
}

/// Counters, for the summary and for measurements.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Bytes of lines handed to the link (`$10=3` included).
    pub bytes_sent: u64,
    /// Lines handed to the link (`$10=3` included).
    pub lines_sent: u64,
    /// Realtime bytes handed to the link (`0x18` and the sender's own `?` included).
    pub realtime_sent: u64,
    /// `ok` answers to pushed lines.
    pub oks: u64,
    /// `error:N` answers to pushed lines.
    pub errors: u64,
    /// `ok`/`error:N` with nothing in flight, or before the banner (an earlier session's).
    pub stray_answers: u64,
    /// The most bytes in flight at any time.
    pub max_in_flight_bytes: usize,
    /// The most lines in flight at any time.
    pub max_in_flight_lines: usize,
    /// Lines longer than the whole buffer, sent alone.
    pub oversized: u64,
    /// `0x18` sent.
    pub resets: u64,
    /// `?` sent.
    pub status_requests: u64,
    /// Status reports received.
    pub status_reports: u64,
    /// `?` taken as lost ([`Config::status_timeout`]).
    pub status_lost: u64,
    /// The longest time from a `?` to its report.
    pub max_status_latency: Duration,
    /// Reports to a `?` sent while the buffer was full (the count held the next line back).
    pub full_status_reports: u64,
    /// The longest time from a `?` sent while the buffer was full to its report.
    pub max_full_status_latency: Duration,
}

/// Why a line cannot be pushed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum PushError {
    /// [`GrblSender::finish`] was called.
    Finished,
    /// Once cleaned, the line is longer than [`MAX_LINE_LEN`] bytes.
    TooLong,
    /// The line holds a byte that cannot go in a grbl line: a realtime character (`?`, `!`,
    /// `~`), which the controller would take out and act on, a control byte or non-ASCII.
    Character(u8),
}

impl std::fmt::Display for PushError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Finished => f.write_str("the job is already complete"),
            Self::TooLong => write!(f, "the line is longer than {MAX_LINE_LEN} bytes"),
            Self::Character(b) if b.is_ascii_graphic() => write!(
                f,
                "the line holds '{}', a realtime command in the grbl dialect",
                char::from(*b)
            ),
            Self::Character(b) => write!(f, "the line holds the byte 0x{b:02X}"),
        }
    }
}

impl std::error::Error for PushError {}

/// A line as grbl senders send it: `(…)` and `;` comments and the blanks around the rest
/// dropped (empty for a blank or comment-only line). A `(` without its `)` is kept, for the
/// controller to refuse.
pub fn clean_line(text: &str) -> Cow<'_, str> {
    if !text.contains('(') {
        return Cow::Borrowed(text.split(';').next().unwrap_or_default().trim());
    }
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(at) = rest.find(['(', ';']) {
        let close = rest[at..].find(')').filter(|_| rest[at..].starts_with('('));
        let Some(close) = close else {
            // `;`, or a `(` never closed: the rest up to a `;` is kept.
            rest = rest.split(';').next().unwrap_or_default();
            break;
        };
        out.push_str(rest[..at].trim_end());
        rest = &rest[at + close + 1..];
        // A word after the comment keeps one blank before it.
        if !out.is_empty() && rest.starts_with([' ', '\t']) {
            out.push(' ');
            rest = rest.trim_start();
        }
    }
    out.push_str(rest);
    Cow::Owned(out.trim().to_string())
}

/// Whether a `[MSG:…]` text asks for a cycle start (`~`).
fn asks_cycle_start(text: &str) -> bool {
    text.to_ascii_lowercase().ends_with("cycle start")
}

/// A line in flight: a pushed line's index, or `None` for the sender's own `$10=3`.
#[derive(Clone, Copy, Debug)]
struct Flight {
    line: Option<usize>,
    len: usize,
}

/// Where sizing is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sizing {
    /// `$10=3` to send.
    Mask,
    /// `$10=3` sent, not answered.
    MaskSent,
    /// `?` to send.
    Ask,
    /// `?` sent at this time.
    Asked(Instant),
}

/// The sans-IO grbl sender. See the [module documentation](self).
#[derive(Debug)]
pub struct GrblSender {
    config: Config,
    rx_buffer: usize,
    /// The pushed lines, cleaned, without terminator.
    lines: Vec<Box<str>>,
    answers: Vec<Option<Answer>>,
    /// The next line to send.
    next: usize,
    finished: bool,
    in_flight: VecDeque<Flight>,
    in_flight_bytes: usize,
    /// Realtime commands of the caller, for the next transmit.
    realtime: Vec<Realtime>,
    phase: Phase,
    /// The phase to take after the banner of a reset made during the job.
    after_banner: Option<Phase>,
    reset_due: bool,
    reset_sent_at: Option<Instant>,
    reset_attempts: u32,
    sizing: Sizing,
    /// When the oldest `?` not yet answered was sent.
    /// When the oldest `?` not yet answered was sent, and whether the buffer was full then.
    status_pending: Option<(Instant, bool)>,
    last_poll: Option<Instant>,
    last_status: Option<String>,
    stats: Stats,
    events: VecDeque<Event>,
}

impl GrblSender {
    /// A sender with no lines, about to reset the controller.
    pub fn new(config: Config) -> Self {
        Self {
            config,
            rx_buffer: config.rx_buffer_bytes.max(1),
            lines: Vec::new(),
            answers: Vec::new(),
            next: 0,
            finished: false,
            in_flight: VecDeque::new(),
            in_flight_bytes: 0,
            realtime: Vec::new(),
            phase: Phase::Resetting,
            after_banner: None,
            reset_due: true,
            reset_sent_at: None,
            reset_attempts: 0,
            sizing: Sizing::Ask,
            status_pending: None,
            last_poll: None,
            last_status: None,
            stats: Stats::default(),
            events: VecDeque::new(),
        }
    }

    /// Add a line to send, cleaned by [`clean_line`]. Returns its number (1 for the first line
    /// pushed), or `None` when nothing is left to send (a blank or comment-only line).
    pub fn push(&mut self, text: &str) -> Result<Option<u32>, PushError> {
        if self.finished {
            return Err(PushError::Finished);
        }
        let line = clean_line(text);
        if line.is_empty() {
            return Ok(None);
        }
        if line.len() > MAX_LINE_LEN {
            return Err(PushError::TooLong);
        }
        let bad = |b: &u8| {
            !(b.is_ascii_graphic() || *b == b' ' || *b == b'\t')
                || Realtime::from_byte(*b).is_some()
        };
        if let Some(&b) = line.as_bytes().iter().find(|b| bad(b)) {
            return Err(PushError::Character(b));
        }
        self.lines.push(line.into_owned().into_boxed_str());
        self.answers.push(None);
        Ok(Some(self.lines.len() as u32))
    }

    /// No more lines: [`Phase::Done`] follows the answer of the last one.
    pub fn finish(&mut self) {
        self.finished = true;
        self.check_done();
    }

    /// Send a realtime command at the next [`transmit`](Self::transmit), ahead of any line and
    /// never counted. [`Realtime::SoftReset`] is [`soft_reset`](Self::soft_reset).
    pub fn realtime(&mut self, command: Realtime) {
        if command == Realtime::SoftReset {
            self.soft_reset();
        } else {
            self.realtime.push(command);
        }
    }

    /// Reset the controller (`0x18`): the lines in flight are dropped by the controller,
    /// unanswered, and the count cleared. Before the first line of the job is sent (after
    /// [`Event::NoBanner`] too), the sender starts over (banner, sizing); once a line was sent,
    /// nothing more is ([`Phase::Stopped`]), unless the job was done ([`Phase::Done`] stays).
    pub fn soft_reset(&mut self) {
        self.drop_in_flight();
        self.realtime.clear();
        // A second reset before the banner keeps what the first decided.
        if self.phase != Phase::Resetting {
            self.after_banner = match self.phase {
                Phase::Done => Some(Phase::Done),
                _ if self.next > 0 => Some(Phase::Stopped),
                _ => None,
            };
        }
        self.phase = Phase::Resetting;
        self.reset_due = true;
        self.reset_attempts = 0;
        self.status_pending = None;
    }

    /// Where the sender is.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// Whether nothing more will be sent but realtime bytes: done, alarm, stopped or failed.
    pub fn is_over(&self) -> bool {
        matches!(
            self.phase,
            Phase::Done | Phase::Alarm | Phase::Stopped | Phase::Failed
        )
    }

    /// The counters.
    pub fn stats(&self) -> Stats {
        self.stats
    }

    /// The buffer size counted against now.
    pub fn rx_buffer_bytes(&self) -> usize {
        self.rx_buffer
    }

    /// Count against `bytes` from now on (at least 1).
    pub fn set_rx_buffer_bytes(&mut self, bytes: usize) {
        self.rx_buffer = bytes.max(1);
    }

    /// Bytes in flight: of lines sent and not yet answered, each with its `\n`.
    pub fn in_flight_bytes(&self) -> usize {
        self.in_flight_bytes
    }

    /// Lines in flight.
    pub fn in_flight_lines(&self) -> usize {
        self.in_flight.len()
    }

    /// How many lines were pushed.
    pub fn pushed(&self) -> usize {
        self.lines.len()
    }

    /// How many pushed lines were sent.
    pub fn sent(&self) -> usize {
        self.next
    }

    /// The line numbered `number` (1-based), as sent.
    pub fn line(&self, number: u32) -> Option<&str> {
        let index = (number as usize).checked_sub(1)?;
        self.lines.get(index).map(|l| &**l)
    }

    /// Each pushed line's answer, in order (`None`: not sent or not answered yet).
    pub fn answers(&self) -> &[Option<Answer>] {
        &self.answers
    }

    /// The last status report received, without its `<` `>`.
    pub fn last_status(&self) -> Option<&str> {
        self.last_status.as_deref()
    }

    /// The next event, if any.
    pub fn next_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// When [`transmit`](Self::transmit) must be called next at the latest, if anything is
    /// timed (a banner awaited, a status poll, a `?` awaited).
    pub fn poll_at(&self) -> Option<Instant> {
        let mut at: Option<Instant> = None;
        let mut take = |t: Instant| at = Some(at.map_or(t, |a| a.min(t)));
        match self.phase {
            Phase::Resetting => {
                if let Some(t) = self.reset_sent_at {
                    take(t + self.config.banner_timeout);
                }
                return at;
            }
            Phase::Failed => return None,
            Phase::Sizing => {
                if let Sizing::Asked(t) = self.sizing {
                    take(t + self.config.status_timeout);
                }
            }
            _ => {}
        }
        if let (Some(interval), Some(t)) = (self.config.status_interval, self.last_poll) {
            take(t + interval);
        }
        if let Some((t, _)) = self.status_pending {
            take(t + self.config.status_timeout);
        }
        at
    }

    /// Append to `out` what should be written to the link now: a reset, realtime bytes, then
    /// lines as the count allows. Returns how many pushed lines were appended.
    pub fn transmit(&mut self, now: Instant, out: &mut Vec<u8>) -> usize {
        if self.phase == Phase::Resetting {
            self.transmit_reset(now, out);
            return 0;
        }
        for command in std::mem::take(&mut self.realtime) {
            self.send_realtime(now, command, out);
        }
        if self.phase == Phase::Sizing {
            self.transmit_sizing(now, out);
        }
        if matches!(self.phase, Phase::Sizing | Phase::Failed) {
            return 0;
        }
        let sent = if self.phase == Phase::Streaming {
            self.transmit_lines(out)
        } else {
            0
        };
        self.poll_status(now, out);
        sent
    }

    fn transmit_reset(&mut self, now: Instant, out: &mut Vec<u8>) {
        let due = self.reset_due
            || self
                .reset_sent_at
                .is_some_and(|t| now.saturating_duration_since(t) >= self.config.banner_timeout);
        if !due {
            return;
        }
        if self.reset_attempts >= self.config.reset_attempts {
            self.phase = Phase::Failed;
            self.events.push_back(Event::NoBanner);
            return;
        }
        out.push(Realtime::SoftReset.byte());
        self.reset_due = false;
        self.reset_sent_at = Some(now);
        self.reset_attempts += 1;
        self.stats.resets += 1;
        self.stats.realtime_sent += 1;
    }

    fn send_realtime(&mut self, now: Instant, command: Realtime, out: &mut Vec<u8>) {
        out.push(command.byte());
        self.stats.realtime_sent += 1;
        if command == Realtime::StatusReport {
            self.stats.status_requests += 1;
            let full = self.is_full();
            self.status_pending.get_or_insert((now, full));
        }
    }

    fn transmit_sizing(&mut self, now: Instant, out: &mut Vec<u8>) {
        match self.sizing {
            Sizing::Mask => {
                out.extend_from_slice(BUFFER_REPORT_LINE.as_bytes());
                out.push(b'\n');
                self.count_sent(None, BUFFER_REPORT_LINE.len() + 1);
                self.sizing = Sizing::MaskSent;
            }
            Sizing::MaskSent => {}
            Sizing::Ask => {
                self.status_pending = None;
                self.send_realtime(now, Realtime::StatusReport, out);
                self.last_poll = Some(now);
                self.sizing = Sizing::Asked(now);
            }
            Sizing::Asked(t) => {
                if now.saturating_duration_since(t) >= self.config.status_timeout {
                    // No report: the configured size stays.
                    self.stats.status_lost += 1;
                    self.status_pending = None;
                    self.start_streaming();
                }
            }
        }
    }

    /// The sender's own `?`, every [`Config::status_interval`], one at a time.
    fn poll_status(&mut self, now: Instant, out: &mut Vec<u8>) {
        let Some(interval) = self.config.status_interval else {
            return;
        };
        if self
            .last_poll
            .is_some_and(|t| now.saturating_duration_since(t) < interval)
        {
            return;
        }
        if let Some((t, _)) = self.status_pending {
            if now.saturating_duration_since(t) < self.config.status_timeout {
                return;
            }
            self.stats.status_lost += 1;
            self.status_pending = None;
        }
        self.send_realtime(now, Realtime::StatusReport, out);
        self.last_poll = Some(now);
    }

    /// Whether the count holds the next line back.
    fn is_full(&self) -> bool {
        self.phase == Phase::Streaming
            && self
                .lines
                .get(self.next)
                .is_some_and(|l| self.in_flight_bytes + l.len() + 1 > self.rx_buffer)
    }

    fn transmit_lines(&mut self, out: &mut Vec<u8>) -> usize {
        let mut sent = 0;
        while let Some(line) = self.lines.get(self.next) {
            let len = line.len() + 1;
            if self.in_flight_bytes + len > self.rx_buffer {
                if !self.in_flight.is_empty() {
                    break;
                }
                self.stats.oversized += 1;
            }
            out.extend_from_slice(line.as_bytes());
            out.push(b'\n');
            self.count_sent(Some(self.next), len);
            self.next += 1;
            sent += 1;
        }
        sent
    }

    /// Count a line handed to the link as in flight.
    fn count_sent(&mut self, line: Option<usize>, len: usize) {
        self.in_flight.push_back(Flight { line, len });
        self.in_flight_bytes += len;
        self.stats.bytes_sent += len as u64;
        self.stats.lines_sent += 1;
        self.stats.max_in_flight_bytes = self.stats.max_in_flight_bytes.max(self.in_flight_bytes);
        self.stats.max_in_flight_lines = self.stats.max_in_flight_lines.max(self.in_flight.len());
    }

    /// Handle one line from the controller (without its terminator). Lines that are none of
    /// grbl's (frames, RepRap replies) are ignored.
    pub fn receive(&mut self, now: Instant, line: &[u8]) {
        let line = line.trim_ascii();
        if line == b"ok" {
            self.on_answer(Answer::Ok);
        } else if let Some(code) = line.strip_prefix(b"error:") {
            self.on_answer(Answer::Error(number(code)));
        } else if let Some(code) = line.strip_prefix(b"ALARM:") {
            self.on_alarm(number(code));
        } else if let Some(report) = StatusText::parse(line) {
            self.on_status(now, report, line);
        } else if line.starts_with(b"Grbl ") {
            self.on_banner();
        } else if let Some(text) = line
            .strip_prefix(b"[MSG:")
            .and_then(|t| t.strip_suffix(b"]"))
        {
            let text = String::from_utf8_lossy(text).into_owned();
            self.events.push_back(if asks_cycle_start(&text) {
                Event::AwaitingCycleStart(text)
            } else {
                Event::Message(text)
            });
        }
    }

    fn on_answer(&mut self, answer: Answer) {
        if self.phase == Phase::Resetting {
            self.stats.stray_answers += 1;
            return;
        }
        let Some(flight) = self.in_flight.pop_front() else {
            self.stats.stray_answers += 1;
            return;
        };
        self.in_flight_bytes -= flight.len;
        match flight.line {
            Some(index) => {
                if let Some(slot) = self.answers.get_mut(index) {
                    *slot = Some(answer);
                }
                match answer {
                    Answer::Ok => self.stats.oks += 1,
                    Answer::Error(code) => {
                        self.stats.errors += 1;
                        self.events.push_back(Event::Refused {
                            number: index as u32 + 1,
                            code,
                            text: self
                                .lines
                                .get(index)
                                .map(|l| l.to_string())
                                .unwrap_or_default(),
                        });
                    }
                    Answer::Dropped => {}
                }
                self.check_done();
            }
            // `$10=3` answered (an `error:` too: a grbl that refuses it reports no `Bf:`).
            None => {
                if self.phase == Phase::Sizing && self.sizing == Sizing::MaskSent {
                    if self.config.size_from_report {
                        self.sizing = Sizing::Ask;
                    } else {
                        self.start_streaming();
                    }
                }
            }
        }
    }

    fn on_alarm(&mut self, code: u8) {
        // Before the banner: the reset's own report (`ALARM:3` after motion cut), not the job's.
        if matches!(
            self.phase,
            Phase::Resetting | Phase::Failed | Phase::Stopped | Phase::Alarm
        ) {
            return;
        }
        self.phase = Phase::Alarm;
        self.events.push_back(Event::Alarm { code });
    }

    fn on_status(&mut self, now: Instant, report: StatusText<'_>, line: &[u8]) {
        self.stats.status_reports += 1;
        if let Some((t, full)) = self.status_pending.take() {
            let latency = now.saturating_duration_since(t);
            self.stats.max_status_latency = self.stats.max_status_latency.max(latency);
            if full {
                self.stats.full_status_reports += 1;
                self.stats.max_full_status_latency =
                    self.stats.max_full_status_latency.max(latency);
            }
        }
        let free_bytes = report
            .field(b"Bf")
            .and_then(|v| v.split(|b| *b == b',').nth(1))
            .and_then(|v| std::str::from_utf8(v).ok())
            .and_then(|v| v.parse::<usize>().ok())
            .filter(|&n| n > 0);
        let inner = line.get(1..line.len() - 1).unwrap_or_default();
        self.last_status = Some(String::from_utf8_lossy(inner).into_owned());
        if self.phase == Phase::Sizing && matches!(self.sizing, Sizing::Asked(_)) {
            if let Some(bytes) = free_bytes {
                self.rx_buffer = bytes;
            }
            self.start_streaming();
        }
    }

    fn on_banner(&mut self) {
        if self.phase == Phase::Resetting {
            self.reset_sent_at = None;
            match self.after_banner.take() {
                Some(phase) => self.phase = phase,
                None => self.start_sizing(),
            }
            return;
        }
        // Not asked for: the controller restarted and dropped what it held.
        let unanswered = !self.in_flight.is_empty() || (self.next > 0 && !self.is_over());
        self.drop_in_flight();
        self.status_pending = None;
        if unanswered {
            if !self.is_over() {
                self.phase = Phase::Failed;
            }
            self.events.push_back(Event::Restarted);
        } else if matches!(self.phase, Phase::Sizing | Phase::Streaming) {
            self.start_sizing();
        }
    }

    fn start_sizing(&mut self) {
        self.phase = Phase::Sizing;
        if self.config.report_buffer {
            self.sizing = Sizing::Mask;
        } else if self.config.size_from_report {
            self.sizing = Sizing::Ask;
        } else {
            self.start_streaming();
        }
    }

    fn start_streaming(&mut self) {
        self.phase = Phase::Streaming;
        self.events.push_back(Event::Ready {
            rx_buffer_bytes: self.rx_buffer,
        });
        self.check_done();
    }

    fn drop_in_flight(&mut self) {
        for flight in self.in_flight.drain(..) {
            if let Some(slot) = flight.line.and_then(|i| self.answers.get_mut(i)) {
                *slot = Some(Answer::Dropped);
            }
        }
        self.in_flight_bytes = 0;
    }

    fn check_done(&mut self) {
        if self.phase == Phase::Streaming
            && self.finished
            && self.next == self.lines.len()
            && self.in_flight.is_empty()
        {
            self.phase = Phase::Done;
            self.events.push_back(Event::Done);
        }
    }
}

/// The number after `error:` or `ALARM:` (0 if it does not read).
fn number(digits: &[u8]) -> u8 {
    std::str::from_utf8(digits)
        .ok()
        .and_then(|d| d.trim().parse().ok())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    const BANNER: &[u8] = b"Grbl 1.1h ['$' for help]";

    fn text(bytes: &[u8]) -> String {
        String::from_utf8_lossy(bytes).into_owned()
    }

    /// A sender counting against `rx` bytes, past its reset and banner, with `lines` pushed.
    fn ready(rx: usize, lines: &[&str]) -> (GrblSender, Instant) {
        let config = Config {
            rx_buffer_bytes: rx,
            size_from_report: false,
            status_interval: None,
            ..Config::default()
        };
        let mut s = GrblSender::new(config);
        for l in lines {
            s.push(l).unwrap();
        }
        let now = Instant::now();
        let mut out = Vec::new();
        s.transmit(now, &mut out);
        assert_eq!(out, [0x18]);
        s.receive(now, BANNER);
        assert_eq!(
            s.next_event(),
            Some(Event::Ready {
                rx_buffer_bytes: rx
            })
        );
        (s, now)
    }

    fn send(s: &mut GrblSender, now: Instant) -> String {
        let mut out = Vec::new();
        s.transmit(now, &mut out);
        text(&out)
    }

    #[test]
    fn comments_and_blanks_are_stripped_as_senders_do() {
        assert_eq!(clean_line("  G1 X1 Y2 ; to the corner"), "G1 X1 Y2");
        assert_eq!(clean_line("G0 (rapid) X5 (fast)"), "G0 X5");
        assert_eq!(clean_line("(only a comment)"), "");
        assert_eq!(clean_line("   "), "");
        assert_eq!(clean_line("; a ; b"), "");
        assert_eq!(clean_line("N10 G1(x;y)X3"), "N10 G1X3");
        assert_eq!(clean_line("G1 X1 (unclosed"), "G1 X1 (unclosed");
        assert_eq!(clean_line("\tM3 S1000\r"), "M3 S1000");
        let mut s = GrblSender::new(Config::default());
        assert_eq!(s.push("(header)"), Ok(None));
        assert_eq!(s.push(""), Ok(None));
        assert_eq!(s.push("G21 ; mm"), Ok(Some(1)));
        assert_eq!(s.push("G1 X1 F100 (feed)"), Ok(Some(2)));
        assert_eq!(s.line(2), Some("G1 X1 F100"));
        assert_eq!(s.push("M117 ok?"), Err(PushError::Character(b'?')));
        assert_eq!(s.push("G1 X\u{e9}"), Err(PushError::Character(0xC3)));
        assert_eq!(s.push(&"G1".repeat(200)), Err(PushError::TooLong));
        assert_eq!(s.pushed(), 2);
        s.finish();
        assert_eq!(s.push("G0 X0"), Err(PushError::Finished));
    }

    #[test]
    fn nothing_but_the_reset_goes_before_the_banner() {
        let mut s = GrblSender::new(Config::default());
        s.push("G0 X1").unwrap();
        s.realtime(Realtime::StatusReport);
        let now = Instant::now();
        assert_eq!(send(&mut s, now), "\u{18}");
        assert_eq!(send(&mut s, now), "");
        // An answer of an earlier session is no line's.
        s.receive(now, b"ok");
        assert_eq!(s.stats().stray_answers, 1);
        assert_eq!(s.phase(), Phase::Resetting);
        // No banner in time: reset again, then give up.
        let timeout = Config::default().banner_timeout;
        assert_eq!(s.poll_at(), Some(now + timeout));
        assert_eq!(send(&mut s, now + timeout), "\u{18}");
        assert_eq!(send(&mut s, now + timeout * 2), "\u{18}");
        assert_eq!(send(&mut s, now + timeout * 3), "");
        assert_eq!(s.phase(), Phase::Failed);
        assert_eq!(s.next_event(), Some(Event::NoBanner));
        assert_eq!(s.stats().resets, 3);
    }

    #[test]
    fn the_buffer_is_sized_from_the_report_after_dollar_ten() {
        let config = Config {
            report_buffer: true,
            status_interval: None,
            ..Config::default()
        };
        let mut s = GrblSender::new(config);
        s.push("G0 X1").unwrap();
        let now = Instant::now();
        assert_eq!(send(&mut s, now), "\u{18}");
        s.receive(now, b"Grbl 1.1h ['$' for help]\r\n");
        s.receive(now, b"[MSG:'$H'|'$X' to unlock]");
        assert_eq!(
            s.next_event(),
            Some(Event::Message("'$H'|'$X' to unlock".into()))
        );
        assert_eq!(send(&mut s, now), "$10=3\n");
        assert_eq!(s.in_flight_bytes(), 6);
        // `?` only once `$10=3` is answered: an earlier report would have no `Bf:`.
        assert_eq!(send(&mut s, now), "");
        s.receive(now, b"ok");
        assert_eq!(s.in_flight_bytes(), 0);
        assert_eq!(send(&mut s, now), "?");
        let later = now + Duration::from_millis(3);
        s.receive(later, b"<Idle|MPos:0.000,0.000,0.000|Bf:15,768|FS:0,0>");
        assert_eq!(
            s.next_event(),
            Some(Event::Ready {
                rx_buffer_bytes: 768
            })
        );
        assert_eq!(s.rx_buffer_bytes(), 768);
        assert_eq!(s.stats().max_status_latency, Duration::from_millis(3));
        assert_eq!(send(&mut s, later), "G0 X1\n");
        assert_eq!(s.answers(), [None]);
        assert_eq!(s.stats().oks, 0, "the `$10=3` answer is not a line's");
    }

    #[test]
    fn a_report_without_bf_or_no_report_keeps_the_configured_size() {
        let mut s = GrblSender::new(Config {
            status_interval: None,
            ..Config::default()
        });
        let now = Instant::now();
        send(&mut s, now);
        s.receive(now, BANNER);
        assert_eq!(send(&mut s, now), "?");
        s.receive(now, b"<Idle|MPos:0.000,0.000,0.000|FS:0,0>");
        assert_eq!(s.rx_buffer_bytes(), GRBL_RX_BUFFER);
        assert_eq!(s.phase(), Phase::Streaming);

        let mut s = GrblSender::new(Config {
            status_interval: None,
            ..Config::default()
        });
        s.push("G0 X1").unwrap();
        send(&mut s, now);
        s.receive(now, BANNER);
        assert_eq!(send(&mut s, now), "?");
        let timeout = Config::default().status_timeout;
        assert_eq!(s.poll_at(), Some(now + timeout));
        assert_eq!(send(&mut s, now + timeout), "G0 X1\n");
        assert_eq!(s.rx_buffer_bytes(), GRBL_RX_BUFFER);
        assert_eq!(s.stats().status_lost, 1);
    }

    #[test]
    fn lines_go_while_their_bytes_fit_and_each_answer_frees_the_oldest() {
        // Five bytes a line with its `\n`: four fit in 22 bytes.
        let lines = ["G1X1", "G1X2", "G1X3", "G1X4", "G1X5", "G1X6"];
        let (mut s, now) = ready(22, &lines);
        s.finish();
        assert_eq!(send(&mut s, now), "G1X1\nG1X2\nG1X3\nG1X4\n");
        assert_eq!((s.in_flight_bytes(), s.in_flight_lines()), (20, 4));
        assert_eq!(send(&mut s, now), "");
        s.receive(now, b"ok");
        assert_eq!(send(&mut s, now), "G1X5\n");
        s.receive(now, b"ok");
        s.receive(now, b"ok");
        assert_eq!(send(&mut s, now), "G1X6\n");
        s.receive(now, b"ok");
        s.receive(now, b"ok");
        assert_eq!(s.phase(), Phase::Streaming);
        s.receive(now, b"ok");
        assert_eq!(s.phase(), Phase::Done);
        assert_eq!(s.answers(), [Some(Answer::Ok); 6]);
        assert_eq!(s.stats().max_in_flight_bytes, 20);
        assert_eq!(s.stats().max_in_flight_lines, 4);
        assert!(s.stats().max_in_flight_bytes <= s.rx_buffer_bytes());
        s.receive(now, b"ok");
        assert_eq!(s.stats().stray_answers, 1);
        assert_eq!(s.stats().oks, 6);
    }

    #[test]
    fn realtime_bytes_go_at_once_and_are_never_counted() {
        let (mut s, now) = ready(10, &["G1X1", "G1X2", "G1X3"]);
        assert_eq!(send(&mut s, now), "G1X1\nG1X2\n");
        s.realtime(Realtime::StatusReport);
        s.realtime(Realtime::FeedHold);
        s.realtime(Realtime::CycleStart);
        s.realtime(Realtime::FeedOverride(forja_protocol::grbl::Step::By(10)));
        let mut out = Vec::new();
        s.transmit(now, &mut out);
        assert_eq!(out, b"?!~\x91");
        assert_eq!(s.in_flight_bytes(), 10);
        let later = now + Duration::from_millis(7);
        s.receive(later, b"<Run|MPos:1.000,0.000,0.000|FS:100,0>");
        assert_eq!(s.last_status(), Some("Run|MPos:1.000,0.000,0.000|FS:100,0"));
        assert_eq!(s.stats().max_status_latency, Duration::from_millis(7));
        // The count held `G1X3` back: the buffer was full.
        assert_eq!(s.stats().full_status_reports, 1);
        assert_eq!(s.stats().max_full_status_latency, Duration::from_millis(7));
        assert_eq!(s.stats().realtime_sent, 5, "0x18 and the four");
    }

    #[test]
    fn an_error_is_counted_and_reported_and_the_stream_goes_on() {
        let (mut s, now) = ready(128, &["G1X1", "G2X2", "G1X3"]);
        s.finish();
        send(&mut s, now);
        s.receive(now, b"ok");
        s.receive(now, b"error:33");
        s.receive(now, b"ok");
        assert_eq!(
            s.next_event(),
            Some(Event::Refused {
                number: 2,
                code: 33,
                text: "G2X2".into()
            })
        );
        assert_eq!(s.next_event(), Some(Event::Done));
        assert_eq!(
            s.answers(),
            [Some(Answer::Ok), Some(Answer::Error(33)), Some(Answer::Ok)]
        );
        assert_eq!((s.stats().oks, s.stats().errors), (2, 1));
    }

    #[test]
    fn an_alarm_stops_the_stream() {
        let (mut s, now) = ready(10, &["G1X1", "G1X2", "G1X3"]);
        assert_eq!(send(&mut s, now), "G1X1\nG1X2\n");
        s.receive(now, b"ALARM:1");
        assert_eq!(s.phase(), Phase::Alarm);
        assert_eq!(s.next_event(), Some(Event::Alarm { code: 1 }));
        s.receive(now, b"error:9");
        s.receive(now, b"error:9");
        assert_eq!(send(&mut s, now), "");
        assert_eq!(
            s.answers(),
            [Some(Answer::Error(9)), Some(Answer::Error(9)), None]
        );
        // The operator may still act on the machine.
        s.realtime(Realtime::StatusReport);
        assert_eq!(send(&mut s, now), "?");
    }

    #[test]
    fn a_soft_reset_clears_the_count_and_stops_the_job() {
        let (mut s, now) = ready(10, &["G1X1", "G1X2", "G1X3"]);
        assert_eq!(send(&mut s, now), "G1X1\nG1X2\n");
        s.receive(now, b"ok");
        s.realtime(Realtime::SoftReset);
        assert_eq!(s.in_flight_bytes(), 0);
        assert_eq!(send(&mut s, now), "\u{18}");
        // An `ok` already on its way belongs to the old session.
        s.receive(now, b"ok");
        s.receive(now, BANNER);
        assert_eq!(s.phase(), Phase::Stopped);
        assert_eq!(send(&mut s, now), "");
        assert_eq!(s.answers(), [Some(Answer::Ok), Some(Answer::Dropped), None]);
        assert_eq!(s.stats().stray_answers, 1);
    }

    #[test]
    fn a_reset_after_the_job_keeps_it_done() {
        let (mut s, now) = ready(128, &["G1X1"]);
        s.finish();
        send(&mut s, now);
        s.receive(now, b"ok");
        s.soft_reset();
        s.soft_reset();
        assert_eq!(send(&mut s, now), "\u{18}");
        s.receive(now, BANNER);
        assert_eq!(s.phase(), Phase::Done);
    }

    #[test]
    fn a_reset_before_the_job_starts_over() {
        let mut s = GrblSender::new(Config {
            size_from_report: false,
            status_interval: None,
            ..Config::default()
        });
        s.push("G0 X1").unwrap();
        let now = Instant::now();
        send(&mut s, now);
        s.soft_reset();
        assert_eq!(send(&mut s, now), "\u{18}");
        s.receive(now, BANNER);
        assert_eq!(send(&mut s, now), "G0 X1\n");
    }

    #[test]
    fn a_restart_of_the_controller_during_the_job_fails_it() {
        let (mut s, now) = ready(128, &["G1X1", "G1X2"]);
        send(&mut s, now);
        s.receive(now, b"ok");
        s.receive(now, BANNER);
        assert_eq!(s.phase(), Phase::Failed);
        assert_eq!(s.next_event(), Some(Event::Restarted));
        assert_eq!(s.answers(), [Some(Answer::Ok), Some(Answer::Dropped)]);
    }

    #[test]
    fn a_tool_change_asks_for_cycle_start() {
        let (mut s, now) = ready(128, &["M6 T1"]);
        send(&mut s, now);
        s.receive(now, b"[MSG:Change to tool T1, then cycle start]");
        s.receive(now, b"ok");
        assert_eq!(
            s.next_event(),
            Some(Event::AwaitingCycleStart(
                "Change to tool T1, then cycle start".into()
            ))
        );
        s.realtime(Realtime::CycleStart);
        assert_eq!(send(&mut s, now), "~");
    }

    #[test]
    fn a_line_longer_than_the_buffer_goes_alone() {
        let (mut s, now) = ready(8, &["G1X1", "G1 X100 Y100", "G1X2"]);
        assert_eq!(send(&mut s, now), "G1X1\n");
        s.receive(now, b"ok");
        assert_eq!(send(&mut s, now), "G1 X100 Y100\n");
        assert_eq!(send(&mut s, now), "");
        s.receive(now, b"ok");
        assert_eq!(send(&mut s, now), "G1X2\n");
        assert_eq!(s.stats().oversized, 1);
    }

    #[test]
    fn the_status_is_polled_one_at_a_time() {
        let mut s = GrblSender::new(Config {
            size_from_report: false,
            ..Config::default()
        });
        let now = Instant::now();
        send(&mut s, now);
        s.receive(now, BANNER);
        let interval = Config::default().status_interval.unwrap();
        assert_eq!(send(&mut s, now), "?");
        assert_eq!(s.poll_at(), Some(now + interval));
        assert_eq!(send(&mut s, now + interval / 2), "");
        // Not answered: no second `?` until the time-out.
        assert_eq!(send(&mut s, now + interval), "");
        let timeout = Config::default().status_timeout;
        assert_eq!(send(&mut s, now + timeout), "?");
        assert_eq!(s.stats().status_lost, 1);
        s.receive(
            now + timeout + Duration::from_millis(2),
            b"<Idle|MPos:0,0,0>",
        );
        assert_eq!(s.stats().max_status_latency, Duration::from_millis(2));
        assert_eq!(send(&mut s, now + timeout + interval), "?");
        assert_eq!(s.stats().status_requests, 3);
    }

    /// A model of grbl's serial side: a receive buffer of `rx` bytes that must never overflow,
    /// realtime bytes taken out as they arrive, lines taken out and answered at random times.
    struct ModelGrbl {
        rx: usize,
        buffer: VecDeque<u8>,
        taken: Vec<String>,
        replies: VecDeque<String>,
    }

    impl ModelGrbl {
        fn feed(&mut self, bytes: &[u8]) {
            for &b in bytes {
                match b {
                    b'?' => self
                        .replies
                        .push_back("<Run|MPos:0.000,0.000,0.000>".into()),
                    0x18 => {
                        self.buffer.clear();
                        self.replies.push_back(text(BANNER));
                    }
                    _ => {
                        assert!(self.buffer.len() < self.rx, "the receive buffer overflowed");
                        self.buffer.push_back(b);
                    }
                }
            }
        }

        fn take_line(&mut self) {
            let Some(end) = self.buffer.iter().position(|&b| b == b'\n') else {
                return;
            };
            let line: Vec<u8> = self.buffer.drain(..=end).collect();
            let line = text(&line[..end]);
            self.replies.push_back(if line.contains("G2") {
                "error:33".into()
            } else {
                "ok".into()
            });
            self.taken.push(line);
        }
    }

    #[test]
    fn a_grbl_receive_buffer_never_overflows_and_every_line_is_answered_in_order() {
        let texts: Vec<String> = (0..2000)
            .map(|i| match i % 7 {
                0 => format!("N{i} G1 X{}.{} Y-{} F3000 ; move", i, i % 10, i * 3),
                3 => "(a comment line)".to_string(),
                5 => format!("G2 X{i} Y1 I1 J0"),
                _ => format!("G1X{}.125Y{}", i, i % 13),
            })
            .collect();
        let mut s = GrblSender::new(Config {
            size_from_report: false,
            ..Config::default()
        });
        let mut expected = Vec::new();
        for t in &texts {
            if s.push(t).unwrap().is_some() {
                expected.push(clean_line(t).into_owned());
            }
        }
        s.finish();
        let mut grbl = ModelGrbl {
            rx: GRBL_RX_BUFFER,
            buffer: VecDeque::new(),
            taken: Vec::new(),
            replies: VecDeque::new(),
        };
        let mut seed = 0x9E37_79B9_7F4A_7C15u64;
        let mut random = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        let mut now = Instant::now();
        for _ in 0..100_000 {
            let mut out = Vec::new();
            s.transmit(now, &mut out);
            grbl.feed(&out);
            for _ in 0..random() % 3 {
                grbl.take_line();
            }
            for _ in 0..random() % 4 {
                if let Some(r) = grbl.replies.pop_front() {
                    s.receive(now, r.as_bytes());
                }
            }
            assert!(s.in_flight_bytes() <= GRBL_RX_BUFFER);
            now += Duration::from_millis(1);
            if s.phase() == Phase::Done {
                break;
            }
        }
        assert_eq!(s.phase(), Phase::Done);
        assert_eq!(grbl.taken, expected);
        let errors = expected.iter().filter(|l| l.contains("G2")).count();
        assert_eq!(s.stats().errors, errors as u64);
        assert_eq!(s.stats().oks + s.stats().errors, expected.len() as u64);
        assert!(s.answers().iter().all(Option::is_some));
        assert!(s.stats().max_in_flight_bytes > GRBL_RX_BUFFER - 30);
        assert!(s.stats().status_reports > 0);
    }
}
