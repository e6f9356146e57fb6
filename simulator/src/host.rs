//! The host's side of a simulated link: a job streamed by the `forja` client's own streamer.
//!
//! [`StreamHost`] drives [`forja_host::streamer::Streamer`], the sender `forja send` uses, over
//! bytes: give it what the controller sent with the time ([`StreamHost::exchange`]), write what
//! it returns to the link. It cuts the bytes into reply lines, turns milliseconds (virtual ones
//! on an in-memory link, the wall clock's on an OS link) into the streamer's instants, and keeps
//! what a test or a summary asks about: every reply line and every event.

use std::time::{Duration, Instant};

use forja_host::streamer::{Config, Event, Phase, PushError, Stats, Streamer};
use forja_protocol::reply::Reply;

/// Streams a job through the client's [`Streamer`]. See the [module documentation](self).
#[derive(Debug)]
pub struct StreamHost {
    streamer: Streamer,
    /// The instant of time 0 ms.
    epoch: Instant,
    partial: Vec<u8>,
    replies: Vec<String>,
    events: Vec<Event>,
}

impl StreamHost {
    /// A host that streams `lines` (G-code without line numbers or checks) with `config`, and
    /// closes the job after them (see [`Streamer::finish`]).
    ///
    /// Errors: a line that cannot be sent (it holds `*` or a control byte, or is too long once
    /// numbered), with its 1-based place in `lines`.
    pub fn new<'a>(
        config: Config,
        lines: impl IntoIterator<Item = &'a str>,
    ) -> Result<Self, (usize, PushError)> {
        let mut streamer = Streamer::new(config);
        for (i, line) in lines.into_iter().enumerate() {
            streamer.push(line).map_err(|e| (i + 1, e))?;
        }
        streamer.finish();
        Ok(Self {
            streamer,
            epoch: Instant::now(),
            partial: Vec::new(),
            replies: Vec::new(),
            events: Vec::new(),
        })
    }

    /// Take the bytes the controller sent (`received`, possibly none) at `now_ms`, and return
    /// the bytes to write to the link now (possibly none).
    pub fn exchange(&mut self, received: &[u8], now_ms: u64) -> Vec<u8> {
        let now = self.epoch + Duration::from_millis(now_ms);
        self.partial.extend_from_slice(received);
        while let Some(end) = self.partial.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = self.partial.drain(..=end).collect();
            let text = String::from_utf8_lossy(&line).trim_end().to_string();
            if !text.is_empty() {
                self.streamer.receive(now, text.as_bytes());
                self.replies.push(text);
            }
        }
        self.streamer.poll(now);
        let mut out = Vec::new();
        self.streamer.transmit(now, &mut out);
        self.events
            .extend(std::iter::from_fn(|| self.streamer.next_event()));
        out
    }

    /// The streamer, for its phase and counts.
    pub fn streamer(&self) -> &Streamer {
        &self.streamer
    }

    /// The streamer's counters.
    pub fn stats(&self) -> Stats {
        self.streamer.stats()
    }

    /// Whether the controller took every line, the closing one included.
    pub fn is_done(&self) -> bool {
        self.streamer.phase() == Phase::Done
    }

    /// Whether nothing more will be sent: the job is done, or it stopped (an alarm, a restart
    /// of the controller, no answer to the handshake, line numbers out of step).
    pub fn is_over(&self) -> bool {
        matches!(
            self.streamer.phase(),
            Phase::Done | Phase::Alarm | Phase::Failed
        )
    }

    /// Every reply line received so far, in order, without its terminator.
    pub fn replies(&self) -> &[String] {
        &self.replies
    }

    /// The refusals (`echo:E…`, `echo:Unknown command: …`) and faults (`Error:…`) among the
    /// replies, in order.
    pub fn faults(&self) -> impl Iterator<Item = &str> {
        self.replies.iter().map(String::as_str).filter(|l| {
            matches!(
                Reply::parse(l.as_bytes()),
                Ok(Reply::Refused { .. } | Reply::Unknown(_) | Reply::Fault { .. })
            )
        })
    }

    /// Every event of the streamer so far, in order.
    pub fn events(&self) -> &[Event] {
        &self.events
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use forja_host::streamer::Window;

    fn text(b: &[u8]) -> &str {
        std::str::from_utf8(b).unwrap()
    }

    #[test]
    fn replies_are_cut_into_lines_and_time_drives_the_streamer() {
        let config = Config {
            window: Window::PING_PONG,
            ..Config::default()
        };
        let mut h = StreamHost::new(config, ["G21 ; mm", "G1 X1"]).unwrap();
        assert_eq!(text(&h.exchange(b"", 0)), "\r\nN0 M110 N0*125\r\n");
        assert!(h.exchange(b"sta", 1).is_empty());
        // `start` ends the partial line: the handshake goes again at once.
        assert_eq!(text(&h.exchange(b"rt\r\n", 2)), "\r\nN0 M110 N0*125\r\n");
        assert_eq!(text(&h.exchange(b"ok\n", 3)), "N1 G21*27\r\n");
        assert_eq!(h.events(), [Event::Synchronised]);
        // Nothing answered for the quiet time: one lone line end.
        let quiet = 3 + config.quiet_timeout.as_millis() as u64;
        assert_eq!(text(&h.exchange(b"", quiet)), "\r\n");
        assert!(h.exchange(b"", quiet + 1).is_empty());
        assert_eq!(text(&h.exchange(b"ok\n", quiet + 2)), "N2 G1 X1*99\r\n");
        assert_eq!(
            text(&h.exchange(b"echo:Unknown command: \"M1\"\nok\n", quiet + 3)),
            "N3*125\r\n"
        );
        assert!(!h.is_done());
        assert!(h.exchange(b"ok\n", quiet + 4).is_empty());
        assert!(h.is_done() && h.is_over());
        assert_eq!(
            h.faults().collect::<Vec<_>>(),
            ["echo:Unknown command: \"M1\""]
        );
        assert_eq!(h.replies().len(), 6);
        assert!(matches!(
            h.events()[1],
            Event::Refused {
                number: 2,
                code: 120,
                ..
            }
        ));
        assert_eq!(h.stats().nudges, 1);
        assert_eq!(h.stats().handshakes, 2);
    }

    #[test]
    fn a_line_that_cannot_be_sent_is_named() {
        let e = StreamHost::new(Config::default(), ["G1 X1", "G1 X2*7"]).unwrap_err();
        assert_eq!(e.0, 2);
    }
}
