//! The controller task: the motion kernel and the portable controller wired to this board,
//! exactly as the simulator wires them (`boards/sim/src/board.rs`).
//!
//! | firmware part | on the ESP32 |
//! |---|---|
//! | step interrupt | [`crate::step::on_interrupt`]: `StepGenerator::on_alarm` over `StepDir` drivers on the STEP/DIR outputs and debounced `LimitInput`s on the switch inputs, sampled from each motion's start until all are released and settled, during homing and after a reported edge |
//! | switch interrupt | [`crate::limits::on_interrupt`]: the GPIO interrupt on either edge of a switch input; acknowledges it and reports the edge through the step generator's `SwitchAlert` |
//! | thread side | [`run`]: `LinkSession` (frames 54/55) through [`WifiLink::poll_session`] and `Firmware::session`, `Firmware::poll` (`forja_app::firmware`, which also assembles the kernel and the controller: [`build`]), the step alarm, the WiFi settings, the watchdog |
//! | peripherals | `DriverPeripherals`: the shared enable line, the switches read again for `M119`; no heater, fan or spindle |
//! | storage | the `forja` partition ([`crate::storage`]): the settings in a `FlashRecordStorage`, the uploaded program in a `SlotProgramStore` (one flash read per line) |
//!
//! The kernel's configuration is [`board::MACHINE`] with the stored settings applied over it
//! (`Settings::load`), as on the simulator.
//!
//! The task runs whether or not a client is connected: with none, replies are discarded and
//! a stored program runs on.

use embassy_time::{Duration, Instant as EmbassyInstant};
use forja_app::controller::ControllerConfig;
use forja_app::firmware::{self, Firmware, Parts as FirmwareParts};
use forja_app::peripherals::{DriverPeripherals, MotorEnables, NoHeater, NoPwm, NoSpindle, Parts};
use forja_hal_abstraction::clock::Clock;
use forja_hal_abstraction::time::Instant;
use forja_motion::StepQueue;
use static_cell::StaticCell;

use crate::board::{self, AXES};
use crate::hardware::{EnableLine, SetupError, Watchdog};
use crate::limits::ThreadLimit;
use crate::link::{self, WifiLink};
use crate::settings::{self, Credentials};
use crate::step::{self, QUEUE_EVENTS};
use crate::storage::{ProgramFlash, Store, Stores};
use crate::timer::StepClock;

/// Planner blocks of the kernel (the simulator's).
pub const PLANNER_BLOCKS: usize = 32;

/// The longest sleep of the controller task, ms: it feeds the watchdog and polls the
/// temperature loops at least this often.
pub const MAX_SLEEP_MS: u64 = 100;

/// The board's peripherals: motor power and the switches for `M119`.
pub type BoardPeripherals = DriverPeripherals<
    NoHeater,
    NoHeater,
    NoPwm,
    NoSpindle,
    MotorEnables<EnableLine, 1>,
    ThreadLimit,
    AXES,
    0,
>;

/// The uploaded program's store.
pub type ProgramStore = ProgramFlash;

/// The firmware of this board, as the application layer assembles it.
pub type BoardFirmware =
    Firmware<'static, AXES, PLANNER_BLOCKS, QUEUE_EVENTS, ProgramStore, BoardPeripherals, Store>;

static QUEUE: StaticCell<StepQueue<AXES, QUEUE_EVENTS>> = StaticCell::new();

/// Build the kernel from [`board::MACHINE`] and the stored settings, hand its step generator to
/// the step interrupt, and build the controller over it.
///
/// Context: init, after `step::install` and the step alarm's self-test; call once.
/// Errors: [`SetupError::Machine`] when the stored settings make a machine the kernel refuses
/// at this clock rate, [`SetupError::Storage`] when this was called before.
pub fn build(
    clock: StepClock,
    stores: Stores,
    enable: EnableLine,
    limits: [ThreadLimit; board::LIMITS],
) -> Result<BoardFirmware, SetupError> {
    let queue = QUEUE
        .try_init(StepQueue::new())
        .ok_or(SetupError::Storage)?;
    let peripherals = DriverPeripherals::new(Parts {
        hot_end: None,
        bed: None,
        fans: [],
        spindle: None,
        motors: MotorEnables([enable]),
        limits: limits.map(Some),
        tolerance_mc: 0,
    });
    let (generator, firmware, _) = firmware::assemble(FirmwareParts {
        machine: board::MACHINE,
        settings: stores.settings,
        queue,
        tick_hz: clock.tick_hz(),
        config: ControllerConfig::new("cnc", board::DRIVERS.timing),
        program: stores.program,
        peripherals,
    })
    .map_err(|_| SetupError::Machine)?;
    step::attach(generator);
    Ok(firmware)
}

/// `at` on embassy's clock: `at` is an instant of the step clock, compared with `now`.
fn embassy_deadline(clock: StepClock, now: Instant, at: Instant) -> EmbassyInstant {
    let ticks = at.signed_ticks_since(now).max(0) as u64;
    let us = ticks * 1_000_000 / u64::from(clock.tick_hz());
    EmbassyInstant::now() + Duration::from_micros(us)
}

/// Run the controller for ever: the session's 54 and 55, `Controller::poll`, the step alarm,
/// new WiFi credentials to the WiFi task, the watchdog; then sleep until the link has news,
/// the controller's `wake_at`, the next keep-alive, or [`MAX_SLEEP_MS`].
///
/// Context: the controller task. Never returns.
pub async fn run(
    mut firmware: BoardFirmware,
    mut link: WifiLink,
    clock: StepClock,
    mut watchdog: Watchdog,
    mut applied: Option<Credentials>,
) -> ! {
    loop {
        let now_ms = link::now_ms();
        while let Some(action) = link.poll_session(now_ms) {
            firmware.session(action, &mut link);
        }
        let now = clock.now();
        if let Some(at) = firmware.poll(now, &mut link, true) {
            step::arm(at);
        }
        let s = firmware.controller().settings();
        settings::track(&mut applied, s.ssid(), s.password());
        watchdog.feed();

        let mut deadline = EmbassyInstant::now() + Duration::from_millis(MAX_SLEEP_MS);
        if let Some(at) = firmware.wake_at() {
            deadline = deadline.min(embassy_deadline(clock, now, at));
        }
        if let Some(at_ms) = link.session_poll_at() {
            let ms = at_ms.wrapping_sub(link::now_ms()) as i32;
            deadline =
                deadline.min(EmbassyInstant::now() + Duration::from_millis(ms.max(0) as u64));
        }
        link.wait(deadline).await;
    }
}
