//! The machine's devices as the application commands them: temperature zones, fans, the
//! spindle, coolant, general-purpose outputs and the beeper.
//!
//! Each trait is one thing a driver can do, object-safe, so that the application holds a
//! board's devices uniformly (`&mut dyn FanControl`, …) and a board lists what it has. Motor
//! power ([`crate::stepper::StepperEnable`]) and end-stops ([`crate::limit::LimitSwitch`]) are
//! devices too, with their own traits. A touch probe is a switch read by the step interrupt as
//! an end-stop is, and fulfils [`crate::limit::LimitSwitch`]; a file store (an SD card) is
//! [`crate::files::FileStore`].
//!
//! # Contract
//!
//! - **Context**: thread (the application's: the task or main loop that runs the controller),
//!   never an interrupt. Only [`TemperatureControl::run`] may block, for one sensor conversion.
//! - **Errors**: one small [`DeviceError`] for every device, so that the application reports
//!   any of them the same way (`forja-app` sends [`DeviceError::Hardware`] as `E196
//!   device-fault`, [`DeviceError::OutOfRange`] as `E195 device-range`, and a
//!   [`DeviceError::Thermal`] fault with the code it carries). A device that cannot do what it
//!   was told changes nothing, unless its documentation says otherwise.
//! - **What the application guarantees**: it calls a device only in the order of the G-code
//!   stream and at the moment the command takes effect (after the motion before it, where the
//!   command waits for it); it applies the G-code rules itself (an `M3` without `S` runs at the
//!   last speed commanded, an `M109` waits for a target within the machine's tolerance): a
//!   device applies exactly what it is told, and keeps no memory of earlier commands beyond its
//!   own state. On alarms and emergency stops it turns every device off.
//!
//! | trait | what | G-code (in `forja-app`) |
//! |---|---|---|
//! | [`TemperatureControl`] | one controlled zone: a hot end, a bed | `M104`/`M109`/`M140`/`M190`/`M116`/`M105`/`M155` |
//! | [`FanControl`] | a fan, duty 0–255 | `M106`/`M107` |
//! | [`SpindleControl`] | a spindle (or a laser), direction and speed | `M3`/`M4`/`M5` |
//! | [`CoolantControl`] | mist and flood coolant | `M7`/`M8`/`M9` |
//! | [`DigitalOutput`] | one general-purpose output, on or off; the power supply's switch | `M42`; `M80`/`M81` |
//! | [`Beeper`] | a buzzer or a speaker that plays tones one after another | `M300` |

use core::fmt;

use crate::{Error, ErrorKind};

/// A device refused a command or reported a fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum DeviceError {
    /// An output or a bus could not be driven.
    Hardware,
    /// A value or a command the device cannot take: a target above its maximum, a direction
    /// it cannot turn, a coolant line it does not have. Nothing changed.
    OutOfRange,
    /// A temperature zone shut itself down (sensor fault, heating stalled, thermal runaway,
    /// over-temperature, heater output fault). The fault is latched until
    /// [`TemperatureControl::clear_fault`].
    Thermal {
        /// The driver's stable wire code (200–299).
        code: u16,
        /// The driver's stable short name (kebab-case).
        name: &'static str,
    },
}

impl fmt::Display for DeviceError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Hardware => f.write_str("device output fault"),
            Self::OutOfRange => f.write_str("value out of the device's range"),
            Self::Thermal { code, name } => write!(f, "thermal fault {code} {name}"),
        }
    }
}

impl Error for DeviceError {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Hardware | Self::Thermal { .. } => ErrorKind::Hardware,
            Self::OutOfRange => ErrorKind::OutOfRange,
        }
    }
}

/// One temperature zone under closed-loop control (a hot end, a bed): a sensor, a heating
/// element and the loop between them, with its thermal protection.
pub trait TemperatureControl {
    /// Set the target in thousandths of a degree Celsius; 0 (or below) turns the heater off.
    ///
    /// Context: thread. Never blocks. Errors: [`DeviceError::OutOfRange`] for a target above
    /// the zone's maximum (the old target stays); the latched fault ([`DeviceError::Thermal`])
    /// until [`TemperatureControl::clear_fault`].
    fn set_target_mc(&mut self, target_mc: i32) -> Result<(), DeviceError>;

    /// The target, millidegrees; 0 when the heater is off.
    ///
    /// Context: thread. Never blocks. Cannot fail.
    fn target_mc(&self) -> i32;

    /// The last temperature measured by [`TemperatureControl::run`], millidegrees; `None`
    /// before the first.
    ///
    /// Context: thread. Never blocks: no sensor is read. Cannot fail.
    fn current_mc(&self) -> Option<i32>;

    /// The heater power the last [`TemperatureControl::run`] applied, 0 (off) to
    /// [`FULL_POWER`](crate::thermal::FULL_POWER) (the `@:` of a temperature report).
    ///
    /// Context: thread. Never blocks. Cannot fail.
    fn power(&self) -> u16;

    /// Run the loop once at `now_ms` (a wrapping millisecond clock): read the sensor, drive
    /// the heater. The application calls it at a fixed period, and once more after a target
    /// of 0 to turn the heater off at once.
    ///
    /// Context: thread. May block for one sensor conversion. Errors: a fault found now or
    /// latched before ([`DeviceError::Thermal`]); the zone has turned its heater off (as far
    /// as its output still obeys) and cleared its target.
    fn run(&mut self, now_ms: u32) -> Result<(), DeviceError>;

    /// The latched fault, if any.
    ///
    /// Context: thread. Never blocks. Cannot fail.
    fn fault(&self) -> Option<DeviceError>;

    /// Clear a latched fault (an operator's reset). The heater stays off until a new target.
    ///
    /// Context: thread. Never blocks. Cannot fail.
    fn clear_fault(&mut self);
}

impl<T: TemperatureControl + ?Sized> TemperatureControl for &mut T {
    fn set_target_mc(&mut self, target_mc: i32) -> Result<(), DeviceError> {
        T::set_target_mc(self, target_mc)
    }
    fn target_mc(&self) -> i32 {
        T::target_mc(self)
    }
    fn current_mc(&self) -> Option<i32> {
        T::current_mc(self)
    }
    fn power(&self) -> u16 {
        T::power(self)
    }
    fn run(&mut self, now_ms: u32) -> Result<(), DeviceError> {
        T::run(self, now_ms)
    }
    fn fault(&self) -> Option<DeviceError> {
        T::fault(self)
    }
    fn clear_fault(&mut self) {
        T::clear_fault(self)
    }
}

/// A fan.
pub trait FanControl {
    /// Run at `duty` out of 255 (the RepRap scale of `M106 S`); 0 stops the fan.
    ///
    /// Context: thread. Never blocks. Errors: [`DeviceError::Hardware`]: the output could not
    /// be driven.
    fn set_duty(&mut self, duty: u8) -> Result<(), DeviceError>;
}

impl<T: FanControl + ?Sized> FanControl for &mut T {
    fn set_duty(&mut self, duty: u8) -> Result<(), DeviceError> {
        T::set_duty(self, duty)
    }
}

/// Which way a spindle turns, seen from above the tool.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Rotation {
    /// Clockwise (`M3`).
    Clockwise,
    /// Counter-clockwise (`M4`).
    CounterClockwise,
}

/// A spindle, or a laser or a torch driven like one.
pub trait SpindleControl {
    /// Turn `rotation` at `rpm` revolutions a minute. The driver clamps `rpm` to what the
    /// spindle can run (a speed above its maximum runs at the maximum).
    ///
    /// Context: thread. Never blocks (waiting for the spindle to reach its speed is the
    /// program's business). Errors: [`DeviceError::OutOfRange`] for a direction the spindle
    /// cannot turn (nothing changed); [`DeviceError::Hardware`] for a write failure, after
    /// which the spindle's state is unknown.
    fn run(&mut self, rotation: Rotation, rpm: u32) -> Result<(), DeviceError>;

    /// Stop (`M5`).
    ///
    /// Context: thread. Never blocks. Errors: [`DeviceError::Hardware`].
    fn stop(&mut self) -> Result<(), DeviceError>;
}

impl<T: SpindleControl + ?Sized> SpindleControl for &mut T {
    fn run(&mut self, rotation: Rotation, rpm: u32) -> Result<(), DeviceError> {
        T::run(self, rotation, rpm)
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        T::stop(self)
    }
}

/// Coolant, as grbl and LinuxCNC have it: mist (`M7`) and flood (`M8`), each on or off on its
/// own; `M9` turns both off.
pub trait CoolantControl {
    /// Turn the mist coolant on or off.
    ///
    /// Context: thread. Never blocks. Errors: [`DeviceError::OutOfRange`] to turn on a mist
    /// line the board does not have (nothing changed); [`DeviceError::Hardware`].
    fn set_mist(&mut self, on: bool) -> Result<(), DeviceError>;

    /// Turn the flood coolant on or off.
    ///
    /// Context: thread. Never blocks. Errors: as [`CoolantControl::set_mist`], for the flood
    /// line.
    fn set_flood(&mut self, on: bool) -> Result<(), DeviceError>;
}

impl<T: CoolantControl + ?Sized> CoolantControl for &mut T {
    fn set_mist(&mut self, on: bool) -> Result<(), DeviceError> {
        T::set_mist(self, on)
    }
    fn set_flood(&mut self, on: bool) -> Result<(), DeviceError> {
        T::set_flood(self, on)
    }
}

/// One general-purpose output (a relay, a vacuum, a clamp): on or off. The driver applies the
/// line's polarity: `true` always means "on".
pub trait DigitalOutput {
    /// Switch the output on (`true`) or off.
    ///
    /// Context: thread. Never blocks. Errors: [`DeviceError::Hardware`].
    fn set_on(&mut self, on: bool) -> Result<(), DeviceError>;
}

impl<T: DigitalOutput + ?Sized> DigitalOutput for &mut T {
    fn set_on(&mut self, on: bool) -> Result<(), DeviceError> {
        T::set_on(self, on)
    }
}

/// The fewest tones a [`Beeper`] keeps waiting behind the one it sounds: Marlin's tone queue,
/// so that a short tune of `M300` lines plays whole.
pub const MIN_WAITING_TONES: usize = 4;

/// A beeper: a buzzer or a speaker that plays tones one after another, as Marlin's beeper does
/// (its tones are queued, so that consecutive `M300` lines make a tune).
///
/// The beeper times its tones itself (a timer, or hardware that stops on its own): the
/// application hands it each tone and never waits for one.
pub trait Beeper {
    /// Sound `frequency_hz` for `duration_ms` once the tones handed over before it have
    /// played (at once when none is sounding), then stop. A `frequency_hz` of 0 is silence
    /// for `duration_ms`: a pause before the next tone. A pitch the beeper cannot sound is
    /// sounded as near as it can (an active buzzer, which has one pitch, sounds its own).
    ///
    /// The beeper keeps at least [`MIN_WAITING_TONES`] tones waiting behind the one it
    /// sounds; a tone beyond those it keeps is not played, and that is not an error: a tone
    /// is a notice, not worth stopping a program for.
    ///
    /// Context: thread. Never blocks: returns before the tone has sounded. Errors:
    /// [`DeviceError::Hardware`]: the output could not be driven.
    fn tone(&mut self, frequency_hz: u16, duration_ms: u16) -> Result<(), DeviceError>;
}

impl<T: Beeper + ?Sized> Beeper for &mut T {
    fn tone(&mut self, frequency_hz: u16, duration_ms: u16) -> Result<(), DeviceError> {
        T::tone(self, frequency_hz, duration_ms)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use std::string::ToString;

    use super::*;

    /// A fan that records its duty.
    struct Duty(u8);

    impl FanControl for Duty {
        fn set_duty(&mut self, duty: u8) -> Result<(), DeviceError> {
            self.0 = duty;
            Ok(())
        }
    }

    #[test]
    fn devices_are_held_as_trait_objects_and_lent() {
        let mut fan = Duty(0);
        {
            let mut lent = &mut fan;
            let held: &mut dyn FanControl = &mut lent;
            held.set_duty(128).unwrap();
        }
        assert_eq!(fan.0, 128);
    }

    /// A beeper that records the tones handed to it.
    struct Tones(std::vec::Vec<(u16, u16)>);

    impl Beeper for Tones {
        fn tone(&mut self, frequency_hz: u16, duration_ms: u16) -> Result<(), DeviceError> {
            self.0.push((frequency_hz, duration_ms));
            Ok(())
        }
    }

    #[test]
    fn a_beeper_is_lent_as_a_trait_object() {
        let mut beeper = Tones(std::vec::Vec::new());
        {
            let mut lent = &mut beeper;
            let held: &mut dyn Beeper = &mut lent;
            held.tone(440, 200).unwrap();
            held.tone(0, 100).unwrap();
        }
        assert_eq!(beeper.0, [(440, 200), (0, 100)]);
    }

    #[test]
    fn errors_have_kinds_and_text() {
        let thermal = DeviceError::Thermal {
            code: 212,
            name: "thermal-runaway",
        };
        assert_eq!(thermal.kind(), ErrorKind::Hardware);
        assert_eq!(DeviceError::OutOfRange.kind(), ErrorKind::OutOfRange);
        assert_eq!(DeviceError::Hardware.kind(), ErrorKind::Hardware);
        assert_eq!(thermal.to_string(), "thermal fault 212 thermal-runaway");
    }
}
