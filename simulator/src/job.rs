//! Job files: G-code programs for the simulator to run.
//!
//! A job is a text file of G-code lines, streamed to the firmware as a host would send it.
//! This module only loads it and checks that it is text; the G-code itself is the protocol
//! and kernel's business. The bundled sample ([`Job::sample`], `jobs/sample.gcode`) is a real
//! toolpath for the default router: a rectangular pocket in rings, a circular pocket with a
//! helical entry, the word FORJA engraved with lines and arcs, a profile groove with rounded
//! corners and four pecked holes, using G0/G1/G2/G3, feeds, spindle commands and both kinds of
//! comment.

use core::fmt;
use std::path::{Path, PathBuf};

/// The bundled sample job's text.
pub const SAMPLE_JOB: &str = include_str!("../jobs/sample.gcode");

/// A loaded job.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Job {
    name: String,
    text: String,
}

impl Job {
    /// The bundled sample job.
    pub fn sample() -> Self {
        Self {
            name: "sample.gcode (bundled)".to_string(),
            text: SAMPLE_JOB.to_string(),
        }
    }

    /// A job from text already in memory, named `name` in messages.
    pub fn from_text(name: impl Into<String>, text: impl Into<String>) -> Self {
        Self {
            name: name.into(),
            text: text.into(),
        }
    }

    /// Load a job file.
    ///
    /// Errors: the file cannot be read, or is not UTF-8 text (naming the first bad line), or
    /// contains a NUL byte.
    pub fn load(path: &Path) -> Result<Self, JobError> {
        let bytes = std::fs::read(path).map_err(|e| JobError::Io {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        let not_text = |at: usize| JobError::NotText {
            path: path.to_path_buf(),
            line: bytes[..at].iter().filter(|&&b| b == b'\n').count() + 1,
        };
        if let Some(at) = bytes.iter().position(|&b| b == 0) {
            return Err(not_text(at));
        }
        let text = std::str::from_utf8(&bytes)
            .map_err(|e| not_text(e.valid_up_to()))?
            .to_string();
        Ok(Self {
            name: path.display().to_string(),
            text,
        })
    }

    /// The name used in messages (the path, for a loaded file).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The whole text.
    pub fn text(&self) -> &str {
        &self.text
    }

    /// The lines, without their line ends.
    pub fn lines(&self) -> impl Iterator<Item = &str> {
        self.text.lines()
    }

    /// Number of lines.
    pub fn line_count(&self) -> usize {
        self.text.lines().count()
    }
}

/// A job file that cannot be used.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum JobError {
    /// It could not be read.
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's message.
        message: String,
    },
    /// It is not text.
    NotText {
        /// The file.
        path: PathBuf,
        /// 1-based line of the first byte that is not text.
        line: usize,
    },
}

impl fmt::Display for JobError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io { path, message } => write!(f, "{}: {message}", path.display()),
            Self::NotText { path, line } => {
                write!(f, "{} line {line}: not UTF-8 text", path.display())
            }
        }
    }
}

impl std::error::Error for JobError {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sample_is_a_real_program() {
        let job = Job::sample();
        let n = job.line_count();
        assert!((200..=600).contains(&n), "{n} lines");
        for word in ["G0 ", "G1 ", "G2 ", "G3 ", "F", "M3", "M5", "M84", "(", ";"] {
            assert!(job.text().contains(word), "sample lacks {word}");
        }
        assert!(job.text().is_ascii());
    }

    #[test]
    fn load_checks_text() {
        let dir = std::env::temp_dir().join(format!("forja-sim-job-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let good = dir.join("good.gcode");
        std::fs::write(&good, "G0 X1\nG1 X2 F100\n").unwrap();
        let job = Job::load(&good).unwrap();
        assert_eq!(job.lines().collect::<Vec<_>>(), ["G0 X1", "G1 X2 F100"]);
        assert_eq!(job.name(), good.display().to_string());

        let bad = dir.join("bad.gcode");
        std::fs::write(&bad, b"G0 X1\nG1 \xff\n").unwrap();
        assert!(matches!(
            Job::load(&bad).unwrap_err(),
            JobError::NotText { line: 2, .. }
        ));
        std::fs::write(&bad, b"G0 X1\n\nG1\0\n").unwrap();
        assert!(matches!(
            Job::load(&bad).unwrap_err(),
            JobError::NotText { line: 3, .. }
        ));
        let e = Job::load(&dir.join("missing.gcode")).unwrap_err();
        assert!(e.to_string().contains("missing.gcode"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
