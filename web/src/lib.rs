//! The operator's web page, as a board serves it: its assets, and the sans-IO codecs of the
//! HTTP and WebSocket server that carries it.
//!
//! Layer: a codec crate like `forja-protocol`: no I/O, no allocation, no panics on any input,
//! no knowledge of the controller, a chip or an executor. A board's link (the ESP32's WiFi
//! server in `forja-drivers`, the simulator's web link in `forja-sim-hal`) owns the sockets and
//! uses three things from here:
//!
//! - **Assets.** The page's files live in `page/`; the build compresses each with gzip and
//!   embeds it here, so a board answers a `GET` with [`Asset::gzip`] and
//!   `Content-Encoding: gzip`, and never decompresses anything. [`asset`] finds a file by its
//!   URL path; [`ASSETS`] lists them all, [`total_gzip_len`] is what they cost in flash,
//!   within [`GZIP_BUDGET`].
//! - **HTTP** ([`http`]): the head of a request parsed from the bytes received so far, the
//!   answers' heads written into the caller's buffer (200 with the gzip body, 101 for the
//!   WebSocket, 400/403/404/405/413/426/431/505 refusals).
//! - **WebSocket** ([`websocket`], RFC 6455): a streaming decoder of the client's frames
//!   (`feed(&[u8])`, masked frames required, named errors with their close codes) and writers
//!   of the server's frames.
//!
//! The contract with the page: `GET /` (and every other path of [`ASSETS`]) serves the page;
//! `/ws` ([`http::WEBSOCKET_PATH`]) is a WebSocket that carries the link's own protocols,
//! byte for byte (`docs/protocol.md`, "The WebSocket transport"): there is no second API.
#![no_std]
#![cfg_attr(not(test), deny(clippy::indexing_slicing))]

#[cfg(test)]
extern crate std;

mod accept;
pub mod http;
pub mod websocket;

/// The most the compressed page may take in a board's flash, bytes: `cargo xtask size`
/// reports [`total_gzip_len`] against it.
pub const GZIP_BUDGET: usize = 64 * 1024;

/// One served file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Asset {
    /// Its URL path, e.g. `/`.
    pub path: &'static str,
    /// Its `Content-Type`.
    pub content_type: &'static str,
    /// Its bytes, gzip-compressed.
    pub gzip: &'static [u8],
    /// Its length before compression, bytes.
    pub raw_len: usize,
}

/// Every served file.
pub static ASSETS: &[Asset] = include!(concat!(env!("OUT_DIR"), "/assets.rs"));

/// The file served at `path` (the request target without its query), if any.
pub fn asset(path: &str) -> Option<&'static Asset> {
    let path = path.split('?').next().unwrap_or(path);
    ASSETS.iter().find(|a| a.path == path)
}

/// The flash the compressed page takes, bytes.
pub fn total_gzip_len() -> usize {
    ASSETS.iter().map(|a| a.gzip.len()).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_is_served_at_the_root_compressed() {
        let page = asset("/").expect("the page");
        assert!(page.content_type.starts_with("text/html"));
        assert_eq!(page.gzip.get(..2), Some(&[0x1f, 0x8b][..]));
        assert!(page.gzip.len() < page.raw_len);
        assert!(asset("/?x=1").is_some());
        assert!(asset("/nothing").is_none());
    }
}
