//! Forja's board-agnostic motion kernel.
#![no_std]
