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
        2..=7 | 13 => "the line was damaged on the link",
        8..=12 => "the line is not valid G-code",
        14 => "the line carried only the XOR checksum where the link requires the CRC-16",
        15 => "the line was cut in two on the link",
        20..=25 => "the frame was damaged on the link or is malformed",
        100..=116 => "the value would make the machine's configuration invalid",
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
        130 => "a word is given twice on one line",
        131 => "the move is longer than the axis travel, or ends beyond what can be counted",
        132 => "the machine has no probe to probe with (G38.2-G38.5)",
        133 => "axis words after G80: give a motion command (G0, G1...) first",
        150 => "a limit switch tripped during motion; motion stopped at once",
        151 => "homing travelled the whole axis without finding its switch",
        152 => "the homing switch stayed triggered after backing off",
        153 => "emergency stop (M112)",
        154 => "the step queue ran dry during motion",
        155 => "a stepper driver or limit switch reported a fault",
        156 => "a soft reset (ctrl-x) cut the motion: steps may be lost; home or unlock ($X)",
        157 => "the probe was already touching (or open, for G38.4/G38.5) before it moved",
        158 => "the probing move reached its end without the probe touching",
        170 => "a program line arrived out of order",
        171 => "the controller's program store is full",
        172 => "a program line is longer than the 39 bytes a stored line may have",
        173 => "no such program line",
        174 => "the controller's program storage failed",
        175 => {
            "no upload is in progress on this link (the controller restarted, or another host \
             took over): upload the program again (forja upload FILE)"
        }
        176 => "no file of that name on the controller's card",
        177 => "the controller's card has no room for the file",
        178 => {
            "the file name is not one the card takes (1 to 63 printable characters, no \
                spaces, slashes or * : < > ? | ;)"
        }
        179 => "a file is being written on the card already",
        180 => "no program is stored: upload one first (forja upload FILE)",
        181 => "no job is running",
        182 => "a job is running: stop it first (forja stop)",
        183 => "a program line failed and the job stopped at it",
        184 => "a stored program line is not valid G-code",
        185 => {
            "the stored program is incomplete (its upload was interrupted): upload it again \
             (forja upload FILE)"
        }
        186 => "there is no interrupted job to resume",
        187 => "home the machine before resuming the job (forja home)",
        188 => "the stored program changed since the job was interrupted: it cannot be resumed",
        189 => "no file is selected: select one first (M23 name)",
        190 => "the controller has no such setting",
        191 => "the setting's value is not valid",
        192 => "the controller does not send that message on request",
        193 => "the program line belongs to a program of another length",
        194 => "the machine has no such device",
        195 => "a value the device cannot take",
        196 => "a device output failed",
        197 => "the controller's receive queue was full: the line was not run",
        198 => "the line was waiting when the machine was stopped or reset: it was not run",
        199 => "no file is being written on the card (M29 without M28)",
        220 => "the controller's card failed",
        210..=214 => "a heater shut itself down (thermal fault)",
        215 => "the temperature is above the heater's maximum target",
        230..=238 => "the controller's settings storage failed",
        300 => "another host is in control of this machine",
        _ => return None,
    })
}

/// Whether an error says that a frame or line was damaged on the link (not refused for what it
/// asked).
pub fn is_link_damage(code: u16) -> bool {
    matches!(code, 1..=7 | 13..=15 | 20..=25)
}

/// Whether an error answering an uploaded line means the upload cannot succeed by sending
/// lines again (as opposed to a frame damaged on the link): among them `no-upload` (175: the
/// controller restarted or another host took over, and only a new upload from line 1 can
/// store the program) and `program-incomplete` (185).
pub fn is_fatal_for_upload(code: u16) -> bool {
    matches!(code, 125 | 126 | 128 | 171 | 172 | 174 | 175 | 182 | 185)
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

    /// The `Self::… => <code>,` arms of a source file's `code` functions.
    fn match_arm_codes(source: &str) -> Vec<u16> {
        source
            .lines()
            .filter_map(|l| {
                let (lhs, rhs) = l.trim().split_once(" => ")?;
                lhs.starts_with("Self::")
                    .then(|| rhs.strip_suffix(','))
                    .flatten()?
                    .parse()
                    .ok()
            })
            .collect()
    }

    /// The codes of a module's wire-code table (`//! | <code> | …`).
    fn table_codes(source: &str) -> Vec<u16> {
        source
            .lines()
            .filter_map(|l| l.strip_prefix("//! | ")?.split(' ').next()?.parse().ok())
            .collect()
    }

    #[test]
    fn every_code_the_controller_sends_is_described() {
        // The codes as their owners define them: the protocol's lines and frames (1–39; 40–59
        // are the client's own encode and parse errors), the kernel's, the application's and
        // the controller's tables, the drivers' heaters and storage, the boards' busy refusal.
        let protocol = match_arm_codes(include_str!("../../protocol/src/error.rs"));
        let kernel = table_codes(include_str!("../../motion/src/error.rs"));
        let application = table_codes(include_str!("../../app/src/error.rs"));
        let controller = table_codes(include_str!("../../app/src/controller/mod.rs"));
        let heater = match_arm_codes(include_str!("../../drivers/src/heater.rs"));
        let storage = match_arm_codes(include_str!("../../drivers/src/storage.rs"));
        assert!(protocol.contains(&15) && kernel.contains(&131) && controller.contains(&198));
        assert!(application.contains(&175) && application.contains(&188));
        assert!(heater.contains(&215) && storage.contains(&238));
        let all = protocol
            .into_iter()
            .filter(|c| *c < 40)
            .chain(kernel)
            .chain(application)
            .chain(controller)
            .chain(heater)
            .chain(storage)
            .chain([300]);
        let missing: Vec<u16> = all.filter(|c| meaning(*c).is_none()).collect();
        assert!(
            missing.is_empty(),
            "codes without a description: {missing:?}"
        );
    }

    #[test]
    fn an_upload_refused_for_no_upload_or_an_incomplete_program_stops() {
        assert!(is_fatal_for_upload(175));
        assert!(is_fatal_for_upload(185));
        assert!(!is_fatal_for_upload(21), "a damaged frame is sent again");
        assert!(is_link_damage(13) && is_link_damage(15));
    }
}
