//! The TCP link against real sockets on the loopback interface.

use std::io::{Read as _, Write as _};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use embedded_io::Write;
use forja_hal_abstraction::link::{LinkState, LinkStatus};
use forja_sim::link::{FaultConfig, FaultInjector, FaultyBytes, HostLink, TcpLink};

const TIMEOUT: Duration = Duration::from_secs(5);

fn bind() -> TcpLink {
    TcpLink::bind("127.0.0.1:0".parse().unwrap(), &b"error: busy\n"[..]).unwrap()
}

/// Poll `link` until `done` holds, for at most five seconds.
fn poll_until<L: HostLink>(link: &mut L, mut done: impl FnMut(&mut L) -> bool) {
    let start = Instant::now();
    loop {
        let _ = link.poll();
        if done(link) {
            return;
        }
        assert!(start.elapsed() < TIMEOUT, "timed out");
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// Read from `link` without blocking until `n` bytes have arrived.
fn receive<L: HostLink>(link: &mut L, n: usize) -> Vec<u8> {
    let mut got = Vec::new();
    poll_until(link, |l| {
        let mut buf = [0u8; 256];
        while l.read_ready().unwrap_or(false) {
            let k = l.read(&mut buf).unwrap_or(0);
            got.extend_from_slice(&buf[..k]);
        }
        got.len() >= n
    });
    got
}

fn client(link: &TcpLink) -> TcpStream {
    let c = TcpStream::connect(link.local_addr().unwrap()).unwrap();
    c.set_read_timeout(Some(TIMEOUT)).unwrap();
    c
}

#[test]
fn carries_bytes_both_ways() {
    let mut link = bind();
    assert_ne!(
        link.local_addr().unwrap().port(),
        0,
        "port 0 resolves to a real port"
    );
    assert_eq!(link.state(), LinkState::Disconnected);
    let mut c = client(&link);
    poll_until(&mut link, |l| l.state() == LinkState::Connected);
    assert_eq!(link.connections(), 1);
    assert_eq!(link.peer_addr(), Some(c.local_addr().unwrap()));

    c.write_all(b"M115\nG0 X10\n").unwrap();
    assert_eq!(receive(&mut link, 12), b"M115\nG0 X10\n");

    link.write_all(b"ok\nok\n").unwrap();
    link.flush().unwrap();
    let mut buf = [0u8; 6];
    c.read_exact(&mut buf).unwrap();
    assert_eq!(&buf, b"ok\nok\n");
}

#[test]
fn a_second_client_is_refused_with_the_busy_message() {
    let mut link = bind();
    let mut first = client(&link);
    poll_until(&mut link, |l| l.state() == LinkState::Connected);

    let mut second = client(&link);
    poll_until(&mut link, |l| l.refused() == 1);
    let mut text = String::new();
    second.read_to_string(&mut text).unwrap();
    assert_eq!(text, "error: busy\n", "one line, then closed");

    // The first client keeps control.
    assert_eq!(link.connections(), 1);
    first.write_all(b"?").unwrap();
    assert_eq!(receive(&mut link, 1), b"?");

    // Once it leaves, the next client is accepted.
    drop(first);
    poll_until(&mut link, |l| l.state() == LinkState::Disconnected);
    let _third = client(&link);
    poll_until(&mut link, |l| l.state() == LinkState::Connected);
    assert_eq!(link.connections(), 2);
    assert_eq!(link.refused(), 1);
}

#[test]
fn writes_without_a_client_are_discarded() {
    let mut link = bind();
    assert!(embedded_io::WriteReady::write_ready(&mut link).unwrap());
    assert_eq!(link.write(b"nobody hears this\n").unwrap(), 18);
    let mut c = client(&link);
    poll_until(&mut link, |l| l.state() == LinkState::Connected);
    link.write_all(b"ok\n").unwrap();
    let mut buf = [0u8; 3];
    c.read_exact(&mut buf).unwrap();
    assert_eq!(&buf, b"ok\n");
}

#[test]
fn fault_injection_over_tcp_is_reproducible() {
    let config = FaultConfig {
        corrupt_rate: 0.02,
        drop_rate: 0.01,
        seed: 42,
    };
    let data: Vec<u8> = (0..20_000).map(|i| b"G1 X1.5 Y-2 F900\n"[i % 17]).collect();
    let mut expected = Vec::new();
    FaultyBytes::new(config)
        .unwrap()
        .apply_all(&data, &mut expected);

    let mut link = FaultInjector::new(bind(), config).unwrap();
    let mut c = client(link.inner());
    poll_until(&mut link, |l| l.state() == LinkState::Connected);
    c.write_all(&data).unwrap();
    let got = receive(&mut link, expected.len());
    assert_eq!(got, expected);
    let stats = link.stats();
    assert_eq!(stats.bytes, data.len() as u64);
    assert!(stats.dropped > 100 && stats.corrupted > 200, "{stats:?}");
}
