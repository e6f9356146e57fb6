//! Firmware boards: `cargo xtask build | flash | qemu | size`, and their steps in `test`.
//!
//! Every firmware crate is described by one [`Firmware`] entry in [`BOARDS`]: adding a board
//! is adding an entry. A board has one or more pin-map variants (Cargo features); `test` builds
//! and lints every one of them.

use std::path::{Path, PathBuf};
use std::process::Command;

use object::read::elf::{ElfFile32, FileHeader, ProgramHeader};
use object::{Object, ObjectSection, ObjectSymbol};

use crate::qemu::{self, QemuBoard};
use crate::{Step, root};

/// One pin-map variant of a firmware crate (a Cargo feature).
pub struct Variant {
    /// The Cargo feature that selects it.
    pub feature: &'static str,
    /// What it is, for messages.
    pub describe: &'static str,
    /// The probe-rs chip name, for variants that run on hardware.
    pub probe_chip: Option<&'static str>,
    /// Whether this variant runs in QEMU (`cargo xtask qemu`).
    pub qemu: bool,
}

/// The memory an image must fit.
pub struct Budget {
    /// The smallest chip the image must fit.
    pub chip: &'static str,
    /// Bytes of flash.
    pub flash: u64,
    /// Bytes of RAM (main SRAM; core-coupled RAM is reported apart).
    pub ram: u64,
}

/// A firmware crate, excluded from the workspace and built here.
pub struct Firmware {
    /// The name on the command line.
    pub name: &'static str,
    /// The crate's directory, from the workspace root.
    pub dir: &'static str,
    /// The binary's name.
    pub bin: &'static str,
    /// The Rust target (also pinned in the crate's `.cargo/config.toml`).
    pub target: &'static str,
    /// Its pin-map variants; the first hardware one is the default for `flash`.
    pub variants: &'static [Variant],
    /// What `size` checks the release images against.
    pub budget: Budget,
}

/// Every firmware board.
pub const BOARDS: &[Firmware] = &[Firmware {
    name: "stm32f4",
    dir: "boards/stm32f4",
    bin: "forja-stm32f4",
    target: "thumbv7em-none-eabihf",
    variants: &[
        Variant {
            feature: "blackpill",
            describe: "Black Pill STM32F411CE, grblHAL breakout pin-out",
            probe_chip: Some("STM32F411CEUx"),
            qemu: false,
        },
        Variant {
            feature: "qemu",
            describe: "QEMU netduinoplus2 (STM32F405), CNC Shield V3 pin-out",
            probe_chip: None,
            qemu: true,
        },
    ],
    budget: Budget {
        chip: "STM32F401",
        flash: 256 * 1024,
        ram: 64 * 1024,
    },
}];

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
        root()
            .join("target")
            .join("firmware")
            .join(format!("{}-{}.elf", self.name, variant.feature))
    }

    /// `cargo <args>` in the crate's directory (so that its `.cargo/config.toml` applies),
    /// for `variant`.
    fn cargo(&self, what: String, args: &[&str], variant: &Variant) -> Step {
        // The feature flags go to cargo, before any `--` that starts the tool's own arguments.
        let split = args.iter().position(|a| *a == "--").unwrap_or(args.len());
        let (cargo_args, tool_args) = args.split_at(split);
        let mut cmd = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
        cmd.args(cargo_args)
            .args(["--no-default-features", "--features", variant.feature])
            .args(tool_args)
            .current_dir(root().join(self.dir))
            .env("CARGO_TARGET_DIR", self.target_dir());
        Step::command(what, cmd)
    }

    /// The release build of `variant`, then the copy of its image.
    pub fn build_steps(&'static self, variant: &'static Variant) -> Vec<Step> {
        let built = self
            .target_dir()
            .join(self.target)
            .join("release")
            .join(self.bin);
        let image = self.image(variant);
        vec![
            self.cargo(
                format!(
                    "{} firmware, {} (release build)",
                    self.name, variant.feature
                ),
                &["build", "--release"],
                variant,
            ),
            Step::call(format!("copy image to {}", image.display()), move || {
                std::fs::copy(&built, &image)
                    .map(drop)
                    .map_err(|e| format!("copy {}: {e}", built.display()))
            }),
        ]
    }

    /// Format check (once) and clippy with -D warnings for `variant`.
    fn lint_steps(&'static self, variant: &'static Variant, with_fmt: bool) -> Vec<Step> {
        let mut steps = Vec::new();
        if with_fmt {
            let mut cmd = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
            cmd.args(["fmt", "--check"])
                .current_dir(root().join(self.dir));
            steps.push(Step::command(
                format!("{} firmware format check", self.name),
                cmd,
            ));
        }
        steps.push(self.cargo(
            format!(
                "{} firmware, {} (clippy -D warnings)",
                self.name, variant.feature
            ),
            &["clippy", "--release", "--", "-D", "warnings"],
            variant,
        ));
        steps
    }
}

/// `cargo xtask build <board>`: release images of every variant (or one).
pub fn build(name: &str, feature: Option<&str>) -> Result<(), String> {
    let board = board(name)?;
    let mut steps = Vec::new();
    for variant in board.variants {
        if feature.is_none_or(|f| f == variant.feature) {
            steps.extend(board.build_steps(variant));
        }
    }
    if steps.is_empty() {
        board.variant(feature, |_| true)?;
    }
    crate::run_all(steps)?;
    for variant in board.variants {
        if feature.is_none_or(|f| f == variant.feature) {
            eprintln!("{}: {}", variant.feature, board.image(variant).display());
        }
    }
    Ok(())
}

/// `cargo xtask flash <board>`: build, then write the image with probe-rs.
pub fn flash(name: &str, feature: Option<&str>) -> Result<(), String> {
    let board = board(name)?;
    let variant = board.variant(feature, |v| v.probe_chip.is_some())?;
    let chip = variant
        .probe_chip
        .ok_or_else(|| format!("{} runs in QEMU, not on a probe", variant.feature))?;
    crate::run_all(board.build_steps(variant))?;
    let probe_rs_present = Command::new("probe-rs")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !probe_rs_present {
        eprintln!(
            "probe-rs is not installed: installing it with `cargo install probe-rs-tools --locked` \
             (one time, several minutes). It needs libudev (Debian/Ubuntu: apt-get install libudev-dev)."
        );
        crate::run_all(vec![Step::cargo(
            "install probe-rs",
            &["install", "probe-rs-tools", "--locked"],
        )])?;
    }
    let image = board.image(variant);
    let mut download = Command::new("probe-rs");
    download.args(["download", "--chip", chip]).arg(&image);
    let mut reset = Command::new("probe-rs");
    reset.args(["reset", "--chip", chip]);
    crate::run_all(vec![
        Step::command(format!("flash {} to {chip}", image.display()), download),
        Step::command("reset the chip".to_string(), reset),
    ])
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
            format!("{} firmware in QEMU: boot, `start`, host link", board.name),
            move || qemu_bringup(board),
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
    /// .vector_table + .text + .rodata + .data (initial values).
    flash: u64,
    /// End of the last byte loaded into flash, from the flash origin (includes the store
    /// sectors the code is placed after).
    flash_end: u64,
    /// .data + .bss + .uninit + the stack reservation.
    ram: u64,
    stack: u64,
    /// Core-coupled RAM (the QEMU build's store).
    ccm: u64,
}

const FLASH_ORIGIN: u64 = 0x0800_0000;

fn usage(image: &Path) -> Result<Usage, String> {
    let data = std::fs::read(image).map_err(|e| format!("{}: {e}", image.display()))?;
    let elf = ElfFile32::<object::Endianness>::parse(&*data)
        .map_err(|e| format!("{}: {e}", image.display()))?;
    let section = |name: &str| elf.section_by_name(name).map_or(0, |s| s.size());
    let endian = elf.endian();
    let flash_end = elf
        .elf_header()
        .program_headers(endian, &*data)
        .map_err(|e| format!("{}: {e}", image.display()))?
        .iter()
        .filter(|p| p.p_filesz(endian) > 0)
        .map(|p| u64::from(p.p_paddr(endian)) + u64::from(p.p_filesz(endian)))
        .filter(|end| *end > FLASH_ORIGIN)
        .max()
        .unwrap_or(FLASH_ORIGIN)
        - FLASH_ORIGIN;
    let stack = elf
        .symbols()
        .find(|s| s.name() == Ok("_stack_reserve"))
        .map_or(0, |s| s.address());
    Ok(Usage {
        flash: section(".vector_table") + section(".text") + section(".rodata") + section(".data"),
        flash_end,
        ram: section(".data") + section(".bss") + section(".uninit") + stack,
        stack,
        ccm: section(".ccmram"),
    })
}

fn kib(bytes: u64) -> String {
    format!("{:.1} KiB", bytes as f64 / 1024.0)
}

/// `cargo xtask size`: build every release image and check it against its board's budget.
pub fn size() -> Result<(), String> {
    let mut steps = Vec::new();
    for board in BOARDS {
        for variant in board.variants {
            steps.extend(board.build_steps(variant));
        }
    }
    crate::run_all(steps)?;
    check_sizes()
}

/// Print the memory use of the images already built; fail when one is over its budget.
pub fn check_sizes() -> Result<(), String> {
    let mut over = Vec::new();
    println!(
        "\n{:<20} {:>10} {:>14} {:>25} {:>9}   budget",
        "image", "flash", "flash extent", "RAM (with stack)", "CCM RAM"
    );
    for board in BOARDS {
        for variant in board.variants {
            let image = board.image(variant);
            let u = usage(&image)?;
            let name = format!("{}/{}", board.name, variant.feature);
            let fits = u.flash_end <= board.budget.flash && u.ram <= board.budget.ram;
            println!(
                "{name:<20} {:>10} {:>14} {:>25} {:>9}   {} ({} flash, {} RAM): {}",
                kib(u.flash),
                kib(u.flash_end),
                format!("{} ({} stack)", kib(u.ram), kib(u.stack)),
                kib(u.ccm),
                board.budget.chip,
                kib(board.budget.flash),
                kib(board.budget.ram),
                if fits { "fits" } else { "OVER" }
            );
            if !fits {
                over.push(name);
            }
        }
    }
    println!(
        "flash = .vector_table + .text + .rodata + .data; flash extent = last flash byte used \
         (code starts after the 48 KiB of vector table and store sectors); \
         RAM = .data + .bss + .uninit + stack reservation."
    );
    if over.is_empty() {
        Ok(())
    } else {
        Err(format!("over budget: {}", over.join(", ")))
    }
}

/// Bytes sent by the QEMU bring-up check: two G-code lines, one 53-byte frame (the example
/// of `forja_protocol::stream`), and a run of garbage. The firmware must count 2 lines, 1
/// frame and 1 dropped run.
fn bringup_stream() -> Vec<u8> {
    let mut bytes = b"N1 G1 X10*98\n".to_vec();
    bytes.extend_from_slice(b"N02Zero");
    bytes.extend_from_slice(&[b'*'; 41]);
    bytes.extend_from_slice(b"ZeroF\n\x01garbage\nM114\n");
    bytes
}

/// Boot the QEMU image, wait for `start`, stream lines, a frame and garbage, and check through
/// the firmware's link counters that every byte went through the UART interrupt and the
/// receive queue to the decoder.
pub fn qemu_bringup(board: &'static Firmware) -> Result<(), String> {
    let variant = board.variant(None, |v| v.qemu)?;
    let image = board.image(variant);
    let mut qemu = QemuBoard::boot(&image)?;
    eprintln!("booted; `start` received on 127.0.0.1:{}", qemu.link_port());
    let stream = bringup_stream();
    qemu.send(&stream)?;
    // rx_bytes, lines, frames, dropped, rx_overruns, uart_errors
    let expected = [stream.len() as u32, 2, 1, 1, 0, 0];
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    loop {
        let got = qemu.read_symbol_words("FORJA_LINK_COUNTERS", 6)?;
        if got == expected {
            break;
        }
        if std::time::Instant::now() > deadline {
            return Err(format!(
                "link counters [rx_bytes, lines, frames, dropped, overruns, uart errors]: \
                 expected {expected:?}, got {got:?}"
            ));
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    if !qemu.is_running() {
        return Err("the firmware reset (QEMU ended)".into());
    }
    let unexpected = qemu.drain();
    if !unexpected.is_empty() {
        return Err(format!(
            "the firmware sent {:?} without a controller to answer",
            String::from_utf8_lossy(&unexpected)
        ));
    }
    eprintln!("link counters as expected: {expected:?}");
    Ok(())
}

/// The firmware steps of `cargo xtask test`: format, clippy and release build of every
/// variant, the size check, and the QEMU bring-up check.
pub fn test_steps() -> Vec<Step> {
    let mut steps = Vec::new();
    for board in BOARDS {
        for (i, variant) in board.variants.iter().enumerate() {
            steps.extend(board.lint_steps(variant, i == 0));
            steps.extend(board.build_steps(variant));
        }
    }
    steps.push(Step::call("firmware sizes".to_string(), check_sizes));
    for board in BOARDS {
        if board.variants.iter().any(|v| v.qemu) {
            let what = format!("{} firmware in QEMU: boot, `start`, host link", board.name);
            if qemu::qemu_available() || std::env::var_os("CI").is_some() {
                steps.push(Step::call(what, move || qemu_bringup(board)));
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
