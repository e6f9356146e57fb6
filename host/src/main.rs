//! The forja command-line client.

fn main() {}
