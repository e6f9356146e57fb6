//! Replies from the controller to a G-code host (seed `003_…txt`, "Replies from the RepRap
//! machine to the host computer").
//!
//! Every reply is one line of printable ASCII ending in `\n`, starting with `start` (once, at
//! boot) or a two-character prefix: `ok`, `rs`, `!!` or `//`. [`Reply::encode`] writes one into
//! the caller's buffer, `\n` included; [`Reply::parse`] reads one back (for the host).
//!
//! ```
//! use forja_protocol::gcode::Decimal;
//! use forja_protocol::reply::Reply;
//!
//! let mut out = [0u8; 64];
//! let reply = Reply::Temperatures { extruder: Decimal::new(201, 0), bed: Decimal::new(117, 0) };
//! let n = reply.encode(&mut out).unwrap();
//! assert_eq!(&out[..n], b"ok T:201 B:117\n");
//! assert_eq!(Reply::parse(&out[..n]), Ok(reply));
//! ```

use heapless::Vec;

pub use crate::decimal::Decimal;
use crate::error::WireError;
pub use crate::error::{EncodeError, ReplyError};
pub use crate::gcode::Word;
use crate::write::{Cursor, Sink};

/// The most axes an `M114` reply carries.
pub const MAX_REPLY_AXES: usize = 8;

/// `FIRMWARE_NAME` in the `M115` reply.
pub const FIRMWARE_NAME: &str = "Forja";
/// `FIRMWARE_VERSION` in the `M115` reply: this crate's version.
pub const FIRMWARE_VERSION: &str = env!("CARGO_PKG_VERSION");
/// `FIRMWARE_URL` in the `M115` reply, percent-encoded as in the seed's sample.
pub const FIRMWARE_URL: &str = "https%3A//github.com/forja-firmware/forja";
/// `PROTOCOL_VERSION` in the `M115` reply: the version of what `docs/protocol.md` describes.
pub const PROTOCOL_VERSION: &str = "0.1";

/// The `M115` key that announces the strong line check: `LINE_CHECK:CRC16` means numbered lines
/// may carry the [`crc16`](crate::gcode::crc16) after `*` (five digits; see
/// [`write_checked`](crate::gcode::write_checked)), and that once one does, every numbered line
/// must until the next `M110`. A host that sees it should send the CRC; one that does not can go
/// on with the XOR.
pub const LINE_CHECK: (&str, &str) = ("LINE_CHECK", "CRC16");

/// The keys every Forja `M115` reply starts with; a board appends its own (`MACHINE_TYPE`,
/// `EXTRUDER_COUNT`, …), and [`LINE_CHECK`].
pub const FORJA_CAPABILITIES: [(&str, &str); 4] = [
    ("FIRMWARE_NAME", FIRMWARE_NAME),
    ("FIRMWARE_VERSION", FIRMWARE_VERSION),
    ("FIRMWARE_URL", FIRMWARE_URL),
    ("PROTOCOL_VERSION", PROTOCOL_VERSION),
];

/// The axes of an `M114` reply, in the order sent (`X`, `Y`, `Z`, `E` for the seed).
pub type Axes = Vec<Word, MAX_REPLY_AXES, u8>;

/// The `KEY:VALUE` pairs of an `M115` reply: given as pairs to encode, read as text when parsed.
/// Two values are equal when they hold the same pairs in the same order.
#[derive(Clone, Copy, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum KeyValues<'a> {
    /// Pairs to write: keys are `[A-Z0-9_]+`, values printable ASCII without spaces.
    Pairs(&'a [(&'a str, &'a str)]),
    /// The text after `ok `, as received (already checked to be pairs).
    Text(&'a str),
}

impl<'a> KeyValues<'a> {
    /// The pairs in order.
    pub fn iter(&self) -> KeyValueIter<'a> {
        match *self {
            Self::Pairs(pairs) => KeyValueIter::Pairs(pairs.iter()),
            Self::Text(text) => KeyValueIter::Text(text.split(' ')),
        }
    }

    /// The value of `key`.
    pub fn get(&self, key: &str) -> Option<&'a str> {
        self.iter().find(|(k, _)| *k == key).map(|(_, v)| v)
    }

    fn is_valid(&self) -> bool {
        if let Self::Text(text) = self
            && !text.split(' ').all(|token| token.contains(':'))
        {
            return false;
        }
        let mut named = false;
        for (key, value) in self.iter() {
            let key_ok = !key.is_empty()
                && key
                    .bytes()
                    .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'_');
            if !key_ok || !value.bytes().all(|b| b.is_ascii_graphic()) {
                return false;
            }
            named |= key == "FIRMWARE_NAME";
        }
        named
    }
}

impl PartialEq for KeyValues<'_> {
    fn eq(&self, other: &Self) -> bool {
        self.iter().eq(other.iter())
    }
}

impl Eq for KeyValues<'_> {}

/// The iterator of [`KeyValues::iter`].
#[derive(Clone, Debug)]
pub enum KeyValueIter<'a> {
    /// Over pairs.
    Pairs(core::slice::Iter<'a, (&'a str, &'a str)>),
    /// Over received text.
    Text(core::str::Split<'a, char>),
}

impl<'a> Iterator for KeyValueIter<'a> {
    type Item = (&'a str, &'a str);

    fn next(&mut self) -> Option<Self::Item> {
        match self {
            Self::Pairs(pairs) => pairs.next().copied(),
            Self::Text(tokens) => tokens
                .next()
                .map(|token| token.split_once(':').unwrap_or((token, ""))),
        }
    }
}

/// One reply line.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Reply<'a> {
    /// `start`: sent once at boot, before anything else.
    Start,
    /// `ok`: the line was taken (and, for an unbuffered command, done).
    Ok,
    /// `ok <text>`: `ok` with other information (`ok Files: {…}`).
    OkWith(&'a str),
    /// `rs <line>`: send line `<line>` again, and those after it.
    Resend(u32),
    /// `!! E<code> <text>` (`!! <text>` when `code` is 0): an error. Followed by `ok` when it
    /// refuses a line (the line had no effect); sent alone when a fault stopped the machine.
    Fault {
        /// The error's stable code; 0 when none is given.
        code: u16,
        /// The error's name and any detail.
        text: &'a str,
    },
    /// `// E<code> <text>`: coded information that needs no action from the host.
    Notice {
        /// The error's stable code, at least 1.
        code: u16,
        /// The error's name and any detail.
        text: &'a str,
    },
    /// `// <text>`: information, at any time.
    Debug(&'a str),
    /// `ok T:<extruder> B:<bed>`: the answer to `M105`, in °C (below -273 when there is no
    /// sensor).
    Temperatures {
        /// The current extruder's temperature.
        extruder: Decimal,
        /// The bed's temperature.
        bed: Decimal,
    },
    /// `ok C: X:<x> Y:<y> Z:<z> E:<e>`: the answer to `M114`, in mm.
    Position(Axes),
    /// `ok KEY:VALUE …` with a `FIRMWARE_NAME` key: the answer to `M115`.
    Capabilities(KeyValues<'a>),
}

/// Printable ASCII: what a reply may carry.
fn printable(text: &str) -> bool {
    text.bytes().all(|b| (b' '..=b'~').contains(&b))
}

/// [`crate::error::split_code`] for a code that fits a `u16`; a larger one is no code.
fn split_code(text: &str) -> Option<(u16, &str)> {
    let (code, detail) = crate::error::split_code(text)?;
    Some((u16::try_from(code).ok()?, detail))
}

impl<'a> Reply<'a> {
    /// `!! E<code> <name>`: a refused line (an `ok` follows) or a fault that stopped the machine.
    pub fn fault(error: &impl WireError) -> Reply<'static> {
        Reply::Fault {
            code: error.code(),
            text: error.name(),
        }
    }

    /// `// E<code> <name>`: coded information that needs no action from the host.
    pub fn notice(error: &impl WireError) -> Reply<'static> {
        Reply::Notice {
            code: error.code(),
            text: error.name(),
        }
    }

    /// Write the reply into `out`, `\n` included, and return its length.
    ///
    /// Fails with [`EncodeError::BufferTooSmall`], or [`EncodeError::InvalidText`] for a text
    /// that is not printable ASCII or would read back as another reply (an empty `OkWith`, a
    /// `Debug` text that starts like a code, `Capabilities` without `FIRMWARE_NAME`), or
    /// [`EncodeError::OutOfRange`] for a `Notice` with code 0 or an axis letter that is not
    /// upper-case ASCII.
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, EncodeError> {
        let mut w = Cursor::new(out);
        let text_ok = |t: &str| {
            if printable(t) {
                Ok(())
            } else {
                Err(EncodeError::InvalidText)
            }
        };
        match self {
            Self::Start => w.put_all(b"start")?,
            Self::Ok => w.put_all(b"ok")?,
            Self::OkWith(text) => {
                text_ok(text)?;
                if !matches!(classify_ok(text), Ok(Reply::OkWith(_))) {
                    return Err(EncodeError::InvalidText);
                }
                w.put_all(b"ok ")?;
                w.put_all(text.as_bytes())?;
            }
            Self::Resend(line) => {
                w.put_all(b"rs ")?;
                w.put_u64(u64::from(*line))?;
            }
            Self::Fault { code, text } => {
                text_ok(text)?;
                w.put_all(b"!! ")?;
                put_coded(&mut w, *code, text)?;
            }
            Self::Notice { code, text } => {
                text_ok(text)?;
                if *code == 0 {
                    return Err(EncodeError::OutOfRange);
                }
                w.put_all(b"// ")?;
                put_coded(&mut w, *code, text)?;
            }
            Self::Debug(text) => {
                text_ok(text)?;
                if split_code(text).is_some() {
                    return Err(EncodeError::InvalidText);
                }
                w.put_all(b"// ")?;
                w.put_all(text.as_bytes())?;
            }
            Self::Temperatures { extruder, bed } => {
                w.put_all(b"ok T:")?;
                extruder.write_checked(&mut w)?;
                w.put_all(b" B:")?;
                bed.write_checked(&mut w)?;
            }
            Self::Position(axes) => {
                w.put_all(b"ok C:")?;
                for axis in axes {
                    if !axis.letter.is_ascii_uppercase() {
                        return Err(EncodeError::OutOfRange);
                    }
                    w.put(b' ')?;
                    w.put(axis.letter)?;
                    w.put(b':')?;
                    axis.value.write_checked(&mut w)?;
                }
            }
            Self::Capabilities(pairs) => {
                if !pairs.is_valid() {
                    return Err(EncodeError::InvalidText);
                }
                w.put_all(b"ok")?;
                for (key, value) in pairs.iter() {
                    w.put(b' ')?;
                    w.put_all(key.as_bytes())?;
                    w.put(b':')?;
                    w.put_all(value.as_bytes())?;
                }
            }
        }
        w.put(b'\n')?;
        Ok(w.len())
    }

    /// Read one reply line (a trailing `\n`, `\r` or `\r\n` is ignored). Also reads Marlin's
    /// `Resend: <line>` as [`Reply::Resend`].
    pub fn parse(line: &'a [u8]) -> Result<Reply<'a>, ReplyError> {
        let mut line = line;
        while let [rest @ .., b'\r' | b'\n'] = line {
            line = rest;
        }
        let text = core::str::from_utf8(line).map_err(|_| ReplyError::Malformed)?;
        if !printable(text) {
            return Err(ReplyError::Malformed);
        }
        if text == "start" {
            return Ok(Reply::Start);
        }
        if text == "ok" {
            return Ok(Reply::Ok);
        }
        if let Some(rest) = text.strip_prefix("ok ") {
            return classify_ok(rest);
        }
        if let Some(rest) = text
            .strip_prefix("rs ")
            .or_else(|| text.strip_prefix("Resend:"))
        {
            let digits = rest.trim_matches(' ');
            if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
                return Err(ReplyError::Malformed);
            }
            return digits
                .parse()
                .map(Reply::Resend)
                .map_err(|_| ReplyError::Malformed);
        }
        if let Some(rest) = text.strip_prefix("!!") {
            let rest = rest.strip_prefix(' ').unwrap_or(rest);
            return Ok(match split_code(rest) {
                Some((code, text)) => Reply::Fault { code, text },
                None => Reply::Fault {
                    code: 0,
                    text: rest,
                },
            });
        }
        if let Some(rest) = text.strip_prefix("//") {
            let rest = rest.strip_prefix(' ').unwrap_or(rest);
            return Ok(match split_code(rest) {
                Some((code, text)) => Reply::Notice { code, text },
                _ => Reply::Debug(rest),
            });
        }
        Err(ReplyError::UnknownPrefix)
    }
}

fn put_coded<S: Sink>(w: &mut S, code: u16, text: &str) -> Result<(), EncodeError> {
    if code == 0 {
        if split_code(text).is_some() {
            return Err(EncodeError::InvalidText);
        }
    } else {
        w.put(b'E')?;
        w.put_u64(u64::from(code))?;
        if !text.is_empty() {
            w.put(b' ')?;
        }
    }
    w.put_all(text.as_bytes())
}

/// What follows `ok `.
fn classify_ok(rest: &str) -> Result<Reply<'_>, ReplyError> {
    if rest.is_empty() {
        return Ok(Reply::Ok);
    }
    if let Some(reply) = parse_temperatures(rest) {
        return Ok(reply);
    }
    if let Some(axes) = rest.strip_prefix("C:").and_then(parse_axes) {
        return Ok(Reply::Position(axes));
    }
    let pairs = KeyValues::Text(rest);
    if pairs.is_valid() {
        return Ok(Reply::Capabilities(pairs));
    }
    Ok(Reply::OkWith(rest))
}

fn parse_temperatures(rest: &str) -> Option<Reply<'_>> {
    let (t, b) = rest.strip_prefix("T:")?.split_once(" B:")?;
    Some(Reply::Temperatures {
        extruder: Decimal::parse(t.as_bytes())?,
        bed: Decimal::parse(b.as_bytes())?,
    })
}

/// ` X:<x> Y:<y> …` after `C:`.
fn parse_axes(rest: &str) -> Option<Axes> {
    let mut axes = Axes::new();
    if rest.is_empty() {
        return Some(axes);
    }
    for token in rest.strip_prefix(' ')?.split(' ') {
        let (letter, value) = token.split_once(':')?;
        let [letter] = letter.as_bytes() else {
            return None;
        };
        if !letter.is_ascii_uppercase() {
            return None;
        }
        axes.push(Word::new(*letter, Decimal::parse(value.as_bytes())?))
            .ok()?;
    }
    Some(axes)
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic, clippy::indexing_slicing)]
mod tests {
    extern crate std;

    use super::*;
    use crate::error::{FrameError, LineError};

    fn encoded(reply: &Reply<'_>) -> std::string::String {
        let mut out = [0u8; 256];
        let n = reply.encode(&mut out).unwrap();
        std::string::String::from_utf8(out[..n].to_vec()).unwrap()
    }

    fn d(text: &str) -> Decimal {
        Decimal::parse(text.as_bytes()).unwrap()
    }

    #[test]
    fn the_seed_replies() {
        let position = Axes::from_slice(&[
            Word::new(b'X', d("0.00")),
            Word::new(b'Y', d("0.00")),
            Word::new(b'Z', d("0.00")),
            Word::new(b'E', d("0.00")),
        ])
        .unwrap();
        let seed_pairs = [
            ("PROTOCOL_VERSION", "0.1"),
            ("FIRMWARE_NAME", "FiveD"),
            ("FIRMWARE_URL", "http%3A//reprap.org"),
            ("MACHINE_TYPE", "Mendel"),
            ("EXTRUDER_COUNT", "1"),
        ];
        let cases = [
            (Reply::Start, "start\n"),
            (Reply::Ok, "ok\n"),
            (Reply::Resend(42), "rs 42\n"),
            (
                Reply::Temperatures {
                    extruder: d("201"),
                    bed: d("117"),
                },
                "ok T:201 B:117\n",
            ),
            (
                Reply::Temperatures {
                    extruder: d("93.2"),
                    bed: d("22.9"),
                },
                "ok T:93.2 B:22.9\n",
            ),
            (
                Reply::Position(position),
                "ok C: X:0.00 Y:0.00 Z:0.00 E:0.00\n",
            ),
            (
                Reply::Capabilities(KeyValues::Pairs(&seed_pairs)),
                "ok PROTOCOL_VERSION:0.1 FIRMWARE_NAME:FiveD FIRMWARE_URL:http%3A//reprap.org MACHINE_TYPE:Mendel EXTRUDER_COUNT:1\n",
            ),
            (
                Reply::OkWith("Files: {SQUARE.G,SQCOM.G,}"),
                "ok Files: {SQUARE.G,SQCOM.G,}\n",
            ),
            (
                Reply::Debug("This is some debugging or other information on a line on its own."),
                "// This is some debugging or other information on a line on its own.\n",
            ),
            (Reply::fault(&FrameError::Structure), "!! E21 frame\n"),
            (
                Reply::notice(&LineError::MissingValue { line: None }),
                "// E9 no-value\n",
            ),
            (
                Reply::Fault {
                    code: 0,
                    text: "thermal runaway",
                },
                "!! thermal runaway\n",
            ),
        ];
        for (reply, text) in cases {
            assert_eq!(encoded(&reply), text);
            assert_eq!(Reply::parse(text.as_bytes()), Ok(reply), "{text}");
        }
    }

    #[test]
    fn forja_capabilities() {
        let mut pairs = std::vec::Vec::from(FORJA_CAPABILITIES);
        pairs.push(("MACHINE_TYPE", "CNC"));
        let reply = Reply::Capabilities(KeyValues::Pairs(&pairs));
        let text = encoded(&reply);
        assert!(text.starts_with("ok FIRMWARE_NAME:Forja FIRMWARE_VERSION:"));
        let parsed = Reply::parse(text.as_bytes()).unwrap();
        assert_eq!(parsed, reply);
        let Reply::Capabilities(kv) = parsed else {
            panic!()
        };
        assert_eq!(kv.get("MACHINE_TYPE"), Some("CNC"));
    }

    #[test]
    fn refused_encodings() {
        let mut out = [0u8; 64];
        for reply in [
            Reply::OkWith(""),
            Reply::OkWith("T:1 B:2"),
            Reply::OkWith("bad\u{7f}"),
            Reply::Debug("E12 looks coded"),
            Reply::Fault {
                code: 0,
                text: "E1",
            },
            Reply::Capabilities(KeyValues::Pairs(&[("MACHINE_TYPE", "x")])),
            Reply::Capabilities(KeyValues::Pairs(&[("FIRMWARE_NAME", "a b")])),
        ] {
            assert_eq!(
                reply.encode(&mut out),
                Err(EncodeError::InvalidText),
                "{reply:?}"
            );
        }
        assert_eq!(
            Reply::Notice { code: 0, text: "x" }.encode(&mut out),
            Err(EncodeError::OutOfRange)
        );
        assert_eq!(
            Reply::Ok.encode(&mut out[..2]),
            Err(EncodeError::BufferTooSmall)
        );
    }

    #[test]
    fn parsing() {
        assert_eq!(Reply::parse(b"Resend: 7\r\n"), Ok(Reply::Resend(7)));
        assert_eq!(Reply::parse(b"rs x"), Err(ReplyError::Malformed));
        assert_eq!(Reply::parse(b"rs 99999999999"), Err(ReplyError::Malformed));
        assert_eq!(Reply::parse(b"echo:busy"), Err(ReplyError::UnknownPrefix));
        assert_eq!(Reply::parse(b"okay"), Err(ReplyError::UnknownPrefix));
        assert_eq!(Reply::parse(b"ok \x01"), Err(ReplyError::Malformed));
        assert_eq!(Reply::parse(b"ok "), Ok(Reply::Ok));
        assert_eq!(Reply::parse(b"//"), Ok(Reply::Debug("")));
        assert_eq!(
            Reply::parse(b"ok T:201 /0 B:117 /0 @:0"),
            Ok(Reply::OkWith("T:201 /0 B:117 /0 @:0"))
        );
        assert_eq!(Reply::parse(b"ok C:"), Ok(Reply::Position(Axes::new())));
        // `E0` is not a code: the text is kept whole and written back as it came.
        let fault = Reply::parse(b"!!E0 E0 E").unwrap();
        assert_eq!(
            fault,
            Reply::Fault {
                code: 0,
                text: "E0 E0 E"
            }
        );
        assert_eq!(encoded(&fault), "!! E0 E0 E\n");
        // `.5` is written `0.5`: a reply may grow when written back.
        let grown = Reply::parse(b"ok C: X:.5").unwrap();
        assert_eq!(encoded(&grown), "ok C: X:0.5\n");
    }
}
