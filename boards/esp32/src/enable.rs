//! The motor drivers' shared enable line.
//!
//! Carrier boards tie the ENABLE inputs of all drivers to one pin. Each axis's [`StepDir`]
//! gets its own [`SharedEnable`] handle; the line is at the enabling level while at least one
//! axis wants its motor energised, and releases every motor when the last one lets go.
//!
//! [`StepDir`]: forja_drivers::stepper::StepDir

use core::cell::RefCell;
use core::convert::Infallible;

use critical_section::Mutex;
use embedded_hal::digital::{ErrorType, OutputPin, PinState};
use esp_hal::gpio::{Level, Output};

/// The line, which level enables, and one bit per axis that wants it.
struct Line {
    pin: Output<'static>,
    active: PinState,
    wanted: u8,
}

static LINE: Mutex<RefCell<Option<Line>>> = Mutex::new(RefCell::new(None));

/// One axis's view of the shared enable line, as an output pin for [`StepDir`].
///
/// [`StepDir`]: forja_drivers::stepper::StepDir
#[derive(Debug)]
pub struct SharedEnable {
    bit: u8,
    active: PinState,
}

/// Hand the shared line over and make one handle per axis; `active` is the level that
/// enables the drivers. The line is left as it is (released, from the pin map).
///
/// Context: init.
pub fn split<const N: usize>(pin: Output<'static>, active: PinState) -> [SharedEnable; N] {
    critical_section::with(|cs| {
        LINE.borrow(cs).replace(Some(Line {
            pin,
            active,
            wanted: 0,
        }))
    });
    core::array::from_fn(|axis| SharedEnable {
        bit: 1 << axis,
        active,
    })
}

impl ErrorType for SharedEnable {
    type Error = Infallible;
}

impl OutputPin for SharedEnable {
    fn set_low(&mut self) -> Result<(), Self::Error> {
        self.set_state(PinState::Low)
    }

    fn set_high(&mut self) -> Result<(), Self::Error> {
        self.set_state(PinState::High)
    }

    fn set_state(&mut self, state: PinState) -> Result<(), Self::Error> {
        let wants = state == self.active;
        critical_section::with(|cs| {
            if let Some(line) = LINE.borrow(cs).borrow_mut().as_mut() {
                if wants {
                    line.wanted |= self.bit;
                } else {
                    line.wanted &= !self.bit;
                }
                let level = if line.wanted != 0 {
                    line.active
                } else {
                    !line.active
                };
                line.pin.set_level(Level::from(level == PinState::High));
            }
        });
        Ok(())
    }
}
