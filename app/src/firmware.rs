//! The firmware, assembled once for every board: the stored settings over the board's machine,
//! the kernel split around the step queue, the controller over the program store and the
//! peripherals, and the thread side's loop.
//!
//! A board describes its parts in a [`Parts`] and calls [`assemble`]. It gets back the two
//! halves of the machine: the [`StepGenerator`] for its step interrupt (call
//! `StepGenerator::on_alarm` at each alarm and re-arm at what it returns) and a [`Firmware`]
//! for its thread context (a task or the main loop), which it polls when the link has bytes,
//! a switch changed, or the instant it asked for has come:
//!
//! ```text
//!  board (wiring)                        forja-app
//!  ──────────────                        ─────────
//!  Parts { machine, settings storage, ──► assemble ──► (StepGenerator ─► step interrupt,
//!          queue, tick_hz, config,                      Firmware      ─► thread context)
//!          program store, peripherals }
//!  thread loop:
//!    session actions (a link with one) ──► Firmware::session
//!    on news or at wake_at             ──► Firmware::poll ──► arm the step alarm
//!    sleep until the link, a switch, or Firmware::wake_at
//! ```
//!
//! Context: init for [`assemble`]; thread for [`Firmware`]. Nothing here blocks but what the
//! storage and the link's writes do.

use core::fmt;
use embedded_io::{Read, ReadReady, Write};

use forja_drivers::session::SessionAction;
use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::program::ProgramStore;
use forja_hal_abstraction::stepper::Stepper;
use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::time::Instant;
use forja_motion::{ConfigError, MachineConfig, StepGenerator, StepQueue, SwitchAlert};

use crate::controller::{
    Controller, ControllerConfig, LoadReport, Peripherals, PollOutcome, Settings,
};

/// What a board hands to [`assemble`]: its machine and its parts.
pub struct Parts<'q, const N: usize, const Q: usize, P, X, S> {
    /// The board's machine: its axes, rates and travel, before the stored settings are applied
    /// over it.
    pub machine: MachineConfig<N>,
    /// Where the settings are kept (read at once, written by frame 00 and `M413`).
    pub settings: S,
    /// The step queue between the kernel and the step interrupt, for the life of the firmware.
    pub queue: &'q mut StepQueue<N, Q>,
    /// The step clock's rate, ticks a second.
    pub tick_hz: u32,
    /// The controller's configuration (the drivers' step timing is its `timing`).
    pub config: ControllerConfig,
    /// Where the uploaded program is kept.
    pub program: P,
    /// The machine's heaters, fans, spindle, motor power and end-stops.
    pub peripherals: X,
}

/// Build the firmware from a board's parts: the stored settings applied over
/// [`Parts::machine`] (a stored value that cannot be used is skipped and counted in the
/// [`LoadReport`]), the kernel split at the step clock's rate with the drivers' timing, and the
/// controller over the program store and the peripherals.
///
/// Context: init, once. Errors: the [`ConfigError`] of a machine the kernel refuses at this
/// clock rate and step timing (the board's own machine is wrong: stored values that would make
/// it so are skipped by the load).
#[allow(clippy::type_complexity)]
pub fn assemble<'q, const N: usize, const B: usize, const Q: usize, P, X, S>(
    parts: Parts<'q, N, Q, P, X, S>,
) -> Result<
    (
        StepGenerator<'q, N, Q>,
        Firmware<'q, N, B, Q, P, X, S>,
        LoadReport,
    ),
    ConfigError,
>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    let Parts {
        machine,
        mut settings,
        queue,
        tick_hz,
        config,
        program,
        peripherals,
    } = parts;
    let (loaded, report) = Settings::load(machine, &mut settings);
    let (kernel, steps) =
        forja_motion::split(queue, loaded.machine().clone(), tick_hz, config.timing)?;
    let controller =
        Controller::new(kernel, program, peripherals, config).with_settings(loaded, settings);
    Ok((
        steps,
        Firmware {
            controller,
            wake_at: None,
        },
        report,
    ))
}

/// The thread side of an assembled firmware: the controller, and when it asked to be polled.
pub struct Firmware<'q, const N: usize, const B: usize, const Q: usize, P, X, S> {
    controller: Controller<'q, N, B, Q, P, X, S>,
    wake_at: Option<Instant>,
}

impl<'q, const N: usize, const B: usize, const Q: usize, P, X, S> Firmware<'q, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// Announce the start (`start`) on `link`. Call once the link is up.
    pub fn boot<W: Write>(&mut self, link: &mut W) {
        self.controller.boot(link);
    }

    /// Poll the controller at `now` if anything may have happened: `news` (bytes on the link,
    /// a switch that changed) or the instant it asked for has come. Returns where to arm the
    /// step alarm, if anywhere.
    ///
    /// Context: thread. Never blocks, except to queue replies on a full link.
    pub fn poll<L: Read + ReadReady + Write>(
        &mut self,
        now: Instant,
        link: &mut L,
        news: bool,
    ) -> Option<Instant> {
        let due = self.wake_at.is_none_or(|at| now.is_at_or_after(at));
        if !due && !news {
            return None;
        }
        let PollOutcome { arm_alarm, wake_at } = self.controller.poll(now, link);
        self.wake_at = wake_at;
        arm_alarm
    }

    /// The latest instant to poll again at (sooner when there is news); `None` when nothing is
    /// timed.
    pub fn wake_at(&self) -> Option<Instant> {
        self.wake_at
    }

    /// Act on a link session's decision (a board whose link has sessions: frames 54 and 55):
    /// announce the new controlling client, or send the keep-alive. A second client is refused
    /// by the link itself, where its connection is, with
    /// [`busy_refusal`](crate::controller::busy_refusal): one refusal for every board.
    pub fn session<W: Write>(&mut self, action: SessionAction, link: &mut W) {
        match action {
            SessionAction::SendConnected => self.controller.on_connect(link),
            SessionAction::SendKeepAlive(n) => self.controller.keep_alive(n, link),
            SessionAction::RefuseSecondClient => {}
        }
    }

    /// The controller, for what a board reads of it (its statistics, its settings).
    pub fn controller(&self) -> &Controller<'q, N, B, Q, P, X, S> {
        &self.controller
    }

    /// The controller alone, the firmware given up (a simulator that keeps what it stored).
    pub fn into_controller(self) -> Controller<'q, N, B, Q, P, X, S> {
        self.controller
    }

    /// The controller, for what a board changes in it.
    pub fn controller_mut(&mut self) -> &mut Controller<'q, N, B, Q, P, X, S> {
        &mut self.controller
    }
}

/// The step interrupt's part of a board: the kernel's step generator with the board's STEP/DIR
/// drivers and limit switches.
pub struct StepSide<'q, const N: usize, const Q: usize, S, L, const K: usize> {
    generator: StepGenerator<'q, N, Q>,
    steppers: [S; N],
    switches: [L; K],
}

impl<'q, const N: usize, const Q: usize, S: Stepper, L: LimitSwitch, const K: usize>
    StepSide<'q, N, Q, S, L, K>
{
    /// The generator [`assemble`] returned, over the board's drivers and switches.
    pub fn new(generator: StepGenerator<'q, N, Q>, steppers: [S; N], switches: [L; K]) -> Self {
        Self {
            generator,
            steppers,
            switches,
        }
    }

    /// Run the step generator at `now`; arm the step alarm at what it returns.
    ///
    /// Context: the step interrupt. Never blocks.
    #[inline]
    pub fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        self.generator
            .on_alarm(now, &mut self.steppers, &mut self.switches)
    }

    /// The handle the switch inputs' pin-change interrupt reports edges through.
    pub fn switch_alert(&self) -> SwitchAlert<'q> {
        self.generator.switch_alert()
    }
}

/// Why a board could not start (it then resets, or reports it where it can).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SetupError {
    /// The crystal oscillator or a PLL did not start.
    Clocks,
    /// The step timer cannot count at the pin map's rate, or its alarm failed its self-test.
    StepTimer,
    /// The host link cannot be set up (a UART's baud rate, the WiFi or the network stack).
    Link,
    /// The link's queues were already taken.
    LinkQueues,
    /// The store's region disagrees with the linker script or the partition table.
    StorageLayout,
    /// No region for the store was found.
    NoStore,
    /// The store rejected its region, or the stored program could not be read.
    Storage,
    /// A motor driver pin could not be driven.
    Stepper,
    /// The machine (the board's, with the stored settings) does not suit the step clock.
    Machine,
}

impl fmt::Display for SetupError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Clocks => "crystal or PLL did not start",
            Self::StepTimer => "step timer rate not reachable, or its alarm failed",
            Self::Link => "host link could not be set up",
            Self::LinkQueues => "host link queues already in use",
            Self::StorageLayout => "store region disagrees with the memory layout",
            Self::NoStore => "no store region",
            Self::Storage => "store region rejected",
            Self::Stepper => "motor driver pin failed",
            Self::Machine => "machine configuration unsuited to the step clock",
        })
    }
}
