//! The operator's web page served by `forja-sim --listen`: the page over HTTP, the link's
//! protocols over its WebSocket, one controlling client across the TCP port and the page,
//! watchers.

mod common;

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Read as _};
use std::net::{SocketAddr, TcpStream};
use std::process::Stdio;
use std::time::Duration;

use forja_sim_hal::link::forja_web;
use forja_sim_hal::link::forja_web::websocket::{CONTROL_NOTICE, Opcode, WATCHING_NOTICE};
use forja_sim_hal::link::web_client::{WsClient, http_request};
use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;

use common::{Running, sim};

const WAIT: Duration = Duration::from_secs(20);

fn text(bytes: &[u8]) -> &str {
    std::str::from_utf8(bytes).unwrap()
}

#[test]
fn the_page_and_its_websocket_are_served_beside_tcp() {
    let mut child = Running(
        sim()
            .args([
                "--listen",
                "--tcp-port",
                "0",
                "--http-port",
                "0",
                "--time-limit",
                "600",
            ])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let mut stdout = BufReader::new(child.0.stdout.take().unwrap());
    let mut fields = HashMap::new();
    while !fields.contains_key("http") {
        let mut line = String::new();
        assert!(stdout.read_line(&mut line).unwrap() > 0, "output ended");
        if let Some((k, v)) = line.trim_end().split_once(": ") {
            fields.insert(k.to_string(), v.to_string());
        }
    }
    let http: SocketAddr = fields["http"].parse().unwrap();
    let tcp: SocketAddr = fields["tcp"].parse().unwrap();
    assert_ne!(http.port(), 0);

    // The page, compressed, and a refusal.
    let page = http_request(http, b"GET / HTTP/1.1\r\nHost: forja\r\n\r\n").unwrap();
    assert_eq!(page.status, 200);
    assert_eq!(page.header("Content-Encoding"), Some("gzip"));
    assert_eq!(page.body, forja_web::asset("/").unwrap().gzip);
    let upload = http_request(
        http,
        b"PUT /job.gcode HTTP/1.1\r\nContent-Length: 3\r\n\r\n\x00\x01\x02",
    );
    assert_eq!(upload.unwrap().status, 405);

    // The controlling page: the notice, frame 54, and a line's `ok`.
    let mut page = WsClient::connect(http).unwrap();
    let greeting = page.text_until("N54Conected", WAIT).unwrap();
    assert!(greeting.starts_with(text(CONTROL_NOTICE)), "{greeting:?}");
    page.send_text("M114\n").unwrap();
    let answer = page.text_until("ok\n", WAIT).unwrap();
    assert!(answer.contains("X:0.000 Y:0.000"), "{answer:?}");

    // A second page watches: the notice, a copy of what the controller is sent, and its own
    // lines refused, never run.
    let mut watcher = WsClient::connect(http).unwrap();
    assert_eq!(
        watcher.text_until("\n", WAIT).unwrap().as_bytes(),
        WATCHING_NOTICE
    );
    watcher.send_text("G0 X50\n").unwrap();
    let refusal = watcher.text_until("E300 link-busy\n", WAIT).unwrap();
    assert!(refusal.contains("// E300 link-busy"), "{refusal:?}");
    page.send_text("M114\n").unwrap();
    let mirrored = watcher.text_until("ok\n", WAIT).unwrap();
    assert!(
        mirrored.contains("X:0.000 Y:0.000"),
        "did not move: {mirrored:?}"
    );
    let own = page.text_until("ok\n", WAIT).unwrap();
    assert!(own.contains("X:0.000 Y:0.000"), "{own:?}");

    // A TCP client is refused while a page is in control: one controller across the ports.
    let mut second = TcpStream::connect(tcp).unwrap();
    second.set_read_timeout(Some(WAIT)).unwrap();
    let mut busy = String::new();
    second.read_to_string(&mut busy).unwrap();
    assert!(busy.contains("E300 link-busy"), "{busy:?}");

    // A malformed frame closes the controlling page with 1002; the watcher takes control.
    page.send_raw(b"\x81\x05G0 X9").unwrap();
    let close = loop {
        let f = page.frame(WAIT).unwrap();
        if f.opcode == 0x8 {
            break f;
        }
    };
    assert_eq!(close.close_code(), Some(1002));
    let taken = watcher.text_until("N54Conected", WAIT).unwrap();
    assert!(taken.contains(text(CONTROL_NOTICE)), "{taken:?}");
    watcher.send_frame(Opcode::Text, b"M114\n").unwrap();
    let answer = watcher.text_until("ok\n", WAIT).unwrap();
    assert!(
        answer.contains("X:0.000 Y:0.000"),
        "the malformed line never ran: {answer:?}"
    );

    kill(Pid::from_raw(child.0.id() as i32), Signal::SIGINT).unwrap();
    assert!(child.0.wait().unwrap().success());
    let mut rest = String::new();
    stdout.read_to_string(&mut rest).unwrap();
    assert!(rest.contains("http: 2 connections, "), "{rest}");
    assert!(rest.contains("1 protocol errors"), "{rest}");
}
