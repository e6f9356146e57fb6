//! What the controller's error codes mean, in words for the person at the machine.
//!
//! Codes are stable (`docs/protocol.md` §5 and the kernel's `motion/src/error.rs`): the client
//! matches on them, never on the text that follows.

/// A sentence for error `code`, with the controller's own `text` (its name and detail) kept
/// for reference: `"the move ends outside the axis travel (E124 soft-limit X)"`.
pub fn explain(code: u16, text: &str) -> String {
    let reference = match (code, text.is_empty()) {
        (0, _) => text.to_string(),
        (_, true) => format!("E{code}"),
        (_, false) => format!("E{code} {text}"),
    };
    match meaning(code) {
        Some(meaning) => format!("{meaning} ({reference})"),
        None => reference,
    }
}

/// What `code` means, if it is a known one.
pub fn meaning(code: u16) -> Option<&'static str> {
    Some(match code {
        1 => "the line was too long",
        2..=7 => "the line was damaged on the link",
        8..=12 => "the line is not valid G-code",
        20..=25 => "the frame was damaged on the link or is malformed",
        120 => "the controller does not support this command",
        121 => "a value is out of range for its command",
        122 => "a required value is missing (an arc's centre or radius, M92's value)",
        123 => "the arc's end point is not on its circle",
        124 => "the move ends outside the axis travel",
        125 => "the machine is in alarm: reset it (forja reset) or home it (forja home) first",
        126 => "the machine stopped on M0: reset it first (forja reset)",
        127 => "the letter names no axis of this machine",
        128 => "the machine must be at rest for this (it is moving or its queue is full)",
        129 => "two commands of the same group on one line",
        150 => "a limit switch tripped during motion; motion stopped at once",
        151 => "homing travelled the whole axis without finding its switch",
        152 => "the homing switch stayed triggered after backing off",
        153 => "emergency stop (M112)",
        154 => "the step queue ran dry during motion",
        155 => "a stepper driver or limit switch reported a fault",
        170 => "a program line arrived out of order",
        171 => "the controller's program store is full",
        172 => "a program line is longer than the 39 bytes a stored line may have",
        173 => "no such program line",
        174 => "the controller's program storage failed",
        180 => "no program is stored: upload one first (forja upload FILE)",
        181 => "no job is running",
        182 => "a job is running: stop it first (forja stop)",
        183 => "a program line failed and the job stopped at it",
        184 => "a stored program line is not valid G-code",
        190 => "the controller has no such setting",
        191 => "the setting's value is not valid",
        192 => "the controller does not send that message on request",
        193 => "the program line belongs to a program of another length",
        194 => "the machine has no such device",
        195 => "a value the device cannot take",
        196 => "a device output failed",
        210..=215 => "a heater shut itself down (thermal fault)",
        _ => return None,
    })
}

/// Whether an error says that a frame or line was damaged on the link (not refused for what it
/// asked).
pub fn is_link_damage(code: u16) -> bool {
    (1..=7).contains(&code) || (20..=25).contains(&code)
}

/// Whether an error answering an uploaded line means the upload cannot succeed by sending
/// lines again (as opposed to a frame damaged on the link).
pub fn is_fatal_for_upload(code: u16) -> bool {
    matches!(code, 125 | 126 | 128 | 171 | 172 | 174 | 182)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn explanations_keep_the_reference() {
        assert_eq!(
            explain(124, "soft-limit X"),
            "the move ends outside the axis travel (E124 soft-limit X)"
        );
        assert_eq!(explain(0, "store-full"), "store-full");
        assert_eq!(explain(999, "odd"), "E999 odd");
        assert!(explain(180, "job-empty").starts_with("no program is stored"));
    }
}
