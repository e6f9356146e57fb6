//! What the tests that run the `forja-sim` binary share. Each test uses what it needs.

#![allow(dead_code)]

use std::process::{Child, Command};

/// The `forja-sim` binary of this build.
pub fn sim() -> Command {
    Command::new(env!("CARGO_BIN_EXE_forja-sim"))
}

/// A running `forja-sim`, killed and reaped when dropped: a test that fails before it ends
/// leaves no simulator behind.
pub struct Running(pub Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
