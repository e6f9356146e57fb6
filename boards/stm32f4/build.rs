//! Picks the linker memory map of the chosen board and checks that exactly one board is chosen.

use std::env;
use std::fs;
use std::path::PathBuf;

/// Board feature, memory map file.
const BOARDS: &[(&str, &str)] = &[("blackpill", "stm32f411.x"), ("qemu", "stm32f405.x")];

fn main() {
    let chosen: Vec<&(&str, &str)> = BOARDS
        .iter()
        .filter(|(feature, _)| {
            env::var_os(format!("CARGO_FEATURE_{}", feature.to_uppercase())).is_some()
        })
        .collect();
    let (feature, map) = match chosen.as_slice() {
        [one] => **one,
        _ => {
            let names: Vec<&str> = BOARDS.iter().map(|(f, _)| *f).collect();
            panic!(
                "forja-stm32f4: enable exactly one board feature ({}), e.g. \
                 `--no-default-features --features qemu`",
                names.join(", ")
            );
        }
    };
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").expect("set by cargo"));
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("set by cargo"));
    let memory = manifest.join("memory");
    for (name, source) in [("memory.x", map), ("layout.x", "layout.x")] {
        let text = fs::read(memory.join(source))
            .unwrap_or_else(|e| panic!("forja-stm32f4: cannot read memory/{source}: {e}"));
        fs::write(out.join(name), text)
            .unwrap_or_else(|e| panic!("forja-stm32f4: cannot write {name}: {e}"));
    }
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rustc-env=FORJA_BOARD={feature}");
}
