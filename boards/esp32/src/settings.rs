//! The WiFi link's settings: which network to join.
//!
//! The network is the controller's `link.ssid` and `link.password` settings (frame 00, kept in
//! the store with the other settings by `forja_app::controller::Settings`). When no network
//! was ever set there, the build's `FORJA_WIFI_SSID` and `FORJA_WIFI_PASSWORD` (read by
//! `option_env!`; an empty or unset password means an open network) are used. Without either,
//! the board starts its own access point (see [`crate::wifi`]).
//!
//! A change of the settings reaches the WiFi task through [`CHANGED`]: the controller task
//! calls [`track`] after each poll, which signals new credentials once, and the WiFi task joins
//! the new network at once.

use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::signal::Signal;
use heapless::String;

/// Longest SSID (IEEE 802.11): 32 bytes.
pub const SSID_LEN: usize = 32;
/// Longest WPA2 passphrase: 63 characters.
pub const PASSWORD_LEN: usize = 63;
/// Shortest WPA2 passphrase.
pub const PASSWORD_MIN_LEN: usize = 8;

/// The network joined in station mode when the settings name none.
const BUILD_SSID: Option<&str> = option_env!("FORJA_WIFI_SSID");
/// Its passphrase.
const BUILD_PASSWORD: Option<&str> = option_env!("FORJA_WIFI_PASSWORD");

/// A network to join.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Credentials {
    /// Its SSID, 1 to 32 printable bytes.
    pub ssid: String<SSID_LEN>,
    /// Its WPA2 passphrase, 8 to 63 printable characters; empty for an open network.
    pub password: String<PASSWORD_LEN>,
}

impl Credentials {
    /// Checked credentials; `None` when the SSID is empty or too long, or the password is
    /// neither empty nor a valid WPA2 passphrase, or either is not printable ASCII.
    pub fn new(ssid: &str, password: &str) -> Option<Self> {
        let printable = |t: &str| t.bytes().all(|b| (b' '..=b'~').contains(&b));
        if ssid.is_empty() || !printable(ssid) || !printable(password) {
            return None;
        }
        if (1..PASSWORD_MIN_LEN).contains(&password.len()) {
            return None;
        }
        Some(Self {
            ssid: String::try_from(ssid).ok()?,
            password: String::try_from(password).ok()?,
        })
    }
}

/// New credentials from the settings, for the WiFi task.
pub static CHANGED: Signal<CriticalSectionRawMutex, Credentials> = Signal::new();

/// The credentials to join: the settings' (`link.ssid`, `link.password`) when they name a
/// network, else the build's, else none.
pub fn credentials(ssid: &str, password: &str) -> Option<Credentials> {
    if !ssid.is_empty() {
        return Credentials::new(ssid, password);
    }
    Credentials::new(BUILD_SSID?, BUILD_PASSWORD.unwrap_or(""))
}

/// Compare the settings' network with `applied` (what the WiFi task was last given) and, when
/// it changed to a valid one, hand it to the WiFi task.
///
/// Context: the controller task, after each poll. Never blocks.
pub fn track(applied: &mut Option<Credentials>, ssid: &str, password: &str) {
    let current = credentials(ssid, password);
    if current != *applied {
        if let Some(new) = current.clone() {
            CHANGED.signal(new);
        }
        *applied = current;
    }
}
