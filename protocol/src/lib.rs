//! Forja's wire codecs: RepRap G-code lines, replies and fixed 53-byte frames.
#![no_std]
