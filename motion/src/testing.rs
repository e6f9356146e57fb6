//! Helpers shared by the unit tests.

/// The next state of a xorshift64 generator, also returned: the tests' random inputs, the same
/// at every run.
pub(crate) fn xorshift(x: &mut u64) -> u64 {
    *x ^= *x << 13;
    *x ^= *x >> 7;
    *x ^= *x << 17;
    *x
}
