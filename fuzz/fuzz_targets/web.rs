//! The web page's codecs: the HTTP request head parser and the WebSocket frame decoder never
//! panic on any bytes; the decoder gives the same data, control frames and error whatever the
//! chunking, never more payload than it was given; a request head parses alike once complete;
//! answers fit their stated buffers; reply bytes made ready for a text frame are UTF-8.
#![no_main]

use forja_web::http::{self, Parsed, Route};
use forja_web::websocket::{Decoder, Event, FrameError, MAX_MESSAGE_LEN, text_ready};
use libfuzzer_sys::fuzz_target;

#[derive(Debug, Default, PartialEq, Eq)]
struct Decoded {
    data: Vec<u8>,
    control: Vec<(u8, Vec<u8>)>,
    error: Option<FrameError>,
}

fn decode(input: &[u8], step: usize, limit: u64) -> Decoded {
    let mut d = Decoder::new(limit);
    let mut out = Decoded::default();
    for piece in input.chunks(step.max(1)) {
        let r = d.feed_all(piece, |e| match e {
            Event::Data(b) => out.data.extend_from_slice(b),
            Event::Ping(p) => out.control.push((9, p.to_vec())),
            Event::Pong(p) => out.control.push((10, p.to_vec())),
            Event::Close { code, reason } => {
                let mut v = code.map_or(Vec::new(), |c| c.to_be_bytes().to_vec());
                v.extend_from_slice(reason);
                out.control.push((8, v));
            }
        });
        if let Err(e) = r {
            out.error = Some(e);
            break;
        }
    }
    out
}

fuzz_target!(|input: &[u8]| {
    let (&step, data) = input.split_first().unwrap_or((&1, &[]));
    let limit = if step & 1 == 0 { MAX_MESSAGE_LEN } else { 300 };

    let whole = decode(data, data.len(), limit);
    assert!(whole.data.len() <= data.len());
    assert_eq!(whole, decode(data, usize::from(step % 17) + 1, limit));
    if let Some(e) = whole.error {
        assert!(matches!(e.close_code(), 1002 | 1009));
    }

    match http::parse(data) {
        Ok(Parsed::Complete { request, head_len }) => {
            assert!(head_len <= data.len() && head_len <= http::MAX_HEAD_LEN);
            let again = http::parse(&data[..head_len]);
            assert_eq!(again, Ok(Parsed::Complete { request, head_len }));
            let mut out = [0u8; 256];
            match request.route() {
                Route::Asset { asset, .. } => {
                    assert!(http::write_asset_head(&mut out[..240], asset).is_ok())
                }
                Route::WebSocket { key } => {
                    assert!(http::write_switching_protocols(&mut out[..129], key).is_ok())
                }
                Route::Refuse(e) => assert!(http::write_error(&mut out, e).is_ok()),
            }
        }
        Ok(Parsed::Partial) => assert!(data.len() < http::MAX_HEAD_LEN),
        Err(e) => {
            let mut out = [0u8; 256];
            assert!(http::write_error(&mut out, e).is_ok());
        }
    }

    let mut text = data.to_vec();
    let ready = text_ready(&mut text, step & 2 == 0);
    assert!(ready <= text.len() && text.len() - ready <= 3);
    assert!(std::str::from_utf8(&text[..ready]).is_ok());
});
