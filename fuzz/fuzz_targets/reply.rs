//! Replies: parsing never panics; a parsed reply re-encodes to a line that parses to the same.
#![no_main]

use forja_protocol::reply::Reply;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(reply) = Reply::parse(data) else {
        return;
    };
    // A reply re-encodes to less than twice its length (".5" is written "0.5").
    let mut out = vec![0u8; 2 * data.len() + 16];
    let len = match reply.encode(&mut out) {
        Ok(len) => len,
        Err(e) => panic!("a parsed reply must encode: {reply:?}: {e:?}"),
    };
    assert_eq!(out[len - 1], b'\n');
    assert_eq!(Reply::parse(&out[..len]), Ok(reply));
});
