//! The simulator's firmware: the motion kernel and the controller wired to the simulated
//! hardware exactly as a firmware board wires them.
//!
//! | firmware part | on the simulator |
//! |---|---|
//! | step interrupt | [`Firmware::on_alarm`]: `StepGenerator::on_alarm` over `forja_drivers::stepper::StepDir` drivers on [`SimStepDirPins`](forja_sim_hal::SimStepDirPins), and `forja_drivers::limit::LimitInput`s on [`SimSwitchPin`]s (the homing switch of each homed axis); the switches' pin-change interrupt ([`SwitchEdges`]) reports their edges to it |
//! | thread side | [`Firmware::poll`]: the links, one `LinkSession` per port (admission of TCP clients, frames 54/55, the idle time-out), one controlling host across the ports, `Controller::poll` with at most [`READ_BUDGET`] bytes of input |
//! | peripherals | `forja_app::peripherals::DriverPeripherals`: PID `HeaterChannel`s over the simulated heaters, fans and the spindle on the PWM outputs, the drivers' enable lines, the switches read again for `M119` |
//! | storage | two `FlashRecordStorage`s on simulated NOR flashes ([`Flash`], [`SimFlash`]): the settings, and the uploaded program (`RecordProgramStore`); kept in a file with `--state` ([`crate::state`]) |
//!
//! The kernel's [`forja_motion::MachineConfig`] is made from the machine file
//! ([`kernel_config`]), then the settings stored in the flash are applied over it, as a
//! firmware board does at start-up.
//!
//! # Links
//!
//! A board has one controller, which serves one host at a time, across all its ports.
//! [`SimBoard::add_port`] adds a link (TCP with a session, a pseudo-terminal, an in-memory
//! pair). Each turn:
//!
//! 1. Every link is polled, and its `forja_drivers::session::LinkSession` decides on the TCP
//!    clients that connected ([`HostLink::admit`]). While another port's host is in control
//!    the session is locked: the client is sent the busy message and closed.
//! 2. The controlling host's session goes on, or ends:
//!    - its host left (closed, hung up, dropped for not reading): what it sent before leaving
//!      still runs, in its session (its replies are discarded), until it is read and no line
//!      of it is held — unless another host wants control first: then the rest is dropped;
//!    - it was silent for the port's idle time-out ([`SimBoard::set_idle_timeout`]; silence
//!      counts only while the controller owes it nothing: no held line, homing cycle or heater
//!      wait): a TCP client is closed and its session ends; a terminal cannot be closed, so it
//!      only gives up control, and takes it back with its next byte, in the same session, if no
//!      other host took control in between.
//! 3. With no host in control, the first port (in the order they were added) whose host has
//!    just arrived, or that has input, takes control. A new session starts with no byte of the
//!    previous one: no unread input (the controller's and the link's), no held or queued line,
//!    no unsent reply; line 1 is expected. On a port with a session the host is greeted with
//!    frame 54 and kept alive with frame 55 every `keep_alive_ms`; the first host of a port
//!    without one receives `start`.
//! 4. Input that arrives on any other port is never run: it is discarded, and the host, if
//!    one is there, is sent the busy message ([`SimBoard::set_busy_message`]) once per turn.
//! 5. The controller reads at most [`READ_BUDGET`] bytes of the controlling port: a flood
//!    never keeps the thread side from the kernel, and the link holds the rest back.
//!
//! Nothing of a turn waits for a host: writes never block (a TCP client that stops reading is
//! dropped, a terminal's output discarded, see [`forja_sim_hal::link`]), so virtual time, motion and
//! the stop flag go on whatever hosts do.
//!
//! # Machine files
//!
//! The kernel has one switch per homed axis: the one on its homing side. Other switches of the
//! file (a hard limit at the far end) are modelled but not wired. Axes without travel limits
//! (rotary, extruder) get ±100 000 mm. `Z` homes first, then the others in file order. The
//! heater named `bed` is the bed, the first other heater the hot end; the output named
//! `spindle` is the spindle (24 000 rpm at full duty), the others are fans 0, 1, … in file
//! order.

use core::any::Any;
use core::fmt;
use std::io;

use forja_app::controller::{
    BUSY_REFUSAL_LEN, ControllerConfig, Key, Realtime, RecordProgramStore,
    Stats as ControllerStats, busy_refusal, realtime,
};
use forja_app::firmware::{self, Parts as FirmwareParts};
use forja_app::job::{JobState, Progress};
use forja_app::peripherals::{DriverPeripherals, MotorEnables, Parts};
use forja_drivers::heater::{HeaterChannel, HeaterConfig, PidGains};
use forja_drivers::limit::{LimitConfig, LimitInput, Polarity};
use forja_drivers::pin::NoPin;
use forja_drivers::pwm::{Fan, FanConfig, Spindle, SpindleConfig};
use forja_drivers::session::{LinkSession, SessionAction};
use forja_drivers::stepper::{StepDir, StepDirConfig};
use forja_drivers::storage::FlashRecordStorage;
use forja_hal_abstraction::clock::Alarm as _;
use forja_hal_abstraction::link::LinkState;
use forja_hal_abstraction::stepper::StepTiming;
use forja_hal_abstraction::time::Instant;
use forja_motion::{
    AxisConfig, AxisKind as KernelAxisKind, HomeDirection, HomingConfig,
    MachineConfig as KernelConfig, MachineState, StepGenerator, StepQueue, SwitchAlert,
};
use forja_protocol::stream::{Decoder, Event};

use forja_sim_hal::config::{AxisKind, MachineConfig, SwitchPolarity, SwitchSide};
use forja_sim_hal::flash::{PAGE, SimFlash};
use forja_sim_hal::link::{HostLink, RX_CAPACITY};
use forja_sim_hal::{
    Firmware, Flow, RunError, RunReport, SimAlarm, SimDriverPin, SimHeater, SimMachine, SimPwm,
    SimSwitchPin, SimTemperatureSensor, Simulation, SwitchEdges,
};

/// Planner blocks of the kernel.
pub const PLANNER_BLOCKS: usize = 32;

/// Events of the step queue (a power of two).
pub const QUEUE_EVENTS: usize = 1024;

/// Bytes of the flash that keeps the uploaded program (enough for the 9999 lines frame 03
/// allows, with room for the flash to reclaim space).
pub const PROGRAM_FLASH_LEN: usize = 1024 * 1024;

/// Bytes of the flash that keeps the settings.
pub const SETTINGS_FLASH_LEN: usize = 16 * 1024;

/// Erase page of both flashes.
pub const FLASH_PAGE: usize = PAGE;

/// The spindle's speed at full duty, rpm.
pub const SPINDLE_MAX_RPM: u32 = 24_000;

/// Fans the board drives at most (outputs beyond are not wired).
pub const MAX_FANS: usize = 4;

/// Travel given to an axis the machine file leaves unlimited, mm either side of 0.
pub const UNLIMITED_TRAVEL_MM: f32 = 100_000.0;

/// Most bytes the controller reads from the controlling port in one turn (a turn is a
/// millisecond of virtual time: 4 MB/s, far above any host link).
pub const READ_BUDGET: usize = 4096;

/// The busy message sent by default to a host whose input is refused because another host is
/// in control: the controller's [`busy_refusal`], as the ESP32 board sends it.
pub fn default_busy_message() -> Vec<u8> {
    let mut out = [0u8; BUSY_REFUSAL_LEN];
    let len = busy_refusal(&mut out);
    out.get(..len).unwrap_or_default().to_vec()
}

/// The program's flash.
pub type ProgramFlash = SimFlash<PROGRAM_FLASH_LEN>;
/// The settings' flash.
pub type SettingsFlash = SimFlash<SETTINGS_FLASH_LEN>;

/// The board's two flashes: what survives a restart.
#[derive(Debug)]
pub struct Flash {
    /// Keeps the uploaded program.
    pub program: ProgramFlash,
    /// Keeps the settings.
    pub settings: SettingsFlash,
}

impl Flash {
    /// Both erased: a board fresh from the factory.
    pub fn erased() -> Self {
        Self {
            program: ProgramFlash::erased(),
            settings: SettingsFlash::erased(),
        }
    }
}

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
}

impl fmt::Display for BoardError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::AxisCount(n) => write!(f, "the motion kernel takes 1 to 8 axes, not {n}"),
            Self::Config(e) => write!(f, "the machine file does not suit the kernel: {e}"),
            Self::Storage(e) => write!(f, "flash: {e}"),
        }
    }
}

impl std::error::Error for BoardError {}

/// A link the board serves. Every [`HostLink`] over `std::io` is one.
pub trait Port: HostLink<Error = io::Error> + Any {}

impl<T: HostLink<Error = io::Error> + Any> Port for T {}

/// The number of a port, from [`SimBoard::add_port`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PortId(usize);

/// What happened to the hosts of a port, counted from its start.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PortStats {
    /// Sessions begun on the port.
    pub sessions: u64,
    /// Times its controlling host was silent for the idle time-out.
    pub idle_timeouts: u64,
    /// Bytes received while another port's host was in control: discarded, never run.
    pub refused_bytes: u64,
    /// Busy messages sent.
    pub busy_replies: u64,
    /// Bytes a host that left had sent and that were dropped unread, because another host
    /// took control first (or it was silent for the time-out).
    pub dropped_bytes: u64,
    /// `M112` lines found in the refused bytes and carried out: an emergency stop acts from
    /// any host.
    pub emergency_stops: u64,
}

struct Served {
    link: Box<dyn Port>,
    /// Who controls a connection-oriented link ([`HostLink::admit`]), its keep-alives and its
    /// idle time-out (on a link without connections: the time-out alone).
    session: LinkSession,
    /// Whether the host is greeted with frame 54 and kept alive with frame 55.
    frames: bool,
    /// The link's connection count at the last look.
    seen: u64,
    /// A host arrived (the count changed) and has not been served yet.
    fresh: bool,
    failure: Option<String>,
    stats: PortStats,
    /// The input received while another host is in control, cut into records as the
    /// controller cuts its own link's, each line looked at for `M112`
    /// ([`Served::refuse_input`]).
    refused: Decoder,
}

impl Served {
    fn present(&self) -> bool {
        self.link.state() == LinkState::Connected
    }

    /// Whether this port's host wants control: one just arrived, or it has input.
    fn wants_control(&mut self) -> bool {
        (self.fresh && self.present()) || self.link.read_ready().unwrap_or(false)
    }

    /// Take and drop the input of a host that is not in control — except that an `M112` line
    /// among it (found as the controller finds it: the records of the stream decoder, and
    /// among its lines [`realtime`], the command word after an optional `N` number, whatever
    /// the checksum) is reported, for the board to carry out: an emergency stop acts from any
    /// host, as realtime commands do from every connection of FluidNC and grblHAL. Returns the
    /// bytes dropped and whether an `M112` came.
    fn refuse_input(&mut self) -> io::Result<(usize, bool)> {
        let mut buf = [0u8; 256];
        let mut dropped = 0;
        let mut stop = false;
        while dropped < RX_CAPACITY && self.link.read_ready()? {
            let n = self.link.read(&mut buf)?;
            if n == 0 {
                break;
            }
            dropped += n;
            self.refused.feed_all(buf.get(..n).unwrap_or(&[]), |event| {
                if let Event::Line(line) = event {
                    stop |= realtime(line) == Some(Realtime::EmergencyStop);
                }
            });
        }
        dropped += self.link.discard_input()?;
        Ok((dropped, stop))
    }
}

/// Who has the board's controller.
#[derive(Debug, Default)]
struct Arbiter {
    /// The port whose host is in control.
    active: Option<usize>,
    /// The port whose session the controller's link state belongs to (it stays when a
    /// terminal's host gives up control for silence, and goes when the session ends).
    owner: Option<usize>,
    busy_message: Vec<u8>,
}

/// A link that lets the controller read at most a fixed number of bytes.
struct Budgeted<'a, L: ?Sized> {
    link: &'a mut L,
    left: usize,
    read: usize,
}

impl<L: embedded_io::ErrorType + ?Sized> embedded_io::ErrorType for Budgeted<'_, L> {
    type Error = L::Error;
}

impl<L: embedded_io::ReadReady + ?Sized> embedded_io::ReadReady for Budgeted<'_, L> {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        if self.left == 0 {
            return Ok(false);
        }
        self.link.read_ready()
    }
}

impl<L: embedded_io::Read + ?Sized> embedded_io::Read for Budgeted<'_, L> {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = buf.len().min(self.left);
        let Some(buf) = buf.get_mut(..n) else {
            return Ok(0);
        };
        if buf.is_empty() {
            return Ok(0);
        }
        let got = self.link.read(buf)?;
        self.left = self.left.saturating_sub(got);
        self.read += got;
        Ok(got)
    }
}

impl<L: embedded_io::Write + ?Sized> embedded_io::Write for Budgeted<'_, L> {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.link.write(buf)
    }
    fn flush(&mut self) -> Result<(), Self::Error> {
        self.link.flush()
    }
}

/// What the board is doing, whatever its number of axes.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardStatus {
    /// The kernel's state.
    pub state: MachineState,
    /// Whether every queued move has finished.
    pub idle: bool,
    /// The job's state.
    pub job: JobState,
    /// The frame-52 figures.
    pub progress: Progress,
    /// The controller's counters.
    pub stats: ControllerStats,
    /// Whether G-code input is held (a line waits for room, or a heater wait).
    pub holding: bool,
    /// The kernel's machine position of each axis, mm.
    pub machine_mm: Vec<f64>,
    /// Axes homed (bit `i` = axis `i`).
    pub homed: u8,
    /// Lines of the stored program.
    pub program_lines: u16,
    /// The served port, if any.
    pub active_port: Option<PortId>,
}

/// The firmware of one axis count.
trait Wiring {
    fn on_alarm(&mut self, now: Instant) -> Option<Instant>;
    fn poll(&mut self, now: Instant, ports: &mut [Served], arb: &mut Arbiter);
    fn status(&self) -> BoardStatus;
    fn keep_alive_ms(&self) -> u32;
    fn program_line(&mut self, index: u16) -> Option<String>;
    fn stored(&mut self) -> Stored;
    fn into_flash(self: Box<Self>) -> Flash;
}

/// What a board keeps in its flash, as its firmware read it when it started: the settings and
/// the uploaded program ([`SimBoard::stored`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Stored {
    /// Every setting as frame 50 shows it: `key=value`.
    pub settings: Vec<String>,
    /// Stored setting values the firmware ignored when it started (unreadable, not decodable,
    /// or making the configuration invalid).
    pub ignored_settings: u16,
    /// The program's lines in order, each `None` when it cannot be read.
    pub program: Vec<Option<String>>,
    /// The program's total number of lines, 0 with no program; more than `program.len()` for
    /// an upload cut short, which does not run.
    pub program_total: u16,
}

/// The kernel's configuration for a machine file. See the [module documentation](self) for
/// how switches, unlimited axes and homing order are mapped.
///
/// Errors: [`BoardError::AxisCount`] unless the file has `N` axes.
pub fn kernel_config<const N: usize>(m: &MachineConfig) -> Result<KernelConfig<N>, BoardError> {
    if m.axes.len() != N {
        return Err(BoardError::AxisCount(m.axes.len()));
    }
    let mut switch = 0u8;
    let axes = core::array::from_fn(|i| {
        let a = &m.axes[i];
        let (min_mm, max_mm) = a
            .travel
            .map_or((-UNLIMITED_TRAVEL_MM, UNLIMITED_TRAVEL_MM), |t| {
                (t.min_mm as f32, t.max_mm as f32)
            });
        let homing = a.homing.map(|h| {
            let c = HomingConfig {
                direction: match h.direction {
                    forja_hal_abstraction::stepper::Direction::Negative => HomeDirection::Min,
                    forja_hal_abstraction::stepper::Direction::Positive => HomeDirection::Max,
                },
                seek_mm_min: h.seek_mm_min as f32,
                locate_mm_min: h.locate_mm_min as f32,
                pull_off_mm: h.pull_off_mm as f32,
                switch,
                order: u8::from(a.letter != 'Z'),
            };
            switch += 1;
            c
        });
        AxisConfig {
            letter: a.letter as u8,
            kind: match a.kind {
                AxisKind::Linear => KernelAxisKind::Linear,
                AxisKind::Rotary => KernelAxisKind::Rotary,
                AxisKind::Extruder => KernelAxisKind::Extruder,
            },
            steps_per_mm: a.steps_per_mm as f32,
            max_rate_mm_min: a.max_rate_mm_min as f32,
            accel_mm_s2: a.accel_mm_s2 as f32,
            min_mm,
            max_mm,
            homing,
        }
    });
    let config = KernelConfig::new(axes);
    config.validate().map_err(BoardError::Config)?;
    Ok(config)
}

/// The slowest driver timing of the machine: what the kernel schedules for.
pub fn slowest_timing(m: &MachineConfig) -> StepTiming {
    m.axes.iter().fold(
        StepTiming {
            min_pulse_ns: 0,
            dir_setup_ns: 0,
        },
        |t, a| StepTiming {
            min_pulse_ns: t.min_pulse_ns.max(a.step_timing.min_pulse_ns),
            dir_setup_ns: t.dir_setup_ns.max(a.step_timing.dir_setup_ns),
        },
    )
}

type Heat = HeaterChannel<SimTemperatureSensor, SimHeater>;
type EnableLine = StepDir<NoPin, NoPin, SimDriverPin>;
type Switch = LimitInput<SimSwitchPin>;
type SimPeripherals<const N: usize> = DriverPeripherals<
    Heat,
    Heat,
    SimPwm,
    Spindle<SimPwm>,
    MotorEnables<EnableLine, N>,
    Switch,
    N,
    MAX_FANS,
>;
type ProgramStore = RecordProgramStore<FlashRecordStorage<ProgramFlash>>;
type SettingsStore = FlashRecordStorage<SettingsFlash>;
type SimFirmware<const N: usize> = firmware::Firmware<
    'static,
    N,
    PLANNER_BLOCKS,
    QUEUE_EVENTS,
    ProgramStore,
    SimPeripherals<N>,
    SettingsStore,
>;

/// PID gains for the simulated heaters (Marlin's defaults, in fractions of full power).
const HOT_END_GAINS: PidGains = PidGains {
    kp: 0.087,
    ki: 0.0042,
    kd: 0.45,
};
const BED_GAINS: PidGains = PidGains {
    kp: 0.39,
    ki: 0.002,
    kd: 4.0,
};

fn polarity(p: SwitchPolarity) -> Polarity {
    match p {
        SwitchPolarity::NormallyOpen => Polarity::NormallyOpen,
        SwitchPolarity::NormallyClosed => Polarity::NormallyClosed,
    }
}

/// The switch on `axis`'s homing side, as the firmware reads it.
fn homing_switch(machine: &SimMachine, axis: usize) -> Option<Switch> {
    let a = machine.config().axes.get(axis)?;
    let side = match a.homing?.direction {
        forja_hal_abstraction::stepper::Direction::Negative => SwitchSide::Min,
        forja_hal_abstraction::stepper::Direction::Positive => SwitchSide::Max,
    };
    let config = a.switch(side)?;
    let pin = machine.switch_pin(axis, side).ok()?;
    Some(LimitInput::new(
        pin,
        LimitConfig::new(polarity(config.polarity), 1),
    ))
}

/// The step queue of a board, on the heap: the kernel and the step interrupt hold it as
/// `'static` (as a firmware board's `static`), and it is freed when the board is dropped.
///
/// It must be the last field of [`Wired`]: fields drop in declaration order, so everything
/// that borrows the queue (the controller's kernel, the step interrupt, the switch alert) is
/// gone before it is freed.
struct QueueBox<const N: usize>(core::ptr::NonNull<StepQueue<N, QUEUE_EVENTS>>);

impl<const N: usize> QueueBox<N> {
    /// A new queue, and the one reference to it the kernel is split from.
    #[allow(unsafe_code)]
    fn new() -> (Self, &'static mut StepQueue<N, QUEUE_EVENTS>) {
        let ptr = core::ptr::NonNull::from(Box::leak(Box::new(StepQueue::new())));
        // SAFETY: the allocation lives until `drop`, which runs after every borrower of this
        // reference is dropped (see the type's documentation); no other reference is made.
        (Self(ptr), unsafe { &mut *ptr.as_ptr() })
    }
}

impl<const N: usize> Drop for QueueBox<N> {
    #[allow(unsafe_code)]
    fn drop(&mut self) {
        // SAFETY: the pointer comes from `Box::leak` in `new`, and the references made from it
        // were held only by fields of `Wired` dropped before this one.
        drop(unsafe { Box::from_raw(self.0.as_ptr()) });
    }
}

struct Wired<const N: usize> {
    firmware: SimFirmware<N>,
    isr: StepGenerator<'static, N, QUEUE_EVENTS>,
    steppers: [StepDir<SimDriverPin, SimDriverPin>; N],
    switches: Vec<Switch>,
    /// The switch inputs' pin-change interrupt: reports edges to the step interrupt.
    switch_alert: SwitchAlert<'static>,
    switch_edges: SwitchEdges,
    alarm: SimAlarm,
    machine: SimMachine,
    booted: bool,
    /// Stored setting values ignored at start-up.
    ignored_settings: u16,
    /// The step queue: last, freed after everything that borrows it.
    _queue: QueueBox<N>,
}

fn storage_error(e: impl fmt::Debug) -> BoardError {
    BoardError::Storage(format!("{e:?}"))
}

impl<const N: usize> Wired<N> {
    /// The pin-change interrupt of the switch inputs, as an EXTI line would raise it: report
    /// an edge when any switch changed since the last look (after each step, and each poll
    /// for switches a test forces).
    fn look_at_switches(&mut self) {
        if self.switch_edges.take() {
            self.switch_alert.notify();
        }
    }

    fn new(machine: &SimMachine, flash: Flash, program_lines: u16) -> Result<Self, BoardError> {
        let file = machine.config();
        let base = kernel_config::<N>(file)?;
        let timing = slowest_timing(file);
        let settings_store = FlashRecordStorage::new(flash.settings, 0..SETTINGS_FLASH_LEN as u32)
            .map_err(storage_error)?;
        let (queue_box, queue) = QueueBox::<N>::new();

        let pins = |axis: usize| {
            machine
                .step_dir_pins(axis)
                .map_err(|e| BoardError::Storage(e.to_string()))
        };
        let mut steppers = Vec::with_capacity(N);
        let mut enables = Vec::with_capacity(N);
        for (axis, a) in file.axes.iter().enumerate() {
            let p = pins(axis)?;
            let config = StepDirConfig::new(a.step_timing);
            steppers.push(StepDir::new(p.step, p.dir, config).map_err(storage_error)?);
            enables
                .push(StepDir::with_enable(NoPin, NoPin, p.enable, config).map_err(storage_error)?);
        }
        let steppers: [_; N] = steppers
            .try_into()
            .map_err(|_| BoardError::AxisCount(file.axes.len()))?;
        let enables: [_; N] = enables
            .try_into()
            .map_err(|_| BoardError::AxisCount(file.axes.len()))?;
        let switches: Vec<Switch> = (0..N)
            .filter_map(|axis| homing_switch(machine, axis))
            .collect();
        let limits: [Option<Switch>; N] = core::array::from_fn(|axis| homing_switch(machine, axis));

        let heater = |i: usize, config: HeaterConfig| -> Option<Heat> {
            Some(HeaterChannel::new(
                machine.temperature_sensor(i).ok()?,
                machine.heater(i).ok()?,
                config,
            ))
        };
        let bed_index = file.heaters.iter().position(|h| h.name == "bed");
        let hot_index = file.heaters.iter().position(|h| h.name != "bed");
        let mut fans: [Option<Fan<SimPwm>>; MAX_FANS] = Default::default();
        let mut spindle = None;
        let mut next_fan = 0;
        for (i, o) in file.outputs.iter().enumerate() {
            let Ok(pwm) = machine.pwm(i) else { continue };
            if o.name == "spindle" {
                spindle = Spindle::new(pwm, SpindleConfig::new(SPINDLE_MAX_RPM)).ok();
            } else if let Some(slot) = fans.get_mut(next_fan) {
                *slot = Fan::new(pwm, FanConfig::DIRECT).ok();
                next_fan += 1;
            }
        }
        let peripherals = DriverPeripherals::new(Parts {
            hot_end: hot_index.and_then(|i| heater(i, HeaterConfig::hot_end(HOT_END_GAINS))),
            bed: bed_index.and_then(|i| heater(i, HeaterConfig::bed(BED_GAINS))),
            fans,
            spindle,
            motors: MotorEnables(enables),
            limits,
            tolerance_mc: 2_000,
        });

        let program_storage = FlashRecordStorage::new(flash.program, 0..PROGRAM_FLASH_LEN as u32)
            .map_err(storage_error)?;
        let program =
            RecordProgramStore::open(program_storage, program_lines).map_err(storage_error)?;
        let mut config = ControllerConfig::new(machine_type(file), timing);
        config.extruders = u8::from(file.axes.iter().any(|a| a.kind == AxisKind::Extruder));
        let (isr, firmware, loaded) = firmware::assemble(FirmwareParts {
            machine: base,
            settings: settings_store,
            queue,
            tick_hz: machine.tick_hz(),
            config,
            program,
            peripherals,
        })
        .map_err(BoardError::Config)?;
        Ok(Self {
            firmware,
            switch_alert: isr.switch_alert(),
            switch_edges: machine.switch_edges(),
            isr,
            steppers,
            switches,
            alarm: machine.alarm(),
            machine: machine.clone(),
            booted: false,
            ignored_settings: loaded.ignored,
            _queue: queue_box,
        })
    }

    /// Decide who is in control this turn (see the [module documentation](self)), greet a
    /// new host, refuse the input of the others.
    fn serve(&mut self, ports: &mut [Served], arb: &mut Arbiter, now_ms: u32) {
        if let Some(i) = arb.active {
            let others_want = ports
                .iter_mut()
                .enumerate()
                .any(|(j, q)| j != i && q.wants_control());
            if let Some(p) = ports.get_mut(i) {
                if !p.present() {
                    // Its host left: what it sent runs on, unless someone else wants control.
                    let draining = p.link.read_ready().unwrap_or(false)
                        || self.firmware.controller().is_holding();
                    if others_want || !draining {
                        self.end_session(p, arb);
                    }
                } else if p.fresh {
                    // A new host on the same port (a client that reconnected at once).
                    self.begin_session(p, i, arb, now_ms);
                } else if p.session.poll_idle(now_ms) {
                    p.stats.idle_timeouts += 1;
                    p.link.hang_up();
                    if p.present() {
                        // A terminal cannot be hung up: it only gives up control.
                        arb.active = None;
                    } else {
                        self.end_session(p, arb);
                    }
                }
            }
        }
        if arb.active.is_none() {
            for (i, p) in ports.iter_mut().enumerate() {
                if !p.wants_control() {
                    continue;
                }
                if p.fresh || arb.owner != Some(i) {
                    self.begin_session(p, i, arb, now_ms);
                } else {
                    // The same host, back after giving up control: its session goes on.
                    arb.active = Some(i);
                    p.session.set_locked(false);
                    p.session.on_connect(now_ms);
                }
                break;
            }
        }
        let mut stop = false;
        for (i, p) in ports.iter_mut().enumerate() {
            if arb.active == Some(i) {
                // The port's input goes to the controller now.
                p.refused.reset();
                continue;
            }
            match p.refuse_input() {
                Ok((0, _)) => {}
                Ok((n, m112)) => {
                    stop |= m112;
                    p.stats.refused_bytes += n as u64;
                    if m112 {
                        p.stats.emergency_stops += 1;
                    }
                    if p.present() {
                        p.stats.busy_replies += 1;
                        let _ = p.link.write_all(&arb.busy_message);
                    }
                }
                Err(e) => {
                    p.failure.get_or_insert(e.to_string());
                }
            }
        }
        if stop {
            // The fault goes to the controlling host, whose waiting lines are answered.
            match arb.active.and_then(|i| ports.get_mut(i)) {
                Some(p) => self.firmware.controller_mut().emergency_stop(&mut p.link),
                None => self.firmware.controller_mut().emergency_stop(&mut Silent),
            }
        }
    }

    /// Start a new session with the host of port `i`: nothing of the previous session is
    /// kept; frame 54 to a host on a port with frames, `start` to the first host of a port
    /// without.
    fn begin_session(&mut self, p: &mut Served, i: usize, arb: &mut Arbiter, now_ms: u32) {
        p.fresh = false;
        p.session.set_locked(false);
        if !p.session.is_connected() {
            // A link without connections: the session only times the host's silence.
            p.session.on_connect(now_ms);
        }
        arb.active = Some(i);
        arb.owner = Some(i);
        p.stats.sessions += 1;
        if p.frames {
            self.firmware.controller_mut().on_connect(&mut p.link);
        } else {
            self.firmware.controller_mut().reset_link();
            if !self.booted {
                self.booted = true;
                self.firmware.controller_mut().boot(&mut p.link);
            }
        }
    }

    /// End the session of the controlling host of `p`: what it sent and was not read is
    /// dropped, and so are its held line and partial input.
    fn end_session(&mut self, p: &mut Served, arb: &mut Arbiter) {
        match p.link.discard_input() {
            Ok(n) => p.stats.dropped_bytes += n as u64,
            Err(e) => {
                p.failure.get_or_insert(e.to_string());
            }
        }
        p.session.on_disconnect();
        self.firmware.controller_mut().reset_link();
        arb.active = None;
        arb.owner = None;
    }
}

/// A link that has nothing to say and hears nothing: the controller's link while no host is
/// served.
struct Silent;

impl embedded_io::ErrorType for Silent {
    type Error = core::convert::Infallible;
}

impl embedded_io::Read for Silent {
    fn read(&mut self, _: &mut [u8]) -> Result<usize, Self::Error> {
        Ok(0)
    }
}

impl embedded_io::ReadReady for Silent {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        Ok(false)
    }
}

impl embedded_io::Write for Silent {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        Ok(buf.len())
    }
    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

fn machine_type(file: &MachineConfig) -> &'static str {
    if file.heaters.is_empty() {
        "cnc"
    } else {
        "printer"
    }
}

impl<const N: usize> Wiring for Wired<N> {
    fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        let next = self
            .isr
            .on_alarm(now, &mut self.steppers, &mut self.switches);
        self.look_at_switches();
        next
    }

    fn poll(&mut self, now: Instant, ports: &mut [Served], arb: &mut Arbiter) {
        self.look_at_switches();
        let now_ms = (u128::from(self.machine.now_ticks()) * 1000
            / u128::from(self.machine.tick_hz())) as u32;
        // The controlling host, if it is still there: every other port refuses new clients.
        let holder = arb
            .active
            .filter(|&a| ports.get(a).is_some_and(Served::present));
        for (i, p) in ports.iter_mut().enumerate() {
            p.session.set_locked(holder.is_some_and(|a| a != i));
            if let Err(e) = p
                .link
                .poll()
                .and_then(|()| p.link.admit(&mut p.session, now_ms))
            {
                p.failure.get_or_insert(e.to_string());
            }
            let seen = p.link.connections();
            if core::mem::replace(&mut p.seen, seen) != seen {
                p.fresh = true;
            }
        }
        self.serve(ports, arb, now_ms);
        let outcome = match arb.active.and_then(|i| ports.get_mut(i)) {
            Some(p) => {
                if p.frames {
                    while let Some(SessionAction::SendKeepAlive(n)) = p.session.poll(now_ms) {
                        self.firmware.controller_mut().keep_alive(n, &mut p.link);
                    }
                }
                let mut link = Budgeted {
                    link: &mut p.link,
                    left: READ_BUDGET,
                    read: 0,
                };
                let outcome = self.firmware.controller_mut().poll(now, &mut link);
                if link.read > 0 || self.firmware.controller().is_holding() {
                    p.session.on_input(now_ms);
                }
                outcome
            }
            None => self.firmware.controller_mut().poll(now, &mut Silent),
        };
        if let Some(at) = outcome.arm_alarm {
            let _ = self.alarm.set_alarm(at);
        }
    }

    fn status(&self) -> BoardStatus {
        let k = self.firmware.controller().kernel();
        BoardStatus {
            state: k.state(),
            idle: k.is_idle() && k.state() != MachineState::Homing,
            job: self.firmware.controller().job().state(),
            progress: self.firmware.controller().progress(),
            stats: self.firmware.controller().stats(),
            holding: self.firmware.controller().is_holding(),
            machine_mm: k.position().machine_mm.to_vec(),
            homed: k.homed_axes(),
            program_lines: forja_hal_abstraction::program::ProgramStore::len(
                self.firmware.controller().program(),
            ),
            active_port: None,
        }
    }

    fn keep_alive_ms(&self) -> u32 {
        self.firmware.controller().settings().keep_alive_ms()
    }

    fn program_line(&mut self, index: u16) -> Option<String> {
        let mut buf = [0u8; forja_hal_abstraction::program::MAX_LINE_LEN];
        let store = self.firmware.controller_mut().program_mut();
        let len =
            forja_hal_abstraction::program::ProgramStore::read(store, index, &mut buf).ok()?;
        Some(String::from_utf8_lossy(buf.get(..len)?).into_owned())
    }

    fn stored(&mut self) -> Stored {
        let settings = self.firmware.controller().settings();
        let settings = Key::all::<N>()
            .map(|key| {
                let mut line = String::new();
                let _ = key.write_name(settings.machine(), &mut line);
                line.push('=');
                let _ = settings.write_value(key, &mut line);
                line
            })
            .collect();
        let store = self.firmware.controller().program();
        let len = forja_hal_abstraction::program::ProgramStore::len(store);
        let program_total = forja_hal_abstraction::program::ProgramStore::total(store);
        Stored {
            settings,
            ignored_settings: self.ignored_settings,
            program: (1..=len).map(|i| self.program_line(i)).collect(),
            program_total,
        }
    }

    fn into_flash(self: Box<Self>) -> Flash {
        let (_, program, _, settings) = self.firmware.into_controller().release();
        Flash {
            program: program.into_inner().into_flash(),
            settings: settings.into_flash(),
        }
    }
}

/// Settings of a [`SimBoard`].
#[derive(Debug)]
pub struct BoardConfig {
    /// Most lines the program store takes (at most 9999).
    pub program_lines: u16,
    /// The flash to start from: erased for a new board, or [`SimBoard::into_flash`] of a
    /// previous one (a restart keeps the settings and the program).
    pub flash: Flash,
}

impl Default for BoardConfig {
    fn default() -> Self {
        Self {
            program_lines: forja_hal_abstraction::program::MAX_LINES,
            flash: Flash::erased(),
        }
    }
}

/// The simulator board: the firmware on a [`SimMachine`]. Implements [`Firmware`] for
/// [`Simulation::run`]; [`SimBoard::run`] adds a host hook.
pub struct SimBoard {
    wiring: Box<dyn Wiring>,
    ports: Vec<Served>,
    arbiter: Arbiter,
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
        let f = config.flash;
        let l = config.program_lines;
        let wiring: Box<dyn Wiring> = match machine.axis_count() {
            1 => Box::new(Wired::<1>::new(machine, f, l)?),
            2 => Box::new(Wired::<2>::new(machine, f, l)?),
            3 => Box::new(Wired::<3>::new(machine, f, l)?),
            4 => Box::new(Wired::<4>::new(machine, f, l)?),
            5 => Box::new(Wired::<5>::new(machine, f, l)?),
            6 => Box::new(Wired::<6>::new(machine, f, l)?),
            7 => Box::new(Wired::<7>::new(machine, f, l)?),
            8 => Box::new(Wired::<8>::new(machine, f, l)?),
            n => return Err(BoardError::AxisCount(n)),
        };
        Ok(Self {
            wiring,
            ports: Vec::new(),
            arbiter: Arbiter {
                busy_message: default_busy_message(),
                ..Arbiter::default()
            },
            machine: machine.clone(),
        })
    }

    /// Serve `link`; `session`: greet each host with frame 54 and keep it alive with frame 55
    /// (TCP, like the ESP32's WiFi).
    ///
    /// Every port has its [`LinkSession`] (keep-alives every `keep_alive_ms` of the stored
    /// settings): a connection-oriented link ([`forja_sim_hal::link::TcpLink`]) admits and refuses
    /// clients through it ([`HostLink::admit`]), with or without frames. The port has no idle
    /// time-out until [`SimBoard::set_idle_timeout`].
    pub fn add_port(&mut self, link: impl Port, session: bool) -> PortId {
        let keep_alive = self.wiring.keep_alive_ms();
        self.ports.push(Served {
            link: Box::new(link),
            session: LinkSession::new(keep_alive),
            frames: session,
            seen: 0,
            fresh: false,
            failure: None,
            stats: PortStats::default(),
            refused: Decoder::new(),
        });
        PortId(self.ports.len() - 1)
    }

    /// The controlling host of port `id` loses control after `timeout_ms` of virtual time
    /// without a byte from it while the controller owes it nothing (see the
    /// [module documentation](self)); `None`: never. Takes effect for the next host.
    pub fn set_idle_timeout(&mut self, id: PortId, timeout_ms: Option<u32>) {
        if let Some(p) = self.ports.get_mut(id.0) {
            let keep_alive = self.wiring.keep_alive_ms();
            let session = LinkSession::new(keep_alive);
            p.session = match timeout_ms {
                Some(ms) => session.with_idle_timeout(ms),
                None => session,
            };
        }
    }

    /// What a host whose input is refused (another host is in control) is sent; by default
    /// [`default_busy_message`].
    pub fn set_busy_message(&mut self, message: impl Into<Vec<u8>>) {
        self.arbiter.busy_message = message.into();
    }

    /// What happened to the hosts of port `id`.
    pub fn port_stats(&self, id: PortId) -> Option<PortStats> {
        Some(self.ports.get(id.0)?.stats)
    }

    /// The link of a port, as its own type.
    pub fn port<T: Port>(&self, id: PortId) -> Option<&T> {
        let link: &dyn Any = &*self.ports.get(id.0)?.link;
        link.downcast_ref()
    }

    /// The link of a port, as its own type, mutably.
    pub fn port_mut<T: Port>(&mut self, id: PortId) -> Option<&mut T> {
        let link: &mut dyn Any = &mut *self.ports.get_mut(id.0)?.link;
        link.downcast_mut()
    }

    /// The first failure of a port's link (the listening socket or the terminal failed).
    pub fn port_failure(&self, id: PortId) -> Option<&str> {
        self.ports.get(id.0)?.failure.as_deref()
    }

    /// The machine.
    pub fn machine(&self) -> &SimMachine {
        &self.machine
    }

    /// What the firmware is doing.
    pub fn status(&self) -> BoardStatus {
        let mut s = self.wiring.status();
        s.active_port = self.arbiter.active.map(PortId);
        s
    }

    /// Line `index` (1-based) of the stored program.
    pub fn program_line(&mut self, index: u16) -> Option<String> {
        self.wiring.program_line(index)
    }

    /// The settings and the program the firmware keeps, as it read them when it started.
    pub fn stored(&mut self) -> Stored {
        self.wiring.stored()
    }

    /// Stop the board and take its flash, to start another on it (a restart).
    pub fn into_flash(self) -> Flash {
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
        sim.run(&mut Hooked { board: self, host })
    }
}

impl Firmware for SimBoard {
    fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        self.wiring.on_alarm(now)
    }

    fn poll(&mut self, now: Instant) -> Flow {
        self.wiring.poll(now, &mut self.ports, &mut self.arbiter);
        Flow::Continue
    }
}

struct Hooked<'a, H> {
    board: &'a mut SimBoard,
    host: H,
}

impl<H: FnMut(&mut SimBoard, Instant) -> Flow> Firmware for Hooked<'_, H> {
    fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
        self.board.on_alarm(now)
    }

    fn poll(&mut self, now: Instant) -> Flow {
        Firmware::poll(self.board, now);
        (self.host)(self.board, now)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_router_file_makes_a_kernel_configuration() {
        let file = MachineConfig::default_router();
        let k = kernel_config::<4>(&file).unwrap();
        let letters: Vec<u8> = k.axes.iter().map(|a| a.letter).collect();
        assert_eq!(letters, b"XYZA");
        let homing: Vec<_> = k.axes.iter().map(|a| a.homing).collect();
        // Switches numbered in axis order; Z first; A does not home and turns freely.
        assert_eq!(
            homing
                .iter()
                .map(|h| h.map(|h| (h.switch, h.order)))
                .collect::<Vec<_>>(),
            [Some((0, 1)), Some((1, 1)), Some((2, 0)), None]
        );
        assert_eq!(homing[2].map(|h| h.direction), Some(HomeDirection::Max));
        assert_eq!(
            (k.axes[3].min_mm, k.axes[3].max_mm),
            (-100_000.0, 100_000.0)
        );
        assert_eq!(k.axes[3].kind, KernelAxisKind::Rotary);
        assert_eq!(kernel_config::<3>(&file), Err(BoardError::AxisCount(4)));
        assert_eq!(slowest_timing(&file), StepTiming::CONSERVATIVE);
    }

    #[test]
    fn a_restart_keeps_the_flash() {
        let machine = SimMachine::new(&MachineConfig::default_router());
        let board = SimBoard::new(&machine, BoardConfig::default()).unwrap();
        assert_eq!(board.status().program_lines, 0);
        assert_eq!(board.status().state, MachineState::Idle);
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
