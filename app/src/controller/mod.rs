//! The controller: the one code path from a host link to the motion kernel, on every board.
//!
//! A [`Controller`] owns the thread side of a machine: the stream [`Decoder`] of the link, its
//! [`LineNumbering`], the [`Kernel`], the [`Job`] with its [`ProgramStore`], the [`Settings`]
//! and their [`RecordStorage`], and the board's [`Peripherals`] (its description of its
//! devices: heaters, fans, spindle, coolant, motor power, end-stops). It speaks both protocols
//! of the link at once — RepRap G-code lines and the 53-byte frames — and answers every line
//! and frame as `docs/protocol.md` ("Controller replies") describes. The kernel's effects go
//! straight to the devices, with the G-code rules applied here (see [`peripherals`]).
//!
//! It is sans-IO and portable: `no_std`, no allocation, no panics, no clock. The board calls
//! [`Controller::poll`] from its thread context (a task or the main loop) with the time and the
//! link (`embedded-io` `Read + ReadReady + Write`), arms the step alarm at what it returns, and
//! calls it again at the latest at [`PollOutcome::wake_at`], which is never later than the
//! kernel allows while the machine moves (`Kernel::poll_within_ms`: half of the motion its step
//! queue holds, at most half of `queue_lead_ms`).
//!
//! ```text
//!  board thread                                    controller
//!  ───────────                                     ──────────
//!  boot(link)                                  ──► "start"
//!  on_connect(link)   (links with a session)   ──► frame 54
//!  keep_alive(n, link) (session::LinkSession)  ──► frame 55
//!  loop {
//!    out = poll(clock.now(), link)              ──► kernel.poll, job, heaters, waits,
//!    if let Some(at) = out.arm_alarm {              read the link, answer lines and frames
//!        alarm.set_alarm(at) }
//!    sleep until out.wake_at or the link has bytes
//!  }
//! ```
//!
//! # Flow control
//!
//! The link is read all the time, so that its realtime records act at once whatever the
//! G-code lines do: each record is looked at as it arrives.
//!
//! - **Frames** (pause, stop, start, positions and progress on request, …) are carried out at
//!   once, and so is **`M112`**, recognised by its command word alone (after an optional `N`
//!   number, whatever its checksum), as Marlin's emergency parser does: the machine stops and
//!   `Error:E153 emergency-stop` goes out; every line received before it and not yet taken is
//!   then answered in order without being run (`echo:E125 alarm-locked` then `ok`; a `G28`,
//!   `G4`, `M109`, `M190` or `M116` that was waiting gets its `ok`, since it ran), and the
//!   `M112` line gets its `ok` last, after its number was checked like any line's.
//! - **Frame `Stop` and frame `Reset`** likewise answer every line received before them and
//!   not yet taken in order without running it (`echo:E198 stopped` then `ok`, with the same
//!   exceptions as after `M112`), so that nothing sent before the stop moves the machine after
//!   it: a waiting line damaged on the link is refused too, not asked again, its number used
//!   up. Lines received after the frame run as usual.
//! - **`M108`** ends an `M109`/`M190`/`M116` wait (of the link or of the stored program) at
//!   once, and **`M410`** stops the motion as frame `Stop` does; the line itself then waits its
//!   turn and gets its `ok` in order.
//! - **Other G-code lines** run at once when nothing is waiting. When the kernel answers
//!   [`Reply::Busy`](forja_motion::Reply::Busy) (the planner is full, an effect waits for the motion
//!   before it, `M226` paused the machine), the line is copied aside and offered again at each
//!   poll; `G28` waits for the end of its homing cycle, `G4` for the motion before it and its
//!   dwell (`echo:busy: processing` every 2 s meanwhile), `M109`, `M190` and `M116` for the
//!   heaters (with a ` T:… /… B:… /…` report every [`ControllerConfig::report_period_ms`]).
//!   Meanwhile the lines that
//!   follow go to a receive queue, in order, with over-long lines and runs of garbage: each is
//!   checked (syntax, line number, checksum) and answered only when its turn comes, exactly as
//!   if it arrived then, so each gets exactly one `ok` (or `rs`), in the order received, and
//!   runs once.
//!
//! The queue holds [`READ_AHEAD_BYTES`] bytes of lines (each counted with one terminator) and
//! room for one line more; the link is read only while a whole line still fits, after which the
//! link's own flow control (the UART queue, TCP) holds the host back. So the guarantee that a
//! realtime record acts at once holds for a host that keeps at most [`READ_AHEAD_BYTES`] bytes
//! of lines sent and not answered: one line in flight (Printrun, OctoPrint) or character
//! counting, as for grbl's receive buffer. A host that sends further ahead loses nothing, but
//! its realtime records wait behind its lines.
//!
//! # Wire codes
//!
//! The controller's own refusals use these codes (the motion block, 100–199):
//!
//! | code | name | meaning |
//! |---|---|---|
//! | 190 | `unknown-setting` | [`SettingError::UnknownKey`]: frame 00 named no setting |
//! | 191 | `bad-setting` | [`SettingError::BadValue`]: the value does not parse or is out of range |
//! | 192 | `bad-request` | [`ControllerError::BadRequest`]: frame 04 asked for a message not sent on request |
//! | 193 | `load-total` | [`ControllerError::LoadTotal`]: a 03 line's total differs from the program's |
//! | 194 | `no-device` | [`PeripheralError::NoDevice`] |
//! | 195 | `device-range` | [`PeripheralError::OutOfRange`] |
//! | 196 | `device-fault` | [`PeripheralError::Hardware`] |
//! | 197 | `queue-full` | [`ControllerError::QueueFull`]: a line found the receive queue full |
//! | 198 | `stopped` | [`ControllerError::Stopped`]: a line waiting when frame `Stop` or `Reset` came |
//!
//! Everything else carries the code of the layer that refused it: the protocol (1–99), the
//! kernel and jobs (100–189), the drivers (200–299).

mod files;
mod frames;
mod gcode;
mod grbl;
mod host;
pub mod peripherals;
mod planner_settings;
pub mod settings;
pub mod store;
mod text;
mod wire;

#[cfg(test)]
mod tests;

use core::fmt;

use embedded_io::{Read, ReadReady, Write};
use forja_hal_abstraction::stepper::StepTiming;
use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::time::{Duration, Instant};
use forja_protocol::error::WireError;
use forja_protocol::frame::{ControllerMessage, FRAME_LEN, is_frame};
use forja_protocol::gcode::{LineNumbering, MAX_LINE_LEN};
use forja_protocol::reply::Reply;
use forja_protocol::stream::{Decoder, Event, FeedResult};

pub use gcode::{Realtime, realtime};
pub use host::{BUSY_INTERVAL_MS, HostProgress, MESSAGE_LEN};
pub use peripherals::{NoPeripherals, PeripheralError, Peripherals, Reading, Temperatures};

use host::HostReports;
use peripherals::{Devices, HeatWait};
pub use settings::{
    AXIS_RECORDS, AxisField, DEFAULT_KEEP_ALIVE_MS, GLOBAL_RECORDS, Key, LoadReport,
    MAX_PASSWORD_LEN, MAX_SSID_LEN, MAX_STARTUP_LINE_LEN, NoStorage, SettingError, Settings,
};
pub use store::{HEADER_RECORD, LINE_RECORDS, RecordProgramStore};

use crate::job::{Job, JobState};
use forja_hal_abstraction::program::ProgramStore;
use forja_motion::error::Alarm;
use forja_motion::{Kernel, MachineState};

/// A refusal of the controller itself (not of the kernel, a store or a peripheral).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ControllerError {
    /// Frame 04 asked for a message type that is not sent on request (only 51 and 52 are).
    /// Code 192.
    BadRequest,
    /// A frame 03 line whose total is not the total of line 1 of the program being loaded.
    /// Code 193.
    LoadTotal,
    /// A G-code line arrived behind waiting lines and the receive queue had no room for it.
    /// [`Controller::poll`] reads the link only while a longest line fits, so only a decoder
    /// event outside that flow control could meet it. Code 197.
    QueueFull,
    /// A G-code line received before a frame `Stop` or `Reset` and not yet answered: it is
    /// answered without running. Code 198.
    Stopped,
}

impl WireError for ControllerError {
    fn code(&self) -> u16 {
        match self {
            Self::BadRequest => 192,
            Self::LoadTotal => 193,
            Self::QueueFull => 197,
            Self::Stopped => 198,
        }
    }

    fn name(&self) -> &'static str {
        match self {
            Self::BadRequest => "bad-request",
            Self::LoadTotal => "load-total",
            Self::QueueFull => "queue-full",
            Self::Stopped => "stopped",
        }
    }
}

impl fmt::Display for ControllerError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A host refused because another host is in control of the machine: code 300 `link-busy`, the
/// first of the boards' range (300–399). A board with several host links, or a link with
/// sessions, sends a refused host [`busy_refusal`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LinkBusy;

impl WireError for LinkBusy {
    fn code(&self) -> u16 {
        300
    }

    fn name(&self) -> &'static str {
        "link-busy"
    }
}

impl fmt::Display for LinkBusy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("another host is in control of this machine")
    }
}

/// Bytes of [`busy_refusal`] at most.
pub const BUSY_REFUSAL_LEN: usize = FRAME_LEN + 1 + 32;

/// The refusal of a host while another is in control, in both protocols, since the refused
/// host's is not known: frame 56 `Error:E300 link-busy` for a frame client, then the notice line
/// `// E300 link-busy` for a G-code host. Written into `out`; returns its length.
pub fn busy_refusal(out: &mut [u8; BUSY_REFUSAL_LEN]) -> usize {
    let Some((frame, rest)) = out.split_first_chunk_mut::<FRAME_LEN>() else {
        return 0;
    };
    let Some((end, notice)) = rest.split_first_mut() else {
        return 0;
    };
    if ControllerMessage::error(&LinkBusy).encode(frame).is_err() {
        return 0;
    }
    *end = b'\n';
    FRAME_LEN + 1 + Reply::notice(&LinkBusy).encode(notice).unwrap_or(0)
}

/// What the controller needs to know of its board, besides the kernel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ControllerConfig {
    /// `MACHINE_TYPE` in the `M115` answer: printable ASCII without spaces.
    pub machine_type: &'static str,
    /// `EXTRUDER_COUNT` in the `M115` answer; `T<n>` is accepted for `n` below it (or `T0`
    /// when 0).
    pub extruders: u8,
    /// The drivers' step timing the kernel was split with: settings that would need faster
    /// steps than it allows are refused.
    pub timing: StepTiming,
    /// How often the temperature loops run
    /// ([`TemperatureControl::run`](forja_hal_abstraction::device::TemperatureControl::run)),
    /// ms.
    pub peripheral_period_ms: u32,
    /// How close to its target a heater must be for `M109` and `M116` to go on, millidegrees
    /// (a heater that is off holds no wait).
    pub heater_tolerance_mc: i32,
    /// How often an `M109`/`M116` wait reports the temperatures, ms.
    pub report_period_ms: u32,
    /// A frame that arrived without a terminator — or, from a host that numbers its lines, a
    /// G-code line whose terminator was lost — is taken after the link has been quiet this
    /// long, ms: no byte arrived while the controller was reading (time it held its input back
    /// does not count).
    pub frame_flush_ms: u32,
}

impl ControllerConfig {
    /// `machine_type`, no extruder, `timing`; heaters every 100 ms and within 2 °C of their
    /// target for a wait to go on, temperature reports every second, unterminated frames (and
    /// numbered lines) taken after 20 ms of quiet.
    pub const fn new(machine_type: &'static str, timing: StepTiming) -> Self {
        Self {
            machine_type,
            extruders: 0,
            timing,
            peripheral_period_ms: 100,
            heater_tolerance_mc: 2_000,
            report_period_ms: 1000,
            frame_flush_ms: 20,
        }
    }
}

/// What one [`Controller::poll`] asks of the board.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PollOutcome {
    /// Arm the step alarm at this instant (an instant already past fires at once).
    pub arm_alarm: Option<Instant>,
    /// Poll again at the latest at this instant (sooner when the link has bytes); `None` when
    /// only new bytes need a poll.
    pub wake_at: Option<Instant>,
}

/// Counters of what the controller did, wrapping.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Stats {
    /// G-code lines answered with `ok` (taken, done, or refused with `echo:E<code>` first).
    pub oks: u32,
    /// G-code lines taken by the kernel (carried out or queued).
    pub executed: u32,
    /// `rs` replies sent.
    pub resends: u32,
    /// G-code lines refused (`echo:E<code>` or `echo:Unknown command` then `ok`).
    pub refused: u32,
    /// Frames received.
    pub frames: u32,
    /// Frame 56 sent.
    pub errors: u32,
    /// Runs of garbage skipped on the link.
    pub garbage_runs: u32,
    /// Stored program lines fed to the kernel by the job.
    pub program_lines: u32,
    /// Faults reported unsolicited (`Error:` or 56): alarms, thermal faults, `M112`.
    pub faults: u32,
}

/// What a controller is doing, whatever its machine's number of axes
/// ([`Controller::status`]): a snapshot for a board, a monitor or a test to read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Status {
    /// The kernel's state.
    pub state: MachineState,
    /// Whether every queued move has finished and no homing cycle runs.
    pub idle: bool,
    /// The job's state.
    pub job: JobState,
    /// The frame-52 figures.
    pub progress: crate::job::Progress,
    /// What the controller has done so far.
    pub stats: Stats,
    /// Whether G-code input is held ([`Controller::is_holding`]).
    pub holding: bool,
    /// Axes homed (bit `i` = axis `i`).
    pub homed: u8,
    /// Lines of the stored program.
    pub program_lines: u16,
    /// The stored program's total number of lines, 0 with no program; more than
    /// `program_lines` for an upload cut short, which does not run.
    pub program_total: u16,
}

/// A wrapping millisecond clock derived from the instants of [`Controller::poll`].
#[derive(Debug, Clone, Copy)]
struct MsClock {
    last: Instant,
    ms: u32,
    rem_ticks: u32,
    ticks_per_ms: u32,
}

impl MsClock {
    fn new(tick_hz: u32) -> Self {
        Self {
            last: Instant::from_ticks(0),
            ms: 0,
            rem_ticks: 0,
            ticks_per_ms: (tick_hz / 1000).max(1),
        }
    }

    /// Move to `now`. An instant before the last one (or one more than 2³¹ ticks later)
    /// counts as no time: the clock never stalls and never runs backwards.
    fn update(&mut self, now: Instant) {
        let d = now.signed_ticks_since(self.last);
        self.last = now;
        if d <= 0 {
            return;
        }
        let total = u64::from(self.rem_ticks) + d as u64;
        let tpm = u64::from(self.ticks_per_ms);
        self.ms = self.ms.wrapping_add((total / tpm) as u32);
        self.rem_ticks = (total % tpm) as u32;
    }

    /// The instant `ms` milliseconds after the last update.
    fn after(&self, ms: u32) -> Instant {
        let ticks = u64::from(ms) * u64::from(self.ticks_per_ms);
        self.last
            .wrapping_add(Duration::from_ticks(ticks.min(i32::MAX as u64) as u32))
    }

    /// Milliseconds from now to `at_ms` on the wrapping clock, 0 when past.
    fn until(&self, at_ms: u32) -> u32 {
        let d = at_ms.wrapping_sub(self.ms) as i32;
        d.max(0) as u32
    }

    fn reached(&self, at_ms: u32) -> bool {
        (self.ms.wrapping_sub(at_ms) as i32) >= 0
    }
}

/// Bytes read from the link and not yet given to the decoder.
const RX_LEN: usize = 128;

/// The link's input: a small receive buffer, and the tail of what the decoder has taken
/// since its last event (to see a frame that waits for a byte after it, or a line that waits
/// for its terminator).
struct Input {
    buf: [u8; RX_LEN],
    start: usize,
    end: usize,
    tail: [u8; FRAME_LEN],
    since_event: usize,
    /// Since when the controller has been reading the link and no byte came, ms.
    quiet_since_ms: u32,
    /// Input was held back (not read) at the end of the last poll.
    deaf: bool,
    /// The realtime commands taken out of the input, for the controller to act on.
    realtime: grbl::RealtimeQueue,
    /// Bytes of a record came since the last terminator (a `?` then is part of a line).
    line_open: bool,
    /// A soft reset (`0x18`) was taken out: the record in the decoder goes with it.
    reset_seen: bool,
}

impl Input {
    const fn new() -> Self {
        Self {
            buf: [0; RX_LEN],
            start: 0,
            end: 0,
            tail: [0; FRAME_LEN],
            since_event: 0,
            quiet_since_ms: 0,
            deaf: false,
            realtime: grbl::RealtimeQueue::new(),
            line_open: false,
            reset_seen: false,
        }
    }

    fn is_empty(&self) -> bool {
        self.start >= self.end
    }

    fn pending(&self) -> &[u8] {
        self.buf.get(self.start..self.end).unwrap_or(&[])
    }

    fn consume(&mut self, n: usize) {
        let taken = self
            .buf
            .get(self.start..self.start.saturating_add(n).min(self.end))
            .unwrap_or(&[]);
        // The tail's last bytes, then the last of those taken.
        let k = taken.len().min(FRAME_LEN);
        crate::bytes::shift_to_front(&mut self.tail, k, FRAME_LEN);
        if let (Some(dst), Some(src)) = (
            self.tail.get_mut(FRAME_LEN - k..),
            taken.get(taken.len() - k..),
        ) {
            dst.copy_from_slice(src);
        }
        self.since_event = self.since_event.saturating_add(taken.len());
        self.start += taken.len();
        if self.start >= self.end {
            self.start = 0;
            self.end = 0;
        }
    }

    /// Read what the link has, without blocking, and take its realtime bytes out (all of
    /// grbl's in the grbl dialect; `0x18` and a `?` between records in any). Returns whether
    /// bytes came.
    fn fill<L: Read + ReadReady>(
        &mut self,
        link: &mut L,
        now_ms: u32,
        grbl: bool,
        may_enter: bool,
    ) -> bool {
        if !self.is_empty() || !matches!(link.read_ready(), Ok(true)) {
            return false;
        }
        match link.read(&mut self.buf) {
            Ok(n) if n > 0 => {
                self.quiet_since_ms = now_ms;
                self.start = 0;
                self.end = self.take_realtime(n.min(RX_LEN), grbl, may_enter);
                true
            }
            _ => false,
        }
    }

    /// Move the realtime bytes of the first `n` bytes read to the realtime queue and the others
    /// to the front of the buffer; how many others. A soft reset drops the bytes before it; in
    /// the grbl dialect, other bytes above `0x7F` are dropped, as grbl drops them.
    fn take_realtime(&mut self, n: usize, grbl: bool, may_enter: bool) -> usize {
        let mut kept = 0;
        for i in 0..n {
            let Some(&b) = self.buf.get(i) else {
                break;
            };
            let grbl = grbl || self.reset_seen;
            // In a RepRap session only the grbl dialect's own bytes are realtime.
            let realtime =
                grbl::realtime_byte(b, grbl, self.line_open).filter(|_| grbl || may_enter);
            match realtime {
                Some(r) => {
                    if r == forja_protocol::grbl::Realtime::SoftReset {
                        kept = 0;
                        self.line_open = false;
                        self.reset_seen = true;
                    }
                    self.realtime.push(r);
                }
                // grbl throws away the other extended-ASCII bytes (a sender's UTF-8 encoding of
                // an override, `C2 91`, leaves its `C2` behind).
                None if grbl && b >= 0x80 => {}
                None => {
                    self.line_open = !matches!(b, b'\n' | b'\r');
                    if let Some(slot) = self.buf.get_mut(kept) {
                        *slot = b;
                    }
                    kept += 1;
                }
            }
        }
        kept
    }

    /// Whether a complete frame may be waiting in the decoder for a byte after it.
    fn frame_waiting(&self) -> bool {
        self.is_empty() && self.since_event >= FRAME_LEN - 1 && is_frame(&self.tail)
    }

    /// Whether the decoder holds the start of a record that waits for its terminator (or for
    /// the byte after a frame).
    fn unterminated(&self) -> bool {
        self.is_empty() && self.since_event > 0 && !matches!(self.tail.last(), Some(b'\n' | b'\r'))
    }

    fn event_seen(&mut self) {
        self.since_event = 0;
    }

    fn clear(&mut self) {
        *self = Self::new();
    }
}

/// A G-code line kept aside (its bytes, as received).
#[derive(Clone, Copy)]
struct LineBuf {
    buf: [u8; MAX_LINE_LEN],
    len: usize,
}

impl LineBuf {
    const EMPTY: Self = Self {
        buf: [0; MAX_LINE_LEN],
        len: 0,
    };

    fn new(bytes: &[u8]) -> Self {
        let mut buf = [0u8; MAX_LINE_LEN];
        let len = bytes.len().min(MAX_LINE_LEN);
        if let (Some(dst), Some(src)) = (buf.get_mut(..len), bytes.get(..len)) {
            dst.copy_from_slice(src);
        }
        Self { buf, len }
    }

    fn bytes(&self) -> &[u8] {
        self.buf.get(..self.len).unwrap_or(&[])
    }
}

/// Bytes of G-code lines (each counted with one terminator) that a host may keep sent and not
/// answered while the controller still reads every byte it sends at once: the limit of the
/// realtime guarantee (see the module documentation, "Flow control").
pub const READ_AHEAD_BYTES: usize = 768;

/// The longest entry of the receive queue: a line of [`MAX_LINE_LEN`] bytes and its terminator.
const MAX_ENTRY: usize = MAX_LINE_LEN + 1;

/// The receive queue: the read-ahead window and room for one longest line, so that reading
/// goes on as long as the host keeps within the window.
const LINE_QUEUE_LEN: usize = READ_AHEAD_BYTES + MAX_ENTRY;

/// The queue entry of a line over [`MAX_LINE_LEN`] bytes (a control byte never starts a line).
const TOO_LONG: u8 = 0x01;

/// The queue entry of a run of garbage of control bytes alone.
const GARBAGE: u8 = 0x02;

/// The queue entry of a run of garbage that held printable bytes too.
const GARBAGE_TEXT: u8 = 0x03;

/// A record the decoder dropped: answered as it arrives, or in its turn behind waiting lines
/// (the resend it may ask for must name the line expected then).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Dropped {
    /// A line over [`MAX_LINE_LEN`] bytes.
    TooLong,
    /// A run of garbage; `text` when it held printable bytes.
    Garbage {
        /// Printable bytes were among it.
        text: bool,
    },
}

/// One entry of the receive queue, taken out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Queued {
    /// A G-code line, as received, not yet checked (its bytes in the buffer given to
    /// [`LineQueue::pop`]).
    Line,
    /// A record dropped here.
    Dropped(Dropped),
}

/// The receive queue: what arrived behind a waiting G-code line, in order, for its turn. A
/// ring of bytes: a line is stored with a `\n` after it (lines never hold one); over-long lines
/// and garbage runs as one control byte each.
struct LineQueue {
    buf: [u8; LINE_QUEUE_LEN],
    head: usize,
    len: usize,
}

impl LineQueue {
    const fn new() -> Self {
        Self {
            buf: [0; LINE_QUEUE_LEN],
            head: 0,
            len: 0,
        }
    }

    fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Bytes free in the read-ahead window (what a character-counting sender may still send).
    fn free_bytes(&self) -> usize {
        READ_AHEAD_BYTES.saturating_sub(self.len)
    }

    /// Drop every entry.
    fn clear(&mut self) {
        self.head = 0;
        self.len = 0;
    }

    /// Whether a longest line still fits.
    fn has_room(&self) -> bool {
        LINE_QUEUE_LEN.saturating_sub(self.len) >= MAX_ENTRY
    }

    fn push_byte(&mut self, b: u8) {
        if let Some(slot) = self.buf.get_mut((self.head + self.len) % LINE_QUEUE_LEN) {
            *slot = b;
            self.len += 1;
        }
    }

    fn pop_byte(&mut self) -> Option<u8> {
        if self.len == 0 {
            return None;
        }
        let b = self.buf.get(self.head).copied();
        self.head = (self.head + 1) % LINE_QUEUE_LEN;
        self.len -= 1;
        b
    }

    /// Queue a line; `false` (and nothing queued) when it does not fit or is not a line the
    /// decoder gives (empty, over [`MAX_LINE_LEN`], holding a terminator or a control byte first).
    fn push_line(&mut self, bytes: &[u8]) -> bool {
        let fits = LINE_QUEUE_LEN.saturating_sub(self.len) > bytes.len();
        let line = match bytes.first() {
            Some(&first) => {
                first >= b' '
                    && bytes.len() <= MAX_LINE_LEN
                    && !bytes.iter().any(|b| matches!(b, b'\n' | b'\r'))
            }
            None => false,
        };
        if !(fits && line) {
            return false;
        }
        for &b in bytes {
            self.push_byte(b);
        }
        self.push_byte(b'\n');
        true
    }

    /// Queue a dropped record, as its [`TOO_LONG`], [`GARBAGE`] or [`GARBAGE_TEXT`] byte;
    /// `false` when full.
    fn push_dropped(&mut self, dropped: Dropped) -> bool {
        if self.len >= LINE_QUEUE_LEN {
            return false;
        }
        self.push_byte(match dropped {
            Dropped::TooLong => TOO_LONG,
            Dropped::Garbage { text: false } => GARBAGE,
            Dropped::Garbage { text: true } => GARBAGE_TEXT,
        });
        true
    }

    /// Take the oldest entry; a line's bytes go to `line`.
    fn pop(&mut self, line: &mut LineBuf) -> Option<Queued> {
        match self.pop_byte()? {
            TOO_LONG => Some(Queued::Dropped(Dropped::TooLong)),
            GARBAGE => Some(Queued::Dropped(Dropped::Garbage { text: false })),
            GARBAGE_TEXT => Some(Queued::Dropped(Dropped::Garbage { text: true })),
            first => {
                line.len = 0;
                let mut b = first;
                while b != b'\n' {
                    if let Some(slot) = line.buf.get_mut(line.len) {
                        *slot = b;
                        line.len += 1;
                    }
                    match self.pop_byte() {
                        Some(next) => b = next,
                        None => break,
                    }
                }
                Some(Queued::Line)
            }
        }
    }
}

/// Why the link's G-code lines are held.
#[derive(Clone, Copy)]
enum Held {
    /// The line in `Link::held_line` (already checked for numbering) waits for the kernel to
    /// take it.
    Line,
    /// A `G28` runs the homing cycle; its `ok` is sent when the cycle ends, as a RepRap host
    /// expects (an `M114` after it then reports the homed position).
    Homing,
    /// A `G4` waits for the moves before it and its own dwell, as Marlin and grbl answer it:
    /// its `ok` is sent when the machine is at rest (a host that ends its job on that `ok`,
    /// CNCjs, ends it when the machine has).
    Dwell,
    /// A `G38.2`–`G38.5` probing move runs; its `ok` is sent when it ends, after the probe's
    /// report, as grbl answers it (a sender's probe macro reads `[PRB:…]` before it goes on).
    Probe,
    /// An `M109`/`M190`/`M116` waits for its heaters; its `ok` is sent when they are there.
    Heat {
        /// What it waits for.
        wait: HeatWait,
        /// When to send the next temperature report.
        next_report_ms: u32,
    },
}

/// The state of the link's session.
struct Link {
    numbering: LineNumbering,
    held: Option<Held>,
    held_line: LineBuf,
    /// What arrived behind the held line, for its turn.
    queue: LineQueue,
    /// The numbered line already asked for again after it arrived intact but not G-code, in
    /// the current numbering (an `M110` clears it).
    asked_again: Option<u32>,
    gcode_seen: bool,
    /// A line ran in the RepRap dialect: only a `$` line takes the link into the grbl dialect
    /// now (a damaged byte that reads `0x18` or `?` does not take a printer host's link there:
    /// a bit flip makes a `8` a ctrl-x).
    reprap_lines: bool,
    frames_seen: bool,
    session: bool,
    started: bool,
    /// The dialect the link speaks.
    dialect: grbl::Dialect,
    /// Its grbl state, in the grbl dialect.
    grbl: grbl::GrblLink,
}

impl Link {
    const fn new() -> Self {
        Self {
            dialect: grbl::Dialect::RepRap,
            grbl: grbl::GrblLink::new(),
            numbering: LineNumbering::new(),
            held: None,
            held_line: LineBuf::EMPTY,
            queue: LineQueue::new(),
            asked_again: None,
            gcode_seen: false,
            reprap_lines: false,
            frames_seen: false,
            session: false,
            started: false,
        }
    }

    /// Whether the next G-code line must wait its turn in the queue rather than be handled.
    fn lines_held(&self) -> bool {
        self.held.is_some() || !self.queue.is_empty()
    }

    /// Whether nothing more can be read until queued lines are taken: a longest line would
    /// not fit the queue.
    fn input_blocked(&self) -> bool {
        !self.queue.has_room()
    }
}

/// Everything but the decoder and the receive buffer, so that a decoded event (which borrows
/// the decoder) can be handled with `&mut self`.
struct Core<'q, const N: usize, const B: usize, const Q: usize, P, X, S> {
    kernel: Kernel<'q, N, B, Q>,
    job: Job,
    program: P,
    devices: Devices<X, N>,
    storage: S,
    settings: Settings<N>,
    config: ControllerConfig,
    link: Link,
    clock: MsClock,
    now: Instant,
    reported_alarm: Option<Alarm>,
    thermal: Option<PeripheralError>,
    job_heat: Option<HeatWait>,
    /// What the host set beside its lines, and the unrequested lines due to it.
    host: HostReports,
    next_peripherals_ms: u32,
    load_total: Option<u16>,
    /// The SD card as the link's host sees it (`files.rs`).
    card: files::Card,
    /// The slots of the coordinate table changed and not yet stored (written at rest).
    coords_unsaved: u16,
    /// grbl's check mode (`$C`): the lines are run through this preview of the machine and
    /// answered, never executed.
    check: Option<forja_motion::preview::Preview<N>>,
    /// Something was given to the kernel during this poll: poll it again before returning.
    taken: bool,
    stats: Stats,
}

/// The portable controller. See the [module documentation](self).
///
/// `N` axes, a planner of `B` blocks and a step queue of `Q` events (as the [`Kernel`]); `P`
/// keeps the uploaded program, `X` is the board's description of its devices
/// ([`Peripherals`]), `S` keeps the settings ([`NoStorage`] when the board has none).
///
/// Context: thread. No method blocks, except where the program store or the settings storage
/// block on a flash write (only on a frame 00 set or a frame 03, refused while the machine
/// moves).
pub struct Controller<'q, const N: usize, const B: usize, const Q: usize, P, X, S = NoStorage> {
    decoder: Decoder,
    input: Input,
    core: Core<'q, N, B, Q, P, X, S>,
}

impl<'q, const N: usize, const B: usize, const Q: usize, P, X>
    Controller<'q, N, B, Q, P, X, NoStorage>
where
    P: ProgramStore,
    X: Peripherals<N>,
{
    /// A controller over `kernel`, keeping the program in `program`, driving `peripherals`,
    /// with the settings of the kernel's configuration kept in RAM only (see
    /// [`Controller::with_settings`]).
    pub fn new(
        kernel: Kernel<'q, N, B, Q>,
        program: P,
        peripherals: X,
        config: ControllerConfig,
    ) -> Self {
        // Nothing is stored: the stored limits and coordinates `with_settings` applies are the
        // kernel's own.
        let settings = Settings::new(*kernel.config());
        Controller::with_settings(kernel, program, peripherals, config, settings, NoStorage)
    }
}

impl<'q, const N: usize, const B: usize, const Q: usize, P, X, S> Controller<'q, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// A controller over `kernel`, keeping the program in `program`, driving `peripherals`,
    /// with `settings` (normally from [`Settings::load`], the kernel having been built from
    /// [`Settings::machine`]) kept in `storage`: frame 00 writes go there, and the stored path
    /// limits and coordinate systems apply at once.
    pub fn with_settings(
        mut kernel: Kernel<'q, N, B, Q>,
        program: P,
        peripherals: X,
        config: ControllerConfig,
        settings: Settings<N>,
        mut storage: S,
    ) -> Self {
        // The stored path limits (`M204`, `M205 S T`): the kernel was built from the
        // machine configuration alone, and is idle.
        let machine = *kernel.config();
        let _ = kernel.set_planner_settings(&machine, settings.path_limits());
        let coords = grbl::load_coordinates(&mut storage, kernel.coordinates());
        kernel.set_coordinates(coords);
        let clock = MsClock::new(kernel.tick_hz());
        Self {
            decoder: Decoder::new(),
            input: Input::new(),
            core: Core {
                kernel,
                job: Job::new(),
                program,
                devices: Devices::new(peripherals),
                storage,
                settings,
                config,
                link: Link::new(),
                clock,
                now: Instant::from_ticks(0),
                reported_alarm: None,
                thermal: None,
                job_heat: None,
                host: HostReports::new(),
                next_peripherals_ms: 0,
                load_total: None,
                card: files::Card::new(),
                coords_unsaved: 0,
                check: None,
                taken: false,
                stats: Stats::default(),
            },
        }
    }

    /// Write `start` (once: later calls write nothing), then run grbl's startup lines (`$N0`,
    /// `$N1`, each echoed `>LINE:ok`) when some are stored and the machine is not in an alarm.
    /// Call it when the board has started, before the first [`Controller::poll`].
    pub fn boot<W: Write>(&mut self, out: &mut W) {
        if !self.core.link.started {
            self.core.link.started = true;
            let _ = wire::reply(out, &Reply::Start);
            self.core.power_on_startup_lines(out);
        }
    }

    /// A new host is on the link (a link with sessions: TCP, WiFi): forget the previous host's
    /// partial input, line numbering and held lines, and write frame 54.
    pub fn on_connect<W: Write>(&mut self, out: &mut W) {
        self.reset_link();
        self.core.link.session = true;
        wire::frame(out, &ControllerMessage::Connected);
    }

    /// `M112` from outside the link: a host of the board that is not in control (see
    /// [`realtime`]), a stop input. The machine stops as for an `M112` line — motion is cut,
    /// the stored program stops, heaters, fans, spindle and motors are shut down — the link's
    /// host is told of the fault on `out`, and the lines it had waiting are answered in order
    /// without running. It stays in alarm until a reset (`M999`, frame `Reset`).
    pub fn emergency_stop<W: Write>(&mut self, out: &mut W) {
        self.core.emergency_stop(out);
    }

    /// Write frame 55 with `counter` (from the board's
    /// [`LinkSession`](crate::session::LinkSession)).
    pub fn keep_alive<W: Write>(&mut self, counter: u32, out: &mut W) {
        wire::frame(out, &ControllerMessage::KeepAlive { counter });
    }

    /// Another host now speaks on the link (a link without sessions changed hands): forget the
    /// partial input, the line numbering (line 1 is expected next) and any held line, whose
    /// replies would go to the new host.
    pub fn reset_link(&mut self) {
        self.decoder.reset();
        self.input.clear();
        let started = self.core.link.started;
        self.core.link = Link::new();
        self.core.check = None;
        self.core.kernel.set_grbl_dialect(false);
        // An upload belongs to the host that sent its line 1 (or its `M28`).
        self.core.load_total = None;
        self.core.end_upload();
        self.core.link.started = started;
    }

    /// Thread-side work at `now`: run the kernel's thread side, watch for alarms and thermal
    /// faults, run the temperature loops, feed the stored program, end waits, then read the
    /// link and answer what it brings, as far as it can be handled now.
    ///
    /// Context: thread. Never blocks on the link (it reads only what `read_ready` announces).
    /// Call it again at the latest at the returned [`PollOutcome::wake_at`].
    pub fn poll<L: Read + ReadReady + Write>(&mut self, now: Instant, link: &mut L) -> PollOutcome {
        let core = &mut self.core;
        core.clock.update(now);
        core.now = now;
        core.taken = false;
        core.enable_motors_if_needed();
        let mut arm = core.kernel.poll(now);
        core.supervise(link);
        core.follow_spindle();
        core.serve_files(link);
        core.feed_job(link);
        core.store_coordinates();
        core.record_checkpoint(link);
        core.release_held(link);

        if self.input.deaf {
            // Quiet counts only while the controller reads: not while it held input back.
            self.input.quiet_since_ms = self.core.clock.ms;
        }
        loop {
            if self.core.link.input_blocked() {
                break;
            }
            let grbl = self.core.speaks_grbl();
            // grbl answers a blank line; the RepRap dialect has nothing to answer.
            self.decoder.set_blank_lines(grbl);
            let may_enter = !self.core.link.reprap_lines;
            let filled =
                self.input.is_empty() && self.input.fill(link, self.core.clock.ms, grbl, may_enter);
            self.act_on_realtime(link);
            if self.input.is_empty() && !filled {
                break;
            }
            if self.input.is_empty() {
                continue;
            }
            let window = self.input.pending();
            let FeedResult { event, remaining } = self.decoder.feed(window);
            let consumed = window.len() - remaining.len();
            self.input.consume(consumed);
            if let Some(event) = event {
                self.core.on_event(event, link);
                self.input.event_seen();
            }
        }
        let quiet = self.core.clock.ms.wrapping_sub(self.input.quiet_since_ms);
        let flush_ms = self.core.config.frame_flush_ms;
        if self.flush_due() && quiet >= flush_ms {
            while let Some(event) = self.decoder.flush() {
                self.core.on_event(event, link);
            }
            self.input.event_seen();
        }
        self.input.deaf = self.core.link.input_blocked();

        let core = &mut self.core;
        if core.taken {
            core.enable_motors_if_needed();
            arm = arm.or(core.kernel.poll(now));
        }
        let frame_wait = self
            .flush_due()
            .then(|| flush_ms.saturating_sub(quiet).max(1));
        PollOutcome {
            arm_alarm: arm,
            wake_at: self.core.wake_at(frame_wait),
        }
    }

    /// Act on the realtime commands taken out of the input, in order; a soft reset also drops
    /// the record the decoder holds (bytes before the reset in the same read were dropped as
    /// they were taken out).
    fn act_on_realtime<W: Write>(&mut self, out: &mut W) {
        if core::mem::take(&mut self.input.reset_seen) {
            self.decoder.reset();
        }
        while let Some(r) = self.input.realtime.pop() {
            self.core.on_realtime(r, out);
        }
    }

    /// Whether the decoder holds a record to take without its terminator once the link is
    /// quiet: a frame waiting for the byte after it, a numbered line whose check verifies (its
    /// terminator was lost), or, from a host that numbers its lines, the start of a numbered
    /// line, which fails its check and is asked again (never run), so that a stop-and-wait host
    /// is not left waiting. An unnumbered part of a line is never taken: a line cut by a pause
    /// (`G1 X1` … `00`, `M114` typed byte by byte) waits for its terminator.
    fn flush_due(&self) -> bool {
        if self.core.link.input_blocked() {
            return false;
        }
        if self.input.frame_waiting() {
            return true;
        }
        if !self.input.unterminated() {
            return false;
        }
        let partial = self.decoder.partial();
        let numbered_start = matches!(partial, [b'N' | b'n', d, ..] if d.is_ascii_digit());
        (numbered_start && self.core.link.numbering.is_numbered())
            || forja_protocol::gcode::is_checked_line(partial)
    }

    /// Take the controller apart: the kernel, the program store, the peripherals and the
    /// settings storage (a board that restarts, a test that inspects the flash).
    pub fn release(self) -> (Kernel<'q, N, B, Q>, P, X, S) {
        let c = self.core;
        (c.kernel, c.program, c.devices.parts, c.storage)
    }

    /// The kernel.
    pub fn kernel(&self) -> &Kernel<'q, N, B, Q> {
        &self.core.kernel
    }

    /// The kernel, to drive it directly (tests, board bring-up).
    pub fn kernel_mut(&mut self) -> &mut Kernel<'q, N, B, Q> {
        &mut self.core.kernel
    }

    /// The job running the stored program.
    pub fn job(&self) -> &Job {
        &self.core.job
    }

    /// The frame-52 figures of the job now.
    pub fn progress(&self) -> crate::job::Progress {
        self.core
            .job
            .progress(&self.core.kernel, &self.core.program)
    }

    /// The program store.
    pub fn program(&self) -> &P {
        &self.core.program
    }

    /// The program store, mutably.
    pub fn program_mut(&mut self) -> &mut P {
        &mut self.core.program
    }

    /// The peripherals.
    pub fn peripherals(&self) -> &X {
        &self.core.devices.parts
    }

    /// The peripherals, mutably.
    pub fn peripherals_mut(&mut self) -> &mut X {
        &mut self.core.devices.parts
    }

    /// The settings.
    pub fn settings(&self) -> &Settings<N> {
        &self.core.settings
    }

    /// The settings storage.
    pub fn storage_mut(&mut self) -> &mut S {
        &mut self.core.storage
    }

    /// The job progress the host announced last (`M73`).
    pub fn host_progress(&self) -> HostProgress {
        self.core.host.progress
    }

    /// The operator's message the host set last (`M117`; empty when none).
    pub fn message(&self) -> &str {
        self.core.host.message.as_str()
    }

    /// What the controller has done so far.
    pub fn stats(&self) -> Stats {
        self.core.stats
    }

    /// The decoder's counters of the link.
    pub fn link_stats(&self) -> forja_protocol::stream::Stats {
        self.decoder.stats()
    }

    /// The thermal fault that stopped the machine, until a reset.
    pub fn thermal_fault(&self) -> Option<PeripheralError> {
        self.core.thermal
    }

    /// Whether the link's G-code input waits (a line for room in the planner, `G28` for its
    /// homing cycle, `M109`/`M116` for the heaters, or lines in the receive queue for their
    /// turn).
    pub fn is_holding(&self) -> bool {
        self.core.link.lines_held()
    }

    /// Whether the host asked for reports every period (`M155 S`, `M27 S`): the controller
    /// owes it those, so its silence is not a sign that it left (OctoPrint sends nothing
    /// during a print from the card once the printer reports by itself).
    pub fn owes_reports(&self) -> bool {
        self.core.auto_reporting() || self.core.card_reporting()
    }

    /// What the controller is doing now.
    pub fn status(&self) -> Status {
        let k = &self.core.kernel;
        Status {
            state: k.state(),
            idle: k.is_idle() && k.state() != MachineState::Homing,
            job: self.core.job.state(),
            progress: self.progress(),
            stats: self.core.stats,
            holding: self.is_holding(),
            homed: k.homed_axes(),
            program_lines: self.core.program.len(),
            program_total: self.core.program.total(),
        }
    }

    /// Line `index` (1-based) of the stored program, read into `buf`; `None` when the store
    /// cannot read it or it is not text.
    ///
    /// Context: thread. Blocks while the program store reads its flash.
    pub fn read_program_line<'b>(
        &mut self,
        index: u16,
        buf: &'b mut [u8; forja_hal_abstraction::program::MAX_LINE_LEN],
    ) -> Option<&'b str> {
        let len = self.core.program.read(index, buf).ok()?;
        core::str::from_utf8(buf.get(..len)?).ok()
    }
}

impl<'q, const N: usize, const B: usize, const Q: usize, P, X, S> Core<'q, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    fn on_event<W: Write>(&mut self, event: Event<'_>, out: &mut W) {
        match event {
            Event::Line(bytes) => self.on_line(bytes, out),
            Event::Frame(frame) => self.on_frame(&frame, out),
            Event::Garbage { text, .. } => self.on_dropped(Dropped::Garbage { text }, out),
            Event::TooLong { .. } => {
                self.link.gcode_seen = true;
                self.on_dropped(Dropped::TooLong, out);
            }
            _ => {}
        }
    }

    fn job_active(&self) -> bool {
        matches!(self.job.state(), JobState::Running | JobState::Paused)
    }

    fn letters(&self) -> [u8; N] {
        core::array::from_fn(|i| self.kernel.config().axes[i].letter)
    }

    /// Energise the drivers before the kernel steps them.
    fn enable_motors_if_needed(&mut self) {
        if self.devices.motors_on {
            return;
        }
        let moving = matches!(
            self.kernel.state(),
            MachineState::Running | MachineState::Homing
        );
        if moving {
            let _ = self.devices.set_motors(true);
        }
    }

    /// Alarms, thermal faults, the temperature loops and the heater waits.
    fn supervise<W: Write>(&mut self, out: &mut W) {
        if self.clock.reached(self.next_peripherals_ms) {
            self.next_peripherals_ms = self
                .clock
                .ms
                .wrapping_add(self.config.peripheral_period_ms.max(1));
            if let Err(e) = self.devices.poll(self.clock.ms)
                && self.thermal.is_none()
            {
                self.thermal = Some(e);
                self.kernel.emergency_stop();
                self.reported_alarm = Some(Alarm::EmergencyStop);
                self.job.stop(&mut self.kernel);
                self.devices.shutdown();
                self.job_heat = None;
                self.end_heat_wait(out);
                self.report_fault(&text::Refusal::new(&e), out);
            }
        }
        match self.kernel.state() {
            MachineState::Alarm(a) => {
                if self.reported_alarm != Some(a) {
                    self.reported_alarm = Some(a);
                    self.devices.shutdown();
                    self.job_heat = None;
                    self.end_heat_wait(out);
                    let r = text::alarm_refusal(&a, &self.letters());
                    self.report_fault(&r, out);
                }
            }
            _ => self.reported_alarm = None,
        }
        if let Some(wait) = self.job_heat
            && self.heat_done(wait)
        {
            self.job_heat = None;
        }
        if matches!(self.link.held, Some(Held::Homing))
            && self.kernel.state() != MachineState::Homing
        {
            self.link.held = None;
            self.ok(out);
        }
        if let Some(probe) = self.kernel.take_probe_report() {
            self.report_probe(&probe, out);
        }
        if matches!(self.link.held, Some(Held::Probe)) && !self.kernel.is_probing() {
            self.link.held = None;
            self.ok(out);
        }
        if matches!(self.link.held, Some(Held::Dwell)) && self.kernel.is_idle() {
            self.link.held = None;
            self.ok(out);
        }
        if let Some(Held::Heat {
            wait,
            next_report_ms,
        }) = self.link.held
        {
            if self.heat_done(wait) {
                self.end_heat_wait(out);
            } else if self.clock.reached(next_report_ms) {
                self.hold_for_heat(wait);
                self.report_temperatures(out);
            }
        }
        self.host_reports(out);
    }

    /// Hold the link's lines for the heating wait `wait`, its next report one report period
    /// from now.
    fn hold_for_heat(&mut self, wait: HeatWait) {
        self.link.held = Some(Held::Heat {
            wait,
            next_report_ms: self
                .clock
                .ms
                .wrapping_add(self.config.report_period_ms.max(1)),
        });
    }

    /// End an `M109`/`M190`/`M116` of the link: its `ok` goes out.
    fn end_heat_wait<W: Write>(&mut self, out: &mut W) {
        if let Some(Held::Heat { .. }) = self.link.held {
            self.link.held = None;
            self.ok(out);
        }
    }

    /// A fault that stopped the machine, not the answer to a line: `Error:` for a G-code host,
    /// 56 for a frame client (both when it cannot tell).
    fn report_fault<W: Write>(&mut self, r: &text::Refusal, out: &mut W) {
        self.stats.faults = self.stats.faults.wrapping_add(1);
        if self.speaks_grbl() {
            return self.grbl_fault(r, out);
        }
        let frames = self.link.frames_seen || self.link.session;
        if self.link.gcode_seen || !frames {
            wire::fault(out, r);
        }
        if frames {
            self.error_frame(r, out);
        }
    }

    fn error_frame<W: Write>(&mut self, r: &text::Refusal, out: &mut W) {
        self.stats.errors = self.stats.errors.wrapping_add(1);
        wire::error_frame(out, r);
    }

    /// When the board should poll again at the latest.
    fn wake_at(&self, frame_flush_ms: Option<u32>) -> Option<Instant> {
        let mut ms = self.clock.until(self.next_peripherals_ms);
        if let Some(Held::Heat { next_report_ms, .. }) = self.link.held {
            ms = ms.min(self.clock.until(next_report_ms));
        }
        if let Some(due) = self.host_reports_in() {
            ms = ms.min(due);
        }
        if let Some(f) = frame_flush_ms {
            ms = ms.min(f);
        }
        if !self.kernel.is_idle()
            || matches!(self.kernel.state(), MachineState::Homing)
            || self.link.lines_held()
        {
            ms = ms.min(self.kernel.poll_within_ms());
        }
        if self.kernel.needs_poll() {
            ms = 0;
        }
        Some(self.clock.after(ms))
    }
}
