//! The controller's [`Peripherals`], built from the drivers of this crate: every board reuses
//! it instead of writing its own.
//!
//! [`DriverPeripherals`] holds what a board has of:
//!
//! | part | type | G-code |
//! |---|---|---|
//! | hot end, bed | any [`TemperatureLoop`] (a [`HeaterChannel`] over a sensor and a heater) | `M104`/`M109`/`M140`/`M116`/`M105` |
//! | fans | `[Option<Fan<P>>; F]`, by `P` index | `M106 P<i> S<duty>`, `M107` |
//! | spindle | any [`SpindleOutput`] (a [`Spindle`]) | `M3`/`M4`/`M5` |
//! | motor power | any [`StepperEnable`] ([`MotorEnables`] for one line per driver, [`NoMotors`] for none) | `M17`/`M18`/`M84`, before motion |
//! | end-stops | `[Option<L>; N]`, `L:` [`LimitSwitch`], the thread side's own reading of each axis's switch | `M119` |
//!
//! A part the board does not have is `None` (or an empty fan array); the placeholder types
//! [`NoHeater`], [`NoSpindle`], [`NoPwm`] and [`NoLimit`] name its type.
//!
//! ```
//! use forja_drivers::heater::{HeaterChannel, HeaterConfig, PidGains};
//! use forja_app::peripherals::{
//!     DriverPeripherals, NoHeater, NoLimit, NoMotors, NoPwm, NoSpindle, Parts,
//! };
//! # use forja_hal_abstraction::{ErrorType, thermal::{Heater, TemperatureSensor}};
//! # struct Sensor; struct Element;
//! # impl ErrorType for Sensor { type Error = core::convert::Infallible; }
//! # impl TemperatureSensor for Sensor { fn read_millicelsius(&mut self) -> Result<i32, Self::Error> { Ok(25_000) } }
//! # impl ErrorType for Element { type Error = core::convert::Infallible; }
//! # impl Heater for Element { fn set_power(&mut self, _: u16) -> Result<(), Self::Error> { Ok(()) } }
//! use forja_app::controller::Peripherals;
//!
//! let gains = PidGains { kp: 0.087, ki: 0.0042, kd: 0.45 };
//! let hot_end = HeaterChannel::new(Sensor, Element, HeaterConfig::hot_end(gains));
//! let mut p: DriverPeripherals<_, NoHeater, NoPwm, NoSpindle, NoMotors, NoLimit, 3, 0> =
//!     DriverPeripherals::new(Parts {
//!         hot_end: Some(hot_end),
//!         bed: None,
//!         fans: [],
//!         spindle: None,
//!         motors: NoMotors,
//!         limits: [None, None, None],
//!         tolerance_mc: 2_000,
//!     });
//! p.poll(0).unwrap();
//! assert_eq!(p.temperatures().hot_end.unwrap().current_mc, 25_000);
//! ```
//!
//! # Execution context
//!
//! Thread (the controller's). [`Peripherals::poll`] and [`Peripherals::shutdown`] read the
//! sensors, which may block for one conversion each.

use core::convert::Infallible;

use crate::controller::{PeripheralError, Peripherals, Reading, Temperatures};
use embedded_hal::digital::OutputPin;
use embedded_hal::pwm::{self, SetDutyCycle};
use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::stepper::StepperEnable;
use forja_hal_abstraction::thermal::{Heater, TemperatureSensor};
use forja_motion::effect::{Heater as Which, Spindle as SpindleCommand};

use forja_drivers::heater::{HeaterChannel, HeaterFault, HeaterReport, PidHeater};
use forja_drivers::pwm::{Fan, Spindle, SpindleError, SpindleState};

/// A temperature control loop: what [`DriverPeripherals`] needs of a hot end or a bed.
pub trait TemperatureLoop {
    /// Read the sensor, run the controller, drive the heater (see [`HeaterChannel::poll`]).
    ///
    /// Context: thread. May block for one conversion. Errors: a fault, found now or latched.
    fn poll(&mut self, now_ms: u32) -> Result<HeaterReport, HeaterFault>;

    /// The controller: target, last measurement, fault.
    fn pid(&self) -> &PidHeater;

    /// The controller, to set a target or clear a fault.
    fn pid_mut(&mut self) -> &mut PidHeater;
}

impl<S: TemperatureSensor, H: Heater> TemperatureLoop for HeaterChannel<S, H> {
    fn poll(&mut self, now_ms: u32) -> Result<HeaterReport, HeaterFault> {
        HeaterChannel::poll(self, now_ms)
    }
    fn pid(&self) -> &PidHeater {
        HeaterChannel::pid(self)
    }
    fn pid_mut(&mut self) -> &mut PidHeater {
        HeaterChannel::pid_mut(self)
    }
}

/// A spindle: what [`DriverPeripherals`] needs of one.
pub trait SpindleOutput {
    /// Apply `state` (see [`Spindle::set`]); returns the speed commanded.
    ///
    /// Context: thread. Errors: as [`Spindle::set`].
    fn set(&mut self, state: SpindleState) -> Result<u32, SpindleError>;

    /// Stop (see [`Spindle::stop`]).
    ///
    /// Context: thread. Errors: a write failure.
    fn stop(&mut self) -> Result<(), SpindleError>;
}

impl<P: SetDutyCycle, D: OutputPin, E: OutputPin> SpindleOutput for Spindle<P, D, E> {
    fn set(&mut self, state: SpindleState) -> Result<u32, SpindleError> {
        Spindle::set(self, state)
    }
    fn stop(&mut self) -> Result<(), SpindleError> {
        Spindle::stop(self)
    }
}

/// The type of an absent heater (`None::<NoHeater>`); it has no values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoHeater {}

impl TemperatureLoop for NoHeater {
    fn poll(&mut self, _: u32) -> Result<HeaterReport, HeaterFault> {
        match *self {}
    }
    fn pid(&self) -> &PidHeater {
        match *self {}
    }
    fn pid_mut(&mut self) -> &mut PidHeater {
        match *self {}
    }
}

/// The type of an absent spindle (`None::<NoSpindle>`); it has no values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoSpindle {}

impl SpindleOutput for NoSpindle {
    fn set(&mut self, _: SpindleState) -> Result<u32, SpindleError> {
        match *self {}
    }
    fn stop(&mut self) -> Result<(), SpindleError> {
        match *self {}
    }
}

/// The PWM type of a board without fans (`fans: []`); it has no values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoPwm {}

impl pwm::ErrorType for NoPwm {
    type Error = Infallible;
}

impl SetDutyCycle for NoPwm {
    fn max_duty_cycle(&self) -> u16 {
        match *self {}
    }
    fn set_duty_cycle(&mut self, _: u16) -> Result<(), Infallible> {
        match *self {}
    }
}

/// The type of an axis without a switch on the thread side (`None::<NoLimit>`); it has no
/// values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoLimit {}

impl ErrorType for NoLimit {
    type Error = Infallible;
}

impl LimitSwitch for NoLimit {
    fn is_triggered(&mut self) -> Result<bool, Infallible> {
        match *self {}
    }
}

/// One enable line per driver, switched together: a [`StepperEnable`] for all of them.
///
/// Typically `K` [`forja_drivers::stepper::StepDir`]s with no STEP or DIR pin
/// ([`forja_drivers::pin::NoPin`]) and each driver's ENABLE pin, when the step interrupt owns the
/// STEP and DIR lines.
#[derive(Debug, Clone)]
pub struct MotorEnables<E, const K: usize>(pub [E; K]);

impl<E: StepperEnable, const K: usize> ErrorType for MotorEnables<E, K> {
    type Error = E::Error;
}

impl<E: StepperEnable, const K: usize> StepperEnable for MotorEnables<E, K> {
    /// Every line is written even when one fails; the first error is returned.
    fn set_enabled(&mut self, enabled: bool) -> Result<(), Self::Error> {
        let mut result = Ok(());
        for e in &mut self.0 {
            if let Err(err) = e.set_enabled(enabled)
                && result.is_ok()
            {
                result = Err(err);
            }
        }
        result
    }
}

/// The motors of a board without enable lines: motor power commands are accepted and do
/// nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NoMotors;

impl ErrorType for NoMotors {
    type Error = Infallible;
}

impl StepperEnable for NoMotors {
    fn set_enabled(&mut self, _: bool) -> Result<(), Infallible> {
        Ok(())
    }
}

/// What a board gives [`DriverPeripherals::new`].
#[derive(Debug)]
pub struct Parts<H, B, P, SP, M, L, const N: usize, const F: usize> {
    /// The hot end, if any.
    pub hot_end: Option<H>,
    /// The bed, if any.
    pub bed: Option<B>,
    /// The fans, by `M106` `P` index (`None` where the board has no fan).
    pub fans: [Option<Fan<P>>; F],
    /// The spindle, if any.
    pub spindle: Option<SP>,
    /// Motor power.
    pub motors: M,
    /// Each axis's switch as the thread side reads it, for `M119`.
    pub limits: [Option<L>; N],
    /// How close to its target a heater must be for `M109`/`M116` to go on, millidegrees.
    pub tolerance_mc: i32,
}

/// The generic [`Peripherals`] over this crate's drivers. See the
/// [module documentation](self).
#[derive(Debug)]
pub struct DriverPeripherals<H, B, P, SP, M, L, const N: usize, const F: usize> {
    parts: Parts<H, B, P, SP, M, L, N, F>,
    rpm: u32,
    now_ms: u32,
}

/// The speed of an `M3`/`M4`: its `S` word rounded to whole rpm, or `last` without one.
fn rpm_or(word: Option<i64>, last: u32) -> u32 {
    word.map_or(last, |v| v.clamp(0, i64::from(u32::MAX)) as u32)
}

/// The stable short name of a heater fault, for the wire.
pub const fn fault_name(fault: HeaterFault) -> &'static str {
    match fault {
        HeaterFault::Sensor => "sensor-fault",
        HeaterFault::HeatingStalled => "heating-stalled",
        HeaterFault::TemperatureDrop => "thermal-runaway",
        HeaterFault::OverTemperature => "over-temperature",
        HeaterFault::Output => "heater-output",
        HeaterFault::TargetTooHigh => "target-too-high",
    }
}

fn thermal(fault: HeaterFault) -> PeripheralError {
    match fault {
        HeaterFault::TargetTooHigh => PeripheralError::OutOfRange,
        f => PeripheralError::Thermal {
            code: f.code(),
            name: fault_name(f),
        },
    }
}

fn reading<T: TemperatureLoop>(h: &T) -> Reading {
    Reading {
        current_mc: h.pid().measured_mc().unwrap_or(0),
        target_mc: h.pid().target_mc(),
    }
}

impl<H, B, P, SP, M, L, const N: usize, const F: usize> DriverPeripherals<H, B, P, SP, M, L, N, F>
where
    H: TemperatureLoop,
    B: TemperatureLoop,
    P: SetDutyCycle,
    SP: SpindleOutput,
    M: StepperEnable,
    L: LimitSwitch,
{
    /// The peripherals of `parts`.
    pub fn new(parts: Parts<H, B, P, SP, M, L, N, F>) -> Self {
        Self {
            parts,
            rpm: 0,
            now_ms: 0,
        }
    }

    /// The parts, to inspect them.
    pub fn parts(&self) -> &Parts<H, B, P, SP, M, L, N, F> {
        &self.parts
    }

    /// The parts, mutably.
    pub fn parts_mut(&mut self) -> &mut Parts<H, B, P, SP, M, L, N, F> {
        &mut self.parts
    }

    /// Give the parts back.
    pub fn into_parts(self) -> Parts<H, B, P, SP, M, L, N, F> {
        self.parts
    }

    fn heaters(&mut self) -> [Option<&mut dyn TemperatureLoop>; 2] {
        [
            self.parts
                .hot_end
                .as_mut()
                .map(|h| h as &mut dyn TemperatureLoop),
            self.parts
                .bed
                .as_mut()
                .map(|h| h as &mut dyn TemperatureLoop),
        ]
    }
}

/// The peripherals of a board whose only part is motor power: no heater, fan or spindle, and
/// no switch read for `M119`.
pub type MotorPeripherals<M, const N: usize> =
    DriverPeripherals<NoHeater, NoHeater, NoPwm, NoSpindle, M, NoLimit, N, 0>;

impl<M: StepperEnable, const N: usize> MotorPeripherals<M, N> {
    /// The peripherals of a board with `motors` and nothing else.
    pub fn motors_only(motors: M) -> Self {
        Self::new(Parts {
            hot_end: None,
            bed: None,
            fans: [],
            spindle: None,
            motors,
            limits: [None; N],
            tolerance_mc: 0,
        })
    }
}

impl<H, B, P, SP, M, L, const N: usize, const F: usize> Peripherals<N>
    for DriverPeripherals<H, B, P, SP, M, L, N, F>
where
    H: TemperatureLoop,
    B: TemperatureLoop,
    P: SetDutyCycle,
    SP: SpindleOutput,
    M: StepperEnable,
    L: LimitSwitch,
{
    fn set_temperature(&mut self, heater: Which, millicelsius: i32) -> Result<(), PeripheralError> {
        let pid = match heater {
            Which::Extruder(None | Some(0)) => self.parts.hot_end.as_mut().map(|h| h.pid_mut()),
            Which::Bed => self.parts.bed.as_mut().map(|h| h.pid_mut()),
            Which::Extruder(Some(_)) => None,
        };
        pid.ok_or(PeripheralError::NoDevice)?
            .set_target(millicelsius)
            .map_err(thermal)
    }

    fn temperatures(&mut self) -> Temperatures {
        Temperatures {
            hot_end: self.parts.hot_end.as_ref().map(reading),
            bed: self.parts.bed.as_ref().map(reading),
        }
    }

    fn heaters_at_target(&mut self) -> bool {
        let tolerance = self.parts.tolerance_mc;
        self.heaters()
            .into_iter()
            .flatten()
            .all(|h| h.pid().is_at_target(tolerance))
    }

    fn set_fan(&mut self, index: u8, duty: u8) -> Result<(), PeripheralError> {
        self.parts
            .fans
            .get_mut(usize::from(index))
            .and_then(Option::as_mut)
            .ok_or(PeripheralError::NoDevice)?
            .set_speed(duty)
            .map_err(|_| PeripheralError::Hardware)
    }

    fn set_spindle(&mut self, command: SpindleCommand) -> Result<(), PeripheralError> {
        let spindle = self
            .parts
            .spindle
            .as_mut()
            .ok_or(PeripheralError::NoDevice)?;
        let state = match command {
            SpindleCommand::Clockwise { rpm } => SpindleState::Clockwise {
                rpm: rpm_or(rpm.and_then(|d| d.round_to_scale(0)), self.rpm),
            },
            SpindleCommand::CounterClockwise { rpm } => SpindleState::CounterClockwise {
                rpm: rpm_or(rpm.and_then(|d| d.round_to_scale(0)), self.rpm),
            },
            SpindleCommand::Off => SpindleState::Off,
        };
        match spindle.set(state) {
            Ok(_) => {
                if let SpindleState::Clockwise { rpm } | SpindleState::CounterClockwise { rpm } =
                    state
                {
                    self.rpm = rpm;
                }
                Ok(())
            }
            Err(SpindleError::NotReversible) => Err(PeripheralError::OutOfRange),
            Err(_) => Err(PeripheralError::Hardware),
        }
    }

    fn set_motors(&mut self, enabled: bool) -> Result<(), PeripheralError> {
        self.parts
            .motors
            .set_enabled(enabled)
            .map_err(|_| PeripheralError::Hardware)
    }

    fn endstops(&mut self) -> [Option<bool>; N] {
        let mut states = [None; N];
        for (state, limit) in states.iter_mut().zip(self.parts.limits.iter_mut()) {
            // A switch that cannot be read reads as triggered, as the kernel takes it.
            *state = limit.as_mut().map(|l| l.is_triggered().unwrap_or(true));
        }
        states
    }

    fn poll(&mut self, now_ms: u32) -> Result<(), PeripheralError> {
        self.now_ms = now_ms;
        let mut first = Ok(());
        for h in self.heaters().into_iter().flatten() {
            if let Err(f) = h.poll(now_ms)
                && first.is_ok()
            {
                first = Err(thermal(f));
            }
        }
        first
    }

    fn shutdown(&mut self) {
        let now_ms = self.now_ms;
        for h in self.heaters().into_iter().flatten() {
            let _ = h.pid_mut().set_target(0);
            // Apply the zero power now rather than at the next period.
            let _ = h.poll(now_ms);
        }
        for fan in self.parts.fans.iter_mut().flatten() {
            let _ = fan.off();
        }
        if let Some(s) = self.parts.spindle.as_mut() {
            let _ = s.stop();
        }
    }

    fn reset(&mut self) {
        for h in self.heaters().into_iter().flatten() {
            h.pid_mut().clear_fault();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use forja_drivers::heater::{HeaterConfig, PidGains};
    use forja_drivers::pwm::{FanConfig, SpindleConfig};

    /// A direction pin that takes every level.
    struct FakeOutput;

    impl embedded_hal::digital::ErrorType for FakeOutput {
        type Error = Infallible;
    }

    impl OutputPin for FakeOutput {
        fn set_low(&mut self) -> Result<(), Infallible> {
            Ok(())
        }
        fn set_high(&mut self) -> Result<(), Infallible> {
            Ok(())
        }
    }
    use forja_protocol::gcode::Decimal;
    use std::cell::Cell;
    use std::rc::Rc;

    /// A heater and sensor around one shared temperature: full power adds 5 °C per poll, 1 % of
    /// the rise above 20 °C is lost per poll.
    #[derive(Clone)]
    struct Plant(Rc<Cell<i32>>, Rc<Cell<Option<()>>>);

    impl ErrorType for Plant {
        type Error = forja_drivers::heater::HeaterFault;
    }

    impl TemperatureSensor for Plant {
        fn read_millicelsius(&mut self) -> Result<i32, Self::Error> {
            match self.1.get() {
                Some(()) => Err(HeaterFault::Sensor),
                None => Ok(self.0.get()),
            }
        }
    }

    impl Heater for Plant {
        fn set_power(&mut self, power: u16) -> Result<(), Self::Error> {
            let t = self.0.get();
            self.0
                .set(t + i32::from(power) * 5_000 / i32::from(u16::MAX) - (t - 20_000) / 100);
            Ok(())
        }
    }

    #[derive(Default)]
    struct Pwm(u16);

    impl pwm::ErrorType for Pwm {
        type Error = Infallible;
    }

    impl SetDutyCycle for Pwm {
        fn max_duty_cycle(&self) -> u16 {
            255
        }
        fn set_duty_cycle(&mut self, duty: u16) -> Result<(), Infallible> {
            self.0 = duty;
            Ok(())
        }
    }

    struct Switch(bool);

    impl ErrorType for Switch {
        type Error = Infallible;
    }

    impl LimitSwitch for Switch {
        fn is_triggered(&mut self) -> Result<bool, Infallible> {
            Ok(self.0)
        }
    }

    struct Enable(Rc<Cell<bool>>);

    impl ErrorType for Enable {
        type Error = Infallible;
    }

    impl StepperEnable for Enable {
        fn set_enabled(&mut self, enabled: bool) -> Result<(), Infallible> {
            self.0.set(enabled);
            Ok(())
        }
    }

    type Board = DriverPeripherals<
        HeaterChannel<Plant, Plant>,
        NoHeater,
        Pwm,
        Spindle<Pwm, FakeOutput>,
        MotorEnables<Enable, 2>,
        Switch,
        2,
        1,
    >;

    /// The board, its sensor fault switch and its enable line.
    type Rig = (Board, Rc<Cell<Option<()>>>, Rc<Cell<bool>>);

    fn board() -> Rig {
        let t = Rc::new(Cell::new(20_000));
        let fault = Rc::new(Cell::new(None));
        let plant = Plant(t.clone(), fault.clone());
        let gains = PidGains {
            kp: 0.087,
            ki: 0.0042,
            kd: 0.45,
        };
        let on = Rc::new(Cell::new(false));
        let spindle =
            Spindle::with_direction(Pwm::default(), FakeOutput, SpindleConfig::new(10_000))
                .unwrap();
        let p = DriverPeripherals::new(Parts {
            hot_end: Some(HeaterChannel::new(
                plant.clone(),
                plant,
                HeaterConfig::hot_end(gains),
            )),
            bed: None,
            fans: [Some(Fan::new(Pwm::default(), FanConfig::DIRECT).unwrap())],
            spindle: Some(spindle),
            motors: MotorEnables([Enable(on.clone()), Enable(on.clone())]),
            limits: [Some(Switch(true)), None],
            tolerance_mc: 2_000,
        });
        (p, fault, on)
    }

    #[test]
    fn heats_to_target_reports_and_waits() {
        let (mut p, _, _) = board();
        assert_eq!(
            p.set_temperature(Which::Bed, 60_000),
            Err(PeripheralError::NoDevice)
        );
        assert_eq!(
            p.set_temperature(Which::Extruder(None), 300_000),
            Err(PeripheralError::OutOfRange)
        );
        p.set_temperature(Which::Extruder(Some(0)), 200_000)
            .unwrap();
        assert!(!p.heaters_at_target());
        let mut ms = 0;
        while !p.heaters_at_target() {
            p.poll(ms).unwrap();
            ms += 100;
            assert!(ms < 200_000, "never reached the target");
        }
        let t = p.temperatures();
        assert_eq!(t.bed, None);
        let hot = t.hot_end.unwrap();
        assert_eq!(hot.target_mc, 200_000);
        assert!((hot.current_mc - 200_000).abs() <= 2_000);
    }

    #[test]
    fn a_sensor_fault_is_a_thermal_error_until_reset() {
        let (mut p, fault, _) = board();
        p.set_temperature(Which::Extruder(None), 200_000).unwrap();
        p.poll(0).unwrap();
        fault.set(Some(()));
        let e = p.poll(100).unwrap_err();
        assert_eq!(
            e,
            PeripheralError::Thermal {
                code: 210,
                name: "sensor-fault"
            }
        );
        fault.set(None);
        assert_eq!(p.poll(200), Err(e), "latched");
        assert_eq!(p.set_temperature(Which::Extruder(None), 200_000), Err(e));
        p.reset();
        p.poll(300).unwrap();
        assert_eq!(p.temperatures().hot_end.unwrap().target_mc, 0);
    }

    #[test]
    fn fans_spindle_motors_endstops_and_shutdown() {
        let (mut p, _, on) = board();
        p.set_fan(0, 128).unwrap();
        assert_eq!(p.set_fan(1, 10), Err(PeripheralError::NoDevice));
        assert_eq!(p.parts().fans[0].as_ref().unwrap().speed(), 128);
        p.set_spindle(SpindleCommand::Clockwise {
            rpm: Some(Decimal::from_integer(5_000)),
        })
        .unwrap();
        // No S: the last speed.
        p.set_spindle(SpindleCommand::CounterClockwise { rpm: None })
            .unwrap();
        assert!(matches!(
            p.parts().spindle.as_ref().unwrap().state(),
            SpindleState::CounterClockwise { rpm: 5_000 }
        ));
        p.set_motors(true).unwrap();
        assert!(on.get());
        assert_eq!(p.endstops(), [Some(true), None]);
        p.set_temperature(Which::Extruder(None), 200_000).unwrap();
        p.shutdown();
        assert_eq!(p.parts().fans[0].as_ref().unwrap().speed(), 0);
        assert_eq!(p.temperatures().hot_end.unwrap().target_mc, 0);
        assert_eq!(
            p.parts().spindle.as_ref().unwrap().state(),
            SpindleState::Off
        );
    }

    #[test]
    fn a_motors_only_board_powers_its_motors_and_has_nothing_else() {
        let on = Rc::new(Cell::new(false));
        let mut p: MotorPeripherals<_, 2> =
            MotorPeripherals::motors_only(MotorEnables([Enable(on.clone())]));
        p.set_motors(true).unwrap();
        assert!(on.get());
        p.set_motors(false).unwrap();
        assert!(!on.get());
        assert_eq!(
            p.set_temperature(Which::Extruder(None), 200_000),
            Err(PeripheralError::NoDevice)
        );
        assert_eq!(p.set_fan(0, 128), Err(PeripheralError::NoDevice));
        assert_eq!(
            p.set_spindle(SpindleCommand::Clockwise { rpm: None }),
            Err(PeripheralError::NoDevice)
        );
        assert_eq!(p.temperatures(), Temperatures::default());
        assert!(p.heaters_at_target());
        assert_eq!(p.endstops(), [None, None]);
        p.poll(0).unwrap();
    }
}
