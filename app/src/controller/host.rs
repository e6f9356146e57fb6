//! What a printer host sets and reads beside its lines, in Marlin's forms: the job progress
//! (`M73`), the operator's message (`M117`), lines to the host (`M118`), temperature
//! auto-reports (`M155`) and the `busy: processing` keep-alive (`M113`).
//!
//! | command | effect | answer |
//! |---|---|---|
//! | `M73 P<percent> R<minutes> L<layer>` | kept for the operator ([`Controller::host_progress`](super::Controller::host_progress)) | `ok` |
//! | `M117 <text>` | kept for the operator's display ([`Controller::message`](super::Controller::message)) | `ok` |
//! | `M118 [A1] [E1] [Pn] <text>` | the text as a line to the host: `// ` first with `A1`, `echo:` first with `E1` | the line, `ok` |
//! | `M155 S<s>` | ` T:… /… B:… /… @:… B@:…` every `s` seconds (0: off) | `ok` |
//! | `M113 S<s>` | `echo:busy: processing` every `s` seconds (0: never) while a line waits for the machine (a homing, `M400`, a full planner; never in the grbl dialect) | `ok`; `M113` alone: `echo:M113 S<s>`, `ok` |

use embedded_io::Write;
use forja_hal_abstraction::program::ProgramStore;
use forja_hal_abstraction::storage::RecordStorage;
use forja_protocol::reply::Reply;

use super::peripherals::Peripherals;
use super::text::Text;
use super::{Core, Held, wire};

/// The longest `M117` message kept, bytes (Marlin's status line holds fewer).
pub const MESSAGE_LEN: usize = 64;

/// The longest `M118` line sent, bytes, its `\n` not counted.
const HOST_LINE_LEN: usize = 96;

/// The default period of `echo:busy: processing`, ms (Marlin's `DEFAULT_KEEPALIVE_INTERVAL`).
pub const BUSY_INTERVAL_MS: u32 = 2_000;

/// The job progress a host announces with `M73`; `None` where it gave no value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct HostProgress {
    /// Percent done, 0–100.
    pub percent: Option<u8>,
    /// Minutes left.
    pub remaining_min: Option<u32>,
    /// The layer being printed.
    pub layer: Option<u32>,
}

/// What the host set and when the next unrequested line is due.
pub(super) struct HostReports {
    pub(super) progress: HostProgress,
    pub(super) message: Text<MESSAGE_LEN>,
    /// `M155` period, ms; 0 when off.
    auto_report_ms: u32,
    next_auto_report_ms: u32,
    /// `M113` period, ms; 0 when off.
    busy_interval_ms: u32,
    /// When the next `busy: processing` is due, while a line waits.
    next_busy_ms: Option<u32>,
}

impl HostReports {
    pub(super) const fn new() -> Self {
        Self {
            progress: HostProgress {
                percent: None,
                remaining_min: None,
                layer: None,
            },
            message: Text::new(),
            auto_report_ms: 0,
            next_auto_report_ms: 0,
            busy_interval_ms: BUSY_INTERVAL_MS,
            next_busy_ms: None,
        }
    }
}

/// An `M118` text split into its flags and its message: `A1` (`// ` first), `E1` (`echo:`
/// first) and `Pn` (the port: every port here, the host's link) lead the text, in any order.
fn host_line(text: &[u8]) -> (&'static str, &[u8]) {
    let mut prefix = "";
    let mut rest = text;
    loop {
        let word_end = rest.iter().position(|b| *b == b' ').unwrap_or(rest.len());
        let (word, tail) = rest.split_at(word_end);
        match word {
            b"A1" => prefix = "// ",
            b"E1" => prefix = "echo:",
            [b'A' | b'E', b'0'] | [b'P', b'0'..=b'9'] => {}
            _ => return (prefix, rest),
        }
        rest = tail.strip_prefix(b" ").unwrap_or(tail);
    }
}

impl<const N: usize, const B: usize, const Q: usize, P, X, S> Core<'_, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// `M73`.
    pub(super) fn set_host_progress(&mut self, progress: HostProgress) {
        let kept = &mut self.host.progress;
        kept.percent = progress.percent.or(kept.percent);
        kept.remaining_min = progress.remaining_min.or(kept.remaining_min);
        kept.layer = progress.layer.or(kept.layer);
    }

    /// `M117`: the message, as far as it fit, in printable ASCII.
    pub(super) fn set_message(&mut self, message: Text<MESSAGE_LEN>) {
        self.host.message = message;
    }

    /// `M118`: the line to the host.
    pub(super) fn host_message<W: Write>(&mut self, text: &[u8], out: &mut W) {
        let (prefix, message) = host_line(text);
        let mut line = Text::<HOST_LINE_LEN>::new();
        line.push(prefix);
        line.push(core::str::from_utf8(message).unwrap_or("?"));
        // One write, the terminator included, as every reply is written.
        let mut bytes = [b'\n'; HOST_LINE_LEN + 1];
        let text = line.as_bytes();
        if let Some(head) = bytes.get_mut(..text.len()) {
            head.copy_from_slice(text);
        }
        let _ = out.write_all(bytes.get(..=text.len()).unwrap_or(&[]));
    }

    /// Whether the host asked for temperature reports every period (`M155 S` above 0).
    pub(super) fn auto_reporting(&self) -> bool {
        self.host.auto_report_ms > 0
    }

    /// `M155 S<seconds>`.
    pub(super) fn set_auto_report(&mut self, seconds: u8) {
        self.host.auto_report_ms = u32::from(seconds) * 1000;
        self.host.next_auto_report_ms = self.clock.ms.wrapping_add(self.host.auto_report_ms);
    }

    /// `M113 S<seconds>`, or `M113` alone (`None`): the period is reported.
    pub(super) fn busy_interval<W: Write>(&mut self, seconds: Option<u8>, out: &mut W) {
        match seconds {
            Some(s) => {
                self.host.busy_interval_ms = u32::from(s) * 1000;
                self.host.next_busy_ms = None;
            }
            None => {
                let mut line = Text::<16>::new();
                line.push("M113 S")
                    .push_number(self.host.busy_interval_ms / 1000);
                let _ = wire::reply(out, &Reply::Echo(line.as_str()));
            }
        }
    }

    /// The unrequested lines that are due: a temperature report (`M155`), a
    /// `busy: processing` while a line waits for the machine.
    pub(super) fn host_reports<W: Write>(&mut self, out: &mut W) {
        let now = self.clock.ms;
        if self.host.auto_report_ms > 0 && self.clock.reached(self.host.next_auto_report_ms) {
            self.host.next_auto_report_ms = now.wrapping_add(self.host.auto_report_ms);
            self.report_temperatures(out);
        }
        let waiting = matches!(
            self.link.held,
            Some(Held::Line | Held::Homing | Held::Dwell | Held::Probe)
        );
        // A grbl sender has no keep-alive line: it polls with `?`.
        if !waiting || self.host.busy_interval_ms == 0 || self.speaks_grbl() {
            self.host.next_busy_ms = None;
            return;
        }
        match self.host.next_busy_ms {
            None => self.host.next_busy_ms = Some(now.wrapping_add(self.host.busy_interval_ms)),
            Some(due) if self.clock.reached(due) => {
                self.host.next_busy_ms = Some(now.wrapping_add(self.host.busy_interval_ms));
                let _ = wire::reply(out, &Reply::Busy);
            }
            Some(_) => {}
        }
    }

    /// How long until [`Core::host_reports`] has a line to write, ms, if it will.
    pub(super) fn host_reports_in(&self) -> Option<u32> {
        let auto =
            (self.host.auto_report_ms > 0).then(|| self.clock.until(self.host.next_auto_report_ms));
        let busy = self.host.next_busy_ms.map(|due| self.clock.until(due));
        match (auto, busy) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::host_line;

    #[test]
    fn m118_flags_lead_the_text() {
        assert_eq!(host_line(b"Hello world"), ("", &b"Hello world"[..]));
        assert_eq!(host_line(b"E1 Hello"), ("echo:", &b"Hello"[..]));
        assert_eq!(
            host_line(b"A1 P0 action:pause"),
            ("// ", &b"action:pause"[..])
        );
        assert_eq!(host_line(b"E1"), ("echo:", &b""[..]));
        assert_eq!(host_line(b"E12 volts"), ("", &b"E12 volts"[..]));
    }
}
