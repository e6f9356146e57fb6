//! # forja-host: the operator's client
//!
//! The library behind the `forja` command: everything the command does is here, and
//! `main.rs` only reads the command line and prints.
//!
//! | module | what |
//! |---|---|
//! | [`link`] | the byte link (serial port or TCP) and the stream of reply lines and frames |
//! | [`program`] | G-code files checked line by line, compact and frame-sized forms |
//! | [`streamer`] | the windowed G-code streamer, a sans-IO state machine |
//! | [`grbl_sender`] | the grbl sender: character counting against the receive buffer, sans-IO |
//! | [`client`] | streaming a job and the interactive console over a link |
//! | [`frames`] | the frame client: upload, actions, jog, positions and progress |
//! | [`codes`] | the controller's error codes in words |
#![forbid(unsafe_code)]

pub mod client;
pub mod codes;
pub mod frames;
pub mod grbl_sender;
pub mod link;
pub mod program;
pub mod streamer;
