//! The client's loops over a real TCP connection to a model controller that follows
//! `docs/protocol.md` with the protocol crate's own decoder and numbering, and damages what it
//! receives: the I/O side of `send`, `console` and `upload`, fast and without the simulator.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use forja_host::client::{self, Quiet};
use forja_host::frames::{FrameClient, UploadOptions};
use forja_host::link::{Connection, LinkSpec};
use forja_host::program::Program;
use forja_host::streamer::{Config, Window};
use forja_protocol::frame::{ClientMessage, ControllerMessage, FRAME_LEN, Progress};
use forja_protocol::gcode::{Line, LineNumbering, Recovery};
use forja_protocol::stream::{Decoder, Event};

/// What the model controller ran and stored.
#[derive(Default)]
struct Seen {
    /// Numbers of the G-code lines run, in order.
    ran: Vec<u32>,
    /// Texts of the program lines stored, in order.
    stored: Vec<String>,
    /// Lone line ends received (a line end right after another): the client's keep-alives.
    keep_alives: usize,
}

/// How the model damages what it receives (a fixed seed: the same bytes, the same damage).
#[derive(Clone, Copy)]
struct Damage {
    /// Probability that a byte has one bit flipped.
    flip: f64,
    /// Probability that a byte is lost.
    drop: f64,
}

/// Serve one client on `listener`: answer G-code lines and frames, damaging received bytes.
fn serve(listener: TcpListener, damage: Damage, seen: Arc<Mutex<Seen>>) {
    let (mut stream, _) = listener.accept().unwrap();
    stream.set_nodelay(true).unwrap();
    let mut decoder = Decoder::new();
    let mut numbering = LineNumbering::new();
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut buf = [0u8; 4096];
    let mut total = 0u16;
    let mut last = 0u8;
    stream.write_all(b"start\n").unwrap();
    loop {
        let n = match stream.read(&mut buf) {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        let mut received = Vec::with_capacity(n);
        let mut keep_alives = 0;
        for &b in &buf[..n] {
            if b == b'\n' && last == b'\n' {
                keep_alives += 1;
            }
            last = b;
            let mut draw = || {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                (rng >> 11) as f64 / (1u64 << 53) as f64
            };
            if draw() < damage.drop {
                continue;
            }
            if draw() < damage.flip {
                received.push(b ^ (1 << (rng % 8)));
            } else {
                received.push(b);
            }
        }
        let mut out: Vec<u8> = Vec::new();
        let mut seen = seen.lock().unwrap();
        seen.keep_alives += keep_alives;
        decoder.feed_all(&received, |event| {
            let recovery = match event {
                Event::Line(bytes) => match Line::parse(bytes) {
                    Ok(line) => match numbering.accept(&line) {
                        Ok(()) => {
                            if let Some(n) = line.number()
                                && !line.is_empty()
                                && !line.is_command(b'M', 110)
                            {
                                seen.ran.push(n);
                            }
                            let reply: &[u8] = if line.is_command(b'M', 114) {
                                b"X:1.0 Y:2.0 Count X:80 Y:160\nok\n"
                            } else {
                                b"ok\n"
                            };
                            out.extend_from_slice(reply);
                            None
                        }
                        Err(e) => Some(numbering.recover(&e)),
                    },
                    Err(e) => Some(numbering.recover(&e)),
                },
                Event::Garbage { .. } => Some(numbering.recover_garbage()),
                Event::Frame(frame) => {
                    let mut reply = [0u8; FRAME_LEN];
                    let answer = match ClientMessage::parse(&frame) {
                        Ok(ClientMessage::LoadLine {
                            index,
                            text,
                            total: t,
                        }) => {
                            if index == 1 {
                                seen.stored.clear();
                                total = t;
                            }
                            if usize::from(index) == seen.stored.len() + 1 && t == total {
                                seen.stored.push(text.to_string());
                                (index == t)
                                    .then_some(ControllerMessage::Confirm { what: "Gcode-load" })
                            } else {
                                Some(ControllerMessage::Error {
                                    code: 170,
                                    detail: "line-order",
                                })
                            }
                        }
                        Ok(ClientMessage::Request { message_type: 52 }) => {
                            Some(ControllerMessage::Progress(Progress {
                                total_lines: seen.stored.len() as u32,
                                ..Progress::default()
                            }))
                        }
                        Ok(_) => None,
                        Err(_) => Some(ControllerMessage::Error {
                            code: 21,
                            detail: "frame",
                        }),
                    };
                    if let Some(m) = answer {
                        m.encode(&mut reply).unwrap();
                        out.extend_from_slice(&reply);
                        out.push(b'\n');
                    }
                    None
                }
                _ => None,
            };
            match recovery {
                Some(Recovery::Resend(n)) => {
                    out.extend_from_slice(format!("rs {n}\nok\n").as_bytes());
                }
                Some(_) => out.extend_from_slice(b"echo:E8 bad-character\nok\n"),
                None => {}
            }
        });
        drop(seen);
        if stream.write_all(&out).is_err() {
            return;
        }
    }
}

fn controller(damage: Damage) -> (String, Arc<Mutex<Seen>>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let seen = Arc::new(Mutex::new(Seen::default()));
    let s = Arc::clone(&seen);
    std::thread::spawn(move || serve(listener, damage, s));
    (addr, seen)
}

fn connect(addr: &str) -> Connection {
    let mut conn = Connection::open(&LinkSpec::Tcp {
        address: addr.into(),
    })
    .unwrap();
    client::drain(&mut conn, Duration::from_millis(100)).unwrap();
    conn
}

fn program(n: usize) -> Program {
    let text: String = (0..n)
        .map(|i| format!("G1 X{}.{} Y-{} F3000 ; move {i}\n", i, i % 10, i * 3 + 1))
        .collect();
    Program::parse(text.as_bytes()).unwrap()
}

#[test]
fn send_runs_every_line_once_through_a_damaging_link() {
    for (corrupt, window) in [
        (0.0, Window::TCP),
        (0.003, Window::TCP),
        (0.003, Window::UART),
        (0.003, Window::PING_PONG),
    ] {
        let (addr, seen) = controller(Damage {
            flip: corrupt,
            drop: corrupt / 3.0,
        });
        let mut conn = connect(&addr);
        let p = program(500);
        let config = Config {
            window,
            ..Config::default()
        };
        let report = client::send_program(&mut conn, &p, config, &mut Quiet).unwrap();
        assert_eq!(report.lines, 500);
        let ran = seen.lock().unwrap().ran.clone();
        let mut expected: Vec<u32> = (1..=500).collect();
        // A line damaged past its checksum is refused by the controller, and reported.
        let refused: Vec<u32> = report
            .refused
            .iter()
            .map(|r| r.source_line as u32)
            .collect();
        expected.retain(|n| !refused.contains(n));
        assert_eq!(
            ran, expected,
            "corrupt {corrupt}, {window:?}: {:?}",
            report.stats
        );
        if corrupt == 0.0 {
            assert_eq!(report.stats.lines_resent, 0);
        }
    }
}

#[test]
fn upload_stores_every_line_through_a_lossy_link() {
    // Frames carry no checksum: a flipped bit inside a G-code text cannot be seen by anyone,
    // so the damage here is lost bytes, which always break a frame's 53-byte structure.
    for drop in [0.0, 0.002] {
        let (addr, seen) = controller(Damage { flip: 0.0, drop });
        let mut conn = connect(&addr);
        let p = program(120);
        let texts = p.frame_texts().unwrap();
        let mut frames = FrameClient::new(&mut conn, Duration::from_millis(500));
        let report = frames
            .upload(&texts, UploadOptions::default(), |_| {})
            .unwrap();
        assert_eq!(report.lines, 120);
        assert_eq!(seen.lock().unwrap().stored, texts, "drop {drop}");
        if drop == 0.0 {
            assert!(report.confirmed);
            assert_eq!(report.resent, 0);
        }
    }
}

#[test]
fn console_shows_replies_and_explains_what_it_does_not_send() {
    let (addr, seen) = controller(Damage {
        flip: 0.0,
        drop: 0.0,
    });
    let mut conn = connect(&addr);
    let (tx, rx) = mpsc::channel();
    for line in ["G21", "M114", "G1 X#", "M110 N5", "G1 X2 ; done"] {
        tx.send(line.to_string()).unwrap();
    }
    drop(tx);
    let mut out = Vec::new();
    client::console(&mut conn, &rx, &mut out, Config::default()).unwrap();
    let out = String::from_utf8(out).unwrap();
    assert!(out.contains("X:1.0 Y:2.0 Count"), "{out}");
    assert!(out.contains("not sent: a letter without a number"), "{out}");
    assert!(
        out.contains("not sent: forja numbers the lines itself"),
        "{out}"
    );
    assert_eq!(seen.lock().unwrap().ran, [1, 2, 3]);
}

#[test]
fn a_silent_controller_is_reported() {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    std::thread::spawn(move || {
        let (s, _): (TcpStream, _) = listener.accept().unwrap();
        std::thread::sleep(Duration::from_secs(5));
        drop(s);
    });
    let mut conn = connect(&addr);
    let config = Config {
        handshake_attempts: 2,
        handshake_interval: Duration::from_millis(200),
        ..Config::default()
    };
    let e = client::send_program(&mut conn, &program(3), config, &mut Quiet).unwrap_err();
    assert!(e.to_string().contains("does not answer"), "{e}");
}

/// The board ends the session of a controlling host that sends nothing for 60 s: an idle
/// console was cut off. It now sends a lone line end every keep-alive period while the person
/// types nothing — not a line: the numbering goes on undisturbed and nothing shows.
#[test]
fn an_idle_console_keeps_its_session_with_lone_line_ends() {
    let (addr, seen) = controller(Damage {
        flip: 0.0,
        drop: 0.0,
    });
    let mut conn = connect(&addr);
    conn.set_keep_alive_period(Duration::from_millis(20));
    let (tx, rx) = mpsc::channel();
    tx.send("M114".to_string()).unwrap();
    // The person types nothing more until the controller has had three keep-alives (the
    // deadline only guards against a hang).
    let s = Arc::clone(&seen);
    let typist = std::thread::spawn(move || {
        let deadline = Instant::now() + Duration::from_secs(20);
        while s.lock().unwrap().keep_alives < 3 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(5));
        }
        tx.send("G1 X2".to_string()).unwrap();
    });
    let mut out = Vec::new();
    client::console(&mut conn, &rx, &mut out, Config::default()).unwrap();
    typist.join().unwrap();
    let seen = seen.lock().unwrap();
    assert!(seen.keep_alives >= 3, "{} keep-alives", seen.keep_alives);
    assert_eq!(seen.ran, [1, 2]);
    let out = String::from_utf8(out).unwrap();
    assert!(out.contains("X:1.0 Y:2.0 Count"), "{out}");
    assert!(!out.lines().any(str::is_empty), "{out:?}");
}

#[test]
fn a_keep_alive_goes_out_only_after_a_period_without_writing() {
    let (addr, seen) = controller(Damage {
        flip: 0.0,
        drop: 0.0,
    });
    let mut conn = connect(&addr);
    let t0 = Instant::now();
    let period = forja_host::link::KEEP_ALIVE_PERIOD;
    assert!(
        period <= Duration::from_secs(30),
        "well inside the 60 s idle time-out"
    );
    conn.send(b"M114\n").unwrap();
    assert!(!conn.keep_alive_at(t0 + period / 2).unwrap());
    assert!(conn.keep_alive_at(t0 + period * 2).unwrap());
    assert!(!conn.keep_alive_at(t0 + period * 2 + period / 2).unwrap());
    assert!(conn.keep_alive_at(t0 + period * 3 + period / 10).unwrap());
    let deadline = Instant::now() + Duration::from_secs(20);
    while seen.lock().unwrap().keep_alives < 2 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(seen.lock().unwrap().keep_alives, 2);
    assert_eq!(
        conn.bytes_written(),
        5 + 2 * forja_host::link::KEEP_ALIVE.len() as u64
    );
}
