//! G-code programs as the client sends them: read from a file, checked line by line, and
//! rewritten in a compact form that means the same.
//!
//! Every source line is parsed with [`forja_protocol::gcode::Line::parse`] before anything is
//! sent, so that a file that does not parse is refused with the number of its first bad line
//! and the machine never runs half of it. Blank and comment-only lines are not sent. Each other
//! line becomes its words without spaces (`G1X2.0Y2.0F3000.0`), the text of `M117`-style
//! commands after one space: comments and spaces dropped, every number exactly as written.
//!
//! A 03 frame carries at most [`MAX_LOAD_TEXT`] bytes of G-code. [`frame_text`] fits a line
//! into that: the compact form, then, if still too long, numbers written in their shortest
//! exact form (`X10.500` as `X10.5`, `F1500.0` as `F1500`, `X0.25` as `X.25`), which is the
//! same value. A line that still does not fit is refused with its line number.

use std::fmt::{self, Write as _};
use std::path::{Path, PathBuf};

use forja_protocol::frame::MAX_LOAD_TEXT;
use forja_protocol::gcode::{Decimal, Line, LineError, MAX_LINE_LEN, Word};

/// One line of a program that is sent: where it came from and what is sent.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ProgramLine {
    /// Its line number in the source file, 1-based.
    pub source_line: usize,
    /// The compact text sent: words without spaces, no comments, no line number.
    pub text: String,
}

/// A checked program: the lines to send, in order.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Program {
    /// Where it was read from (for messages), if from a file.
    pub path: Option<PathBuf>,
    /// The lines to send (blank and comment-only source lines are left out).
    pub lines: Vec<ProgramLine>,
    /// How many source lines the file has.
    pub source_lines: usize,
}

/// Why a program cannot be used.
#[derive(Debug)]
#[non_exhaustive]
pub enum ProgramError {
    /// The file could not be read.
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        error: std::io::Error,
    },
    /// A line does not parse, or cannot be sent as it is.
    Line {
        /// The file, if any.
        path: Option<PathBuf>,
        /// Its 1-based line number.
        line: usize,
        /// What is wrong, for people.
        reason: String,
    },
}

impl fmt::Display for ProgramError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io { path, error } if error.kind() == std::io::ErrorKind::NotFound => {
                write!(f, "there is no file {}", path.display())
            }
            Self::Io { path, error } => write!(f, "cannot read {}: {}", path.display(), error),
            Self::Line { path, line, reason } => match path {
                Some(path) => write!(f, "{}, line {line}: {reason}", path.display()),
                None => write!(f, "line {line}: {reason}"),
            },
        }
    }
}

impl std::error::Error for ProgramError {}

/// `raw` up to its `;` comment: the first `;` outside a `(…)` comment (a CAM post writes
/// `(tool: 3.175 mm; stock top at Z0)`).
fn before_semicolon_comment(raw: &[u8]) -> &[u8] {
    let mut in_paren = false;
    for (i, &b) in raw.iter().enumerate() {
        match b {
            b'(' => in_paren = true,
            b')' => in_paren = false,
            b';' if !in_paren => return raw.get(..i).unwrap_or(raw),
            _ => {}
        }
    }
    raw
}

/// What a [`LineError`] means, for people.
pub fn describe_line_error(error: &LineError) -> String {
    match *error {
        LineError::TooLong => format!("the line is longer than {MAX_LINE_LEN} bytes"),
        LineError::ChecksumMismatch { computed, received } => {
            format!("the checksum after '*' is {received}, but the line's bytes give {computed}")
        }
        LineError::MissingChecksum => "the line has an N number but no '*' checksum".into(),
        LineError::MissingLineNumber => "the line has a '*' checksum but no N number".into(),
        LineError::BadChecksum => "the checksum after '*' is not a number from 0 to 255".into(),
        LineError::BadLineNumber => "the N line number is not a whole number in range".into(),
        LineError::OutOfOrder { expected, got } => {
            format!("line number {got} is out of order ({expected} expected)")
        }
        LineError::UnexpectedCharacter { .. } => {
            "a character that cannot start a G-code word (words are a letter and a number)".into()
        }
        LineError::MissingValue { .. } => "a letter without a number after it".into(),
        LineError::NumberOutOfRange { .. } => {
            "a number with more than 18 decimals or too large".into()
        }
        LineError::TooManyWords { .. } => "more than 32 words on one line".into(),
        LineError::UnclosedComment { .. } => "a '(' comment that is not closed".into(),
        _ => error.to_string(),
    }
}

impl Program {
    /// Read and check a G-code file.
    ///
    /// Errors: the file cannot be read, or a line does not parse (with its number), or a line
    /// holds `M110` (line numbers are the client's own business while it streams).
    pub fn load(path: &Path) -> Result<Self, ProgramError> {
        let bytes = std::fs::read(path).map_err(|error| ProgramError::Io {
            path: path.to_path_buf(),
            error,
        })?;
        Self::parse(&bytes)
            .map_err(|e| match e {
                ProgramError::Line { line, reason, .. } => ProgramError::Line {
                    path: Some(path.to_path_buf()),
                    line,
                    reason,
                },
                e => e,
            })
            .map(|mut p| {
                p.path = Some(path.to_path_buf());
                p
            })
    }

    /// Check G-code text (as [`Program::load`], without a file).
    pub fn parse(bytes: &[u8]) -> Result<Self, ProgramError> {
        let mut lines = Vec::new();
        let mut count = 0;
        let pieces: Vec<&[u8]> = bytes.split(|&b| b == b'\n').collect();
        let last = pieces.len();
        for (i, raw) in pieces.into_iter().enumerate() {
            let n = i + 1;
            if n == last && raw.is_empty() {
                break;
            }
            count = n;
            let err = |reason: String| ProgramError::Line {
                path: None,
                line: n,
                reason,
            };
            // A `;` comment is the file's, never sent: a slicer's long settings comments
            // must not count against the length of a line.
            let code = before_semicolon_comment(raw);
            let line = Line::parse(code).map_err(|e| err(describe_line_error(&e)))?;
            if line.is_empty() {
                continue;
            }
            if line.is_command(b'M', 110) {
                return Err(err(
                    "M110 sets line numbers, which forja manages itself while it sends; remove \
                     the line"
                        .into(),
                ));
            }
            let text = compact(&line, false);
            // N<number> and *<checksum> must still fit a line.
            if text.len() + 16 > MAX_LINE_LEN {
                return Err(err(format!(
                    "the line is too long to send ({} bytes of G-code, at most {})",
                    text.len(),
                    MAX_LINE_LEN - 16
                )));
            }
            lines.push(ProgramLine {
                source_line: n,
                text,
            });
        }
        Ok(Self {
            path: None,
            lines,
            source_lines: count,
        })
    }

    /// The lines' texts, in order.
    pub fn texts(&self) -> impl Iterator<Item = &str> {
        self.lines.iter().map(|l| l.text.as_str())
    }

    /// The lines as 03-frame texts (at most [`MAX_LOAD_TEXT`] bytes each).
    ///
    /// Errors: the first line that cannot be shortened enough, with its source line number.
    pub fn frame_texts(&self) -> Result<Vec<String>, ProgramError> {
        self.lines
            .iter()
            .map(|l| {
                let parsed = Line::parse(l.text.as_bytes()).map_err(|e| ProgramError::Line {
                    path: self.path.clone(),
                    line: l.source_line,
                    reason: describe_line_error(&e),
                })?;
                frame_text(&parsed).ok_or_else(|| ProgramError::Line {
                    path: self.path.clone(),
                    line: l.source_line,
                    reason: format!(
                        "the line does not fit the {MAX_LOAD_TEXT} bytes a program line may \
                         have, even without spaces and comments (\"{}\", {} bytes); split it \
                         into shorter moves",
                        compact(&parsed, true),
                        compact(&parsed, true).len()
                    ),
                })
            })
            .collect()
    }
}

/// The words of `line` without spaces; a text argument after one space. With `shortest`,
/// numbers are written in their shortest exact form.
pub fn compact(line: &Line<'_>, shortest: bool) -> String {
    let mut out = String::new();
    for word in line.words() {
        push_word(&mut out, word, shortest);
    }
    if let Some(text) = line.text_arg() {
        out.push(' ');
        out.push_str(&String::from_utf8_lossy(text));
    }
    out
}

/// The text of a 03 frame for `line`: the compact form, or the shortest one if that does not
/// fit; `None` if neither fits [`MAX_LOAD_TEXT`] bytes.
pub fn frame_text(line: &Line<'_>) -> Option<String> {
    [false, true]
        .into_iter()
        .map(|shortest| compact(line, shortest))
        .find(|t| t.len() <= MAX_LOAD_TEXT)
}

fn push_word(out: &mut String, word: &Word, shortest: bool) {
    out.push(char::from(word.letter));
    if word.bare {
        // A flag (`G28 X Y`): the next word starts with its letter, so it reads back alone.
        return;
    }
    if shortest {
        out.push_str(&shortest_decimal(word.value));
    } else {
        let _ = write!(out, "{}", word.value);
    }
}

/// The shortest text that reads back as the same value: no trailing fractional zeros, no
/// point without decimals, no leading `0` before the point.
pub fn shortest_decimal(value: Decimal) -> String {
    let mut mantissa = value.mantissa();
    let mut scale = value.scale();
    while scale > 0 && mantissa % 10 == 0 {
        mantissa /= 10;
        scale -= 1;
    }
    let text = Decimal::new(mantissa, scale).to_string();
    if let Some(rest) = text.strip_prefix("0.") {
        format!(".{rest}")
    } else if let Some(rest) = text.strip_prefix("-0.") {
        format!("-.{rest}")
    } else {
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_semicolon_inside_a_parenthesised_comment_does_not_start_a_comment() {
        let p = Program::parse(b"(tool: 3.175 mm; stock top at Z0)\nG1 X1 (a;b) Y2 ; c\n").unwrap();
        let texts: Vec<_> = p.texts().collect();
        assert_eq!(texts, ["G1X1Y2"]);
    }

    #[test]
    fn compact_drops_comments_and_spaces_and_keeps_numbers() {
        let p = Program::parse(
            b"; header\n\nG21 (mm)\nG1 X2.0 Y2.0 F3000.0 ; move\nM117 Hello there\n(only)\n",
        )
        .unwrap();
        let texts: Vec<_> = p.texts().collect();
        assert_eq!(texts, ["G21", "G1X2.0Y2.0F3000.0", "M117 Hello there"]);
        assert_eq!(p.lines[1].source_line, 4);
        assert_eq!(p.source_lines, 6);
        // Flags stay flags: `G28 W` is not `G28 W0`.
        let p = Program::parse(b"G28 W\nM84 X Y E\nG28 X Y10\n").unwrap();
        assert_eq!(p.texts().collect::<Vec<_>>(), ["G28W", "M84XYE", "G28XY10"]);
        // A slicer's settings comment longer than a line is left out with its line.
        let long = format!(
            "G1 X1 ; {}\n; {}\nG1 X2\n",
            "x".repeat(400),
            "y".repeat(600)
        );
        let p = Program::parse(long.as_bytes()).unwrap();
        assert_eq!(p.texts().collect::<Vec<_>>(), ["G1X1", "G1X2"]);
    }

    #[test]
    fn bad_lines_are_refused_with_their_number() {
        let e = Program::parse(b"G21\nG1 X1\nG1 #5\n").unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 3: a character that cannot start a G-code word (words are a letter and a \
             number)"
        );
        let e = Program::parse(b"G1 X1\nM110 N5\n").unwrap_err();
        assert!(e.to_string().starts_with("line 2: M110"), "{e}");
        let e = Program::parse(b"G1 X(\n").unwrap_err();
        assert!(e.to_string().starts_with("line 1: "), "{e}");
    }

    #[test]
    fn shortest_numbers_keep_their_value() {
        let d = |m, s| shortest_decimal(Decimal::new(m, s));
        assert_eq!(d(10500, 3), "10.5");
        assert_eq!(d(15000, 1), "1500");
        assert_eq!(d(25, 2), ".25");
        assert_eq!(d(-250, 3), "-.25");
        assert_eq!(d(0, 3), "0");
        assert_eq!(d(-7, 0), "-7");
        for (m, s) in [(10500, 3), (25, 2), (-250, 3), (0, 3), (123_456, 4)] {
            let text = d(m, s);
            let back = Decimal::parse(text.as_bytes()).unwrap();
            assert_eq!(back.to_f64(), Decimal::new(m, s).to_f64());
        }
    }

    #[test]
    fn frame_texts_shorten_or_refuse() {
        let p = Program::parse(
            b"G1 X100.0000 Y200.0000 Z-0.5000 F1500.000 ; long\nG1 X1\n\
              G1 X123.4567 Y123.4567 Z123.4567 A123.4567 F1234.5\n",
        );
        let p = p.unwrap();
        let e = p.frame_texts().unwrap_err();
        assert!(
            e.to_string().starts_with("line 3: the line does not fit"),
            "{e}"
        );
        let p =
            Program::parse(b"G1 X100.0000 Y200.0000 Z-0.5000 A0.0000 F1500.000 ; long\nG1 X1\n")
                .unwrap();
        assert_eq!(p.lines[0].text.len(), 44);
        let texts = p.frame_texts().unwrap();
        assert_eq!(texts, ["G1X100Y200Z-.5A0F1500", "G1X1"]);
        for t in &texts {
            assert!(t.len() <= MAX_LOAD_TEXT);
        }
    }

    #[test]
    fn crlf_files_and_a_last_line_without_newline() {
        let p = Program::parse(b"G21\r\nG1 X1\r\nG1 X2").unwrap();
        assert_eq!(p.texts().collect::<Vec<_>>(), ["G21", "G1X1", "G1X2"]);
        assert_eq!(p.source_lines, 3);
    }
}
