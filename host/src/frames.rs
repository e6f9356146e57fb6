//! The frame client: upload a program, run actions, jog, read positions and progress, over
//! the fixed 53-byte frames (`frame-protocol.md`).
//!
//! Frames 01 (jog) and 02 (actions) have no answer when they are carried out; a refusal is
//! answered with a 56. To know, the client follows each with a 04 request for a 52: the
//! controller handles frames in order, so a 56 that arrives before the 52 is the refusal of the
//! frame, and a 52 alone means it was taken.
//!
//! Uploads do not overrun a UART controller: frames go out in batches of
//! [`UploadOptions::batch`] lines, each followed by a 04→52 request whose `NL` (lines stored)
//! says where the store is; lines that did not make it (a frame damaged on the link) are sent
//! again from there.

use std::fmt;
use std::io;
use std::time::{Duration, Instant};

use forja_protocol::frame::{
    Action, ClientMessage, ControllerMessage, Decimal, FRAME_LEN, MAX_LOAD_LINES, Positions,
    Progress, message_type,
};

use crate::codes;
use crate::link::{Connection, Incoming};

/// A controller message, owned.
#[derive(Clone, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Message {
    /// 50: a setting's value.
    Setting {
        /// The setting.
        key: String,
        /// Its value.
        value: String,
    },
    /// 51: positions.
    Positions(Positions),
    /// 52: progress.
    Progress(Progress),
    /// 53: a confirmation.
    Confirm(String),
    /// 54: connected.
    Connected,
    /// 55: keep-alive.
    KeepAlive(u32),
    /// 56: an error.
    Error {
        /// Its code (0 when none was given).
        code: u16,
        /// Its name and detail.
        detail: String,
    },
}

impl Message {
    /// Decode a frame received from a controller.
    pub fn decode(frame: &[u8; FRAME_LEN]) -> Option<Self> {
        Some(match ControllerMessage::decode(frame).ok()? {
            ControllerMessage::Setting { key, value } => Self::Setting {
                key: key.into(),
                value: value.into(),
            },
            ControllerMessage::Positions(p) => Self::Positions(p),
            ControllerMessage::Progress(p) => Self::Progress(p),
            ControllerMessage::Confirm { what } => Self::Confirm(what.into()),
            ControllerMessage::Connected => Self::Connected,
            ControllerMessage::KeepAlive { counter } => Self::KeepAlive(counter),
            ControllerMessage::Error { code, detail } => Self::Error {
                code,
                detail: detail.into(),
            },
            _ => return None,
        })
    }
}

/// Why a frame exchange failed.
#[derive(Debug)]
#[non_exhaustive]
pub enum FrameError {
    /// The link failed.
    Io(io::Error),
    /// The controller did not answer in time.
    NoAnswer {
        /// What was asked.
        what: String,
    },
    /// The controller refused: a 56.
    Refused {
        /// What was asked.
        what: String,
        /// The code.
        code: u16,
        /// The name and detail.
        detail: String,
    },
    /// The link damaged a frame around an action: whether it was carried out is not known.
    Doubtful {
        /// What was asked.
        what: String,
    },
    /// Something the client cannot send (an empty program, one too long, a bad value).
    Invalid(String),
}

impl fmt::Display for FrameError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io(e) => write!(f, "the link to the controller failed: {e}"),
            Self::NoAnswer { what } => write!(
                f,
                "the controller did not answer {what}: is it on, and does it speak the frame \
                 protocol on this link?"
            ),
            Self::Refused { what, code, detail } => write!(
                f,
                "the controller refused {what}: {}",
                codes::explain(*code, detail)
            ),
            Self::Doubtful { what } => write!(
                f,
                "the link damaged a frame around {what}: check with 'forja status' whether it \
                 was carried out"
            ),
            Self::Invalid(message) => f.write_str(message),
        }
    }
}

impl std::error::Error for FrameError {}

impl From<io::Error> for FrameError {
    fn from(e: io::Error) -> Self {
        Self::Io(e)
    }
}

/// How many times a request for a message is sent before the controller is declared silent.
pub const REQUEST_ATTEMPTS: usize = 6;

/// How an upload goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UploadOptions {
    /// Lines sent before each check of the store (04→52). Four 54-byte frames and the
    /// request fit a 256-byte UART buffer with room to spare.
    pub batch: usize,
    /// How long to wait for the answer to a check.
    pub timeout: Duration,
}

impl Default for UploadOptions {
    fn default() -> Self {
        Self {
            batch: 3,
            timeout: Duration::from_secs(2),
        }
    }
}

/// What an upload did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct UploadReport {
    /// Lines stored.
    pub lines: usize,
    /// Frames sent again because the store did not have them.
    pub resent: usize,
    /// Whether the controller confirmed the program (53 `Confirm:Gcode-load`).
    pub confirmed: bool,
}

/// Frame exchanges over a [`Connection`].
#[derive(Debug)]
pub struct FrameClient<'c> {
    conn: &'c mut Connection,
    timeout: Duration,
    /// 56s received outside of an exchange, and text lines (`Error:…` alarms).
    notices: Vec<String>,
    /// Frames the controller reported damaged on the link.
    damaged: u64,
}

impl<'c> FrameClient<'c> {
    /// A client on `conn`; answers are awaited at most `timeout`.
    pub fn new(conn: &'c mut Connection, timeout: Duration) -> Self {
        Self {
            conn,
            timeout,
            notices: Vec::new(),
            damaged: 0,
        }
    }

    /// Messages received that no exchange asked for (alarms, stray errors), oldest first.
    pub fn take_notices(&mut self) -> Vec<String> {
        std::mem::take(&mut self.notices)
    }

    fn encode(msg: &ClientMessage<'_>, out: &mut Vec<u8>) -> Result<(), FrameError> {
        let mut frame = [0u8; FRAME_LEN];
        msg.encode(&mut frame)
            .map_err(|e| FrameError::Invalid(format!("cannot encode {msg:?}: {e}")))?;
        out.extend_from_slice(&frame);
        out.push(b'\n');
        Ok(())
    }

    /// Keep the session while nothing is asked: see [`Connection::keep_alive`].
    pub fn keep_alive(&mut self) -> io::Result<bool> {
        self.conn.keep_alive()
    }

    /// Send one frame.
    pub fn send(&mut self, msg: &ClientMessage<'_>) -> Result<(), FrameError> {
        let mut out = Vec::with_capacity(FRAME_LEN + 1);
        Self::encode(msg, &mut out)?;
        Ok(self.conn.send(&out)?)
    }

    /// The next message, or `None` after `timeout`. G-code lines (an alarm's `Error:…`) are kept
    /// as notices.
    fn next_message(&mut self, deadline: Instant) -> Result<Option<Message>, FrameError> {
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.conn.receive(left)? {
                Some(Incoming::Frame(frame)) => {
                    if let Some(m) = Message::decode(&frame) {
                        return Ok(Some(m));
                    }
                }
                Some(Incoming::Line(line)) => {
                    if line.starts_with(b"Error:") || line.starts_with(b"!!") {
                        self.notices
                            .push(String::from_utf8_lossy(&line).into_owned());
                    }
                }
                Some(Incoming::Garbage(_)) => {}
                None => return Ok(None),
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
        }
    }

    /// Ask for message `wanted` (51 or 52) and wait for it. A 56 that comes first is returned
    /// as [`FrameError::Refused`] of `what`; the request is sent again when it goes unanswered
    /// or the controller reports a damaged frame, [`REQUEST_ATTEMPTS`] times in all.
    fn request(&mut self, wanted: u8, what: &str) -> Result<Message, FrameError> {
        let mut refusal = None;
        for _ in 0..REQUEST_ATTEMPTS {
            self.send(&ClientMessage::Request {
                message_type: wanted,
            })?;
            let deadline = Instant::now() + self.timeout;
            while let Some(m) = self.next_message(deadline)? {
                match m {
                    Message::Positions(_) if wanted == message_type::POSITIONS => {
                        return match refusal {
                            Some(e) => Err(e),
                            None => Ok(m),
                        };
                    }
                    Message::Progress(_) if wanted == message_type::PROGRESS => {
                        return match refusal {
                            Some(e) => Err(e),
                            None => Ok(m),
                        };
                    }
                    Message::Error { code, .. } if codes::is_link_damage(code) => {
                        // A frame of ours was damaged on the way, maybe this request: send it
                        // again now (a second answer is harmless). An action sent before it
                        // is in doubt.
                        self.damaged += 1;
                        break;
                    }
                    Message::Error { code, detail } if refusal.is_none() => {
                        refusal = Some(FrameError::Refused {
                            what: what.into(),
                            code,
                            detail,
                        });
                    }
                    Message::Error { code, detail } => {
                        self.notices.push(codes::explain(code, &detail));
                    }
                    _ => {}
                }
            }
        }
        Err(FrameError::NoAnswer { what: what.into() })
    }

    /// The positions (51).
    pub fn positions(&mut self) -> Result<Positions, FrameError> {
        match self.request(message_type::POSITIONS, "the request for positions")? {
            Message::Positions(p) => Ok(p),
            _ => Err(FrameError::NoAnswer {
                what: "the request for positions".into(),
            }),
        }
    }

    /// The progress (52).
    pub fn progress(&mut self) -> Result<Progress, FrameError> {
        self.progress_after("the request for progress")
    }

    fn progress_after(&mut self, what: &str) -> Result<Progress, FrameError> {
        match self.request(message_type::PROGRESS, what)? {
            Message::Progress(p) => Ok(p),
            _ => Err(FrameError::NoAnswer { what: what.into() }),
        }
    }

    /// Run an action (02) and confirm that it was taken.
    pub fn action(&mut self, action: Action) -> Result<Progress, FrameError> {
        self.confirmed(&ClientMessage::Action(action), &action_name(action))
    }

    /// Jog `axis` by `distance` mm (01) and confirm that it was taken.
    pub fn jog(&mut self, axis: u8, distance: Decimal) -> Result<Progress, FrameError> {
        let msg = jog_message(axis, distance)?;
        self.confirmed(&msg, &format!("the jog of {}", char::from(axis)))
    }

    /// Send `msg`, which has no answer when carried out, and confirm it with a 52.
    fn confirmed(&mut self, msg: &ClientMessage<'_>, what: &str) -> Result<Progress, FrameError> {
        let damaged = self.damaged;
        self.send(msg)?;
        let progress = self.progress_after(what)?;
        if self.damaged != damaged {
            return Err(FrameError::Doubtful { what: what.into() });
        }
        Ok(progress)
    }

    /// Store `lines` (03 frames) as the controller's program. `on_progress` is called with the
    /// number of lines stored so far.
    pub fn upload(
        &mut self,
        lines: &[String],
        options: UploadOptions,
        mut on_progress: impl FnMut(usize),
    ) -> Result<UploadReport, FrameError> {
        let total = lines.len();
        if total == 0 {
            return Err(FrameError::Invalid(
                "the program has no G-code lines to upload".into(),
            ));
        }
        if total > usize::from(MAX_LOAD_LINES) {
            return Err(FrameError::Invalid(format!(
                "the program has {total} lines; a controller stores at most {MAX_LOAD_LINES}: \
                 stream it with 'forja send' instead"
            )));
        }
        let total16 = total as u16;
        let batch = options.batch.max(1);
        let mut report = UploadReport::default();
        let mut next = 1usize;
        let mut stalls = 0;
        let mut last_error: Option<FrameError> = None;
        while next <= total {
            let end = (next + batch - 1).min(total);
            let mut out = Vec::with_capacity((end - next + 2) * (FRAME_LEN + 1));
            for (index, text) in (next..=end).zip(lines.iter().skip(next - 1)) {
                Self::encode(
                    &ClientMessage::LoadLine {
                        index: index as u16,
                        text,
                        total: total16,
                    },
                    &mut out,
                )?;
            }
            Self::encode(
                &ClientMessage::Request {
                    message_type: message_type::PROGRESS,
                },
                &mut out,
            )?;
            self.conn.send(&out)?;
            let deadline = Instant::now() + options.timeout;
            let mut stored = None;
            while let Some(m) = self.next_message(deadline)? {
                match m {
                    Message::Progress(p) => {
                        stored = Some(p.total_lines as usize);
                        break;
                    }
                    Message::Confirm(what) if what == "Gcode-load" => report.confirmed = true,
                    Message::Error { code, detail } => {
                        if codes::is_fatal_for_upload(code) {
                            return Err(FrameError::Refused {
                                what: format!("program line {next}"),
                                code,
                                detail,
                            });
                        }
                        last_error = Some(FrameError::Refused {
                            what: "a program line".into(),
                            code,
                            detail,
                        });
                    }
                    _ => {}
                }
            }
            let before = next;
            match stored {
                // Line 1 clears the store, so a count below `next - 1` means the program was
                // replaced or lost: start over.
                Some(n) if n + 1 < next => next = 1,
                Some(n) => next = n.min(total) + 1,
                None => {}
            }
            if next <= end {
                report.resent += end + 1 - next.max(before);
            }
            if next > before {
                stalls = 0;
                on_progress(next - 1);
            } else {
                stalls += 1;
                if stalls >= 5 {
                    return Err(last_error.unwrap_or(FrameError::NoAnswer {
                        what: format!("program line {next}"),
                    }));
                }
            }
        }
        if !report.confirmed {
            // The confirmation follows the last line; give it a moment if it is late.
            let deadline = Instant::now() + Duration::from_millis(300);
            while let Some(m) = self.next_message(deadline)? {
                if matches!(&m, Message::Confirm(w) if w == "Gcode-load") {
                    report.confirmed = true;
                    break;
                }
            }
        }
        report.lines = total;
        Ok(report)
    }
}

/// The 01 frame for a jog of `distance` mm: steps of 0.0001 mm as in the seed's example
/// (`S0.0001X+1000` is +0.1 mm), or of the distance's own resolution when it is finer.
pub fn jog_message(axis: u8, distance: Decimal) -> Result<ClientMessage<'static>, FrameError> {
    let axis = axis.to_ascii_uppercase();
    if !axis.is_ascii_uppercase() {
        return Err(FrameError::Invalid(format!(
            "'{}' is not an axis letter",
            char::from(axis)
        )));
    }
    let scale = distance.scale().max(4);
    let count = distance
        .round_to_scale(scale)
        .and_then(|c| i32::try_from(c).ok())
        .ok_or_else(|| FrameError::Invalid(format!("a jog of {distance} mm is too long")))?;
    Ok(ClientMessage::Jog {
        step: Decimal::new(1, scale),
        axis,
        count,
    })
}

fn action_name(action: Action) -> String {
    match action {
        Action::HomeAll => "homing".into(),
        Action::Home(axis) => format!("homing {}", char::from(axis)),
        Action::Reset => "the reset".into(),
        Action::Stop => "the stop".into(),
        Action::Rewind => "the rewind".into(),
        Action::Start => "the start".into(),
        Action::Pause => "the pause".into(),
    }
}

/// `mm:ss`.
pub fn mm_ss(seconds: u32) -> String {
    format!("{:02}:{:02}", seconds / 60, seconds % 60)
}

/// One line describing positions and progress: `X 150.0000  Y … │ line 3/120 │ 00:05 of 01:30`.
pub fn status_line(positions: &Positions, progress: &Progress) -> String {
    let mut out = String::new();
    for a in positions.axes() {
        if !out.is_empty() {
            out.push_str("  ");
        }
        out.push_str(&format!(
            "{} {:>10}",
            char::from(a.axis),
            a.mm().to_string()
        ));
    }
    if progress.total_lines > 0 {
        out.push_str(&format!(
            " | line {}/{} | {} of {}",
            progress.current_line,
            progress.total_lines,
            mm_ss(progress.elapsed_s),
            mm_ss(progress.estimated_s)
        ));
    } else {
        out.push_str(" | no program stored");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn jog(axis: u8, text: &str) -> [u8; FRAME_LEN] {
        let msg = jog_message(axis, Decimal::parse(text.as_bytes()).unwrap()).unwrap();
        let mut out = [0u8; FRAME_LEN];
        msg.encode(&mut out).unwrap();
        out
    }

    #[test]
    fn jogs_use_the_seeds_step_size() {
        assert!(jog(b'x', "+0.1").starts_with(b"N01S0.0001X+1000*"));
        assert!(jog(b'Y', "-2").starts_with(b"N01S0.0001Y-20000*"));
        assert!(jog(b'Z', "0.00005").starts_with(b"N01S0.00001Z+5*"));
        assert!(jog_message(b'X', Decimal::new(1, 0)).is_ok());
        assert!(jog_message(b'1', Decimal::new(1, 0)).is_err());
        assert!(jog_message(b'X', Decimal::new(900_000, 0)).is_err());
    }

    #[test]
    fn status_lines_read_well() {
        let positions = Positions::from_slice(&[
            forja_protocol::frame::AxisPosition {
                axis: b'X',
                value_tenth_um: 1_500_000,
            },
            forja_protocol::frame::AxisPosition {
                axis: b'Y',
                value_tenth_um: -25,
            },
        ])
        .unwrap();
        let progress = Progress {
            elapsed_s: 5,
            estimated_s: 90,
            total_lines: 120,
            current_line: 3,
        };
        assert_eq!(
            status_line(&positions, &progress),
            "X   150.0000  Y    -0.0025 | line 3/120 | 00:05 of 01:30"
        );
    }
}
