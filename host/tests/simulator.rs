//! Every `forja` subcommand against the simulator (`forja-sim --listen`), over TCP and over
//! its pseudo-terminal.

mod common;

use std::time::Duration;

use common::{
    Sim, axis, forja, forja_with_input, positions, scratch, settle, sim_binary, text, with,
};

/// A job of `n` relative moves of different lengths, and how far it moves X and Y: a move run
/// twice or not at all moves the end by at least 0.05 mm, four steps of the default machine.
fn relative_job(n: usize) -> (String, f64, f64) {
    let mut job = String::from("; a test job\nG21 G91 ; relative\nG1 F6000\n");
    let (mut dx, mut dy) = (0.0, 0.0);
    for i in 0..n {
        let x = ((i % 7) as f64 + 1.0) * 0.05 * if i % 2 == 0 { 1.0 } else { -1.0 };
        let y = ((i % 5) as f64 + 1.0) * 0.05 * if i % 3 == 0 { -1.0 } else { 1.0 };
        job.push_str(&format!("G1 X{x:.2} Y{y:.2} ; move {i}\n"));
        dx += x;
        dy += y;
    }
    job.push_str("G90\n");
    (job, dx, dy)
}

fn assert_near(got: f64, want: f64, what: &str) {
    assert!(
        (got - want).abs() < 0.002,
        "{what}: {got} instead of {want}"
    );
}

fn send_and_check(sim: &Sim, link: &[String], name: &str, n: usize) {
    let dir = scratch(name);
    let (job, dx, dy) = relative_job(n);
    let file = dir.join("job.gcode");
    std::fs::write(&file, job).unwrap();
    let before = positions(link);
    let (x, y) = (axis(&before, 'X') + dx, axis(&before, 'Y') + dy);
    let out = forja(&with(link, &["send", file.to_str().unwrap()]));
    assert!(out.status.success(), "{}", text(&out));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains(&format!("{} lines in", n + 3)),
        "{}",
        text(&out)
    );
    let at = settle(link, Duration::from_secs(30));
    assert_near(axis(&at, 'X'), x, "X");
    assert_near(axis(&at, 'Y'), y, "Y");
    let _ = sim;
}

#[test]
fn send_over_tcp_runs_every_move_once() {
    let dir = scratch("send-tcp");
    let sim = Sim::start(&dir, &[]);
    send_and_check(&sim, &sim.tcp_args(), "send-tcp-job", 120);
}

#[test]
fn send_over_the_pseudo_terminal_runs_every_move_once() {
    let dir = scratch("send-pty");
    let sim = Sim::start(&dir, &[]);
    send_and_check(&sim, &sim.pty_args(), "send-pty-job", 120);
}

#[test]
fn send_through_a_damaging_link_runs_every_move_once() {
    let dir = scratch("send-faults");
    let sim = Sim::start(&dir, &["--corrupt-rate", "0.003", "--seed", "11"]);
    send_and_check(&sim, &sim.pty_args(), "send-faults-job", 200);
    let dir = scratch("send-faults-tcp");
    let sim = Sim::start(&dir, &["--corrupt-rate", "0.003", "--seed", "12"]);
    send_and_check(&sim, &sim.tcp_args(), "send-faults-tcp-job", 200);
}

/// Which link of the simulator a test uses.
#[derive(Clone, Copy, Debug)]
enum Via {
    Tcp,
    Pty,
}

fn link_of(sim: &Sim, via: Via) -> Vec<String> {
    match via {
        Via::Tcp => sim.tcp_args(),
        Via::Pty => sim.pty_args(),
    }
}

#[test]
fn upload_then_run_pause_stop_rewind_over_tcp() {
    upload_then_run_pause_stop_rewind(Via::Tcp);
}

#[test]
fn upload_then_run_pause_stop_rewind_over_the_pseudo_terminal() {
    upload_then_run_pause_stop_rewind(Via::Pty);
}

fn upload_then_run_pause_stop_rewind(via: Via) {
    let dir = scratch(&format!("upload-{via:?}"));
    let sim = Sim::start(&dir, &[]);
    let link = link_of(&sim, via);
    // Long lines are shortened to fit a 03 frame.
    let (job, dx, dy) = relative_job(40);
    let before = positions(&link);
    let (x, y) = (axis(&before, 'X') + dx, axis(&before, 'Y') + dy);
    let job = job.replacen(
        "G91 ; relative\n",
        "G91 ; relative\nG1 X0.00000 Y0.00000 Z0.00000 A0.00000 F6000.000 ; long\n",
        1,
    );
    let file = dir.join("job.gcode");
    std::fs::write(&file, &job).unwrap();
    let out = forja(&with(&link, &["upload", file.to_str().unwrap()]));
    assert!(out.status.success(), "{}", text(&out));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("44 lines stored"), "{}", text(&out));
    assert!(stdout.contains("1 shortened"), "{}", text(&out));
    assert!(stdout.contains("confirmed"), "{}", text(&out));

    let out = forja(&with(&link, &["run"]));
    assert!(out.status.success(), "{}", text(&out));
    let at = settle(&link, Duration::from_secs(30));
    assert_near(axis(&at, 'X'), x, "X");
    assert_near(axis(&at, 'Y'), y, "Y");
    let out = forja(&with(&link, &["status", "--once"]));
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("/44"),
        "{}",
        text(&out)
    );

    for (command, said) in [
        ("rewind", "line 1"),
        ("pause", ""),
        ("stop", "stopped"),
        ("reset", "reset"),
    ] {
        let out = forja(&with(&link, &[command]));
        let all = text(&out);
        if command == "pause" {
            // Nothing is running: the controller says so, in words.
            assert!(!out.status.success(), "{all}");
            assert!(all.contains("no job is running"), "{all}");
        } else {
            assert!(out.status.success(), "{all}");
            assert!(all.contains(said), "{all}");
        }
    }
}

#[test]
fn upload_refuses_a_line_that_cannot_fit_with_its_number() {
    let dir = scratch("upload-long");
    let file = dir.join("job.gcode");
    std::fs::write(
        &file,
        "G21\nG1 X123.4567 Y123.4567 Z12.3456 A123.4567 F1234.5\n",
    )
    .unwrap();
    let out = forja(&["--tcp", "127.0.0.1:9", "upload", file.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("line 2: the line does not fit"), "{err}");
}

#[test]
fn jog_home_and_status_over_tcp() {
    jog_home_and_status(Via::Tcp);
}

#[test]
fn jog_home_and_status_over_the_pseudo_terminal() {
    jog_home_and_status(Via::Pty);
}

fn jog_home_and_status(via: Via) {
    let dir = scratch(&format!("jog-{via:?}"));
    let sim = Sim::start(&dir, &[]);
    let link = link_of(&sim, via);
    let before = positions(&link);
    let out = forja(&with(&link, &["jog", "X+0.1", "Y-2"]));
    assert!(out.status.success(), "{}", text(&out));
    let at = settle(&link, Duration::from_secs(20));
    assert_near(axis(&at, 'X'), axis(&before, 'X') + 0.1, "X");
    assert_near(axis(&at, 'Y'), axis(&before, 'Y') - 2.0, "Y");
    let out = forja(&with(&link, &["home", "x"]));
    assert!(out.status.success(), "{}", text(&out));
    let homed = settle(&link, Duration::from_secs(60));
    assert_near(axis(&homed, 'Y'), axis(&at, 'Y'), "Y stays");
    let out = forja(&with(&link, &["home", "Q"]));
    assert!(!out.status.success(), "{}", text(&out));
    let out = forja(&with(
        &link,
        &["status", "--count", "2", "--interval", "50"],
    ));
    assert!(out.status.success(), "{}", text(&out));
    assert_eq!(String::from_utf8_lossy(&out.stdout).lines().count(), 2);
}

#[test]
fn console_sends_lines_and_shows_replies() {
    let dir = scratch("console");
    let sim = Sim::start(&dir, &[]);
    for link in [sim.tcp_args(), sim.pty_args()] {
        let out = forja_with_input(
            &with(&link, &["console"]),
            "G21\nG91\nG1 X1 F3000\nG90\nM114\nG1 X#\n",
        );
        assert!(out.status.success(), "{}", text(&out));
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(stdout.contains(" Count X:"), "{}", text(&out));
        assert!(stdout.contains("not sent:"), "{}", text(&out));
        assert!(!stdout.contains("rs "), "{}", text(&out));
    }
}

#[test]
fn an_alarm_stops_the_job_with_a_message() {
    let dir = scratch("alarm");
    let sim = Sim::start(&dir, &[]);
    let file = dir.join("job.gcode");
    std::fs::write(&file, "G21 G91\nG1 X1 F6000\nM112\nG1 X2\nG1 X3\n").unwrap();
    let out = forja(&with(&sim.tcp_args(), &["send", file.to_str().unwrap()]));
    let all = text(&out);
    assert_eq!(out.status.code(), Some(1), "{all}");
    assert!(all.contains("went into alarm"), "{all}");
    assert!(all.contains("emergency stop (M112)"), "{all}");
    // A locked machine refuses the next job's first move, and says what to do.
    let out = forja(&with(&sim.tcp_args(), &["send", file.to_str().unwrap()]));
    let all = text(&out);
    assert_eq!(out.status.code(), Some(1), "{all}");
    assert!(all.contains("reset it (forja reset)"), "{all}");
    let out = forja(&with(&sim.tcp_args(), &["jog", "X+1"]));
    assert!(text(&out).contains("in alarm"), "{}", text(&out));
    let out = forja(&with(&sim.tcp_args(), &["reset"]));
    assert!(out.status.success(), "{}", text(&out));
    let out = forja(&with(&sim.tcp_args(), &["jog", "X+1"]));
    assert!(out.status.success(), "{}", text(&out));
}

#[test]
fn plot_overlays_the_step_trace() {
    let dir = scratch("plot");
    let trace = dir.join("trace.csv");
    let sim = Sim::start(&dir, &["--trace", trace.to_str().unwrap()]);
    let file = dir.join("job.gcode");
    std::fs::write(
        &file,
        "G21 G90\nG0 X10 Y10\nG1 X30 F6000\nG2 X40 Y20 I0 J10\nG1 Y30\nG0 X0 Y0\n",
    )
    .unwrap();
    let out = forja(&with(&sim.tcp_args(), &["send", file.to_str().unwrap()]));
    assert!(out.status.success(), "{}", text(&out));
    settle(&sim.tcp_args(), Duration::from_secs(30));
    sim.stop();
    let machine = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../boards/sim-hal/machines/default.toml"
    );
    // The plot is the simulator's: the toolpath as its kernel reads the job, the steps of the
    // run under `forja send` over it.
    for ext in ["png", "svg"] {
        let image = dir.join(format!("plot.{ext}"));
        let out = std::process::Command::new(sim_binary())
            .args([
                "--machine",
                machine,
                "--job",
                file.to_str().unwrap(),
                "--check",
            ])
            .args(["--plot", image.to_str().unwrap()])
            .args(["--plot-trace", trace.to_str().unwrap()])
            .output()
            .expect("forja-sim runs");
        assert!(out.status.success(), "{}", text(&out));
        let stdout = String::from_utf8_lossy(&out.stdout);
        let off: f64 = stdout
            .split("; ends ")
            .nth(1)
            .and_then(|s| s.split(' ').next())
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("{stdout}"));
        assert!(
            off < 0.02,
            "the machine ended {off} mm from the program's end"
        );
        assert!(std::fs::metadata(&image).unwrap().len() > 1000);
    }
}

#[test]
fn missing_port_and_refused_connection_read_well() {
    let out = forja(&["--port", "/dev/ttyFORJA-missing", "status"]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.starts_with("forja: there is no serial port /dev/ttyFORJA-missing"),
        "{err}"
    );
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    drop(listener);
    let out = forja(&["--tcp", &addr, "run"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("refused the connection"), "{err}");
    let out = forja(&["status"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("say where the controller is"), "{err}");
}
