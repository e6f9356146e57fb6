//! `forja-sim --listen` never waits for a host: a client that floods and stops reading is
//! dropped, motion goes on, and SIGTERM ends the program promptly.

mod common;

use std::io::{BufRead, BufReader, ErrorKind, Read as _, Write as _};
use std::net::{SocketAddr, TcpStream};
use std::process::Stdio;
use std::time::{Duration, Instant};

use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;

use common::{Running, sim};

/// Item 6: a client that stops reading blocked the simulator's thread in a write: virtual
/// time stopped and SIGTERM was ignored.
#[test]
fn a_client_that_floods_and_never_reads_cannot_freeze_the_simulator() {
    let mut child = Running(
        sim()
            .args(["--listen", "--tcp-port", "0", "--time-limit", "600"])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let mut stdout = BufReader::new(child.0.stdout.take().unwrap());
    let tcp: SocketAddr = loop {
        let mut line = String::new();
        assert!(
            stdout.read_line(&mut line).unwrap() > 0,
            "output ended early"
        );
        if let Some(addr) = line.trim_end().strip_prefix("tcp: ") {
            break addr.parse().unwrap();
        }
    };

    // Requests whose answers are long (M115), sent as fast as the socket takes them, never a
    // byte read back.
    let mut client = TcpStream::connect(tcp).unwrap();
    client.set_nonblocking(true).unwrap();
    let flood = b"M115\n".repeat(4096);
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut sent = 0usize;
    let dropped = loop {
        match client.write(&flood) {
            Ok(n) => sent += n,
            Err(e) if e.kind() == ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            // Reset or broken pipe: the simulator dropped the client.
            Err(_) => break true,
        }
        if Instant::now() > deadline {
            break false;
        }
    };
    assert!(dropped, "the client was never dropped ({sent} bytes sent)");

    // The simulator still answers, and a signal ends it at once.
    let mut next = TcpStream::connect(tcp).unwrap();
    next.set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut greeting = [0u8; 3];
    next.read_exact(&mut greeting).unwrap();
    assert_eq!(&greeting, b"N54");

    kill(Pid::from_raw(child.0.id() as i32), Signal::SIGTERM).unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let status = loop {
        if let Some(status) = child.0.try_wait().unwrap() {
            break status;
        }
        assert!(
            Instant::now() < deadline,
            "SIGTERM did not end the simulator"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(status.success(), "{status:?}");
    let mut rest = String::new();
    stdout.read_to_string(&mut rest).unwrap();
    assert!(rest.contains("ended (interrupted)"), "{rest}");
    assert!(rest.contains("1 dropped for not reading"), "{rest}");
}
