//! Limit switches through the simulator board, as a machine meets them: the board's
//! pin-change interrupt on the switch inputs reports each edge to the step interrupt, which
//! samples the switches only then (and at the start of each motion).
//!
//! - A move through the homing switch of an unhomed axis (no soft limits yet) trips the hard
//!   limit: the `!!` alarm, motion stopped within one step of the switch, the machine locked
//!   until a reset.
//! - A switch hit by hand while the machine moves another axis stops it too (the edge is
//!   reported whatever moves).

use forja_sim::board::BoardConfig;
use forja_sim_hal::config::SwitchSide;
use forja_sim_hal::link::MemoryLink;
use forja_tests::{Replies, Rig};

/// The default router: X at 150 mm, its normally-closed homing switch at X = 0 (80 steps/mm).
/// Unhomed, the firmware counts X from where it stands: X0 in G-code is 150 mm on the
/// machine.
fn rig() -> (Rig, forja_sim_hal::link::MemoryHost, Replies) {
    let mut rig = Rig::new("default", BoardConfig::default());
    let (link, mut host) = MemoryLink::pair();
    rig.board.add_port(link, true);
    let mut replies = Replies::default();
    rig.exchange(&mut host, &mut replies, 50);
    (rig, host, replies)
}

#[test]
fn a_move_through_the_switch_trips_the_hard_limit_within_one_step() {
    let (mut rig, mut host, mut replies) = rig();
    host.send(b"G1 X-170 F6000\n");
    rig.exchange(&mut host, &mut replies, 50);
    rig.settle(&mut host, &mut replies);
    let alarms: Vec<&String> = replies
        .lines
        .iter()
        .filter(|l| l.starts_with("Error:"))
        .collect();
    assert!(
        alarms
            .iter()
            .any(|l| l.starts_with("Error:E150 hard-limit X")),
        "a hard-limit alarm: {:?}",
        replies.lines
    );
    // The switch triggers at step 0; the step that reached it is the last one.
    let x = rig.machine.position_steps(0).unwrap();
    assert_eq!(x, 0, "X stopped at the switch, not beyond it");
    assert_eq!(rig.machine.violation_count(), 0);

    // Locked until a reset: a move is refused and changes nothing.
    replies.lines.clear();
    host.send(b"G1 X10\n");
    rig.exchange(&mut host, &mut replies, 100);
    assert!(
        replies.lines.iter().any(|l| l.starts_with("echo:E125")),
        "refused while in alarm: {:?}",
        replies.lines
    );
    assert_eq!(rig.machine.position_steps(0).unwrap(), 0);
}

#[test]
fn a_switch_hit_during_a_move_of_its_axis_stops_it_at_once() {
    let (mut rig, mut host, mut replies) = rig();
    host.send(b"G1 X-100 F3000\n");
    // Let X get going (from 150 mm towards 50 mm), then a hand presses its switch.
    rig.exchange(&mut host, &mut replies, 100);
    let moving_at = rig.machine.position_steps(0).unwrap();
    assert!(moving_at < 150 * 80, "X moves: {moving_at}");
    rig.machine
        .force_switch(0, SwitchSide::Min, Some(true))
        .unwrap();
    let pressed_at = rig.machine.position_steps(0).unwrap();
    rig.settle(&mut host, &mut replies);
    let stopped_at = rig.machine.position_steps(0).unwrap();
    assert!(
        replies
            .lines
            .iter()
            .any(|l| l.starts_with("Error:E150 hard-limit X")),
        "a hard-limit alarm: {:?}",
        replies.lines
    );
    assert!(
        stopped_at > 50 * 80,
        "stopped short of the target: {stopped_at}"
    );
    // The next step after the press was not made (the press comes between two steps).
    assert!(
        pressed_at - stopped_at <= 1,
        "pressed at {pressed_at}, stopped at {stopped_at}"
    );
}
