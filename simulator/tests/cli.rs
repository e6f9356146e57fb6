//! The `forja-sim` program.

mod common;

use std::io::{BufRead, BufReader, Read as _, Write as _};
use std::net::TcpStream;
use std::path::PathBuf;
use std::process::Stdio;
use std::time::{Duration, Instant};

use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;

use common::{Running, sim};

fn temp_path(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("forja-sim-cli-{}-{name}", std::process::id()))
}

#[test]
fn check_describes_the_default_machine_and_the_sample_job() {
    let out = sim().arg("--check").output().unwrap();
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("machine: Forja reference router"), "{text}");
    assert!(
        text.contains("  X: linear, 80 steps/mm, 0..300 mm"),
        "{text}"
    );
    assert!(text.contains("  Z: linear, 400 steps/mm"), "{text}");
    assert!(text.contains("  A: rotary"), "{text}");
    assert!(
        text.contains("job: sample.gcode (bundled), 336 lines"),
        "{text}"
    );

    let out = sim()
        .args(["--check", "--machine", "builtin:printer"])
        .output()
        .unwrap();
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).contains("heater hotend: 40 W"));
}

#[test]
fn a_bad_machine_file_is_reported_with_its_line_and_field() {
    let path = temp_path("bad.toml");
    let text = forja_sim_hal::MachineConfig::bundled_toml("default")
        .unwrap()
        .replacen("accel_mm_s2 = 500.0", "accel_mm_s2 = 0", 2);
    std::fs::write(&path, &text).unwrap();
    let line = text.lines().position(|l| l == "accel_mm_s2 = 0").unwrap() + 1;
    let out = sim()
        .args(["--check", "--machine"])
        .arg(&path)
        .output()
        .unwrap();
    std::fs::remove_file(&path).unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains(&format!(
            "machine file line {line}: axis X: accel_mm_s2 must be > 0"
        )),
        "{err}"
    );

    let out = sim()
        .args(["--check", "--machine", "builtin:lathe"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no bundled machine \"lathe\""));

    let out = sim().args(["--corrupt-rate", "2"]).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("corrupt rate 2 is not in 0..=1"));
}

#[test]
fn running_the_sample_job_prints_the_result() {
    let out = sim().output().unwrap();
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(out.status.success(), "{text}");
    assert!(text.contains("result: finished"), "{text}");
    assert!(
        text.contains("lines run: 313 of 313 (G28 included); executed 315 (with M110"),
        "{text}"
    );
    assert!(text.contains("refused 0, resends 0"), "{text}");
    assert!(
        text.contains("final position: X 10.000 Y 280.000 Z 25.000 A 0.000"),
        "{text}"
    );
    assert!(text.contains("timing violations: 0"), "{text}");

    // A job with a refused line runs to its end and says so, with exit status 2.
    let path = temp_path("refused.gcode");
    std::fs::write(&path, "G1 X5 F600\nG1 Q5\nG1 X6\n").unwrap();
    let out = sim()
        .args(["--no-home", "--job"])
        .arg(&path)
        .output()
        .unwrap();
    std::fs::remove_file(&path).unwrap();
    assert_eq!(out.status.code(), Some(2));
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("echo:E127 unknown-axis Q"), "{text}");
    assert!(text.contains("final position: X 156.000"), "{text}");
}

#[test]
fn listen_prints_where_and_serves_tcp_and_the_pty() {
    let link = temp_path("tty");
    let mut child = Running(
        sim()
            .args([
                "--listen",
                "--tcp-port",
                "0",
                "--time-limit",
                "60",
                "--drop-rate",
                "0.5",
                "--seed",
                "3",
                "--pty-link",
            ])
            .arg(&link)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let mut stdout = BufReader::new(child.0.stdout.take().unwrap());
    let mut fields = std::collections::HashMap::new();
    while !fields.contains_key("pty-link") {
        let mut line = String::new();
        assert!(
            stdout.read_line(&mut line).unwrap() > 0,
            "output ended early"
        );
        if let Some((k, v)) = line.trim_end().split_once(": ") {
            fields.insert(k.to_string(), v.to_string());
        }
    }
    let tcp: std::net::SocketAddr = fields["tcp"].parse().unwrap();
    assert_ne!(tcp.port(), 0);
    assert!(fields["pty"].starts_with("/dev/pts/"));
    assert_eq!(
        std::fs::read_link(&link).unwrap(),
        PathBuf::from(&fields["pty"])
    );

    // A controlling TCP client, and a second one that is turned away with one line.
    let mut first = TcpStream::connect(tcp).unwrap();
    first.write_all(&[b'x'; 1000]).unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut second = loop {
        // Wait until the first client has been accepted, then connect the second.
        std::thread::sleep(Duration::from_millis(50));
        let mut s = TcpStream::connect(tcp).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut text = String::new();
        if s.read_to_string(&mut text).is_ok() && text.contains("E300 link-busy") {
            break text;
        }
        assert!(Instant::now() < deadline, "no busy message");
    };
    second.truncate(second.trim_end().len());
    assert!(second.ends_with("// E300 link-busy"), "{second}");

    // The pty by its link name.
    let mut port = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&link)
        .unwrap();
    port.write_all(b"M115\n").unwrap();
    std::thread::sleep(Duration::from_millis(200));
    drop(port);
    drop(first);
    std::thread::sleep(Duration::from_millis(200));

    kill(Pid::from_raw(child.0.id() as i32), Signal::SIGINT).unwrap();
    let status = child.0.wait().unwrap();
    assert!(status.success(), "{status:?}");
    let mut rest = String::new();
    stdout.read_to_string(&mut rest).unwrap();
    let mut err = String::new();
    child
        .0
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    assert!(rest.contains("ended (interrupted)"), "{rest}");
    assert!(
        rest.contains("tcp: 1 connections, ") && rest.contains("(1000 from the host, "),
        "{rest}"
    );
    assert!(rest.contains("pty: 1 connections, "), "{rest}");
    assert!(err.contains("tcp: host connected"), "{err}");
    assert!(err.contains("pty: host disconnected"), "{err}");
    assert!(
        std::fs::symlink_metadata(&link).is_err(),
        "link removed on exit"
    );
}
