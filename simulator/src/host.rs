//! The host's side of a simulated link: a job streamed by the `forja` client's own senders.
//!
//! [`StreamHost`] drives [`forja_host::streamer::Streamer`], the sender `forja send` uses, over
//! bytes: give it what the controller sent with the time ([`StreamHost::exchange`]), write what
//! it returns to the link. It cuts the bytes into reply lines, turns milliseconds (virtual ones
//! on an in-memory link, the wall clock's on an OS link) into the streamer's instants, and keeps
//! what a test or a summary asks about: every reply line and every event.
//!
//! [`GrblHost`] does the same in the grbl dialect with
//! [`forja_host::grbl_sender::GrblSender`], the sender of `forja send --grbl` (character
//! counting), and plays the operator: it answers a hold that asks for a cycle start (an `M6`
//! tool change) with `~`, and keeps a log of what it told and did.

use std::time::{Duration, Instant};

use forja_host::grbl_sender::{self, GrblSender};
use forja_host::streamer::{Config, Event, Phase, PushError, Stats, Streamer};
use forja_protocol::grbl::{Realtime, StatusText};
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

/// A refused line, an alarm or a failure of a [`GrblHost`]'s run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GrblFault {
    /// What came: `error:15`, `ALARM:1`, `the controller restarted`, `no banner`.
    pub what: String,
    /// For a refused line: its 1-based place among the lines given to [`GrblHost::new`], and
    /// the line as sent.
    pub line: Option<(usize, String)>,
}

/// Streams a job in the grbl dialect through the client's [`GrblSender`], and answers the
/// holds that ask for a cycle start as an operator would. See the [module documentation](self).
#[derive(Debug)]
pub struct GrblHost {
    sender: GrblSender,
    /// The instant of time 0 µs.
    epoch: Instant,
    partial: Vec<u8>,
    replies: Vec<String>,
    /// The place among the lines given to [`GrblHost::new`] of each line pushed.
    places: Vec<usize>,
    faults: Vec<GrblFault>,
    log: Vec<String>,
    cycle_start: bool,
    /// The `Ln:` of the last status report, and how many reports had a smaller one.
    line_number: u32,
    line_number_regressions: u32,
}

impl GrblHost {
    /// A host that streams `lines` (G-code, cleaned as [`grbl_sender::clean_line`] says) with
    /// `config`, and ends the job after them ([`GrblSender::finish`]). It answers a hold that
    /// asks for a cycle start with `~` (see [`GrblHost::set_cycle_start`]).
    ///
    /// Errors: a line that cannot be sent (it holds a realtime character or a control byte, or
    /// is too long), with its 1-based place in `lines`.
    pub fn new<'a>(
        config: grbl_sender::Config,
        lines: impl IntoIterator<Item = &'a str>,
    ) -> Result<Self, (usize, grbl_sender::PushError)> {
        let mut sender = GrblSender::new(config);
        let mut places = Vec::new();
        for (i, line) in lines.into_iter().enumerate() {
            if sender.push(line).map_err(|e| (i + 1, e))?.is_some() {
                places.push(i + 1);
            }
        }
        sender.finish();
        Ok(Self {
            sender,
            epoch: Instant::now(),
            partial: Vec::new(),
            replies: Vec::new(),
            places,
            faults: Vec::new(),
            log: Vec::new(),
            cycle_start: true,
            line_number: 0,
            line_number_regressions: 0,
        })
    }

    /// Whether a hold that asks for a cycle start is answered with `~` (the default), as the
    /// operator presses cycle start once the tool is changed.
    pub fn set_cycle_start(&mut self, on: bool) {
        self.cycle_start = on;
    }

    /// Take the bytes the controller sent (`received`, possibly none) at `now_us`
    /// microseconds, and return the bytes to write to the link now (possibly none).
    pub fn exchange(&mut self, received: &[u8], now_us: u64) -> Vec<u8> {
        let now = self.epoch + Duration::from_micros(now_us);
        self.partial.extend_from_slice(received);
        while let Some(end) = self.partial.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = self.partial.drain(..=end).collect();
            let text = String::from_utf8_lossy(&line).trim_end().to_string();
            if text.is_empty() {
                continue;
            }
            self.sender.receive(now, text.as_bytes());
            if let Some(number) = StatusText::parse(text.as_bytes())
                .and_then(|r| r.field(b"Ln"))
                .and_then(|v| std::str::from_utf8(v).ok()?.parse::<u32>().ok())
            {
                if number < self.line_number {
                    self.line_number_regressions += 1;
                }
                self.line_number = number;
            }
            self.replies.push(text);
        }
        let at = now_us as f64 / 1e6;
        while let Some(event) = self.sender.next_event() {
            match event {
                grbl_sender::Event::Refused { number, code, text } => {
                    let place = self.places.get(number as usize - 1).copied().unwrap_or(0);
                    self.fault(format!("error:{code}"), Some((place, text)));
                }
                grbl_sender::Event::Alarm { code } => self.fault(format!("ALARM:{code}"), None),
                grbl_sender::Event::Restarted => self.fault("the controller restarted", None),
                grbl_sender::Event::NoBanner => self.fault("no banner", None),
                grbl_sender::Event::AwaitingCycleStart(text) if self.cycle_start => {
                    self.sender.realtime(Realtime::CycleStart);
                    self.log.push(format!(
                        "[{at:.3} s] [MSG:{text}]: operator: cycle start (~)"
                    ));
                }
                grbl_sender::Event::AwaitingCycleStart(text)
                | grbl_sender::Event::Message(text) => {
                    self.log.push(format!("[{at:.3} s] [MSG:{text}]"));
                }
                _ => {}
            }
        }
        let mut out = Vec::new();
        self.sender.transmit(now, &mut out);
        out
    }

    fn fault(&mut self, what: impl Into<String>, line: Option<(usize, String)>) {
        self.faults.push(GrblFault {
            what: what.into(),
            line,
        });
    }

    /// The sender, for its phase, counts and answers.
    pub fn sender(&self) -> &GrblSender {
        &self.sender
    }

    /// The sender's counters.
    pub fn stats(&self) -> grbl_sender::Stats {
        self.sender.stats()
    }

    /// Whether every line was answered.
    pub fn is_done(&self) -> bool {
        self.sender.phase() == grbl_sender::Phase::Done
    }

    /// Whether nothing more will be sent: the job is done, or it stopped (an alarm, a restart
    /// of the controller, no banner).
    pub fn is_over(&self) -> bool {
        self.sender.is_over()
    }

    /// Every line received so far, in order, without its terminator.
    pub fn replies(&self) -> &[String] {
        &self.replies
    }

    /// The refusals (`error:N`, with the line), alarms and failures, in order.
    pub fn faults(&self) -> &[GrblFault] {
        &self.faults
    }

    /// The operator's log: each `[MSG:…]` with its virtual time, and the cycle starts sent.
    pub fn log(&self) -> &[String] {
        &self.log
    }

    /// How many status reports gave a smaller `Ln:` than the report before: the controller
    /// prepared a line's motion after a later line's (0 when lines run in order).
    pub fn line_number_regressions(&self) -> u32 {
        self.line_number_regressions
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

    #[test]
    fn the_grbl_host_resets_counts_and_answers_a_tool_change() {
        let config = grbl_sender::Config {
            report_buffer: true,
            status_interval: None,
            ..grbl_sender::Config::default()
        };
        let mut h = GrblHost::new(config, ["(setup)", "N10 M6 T2", "N20 G0 X1 ; go"]).unwrap();
        assert_eq!(h.exchange(b"", 0), [0x18]);
        assert_eq!(
            text(&h.exchange(b"Grbl 1.1h ['$' for help]\r\n", 10)),
            "$10=3\n"
        );
        assert_eq!(text(&h.exchange(b"ok\n", 20)), "?");
        assert_eq!(
            text(&h.exchange(b"<Idle|MPos:0.000,0.000,0.000|Bf:15,768|Ln:0>\n", 1020)),
            "N10 M6 T2\nN20 G0 X1\n"
        );
        assert_eq!(h.stats().max_status_latency, Duration::from_micros(1000));
        assert_eq!(h.sender().rx_buffer_bytes(), 768);
        // The hold: the operator's `~`, logged.
        let out = h.exchange(
            b"[MSG:Change to tool T2, then cycle start]\nok\n",
            2_500_000,
        );
        assert_eq!(text(&out), "~");
        assert_eq!(
            h.log(),
            ["[2.500 s] [MSG:Change to tool T2, then cycle start]: operator: cycle start (~)"]
        );
        assert!(
            h.exchange(
                b"<Run|MPos:0.5,0,0|Ln:20>\n<Run|MPos:0.6,0,0|Ln:10>\n",
                2_600_000
            )
            .is_empty()
        );
        assert_eq!(h.line_number_regressions(), 1);
        assert!(!h.is_over());
        h.exchange(b"error:20\n", 2_700_000);
        assert!(h.is_done());
        assert_eq!(
            h.faults(),
            [GrblFault {
                what: "error:20".into(),
                line: Some((3, "N20 G0 X1".into()))
            }]
        );
    }
}
