//! Checks that exactly one chip is chosen. (The build-time WiFi settings, `FORJA_WIFI_SSID`,
//! `FORJA_WIFI_PASSWORD` and `FORJA_AP_PASSWORD`, are read by the port with `option_env!`,
//! which Cargo tracks itself.)

use std::env;

/// The chip features.
const CHIPS: &[&str] = &["esp32c3", "esp32c6", "esp32s3", "esp32"];

fn main() {
    let chosen: Vec<&str> = CHIPS
        .iter()
        .copied()
        .filter(|chip| env::var_os(format!("CARGO_FEATURE_{}", chip.to_uppercase())).is_some())
        .collect();
    if chosen.len() != 1 {
        panic!(
            "forja-esp32: enable exactly one chip feature ({}), e.g. \
             `--no-default-features --features esp32c6`",
            CHIPS.join(", ")
        );
    }
    println!("cargo:rerun-if-changed=build.rs");
}
