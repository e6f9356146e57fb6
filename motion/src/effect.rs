//! What the kernel hands back to the controller: commands for other subsystems, in order.
//!
//! Heaters, fans, spindles, coolant, the beeper, the link's line numbering, storage and motor
//! power are not the motion kernel's hardware, but their commands arrive in the same G-code
//! stream and must take effect at the right place in it. The kernel therefore recognises them,
//! parses their arguments, and returns each as an [`Effect`] from [`crate::Kernel::execute`] —
//! at the moment it is to be carried out:
//!
//! - an effect whose [`Effect::sync`] is [`Sync::Now`] is returned as soon as its line is
//!   offered (motion already queued keeps running): temperature targets, reports, line numbers,
//!   storage commands, motors on, tones;
//! - an effect that is [`Sync::AfterMotion`] is returned only once every move before it has
//!   finished: until then `execute` answers [`crate::Reply::Busy`] for that line. Spindle,
//!   coolant, fan, tool change, motors off, program stop, pause and program end thus happen
//!   exactly between the moves around them, as grbl does for its spindle and coolant.
//!
//! The controller executes each effect when it receives it, then acknowledges the line.
//! Waiting effects (`M109`, `M116`) are the controller's to wait for: it offers no further line
//! to the kernel until the wait is over, while the moves already queued go on.

use forja_protocol::gcode::Decimal;

/// When an effect is to be carried out relative to the motion queued before it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sync {
    /// At once: the moves already queued go on.
    Now,
    /// After every move queued before it has finished (the kernel waits before returning it).
    AfterMotion,
}

/// A heater named by a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Heater {
    /// An extruder's hot end: the `T` word of the command, or the current tool (`None`).
    Extruder(Option<u8>),
    /// The bed (`M140`, `M190`).
    Bed,
    /// The chamber (`M141`).
    Chamber,
}

/// Whether and how a heater command holds further lines (`M109`, `M190`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TemperatureWait {
    /// `M104`, `M140`: set the target and go on.
    No,
    /// `M109 S`, `M190 S`: wait while the heater heats up to the target; a heater above it
    /// does not hold the lines (Marlin's rule).
    Heating,
    /// `M109 R`, `M190 R`: wait until the heater is at the target, heating or cooling.
    Reach,
}

/// Spindle state (`M3`/`M4`/`M5`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Spindle {
    /// `M3`: clockwise, at `rpm` (the `S` word) when given.
    Clockwise {
        /// Speed, when the line has `S`.
        rpm: Option<Decimal>,
    },
    /// `M4`: counter-clockwise.
    CounterClockwise {
        /// Speed, when the line has `S`.
        rpm: Option<Decimal>,
    },
    /// `M5`: stopped.
    Off,
    /// `S` alone on a line: the speed of the spindle if it runs, and of the next `M3`/`M4`
    /// without `S`.
    Speed {
        /// The `S` word.
        rpm: Decimal,
    },
}

/// Coolant state (`M7`/`M8`/`M9`), as grbl and LinuxCNC have it: mist and flood are turned on
/// each on its own (both may be on), and turned off together.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coolant {
    /// `M7`: mist on.
    Mist,
    /// `M8`: flood on.
    Flood,
    /// `M9`: mist and flood off.
    Off,
}

/// SD card / file storage commands `M20`–`M30`, `M32`, for the controller's storage subsystem.
/// A file name is the command's free text, as given.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Storage<'l> {
    /// `M20`: list files.
    List,
    /// `M21`: initialise the card.
    Init,
    /// `M22`: release the card.
    Release,
    /// `M23 <name>`: select a file.
    Select(&'l [u8]),
    /// `M24`: start or resume printing the selected file.
    Start,
    /// `M25`: pause printing the selected file.
    Pause,
    /// `M26 S<bytes>`: set the position in the file.
    SetPosition(u32),
    /// `M27`: report the printing status.
    Report,
    /// `M27 S<seconds>`: report the printing status every so many seconds (0: stop).
    ReportEvery(u8),
    /// `M28 <name>`: begin writing to a file.
    BeginWrite(&'l [u8]),
    /// `M29 <name>`: stop writing.
    EndWrite(Option<&'l [u8]>),
    /// `M30 <name>`: delete a file (`M30` alone is program end, [`Effect::ProgramEnd`]).
    Delete(&'l [u8]),
    /// `M32 <name>`: select a file and start printing it.
    SelectAndStart(&'l [u8]),
}

/// How motion stopped on a program command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopKind {
    /// `M0`: the moves before it finished; the machine is halted until a reset.
    Program,
    /// `M112`: motion was cut at once; the machine is in alarm until a reset or a homing.
    Emergency,
}

/// A command for a subsystem other than motion, returned in stream order. See the module
/// documentation for when each is returned.
/// Every effect is handled by the application layer: the enum is exhaustive on purpose, so
/// that a new effect does not compile until it is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Effect<'l> {
    /// `M104`, `M109` (`wait`), `M140`, `M190` (`wait`): set a heater's target, °C (`S` or
    /// `R`, 0 = off).
    SetTemperature {
        /// Which heater.
        heater: Heater,
        /// Target temperature in °C.
        celsius: Decimal,
        /// Whether to hold further lines until this heater reaches it.
        wait: TemperatureWait,
    },
    /// `M116`: hold further lines until every heater is at its target.
    WaitForTemperatures,
    /// `M105`: report temperatures (`ok T:… B:…`).
    ReportTemperatures,
    /// `M106` (`S` 0–255, default 255; `P` fan index) and `M107` (duty 0).
    Fan {
        /// Fan index (`P`, default 0).
        index: u8,
        /// PWM duty, 0–255.
        duty: u8,
    },
    /// `M3`, `M4`, `M5`.
    Spindle(Spindle),
    /// `M7`, `M8`, `M9`.
    Coolant(Coolant),
    /// `M110`: the next line number the link expects is this plus one.
    SetLineNumber(u32),
    /// `M115`: report firmware name and capabilities.
    ReportFirmware,
    /// `M119`: report the limit switches.
    ReportEndstops,
    /// `M20`–`M29`, `M30 <name>`, `M32`.
    Storage(Storage<'l>),
    /// `T<n>`: select tool `n`.
    SelectTool(u8),
    /// `M17` (on), `M18`/`M84` (off): stepper driver power. Releasing an axis loses its homed
    /// state (the kernel forgets it).
    Motors {
        /// Energise (`true`) or release the motors.
        enabled: bool,
        /// The axes concerned, bit `i` for axis `i`: every axis for `M17` and a bare `M84`,
        /// the named ones for `M84 X Y E`.
        axes: u8,
    },
    /// `M0` or `M112`: motion stopped; the controller turns heaters and motors off.
    Stopped(StopKind),
    /// `M400`: every move before it has finished (returned once they have).
    MotionDone,
    /// `M410`: stop every move now and drop those queued (Marlin's quick stop); the machine
    /// keeps its position and homing. The controller stops the motion as a stop frame does.
    QuickStop,
    /// `M73`: the host's progress of its job, for the operator (`P` percent done, `R` minutes
    /// left, `L` the layer being printed).
    Progress {
        /// `P`, percent done (0–100).
        percent: Option<u8>,
        /// `R`, minutes left.
        remaining_min: Option<u32>,
        /// `L`, the current layer.
        layer: Option<u32>,
    },
    /// `M117 <text>`: a message for the operator's display (empty: clear it).
    Message(&'l [u8]),
    /// `M118 [A1] [E1] [Pn] <text>`: a line to the host, as given after the command.
    HostMessage(&'l [u8]),
    /// `M155 S<seconds>`: report the temperatures every so many seconds without being asked
    /// (0: stop).
    AutoReport {
        /// The period, s.
        seconds: u8,
    },
    /// `M113 S<seconds>`: the period of `busy: processing` while a command blocks (0: never);
    /// `None` (no `S`) asks for the period.
    BusyInterval(Option<u8>),
    /// `M42 P<index> S<0–255>`: a general-purpose output on (`S` above 0) or off; grblHAL's
    /// `M62`–`M65 P<index>` too.
    Output {
        /// The output's index (`P`).
        index: u8,
        /// On or off.
        on: bool,
        /// After the motion before it (`M62`/`M63`), rather than at once (`M42`, `M64`/`M65`).
        synced: bool,
    },
    /// `M80` (on, at once), `M81` (off, after the motion before it): the machine's power
    /// supply.
    PowerSupply {
        /// On or off.
        on: bool,
    },
    /// `M300 S<Hz> P<ms>`: a tone of the beeper, at once, as Marlin queues it to its beeper:
    /// the moves queued before it go on (an `M400` before it sounds it after them).
    Tone {
        /// The pitch, Hz (`S`, 260 without it, at most 20 000); 0 is silence: a pause between
        /// tones.
        frequency_hz: u16,
        /// How long, ms (`P`, 1000 without it; a longer one is cut to 5000, as Marlin cuts
        /// it).
        duration_ms: u16,
    },
    /// `M226` (and grbl's `M0`): the program pauses here (motion before it is done);
    /// [`crate::Kernel::resume`] continues.
    Paused,
    /// `M6`: the program pauses here for a manual tool change to tool `T` (the one `T` last
    /// selected when `None`); [`crate::Kernel::resume`] (cycle start) continues.
    ToolChange(Option<u8>),
    /// `M2`, `M30`: end of program, once the motion before it is done. The kernel has reset
    /// its modal state (`G1`, `G17`, `G90`, `G94`); the controller stops the spindle and ends
    /// the stored program that ran it.
    ProgramEnd,
}

impl Effect<'_> {
    /// When the effect is to be carried out.
    pub fn sync(&self) -> Sync {
        match self {
            Self::Spindle(_)
            | Self::Coolant(_)
            | Self::Fan { .. }
            | Self::SelectTool(_)
            | Self::Output { synced: true, .. }
            | Self::Motors { enabled: false, .. }
            | Self::Stopped(StopKind::Program)
            | Self::Paused
            | Self::MotionDone
            | Self::PowerSupply { on: false }
            | Self::ProgramEnd => Sync::AfterMotion,
            _ => Sync::Now,
        }
    }
}

/// The same slice of `to` as `s` is of `from` (both the same line text).
fn rebase_slice<'a>(s: &[u8], from: &[u8], to: &'a [u8]) -> &'a [u8] {
    let off = (s.as_ptr() as usize).wrapping_sub(from.as_ptr() as usize);
    to.get(off..off.saturating_add(s.len())).unwrap_or(&[])
}

impl Effect<'_> {
    /// The same effect with its texts borrowed from `to`, a copy of the line `from`.
    pub fn rebase<'a>(self, from: &[u8], to: &'a [u8]) -> Effect<'a> {
        let r = |s: &[u8]| rebase_slice(s, from, to);
        match self {
            Effect::Storage(st) => Effect::Storage(match st {
                Storage::Select(n) => Storage::Select(r(n)),
                Storage::BeginWrite(n) => Storage::BeginWrite(r(n)),
                Storage::EndWrite(n) => Storage::EndWrite(n.map(r)),
                Storage::Delete(n) => Storage::Delete(r(n)),
                Storage::SelectAndStart(n) => Storage::SelectAndStart(r(n)),
                Storage::List => Storage::List,
                Storage::Init => Storage::Init,
                Storage::Release => Storage::Release,
                Storage::Start => Storage::Start,
                Storage::Pause => Storage::Pause,
                Storage::SetPosition(p) => Storage::SetPosition(p),
                Storage::Report => Storage::Report,
                Storage::ReportEvery(s) => Storage::ReportEvery(s),
            }),
            Effect::SetTemperature {
                heater,
                celsius,
                wait,
            } => Effect::SetTemperature {
                heater,
                celsius,
                wait,
            },
            Effect::WaitForTemperatures => Effect::WaitForTemperatures,
            Effect::ReportTemperatures => Effect::ReportTemperatures,
            Effect::Fan { index, duty } => Effect::Fan { index, duty },
            Effect::Spindle(s) => Effect::Spindle(s),
            Effect::Coolant(c) => Effect::Coolant(c),
            Effect::SetLineNumber(n) => Effect::SetLineNumber(n),
            Effect::ReportFirmware => Effect::ReportFirmware,
            Effect::ReportEndstops => Effect::ReportEndstops,
            Effect::SelectTool(t) => Effect::SelectTool(t),
            Effect::ToolChange(t) => Effect::ToolChange(t),
            Effect::Motors { enabled, axes } => Effect::Motors { enabled, axes },
            Effect::Stopped(k) => Effect::Stopped(k),
            Effect::Paused => Effect::Paused,
            Effect::ProgramEnd => Effect::ProgramEnd,
            Effect::MotionDone => Effect::MotionDone,
            Effect::QuickStop => Effect::QuickStop,
            Effect::Progress {
                percent,
                remaining_min,
                layer,
            } => Effect::Progress {
                percent,
                remaining_min,
                layer,
            },
            Effect::Message(t) => Effect::Message(r(t)),
            Effect::HostMessage(t) => Effect::HostMessage(r(t)),
            Effect::AutoReport { seconds } => Effect::AutoReport { seconds },
            Effect::BusyInterval(s) => Effect::BusyInterval(s),
            Effect::Output { index, on, synced } => Effect::Output { index, on, synced },
            Effect::PowerSupply { on } => Effect::PowerSupply { on },
            Effect::Tone {
                frequency_hz,
                duration_ms,
            } => Effect::Tone {
                frequency_hz,
                duration_ms,
            },
        }
    }
}
