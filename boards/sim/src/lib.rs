//! Forja's host simulator board.
