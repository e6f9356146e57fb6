//! The pseudo-terminal link, opened by path as host serial software opens a port.

use std::fs::{File, OpenOptions};
use std::io::{Read as _, Write as _};
use std::os::fd::AsFd;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use embedded_io::{Read, ReadReady, Write};
use forja_hal_abstraction::link::{LinkState, LinkStatus};
use forja_sim_hal::link::{PortLink, PtyLink};
use nix::fcntl::OFlag;
use nix::sys::termios::{SetArg, SpecialCharacterIndices, cfmakeraw, tcgetattr, tcsetattr};

const TIMEOUT: Duration = Duration::from_secs(5);

fn temp_path(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("forja-sim-{}-{name}", std::process::id()))
}

/// Open the terminal like a serial port: no controlling terminal, raw mode, reads that wait
/// at most a second.
fn open_port(path: &Path) -> File {
    let port = OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(OFlag::O_NOCTTY.bits())
        .open(path)
        .unwrap();
    let mut t = tcgetattr(port.as_fd()).unwrap();
    cfmakeraw(&mut t);
    t.control_chars[SpecialCharacterIndices::VMIN as usize] = 0;
    t.control_chars[SpecialCharacterIndices::VTIME as usize] = 10;
    tcsetattr(port.as_fd(), SetArg::TCSANOW, &t).unwrap();
    port
}

fn poll_until(link: &mut PtyLink, mut done: impl FnMut(&mut PtyLink) -> bool) {
    let start = Instant::now();
    loop {
        link.poll().unwrap();
        if done(link) {
            return;
        }
        assert!(start.elapsed() < TIMEOUT, "timed out");
        std::thread::sleep(Duration::from_millis(1));
    }
}

fn receive(link: &mut PtyLink, n: usize) -> Vec<u8> {
    let mut got = Vec::new();
    poll_until(link, |l| {
        let mut buf = [0u8; 64];
        while l.read_ready().unwrap() {
            let k = l.read(&mut buf).unwrap();
            got.extend_from_slice(&buf[..k]);
        }
        got.len() >= n
    });
    got
}

fn read_exactly(port: &mut File, n: usize) -> Vec<u8> {
    let mut got = vec![0u8; n];
    port.read_exact(&mut got).unwrap();
    got
}

#[test]
fn carries_bytes_both_ways_and_tracks_the_peer() {
    let link_path = temp_path("tty");
    let mut link = PtyLink::open(Some(&link_path)).unwrap();
    let slave = link.slave_path().to_path_buf();
    assert!(slave.starts_with("/dev/pts/"), "{}", slave.display());
    assert_eq!(std::fs::read_link(&link_path).unwrap(), slave);

    link.poll().unwrap();
    assert_eq!(
        link.state(),
        LinkState::Disconnected,
        "nobody has the slave open"
    );
    assert_eq!(
        link.write(b"lost\n").unwrap(),
        5,
        "discarded while disconnected"
    );

    let mut port = open_port(&link_path);
    poll_until(&mut link, |l| l.state() == LinkState::Connected);
    assert_eq!(link.connections(), 1);

    // Raw both ways: CR, LF, 0x00, 0x03 (Ctrl-C) and 0xFF arrive unchanged, nothing echoes.
    let host_bytes = b"G1 X1\r\n\x00\x03\xff?";
    port.write_all(host_bytes).unwrap();
    assert_eq!(receive(&mut link, host_bytes.len()), host_bytes);
    let reply = b"ok\n\x18\xfe";
    link.write_all(reply).unwrap();
    link.flush().unwrap();
    assert_eq!(read_exactly(&mut port, reply.len()), reply);

    // The peer's last bytes before closing are kept, then the link is disconnected.
    port.write_all(b"M2\n").unwrap();
    drop(port);
    poll_until(&mut link, |l| l.state() == LinkState::Disconnected);
    assert_eq!(receive(&mut link, 3), b"M2\n");

    // A new peer sees only what is sent to it, and is counted.
    assert_eq!(link.write(b"stale\n").unwrap(), 6);
    let mut port = open_port(&slave);
    poll_until(&mut link, |l| l.state() == LinkState::Connected);
    assert_eq!(link.connections(), 2);
    link.write_all(b"hello\n").unwrap();
    assert_eq!(read_exactly(&mut port, 6), b"hello\n");

    drop(link);
    assert!(
        std::fs::symlink_metadata(&link_path).is_err(),
        "the symbolic link is removed with the link"
    );
    // With the master gone the peer reads end of file or an error, never a byte.
    let mut buf = [0u8; 8];
    assert!(matches!(port.read(&mut buf), Ok(0) | Err(_)));
}

#[test]
fn symlink_replaces_a_symlink_but_not_a_file() {
    let path = temp_path("existing");
    std::fs::write(&path, "keep me").unwrap();
    let e = PtyLink::open(Some(&path)).unwrap_err();
    assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists);
    assert_eq!(std::fs::read_to_string(&path).unwrap(), "keep me");
    std::fs::remove_file(&path).unwrap();

    std::os::unix::fs::symlink("/nonexistent", &path).unwrap();
    let link = PtyLink::open(Some(&path)).unwrap();
    assert_eq!(std::fs::read_link(&path).unwrap(), link.slave_path());
    assert_eq!(link.symlink_path(), Some(path.as_path()));
}

/// Item 6: a peer that holds the terminal open and never reads made writes wait forever. Now
/// what does not fit is discarded whole and counted, and every write returns at once.
#[test]
fn a_peer_that_stops_reading_never_makes_a_write_wait() {
    let mut link = PtyLink::open(None).unwrap();
    let _port = open_port(link.slave_path());
    poll_until(&mut link, |l| l.state() == LinkState::Connected);
    let (done, result) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let reply = [b'x'; 300];
        for _ in 0..2_000 {
            assert_eq!(link.write(&reply).unwrap(), reply.len());
        }
        let _ = done.send(link.tx_discarded());
    });
    let discarded = result
        .recv_timeout(Duration::from_secs(30))
        .expect("a write waited for the peer");
    assert!(discarded > 0, "nothing discarded");
    assert_eq!(discarded % 300, 0, "replies are discarded whole");
}
