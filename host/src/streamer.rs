//! The windowed G-code streamer: a sans-IO state machine (smoltcp's shape).
//!
//! The streamer owns the numbered lines of a job and decides what to send and when; it never
//! reads a clock or touches a link. The caller moves bytes:
//!
//! ```text
//! loop {
//!     streamer.transmit(now, &mut out);      // bytes to write, as the window allows
//!     link.write_all(&out);
//!     for each reply line received:
//!         streamer.receive(now, line);       // `ok`, `rs N`, `echo:…`, `Error:…`, `start`
//!     streamer.poll(now);                    // time-outs; call again at `poll_at()`
//!     while let Some(event) = streamer.next_event() { … }
//! }
//! ```
//!
//! # The algorithm
//!
//! **Handshake.** The controller may hold a partial line or a line number from an earlier
//! session, so the streamer first sends a line break (to end any partial line) and
//! `N0 M110 N0*cs` (the next line expected is then 1), and waits for its `ok`, repeating it
//! every [`Config::handshake_interval`] (or at once after an `rs` or a `start`). `M110` is
//! never sent again once a program line has been sent: it would let the controller accept a
//! line a second time.
//!
//! **Window.** Lines are numbered from 1, each sent as `N<n> <text>*<checksum>` followed by
//! CR LF. The second terminator costs one byte and means that a damaged terminator never merges
//! two lines into one (the controller drops empty lines without a reply). The streamer keeps
//! sending while the lines sent and not yet answered (the *in flight* queue) stay within
//! [`Window::lines`] lines and [`Window::bytes`] bytes, the room of the controller's receive
//! buffer; the controller delays its `ok` while its planner is full, which holds the sender back
//! without ever letting the link idle while there is room.
//!
//! **Replies.** Every terminal reply (`ok…` or `rs N`) answers the oldest line in flight; the
//! `ok` that follows an `rs N` (Marlin's form) belongs to it, and report lines (positions,
//! temperatures, `Cap:` lines, `echo:busy: processing`) answer nothing.
//! - `ok`: the line the controller expected was accepted; it is line `accepted + 1`.
//!   Preceded by `echo:E<code> …`, `echo:Unknown command: …` or `// E<code> …`, that line was
//!   refused (it had no effect) and is reported with its number; the alarm codes (125, 126,
//!   150–155) stop the job.
//! - `rs N`: the controller expects line `N`: every line before `N` is accepted, and from `N`
//!   on everything must be sent again, unless a copy of line `N` is already in flight behind
//!   the line this reply answers. That test does both jobs the rewind needs: the first `rs N`
//!   rewinds to `N` once, and the `rs N` answers of the lines that were in flight when it did
//!   (one per line) find the resent copy of `N` behind them and are recognised as such. It
//!   also keeps a late duplicate from starting a new round of resends.
//! - Because the controller takes lines only in order and refuses any other number, sending a
//!   line again is always safe: a copy of a line that was already accepted is refused with
//!   `rs`, never run twice.
//!
//! **Damaged links.** Each damaged line costs the lines in flight behind it, which the
//! controller refuses as out of order; so the line window halves at each rewind (not below two
//! lines) and grows back by one line for each window's worth of lines accepted in a row.
//!
//! **Recovery.** Replies are counted, not named, and a damaged link breaks the count: a line
//! cut in two by a damaged byte gets two answers. A surplus answer frees a place in the window
//! that no line left, and a host that sends as soon as an answer frees a place (one answer at a
//! time, as `forja send` reads them) would keep the surplus forever, every `rs` sending a line
//! that earns another `rs`: a resend storm. So after an `rs`, until a line is accepted, only
//! the line asked for is sent, once and alone. An `rs` that then empties the in-flight count
//! cannot tell a refused copy from a late surplus answer: the copy is sent again only after
//! [`Config::quiet_timeout`] without an answer, and an answer that comes meanwhile finds
//! nothing in flight and is dropped, which ends the surplus.
//!
//! **Refusals.** A refusal with a kernel code (100 and up) concerns an intact line: the line
//! `accepted + 1` is reported at once. A refusal by the G-code parser (codes below 100) answers
//! either a damaged scrap of a line (the controller still expects the same line) or a line
//! damaged in a way its checksum could not see (the controller skipped it): it is not counted
//! until the next `rs N` tells which, and reported as refused only in the second case.
//!
//! **End of the job.** [`Streamer::finish`] appends one empty numbered line. The controller
//! accepts it only after every line before it; its `ok` (or an `rs` naming the line after it)
//! is the proof that the whole job was taken, so a stray `ok` cannot end the job early.
//!
//! **Nudge.** A line whose terminators were both lost waits in the controller, unanswered,
//! until more bytes come; with only the line asked for in flight (recovery) or the window full,
//! none would. So when lines are in flight and nothing is answered for
//! [`Config::quiet_timeout`], one lone line end is sent: it ends such a line (whose answer was
//! owed anyway) and is otherwise an empty line, which the controller drops without a reply. A
//! command that blocks (a heating wait) gets one nudge per silence, not a stream of them.
//!
//! **Time-outs.** If lines are in flight and nothing is answered for
//! [`Config::reply_timeout`], the streamer assumes replies were lost, forgets the in-flight
//! accounting and sends the first line not known to be accepted again (a copy is harmless).
//! An `echo:busy: processing` while lines are in flight restarts that time: a command still
//! runs (a homing, a long dwell). An unsolicited `Error:` (one not followed by a line's `ok`
//! within [`Config::alarm_grace`], or with nothing in flight) is an alarm: the streamer stops
//! sending.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use forja_protocol::gcode::{Check, EncodeError, MAX_LINE_LEN, write_checked};
use forja_protocol::reply::Reply;

/// How much may be in flight: sent to the controller and not yet answered.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Window {
    /// Most bytes in flight (the controller's receive buffer). At least one line is always
    /// allowed, however long.
    pub bytes: usize,
    /// Most lines in flight.
    pub lines: usize,
}

impl Window {
    /// A UART controller: a 256-byte receive buffer.
    pub const UART: Window = Window {
        bytes: 256,
        lines: 32,
    };
    /// A TCP controller: the socket buffers hold far more than a UART's.
    pub const TCP: Window = Window {
        bytes: 2048,
        lines: 128,
    };
    /// One line at a time: send, wait for its answer (what most RepRap hosts do).
    pub const PING_PONG: Window = Window { bytes: 1, lines: 1 };
}

/// The streamer's settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Config {
    /// How much may be in flight.
    pub window: Window,
    /// With lines in flight and no answer for this long, replies are taken as lost and the first
    /// line not known to be accepted is sent again.
    pub reply_timeout: Duration,
    /// The handshake's `M110` is sent again after this long without an answer.
    pub handshake_interval: Duration,
    /// The handshake gives up after this many `M110`s without an `ok`.
    pub handshake_attempts: u32,
    /// With no line in flight by the count but some not known to be accepted, and no answer
    /// for this long, the first of them is sent again.
    pub quiet_timeout: Duration,
    /// An `Error:` (or `!!`) not followed by a line's `ok` within this long is an alarm.
    pub alarm_grace: Duration,
    /// The check written after `*` on every numbered line, the handshake's `M110` included:
    /// [`Check::Crc16`] for a controller that announces `LINE_CHECK:CRC16` in its `M115`
    /// answer (see [`crate::client::probe_line_check`]), which then refuses a damaged line
    /// that the XOR would let through.
    pub check: Check,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            window: Window::UART,
            reply_timeout: Duration::from_secs(10),
            handshake_interval: Duration::from_millis(1000),
            handshake_attempts: 10,
            quiet_timeout: Duration::from_millis(500),
            alarm_grace: Duration::from_millis(500),
            check: Check::Xor,
        }
    }
}

/// Where the streamer is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Waiting for the `ok` of the `M110` that sets the line numbers.
    Handshake,
    /// Sending lines.
    Streaming,
    /// Every line, the closing one included, was accepted.
    Done,
    /// The machine went into alarm; nothing more is sent.
    Alarm,
    /// The controller did not answer the handshake, restarted during the job, or its line
    /// numbers went out of step; nothing more is sent.
    Failed,
}

/// Something the caller should know about.
#[derive(Clone, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Event {
    /// The handshake's `M110` was accepted: lines are being sent.
    Synchronised,
    /// The controller refused a line: it had no effect. The job goes on unless
    /// [`Event::Alarm`] follows.
    Refused {
        /// The line's number (1 is the first line pushed).
        number: u32,
        /// The error's code (0 if none was given).
        code: u16,
        /// The error's text.
        text: String,
    },
    /// The controller asked for lines again from `from`; they are being resent.
    Rewound {
        /// The first line resent.
        from: u32,
    },
    /// Nothing was answered for [`Config::reply_timeout`]; line `from` was sent again.
    Stalled {
        /// The line sent again.
        from: u32,
    },
    /// The machine went into alarm. Nothing more is sent.
    Alarm {
        /// The alarm's code (0 if none was given).
        code: u16,
        /// The alarm's text.
        text: String,
    },
    /// The controller restarted (`start`) while lines were in its hands. Nothing more is sent.
    Restarted,
    /// The controller did not answer the handshake.
    NoAnswer,
    /// The controller asks for a line this client never sent: its numbering is out of step.
    OutOfStep {
        /// The line it asked for.
        asked: u32,
    },
    /// Every line was accepted.
    Done,
}

/// Counters, for the summary and for measurements.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Bytes handed to the link (handshake included).
    pub bytes_sent: u64,
    /// Lines handed to the link, copies included.
    pub lines_sent: u64,
    /// Lines sent again after an `rs` or a time-out.
    pub lines_resent: u64,
    /// Rewinds after an `rs`.
    pub rewinds: u64,
    /// `rs` answers that needed no rewind (a copy was already on its way).
    pub resends_absorbed: u64,
    /// `rs` answers to a line sent again alone, answered by sending it again only after
    /// [`Config::quiet_timeout`] (see "Recovery" in the module documentation).
    pub resends_deferred: u64,
    /// Time-outs.
    pub stalls: u64,
    /// Lone line ends sent into a silence (see "Nudge" in the module documentation).
    pub nudges: u64,
    /// Lines refused by the controller.
    pub refused: u64,
    /// Parser refusals that turned out not to concern a line of the job (the controller still
    /// asked for the line afterwards): damaged scraps of lines.
    pub refusals_dismissed: u64,
    /// `M110`s sent.
    pub handshakes: u64,
    /// `ok`s received with no line of the job waiting for one.
    pub stray_oks: u64,
}

/// Why a line cannot be pushed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum PushError {
    /// [`Streamer::finish`] was called: the job is closed.
    Finished,
    /// The line holds `*` or a control byte, or is too long once numbered.
    Encode(EncodeError),
}

impl std::fmt::Display for PushError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Finished => f.write_str("the job is already complete"),
            Self::Encode(EncodeError::TooLong) => f.write_str("the line is too long"),
            Self::Encode(_) => f.write_str("the line holds '*' or a control character"),
        }
    }
}

impl std::error::Error for PushError {}

#[derive(Clone, Copy, Debug)]
struct Sent {
    number: u32,
    len: usize,
}

/// The terminator sent after each line (see the module documentation).
const TERMINATOR: &[u8] = b"\r\n";

/// The sans-IO windowed streamer. See the [module documentation](self).
#[derive(Debug)]
pub struct Streamer {
    config: Config,
    /// `lines[k]` is line number `k + 1`, with its terminator.
    lines: Vec<Box<[u8]>>,
    /// Lines pushed by the caller (the closing line not counted).
    pushed: u32,
    finished: bool,
    /// The next line to send.
    next: u32,
    /// The highest line number sent so far: after a rewind, the controller may still have
    /// accepted lines up to it (their first copies, when the `rs` was a surplus answer), and its
    /// next `rs` may name any line up to the one after it.
    sent_through: u32,
    accepted: u32,
    in_flight: VecDeque<Sent>,
    in_flight_bytes: usize,
    phase: Phase,
    handshake_sent_at: Option<Instant>,
    /// When the oldest line in flight was sent or the last answer came, whichever is later.
    last_activity: Option<Instant>,
    pending_fault: Option<(u16, String, Instant)>,
    pending_notice: Option<(u16, String)>,
    /// An `rs` came: the `ok` after it belongs to it.
    resend_ok_due: bool,
    /// `ok`s after a protocol-level refusal notice (codes below 20), not counted as accepted
    /// lines: the refusal of a damaged scrap of a line, or of a line damaged in a way the
    /// checksum could not see. The next `rs` tells which: the first line concerned, and how
    /// many.
    uncounted: Option<(u32, u32, u16, String)>,
    out_of_step: u32,
    /// The line window in use: [`Window::lines`] on a clean link, halved at each rewind and
    /// grown back by one line per window of lines accepted in a row (each damaged line costs
    /// the lines in flight behind it, so a damaged link is better served by a smaller window).
    cap: usize,
    /// Lines accepted since the cap last changed.
    run: usize,
    /// An `rs` came and no line was accepted since: only the line asked for is sent, alone
    /// (see "Recovery" in the module documentation).
    recovering: bool,
    /// A lone line end is to be sent (see "Nudge" in the module documentation).
    nudge_due: bool,
    /// The nudge for the present silence was sent.
    nudged: bool,
    stats: Stats,
    events: VecDeque<Event>,
}

/// The first error code of the motion kernel: codes below it are the protocol's own (a line
/// that did not parse), codes from it on concern a line that arrived intact.
pub const FIRST_COMMAND_CODE: u16 = 100;

/// The code of the kernel's `unsupported-command`, under which an `echo:Unknown command` is
/// reported.
pub const UNKNOWN_COMMAND_CODE: u16 = 120;

/// The codes after which a job cannot go on: the machine is locked in alarm or halted.
pub fn is_alarm_code(code: u16) -> bool {
    matches!(code, 125 | 126 | 150..=155)
}

impl Streamer {
    /// A streamer with no lines, about to handshake.
    pub fn new(config: Config) -> Self {
        Self {
            config,
            lines: Vec::new(),
            pushed: 0,
            finished: false,
            next: 1,
            sent_through: 0,
            accepted: 0,
            in_flight: VecDeque::new(),
            in_flight_bytes: 0,
            phase: Phase::Handshake,
            handshake_sent_at: None,
            last_activity: None,
            pending_fault: None,
            pending_notice: None,
            resend_ok_due: false,
            uncounted: None,
            out_of_step: 0,
            cap: config.window.lines.max(1),
            run: 0,
            recovering: false,
            nudge_due: false,
            nudged: false,
            stats: Stats::default(),
            events: VecDeque::new(),
        }
    }

    /// Add a line to send (its text without line number or checksum; a `;` comment and
    /// surrounding blanks are dropped). Returns its number.
    pub fn push(&mut self, text: &str) -> Result<u32, PushError> {
        if self.finished {
            return Err(PushError::Finished);
        }
        let number = self.lines.len() as u32 + 1;
        self.push_numbered(number, text.as_bytes())
            .map_err(PushError::Encode)?;
        self.pushed += 1;
        Ok(number)
    }

    fn push_numbered(&mut self, number: u32, body: &[u8]) -> Result<(), EncodeError> {
        let mut buf = [0u8; MAX_LINE_LEN + 2];
        let n = write_checked(number, body, self.config.check, &mut buf)?;
        let mut line = buf.get(..n).unwrap_or_default().to_vec();
        line.extend_from_slice(TERMINATOR);
        self.lines.push(line.into_boxed_slice());
        Ok(())
    }

    /// No more lines: append the closing line whose acceptance proves that the whole job was
    /// taken. [`Phase::Done`] follows its `ok`.
    pub fn finish(&mut self) {
        if !self.finished {
            let number = self.lines.len() as u32 + 1;
            // An empty body always encodes.
            let _ = self.push_numbered(number, b"");
            self.finished = true;
        }
    }

    /// Where the streamer is.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// The counters.
    pub fn stats(&self) -> Stats {
        self.stats
    }

    /// How many of the pushed lines are known to be accepted.
    pub fn accepted(&self) -> u32 {
        self.accepted.min(self.pushed)
    }

    /// How many lines were pushed (the closing line not counted).
    pub fn pushed(&self) -> u32 {
        self.pushed
    }

    /// The line window in use now (see [`Window::lines`]; smaller after resends).
    pub fn window_lines(&self) -> usize {
        self.cap
    }

    /// Lines in flight, as the streamer counts them.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    /// Whether nothing is in flight and every pushed line was accepted.
    pub fn is_idle(&self) -> bool {
        self.in_flight.is_empty() && self.accepted >= self.pushed
    }

    /// The next event, if any.
    pub fn next_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// When [`poll`](Self::poll) (or [`transmit`](Self::transmit), for the handshake) must be
    /// called next at the latest, if anything is timed.
    pub fn poll_at(&self) -> Option<Instant> {
        let mut at: Option<Instant> = None;
        let mut take = |t: Instant| at = Some(at.map_or(t, |a| a.min(t)));
        match self.phase {
            Phase::Handshake => {
                if let Some(sent) = self.handshake_sent_at {
                    take(sent + self.config.handshake_interval);
                }
            }
            Phase::Streaming => {
                if let (Some(after), Some(t)) = (self.stall_after(), self.last_activity) {
                    take(t + after);
                }
                if let Some(t) = self.last_activity
                    && !self.in_flight.is_empty()
                    && !self.nudged
                {
                    take(t + self.config.quiet_timeout);
                }
            }
            _ => {}
        }
        if let Some((_, _, t)) = &self.pending_fault {
            take(*t + self.config.alarm_grace);
        }
        at
    }

    /// Append to `out` what should be written to the link now, as the window allows. Returns how
    /// many lines were appended.
    pub fn transmit(&mut self, now: Instant, out: &mut Vec<u8>) -> usize {
        match self.phase {
            Phase::Handshake => self.transmit_handshake(now, out),
            Phase::Streaming => self.transmit_lines(now, out),
            _ => 0,
        }
    }

    fn transmit_handshake(&mut self, now: Instant, out: &mut Vec<u8>) -> usize {
        let due = self
            .handshake_sent_at
            .is_none_or(|t| now.duration_since(t) >= self.config.handshake_interval);
        if !due {
            return 0;
        }
        if self.stats.handshakes >= u64::from(self.config.handshake_attempts) {
            self.phase = Phase::Failed;
            self.events.push_back(Event::NoAnswer);
            return 0;
        }
        let mut buf = [0u8; 32];
        let n = write_checked(0, b"M110 N0", self.config.check, &mut buf).unwrap_or(0);
        let start = out.len();
        out.extend_from_slice(TERMINATOR);
        out.extend_from_slice(buf.get(..n).unwrap_or_default());
        out.extend_from_slice(TERMINATOR);
        self.stats.bytes_sent += (out.len() - start) as u64;
        self.stats.handshakes += 1;
        self.handshake_sent_at = Some(now);
        1
    }

    fn transmit_lines(&mut self, now: Instant, out: &mut Vec<u8>) -> usize {
        if self.nudge_due {
            self.nudge_due = false;
            out.extend_from_slice(TERMINATOR);
            self.stats.bytes_sent += TERMINATOR.len() as u64;
            self.stats.nudges += 1;
        }
        let mut sent = 0;
        while let Some(line) = self.lines.get(self.next as usize - 1) {
            if self.recovering && self.next > self.accepted + 1 {
                break;
            }
            let len = line.len();
            let full = self.in_flight.len() >= self.cap
                || self.in_flight_bytes + len > self.config.window.bytes;
            if !self.in_flight.is_empty() && full {
                break;
            }
            if self.in_flight.is_empty() {
                self.last_activity = Some(now);
            }
            out.extend_from_slice(line);
            self.in_flight.push_back(Sent {
                number: self.next,
                len,
            });
            self.in_flight_bytes += len;
            self.stats.bytes_sent += len as u64;
            self.stats.lines_sent += 1;
            self.sent_through = self.sent_through.max(self.next);
            self.next += 1;
            sent += 1;
        }
        sent
    }

    /// Handle one reply line from the controller (without its terminator). Frames and lines
    /// that are not replies are ignored.
    pub fn receive(&mut self, now: Instant, line: &[u8]) {
        let Ok(reply) = Reply::parse(line) else {
            return;
        };
        if matches!(reply, Reply::Ok) && std::mem::take(&mut self.resend_ok_due) {
            // The `ok` that follows an `rs`: the `rs` was the answer.
            return;
        }
        self.resend_ok_due = false;
        match reply {
            Reply::Start => self.on_start(),
            Reply::Notice { code, text } | Reply::Refused { code, text } => {
                self.pending_notice = Some((code, text.to_string()));
            }
            Reply::Unknown(command) => {
                self.pending_notice = Some((
                    UNKNOWN_COMMAND_CODE,
                    format!("unsupported-command {command}"),
                ));
            }
            Reply::Fault { code, text } => self.on_fault(now, code, text),
            Reply::Resend(n) => {
                self.resend_ok_due = true;
                self.on_resend(now, n);
            }
            // A command still runs: its answer is not lost.
            Reply::Busy if !self.in_flight.is_empty() => {
                self.last_activity = Some(now);
                self.nudged = false;
            }
            Reply::Ok | Reply::OkWith(_) | Reply::Temperatures { ok: true, .. } => self.on_ok(now),
            // Reports and lines an `ok` follows.
            _ => {}
        }
    }

    /// Handle time-outs: call at [`poll_at`](Self::poll_at).
    pub fn poll(&mut self, now: Instant) {
        if let Some((code, text, t)) = &self.pending_fault
            && now.duration_since(*t) >= self.config.alarm_grace
        {
            let (code, text) = (*code, text.clone());
            self.alarm(code, text);
        }
        if self.phase == Phase::Streaming
            && !self.in_flight.is_empty()
            && !self.nudged
            && self
                .last_activity
                .is_some_and(|t| now.duration_since(t) >= self.config.quiet_timeout)
        {
            self.nudged = true;
            self.nudge_due = true;
        }
        let (Some(after), Some(t)) = (self.stall_after(), self.last_activity) else {
            return;
        };
        if now.duration_since(t) < after {
            return;
        }
        // Replies were lost, or the controller is very slow: forget the accounting and send
        // the first line not known to be accepted again (a copy of an accepted line is refused
        // by its number, never run).
        self.stats.stalls += 1;
        self.in_flight.clear();
        self.in_flight_bytes = 0;
        let from = self.accepted + 1;
        if from < self.next {
            self.stats.lines_resent += u64::from(self.next - from);
            self.next = from;
        }
        self.last_activity = Some(now);
        self.events.push_back(Event::Stalled { from });
    }

    fn on_start(&mut self) {
        match self.phase {
            Phase::Handshake => self.handshake_sent_at = None,
            Phase::Streaming if self.stats.lines_sent == 0 => {
                self.phase = Phase::Handshake;
                self.handshake_sent_at = None;
            }
            Phase::Streaming => {
                self.phase = Phase::Failed;
                self.events.push_back(Event::Restarted);
            }
            _ => {}
        }
    }

    fn on_fault(&mut self, now: Instant, code: u16, text: &str) {
        if let Some((code, text, _)) = self.pending_fault.take() {
            self.alarm(code, text);
        }
        if self.phase == Phase::Streaming && !self.in_flight.is_empty() {
            self.pending_fault = Some((code, text.to_string(), now));
        } else if self.phase != Phase::Handshake {
            self.alarm(code, text.to_string());
        }
    }

    fn alarm(&mut self, code: u16, text: String) {
        self.pending_fault = None;
        if matches!(self.phase, Phase::Alarm | Phase::Failed | Phase::Done) {
            return;
        }
        self.phase = Phase::Alarm;
        self.events.push_back(Event::Alarm { code, text });
    }

    /// The line a terminal reply answers: the oldest in flight.
    fn answered(&mut self, now: Instant) -> Option<Sent> {
        self.last_activity = Some(now);
        self.nudged = false;
        let sent = self.in_flight.pop_front()?;
        self.in_flight_bytes -= sent.len;
        Some(sent)
    }

    /// How long without an answer before lines are sent again, if lines are waiting for one:
    /// [`Config::reply_timeout`] while lines are in flight, [`Config::quiet_timeout`] when the
    /// in-flight count is down to zero but some lines are not known to be accepted (their
    /// answers were taken by damaged scraps of lines).
    fn stall_after(&self) -> Option<Duration> {
        if self.phase != Phase::Streaming {
            None
        } else if !self.in_flight.is_empty() {
            Some(self.config.reply_timeout)
        } else if self.accepted + 1 < self.next {
            Some(self.config.quiet_timeout)
        } else {
            None
        }
    }

    fn on_ok(&mut self, now: Instant) {
        let refusal = self
            .pending_fault
            .take()
            .map(|(c, t, _)| (c, t))
            .or_else(|| self.pending_notice.take());
        self.pending_notice = None;
        match self.phase {
            Phase::Handshake => {
                self.phase = Phase::Streaming;
                self.events.push_back(Event::Synchronised);
                return;
            }
            Phase::Streaming => {}
            _ => return,
        }
        self.answered(now);
        if self.accepted + 1 >= self.next {
            // No line of ours is waiting for an answer. (After a rewind this may be the `ok` of
            // a first copy sent before it, when the `rs` was a surplus answer: the `rs` that
            // answers the new copy then tells, and counts it.)
            self.stats.stray_oks += 1;
            return;
        }
        self.out_of_step = 0;
        match refusal {
            None => {
                self.accept_next();
                self.run += 1;
                if self.run >= self.cap && self.cap < self.config.window.lines {
                    self.cap += 1;
                    self.run = 0;
                }
            }
            Some((code, text)) if code < FIRST_COMMAND_CODE => {
                // The G-code parser refused what it received: a damaged scrap of a line (the
                // controller still expects the same line), or a line damaged past its checksum
                // (the controller skipped it). Not counted; the next `rs` tells.
                let line = self.accepted + 1;
                self.uncounted = Some(match self.uncounted.take() {
                    Some((first, count, c, t)) => (first, count + 1, c, t),
                    None => (line, 1, code, text),
                });
            }
            Some((code, text)) => {
                self.accept_next();
                if self.accepted <= self.pushed {
                    self.report_refusal(self.accepted, code, text.clone());
                    if is_alarm_code(code) {
                        self.alarm(code, text);
                        return;
                    }
                }
            }
        }
        self.check_done();
    }

    /// The controller took line `accepted + 1`.
    fn accept_next(&mut self) {
        self.accepted += 1;
        self.recovering = false;
    }

    fn report_refusal(&mut self, number: u32, code: u16, text: String) {
        self.stats.refused += 1;
        self.events.push_back(Event::Refused { number, code, text });
    }

    /// An authoritative `rs n`: lines before `n` are accepted. If the count of accepted lines
    /// falls short of that while parser refusals were not counted, those were lines skipped by
    /// the controller: report them.
    fn settle_uncounted(&mut self, n: u32) {
        let Some((first, count, code, text)) = self.uncounted.take() else {
            return;
        };
        let skipped = (n - 1).saturating_sub(self.accepted).min(count);
        for k in 0..skipped {
            let number = first + k;
            if number <= self.pushed {
                self.report_refusal(number, code, format!("{text} (damaged on the link)"));
            }
        }
        self.stats.refusals_dismissed += u64::from(count - skipped);
    }

    fn on_resend(&mut self, now: Instant, n: u32) {
        self.pending_notice = None;
        if let Some((code, text, _)) = self.pending_fault.take() {
            self.alarm(code, text);
        }
        match self.phase {
            Phase::Handshake => {
                // The M110 was damaged: send it again now.
                self.handshake_sent_at = None;
                return;
            }
            Phase::Streaming => {}
            _ => return,
        }
        self.answered(now);
        if n == 0 || n > self.sent_through + 1 {
            self.out_of_step += 1;
            if self.out_of_step as usize > self.config.window.lines + 2 {
                self.phase = Phase::Failed;
                self.events.push_back(Event::OutOfStep { asked: n });
            }
            return;
        }
        self.out_of_step = 0;
        self.settle_uncounted(n);
        self.accepted = n - 1;
        self.next = self.next.max(n);
        let resent_alone = self.recovering && self.in_flight.is_empty() && self.next == n + 1;
        self.recovering = true;
        if n == self.next || self.in_flight.iter().any(|s| s.number == n) {
            self.stats.resends_absorbed += 1;
        } else if resent_alone {
            // The copy of line `n` sent alone was refused, or this `rs` is the second answer to
            // a line cut in two and the copy's answer is still coming: only the quiet time-out
            // tells, and then sends it again.
            self.stats.resends_deferred += 1;
        } else {
            self.stats.rewinds += 1;
            self.stats.lines_resent += u64::from(self.next - n);
            self.next = n;
            self.cap = (self.cap / 2).max(2).min(self.config.window.lines.max(1));
            self.run = 0;
            self.events.push_back(Event::Rewound { from: n });
        }
        self.check_done();
    }

    fn check_done(&mut self) {
        if self.finished && self.accepted as usize >= self.lines.len() {
            self.phase = Phase::Done;
            self.events.push_back(Event::Done);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use forja_protocol::gcode::{Line, LineNumbering, Recovery};
    use forja_protocol::stream::{Decoder, Event as StreamEvent};

    fn lines_of(out: &[u8]) -> Vec<String> {
        String::from_utf8(out.to_vec())
            .unwrap()
            .split("\r\n")
            .filter(|l| !l.is_empty())
            .map(str::to_string)
            .collect()
    }

    fn synced(config: Config, texts: &[&str]) -> (Streamer, Instant) {
        let now = Instant::now();
        let mut s = Streamer::new(config);
        for t in texts {
            s.push(t).unwrap();
        }
        s.finish();
        let mut out = Vec::new();
        assert_eq!(s.transmit(now, &mut out), 1);
        assert_eq!(lines_of(&out), ["N0 M110 N0*125"]);
        assert!(
            out.starts_with(b"\r\n"),
            "a leading break ends any partial line"
        );
        s.receive(now, b"ok");
        assert_eq!(s.next_event(), Some(Event::Synchronised));
        (s, now)
    }

    #[test]
    fn the_window_limits_lines_and_bytes() {
        let config = Config {
            window: Window {
                bytes: 30,
                lines: 8,
            },
            ..Config::default()
        };
        let (mut s, now) = synced(config, &["G1 X1", "G1 X2", "G1 X3", "G1 X4"]);
        let mut out = Vec::new();
        // "N1 G1 X1*96\r\n" is 13 bytes: two fit in 30 bytes, three do not.
        assert_eq!(s.transmit(now, &mut out), 2);
        assert_eq!(s.in_flight(), 2);
        out.clear();
        assert_eq!(s.transmit(now, &mut out), 0, "the window is full");
        s.receive(now, b"ok");
        assert_eq!(s.accepted(), 1);
        assert_eq!(s.transmit(now, &mut out), 1);
        assert_eq!(lines_of(&out), ["N3 G1 X3*96"]);
    }

    #[test]
    fn a_resend_rewinds_once_and_absorbs_the_answers_of_lines_in_flight() {
        let config = Config {
            window: Window {
                bytes: 52,
                lines: 8,
            },
            ..Config::default()
        };
        let texts = ["G1 X1", "G1 X2", "G1 X3", "G1 X4", "G1 X5", "G1 X6"];
        let (mut s, now) = synced(config, &texts);
        let mut out = Vec::new();
        assert_eq!(s.transmit(now, &mut out), 4); // 1 2 3 4
        s.receive(now, b"ok"); // 1
        s.receive(now, b"// E2 checksum-mismatch");
        s.receive(now, b"rs 2"); // 2 damaged
        s.receive(now, b"ok");
        assert_eq!(s.next_event(), Some(Event::Rewound { from: 2 }));
        out.clear();
        // Until a line is accepted, only the line asked for goes, alone.
        assert_eq!(s.transmit(now, &mut out), 1);
        assert_eq!(lines_of(&out), ["N2 G1 X2*96"]);
        s.receive(now, b"rs 2"); // 3, out of order
        s.receive(now, b"ok");
        s.receive(now, b"rs 2"); // 4, out of order
        s.receive(now, b"ok");
        out.clear();
        assert_eq!(s.transmit(now, &mut out), 0);
        assert_eq!(s.next_event(), None, "no second rewind");
        assert_eq!(s.stats().resends_absorbed, 2);
        s.receive(now, b"ok"); // 2
        assert_eq!(s.accepted(), 2);
        out.clear();
        assert_eq!(s.transmit(now, &mut out), 4, "the window is open again");
        for _ in 0..4 {
            s.receive(now, b"ok"); // 3 4 5 6
            out.clear();
            s.transmit(now, &mut out);
        }
        for _ in 0..1 {
            s.receive(now, b"ok"); // closing
            out.clear();
            s.transmit(now, &mut out);
        }
        assert_eq!(s.phase(), Phase::Done);
        assert_eq!(s.accepted(), 6);
        assert_eq!(s.stats().rewinds, 1);
    }

    #[test]
    fn refusals_are_reported_with_their_line_and_alarms_stop_the_job() {
        let (mut s, now) = synced(Config::default(), &["G1 X1", "G1 X999", "G1 X2"]);
        let mut out = Vec::new();
        s.transmit(now, &mut out);
        s.receive(now, b"ok");
        s.receive(now, b"echo:E124 soft-limit X");
        s.receive(now, b"ok");
        assert_eq!(
            s.next_event(),
            Some(Event::Refused {
                number: 2,
                code: 124,
                text: "soft-limit X".into()
            })
        );
        assert_eq!(s.phase(), Phase::Streaming);
        // An unsolicited `Error:`: no `ok` follows within the grace time.
        s.receive(now, b"Error:E150 hard-limit X");
        assert_eq!(s.phase(), Phase::Streaming);
        s.poll(now + Duration::from_secs(1));
        assert_eq!(
            s.next_event(),
            Some(Event::Alarm {
                code: 150,
                text: "hard-limit X".into()
            })
        );
        assert_eq!(s.phase(), Phase::Alarm);
        out.clear();
        assert_eq!(s.transmit(now, &mut out), 0);
    }

    #[test]
    fn a_locked_machine_stops_the_job_at_its_first_refusal() {
        let (mut s, now) = synced(Config::default(), &["G1 X1", "G1 X2"]);
        let mut out = Vec::new();
        s.transmit(now, &mut out);
        s.receive(now, b"echo:E125 alarm-locked");
        s.receive(now, b"ok");
        assert!(matches!(
            s.next_event(),
            Some(Event::Refused { number: 1, .. })
        ));
        assert!(matches!(
            s.next_event(),
            Some(Event::Alarm { code: 125, .. })
        ));
        assert_eq!(s.phase(), Phase::Alarm);
    }

    #[test]
    fn the_handshake_repeats_and_gives_up() {
        let config = Config {
            handshake_attempts: 3,
            ..Config::default()
        };
        assert!(config.quiet_timeout < config.reply_timeout);
        let mut s = Streamer::new(config);
        s.push("G1 X1").unwrap();
        let t0 = Instant::now();
        let mut out = Vec::new();
        assert_eq!(s.transmit(t0, &mut out), 1);
        assert_eq!(s.transmit(t0, &mut out), 0);
        assert_eq!(s.poll_at(), Some(t0 + config.handshake_interval));
        s.receive(t0, b"rs 57");
        s.receive(t0, b"ok");
        assert_eq!(s.transmit(t0, &mut out), 1, "resent at once after an rs");
        let t1 = t0 + config.handshake_interval;
        assert_eq!(s.transmit(t1, &mut out), 1);
        let t2 = t1 + config.handshake_interval;
        assert_eq!(s.transmit(t2, &mut out), 0);
        assert_eq!(s.phase(), Phase::Failed);
        assert_eq!(s.next_event(), Some(Event::NoAnswer));
    }

    #[test]
    fn a_restart_during_the_job_fails_it() {
        let (mut s, now) = synced(Config::default(), &["G1 X1", "G1 X2"]);
        let mut out = Vec::new();
        s.transmit(now, &mut out);
        s.receive(now, b"ok");
        s.receive(now, b"start");
        assert_eq!(s.phase(), Phase::Failed);
        assert_eq!(s.next_event(), Some(Event::Restarted));
    }

    #[test]
    fn a_stall_resends_the_first_line_not_accepted() {
        let (mut s, t0) = synced(Config::default(), &["G1 X1", "G1 X2", "G1 X3"]);
        let mut out = Vec::new();
        s.transmit(t0, &mut out);
        s.receive(t0, b"ok");
        let t1 = t0 + Duration::from_secs(11);
        assert!(s.poll_at().unwrap() <= t1);
        s.poll(t1);
        assert_eq!(s.next_event(), Some(Event::Stalled { from: 2 }));
        out.clear();
        s.transmit(t1, &mut out);
        assert!(lines_of(&out)[0].starts_with("N2 "));
    }

    #[test]
    fn the_closing_line_or_the_rs_after_it_ends_the_job() {
        let (mut s, now) = synced(Config::default(), &["G1 X1"]);
        let mut out = Vec::new();
        s.transmit(now, &mut out);
        assert_eq!(lines_of(&out), ["N1 G1 X1*96", "N2*124"]);
        s.receive(now, b"ok");
        assert_eq!(s.phase(), Phase::Streaming);
        s.receive(now, b"rs 3");
        s.receive(now, b"ok");
        assert_eq!(s.phase(), Phase::Done);
        assert_eq!(s.accepted(), 1);
    }

    /// A line cut in two gets two answers. Read one answer at a time, each followed by what the
    /// window allows, the surplus answer must not become a line sent: it would keep one answer
    /// too many in the pipe for ever, each `rs` sending a line that earns another (a storm).
    #[test]
    fn a_surplus_answer_is_dropped_not_turned_into_a_line() {
        let config = Config {
            window: Window {
                bytes: 256,
                lines: 2,
            },
            ..Config::default()
        };
        let (mut s, now) = synced(config, &["G1 X1", "G1 X2"]);
        let mut sent = Vec::new();
        let mut turn = |s: &mut Streamer, reply: &[u8]| {
            if !reply.is_empty() {
                s.receive(now, reply);
            }
            let mut out = Vec::new();
            s.transmit(now, &mut out);
            sent.extend(lines_of(&out).into_iter().map(|l| l[..2].to_string()));
        };
        turn(&mut s, b""); // 1 2
        turn(&mut s, b"rs 1"); // 1 cut in two: its first part
        turn(&mut s, b"ok");
        turn(&mut s, b"rs 1"); // its second part: the surplus
        turn(&mut s, b"ok");
        turn(&mut s, b"rs 1"); // 2, out of order
        turn(&mut s, b"ok");
        turn(&mut s, b"ok"); // the copy of 1
        assert_eq!(s.accepted(), 1);
        turn(&mut s, b"ok"); // 2
        turn(&mut s, b"ok"); // the closing line
        assert_eq!(sent, ["N1", "N2", "N1", "N2", "N3"]);
        assert_eq!(s.phase(), Phase::Done);
        assert_eq!(s.in_flight(), 0);
        assert_eq!(s.stats().resends_deferred, 1);
    }

    /// A line whose terminators were lost waits in the controller until more bytes come: after
    /// a quiet time with lines in flight, one lone line end goes out, once per silence.
    #[test]
    fn a_silence_with_lines_in_flight_is_nudged_once() {
        let (mut s, now) = synced(Config::default(), &["G1 X1"]);
        let mut out = Vec::new();
        s.transmit(now, &mut out);
        let quiet = now + Config::default().quiet_timeout;
        assert_eq!(s.poll_at(), Some(quiet));
        s.poll(quiet);
        out.clear();
        assert_eq!(s.transmit(quiet, &mut out), 0);
        assert_eq!(out, b"\r\n");
        s.poll(quiet + Duration::from_secs(1));
        out.clear();
        s.transmit(quiet + Duration::from_secs(1), &mut out);
        assert!(out.is_empty(), "one nudge per silence");
        assert_eq!(s.stats().nudges, 1);
        s.receive(quiet, b"ok");
        s.receive(quiet, b"ok");
        assert_eq!(s.phase(), Phase::Done);
    }

    #[test]
    fn stray_oks_cannot_run_ahead_of_what_was_sent() {
        let (mut s, now) = synced(Config::default(), &["G1 X1", "G1 X2"]);
        s.receive(now, b"ok");
        s.receive(now, b"ok");
        assert_eq!(s.accepted(), 0);
        let mut out = Vec::new();
        s.transmit(now, &mut out);
        s.receive(now, b"rs 1");
        s.receive(now, b"ok");
        assert_eq!(s.next_event(), Some(Event::Rewound { from: 1 }));
        s.receive(now, b"ok");
        s.receive(now, b"ok");
        assert_eq!(s.accepted(), 0, "no line of ours was resent yet");
    }

    /// A controller as the protocol crate specifies it: it decodes the mixed stream, checks
    /// numbering, and answers every record.
    struct ModelController {
        decoder: Decoder,
        numbering: LineNumbering,
        /// The numbers of the lines run, in order.
        executed: Vec<u32>,
        /// What they held: their words in canonical form.
        bodies: Vec<Vec<u8>>,
    }

    /// The canonical form of a line's words, without number or check.
    fn body_of(line: &Line<'_>) -> Vec<u8> {
        let bare = Line::from_parts(None, line.words(), line.text_arg()).unwrap();
        let mut out = [0u8; 512];
        let n = bare.encode(&mut out).unwrap();
        out[..n].to_vec()
    }

    impl ModelController {
        fn new() -> Self {
            Self {
                decoder: Decoder::new(),
                numbering: LineNumbering::new(),
                executed: Vec::new(),
                bodies: Vec::new(),
            }
        }

        fn feed(&mut self, bytes: &[u8]) -> Vec<String> {
            let mut replies = Vec::new();
            let numbering = &mut self.numbering;
            let executed = &mut self.executed;
            let bodies = &mut self.bodies;
            self.decoder.feed_all(bytes, |event| {
                let recovery = match event {
                    StreamEvent::Line(bytes) => match Line::parse(bytes) {
                        Ok(line) => match numbering.accept(&line) {
                            Ok(()) => {
                                if let Some(n) = line
                                    .number()
                                    .filter(|_| !line.is_empty() && !line.is_command(b'M', 110))
                                {
                                    executed.push(n);
                                    bodies.push(body_of(&line));
                                }
                                replies.push("ok".to_string());
                                None
                            }
                            Err(e) => Some(numbering.recover(&e)),
                        },
                        Err(e) => Some(numbering.recover(&e)),
                    },
                    StreamEvent::Garbage { .. } => Some(numbering.recover_garbage()),
                    StreamEvent::TooLong { .. } => {
                        Some(numbering.recover(&forja_protocol::gcode::LineError::TooLong))
                    }
                    _ => None,
                };
                match recovery {
                    Some(Recovery::Resend(n)) => {
                        replies.push(format!("rs {n}"));
                        replies.push("ok".into());
                    }
                    Some(Recovery::Drop) => {}
                    Some(_) => {
                        replies.push("echo:E8 refused".into());
                        replies.push("ok".into());
                    }
                    None => {}
                }
            });
            replies
        }
    }

    /// A tiny xorshift generator: the same seed gives the same faults.
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn chance(&mut self, p: f64) -> bool {
            (self.next() >> 11) as f64 / (1u64 << 53) as f64 <= p
        }
    }

    /// Stream `texts` through a damaging link (bit flips and drops towards the controller,
    /// in chunks) and return the numbers of the lines the controller ran or refused (with a
    /// report to the sender). (What they hold is
    /// not compared: two flips of the same bit in one line cancel in the protocol's XOR
    /// checksum, which no sender can detect.)
    fn run_faulty(
        texts: &[String],
        seed: u64,
        corrupt: f64,
        drop: f64,
        window: Window,
    ) -> (Vec<u32>, Vec<u32>, Stats) {
        let (ran, _, refused, stats) = run_checked(texts, seed, corrupt, drop, window, Check::Xor);
        (ran, refused, stats)
    }

    /// [`run_faulty`] with the check of choice, also giving what the lines run held.
    fn run_checked(
        texts: &[String],
        seed: u64,
        corrupt: f64,
        drop: f64,
        window: Window,
        check: Check,
    ) -> (Vec<u32>, Vec<Vec<u8>>, Vec<u32>, Stats) {
        let mut rng = Rng(seed | 1);
        let config = Config {
            window,
            check,
            ..Config::default()
        };
        let mut s = Streamer::new(config);
        for t in texts {
            s.push(t).unwrap();
        }
        s.finish();
        let mut c = ModelController::new();
        let mut refused = Vec::new();
        let mut now = Instant::now();
        let mut wire: VecDeque<u8> = VecDeque::new();
        let mut replies: VecDeque<String> = VecDeque::new();
        for _ in 0..200_000 {
            let mut out = Vec::new();
            s.transmit(now, &mut out);
            for b in out {
                if rng.chance(drop) {
                    continue;
                }
                let b = if rng.chance(corrupt) {
                    b ^ (1 << (rng.next() % 8))
                } else {
                    b
                };
                wire.push_back(b);
            }
            // The controller reads a chunk, then idles: a partial record is flushed on idle.
            let take = (rng.next() % 64) as usize;
            let chunk: Vec<u8> = (0..take).filter_map(|_| wire.pop_front()).collect();
            replies.extend(c.feed(&chunk));
            if wire.is_empty() && rng.chance(0.05) {
                let numbering = &mut c.numbering;
                if let Some(StreamEvent::Line(bytes)) = c.decoder.flush() {
                    let r = match Line::parse(bytes) {
                        Ok(line) => match numbering.accept(&line) {
                            Ok(()) => {
                                if let Some(n) = line
                                    .number()
                                    .filter(|_| !line.is_empty() && !line.is_command(b'M', 110))
                                {
                                    c.executed.push(n);
                                    c.bodies.push(body_of(&line));
                                }
                                "ok".to_string()
                            }
                            Err(e) => match numbering.recover(&e) {
                                Recovery::Resend(n) => format!("rs {n}"),
                                _ => "ok".into(),
                            },
                        },
                        Err(e) => match numbering.recover(&e) {
                            Recovery::Resend(n) => format!("rs {n}"),
                            Recovery::Drop => String::new(),
                            _ => "ok".into(),
                        },
                    };
                    if r.starts_with("rs ") {
                        replies.push_back(r);
                        replies.push_back("ok".into());
                    } else if !r.is_empty() {
                        replies.push_back(r);
                    }
                }
            }
            for _ in 0..(rng.next() % 4) {
                if let Some(r) = replies.pop_front() {
                    s.receive(now, r.as_bytes());
                }
            }
            now += Duration::from_millis(1);
            s.poll(now);
            while let Some(event) = s.next_event() {
                if let Event::Refused { number, .. } = event {
                    refused.push(number);
                }
            }
            if s.phase() == Phase::Done {
                return (c.executed, c.bodies, refused, s.stats());
            }
            assert!(
                matches!(s.phase(), Phase::Handshake | Phase::Streaming),
                "{:?}",
                s.phase()
            );
        }
        panic!("the job did not finish: {:?}", s.stats());
    }

    #[test]
    fn every_line_runs_exactly_once_in_order_over_a_damaging_link() {
        let texts: Vec<String> = (0..400)
            .map(|i| format!("G1X{}.{}Y-{}F3000", i, i % 10, i * 3 + 1))
            .collect();
        for seed in 1..=12 {
            for window in [Window::UART, Window::PING_PONG, Window::TCP] {
                let (ran, refused, stats) = run_faulty(&texts, seed, 0.002, 0.0005, window);
                let context = format!("seed {seed}, window {window:?}, {stats:?}");
                assert!(
                    ran.windows(2).all(|w| w[0] < w[1]),
                    "{context}: out of order"
                );
                // Damage that the XOR checksum cannot see (two flips of the same bit) can
                // still make a line invalid: the controller refuses it, the sender reports
                // it, and it has had its turn.
                let mut all: Vec<u32> = ran.iter().chain(&refused).copied().collect();
                all.sort_unstable();
                let expected: Vec<u32> = (1..=texts.len() as u32).collect();
                assert!(all == expected, "{context}: refused {refused:?}");
                assert!(stats.lines_sent < 2 * texts.len() as u64, "{context}");
            }
        }
    }

    #[test]
    fn with_the_crc_every_line_runs_exactly_once_in_order_as_sent() {
        // Damage the XOR misses (two flips of the same bit, two equal bytes lost) would run a
        // wrong line, or a copy of the line before under the next number ("one line ran twice
        // and one was skipped"). The CRC-16 refuses it: every line runs once, as sent, in order.
        let texts: Vec<String> = (0..400)
            .map(|i| format!("G1X{}.{}Y-{}F3000", i, i % 10, i * 3 + 1))
            .collect();
        let expected: Vec<Vec<u8>> = texts
            .iter()
            .map(|t| body_of(&Line::parse(t.as_bytes()).unwrap()))
            .collect();
        for seed in 1..=12 {
            for window in [Window::UART, Window::PING_PONG, Window::TCP] {
                let (ran, bodies, refused, stats) =
                    run_checked(&texts, seed, 0.01, 0.005, window, Check::Crc16);
                let context = format!("seed {seed}, window {window:?}, {stats:?}");
                let numbers: Vec<u32> = (1..=texts.len() as u32).collect();
                assert_eq!(ran, numbers, "{context}");
                assert!(refused.is_empty(), "{context}: refused {refused:?}");
                assert!(
                    bodies == expected,
                    "{context}: a line ran other words than sent"
                );
            }
        }
    }

    #[test]
    fn a_very_damaging_link_still_runs_no_line_twice() {
        // About one line in three is damaged: the reply accounting goes astray, which costs
        // resends, but the controller's numbering keeps every line to one run.
        let texts: Vec<String> = (0..400)
            .map(|i| format!("G1X{}.{}Y-{}F3000", i, i % 10, i * 3 + 1))
            .collect();
        for seed in 1..=12 {
            for window in [Window::UART, Window::PING_PONG, Window::TCP] {
                let (ran, refused, stats) = run_faulty(&texts, seed, 0.01, 0.003, window);
                let context = format!("seed {seed}, window {window:?}, {stats:?}");
                assert!(
                    ran.windows(2).all(|w| w[0] < w[1]),
                    "{context}: twice or out of order"
                );
                let missing = texts.len() - ran.len();
                assert!(
                    missing <= refused.len(),
                    "{context}: {missing} lines did not run"
                );
                assert!(stats.lines_sent < 8 * texts.len() as u64, "{context}");
            }
        }
    }
}
