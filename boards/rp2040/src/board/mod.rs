//! The pin map: BigTreeTech SKR Pico V1.0 (RP2040, 12 MHz crystal, 2 MiB W25Q16 flash, four
//! TMC2209 drivers), the only part of the firmware that is particular to the board.
//!
//! Motor, switch and output pins are those of Klipper's
//! `config/generic-bigtreetech-skr-pico-v1.0.cfg`, so that a machine wired for it works
//! unchanged. The host link is UART0 on the board's 3-pin UART header (GPIO0 TX, GPIO1 RX,
//! 3.3 V levels), the one meant for a Raspberry Pi; the USB port is not used.
//!
//! | function | pin | Klipper's name |
//! |---|---|---|
//! | X step / dir / enable | GPIO11 / GPIO10 / GPIO12 | `stepper_x` |
//! | Y step / dir / enable | GPIO6 / GPIO5 / GPIO7 | `stepper_y` |
//! | Z step / dir / enable | GPIO19 / GPIO28 / GPIO2 | `stepper_z` |
//! | A (E socket) step / dir / enable | GPIO14 / GPIO13 / GPIO15 | `extruder` |
//! | X / Y / Z limit (to ground, pull-up) | GPIO4 / GPIO3 / GPIO25 | `endstop_pin: ^gpio4`, `^gpio3`, `^gpio25` |
//! | host UART TX / RX (UART0), 115 200 8N1 | GPIO0 / GPIO1 | (`[mcu] serial` on UART0) |
//! | hot end, bed heater (held off) | GPIO23, GPIO21 | `heater_pin` |
//! | fans (held off) | GPIO17, GPIO18, GPIO20 | `[fan]`, `[heater_fan]` |
//! | TMC2209 UART, addresses X 0, Y 2, Z 1, E 3 (not used) | GPIO8 TX / GPIO9 RX | `tx_pin`, `uart_pin` |
//!
//! Each driver has its own ENABLE line, active low. Klipper inverts the DIR lines of X, Y and E
//! (`!gpio10`) for its reference printer; here every DIR line is driven as wired, so a motor
//! that turns the wrong way is turned round at its connector.
//!
//! The TMC2209s are not configured over their UART: they run with their power-on settings,
//! whose microstep resolution comes from the MS1/MS2 pins that the board straps as UART
//! addresses (datasheet, "MS1 MS2" table): 1/8 on X (address 0), 1/64 on Y (2), 1/32 on Z (1)
//! and 1/16 on E (3). [`machine`] assumes 1/16 on every axis, so set each
//! axis's steps/mm to match (frame 00) before moving a real machine.

use core::ops::Range;

use embedded_hal::digital::PinState;
use forja_drivers::limit::Polarity;
use forja_drivers::stepper::StepDirConfig;
use forja_hal_abstraction::stepper::StepTiming;
use forja_motion::{AxisConfig, AxisKind, HomeDirection, HomingConfig, MachineConfig};
use rp2040_hal::gpio::bank0::{Gpio0, Gpio1};
use rp2040_hal::gpio::{
    self, DynPinId, FunctionSioInput, FunctionSioOutput, FunctionUart, Pin, PullDown, PullUp,
};

/// The board's name.
pub const NAME: &str = "BigTreeTech SKR Pico V1.0";

/// The crystal: 12 MHz, from which the PLL makes the 125 MHz system clock.
pub const XTAL_HZ: u32 = 12_000_000;

/// Motor outputs (step/dir/enable): X, Y, Z and A on the extruder socket.
pub const AXES: usize = 4;

/// Limit switch inputs: X, Y and Z.
pub const LIMITS: usize = 3;

/// Baud rate of the host UART (8N1).
pub const HOST_BAUD: u32 = 115_200;

/// How the TMC2209s' lines are driven: active-high STEP, active-low ENABLE, a timing that
/// covers them.
pub const DRIVERS: StepDirConfig = StepDirConfig::new(StepTiming::CONSERVATIVE);

/// The settings store: four 4 KiB sectors below the program store, at the top of the 2 MiB
/// flash (offsets from its first byte; `memory.x` keeps the code below them).
pub const SETTINGS_REGION: Range<u32> = 0x1F_4000..0x1F_8000;

/// The program store: the flash's last eight sectors.
pub const PROGRAM_REGION: Range<u32> = 0x1F_8000..0x20_0000;

/// Switches close to ground at the limit, against the input's pull-up (Klipper's `^`).
pub const LIMIT_POLARITY: Polarity = Polarity::NormallyOpen;

/// The machine until settings (frame 00) change it: the STM32F4 boards' and the simulator's
/// default (`boards/sim-hal/machines/default.toml`), a 300 × 300 mm gantry router with 100 mm of
/// Z and a rotary A, at 1/16 microstepping (see above for the SKR Pico's drivers).
///
/// | axis | steps/mm | max rate, mm/min | accel, mm/s² | travel, mm | homes |
/// |---|---|---|---|---|---|
/// | X | 80 | 6000 | 500 | 0 – 300 | to min, limit input 0, second |
/// | Y | 80 | 6000 | 500 | 0 – 300 | to min, limit input 1, second |
/// | Z | 400 | 1200 | 200 | 0 – 100 | to max, limit input 2, first |
/// | A | 80 per degree | 3600 | 720 | unlimited | no |
pub const fn machine() -> MachineConfig<AXES> {
    let x_home = HomingConfig {
        direction: HomeDirection::Min,
        seek_mm_min: 2000.0,
        locate_mm_min: 100.0,
        pull_off_mm: 2.0,
        switch: 0,
        order: 1,
    };
    let y_home = HomingConfig {
        switch: 1,
        ..x_home
    };
    let z_home = HomingConfig {
        direction: HomeDirection::Max,
        seek_mm_min: 600.0,
        locate_mm_min: 50.0,
        pull_off_mm: 1.0,
        switch: 2,
        order: 0,
    };
    let mut a = AxisConfig::linear(b'A', 80.0, 3600.0, 720.0, 0.0);
    a.kind = AxisKind::Rotary;
    a.min_mm = -100_000.0;
    a.max_mm = 100_000.0;
    MachineConfig::new([
        AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 300.0).with_homing(x_home),
        AxisConfig::linear(b'Y', 80.0, 6000.0, 500.0, 300.0).with_homing(y_home),
        AxisConfig::linear(b'Z', 400.0, 1200.0, 200.0, 100.0).with_homing(z_home),
        a,
    ])
}

/// A push-pull output, any pin.
pub type Output = Pin<DynPinId, FunctionSioOutput, PullDown>;

/// An input with its pull-up, any pin.
pub type Input = Pin<DynPinId, FunctionSioInput, PullUp>;

/// The host UART's TX and RX pins.
pub type HostUartPins = (
    Pin<Gpio0, FunctionUart, PullDown>,
    Pin<Gpio1, FunctionUart, PullDown>,
);

/// The board's GPIO, configured.
pub struct Pins {
    /// ENABLE of each motor driver, in axis order, released (high).
    pub enable: [Output; AXES],
    /// STEP of each motor, in axis order, low.
    pub step: [Output; AXES],
    /// DIR of each motor, in axis order.
    pub dir: [Output; AXES],
    /// Limit switch inputs, with pull-ups, in axis order.
    pub limits: [Input; LIMITS],
    /// The host UART's pins.
    pub uart: HostUartPins,
}

/// A pin as it comes out of reset.
type Reset<I> = Pin<I, gpio::FunctionNull, PullDown>;

/// `pin` as an output at `level`.
fn output<I>(pin: Reset<I>, level: PinState) -> Output
where
    I: gpio::PinId + gpio::ValidFunction<FunctionSioOutput>,
{
    pin.into_push_pull_output_in_state(level).into_dyn_pin()
}

/// Configure the board's pins: the drivers' ENABLE lines released first, the heaters and
/// fans off, then STEP, DIR, the switch inputs and the UART.
///
/// Context: init, first thing.
pub fn pins(p: gpio::Pins) -> Pins {
    let enable = [
        output(p.gpio12, PinState::High),
        output(p.gpio7, PinState::High),
        output(p.gpio2, PinState::High),
        output(p.gpio15, PinState::High),
    ];
    // Outputs this firmware does not drive yet: low, so that nothing heats or spins. A pin
    // keeps its function when its handle goes.
    let _off = [
        output(p.gpio23, PinState::Low),
        output(p.gpio21, PinState::Low),
        output(p.gpio17, PinState::Low),
        output(p.gpio18, PinState::Low),
        output(p.gpio20, PinState::Low),
    ];
    Pins {
        enable,
        step: [
            output(p.gpio11, PinState::Low),
            output(p.gpio6, PinState::Low),
            output(p.gpio19, PinState::Low),
            output(p.gpio14, PinState::Low),
        ],
        dir: [
            output(p.gpio10, PinState::Low),
            output(p.gpio5, PinState::Low),
            output(p.gpio28, PinState::Low),
            output(p.gpio13, PinState::Low),
        ],
        limits: [
            p.gpio4.into_pull_up_input().into_dyn_pin(),
            p.gpio3.into_pull_up_input().into_dyn_pin(),
            p.gpio25.into_pull_up_input().into_dyn_pin(),
        ],
        uart: (p.gpio0.into_function(), p.gpio1.into_function()),
    }
}
