//! The WiFi radio and connection: station mode on the configured network, reconnecting by
//! itself, and the board's own access point when there is no network to join.
//!
//! | situation | mode | the board is reachable at |
//! |---|---|---|
//! | credentials, network found | station | the address the network's DHCP server gave, port [`crate::link::PORT`] |
//! | no credentials | access point `forja-XXXXXX` | [`AP_ADDRESS`], port [`crate::link::PORT`] (its DHCP server gives the client an address) |
//! | credentials, [`FALLBACK_AFTER`] failed attempts in a row | access point and station: the station keeps trying | both |
//! | new credentials set over the link ([`join`]) | station on the new network, then as above | |
//!
//! The network is the controller's `link.ssid` / `link.password` settings, or, when none was
//! ever set, the build's `FORJA_WIFI_SSID` / `FORJA_WIFI_PASSWORD` ([`default_network`]; an
//! empty or unset password means an open network): `forja_app::wifi` chooses, and its
//! `CredentialWatch` tells the controller task of a change, which [`join`]s it.
//!
//! A lost network is joined again after [`backoff`] (1 s, doubling up to 30 s). Once the
//! access point is up it stays up until the board restarts or new credentials are set (then
//! the board tries the new network, and offers the access point again after three failed
//! attempts).
//!
//! The motion side does not depend on any of this: a program stored on the board keeps
//! running while the WiFi is down; only the host link is gone (see [`crate::link`]).
//!
//! The access point's passphrase is `FORJA_AP_PASSWORD` at build time (8 to 63 characters),
//! else [`DEFAULT_AP_PASSWORD`]: change it for a board that stays in the field.

use core::fmt::Write as _;
use core::net::Ipv4Addr;

use embassy_futures::select::{Either, select};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::signal::Signal;
use embassy_time::{Duration, Timer};
use esp_hal::peripherals::WIFI;
use esp_hal::rng::Rng;
use esp_radio::wifi::ap::AccessPointConfig;
use esp_radio::wifi::sta::StationConfig;
use esp_radio::wifi::{AuthenticationMethodConfig, Config, ControllerConfig};
pub use esp_radio::wifi::{Interface, WifiController};
use forja_app::firmware::SetupError;
use forja_app::wifi::Credentials;
use heapless::String;

/// The access point's own address (ESP-IDF's default for a soft AP); it serves DHCP in
/// `192.168.4.0/24`.
pub const AP_ADDRESS: Ipv4Addr = Ipv4Addr::new(192, 168, 4, 1);

/// Prefix length of the access point's network.
pub const AP_PREFIX_LEN: u8 = 24;

/// The access point's passphrase when `FORJA_AP_PASSWORD` is not set at build time.
pub const DEFAULT_AP_PASSWORD: &str = "forja-setup";

/// Failed station attempts in a row after which the access point comes up too.
pub const FALLBACK_AFTER: u32 = 3;

/// The longest wait between two station attempts.
pub const MAX_BACKOFF: Duration = Duration::from_secs(30);

/// The network joined in station mode when the settings name none.
const BUILD_SSID: Option<&str> = option_env!("FORJA_WIFI_SSID");
/// Its passphrase.
const BUILD_PASSWORD: Option<&str> = option_env!("FORJA_WIFI_PASSWORD");

/// New credentials from the settings, for the WiFi task.
static CHANGED: Signal<CriticalSectionRawMutex, Credentials> = Signal::new();

/// The build's network (`FORJA_WIFI_SSID`, `FORJA_WIFI_PASSWORD`), if it names a valid one.
pub fn default_network() -> Option<Credentials> {
    Credentials::new(BUILD_SSID?, BUILD_PASSWORD.unwrap_or(""))
}

/// Hand `credentials` to the WiFi task, which joins that network at once.
///
/// Context: thread. Never blocks.
pub fn join(credentials: &Credentials) {
    CHANGED.signal(credentials.clone());
}

/// The access point's passphrase.
fn ap_password() -> &'static str {
    match option_env!("FORJA_AP_PASSWORD") {
        Some(p) if (8..=63).contains(&p.len()) => p,
        _ => DEFAULT_AP_PASSWORD,
    }
}

/// The wait before station attempt `failures + 1`: nothing after a first loss, then 1 s,
/// doubling, at most [`MAX_BACKOFF`].
pub fn backoff(failures: u32) -> Duration {
    if failures == 0 {
        return Duration::from_ticks(0);
    }
    let secs = 1u64 << (failures - 1).min(5);
    Duration::from_secs(secs).min(MAX_BACKOFF)
}

/// An access point's SSID.
pub type ApSsid = String<32>;

/// `forja-` and the last three bytes of the access point's MAC address, in hexadecimal.
pub fn ap_ssid(mac: [u8; 6]) -> ApSsid {
    let mut ssid = String::new();
    let _ = write!(ssid, "forja-{:02x}{:02x}{:02x}", mac[3], mac[4], mac[5]);
    ssid
}

/// The radio, brought up: the WiFi driver, its two interfaces and a random seed for the
/// network stacks.
pub struct Radio {
    /// The WiFi driver, for the WiFi task ([`run`]).
    pub controller: WifiController<'static>,
    /// The station interface.
    pub station: Interface,
    /// The access point interface.
    pub access_point: Interface,
    /// A random seed for the network stacks.
    pub seed: u64,
}

/// Start the WiFi driver on `wifi` (it allocates from the heap of [`crate::system::init`]).
///
/// Context: init, after esp-rtos is started ([`crate::system::start_rtos`]).
/// Errors: [`SetupError::Link`] when the driver does not start.
pub fn radio(wifi: WIFI<'static>) -> Result<Radio, SetupError> {
    let controller =
        WifiController::new(wifi, ControllerConfig::default()).map_err(|_| SetupError::Link)?;
    let rng = Rng::new();
    Ok(Radio {
        controller,
        station: Interface::station(),
        access_point: Interface::access_point(),
        seed: (u64::from(rng.random()) << 32) | u64::from(rng.random()),
    })
}

/// Which interfaces are up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Station,
    AccessPoint,
    Both,
}

fn station_config(credentials: &Credentials) -> Option<StationConfig> {
    let authentication = if credentials.is_open() {
        AuthenticationMethodConfig::Open
    } else {
        AuthenticationMethodConfig::Wpa2Personal(credentials.password().try_into().ok()?)
    };
    Some(
        StationConfig::default()
            .with_ssid(credentials.ssid().try_into().ok()?)
            .with_authentication(authentication),
    )
}

fn access_point_config(ssid: &str) -> Option<AccessPointConfig> {
    Some(
        AccessPointConfig::default()
            .with_ssid(ssid.try_into().ok()?)
            .with_authentication(AuthenticationMethodConfig::Wpa2Personal(
                ap_password().try_into().ok()?,
            )),
    )
}

fn config(mode: Mode, credentials: Option<&Credentials>, ap_ssid: &str) -> Option<Config> {
    let station = credentials.and_then(station_config);
    let ap = access_point_config(ap_ssid)?;
    Some(match (mode, station) {
        (Mode::Station, Some(station)) => Config::Station(station),
        (Mode::Both, Some(station)) => Config::AccessPointStation(station, ap),
        _ => Config::AccessPoint(ap),
    })
}

/// Run the WiFi connection for ever, starting with `credentials`; the access point, when it
/// comes up, is `ap_ssid`.
///
/// Context: a task. Never returns.
pub async fn run(
    mut controller: WifiController<'static>,
    mut credentials: Option<Credentials>,
    ap_ssid: ApSsid,
) -> ! {
    let mut mode = if credentials.is_some() {
        Mode::Station
    } else {
        Mode::AccessPoint
    };
    loop {
        let applied = config(mode, credentials.as_ref(), &ap_ssid)
            .is_some_and(|c| controller.set_config(&c).is_ok());
        if !applied {
            // Stored credentials the driver refuses: serve the access point so that new ones
            // can be set.
            credentials = None;
            mode = Mode::AccessPoint;
            if let Some(c) = config(mode, None, &ap_ssid) {
                let _ = controller.set_config(&c);
            }
        }
        let next = match mode {
            Mode::AccessPoint => CHANGED.wait().await,
            Mode::Station | Mode::Both => {
                match select(keep_station(&mut controller, &mut mode), CHANGED.wait()).await {
                    Either::First(()) => continue,
                    Either::Second(next) => next,
                }
            }
        };
        let _ = controller.disconnect_async().await;
        credentials = Some(next);
        mode = Mode::Station;
    }
}

/// Join the network and rejoin it whenever it is lost. Returns when the access point must
/// come up as well (`mode` is then [`Mode::Both`]).
async fn keep_station(controller: &mut WifiController<'static>, mode: &mut Mode) {
    let mut failures = 0u32;
    loop {
        Timer::after(backoff(failures)).await;
        match controller.connect_async().await {
            Ok(_) => match controller.wait_for_disconnect_async().await {
                Ok(_) => failures = 0,
                Err(_) => failures = failures.saturating_add(1),
            },
            Err(_) => {
                failures = failures.saturating_add(1);
                if failures >= FALLBACK_AFTER && *mode == Mode::Station {
                    *mode = Mode::Both;
                    return;
                }
            }
        }
    }
}
