//! Espressif ESP32-C3-DevKitM-1 wired to three step/dir driver sticks (A4988, DRV8825,
//! TMC2209 in step/dir mode) and three end-stops.
//!
//! The C3 has few free pins: of GPIO0–10 and 18–21, GPIO2, 8 and 9 are strapping pins (the
//! boot mode is read from them at reset; the DevKitM-1 also has its RGB LED on GPIO8 and the
//! BOOT button on GPIO9), GPIO18/19 are the USB Serial/JTAG port that flashes the board, and
//! GPIO11–17 belong to the SPI flash (ESP32-C3 datasheet, "Strapping Pins" and "Pin
//! Overview"; DevKitM-1 user guide, "Pin Layout"). That leaves exactly the ten pins below:
//!
//! | function | pin | why there |
//! |---|---|---|
//! | X step / dir | GPIO4 / GPIO5 | plain GPIO (JTAG pads, unused: the C3 debugs over USB) |
//! | Y step / dir | GPIO6 / GPIO7 | as above |
//! | Z step / dir | GPIO10 / GPIO21 | GPIO21 is U0TXD: the ROM's boot log toggles it, harmless on a DIR line |
//! | drivers enable (active low, shared) | GPIO3 | an input until the firmware drives it high |
//! | X / Y / Z limit (to ground, pull-up) | GPIO0 / GPIO1 / GPIO20 | GPIO0/1 are the unused 32 kHz crystal pads; GPIO20 (U0RXD) is an input at boot |
//!
//! STEP lines are on pins that nothing drives at boot, so no stray pulse reaches a driver;
//! the driver carrier's pull-up on ENABLE keeps the motors released until the firmware runs.

/// The board's name, as reported to hosts.
pub const NAME: &str = "ESP32-C3-DevKitM-1";

/// The chip, as espflash names it.
pub const CHIP: &str = "esp32c3";

/// Move this board's pins out of `$p` (esp-hal's `Peripherals`) and configure them.
macro_rules! pins {
    ($p:ident) => {
        $crate::board::configure!(
            step: [$p.GPIO4, $p.GPIO6, $p.GPIO10],
            dir: [$p.GPIO5, $p.GPIO7, $p.GPIO21],
            enable: $p.GPIO3,
            limits: [$p.GPIO0, $p.GPIO1, $p.GPIO20]
        )
    };
}
pub(crate) use pins;
