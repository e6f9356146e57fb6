//! Marlin's SD-card commands on the test board's card (a RAM file store): uploads with
//! `M28`/`M29` that are stored and never run, the file list, printing with `M23`/`M24`,
//! `M25`/`M26`/`M27`, the frame actions on a selected file, deletion, and a board without a
//! card.

use super::*;
use forja_hal_abstraction::files::FileName;
use forja_protocol::gcode::{Check, write_checked};
use std::vec;

impl Bench {
    /// The board's card.
    fn card(&mut self) -> &mut FakeCard {
        self.ctl.peripherals_mut().card.as_mut().expect("a card")
    }

    /// The whole of file `name`, as text.
    fn file_text(&mut self, name: &str) -> String {
        let name = FileName::new(name.as_bytes()).unwrap();
        let card = self.card();
        let size = card.size(&name).unwrap() as usize;
        let mut buf = vec![0; size];
        assert_eq!(card.read(&name, 0, &mut buf), Ok(size));
        String::from_utf8(buf).unwrap()
    }

    /// Send every line, run until each is answered, and return the answers.
    fn ask_all(&mut self, lines: &[&str]) -> Vec<String> {
        for l in lines {
            self.send(l);
        }
        self.run_ms(20);
        self.take()
    }

    /// Upload `lines` to file `name` as a host does: `M28`, the lines, `M29`.
    fn upload(&mut self, name: &str, lines: &[String]) -> Vec<String> {
        self.send(&format!("M28 {name}"));
        for l in lines {
            self.send(l);
        }
        self.send("M29");
        self.run_ms(20);
        self.take()
    }

    /// The `SD printing byte` answer of `M27`, as (byte, size); `None` for `Not SD printing`.
    fn sd_position(&mut self) -> Option<(u32, u32)> {
        let out = self.ask("M27");
        assert_eq!(out.len(), 2, "{out:?}");
        assert_eq!(out[1], "ok");
        if out[0] == "Not SD printing" {
            return None;
        }
        let rest = out[0]
            .strip_prefix("SD printing byte ")
            .expect("M27 answer");
        let (byte, size) = rest.split_once('/').unwrap();
        Some((byte.parse().unwrap(), size.parse().unwrap()))
    }
}

/// `n` relative moves along X of different lengths, their sum `total_mm`.
fn moves(n: usize) -> (Vec<String>, f64) {
    let mut lines = vec!["G91".to_string(), "G1 F6000".to_string()];
    let mut total = 0.0;
    for i in 0..n {
        let mm = 0.05 * ((i % 5) as f64 + 1.0);
        total += mm;
        lines.push(format!("G1 X{mm:.2}"));
    }
    lines.push("G90".to_string());
    (lines, total)
}

/// `n` absolute moves along X, back and forth, ending at `end_mm`.
fn absolute_moves(n: usize) -> (Vec<String>, f64) {
    let mut lines = vec!["G90".to_string(), "G1 F6000".to_string()];
    let mut x = 0.0;
    for i in 0..n {
        x = 0.1 * (i % 50) as f64 + 0.05 * (i / 50 % 4) as f64;
        lines.push(format!("G1 X{x:.2}"));
    }
    (lines, (x * 100.0).round() / 100.0)
}

#[test]
fn m115_announces_the_card_only_on_a_board_with_one() {
    let mut b = Bench::new();
    b.take();
    let out = b.ask("M115");
    for cap in [
        "Cap:SDCARD:1",
        "Cap:AUTOREPORT_SD_STATUS:1",
        "Cap:LFN_WRITE:1",
    ] {
        assert!(out.contains(&cap.to_string()), "{out:?}");
    }
    b.ctl.peripherals_mut().card = None;
    let out = b.ask("M115");
    assert!(!out.iter().any(|l| l.contains("SDCARD")), "{out:?}");
}

#[test]
fn an_upload_is_stored_never_run_and_listed() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M21"), ["echo:SD card ok", "ok"]);
    let lines: Vec<String> = [
        "G1 X10 F3000",
        "; a comment",
        "g1  y2.50 (inline) ; and after",
        "",
        "M104 S200",
        "M117 Hello there",
    ]
    .iter()
    .map(|l| l.to_string())
    .collect();
    let out = b.upload("/CUBE~1.GCO", &lines);
    // `M28`'s answer, one `ok` per line (the empty record is no line), `M29`'s.
    let mut expected = vec!["Writing to file: CUBE~1.GCO", "ok"];
    expected.extend(["ok"; 5]);
    expected.extend(["Done saving file.", "ok"]);
    assert_eq!(out, expected);
    b.run_ms(200);
    assert_eq!(b.wiring.positions(), [0; 3], "nothing moved");
    assert_eq!(b.ctl.peripherals().hot.target_mc, 0, "nothing ran");
    assert_eq!(b.ctl.message(), "");
    // Stored in canonical form, comments dropped.
    assert_eq!(
        b.file_text("cube~1.gco"),
        "G1 X10 F3000\nG1 Y2.50\nM104 S200\nM117 Hello there\n"
    );
    assert_eq!(
        b.ask("M20"),
        ["Begin file list", "CUBE~1.GCO 49", "End file list", "ok"]
    );
}

#[test]
fn numbered_lines_are_checked_then_stored_without_number_and_checksum() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(
        b.ask(&numbered(1, "M28 job.gco")),
        ["Writing to file: job.gco", "ok"]
    );
    assert_eq!(b.ask(&numbered(2, "G1 X5")), ["ok"]);
    // A damaged line is asked again, and stored once, as resent.
    let good = numbered(3, "G1 X6");
    let damaged = good.replace("X6", "X7");
    assert_eq!(b.ask(&damaged), ["rs 3", "ok"]);
    assert_eq!(b.ask(&good), ["ok"]);
    // With the strong check too (the link requires it from then on).
    let strong = |n: u32, body: &str| {
        let mut buf = [0u8; 64];
        let len = write_checked(n, body.as_bytes(), Check::Crc16, &mut buf).unwrap();
        String::from_utf8(buf[..len].to_vec()).unwrap()
    };
    assert_eq!(b.ask(&strong(4, "G4")), ["ok"]);
    assert_eq!(b.ask(&strong(5, "M29")), ["Done saving file.", "ok"]);
    assert_eq!(b.file_text("JOB.GCO"), "G1 X5\nG1 X6\nG4\n");
    assert_eq!(b.wiring.positions(), [0; 3]);
}

#[test]
fn a_file_prints_every_move_once_and_says_when_done() {
    let mut b = Bench::new();
    b.take();
    let (lines, total) = moves(300);
    let out = b.upload("moves.gco", &lines);
    assert_eq!(out.last().map(String::as_str), Some("ok"));
    assert!(out.contains(&"Done saving file.".to_string()), "{out:?}");
    let size = b.file_text("moves.gco").len();
    assert_eq!(
        b.ask("M23 /MOVES.GCO"),
        [
            format!("File opened: MOVES.GCO Size: {size}").as_str(),
            "File selected",
            "ok"
        ]
    );
    assert_eq!(b.sd_position(), Some((0, size as u32)));
    assert_eq!(b.ask("M24"), ["ok"]);
    b.run_ms(50);
    let (byte, of) = b.sd_position().expect("printing");
    assert!(byte > 0 && byte < of, "{byte}/{of}");
    // Frame 52 counts the file's lines.
    b.send_frame(&ClientMessage::Request { message_type: 52 });
    b.run_ms(2);
    let out = b.take();
    let Some(ControllerMessage::Progress(p)) = frames_of(&out).first().cloned() else {
        panic!("{out:?}")
    };
    assert_eq!(p.total_lines, lines.len() as u32);
    assert!(
        p.current_line > 1 && p.current_line < p.total_lines,
        "{p:?}"
    );
    b.run_until(60_000, |b| b.out.contains("Done printing file"));
    b.idle();
    let out = b.take();
    assert_eq!(out.iter().filter(|l| *l == "Done printing file").count(), 1);
    assert!(
        (b.position_mm()[0] - total).abs() < 1e-6,
        "{:?}",
        b.position_mm()
    );
    assert_eq!(b.wiring.positions()[0], (total * 80.0).round() as i32);
    assert_eq!(b.ctl.job().state(), JobState::Finished);
    assert_eq!(b.sd_position(), None);
    b.run_ms(100);
    assert!(b.take().is_empty(), "said once");
    assert_eq!(b.violations(), 0);
}

#[test]
fn m25_pauses_the_reading_and_host_commands_run_until_m24() {
    let mut b = Bench::new();
    b.take();
    let (lines, total) = absolute_moves(200);
    b.upload("p.g", &lines);
    assert_eq!(
        b.ask_all(&["M23 p.g", "M24"]).last().map(String::as_str),
        Some("ok")
    );
    b.run_ms(100);
    assert_eq!(b.ask("M25"), ["ok"]);
    let (paused_at, size) = b.sd_position().expect("still printing");
    b.idle();
    assert!(b.position_mm()[0] > 0.0);
    b.run_ms(500);
    assert_eq!(b.sd_position(), Some((paused_at, size)), "no line read");
    // The host's own commands run meanwhile (a park and back).
    assert_eq!(
        b.ask_all(&["G91", "G1 Z2 F600", "G1 Z-2", "G90"]),
        ["ok"; 4]
    );
    b.idle();
    assert_eq!(b.ask("M24"), ["ok"]);
    b.run_until(60_000, |b| b.out.contains("Done printing file"));
    b.idle();
    assert!(
        (b.position_mm()[0] - total).abs() < 1e-6,
        "{:?} {total}",
        b.position_mm()
    );
    assert_eq!(b.position_mm()[2], 0.0);
}

#[test]
fn m26_sets_the_byte_to_go_on_from() {
    let mut b = Bench::new();
    b.take();
    let lines: Vec<String> = (1..=4).map(|k| format!("G1 X{k} F3000")).collect();
    b.upload("j.g", &lines);
    b.ask("M23 j.g");
    // From the third line (two lines of 12 bytes before it).
    assert_eq!(b.ask("M26 S24"), ["ok"]);
    assert_eq!(b.sd_position(), Some((24, 48)));
    b.send_frame(&ClientMessage::Request { message_type: 52 });
    b.run_ms(2);
    let out = b.take();
    assert!(
        matches!(frames_of(&out).first(), Some(ControllerMessage::Progress(p)) if p.current_line == 3 && p.total_lines == 4),
        "{out:?}"
    );
    assert_eq!(b.ask("M24"), ["ok"]);
    b.run_until(10_000, |b| b.out.contains("Done printing file"));
    b.idle();
    b.take();
    assert_eq!(b.position_mm()[0], 4.0);
    assert_eq!(b.ctl.stats().program_lines, 2);
    // Cancelled as OctoPrint cancels: pause, report, back to the start.
    assert_eq!(b.ask_all(&["M24"]), ["ok"]);
    assert_eq!(b.ask_all(&["M25", "M27", "M26 S0"]).len(), 4);
    assert_eq!(b.ask("M26"), ["echo:E122 missing-value S", "ok"]);
}

#[test]
fn a_refused_m28_lets_nothing_after_it_run() {
    let mut b = Bench::new();
    b.take();
    let out = b.ask_all(&[
        "M28 bad name.g",
        "G1 X20 F3000",
        "M104 S200",
        "M28 other.g",
        "M29",
    ]);
    assert_eq!(
        out,
        [
            "echo:E178 bad-file-name bad name.g",
            "open failed, File: bad name.g.",
            "ok",
            "echo:E178 bad-file-name bad name.g",
            "ok",
            "echo:E178 bad-file-name bad name.g",
            "ok",
            "echo:E178 bad-file-name bad name.g",
            "ok",
            "ok",
        ]
    );
    b.run_ms(200);
    assert_eq!(b.wiring.positions(), [0; 3]);
    assert_eq!(b.ctl.peripherals().hot.target_mc, 0);
    assert_eq!(b.ask("M20"), ["Begin file list", "End file list", "ok"]);
    // After `M29` lines run again.
    assert_eq!(b.ask("G1 X1 F3000"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 1.0);
}

#[test]
fn a_line_that_does_not_fit_abandons_the_file() {
    let mut b = Bench::new();
    b.take();
    let long: Vec<String> = (0..2000).map(|k| format!("G1 X{}.5 Y1", k % 100)).collect();
    let out = b.upload("big.g", &long);
    assert!(
        out.contains(&"echo:E177 files-full big.g".to_string()),
        "{out:?}"
    );
    assert!(!out.contains(&"Done saving file.".to_string()));
    assert_eq!(
        out.iter().filter(|l| l.starts_with("ok")).count(),
        long.len() + 2
    );
    assert_eq!(b.ask("M20"), ["Begin file list", "End file list", "ok"]);
    assert_eq!(b.card().writing(), None);
    assert_eq!(b.wiring.positions(), [0; 3]);
}

#[test]
fn realtime_commands_act_during_an_upload_and_are_not_stored() {
    let mut b = Bench::new();
    b.take();
    let out = b.ask_all(&[
        "M28 r.g", "G1 X1", "M410", "M108", "M110 N7", "G1 X2", "M29",
    ]);
    assert_eq!(
        out,
        [
            "Writing to file: r.g",
            "ok",
            "ok",
            "ok",
            "ok",
            "ok",
            "ok",
            "Done saving file.",
            "ok"
        ]
    );
    assert_eq!(b.file_text("r.g"), "G1 X1\nG1 X2\n");
    b.send("M28 s.g");
    b.send("M112");
    b.run_ms(10);
    let out = b.take();
    assert_eq!(out[..2], ["Writing to file: s.g", "ok"]);
    assert!(
        out.contains(&"Error:E153 emergency-stop".to_string()),
        "{out:?}"
    );
    assert_eq!(
        b.ask_all(&["G1 X3", "M29"]),
        ["ok", "Done saving file.", "ok"]
    );
    assert_eq!(b.file_text("s.g"), "G1 X3\n");
}

#[test]
fn a_host_that_leaves_abandons_its_upload() {
    let mut b = Bench::new();
    b.take();
    b.ask_all(&["M28 gone.g", "G1 X1"]);
    b.ctl.reset_link();
    assert_eq!(b.card().writing(), None);
    assert_eq!(b.ask("M20"), ["Begin file list", "End file list", "ok"]);
    // The new host's lines run.
    assert_eq!(b.ask("G1 X1 F3000"), ["ok"]);
}

#[test]
fn frame_actions_and_progress_act_on_the_selected_file() {
    let mut b = Bench::new();
    b.take();
    let (lines, end) = absolute_moves(400);
    b.upload("f.g", &lines);
    b.ask("M23 f.g");
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(150);
    b.send_frame(&ClientMessage::Action(Action::Stop));
    b.run_ms(5);
    b.idle();
    assert_eq!(b.ctl.job().state(), JobState::Idle);
    assert_eq!(b.sd_position(), None, "a stop ends the print");
    let (stopped_at, _) = {
        b.send_frame(&ClientMessage::Request { message_type: 52 });
        b.run_ms(2);
        let out = b.take();
        match frames_of(&out).first() {
            Some(ControllerMessage::Progress(p)) => (p.current_line, p.total_lines),
            _ => panic!("{out:?}"),
        }
    };
    assert!(
        stopped_at > 2 && stopped_at < lines.len() as u32,
        "{stopped_at}"
    );
    // Start goes on from the line that was moving.
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(5);
    let p = b.ctl.progress();
    assert!(u32::from(p.current_line) >= stopped_at, "{p:?}");
    b.run_until(60_000, |b| b.out.contains("Done printing file"));
    b.idle();
    assert!(
        (b.position_mm()[0] - end).abs() < 1e-6,
        "{} {end} {:?}",
        b.position_mm()[0],
        b.ctl.job().state()
    );
    b.take();
    // Rewind, and a program uploaded with frames is what Start runs from then on.
    b.send_frame(&ClientMessage::Action(Action::Rewind));
    b.run_ms(2);
    assert_eq!(b.ctl.job().next_line(), 1);
    b.send_frame(&ClientMessage::LoadLine {
        index: 1,
        text: "G1 Y3 F3000",
        total: 1,
    });
    b.run_ms(2);
    b.take();
    assert!(b.ctl.job().file().is_none());
    assert_eq!(b.sd_position(), None);
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(5);
    b.idle();
    assert_eq!(b.position_mm()[1], 3.0);
}

#[test]
fn blank_lines_comments_and_long_comments_are_skipped() {
    let mut b = Bench::new();
    b.take();
    let text = format!(
        "G1 X1 F3000\r\n\n; {}\n   \nG1 X2 ;{}\n(only a comment)\nG1 X3",
        "c".repeat(900),
        "d".repeat(400)
    );
    let name = FileName::new(b"c.g").unwrap();
    let card = b.card();
    card.create(&name).unwrap();
    card.append(text.as_bytes()).unwrap();
    card.finish().unwrap();
    assert_eq!(b.ask_all(&["M23 c.g", "M24"]).len(), 4);
    b.run_until(10_000, |b| b.out.contains("Done printing file"));
    b.idle();
    assert_eq!(b.position_mm()[0], 3.0);
    assert!(error_codes(&b.take()).is_empty());
}

#[test]
fn a_line_that_fails_stops_the_file_and_m27_says_so() {
    let mut b = Bench::new();
    b.take();
    let lines = ["G1 X1 F3000", "G1 X2 Q5", "G1 X3"].map(String::from);
    b.upload("e.g", &lines);
    let mut out = b.ask_all(&["M23 e.g", "M24"]);
    b.run_ms(500);
    out.extend(b.take());
    assert_eq!(error_codes(&out), [183], "{out:?}");
    assert!(!out.contains(&"Done printing file".to_string()));
    b.idle();
    assert_eq!(b.position_mm()[0], 1.0);
    assert_eq!(b.sd_position(), None);
    // A line over 256 bytes before any comment stops it too.
    let lines = [format!("G1 X1 F3000 {}", "X1 ".repeat(90))];
    let name = FileName::new(b"l.g").unwrap();
    let card = b.card();
    card.create(&name).unwrap();
    card.append(lines[0].as_bytes()).unwrap();
    card.finish().unwrap();
    let mut out = b.ask_all(&["M23 l.g", "M24"]);
    b.run_ms(50);
    out.extend(b.take());
    assert_eq!(error_codes(&out), [184], "{out:?}");
}

#[test]
fn file_commands_refuse_what_they_cannot_do() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M24"), ["echo:E189 no-file-selected", "ok"]);
    assert_eq!(b.ask("M26 S0"), ["echo:E189 no-file-selected", "ok"]);
    assert_eq!(b.ask("M25"), ["ok"]);
    assert_eq!(b.sd_position(), None);
    assert_eq!(
        b.ask("M23 nothing.g"),
        [
            "echo:E176 no-such-file nothing.g",
            "open failed, File: nothing.g.",
            "ok"
        ]
    );
    let (lines, _) = moves(400);
    b.upload("busy.g", &lines);
    b.ask_all(&["M23 busy.g", "M24"]);
    b.run_ms(20);
    // While it prints: no other file, no new version of it, no leaving the card.
    assert_eq!(
        b.ask("M23 busy.g"),
        ["echo:E182 job-busy", "open failed, File: busy.g.", "ok"]
    );
    assert_eq!(
        b.ask_all(&["M28 busy.g", "G1 X1", "M29"]),
        [
            "echo:E182 job-busy",
            "open failed, File: busy.g.",
            "ok",
            "echo:E182 job-busy",
            "ok",
            "ok"
        ]
    );
    assert_eq!(b.ask("M22"), ["echo:E182 job-busy", "ok"]);
    // Moves of the link are refused while it prints, reports answered.
    assert_eq!(b.ask("G1 X9"), ["echo:E182 job-busy", "ok"]);
    assert!(b.sd_position().is_some());
    // No other file is written while the machine moves (a flash erase would stall it).
    assert_eq!(
        b.ask_all(&["M28 next.g", "G1 X1", "M29"]),
        [
            "echo:E128 not-idle",
            "open failed, File: next.g.",
            "ok",
            "echo:E128 not-idle",
            "ok",
            "ok"
        ]
    );
    assert_eq!(b.ask("M21"), ["echo:SD card ok", "ok"]);
}

#[test]
fn the_card_is_written_only_while_the_machine_is_at_rest() {
    let mut b = Bench::new();
    b.take();
    b.upload("a.g", &["G1 X1".to_string()]);
    assert_eq!(b.ask("G1 X50 F600"), ["ok"]);
    b.run_ms(100);
    assert_eq!(
        b.ask("M30 a.g"),
        ["echo:E128 not-idle", "Deletion failed, File: a.g.", "ok"]
    );
    assert_eq!(
        b.ask_all(&["M28 b.g", "G1 X2", "M29"]),
        [
            "echo:E128 not-idle",
            "open failed, File: b.g.",
            "ok",
            "echo:E128 not-idle",
            "ok",
            "ok"
        ]
    );
    b.idle();
    assert_eq!(b.position_mm()[0], 50.0, "the refused lines moved nothing");
    assert_eq!(b.file_text("a.g"), "G1 X1\n");
    assert_eq!(b.card().writing(), None);
    assert_eq!(b.ask("M30 a.g"), ["File deleted:a.g", "ok"]);
    assert!(
        b.upload("b.g", &["G1 X2".to_string()])
            .contains(&"Done saving file.".to_string())
    );
}

#[test]
fn m22_releases_the_card_until_m21() {
    let mut b = Bench::new();
    b.take();
    b.upload("a.g", &["G1 X1".to_string()]);
    b.ask("M23 a.g");
    assert_eq!(b.ask("M22"), ["echo:SD card released", "ok"]);
    assert!(b.ctl.job().file().is_none());
    assert_eq!(b.ask("M23 a.g"), ["echo:No media", "ok"]);
    assert_eq!(
        b.ask("M20"),
        ["Begin file list", "End file list", "echo:No media", "ok"]
    );
    assert_eq!(b.ask("M21"), ["echo:SD card ok", "ok"]);
    assert_eq!(
        b.ask("M20"),
        ["Begin file list", "a.g 6", "End file list", "ok"]
    );
}

#[test]
fn m27_s_reports_every_so_many_seconds() {
    let mut b = Bench::new();
    b.take();
    let (mut lines, _) = moves(400);
    lines[1] = "G1 F600".to_string();
    b.upload("r.g", &lines);
    assert_eq!(b.ask("M27 S1"), ["ok"]);
    b.run_ms(2_100);
    assert_eq!(b.take(), ["Not SD printing", "Not SD printing"]);
    b.ask_all(&["M23 r.g", "M24"]);
    b.run_ms(1_000);
    let out = b.take();
    assert_eq!(out.len(), 1, "{out:?}");
    assert!(out[0].starts_with("SD printing byte "), "{out:?}");
    assert_eq!(b.ask("M27 S0"), ["ok"]);
    b.run_ms(3_000);
    assert!(!b.take().iter().any(|l| l.contains("SD printing")));
}

#[test]
fn a_board_without_a_card_answers_as_marlin_without_one() {
    let mut b = Bench::new();
    b.take();
    b.ctl.peripherals_mut().card = None;
    assert_eq!(b.ask("M21"), ["echo:SD init fail", "ok"]);
    assert_eq!(
        b.ask("M20"),
        ["Begin file list", "End file list", "echo:No media", "ok"]
    );
    for command in ["M22", "M23 a.g", "M24", "M25", "M26 S0"] {
        assert_eq!(b.ask(command), ["echo:No media", "ok"], "{command}");
    }
    assert_eq!(b.ask("M27"), ["Not SD printing", "ok"]);
    assert_eq!(
        b.ask_all(&["M28 a.g", "G1 X5 F3000", "M29"]),
        [
            "echo:E194 no-device sd-card",
            "open failed, File: a.g.",
            "ok",
            "echo:E194 no-device sd-card",
            "ok",
            "ok"
        ]
    );
    b.run_ms(100);
    assert_eq!(b.wiring.positions(), [0; 3]);
}

#[test]
fn m30_deletes_a_file_and_m32_selects_and_starts_one() {
    let mut b = Bench::new();
    b.take();
    b.upload("a.g", &["G1 X1 F3000".to_string()]);
    b.upload("b.g", &["G1 Y2 F3000".to_string()]);
    assert_eq!(b.ask("M30 /A.G"), ["File deleted:A.G", "ok"]);
    assert_eq!(
        b.ask("M30 a.g"),
        [
            "echo:E176 no-such-file a.g",
            "Deletion failed, File: a.g.",
            "ok"
        ]
    );
    assert_eq!(
        b.ask("M32 !b.g#"),
        ["File opened: b.g Size: 12", "File selected", "ok"]
    );
    b.run_until(10_000, |b| b.out.contains("Done printing file"));
    b.idle();
    b.take();
    assert_eq!(b.position_mm(), [0.0, 2.0, 0.0]);
    // `M30` alone still ends a program.
    assert_eq!(b.ask("M30"), ["ok"]);
    // The file printing cannot be deleted; once stopped, it can, and is no longer selected.
    let (lines, _) = moves(400);
    b.upload("long.g", &lines);
    assert_eq!(b.ask_all(&["M32 long.g"]).len(), 3);
    b.run_ms(20);
    assert_eq!(
        b.ask("M30 long.g"),
        ["echo:E182 job-busy", "Deletion failed, File: long.g.", "ok"]
    );
    assert_eq!(b.ask_all(&["M25"]), ["ok"]);
    b.idle();
    assert_eq!(b.ask("M30 long.g"), ["File deleted:long.g", "ok"]);
    assert!(b.ctl.job().file().is_none());
    assert_eq!(b.ask("M24"), ["echo:E189 no-file-selected", "ok"]);
}
