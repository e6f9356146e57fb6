//! The kernel bench program, chip-independent: each bench image (the STM32F4's
//! `kernel_bench` example, the RP2040's, `bench/riscv32`) includes this file as a module and
//! calls [`run`] from its entry point, with the chip's vector table or start-up linked in.
//! `cargo xtask bench` builds each image with its firmware's release profile and runs it in
//! an instruction-counting emulator (`xtask/scripts/count_insns.py`), which finds the marker
//! functions below in the symbol table and counts the instructions executed from each one's
//! first instruction to its return. Nothing here touches a peripheral: the step and
//! direction lines are the firmware's own drivers (`StepDir`, `LimitInput`) over pins whose
//! register accesses go to statics: one volatile store per edge, one volatile load per switch
//! sample, as on a GPIO's BSRR and IDR.
//!
//! | marker | what one call runs |
//! |---|---|
//! | [`bench_isr`] | `StepGenerator::on_alarm`: one interrupt's worth of step events, pins and switch samples included |
//! | [`bench_prep`] | `Kernel::poll`: segment preparation (thread side) |
//! | [`bench_line`] | `Line::parse_in` and `Kernel::execute` of one G-code line: parse, interpret, plan |
//!
//! The program runs three phases, each announced by [`bench_phase`] and closed by
//! [`bench_result`] with its counts of step events and lines:
//!
//! 1. one axis moving: `G1 X200 F12000` (16,000 steps, X at up to 16 kHz);
//! 2. three axes moving: `G1 X300 Y80 Z10 F6000` (18,400 steps on X, Y and Z at once);
//! 3. a path of 1,000 lines of 1 mm `G1` segments along a slowly turning curve at
//!    6,000 mm/min, each line parsed, interpreted and planned as it is taken.
//!
//! Every axis has a limit switch at its maximum with hard limits on, and every move goes
//! towards them. As on the board, the interrupt samples every switch at the start of each
//! motion, until all read released and settled (the largest calls of the table), and then
//! only after an edge is reported by the switch lines' EXTI interrupt (none here: the
//! switches stay released).
//! The machine is the one of the host benchmarks (`motion/benches/kernel.rs`); the step
//! clock runs at the Black Pill's 8 MHz.

use core::convert::Infallible;
use core::fmt::Write as _;
use core::hint::black_box;
use core::panic::PanicInfo;
use core::sync::atomic::AtomicU32;

use embedded_hal::digital::{ErrorType, InputPin, OutputPin};
use forja_drivers::limit::{LimitConfig, LimitInput, Polarity};
use forja_drivers::pin::NoPin;
use forja_drivers::stepper::{StepDir, StepDirConfig};
use forja_hal_abstraction::stepper::StepTiming;
use forja_hal_abstraction::time::Instant;
use forja_motion::{
    AxisConfig, HomeDirection, HomingConfig, Kernel, MachineConfig, Reply, StepGenerator,
    StepQueue, split,
};
use forja_protocol::gcode::Line;

/// Axes of the bench machine.
const AXES: usize = 3;
/// Step queue depth (the kernel's default).
const QUEUE: usize = 256;
/// Planner depth (the kernel's default).
const BLOCKS: usize = 32;
/// The step clock: the Black Pill's TIM2 rate.
const TICK_HZ: u32 = 8_000_000;
/// Machine time between two runs of the thread side (the firmware's 1 kHz service tick).
const POLL_TICKS: u32 = TICK_HZ / 1000;
/// Lines of the 1 mm path.
const PATH_LINES: u32 = 1000;

/// Stands in for a GPIO port's bit set/reset register: every edge is one volatile store to
/// it, as to the register (so that the compiler keeps every one).
static GPIO_BSRR: AtomicU32 = AtomicU32::new(0);
/// Stands in for a GPIO port's input data register: every switch sample is one volatile load
/// of it. It stays 0, all switch inputs low: released.
static GPIO_IDR: AtomicU32 = AtomicU32::new(0);

/// A volatile store to `register`, as a GPIO register write.
#[inline]
fn write_register(register: &AtomicU32, value: u32) {
    // SAFETY: the pointer comes from a live, aligned static, and nothing else accesses the
    // static at the same time (the bench runs on one core without interrupts).
    unsafe { register.as_ptr().write_volatile(value) }
}

/// A volatile load of `register`, as a GPIO register read.
#[inline]
fn read_register(register: &AtomicU32) -> u32 {
    // SAFETY: as in `write_register`.
    unsafe { register.as_ptr().read_volatile() }
}

/// An output line written through [`GPIO_BSRR`], as `stm32f4xx-hal` writes BSRR.
struct RegPin {
    mask: u32,
}

impl ErrorType for RegPin {
    type Error = Infallible;
}

impl OutputPin for RegPin {
    #[inline]
    fn set_low(&mut self) -> Result<(), Infallible> {
        write_register(&GPIO_BSRR, self.mask << 16);
        Ok(())
    }

    #[inline]
    fn set_high(&mut self) -> Result<(), Infallible> {
        write_register(&GPIO_BSRR, self.mask);
        Ok(())
    }
}

/// An input line read from [`GPIO_IDR`].
struct RegInput {
    mask: u32,
}

impl ErrorType for RegInput {
    type Error = Infallible;
}

impl InputPin for RegInput {
    #[inline]
    fn is_high(&mut self) -> Result<bool, Infallible> {
        Ok(read_register(&GPIO_IDR) & self.mask != 0)
    }

    #[inline]
    fn is_low(&mut self) -> Result<bool, Infallible> {
        self.is_high().map(|h| !h)
    }
}

/// The firmware's motor driver type, on register-backed pins.
type Stepper = StepDir<RegPin, RegPin, NoPin>;
/// The firmware's limit switch type, on a register-backed input.
type Switch = LimitInput<RegInput>;
/// The interrupt side of the bench machine.
type Isr = StepGenerator<'static, AXES, QUEUE>;
/// The thread side of the bench machine.
type Thread = Kernel<'static, AXES, BLOCKS, QUEUE>;

/// Marker: one step interrupt.
#[unsafe(no_mangle)]
#[inline(never)]
fn bench_isr(
    isr: &mut Isr,
    at: Instant,
    steppers: &mut [Stepper; AXES],
    switches: &mut [Switch; AXES],
) -> Option<Instant> {
    isr.on_alarm(at, steppers, switches)
}

/// Marker: one run of the thread side's segment preparation.
#[unsafe(no_mangle)]
#[inline(never)]
fn bench_prep(kernel: &mut Thread, now: Instant) -> Option<Instant> {
    kernel.poll(now)
}

/// Marker: parse, interpret and plan one line. `false` when the kernel answered `Busy`.
#[unsafe(no_mangle)]
#[inline(never)]
fn bench_line(kernel: &mut Thread, text: &[u8]) -> bool {
    let mut line = Line::empty();
    match line.parse_in(text) {
        Ok(()) => !matches!(kernel.execute(&line), Ok(Reply::Busy)),
        Err(_) => true,
    }
}

/// Marker: the following marker calls belong to phase `phase` (read from its argument).
#[unsafe(no_mangle)]
#[inline(never)]
fn bench_phase(phase: u32) {
    black_box(phase);
}

/// Marker: phase `phase` is over; it made `step_events` steps and took `lines` lines (read
/// from its arguments).
#[unsafe(no_mangle)]
#[inline(never)]
fn bench_result(phase: u32, step_events: u32, lines: u32) {
    black_box((phase, step_events, lines));
}

/// Marker: the bench is over (the counter stops here).
#[unsafe(no_mangle)]
#[inline(never)]
fn bench_done() -> ! {
    loop {
        black_box(0u32);
        core::hint::spin_loop();
    }
}

/// Marker: the bench failed (a panic, or a kernel that refused its set-up).
#[unsafe(no_mangle)]
#[inline(never)]
fn bench_failed() -> ! {
    loop {
        black_box(1u32);
        core::hint::spin_loop();
    }
}

#[panic_handler]
fn panic(_: &PanicInfo) -> ! {
    bench_failed()
}

/// A linear axis of the host benchmarks' machine, homing to a switch at its maximum.
fn axis(letter: u8, steps_per_mm: f32, rate: f32, accel: f32, switch: u8) -> AxisConfig {
    AxisConfig::linear(letter, steps_per_mm, rate, accel, 1000.0).with_homing(HomingConfig {
        direction: HomeDirection::Max,
        seek_mm_min: rate / 2.0,
        locate_mm_min: rate / 20.0,
        pull_off_mm: 1.0,
        switch,
        order: switch,
    })
}

/// The thread and interrupt sides with their pins, and the simulated time.
struct Bench {
    kernel: Thread,
    isr: Isr,
    steppers: [Stepper; AXES],
    switches: [Switch; AXES],
    now: u32,
    alarm: Option<Instant>,
    steps: u32,
}

impl Bench {
    /// Run the interrupt side up to the next poll, then poll: what the firmware does in one
    /// service period. Counts the steps made.
    fn run_period(&mut self) {
        let until = Instant::from_ticks(self.now.wrapping_add(POLL_TICKS));
        while let Some(at) = self.alarm {
            if at.signed_ticks_since(until) > 0 {
                break;
            }
            let before = self.isr.positions();
            self.alarm = bench_isr(&mut self.isr, at, &mut self.steppers, &mut self.switches);
            let after = self.isr.positions();
            for (a, b) in after.iter().zip(before.iter()) {
                self.steps = self.steps.wrapping_add(a.wrapping_sub(*b).unsigned_abs());
            }
        }
        self.now = until.ticks();
        self.poll();
    }

    /// The thread loop's turn: the thread side, again at once while it has steps left to
    /// prepare, as the firmware's loop does.
    fn poll(&mut self) {
        loop {
            if let Some(at) = bench_prep(&mut self.kernel, Instant::from_ticks(self.now)) {
                self.alarm = Some(at);
            }
            if !self.kernel.needs_poll() {
                break;
            }
        }
    }

    /// Run phase `phase`: feed `lines` as the kernel takes them, until the machine is at rest.
    fn phase(&mut self, phase: u32, lines: &mut dyn FnMut(&mut LineText) -> bool) {
        bench_phase(phase);
        self.steps = 0;
        let mut taken = 0u32;
        let mut text = LineText::new();
        let mut pending = lines(&mut text);
        loop {
            // As the firmware's loop (`Controller::poll`): the thread side runs again in the
            // same period only when a line was taken.
            let mut took = false;
            while pending && self.kernel.can_accept() {
                if !bench_line(&mut self.kernel, text.bytes()) {
                    break;
                }
                taken += 1;
                took = true;
                text.clear();
                pending = lines(&mut text);
            }
            if took {
                self.poll();
            }
            self.run_period();
            if !pending && self.kernel.is_idle() {
                break;
            }
        }
        bench_result(phase, self.steps, taken);
    }
}

/// One G-code line being written.
struct LineText {
    buf: [u8; 48],
    len: usize,
}

impl LineText {
    fn new() -> Self {
        Self {
            buf: [0; 48],
            len: 0,
        }
    }

    fn clear(&mut self) {
        self.len = 0;
    }

    fn bytes(&self) -> &[u8] {
        self.buf.get(..self.len).unwrap_or_default()
    }
}

impl core::fmt::Write for LineText {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        let end = self.len + s.len();
        let dst = self.buf.get_mut(self.len..end).ok_or(core::fmt::Error)?;
        dst.copy_from_slice(s.as_bytes());
        self.len = end;
        Ok(())
    }
}

/// Writes `x` (mm) with three decimals.
fn write_mm(out: &mut LineText, letter: char, x: f64) -> core::fmt::Result {
    let um = (x * 1000.0 + 0.5) as u32;
    write!(out, " {letter}{}.{:03}", um / 1000, um % 1000)
}

/// Static lines, one after another.
fn fixed<'a>(lines: &'a [&'a str]) -> impl FnMut(&mut LineText) -> bool + 'a {
    let mut next = 0;
    move |out| match lines.get(next) {
        Some(l) => {
            next += 1;
            out.write_str(l).is_ok()
        }
        None => false,
    }
}

/// The step queue of the bench machine, which the image's entry point allocates statically.
pub type Queue = StepQueue<AXES, QUEUE>;

/// The bench program: the three phases, then [`bench_done`]. Called once, from the image's
/// entry point.
pub fn run(queue: &'static mut Queue) -> ! {
    let config = MachineConfig::new([
        axis(b'X', 80.0, 12_000.0, 3000.0, 0),
        axis(b'Y', 80.0, 12_000.0, 3000.0, 1),
        axis(b'Z', 400.0, 900.0, 200.0, 2),
    ]);
    let timing = StepTiming::CONSERVATIVE;
    let Ok((kernel, isr)) = split::<AXES, BLOCKS, QUEUE>(queue, config, TICK_HZ, timing) else {
        bench_failed()
    };
    let driver = StepDirConfig::new(timing);
    let stepper = |n: u32| {
        StepDir::new(
            RegPin { mask: 1 << n },
            RegPin { mask: 1 << (n + 8) },
            driver,
        )
        .unwrap_or_else(|_| bench_failed())
    };
    let limit = LimitConfig::new(Polarity::NormallyClosed, 3);
    let switch = |n: u32| LimitInput::new(RegInput { mask: 1 << n }, limit);
    let mut bench = Bench {
        kernel,
        isr,
        steppers: [stepper(0), stepper(1), stepper(2)],
        switches: [switch(0), switch(1), switch(2)],
        now: 0,
        alarm: None,
        steps: 0,
    };

    bench.phase(1, &mut fixed(&["G1 X200 F12000"]));
    bench.phase(2, &mut fixed(&["G1 X300 Y80 Z10 F6000"]));

    // A curve turning by 0.05 rad per 1 mm segment (a circle of 20 mm radius), as in the host
    // benchmarks; the rotation is a recurrence so that no trigonometry runs on the target.
    let (cos_step, sin_step) = (0.998_750_260_394_966_3_f64, 0.049_979_169_270_678_33_f64);
    let (mut x, mut y) = (300.0f64, 80.0f64);
    let (mut c, mut s) = (1.0f64, 0.0f64);
    let mut k = 0;
    bench.phase(3, &mut |out: &mut LineText| {
        if k == PATH_LINES {
            return false;
        }
        k += 1;
        x += c;
        y += s;
        (c, s) = (c * cos_step - s * sin_step, s * cos_step + c * sin_step);
        out.write_str("G1").is_ok()
            && write_mm(out, 'X', x).is_ok()
            && write_mm(out, 'Y', y).is_ok()
            && out.write_str(" F6000").is_ok()
    });
    bench_done()
}
