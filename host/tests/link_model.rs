//! Link use of the windowed streamer on a modelled serial link, in virtual time.
//!
//! The model: the host writes lines into a link of `baud` bits a second (10 bits a byte); each
//! line reaches the controller `latency` after its last byte left (a USB-serial adapter's
//! latency, the operating system's), the controller takes `process` to handle it (numbering
//! checked by the protocol crate's `LineNumbering`, as the firmware does) and its `ok` comes
//! back the same way. The streamer is the real one, driven in virtual time. Link use is the
//! time the host→controller direction spends transmitting over the time from the first byte
//! to the last `ok`. `cargo test -p forja-host --test link_model -- --nocapture` prints the
//! table of `docs/performance.md`.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use forja_host::streamer::{Config, Phase, Streamer, Window};
use forja_protocol::gcode::{Line, LineNumbering};

struct Model {
    baud: f64,
    latency_s: f64,
    process_s: f64,
}

struct Outcome {
    link_use: f64,
    lines_per_s: f64,
}

fn job() -> Vec<String> {
    // Short segments, as a slicer or CAM post-processor writes them (about 24 bytes a line).
    (0..2000)
        .map(|i| {
            let a = f64::from(i) * 0.01;
            format!(
                "G1X{:.3}Y{:.3}F3000",
                50.0 + 40.0 * a.cos(),
                50.0 + 40.0 * a.sin()
            )
        })
        .collect()
}

fn run(model: &Model, window: Window, lines: &[String]) -> Outcome {
    let byte_s = 10.0 / model.baud;
    let base = Instant::now();
    let at = |t: f64| base + Duration::from_secs_f64(t);
    let mut s = Streamer::new(Config {
        window,
        ..Config::default()
    });
    for l in lines {
        s.push(l).unwrap();
    }
    s.finish();
    let mut numbering = LineNumbering::new();
    let mut t = 0.0f64;
    let mut link_free = 0.0f64;
    let mut ctrl_free = 0.0f64;
    let mut busy = 0.0f64;
    let mut first_byte: Option<f64> = None;
    // (time the reply reaches the host, the reply)
    let mut replies: VecDeque<(f64, String)> = VecDeque::new();
    let mut out = Vec::new();
    loop {
        out.clear();
        s.transmit(at(t), &mut out);
        for record in out.split(|&b| b == b'\n') {
            let record = record.strip_suffix(b"\r").unwrap_or(record);
            if record.is_empty() {
                continue;
            }
            let len = record.len() as f64 + 2.0;
            let start = t.max(link_free);
            first_byte.get_or_insert(start);
            link_free = start + len * byte_s;
            busy += len * byte_s;
            let handled = (link_free + model.latency_s).max(ctrl_free) + model.process_s;
            ctrl_free = handled;
            let line = Line::parse(record).unwrap();
            let reply = match numbering.accept(&line) {
                Ok(()) => "ok".to_string(),
                Err(e) => match numbering.recover(&e) {
                    forja_protocol::gcode::Recovery::Resend(n) => format!("rs {n}\nok"),
                    _ => "ok".to_string(),
                },
            };
            let back = handled + (reply.len() as f64 + 1.0) * byte_s + model.latency_s;
            replies.push_back((back, reply));
        }
        if s.phase() == Phase::Done {
            break;
        }
        let (when, reply) = replies.pop_front().expect("a reply is due");
        t = t.max(when);
        for line in reply.lines() {
            s.receive(at(t), line.as_bytes());
        }
        assert!(matches!(
            s.phase(),
            Phase::Streaming | Phase::Done | Phase::Handshake
        ));
    }
    let elapsed = t - first_byte.unwrap_or(0.0);
    Outcome {
        link_use: busy / elapsed,
        lines_per_s: lines.len() as f64 / elapsed,
    }
}

#[test]
fn a_window_keeps_a_serial_link_busy() {
    let lines = job();
    let mean = lines.iter().map(|l| l.len() + 10).sum::<usize>() as f64 / lines.len() as f64;
    println!("mean line on the wire: {mean:.1} bytes (N…*cs CR LF)");
    println!("| link | latency each way | one line at a time | window 256 B | window 2048 B |");
    println!("|---|---|---|---|---|");
    let mut checks = Vec::new();
    for (baud, latency_ms) in [
        (115_200.0, 1.0),
        (115_200.0, 16.0),
        (250_000.0, 1.0),
        (1_000_000.0, 1.0),
    ] {
        let model = Model {
            baud,
            latency_s: latency_ms / 1000.0,
            process_s: 50e-6,
        };
        let ping = run(&model, Window::PING_PONG, &lines);
        let uart = run(&model, Window::UART, &lines);
        let wide = run(
            &model,
            Window {
                bytes: 2048,
                lines: 128,
            },
            &lines,
        );
        println!(
            "| {baud} baud | {latency_ms} ms | {:.0} % ({:.0} lines/s) | {:.0} % ({:.0} lines/s) \
             | {:.0} % ({:.0} lines/s) |",
            ping.link_use * 100.0,
            ping.lines_per_s,
            uart.link_use * 100.0,
            uart.lines_per_s,
            wide.link_use * 100.0,
            wide.lines_per_s
        );
        checks.push((
            baud,
            latency_ms,
            ping.link_use,
            uart.link_use,
            wide.link_use,
        ));
    }
    for (baud, latency_ms, ping, uart, wide) in checks {
        assert!(uart > ping, "{baud} {latency_ms}");
        assert!(wide >= uart - 0.01, "{baud} {latency_ms}");
        if baud == 115_200.0 && latency_ms == 1.0 {
            assert!(uart > 0.97, "{uart}");
            assert!(ping < 0.6, "{ping}");
        }
    }
}
