//! The TCP link against real sockets on the loopback interface, its clients admitted and
//! refused by session rules of one controlling client (the board's are the application's
//! `LinkSession`, whose rules its own tests cover).

use std::io::{Read as _, Write as _};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use embedded_io::{ReadReady, Write};
use forja_drivers::port_link::{Admission, Admit};
use forja_hal_abstraction::link::{LinkState, LinkStatus};
use forja_sim_hal::link::{FaultConfig, FaultInjector, FaultyBytes, PortLink, TcpLink};

const TIMEOUT: Duration = Duration::from_secs(5);

fn bind() -> TcpLink {
    TcpLink::bind("127.0.0.1:0".parse().unwrap(), &b"error: busy\n"[..]).unwrap()
}

/// Session rules of one controlling client: the first client controls, any other is refused
/// while it does.
#[derive(Default)]
struct OneClient {
    /// When the controlling client was admitted, while it is in control.
    admitted_ms: Option<u32>,
}

impl LinkStatus for OneClient {
    fn state(&self) -> LinkState {
        if self.admitted_ms.is_some() {
            LinkState::Connected
        } else {
            LinkState::Disconnected
        }
    }
}

impl Admission for OneClient {
    fn on_connect(&mut self, now_ms: u32) -> Admit {
        if self.admitted_ms.is_some() {
            return Admit::Refuse;
        }
        self.admitted_ms = Some(now_ms);
        Admit::Control
    }
    fn on_disconnect(&mut self) {
        self.admitted_ms = None;
    }
}

/// A link and the session rules that decide who controls it, as a board serves them.
struct Served<L> {
    link: L,
    session: OneClient,
}

fn served<L: PortLink>(link: L) -> Served<L> {
    Served {
        link,
        session: OneClient::default(),
    }
}

/// Poll `s` (its link, then admission) until `done` holds, for at most five seconds.
fn poll_until<L: PortLink>(s: &mut Served<L>, mut done: impl FnMut(&mut Served<L>) -> bool) {
    let start = Instant::now();
    loop {
        let _ = s.link.poll();
        let _ = s.link.admit(&mut s.session, 0);
        if done(s) {
            return;
        }
        assert!(start.elapsed() < TIMEOUT, "timed out");
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// Read from `s` without blocking until `n` bytes have arrived.
fn receive<L: PortLink>(s: &mut Served<L>, n: usize) -> Vec<u8> {
    let mut got = Vec::new();
    poll_until(s, |s| {
        let mut buf = [0u8; 256];
        while s.link.read_ready().unwrap_or(false) {
            let k = s.link.read(&mut buf).unwrap_or(0);
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
    let mut s = served(bind());
    assert_ne!(
        s.link.local_addr().unwrap().port(),
        0,
        "port 0 resolves to a real port"
    );
    assert_eq!(s.link.state(), LinkState::Disconnected);
    let mut c = client(&s.link);
    poll_until(&mut s, |s| s.link.state() == LinkState::Connected);
    assert_eq!(s.link.connections(), 1);
    assert_eq!(s.link.peer_addr(), Some(c.local_addr().unwrap()));

    c.write_all(b"M115\nG0 X10\n").unwrap();
    assert_eq!(receive(&mut s, 12), b"M115\nG0 X10\n");

    s.link.write_all(b"ok\nok\n").unwrap();
    s.link.flush().unwrap();
    let mut buf = [0u8; 6];
    c.read_exact(&mut buf).unwrap();
    assert_eq!(&buf, b"ok\nok\n");
}

#[test]
fn a_second_client_is_refused_with_the_busy_message() {
    let mut s = served(bind());
    let mut first = client(&s.link);
    poll_until(&mut s, |s| s.link.state() == LinkState::Connected);

    let mut second = client(&s.link);
    poll_until(&mut s, |s| s.link.refused() == 1);
    let mut text = String::new();
    second.read_to_string(&mut text).unwrap();
    assert_eq!(text, "error: busy\n", "one line, then closed");

    // The first client keeps control.
    assert_eq!(s.link.connections(), 1);
    first.write_all(b"?").unwrap();
    assert_eq!(receive(&mut s, 1), b"?");

    // Once it leaves, the next client is accepted.
    drop(first);
    poll_until(&mut s, |s| s.link.state() == LinkState::Disconnected);
    let _third = client(&s.link);
    poll_until(&mut s, |s| s.link.state() == LinkState::Connected);
    assert_eq!(s.link.connections(), 2);
    assert_eq!(s.link.refused(), 1);
}

/// The refusal is the session rules' decision, and so is the admission of the next client:
/// the rules that refused the second client admit a third once the first has closed, and hear
/// of each admission at the time the link was given.
#[test]
fn the_session_admits_and_refuses() {
    let mut s = served(bind());
    let first = client(&s.link);
    let start = Instant::now();
    while !s.link.admit(&mut s.session, 100).unwrap() {
        assert!(start.elapsed() < TIMEOUT, "timed out");
        std::thread::sleep(Duration::from_millis(1));
    }
    assert_eq!(
        s.session.admitted_ms,
        Some(100),
        "admitted at the link's time"
    );

    let mut second = client(&s.link);
    poll_until(&mut s, |s| s.link.refused() == 1);
    let mut text = String::new();
    second.read_to_string(&mut text).unwrap();
    assert_eq!(text, "error: busy\n");
    assert_eq!(
        s.session.admitted_ms,
        Some(100),
        "the controller is untouched"
    );

    drop(first);
    let _third = client(&s.link);
    let start = Instant::now();
    loop {
        let _ = s.link.poll();
        if s.link.admit(&mut s.session, 5_000).unwrap() {
            break;
        }
        assert!(start.elapsed() < TIMEOUT, "timed out");
        std::thread::sleep(Duration::from_millis(1));
    }
    assert_eq!((s.link.connections(), s.link.refused()), (2, 1));
    assert_eq!(s.session.admitted_ms, Some(5_000), "a new session");
}

#[test]
fn writes_without_a_client_are_discarded() {
    let mut s = served(bind());
    assert!(embedded_io::WriteReady::write_ready(&mut s.link).unwrap());
    assert_eq!(s.link.write(b"nobody hears this\n").unwrap(), 18);
    let mut c = client(&s.link);
    poll_until(&mut s, |s| s.link.state() == LinkState::Connected);
    s.link.write_all(b"ok\n").unwrap();
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

    let mut s = served(FaultInjector::new(bind(), config).unwrap());
    let mut c = client(s.link.inner());
    poll_until(&mut s, |s| s.link.state() == LinkState::Connected);
    c.write_all(&data).unwrap();
    let got = receive(&mut s, expected.len());
    assert_eq!(got, expected);
    let stats = s.link.stats();
    assert_eq!(stats.bytes, data.len() as u64);
    assert!(stats.dropped > 100 && stats.corrupted > 200, "{stats:?}");
}

/// Item 6: a write to a client whose receive window and the link's transmit buffer are full
/// waited for it forever. Now the client is dropped and every write returns at once.
#[test]
fn a_client_that_stops_reading_is_dropped_not_waited_for() {
    let (done, result) = std::sync::mpsc::channel();
    let mut s = served(bind());
    let _client = client(&s.link);
    poll_until(&mut s, |s| s.link.state() == LinkState::Connected);
    std::thread::spawn(move || {
        let reply = [b'x'; 300];
        let mut writes = 0u32;
        while s.link.state() == LinkState::Connected && writes < 1_000_000 {
            assert_eq!(s.link.write(&reply).unwrap(), reply.len());
            writes += 1;
        }
        let _ = done.send((s.link.overflows(), s.link.state(), writes));
    });
    let (overflows, state, writes) = result
        .recv_timeout(Duration::from_secs(30))
        .expect("a write waited for the client");
    assert_eq!((overflows, state), (1, LinkState::Disconnected), "{writes}");
}

/// Item 5: the next client starts with nothing of the previous one: bytes the previous one
/// sent and that were not read are not read after the new one takes control.
#[test]
fn a_new_client_reads_nothing_of_the_previous_one() {
    let mut s = served(bind());
    let mut first = client(&s.link);
    poll_until(&mut s, |s| s.link.state() == LinkState::Connected);
    first.write_all(b"G1 X50\n").unwrap();
    poll_until(&mut s, |s| s.link.read_ready().unwrap_or(false));
    drop(first);
    let mut second = client(&s.link);
    poll_until(&mut s, |s| s.link.connections() == 2);
    assert!(
        !s.link.read_ready().unwrap(),
        "the first client's line is read"
    );
    second.write_all(b"M114\n").unwrap();
    assert_eq!(receive(&mut s, 5), b"M114\n");
}
