//! The G-code side of the client: stream a program, or talk to the controller line by line.
//!
//! Both drive a [`Streamer`] over a [`Connection`]: write what it releases, hand it every
//! reply line, call it back at its deadlines.

use std::fmt;
use std::io;
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::{Duration, Instant};

use forja_protocol::gcode::{Check, Line};
use forja_protocol::reply::{LINE_CHECK, Reply};

use crate::codes;
use crate::link::{Connection, Incoming};
use crate::program::{Program, compact, describe_line_error};
use crate::streamer::{Config, Event, Phase, Stats, Streamer};

/// The longest the loop waits for the link between two looks at the streamer.
const TICK: Duration = Duration::from_millis(100);

/// A line the controller refused.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Refusal {
    /// The line's number in the source file.
    pub source_line: usize,
    /// The error's code.
    pub code: u16,
    /// The controller's text.
    pub text: String,
}

impl fmt::Display for Refusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "line {} was refused: {}",
            self.source_line,
            codes::explain(self.code, &self.text)
        )
    }
}

/// What a streamed job did.
#[derive(Clone, Debug, PartialEq)]
pub struct SendReport {
    /// Lines of the program sent (blank and comment lines not counted).
    pub lines: usize,
    /// From the first byte sent to the last line's acceptance.
    pub elapsed: Duration,
    /// The streamer's counters.
    pub stats: Stats,
    /// Lines the controller refused.
    pub refused: Vec<Refusal>,
    /// The link's bit rate, if it has one.
    pub bit_rate: Option<u32>,
}

impl SendReport {
    /// The share of the time the link was transmitting, for a link with a bit rate (10 bits a
    /// byte on a UART).
    pub fn link_use(&self) -> Option<f64> {
        let rate = f64::from(self.bit_rate?);
        let busy_s = self.stats.bytes_sent as f64 * 10.0 / rate;
        Some(busy_s / self.elapsed.as_secs_f64().max(1e-9))
    }

    /// Lines accepted a second.
    pub fn lines_per_second(&self) -> f64 {
        self.lines as f64 / self.elapsed.as_secs_f64().max(1e-9)
    }
}

/// Why a job could not be streamed to the end.
#[derive(Debug)]
#[non_exhaustive]
pub enum SendError {
    /// The link failed.
    Io(io::Error),
    /// The controller never answered the handshake.
    NoAnswer,
    /// The machine went into alarm.
    Alarm {
        /// The alarm's code.
        code: u16,
        /// Its text.
        text: String,
        /// For a job, the last source line known to be accepted when it happened (`None`
        /// inside: none was).
        accepted_through: Option<Option<usize>>,
    },
    /// The controller restarted during the job.
    Restarted {
        /// The last source line known to be accepted.
        accepted_through: Option<usize>,
    },
    /// The controller's line numbers went out of step with the client's.
    OutOfStep {
        /// The line it asked for.
        asked: u32,
    },
}

impl fmt::Display for SendError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let through = |line: &Option<usize>| match line {
            Some(n) => format!("; lines up to {n} of the file were taken"),
            None => "; no line of the file was taken".into(),
        };
        match self {
            Self::Io(e) => write!(f, "the link to the controller failed: {e}"),
            Self::NoAnswer => f.write_str(
                "the controller does not answer: check that it is on, that this is its port, \
                 and the baud rate (--baud)",
            ),
            Self::Alarm {
                code,
                text,
                accepted_through,
            } => {
                let what = codes::explain(*code, text);
                if matches!(code, 125 | 126) {
                    // The machine was already locked: the explanation says what to do.
                    f.write_str(&what)?;
                } else {
                    write!(f, "the machine went into alarm and stopped: {what}")?;
                }
                match accepted_through {
                    Some(line) => f.write_str(&through(line)),
                    None => Ok(()),
                }
            }
            Self::Restarted { accepted_through } => write!(
                f,
                "the controller restarted during the job (power or reset?){}",
                through(accepted_through)
            ),
            Self::OutOfStep { asked } => write!(
                f,
                "the controller asks for line {asked}, which this client never sent: is another \
                 program talking to it?"
            ),
        }
    }
}

impl std::error::Error for SendError {}

impl From<io::Error> for SendError {
    fn from(e: io::Error) -> Self {
        Self::Io(e)
    }
}

/// Told about a streamed job as it goes.
pub trait Observer {
    /// `accepted` of `total` lines were taken by the controller.
    fn progress(&mut self, accepted: u32, total: u32) {
        let _ = (accepted, total);
    }
    /// Something to show the person: a refused line, a resend, a message of the controller.
    fn notice(&mut self, text: &str) {
        let _ = text;
    }
}

/// An observer that ignores everything.
#[derive(Debug, Default, Clone, Copy)]
pub struct Quiet;

impl Observer for Quiet {}

/// Read and drop what the controller sends until it has been quiet for a moment (its boot
/// banner, replies meant for an earlier session), at most `limit`.
pub fn drain(conn: &mut Connection, limit: Duration) -> io::Result<()> {
    let end = Instant::now() + limit;
    while Instant::now() < end {
        if conn.receive(Duration::from_millis(100))?.is_none() {
            break;
        }
    }
    Ok(())
}

/// How long [`send_program`] waits for the `M115` answer.
const PROBE_LIMIT: Duration = Duration::from_secs(2);

/// How many times [`probe_line_check`] asks: an `M115` or its answer damaged on the link gets
/// an `ok` (or a refusal) with no capabilities line, which a firmware without `M115` gives too.
pub const PROBE_ATTEMPTS: u32 = 3;

/// Ask the controller with `M115` which check it takes on numbered lines: [`Check::Crc16`]
/// when its answer announces `LINE_CHECK:CRC16`, else [`Check::Xor`] (another firmware, or no
/// answer within `limit`). An answer without a capabilities line (the question or the answer
/// damaged on the link, or a firmware without `M115`) is asked again, [`PROBE_ATTEMPTS`] times
/// in all, before the XOR is chosen.
pub fn probe_line_check(conn: &mut Connection, limit: Duration) -> io::Result<Check> {
    let end = Instant::now() + limit;
    for _ in 0..PROBE_ATTEMPTS {
        conn.send(b"\r\nM115\r\n")?;
        // The firmware line, then `Cap:` lines, then the `ok` that ends the answer: read up
        // to that `ok`, so that it is not taken for the answer to a later line.
        let mut check = None;
        while let Some(wait) = end.checked_duration_since(Instant::now()) {
            let Some(Incoming::Line(line)) = conn.receive(wait)? else {
                continue;
            };
            match Reply::parse(&line) {
                Ok(Reply::Firmware(kv)) => {
                    let (key, value) = LINE_CHECK;
                    check = Some(if kv.get(key) == Some(value) {
                        Check::Crc16
                    } else {
                        Check::Xor
                    });
                }
                Ok(Reply::Ok | Reply::OkWith(_)) => match check {
                    Some(check) => return Ok(check),
                    None => break,
                },
                _ => {}
            }
        }
        if let Some(check) = check {
            return Ok(check);
        }
    }
    Ok(Check::Xor)
}

/// Stream `program` over `conn` and wait until the controller has taken every line. The
/// controller is first asked which check it takes ([`probe_line_check`]); lines go with the
/// CRC-16 when it announces it.
pub fn send_program(
    conn: &mut Connection,
    program: &Program,
    config: Config,
    observer: &mut dyn Observer,
) -> Result<SendReport, SendError> {
    let check = probe_line_check(conn, PROBE_LIMIT)?;
    let mut streamer = Streamer::new(Config { check, ..config });
    for line in &program.lines {
        // Program lines were checked when loaded: they always encode.
        streamer.push(&line.text).map_err(|e| {
            SendError::Io(io::Error::new(
                io::ErrorKind::InvalidData,
                format!("line {}: {e}", line.source_line),
            ))
        })?;
    }
    streamer.finish();
    let source_line = |n: u32| {
        (n as usize)
            .checked_sub(1)
            .and_then(|k| program.lines.get(k))
            .map(|l| l.source_line)
    };
    let total = program.lines.len() as u32;
    let mut refused = Vec::new();
    let mut out = Vec::new();
    let mut started: Option<Instant> = None;
    let mut last_accepted = u32::MAX;
    loop {
        let now = Instant::now();
        out.clear();
        let phase_before = streamer.phase();
        streamer.transmit(now, &mut out);
        if !out.is_empty() {
            if phase_before == Phase::Streaming && started.is_none() {
                started = Some(now);
            }
            conn.send(&out)?;
        }
        while let Some(event) = streamer.next_event() {
            match event {
                Event::Refused { number, code, text } => {
                    let r = Refusal {
                        source_line: source_line(number).unwrap_or(0),
                        code,
                        text,
                    };
                    observer.notice(&r.to_string());
                    refused.push(r);
                }
                Event::Rewound { from } => {
                    if let Some(n) = source_line(from) {
                        observer.notice(&format!("resending from line {n}"));
                    }
                }
                Event::Stalled { from } => observer.notice(&format!(
                    "no answer in time; sending line {} again",
                    source_line(from).unwrap_or(0)
                )),
                Event::Alarm { code, text } => {
                    return Err(SendError::Alarm {
                        code,
                        text,
                        accepted_through: Some(source_line(streamer.accepted())),
                    });
                }
                Event::Restarted => {
                    return Err(SendError::Restarted {
                        accepted_through: source_line(streamer.accepted()),
                    });
                }
                Event::NoAnswer => return Err(SendError::NoAnswer),
                Event::OutOfStep { asked } => return Err(SendError::OutOfStep { asked }),
                _ => {}
            }
        }
        if streamer.accepted() != last_accepted {
            last_accepted = streamer.accepted();
            observer.progress(last_accepted, total);
        }
        if streamer.phase() == Phase::Done {
            break;
        }
        let wait = streamer
            .poll_at()
            .map_or(TICK, |t| t.saturating_duration_since(Instant::now()))
            .min(TICK);
        if let Some(Incoming::Line(line)) = conn.receive(wait)? {
            if line.starts_with(b"//") && !is_link_noise(&line) {
                observer.notice(&format!("controller: {}", String::from_utf8_lossy(&line)));
            }
            streamer.receive(Instant::now(), &line);
        }
        streamer.poll(Instant::now());
    }
    Ok(SendReport {
        lines: program.lines.len(),
        elapsed: started.map_or(Duration::ZERO, |t| t.elapsed()),
        stats: streamer.stats(),
        refused,
        bit_rate: conn.bit_rate(),
    })
}

/// Notices about damaged lines, which the streamer handles by itself (`// E2 …` to `// E25 …`).
fn is_link_noise(line: &[u8]) -> bool {
    let text = String::from_utf8_lossy(line);
    let Some(rest) = text.strip_prefix("// E") else {
        return false;
    };
    let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
    digits.parse::<u16>().is_ok_and(|c| (1..100).contains(&c))
}

/// Why the console ended with an error.
pub type ConsoleError = SendError;

/// An interactive session: each line received on `input` is checked, sent with a line number
/// and checksum (resent if damaged), and every reply of the controller is written to `output`
/// as it comes (its resend requests excepted). While the person types nothing, a lone line end
/// goes out every [`crate::link::KEEP_ALIVE_PERIOD`] ([`Connection::keep_alive`]), so that the
/// board's idle time-out does not end the session. Ends when `input` closes and every line
/// was taken.
pub fn console(
    conn: &mut Connection,
    input: &Receiver<String>,
    output: &mut dyn io::Write,
    config: Config,
) -> Result<Stats, ConsoleError> {
    let mut streamer = Streamer::new(config);
    let mut out = Vec::new();
    let mut open = true;
    loop {
        let now = Instant::now();
        out.clear();
        streamer.transmit(now, &mut out);
        conn.send(&out)?;
        // The person may type nothing for a long while: the board must not take them for gone.
        conn.keep_alive()?;
        while let Some(event) = streamer.next_event() {
            match event {
                Event::Alarm { code, text } => {
                    return Err(SendError::Alarm {
                        code,
                        text,
                        accepted_through: None,
                    });
                }
                Event::Restarted => {
                    return Err(SendError::Restarted {
                        accepted_through: None,
                    });
                }
                Event::NoAnswer => return Err(SendError::NoAnswer),
                Event::OutOfStep { asked } => return Err(SendError::OutOfStep { asked }),
                Event::Refused { code, text, .. } => {
                    writeln!(output, "refused: {}", codes::explain(code, &text))?;
                }
                _ => {}
            }
        }
        if streamer.phase() == Phase::Done {
            return Ok(streamer.stats());
        }
        while open {
            match input.try_recv() {
                Ok(text) => {
                    if let Some(message) = console_line(&mut streamer, &text) {
                        writeln!(output, "{message}")?;
                    }
                }
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => {
                    open = false;
                    streamer.finish();
                }
            }
        }
        let wait = streamer
            .poll_at()
            .map_or(Duration::from_millis(20), |t| {
                t.saturating_duration_since(Instant::now())
            })
            .min(Duration::from_millis(20));
        let phase = streamer.phase();
        if let Some(Incoming::Line(line)) = conn.receive(wait)? {
            // Resend requests, damage notices and the `ok`s of the handshake and of the closing
            // line are the client's business, not the person's.
            let internal = phase != Phase::Streaming
                || line.starts_with(b"rs ")
                || line.starts_with(b"start")
                || is_link_noise(&line)
                || (line.as_slice() == b"ok" && streamer.accepted() >= streamer.pushed());
            if !internal {
                writeln!(output, "{}", String::from_utf8_lossy(&line))?;
                output.flush()?;
            }
            streamer.receive(Instant::now(), &line);
        }
        streamer.poll(Instant::now());
    }
}

/// Check one line typed at the console and queue it; a message for the person if it cannot
/// be sent.
fn console_line(streamer: &mut Streamer, text: &str) -> Option<String> {
    let line = match Line::parse(text.as_bytes()) {
        Ok(line) => line,
        Err(e) => return Some(format!("not sent: {}", describe_line_error(&e))),
    };
    if line.is_empty() {
        return None;
    }
    if line.is_command(b'M', 110) {
        return Some("not sent: forja numbers the lines itself (M110)".into());
    }
    match streamer.push(&compact(&line, false)) {
        Ok(_) => None,
        Err(e) => Some(format!("not sent: {e}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::Link;
    use std::collections::VecDeque;

    /// A controller that answers each `M115` with the next of `answers`.
    struct Scripted {
        answers: VecDeque<&'static [u8]>,
        pending: Vec<u8>,
        asked: usize,
    }

    impl Link for Scripted {
        fn write_all(&mut self, bytes: &[u8]) -> io::Result<()> {
            if bytes.windows(4).any(|w| w == b"M115") {
                self.asked += 1;
                if let Some(a) = self.answers.pop_front() {
                    self.pending.extend_from_slice(a);
                }
            }
            Ok(())
        }

        fn read(&mut self, buf: &mut [u8], _timeout: Duration) -> io::Result<usize> {
            let n = buf.len().min(self.pending.len());
            buf[..n].copy_from_slice(&self.pending[..n]);
            self.pending.drain(..n);
            Ok(n)
        }
    }

    fn probe(answers: &[&'static [u8]]) -> (Check, usize) {
        let link = Scripted {
            answers: answers.iter().copied().collect(),
            pending: Vec::new(),
            asked: 0,
        };
        let mut conn = Connection::new(Box::new(link));
        conn.record();
        let check = probe_line_check(&mut conn, Duration::from_millis(200)).unwrap();
        let asked = conn
            .transcript()
            .iter()
            .filter(|(sent, b)| *sent && b.windows(4).any(|w| w == b"M115"))
            .count();
        (check, asked)
    }

    const CAPS: &[u8] = b"FIRMWARE_NAME:Forja LINE_CHECK:CRC16\nCap:ARCS:1\nok\n";

    #[test]
    fn a_damaged_m115_answer_is_asked_again_not_taken_for_the_xor() {
        assert_eq!(
            probe(&[b"echo:E8 bad-character\nok\n", CAPS]),
            (Check::Crc16, 2)
        );
        assert_eq!(probe(&[b"ok\n", b"ok\n", CAPS]), (Check::Crc16, 3));
    }

    #[test]
    fn a_firmware_without_the_crc_gets_the_xor() {
        assert_eq!(
            probe(&[b"FIRMWARE_NAME:Marlin PROTOCOL_VERSION:1.0\nok\n"]),
            (Check::Xor, 1)
        );
        assert_eq!(
            probe(&[b"ok\n", b"ok\n", b"ok\n", CAPS]),
            (Check::Xor, PROBE_ATTEMPTS as usize)
        );
    }
}
