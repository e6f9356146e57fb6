//! The whole controller on the simulated router, under any script of host input: the safety
//! invariants of `forja_tests::invariants` (acknowledged moves run once, refused lines change
//! nothing, positions stay true, homed axes keep their travel, the realtime path acts within
//! 10 ms). Two input bytes make one operation ([`Op::decode`]).
#![no_main]

use forja_tests::invariants::{Op, run};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    run(&Op::decode(data));
});
