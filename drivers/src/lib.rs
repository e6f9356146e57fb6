//! Forja's plugin drivers over embedded-hal and embedded-io.
#![no_std]
