//! A G-code sender, as host software streams a job: numbered, checksummed lines, one at a
//! time, each sent when the previous one is answered.
//!
//! [`GcodeSender`] is sans-IO: give it what the controller sent ([`GcodeSender::poll`]) with
//! the time, write what it returns to the link. It behaves like Printrun and OctoPrint:
//!
//! - it opens with `N-1 M110 N-1*<cs>` (the numbering restarts at 0) and numbers the job's
//!   lines from 0, comments and blank lines left out;
//! - it sends the next line on `ok`, and goes back to line `n` on `rs n` (or `Resend: n`);
//!   until its opening `M110` is answered with `ok`, any `rs` asks for the `M110` again (the
//!   controller, which expects line 1 after a start, does not know this host's numbering
//!   before it);
//! - it notes `!!` lines (a refused line, or a fault) and keeps going: an `ok` follows a
//!   refused line;
//! - when nothing has come back for [`GcodeSender::timeout_ms`] while a line is unanswered, it
//!   sends a lone line end: if the line's own end was lost on the link, that completes it;
//!   otherwise the empty line is ignored.

use forja_protocol::gcode::write_numbered;
use forja_protocol::reply::Reply;

/// What the sender saw.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SenderStats {
    /// Lines written (resends included).
    pub sent: u64,
    /// Lines answered with `ok`.
    pub acked: u64,
    /// `rs` replies received.
    pub resends: u64,
    /// Lone line ends sent after a time-out.
    pub nudges: u64,
    /// `ok` or `rs` received with no line waiting for one.
    pub stray: u64,
    /// The `!!` lines received, in order.
    pub faults: Vec<String>,
    /// The `//` lines received, in order.
    pub notes: Vec<String>,
    /// Other lines received (frames, the `ok …` answers of reports), in order.
    pub other: Vec<String>,
}

/// Streams a job as a host does. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct GcodeSender {
    /// Each line as sent, `\n` included; line `i` has number `i - 1`.
    lines: Vec<Vec<u8>>,
    next: usize,
    waiting: Option<usize>,
    /// The opening `M110` has been answered with `ok`.
    opened: bool,
    last_heard_ms: u64,
    partial: Vec<u8>,
    /// Time without a reply after which a lone line end is sent.
    pub timeout_ms: u64,
    stats: SenderStats,
}

/// `text` without its `;` and `( … )` comments, trimmed.
fn strip(text: &str) -> String {
    let mut out = String::new();
    let mut in_paren = false;
    for c in text.chars() {
        match c {
            ';' if !in_paren => break,
            '(' if !in_paren => in_paren = true,
            ')' if in_paren => in_paren = false,
            c if !in_paren => out.push(c),
            _ => {}
        }
    }
    out.trim().to_string()
}

fn encode(number: i64, body: &str) -> Result<Vec<u8>, String> {
    let mut buf = [0u8; 300];
    let mut line = if number < 0 {
        let head = format!("N{number} {body}");
        let cs = forja_protocol::gcode::checksum(head.as_bytes());
        format!("{head}*{cs}").into_bytes()
    } else {
        let n = write_numbered(number as u32, body.as_bytes(), &mut buf)
            .map_err(|e| format!("line {number} ({body}): {e}"))?;
        buf[..n].to_vec()
    };
    line.push(b'\n');
    Ok(line)
}

impl GcodeSender {
    /// A sender for the lines of a job (comments and blank lines are left out).
    ///
    /// Errors: a line that cannot be sent (too long once numbered, or holding a `*`).
    pub fn new<'a>(job: impl IntoIterator<Item = &'a str>) -> Result<Self, String> {
        let mut lines = vec![encode(-1, "M110 N-1")?];
        for body in job.into_iter().map(strip).filter(|b| !b.is_empty()) {
            let number = lines.len() as i64 - 1;
            lines.push(encode(number, &body)?);
        }
        Ok(Self {
            lines,
            next: 0,
            waiting: None,
            opened: false,
            last_heard_ms: 0,
            partial: Vec::new(),
            timeout_ms: 2_000,
            stats: SenderStats::default(),
        })
    }

    /// Lines to send, the opening `M110` included.
    pub fn len(&self) -> usize {
        self.lines.len()
    }

    /// Whether there is nothing to send.
    pub fn is_empty(&self) -> bool {
        self.lines.is_empty()
    }

    /// Whether every line has been sent and answered with `ok`.
    pub fn is_done(&self) -> bool {
        self.next >= self.lines.len() && self.waiting.is_none()
    }

    /// What the sender saw so far.
    pub fn stats(&self) -> &SenderStats {
        &self.stats
    }

    fn on_reply(&mut self, line: &str) {
        match Reply::parse(line.as_bytes()) {
            Ok(Reply::Resend(n)) => {
                self.stats.resends += 1;
                if self.waiting.take().is_none() {
                    self.stats.stray += 1;
                }
                // Line number n is at index n + 1; until the opening M110 is answered, the
                // controller does not know this host's numbering and the M110 goes again.
                self.next = if self.opened {
                    (n as usize).saturating_add(1).min(self.lines.len())
                } else {
                    0
                };
            }
            Ok(
                Reply::Ok
                | Reply::OkWith(_)
                | Reply::Temperatures { .. }
                | Reply::Position(_)
                | Reply::Capabilities(_),
            ) => {
                if line != "ok" {
                    self.stats.other.push(line.to_string());
                }
                match self.waiting.take() {
                    Some(i) => {
                        self.stats.acked += 1;
                        self.opened = true;
                        self.next = i + 1;
                    }
                    None => self.stats.stray += 1,
                }
            }
            Ok(Reply::Fault { .. }) => self.stats.faults.push(line.to_string()),
            Ok(Reply::Notice { .. } | Reply::Debug(_)) => self.stats.notes.push(line.to_string()),
            _ => self.stats.other.push(line.to_string()),
        }
    }

    /// Take the bytes the controller sent (`received`, possibly none) at `now_ms`, and return
    /// the bytes to write to the link now (possibly none).
    pub fn poll(&mut self, received: &[u8], now_ms: u64) -> Vec<u8> {
        if !received.is_empty() {
            self.last_heard_ms = now_ms;
            self.partial.extend_from_slice(received);
        }
        while let Some(end) = self.partial.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = self.partial.drain(..=end).collect();
            let text = String::from_utf8_lossy(&line);
            let text = text.trim_end();
            if !text.is_empty() {
                self.on_reply(text);
            }
        }
        if self.waiting.is_none() {
            if let Some(line) = self.lines.get(self.next) {
                self.waiting = Some(self.next);
                self.stats.sent += 1;
                self.last_heard_ms = now_ms;
                return line.clone();
            }
            return Vec::new();
        }
        if now_ms.saturating_sub(self.last_heard_ms) >= self.timeout_ms {
            self.last_heard_ms = now_ms;
            self.stats.nudges += 1;
            return b"\n".to_vec();
        }
        Vec::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn text(b: &[u8]) -> &str {
        std::str::from_utf8(b).unwrap()
    }

    #[test]
    fn numbers_lines_follows_ok_and_rs_and_nudges() {
        let mut s = GcodeSender::new(["G21 ; mm", "", "(a comment)", "G1 X1 (fast)"]).unwrap();
        assert_eq!(s.len(), 3);
        assert_eq!(text(&s.poll(b"start\n", 0)), "N-1 M110 N-1*125\n");
        assert!(s.poll(b"", 1).is_empty());
        assert_eq!(text(&s.poll(b"ok\n", 2)), "N0 G21*26\n");
        assert_eq!(text(&s.poll(b"rs 0\n", 3)), "N0 G21*26\n");
        assert_eq!(text(&s.poll(b"ok\nok\n", 4)), "N1 G1 X1*96\n");
        assert_eq!(s.stats().stray, 1);
        assert_eq!(text(&s.poll(b"", 2_004)), "\n");
        assert_eq!(s.stats().nudges, 1);
        assert!(!s.is_done());
        assert!(
            s.poll(b"!! E120 unsupported-command M1\no", 2_005)
                .is_empty()
        );
        assert!(s.poll(b"k\n", 2_006).is_empty());
        assert!(s.is_done());
        assert_eq!(s.stats().faults, ["!! E120 unsupported-command M1"]);
        assert_eq!(s.stats().acked, 3);
    }
}
