//! Wemos D1 R32 (ESPDUINO-32, an ESP32 in the Arduino Uno form factor) with a Protoneer
//! Arduino CNC Shield V3, wired as grblHAL's `espduino-32_wemos_d1_r32_uno_map.h`, so that the
//! shields made for GRBL work unchanged.
//!
//! | function | pin | shield |
//! |---|---|---|
//! | X step / dir | GPIO26 / GPIO16 | D2 / D5 |
//! | Y step / dir | GPIO25 / GPIO27 | D3 / D6 |
//! | Z step / dir | GPIO17 / GPIO14 | D4 / D7 |
//! | drivers enable (active low, shared) | GPIO12 | D8 |
//! | X / Y / Z limit (to ground, pull-up) | GPIO13 / GPIO5 / GPIO23 | D9 / D10 / D11 |
//!
//! GPIO12 (MTDI) and GPIO5 are strapping pins of the ESP32: MTDI high at reset selects a
//! 1.8 V flash supply, which a 3.3 V flash module does not boot from. Nothing on the shield
//! may hold GPIO12 high at reset (no pull-up on the shield's EN line).

/// The board's name, as reported to hosts.
pub const NAME: &str = "Wemos D1 R32 + CNC Shield V3";

/// The chip, as espflash names it.
pub const CHIP: &str = "esp32";

/// Move this board's pins out of `$p` (esp-hal's `Peripherals`) and configure them.
macro_rules! pins {
    ($p:ident) => {
        $crate::board::configure!(
            step: [$p.GPIO26, $p.GPIO25, $p.GPIO17],
            dir: [$p.GPIO16, $p.GPIO27, $p.GPIO14],
            enable: $p.GPIO12,
            limits: [$p.GPIO13, $p.GPIO5, $p.GPIO23]
        )
    };
}
pub(crate) use pins;
