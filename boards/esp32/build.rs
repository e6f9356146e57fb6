//! Checks that exactly one chip is chosen, and rebuilds when the build-time WiFi settings
//! change.

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
    for var in [
        "FORJA_WIFI_SSID",
        "FORJA_WIFI_PASSWORD",
        "FORJA_AP_PASSWORD",
    ] {
        println!("cargo:rerun-if-env-changed={var}");
    }
    println!("cargo:rerun-if-changed=build.rs");
}
