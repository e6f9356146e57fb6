//! What the client needs of a machine file: each axis's letter, steps per mm and start
//! position.
//!
//! The machine file is the simulator's TOML format (`boards/sim-hal/machines/*.toml`); only the
//! `[[axis]]` tables' `letter`, `steps_per_mm` and `start_mm` are read, every other field is
//! ignored, so that the file can grow without the client following.

use std::fmt;
use std::path::Path;

use serde::Deserialize;

/// One axis.
#[derive(Clone, Debug, PartialEq)]
pub struct AxisInfo {
    /// Its letter, upper case.
    pub letter: char,
    /// Steps per mm (per degree for a rotary axis).
    pub steps_per_mm: f64,
    /// Its machine position when the machine starts, mm.
    pub start_mm: f64,
}

/// The axes of a machine.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MachineInfo {
    /// The machine's name, if the file gives one.
    pub name: Option<String>,
    /// Its axes, in file order.
    pub axes: Vec<AxisInfo>,
}

#[derive(Deserialize)]
struct File {
    name: Option<String>,
    #[serde(default)]
    axis: Vec<AxisEntry>,
}

#[derive(Deserialize)]
struct AxisEntry {
    letter: String,
    steps_per_mm: f64,
    #[serde(default)]
    start_mm: f64,
}

/// A machine file that cannot be used.
#[derive(Debug)]
pub struct MachineError(String);

impl fmt::Display for MachineError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for MachineError {}

impl MachineInfo {
    /// Read a machine file.
    ///
    /// Errors: the file cannot be read, is not TOML, or an axis lacks `letter` or a positive
    /// `steps_per_mm`.
    pub fn load(path: &Path) -> Result<Self, MachineError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| MachineError(format!("cannot read {}: {e}", path.display())))?;
        Self::parse(&text).map_err(|e| MachineError(format!("{}: {e}", path.display())))
    }

    /// Read a machine file's text.
    pub fn parse(text: &str) -> Result<Self, MachineError> {
        let file: File = toml::from_str(text)
            .map_err(|e| MachineError(format!("not a valid machine file: {e}")))?;
        let mut axes = Vec::new();
        for (i, a) in file.axis.into_iter().enumerate() {
            let mut chars = a.letter.chars();
            let (Some(letter), None) = (chars.next(), chars.next()) else {
                return Err(MachineError(format!(
                    "axis {}: letter must be one letter, not \"{}\"",
                    i + 1,
                    a.letter
                )));
            };
            if !(a.steps_per_mm.is_finite() && a.steps_per_mm > 0.0) {
                return Err(MachineError(format!(
                    "axis {letter}: steps_per_mm must be a positive number"
                )));
            }
            axes.push(AxisInfo {
                letter: letter.to_ascii_uppercase(),
                steps_per_mm: a.steps_per_mm,
                start_mm: a.start_mm,
            });
        }
        Ok(Self {
            name: file.name,
            axes,
        })
    }

    /// The axis with `letter`.
    pub fn axis(&self, letter: char) -> Option<&AxisInfo> {
        self.axes
            .iter()
            .find(|a| a.letter == letter.to_ascii_uppercase())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_axes_and_ignores_the_rest() {
        let m = MachineInfo::parse(
            "name = \"m\"\ntick_hz = 1000\n[[axis]]\nletter = \"x\"\nsteps_per_mm = 80.0\n\
             start_mm = 150.0\n[axis.homing]\ndirection = \"negative\"\n[[axis]]\nletter = \"Z\"\n\
             steps_per_mm = 400\n",
        )
        .unwrap();
        assert_eq!(m.name.as_deref(), Some("m"));
        assert_eq!(m.axis('X').unwrap().start_mm, 150.0);
        assert_eq!(m.axis('z').unwrap().steps_per_mm, 400.0);
        assert_eq!(m.axis('z').unwrap().start_mm, 0.0);
        let e = MachineInfo::parse("[[axis]]\nletter = \"X\"\nsteps_per_mm = 0\n").unwrap_err();
        assert_eq!(
            e.to_string(),
            "axis X: steps_per_mm must be a positive number"
        );
    }
}
