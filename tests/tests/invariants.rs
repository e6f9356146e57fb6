//! The controller's safety invariants ([`forja_tests::invariants`]) under arbitrary scripts of
//! host input: moves, refused and damaged lines, realtime frames, `M112`, jogs and homing.
//! The same scripts run for much longer under `cargo xtask fuzz` (target `controller`).

use forja_tests::invariants::{BadLine, Op, run};
use proptest::prelude::*;

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 48,
        max_shrink_iters: 200,
        failure_persistence: None,
        // The same scripts on every run: CI is reproducible, and `cargo xtask fuzz` explores.
        rng_seed: proptest::test_runner::RngSeed::Fixed(0x0046_4f52_4a41),
        ..ProptestConfig::default()
    })]

    #[test]
    fn invariants_hold_for_any_script(bytes in prop::collection::vec(any::<u8>(), 0..80)) {
        run(&Op::decode(&bytes));
    }
}

/// The reported sequence: a move, a pause in the middle of it, a stop, then more moves.
#[test]
fn stop_during_pause_keeps_the_position_true() {
    run(&[
        Op::Move {
            axis: 0,
            units: 100,
        },
        Op::Wait { ms: 40 },
        Op::Pause,
        Op::Wait { ms: 300 },
        Op::Stop,
        Op::Move { axis: 0, units: 50 },
        Op::Move {
            axis: 1,
            units: -40,
        },
    ]);
}

/// A refused line changes no modal state: the moves after it stay relative.
#[test]
fn refused_lines_change_nothing() {
    run(&[
        Op::Move { axis: 0, units: 10 },
        Op::Bad(BadLine::ModalThenBad),
        Op::Move { axis: 0, units: 10 },
        Op::Bad(BadLine::UnknownAxis),
        Op::Bad(BadLine::UnknownCommand),
        Op::Move {
            axis: 1,
            units: -10,
        },
    ]);
}

/// Moves acknowledged during a pause run once after it.
#[test]
fn moves_acknowledged_during_a_pause_run_after_it() {
    let mut script = vec![
        Op::Move {
            axis: 0,
            units: 100,
        },
        Op::Wait { ms: 20 },
        Op::Pause,
    ];
    for _ in 0..6 {
        script.push(Op::Move { axis: 0, units: 1 });
    }
    script.push(Op::Status);
    script.push(Op::Wait { ms: 40 });
    script.push(Op::Start);
    run(&script);
}

/// Short moves queued before a pause all run after it (found by the script test).
#[test]
fn queued_moves_survive_a_pause() {
    let mut script = vec![Op::Move { axis: 0, units: 1 }; 7];
    script.extend([Op::Pause, Op::Status, Op::Wait { ms: 40 }, Op::Start]);
    run(&script);
}

/// Damaged lines are asked for again and run once.
#[test]
fn damaged_lines_run_once() {
    let mut script = Vec::new();
    for i in 0..20u8 {
        script.push(Op::Corrupt { at: i * 3 });
        script.push(Op::Move {
            axis: usize::from(i % 3),
            units: 3,
        });
    }
    run(&script);
}

/// `M112` acts at once behind a long dwell and a held line, and frame 04 is answered.
#[test]
fn realtime_path_behind_held_lines() {
    let mut script = vec![
        Op::Move {
            axis: 0,
            units: 100,
        },
        Op::Pause,
    ];
    for _ in 0..5 {
        script.push(Op::Move { axis: 1, units: 10 });
    }
    script.push(Op::Status);
    script.push(Op::Emergency);
    script.push(Op::Move { axis: 2, units: 10 });
    run(&script);
}

/// Found by `cargo xtask fuzz`: a move damaged on the link, the controller's `rs` for it, and
/// frame `Reset` sent before the host read that `rs`. The host sent the move again, and it ran
/// after the reset, in the reset's absolute mode: into the Y switch. A host does not send a move
/// written before a stop to run after it (the session's host now sends its number as an empty
/// line); and a damaged line still waiting when the stop comes is refused by the controller,
/// not asked again (`stop_refuses_a_damaged_waiting_line_instead_of_asking_it_again`).
#[test]
fn a_line_damaged_before_a_reset_does_not_run_after_it() {
    let bytes = [
        26, 26, 26, 28, 88, 58, 28, 58, 127, 28, 28, 88, 28, 28, 58, 28, 93, 181, 93, 181, 246, 17,
        49, 13, 61, 230, 230, 230, 93, 230, 230, 55, 45, 61, 36, 25, 44, 41, 44, 0, 44, 0, 44, 255,
        20, 0, 246, 17, 49, 13, 61, 230, 230, 230, 93, 230, 230, 55, 45, 61, 36, 25, 44, 41, 44, 0,
        44, 0, 136,
    ];
    run(&Op::decode(&bytes));
}

/// Found by `cargo xtask fuzz`: a jog sent while a move was waiting to be sent again (damaged)
/// acts before that move; the session's host chose its direction from where the move would
/// end, and the jog took Z into its switch. The operator's jog must be clear of the ends
/// wherever it falls among the moves not yet run.
#[test]
fn a_jog_among_moves_not_yet_run_keeps_clear_of_the_switches() {
    let bytes = [
        0x56, 0x56, 0x56, 0x56, 0x56, 0x56, 0x56, 0x56, 0x26, 0x56, 0x56, 0x56, 0x56, 0x56, 0x4f,
        0x56, 0x3c, 0x60, 0xbb, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x56, 0x26, 0x56, 0x56,
        0x56, 0x56, 0x56, 0x4f, 0x56, 0x3c, 0x60, 0xbb, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d,
        0x7d, 0x76, 0x56, 0x56, 0x7d, 0x7d, 0x7d, 0x7d, 0x76, 0x56, 0x56, 0x7d, 0x7d, 0x04, 0x7d,
        0x7d, 0x7d, 0x3b, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d, 0x7d,
        0x23, 0x7d, 0x7d, 0x7d, 0x7d,
    ];
    run(&Op::decode(&bytes));
}

/// Found by the `controller` fuzz target: a move, a jog, a pause, two moves held behind it,
/// `M112` and `M999`; the machine must come to rest with its position true.
#[test]
fn an_emergency_stop_during_a_pause_with_moves_held_comes_to_rest() {
    run(&Op::decode(&[
        0x04, 0x32, 0x01, 0x00, 0x00, 0x00, 0xb7, 0x00, 0xac, 0x00, 0x00, 0x00, 0x33, 0x00, 0x00,
        0x00, 0x01, 0x00, 0x00, 0x99, 0x01,
    ]));
}

/// Found by the `controller` fuzz target with the one above.
#[test]
fn a_second_emergency_stop_script_comes_to_rest() {
    run(&Op::decode(&[
        0x00, 0x95, 0x4b, 0x75, 0x0a, 0x00, 0x57, 0xff, 0x12, 0xff, 0x5f, 0x00, 0x00, 0x00, 0xcc,
        0x08,
    ]));
}
