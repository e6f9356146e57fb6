//! The touch probe through the simulator board, as a CNC operator uses it: the default router's
//! probe closes when the tool touches the top of a 20 mm stock (machine Z 20). A host sends
//! RepRap G-code lines over an in-memory link and reads the replies.
//!
//! - `G38.2` down onto the stock stops where the probe closed, within one Z step (1/400 mm),
//!   reports the contact and is answered `ok`; `G10 L20` then makes that work Z 0.
//! - `G38.2` that ends without contact, above the stock or with the probe held open (a cut
//!   wire), is the probe alarm (`Error:E158`) where the move ended, and the machine is locked.

mod common;

use common::Rig;
use forja_motion::{Alarm, MachineState};

/// Z steps per mm on the router.
const Z_STEPS_PER_MM: i64 = 400;

/// What these tests do with the rig.
trait RigExt {
    /// The move `line` answered `ok`, and made (`M400` waits for it).
    fn moved(&mut self, line: &str);
    /// Where Z is, in steps.
    fn z_steps(&self) -> i64;
}

impl RigExt for Rig {
    /// The move `line` answered `ok`, and made (`M400` waits for it).
    fn moved(&mut self, line: &str) {
        self.ok(line);
        self.ok("M400");
    }

    fn z_steps(&self) -> i64 {
        self.machine.position_steps(2).unwrap()
    }
}

/// The router homed (Z at the top), the tool above the stock at machine Z 30.
fn homed_above_the_stock() -> Rig {
    let mut rig = Rig::router();
    rig.ok("G28");
    assert!(
        (rig.z_steps() - 99 * Z_STEPS_PER_MM).abs() <= Z_STEPS_PER_MM,
        "Z homed up"
    );
    rig.moved("G0 X100 Y100");
    rig.moved("G0 Z30");
    assert_eq!(rig.z_steps(), 30 * Z_STEPS_PER_MM);
    assert!(!rig.machine.probe_touching());
    rig
}

/// `G38.2` down from machine Z 30 onto the stock, then `G10 L20` to make its top work Z 0.
fn probe_the_stock_top(rig: &mut Rig) {
    let out = rig.ask("G38.2 Z0 F100");
    assert_eq!(out.last().map(String::as_str), Some("ok"), "{out:?}");
    assert!(
        out.iter()
            .any(|l| l.contains("Probe: contact at") && l.contains("Z:20.000")),
        "the contact reported: {out:?}"
    );
    // Stopped on the step that closed the probe: the stock's top, 20 mm.
    let z = rig.z_steps();
    assert!(
        (z - 20 * Z_STEPS_PER_MM).abs() <= 1,
        "Z stopped at {z} steps"
    );
    assert!(rig.machine.probe_touching());
    let machine_z = rig.board.status().machine_mm[2];
    assert!(
        (machine_z - 20.0).abs() <= 1.0 / Z_STEPS_PER_MM as f64,
        "the kernel's Z: {machine_z}"
    );
    assert_eq!(rig.board.status().controller.state, MachineState::Idle);

    rig.ok("G10 L20 P1 Z0");
    let out = rig.ask("M114");
    assert!(
        out[0].starts_with("X:100.000 Y:100.000 Z:0.000 "),
        "{out:?}"
    );
}

#[test]
fn g38_2_stops_on_the_stock_and_g10_l20_makes_it_work_zero() {
    let mut rig = homed_above_the_stock();
    probe_the_stock_top(&mut rig);
    rig.moved("G0 Z25");
    assert_eq!(
        rig.z_steps(),
        45 * Z_STEPS_PER_MM,
        "work Z 25 is machine Z 45"
    );
    assert!(!rig.machine.probe_touching());
    assert_eq!(rig.machine.violation_count(), 0);
}

/// The probe alarm after a `G38.2`, the machine locked with Z where the move ended.
fn assert_probe_alarm(rig: &mut Rig, out: &[String], z_steps: i64) {
    assert!(
        out.iter()
            .any(|l| l.starts_with("Error:E158 probe-no-contact")),
        "the probe alarm: {out:?}"
    );
    assert_eq!(rig.z_steps(), z_steps, "the whole move ran");
    assert_eq!(
        rig.board.status().controller.state,
        MachineState::Alarm(Alarm::ProbeFailContact)
    );
    // Locked until a reset: a move is refused and changes nothing.
    let out = rig.ask("G0 Z30");
    assert!(out.iter().any(|l| l.starts_with("echo:E125")), "{out:?}");
    assert_eq!(rig.z_steps(), z_steps);
}

#[test]
fn g38_2_that_ends_above_the_stock_is_the_probe_alarm() {
    let mut rig = homed_above_the_stock();
    probe_the_stock_top(&mut rig);
    rig.moved("G0 Z25");
    // Work Z 25 down to 21: machine 45 to 41, never reaching the stock at 20.
    let out = rig.ask("G38.2 Z21 F100");
    assert_probe_alarm(&mut rig, &out, 41 * Z_STEPS_PER_MM);
}

#[test]
fn a_probe_held_open_never_touches() {
    let mut rig = homed_above_the_stock();
    // A cut wire: the probe reads open on the stock too.
    rig.machine.force_probe(Some(false)).unwrap();
    let out = rig.ask("G38.2 Z15 F300");
    assert_probe_alarm(&mut rig, &out, 15 * Z_STEPS_PER_MM);
}
