//! The protocol's errors and their stable wire codes.
//!
//! Every error of this crate has a number in `1..=99` ([`WireError::code`]) and a short,
//! lower-case, kebab-case name ([`WireError::name`], which is also its `Display`). Both go on
//! the wire: `!! E<code> <name>` and `// E<code> <name>` on the G-code link, `Error:E<code>
//! <name>` in frame 56. Codes and names never change meaning once released; new ones are added
//! at the end of their block.
//!
//! | block | owner |
//! |---|---|
//! | 1–19 | [`LineError`]: G-code lines and line numbering |
//! | 20–39 | [`FrameError`]: 53-byte frames |
//! | 40–49 | [`EncodeError`]: writing a line, a frame or a reply |
//! | 50–59 | [`ReplyError`]: reading a controller's reply |
//! | 60–99 | reserved for the protocol |
//! | 100–199 | the motion kernel |
//! | 200–299 | storage and drivers |
//! | 300–399 | boards |
//!
//! Code 0 is never an error: in frame 56 it means "no code given".

use core::fmt;

/// An error that can be reported on the wire.
///
/// Implemented by every error of this crate, and meant to be implemented by the errors of the
/// other layers too (motion, drivers, boards) so that [`crate::reply`] and
/// [`crate::frame::ControllerMessage::error`] can report them.
pub trait WireError {
    /// The stable numeric code (see the [module documentation](self) for the allocation).
    fn code(&self) -> u16;
    /// The stable short name: lower case, no spaces (kebab-case), at most 24 bytes.
    fn name(&self) -> &'static str;
}

impl<T: WireError + ?Sized> WireError for &T {
    fn code(&self) -> u16 {
        T::code(self)
    }
    fn name(&self) -> &'static str {
        T::name(self)
    }
}

/// Why a G-code line was refused.
///
/// The variants for which [`is_framing`](LineError::is_framing) holds concern the line's framing
/// (its length, `N` and `*` fields, its check and its place in the numbering): the line may have
/// been damaged on the link and a resend repairs it. The others concern its body: the line
/// arrived intact (its check matched, if it had one) but is not valid G-code; `line` is then its
/// number, if it had one.
/// [`LineNumbering::recover`](crate::gcode::LineNumbering::recover) turns either into a reply.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum LineError {
    /// The line is longer than [`MAX_LINE_LEN`](crate::gcode::MAX_LINE_LEN) bytes. Code 1.
    TooLong,
    /// The checksum after `*` is not the XOR of the bytes before it. Code 2.
    ChecksumMismatch {
        /// The XOR of the bytes before `*`.
        computed: u8,
        /// The number written after `*`.
        received: u8,
    },
    /// The line has an `N` number but no `*` checksum. Code 3.
    MissingChecksum,
    /// The line has a `*` checksum but no `N` number. Code 4.
    MissingLineNumber,
    /// The field after `*` is not a number in `0..=255`, or is followed by more than a comment.
    /// Code 5.
    BadChecksum,
    /// The `N` field is not an integer in `0..=4294967295` (or `-1` on an `M110` line).
    /// Code 6.
    BadLineNumber,
    /// The line's number is not the one expected next. Code 7.
    OutOfOrder {
        /// The line number expected (the one to ask again).
        expected: u32,
        /// The line number received.
        got: u32,
    },
    /// A byte that cannot start a word: not a letter, space, tab or comment. Code 8.
    UnexpectedCharacter {
        /// The line's number, if it had one.
        line: Option<u32>,
    },
    /// A letter with no number after it. Code 9.
    MissingValue {
        /// The line's number, if it had one.
        line: Option<u32>,
    },
    /// A number with more than 18 fractional digits or a mantissa beyond 64 bits. Code 10.
    NumberOutOfRange {
        /// The line's number, if it had one.
        line: Option<u32>,
    },
    /// More than [`MAX_WORDS`](crate::gcode::MAX_WORDS) words. Code 11.
    TooManyWords {
        /// The line's number, if it had one.
        line: Option<u32>,
    },
    /// A `(` comment without its `)`. Code 12.
    UnclosedComment {
        /// The line's number, if it had one.
        line: Option<u32>,
    },
    /// The CRC-16 after `*` (five digits, see [`crc16`](crate::gcode::crc16)) is not the CRC of
    /// the bytes before it. Code 13.
    CrcMismatch {
        /// The CRC of the bytes before `*`.
        computed: u16,
        /// The number written after `*`.
        received: u16,
    },
    /// A numbered line with only the XOR checksum from a host that sends the CRC-16: once a
    /// line with the CRC is accepted, every numbered line must carry it, until the next `M110`.
    /// Code 14.
    WeakChecksum,
    /// The record holds nothing but a checksum (one to five digits): the rest of a numbered line
    /// whose `*` was damaged into a line end, the line itself having arrived (and been answered)
    /// as a record of its own. Code 15.
    Fragment,
}

impl LineError {
    /// The line to ask again when the error alone tells it: `Some(expected)` for
    /// [`LineError::OutOfOrder`]. For the other framing errors the expected line is known only
    /// to the link's [`LineNumbering`](crate::gcode::LineNumbering); use its
    /// [`recover`](crate::gcode::LineNumbering::recover).
    pub fn resend_line(&self) -> Option<u32> {
        match *self {
            Self::OutOfOrder { expected, .. } => Some(expected),
            _ => None,
        }
    }

    /// Whether a resend may repair the line: the error concerns its length, its `N` or `*`
    /// field, or its place in the numbering, any of which a damaged link can cause.
    pub fn is_framing(&self) -> bool {
        matches!(
            self,
            Self::TooLong
                | Self::ChecksumMismatch { .. }
                | Self::MissingChecksum
                | Self::MissingLineNumber
                | Self::BadChecksum
                | Self::BadLineNumber
                | Self::OutOfOrder { .. }
                | Self::CrcMismatch { .. }
                | Self::WeakChecksum
                | Self::Fragment
        )
    }

    /// For an error in the body of a line that arrived intact: its line number, if it had one.
    pub fn line(&self) -> Option<u32> {
        match *self {
            Self::UnexpectedCharacter { line }
            | Self::MissingValue { line }
            | Self::NumberOutOfRange { line }
            | Self::TooManyWords { line }
            | Self::UnclosedComment { line } => line,
            _ => None,
        }
    }

    /// The stable numeric code (see the [module documentation](self)).
    pub const fn code(&self) -> u16 {
        match self {
            Self::TooLong => 1,
            Self::ChecksumMismatch { .. } => 2,
            Self::MissingChecksum => 3,
            Self::MissingLineNumber => 4,
            Self::BadChecksum => 5,
            Self::BadLineNumber => 6,
            Self::OutOfOrder { .. } => 7,
            Self::UnexpectedCharacter { .. } => 8,
            Self::MissingValue { .. } => 9,
            Self::NumberOutOfRange { .. } => 10,
            Self::TooManyWords { .. } => 11,
            Self::UnclosedComment { .. } => 12,
            Self::CrcMismatch { .. } => 13,
            Self::WeakChecksum => 14,
            Self::Fragment => 15,
        }
    }

    /// The stable short name, also its `Display`.
    pub const fn name(&self) -> &'static str {
        match self {
            Self::TooLong => "line-too-long",
            Self::ChecksumMismatch { .. } => "checksum-mismatch",
            Self::MissingChecksum => "no-checksum",
            Self::MissingLineNumber => "no-line-number",
            Self::BadChecksum => "bad-checksum",
            Self::BadLineNumber => "bad-line-number",
            Self::OutOfOrder { .. } => "line-order",
            Self::UnexpectedCharacter { .. } => "bad-character",
            Self::MissingValue { .. } => "no-value",
            Self::NumberOutOfRange { .. } => "number-range",
            Self::TooManyWords { .. } => "too-many-words",
            Self::UnclosedComment { .. } => "open-comment",
            Self::CrcMismatch { .. } => "crc-mismatch",
            Self::WeakChecksum => "weak-checksum",
            Self::Fragment => "line-fragment",
        }
    }
}

/// Why bytes are not a valid 53-byte frame or message.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum FrameError {
    /// Not exactly [`FRAME_LEN`](crate::frame::FRAME_LEN) bytes. Code 20.
    Length,
    /// Not `N`, two digits, 49 bytes, `F`; also used for garbage skipped on a link. Code 21.
    Structure,
    /// A message type this side does not know. Code 22.
    UnknownType {
        /// The two-digit type read.
        message_type: u8,
    },
    /// The closing keyword of a 02 or 04 does not mirror the opening one. Code 23.
    Mirror,
    /// A field of the payload is malformed, out of range or not followed by `*` padding only.
    /// Code 24.
    Payload,
    /// A 02 keyword that names no action. Code 25.
    UnknownAction,
}

impl FrameError {
    /// The stable numeric code (see the [module documentation](self)).
    pub const fn code(&self) -> u16 {
        match self {
            Self::Length => 20,
            Self::Structure => 21,
            Self::UnknownType { .. } => 22,
            Self::Mirror => 23,
            Self::Payload => 24,
            Self::UnknownAction => 25,
        }
    }

    /// The stable short name, also its `Display`.
    pub const fn name(&self) -> &'static str {
        match self {
            Self::Length => "frame-length",
            Self::Structure => "frame",
            Self::UnknownType { .. } => "frame-type",
            Self::Mirror => "frame-mirror",
            Self::Payload => "frame-payload",
            Self::UnknownAction => "frame-action",
        }
    }
}

/// Why a line, frame or reply could not be written.
///
/// On error the output buffer holds unspecified bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum EncodeError {
    /// The caller's buffer is too small. Code 40.
    BufferTooSmall,
    /// The result would exceed the protocol's limit: a line over
    /// [`MAX_LINE_LEN`](crate::gcode::MAX_LINE_LEN), a payload over 49 bytes, a 03 text over 39.
    /// Code 41.
    TooLong,
    /// A text holds a byte the format cannot carry (`*` in a frame, a control byte, a space in a
    /// key), or would read back as something else. Code 42.
    InvalidText,
    /// A number does not fit its field, or a letter is not an upper-case ASCII letter. Code 43.
    OutOfRange,
}

impl EncodeError {
    /// The stable numeric code (see the [module documentation](self)).
    pub const fn code(&self) -> u16 {
        match self {
            Self::BufferTooSmall => 40,
            Self::TooLong => 41,
            Self::InvalidText => 42,
            Self::OutOfRange => 43,
        }
    }

    /// The stable short name, also its `Display`.
    pub const fn name(&self) -> &'static str {
        match self {
            Self::BufferTooSmall => "buffer-small",
            Self::TooLong => "too-long",
            Self::InvalidText => "bad-text",
            Self::OutOfRange => "out-of-range",
        }
    }
}

/// Why a line from a controller is not a reply this crate knows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum ReplyError {
    /// The line starts with none of `start`, `ok`, `rs`, `Resend:`, `!!`, `//`. Code 50.
    UnknownPrefix,
    /// The prefix is known but what follows is malformed (`rs` without a number, a byte
    /// outside printable ASCII). Code 51.
    Malformed,
}

impl ReplyError {
    /// The stable numeric code (see the [module documentation](self)).
    pub const fn code(&self) -> u16 {
        match self {
            Self::UnknownPrefix => 50,
            Self::Malformed => 51,
        }
    }

    /// The stable short name, also its `Display`.
    pub const fn name(&self) -> &'static str {
        match self {
            Self::UnknownPrefix => "reply-prefix",
            Self::Malformed => "reply-malformed",
        }
    }
}

macro_rules! display_and_error {
    ($($t:ty),*) => {$(
        impl WireError for $t {
            fn code(&self) -> u16 {
                <$t>::code(self)
            }
            fn name(&self) -> &'static str {
                <$t>::name(self)
            }
        }
        impl fmt::Display for $t {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(self.name())
            }
        }
        impl core::error::Error for $t {}
    )*};
}

display_and_error!(LineError, FrameError, EncodeError, ReplyError);

/// `E<1 to 5 digits>` then the end or a space, the number not 0: the code and the rest, as on
/// `!!` and `//` lines and in frame 56. `E0` is not a code: code 0 means none.
pub(crate) fn split_code(text: &str) -> Option<(u32, &str)> {
    let rest = text.strip_prefix('E')?;
    let n = rest.bytes().take_while(u8::is_ascii_digit).count();
    if !(1..=5).contains(&n) {
        return None;
    }
    let (code, after) = rest.split_at_checked(n)?;
    let detail = match after.strip_prefix(' ') {
        Some(detail) => detail,
        None if after.is_empty() => after,
        None => return None,
    };
    let code: u32 = code.parse().ok()?;
    (code > 0).then_some((code, detail))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic, clippy::indexing_slicing)]
mod tests {
    use super::*;

    fn all() -> [&'static dyn WireError; 28] {
        [
            &LineError::TooLong,
            &LineError::ChecksumMismatch {
                computed: 0,
                received: 1,
            },
            &LineError::MissingChecksum,
            &LineError::MissingLineNumber,
            &LineError::BadChecksum,
            &LineError::BadLineNumber,
            &LineError::OutOfOrder {
                expected: 1,
                got: 2,
            },
            &LineError::UnexpectedCharacter { line: None },
            &LineError::MissingValue { line: None },
            &LineError::NumberOutOfRange { line: None },
            &LineError::TooManyWords { line: None },
            &LineError::UnclosedComment { line: None },
            &LineError::CrcMismatch {
                computed: 0,
                received: 1,
            },
            &LineError::WeakChecksum,
            &LineError::Fragment,
            &FrameError::Length,
            &FrameError::Structure,
            &FrameError::UnknownType { message_type: 9 },
            &FrameError::Mirror,
            &FrameError::Payload,
            &FrameError::UnknownAction,
            &EncodeError::BufferTooSmall,
            &EncodeError::TooLong,
            &EncodeError::InvalidText,
            &EncodeError::OutOfRange,
            &ReplyError::UnknownPrefix,
            &ReplyError::Malformed,
            &LineError::TooLong,
        ]
    }

    #[test]
    fn codes_are_unique_and_in_the_protocol_block() {
        let errors = all();
        let distinct = &errors[..errors.len() - 1];
        for (i, a) in distinct.iter().enumerate() {
            assert!((1..=99).contains(&a.code()), "{}", a.name());
            assert!(a.name().len() <= 24);
            assert!(
                a.name()
                    .bytes()
                    .all(|b| b.is_ascii_lowercase() || b == b'-')
            );
            for b in &distinct[i + 1..] {
                assert_ne!(a.code(), b.code());
                assert_ne!(a.name(), b.name());
            }
        }
    }

    #[test]
    fn the_code_table_is_stable() {
        let table: [(u16, &str); 27] = [
            (1, "line-too-long"),
            (2, "checksum-mismatch"),
            (3, "no-checksum"),
            (4, "no-line-number"),
            (5, "bad-checksum"),
            (6, "bad-line-number"),
            (7, "line-order"),
            (8, "bad-character"),
            (9, "no-value"),
            (10, "number-range"),
            (11, "too-many-words"),
            (12, "open-comment"),
            (13, "crc-mismatch"),
            (14, "weak-checksum"),
            (15, "line-fragment"),
            (20, "frame-length"),
            (21, "frame"),
            (22, "frame-type"),
            (23, "frame-mirror"),
            (24, "frame-payload"),
            (25, "frame-action"),
            (40, "buffer-small"),
            (41, "too-long"),
            (42, "bad-text"),
            (43, "out-of-range"),
            (50, "reply-prefix"),
            (51, "reply-malformed"),
        ];
        for (e, (code, name)) in all().iter().zip(table) {
            assert_eq!((e.code(), e.name()), (code, name));
        }
    }
}
