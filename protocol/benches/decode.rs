//! Decode throughput of the protocol layer: G-code lines, 53-byte frames and the mixed stream.
//!
//! Run with `cargo bench -p forja-protocol` (or `cargo xtask bench`); the figures are recorded
//! in `docs/performance.md`.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use forja_protocol::frame::{
    AxisPosition, ClientMessage, ControllerMessage, FRAME_LEN, Positions, Progress,
};
use forja_protocol::gcode::{Decimal, Line, write_numbered};
use forja_protocol::stream::{Decoder, Event};

/// A program as a slicer writes it, numbered and checksummed as a host streams it: one line
/// per entry, `\n`-terminated.
fn program(lines: u32) -> Vec<u8> {
    let mut out = Vec::new();
    let mut buf = [0u8; 256];
    for n in 1..=lines {
        let x = f64::from(n % 200) * 0.731 + 10.0;
        let y = f64::from(n % 170) * 0.517 + 20.0;
        let e = f64::from(n) * 0.033_21;
        let body = match n % 10 {
            0 => "G0 Z0.3 F9000".to_string(),
            1 => format!("G1 X{x:.3} Y{y:.3} F1800"),
            _ => format!("G1 X{x:.3} Y{y:.3} E{e:.5}"),
        };
        let len = write_numbered(n, body.as_bytes(), &mut buf).expect("fits");
        out.extend_from_slice(&buf[..len]);
        out.push(b'\n');
    }
    out
}

/// The frames a client sends while loading and running a program.
fn client_frames(count: u16) -> Vec<[u8; FRAME_LEN]> {
    (1..=count)
        .map(|i| {
            let msg = match i % 4 {
                0 => ClientMessage::Request { message_type: 51 },
                1 => ClientMessage::Jog {
                    step: Decimal::new(1, 2),
                    axis: b'X',
                    count: -250,
                },
                _ => ClientMessage::LoadLine {
                    index: i,
                    text: "G1 X12.345 Y67.89 E0.12345",
                    total: count,
                },
            };
            let mut out = [0u8; FRAME_LEN];
            msg.encode(&mut out).expect("valid");
            out
        })
        .collect()
}

/// The frames a controller sends: positions and progress.
fn controller_frames(count: u32) -> Vec<[u8; FRAME_LEN]> {
    (0..count)
        .map(|i| {
            let msg = if i % 2 == 0 {
                let mut p = Positions::new();
                for (axis, v) in [(b'X', 1), (b'Y', -2), (b'Z', 3), (b'A', 4)] {
                    p.push(AxisPosition {
                        axis,
                        value_tenth_um: v * (i as i32 + 12_345),
                    })
                    .expect("four axes");
                }
                ControllerMessage::Positions(p)
            } else {
                ControllerMessage::Progress(Progress {
                    elapsed_s: i,
                    estimated_s: 3000,
                    total_lines: 5000,
                    current_line: i,
                })
            };
            let mut out = [0u8; FRAME_LEN];
            msg.encode(&mut out).expect("valid");
            out
        })
        .collect()
}

fn lines(c: &mut Criterion) {
    let text = program(2000);
    let records: Vec<&[u8]> = text
        .split(|&b| b == b'\n')
        .filter(|l| !l.is_empty())
        .collect();
    let mut group = c.benchmark_group("gcode");
    group.throughput(Throughput::Bytes(text.len() as u64));
    group.bench_function("Line::parse", |b| {
        b.iter(|| {
            let mut words = 0;
            for record in &records {
                words += Line::parse(black_box(record)).map_or(0, |l| l.words().len());
            }
            words
        })
    });
    group.finish();
}

fn frames(c: &mut Criterion) {
    let client = client_frames(2000);
    let controller = controller_frames(2000);
    let mut group = c.benchmark_group("frame");
    group.throughput(Throughput::Bytes((client.len() * FRAME_LEN) as u64));
    group.bench_function("ClientMessage::decode", |b| {
        b.iter(|| {
            client
                .iter()
                .filter(|f| ClientMessage::decode(black_box(&f[..])).is_ok())
                .count()
        })
    });
    group.throughput(Throughput::Bytes((controller.len() * FRAME_LEN) as u64));
    group.bench_function("ControllerMessage::decode", |b| {
        b.iter(|| {
            controller
                .iter()
                .filter(|f| ControllerMessage::decode(black_box(&f[..])).is_ok())
                .count()
        })
    });
    group.finish();
}

fn mixed(c: &mut Criterion) {
    // Two G-code lines, then a frame, over and over, as a controller receives them.
    let text = program(3000);
    let frames = client_frames(1500);
    let mut link = Vec::new();
    for (i, line) in text.split_inclusive(|&b| b == b'\n').enumerate() {
        link.extend_from_slice(line);
        if i % 2 == 1
            && let Some(f) = frames.get(i / 2)
        {
            link.extend_from_slice(f);
            link.push(b'\n');
        }
    }
    let mut group = c.benchmark_group("stream");
    group.throughput(Throughput::Bytes(link.len() as u64));
    for chunk in [1usize, 64, 4096] {
        group.bench_function(format!("split/{chunk}-byte chunks"), |b| {
            b.iter(|| {
                let mut decoder = Decoder::new();
                let mut n = 0usize;
                for piece in link.chunks(chunk) {
                    decoder.feed_all(black_box(piece), |_| n += 1);
                }
                n
            })
        });
    }
    group.bench_function("split+decode/64-byte chunks", |b| {
        b.iter(|| {
            let mut decoder = Decoder::new();
            let mut ok = 0usize;
            for piece in link.chunks(64) {
                decoder.feed_all(black_box(piece), |event| match event {
                    Event::Line(bytes) => ok += usize::from(Line::parse(bytes).is_ok()),
                    Event::Frame(frame) => ok += usize::from(ClientMessage::parse(&frame).is_ok()),
                    _ => {}
                });
            }
            ok
        })
    });
    group.finish();
}

criterion_group!(benches, lines, frames, mixed);
criterion_main!(benches);
