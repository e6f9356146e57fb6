//! A driver that reports an error while the machine moves stops it at once with a driver-fault
//! alarm naming its axis, whichever edge the error comes on: a rising edge, the end of a pulse
//! with one line raised (the step interrupt's short path), or with several.

mod common;

use core::convert::Infallible;

use common::machine;
use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::stepper::{Direction, StepTiming, Stepper};
use forja_hal_abstraction::time::Instant;
use forja_hal_abstraction::{Error, ErrorKind, ErrorType};
use forja_motion::{Alarm, MachineState, Reply, StepQueue, split};
use forja_protocol::gcode::Line;

const HZ: u32 = 1_000_000;

#[derive(Debug)]
struct Broken;

impl Error for Broken {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Other
    }
}

/// Which call of a driver fails.
#[derive(Clone, Copy, PartialEq)]
enum Failing {
    Never,
    /// The `n`-th rising edge (from 1).
    Begin(u32),
    /// The `n`-th end of a pulse (from 1).
    End(u32),
}

/// A step/direction driver that counts its edges and fails where it is told to.
struct Driver {
    failing: Failing,
    begins: u32,
    ends: u32,
    /// The step line is high.
    high: bool,
}

impl Driver {
    fn new(failing: Failing) -> Self {
        Self {
            failing,
            begins: 0,
            ends: 0,
            high: false,
        }
    }
}

impl ErrorType for Driver {
    type Error = Broken;
}

impl Stepper for Driver {
    fn set_direction(&mut self, _direction: Direction) -> Result<(), Broken> {
        Ok(())
    }

    fn step_begin(&mut self) -> Result<(), Broken> {
        self.begins += 1;
        self.high = true;
        if self.failing == Failing::Begin(self.begins) {
            return Err(Broken);
        }
        Ok(())
    }

    fn step_end(&mut self) -> Result<(), Broken> {
        self.ends += 1;
        self.high = false;
        if self.failing == Failing::End(self.ends) {
            return Err(Broken);
        }
        Ok(())
    }

    fn timing(&self) -> StepTiming {
        StepTiming::CONSERVATIVE
    }
}

/// A switch that never triggers.
struct Open;

impl ErrorType for Open {
    type Error = Infallible;
}

impl LimitSwitch for Open {
    fn is_triggered(&mut self) -> Result<bool, Infallible> {
        Ok(false)
    }
}

/// Run `line` on the test machine with `drivers` (X, Y, Z), the thread side polled every
/// millisecond, until the machine is idle or in an alarm (at most 10 s). Returns its state.
fn run(line: &str, drivers: &mut [Driver; 3]) -> MachineState {
    let mut q = StepQueue::<3, 256>::new();
    let (mut kernel, mut isr) =
        split::<3, 32, 256>(&mut q, machine(), HZ, StepTiming::CONSERVATIVE).expect("valid");
    let mut switches = [Open, Open, Open];
    let parsed = Line::parse(line.as_bytes()).expect("a line");
    let reply = kernel.execute(&parsed).expect("taken");
    assert!(matches!(reply, Reply::Ok), "{reply:?}");
    let mut now = 0u32;
    let mut alarm: Option<Instant> = None;
    for _ in 0..10_000 {
        let until = Instant::from_ticks(now.wrapping_add(HZ / 1000));
        while let Some(at) = alarm {
            if at.signed_ticks_since(until) > 0 {
                break;
            }
            alarm = isr.on_alarm(at, drivers, &mut switches);
        }
        now = until.ticks();
        let at = Instant::from_ticks(now);
        let mut arm = kernel.poll(at);
        while kernel.needs_poll() {
            arm = arm.or(kernel.poll(at));
        }
        alarm = alarm.or(arm);
        match kernel.state() {
            MachineState::Idle | MachineState::Alarm(_) if alarm.is_none() => break,
            _ => {}
        }
    }
    kernel.state()
}

fn drivers(x: Failing, y: Failing) -> [Driver; 3] {
    [Driver::new(x), Driver::new(y), Driver::new(Failing::Never)]
}

#[test]
fn the_drivers_that_do_not_fail_take_the_whole_move() {
    let mut d = drivers(Failing::Never, Failing::Never);
    assert_eq!(run("G1 X10 Y5 F3000", &mut d), MachineState::Idle);
    assert_eq!((d[0].begins, d[0].ends), (800, 800));
    assert_eq!((d[1].begins, d[1].ends), (400, 400));
}

/// Run `line` with X's and Y's drivers failing as told: the machine must stop in a
/// driver-fault alarm naming `axis`, with every step line low. Returns the drivers.
fn stopped_by(line: &str, x: Failing, y: Failing, axis: u8) -> [Driver; 3] {
    let mut d = drivers(x, y);
    assert_eq!(
        run(line, &mut d),
        MachineState::Alarm(Alarm::DriverFault { axis })
    );
    assert!(d.iter().all(|d| !d.high), "a step line left high");
    d
}

#[test]
fn a_failed_end_of_pulse_on_one_axis_stops_it_there() {
    let d = stopped_by("G1 X10 F3000", Failing::End(100), Failing::Never, 0);
    // No step after the failure.
    assert_eq!(d[0].begins, 100);
}

#[test]
fn a_failed_end_of_pulse_with_several_lines_raised_stops_the_move() {
    // A diagonal: X and Y step together, their pulses end in one call.
    let d = stopped_by("G1 X10 Y10 F3000", Failing::Never, Failing::End(50), 1);
    assert_eq!(d[1].begins, 50);
    assert!(d[0].begins <= 51, "{}", d[0].begins);
}

#[test]
fn a_failed_rising_edge_stops_the_move() {
    let d = stopped_by("G1 X10 F3000", Failing::Begin(30), Failing::Never, 0);
    assert_eq!(d[0].begins, 30);
}

#[test]
fn a_failed_rising_edge_leaves_no_line_of_its_event_high() {
    // A diagonal: X rises first, then Y's driver fails in the same event; X's pulse still ends.
    let d = stopped_by("G1 X10 Y10 F3000", Failing::Never, Failing::Begin(20), 1);
    assert_eq!((d[0].begins, d[1].begins), (20, 20));
}
