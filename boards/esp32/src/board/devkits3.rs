//! Espressif ESP32-S3-DevKitC-1 wired to three step/dir driver sticks and three end-stops.
//!
//! Avoided: the strapping pins GPIO0, 3, 45 and 46, the USB pins GPIO19/20, UART0 on
//! GPIO43/44, the flash and PSRAM pins GPIO26–37 and the RGB LED (GPIO38 or GPIO48 depending
//! on the board revision) (ESP32-S3 datasheet, "Strapping Pins"; DevKitC-1 user guide).
//!
//! | function | pin |
//! |---|---|
//! | X step / dir | GPIO4 / GPIO5 |
//! | Y step / dir | GPIO6 / GPIO7 |
//! | Z step / dir | GPIO15 / GPIO16 |
//! | drivers enable (active low, shared) | GPIO17 |
//! | X / Y / Z limit (to ground, pull-up) | GPIO9 / GPIO10 / GPIO11 |

/// The board's name, as reported to hosts.
pub const NAME: &str = "ESP32-S3-DevKitC-1";

/// The chip, as espflash names it.
pub const CHIP: &str = "esp32s3";

/// Move this board's pins out of `$p` (esp-hal's `Peripherals`) and configure them.
macro_rules! pins {
    ($p:ident) => {
        $crate::board::configure!(
            step: [$p.GPIO4, $p.GPIO6, $p.GPIO15],
            dir: [$p.GPIO5, $p.GPIO7, $p.GPIO16],
            enable: $p.GPIO17,
            limits: [$p.GPIO9, $p.GPIO10, $p.GPIO11]
        )
    };
}
pub(crate) use pins;
