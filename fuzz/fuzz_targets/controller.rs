//! The whole controller on the simulated router, under any script of host input: the safety
//! invariants of `forja_tests::invariants` (acknowledged moves run once, refused lines change
//! nothing, positions stay true, homed axes keep their travel, the realtime path acts within
//! 10 ms). Two input bytes make one operation ([`Op::decode`]); `cargo xtask fuzz` caps an
//! input at 80 bytes, the length of the proptest's scripts, and
//! `cargo xtask fuzz --target controller --runs 10000000 --sanitizer none` is a full campaign.
#![no_main]

use forja_tests::invariants::{Op, run};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    run(&Op::decode(data));
});
