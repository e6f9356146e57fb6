//! A board's description of its devices, for the controller: which it has, and what each is.
//!
//! [`Parts`] lists them, each device as a trait object of `forja_hal_abstraction::device`
//! (any driver of `forja-drivers` that implements it, or a board's own), and implements the
//! controller's [`Peripherals`]:
//!
//! | part | field | G-code |
//! |---|---|---|
//! | hot end, bed | `Option<&mut dyn TemperatureControl>` (a [`HeaterChannel`](forja_drivers::heater::HeaterChannel) over a sensor and a heater) | `M104`/`M109`/`M140`/`M116`/`M105` |
//! | fans | `[Option<&mut dyn FanControl>; F]`, by `P` index (a [`Fan`](forja_drivers::pwm::Fan)) | `M106 P<i> S<duty>`, `M107` |
//! | spindle | `Option<&mut dyn SpindleControl>` (a [`Spindle`](forja_drivers::pwm::Spindle)) | `M3`/`M4`/`M5` |
//! | coolant | `Option<&mut dyn CoolantControl>` (a [`Coolant`](forja_drivers::coolant::Coolant)) | `M7`/`M8`/`M9` |
//! | beeper | `Option<&mut dyn Beeper>` (a board's own: `forja-drivers` has none, since `embedded-hal` has no PWM whose frequency can be set) | `M300` |
//! | motor power | any [`StepperEnable`] ([`MotorEnables`] for one line per driver, [`NoMotors`] for none) | `M17`/`M18`/`M84`, before motion |
//! | end-stops | `[Option<L>; N]`, `L:` [`LimitSwitch`], the thread side's own reading of each axis's switch | `M119` |
//! | file store | `Option<&mut dyn FileStore>` (an SD card, a directory, a [`RamFileStore`](forja_hal_abstraction::files::RamFileStore)) | `M20`–`M32` |
//!
//! A device the board does not have is `None` (or no fan at all: `F` is 0). The devices are
//! lent for `'a`: a firmware board keeps them for its whole life (RTIC init locals, statics)
//! and lends them as `Send` trait objects ([`SendDevices`], the default), since it moves its
//! parts to the task that runs the controller; the simulator keeps them in its board's static
//! RAM and lends them as they are ([`LocalDevices`]: its devices share their state through
//! `Rc` on its one thread). The G-code rules (the last spindle speed, the heater tolerance of a
//! wait, what is turned off when) are the controller's, not the parts'. A board whose parts are
//! motion alone (motor power, and perhaps its switches read for `M119`) uses
//! [`MotorPeripherals`] instead ([`MotorPeripherals::motors_only`]).
//!
//! ```
//! use forja_drivers::heater::{HeaterChannel, HeaterConfig, PidGains};
//! use forja_app::controller::Peripherals;
//! use forja_app::peripherals::{NoLimit, NoMotors, Parts};
//! # use forja_hal_abstraction::{ErrorType, thermal::{Heater, TemperatureSensor}};
//! # struct Sensor; struct Element;
//! # impl ErrorType for Sensor { type Error = core::convert::Infallible; }
//! # impl TemperatureSensor for Sensor { fn read_millicelsius(&mut self) -> Result<i32, Self::Error> { Ok(25_000) } }
//! # impl ErrorType for Element { type Error = core::convert::Infallible; }
//! # impl Heater for Element { fn set_power(&mut self, _: u16) -> Result<(), Self::Error> { Ok(()) } }
//!
//! let gains = PidGains { kp: 0.087, ki: 0.0042, kd: 0.45 };
//! let mut hot_end = HeaterChannel::new(Sensor, Element, HeaterConfig::hot_end(gains));
//! let mut parts: Parts<'_, NoMotors, NoLimit, 3> = Parts {
//!     hot_end: Some(&mut hot_end),
//!     ..Parts::new(NoMotors, [None, None, None])
//! };
//! let zone = Peripherals::<3>::hot_end(&mut parts).unwrap();
//! zone.run(0).unwrap();
//! assert_eq!(zone.current_mc(), Some(25_000));
//! assert!(Peripherals::<3>::spindle(&mut parts).is_none());
//! ```
//!
//! # Execution context
//!
//! Thread (the controller's). The accessors only answer the devices; the devices' own methods
//! say what they may block on.

use core::convert::Infallible;

use forja_hal_abstraction::ErrorType;
use forja_hal_abstraction::device::{
    Beeper, CoolantControl, DeviceError, FanControl, SpindleControl, TemperatureControl,
};
use forja_hal_abstraction::files::{FileError, FileInfo, FileName, FileStore};
use forja_hal_abstraction::limit::LimitSwitch;
use forja_hal_abstraction::stepper::StepperEnable;

use crate::controller::Peripherals;

/// The trait objects a [`Parts`] lends its devices as. See the
/// [module documentation](self).
pub trait DeviceObjects {
    /// A temperature zone.
    type Zone: TemperatureControl + ?Sized;
    /// A fan.
    type Fan: FanControl + ?Sized;
    /// A spindle.
    type Spindle: SpindleControl + ?Sized;
    /// Coolant.
    type Coolant: CoolantControl + ?Sized;
    /// A beeper.
    type Beeper: Beeper + ?Sized;
    /// A file store.
    type Files: FileStore + ?Sized;
}

/// Devices lent as `Send` trait objects (`dyn TemperatureControl + Send`, …): a firmware
/// board's, whose parts move to the task that runs the controller.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SendDevices {}

impl DeviceObjects for SendDevices {
    type Zone = dyn TemperatureControl + Send;
    type Fan = dyn FanControl + Send;
    type Spindle = dyn SpindleControl + Send;
    type Coolant = dyn CoolantControl + Send;
    type Beeper = dyn Beeper + Send;
    type Files = dyn FileStore + Send;
}

/// Devices lent as they are (`dyn TemperatureControl`, …): those of a program on one thread,
/// such as the simulator's, which share their state through `Rc`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LocalDevices {}

impl DeviceObjects for LocalDevices {
    type Zone = dyn TemperatureControl;
    type Fan = dyn FanControl;
    type Spindle = dyn SpindleControl;
    type Coolant = dyn CoolantControl;
    type Beeper = dyn Beeper;
    type Files = dyn FileStore;
}

/// A board's devices, as the controller reaches them. See the [module documentation](self).
///
/// `'a`: how long the devices are lent (`'static` on a firmware board); `M`: motor power; `L`:
/// the end-stops as the thread side reads them ([`NoLimit`] for none); `N` axes; `F` fan
/// indices (0 for none); `D`: the trait objects the devices are lent as ([`SendDevices`] or
/// [`LocalDevices`]).
pub struct Parts<'a, M, L, const N: usize, const F: usize = 0, D: DeviceObjects = SendDevices> {
    /// The hot end, if any.
    pub hot_end: Option<&'a mut D::Zone>,
    /// The bed, if any.
    pub bed: Option<&'a mut D::Zone>,
    /// The fans, by `M106` `P` index (`None` where the board has no fan).
    pub fans: [Option<&'a mut D::Fan>; F],
    /// The spindle, if any.
    pub spindle: Option<&'a mut D::Spindle>,
    /// The coolant, if any.
    pub coolant: Option<&'a mut D::Coolant>,
    /// The beeper, if any.
    pub beeper: Option<&'a mut D::Beeper>,
    /// Motor power.
    pub motors: M,
    /// Each axis's switch as the thread side reads it, for `M119`.
    pub endstops: [Option<L>; N],
    /// The file store of the SD-card commands, if any.
    pub files: Option<&'a mut D::Files>,
}

impl<M, L, const N: usize, const F: usize, D: DeviceObjects> Parts<'_, M, L, N, F, D> {
    /// A board with `motors` and `endstops` and no other device; fill in the others it has
    /// (`Parts { spindle: Some(&mut spindle), ..Parts::new(motors, endstops) }`).
    pub fn new(motors: M, endstops: [Option<L>; N]) -> Self {
        Self {
            hot_end: None,
            bed: None,
            fans: core::array::from_fn(|_| None),
            spindle: None,
            coolant: None,
            beeper: None,
            motors,
            endstops,
            files: None,
        }
    }
}

// Each device is answered through the `&mut T` implementation of its trait, whatever object
// type `D` lends it as.
impl<M, L, const N: usize, const F: usize, D> Peripherals<N> for Parts<'_, M, L, N, F, D>
where
    M: StepperEnable,
    L: LimitSwitch,
    D: DeviceObjects,
{
    fn hot_end(&mut self) -> Option<&mut dyn TemperatureControl> {
        self.hot_end.as_mut().map(|z| z as _)
    }

    fn bed(&mut self) -> Option<&mut dyn TemperatureControl> {
        self.bed.as_mut().map(|z| z as _)
    }

    fn fan(&mut self, index: u8) -> Option<&mut dyn FanControl> {
        let fan = self.fans.get_mut(usize::from(index))?;
        fan.as_mut().map(|f| f as _)
    }

    fn spindle(&mut self) -> Option<&mut dyn SpindleControl> {
        self.spindle.as_mut().map(|s| s as _)
    }

    fn coolant(&mut self) -> Option<&mut dyn CoolantControl> {
        self.coolant.as_mut().map(|c| c as _)
    }

    fn beeper(&mut self) -> Option<&mut dyn Beeper> {
        self.beeper.as_mut().map(|b| b as _)
    }

    fn set_motors(&mut self, enabled: bool) -> Result<(), DeviceError> {
        power(&mut self.motors, enabled)
    }

    fn endstop(&mut self, axis: usize) -> Option<bool> {
        read_endstop(&mut self.endstops, axis)
    }

    fn files(&mut self) -> Option<&mut dyn FileStore> {
        self.files.as_mut().map(|f| f as _)
    }
}

/// The peripherals of a board whose parts are motion alone: motor power, the end-stops as
/// the thread side reads them for `M119` ([`NoLimit`]: none), and perhaps a card `C` for the
/// SD-card commands ([`NoCard`]: none). It has no heater, fan, spindle, coolant or beeper: their
/// commands are refused (`E194 no-device`; without a card the SD-card commands are answered
/// as Marlin without one answers them), and the code that drives them is left out of the
/// board's image. Every part is held by value and called without a trait object.
#[derive(Debug, Clone)]
pub struct MotorPeripherals<M, const N: usize, L = NoLimit, C = NoCard> {
    /// Motor power.
    pub motors: M,
    /// Each axis's switch as the thread side reads it, for `M119`.
    pub endstops: [Option<L>; N],
    /// The file store of the SD-card commands, if any.
    pub files: Option<C>,
}

impl<M, const N: usize> MotorPeripherals<M, N> {
    /// The peripherals of a board with `motors` and nothing else.
    pub fn motors_only(motors: M) -> Self {
        Self::new(motors, [None; N])
    }
}

impl<M, const N: usize, L, C> MotorPeripherals<M, N, L, C> {
    /// The peripherals of a board with `motors` and `endstops`, and no card.
    pub fn new(motors: M, endstops: [Option<L>; N]) -> Self {
        Self {
            motors,
            endstops,
            files: None,
        }
    }
}

impl<M: StepperEnable, const N: usize, L: LimitSwitch, C: FileStore> Peripherals<N>
    for MotorPeripherals<M, N, L, C>
{
    fn set_motors(&mut self, enabled: bool) -> Result<(), DeviceError> {
        power(&mut self.motors, enabled)
    }

    fn endstop(&mut self, axis: usize) -> Option<bool> {
        read_endstop(&mut self.endstops, axis)
    }

    fn files(&mut self) -> Option<&mut dyn FileStore> {
        self.files.as_mut().map(|f| f as _)
    }
}

/// Energise or release `motors`; a line that cannot be driven is a hardware fault.
fn power<M: StepperEnable>(motors: &mut M, enabled: bool) -> Result<(), DeviceError> {
    motors
        .set_enabled(enabled)
        .map_err(|_| DeviceError::Hardware)
}

/// The switch of `axis`, if it has one: a switch that cannot be read reads as triggered, as
/// the kernel takes it.
fn read_endstop<L: LimitSwitch>(endstops: &mut [Option<L>], axis: usize) -> Option<bool> {
    let limit = endstops.get_mut(axis)?.as_mut()?;
    Some(limit.is_triggered().unwrap_or(true))
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

/// The type of a board's card when it has none (`None::<NoCard>`); it has no values, so the
/// SD-card code is left out of the image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoCard {}

impl FileStore for NoCard {
    fn file(&mut self, _: usize) -> Result<Option<FileInfo>, FileError> {
        match *self {}
    }
    fn size(&mut self, _: &FileName) -> Result<u32, FileError> {
        match *self {}
    }
    fn read(&mut self, _: &FileName, _: u32, _: &mut [u8]) -> Result<usize, FileError> {
        match *self {}
    }
    fn remove(&mut self, _: &FileName) -> Result<(), FileError> {
        match *self {}
    }
    fn create(&mut self, _: &FileName) -> Result<(), FileError> {
        match *self {}
    }
    fn append(&mut self, _: &[u8]) -> Result<(), FileError> {
        match *self {}
    }
    fn finish(&mut self) -> Result<(), FileError> {
        match *self {}
    }
    fn abandon(&mut self) -> Result<(), FileError> {
        match *self {}
    }
    fn writing(&self) -> Option<FileName> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::peripherals::{Devices, HeatWait};
    use crate::controller::{PeripheralError, Temperatures};
    use embedded_hal::digital::OutputPin;
    use embedded_hal::pwm::{self, SetDutyCycle};
    use forja_drivers::coolant::Coolant;
    use forja_drivers::heater::{HeaterChannel, HeaterConfig, HeaterFault, PidGains};
    use forja_drivers::output::Output;
    use forja_drivers::pwm::{Fan, FanConfig, Spindle, SpindleConfig, SpindleState};
    use forja_hal_abstraction::thermal::{Heater, TemperatureSensor};
    use forja_motion::effect::{
        Coolant as CoolantCommand, Heater as Which, Spindle as SpindleCommand,
    };
    use forja_protocol::gcode::Decimal;
    use std::cell::Cell;
    use std::rc::Rc;

    /// An output pin that records its level.
    #[derive(Clone, Default)]
    struct FakeOutput(Rc<Cell<bool>>);

    impl embedded_hal::digital::ErrorType for FakeOutput {
        type Error = Infallible;
    }

    impl OutputPin for FakeOutput {
        fn set_low(&mut self) -> Result<(), Infallible> {
            self.0.set(false);
            Ok(())
        }
        fn set_high(&mut self) -> Result<(), Infallible> {
            self.0.set(true);
            Ok(())
        }
    }

    /// A heater and sensor around one shared temperature: full power adds 5 °C per poll, 1 % of
    /// the rise above 20 °C is lost per poll.
    #[derive(Clone)]
    struct Plant(Rc<Cell<i32>>, Rc<Cell<Option<()>>>);

    impl ErrorType for Plant {
        type Error = HeaterFault;
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

    /// The devices of the test board, owned by the test and lent to its parts.
    struct Owned {
        hot_end: HeaterChannel<Plant, Plant>,
        fan: Fan<Pwm>,
        spindle: Spindle<Pwm, FakeOutput>,
        coolant: Coolant<FakeOutput, FakeOutput>,
        /// The sensor fault switch, the enable line, the mist and flood lines.
        fault: Rc<Cell<Option<()>>>,
        on: Rc<Cell<bool>>,
        lines: [FakeOutput; 2],
    }

    type Board<'a> = Devices<Parts<'a, MotorEnables<Enable, 2>, Switch, 2, 1, LocalDevices>, 2>;

    /// How close to its target a heater must be, as the controller is configured.
    const TOLERANCE_MC: i32 = 2_000;

    fn owned() -> Owned {
        let t = Rc::new(Cell::new(20_000));
        let fault = Rc::new(Cell::new(None));
        let plant = Plant(t, fault.clone());
        let gains = PidGains {
            kp: 0.087,
            ki: 0.0042,
            kd: 0.45,
        };
        let lines = [FakeOutput::default(), FakeOutput::default()];
        let line = |l: &FakeOutput| Output::new(l.clone(), embedded_hal::digital::PinState::High);
        Owned {
            hot_end: HeaterChannel::new(plant.clone(), plant, HeaterConfig::hot_end(gains)),
            fan: Fan::new(Pwm::default(), FanConfig::DIRECT).unwrap(),
            spindle: Spindle::with_direction(
                Pwm::default(),
                FakeOutput::default(),
                SpindleConfig::new(10_000),
            )
            .unwrap(),
            coolant: Coolant::mist_and_flood(line(&lines[0]).unwrap(), line(&lines[1]).unwrap()),
            fault,
            on: Rc::new(Cell::new(false)),
            lines,
        }
    }

    fn board(o: &mut Owned) -> Board<'_> {
        Devices::new(Parts {
            hot_end: Some(&mut o.hot_end),
            fans: [Some(&mut o.fan)],
            spindle: Some(&mut o.spindle),
            coolant: Some(&mut o.coolant),
            ..Parts::new(
                MotorEnables([Enable(o.on.clone()), Enable(o.on.clone())]),
                [Some(Switch(true)), None],
            )
        })
    }

    #[test]
    fn heats_to_target_reports_and_waits() {
        let mut o = owned();
        let mut p = board(&mut o);
        assert_eq!(
            p.set_temperature(Which::Bed, 60_000),
            Err(PeripheralError::NoDevice)
        );
        assert_eq!(
            p.set_temperature(Which::Extruder(Some(1)), 60_000),
            Err(PeripheralError::NoDevice)
        );
        assert_eq!(
            p.set_temperature(Which::Extruder(None), 300_000),
            Err(PeripheralError::OutOfRange)
        );
        assert!(
            p.heat_done(HeatWait::ALL, TOLERANCE_MC),
            "a heater that is off holds no wait"
        );
        p.set_temperature(Which::Extruder(Some(0)), 200_000)
            .unwrap();
        assert!(!p.heat_done(HeatWait::ALL, TOLERANCE_MC));
        let mut ms = 0;
        while !p.heat_done(HeatWait::ALL, TOLERANCE_MC) {
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
        let mut o = owned();
        let fault = o.fault.clone();
        let mut p = board(&mut o);
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
        assert!(
            !p.heat_done(HeatWait::ALL, i32::MAX),
            "a faulted heater holds the wait"
        );
        assert_eq!(p.set_temperature(Which::Extruder(None), 200_000), Err(e));
        p.reset();
        p.poll(300).unwrap();
        assert_eq!(p.temperatures().hot_end.unwrap().target_mc, 0);
    }

    #[test]
    fn fans_spindle_coolant_motors_endstops_and_shutdown() {
        let mut o = owned();
        let mut p = board(&mut o);
        p.set_fan(0, 128).unwrap();
        assert_eq!(p.set_fan(1, 10), Err(PeripheralError::NoDevice));
        p.set_spindle(SpindleCommand::Clockwise {
            rpm: Some(Decimal::from_integer(5_000)),
        })
        .unwrap();
        // No S: the last speed.
        p.set_spindle(SpindleCommand::CounterClockwise { rpm: None })
            .unwrap();
        p.set_coolant(CoolantCommand::Mist).unwrap();
        p.set_coolant(CoolantCommand::Flood).unwrap();
        p.set_motors(true).unwrap();
        assert!(p.motors_on);
        assert_eq!(p.endstops(), [Some(true), None]);
        p.set_temperature(Which::Extruder(None), 200_000).unwrap();
        drop(p);
        assert_eq!(o.fan.speed(), 128);
        assert_eq!(
            o.spindle.state(),
            SpindleState::CounterClockwise { rpm: 5_000 }
        );
        assert!(
            o.coolant.is_mist_on() && o.coolant.is_flood_on(),
            "both on at once"
        );
        assert!(o.on.get());

        let mut p = board(&mut o);
        p.set_coolant(CoolantCommand::Off).unwrap();
        p.set_coolant(CoolantCommand::Flood).unwrap();
        p.shutdown();
        assert_eq!(p.temperatures().hot_end.unwrap().target_mc, 0);
        drop(p);
        assert_eq!(o.fan.speed(), 0);
        assert_eq!(o.spindle.state(), SpindleState::Off);
        assert!(!o.lines[0].0.get() && !o.lines[1].0.get(), "coolant off");
    }

    #[test]
    fn program_end_stops_the_spindle_and_the_coolant_of_the_board() {
        let mut o = owned();
        let mut p = board(&mut o);
        p.set_spindle(SpindleCommand::Clockwise { rpm: None })
            .unwrap();
        p.set_coolant(CoolantCommand::Flood).unwrap();
        p.end_program().unwrap();
        drop(p);
        assert_eq!(o.spindle.state(), SpindleState::Off);
        assert!(!o.coolant.is_flood_on());
        // A board without them has nothing to stop.
        let mut bare: Devices<MotorPeripherals<NoMotors, 2>, 2> =
            Devices::new(MotorPeripherals::motors_only(NoMotors));
        assert_eq!(bare.endstops(), [None, None]);
        bare.end_program().unwrap();
    }

    #[test]
    fn a_motors_only_board_powers_its_motors_and_has_nothing_else() {
        let on = Rc::new(Cell::new(false));
        let mut p: Devices<MotorPeripherals<_, 2>, 2> = Devices::new(
            MotorPeripherals::motors_only(MotorEnables([Enable(on.clone())])),
        );
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
        assert_eq!(
            p.set_coolant(CoolantCommand::Off),
            Err(PeripheralError::NoDevice)
        );
        assert_eq!(p.temperatures(), Temperatures::default());
        assert!(p.heat_done(HeatWait::ALL, TOLERANCE_MC));
        assert_eq!(p.endstops(), [None, None]);
        p.poll(0).unwrap();
        // With its switches read for `M119`.
        let mut p: Devices<_, 2> = Devices::new(MotorPeripherals::<_, 2, _>::new(
            NoMotors,
            [Some(Switch(true)), None],
        ));
        assert_eq!(p.endstops(), [Some(true), None]);
        assert_eq!(p.set_fan(0, 1), Err(PeripheralError::NoDevice));
        assert_eq!(p.tone(440, 200), Err(PeripheralError::NoDevice));
    }

    /// A beeper that records the tones handed to it.
    #[derive(Default)]
    struct Tones(std::vec::Vec<(u16, u16)>);

    impl Beeper for Tones {
        fn tone(&mut self, frequency_hz: u16, duration_ms: u16) -> Result<(), DeviceError> {
            self.0.push((frequency_hz, duration_ms));
            Ok(())
        }
    }

    #[test]
    fn tones_go_to_the_boards_beeper_and_are_refused_without_one() {
        let mut beeper = Tones::default();
        {
            let mut p: Devices<Parts<'_, NoMotors, NoLimit, 2, 0, LocalDevices>, 2> =
                Devices::new(Parts {
                    beeper: Some(&mut beeper),
                    ..Parts::new(NoMotors, [None, None])
                });
            p.tone(440, 200).unwrap();
            p.tone(0, 100).unwrap();
        }
        assert_eq!(beeper.0, [(440, 200), (0, 100)]);
        let mut o = owned();
        let mut p = board(&mut o);
        assert_eq!(p.tone(440, 200), Err(PeripheralError::NoDevice));
    }
}
