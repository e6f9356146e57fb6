//! Programs uploaded with frames over TCP (issue 11, item 7): a half-uploaded program never
//! runs, a line of another host's upload is never spliced in, and an interrupted upload stays
//! incomplete across a restart until it is uploaded again from line 1.

use forja_app::job::JobState;
use forja_protocol::frame::{Action, ClientMessage, ControllerMessage};
use forja_sim::board::BoardConfig;
use forja_sim_hal::link::TcpLink;
use forja_tests::{HostEnd, Replies, Rig, TcpHost, frame};

/// No host on the link, while the firmware notices the last one has gone.
struct NoHost;

impl HostEnd for NoHost {
    fn send(&mut self, _: &[u8]) {}
    fn receive(&mut self) -> Vec<u8> {
        Vec::new()
    }
}

/// A TCP port on `rig`, and a host connected to it.
fn serve(rig: &mut Rig) -> (std::net::SocketAddr, TcpHost, Replies) {
    let tcp = TcpLink::bind("127.0.0.1:0".parse().unwrap(), b"busy\n".to_vec()).unwrap();
    let addr = tcp.local_addr().unwrap();
    rig.board.add_port(tcp, true);
    let mut replies = Replies::default();
    let mut host = TcpHost::connect(addr);
    rig.exchange(&mut host, &mut replies, 50);
    (addr, host, replies)
}

fn send(rig: &mut Rig, host: &mut TcpHost, replies: &mut Replies, msg: &ClientMessage<'_>) {
    host.send(&frame(msg));
    rig.exchange(host, replies, 20);
}

/// Program `tag`: ten absolute moves.
fn program(tag: u32) -> Vec<String> {
    (1..=10).map(|k| format!("G1 X{k}.{tag} F3000")).collect()
}

/// The `NL` and `LA` of a fresh 52.
fn progress(rig: &mut Rig, host: &mut TcpHost, replies: &mut Replies) -> (u32, u32) {
    replies.clear();
    send(
        rig,
        host,
        replies,
        &ClientMessage::Request { message_type: 52 },
    );
    replies
        .frames()
        .iter()
        .find_map(|m| match m {
            ControllerMessage::Progress(p) => Some((p.total_lines, p.current_line)),
            _ => None,
        })
        .expect("a 52 frame")
}

fn load(
    rig: &mut Rig,
    host: &mut TcpHost,
    replies: &mut Replies,
    lines: &[String],
    range: std::ops::RangeInclusive<usize>,
) {
    for k in range {
        let msg = ClientMessage::LoadLine {
            index: k as u16,
            text: &lines[k - 1],
            total: lines.len() as u16,
        };
        host.send(&frame(&msg));
    }
    rig.exchange(host, replies, 50);
}

#[test]
fn a_half_uploaded_program_never_runs_and_takes_no_other_hosts_lines() {
    let mut rig = Rig::new("default", BoardConfig::default());
    let (addr, mut host, mut replies) = serve(&mut rig);
    let a = program(1);
    load(&mut rig, &mut host, &mut replies, &a, 1..=4);
    assert!(replies.error_codes().is_empty(), "{:?}", replies.lines);
    assert_eq!(progress(&mut rig, &mut host, &mut replies), (4, 0));
    replies.clear();
    send(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::Start),
    );
    rig.exchange(&mut host, &mut replies, 500);
    assert_eq!(replies.error_codes(), [185], "{:?}", replies.lines);
    let status = rig.board.status();
    assert_eq!(
        (status.controller.job, status.controller.stats.program_lines),
        (JobState::Idle, 0)
    );

    // The host goes; another one sends lines 5–10 of its own program of ten lines.
    drop(host);
    rig.exchange(&mut NoHost, &mut replies, 50);
    let mut host = TcpHost::connect(addr);
    let mut replies = Replies::default();
    rig.exchange(&mut host, &mut replies, 50);
    replies.clear();
    let b = program(2);
    load(&mut rig, &mut host, &mut replies, &b, 5..=10);
    // Line 5 would continue the program, but no upload is open for it; the rest are out of
    // order.
    assert_eq!(
        replies.error_codes(),
        [175, 170, 170, 170, 170, 170],
        "{:?}",
        replies.lines
    );
    assert_eq!(progress(&mut rig, &mut host, &mut replies), (4, 0));

    // A restart: the program is still the incomplete one, and still does not run.
    let machine = rig.machine.clone();
    let flash = rig.board.into_flash();
    drop(host);
    let mut rig = Rig::on(
        machine,
        BoardConfig {
            flash,
            ..BoardConfig::default()
        },
    );
    assert_eq!(rig.board.status().controller.program_lines, 4);
    let (_, mut host, mut replies) = serve(&mut rig);
    assert_eq!(progress(&mut rig, &mut host, &mut replies), (4, 0));
    replies.clear();
    send(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::Start),
    );
    load(&mut rig, &mut host, &mut replies, &a, 5..=5);
    assert_eq!(replies.error_codes(), [185, 175], "{:?}", replies.lines);

    // Uploaded again from line 1, the whole program runs, each line once.
    replies.clear();
    load(&mut rig, &mut host, &mut replies, &b, 1..=10);
    assert!(replies.error_codes().is_empty(), "{:?}", replies.lines);
    assert!(
        replies
            .frames()
            .contains(&ControllerMessage::Confirm { what: "Gcode-load" })
    );
    assert_eq!(progress(&mut rig, &mut host, &mut replies), (10, 1));
    send(
        &mut rig,
        &mut host,
        &mut replies,
        &ClientMessage::Action(Action::Start),
    );
    rig.settle(&mut host, &mut replies);
    let status = rig.board.status();
    assert_eq!(
        (status.controller.job, status.controller.stats.program_lines),
        (JobState::Finished, 10)
    );
}
