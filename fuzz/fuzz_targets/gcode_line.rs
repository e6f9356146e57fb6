//! G-code lines: parsing never panics; what parses re-encodes to a line that parses to the
//! same; a canonical numbered line damaged in one byte is refused; line numbering never panics.
#![no_main]

use forja_protocol::gcode::{EncodeError, Line, LineNumbering, MAX_LINE_LEN, checksum};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut numbering = LineNumbering::new();
    let line = match Line::parse(data) {
        Ok(line) => line,
        Err(error) => {
            let _ = numbering.recover(&error);
            return;
        }
    };
    let _ = numbering.accept(&line);

    let mut out = [0u8; 4 * MAX_LINE_LEN];
    let len = match line.encode(&mut out) {
        Ok(len) => len,
        // The canonical form may outgrow the limit ("X1X1…" gains spaces); nothing else fails.
        Err(EncodeError::TooLong) => return,
        Err(e) => panic!("encode failed: {e:?}"),
    };
    let encoded = &out[..len];
    assert!(len <= MAX_LINE_LEN);
    let again = Line::parse(encoded).expect("a canonical line parses");
    assert_eq!(again, line);
    let mut out2 = [0u8; MAX_LINE_LEN];
    let len2 = again.encode(&mut out2).expect("encodes again");
    assert_eq!(&out2[..len2], encoded);

    if let Some(cs) = line.checksum() {
        let star = encoded.iter().position(|&b| b == b'*').expect("numbered");
        assert_eq!(checksum(encoded), cs);
        assert_eq!(checksum(&encoded[..star]), cs);
        // One damaged byte of a checksummed line is always caught.
        let at = usize::from(data.first().copied().unwrap_or(0)) % len;
        let mut damaged = out2;
        let new = data.last().copied().unwrap_or(0x5a);
        if damaged[at] != new {
            damaged[at] = new;
            assert!(
                Line::parse(&damaged[..len]).is_err(),
                "undetected damage: {:?}",
                String::from_utf8_lossy(&damaged[..len])
            );
        }
    }
});
