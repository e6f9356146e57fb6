//! The controller task: the thread side of the firmware on the WiFi link.
//!
//! Each turn ([`run`]): the session's 54 and 55 (a new client's greeting from
//! [`WifiLink::take_greeting`], the keep-alives from its `LinkSession`, both sent with
//! `Firmware::session`), `Firmware::poll`, the step alarm where it asks
//! ([`StepCell::arm`]), new WiFi credentials from the settings to the WiFi task
//! (`CredentialWatch::update`, [`wifi::join`]), the watchdog; then it sleeps until bytes
//! arrive, a client comes or goes, the controller's `wake_at`, the next keep-alive, or
//! [`MAX_SLEEP_MS`].
//!
//! The task runs whether or not a client is connected: with none, replies are discarded and
//! a stored program runs on.

use embassy_time::{Duration, Instant as EmbassyInstant};
use forja_app::controller::Peripherals;
use forja_app::firmware::Firmware;
use forja_app::session::SessionAction;
use forja_app::wifi::CredentialWatch;
use forja_drivers::tcp;
use forja_hal_abstraction::clock::Clock;
use forja_hal_abstraction::program::ProgramStore;
use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::time::Instant;

use crate::link::WifiLink;
use crate::step::StepCell;
use crate::timer::StepClock;
use crate::watchdog::Watchdog;
use crate::wifi;

/// The longest sleep of the controller task, ms: it feeds the watchdog and polls the
/// temperature loops at least this often.
pub const MAX_SLEEP_MS: u64 = 100;

/// `at` on embassy's clock: `at` is an instant of the step clock, compared with `now`.
fn embassy_deadline(clock: StepClock, now: Instant, at: Instant) -> EmbassyInstant {
    let ticks = at.signed_ticks_since(now).max(0) as u64;
    let us = ticks * 1_000_000 / u64::from(clock.tick_hz());
    EmbassyInstant::now() + Duration::from_micros(us)
}

/// Run the controller for ever: the session's 54 and 55, `Controller::poll`, the step alarm
/// of `step`, new WiFi credentials to the WiFi task, the watchdog; then sleep until the link
/// has news, the controller's `wake_at`, the next keep-alive, or [`MAX_SLEEP_MS`].
///
/// Context: the controller task. Never returns.
pub async fn run<const N: usize, const B: usize, const Q: usize, const K: usize, P, X, S>(
    mut firmware: Firmware<'static, N, B, Q, P, X, S>,
    mut link: WifiLink,
    clock: StepClock,
    step: &'static StepCell<N, Q, K>,
    mut watchdog: Watchdog,
    mut network: CredentialWatch,
) -> !
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    loop {
        let now_ms = tcp::now_ms();
        if link.take_greeting() {
            firmware.session(SessionAction::SendConnected, &mut link);
        }
        while let Some(keep_alive) = link.admission(|s| s.poll(now_ms)) {
            firmware.session(keep_alive, &mut link);
            link.count_keep_alive();
        }
        let now = clock.now();
        if let Some(at) = firmware.poll(now, &mut link, true) {
            step.arm(at);
        }
        if let Some(credentials) = network.update(firmware.controller().settings()) {
            wifi::join(credentials);
        }
        watchdog.feed();

        let mut deadline = EmbassyInstant::now() + Duration::from_millis(MAX_SLEEP_MS);
        if let Some(at) = firmware.wake_at() {
            deadline = deadline.min(embassy_deadline(clock, now, at));
        }
        if let Some(at_ms) = link.admission(|s| s.poll_at()) {
            let ms = at_ms.wrapping_sub(tcp::now_ms()) as i32;
            deadline =
                deadline.min(EmbassyInstant::now() + Duration::from_millis(ms.max(0) as u64));
        }
        link.wait(deadline).await;
    }
}
