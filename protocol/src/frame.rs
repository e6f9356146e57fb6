//! Fixed 53-byte frames (seed `000_…txt`, read as `frame-protocol.md` resolves it).
//!
//! ```text
//! N tt <payload: 49 bytes> F
//! 0 12 3 ............... 51 52
//! ```
//!
//! A frame is `N`, a two-digit message type, 49 payload bytes padded with `*`, and `F`: exactly
//! [`FRAME_LEN`] printable ASCII bytes, no checksum. [`ClientMessage`] holds the types the
//! operator's client sends (00–04), [`ControllerMessage`] those the controller sends (50–56).
//! Each has `decode` (bytes to message, borrowing the text fields) and `encode` (message to
//! the caller's `[u8; FRAME_LEN]`, no terminator: emitters add `\n`).
//!
//! ```
//! use forja_protocol::frame::{Action, ClientMessage, FRAME_LEN};
//!
//! let frame = b"N02Zero*****************************************ZeroF";
//! let msg = ClientMessage::decode(frame).unwrap();
//! assert_eq!(msg, ClientMessage::Action(Action::HomeAll));
//!
//! let mut out = [0u8; FRAME_LEN];
//! msg.encode(&mut out).unwrap();
//! assert_eq!(&out, frame);
//! ```

use heapless::Vec;

pub use crate::decimal::Decimal;
pub use crate::error::{EncodeError, FrameError};
use crate::error::{WireError, split_code};
use crate::write::{Cursor, Sink};

/// Bytes in one frame: `N`, two type digits, the payload, `F`.
pub const FRAME_LEN: usize = 53;
/// Bytes of payload in one frame.
pub const PAYLOAD_LEN: usize = 49;
/// The first byte of a frame.
pub const START: u8 = b'N';
/// The last byte of a frame.
pub const END: u8 = b'F';
/// The byte that fills unused payload.
pub const PAD: u8 = b'*';
/// The longest G-code text one 03 frame carries.
pub const MAX_LOAD_TEXT: usize = 39;
/// The most lines a program loaded with 03 frames may have (four digits).
pub const MAX_LOAD_LINES: u16 = 9999;
/// The most axes one 51 frame carries (`E` + 12 bytes per axis fit 49 bytes four times).
pub const MAX_POSITION_AXES: usize = 4;
/// The largest time a 52 frame shows, in seconds: `99:59`.
pub const MAX_PROGRESS_S: u32 = 99 * 60 + 59;
/// The largest line count a 52 frame shows.
pub const MAX_PROGRESS_LINES: u32 = 9999;
/// The 55 counter is shown modulo this (seven digits).
pub const KEEP_ALIVE_MODULUS: u32 = 10_000_000;
/// The largest position a 51 frame shows, in tenths of a micrometre: `99999.9999` mm.
pub const MAX_POSITION_TENTH_UM: i32 = 999_999_999;
/// What a 53 frame confirms when a program has been loaded: `Confirm:Gcode-load`.
pub const CONFIRM_GCODE_LOAD: &str = "Gcode-load";

/// The two-digit message types.
pub mod message_type {
    /// 00, client: set or read a setting.
    pub const SETTING: u8 = 0;
    /// 01, client: jog an axis by steps.
    pub const JOG: u8 = 1;
    /// 02, client: run an action.
    pub const ACTION: u8 = 2;
    /// 03, client: load one program line.
    pub const LOAD_LINE: u8 = 3;
    /// 04, client: ask for a message.
    pub const REQUEST: u8 = 4;
    /// 50, controller: a setting's value.
    pub const SETTING_VALUE: u8 = 50;
    /// 51, controller: positions (also accepted as 01 from a controller).
    pub const POSITIONS: u8 = 51;
    /// 52, controller: progress (also accepted as 02 from a controller).
    pub const PROGRESS: u8 = 52;
    /// 53, controller: a confirmation.
    pub const CONFIRM: u8 = 53;
    /// 54, controller: connected.
    pub const CONNECTED: u8 = 54;
    /// 55, controller: keep-alive.
    pub const KEEP_ALIVE: u8 = 55;
    /// 56, controller: an error.
    pub const ERROR: u8 = 56;
}

/// Whether `bytes` has the structure of a frame: [`FRAME_LEN`] printable ASCII bytes, `N`,
/// two digits, `F`. Says nothing of the payload.
pub fn is_frame(bytes: &[u8]) -> bool {
    matches!(
        bytes,
        [START, t0, t1, .., END] if bytes.len() == FRAME_LEN
            && t0.is_ascii_digit()
            && t1.is_ascii_digit()
            && bytes.iter().all(|&b| is_printable(b))
    )
}

fn is_printable(b: u8) -> bool {
    (b' '..=b'~').contains(&b)
}

/// A byte that a text field of a payload may hold: printable ASCII except `*`.
fn is_text(b: u8) -> bool {
    is_printable(b) && b != PAD
}

/// A byte of a setting key: printable ASCII except space, `*`, `=` and `?`.
fn is_key(b: u8) -> bool {
    is_text(b) && !matches!(b, b' ' | b'=' | b'?')
}

/// A structurally valid frame, borrowed (smoltcp's `Packet` view).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Frame<'a> {
    bytes: &'a [u8; FRAME_LEN],
}

impl<'a> Frame<'a> {
    /// Check the structure ([`is_frame`]): [`FrameError::Length`] unless exactly
    /// [`FRAME_LEN`] bytes, [`FrameError::Structure`] unless `N`, two digits, printable ASCII,
    /// `F`.
    pub fn new_checked(bytes: &'a [u8]) -> Result<Self, FrameError> {
        let bytes: &[u8; FRAME_LEN] = bytes.try_into().map_err(|_| FrameError::Length)?;
        if !is_frame(bytes) {
            return Err(FrameError::Structure);
        }
        Ok(Self { bytes })
    }

    /// The two-digit message type.
    pub fn message_type(&self) -> u8 {
        let [_, t0, t1, ..] = *self.bytes;
        (t0 - b'0') * 10 + (t1 - b'0')
    }

    /// The 49 payload bytes.
    pub fn payload(&self) -> &'a [u8] {
        self.bytes.get(3..FRAME_LEN - 1).unwrap_or(&[])
    }

    /// The whole frame.
    pub fn as_bytes(&self) -> &'a [u8; FRAME_LEN] {
        self.bytes
    }
}

/// What a 02 frame asks the controller to do.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Action {
    /// `Zero`: home every axis.
    HomeAll,
    /// `ZeroX`, `ZeroY`, `ZeroZ`, `ZeroA` …: home one axis (upper-case letter).
    Home(u8),
    /// `Reset`: soft reset (alarms cleared, modal state to defaults, program kept).
    Reset,
    /// `Stop`: abort motion and the program (planner flushed, position kept).
    Stop,
    /// `Rewind`: set the program line back to 1.
    Rewind,
    /// `Start`: run the stored program from the current line, or resume after `Pause`.
    Start,
    /// `Pause`: hold motion, decelerating without losing steps.
    Pause,
}

impl Action {
    /// The keyword without its axis letter.
    fn word(&self) -> &'static [u8] {
        match self {
            Self::HomeAll | Self::Home(_) => b"Zero",
            Self::Reset => b"Reset",
            Self::Stop => b"Stop",
            Self::Rewind => b"Rewind",
            Self::Start => b"Start",
            Self::Pause => b"Pause",
        }
    }

    /// The action named by a keyword (`Zero`, `ZeroX`, `Reset`, …).
    pub fn from_keyword(keyword: &[u8]) -> Option<Self> {
        Some(match keyword {
            b"Zero" => Self::HomeAll,
            [b'Z', b'e', b'r', b'o', axis] if axis.is_ascii_uppercase() => Self::Home(*axis),
            b"Reset" => Self::Reset,
            b"Stop" => Self::Stop,
            b"Rewind" => Self::Rewind,
            b"Start" => Self::Start,
            b"Pause" => Self::Pause,
            _ => return None,
        })
    }

    fn write_keyword<S: Sink>(&self, out: &mut S) -> Result<(), EncodeError> {
        out.put_all(self.word())?;
        match *self {
            Self::Home(axis) if axis.is_ascii_uppercase() => out.put(axis),
            Self::Home(_) => Err(EncodeError::OutOfRange),
            _ => Ok(()),
        }
    }

    fn keyword_len(&self) -> usize {
        self.word().len() + usize::from(matches!(self, Self::Home(_)))
    }
}

/// A message from the operator's client to the controller (types 00–04).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum ClientMessage<'a> {
    /// 00 `key=value`: set a setting. Answered by a 50 (or a 56).
    SetSetting {
        /// The setting's name: printable ASCII without space, `*`, `=` or `?`.
        key: &'a str,
        /// The new value: printable ASCII without `*`; may be empty.
        value: &'a str,
    },
    /// 00 `key` or `key?`: read a setting. Answered by a 50 (or a 56). Emitted as `key`.
    ReadSetting {
        /// The setting's name.
        key: &'a str,
    },
    /// 01 `S<step>` `<axis>` `<±count>`: move `axis` by `count × step` mm, relative, at the jog
    /// feed rate. `S0.0001X+1000` moves X by +0.1 mm.
    Jog {
        /// The step size in mm (not negative).
        step: Decimal,
        /// The axis, an upper-case letter.
        axis: u8,
        /// How many steps, signed.
        count: i32,
    },
    /// 02 `keyword***…***keyword`: run an action.
    Action(Action),
    /// 03 `dddd` `C` text `*…` `f` `dddd`: store one line of a program (not run it).
    LoadLine {
        /// This line's index, `1..=total`.
        index: u16,
        /// The G-code text, at most [`MAX_LOAD_TEXT`] bytes of printable ASCII without `*`.
        text: &'a str,
        /// How many lines the program has, at most [`MAX_LOAD_LINES`].
        total: u16,
    },
    /// 04 `xx***…***xx`: ask for a message of type `xx` (51 positions, 52 progress, …).
    Request {
        /// The type wanted, `0..=99`.
        message_type: u8,
    },
}

impl<'a> ClientMessage<'a> {
    /// Decode one frame (exactly [`FRAME_LEN`] bytes, no terminator).
    pub fn decode(bytes: &'a [u8]) -> Result<Self, FrameError> {
        Self::parse(&Frame::new_checked(bytes)?)
    }

    /// Decode the payload of a structurally valid frame.
    pub fn parse(frame: &Frame<'a>) -> Result<Self, FrameError> {
        let p = frame.payload();
        match frame.message_type() {
            message_type::SETTING => parse_setting_request(p),
            message_type::JOG => parse_jog(p),
            message_type::ACTION => parse_action(p).map(Self::Action),
            message_type::LOAD_LINE => parse_load_line(p),
            message_type::REQUEST => {
                let inner = mirrored(p, 2)?;
                let message_type = digits(inner).ok_or(FrameError::Payload)?;
                Ok(Self::Request {
                    message_type: message_type as u8,
                })
            }
            t => Err(FrameError::UnknownType { message_type: t }),
        }
    }

    /// The two-digit type this message is sent as.
    pub fn message_type(&self) -> u8 {
        match self {
            Self::SetSetting { .. } | Self::ReadSetting { .. } => message_type::SETTING,
            Self::Jog { .. } => message_type::JOG,
            Self::Action(_) => message_type::ACTION,
            Self::LoadLine { .. } => message_type::LOAD_LINE,
            Self::Request { .. } => message_type::REQUEST,
        }
    }

    /// Write the frame into `out` (no terminator).
    ///
    /// Fails with [`EncodeError::InvalidText`] for a key or text the payload cannot carry,
    /// [`EncodeError::TooLong`] when it does not fit 49 bytes (a 03 text over 39),
    /// [`EncodeError::OutOfRange`] for a negative step, an axis that is not an upper-case
    /// letter, an index not in `1..=total`, a total over 9999 or a requested type over 99.
    pub fn encode(&self, out: &mut [u8; FRAME_LEN]) -> Result<(), EncodeError> {
        write_frame(out, self.message_type(), |w| match *self {
            Self::SetSetting { key, value } => {
                put_key(w, key)?;
                w.put(b'=')?;
                put_text(w, value)
            }
            Self::ReadSetting { key } => put_key(w, key),
            Self::Jog { step, axis, count } => {
                if step.is_negative() || !axis.is_ascii_uppercase() {
                    return Err(EncodeError::OutOfRange);
                }
                w.put(b'S')?;
                step.write_checked(w)?;
                w.put(axis)?;
                w.put(if count < 0 { b'-' } else { b'+' })?;
                w.put_u64(u64::from(count.unsigned_abs()))
            }
            Self::Action(action) => {
                let len = action.keyword_len();
                action.write_keyword(w)?;
                (0..PAYLOAD_LEN.saturating_sub(2 * len)).try_for_each(|_| w.put(PAD))?;
                action.write_keyword(w)
            }
            Self::LoadLine { index, text, total } => {
                if index == 0 || index > total || total > MAX_LOAD_LINES {
                    return Err(EncodeError::OutOfRange);
                }
                if text.len() > MAX_LOAD_TEXT {
                    return Err(EncodeError::TooLong);
                }
                w.put_padded(u64::from(index), 4)?;
                w.put(b'C')?;
                put_text(w, text)?;
                (text.len()..MAX_LOAD_TEXT).try_for_each(|_| w.put(PAD))?;
                w.put(b'f')?;
                w.put_padded(u64::from(total), 4)
            }
            Self::Request { message_type } => {
                if message_type > 99 {
                    return Err(EncodeError::OutOfRange);
                }
                w.put_padded(u64::from(message_type), 2)?;
                (0..PAYLOAD_LEN - 4).try_for_each(|_| w.put(PAD))?;
                w.put_padded(u64::from(message_type), 2)
            }
        })
    }
}

/// One axis of a 51 frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct AxisPosition {
    /// The axis, an upper-case letter (written in lower case on the wire).
    pub axis: u8,
    /// The position in tenths of a micrometre (1e-4 mm), within ±[`MAX_POSITION_TENTH_UM`].
    pub value_tenth_um: i32,
}

impl AxisPosition {
    /// An axis at `mm`, rounded half away from zero to 1e-4 mm; `None` beyond ±99999.9999 mm.
    pub fn from_mm(axis: u8, mm: Decimal) -> Option<Self> {
        let value = mm.round_to_scale(4)?;
        let value_tenth_um = i32::try_from(value)
            .ok()
            .filter(|v| v.unsigned_abs() <= MAX_POSITION_TENTH_UM.unsigned_abs())?;
        Some(Self {
            axis,
            value_tenth_um,
        })
    }

    /// The position in mm, exactly (four decimals).
    pub fn mm(&self) -> Decimal {
        Decimal::new(i64::from(self.value_tenth_um), 4)
    }
}

/// The axes of a 51 frame, in the order sent (at most [`MAX_POSITION_AXES`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Positions {
    axes: Vec<AxisPosition, MAX_POSITION_AXES, u8>,
}

impl Positions {
    /// No axes.
    pub const fn new() -> Self {
        Self { axes: Vec::new() }
    }

    /// The axes of `axes`; [`EncodeError::TooLong`] beyond [`MAX_POSITION_AXES`].
    pub fn from_slice(axes: &[AxisPosition]) -> Result<Self, EncodeError> {
        Ok(Self {
            axes: Vec::from_slice(axes).map_err(|_| EncodeError::TooLong)?,
        })
    }

    /// Add an axis; [`EncodeError::TooLong`] when [`MAX_POSITION_AXES`] are already there.
    pub fn push(&mut self, axis: AxisPosition) -> Result<(), EncodeError> {
        self.axes.push(axis).map_err(|_| EncodeError::TooLong)
    }

    /// The axes in order.
    pub fn axes(&self) -> &[AxisPosition] {
        &self.axes
    }

    /// The position of `axis` (upper or lower case), in tenths of a micrometre.
    pub fn get(&self, axis: u8) -> Option<i32> {
        let axis = axis.to_ascii_uppercase();
        self.axes
            .iter()
            .find(|a| a.axis == axis)
            .map(|a| a.value_tenth_um)
    }
}

/// The contents of a 52 frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Progress {
    /// Time since the program started, in seconds (shown as mm:ss, saturating at 99:59).
    pub elapsed_s: u32,
    /// Estimated total time, in seconds (shown as mm:ss, saturating at 99:59).
    pub estimated_s: u32,
    /// Lines in the program (shown in four digits, saturating at 9999).
    pub total_lines: u32,
    /// The line being run (shown in four digits, saturating at 9999).
    pub current_line: u32,
}

/// A message from the controller to the operator's client (types 50–56).
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum ControllerMessage<'a> {
    /// 50 `key=value`: a setting's value, the answer to a 00.
    Setting {
        /// The setting's name: printable ASCII without space, `*`, `=` or `?`.
        key: &'a str,
        /// Its value: printable ASCII without `*`.
        value: &'a str,
    },
    /// 51 `E` then per axis `±ddddd.dddd` and the axis letter in lower case.
    Positions(Positions),
    /// 52 `ELmm:ssESmm:ssNLddddLAdddd`.
    Progress(Progress),
    /// 53 `Confirm:<what>`; a loaded program is confirmed with [`CONFIRM_GCODE_LOAD`].
    Confirm {
        /// What is confirmed: printable ASCII without `*`.
        what: &'a str,
    },
    /// 54 `Conected` (the seed's spelling, which clients match on).
    Connected,
    /// 55 `Vivo` + seven digits: the keep-alive, its counter shown modulo
    /// [`KEEP_ALIVE_MODULUS`].
    KeepAlive {
        /// The counter.
        counter: u32,
    },
    /// 56 `Error:E<code> <detail>` (or `Error:<detail>` when `code` is 0): something the
    /// client sent was refused, or the machine has an alarm. Not in the seed.
    Error {
        /// The error's stable code (see [`crate::error`]); 0 when none is given.
        code: u16,
        /// The error's name and any detail (`line-order 0004`): printable ASCII without `*`.
        detail: &'a str,
    },
}

impl<'a> ControllerMessage<'a> {
    /// A 56 reporting `error` by its code and name.
    pub fn error(error: &impl WireError) -> ControllerMessage<'static> {
        ControllerMessage::Error {
            code: error.code(),
            detail: error.name(),
        }
    }

    /// Decode one frame (exactly [`FRAME_LEN`] bytes, no terminator). Types 01 and 02 are read
    /// as 51 and 52, as the seed's examples write them.
    pub fn decode(bytes: &'a [u8]) -> Result<Self, FrameError> {
        Self::parse(&Frame::new_checked(bytes)?)
    }

    /// Decode the payload of a structurally valid frame.
    pub fn parse(frame: &Frame<'a>) -> Result<Self, FrameError> {
        let p = frame.payload();
        match frame.message_type() {
            message_type::SETTING_VALUE => {
                let (key, value) = split_setting(text_field(p)?).ok_or(FrameError::Payload)?;
                Ok(Self::Setting { key, value })
            }
            message_type::POSITIONS | message_type::JOG => parse_positions(p).map(Self::Positions),
            message_type::PROGRESS | message_type::ACTION => parse_progress(p).map(Self::Progress),
            message_type::CONFIRM => {
                let text = text_field(p)?;
                let what = text.strip_prefix("Confirm:").ok_or(FrameError::Payload)?;
                Ok(Self::Confirm { what })
            }
            message_type::CONNECTED => match text_field(p)? {
                "Conected" => Ok(Self::Connected),
                _ => Err(FrameError::Payload),
            },
            message_type::KEEP_ALIVE => {
                let (head, pad) = p.split_at_checked(11).ok_or(FrameError::Payload)?;
                let counter = match head {
                    [b'V', b'i', b'v', b'o', count @ ..] => digits(count),
                    _ => None,
                };
                match counter {
                    Some(counter) if is_padding(pad) => Ok(Self::KeepAlive { counter }),
                    _ => Err(FrameError::Payload),
                }
            }
            message_type::ERROR => {
                let text = text_field(p)?;
                let text = text.strip_prefix("Error:").ok_or(FrameError::Payload)?;
                match split_code(text) {
                    Some((code, detail)) => Ok(Self::Error {
                        code: u16::try_from(code).map_err(|_| FrameError::Payload)?,
                        detail,
                    }),
                    None => Ok(Self::Error {
                        code: 0,
                        detail: text,
                    }),
                }
            }
            t => Err(FrameError::UnknownType { message_type: t }),
        }
    }

    /// The two-digit type this message is sent as (always 50–56).
    pub fn message_type(&self) -> u8 {
        match self {
            Self::Setting { .. } => message_type::SETTING_VALUE,
            Self::Positions(_) => message_type::POSITIONS,
            Self::Progress(_) => message_type::PROGRESS,
            Self::Confirm { .. } => message_type::CONFIRM,
            Self::Connected => message_type::CONNECTED,
            Self::KeepAlive { .. } => message_type::KEEP_ALIVE,
            Self::Error { .. } => message_type::ERROR,
        }
    }

    /// Write the frame into `out` (no terminator).
    ///
    /// Times and line counts of a 52 saturate; the 55 counter wraps. Fails with
    /// [`EncodeError::InvalidText`] for a text the payload cannot carry (or, with code 0, a
    /// detail that would read back as a code), [`EncodeError::TooLong`] when it does not fit
    /// 49 bytes, [`EncodeError::OutOfRange`] for a position beyond ±99999.9999 mm or an axis
    /// that is not an upper-case letter.
    pub fn encode(&self, out: &mut [u8; FRAME_LEN]) -> Result<(), EncodeError> {
        write_frame(out, self.message_type(), |w| match self {
            Self::Setting { key, value } => {
                put_key(w, key)?;
                w.put(b'=')?;
                put_text(w, value)
            }
            Self::Positions(positions) => {
                w.put(b'E')?;
                positions.axes().iter().try_for_each(|a| {
                    if !a.axis.is_ascii_uppercase()
                        || a.value_tenth_um.unsigned_abs() > MAX_POSITION_TENTH_UM.unsigned_abs()
                    {
                        return Err(EncodeError::OutOfRange);
                    }
                    let magnitude = a.value_tenth_um.unsigned_abs();
                    w.put(if a.value_tenth_um < 0 { b'-' } else { b'+' })?;
                    w.put_padded(u64::from(magnitude / 10_000), 5)?;
                    w.put(b'.')?;
                    w.put_padded(u64::from(magnitude % 10_000), 4)?;
                    w.put(a.axis.to_ascii_lowercase())
                })
            }
            Self::Progress(p) => {
                let lines = |n: u32| u64::from(n.min(MAX_PROGRESS_LINES));
                w.put_all(b"EL")?;
                put_mm_ss(w, p.elapsed_s)?;
                w.put_all(b"ES")?;
                put_mm_ss(w, p.estimated_s)?;
                w.put_all(b"NL")?;
                w.put_padded(lines(p.total_lines), 4)?;
                w.put_all(b"LA")?;
                w.put_padded(lines(p.current_line), 4)
            }
            Self::Confirm { what } => {
                w.put_all(b"Confirm:")?;
                put_text(w, what)
            }
            Self::Connected => w.put_all(b"Conected"),
            Self::KeepAlive { counter } => {
                w.put_all(b"Vivo")?;
                w.put_padded(u64::from(counter % KEEP_ALIVE_MODULUS), 7)
            }
            Self::Error { code, detail } => {
                w.put_all(b"Error:")?;
                if *code == 0 {
                    if split_code(detail).is_some() {
                        return Err(EncodeError::InvalidText);
                    }
                } else {
                    w.put(b'E')?;
                    w.put_u64(u64::from(*code))?;
                    if !detail.is_empty() {
                        w.put(b' ')?;
                    }
                }
                put_text(w, detail)
            }
        })
    }
}

/// Write `N`, the type, the payload written by `payload` padded with `*`, and `F`.
fn write_frame(
    out: &mut [u8; FRAME_LEN],
    message_type: u8,
    payload: impl FnOnce(&mut Cursor<'_>) -> Result<(), EncodeError>,
) -> Result<(), EncodeError> {
    let (head, rest) = out
        .split_first_chunk_mut::<3>()
        .ok_or(EncodeError::BufferTooSmall)?;
    let (end, body) = rest.split_last_mut().ok_or(EncodeError::BufferTooSmall)?;
    *head = [
        START,
        b'0' + message_type / 10 % 10,
        b'0' + message_type % 10,
    ];
    *end = END;
    let mut cursor = Cursor::new(body);
    payload(&mut cursor).map_err(|e| match e {
        EncodeError::BufferTooSmall => EncodeError::TooLong,
        e => e,
    })?;
    cursor.fill(PAD);
    Ok(())
}

fn put_text<S: Sink>(w: &mut S, text: &str) -> Result<(), EncodeError> {
    if !text.bytes().all(is_text) {
        return Err(EncodeError::InvalidText);
    }
    w.put_all(text.as_bytes())
}

fn put_key<S: Sink>(w: &mut S, key: &str) -> Result<(), EncodeError> {
    if key.is_empty() || !key.bytes().all(is_key) {
        return Err(EncodeError::InvalidText);
    }
    w.put_all(key.as_bytes())
}

fn put_mm_ss<S: Sink>(w: &mut S, seconds: u32) -> Result<(), EncodeError> {
    let s = seconds.min(MAX_PROGRESS_S);
    w.put_padded(u64::from(s / 60), 2)?;
    w.put(b':')?;
    w.put_padded(u64::from(s % 60), 2)
}

fn is_padding(bytes: &[u8]) -> bool {
    bytes.iter().all(|&b| b == PAD)
}

/// The decimal value of `bytes`, all digits, at most nine of them.
fn digits(bytes: &[u8]) -> Option<u32> {
    if bytes.is_empty() || bytes.len() > 9 || !bytes.iter().all(u8::is_ascii_digit) {
        return None;
    }
    Some(
        bytes
            .iter()
            .fold(0u32, |v, &b| v * 10 + u32::from(b - b'0')),
    )
}

/// The text at the start of a payload: up to the first `*`, everything after being `*`.
fn text_field(p: &[u8]) -> Result<&str, FrameError> {
    let end = p.iter().position(|&b| b == PAD).unwrap_or(p.len());
    let (text, pad) = p.split_at(end);
    if !is_padding(pad) || !text.iter().all(|&b| is_text(b)) {
        return Err(FrameError::Payload);
    }
    core::str::from_utf8(text).map_err(|_| FrameError::Payload)
}

/// `key=value` with a valid key.
fn split_setting(text: &str) -> Option<(&str, &str)> {
    let (key, value) = text.split_once('=')?;
    (!key.is_empty() && key.bytes().all(is_key)).then_some((key, value))
}

fn parse_setting_request(p: &[u8]) -> Result<ClientMessage<'_>, FrameError> {
    let text = text_field(p)?;
    if let Some((key, value)) = split_setting(text) {
        return Ok(ClientMessage::SetSetting { key, value });
    }
    let key = text.strip_suffix('?').unwrap_or(text);
    if key.is_empty() || !key.bytes().all(is_key) {
        return Err(FrameError::Payload);
    }
    Ok(ClientMessage::ReadSetting { key })
}

fn parse_jog(p: &[u8]) -> Result<ClientMessage<'_>, FrameError> {
    let text = text_field(p)?.as_bytes();
    let [b'S', rest @ ..] = text else {
        return Err(FrameError::Payload);
    };
    let axis_at = rest
        .iter()
        .position(u8::is_ascii_uppercase)
        .ok_or(FrameError::Payload)?;
    let (step, rest) = rest.split_at(axis_at);
    let [axis, count @ ..] = rest else {
        return Err(FrameError::Payload);
    };
    let unsigned = step
        .first()
        .is_some_and(|&b| b.is_ascii_digit() || b == b'.');
    let step = Decimal::parse(step)
        .filter(|_| unsigned)
        .ok_or(FrameError::Payload)?;
    let (negative, magnitude) = match count {
        [b'+', m @ ..] => (false, m),
        [b'-', m @ ..] => (true, m),
        m => (false, m),
    };
    if magnitude.is_empty() || magnitude.len() > 10 || !magnitude.iter().all(u8::is_ascii_digit) {
        return Err(FrameError::Payload);
    }
    let magnitude = magnitude
        .iter()
        .fold(0i64, |v, &b| v * 10 + i64::from(b - b'0'));
    let count = i32::try_from(if negative { -magnitude } else { magnitude })
        .map_err(|_| FrameError::Payload)?;
    Ok(ClientMessage::Jog {
        step,
        axis: *axis,
        count,
    })
}

/// The inner keyword of `keyword***…***keyword`, checking the mirror.
fn mirrored(p: &[u8], len: usize) -> Result<&[u8], FrameError> {
    let (head, rest) = p.split_at_checked(len).ok_or(FrameError::Payload)?;
    let (middle, tail) = rest
        .split_at_checked(rest.len().saturating_sub(len))
        .ok_or(FrameError::Payload)?;
    if head.contains(&PAD) || !is_padding(middle) {
        return Err(FrameError::Payload);
    }
    if head != tail {
        return Err(FrameError::Mirror);
    }
    Ok(head)
}

fn parse_action(p: &[u8]) -> Result<Action, FrameError> {
    let first = p
        .iter()
        .position(|&b| b == PAD)
        .ok_or(FrameError::Payload)?;
    let last = p
        .iter()
        .rposition(|&b| b == PAD)
        .ok_or(FrameError::Payload)?;
    let (head, rest) = p.split_at_checked(first).ok_or(FrameError::Payload)?;
    let (middle, tail) = rest
        .split_at_checked(last + 1 - first)
        .ok_or(FrameError::Payload)?;
    if head.is_empty() || !is_padding(middle) {
        return Err(FrameError::Payload);
    }
    if head != tail {
        return Err(FrameError::Mirror);
    }
    Action::from_keyword(head).ok_or(FrameError::UnknownAction)
}

fn parse_load_line(p: &[u8]) -> Result<ClientMessage<'_>, FrameError> {
    let (index, rest) = p.split_at_checked(4).ok_or(FrameError::Payload)?;
    let (c, rest) = rest.split_first().ok_or(FrameError::Payload)?;
    let (text, rest) = rest
        .split_at_checked(MAX_LOAD_TEXT)
        .ok_or(FrameError::Payload)?;
    let (f, total) = rest.split_first().ok_or(FrameError::Payload)?;
    if *c != b'C' || *f != b'f' || index.len() != 4 || total.len() != 4 {
        return Err(FrameError::Payload);
    }
    let index = digits(index).ok_or(FrameError::Payload)? as u16;
    let total = digits(total).ok_or(FrameError::Payload)? as u16;
    if index == 0 || index > total {
        return Err(FrameError::Payload);
    }
    Ok(ClientMessage::LoadLine {
        index,
        text: text_field(text)?,
        total,
    })
}

fn parse_positions(p: &[u8]) -> Result<Positions, FrameError> {
    let [b'E', rest @ ..] = p else {
        return Err(FrameError::Payload);
    };
    let mut rest = rest;
    let mut positions = Positions::new();
    while let Some((group, after)) = rest.split_first_chunk::<12>() {
        if group.first() == Some(&PAD) {
            break;
        }
        let [sign, int @ .., b'.', f0, f1, f2, f3, axis] = group else {
            return Err(FrameError::Payload);
        };
        let int = digits(int).filter(|_| int.len() == 5);
        let frac = digits(&[*f0, *f1, *f2, *f3]);
        let (Some(int), Some(frac)) = (int, frac) else {
            return Err(FrameError::Payload);
        };
        if !axis.is_ascii_lowercase() {
            return Err(FrameError::Payload);
        }
        // At most 99999 * 10000 + 9999, within i32.
        let magnitude = (int * 10_000 + frac) as i32;
        let value_tenth_um = match sign {
            b'+' => magnitude,
            b'-' => -magnitude,
            _ => return Err(FrameError::Payload),
        };
        positions
            .push(AxisPosition {
                axis: axis.to_ascii_uppercase(),
                value_tenth_um,
            })
            .map_err(|_| FrameError::Payload)?;
        rest = after;
    }
    if !is_padding(rest) {
        return Err(FrameError::Payload);
    }
    Ok(positions)
}

fn parse_progress(p: &[u8]) -> Result<Progress, FrameError> {
    let (head, pad) = p.split_first_chunk::<26>().ok_or(FrameError::Payload)?;
    #[rustfmt::skip]
    let [
        b'E', b'L', em0, em1, b':', es0, es1,
        b'E', b'S', tm0, tm1, b':', ts0, ts1,
        b'N', b'L', n0, n1, n2, n3,
        b'L', b'A', l0, l1, l2, l3,
    ] = *head
    else {
        return Err(FrameError::Payload);
    };
    let time = |m: [u8; 2], s: [u8; 2]| -> Option<u32> {
        Some(digits(&m)? * 60 + digits(&s).filter(|&s| s < 60)?)
    };
    let parsed = (|| {
        Some(Progress {
            elapsed_s: time([em0, em1], [es0, es1])?,
            estimated_s: time([tm0, tm1], [ts0, ts1])?,
            total_lines: digits(&[n0, n1, n2, n3])?,
            current_line: digits(&[l0, l1, l2, l3])?,
        })
    })();
    match parsed {
        Some(progress) if is_padding(pad) => Ok(progress),
        _ => Err(FrameError::Payload),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic, clippy::indexing_slicing)]
mod tests {
    extern crate std;
    use std::vec::Vec as StdVec;

    use super::*;

    /// Every frame line of the seed, verbatim.
    pub(crate) const SEED_FRAMES: [&str; 9] = [
        "N00*************************************************F",
        "N01E+00000.0000x+00000.0000y+00000.0000z+00000.0000aF",
        "N02EL00:00ES00:00NL0000LA0000***********************F",
        "N53Confirm:Gcode-load*******************************F",
        "N54Conected*****************************************F",
        "N55Vivo0000000**************************************F",
        "N030001CG015***********************************f0005F",
        "N030002CG645***********************************f0005F",
        "N030003CG395***********************************f0005F",
    ];

    /// The seed's 02 payloads, verbatim (each written with `N02` … `F` around it).
    pub(crate) const SEED_ACTIONS: [(&str, Action); 10] = [
        (
            "Zero*****************************************Zero",
            Action::HomeAll,
        ),
        (
            "ZeroX***************************************ZeroX",
            Action::Home(b'X'),
        ),
        (
            "ZeroY***************************************ZeroY",
            Action::Home(b'Y'),
        ),
        (
            "ZeroZ***************************************ZeroZ",
            Action::Home(b'Z'),
        ),
        (
            "ZeroA***************************************ZeroA",
            Action::Home(b'A'),
        ),
        (
            "Reset***************************************Reset",
            Action::Reset,
        ),
        (
            "Stop*****************************************Stop",
            Action::Stop,
        ),
        (
            "Rewind*************************************Rewind",
            Action::Rewind,
        ),
        (
            "Start***************************************Start",
            Action::Start,
        ),
        (
            "Pause***************************************Pause",
            Action::Pause,
        ),
    ];

    fn client(msg: &ClientMessage<'_>) -> [u8; FRAME_LEN] {
        let mut out = [0u8; FRAME_LEN];
        msg.encode(&mut out).unwrap();
        out
    }

    fn controller(msg: &ControllerMessage<'_>) -> [u8; FRAME_LEN] {
        let mut out = [0u8; FRAME_LEN];
        msg.encode(&mut out).unwrap();
        out
    }

    /// A frame that lives for the whole test, so that decoded messages may borrow it.
    fn fr(ty: &str, payload: &str) -> &'static [u8] {
        frame(ty, payload).leak()
    }

    fn frame(ty: &str, payload: &str) -> StdVec<u8> {
        let mut v = StdVec::new();
        v.push(b'N');
        v.extend_from_slice(ty.as_bytes());
        v.extend_from_slice(payload.as_bytes());
        v.resize(FRAME_LEN - 1, PAD);
        v.push(b'F');
        v
    }

    #[test]
    fn every_seed_action_is_exactly_one_payload_and_round_trips() {
        for (payload, action) in SEED_ACTIONS {
            assert_eq!(payload.len(), PAYLOAD_LEN, "{payload}");
            let bytes = std::format!("N02{payload}F");
            assert_eq!(bytes.len(), FRAME_LEN);
            let msg = ClientMessage::decode(bytes.as_bytes()).unwrap();
            assert_eq!(msg, ClientMessage::Action(action));
            assert_eq!(&client(&msg), bytes.as_bytes());
        }
    }

    #[test]
    fn the_seed_load_lines() {
        let texts = ["G015", "G645", "G395", "H214", "B687"];
        for (i, text) in texts.iter().enumerate() {
            let bytes = std::format!(
                "N03{:04}C{text}{}f0005F",
                i + 1,
                "*".repeat(MAX_LOAD_TEXT - text.len())
            );
            let msg = ClientMessage::decode(bytes.as_bytes()).unwrap();
            assert_eq!(
                msg,
                ClientMessage::LoadLine {
                    index: i as u16 + 1,
                    text,
                    total: 5
                }
            );
            assert_eq!(&client(&msg), bytes.as_bytes());
        }
        for line in &SEED_FRAMES[6..] {
            assert!(ClientMessage::decode(line.as_bytes()).is_ok());
        }
    }

    #[test]
    fn the_seed_controller_frames() {
        let zero = |axis| AxisPosition {
            axis,
            value_tenth_um: 0,
        };
        let expected = [
            ControllerMessage::Positions(
                Positions::from_slice(&[zero(b'X'), zero(b'Y'), zero(b'Z'), zero(b'A')]).unwrap(),
            ),
            ControllerMessage::Progress(Progress::default()),
            ControllerMessage::Confirm {
                what: CONFIRM_GCODE_LOAD,
            },
            ControllerMessage::Connected,
            ControllerMessage::KeepAlive { counter: 0 },
        ];
        for (text, msg) in SEED_FRAMES[1..6].iter().zip(expected) {
            let decoded = ControllerMessage::decode(text.as_bytes()).unwrap();
            assert_eq!(decoded, msg, "{text}");
            let encoded = controller(&decoded);
            // 51 and 52 are emitted under their own types; the payload is the seed's.
            assert_eq!(&encoded[3..], &text.as_bytes()[3..]);
            assert_eq!(ControllerMessage::decode(&encoded).unwrap(), decoded);
        }
        let mut n51 = controller(&ControllerMessage::decode(SEED_FRAMES[1].as_bytes()).unwrap());
        n51[1..3].copy_from_slice(b"01");
        assert_eq!(&n51, SEED_FRAMES[1].as_bytes());
    }

    #[test]
    fn the_seed_layout_template_is_not_a_message() {
        // `N00***…F` shows the layout; its empty payload names no setting.
        assert_eq!(
            ClientMessage::decode(SEED_FRAMES[0].as_bytes()),
            Err(FrameError::Payload)
        );
        // The 04 template `xx***…xx` is one byte short of a payload.
        let template = "xx********************************************xx";
        assert_eq!(template.len(), PAYLOAD_LEN - 1);
        assert_eq!(
            ClientMessage::decode(std::format!("N04{template}F").as_bytes()),
            Err(FrameError::Length)
        );
    }

    #[test]
    fn settings() {
        let set = ClientMessage::decode(fr("00", "steps_x=80.0")).unwrap();
        assert_eq!(
            set,
            ClientMessage::SetSetting {
                key: "steps_x",
                value: "80.0"
            }
        );
        for payload in ["steps_x", "steps_x?"] {
            assert_eq!(
                ClientMessage::decode(fr("00", payload)).unwrap(),
                ClientMessage::ReadSetting { key: "steps_x" }
            );
        }
        assert_eq!(
            &client(&ClientMessage::ReadSetting { key: "k" })[..5],
            b"N00k*"
        );
        assert_eq!(
            ClientMessage::decode(fr("00", "a b")),
            Err(FrameError::Payload)
        );
        assert_eq!(
            ClientMessage::decode(fr("00", "=5")),
            Err(FrameError::Payload)
        );
        assert_eq!(
            ClientMessage::decode(fr("00", "k=v*x")),
            Err(FrameError::Payload)
        );
        let answer = ControllerMessage::decode(fr("50", "steps_x=80.0")).unwrap();
        assert_eq!(
            answer,
            ControllerMessage::Setting {
                key: "steps_x",
                value: "80.0"
            }
        );
        assert_eq!(controller(&answer).as_slice(), frame("50", "steps_x=80.0"));
        assert_eq!(
            ControllerMessage::decode(fr("50", "steps_x")),
            Err(FrameError::Payload)
        );
        let mut out = [0u8; FRAME_LEN];
        assert_eq!(
            ClientMessage::SetSetting {
                key: "a",
                value: "b*"
            }
            .encode(&mut out),
            Err(EncodeError::InvalidText)
        );
        assert_eq!(
            ClientMessage::ReadSetting { key: "a=b" }.encode(&mut out),
            Err(EncodeError::InvalidText)
        );
        let long = "v".repeat(48);
        assert_eq!(
            ClientMessage::SetSetting {
                key: "k",
                value: &long
            }
            .encode(&mut out),
            Err(EncodeError::TooLong)
        );
        let fits = "v".repeat(47);
        let msg = ClientMessage::SetSetting {
            key: "k",
            value: &fits,
        };
        assert_eq!(ClientMessage::decode(&client(&msg)).unwrap(), msg);
    }

    #[test]
    fn jog() {
        let msg = ClientMessage::decode(fr("01", "S0.0001X+1000")).unwrap();
        assert_eq!(
            msg,
            ClientMessage::Jog {
                step: Decimal::new(1, 4),
                axis: b'X',
                count: 1000
            }
        );
        assert_eq!(client(&msg).as_slice(), frame("01", "S0.0001X+1000"));
        let msg = ClientMessage::decode(fr("01", "S1A-2147483648")).unwrap();
        assert_eq!(
            msg,
            ClientMessage::Jog {
                step: Decimal::new(1, 0),
                axis: b'A',
                count: i32::MIN
            }
        );
        assert_eq!(client(&msg).as_slice(), frame("01", "S1A-2147483648"));
        // An unsigned count is read as positive and written with its sign.
        let msg = ClientMessage::decode(fr("01", "S0.5Z7")).unwrap();
        assert_eq!(client(&msg).as_slice(), frame("01", "S0.5Z+7"));
        for bad in [
            "S-1X+1",
            "SX+1",
            "S1X",
            "S1X+",
            "S1x+1",
            "S1X+2147483648",
            "0.1X+1",
            "S1X+1 ",
        ] {
            assert_eq!(
                ClientMessage::decode(fr("01", bad)),
                Err(FrameError::Payload),
                "{bad}"
            );
        }
    }

    #[test]
    fn actions() {
        let short = std::format!("N02Stop{}StopF", "*".repeat(40));
        assert_eq!(
            ClientMessage::decode(short.as_bytes()),
            Err(FrameError::Length)
        );
        let mut bytes = frame("02", "Zero");
        bytes[FRAME_LEN - 5..FRAME_LEN - 1].copy_from_slice(b"Stop");
        assert_eq!(ClientMessage::decode(&bytes), Err(FrameError::Mirror));
        let mut bytes = frame("02", "Jump");
        bytes[FRAME_LEN - 5..FRAME_LEN - 1].copy_from_slice(b"Jump");
        assert_eq!(
            ClientMessage::decode(&bytes),
            Err(FrameError::UnknownAction)
        );
        let mut bytes = frame("02", "Zero*x");
        bytes[FRAME_LEN - 5..FRAME_LEN - 1].copy_from_slice(b"Zero");
        assert_eq!(ClientMessage::decode(&bytes), Err(FrameError::Payload));
        assert_eq!(
            ClientMessage::decode(fr("02", "")),
            Err(FrameError::Payload)
        );
        let msg = ClientMessage::Action(Action::Home(b'B'));
        assert_eq!(ClientMessage::decode(&client(&msg)).unwrap(), msg);
        let mut out = [0u8; FRAME_LEN];
        assert_eq!(
            ClientMessage::Action(Action::Home(b'x')).encode(&mut out),
            Err(EncodeError::OutOfRange)
        );
    }

    #[test]
    fn load_line_limits() {
        let text = "G1 X10.5 Y20.25 Z0.3 F1800 E0.0123 S255";
        assert_eq!(text.len(), MAX_LOAD_TEXT);
        let msg = ClientMessage::LoadLine {
            index: 9999,
            text,
            total: 9999,
        };
        let bytes = client(&msg);
        assert_eq!(&bytes[..8], b"N039999C");
        assert_eq!(ClientMessage::decode(&bytes).unwrap(), msg);
        let mut out = [0u8; FRAME_LEN];
        let too_long = std::format!("{text}0");
        assert_eq!(
            ClientMessage::LoadLine {
                index: 1,
                text: &too_long,
                total: 1
            }
            .encode(&mut out),
            Err(EncodeError::TooLong)
        );
        for (index, total) in [(0, 1), (2, 1), (1, 10000)] {
            assert_eq!(
                ClientMessage::LoadLine {
                    index,
                    text: "G1",
                    total
                }
                .encode(&mut out),
                Err(EncodeError::OutOfRange)
            );
        }
        let mut bad = client(&ClientMessage::LoadLine {
            index: 1,
            text: "G1",
            total: 1,
        });
        bad[3..7].copy_from_slice(b"0002");
        assert_eq!(ClientMessage::decode(&bad), Err(FrameError::Payload));
        bad[3..7].copy_from_slice(b"000a");
        assert_eq!(ClientMessage::decode(&bad), Err(FrameError::Payload));
        let empty = ClientMessage::LoadLine {
            index: 1,
            text: "",
            total: 1,
        };
        assert_eq!(ClientMessage::decode(&client(&empty)).unwrap(), empty);
    }

    #[test]
    fn requests() {
        for ty in [0u8, 51, 52, 99] {
            let msg = ClientMessage::Request { message_type: ty };
            let bytes = client(&msg);
            assert_eq!(&bytes[3..5], std::format!("{ty:02}").as_bytes());
            assert_eq!(&bytes[50..], std::format!("{ty:02}F").as_bytes());
            assert_eq!(ClientMessage::decode(&bytes).unwrap(), msg);
        }
        let mut bytes = client(&ClientMessage::Request { message_type: 51 });
        bytes[51] = b'2';
        assert_eq!(ClientMessage::decode(&bytes), Err(FrameError::Mirror));
        let mut out = [0u8; FRAME_LEN];
        assert_eq!(
            ClientMessage::Request { message_type: 100 }.encode(&mut out),
            Err(EncodeError::OutOfRange)
        );
    }

    #[test]
    fn positions() {
        let positions = Positions::from_slice(&[
            AxisPosition {
                axis: b'X',
                value_tenth_um: MAX_POSITION_TENTH_UM,
            },
            AxisPosition {
                axis: b'Y',
                value_tenth_um: -1,
            },
            AxisPosition::from_mm(b'Z', Decimal::new(-123_456_789, 5)).unwrap(),
        ])
        .unwrap();
        let msg = ControllerMessage::Positions(positions.clone());
        let bytes = controller(&msg);
        assert_eq!(
            &bytes[..],
            frame("51", "E+99999.9999x-00000.0001y-01234.5679z").as_slice()
        );
        assert_eq!(ControllerMessage::decode(&bytes).unwrap(), msg);
        assert_eq!(positions.get(b'z'), Some(-12_345_679));
        assert_eq!(positions.axes()[2].mm(), Decimal::new(-12_345_679, 4));
        let empty = ControllerMessage::Positions(Positions::new());
        assert_eq!(
            ControllerMessage::decode(&controller(&empty)).unwrap(),
            empty
        );
        let mut out = [0u8; FRAME_LEN];
        let over = Positions::from_slice(&[AxisPosition {
            axis: b'X',
            value_tenth_um: 1_000_000_000,
        }])
        .unwrap();
        assert_eq!(
            ControllerMessage::Positions(over).encode(&mut out),
            Err(EncodeError::OutOfRange)
        );
        assert!(AxisPosition::from_mm(b'X', Decimal::new(100_000, 0)).is_none());
        assert!(
            Positions::from_slice(
                &[AxisPosition {
                    axis: b'X',
                    value_tenth_um: 0
                }; 5]
            )
            .is_err()
        );
        for bad in [
            "E+00000.0000X",
            "E+0000.00000x",
            "E*00000.0000x",
            "E+00000.0000x+",
            "X",
        ] {
            assert_eq!(
                ControllerMessage::decode(fr("51", bad)),
                Err(FrameError::Payload),
                "{bad}"
            );
        }
    }

    #[test]
    fn progress() {
        let msg = ControllerMessage::Progress(Progress {
            elapsed_s: 61,
            estimated_s: 100_000,
            total_lines: 12_000,
            current_line: 42,
        });
        let bytes = controller(&msg);
        assert_eq!(
            &bytes[..],
            frame("52", "EL01:01ES99:59NL9999LA0042").as_slice()
        );
        assert_eq!(
            ControllerMessage::decode(&bytes).unwrap(),
            ControllerMessage::Progress(Progress {
                elapsed_s: 61,
                estimated_s: MAX_PROGRESS_S,
                total_lines: 9999,
                current_line: 42,
            })
        );
        assert_eq!(
            ControllerMessage::decode(fr("52", "EL01:60ES00:00NL0000LA0000")),
            Err(FrameError::Payload)
        );
        assert_eq!(
            ControllerMessage::decode(fr("52", "EL01:00ES00:00NL0000LA000")),
            Err(FrameError::Payload)
        );
    }

    #[test]
    fn keep_alive_confirm_error() {
        let msg = ControllerMessage::KeepAlive {
            counter: 12_345_678,
        };
        let bytes = controller(&msg);
        assert_eq!(&bytes[..], frame("55", "Vivo2345678").as_slice());
        let msg = ControllerMessage::Confirm { what: "Setting" };
        assert_eq!(ControllerMessage::decode(&controller(&msg)).unwrap(), msg);
        let msg = ControllerMessage::error(&FrameError::Structure);
        assert_eq!(
            &controller(&msg)[..],
            frame("56", "Error:E21 frame").as_slice()
        );
        let msg = ControllerMessage::Error {
            code: 7,
            detail: "line-order 0004",
        };
        assert_eq!(
            &controller(&msg)[..],
            frame("56", "Error:E7 line-order 0004").as_slice()
        );
        assert_eq!(ControllerMessage::decode(&controller(&msg)).unwrap(), msg);
        // The uncoded examples of frame-protocol.md read with code 0.
        for detail in ["frame", "line-order 0004", "store-full", "alarm limit-x"] {
            let decoded =
                ControllerMessage::decode(fr("56", &std::format!("Error:{detail}"))).unwrap();
            assert_eq!(decoded, ControllerMessage::Error { code: 0, detail });
            assert_eq!(
                &controller(&decoded)[3..],
                &frame("56", &std::format!("Error:{detail}"))[3..]
            );
        }
        let mut out = [0u8; FRAME_LEN];
        assert_eq!(
            ControllerMessage::Error {
                code: 0,
                detail: "E12 x"
            }
            .encode(&mut out),
            Err(EncodeError::InvalidText)
        );
        let coded = ControllerMessage::Error {
            code: 65535,
            detail: "",
        };
        assert_eq!(
            ControllerMessage::decode(&controller(&coded)).unwrap(),
            coded
        );
        assert_eq!(
            ControllerMessage::decode(fr("56", "Error:E65536")),
            Err(FrameError::Payload)
        );
        assert_eq!(
            ControllerMessage::decode(fr("54", "Connected")),
            Err(FrameError::Payload)
        );
    }

    #[test]
    fn structure() {
        assert_eq!(ClientMessage::decode(b"N02"), Err(FrameError::Length));
        let mut bytes = frame("02", "Zero");
        bytes[52] = b'G';
        assert_eq!(ClientMessage::decode(&bytes), Err(FrameError::Structure));
        let mut bytes = frame("0A", "");
        assert_eq!(ClientMessage::decode(&bytes), Err(FrameError::Structure));
        bytes[2] = b'9';
        assert_eq!(
            ClientMessage::decode(&bytes),
            Err(FrameError::UnknownType { message_type: 9 })
        );
        assert_eq!(
            ControllerMessage::decode(fr("03", "")),
            Err(FrameError::UnknownType { message_type: 3 })
        );
        let mut bytes = frame("54", "Conected");
        bytes[20] = 0x80;
        assert_eq!(
            ControllerMessage::decode(&bytes),
            Err(FrameError::Structure)
        );
    }
}
