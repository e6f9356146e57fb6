//! `Sec-WebSocket-Accept` (RFC 6455 §4.2.2): base64(SHA-1(key + GUID)). SHA-1 (RFC 3174) and
//! base64 (RFC 4648, with padding) are written out here for that one use: a handshake hashes
//! 60 bytes, so speed does not matter and a dependency would not pay.

/// The GUID every server appends to the client's key.
const GUID: &[u8] = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11";

/// Length of a `Sec-WebSocket-Accept` value: base64 of 20 bytes.
pub const ACCEPT_LEN: usize = 28;

/// The `Sec-WebSocket-Accept` value answering the client's `Sec-WebSocket-Key` `key`.
pub fn accept_key(key: &[u8]) -> [u8; ACCEPT_LEN] {
    base64_20(&sha1(&[key, GUID]))
}

/// SHA-1 of the concatenation of `parts`.
fn sha1(parts: &[&[u8]]) -> [u8; 20] {
    let mut h: [u32; 5] = [
        0x6745_2301,
        0xEFCD_AB89,
        0x98BA_DCFE,
        0x1032_5476,
        0xC3D2_E1F0,
    ];
    let total: usize = parts.iter().map(|p| p.len()).sum();
    let bits = (total as u64).wrapping_mul(8).to_be_bytes();
    let mut block = [0u8; 64];
    let mut fill = 0;
    let mut push = |byte: u8, h: &mut [u32; 5]| {
        if let Some(slot) = block.get_mut(fill) {
            *slot = byte;
        }
        fill += 1;
        if fill == block.len() {
            compress(h, &block);
            fill = 0;
        }
    };
    for byte in parts.iter().flat_map(|p| p.iter().copied()) {
        push(byte, &mut h);
    }
    // Padding: 0x80, zeros up to 56 mod 64, the length in bits.
    let zeros = (119 - total % 64) % 64;
    push(0x80, &mut h);
    for _ in 0..zeros {
        push(0, &mut h);
    }
    for byte in bits {
        push(byte, &mut h);
    }
    let mut out = [0u8; 20];
    for (chunk, word) in out.chunks_exact_mut(4).zip(h) {
        chunk.copy_from_slice(&word.to_be_bytes());
    }
    out
}

/// One 64-byte block into the state.
fn compress(h: &mut [u32; 5], block: &[u8; 64]) {
    let mut w = [0u32; 80];
    for (word, bytes) in w.iter_mut().zip(block.chunks_exact(4)) {
        *word = bytes.iter().fold(0u32, |acc, &b| (acc << 8) | u32::from(b));
    }
    for t in 16..80 {
        let x = [t - 3, t - 8, t - 14, t - 16]
            .iter()
            .fold(0u32, |acc, &i| acc ^ w.get(i).copied().unwrap_or(0));
        if let Some(word) = w.get_mut(t) {
            *word = x.rotate_left(1);
        }
    }
    let [mut a, mut b, mut c, mut d, mut e] = *h;
    for (t, word) in w.iter().enumerate() {
        let (f, k) = match t {
            0..20 => ((b & c) | (!b & d), 0x5A82_7999),
            20..40 => (b ^ c ^ d, 0x6ED9_EBA1),
            40..60 => ((b & c) | (b & d) | (c & d), 0x8F1B_BCDC),
            _ => (b ^ c ^ d, 0xCA62_C1D6),
        };
        let temp = a
            .rotate_left(5)
            .wrapping_add(f)
            .wrapping_add(e)
            .wrapping_add(k)
            .wrapping_add(*word);
        e = d;
        d = c;
        c = b.rotate_left(30);
        b = a;
        a = temp;
    }
    for (state, v) in h.iter_mut().zip([a, b, c, d, e]) {
        *state = state.wrapping_add(v);
    }
}

/// Base64 of 20 bytes: 27 characters and one `=`.
fn base64_20(bytes: &[u8; 20]) -> [u8; ACCEPT_LEN] {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let sextet = |v: u32| ALPHABET.get((v & 63) as usize).copied().unwrap_or(b'=');
    let mut out = [b'='; ACCEPT_LEN];
    for (group, chunk) in out.chunks_exact_mut(4).zip(bytes.chunks(3)) {
        let n = chunk.len();
        let v = chunk
            .iter()
            .chain([0u8, 0].iter())
            .take(3)
            .fold(0u32, |acc, &b| (acc << 8) | u32::from(b));
        for (i, slot) in group.iter_mut().enumerate().take(n + 1) {
            *slot = sextet(v >> (18 - 6 * i));
        }
    }
    out
}

/// Whether `key` is a valid `Sec-WebSocket-Key`: base64 of 16 bytes (24 characters, the last
/// two `==`).
pub fn is_valid_key(key: &[u8]) -> bool {
    let is_b64 = |c: &u8| c.is_ascii_alphanumeric() || *c == b'+' || *c == b'/';
    key.len() == 24 && key.get(..22).is_some_and(|k| k.iter().all(is_b64)) && key.ends_with(b"==")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rfc_6455_example() {
        assert_eq!(
            &accept_key(b"dGhlIHNhbXBsZSBub25jZQ=="),
            b"s3pPLMBiTxaQ9kYGzzhZRbK+xOo="
        );
        assert!(is_valid_key(b"dGhlIHNhbXBsZSBub25jZQ=="));
    }

    #[test]
    fn sha1_known_answers() {
        let hex = |h: [u8; 20]| {
            h.iter()
                .map(|b| char::from_digit(u32::from(b >> 4), 16).unwrap())
                .zip(
                    h.iter()
                        .map(|b| char::from_digit(u32::from(b & 15), 16).unwrap()),
                )
                .fold(std::string::String::new(), |mut s, (a, b)| {
                    s.push(a);
                    s.push(b);
                    s
                })
        };
        assert_eq!(
            hex(sha1(&[b""])),
            "da39a3ee5e6b4b0d3255bfef95601890afd80709"
        );
        assert_eq!(
            hex(sha1(&[b"abc"])),
            "a9993e364706816aba3e25717850c26c9cd0d89d"
        );
        // 56 bytes: the padding takes a second block.
        assert_eq!(
            hex(sha1(&[
                b"abcdbcdecdefdefgefghfghighij",
                b"hijkijkljklmklmnlmnomnopnopq"
            ])),
            "84983e441c3bd26ebaae4aa1f95129e5e54670f1"
        );
        let million = [b'a'; 1000];
        let parts = [&million[..]; 1000];
        assert_eq!(
            hex(sha1(&parts)),
            "34aa973cd4c4daa4f61eeb2bdbad27316534016f"
        );
    }

    #[test]
    fn keys_that_are_not_16_bytes_of_base64_are_refused() {
        for key in [
            &b""[..],
            b"abc",
            b"dGhlIHNhbXBsZSBub25jZQ=",
            b"dGhlIHNhbXBsZSBub25jZ*==",
        ] {
            assert!(!is_valid_key(key), "{key:?}");
        }
    }
}
