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
//! # Motion boards
//!
//! A board whose parts are STEP/DIR drivers, their motor power, limit switches, a settings
//! store, a program store and one host link (no heater, fan or spindle: the STM32F4 and
//! RP2040 boards) describes them once in a [`MotionParts`] and calls [`assemble_motion`]. It
//! gets its [`StepSide`] for the step interrupt and a [`LinkedFirmware`], the firmware on its
//! link, for its thread context:
//!
//! ```text
//!  MotionParts { machine, config,   ──► assemble_motion ──► (StepSide       ─► step interrupt,
//!    queue, tick_hz, steppers,                               LinkedFirmware ─► thread context)
//!    motors, switches, settings,
//!    program, link }
//!  thread context: LinkedFirmware::poll(now, news)
//!    polls the controller when `news` (the board's: a switch changed), bytes wait on the
//!    link (ReadReady), or wake_at has come
//! ```
//!
//! Context: init for [`assemble`] and [`assemble_motion`]; thread for [`Firmware`] and
//! [`LinkedFirmware`]. Nothing here blocks but what the storage and the link's writes do.

use core::fmt;
use embedded_io::{Read, ReadReady, Write};

use forja_hal_abstraction::files::FileStore;
use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::program::ProgramStore;
use forja_hal_abstraction::stepper::{Stepper, StepperEnable};
use forja_hal_abstraction::storage::RecordStorage;
use forja_hal_abstraction::time::Instant;
use forja_motion::{ConfigError, MachineConfig, StepGenerator, StepQueue, SwitchAlert};

use crate::controller::{
    Controller, ControllerConfig, LoadReport, Peripherals, PollOutcome, Settings,
};
use crate::peripherals::{MotorPeripherals, NoCard, NoLimit};
use crate::session::SessionAction;

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
    let (kernel, steps) = forja_motion::split(queue, *loaded.machine(), tick_hz, config.timing)?;
    let controller =
        Controller::with_settings(kernel, program, peripherals, config, loaded, settings);
    Ok((
        steps,
        Firmware {
            controller,
            wake_at: None,
            loaded: report,
        },
        report,
    ))
}

/// The thread side of an assembled firmware: the controller, and when it asked to be polled.
pub struct Firmware<'q, const N: usize, const B: usize, const Q: usize, P, X, S> {
    controller: Controller<'q, N, B, Q, P, X, S>,
    wake_at: Option<Instant>,
    /// What the settings load found in the storage at start-up.
    loaded: LoadReport,
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

    /// Whether the last poll left steps to prepare before the step queue holds its lead
    /// (`Kernel::needs_poll`): poll again at once, after the board's other work of the moment
    /// (`wake_at` is then the poll's own instant).
    pub fn needs_poll(&self) -> bool {
        self.controller.kernel().needs_poll()
    }

    /// Send what a link session asks of the controller (a board whose link has sessions:
    /// frames 54 and 55): announce the new controlling client, or send the keep-alive. A
    /// client the session refuses ([`Admit::Refuse`](crate::session::Admit::Refuse)) is
    /// refused by the link itself, where its connection is, with
    /// [`busy_refusal`](crate::controller::busy_refusal): one refusal for every board.
    pub fn session<W: Write>(&mut self, action: SessionAction, link: &mut W) {
        match action {
            SessionAction::SendConnected => self.controller.on_connect(link),
            SessionAction::SendKeepAlive(n) => self.controller.keep_alive(n, link),
        }
    }

    /// The controller, for what a board reads of it (its statistics, its settings).
    pub fn controller(&self) -> &Controller<'q, N, B, Q, P, X, S> {
        &self.controller
    }

    /// What [`assemble`] found in the settings storage: the stored values it applied and those
    /// it ignored.
    pub fn load_report(&self) -> LoadReport {
        self.loaded
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

/// What a motion board hands to [`assemble_motion`]: its machine, the drivers and switches of
/// its step interrupt, its motor power, its two stores, its card if it has one, and its host
/// link. A board that has nothing else (no heater, fan or spindle) describes itself in this
/// one value.
pub struct MotionParts<'q, const N: usize, const Q: usize, const K: usize, T, M, L, P, S, W, C> {
    /// The board's machine, before the stored settings are applied over it.
    pub machine: MachineConfig<N>,
    /// The controller's configuration (the drivers' step timing is its `timing`).
    pub config: ControllerConfig,
    /// The step queue between the kernel and the step interrupt, for the life of the firmware.
    pub queue: &'q mut StepQueue<N, Q>,
    /// The step clock's rate, ticks a second.
    pub tick_hz: u32,
    /// The STEP/DIR drivers, in axis order, for the step interrupt.
    pub steppers: [T; N],
    /// The motors' power (their enable lines), for the thread side.
    pub motors: M,
    /// The limit switches, in limit input order, for the step interrupt.
    pub switches: [L; K],
    /// Where the settings are kept.
    pub settings: S,
    /// Where the uploaded program is kept.
    pub program: P,
    /// The host link.
    pub link: W,
    /// The file store of the SD-card commands (`None::<NoCard>` for none).
    pub files: Option<C>,
}

/// The thread side of a motion board: its [`Firmware`] with [`MotorPeripherals`], and `C` its
/// card ([`NoCard`]: none).
pub type MotionFirmware<
    'q,
    const N: usize,
    const B: usize,
    const Q: usize,
    P,
    M,
    S,
    W,
    C = NoCard,
> = LinkedFirmware<'q, N, B, Q, P, MotorPeripherals<M, N, NoLimit, C>, S, W>;

/// Build a motion board's firmware from its [`MotionParts`]: [`assemble`] over
/// [`MotorPeripherals`] (motor power only), the step generator joined to the drivers and
/// switches in a [`StepSide`], the firmware joined to the host link in a [`LinkedFirmware`].
/// Stored values that cannot be used are skipped, as by [`assemble`].
///
/// Context: init, once. Errors: [`SetupError::Machine`] when the kernel refuses the machine
/// (the board's, with the stored settings) at this clock rate and step timing.
#[allow(clippy::type_complexity)]
pub fn assemble_motion<
    'q,
    const N: usize,
    const B: usize,
    const Q: usize,
    const K: usize,
    T,
    M,
    L,
    P,
    S,
    W,
    C,
>(
    parts: MotionParts<'q, N, Q, K, T, M, L, P, S, W, C>,
) -> Result<
    (
        StepSide<'q, N, Q, T, L, K>,
        MotionFirmware<'q, N, B, Q, P, M, S, W, C>,
    ),
    SetupError,
>
where
    T: Stepper,
    M: StepperEnable,
    L: LimitSwitch,
    P: ProgramStore,
    S: RecordStorage,
    W: Read + ReadReady + Write,
    C: FileStore,
{
    let peripherals = MotorPeripherals {
        motors: parts.motors,
        endstops: [None; N],
        files: parts.files,
    };
    let (generator, firmware, _) = assemble(Parts {
        machine: parts.machine,
        settings: parts.settings,
        queue: parts.queue,
        tick_hz: parts.tick_hz,
        config: parts.config,
        program: parts.program,
        peripherals,
    })
    .map_err(|_| SetupError::Machine)?;
    Ok((
        StepSide::new(generator, parts.steppers, parts.switches),
        LinkedFirmware::new(firmware, parts.link),
    ))
}

/// A [`Firmware`] on its host link: the thread side of a board with one link, which the link
/// itself tells of the bytes that wait on it.
pub struct LinkedFirmware<'q, const N: usize, const B: usize, const Q: usize, P, X, S, W> {
    firmware: Firmware<'q, N, B, Q, P, X, S>,
    link: W,
}

impl<'q, const N: usize, const B: usize, const Q: usize, P, X, S, W>
    LinkedFirmware<'q, N, B, Q, P, X, S, W>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
    W: Read + ReadReady + Write,
{
    /// `firmware` on `link`.
    pub fn new(firmware: Firmware<'q, N, B, Q, P, X, S>, link: W) -> Self {
        Self { firmware, link }
    }

    /// Announce the start (`start`) on the link. Call once the link is up.
    ///
    /// Context: init or thread.
    pub fn boot(&mut self) {
        self.firmware.boot(&mut self.link);
    }

    /// Poll the firmware at `now` when there is news or its [`wake_at`](Self::wake_at) has
    /// come: the news is `news` (the board's: a switch changed) or bytes waiting on the link
    /// (`ReadReady`; a link that cannot tell counts as news). Returns where to arm the step
    /// alarm, if anywhere.
    ///
    /// Context: thread. Never blocks, except to queue replies on a full link.
    pub fn poll(&mut self, now: Instant, news: bool) -> Option<Instant> {
        let news = news || self.link.read_ready().unwrap_or(true);
        self.firmware.poll(now, &mut self.link, news)
    }

    /// The latest instant to poll again at (sooner when there is news); `None` when nothing is
    /// timed.
    pub fn wake_at(&self) -> Option<Instant> {
        self.firmware.wake_at()
    }

    /// See [`Firmware::needs_poll`].
    pub fn needs_poll(&self) -> bool {
        self.firmware.needs_poll()
    }

    /// The firmware, for what a board reads of it (its controller's statistics).
    pub fn firmware(&self) -> &Firmware<'q, N, B, Q, P, X, S> {
        &self.firmware
    }

    /// The link, for what a board reads of it (its counters).
    pub fn link(&self) -> &W {
        &self.link
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

#[cfg(test)]
mod tests {
    use std::cell::Cell;
    use std::collections::VecDeque;
    use std::rc::Rc;
    use std::vec::Vec;

    use core::convert::Infallible;
    use forja_hal_abstraction::ErrorType;
    use forja_hal_abstraction::files::RamFileStore;
    use forja_hal_abstraction::program::RamStore;
    use forja_hal_abstraction::stepper::{Direction, StepTiming};
    use forja_motion::{AxisConfig, HomeDirection, HomingConfig};

    use super::*;
    use crate::controller::Key;
    use crate::controller::settings::tests::VecStorage;
    use crate::peripherals::MotorEnables;

    const TICK_HZ: u32 = 1_000_000;

    /// A link in memory whose `ReadReady` says "nothing" the next `hides` times it is asked.
    #[derive(Default)]
    struct MemLink {
        rx: VecDeque<u8>,
        tx: Vec<u8>,
        hides: u32,
    }

    impl MemLink {
        fn replies(&mut self) -> std::string::String {
            std::string::String::from_utf8(core::mem::take(&mut self.tx)).unwrap()
        }
    }

    impl embedded_io::ErrorType for MemLink {
        type Error = Infallible;
    }

    impl Read for MemLink {
        fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
            let n = buf.len().min(self.rx.len());
            for (d, s) in buf.iter_mut().zip(self.rx.drain(..n)) {
                *d = s;
            }
            Ok(n)
        }
    }

    impl ReadReady for MemLink {
        fn read_ready(&mut self) -> Result<bool, Infallible> {
            if self.hides > 0 {
                self.hides -= 1;
                return Ok(false);
            }
            Ok(!self.rx.is_empty())
        }
    }

    impl Write for MemLink {
        fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
            self.tx.extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> Result<(), Infallible> {
            Ok(())
        }
    }

    /// A driver that counts its step pulses.
    struct Counting(Rc<Cell<u32>>);

    impl ErrorType for Counting {
        type Error = Infallible;
    }

    impl Stepper for Counting {
        fn set_direction(&mut self, _: Direction) -> Result<(), Infallible> {
            Ok(())
        }
        fn step_begin(&mut self) -> Result<(), Infallible> {
            self.0.set(self.0.get() + 1);
            Ok(())
        }
        fn step_end(&mut self) -> Result<(), Infallible> {
            Ok(())
        }
        fn timing(&self) -> StepTiming {
            StepTiming::CONSERVATIVE
        }
    }

    /// A switch, hit while its cell is set.
    struct Switch(Rc<Cell<bool>>);

    impl ErrorType for Switch {
        type Error = Infallible;
    }

    impl LimitSwitch for Switch {
        fn is_triggered(&mut self) -> Result<bool, Infallible> {
            Ok(self.0.get())
        }
    }

    /// The motors' power.
    struct Power(Rc<Cell<bool>>);

    impl ErrorType for Power {
        type Error = Infallible;
    }

    impl StepperEnable for Power {
        fn set_enabled(&mut self, enabled: bool) -> Result<(), Infallible> {
            self.0.set(enabled);
            Ok(())
        }
    }

    type Board<'q> = (
        StepSide<'q, 2, 256, Counting, Switch, 1>,
        MotionFirmware<
            'q,
            2,
            8,
            256,
            RamStore<4>,
            MotorEnables<Power, 1>,
            VecStorage,
            MemLink,
            RamFileStore<1024, 2>,
        >,
    );

    /// What a test watches of the board: X's steps, the motors' power, the switch at X's
    /// maximum.
    struct Watch {
        steps: Rc<Cell<u32>>,
        power: Rc<Cell<bool>>,
        hit: Rc<Cell<bool>>,
    }

    /// A two-axis motion board with a switch at the maximum of X.
    fn board(queue: &mut StepQueue<2, 256>) -> (Board<'_>, Watch) {
        let watch = Watch {
            steps: Rc::new(Cell::new(0)),
            power: Rc::new(Cell::new(false)),
            hit: Rc::new(Cell::new(false)),
        };
        let x_home = HomingConfig {
            direction: HomeDirection::Max,
            seek_mm_min: 1000.0,
            locate_mm_min: 100.0,
            pull_off_mm: 1.0,
            switch: 0,
            order: 0,
        };
        let parts = assemble_motion(MotionParts {
            machine: MachineConfig::new([
                AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 200.0).with_homing(x_home),
                AxisConfig::linear(b'Y', 80.0, 6000.0, 500.0, 200.0),
            ]),
            config: ControllerConfig::new("cnc", StepTiming::CONSERVATIVE),
            queue,
            tick_hz: TICK_HZ,
            steppers: [
                Counting(watch.steps.clone()),
                Counting(Rc::new(Cell::new(0))),
            ],
            motors: MotorEnables([Power(watch.power.clone())]),
            switches: [Switch(watch.hit.clone())],
            settings: VecStorage::default(),
            program: RamStore::new(),
            link: MemLink::default(),
            files: Some(RamFileStore::new()),
        })
        .unwrap();
        (parts, watch)
    }

    /// Run the thread side and the step interrupt as a board does, from `now` in steps of
    /// 100 µs, until `done` or 2 s have passed; the last instant polled and the alarm armed.
    fn run(
        (step, fw): &mut Board<'_>,
        mut now: Instant,
        mut alarm: Option<Instant>,
        done: impl Fn() -> bool,
    ) -> (Instant, Option<Instant>) {
        for _ in 0..20_000 {
            if let Some(at) = fw.poll(now, false) {
                alarm = Some(at);
            }
            while let Some(at) = alarm.filter(|at| now.is_at_or_after(*at)) {
                alarm = step.on_alarm(at);
            }
            if done() {
                break;
            }
            now = now.wrapping_add(forja_hal_abstraction::time::Duration::from_ticks(100));
        }
        (now, alarm)
    }

    /// One millisecond of the step clock.
    fn ms(n: u32) -> forja_hal_abstraction::time::Duration {
        forja_hal_abstraction::time::Duration::from_ticks(n * TICK_HZ / 1_000)
    }

    #[test]
    fn a_motion_board_boots_moves_and_powers_its_motors() {
        let mut queue = StepQueue::new();
        let (mut b, watch) = board(&mut queue);
        b.1.boot();
        assert!(b.1.link.replies().starts_with("start"));
        b.1.link.rx.extend(b"G1 X1 F600\n");
        run(&mut b, Instant::from_ticks(0), None, || false);
        assert!(watch.power.get(), "motors energised for the motion");
        assert_eq!(watch.steps.get(), 80, "1 mm of X at 80 steps/mm");
        assert!(b.1.link.replies().contains("ok"));
        assert_eq!(b.1.firmware().controller().stats().oks, 1);
        // Its card holds what `M28` uploads.
        b.1.link.rx.extend(b"M28 a.g\nG1 X2\nM29\nM20\n");
        run(&mut b, Instant::from_ticks(0), None, || false);
        let replies = b.1.link.replies();
        assert!(replies.contains("Done saving file."), "{replies}");
        assert!(replies.contains("a.g 6"), "{replies}");
    }

    #[test]
    fn a_board_reads_back_its_status_its_settings_load_and_its_program() {
        let machine = MachineConfig::new([AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 200.0)]);
        // One stored value that no longer validates: ignored at start-up, and said so.
        let mut settings = VecStorage::default();
        let mut buf = [0u8; 8];
        let bad = postcard::to_slice(&-1f32, &mut buf).unwrap().to_vec();
        settings.records.push((Key::JogFeed.record(&machine), bad));
        let mut program = RamStore::<4>::new();
        program.begin(3).unwrap();
        program.store(1, b"G90").unwrap();
        program.store(2, b"G1 X1").unwrap();
        let mut queue = StepQueue::<1, 256>::new();
        let (_, mut fw, report) = assemble::<1, 8, 256, _, _, _>(Parts {
            machine,
            settings,
            queue: &mut queue,
            tick_hz: TICK_HZ,
            config: ControllerConfig::new("cnc", StepTiming::CONSERVATIVE),
            program,
            peripherals: crate::controller::NoPeripherals,
        })
        .unwrap();
        assert_eq!(fw.load_report(), report);
        assert_eq!(report.ignored, 1);

        let status = fw.controller().status();
        assert!(status.idle && !status.holding);
        assert_eq!(status.state, forja_motion::MachineState::Idle);
        assert_eq!((status.program_lines, status.program_total), (2, 3));
        assert_eq!(status.homed, 0);
        assert_eq!(status.stats, fw.controller().stats());

        let mut line = [0u8; forja_hal_abstraction::program::MAX_LINE_LEN];
        let c = fw.controller_mut();
        assert_eq!(c.read_program_line(2, &mut line), Some("G1 X1"));
        assert_eq!(c.read_program_line(3, &mut line), None, "not stored yet");
    }

    #[test]
    fn bytes_on_the_link_are_news_before_wake_at() {
        let mut queue = StepQueue::new();
        let ((_, mut fw), _) = board(&mut queue);
        fw.boot();
        let t0 = Instant::from_ticks(0);
        fw.poll(t0, true);
        let wake = fw.wake_at().expect("a timed poll");
        let t1 = t0.wrapping_add(ms(1));
        assert!(!t1.is_at_or_after(wake));
        fw.link.replies();

        // The link does not tell of the line and the board has no news: not polled.
        fw.link.rx.extend(b"M17\n");
        fw.link.hides = 1;
        assert_eq!(fw.poll(t1, false), None);
        assert!(fw.link.replies().is_empty());
        // It tells: the line is answered before wake_at.
        fw.poll(t1, false);
        assert!(fw.link.replies().contains("ok"));
    }

    #[test]
    fn the_boards_flag_is_news_a_switch_hit_is_reported_before_wake_at() {
        let mut queue = StepQueue::new();
        let (mut b, watch) = board(&mut queue);
        b.1.boot();
        b.1.link.rx.extend(b"G1 X100 F3000\n");
        let steps = watch.steps.clone();
        let (now, alarm) = run(&mut b, Instant::from_ticks(0), None, || steps.get() >= 400);
        assert!(watch.steps.get() >= 400, "the move went on");
        b.1.link.replies();

        // The switch at X's maximum closes: its interrupt tells the step interrupt, which
        // stops at its next alarm.
        watch.hit.set(true);
        b.0.switch_alert().notify();
        let mut alarm = alarm;
        while let Some(at) = alarm {
            alarm = b.0.on_alarm(at);
        }
        let stopped_at = watch.steps.get();
        assert!(stopped_at < 8_000, "stopped before the end of the move");

        // Nothing on the link and no news from the board: the controller does not hear of it
        // before its wake_at.
        let wake = b.1.wake_at().expect("a timed poll while moving");
        assert!(!now.is_at_or_after(wake));
        assert_eq!(b.1.poll(now, false), None);
        assert!(b.1.link.replies().is_empty());
        // The board's flag (its switch lines fired): polled now, the stop is reported.
        b.1.poll(now, true);
        assert!(!b.1.link.replies().is_empty());
    }
}
