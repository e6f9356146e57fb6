//! The crate graph's rules, checked from `cargo metadata` (`cargo xtask test`, step "crate
//! graph").
//!
//! The layers point one way (see `docs/architecture.md`): the hardware traits and the codecs
//! (the protocol's, and the web page's HTTP and WebSocket with its assets) stand alone, the drivers know only the traits, the kernel knows no driver, application or
//! board, and the operator's client knows none of the firmware. A forbidden arrow fails the
//! check, whether it is a direct dependency or reached through another Forja crate. Only what
//! ships counts (normal and build dependencies): a test may use anything.
//!
//! Every crate under `boards/` counts as a board, a board's HAL (`boards/sim-hal`, the
//! simulator's virtual hardware) included: the kernel depends on none (its tests run it on the
//! simulator's hardware, through a dev-dependency). A board's HAL knows no firmware: neither
//! the kernel nor the application, nor a board that wires it; the firmware runs on it, not in
//! it.
//!
//! Every crate under `ports/` is a chip family's support (`forja-port-stm32f4`, …: its step
//! timer, flash, link and start-up over the chip's HAL), which the boards of that family wire:
//! no portable crate (traits, codecs, kernel, drivers, application) reaches a port, and a port
//! reaches no board.
//!
//! The firmware boards and their ports are outside the workspace (they pin their own targets),
//! so their manifests are read as well.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::process::Command;

use serde_json::Value;

use crate::root;

/// Manifests read besides the workspace's: the firmware boards.
const FIRMWARE_MANIFESTS: &[&str] = &[
    "boards/stm32f4/Cargo.toml",
    "boards/esp32/Cargo.toml",
    "boards/rp2040/Cargo.toml",
];

const HAL: &str = "forja-hal-abstraction";
const PROTOCOL: &str = "forja-protocol";
const WEB: &str = "forja-web";
const KERNEL: &str = "forja-motion";
const APP: &str = "forja-app";
const DRIVERS: &str = "forja-drivers";
const CLIENT: &str = "forja-host";
const SIMULATOR: &str = "forja-sim";
const SIMULATOR_HAL: &str = "forja-sim-hal";
const SIMULATOR_PROGRAM: &str = "forja-simulator";

/// A Forja package: whether it is a board or a chip family's support, and the Forja crates it
/// depends on (normal and build dependencies).
struct Package {
    board: bool,
    port: bool,
    deps: BTreeSet<String>,
}

/// The Forja packages of `manifest`'s workspace (or of the one package, for a firmware board).
fn packages_of(manifest: &Path, into: &mut BTreeMap<String, Package>) -> Result<(), String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "metadata",
            "--no-deps",
            "--format-version",
            "1",
            "--offline",
        ])
        .arg("--manifest-path")
        .arg(manifest)
        .current_dir(root())
        .output()
        .map_err(|e| format!("cargo metadata: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "cargo metadata --manifest-path {}: {}",
            manifest.display(),
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    let meta: Value =
        serde_json::from_slice(&out.stdout).map_err(|e| format!("cargo metadata's output: {e}"))?;
    let boards = root().join("boards");
    let ports = root().join("ports");
    for p in meta["packages"].as_array().into_iter().flatten() {
        let Some(name) = p["name"].as_str().filter(|n| n.starts_with("forja-")) else {
            continue;
        };
        let under = |dir: &Path| {
            p["manifest_path"]
                .as_str()
                .is_some_and(|m| Path::new(m).starts_with(dir))
        };
        let (board, port) = (under(&boards), under(&ports));
        let deps = p["dependencies"]
            .as_array()
            .into_iter()
            .flatten()
            .filter(|d| d["kind"].as_str() != Some("dev"))
            .filter_map(|d| d["name"].as_str())
            .filter(|n| n.starts_with("forja-"))
            .map(str::to_string)
            .collect();
        into.insert(name.to_string(), Package { board, port, deps });
    }
    Ok(())
}

/// Every Forja crate `name` reaches through its dependencies.
fn reach(name: &str, packages: &BTreeMap<String, Package>) -> BTreeSet<String> {
    let mut seen = BTreeSet::new();
    let mut todo = vec![name.to_string()];
    while let Some(n) = todo.pop() {
        for d in packages.get(&n).map(|p| &p.deps).into_iter().flatten() {
            if seen.insert(d.clone()) {
                todo.push(d.clone());
            }
        }
    }
    seen
}

/// Whether `name` is a board's HAL: a crate under `boards/` named `…-hal`.
fn is_board_hal(name: &str, packages: &BTreeMap<String, Package>) -> bool {
    name.ends_with("-hal") && packages.get(name).is_some_and(|p| p.board)
}

/// The crates `name` must not reach, with the reason.
fn forbidden(name: &str, packages: &BTreeMap<String, Package>) -> Vec<(String, &'static str)> {
    let boards = packages
        .iter()
        .filter(|(_, p)| p.board)
        .map(|(n, _)| n.clone());
    let ports = || {
        packages
            .iter()
            .filter(|(_, p)| p.port)
            .map(|(n, _)| (n.clone(), "portable crates name no chip"))
    };
    let named = |list: &[&str], why: &'static str| -> Vec<(String, &'static str)> {
        list.iter().map(|n| (n.to_string(), why)).collect()
    };
    match name {
        HAL | PROTOCOL | WEB => packages
            .keys()
            .filter(|n| n.as_str() != name)
            .map(|n| (n.clone(), "the traits and the codecs stand alone"))
            .collect(),
        DRIVERS => {
            let mut v = named(
                &[KERNEL, APP],
                "a driver implements the traits of hal-abstraction only",
            );
            v.extend(ports());
            v
        }
        APP => ports().collect(),
        KERNEL => {
            let mut v = named(
                &[DRIVERS, APP],
                "the kernel reaches hardware through traits",
            );
            v.extend(boards.map(|b| (b, "the kernel is board-agnostic")));
            v.extend(ports());
            v
        }
        port if packages.get(port).is_some_and(|p| p.port) => boards
            .map(|b| (b, "a chip's support knows no board that wires it"))
            .collect(),
        CLIENT => named(
            &[KERNEL, APP, SIMULATOR, SIMULATOR_HAL, SIMULATOR_PROGRAM],
            "the client speaks the protocol, it does not embed the firmware",
        ),
        SIMULATOR => named(
            &[SIMULATOR_PROGRAM],
            "the board knows no program that runs it",
        ),
        hal if is_board_hal(hal, packages) => {
            let mut v = named(
                &[KERNEL, APP, SIMULATOR_PROGRAM],
                "a board's HAL knows no firmware",
            );
            v.extend(
                boards
                    .filter(|b| b != hal)
                    .map(|b| (b, "a board's HAL knows no board that wires it")),
            );
            v
        }
        _ => Vec::new(),
    }
}

/// Check the rules; the error lists every forbidden arrow.
pub fn check() -> Result<(), String> {
    let mut packages = BTreeMap::new();
    packages_of(&root().join("Cargo.toml"), &mut packages)?;
    for m in FIRMWARE_MANIFESTS {
        packages_of(&root().join(m), &mut packages)?;
    }
    for must in [
        HAL,
        PROTOCOL,
        WEB,
        KERNEL,
        APP,
        DRIVERS,
        CLIENT,
        SIMULATOR,
        SIMULATOR_HAL,
        SIMULATOR_PROGRAM,
    ] {
        if !packages.contains_key(must) {
            return Err(format!("no package {must} in the workspace"));
        }
    }
    let mut wrong = Vec::new();
    for name in packages.keys() {
        let reached = reach(name, &packages);
        for (to, why) in forbidden(name, &packages) {
            if reached.contains(&to) {
                wrong.push(format!("{name} → {to} ({why})"));
            }
        }
    }
    if wrong.is_empty() {
        eprintln!("{} Forja crates, no forbidden arrow", packages.len());
        Ok(())
    } else {
        Err(format!("forbidden arrows:\n  {}", wrong.join("\n  ")))
    }
}
