//! The host link over WiFi: a TCP server on [`PORT`] with one controlling client at a time,
//! across both stacks (station and access point), and the operator's web page on
//! [`WEB_PORT`], whose WebSocket carries the same link under the same session.
//!
//! The link is `forja_drivers::tcp` ([`TcpServer`], [`TcpLink`]): the receive and transmit
//! queues with their flow control, the admission of clients, and the waking of the controller
//! task are documented and tested there; the session rules it admits clients by are the
//! application's [`LinkSession`] (frames 54/55, the refusal of a second client with the
//! application's `busy_refusal`, code 300 `link-busy`). This module fixes its sizes for the
//! ESP32 family and keeps it in [`LINK`]:
//!
//! | what | value |
//! |---|---|
//! | port | [`PORT`], the simulator's |
//! | listening tasks | [`LISTENERS`] per stack, each running [`listen`] |
//! | receive / transmit queues | [`RX_LEN`] / [`TX_LEN`] bytes |
//! | session | [`LinkSession`], keep-alives every [`DEFAULT_KEEP_ALIVE_MS`] until the board applies its stored `keep_alive_ms` |
//! | counters | [`FORJA_LINK_COUNTERS`], read by a debugger by symbol name |
//! | web page | port [`WEB_PORT`], [`WEB_LISTENERS`] tasks per stack, each running [`listen_web`] (`forja_drivers::web`): the page's assets, the WebSocket at `/ws` that controls or watches |
//! | watchers' mirror | [`MIRROR`], `forja_drivers::web::MIRROR_LEN` bytes; counters [`FORJA_WEB_COUNTERS`] |

use forja_app::controller::{DEFAULT_KEEP_ALIVE_MS, busy_refusal};
use forja_app::session::LinkSession;
use forja_drivers::tcp::{LinkCounters, TcpLink, TcpQueues, TcpServer};
use forja_drivers::web::{Mirror, WebCounters};

use crate::net::Stack;

/// The TCP port of the host link, the simulator's too.
pub const PORT: u16 = 2323;

/// Listening sockets per stack.
pub const LISTENERS: usize = 2;

/// The port of the operator's web page.
pub const WEB_PORT: u16 = 80;

/// Web sockets per stack: a controlling page, a watching one, and one to load a page's assets.
pub const WEB_LISTENERS: usize = 3;

/// Bytes of the receive queue (client to controller).
pub const RX_LEN: usize = 2048;

/// Bytes of the transmit queue (controller to client).
pub const TX_LEN: usize = 2048;

/// The link counters, at a symbol a debugger can find: connections, refusals, keep-alives,
/// bytes and dropped replies.
#[unsafe(no_mangle)]
pub static FORJA_LINK_COUNTERS: LinkCounters = LinkCounters::new();

/// The web page's counters, at a symbol a debugger can find: assets served, requests
/// refused, watchers, protocol errors.
#[unsafe(no_mangle)]
pub static FORJA_WEB_COUNTERS: WebCounters = WebCounters::new();

/// What the controlling client is sent, copied for the web page's watchers.
pub static MIRROR: Mirror = Mirror::new();

/// The host link's byte queues.
static QUEUES: TcpQueues<RX_LEN, TX_LEN> = TcpQueues::new();

/// The host link: its session over the queues. The controller task takes its end once
/// ([`TcpServer::take`]); the listening tasks serve it ([`listen`]). The board sets the
/// session's keep-alive interval from its settings at init ([`TcpServer::admission`]).
pub static LINK: TcpServer<LinkSession, RX_LEN, TX_LEN> = TcpServer::new(
    &QUEUES,
    &FORJA_LINK_COUNTERS,
    LinkSession::new(DEFAULT_KEEP_ALIVE_MS),
)
.with_mirror(&MIRROR);

/// The controller's end of the host link.
pub type WifiLink = TcpLink<'static, LinkSession, RX_LEN, TX_LEN>;

/// Serve one listening socket of `stack` for ever: accept a client, then either serve it as
/// the controller or refuse it, as the session decides.
///
/// Context: a task ([`LISTENERS`] per stack). Never returns.
pub async fn listen(stack: Stack<'static>) -> ! {
    LINK.listen(stack, PORT, busy_refusal).await
}

/// Serve one web socket of `stack` for ever: the page's assets, and the link over a WebSocket,
/// under the same session as [`listen`]'s clients (a second client watches).
///
/// Context: a task ([`WEB_LISTENERS`] per stack). Never returns.
pub async fn listen_web(stack: Stack<'static>) -> ! {
    LINK.listen_web(stack, WEB_PORT, &FORJA_WEB_COUNTERS, busy_refusal)
        .await
}
