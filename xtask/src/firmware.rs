//! Firmware boards: `cargo xtask build | flash | qemu | size`, and their steps in `test`.
//!
//! Every firmware crate is described by one [`Firmware`] entry in [`BOARDS`]: adding a board
//! is adding an entry. A board has one or more variants (Cargo features: pin maps or chips);
//! `test` formats, lints and builds every variant that is built by default, and `size` checks
//! them against the board's budget, and the operator's web page (`forja-web`, embedded in the
//! ESP32 images) against its own.

use std::path::{Path, PathBuf};
use std::process::Command;

use object::read::elf::{ElfFile32, FileHeader, ProgramHeader};
use object::{Object, ObjectSection, ObjectSymbol};

use forja_sim_hal::link::forja_web;

use crate::qemu;
use crate::{Step, root};

/// How a variant's image gets onto the hardware.
pub enum Flasher {
    /// probe-rs through a debug probe, with this probe-rs chip name.
    ProbeRs(&'static str),
    /// espflash over the chip's USB or UART boot loader, with this espflash chip name. The
    /// build also writes a merged image (`<board>-<variant>.bin`) that any ESP flasher writes at
    /// offset 0.
    Espflash(&'static str),
}

/// The Rust toolchain a variant builds with.
pub enum Toolchain {
    /// The toolchain of `rust-toolchain.toml` (its target added with rustup when missing).
    Pinned,
    /// Espressif's `esp` toolchain for the Xtensa chips, installed with `espup`; the core
    /// library is built from source (`-Zbuild-std=core,alloc`).
    Esp,
}

/// One variant of a firmware crate (a Cargo feature: a pin map or a chip).
pub struct Variant {
    /// The Cargo feature that selects it.
    pub feature: &'static str,
    /// What it is, for messages.
    pub describe: &'static str,
    /// The Rust target.
    pub target: &'static str,
    /// The toolchain it needs.
    pub toolchain: Toolchain,
    /// How it is flashed, for variants that run on hardware.
    pub flasher: Option<Flasher>,
    /// Whether this variant runs in QEMU (`cargo xtask qemu`).
    pub qemu: bool,
    /// Built by `build` without `--variant`, and by `test` and `size`. The others need a
    /// toolchain or target that CI does not install, and are built on request.
    pub by_default: bool,
    /// The most code (flash bytes, as `size` counts them) the image may have: the room kept
    /// for the features to come below the chip's budget. `size` and `test` fail above it.
    pub code_target: Option<u64>,
}

/// How an image's sections map onto the chip's memories, for `size`.
pub enum MemoryMap {
    /// `cortex-m-rt`: flash at this origin (vector table, code, read-only data, `.data`
    /// initial values); RAM is `.data`, `.bss`, `.uninit` and the `_stack_reserve` symbol;
    /// core-coupled RAM is `.ccmram`.
    CortexM {
        /// The flash origin.
        flash_origin: u64,
    },
    /// esp-hal's `linkall.x` (ESP32-C3 and kin): the image holds every loaded segment and
    /// goes into an app partition; RAM is the code and data placed in SRAM (`.trap`,
    /// `.rwtext*`, `.data*`, `.bss*`, `.noinit`); the stack is all the RAM left (`.stack`);
    /// the RAM the ROM boot loader used, reclaimed for the heap, is `.dram2_uninit`.
    Esp,
}

/// The memory an image must fit.
pub struct Budget {
    /// The smallest chip the image must fit.
    pub chip: &'static str,
    /// Bytes of flash for the image (the app partition on an ESP32).
    pub flash: u64,
    /// Bytes of RAM for the image (main SRAM; core-coupled and reclaimed RAM are reported
    /// apart).
    pub ram: u64,
    /// How to read the image's sections.
    pub map: MemoryMap,
}

/// A firmware crate, excluded from the root workspace and built here: the root of a workspace
/// of its own, with its family's chip support (`ports/<family>`) as the other member.
pub struct Firmware {
    /// The name on the command line.
    pub name: &'static str,
    /// The crate's directory, from the workspace root.
    pub dir: &'static str,
    /// The binary's name.
    pub bin: &'static str,
    /// Its variants; the first hardware one is the default for `flash`.
    pub variants: &'static [Variant],
    /// What `size` checks the default images against.
    pub budget: Budget,
    /// The partition table espflash writes, from the crate's directory (ESP32 boards).
    pub partition_table: Option<&'static str>,
}

/// Every firmware board.
pub const BOARDS: &[Firmware] = &[
    Firmware {
        name: "stm32f4",
        dir: "boards/stm32f4",
        bin: "forja-stm32f4",
        variants: &[
            Variant {
                feature: "blackpill",
                describe: "Black Pill STM32F411CE, grblHAL breakout pin-out",
                target: "thumbv7em-none-eabihf",
                toolchain: Toolchain::Pinned,
                flasher: Some(Flasher::ProbeRs("STM32F411CEUx")),
                qemu: false,
                by_default: true,
                // 160 KiB of the STM32F401's 256 (less the 48 KiB of vector table and stores).
                code_target: Some(160 * 1024),
            },
            Variant {
                feature: "qemu",
                describe: "QEMU netduinoplus2 (STM32F405), CNC Shield V3 pin-out",
                target: "thumbv7em-none-eabihf",
                toolchain: Toolchain::Pinned,
                flasher: None,
                qemu: true,
                by_default: true,
                code_target: None,
            },
        ],
        budget: Budget {
            chip: "STM32F401",
            flash: 256 * 1024,
            ram: 64 * 1024,
            map: MemoryMap::CortexM {
                flash_origin: 0x0800_0000,
            },
        },
        partition_table: None,
    },
    Firmware {
        name: "esp32",
        dir: "boards/esp32",
        bin: "forja-esp32",
        variants: &[
            Variant {
                feature: "esp32c3",
                describe: "ESP32-C3-DevKitM-1, three step/dir drivers",
                target: "riscv32imc-unknown-none-elf",
                toolchain: Toolchain::Pinned,
                flasher: Some(Flasher::Espflash("esp32c3")),
                qemu: false,
                by_default: true,
                code_target: None,
            },
            Variant {
                feature: "esp32c6",
                describe: "ESP32-C6-DevKitC-1, three step/dir drivers",
                target: "riscv32imac-unknown-none-elf",
                toolchain: Toolchain::Pinned,
                flasher: Some(Flasher::Espflash("esp32c6")),
                qemu: false,
                by_default: false,
                code_target: None,
            },
            Variant {
                feature: "esp32s3",
                describe: "ESP32-S3-DevKitC-1, three step/dir drivers",
                target: "xtensa-esp32s3-none-elf",
                toolchain: Toolchain::Esp,
                flasher: Some(Flasher::Espflash("esp32s3")),
                qemu: false,
                by_default: false,
                code_target: None,
            },
            Variant {
                feature: "esp32",
                describe: "Wemos D1 R32 (ESP32) with a CNC Shield V3",
                target: "xtensa-esp32-none-elf",
                toolchain: Toolchain::Esp,
                flasher: Some(Flasher::Espflash("esp32")),
                qemu: false,
                by_default: false,
                code_target: None,
            },
        ],
        // The ESP32-C3 is the smallest of the four chips: 400 KiB of SRAM, of which esp-hal's
        // linker script gives the program about 320 KiB (the rest is cache and ROM data); a
        // 4 MiB flash whose app partition (partitions.csv) is 1.25 MiB, the rest the stores.
        budget: Budget {
            chip: "ESP32-C3, 4 MiB flash",
            flash: 1280 * 1024,
            ram: 320 * 1024,
            map: MemoryMap::Esp,
        },
        partition_table: Some("partitions.csv"),
    },
    Firmware {
        name: "rp2040",
        dir: "boards/rp2040",
        bin: "forja-rp2040",
        variants: &[Variant {
            feature: "skr-pico",
            describe: "BigTreeTech SKR Pico V1.0 (RP2040), four TMC2209 drivers",
            target: "thumbv6m-none-eabi",
            toolchain: Toolchain::Pinned,
            flasher: Some(Flasher::ProbeRs("RP2040")),
            qemu: false,
            by_default: true,
            code_target: None,
        }],
        // The SKR Pico's 2 MiB flash less the 48 KiB of settings and program stores at its top
        // (boards/rp2040/memory.x); the RP2040's 264 KiB of SRAM.
        budget: Budget {
            chip: "RP2040, 2 MiB flash",
            flash: (2048 - 48) * 1024,
            ram: 264 * 1024,
            map: MemoryMap::CortexM {
                flash_origin: 0x1000_0000,
            },
        },
        partition_table: None,
    },
];

/// The board named `name`.
pub fn board(name: &str) -> Result<&'static Firmware, String> {
    BOARDS.iter().find(|b| b.name == name).ok_or_else(|| {
        let names: Vec<&str> = BOARDS.iter().map(|b| b.name).collect();
        format!(
            "no firmware board {name}; the boards are: {}",
            names.join(", ")
        )
    })
}

impl Firmware {
    /// The variant named `feature`, or the first one `pick` accepts.
    pub fn variant(
        &self,
        feature: Option<&str>,
        pick: impl Fn(&Variant) -> bool,
    ) -> Result<&'static Variant, String> {
        let found = match feature {
            Some(f) => self.variants.iter().find(|v| v.feature == f),
            None => self.variants.iter().find(|v| pick(v)),
        };
        found.ok_or_else(|| {
            let names: Vec<&str> = self.variants.iter().map(|v| v.feature).collect();
            format!(
                "{}: no such variant; the variants are: {}",
                self.name,
                names.join(", ")
            )
        })
    }

    /// The target directory of this crate's builds (shared by its variants: Cargo keeps
    /// each feature set's dependencies apart).
    fn target_dir(&self) -> PathBuf {
        root().join("target").join("firmware").join(self.name)
    }

    /// Where the release image of `variant` is copied after a build.
    pub fn image(&self, variant: &Variant) -> PathBuf {
        self.output(variant, "elf")
    }

    /// `target/firmware/<board>-<variant>.<extension>`.
    fn output(&self, variant: &Variant, extension: &str) -> PathBuf {
        root()
            .join("target")
            .join("firmware")
            .join(format!("{}-{}.{extension}", self.name, variant.feature))
    }

    /// `cargo <args>` in the crate's directory (so that its `.cargo/config.toml` applies),
    /// for `variant`: its toolchain, target and feature.
    fn cargo(&self, what: String, args: &[&str], variant: &Variant) -> Step {
        // The feature flags go to cargo, before any `--` that starts the tool's own arguments.
        let split = args.iter().position(|a| *a == "--").unwrap_or(args.len());
        let (cargo_args, tool_args) = args.split_at(split);
        let mut cmd = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
        if let Toolchain::Esp = variant.toolchain {
            // The `+esp` form needs rustup's `cargo` proxy, not the pinned toolchain's cargo.
            cmd = Command::new("cargo");
            cmd.arg("+esp");
        }
        cmd.args(cargo_args)
            .args(["--target", variant.target])
            .args(["--no-default-features", "--features", variant.feature]);
        if let Toolchain::Esp = variant.toolchain {
            cmd.arg("-Zbuild-std=core,alloc");
        }
        cmd.args(tool_args)
            .current_dir(root().join(self.dir))
            .env("CARGO_TARGET_DIR", self.target_dir());
        Step::command(what, cmd)
    }

    /// The release build of `variant`, the copy of its image and, for an ESP32, the merged
    /// flash image beside it; preceded by the toolchain check.
    pub fn build_steps(&'static self, variant: &'static Variant) -> Vec<Step> {
        let built = self
            .target_dir()
            .join(variant.target)
            .join("release")
            .join(self.bin);
        let image = self.image(variant);
        let mut steps = vec![
            Step::call(
                format!("{} toolchain for {}", self.name, variant.target),
                move || ensure_toolchain(variant),
            ),
            self.cargo(
                format!(
                    "{} firmware, {} (release build)",
                    self.name, variant.feature
                ),
                &["build", "--release"],
                variant,
            ),
            Step::call(format!("copy image to {}", image.display()), {
                let image = image.clone();
                move || {
                    std::fs::copy(&built, &image)
                        .map(drop)
                        .map_err(|e| format!("copy {}: {e}", built.display()))
                }
            }),
        ];
        if let Some(Flasher::Espflash(chip)) = variant.flasher {
            let merged = self.output(variant, "bin");
            steps.push(Step::call("espflash".to_string(), ensure_espflash));
            let mut cmd = Command::new("espflash");
            cmd.args(["save-image", "--chip", chip, "--merge", "--skip-padding"])
                .args(["--flash-size", "4mb", "--skip-update-check"]);
            if let Some(table) = self.partition_table {
                cmd.arg("--partition-table")
                    .arg(root().join(self.dir).join(table));
            }
            cmd.arg(&image).arg(&merged);
            steps.push(Step::command(
                format!("flash image {} (espflash save-image)", merged.display()),
                cmd,
            ));
        }
        steps
    }

    /// Format check (once) and clippy with -D warnings for `variant`, over every member of
    /// the firmware's workspace: the board and its family's chip support (`ports/<family>`).
    fn lint_steps(&'static self, variant: &'static Variant, with_fmt: bool) -> Vec<Step> {
        let mut steps = Vec::new();
        if with_fmt {
            // At a workspace's root, `cargo fmt` checks every member (and no path dependency
            // outside it, which `--all` would add).
            let mut cmd = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
            cmd.args(["fmt", "--check"])
                .current_dir(root().join(self.dir));
            steps.push(Step::command(
                format!("{} firmware format check", self.name),
                cmd,
            ));
        }
        steps.push(Step::call(
            format!("{} toolchain for {}", self.name, variant.target),
            move || ensure_toolchain(variant),
        ));
        steps.push(self.cargo(
            format!(
                "{} firmware, {} (clippy -D warnings)",
                self.name, variant.feature
            ),
            &["clippy", "--release", "--workspace", "--", "-D", "warnings"],
            variant,
        ));
        steps
    }
}

/// Whether `program --version` runs.
fn installed(program: &str) -> bool {
    Command::new(program)
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success())
}

/// Make sure `variant` can be built: add the pinned toolchain's target when rustup lacks it;
/// for the Xtensa chips, check that the `esp` toolchain is there (espup installs it).
fn ensure_toolchain(variant: &Variant) -> Result<(), String> {
    match variant.toolchain {
        Toolchain::Pinned => ensure_target(variant.target),
        Toolchain::Esp => {
            let present = Command::new("rustup")
                .args(["run", "esp", "rustc", "--version"])
                .output()
                .is_ok_and(|o| o.status.success());
            if present {
                Ok(())
            } else {
                Err(format!(
                    "{} needs Espressif's `esp` toolchain: `cargo install espup --locked`, then \
                     `espup install`, then `. ~/export-esp.sh` in this shell (see \
                     boards/esp32/README.md)",
                    variant.describe
                ))
            }
        }
    }
}

/// Add the pinned toolchain's Rust `target` with rustup when it lacks it.
pub fn ensure_target(target: &str) -> Result<(), String> {
    let installed = Command::new("rustup")
        .args(["target", "list", "--installed"])
        .current_dir(root())
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).into_owned())
        .unwrap_or_default();
    if installed.lines().any(|t| t.trim() == target) {
        return Ok(());
    }
    eprintln!("adding the Rust target {target} (rustup)");
    let status = Command::new("rustup")
        .args(["target", "add", target])
        .current_dir(root())
        .status()
        .map_err(|e| format!("rustup: {e}"))?;
    if status.success() {
        Ok(())
    } else {
        Err(format!("rustup target add {target} failed"))
    }
}

/// The espflash release installed when none is: one whose minimum Rust is the pinned
/// toolchain's, so that CI installs the same tool every time.
const ESPFLASH_VERSION: &str = "4.7.0";

/// Install espflash when it is missing (about four minutes on two cores, once).
fn ensure_espflash() -> Result<(), String> {
    if installed("espflash") {
        return Ok(());
    }
    eprintln!(
        "espflash is not installed: installing it with `cargo install espflash --locked \
         --version {ESPFLASH_VERSION}` (one time, about four minutes)."
    );
    Step::cargo(
        "install espflash",
        &[
            "install",
            "espflash",
            "--locked",
            "--version",
            ESPFLASH_VERSION,
        ],
    )
    .run()
}

/// The variants `build` makes without `--variant`, and `test` and `size` check.
fn default_variants(board: &Firmware) -> impl Iterator<Item = &'static Variant> + '_ {
    board.variants.iter().filter(|v| v.by_default)
}

/// `cargo xtask build <board>`: release images of the default variants (or of one).
pub fn build(name: &str, feature: Option<&str>) -> Result<(), String> {
    let board = board(name)?;
    let chosen: Vec<&'static Variant> = match feature {
        Some(f) => vec![board.variant(Some(f), |_| true)?],
        None => default_variants(board).collect(),
    };
    let steps = chosen.iter().flat_map(|v| board.build_steps(v)).collect();
    crate::run_all(steps)?;
    for variant in chosen {
        eprintln!("{}: {}", variant.feature, board.image(variant).display());
        if let Some(Flasher::Espflash(_)) = variant.flasher {
            eprintln!(
                "{}: {} (write at offset 0)",
                variant.feature,
                board.output(variant, "bin").display()
            );
        }
    }
    Ok(())
}

/// `cargo xtask flash <board>`: build, then write the image with probe-rs or espflash.
pub fn flash(name: &str, feature: Option<&str>) -> Result<(), String> {
    let board = board(name)?;
    let variant = board.variant(feature, |v| v.flasher.is_some())?;
    let flasher = variant
        .flasher
        .as_ref()
        .ok_or_else(|| format!("{} runs in QEMU, not on hardware", variant.feature))?;
    crate::run_all(board.build_steps(variant))?;
    let image = board.image(variant);
    match flasher {
        Flasher::ProbeRs(chip) => {
            if !installed("probe-rs") {
                eprintln!(
                    "probe-rs is not installed: installing it with `cargo install probe-rs-tools --locked` \
                     (one time, several minutes). It needs libudev (Debian/Ubuntu: apt-get install libudev-dev)."
                );
                crate::run_all(vec![Step::cargo(
                    "install probe-rs",
                    &["install", "probe-rs-tools", "--locked"],
                )])?;
            }
            let mut download = Command::new("probe-rs");
            download.args(["download", "--chip", chip]).arg(&image);
            let mut reset = Command::new("probe-rs");
            reset.args(["reset", "--chip", chip]);
            crate::run_all(vec![
                Step::command(format!("flash {} to {chip}", image.display()), download),
                Step::command("reset the chip".to_string(), reset),
            ])
        }
        Flasher::Espflash(chip) => {
            // The build steps installed espflash. It finds the board's USB port itself, or asks
            // which one when there are several (ESPFLASH_PORT or --port in a script).
            let mut cmd = Command::new("espflash");
            cmd.args(["flash", "--chip", chip, "--skip-update-check"]);
            if let Some(table) = board.partition_table {
                cmd.arg("--partition-table")
                    .arg(root().join(board.dir).join(table));
            }
            cmd.arg(&image);
            crate::run_all(vec![Step::command(
                format!("flash {} to {chip} (espflash)", image.display()),
                cmd,
            )])
        }
    }
}

/// `cargo xtask qemu <board>`: build the QEMU variant and run it, the host link on a TCP port;
/// with `check`, run the end-to-end check instead.
pub fn run_qemu(name: &str, port: u16, check: bool) -> Result<(), String> {
    let board = board(name)?;
    let variant = board.variant(None, |v| v.qemu)?;
    if !qemu::qemu_available() {
        return Err(format!(
            "{} not found: install it (Debian/Ubuntu: apt-get install qemu-system-arm)",
            qemu::QEMU
        ));
    }
    crate::run_all(board.build_steps(variant))?;
    if check {
        return crate::run_all(vec![Step::call(
            format!(
                "{} firmware in QEMU: end-to-end job, program, positions vs simulator",
                board.name
            ),
            move || qemu_end_to_end(board),
        )]);
    }
    let port = if port == 0 { qemu::free_port()? } else { port };
    eprintln!(
        "\n{} in QEMU `{}`: the host link (USART6) is on 127.0.0.1:{port}.\n\
         QEMU starts the firmware when a client connects there (e.g. `nc 127.0.0.1 {port}`);\n\
         the firmware answers `start`. Ctrl-C ends QEMU.",
        variant.describe,
        qemu::MACHINE
    );
    let image = board.image(variant);
    let status = qemu::command(&image, port, true, None)
        .status()
        .map_err(|e| format!("start {}: {e}", qemu::QEMU))?;
    if status.success() {
        Ok(())
    } else {
        Err(format!("{} ended with {status}", qemu::QEMU))
    }
}

/// Memory use of one image.
struct Usage {
    /// Bytes of the image in flash.
    flash: u64,
    /// Cortex-M: the end of the last byte loaded into flash, from the flash origin (includes
    /// the store sectors the code is placed after). ESP32: the image's size in its partition.
    flash_end: u64,
    /// RAM the image takes: statics, RAM code and (Cortex-M) the stack reservation.
    ram: u64,
    /// The stack: the reservation (Cortex-M) or all the RAM left (ESP32).
    stack: u64,
    /// Core-coupled RAM (Cortex-M: the QEMU build's store) or the reclaimed boot loader RAM
    /// (ESP32: heap).
    other: u64,
}

fn usage(image: &Path, map: &MemoryMap) -> Result<Usage, String> {
    let data = std::fs::read(image).map_err(|e| format!("{}: {e}", image.display()))?;
    let elf = ElfFile32::<object::Endianness>::parse(&*data)
        .map_err(|e| format!("{}: {e}", image.display()))?;
    let section = |name: &str| elf.section_by_name(name).map_or(0, |s| s.size());
    let sections_with = |prefixes: &[&str]| -> u64 {
        elf.sections()
            .filter(|s| {
                s.name().is_ok_and(|n| {
                    prefixes
                        .iter()
                        .any(|p| n == *p || n.starts_with(&format!("{p}.")))
                })
            })
            .map(|s| s.size())
            .sum()
    };
    let endian = elf.endian();
    let loaded: Vec<(u64, u64)> = elf
        .elf_header()
        .program_headers(endian, &*data)
        .map_err(|e| format!("{}: {e}", image.display()))?
        .iter()
        .filter(|p| p.p_filesz(endian) > 0)
        .map(|p| (u64::from(p.p_paddr(endian)), u64::from(p.p_filesz(endian))))
        .collect();
    match map {
        MemoryMap::CortexM { flash_origin } => {
            let flash_end = loaded
                .iter()
                .map(|(start, len)| start + len)
                .filter(|end| end > flash_origin)
                .max()
                .unwrap_or(*flash_origin)
                - flash_origin;
            let stack = elf
                .symbols()
                .find(|s| s.name() == Ok("_stack_reserve"))
                .map_or(0, |s| s.address());
            Ok(Usage {
                flash: section(".vector_table")
                    + section(".text")
                    + section(".rodata")
                    + section(".data"),
                flash_end,
                ram: section(".data") + section(".bss") + section(".uninit") + stack,
                stack,
                other: section(".ccmram"),
            })
        }
        MemoryMap::Esp => {
            let flash: u64 = loaded.iter().map(|(_, len)| len).sum();
            Ok(Usage {
                flash,
                flash_end: flash,
                ram: sections_with(&[".trap", ".rwtext", ".data", ".bss", ".noinit"]),
                stack: section(".stack"),
                other: section(".dram2_uninit"),
            })
        }
    }
}

fn kib(bytes: u64) -> String {
    format!("{:.1} KiB", bytes as f64 / 1024.0)
}

/// `cargo xtask size`: build every default release image and check it against its board's
/// budget.
pub fn size() -> Result<(), String> {
    let mut steps = Vec::new();
    for board in BOARDS {
        for variant in default_variants(board) {
            steps.extend(board.build_steps(variant));
        }
    }
    crate::run_all(steps)?;
    check_sizes()
}

/// Print the memory use of the default images already built; fail when one is over its
/// budget.
pub fn check_sizes() -> Result<(), String> {
    let mut over = Vec::new();
    println!(
        "\n{:<20} {:>10} {:>14} {:>26} {:>10}   budget",
        "image", "flash", "flash extent", "RAM (stack)", "other RAM"
    );
    for board in BOARDS {
        for variant in default_variants(board) {
            let image = board.image(variant);
            let u = usage(&image, &board.budget.map)?;
            let name = format!("{}/{}", board.name, variant.feature);
            let fits = u.flash_end <= board.budget.flash && u.ram <= board.budget.ram;
            let target = variant.code_target.map(|t| (t, u.flash <= t));
            println!(
                "{name:<20} {:>10} {:>14} {:>26} {:>10}   {} ({} flash, {} RAM): {}",
                kib(u.flash),
                kib(u.flash_end),
                format!("{} ({} stack)", kib(u.ram), kib(u.stack)),
                kib(u.other),
                board.budget.chip,
                kib(board.budget.flash),
                kib(board.budget.ram),
                if fits { "fits" } else { "OVER" }
            );
            if let Some((t, met)) = target {
                println!(
                    "{:<20} code target {}: {}, {} left",
                    "",
                    kib(t),
                    if met { "met" } else { "OVER" },
                    kib(t.saturating_sub(u.flash))
                );
            }
            if !fits || target.is_some_and(|(_, met)| !met) {
                over.push(name);
            }
        }
    }
    println!(
        "stm32f4: flash = .vector_table + .text + .rodata + .data; flash extent = last flash \
         byte used (code starts after the 48 KiB of vector table and store sectors); RAM = \
         .data + .bss + .uninit (the qemu image's 32 KiB RAM store included) + \
         stack reservation; other = CCM RAM.\n\
         esp32: flash = the loaded segments, in the 1.25 MiB app partition; RAM = .trap + \
         .rwtext + .data + .bss + .noinit (code and statics in SRAM), the stack is the RAM \
         left; other = the boot loader's RAM reclaimed for the heap.\n\
         rp2040: as stm32f4, but the image starts at the flash's first byte (the 256-byte boot \
         loader) and its budget is the flash below the 48 KiB of stores at the top."
    );
    if !web_page_fits() {
        over.push("web page".to_string());
    }
    if over.is_empty() {
        Ok(())
    } else {
        Err(format!("over budget: {}", over.join(", ")))
    }
}

/// Print what the operator's web page (`forja-web`'s assets, gzip-compressed, embedded in the
/// ESP32 images' flash) costs against [`forja_web::GZIP_BUDGET`]; whether it fits.
fn web_page_fits() -> bool {
    let total = forja_web::total_gzip_len();
    let raw: usize = forja_web::ASSETS.iter().map(|a| a.raw_len).sum();
    let fits = total <= forja_web::GZIP_BUDGET;
    println!(
        "\nweb page: {} gzip ({} raw) in {} files, budget {} gzip: {}; embedded in the esp32 \
         images above (their flash includes it)",
        kib(total as u64),
        kib(raw as u64),
        forja_web::ASSETS.len(),
        kib(forja_web::GZIP_BUDGET as u64),
        if fits { "fits" } else { "OVER" }
    );
    for asset in forja_web::ASSETS {
        println!(
            "  {:<20} {:>10} gzip {:>10} raw  {}",
            asset.path,
            kib(asset.gzip.len() as u64),
            kib(asset.raw_len as u64),
            asset.content_type
        );
    }
    fits
}

/// Boot the QEMU image and run the end-to-end test of [`qemu::end_to_end`]: a G-code job with
/// a resend, a program uploaded with frames and run, and the final positions compared with the
/// simulator's.
pub fn qemu_end_to_end(board: &'static Firmware) -> Result<(), String> {
    let variant = board.variant(None, |v| v.qemu)?;
    let image = board.image(variant);
    let started = std::time::Instant::now();
    let run = qemu::end_to_end(&image)?;
    let [stream, upload, program] = run.times;
    eprintln!(
        "positions match the simulator's: M114 [{}], 51 [{}], simulator [{}]\n\
         wall time {:.1} s (job {:.1} s, upload {:.1} s, program {:.1} s)",
        fmt_position(&run.m114, 3),
        fmt_position(&run.positions, 4),
        fmt_position(&run.simulated, 4),
        started.elapsed().as_secs_f64(),
        stream.as_secs_f64(),
        upload.as_secs_f64(),
        program.as_secs_f64()
    );
    Ok(())
}

fn fmt_position(p: &[f64], decimals: usize) -> String {
    p.iter()
        .map(|v| format!("{v:.decimals$}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// The firmware steps of `cargo xtask test`: format, clippy and release build of every
/// default variant, the size check, and the QEMU end-to-end test.
pub fn test_steps() -> Vec<Step> {
    let mut steps = Vec::new();
    for board in BOARDS {
        for (i, variant) in default_variants(board).enumerate() {
            steps.extend(board.lint_steps(variant, i == 0));
            steps.extend(board.build_steps(variant));
        }
    }
    steps.push(Step::call("firmware sizes".to_string(), check_sizes));
    for board in BOARDS {
        if board.variants.iter().any(|v| v.qemu) {
            let what = format!(
                "{} firmware in QEMU: end-to-end job, program, positions vs simulator",
                board.name
            );
            if qemu::qemu_available() || std::env::var_os("CI").is_some() {
                steps.push(Step::call(what, move || qemu_end_to_end(board)));
            } else {
                steps.push(Step::call(what, || {
                    eprintln!(
                        "SKIPPED: {} is not installed (apt-get install qemu-system-arm); \
                         CI installs it and runs this step",
                        qemu::QEMU
                    );
                    Ok(())
                }));
            }
        }
    }
    steps
}
