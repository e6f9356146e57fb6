//! Coolant through the simulator board, as a CNC job uses it: the default router has a flood
//! valve and a mist valve on two digital outputs (`flood`, `mist`). A host sends G-code lines
//! over an in-memory link and reads the replies; the test reads the valves' lines.
//!
//! - `M8` turns the flood on, `M7` the mist, each after the motion before it (and is answered
//!   then); `M9` turns both off, and so does the end of the program (`M2`).
//! - In the grbl dialect, the realtime bytes `0xA0` (flood) and `0xA1` (mist) toggle them, and
//!   the status report's `A:` field shows `F` and `M` while they are on.

mod common;

use common::{ANSWER_LIMIT_S, Rig};
use forja_sim_hal::config::{FLOOD, MIST};

/// grbl's realtime byte that toggles the flood coolant.
const FLOOD_TOGGLE: u8 = 0xA0;

/// grbl's realtime byte that toggles the mist coolant.
const MIST_TOGGLE: u8 = 0xA1;

/// grbl's soft reset (ctrl-x): the link enters the grbl dialect.
const SOFT_RESET: u8 = 0x18;

/// What these tests do with the rig.
trait RigExt {
    /// Whether the flood and the mist are on.
    fn coolant(&self) -> (bool, bool);
    /// When the output `name` was last switched, ticks.
    fn last_switched_ticks(&self, name: &str) -> u64;
    /// When X made its last traced step, ticks.
    fn last_x_step_ticks(&self) -> u64;
    /// Enter the grbl dialect: the soft reset, then grbl's banner.
    fn enter_grbl(&mut self);
    /// A grbl status report (`?`).
    fn status(&mut self) -> String;
    /// The next status report that carries the overrides, and with them the accessories
    /// (grbl sends them every few reports, not in each).
    fn accessories_report(&mut self) -> String;
}

impl RigExt for Rig {
    /// Whether the flood and the mist are on.
    fn coolant(&self) -> (bool, bool) {
        (
            self.machine.output_on(FLOOD).unwrap(),
            self.machine.output_on(MIST).unwrap(),
        )
    }

    /// When the output `name` was last switched, ticks.
    fn last_switched_ticks(&self, name: &str) -> u64 {
        let index = self.machine.digital_output_index(name).unwrap();
        let history = self.machine.digital_output_history(index).unwrap();
        history.last().unwrap().time_ticks
    }

    /// When X made its last traced step, ticks.
    fn last_x_step_ticks(&self) -> u64 {
        let x = self.machine.axis_index('X').unwrap();
        *self.machine.step_times(x).last().unwrap()
    }

    /// Enter the grbl dialect: the soft reset, then grbl's banner.
    fn enter_grbl(&mut self) {
        self.host.send(&[SOFT_RESET]);
        let out = self.run_until(|lines| lines.iter().any(|l| l.starts_with("Grbl 1.1h")));
        assert!(
            out.iter().any(|l| l.starts_with("Grbl 1.1h")),
            "the banner: {out:?}"
        );
    }

    /// A grbl status report (`?`).
    fn status(&mut self) -> String {
        self.host.send(b"?");
        let out = self.run_until(|lines| lines.iter().any(|l| l.starts_with('<')));
        out.into_iter()
            .find(|l| l.starts_with('<') && l.ends_with('>'))
            .unwrap_or_else(|| panic!("no status report within {ANSWER_LIMIT_S} s"))
    }

    /// The next status report that carries the overrides, and with them the accessories
    /// (grbl sends them every few reports, not in each).
    fn accessories_report(&mut self) -> String {
        for _ in 0..30 {
            let report = self.status();
            if report.contains("|Ov:") {
                return report;
            }
        }
        panic!("no status report with the overrides in 30");
    }
}

#[test]
fn m8_and_m7_turn_on_after_the_motion_before_them_and_m9_and_m2_turn_both_off() {
    let mut rig = Rig::router();
    assert_eq!(rig.coolant(), (false, false), "off at power-up");
    rig.ok("G28");
    rig.ok("G0 X100 Y100");
    rig.ok("M400");
    rig.machine.set_tracing(true);

    // Behind a 50 mm move (1 s at 3000 mm/min): switched when the move has ended, and
    // answered then.
    rig.ok("G1 X150 F3000");
    rig.ok("M8");
    assert_eq!(rig.coolant(), (true, false));
    let last_step = rig.last_x_step_ticks();
    let flood_on = rig.last_switched_ticks(FLOOD);
    assert!(
        flood_on >= last_step,
        "flood on at {flood_on}, before the move's last step at {last_step}"
    );

    rig.ok("G1 X100");
    rig.ok("M7");
    assert_eq!(rig.coolant(), (true, true), "both at once");
    assert!(rig.last_switched_ticks(MIST) >= rig.last_x_step_ticks());

    rig.ok("G1 X150");
    rig.ok("M9");
    assert_eq!(rig.coolant(), (false, false));
    assert!(rig.last_switched_ticks(FLOOD) >= rig.last_x_step_ticks());
    assert_eq!(
        rig.last_switched_ticks(FLOOD),
        rig.last_switched_ticks(MIST),
        "M9: both together"
    );

    rig.ok("M8");
    rig.ok("M7");
    rig.ok("M400");
    assert_eq!(rig.coolant(), (true, true));
    let out = rig.ask("M2");
    assert_eq!(out.last().map(String::as_str), Some("ok"), "{out:?}");
    rig.ok("M400");
    assert_eq!(rig.coolant(), (false, false), "program end");
    assert_eq!(rig.machine.violation_count(), 0);
}

#[test]
fn grbls_realtime_toggles_switch_the_coolant_and_the_status_shows_it() {
    let mut rig = Rig::router();
    rig.enter_grbl();
    let report = rig.accessories_report();
    assert!(!report.contains("|A:"), "nothing on: {report}");

    rig.host.send(&[FLOOD_TOGGLE]);
    let report = rig.accessories_report();
    assert_eq!(rig.coolant(), (true, false));
    assert!(report.ends_with("|A:F>"), "{report}");

    rig.host.send(&[MIST_TOGGLE]);
    let report = rig.accessories_report();
    assert_eq!(rig.coolant(), (true, true));
    assert!(report.ends_with("|A:FM>"), "{report}");

    rig.host.send(&[FLOOD_TOGGLE]);
    let report = rig.accessories_report();
    assert_eq!(rig.coolant(), (false, true));
    assert!(report.ends_with("|A:M>"), "{report}");

    rig.host.send(&[MIST_TOGGLE]);
    let report = rig.accessories_report();
    assert_eq!(rig.coolant(), (false, false));
    assert!(!report.contains("|A:"), "{report}");

    // `M8` in the dialect too, and the soft reset turns it off as grbl's does.
    rig.ok("M8");
    let report = rig.accessories_report();
    assert_eq!(rig.coolant(), (true, false));
    assert!(report.ends_with("|A:F>"), "{report}");
    rig.enter_grbl();
    assert_eq!(rig.coolant(), (false, false), "the reset");
}
