//! The network a WiFi board joins: checked credentials from the controller's `link.ssid` and
//! `link.password` settings (frame 00, kept in the store with the other [`Settings`]), else
//! the board's build-time default, and the watch that tells the board's WiFi side when the
//! settings name another network.
//!
//! | settings | default | the board joins |
//! |---|---|---|
//! | `link.ssid` set | any | the settings' network, if its credentials are valid; else none |
//! | `link.ssid` empty | given | the default network |
//! | `link.ssid` empty | none | none: the board offers its own access point, if it has one |
//!
//! Valid credentials: an SSID of 1 to [`SSID_LEN`] bytes, a password either empty (an open
//! network) or a WPA2 passphrase of [`PASSWORD_MIN_LEN`] to [`PASSWORD_LEN`] characters, both
//! printable ASCII.
//!
//! A board keeps one [`CredentialWatch`] on its thread side and calls
//! [`CredentialWatch::update`] after each poll of the controller: when a frame 00 changed the
//! network to a valid one, it returns the new credentials once, for the WiFi side to join at
//! once.
//!
//! # Contract
//!
//! Thread. No allocation, never blocks, never fails. The password is never printed
//! (`Debug` shows `<hidden>`, as frame 50 does).

use core::fmt;

use crate::controller::Settings;

/// Longest SSID (IEEE 802.11): 32 bytes.
pub const SSID_LEN: usize = 32;
/// Longest WPA2 passphrase: 63 characters.
pub const PASSWORD_LEN: usize = 63;
/// Shortest WPA2 passphrase.
pub const PASSWORD_MIN_LEN: usize = 8;

/// A network to join: checked credentials.
#[derive(Clone, PartialEq, Eq)]
pub struct Credentials {
    ssid: [u8; SSID_LEN],
    password: [u8; PASSWORD_LEN],
    ssid_len: u8,
    password_len: u8,
}

/// Whether `text` is printable ASCII.
fn printable(text: &str) -> bool {
    text.bytes().all(|b| (b' '..=b'~').contains(&b))
}

impl Credentials {
    /// Checked credentials; `None` when the SSID is empty or too long, or the password is
    /// neither empty nor a valid WPA2 passphrase, or either is not printable ASCII.
    pub fn new(ssid: &str, password: &str) -> Option<Self> {
        if ssid.is_empty() || !printable(ssid) || !printable(password) {
            return None;
        }
        if (1..PASSWORD_MIN_LEN).contains(&password.len()) {
            return None;
        }
        let mut credentials = Self {
            ssid: [0; SSID_LEN],
            password: [0; PASSWORD_LEN],
            ssid_len: u8::try_from(ssid.len()).ok()?,
            password_len: u8::try_from(password.len()).ok()?,
        };
        credentials
            .ssid
            .get_mut(..ssid.len())?
            .copy_from_slice(ssid.as_bytes());
        credentials
            .password
            .get_mut(..password.len())?
            .copy_from_slice(password.as_bytes());
        Some(credentials)
    }

    /// The network's SSID.
    pub fn ssid(&self) -> &str {
        text(&self.ssid, self.ssid_len)
    }

    /// Its WPA2 passphrase; empty for an open network.
    pub fn password(&self) -> &str {
        text(&self.password, self.password_len)
    }

    /// Whether the network is open (no passphrase).
    pub fn is_open(&self) -> bool {
        self.password_len == 0
    }

    /// The network `settings` name (`link.ssid`, `link.password`) when they name one, else
    /// `default`; `None` when the settings' credentials are not valid, or there is neither.
    pub fn chosen<const N: usize>(
        settings: &Settings<N>,
        default: Option<&Credentials>,
    ) -> Option<Self> {
        if settings.ssid().is_empty() {
            default.cloned()
        } else {
            Self::new(settings.ssid(), settings.password())
        }
    }
}

/// The first `len` bytes of `bytes`, checked printable ASCII when they were stored.
fn text(bytes: &[u8], len: u8) -> &str {
    bytes
        .get(..usize::from(len))
        .and_then(|b| core::str::from_utf8(b).ok())
        .unwrap_or("")
}

impl fmt::Debug for Credentials {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Credentials")
            .field("ssid", &self.ssid())
            .field("password", &"<hidden>")
            .finish()
    }
}

/// The network the board was last told to join, and the default it falls back to: see the
/// [module documentation](self).
#[derive(Debug, Clone)]
pub struct CredentialWatch {
    default: Option<Credentials>,
    applied: Option<Credentials>,
}

impl CredentialWatch {
    /// The network `settings` name, over `default` (the board's build-time network, if any):
    /// what the WiFi side joins at start ([`CredentialWatch::current`]).
    pub fn new<const N: usize>(settings: &Settings<N>, default: Option<Credentials>) -> Self {
        let applied = Credentials::chosen(settings, default.as_ref());
        Self { default, applied }
    }

    /// The network in force: the one to join, or `None` (no network, or settings naming
    /// one with invalid credentials).
    pub fn current(&self) -> Option<&Credentials> {
        self.applied.as_ref()
    }

    /// Compare the network `settings` name with the one in force; when it changed to a valid
    /// one, return it (once), for the WiFi side to join. A change to invalid credentials only
    /// clears the one in force.
    pub fn update<const N: usize>(&mut self, settings: &Settings<N>) -> Option<&Credentials> {
        let chosen = Credentials::chosen(settings, self.default.as_ref());
        if chosen == self.applied {
            return None;
        }
        self.applied = chosen;
        self.applied.as_ref()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::settings::tests::VecStorage;
    use forja_motion::{AxisConfig, MachineConfig};

    fn settings(ssid: &str, password: &str) -> Settings<1> {
        let mut storage = VecStorage::default();
        let mut s = Settings::new(MachineConfig::new([AxisConfig::linear(
            b'X', 80.0, 6000.0, 500.0, 200.0,
        )]));
        let ok = |m: &MachineConfig<1>| m.validate();
        s.set("link.ssid", ssid, &mut storage, &ok).unwrap();
        s.set("link.password", password, &mut storage, &ok).unwrap();
        s
    }

    #[test]
    fn credentials_are_checked() {
        let c = Credentials::new("workshop", "s3cret-pass").unwrap();
        assert_eq!((c.ssid(), c.password()), ("workshop", "s3cret-pass"));
        assert!(!c.is_open());
        assert!(Credentials::new("cafe", "").unwrap().is_open());
        assert_eq!(Credentials::new("", "s3cret-pass"), None, "no SSID");
        assert_eq!(Credentials::new(&"x".repeat(33), ""), None, "SSID too long");
        assert!(Credentials::new(&"x".repeat(32), &"p".repeat(63)).is_some());
        assert_eq!(
            Credentials::new("x", &"p".repeat(64)),
            None,
            "password too long"
        );
        assert_eq!(
            Credentials::new("x", "short"),
            None,
            "not a WPA2 passphrase"
        );
        assert_eq!(Credentials::new("caf\u{e9}", ""), None, "not ASCII");
        assert_eq!(Credentials::new("x", "tab\tinside"), None, "not printable");
    }

    #[test]
    fn the_password_is_never_printed() {
        let c = Credentials::new("workshop", "s3cret-pass").unwrap();
        let shown = std::format!("{c:?}");
        assert!(shown.contains("workshop") && !shown.contains("s3cret"));
    }

    #[test]
    fn the_settings_network_comes_before_the_default() {
        let default = Credentials::new("factory", "");
        let watch = CredentialWatch::new(&settings("workshop", "s3cret-pass"), default.clone());
        assert_eq!(watch.current().map(Credentials::ssid), Some("workshop"));
        let watch = CredentialWatch::new(&settings("", ""), default);
        assert_eq!(watch.current().map(Credentials::ssid), Some("factory"));
        let watch = CredentialWatch::new(&settings("", ""), None);
        assert_eq!(watch.current(), None);
        let watch = CredentialWatch::new(&settings("workshop", "short"), None);
        assert_eq!(watch.current(), None, "invalid settings are not joined");
    }

    #[test]
    fn a_new_network_is_handed_over_once() {
        let mut watch = CredentialWatch::new(&settings("", ""), None);
        assert_eq!(watch.update(&settings("", "")), None);
        let s = settings("workshop", "s3cret-pass");
        assert_eq!(watch.update(&s).map(Credentials::ssid), Some("workshop"));
        assert_eq!(watch.update(&s), None, "once");
        assert_eq!(watch.update(&settings("workshop", "short")), None);
        assert_eq!(watch.current(), None, "invalid: none in force");
        assert_eq!(
            watch.update(&s).map(Credentials::ssid),
            Some("workshop"),
            "valid again: handed over again"
        );
    }
}
