//! How much code each board crate holds outside its pin maps: a board is wiring (pins, clocks,
//! timers, interrupt bindings, its link, the description of its parts), and the application
//! layer does the rest, so this count stays small. `cargo xtask size` prints it, and it and
//! `cargo xtask test` fail when a board is over [`BOARD_LINES_BUDGET`].
//!
//! Counted: the lines of `boards/<board>/src/**/*.rs` that hold code, leaving out blank lines,
//! comments (`//`, `///`, `//!`) and the pin maps (`src/board/`), and each file's
//! `#[cfg(test)]` module at its end.

use std::fs;
use std::path::Path;

use crate::root;

/// The most lines of code a board should hold outside its pin maps.
pub const BOARD_LINES_BUDGET: usize = 300;

/// Lines of code in `source`, its trailing `#[cfg(test)]` module left out.
fn code_lines(source: &str) -> usize {
    let body = source
        .find("\n#[cfg(test)]\nmod ")
        .map_or(source, |i| &source[..i]);
    body.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with("//"))
        .count()
}

/// Lines of code in the `.rs` files under `dir`, `skip` (a folder) left out.
fn count(dir: &Path, skip: &Path) -> Result<usize, String> {
    let mut total = 0;
    let entries = fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    for entry in entries {
        let path = entry.map_err(|e| e.to_string())?.path();
        if path == skip {
            continue;
        }
        if path.is_dir() {
            total += count(&path, skip)?;
        } else if path.extension().is_some_and(|e| e == "rs") {
            let text = fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
            total += code_lines(&text);
        }
    }
    Ok(total)
}

/// Print each board's lines of code outside its pin maps against [`BOARD_LINES_BUDGET`].
///
/// Errors: a board over the budget (named with its count).
pub fn report() -> Result<(), String> {
    let boards = root().join("boards");
    let mut names: Vec<String> = fs::read_dir(&boards)
        .map_err(|e| format!("{}: {e}", boards.display()))?
        .filter_map(|e| e.ok())
        .filter(|e| e.path().join("src").is_dir())
        .filter_map(|e| e.file_name().into_string().ok())
        // A board's HAL (the simulator's virtual hardware, `boards/sim-hal`) is not wiring.
        .filter(|n| !n.ends_with("-hal"))
        .collect();
    names.sort();
    let mut over = Vec::new();
    println!(
        "\nboard crate       lines of code outside the pin maps (src/board/), budget {BOARD_LINES_BUDGET}"
    );
    for name in names {
        let src = boards.join(&name).join("src");
        let lines = count(&src, &src.join("board"))?;
        let verdict = if lines <= BOARD_LINES_BUDGET {
            "within".to_string()
        } else {
            over.push(format!("{name} ({lines})"));
            format!("{} over", lines - BOARD_LINES_BUDGET)
        };
        println!("{name:<17} {lines:>6}   {verdict}");
    }
    if over.is_empty() {
        Ok(())
    } else {
        Err(format!(
            "board crates over the {BOARD_LINES_BUDGET}-line budget: {}",
            over.join(", ")
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn comments_blank_lines_and_the_test_module_do_not_count() {
        let src = "//! doc\n\nuse a;\n/// item\nfn f() {}\n    // note\n\n#[cfg(test)]\nmod tests {\n    fn t() {}\n}\n";
        assert_eq!(code_lines(src), 2);
    }
}
