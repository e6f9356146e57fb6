//! Pin maps: the only part of the firmware that differs from one ESP32 board to another.
//!
//! Each board module names the board and moves its pins out of esp-hal's `Peripherals` with a
//! `pins!` macro (a macro, because the pins are distinct fields of that struct and the rest of
//! it is still needed by [`crate::hardware`]). Every map has the same shape:
//!
//! | item | what |
//! |---|---|
//! | `NAME` | the board's name |
//! | `CHIP` | the chip, as espflash names it |
//! | `pins!(peripherals)` | the GPIO pins configured into [`Pins`] |
//!
//! Exactly one chip feature is enabled; `build.rs` rejects zero or two.

use esp_hal::gpio::{Input, Output};
use forja_drivers::limit::Polarity;
use forja_drivers::stepper::StepDirConfig;
use forja_hal_abstraction::stepper::StepTiming;
use forja_motion::{AxisConfig, HomeDirection, HomingConfig, MachineConfig};

#[cfg(feature = "esp32c3")]
mod devkitm1;
#[cfg(feature = "esp32c3")]
pub use devkitm1::*;

#[cfg(feature = "esp32c6")]
mod devkitc6;
#[cfg(feature = "esp32c6")]
pub use devkitc6::*;

#[cfg(feature = "esp32s3")]
mod devkits3;
#[cfg(feature = "esp32s3")]
pub use devkits3::*;

#[cfg(feature = "esp32")]
mod d1r32;
#[cfg(feature = "esp32")]
pub use d1r32::*;

/// Motor outputs (step/dir pairs) on every map: X, Y and Z.
pub const AXES: usize = 3;

/// Limit switch inputs on every map: X, Y and Z.
pub const LIMITS: usize = 3;

/// How the motor driver lines are driven: active-high STEP, active-low ENABLE, and a timing
/// that covers the A4988, DRV8825 and TMC2209 sticks of the usual carrier boards.
pub const DRIVERS: StepDirConfig = StepDirConfig::new(StepTiming::CONSERVATIVE);

/// The machine the kernel is built from where no stored setting says otherwise (frame 00
/// `x.steps_per_mm` etc. override it): a small three-axis router, X and Y on GT2 belts with
/// 20-tooth pulleys at 1/16 microstep (80 steps/mm), Z on an 8 mm lead screw (400 steps/mm).
/// Each axis homes on its own switch (limit input `i` for axis `i`): Z up first, then X and Y
/// to their minimum.
pub const MACHINE: MachineConfig<AXES> = MachineConfig::new([
    AxisConfig::linear(b'X', 80.0, 3_000.0, 500.0, 300.0).with_homing(homing(
        HomeDirection::Min,
        0,
        1,
    )),
    AxisConfig::linear(b'Y', 80.0, 3_000.0, 500.0, 300.0).with_homing(homing(
        HomeDirection::Min,
        1,
        1,
    )),
    AxisConfig::linear(b'Z', 400.0, 600.0, 100.0, 80.0).with_homing(homing(
        HomeDirection::Max,
        2,
        0,
    )),
]);

/// Homing of one axis of [`MACHINE`] towards `direction` on limit input `switch`.
const fn homing(direction: HomeDirection, switch: u8, order: u8) -> HomingConfig {
    HomingConfig {
        direction,
        seek_mm_min: 500.0,
        locate_mm_min: 50.0,
        pull_off_mm: 2.0,
        switch,
        order,
    }
}

/// Switches close to ground at the limit, against the input's pull-up.
pub const LIMIT_POLARITY: Polarity = Polarity::NormallyOpen;

/// The board's GPIO, configured.
pub struct Pins {
    /// STEP output of each motor, in axis order, idle low.
    pub step: [Output<'static>; AXES],
    /// DIR output of each motor, in axis order.
    pub dir: [Output<'static>; AXES],
    /// The enable line shared by every motor driver (active low), released.
    pub enable: Output<'static>,
    /// Limit switch inputs, with pull-ups, in axis order.
    pub limits: [Input<'static>; LIMITS],
}

/// Configure the pins of one map: STEP and DIR low, ENABLE released (high), limit inputs with
/// pull-ups. Used by the maps' `pins!` macros.
macro_rules! configure {
    (step: [$($s:expr),+], dir: [$($d:expr),+], enable: $e:expr, limits: [$($l:expr),+]) => {{
        use esp_hal::gpio::{Input, InputConfig, Level, Output, OutputConfig, Pull};
        let out = || OutputConfig::default();
        let input = || InputConfig::default().with_pull(Pull::Up);
        $crate::board::Pins {
            // The enable line first: the drivers stay released while the others are set up.
            enable: Output::new($e, Level::High, out()),
            step: [$(Output::new($s, Level::Low, out())),+],
            dir: [$(Output::new($d, Level::Low, out())),+],
            limits: [$(Input::new($l, input())),+],
        }
    }};
}
pub(crate) use configure;
