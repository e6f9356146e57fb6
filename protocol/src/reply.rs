//! Replies from the controller to a G-code host, in the forms that printer hosts parse:
//! Marlin's, as OctoPrint (`comm.py`), Printrun (`printcore`) and CNCjs (its Marlin line
//! parsers) read them. Seed `003_…txt` gives the prefixes `ok`, `rs`, `!!` and `//`; where the
//! hosts read another form, the host's form is the one sent, and `docs/protocol.md` says so.
//!
//! Every reply is one line of printable ASCII ending in `\n`. [`Reply::encode`] writes one
//! into the caller's buffer, `\n` included; [`Reply::parse`] reads one back (for the host).
//!
//! | reply | form | follows it |
//! |---|---|---|
//! | [`Reply::Ok`] | `ok` | |
//! | [`Reply::Resend`] | `rs <line>` (Marlin's `Resend: <line>` is read too) | `ok` |
//! | [`Reply::Refused`] | `echo:E<code> <name> <detail>`: the line changed nothing | `ok` |
//! | [`Reply::Unknown`] | `echo:Unknown command: "<command>"` | `ok` |
//! | [`Reply::Busy`] | `echo:busy: processing`, every few seconds while a command blocks | |
//! | [`Reply::Fault`] | `Error:E<code> <name> <detail>`: a fault stopped the machine | |
//! | [`Reply::Temperatures`] | `ok T:25.0 /200.0 B:25.0 /60.0 @:0 B@:0` (`M105`), the same without `ok` (waits, `M155`) | |
//! | [`Reply::Position`] | `X:10.00 Y:0.00 Z:0.00 E:0.00 Count X:800 Y:0 Z:0` (`M114`) | `ok` |
//! | [`Reply::Firmware`], [`Reply::Capability`] | `FIRMWARE_NAME:Forja …`, then `Cap:<NAME>:<0/1>` lines (`M115`) | `ok` |
//!
//! ```
//! use forja_protocol::gcode::Decimal;
//! use forja_protocol::reply::{Heat, Reply};
//!
//! let mut out = [0u8; 64];
//! let hot_end = Heat { current: Decimal::new(2012, 1), target: Decimal::new(200, 0), power: 64 };
//! let reply = Reply::Temperatures { hot_end: Some(hot_end), bed: None, ok: true };
//! let n = reply.encode(&mut out).unwrap();
//! assert_eq!(&out[..n], b"ok T:201.2 /200 @:64\n");
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
/// `EXTRUDER_COUNT`, …), and [`LINE_CHECK`]. The `Cap:` lines follow ([`Reply::Capability`]).
pub const FORJA_CAPABILITIES: [(&str, &str); 4] = [
    ("FIRMWARE_NAME", FIRMWARE_NAME),
    ("FIRMWARE_VERSION", FIRMWARE_VERSION),
    ("FIRMWARE_URL", FIRMWARE_URL),
    ("PROTOCOL_VERSION", PROTOCOL_VERSION),
];

/// The axes of an `M114` reply, in the order sent (`X`, `Y`, `Z`, `E` for a printer).
pub type Axes = Vec<Word, MAX_REPLY_AXES, u8>;

/// The step counts after `Count` in an `M114` reply: an axis letter and its motor's position
/// in steps.
pub type Counts = Vec<(u8, i32), MAX_REPLY_AXES, u8>;

/// The reply text that a refused line's code and name come after: `echo:`.
pub const REFUSED_PREFIX: &str = "echo:";

/// The text of [`Reply::Busy`], after `echo:`.
pub const BUSY_TEXT: &str = "busy: processing";

/// One heater in a temperature report: `<current> /<target>`, and its power.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Heat {
    /// The measured temperature, °C.
    pub current: Decimal,
    /// The target, °C; 0 when the heater is off.
    pub target: Decimal,
    /// The heater's power on Marlin's scale, 0 (off) to 127 (full), sent as `@:` (`B@:` for
    /// the bed).
    pub power: u8,
}

/// The `KEY:VALUE` pairs of an `M115` reply: given as pairs to encode, read as text when parsed.
/// Two values are equal when they hold the same pairs in the same order.
#[derive(Clone, Copy, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum KeyValues<'a> {
    /// Pairs to write: keys are `[A-Z0-9_]+`, values printable ASCII without spaces.
    Pairs(&'a [(&'a str, &'a str)]),
    /// The line as received (already checked to be pairs).
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
    /// `ok`: the line was taken (and, for an unbuffered command, done); after a
    /// [`Reply::Refused`], [`Reply::Unknown`] or [`Reply::Resend`], the line is answered and
    /// the host may send the next.
    Ok,
    /// `ok <text>`: `ok` with other information (`ok x_min:open y_min:TRIGGERED`).
    OkWith(&'a str),
    /// `rs <line>`: send line `<line>` again, and those after it. An `ok` follows.
    Resend(u32),
    /// `echo:E<code> <text>`: the line was refused and changed nothing. An `ok` follows.
    Refused {
        /// The error's stable code, at least 1.
        code: u16,
        /// The error's name and any detail.
        text: &'a str,
    },
    /// `echo:Unknown command: "<command>"`: a command this firmware does not have; nothing
    /// changed. An `ok` follows. Hosts pass over it (Marlin's form).
    Unknown(&'a str),
    /// `echo:busy: processing`: a command is still running (a homing, a dwell, `M400`); sent
    /// every few seconds until its `ok`, so that a host does not time out.
    Busy,
    /// `echo:<text>`: a message for the operator (`M118`), or information.
    Echo(&'a str),
    /// `Error:E<code> <text>` (`Error:<text>` when `code` is 0): a fault that stopped the
    /// machine, sent alone. Hosts stop their job on it.
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
    /// `// <text>`: information, at any time (`// action:notification …` for OctoPrint).
    Debug(&'a str),
    /// `T:<c> /<t> B:<c> /<t> @:<p> B@:<p>`, the heaters the machine has: the answer to
    /// `M105` after `ok ` (`ok: true`), a report during a heating wait or from `M155` without.
    Temperatures {
        /// The current hot end, `T`.
        hot_end: Option<Heat>,
        /// The bed, `B`.
        bed: Option<Heat>,
        /// Whether the report is `M105`'s answer, `ok ` first.
        ok: bool,
    },
    /// `X:<x> Y:<y> … Count X:<n> …`: the answer to `M114`, in mm, then the step counts. An
    /// `ok` follows.
    Position {
        /// The work positions, mm.
        axes: Axes,
        /// The motors' step counts.
        counts: Counts,
    },
    /// `FIRMWARE_NAME:… KEY:VALUE …`: the first line of the answer to `M115`; `Cap:` lines
    /// and `ok` follow.
    Firmware(KeyValues<'a>),
    /// `Cap:<NAME>:<0|1>`: one capability in the answer to `M115`.
    Capability {
        /// The capability, `[A-Z0-9_]+` (`AUTOREPORT_TEMP`, `EMERGENCY_PARSER`).
        name: &'a str,
        /// Whether the firmware has it.
        enabled: bool,
    },
}

/// Printable ASCII: what a reply may carry.
fn printable(text: &str) -> bool {
    text.bytes().all(|b| (b' '..=b'~').contains(&b))
}

/// A capability or key name: `[A-Z0-9_]+`.
fn is_key(key: &str) -> bool {
    !key.is_empty()
        && key
            .bytes()
            .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'_')
}

/// [`crate::error::split_code`] for a code that fits a `u16`; a larger one is no code.
fn split_code(text: &str) -> Option<(u16, &str)> {
    let (code, detail) = crate::error::split_code(text)?;
    Some((u16::try_from(code).ok()?, detail))
}

/// The prefix of Marlin's unknown-command message.
const UNKNOWN_PREFIX: &str = "Unknown command: \"";

impl<'a> Reply<'a> {
    /// `Error:E<code> <name>`: a fault that stopped the machine.
    pub fn fault(error: &impl WireError) -> Reply<'static> {
        Reply::Fault {
            code: error.code(),
            text: error.name(),
        }
    }

    /// `echo:E<code> <name>`: a refused line (an `ok` follows).
    pub fn refused(error: &impl WireError) -> Reply<'static> {
        Reply::Refused {
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

    /// Whether an `ok` follows this reply for the same line ([`Reply::Resend`],
    /// [`Reply::Refused`], [`Reply::Unknown`], [`Reply::Position`], [`Reply::Firmware`],
    /// [`Reply::Capability`]): a host counts that `ok`, not this line, as the line's answer.
    pub fn ok_follows(&self) -> bool {
        matches!(
            self,
            Self::Resend(_)
                | Self::Refused { .. }
                | Self::Unknown(_)
                | Self::Position { .. }
                | Self::Firmware(_)
                | Self::Capability { .. }
        )
    }

    /// Write the reply into `out`, `\n` included, and return its length.
    ///
    /// Fails with [`EncodeError::BufferTooSmall`], or [`EncodeError::InvalidText`] for a text
    /// that is not printable ASCII or would read back as another reply (an `OkWith` without a
    /// word or that starts like a temperature report, a `Debug` or `Echo` text that starts
    /// like a code, `Firmware` without `FIRMWARE_NAME`, a command with a `"`), or
    /// [`EncodeError::OutOfRange`] for a `Notice` or `Refused` with code 0, a report without a
    /// heater, or an axis letter that is not upper-case ASCII.
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
                if !plain_ok_text(text) {
                    return Err(EncodeError::InvalidText);
                }
                w.put_all(b"ok ")?;
                w.put_all(text.as_bytes())?;
            }
            Self::Resend(line) => {
                w.put_all(b"rs ")?;
                w.put_u64(u64::from(*line))?;
            }
            Self::Refused { code, text } => {
                text_ok(text)?;
                if *code == 0 {
                    return Err(EncodeError::OutOfRange);
                }
                w.put_all(REFUSED_PREFIX.as_bytes())?;
                put_coded(&mut w, *code, text)?;
            }
            Self::Unknown(command) => {
                text_ok(command)?;
                if command.contains('"') {
                    return Err(EncodeError::InvalidText);
                }
                w.put_all(b"echo:")?;
                w.put_all(UNKNOWN_PREFIX.as_bytes())?;
                w.put_all(command.as_bytes())?;
                w.put(b'"')?;
            }
            Self::Busy => {
                w.put_all(b"echo:")?;
                w.put_all(BUSY_TEXT.as_bytes())?;
            }
            Self::Echo(text) => {
                text_ok(text)?;
                if !matches!(classify_echo(text), Reply::Echo(_)) {
                    return Err(EncodeError::InvalidText);
                }
                w.put_all(b"echo:")?;
                w.put_all(text.as_bytes())?;
            }
            Self::Fault { code, text } => {
                text_ok(text)?;
                w.put_all(b"Error:")?;
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
            Self::Temperatures { hot_end, bed, ok } => {
                if hot_end.is_none() && bed.is_none() {
                    return Err(EncodeError::OutOfRange);
                }
                if *ok {
                    w.put_all(b"ok ")?;
                } else {
                    // Marlin's reports start with a space; hosts trim it.
                    w.put(b' ')?;
                }
                let zones = [(b"T:" as &[u8], hot_end), (b"B:", bed)];
                let mut first = true;
                for (name, heat) in zones {
                    let Some(h) = heat else { continue };
                    if !first {
                        w.put(b' ')?;
                    }
                    first = false;
                    w.put_all(name)?;
                    h.current.write_checked(&mut w)?;
                    w.put_all(b" /")?;
                    h.target.write_checked(&mut w)?;
                }
                for (name, heat) in [(b" @:" as &[u8], hot_end), (b" B@:", bed)] {
                    if let Some(h) = heat {
                        w.put_all(name)?;
                        w.put_u64(u64::from(h.power))?;
                    }
                }
            }
            Self::Position { axes, counts } => {
                let mut first = true;
                for axis in axes {
                    if !axis.letter.is_ascii_uppercase() {
                        return Err(EncodeError::OutOfRange);
                    }
                    if !first {
                        w.put(b' ')?;
                    }
                    first = false;
                    w.put(axis.letter)?;
                    w.put(b':')?;
                    axis.value.write_checked(&mut w)?;
                }
                if first {
                    return Err(EncodeError::OutOfRange);
                }
                if !counts.is_empty() {
                    w.put_all(b" Count")?;
                    for (letter, steps) in counts {
                        if !letter.is_ascii_uppercase() {
                            return Err(EncodeError::OutOfRange);
                        }
                        w.put(b' ')?;
                        w.put(*letter)?;
                        w.put(b':')?;
                        w.put_i64(i64::from(*steps))?;
                    }
                }
            }
            Self::Firmware(pairs) => {
                if !pairs.is_valid() {
                    return Err(EncodeError::InvalidText);
                }
                let mut first = true;
                for (key, value) in pairs.iter() {
                    if !first {
                        w.put(b' ')?;
                    }
                    first = false;
                    w.put_all(key.as_bytes())?;
                    w.put(b':')?;
                    w.put_all(value.as_bytes())?;
                }
            }
            Self::Capability { name, enabled } => {
                if !is_key(name) {
                    return Err(EncodeError::InvalidText);
                }
                w.put_all(b"Cap:")?;
                w.put_all(name.as_bytes())?;
                w.put_all(if *enabled { b":1" } else { b":0" })?;
            }
        }
        w.put(b'\n')?;
        Ok(w.len())
    }

    /// Read one reply line (a trailing `\n`, `\r` or `\r\n` is ignored). Also reads Marlin's
    /// `Resend: <line>` as [`Reply::Resend`], `!!` (the seed's fault prefix) as
    /// [`Reply::Fault`], and `echo:` lines that are none of the above as [`Reply::Echo`].
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
        if let Some(rest) = text.strip_prefix("echo:") {
            return Ok(classify_echo(rest));
        }
        if let Some(rest) = text
            .strip_prefix("Error:")
            .or_else(|| text.strip_prefix("!!"))
        {
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
        if let Some(rest) = text.strip_prefix("Cap:") {
            let (name, value) = rest.rsplit_once(':').ok_or(ReplyError::Malformed)?;
            if !is_key(name) || !matches!(value, "0" | "1") {
                return Err(ReplyError::Malformed);
            }
            return Ok(Reply::Capability {
                name,
                enabled: value == "1",
            });
        }
        if text.starts_with("FIRMWARE_NAME:") {
            let pairs = KeyValues::Text(text);
            return if pairs.is_valid() {
                Ok(Reply::Firmware(pairs))
            } else {
                Err(ReplyError::Malformed)
            };
        }
        if let Some(reply) = parse_temperatures(text.trim_start_matches(' '), false) {
            return Ok(reply);
        }
        if let Some(reply) = parse_position(text) {
            return Ok(reply);
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

/// Whether `ok <text>` reads back as [`Reply::OkWith`]: `text` has a word, and its first word
/// does not start like a heater's reading (`T:`, `B:`, `@:`, `B@:`), as a temperature report
/// does. Stricter than the parser, which takes a text for a report only when all of it reads
/// as one, so that the encoder needs none of the report's parsing (an MCU's code).
fn plain_ok_text(text: &str) -> bool {
    text.split(' ')
        .find(|word| !word.is_empty())
        .is_some_and(|first| {
            !["T:", "B:", "@:", "B@:"]
                .iter()
                .any(|heater| first.starts_with(heater))
        })
}

/// What follows `ok `.
fn classify_ok(rest: &str) -> Result<Reply<'_>, ReplyError> {
    if rest.is_empty() {
        return Ok(Reply::Ok);
    }
    if let Some(reply) = parse_temperatures(rest, true) {
        return Ok(reply);
    }
    Ok(Reply::OkWith(rest))
}

/// What follows `echo:`.
fn classify_echo(rest: &str) -> Reply<'_> {
    if rest == BUSY_TEXT {
        return Reply::Busy;
    }
    if let Some(command) = rest
        .strip_prefix(UNKNOWN_PREFIX)
        .and_then(|r| r.strip_suffix('"'))
        .filter(|c| !c.contains('"'))
    {
        return Reply::Unknown(command);
    }
    match split_code(rest) {
        Some((code, text)) if code > 0 => Reply::Refused { code, text },
        _ => Reply::Echo(rest),
    }
}

/// `T:<c> /<t> B:<c> /<t> @:<p> B@:<p>` (each part optional, at least one heater).
fn parse_temperatures(text: &str, ok: bool) -> Option<Reply<'_>> {
    let mut hot_end: Option<Heat> = None;
    let mut bed: Option<Heat> = None;
    let mut tokens = text.split(' ').filter(|t| !t.is_empty());
    while let Some(token) = tokens.next() {
        let (name, value) = token.split_once(':')?;
        let number = |v: &str| Decimal::parse(v.as_bytes());
        match name {
            "T" | "B" => {
                let target = tokens.next()?.strip_prefix('/')?;
                let heat = Heat {
                    current: number(value)?,
                    target: number(target)?,
                    power: 0,
                };
                let slot = if name == "T" { &mut hot_end } else { &mut bed };
                if slot.replace(heat).is_some() {
                    return None;
                }
            }
            "@" | "B@" => {
                let slot = if name == "@" { &mut hot_end } else { &mut bed };
                slot.as_mut()?.power = value.parse().ok()?;
            }
            _ => return None,
        }
    }
    (hot_end.is_some() || bed.is_some()).then_some(Reply::Temperatures { hot_end, bed, ok })
}

/// `X:<x> Y:<y> … [Count X:<n> …]`.
fn parse_position(text: &str) -> Option<Reply<'_>> {
    let (positions, steps) = match text.split_once(" Count") {
        Some((p, s)) => (p, Some(s)),
        None => (text, None),
    };
    let mut axes = Axes::new();
    for token in positions.split(' ') {
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
    let mut counts = Counts::new();
    if let Some(steps) = steps {
        for token in steps.split(' ').filter(|t| !t.is_empty()) {
            let (letter, value) = token.split_once(':')?;
            let [letter] = letter.as_bytes() else {
                return None;
            };
            if !letter.is_ascii_uppercase() {
                return None;
            }
            counts.push((*letter, value.parse().ok()?)).ok()?;
        }
    }
    Some(Reply::Position { axes, counts })
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

    fn heat(current: &str, target: &str, power: u8) -> Heat {
        Heat {
            current: d(current),
            target: d(target),
            power,
        }
    }

    /// The lines as Marlin writes them and OctoPrint, Printrun and CNCjs read them.
    #[test]
    fn the_replies_printer_hosts_parse() {
        let position = Axes::from_slice(&[
            Word::new(b'X', d("10.00")),
            Word::new(b'Y', d("0.00")),
            Word::new(b'Z', d("0.20")),
            Word::new(b'E', d("-2.00")),
        ])
        .unwrap();
        let counts = Counts::from_slice(&[(b'X', 800), (b'Y', 0), (b'Z', 80)]).unwrap();
        let firmware = [("FIRMWARE_NAME", "Forja"), ("EXTRUDER_COUNT", "1")];
        let cases = [
            (Reply::Start, "start\n"),
            (Reply::Ok, "ok\n"),
            (Reply::Resend(42), "rs 42\n"),
            (
                Reply::Temperatures {
                    hot_end: Some(heat("25.0", "200.0", 127)),
                    bed: Some(heat("25.0", "60.0", 0)),
                    ok: true,
                },
                "ok T:25.0 /200.0 B:25.0 /60.0 @:127 B@:0\n",
            ),
            (
                Reply::Temperatures {
                    hot_end: Some(heat("93.2", "0", 0)),
                    bed: None,
                    ok: false,
                },
                " T:93.2 /0 @:0\n",
            ),
            (
                Reply::Position {
                    axes: position,
                    counts,
                },
                "X:10.00 Y:0.00 Z:0.20 E:-2.00 Count X:800 Y:0 Z:80\n",
            ),
            (
                Reply::Firmware(KeyValues::Pairs(&firmware)),
                "FIRMWARE_NAME:Forja EXTRUDER_COUNT:1\n",
            ),
            (
                Reply::Capability {
                    name: "AUTOREPORT_TEMP",
                    enabled: true,
                },
                "Cap:AUTOREPORT_TEMP:1\n",
            ),
            (Reply::Unknown("M123"), "echo:Unknown command: \"M123\"\n"),
            (Reply::Busy, "echo:busy: processing\n"),
            (Reply::Echo("Hello"), "echo:Hello\n"),
            (
                Reply::OkWith("x_min:open y_min:TRIGGERED"),
                "ok x_min:open y_min:TRIGGERED\n",
            ),
            (
                Reply::Debug("action:notification Halted"),
                "// action:notification Halted\n",
            ),
            (Reply::fault(&FrameError::Structure), "Error:E21 frame\n"),
            (
                Reply::refused(&LineError::MissingValue { line: None }),
                "echo:E9 no-value\n",
            ),
            (
                Reply::notice(&LineError::MissingValue { line: None }),
                "// E9 no-value\n",
            ),
            (
                Reply::Fault {
                    code: 0,
                    text: "thermal runaway",
                },
                "Error:thermal runaway\n",
            ),
        ];
        for (reply, text) in cases {
            assert_eq!(encoded(&reply), text);
            assert_eq!(Reply::parse(text.as_bytes()), Ok(reply), "{text}");
        }
    }

    #[test]
    fn the_lines_an_ok_follows() {
        assert!(Reply::Resend(1).ok_follows());
        assert!(Reply::Unknown("M1").ok_follows());
        assert!(!Reply::Busy.ok_follows());
        assert!(!Reply::Fault { code: 1, text: "" }.ok_follows());
        assert!(!Reply::Ok.ok_follows());
    }

    #[test]
    fn forja_firmware_line() {
        let mut pairs = std::vec::Vec::from(FORJA_CAPABILITIES);
        pairs.push(("MACHINE_TYPE", "CNC"));
        let reply = Reply::Firmware(KeyValues::Pairs(&pairs));
        let text = encoded(&reply);
        assert!(text.starts_with("FIRMWARE_NAME:Forja FIRMWARE_VERSION:"));
        let parsed = Reply::parse(text.as_bytes()).unwrap();
        assert_eq!(parsed, reply);
        let Reply::Firmware(kv) = parsed else {
            panic!()
        };
        assert_eq!(kv.get("MACHINE_TYPE"), Some("CNC"));
    }

    #[test]
    fn refused_encodings() {
        let mut out = [0u8; 64];
        for reply in [
            Reply::OkWith(""),
            Reply::OkWith("T:1 /0 B:2 /0"),
            Reply::OkWith("  B@:1"),
            Reply::OkWith("   "),
            Reply::OkWith("bad\u{7f}"),
            Reply::Debug("E12 looks coded"),
            Reply::Echo("E12 looks coded"),
            Reply::Echo("busy: processing"),
            Reply::Unknown("M1 \"x\""),
            Reply::Fault {
                code: 0,
                text: "E1",
            },
            Reply::Firmware(KeyValues::Pairs(&[("MACHINE_TYPE", "x")])),
            Reply::Firmware(KeyValues::Pairs(&[("FIRMWARE_NAME", "a b")])),
            Reply::Capability {
                name: "lower",
                enabled: true,
            },
        ] {
            assert_eq!(
                reply.encode(&mut out),
                Err(EncodeError::InvalidText),
                "{reply:?}"
            );
        }
        for reply in [
            Reply::Notice { code: 0, text: "x" },
            Reply::Refused { code: 0, text: "x" },
            Reply::Temperatures {
                hot_end: None,
                bed: None,
                ok: true,
            },
        ] {
            assert_eq!(reply.encode(&mut out), Err(EncodeError::OutOfRange));
        }
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
        assert_eq!(Reply::parse(b"echo:busy"), Ok(Reply::Echo("busy")));
        assert_eq!(Reply::parse(b"okay"), Err(ReplyError::UnknownPrefix));
        assert_eq!(Reply::parse(b"ok \x01"), Err(ReplyError::Malformed));
        assert_eq!(Reply::parse(b"ok "), Ok(Reply::Ok));
        assert_eq!(Reply::parse(b"//"), Ok(Reply::Debug("")));
        assert_eq!(Reply::parse(b"Cap:X:2"), Err(ReplyError::Malformed));
        // The seed's fault prefix is read too.
        assert_eq!(
            Reply::parse(b"!! E153 emergency-stop"),
            Ok(Reply::Fault {
                code: 153,
                text: "emergency-stop"
            })
        );
        // `E0` is not a code: the text is kept whole and written back as it came.
        let fault = Reply::parse(b"Error:E0 E0 E").unwrap();
        assert_eq!(
            fault,
            Reply::Fault {
                code: 0,
                text: "E0 E0 E"
            }
        );
        assert_eq!(encoded(&fault), "Error:E0 E0 E\n");
        // `.5` is written `0.5`: a reply may grow when written back.
        let grown = Reply::parse(b"X:.5 Count X:40").unwrap();
        assert_eq!(encoded(&grown), "X:0.5 Count X:40\n");
    }
}
