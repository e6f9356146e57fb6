//! The simulator's firmware: the motion kernel and the controller wired to the simulated
//! hardware exactly as a firmware board wires them.
//!
//! | firmware part | on the simulator |
//! |---|---|
//! | step interrupt | [`Firmware::on_alarm`]: `StepGenerator::on_alarm` over `forja_drivers::stepper::StepDir` drivers on [`SimStepDirPins`](forja_sim_hal::SimStepDirPins), and `forja_drivers::limit::LimitInput`s on the homing switches' [`SimSwitchPin`]s, then on the touch probe's (`G38.2`–`G38.5`) when the machine file has one; the switches' pin-change interrupt ([`SwitchEdges`]) reports their edges, the probe's too, to it |
//! | thread side | [`Firmware::poll`]: the ports' links, one controlling host across them and `Controller::poll` on its link, by [`forja_app::hosts::Arbiter`] (see [Links](#links)) |
//! | peripherals | `forja_app::peripherals::Parts`: PID `HeaterChannel`s over the simulated heaters, `Fan`s and the `Spindle` on the PWM outputs, the simulated beeper when the machine file has one (kept in the board's static RAM beside the step queue, as a firmware board keeps its devices in statics), the `Coolant` on the machine file's `flood` and `mist` digital outputs when it has them ([`SimOutputPin`](forja_sim_hal::SimOutputPin)s, kept in the static RAM too), the drivers' enable lines, the switches read again for `M119` |
//! | storage | the board's two flashes ([`BoardFlash`]): `FlashRecordStorage` for the settings, `RecordProgramStore` for the uploaded program; kept in a state file with `BoardFlash::open`; the SD card, a directory of the host ([`BoardConfig::sd_dir`]); opened together as [`BoardStores`] |
//! | read back | what tests and the `forja-sim` program read of the firmware, whatever its number of axes ([`SimBoard::status`], [`SimBoard::program_line`], [`SimBoard::settings`], [`SimBoard::load_report`]): the controller's own accessors (`Controller::status`, `Controller::read_program_line`, the settings' `Display`), adapted |
//!
//! The kernel's [`forja_motion::MachineConfig`] is the machine file read as the board's
//! machine ([`parts::machine`]), with the settings stored in the flash applied over it, as a
//! firmware board does at start-up; which heater, output and switch is which part is the
//! machine file's ([`forja_sim_hal::config`]).
//!
//! # Links
//!
//! [`SimBoard::add_port`] adds a link (TCP with a session, a pseudo-terminal, an in-memory
//! pair). The board has one controller, which serves one host at a time across all its ports,
//! by the rules of [`forja_app::hosts`]: other ports' input is refused with the busy message
//! ([`SimBoard::set_busy_message`]) and never run, but an `M112` in it is carried out; a
//! controlling host that is silent for its port's idle time-out
//! ([`SimBoard::set_idle_timeout`]) loses control; the controller reads at most
//! [`READ_BUDGET`] bytes a turn. Writes never block (a TCP client that stops reading is
//! dropped, a terminal's output discarded, see [`forja_sim_hal::link`]), so virtual time,
//! motion and the stop flag go on whatever hosts do.

pub mod parts;

use core::any::Any;
use core::fmt;
use std::io;

use forja_app::controller::{LoadReport, Peripherals, RecordProgramStore, Status};
use forja_app::firmware::{self, Parts as FirmwareParts};
use forja_app::hosts::{Arbiter, Port, PortLink};
use forja_app::peripherals::{LocalDevices, MotorEnables, Parts};
use forja_app::session::LinkSession;
use forja_drivers::heater::HeaterChannel;
use forja_drivers::limit::LimitInput;
use forja_drivers::pin::NoPin;
use forja_drivers::pwm::{Fan, FanConfig, Spindle};
use forja_drivers::stepper::StepDir;
use forja_hal_abstraction::clock::Alarm as _;
use forja_hal_abstraction::program::{MAX_LINE_LEN, MAX_LINES};
use forja_hal_abstraction::time::Instant;
use forja_motion::{StepGenerator, StepQueue, SwitchAlert};
use forja_sim_hal::link::RX_CAPACITY;
use forja_sim_hal::ram::StaticRam;
use forja_sim_hal::state::BoardFlash;
use forja_sim_hal::stores::{BoardStores, ProgramRecords, SettingsRecords, StoresError};
use forja_sim_hal::{
    Firmware, Flow, RunError, RunReport, SimDriverPin, SimMachine, SimSwitchPin, Simulation,
    SwitchEdges,
};

pub use forja_app::hosts::PortStats;
pub use parts::MAX_FANS;

/// Planner blocks of the kernel.
pub const PLANNER_BLOCKS: usize = 32;

/// Events of the step queue (a power of two).
pub const QUEUE_EVENTS: usize = 1024;

/// Most bytes the controller reads from the controlling port in one turn (a turn is a
/// millisecond of virtual time: 4 MB/s, far above any host link).
pub const READ_BUDGET: usize = 4096;

/// Why the board could not be built.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum BoardError {
    /// The kernel takes 1 to 8 axes.
    AxisCount(usize),
    /// The machine file makes a kernel configuration that does not validate.
    Config(forja_motion::ConfigError),
    /// A flash region could not be opened.
    Storage(String),
    /// A store of the board could not be opened: its flashes' records, its SD card.
    Stores(StoresError),
}

impl fmt::Display for BoardError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::AxisCount(n) => write!(f, "the motion kernel takes 1 to 8 axes, not {n}"),
            Self::Config(e) => write!(f, "the machine file does not suit the kernel: {e}"),
            Self::Storage(e) => write!(f, "flash: {e}"),
            Self::Stores(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for BoardError {}

/// A link the board serves. Every [`PortLink`] over `std::io` is one.
pub trait ServedLink: PortLink<Error = io::Error> + Any {}

impl<T: PortLink<Error = io::Error> + Any> ServedLink for T {}

type Ports = Vec<Port<Box<dyn ServedLink>>>;

/// The number of a port, from [`SimBoard::add_port`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PortId(usize);

/// What the board is doing, whatever its number of axes: the controller's [`Status`], the
/// kernel's position and the served port.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardStatus {
    /// What the controller is doing (`Controller::status`).
    pub controller: Status,
    /// The kernel's machine position of each axis, mm.
    pub machine_mm: Vec<f64>,
    /// The served port, if any.
    pub active_port: Option<PortId>,
}

/// The firmware of one axis count.
trait Wiring {
    fn on_alarm(&mut self, now: Instant) -> Option<Instant>;
    fn poll(&mut self, now: Instant, ports: &mut Ports, arbiter: &mut Arbiter<Vec<u8>>) -> Flow;
    fn status(&self, active_port: Option<PortId>) -> BoardStatus;
    fn keep_alive_ms(&self) -> u32;
    fn program_line(&mut self, index: u16) -> Option<String>;
    fn settings(&self) -> String;
    fn load_report(&self) -> LoadReport;
    fn into_flash(self: Box<Self>) -> BoardFlash;
}

type SimFirmware<const N: usize, X> =
    firmware::Firmware<'static, N, PLANNER_BLOCKS, QUEUE_EVENTS, ProgramStore, X, SettingsStore>;
type ProgramStore = RecordProgramStore<ProgramRecords>;
type SettingsStore = SettingsRecords;

/// The firmware of `N` axes with its peripherals `X`, the queue and the devices in `R`.
struct Wired<const N: usize, X, R> {
    firmware: SimFirmware<N, X>,
    isr: StepGenerator<'static, N, QUEUE_EVENTS>,
    /// The STEP/DIR drivers, and the homing switches then the probe, for the step interrupt.
    drivers: [StepDir<SimDriverPin, SimDriverPin>; N],
    limits: Vec<LimitInput<SimSwitchPin>>,
    /// The switch inputs' pin-change interrupt: reports edges to the step interrupt.
    switch_alert: SwitchAlert<'static>,
    switch_edges: SwitchEdges,
    /// The machine: its clock, and the step alarm the thread side arms.
    machine: SimMachine,
    /// The step queue and the thread side's devices: last, freed after everything that
    /// borrows them.
    _ram: StaticRam<R>,
}

fn storage_error(e: impl fmt::Debug) -> BoardError {
    BoardError::Storage(format!("{e:?}"))
}

/// Builds the firmware of one axis count on a machine, as a board's configuration says.
type Wire = fn(&SimMachine, BoardConfig) -> Result<Box<dyn Wiring>, BoardError>;

/// The firmware of each axis count the kernel takes, 1 to 8.
const WIRINGS: [Wire; 8] = [
    wire::<1>, wire::<2>, wire::<3>, wire::<4>, wire::<5>, wire::<6>, wire::<7>, wire::<8>,
];

/// The firmware of `N` axes on `machine` and its parts, with the flash and the program size of
/// `config`.
fn wire<const N: usize>(
    machine: &SimMachine,
    config: BoardConfig,
) -> Result<Box<dyn Wiring>, BoardError> {
    let pins = parts::pins::<N>(machine)?;
    let mut steppers = Vec::with_capacity(N);
    let mut enables = Vec::with_capacity(N);
    for (p, c) in pins.drivers {
        steppers.push(StepDir::new(p.step, p.dir, c).map_err(storage_error)?);
        let enable = StepDir::with_enable(NoPin, NoPin, p.enable, c);
        enables.push(enable.map_err(storage_error)?);
    }
    let heaters = [pins.hot_end, pins.bed]
        .map(|h| h.map(|h| HeaterChannel::new(h.sensor, h.heater, h.config)));
    let fans = pins.fans.map(|f| Fan::new(f?, FanConfig::DIRECT).ok());
    let spindle = pins.spindle.and_then(|(p, c)| Spindle::new(p, c).ok());
    let stores = BoardStores::open(config.flash, config.sd_dir).map_err(BoardError::Stores)?;
    let coolant = pins.coolant.into_coolant();
    let devices = (heaters, fans, spindle, coolant, pins.beeper);
    #[allow(unsafe_code)]
    // SAFETY: the RAM is the last field of `Wired`: everything that borrows the queue and the
    // devices in it (the firmware, the step interrupt, the switch alert) drops before it.
    let (ram, (queue, ([hot_end, bed], fans, spindle, coolant, beeper), card)) =
        unsafe { StaticRam::new((StepQueue::new(), devices, stores.card)) };
    let (isr, firmware, _) = firmware::assemble(FirmwareParts {
        machine: parts::machine(machine.config())?,
        settings: stores.settings,
        queue,
        tick_hz: machine.tick_hz(),
        config: parts::controller(machine.config()),
        program: RecordProgramStore::open(stores.program, config.program_lines)
            .map_err(storage_error)?,
        peripherals: Parts::<_, _, N, MAX_FANS, LocalDevices> {
            hot_end: hot_end.as_mut().map(|z| z as _),
            bed: bed.as_mut().map(|z| z as _),
            fans: fans.each_mut().map(|f| f.as_mut().map(|f| f as _)),
            spindle: spindle.as_mut().map(|s| s as _),
            coolant: coolant.as_deref_mut(),
            beeper: beeper.as_mut().map(|b| b as _),
            motors: MotorEnables(array::<_, N>(enables)?),
            endstops: pins.homing_switches.each_ref().map(parts::limit_input),
            files: Some(card),
        },
    })
    .map_err(BoardError::Config)?;
    Ok(Box::new(Wired {
        firmware,
        switch_alert: isr.switch_alert(),
        switch_edges: machine.switch_edges(),
        isr,
        drivers: array(steppers)?,
        limits: parts::step_switches(&pins.homing_switches, &pins.probe),
        machine: machine.clone(),
        _ram: ram,
    }))
}

/// One part per axis, as the kernel takes them.
fn array<T, const N: usize>(parts: Vec<T>) -> Result<[T; N], BoardError> {
    let len = parts.len();
    parts.try_into().map_err(|_| BoardError::AxisCount(len))
}

/// The pin-change interrupt of the switch inputs, as an EXTI line would raise it: report an
/// edge to the step interrupt when any switch changed since the last look (after each step, and
/// each poll for switches a test forces).
fn look_at_switches(edges: &mut SwitchEdges, alert: &SwitchAlert<'_>) {
    if edges.take() {
        alert.notify();
    }
}

impl<const N: usize, X: Peripherals<N>, R> Wiring for Wired<N, X, R> {
    fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        let next = self.isr.on_alarm(now, &mut self.drivers, &mut self.limits);
        look_at_switches(&mut self.switch_edges, &self.switch_alert);
        next
    }

    fn poll(&mut self, now: Instant, ports: &mut Ports, arbiter: &mut Arbiter<Vec<u8>>) -> Flow {
        look_at_switches(&mut self.switch_edges, &self.switch_alert);
        let now_ms = self.machine.now_ms() as u32;
        let controller = self.firmware.controller_mut();
        if let Some(at) = arbiter.poll(ports, controller, now, now_ms).arm_alarm {
            let _ = self.machine.alarm().set_alarm(at);
        }
        Flow::again_if(self.firmware.needs_poll())
    }

    fn status(&self, active_port: Option<PortId>) -> BoardStatus {
        let c = self.firmware.controller();
        BoardStatus {
            controller: c.status(),
            machine_mm: c.kernel().position().machine_mm.to_vec(),
            active_port,
        }
    }

    fn keep_alive_ms(&self) -> u32 {
        self.firmware.controller().settings().keep_alive_ms()
    }

    fn program_line(&mut self, index: u16) -> Option<String> {
        let mut buf = [0; MAX_LINE_LEN];
        let c = self.firmware.controller_mut();
        Some(c.read_program_line(index, &mut buf)?.to_owned())
    }

    fn settings(&self) -> String {
        self.firmware.controller().settings().to_string()
    }

    fn load_report(&self) -> LoadReport {
        self.firmware.load_report()
    }

    fn into_flash(self: Box<Self>) -> BoardFlash {
        let (_, program, _, settings) = self.firmware.into_controller().release();
        BoardStores::into_flash(program.into_inner(), settings)
    }
}

/// Settings of a [`SimBoard`].
#[derive(Debug)]
pub struct BoardConfig {
    /// Most lines the program store takes (at most 9999).
    pub program_lines: u16,
    /// The flash to start from: erased for a new board, [`SimBoard::into_flash`] of a previous
    /// one (a restart keeps the settings and the program), or a state file's
    /// ([`BoardFlash::open`]).
    pub flash: BoardFlash,
    /// The directory that is the SD card (`M20`–`M32`,
    /// [`DirFileStore`](forja_sim_hal::DirFileStore)); `None`: a fresh temporary directory,
    /// removed with the board.
    pub sd_dir: Option<std::path::PathBuf>,
}

impl Default for BoardConfig {
    fn default() -> Self {
        Self {
            program_lines: MAX_LINES,
            flash: BoardFlash::erased(),
            sd_dir: None,
        }
    }
}

/// The simulator board: the firmware on a [`SimMachine`]. Implements [`Firmware`] for
/// [`Simulation::run`]; [`SimBoard::run`] adds a host hook.
pub struct SimBoard {
    wiring: Box<dyn Wiring>,
    ports: Ports,
    arbiter: Arbiter<Vec<u8>>,
    machine: SimMachine,
}

impl fmt::Debug for SimBoard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimBoard")
            .field("machine", &self.machine)
            .field("ports", &self.ports.len())
            .finish_non_exhaustive()
    }
}

impl SimBoard {
    /// The firmware on `machine`: its kernel built from the machine file and the settings in
    /// `config.flash`.
    ///
    /// Errors: a machine of more than 8 axes, a machine file the kernel refuses, a flash that
    /// cannot be opened.
    pub fn new(machine: &SimMachine, config: BoardConfig) -> Result<Self, BoardError> {
        let n = machine.axis_count();
        let wire = WIRINGS
            .get(n.wrapping_sub(1))
            .ok_or(BoardError::AxisCount(n))?;
        Ok(Self {
            wiring: wire(machine, config)?,
            ports: Vec::new(),
            arbiter: Arbiter::new(READ_BUDGET, RX_CAPACITY),
            machine: machine.clone(),
        })
    }

    /// Serve `link`; `frames`: greet each host with frame 54 and keep it alive with frame 55
    /// (TCP, like the ESP32's WiFi).
    ///
    /// Every port has its [`LinkSession`] (keep-alives every `keep_alive_ms` of the stored
    /// settings): a connection-oriented link ([`forja_sim_hal::link::TcpLink`]) admits and
    /// refuses clients through it ([`PortLink::admit`]), with or without frames. The port has
    /// no idle time-out until [`SimBoard::set_idle_timeout`].
    pub fn add_port(&mut self, link: impl ServedLink, frames: bool) -> PortId {
        let session = LinkSession::new(self.wiring.keep_alive_ms());
        self.ports.push(Port::new(Box::new(link), session, frames));
        PortId(self.ports.len() - 1)
    }

    /// The controlling host of port `id` loses control after `timeout_ms` of virtual time
    /// without a byte from it while the controller owes it nothing (see
    /// [`forja_app::hosts`]); `None`: never. Takes effect for the next host.
    pub fn set_idle_timeout(&mut self, id: PortId, timeout_ms: Option<u32>) {
        let session = LinkSession::new(self.wiring.keep_alive_ms());
        let session = timeout_ms.map_or(session.clone(), |ms| session.with_idle_timeout(ms));
        if let Some(p) = self.ports.get_mut(id.0) {
            p.set_session(session);
        }
    }

    /// What a host whose input is refused (another host is in control) is sent; by default
    /// the controller's `busy_refusal`, as the ESP32 board sends it.
    pub fn set_busy_message(&mut self, message: impl Into<Vec<u8>>) {
        self.arbiter.set_busy_message(message.into());
    }

    /// What happened to the hosts of port `id`.
    pub fn port_stats(&self, id: PortId) -> Option<PortStats> {
        Some(self.ports.get(id.0)?.stats())
    }

    /// The link of a port, as its own type.
    pub fn port<T: ServedLink>(&self, id: PortId) -> Option<&T> {
        let link: &dyn Any = &**self.ports.get(id.0)?.link();
        link.downcast_ref()
    }

    /// The first failure of a port's link (the listening socket or the terminal failed).
    pub fn port_failure(&self, id: PortId) -> Option<&io::Error> {
        self.ports.get(id.0)?.failure()
    }

    /// The machine.
    pub fn machine(&self) -> &SimMachine {
        &self.machine
    }

    /// What the firmware is doing.
    pub fn status(&self) -> BoardStatus {
        self.wiring.status(self.arbiter.active().map(PortId))
    }

    /// Line `index` (1-based) of the stored program.
    pub fn program_line(&mut self, index: u16) -> Option<String> {
        self.wiring.program_line(index)
    }

    /// Every setting as the firmware applies it, one `key=value` line each, as frame 50 shows
    /// it.
    pub fn settings(&self) -> String {
        self.wiring.settings()
    }

    /// What the firmware found in the flash when it started: the stored setting values it
    /// applied, and those it ignored (unreadable, not decodable, or making the configuration
    /// invalid).
    pub fn load_report(&self) -> LoadReport {
        self.wiring.load_report()
    }

    /// Stop the board and take its flash, to start another on it (a restart).
    pub fn into_flash(self) -> BoardFlash {
        self.wiring.into_flash()
    }

    /// Run under `sim`, calling `host` after every thread-side poll (the host's turn: read
    /// replies, send lines). The run ends when `host` returns [`Flow::Stop`], at the time
    /// limit, or on the stop flag.
    ///
    /// Errors: [`RunError`].
    pub fn run<H: FnMut(&mut SimBoard, Instant) -> Flow>(
        &mut self,
        sim: &mut Simulation,
        host: H,
    ) -> Result<RunReport, RunError> {
        sim.run_hooked(self, host)
    }
}

impl Firmware for SimBoard {
    fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        self.wiring.on_alarm(now)
    }

    fn poll(&mut self, now: Instant) -> Flow {
        self.wiring.poll(now, &mut self.ports, &mut self.arbiter)
    }
}

#[cfg(test)]
mod tests {
    use forja_motion::MachineState;
    use forja_sim_hal::link::MemoryLink;
    use forja_sim_hal::{MachineConfig, SimulationConfig};

    use super::*;

    /// `lines` sent to a board on `machine` through an in-memory port; its reply lines once
    /// `oks` lines have been answered `ok` (at most 60 s of virtual time).
    fn answers(machine: &SimMachine, lines: &str, oks: usize) -> Vec<String> {
        let mut board = SimBoard::new(machine, BoardConfig::default()).unwrap();
        let (link, host) = MemoryLink::pair();
        board.add_port(link, false);
        host.send(lines.as_bytes());
        let mut config = SimulationConfig::new(machine.tick_hz());
        config.time_limit_ticks = Some(60 * u64::from(machine.tick_hz()));
        let mut sim = Simulation::new(machine.clone(), config);
        let mut text = String::new();
        board
            .run(&mut sim, |_, _| {
                text.push_str(&String::from_utf8_lossy(&host.take_received()));
                if text.lines().filter(|l| *l == "ok").count() >= oks {
                    Flow::Stop
                } else {
                    Flow::Continue
                }
            })
            .unwrap();
        text.lines().map(str::to_string).collect()
    }

    #[test]
    fn the_printer_plays_m300_tones_in_order_and_the_router_has_no_beeper() {
        let file = MachineConfig::bundled_toml("printer").unwrap();
        let machine = SimMachine::new(&MachineConfig::from_toml_str(file).unwrap());
        machine.set_tracing(true);
        let x = machine.axis_index('X').unwrap();
        let lines = "G1 X110 F3000\nM300 S440 P200\nM300 S0 P100\nM300 S880 P50\nM400\nM300\n";
        let out = answers(&machine, lines, 6);
        assert!(out.iter().all(|l| !l.starts_with("echo:E")), "{out:?}");
        let tones = machine.tones();
        let hz: Vec<u16> = tones.iter().map(|t| t.frequency_hz).collect();
        assert_eq!(hz, [440, 0, 880, 260]);
        // One after another, each for its length (1 ms = 1000 ticks).
        assert_eq!(tones[0].end_ticks - tones[0].start_ticks, 200_000);
        assert_eq!(tones[1].start_ticks, tones[0].end_ticks);
        assert_eq!(tones[2].start_ticks, tones[1].end_ticks);
        assert!(tones[3].start_ticks >= tones[2].end_ticks);
        // The first three while the move runs, as Marlin queues them; the last after `M400`.
        let last_step = *machine.step_times(x).last().unwrap();
        assert!(tones[2].start_ticks < last_step, "{tones:?}");
        assert!(tones[3].start_ticks >= last_step, "{tones:?}");
        assert_eq!(machine.dropped_tones(), 0);

        let router = SimMachine::new(&MachineConfig::default_router());
        let out = answers(&router, "M300 S440 P200\n", 1);
        assert!(
            out.ends_with(&["echo:E194 no-device beeper".to_string(), "ok".to_string()]),
            "{out:?}"
        );
    }

    #[test]
    fn a_restart_keeps_the_flash() {
        let machine = SimMachine::new(&MachineConfig::default_router());
        let board = SimBoard::new(&machine, BoardConfig::default()).unwrap();
        assert_eq!(board.status().controller.program_lines, 0);
        assert_eq!(board.status().controller.state, MachineState::Idle);
        let flash = board.into_flash();
        let board = SimBoard::new(
            &machine,
            BoardConfig {
                flash,
                ..BoardConfig::default()
            },
        )
        .unwrap();
        assert_eq!(board.status().active_port, None);
    }
}
