//! Writing replies and frames to the link.
//!
//! A write that fails (the link went away) is dropped: the controller never stalls or fails
//! on its output. Each reply or frame is written with one `write_all`, terminator included.

use embedded_io::Write;
use forja_protocol::frame::{ControllerMessage, FRAME_LEN};
use forja_protocol::reply::Reply;

use super::text::Refusal;

/// The longest reply line written (an `M115` answer is the longest).
const REPLY_BUF: usize = 320;

/// Write one reply line; `false` (and nothing written) when it does not encode.
pub(crate) fn reply<W: Write>(out: &mut W, reply: &Reply<'_>) -> bool {
    let mut buf = [0u8; REPLY_BUF];
    match reply.encode(&mut buf) {
        Ok(n) => {
            let _ = out.write_all(buf.get(..n).unwrap_or(&[]));
            true
        }
        Err(_) => false,
    }
}

/// `ok`.
pub(crate) fn ok<W: Write>(out: &mut W) {
    let _ = out.write_all(b"ok\n");
}

/// `Error:E<code> <text>`: a fault that stopped the machine.
pub(crate) fn fault<W: Write>(out: &mut W, r: &Refusal) {
    let _ = reply(
        out,
        &Reply::Fault {
            code: r.code,
            text: r.text(),
        },
    );
}

/// `echo:E<code> <text>`: a refused line (its `ok` is the caller's).
pub(crate) fn refused<W: Write>(out: &mut W, r: &Refusal) {
    let _ = reply(
        out,
        &Reply::Refused {
            code: r.code,
            text: r.text(),
        },
    );
}

/// `rs <line>` then `ok`, as Marlin answers: a host sends the line again at once, without
/// waiting out a time-out for the `ok` it counts on.
pub(crate) fn resend<W: Write>(out: &mut W, line: u32) {
    let _ = reply(out, &Reply::Resend(line));
    ok(out);
}

/// One frame and its `\n`. A message that does not encode (a text too long for the payload)
/// is written as a 56 with the name alone, and if even that fails, not at all.
pub(crate) fn frame<W: Write>(out: &mut W, msg: &ControllerMessage<'_>) {
    let mut buf = [b'\n'; FRAME_LEN + 1];
    let Some((head, _)) = buf.split_first_chunk_mut::<FRAME_LEN>() else {
        return;
    };
    if msg.encode(head).is_ok() {
        let _ = out.write_all(&buf);
    }
}

/// Frame 56 for a refusal: `Error:E<code> <name> <detail>`; the detail is dropped when the
/// whole does not fit the payload.
pub(crate) fn error_frame<W: Write>(out: &mut W, r: &Refusal) {
    let mut buf = [b'\n'; FRAME_LEN + 1];
    let Some((head, _)) = buf.split_first_chunk_mut::<FRAME_LEN>() else {
        return;
    };
    let text = r.text();
    let full = ControllerMessage::Error {
        code: r.code,
        detail: text,
    };
    let short = ControllerMessage::Error {
        code: r.code,
        detail: text.split(' ').next().unwrap_or(""),
    };
    if full.encode(head).is_ok() || short.encode(head).is_ok() {
        let _ = out.write_all(&buf);
    }
}
