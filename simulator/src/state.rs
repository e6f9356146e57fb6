//! The board's flash in a state file (`forja-sim --state FILE`): settings and the uploaded
//! program survive a restart of the simulator, as they survive a power cycle of a board.
//!
//! The file and its flash model are the simulated hardware's
//! ([`forja_sim_hal::state`]); this module starts the board on it ([`board_config`]) and
//! says what it keeps ([`describe`], `--check --state FILE`).

use std::path::Path;

use forja_sim::board::{BoardConfig, SimBoard};
use forja_sim_hal::state::BoardFlash;
use forja_sim_hal::{MachineConfig, SimMachine};

/// A board's settings with the flash of the state file at `state` ([`BoardFlash::open`]), or
/// erased without one.
///
/// Errors: the [`StateError`](forja_sim_hal::state::StateError) of [`BoardFlash::open`], as
/// text.
pub fn board_config(state: Option<&Path>) -> Result<BoardConfig, String> {
    Ok(BoardConfig {
        flash: match state {
            Some(path) => BoardFlash::open(path).map_err(|e| e.to_string())?,
            None => BoardFlash::erased(),
        },
        ..BoardConfig::default()
    })
}

/// What the state file at `path` keeps, as the firmware finds it when it starts on it: every
/// setting (`key=value`, as frame 50 shows it), then the stored program, line by line, and
/// whether it is complete. The firmware is started on a copy of the file
/// ([`BoardFlash::snapshot`]), which stays as it is.
///
/// Errors: a [`StateError`](forja_sim_hal::state::StateError), or a firmware that does not
/// start on the file, as text.
pub fn describe(machine: &MachineConfig, path: &Path) -> Result<String, String> {
    let config = BoardConfig {
        flash: BoardFlash::snapshot(path).map_err(|e| e.to_string())?,
        ..BoardConfig::default()
    };
    let mut board = SimBoard::new(&SimMachine::new(machine), config).map_err(|e| {
        format!(
            "state file {}: the firmware does not start: {e}",
            path.display()
        )
    })?;
    let status = board.status();
    let program: Vec<Option<String>> = (1..=status.controller.program_lines)
        .map(|i| board.program_line(i))
        .collect();
    let (settings, ignored) = (board.settings(), board.load_report().ignored);
    let program_total = status.controller.program_total;
    let incomplete = (usize::from(program_total) > program.len()).then_some(program_total);
    let mut out = format!("state: {}\n  settings:\n", path.display());
    for line in settings.lines() {
        out.push_str(&format!("    {line}\n"));
    }
    if ignored > 0 {
        out.push_str(&format!("    ({ignored} stored values ignored)\n"));
    }
    out.push_str(&match (program.len(), incomplete) {
        (0, _) => "  program: none\n".to_string(),
        (n, None) => format!("  program: {n} lines, complete\n"),
        (n, Some(total)) => {
            format!("  program: {n} of {total} lines, incomplete (an upload cut short: it does not run)\n")
        }
    });
    for (index, line) in program.iter().enumerate() {
        match line {
            Some(text) => out.push_str(&format!("    {:04} {text}\n", index + 1)),
            None => out.push_str(&format!("    {:04} (unreadable)\n", index + 1)),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use forja_sim_hal::state::{PROGRAM_FLASH_LEN, SETTINGS_FLASH_LEN, header};

    use super::*;

    #[test]
    fn the_firmware_starts_on_any_flash_contents() {
        // Power cuts leave torn records; a damaged file may hold anything. The firmware starts
        // (the storage layer ignores or repairs what does not check), and never panics.
        let path =
            std::env::temp_dir().join(format!("forja-sim-state-{}-noise", std::process::id()));
        let machine = MachineConfig::default_router();
        let mut seed = 0x9E37_79B9_7F4A_7C15_u64;
        for fill in 0..4u8 {
            let mut bytes = header();
            for _ in 0..SETTINGS_FLASH_LEN + PROGRAM_FLASH_LEN {
                seed ^= seed << 13;
                seed ^= seed >> 7;
                seed ^= seed << 17;
                bytes.push(match fill {
                    0 => 0x00,
                    1 => seed as u8,
                    2 => (seed as u8) | 0xF0,
                    _ => 0xFF,
                });
            }
            std::fs::write(&path, &bytes).unwrap();
            match describe(&machine, &path) {
                Ok(text) => {
                    assert!(text.contains("x.steps_per_mm=80\n"), "{text}");
                    assert!(text.contains("program: none\n"), "{text}");
                }
                // Noise that is not records: refused by name, not a panic.
                Err(e) => {
                    assert_ne!(fill, 3, "an erased flash starts: {e}");
                    assert!(e.contains("the firmware does not start: flash:"), "{e}");
                }
            }
            assert_eq!(
                std::fs::read(&path).unwrap(),
                bytes,
                "--check changes nothing"
            );
        }
        std::fs::remove_file(&path).unwrap();
    }
}
