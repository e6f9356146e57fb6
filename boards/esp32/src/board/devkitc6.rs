//! Espressif ESP32-C6-DevKitC-1 wired to three step/dir driver sticks and three end-stops.
//!
//! Avoided: the strapping pins GPIO4, 5, 8, 9 and 15 (GPIO8 also drives the RGB LED, GPIO9 is
//! the BOOT button), the USB Serial/JTAG pins GPIO12/13, UART0 on GPIO16/17 and the SPI flash
//! on GPIO24–30 (ESP32-C6 datasheet, "Strapping Pins"; DevKitC-1 user guide, "Pin Layout").
//!
//! | function | pin |
//! |---|---|
//! | X step / dir | GPIO0 / GPIO1 |
//! | Y step / dir | GPIO2 / GPIO3 |
//! | Z step / dir | GPIO6 / GPIO7 |
//! | drivers enable (active low, shared) | GPIO18 |
//! | X / Y / Z limit (to ground, pull-up) | GPIO19 / GPIO20 / GPIO21 |

/// The board's name, as reported to hosts.
pub const NAME: &str = "ESP32-C6-DevKitC-1";

/// The chip, as espflash names it.
pub const CHIP: &str = "esp32c6";

/// Move this board's pins out of `$p` (esp-hal's `Peripherals`) and configure them.
macro_rules! pins {
    ($p:ident) => {
        $crate::board::configure!(
            step: [$p.GPIO0, $p.GPIO2, $p.GPIO6],
            dir: [$p.GPIO1, $p.GPIO3, $p.GPIO7],
            enable: $p.GPIO18,
            limits: [$p.GPIO19, $p.GPIO20, $p.GPIO21]
        )
    };
}
pub(crate) use pins;
