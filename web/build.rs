//! Compresses the page's files (`page/`) with gzip into `OUT_DIR`, and writes the table of
//! assets `src/lib.rs` includes.

use std::fmt::Write as _;
use std::path::Path;
use std::{env, fs};

/// The served files: URL path, file under `page/`, content type.
const FILES: &[(&str, &str, &str)] = &[
    ("/", "index.html", "text/html; charset=utf-8"),
    ("/app.js", "app.js", "text/javascript; charset=utf-8"),
    ("/style.css", "style.css", "text/css; charset=utf-8"),
];

fn main() {
    let out = env::var("OUT_DIR").expect("cargo sets OUT_DIR");
    let mut table = String::from("&[\n");
    for (url, file, content_type) in FILES {
        let src = Path::new("page").join(file);
        println!("cargo::rerun-if-changed={}", src.display());
        let raw = fs::read(&src).unwrap_or_else(|e| panic!("{}: {e}", src.display()));
        let gz = gzip(&raw);
        let dst = Path::new(&out).join(format!("{file}.gz"));
        fs::write(&dst, &gz).unwrap_or_else(|e| panic!("{}: {e}", dst.display()));
        let _ = writeln!(
            table,
            "    Asset {{ path: {url:?}, content_type: {content_type:?}, gzip: include_bytes!({:?}), raw_len: {} }},",
            dst.display().to_string(),
            raw.len()
        );
    }
    table.push(']');
    fs::write(Path::new(&out).join("assets.rs"), table).expect("write the asset table");
}

/// A gzip member (RFC 1952) around a raw deflate stream at the best compression.
fn gzip(raw: &[u8]) -> Vec<u8> {
    let mut gz = vec![0x1f, 0x8b, 8, 0, 0, 0, 0, 0, 2, 255];
    gz.extend(miniz_oxide::deflate::compress_to_vec(raw, 10));
    gz.extend(crc32(raw).to_le_bytes());
    gz.extend((raw.len() as u32).to_le_bytes());
    gz
}

/// CRC-32 (IEEE 802.3), as gzip's trailer needs.
fn crc32(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}
