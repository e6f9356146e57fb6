//! Line numbering across restarts of the numbering (`M110`).

use super::*;

#[test]
fn m110_gives_a_number_asked_again_before_its_one_resend_anew() {
    let mut b = Bench::new();
    b.take();
    // A line that fails to parse: asked again once, then refused and used up.
    assert_eq!(b.ask(&numbered(1, "G1 X#1")), ["rs 1", "ok"]);
    assert_eq!(b.ask(&numbered(1, "G1 X#1")), ["echo:E9 no-value", "ok"]);
    // The numbering restarts: line 1 is a new line, owed its one resend.
    assert_eq!(b.ask("M110 N0"), ["ok"]);
    assert_eq!(b.ask(&numbered(1, "G1 X#1")), ["rs 1", "ok"]);
    assert_eq!(b.ask(&numbered(1, "G1 X1 F3000")), ["ok"]);
    // A line the interpreter refuses for damage: the same, across `N<n> M110`.
    assert_eq!(b.ask(&numbered(2, "G1 X1 X2")), ["rs 2", "ok"]);
    assert_eq!(
        b.ask(&numbered(2, "G1 X1 X2")),
        ["echo:E130 repeated-word X", "ok"]
    );
    assert_eq!(b.ask(&numbered(3, "M110 N1")), ["ok"]);
    assert_eq!(b.ask(&numbered(2, "G1 X1 X2")), ["rs 2", "ok"]);
    assert_eq!(b.ask(&numbered(2, "G1 X2")), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 2.0);
    assert_eq!(b.ctl.stats().executed, 4);
}
