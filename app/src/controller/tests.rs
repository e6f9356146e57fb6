//! Host tests of the controller: a kernel on the simulated interrupt side, an in-memory link,
//! fake peripherals and a virtual clock. Every rule of the reply policy has a test here.

use std::boxed::Box;
use std::collections::VecDeque;
use std::format;
use std::string::{String, ToString};
use std::vec::Vec;

use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::stepper::StepTiming;
use forja_protocol::frame::{Action, ClientMessage, ControllerMessage, FRAME_LEN};
use forja_protocol::gcode::{Decimal, checksum, write_numbered};

use super::settings::tests::VecStorage;
use super::*;
use crate::job::JobState;
use forja_hal_abstraction::device::{
    Beeper, CoolantControl, DeviceError, DigitalOutput, FanControl, Rotation, SpindleControl,
    TemperatureControl,
};
use forja_hal_abstraction::files::{FileStore, RamFileStore};
use forja_hal_abstraction::program::{ProgramStore, RamStore};
use forja_motion::StepQueue;
use forja_motion::config::{AxisConfig, HomeDirection, HomingConfig, MachineConfig};
use forja_motion::{MachineState, split};
use forja_sim_hal::SimLimitSwitch;

#[path = "../../../motion/tests/common/bench.rs"]
#[allow(dead_code)]
mod bench;
use bench::Wiring;

mod files;
mod grbl;
mod marlin;
mod numbering;
mod programs;
mod realtime;

const TICK_HZ: u32 = 1_000_000;

/// An in-memory link: what the host sent, what the controller wrote.
#[derive(Default)]
struct MemLink {
    rx: VecDeque<u8>,
    tx: Vec<u8>,
}

impl embedded_io::ErrorType for MemLink {
    type Error = core::convert::Infallible;
}

impl embedded_io::Read for MemLink {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = buf.len().min(self.rx.len());
        for (d, s) in buf.iter_mut().zip(self.rx.drain(..n)) {
            *d = s;
        }
        Ok(n)
    }
}

impl embedded_io::ReadReady for MemLink {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        Ok(!self.rx.is_empty())
    }
}

impl embedded_io::Write for MemLink {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.tx.extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// A heater that moves 20 °C a second towards its target (from 20 °C ambient) and latches a
/// fault the test hands it at its next loop.
struct FakeZone {
    current_mc: i32,
    target_mc: i32,
    last_ms: Option<u32>,
    /// A fault for the next loop to find.
    pending: Option<DeviceError>,
    latched: Option<DeviceError>,
}

impl FakeZone {
    fn ambient() -> Self {
        Self {
            current_mc: 20_000,
            target_mc: 0,
            last_ms: None,
            pending: None,
            latched: None,
        }
    }
}

impl TemperatureControl for FakeZone {
    fn set_target_mc(&mut self, mc: i32) -> Result<(), DeviceError> {
        if let Some(e) = self.latched {
            return Err(e);
        }
        if mc > 280_000 {
            return Err(DeviceError::OutOfRange);
        }
        self.target_mc = mc.max(0);
        Ok(())
    }
    fn target_mc(&self) -> i32 {
        self.target_mc
    }
    fn current_mc(&self) -> Option<i32> {
        Some(self.current_mc)
    }
    fn power(&self) -> u16 {
        if self.target_mc > self.current_mc {
            u16::MAX
        } else {
            0
        }
    }
    fn run(&mut self, now_ms: u32) -> Result<(), DeviceError> {
        let dt = self.last_ms.map_or(0, |l| now_ms.wrapping_sub(l)) as i32;
        self.last_ms = Some(now_ms);
        let goal = self.target_mc.max(20_000);
        let step = (20 * dt).min((goal - self.current_mc).abs());
        self.current_mc += step * (goal - self.current_mc).signum();
        if let Some(e) = self.pending.take() {
            self.latched = Some(e);
        }
        match self.latched {
            Some(e) => {
                // A fault turns the heater off and clears the target.
                self.target_mc = 0;
                Err(e)
            }
            None => Ok(()),
        }
    }
    fn fault(&self) -> Option<DeviceError> {
        self.latched
    }
    fn clear_fault(&mut self) {
        self.latched = None;
    }
}

/// An output that records whether it is on.
#[derive(Default)]
struct FakeOutput(bool);

impl DigitalOutput for FakeOutput {
    fn set_on(&mut self, on: bool) -> Result<(), DeviceError> {
        self.0 = on;
        Ok(())
    }
}

/// A beeper that records the tones handed to it, in order.
#[derive(Default)]
struct FakeBeeper(Vec<(u16, u16)>);

impl Beeper for FakeBeeper {
    fn tone(&mut self, frequency_hz: u16, duration_ms: u16) -> Result<(), DeviceError> {
        self.0.push((frequency_hz, duration_ms));
        Ok(())
    }
}

/// A fan that records its duty.
struct FakeFan(u8);

impl FanControl for FakeFan {
    fn set_duty(&mut self, duty: u8) -> Result<(), DeviceError> {
        self.0 = duty;
        Ok(())
    }
}

/// What the spindle was last told.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Turning {
    At(Rotation, u32),
    Stopped,
}

/// A spindle that records what it is told and counts its stops.
#[derive(Default)]
struct FakeSpindle {
    last: Option<Turning>,
    stops: u32,
}

impl SpindleControl for FakeSpindle {
    fn run(&mut self, rotation: Rotation, rpm: u32) -> Result<(), DeviceError> {
        self.last = Some(Turning::At(rotation, rpm));
        Ok(())
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        self.last = Some(Turning::Stopped);
        self.stops += 1;
        Ok(())
    }
}

/// Coolant that records its two lines.
#[derive(Default)]
struct FakeCoolant {
    mist: bool,
    flood: bool,
}

impl CoolantControl for FakeCoolant {
    fn set_mist(&mut self, on: bool) -> Result<(), DeviceError> {
        self.mist = on;
        Ok(())
    }
    fn set_flood(&mut self, on: bool) -> Result<(), DeviceError> {
        self.flood = on;
        Ok(())
    }
}

/// The test board's SD card: 16 KiB for at most 8 files, in RAM.
type FakeCard = RamFileStore<16384, 8>;

/// The test board's devices: two heaters, two fans, outputs, a spindle, coolant and a beeper
/// that record what they are told, motor power, end-stops read from the simulated switches,
/// an SD card.
struct Fake {
    hot: FakeZone,
    bed: FakeZone,
    fans: [FakeFan; 2],
    /// `M42` outputs 0 and 1.
    outputs: [FakeOutput; 2],
    /// The power supply's switch (`M80`, `M81`).
    psu: FakeOutput,
    spindle: FakeSpindle,
    /// `None`: the board has no coolant.
    coolant: Option<FakeCoolant>,
    /// `None`: the board has no beeper.
    beeper: Option<FakeBeeper>,
    motors: bool,
    motor_calls: u32,
    switches: Vec<SimLimitSwitch>,
    /// `None`: the board has no card.
    card: Option<Box<FakeCard>>,
}

impl Fake {
    fn new(switches: Vec<SimLimitSwitch>) -> Self {
        Self {
            hot: FakeZone::ambient(),
            bed: FakeZone::ambient(),
            fans: [FakeFan(0), FakeFan(0)],
            outputs: [FakeOutput(false), FakeOutput(false)],
            psu: FakeOutput(false),
            spindle: FakeSpindle::default(),
            coolant: Some(FakeCoolant::default()),
            beeper: Some(FakeBeeper::default()),
            motors: false,
            motor_calls: 0,
            switches,
            card: Some(Box::new(FakeCard::new())),
        }
    }
}

impl Peripherals<3> for Fake {
    fn hot_end(&mut self) -> Option<&mut dyn TemperatureControl> {
        Some(&mut self.hot)
    }
    fn bed(&mut self) -> Option<&mut dyn TemperatureControl> {
        Some(&mut self.bed)
    }
    fn fan(&mut self, index: u8) -> Option<&mut dyn FanControl> {
        let fan = self.fans.get_mut(usize::from(index))?;
        Some(fan)
    }
    fn output(&mut self, index: u8) -> Option<&mut dyn DigitalOutput> {
        let output = self.outputs.get_mut(usize::from(index))?;
        Some(output)
    }
    fn power_supply(&mut self) -> Option<&mut dyn DigitalOutput> {
        Some(&mut self.psu)
    }
    fn spindle(&mut self) -> Option<&mut dyn SpindleControl> {
        Some(&mut self.spindle)
    }
    fn coolant(&mut self) -> Option<&mut dyn CoolantControl> {
        let coolant = self.coolant.as_mut()?;
        Some(coolant)
    }
    fn beeper(&mut self) -> Option<&mut dyn Beeper> {
        let beeper = self.beeper.as_mut()?;
        Some(beeper)
    }
    fn set_motors(&mut self, enabled: bool) -> Result<(), DeviceError> {
        self.motors = enabled;
        self.motor_calls += 1;
        Ok(())
    }
    fn endstop(&mut self, axis: usize) -> Option<bool> {
        self.switches.get_mut(axis)?.is_triggered().ok()
    }
    fn files(&mut self) -> Option<&mut dyn FileStore> {
        let card = self.card.as_mut()?;
        Some(&mut **card)
    }
}

type Ctl<P> = Controller<'static, 3, 32, 256, P, Fake, VecStorage>;

/// The controller on a simulated machine, polled every millisecond of virtual time, keeping
/// its program in `P`.
struct Bench<P: ProgramStore = RamStore<8>> {
    ctl: Ctl<P>,
    /// The step interrupt on the simulated machine.
    wiring: Wiring<'static, 3, 256>,
    link: MemLink,
    /// Everything the controller wrote, as text.
    out: String,
}

fn machine() -> MachineConfig<3> {
    let homing = |switch| HomingConfig {
        direction: HomeDirection::Min,
        seek_mm_min: 3000.0,
        locate_mm_min: 300.0,
        pull_off_mm: 1.0,
        switch,
        order: switch,
    };
    MachineConfig::new([
        AxisConfig::linear(b'X', 80.0, 6000.0, 1000.0, 200.0).with_homing(homing(0)),
        AxisConfig::linear(b'Y', 80.0, 6000.0, 1000.0, 200.0).with_homing(homing(1)),
        AxisConfig::linear(b'Z', 400.0, 900.0, 200.0, 100.0),
    ])
}

impl Bench {
    fn new() -> Self {
        Self::with_machine(machine())
    }

    fn with_machine(config: MachineConfig<3>) -> Self {
        Self::boot(config, RamStore::<8>::new(), VecStorage::default(), [0; 3])
    }
}

impl<P: ProgramStore> Bench<P> {
    /// Switch on: a new kernel of `config` over `program` and the settings `storage`, the
    /// motors at `physical` (steps from where the machine was first switched on), the homing
    /// switches of X and Y 10 mm below that first place.
    fn boot(
        config: MachineConfig<3>,
        program: P,
        mut storage: VecStorage,
        physical: [i32; 3],
    ) -> Self {
        let queue: &'static mut StepQueue<3, 256> = Box::leak(Box::new(StepQueue::new()));
        let timing = StepTiming::CONSERVATIVE;
        let (kernel, isr) = split::<3, 32, 256>(queue, config, TICK_HZ, timing).unwrap();
        let mut wiring = Wiring::new(isr, &config, TICK_HZ, timing);
        wiring.add_switch(0, -800, true);
        wiring.add_switch(1, -800, true);
        for (axis, steps) in physical.into_iter().enumerate() {
            wiring
                .machine
                .set_position_steps(axis, i64::from(steps))
                .unwrap();
        }
        let fake = Fake::new(wiring.switches().to_vec());
        let mut cfg = ControllerConfig::new("test-bench", timing);
        cfg.extruders = 1;
        cfg.heater_tolerance_mc = 1_000;
        let (settings, _) = Settings::load(config, &mut storage);
        let ctl = Controller::with_settings(kernel, program, fake, cfg, settings, storage);
        let mut b = Self {
            ctl,
            wiring,
            link: MemLink::default(),
            out: String::new(),
        };
        b.ctl.boot(&mut b.link);
        b
    }

    /// Power off: the program store, the settings storage, and where the motors are.
    fn power_off(self) -> (P, VecStorage, [i32; 3]) {
        let physical = self.wiring.positions();
        let (_, program, _, storage) = self.ctl.release();
        (program, storage, physical)
    }

    /// Run virtual time forward `ms` milliseconds. Each turn of the thread loop polls the
    /// controller again at once while the kernel has steps left to prepare, as a board does.
    fn run_ms(&mut self, ms: u64) {
        let until = self.wiring.now() + ms * 1000;
        let (ctl, link) = (&mut self.ctl, &mut self.link);
        self.wiring.advance_to(until, |now| {
            let mut arm = ctl.poll(now, link).arm_alarm;
            while ctl.kernel().needs_poll() {
                arm = arm.or(ctl.poll(now, link).arm_alarm);
            }
            arm
        });
        self.collect();
    }

    fn collect(&mut self) {
        let bytes = core::mem::take(&mut self.link.tx);
        self.out.push_str(&String::from_utf8(bytes).unwrap());
    }

    /// Take the output so far, as lines.
    fn take(&mut self) -> Vec<String> {
        self.collect();
        let text = core::mem::take(&mut self.out);
        text.lines().map(str::to_string).collect()
    }

    fn send(&mut self, text: &str) {
        self.link.rx.extend(text.as_bytes());
        self.link.rx.push_back(b'\n');
    }

    fn send_raw(&mut self, bytes: &[u8]) {
        self.link.rx.extend(bytes);
    }

    fn send_numbered(&mut self, n: u32, body: &str) {
        let mut buf = [0u8; 300];
        let len = write_numbered(n, body.as_bytes(), &mut buf).unwrap();
        self.send(core::str::from_utf8(&buf[..len]).unwrap());
    }

    fn send_frame(&mut self, msg: &ClientMessage<'_>) {
        let mut f = [0u8; FRAME_LEN];
        msg.encode(&mut f).unwrap();
        self.send_raw(&f);
        self.send_raw(b"\n");
    }

    /// Send `text`, run until it is answered (at most `ms`), and return the reply lines.
    fn ask(&mut self, text: &str) -> Vec<String> {
        self.send(text);
        self.run_ms(5);
        self.take()
    }

    fn run_until(&mut self, max_ms: u64, mut done: impl FnMut(&mut Self) -> bool) {
        for _ in 0..max_ms {
            if done(self) {
                return;
            }
            self.run_ms(1);
        }
        panic!("not done after {max_ms} ms; output: {:?}", self.out);
    }

    /// Stream moves as a host that waits for each `ok` does, until one is held for room in
    /// the planner. Returns how many lines were sent.
    fn fill_planner(&mut self) -> u32 {
        self.take();
        for i in 0..100u32 {
            let x = if i % 2 == 0 { 30 } else { 0 };
            self.send(&format!("G1 X{x} F3000"));
            self.run_ms(1);
            if self.take().is_empty() {
                assert!(self.ctl.is_holding());
                return i + 1;
            }
        }
        panic!("the planner never filled");
    }

    fn idle(&mut self) {
        self.run_ms(2);
        self.run_until(60_000, |b| {
            b.ctl.kernel().is_idle() && b.ctl.kernel().state() != MachineState::Homing
        });
    }

    fn position_mm(&self) -> [f64; 3] {
        self.ctl.kernel().position().machine_mm
    }

    fn violations(&self) -> usize {
        self.wiring.machine.violations().len()
    }
}

fn frames_of(lines: &[String]) -> Vec<ControllerMessage<'_>> {
    lines
        .iter()
        .filter(|l| l.len() == FRAME_LEN && l.starts_with('N'))
        .map(|l| ControllerMessage::decode(l.as_bytes()).unwrap())
        .collect()
}

fn error_codes(lines: &[String]) -> Vec<u16> {
    frames_of(lines)
        .iter()
        .filter_map(|m| match m {
            ControllerMessage::Error { code, .. } => Some(*code),
            _ => None,
        })
        .collect()
}

fn numbered(n: i64, body: &str) -> String {
    let head = format!("N{n} {body}");
    format!("{head}*{}", checksum(head.as_bytes()))
}

#[test]
fn boot_says_start_once() {
    let mut b = Bench::new();
    b.ctl.boot(&mut b.link);
    assert_eq!(b.take(), ["start"]);
}

#[test]
fn every_line_gets_exactly_one_terminal_reply() {
    let mut b = Bench::new();
    b.take();
    let lines = [
        "G21 G90",
        "G1 X10 Y5 F3000",
        "; a comment only",
        "(another)",
        "   ",
        "G1 X12",
        "M114",
        "M105",
        "M115",
        "M119",
        "G4 P10",
    ];
    for (i, l) in lines.iter().enumerate() {
        b.send_numbered(i as u32 + 1, l);
    }
    b.run_ms(2000);
    let out = b.take();
    let terminal: Vec<&String> = out.iter().filter(|l| l.starts_with("ok")).collect();
    assert_eq!(terminal.len(), lines.len(), "{out:?}");
    assert!(
        out.iter()
            .all(|l| !l.starts_with("rs") && !l.starts_with("echo:") && !l.starts_with("Error:"))
    );
    assert!(
        out.iter()
            .any(|l| l.starts_with("X:12.000 Y:5.000 Z:0.000 Count X:")),
        "{out:?}"
    );
    assert!(
        out.contains(&"ok T:20.0 /0.0 B:20.0 /0.0 @:0 B@:0".to_string()),
        "{out:?}"
    );
    assert!(
        out.iter().any(|l| l.starts_with("FIRMWARE_NAME:Forja ")
            && l.contains("MACHINE_TYPE:test-bench")
            && l.contains("EXTRUDER_COUNT:1")),
        "{out:?}"
    );
    assert!(
        out.contains(&"ok x_min:open y_min:open".to_string()),
        "{out:?}"
    );
    assert_eq!(b.position_mm(), [12.0, 5.0, 0.0]);
    assert_eq!(b.ctl.stats().oks, lines.len() as u32);
    assert_eq!(b.violations(), 0);
}

#[test]
fn printrun_opening_with_line_minus_one() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask(&numbered(-1, "M110 N-1")), ["ok"]);
    assert_eq!(b.ask(&numbered(0, "G1 X1")), ["ok"]);
    assert_eq!(b.ask(&numbered(1, "G1 X2")), ["ok"]);
    assert_eq!(b.ask(&numbered(5, "G1 X3")), ["rs 2", "ok"]);
}

#[test]
fn transport_failures_get_rs_alone() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask(&numbered(1, "G1 X1")), ["ok"]);
    // Checksum mismatch.
    let good = numbered(2, "G1 X2");
    let bad = good.replace("X2", "X3");
    assert_eq!(b.ask(&bad), ["rs 2", "ok"]);
    // N without *, * without N.
    assert_eq!(b.ask("N2 G1 X2"), ["rs 2", "ok"]);
    assert_eq!(
        b.ask(&format!("G1 X2*{}", checksum(b"G1 X2"))),
        ["rs 2", "ok"]
    );
    // Not the line expected; each out-of-order line gets its own rs.
    b.send(&numbered(3, "G1 X3"));
    b.send(&numbered(4, "G1 X4"));
    b.run_ms(5);
    assert_eq!(b.take(), ["rs 2", "ok", "rs 2", "ok"]);
    // An over-long numbered line.
    let long = numbered(2, &format!("G1 X2 ({})", "x".repeat(300)));
    assert_eq!(b.ask(&long), ["rs 2", "ok"]);
    // A damaged line number.
    assert_eq!(b.ask("N2x G1*99"), ["rs 2", "ok"]);
    // The resent line is taken, once.
    assert_eq!(b.ask(&good), ["ok"]);
    assert_eq!(b.ask(&good), ["rs 3", "ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 2.0);
    assert_eq!(b.ctl.stats().executed, 2);
}

#[test]
fn a_numbered_line_that_arrived_intact_but_is_not_gcode_is_refused_and_used_up() {
    let mut b = Bench::new();
    b.take();
    // Asked again once (the checksum misses some double faults), then refused and its
    // number used up: resending it again would repeat forever.
    assert_eq!(b.ask(&numbered(1, "G1 X#1")), ["rs 1", "ok"]);
    assert_eq!(b.ask(&numbered(1, "G1 X#1")), ["echo:E9 no-value", "ok"]);
    assert_eq!(b.ask(&numbered(2, "G1 X1")), ["ok"]);
}

#[test]
fn unnumbered_lines_run_without_numbering_checks() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask(&numbered(1, "G1 X1")), ["ok"]);
    assert_eq!(b.ask("G1 X5"), ["ok"]);
    assert_eq!(b.ask(&numbered(2, "G1 X6")), ["ok"]);
    // Unnumbered over-long lines are refused, not resent.
    let mut c = Bench::new();
    c.take();
    assert_eq!(
        c.ask(&format!("G1 X1 ({})", "x".repeat(300))),
        ["echo:E1 line-too-long", "ok"]
    );
}

#[test]
fn a_probe_contact_is_echoed_at_its_machine_position_negative_ones_too() {
    let mut b = Bench::new();
    b.take();
    let probe = forja_motion::ProbeReport {
        machine_nm: [-1_500_000, -500_000, 20_000_000],
        tripped: true,
    };
    b.ctl.core.report_probe(&probe, &mut b.link);
    b.collect();
    assert_eq!(
        b.take(),
        ["echo:Probe: contact at X:-1.500 Y:-0.500 Z:20.000"],
        "(before, euclidean division wrote -1.5 mm as -2.500)"
    );
}

#[test]
fn refused_commands_get_a_fault_line_and_ok_and_change_nothing() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M31"), ["echo:Unknown command: \"M31\"", "ok"]);
    assert_eq!(b.ask("G38.6 X1"), ["echo:Unknown command: \"G38.6\"", "ok"]);
    assert_eq!(b.ask("G38.2 X1"), ["echo:E132 no-probe", "ok"]);
    assert_eq!(b.ask("M106 P7 S100"), ["echo:E194 no-device fan 7", "ok"]);
    assert_eq!(b.ask("T3"), ["echo:E121 bad-value T3", "ok"]);
    assert_eq!(b.ask("M104 S900"), ["echo:E195 device-range", "ok"]);
    // Soft limits, once homed.
    b.send_frame(&ClientMessage::Action(Action::HomeAll));
    b.idle();
    b.take();
    assert_eq!(b.ask("G1 X250"), ["echo:E124 soft-limit X", "ok"]);
    b.idle();
    assert_eq!(b.position_mm()[..2], [1.0, 1.0]);
    assert_eq!(b.ctl.stats().refused, 7);
}

#[test]
fn a_full_planner_delays_the_ok_and_stops_reading() {
    let mut b = Bench::new();
    b.take();
    for i in 0..80u32 {
        let x = if i % 2 == 0 { 20 } else { 0 };
        b.send_numbered(i + 1, &format!("G1 X{x} F6000"));
    }
    b.run_ms(20);
    let oks = b.take().len();
    assert!(oks < 60, "{oks} oks while the planner holds 32 blocks");
    assert!(b.ctl.is_holding());
    assert!(!b.link.rx.is_empty(), "input is left unread");
    let mut total = oks;
    b.run_until(60_000, |b| {
        total += b.take().iter().filter(|l| *l == "ok").count();
        total == 80
    });
    b.idle();
    assert_eq!(b.ctl.stats().executed, 80);
    assert_eq!(b.position_mm()[0], 0.0);
    assert_eq!(b.violations(), 0);
}

#[test]
fn frames_get_through_while_a_line_waits_for_room() {
    let mut b = Bench::new();
    b.take();
    let sent = b.fill_planner();
    // Pause (feed hold) and a position request get through; Start resumes.
    b.send_frame(&ClientMessage::Action(Action::Pause));
    b.send_frame(&ClientMessage::Request { message_type: 51 });
    b.run_ms(500);
    let out = b.take();
    assert_eq!(
        frames_of(&out)
            .iter()
            .filter(|m| matches!(m, ControllerMessage::Positions(_)))
            .count(),
        1,
        "{out:?}"
    );
    assert!(matches!(
        b.ctl.kernel().state(),
        MachineState::Hold { stopped: true }
    ));
    let held_at = b.position_mm();
    b.run_ms(200);
    assert_eq!(b.position_mm(), held_at);
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_until(60_000, |b| {
        b.ctl.stats().oks == sent && b.ctl.kernel().is_idle()
    });
    assert_eq!(
        b.position_mm()[0],
        if sent.is_multiple_of(2) { 0.0 } else { 30.0 }
    );
}

#[test]
fn m109_holds_lines_and_reports_progress_until_at_temperature() {
    let mut b = Bench::new();
    b.take();
    b.send("M109 S200");
    b.send("M105");
    b.run_ms(3000);
    let out = b.take();
    assert!(out.iter().all(|l| !l.starts_with("ok")), "{out:?}");
    let progress: Vec<&String> = out.iter().filter(|l| l.starts_with(" T:")).collect();
    assert!((2..=4).contains(&progress.len()), "{out:?}");
    assert!(progress[0].contains(" /200.0 B:"), "{out:?}");
    b.run_until(20_000, |b| b.ctl.stats().oks == 2);
    let out = b.take();
    assert_eq!(out.iter().filter(|l| l.starts_with("ok")).count(), 2);
    assert!(
        out.iter()
            .any(|l| l.starts_with("ok T:19") || l.starts_with("ok T:20"))
    );
    // M116 waits for every heater.
    b.send("M140 S60");
    b.send("M116");
    b.run_ms(100);
    assert!(b.ctl.is_holding());
    b.run_until(10_000, |b| !b.ctl.is_holding());
}

#[test]
fn garbage_gets_one_error_frame_per_run_and_a_resend_when_numbered() {
    let mut b = Bench::new();
    b.take();
    b.send_raw(b"\x01\x02\x03junk\n\x7f\n");
    b.run_ms(5);
    let out = b.take();
    assert_eq!(error_codes(&out), [21, 21], "{out:?}");
    // Nothing tells yet which protocol the host speaks: both answers go out, the G-code one
    // only for the run that lost text (`junk`).
    assert_eq!(out[1..3], ["echo:E8 bad-character", "ok"], "{out:?}");
    assert_eq!(out.len(), 4);
    assert_eq!(b.ask(&numbered(1, "G1 X1")), ["ok"]);
    b.send_raw(b"N2 G1\x01X2*1\n");
    b.run_ms(5);
    // A G-code host: no 56, only the resend.
    assert_eq!(b.take(), ["rs 2", "ok"]);
}

#[test]
fn settings_are_read_set_stored_and_refused() {
    let mut b = Bench::new();
    b.take();
    b.send_frame(&ClientMessage::SetSetting {
        key: "x.steps_per_mm",
        value: "100",
    });
    b.send_frame(&ClientMessage::ReadSetting { key: "Y.MAX" });
    b.send_frame(&ClientMessage::SetSetting {
        key: "link.password",
        value: "hunter2",
    });
    b.send_frame(&ClientMessage::SetSetting {
        key: "q.max",
        value: "1",
    });
    b.send_frame(&ClientMessage::SetSetting {
        key: "x.max",
        value: "-3",
    });
    b.send_frame(&ClientMessage::SetSetting {
        key: "x.max_rate",
        value: "600000",
    });
    b.run_ms(5);
    let out = b.take();
    let f = frames_of(&out);
    assert_eq!(
        f[..3],
        [
            ControllerMessage::Setting {
                key: "x.steps_per_mm",
                value: "100"
            },
            ControllerMessage::Setting {
                key: "y.max",
                value: "200"
            },
            ControllerMessage::Setting {
                key: "link.password",
                value: "<hidden>"
            },
        ]
    );
    assert_eq!(error_codes(&out), [190, 105, 110]);
    assert_eq!(b.ctl.settings().machine().axes[0].steps_per_mm, 100.0);
    assert_eq!(b.ctl.settings().password(), "hunter2");
    // Stored: a restart would find them.
    let (loaded, report) = Settings::load(machine(), b.ctl.storage_mut());
    assert_eq!(report.applied, 2);
    assert_eq!(loaded.machine().axes[0].steps_per_mm, 100.0);
    // The running kernel keeps its configuration until the next start.
    assert_eq!(b.ctl.kernel().config().axes[0].steps_per_mm, 80.0);
}

#[test]
fn jog_moves_without_reply_and_bad_jogs_are_refused() {
    let mut b = Bench::new();
    b.take();
    b.send_frame(&ClientMessage::Jog {
        step: Decimal::new(1, 1),
        axis: b'X',
        count: 25,
    });
    b.send_frame(&ClientMessage::Jog {
        step: Decimal::new(1, 0),
        axis: b'Q',
        count: 1,
    });
    b.idle();
    let out = b.take();
    assert_eq!(error_codes(&out), [127]);
    assert_eq!(out.len(), 1);
    assert_eq!(b.position_mm()[0], 2.5);
    // A broken mirror is a framing error; nothing moves.
    let mut frame = [0u8; FRAME_LEN];
    ClientMessage::Action(Action::Stop)
        .encode(&mut frame)
        .unwrap();
    frame[FRAME_LEN - 2] = b'q';
    b.send_raw(&frame);
    b.send_raw(b"\n");
    b.run_ms(5);
    assert_eq!(error_codes(&b.take()), [23]);
}

#[test]
fn homing_with_switches_and_positions_report() {
    let mut b = Bench::new();
    b.take();
    b.send_frame(&ClientMessage::Action(Action::Home(b'X')));
    b.idle();
    b.send_frame(&ClientMessage::Action(Action::HomeAll));
    b.idle();
    b.send_frame(&ClientMessage::Request { message_type: 51 });
    b.send_frame(&ClientMessage::Action(Action::Home(b'Z')));
    b.run_ms(5);
    let out = b.take();
    let f = frames_of(&out);
    let ControllerMessage::Positions(p) = &f[0] else {
        panic!("{out:?}")
    };
    assert_eq!(p.get(b'X'), Some(10_000));
    assert_eq!(p.get(b'Y'), Some(10_000));
    assert_eq!(error_codes(&out), [121], "Z has no switch");
    assert_eq!(b.ctl.kernel().homed_axes(), 0b011);
    assert!(b.ctl.peripherals().motors);
    assert_eq!(b.violations(), 0);
    assert_eq!(b.ask("G1 X50"), ["ok"]);
    // Homing waits for the move before it: its ok comes when the cycle has started.
    assert!(b.ask("G28 X0").is_empty());
    b.idle();
    // A homing of more than 2 s: the host hears `busy: processing` every 2 s meanwhile.
    let out = b.take();
    let (busy, rest): (Vec<_>, Vec<_>) = out.iter().partition(|l| *l == "echo:busy: processing");
    assert_eq!(rest, ["ok"]);
    assert!(!busy.is_empty(), "{out:?}");
    assert_eq!(b.position_mm()[0], 1.0);
}

#[test]
fn program_upload_run_pause_resume_stop_rewind() {
    let mut b = Bench::new();
    b.take();
    let program = ["G1 X20 F6000", "G1 Y20", "G1 X0", "G1 Y0", "G1 X40 F600"];
    for (i, text) in program.iter().enumerate() {
        b.send_frame(&ClientMessage::LoadLine {
            index: i as u16 + 1,
            text,
            total: program.len() as u16,
        });
    }
    b.run_ms(5);
    let out = b.take();
    assert_eq!(
        frames_of(&out),
        [ControllerMessage::Confirm { what: "Gcode-load" }]
    );
    assert_eq!(b.ctl.program().len(), 5);
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_until(20_000, |b| b.ctl.progress().current_line == 5);
    b.run_ms(500);
    // While it runs, moves from the link are refused; reports still work.
    assert_eq!(b.ask("G1 Z5"), ["echo:E182 job-busy", "ok"]);
    assert!(b.ask("M114")[0].starts_with("X:40.000"));
    b.send_frame(&ClientMessage::Action(Action::Pause));
    b.run_ms(300);
    let paused = b.position_mm();
    b.run_ms(300);
    assert_eq!(b.position_mm(), paused);
    assert_eq!(b.ctl.job().state(), JobState::Paused);
    b.send_frame(&ClientMessage::Request { message_type: 52 });
    b.send_frame(&ClientMessage::Action(Action::Rewind));
    b.run_ms(5);
    let out = b.take();
    let f = frames_of(&out);
    let ControllerMessage::Progress(p) = &f[0] else {
        panic!("{out:?}")
    };
    assert_eq!((p.total_lines, p.current_line), (5, 5));
    assert_eq!(error_codes(&out), [182], "no rewind while paused");
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(300);
    assert!(b.position_mm()[0] > paused[0]);
    b.send_frame(&ClientMessage::Action(Action::Stop));
    b.idle();
    assert_eq!(b.ctl.job().state(), JobState::Idle);
    assert!(b.position_mm()[0] < 40.0);
    b.send_frame(&ClientMessage::Action(Action::Rewind));
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_until(60_000, |b| b.ctl.job().state() == JobState::Finished);
    assert_eq!(b.position_mm(), [40.0, 0.0, 0.0]);
    assert!(b.take().iter().all(|l| !l.starts_with('N')));
    assert_eq!(b.violations(), 0);
}

#[test]
fn program_end_waits_for_the_motion_stops_the_spindle_and_resets_modes() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("G94 G91 G1 F6000"), ["ok"]);
    assert_eq!(b.ask("M3 S1000"), ["ok"]);
    assert_eq!(b.ask("X20"), ["ok"]);
    // M2 waits for the move before it: its ok comes when the machine is at rest.
    b.send("M2");
    b.run_ms(5);
    assert!(b.take().is_empty());
    assert_ne!(b.ctl.peripherals().spindle.last, Some(Turning::Stopped));
    b.run_until(10_000, |b| b.ctl.stats().oks == 4);
    assert_eq!(b.take(), ["ok"]);
    assert_eq!(b.position_mm()[0], 20.0);
    assert_eq!(b.ctl.peripherals().spindle.last, Some(Turning::Stopped));
    // Absolute again: X5 goes to 5, not 25.
    assert_eq!(b.ask("X5"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 5.0);
    assert_eq!(b.ask("G93"), ["ok"]);
    assert_eq!(b.ask("G94"), ["ok"]);
    assert_eq!(b.ask("G95"), ["echo:Unknown command: \"G95\"", "ok"]);
}

#[test]
fn program_end_in_a_stored_program_ends_the_job() {
    let mut b = Bench::new();
    b.take();
    let program = ["G91 G1 F6000", "M3 S500", "X10", "M30", "X10"];
    for (i, text) in program.iter().enumerate() {
        b.send_frame(&ClientMessage::LoadLine {
            index: i as u16 + 1,
            text,
            total: program.len() as u16,
        });
    }
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_until(10_000, |b| b.ctl.job().state() == JobState::Finished);
    b.idle();
    assert_eq!(b.position_mm()[0], 10.0, "the line after M30 does not run");
    assert_eq!(b.ctl.peripherals().spindle.last, Some(Turning::Stopped));
    assert!(error_codes(&b.take()).is_empty());
    // Absolute again after the program's G91.
    assert_eq!(b.ask("G1 X3"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 3.0);
    // The next start runs it from the top.
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(5);
    b.run_until(10_000, |b| b.ctl.job().state() == JobState::Finished);
    b.idle();
    assert_eq!(b.position_mm()[0], 13.0);
}

/// Ask for frame 52 and return (lines stored, `LA`).
fn progress_frame(b: &mut Bench) -> (u32, u32) {
    b.take();
    b.send_frame(&ClientMessage::Request { message_type: 52 });
    b.run_ms(2);
    let out = b.take();
    match frames_of(&out).first() {
        Some(ControllerMessage::Progress(p)) => (p.total_lines, p.current_line),
        _ => panic!("{out:?}"),
    }
}

#[test]
fn progress_reports_the_running_line_or_the_next_one_to_run() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(progress_frame(&mut b), (0, 0), "no program");
    let program = ["G1 X10 F600", "G1 X0", "G1 X10", "G1 X0"];
    for (i, text) in program.iter().enumerate() {
        b.send_frame(&ClientMessage::LoadLine {
            index: i as u16 + 1,
            text,
            total: program.len() as u16,
        });
    }
    b.run_ms(5);
    assert_eq!(progress_frame(&mut b), (4, 1), "before the first start");
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(1500);
    assert_eq!(progress_frame(&mut b), (4, 2), "line 2 moves");
    // Stopped in line 2: it runs again on the next start.
    b.send_frame(&ClientMessage::Action(Action::Stop));
    b.idle();
    assert_eq!(progress_frame(&mut b), (4, 2));
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_until(20_000, |b| b.ctl.job().state() == JobState::Finished);
    assert_eq!(progress_frame(&mut b), (4, 4), "finished");
    b.send_frame(&ClientMessage::Action(Action::Rewind));
    b.run_ms(2);
    assert_eq!(progress_frame(&mut b), (4, 1), "after a rewind");
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(2);
    assert_eq!(
        progress_frame(&mut b),
        (4, 1),
        "the new run, not the last one"
    );
}

#[test]
fn bad_program_lines_leave_the_store_as_it_was() {
    let mut b = Bench::new();
    b.take();
    let load = |b: &mut Bench, index, text, total| {
        b.send_frame(&ClientMessage::LoadLine { index, text, total });
    };
    load(&mut b, 1, "G1 X1", 8);
    load(&mut b, 3, "G1 X3", 8);
    load(&mut b, 2, "G1 X#", 8);
    load(&mut b, 2, "G1 X2", 7);
    for i in 2..=8 {
        load(&mut b, i, "G1 X2", 8);
    }
    load(&mut b, 9, "G1 X9", 9);
    b.run_ms(5);
    let out = b.take();
    assert_eq!(error_codes(&out), [170, 9, 193, 193], "{out:?}");
    let f = frames_of(&out);
    assert!(matches!(
        f[0],
        ControllerMessage::Error {
            code: 170,
            detail: "line-order 0003 expected 0002"
        }
    ));
    assert_eq!(b.ctl.program().len(), 8);
    // Start with the store as it is: the eight lines run.
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_until(20_000, |b| b.ctl.job().state() == JobState::Finished);
    assert_eq!(b.ctl.stats().program_lines, 8);
}

#[test]
fn a_hard_limit_is_reported_unsolicited_and_lines_in_alarm_are_refused() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("G1 X-20 F3000"), ["ok"]);
    b.run_ms(1000);
    let out = b.take();
    assert_eq!(out, ["Error:E150 hard-limit X"]);
    assert_eq!(b.ctl.peripherals().spindle.stops, 1, "shut down once");
    assert_eq!(b.ask("M119"), ["ok x_min:TRIGGERED y_min:open"]);
    assert_eq!(b.ask("G1 X5"), ["echo:E125 alarm-locked", "ok"]);
    assert!(b.ask("M105")[0].starts_with("ok T:"));
    // Homing clears it; its ok comes when the cycle is done, and the position follows it.
    b.send("G28");
    b.send("M114");
    b.run_ms(5);
    assert!(b.take().is_empty());
    b.idle();
    b.run_ms(5);
    assert_eq!(
        b.take(),
        ["ok", "X:1.000 Y:1.000 Z:0.000 Count X:80 Y:80 Z:0", "ok"]
    );
    assert_eq!(b.ask("G1 X5"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 5.0);
}

#[test]
fn m112_stops_everything_until_a_reset() {
    let mut b = Bench::new();
    b.take();
    b.send("M3 S1000");
    b.send("G1 X100 F3000");
    b.run_ms(300);
    b.send("M112");
    b.run_ms(300);
    let out = b.take();
    assert_eq!(out, ["ok", "ok", "Error:E153 emergency-stop", "ok"]);
    assert!(!b.ctl.peripherals().motors);
    assert_eq!(b.ctl.peripherals().spindle.last, Some(Turning::Stopped));
    let stopped = b.position_mm();
    b.run_ms(300);
    assert_eq!(b.position_mm(), stopped);
    assert_eq!(b.ask("G28"), ["echo:E125 alarm-locked", "ok"]);
    assert_eq!(b.ask("M104 S200"), ["echo:E125 alarm-locked", "ok"]);
    assert_eq!(b.ask("M999"), ["ok"]);
    assert_eq!(b.ask("G1 X0"), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 0.0);
    assert!(b.ctl.peripherals().motors);
}

#[test]
fn m112_is_carried_out_even_behind_a_held_line() {
    let mut b = Bench::new();
    b.take();
    b.fill_planner();
    b.send("M112");
    b.run_ms(5);
    // The fault goes out at once; the held line, received first, is answered (refused) before
    // the M112 line's own ok.
    assert_eq!(
        b.take(),
        [
            "Error:E153 emergency-stop",
            "echo:E125 alarm-locked",
            "ok",
            "ok"
        ]
    );
}

#[test]
fn a_thermal_fault_raises_an_alarm_and_shuts_down() {
    let mut b = Bench::new();
    b.take();
    b.send_frame(&ClientMessage::Request { message_type: 52 });
    assert_eq!(
        b.ask("M104 S200"),
        [
            "N52EL00:00ES00:00NL0000LA0000***********************F",
            "ok"
        ]
    );
    b.send("G1 X50 F3000");
    b.run_ms(50);
    b.ctl.peripherals_mut().hot.pending = Some(DeviceError::Thermal {
        code: 212,
        name: "thermal-runaway",
    });
    b.run_ms(200);
    let out = b.take();
    assert!(
        out.contains(&"Error:E212 thermal-runaway".to_string()),
        "{out:?}"
    );
    assert_eq!(error_codes(&out), [212]);
    assert!(matches!(
        b.ctl.kernel().state(),
        MachineState::Alarm(forja_motion::Alarm::EmergencyStop)
    ));
    assert_eq!(b.ctl.peripherals().hot.target_mc, 0);
    assert_eq!(b.ask("M104 S200"), ["echo:E125 alarm-locked", "ok"]);
    b.send_frame(&ClientMessage::Action(Action::Reset));
    b.run_ms(200);
    assert!(b.take().is_empty());
    assert_eq!(b.ctl.thermal_fault(), None);
    assert_eq!(b.ask("M104 S200"), ["ok"]);
}

#[test]
fn a_frame_without_terminator_is_taken_when_the_link_goes_quiet() {
    let mut b = Bench::new();
    b.take();
    let mut frame = [0u8; FRAME_LEN];
    ClientMessage::Request { message_type: 52 }
        .encode(&mut frame)
        .unwrap();
    b.send_raw(&frame);
    b.run_ms(5);
    assert!(b.take().is_empty());
    b.run_ms(30);
    assert_eq!(frames_of(&b.take()).len(), 1);
    // Back to back, the first is taken at once, the second after the quiet time.
    b.send_raw(&frame);
    b.send_raw(&frame);
    b.run_ms(2);
    assert_eq!(frames_of(&b.take()).len(), 1);
    b.run_ms(30);
    assert_eq!(frames_of(&b.take()).len(), 1);
}

#[test]
fn a_numbered_line_whose_terminator_was_lost_is_taken_when_the_link_goes_quiet() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask(&numbered(1, "G1 X1 F3000")), ["ok"]);
    // Intact but for its line end: it passes its checksum and runs.
    b.send_raw(numbered(2, "G1 X2").as_bytes());
    b.run_ms(5);
    assert!(b.take().is_empty(), "not before the link is quiet");
    b.run_ms(30);
    assert_eq!(b.take(), ["ok"]);
    // Truncated (the last checksum digit and the line end lost): asked for again.
    let line = numbered(3, "G1 X3");
    b.send_raw(&line.as_bytes()[..line.len() - 1]);
    b.run_ms(30);
    assert_eq!(b.take(), ["rs 3", "ok"]);
    assert_eq!(b.ask(&line), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 3.0);
}

#[test]
fn an_unterminated_console_line_is_never_cut_short() {
    let mut b = Bench::new();
    b.take();
    b.send_raw(b"G1 F3000 X5");
    b.run_ms(1000);
    assert!(b.take().is_empty());
    b.send_raw(b"0\n");
    b.run_ms(5);
    assert_eq!(b.take(), ["ok"]);
    b.idle();
    assert_eq!(b.position_mm()[0], 50.0);
}

#[test]
fn quiet_does_not_count_while_input_is_held_back() {
    let mut b = Bench::new();
    b.take();
    // M109 holds further lines; more than the read-ahead window follows, so the receive queue
    // fills and reading stops, with the start of the last line sent last.
    let mut burst = numbered(1, "M109 S30");
    burst.push('\n');
    let mut n = 2;
    while burst.len() < READ_AHEAD_BYTES + 2 * MAX_LINE_LEN {
        burst.push_str(&numbered(n, "G90"));
        burst.push('\n');
        n += 1;
    }
    let last = numbered(n, "G1 X2 F3000");
    let (head, rest) = last.split_at(4);
    burst.push_str(head);
    b.send_raw(burst.as_bytes());
    b.run_ms(5);
    assert!(b.ctl.is_holding());
    assert!(!b.link.rx.is_empty(), "reading stopped");
    b.run_until(10_000, |b| !b.ctl.is_holding());
    b.run_ms(1);
    let out: Vec<String> = b
        .take()
        .into_iter()
        .filter(|l| !l.starts_with("//"))
        .collect();
    assert!(b.link.rx.is_empty(), "reading resumed");
    assert_eq!(out.len() as i64, n - 1, "{out:?}");
    assert!(out.iter().all(|l| l == "ok"), "{out:?}");
    // The rest of the last line comes a little after reading resumes: the line is whole.
    b.run_ms(5);
    b.send(rest);
    b.run_ms(5);
    let out = b.take();
    assert_eq!(out, ["ok"], "{out:?}");
    b.idle();
    assert_eq!(b.position_mm()[0], 2.0);
}

#[test]
fn requests_and_actions_that_cannot_be_done_are_refused() {
    let mut b = Bench::new();
    b.take();
    b.send_frame(&ClientMessage::Request { message_type: 53 });
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.send_frame(&ClientMessage::Action(Action::Pause));
    b.send(&format!("N99{}F", "*".repeat(49)));
    b.run_ms(5);
    let out = b.take();
    assert_eq!(error_codes(&out), [192, 180, 181, 22], "{out:?}");
}

#[test]
fn connect_and_keep_alive_frames() {
    let mut b = Bench::new();
    b.take();
    b.send(&numbered(1, "G1 X1"));
    b.run_ms(5);
    b.ctl.on_connect(&mut b.link);
    b.ctl.keep_alive(7, &mut b.link);
    let out = b.take();
    assert_eq!(
        out[1],
        "N54Conected*****************************************F"
    );
    assert_eq!(
        out[2],
        "N55Vivo0000007**************************************F"
    );
    // A new host starts numbering afresh.
    assert_eq!(b.ask(&numbered(1, "G1 X2")), ["ok"]);
}

#[test]
fn effects_reach_the_peripherals_in_stream_order() {
    let mut b = Bench::new();
    b.take();
    b.send("G1 X30 F3000");
    b.send("M106 P1 S128");
    b.send("M4 S500");
    b.send("M84");
    b.run_ms(10);
    assert_eq!(
        b.ctl.peripherals().fans[1].0,
        0,
        "the fan waits for the move"
    );
    b.idle();
    b.run_ms(10);
    assert_eq!(b.ctl.peripherals().fans[1].0, 128);
    assert!(matches!(
        b.ctl.peripherals().spindle.last,
        Some(Turning::At(Rotation::CounterClockwise, _))
    ));
    assert!(!b.ctl.peripherals().motors);
    assert_eq!(b.take().len(), 4);
    // The next move energises the motors again.
    assert_eq!(b.ask("G1 X0"), ["ok"]);
    b.idle();
    assert!(b.ctl.peripherals().motors);
    assert_eq!(b.position_mm()[0], 0.0);
}

/// The mist and flood lines of the test board's coolant.
fn coolant(b: &Bench) -> (bool, bool) {
    let c = b.ctl.peripherals().coolant.as_ref().unwrap();
    (c.mist, c.flood)
}

#[test]
fn coolant_follows_the_motion_and_goes_off_at_program_end_and_on_a_stop() {
    let mut b = Bench::new();
    b.take();
    b.send("G1 X30 F3000");
    b.send("M7");
    b.send("M8");
    b.run_ms(10);
    assert_eq!(
        coolant(&b),
        (false, false),
        "the coolant waits for the move"
    );
    b.idle();
    b.run_ms(10);
    assert_eq!(coolant(&b), (true, true), "mist and flood on together");
    assert_eq!(b.take(), ["ok", "ok", "ok"]);
    assert_eq!(b.ask("M9"), ["ok"]);
    assert_eq!(coolant(&b), (false, false));
    assert_eq!(b.ask("M8"), ["ok"]);
    assert_eq!(coolant(&b), (false, true));
    assert_eq!(b.ask("M2"), ["ok"]);
    assert_eq!(coolant(&b), (false, false), "program end");
    assert_eq!(b.ask("M7"), ["ok"]);
    b.send("M112");
    b.run_ms(5);
    assert_eq!(b.take(), ["Error:E153 emergency-stop", "ok"]);
    assert_eq!(coolant(&b), (false, false), "an emergency stop");
}

#[test]
fn coolant_on_a_board_without_it_is_refused_and_program_end_goes_on() {
    let mut b = Bench::new();
    b.take();
    b.ctl.peripherals_mut().coolant = None;
    assert_eq!(b.ask("M8"), ["echo:E194 no-device coolant", "ok"]);
    assert_eq!(b.ask("M3 S100"), ["ok"]);
    assert_eq!(b.ask("M30"), ["ok"]);
    assert_eq!(b.ctl.peripherals().spindle.last, Some(Turning::Stopped));
}

#[test]
fn m3_without_s_runs_at_the_last_speed() {
    let mut b = Bench::new();
    b.take();
    assert_eq!(b.ask("M3"), ["ok"]);
    let last = |b: &Bench| b.ctl.peripherals().spindle.last;
    assert_eq!(last(&b), Some(Turning::At(Rotation::Clockwise, 0)));
    assert_eq!(b.ask("M3 S1200"), ["ok"]);
    assert_eq!(b.ask("M5"), ["ok"]);
    assert_eq!(b.ask("M4"), ["ok"]);
    assert_eq!(
        last(&b),
        Some(Turning::At(Rotation::CounterClockwise, 1200))
    );
}

#[test]
fn a_program_line_that_fails_stops_the_job_with_an_error_frame() {
    let mut b = Bench::new();
    b.take();
    for (i, text) in ["G1 X5 F3000", "M20", "G1 X9"].iter().enumerate() {
        b.send_frame(&ClientMessage::LoadLine {
            index: i as u16 + 1,
            text,
            total: 3,
        });
    }
    b.send_frame(&ClientMessage::Action(Action::Start));
    b.run_ms(2000);
    let out = b.take();
    // A file command is the host's, not a program's: `E183 job-line 0002`.
    assert_eq!(error_codes(&out), [183], "{out:?}");
    // The job stops at the refused line: nothing after it runs.
    assert_eq!(b.ctl.job().state(), JobState::Idle);
    assert!(b.position_mm()[0] <= 5.0);
    assert_eq!(b.ctl.job().next_line(), 2);
}

#[test]
fn the_busy_refusal_speaks_both_protocols() {
    let mut out = [0u8; BUSY_REFUSAL_LEN];
    let len = busy_refusal(&mut out);
    let text = core::str::from_utf8(&out[..len]).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 2, "{text:?}");
    assert_eq!(error_codes(&[lines[0].to_string()]), [300]);
    assert_eq!(lines[1], "// E300 link-busy");
    assert!(text.ends_with('\n'));
}
