//! # Forja's wire codecs
//!
//! This crate is the layer between a byte link (a UART, a TCP socket) and the motion kernel. It
//! turns bytes into typed messages and typed messages into bytes, and does nothing else: no
//! I/O, no clock, no allocation, no global state. The same code runs in the firmware (RTIC,
//! esp-hal), in the simulator and in the host client.
//!
//! | module | what |
//! |---|---|
//! | [`gcode`] | RepRap G-code lines: words, comments, `N`/`*` checksums, line-number continuity |
//! | [`reply`] | the controller's replies to a G-code host: `start`, `ok`, `rs`, `!!`, `//`, M105, M114, M115 |
//! | [`frame`] | the fixed 53-byte frames of the operator's client, both directions |
//! | [`stream`] | one decoder for a link that mixes frames and G-code lines, fed in chunks |
//! | [`grbl`] | the grbl 1.1 dialect of CNC senders: realtime bytes, `$` commands, status reports, `ok`/`error:N`/`ALARM:N` |
//! | [`error`] | the errors and their stable wire codes |
//!
//! The protocols themselves, byte by byte, with every choice made where the founding documents
//! were ambiguous, are described in `docs/protocol.md`.
//!
//! ## Contract
//!
//! - **Untrusted input never panics**: every decoder returns a typed error for any bytes. There
//!   is no `unsafe`, no `unwrap`, no indexing that can fail; the fuzz targets in `fuzz/` check
//!   this and the round-trip invariants.
//! - **Bounded memory**: a parsed [`gcode::Line`] holds at most [`gcode::MAX_WORDS`] words, the
//!   [`stream::Decoder`] one [`gcode::MAX_LINE_LEN`] buffer; texts are borrowed from the input.
//! - **Exact numbers**: numbers are read digit by digit into [`gcode::Decimal`], never through a
//!   float, and refused (not wrapped or rounded) when out of range.
//! - **What is written can be read back**: every `encode` either fails with an
//!   [`error::EncodeError`] or writes bytes that decode to the same message.
//! - **Context**: everything is plain computation, callable from any context (thread or
//!   interrupt); the cost is linear in the bytes handled (see `docs/performance.md`).
#![no_std]
#![forbid(unsafe_code)]
#![deny(clippy::unwrap_used, clippy::panic, clippy::indexing_slicing)]

mod decimal;
pub mod error;
pub mod frame;
pub mod gcode;
pub mod grbl;
pub mod reply;
pub mod stream;
mod write;
