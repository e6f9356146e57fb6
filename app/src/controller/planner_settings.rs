//! `M500`–`M503`, Marlin's settings commands, on the planner settings (`M92`, `M201`, `M203`,
//! `M204`, `M205`): kept in the settings storage, given back to the kernel, reset to the
//! board's defaults, reported.
//!
//! | command | effect | answer |
//! |---|---|---|
//! | `M500` | the settings the kernel runs with are stored (records of [`Settings`](super::Settings): `<axis>.steps_per_mm`, `.max_rate`, `.accel`, `junction_deviation`, `print_accel`, `retract_accel`, `travel_accel`, `min_print_feed`, `min_travel_feed`); they are the kernel's at the next start | `echo:Settings stored`, `ok` |
//! | `M501` | the stored settings, given to the kernel once the motion before it is done | `echo:Stored settings retrieved`, `ok` |
//! | `M502` | the board's defaults, given to the kernel (not stored: `M500` stores them) | `echo:Hardcoded default settings loaded`, `ok` |
//! | `M503` | the settings as the G-code lines that set them | `echo:` lines, `ok` |
//!
//! A storage that fails refuses `M500` (`echo:E174 store-device`); the records written before
//! the failure are kept (each setting is a record of its own, old or new after a power cut).

use embedded_io::Write;
use forja_hal_abstraction::program::ProgramStore;
use forja_hal_abstraction::storage::RecordStorage;
use forja_motion::{PathLimits, PlannerSettings, Reply as KernelReply};
use forja_protocol::gcode::{Decimal, Line};
use forja_protocol::reply::Reply;

use super::peripherals::Peripherals;
use super::text::{self, Refusal, Text};
use super::{Core, Held, LineBuf, wire};

/// `v` rounded to `scale` decimals, for a report (a decimal: no float formatting in the
/// firmware image).
fn fixed(v: f32, scale: u8) -> Decimal {
    Decimal::from_f32(v, scale).unwrap_or(Decimal::from_integer(0))
}

/// The settings `M500` stores, in the order stored, with their values from `s` (axis settings
/// for each axis, then the machine-wide ones).
fn records<const N: usize>(
    s: &PlannerSettings<N>,
    mut each: impl FnMut(&str, f32) -> bool,
) -> bool {
    for i in 0..N {
        let letter = s.letters[i].to_ascii_lowercase();
        let axis = [
            ("steps_per_mm", s.steps_per_mm[i]),
            ("max_rate", s.max_rate_mm_s[i] * 60.0),
            ("accel", s.max_accel_mm_s2[i]),
        ];
        for (field, value) in axis {
            let mut key = Text::<24>::new();
            key.push_byte(letter).push(".").push(field);
            if !each(key.as_str(), value) {
                return false;
            }
        }
    }
    let p = s.path;
    [
        ("junction_deviation", s.junction_deviation_mm),
        ("print_accel", p.print_accel_mm_s2.unwrap_or(0.0)),
        ("retract_accel", p.retract_accel_mm_s2.unwrap_or(0.0)),
        ("travel_accel", p.travel_accel_mm_s2.unwrap_or(0.0)),
        ("min_print_feed", p.min_extruding_feed_mm_s),
        ("min_travel_feed", p.min_travel_feed_mm_s),
    ]
    .into_iter()
    .all(|(key, value)| each(key, value))
}

impl<const N: usize, const B: usize, const Q: usize, P, X, S> Core<'_, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// `M500`–`M503` (see the module documentation): whether `line` was one (it is answered,
    /// or held until the machine is idle).
    pub(super) fn settings_command<W: Write>(
        &mut self,
        line: &Line<'_>,
        bytes: &[u8],
        out: &mut W,
    ) -> bool {
        let number = line
            .command()
            .filter(|w| w.letter == b'M')
            .and_then(|w| w.value.as_integer());
        let Some(number @ 500..=503) = number else {
            return false;
        };
        if let Some(letter) = line.words().get(1).map(|w| w.letter) {
            let e = forja_motion::CommandError::UnknownAxis { letter };
            self.refuse(&text::command_refusal(&e, &[]), out);
            return true;
        }
        let done = match number {
            500 => self.store_planner_settings(),
            501 => self.give_planner_settings(false, "Stored settings retrieved"),
            502 => self.give_planner_settings(true, "Hardcoded default settings loaded"),
            _ => {
                self.report_planner_settings(out);
                Ok(Some(""))
            }
        };
        match done {
            Ok(None) => {
                self.link.held_line = LineBuf::new(bytes);
                self.link.held = Some(Held::Line);
            }
            Ok(Some(message)) => {
                if !message.is_empty() {
                    let _ = wire::reply(out, &Reply::Echo(message));
                }
                self.stats.executed = self.stats.executed.wrapping_add(1);
                self.ok(out);
            }
            Err(r) => self.refuse(&r, out),
        }
        true
    }

    /// `M500`.
    fn store_planner_settings(&mut self) -> Result<Option<&'static str>, Refusal> {
        let now = self.kernel.planner_settings();
        let mut failed = None;
        let settings = &mut self.settings;
        let storage = &mut self.storage;
        records(&now, |key, value| {
            let mut text = Text::<24>::new();
            let _ = super::settings::write_number(&mut text, value);
            match settings.set(key, text.as_str(), storage, &|c| c.validate()) {
                Ok(_) => true,
                Err(e) => {
                    failed = Some(Refusal::new(&e));
                    false
                }
            }
        });
        match failed {
            Some(r) => Err(r),
            None => Ok(Some("Settings stored")),
        }
    }

    /// `M501`, `M502`: the stored planner settings, or the defaults (no path limits), to the
    /// kernel; `None` while the machine is not idle.
    fn give_planner_settings(
        &mut self,
        defaults: bool,
        message: &'static str,
    ) -> Result<Option<&'static str>, Refusal> {
        let (machine, path) = if defaults {
            (self.settings.defaults(), PathLimits::NONE)
        } else {
            (self.settings.machine(), self.settings.path_limits())
        };
        match self.kernel.set_planner_settings(machine, path) {
            Ok(KernelReply::Busy) => Ok(None),
            Ok(_) => Ok(Some(message)),
            Err(e) => Err(text::command_refusal(&e, &self.letters())),
        }
    }

    /// `M503`: the settings as Marlin reports them, one `echo:` line each.
    fn report_planner_settings<W: Write>(&mut self, out: &mut W) {
        let s = self.kernel.planner_settings();
        let mut line = Text::<160>::new();
        let emit = |line: &mut Text<160>, out: &mut W| {
            let _ = wire::reply(out, &Reply::Echo(line.as_str()));
            *line = Text::new();
        };
        let axes = |line: &mut Text<160>, command: &str, values: &[f32; N]| {
            line.push("  ").push(command);
            for (&letter, &v) in s.letters.iter().zip(values) {
                line.push(" ").push_byte(letter).push_decimal(fixed(v, 2));
            }
        };
        line.push("; Steps per unit:");
        emit(&mut line, out);
        axes(&mut line, "M92", &s.steps_per_mm);
        emit(&mut line, out);
        line.push("; Max feedrates (units/s):");
        emit(&mut line, out);
        axes(&mut line, "M203", &s.max_rate_mm_s);
        emit(&mut line, out);
        line.push("; Max Acceleration (units/s2):");
        emit(&mut line, out);
        axes(&mut line, "M201", &s.max_accel_mm_s2);
        emit(&mut line, out);
        line.push(
            "; Acceleration (units/s2) (P<print-accel> R<retract-accel> T<travel-accel>), \
             none given: the per-axis limits alone:",
        );
        emit(&mut line, out);
        line.push("  M204");
        let p = s.path;
        for (letter, cap) in [
            ("P", p.print_accel_mm_s2),
            ("R", p.retract_accel_mm_s2),
            ("T", p.travel_accel_mm_s2),
        ] {
            if let Some(v) = cap {
                line.push(" ").push(letter).push_decimal(fixed(v, 2));
            }
        }
        emit(&mut line, out);
        line.push("; Advanced (S<min_feedrate> T<min_travel_feedrate> J<junc_dev>):");
        emit(&mut line, out);
        line.push("  M205 S")
            .push_decimal(fixed(p.min_extruding_feed_mm_s, 2));
        line.push(" T")
            .push_decimal(fixed(p.min_travel_feed_mm_s, 2));
        line.push(" J")
            .push_decimal(fixed(s.junction_deviation_mm, 3));
        emit(&mut line, out);
    }
}
