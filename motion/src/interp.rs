//! The G-code interpreter: modal state and the meaning of each supported command.
//!
//! Thread side. Positions are kept exactly, in integer nanometres, so that relative moves,
//! `G92` offsets and inch conversions never accumulate rounding; step targets are rounded from
//! them once per move. The interpreter only decides what a line means ([`Action`]); the kernel
//! checks it (soft limits, state) and commits it, so a refused line leaves no trace.
//!
//! | command | meaning |
//! |---|---|
//! | `G0`, `G1` | straight move (rapid, or at `F`; an `F` on the `G1` line is reached within the move) |
//! | `G2`, `G3` | clockwise / counter-clockwise arc, `I`/`J`/`K` centre offsets or `R` radius; `G17`/`G18`/`G19` pick the plane |
//! | `G4` | dwell `P` ms or `S` s |
//! | `G20`, `G21` | inches, millimetres |
//! | `G28` | home all axes, or those named (bare letters or values, which are ignored; Prusa's `W` changes nothing) |
//! | `G90`, `G91` | absolute, relative |
//! | `G92` | set the current position (all axes to 0 without words) |
//! | `G93`, `G94` | feed in inverse time (each feed move's `F` is moves per minute), in units per minute (`G95` is refused) |
//! | `G10 L2 P`, `G10 L20 P` | set the origin of work coordinate system `P` (1–9, 0 the active one): to the values (`L2`), or so that the position now reads as the values (`L20`) |
//! | `G40`, `G64`, `G61`, `G61.1` | no cutter compensation, path blending, exact stop (each move ends at rest) |
//! | `G38.2`–`G38.5` | probe towards the target: stop on contact (`.2`, `.3`) or on loss of contact (`.4`, `.5`); `.2` and `.4` are an alarm when the probe never changes. At the feed, not overridden; the kernel takes nothing else until the probe is over and goes on from where it stopped |
//! | `G81`, `G82`, `G83`, `G80` | drilling cycles at each line's X/Y in the XY plane: drill, drill and dwell `P` seconds, peck drill by `Q` (module `drill`); `R` and `Z` (and `P`, `Q`) kept from line to line; `G80` ends the cycle mode and leaves no motion mode |
//! | `G98`, `G99` | after each hole, back to the Z the cycle started at (or `R` if higher), to `R` |
//! | `G43.1 Z`, `G49` | dynamic tool length offset on Z, none |
//! | `G53` | this line's move in machine coordinates |
//! | `G54`–`G59`, `G59.1`–`G59.3` | select a work coordinate system |
//! | `G28.1`, `G30.1` | store the position now (grbl's `G28`/`G30` go there) |
//! | `G92.1` | clear the `G92` offset |
//! | `M2`, `M30` | end of program: after the motion before it, `G1`, `G17`, `G90`, `G94` and the spindle off (`M30` with a file name is RepRap's delete file, a storage effect) |
//! | `M82`, `M83` | extruder absolute, relative |
//! | `M17`, `M18`, `M84` | motors on, off (`M18`/`M84` with axis letters: those axes) |
//! | `M92` | set steps per unit |
//! | `M0` (grbl dialect), `M6` | pause until cycle start (`M6`: for a manual tool change, naming `T`) |
//! | `M62`–`M65` | outputs on/off with the motion (`M62`/`M63`) or at once (`M64`/`M65`), as [`crate::Effect::Output`] |
//! | `M201`, `M203` | maximum acceleration (mm/s²), maximum feed rate (mm/s) of the named axes |
//! | `M204` | acceleration along the path: `P` printing, `R` retracting, `T` travel moves, `S` printing and travel (mm/s²) |
//! | `M205` | `J` junction deviation (mm), `S` and `T` the slowest extruding and travel feeds (mm/s); the jerks `X Y Z E` and `B` are checked and left out |
//! | `M220` | feed-rate override, percent (`S`); `B` backs it up, `R` restores it |
//! | `M221` | flow of the extruders, percent (`S`); `T` names one extruder |
//! | `M114` | report position |
//! | `M0`, `M112`, `M226` | stop, emergency stop, pause |
//! | `M3`–`M5`, `M7`–`M9`, `M73`, `M104`–`M107`, `M109`, `M110`, `M113`, `M115`–`M119`, `M140`, `M155`, `M190`, `M400`, `M410`, `M20`–`M30`, `M32`, `T` | returned as [`crate::Effect`]s |
//! | `M900` | linear advance: `K0` (none, what this planner does) is taken, another factor refused |
//! | `M42`, `M80`, `M81`, `M141` | an output, the power supply, the chamber: returned as [`crate::Effect`]s |
//! | `M300` | a tone of the beeper, `S` Hz (260; 0: a pause) for `P` ms (1000, at most 5000): returned as an [`crate::Effect`] |
//!
//! ## Planner settings and overrides
//!
//! `M201`, `M203`, `M204` and `M205` come back as [`Action::SetLimits`]: the kernel plans the
//! moves after the line with them (Marlin's order: the moves queued before keep theirs). Values
//! are in the current unit (`G20`: inches, so that `M203 X1` is 25.4 mm/s), as Marlin reads
//! them; each must be a finite number, positive for accelerations and rates, not negative for
//! `M205`. The planner uses junction deviation, so `M205` takes what Marlin takes without
//! `CLASSIC_JERK`: `J`, `S` and `T`. The classic jerks (`X`, `Y`, `Z`, `E` and any other axis
//! letter) do not apply to a junction-deviation planner and `B` (the shortest segment time,
//! which Marlin's `SLOWDOWN` stretches short segments to) has no counterpart here: they are
//! checked, then left out.
//!
//! `M220` (feed) and `M221` (flow) are overrides kept in the interpreter's state and apply to
//! the moves of later lines, not to moves already queued. The feed override scales the feed of
//! every later G-code move, `G0` included (its maximum rate), when the move is planned; the
//! axes' maximum rates still cap it. The flow override scales the filament an extruder feeds:
//! its machine position moves by the commanded distance × flow while its work position (what
//! `M114` reports) advances by the commanded distance, in absolute and relative extrusion
//! alike; the `G92` offset takes the difference, so `G92 E0` after a flow change sets the
//! reported position and the motor goes on from where it is (Marlin's `e_factor`). Both are
//! integer percentages from 1 to [`MAX_PERCENT`], 100 at power-on and after a reset.

use forja_protocol::gcode::{Decimal, Line, pow10};

use crate::arc::{ArcCenter, ArcCutter, Nm};
use crate::config::{AxisKind, MachineConfig};
use crate::coords::{Coordinates, SYSTEMS, Slot};
use crate::drill::{DrillCycle, DrillKind};
use crate::effect::{Coolant, Effect, Heater, Spindle, StopKind, Storage, TemperatureWait};
use crate::error::CommandError;
use crate::planner::{PathLimits, times};

/// Nanometres per millimetre: positions are kept in integer nanometres.
pub const NM_PER_MM: f64 = 1e6;

/// `mm` in nanometres, rounded. Not on the per-line path (it converts limits and homing
/// distances); out of line, its hundred bytes of software double precision and saturation are
/// in the image once.
#[inline(never)]
pub(crate) fn mm_to_nm(mm: f32) -> Nm {
    libm::round(f64::from(mm) * NM_PER_MM) as Nm
}
/// The largest `M220`/`M221` percentage accepted (the top of Marlin's display range): a tenfold
/// feed or flow is the most a line may ask for.
pub(crate) const MAX_PERCENT: u32 = 999;
/// Largest position magnitude accepted, nm (100 m).
const MAX_NM: i64 = 100_000_000_000;
/// The slowest feed accepted, mm/min (grblHAL's `MINIMUM_FEED_RATE`): slower `F` words are
/// refused. Faster ones are capped by the axes' maximum rates when the move is planned.
pub(crate) const MIN_FEED_MM_MIN: f32 = 1.0;
/// The pitch of an `M300` without `S`, Hz (Marlin's).
const TONE_HZ: u16 = 260;
/// The length of an `M300` without `P`, ms (Marlin's).
const TONE_MS: u16 = 1000;
/// The highest `M300` pitch accepted, Hz: the top of human hearing. Higher `S` words are
/// refused.
const MAX_TONE_HZ: u32 = 20_000;
/// The longest `M300` tone, ms: longer `P` words are cut to it, as Marlin cuts them.
const MAX_TONE_MS: i64 = 5000;

/// What one line asks for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Action<'l, const N: usize> {
    /// Only modal state changed.
    None,
    /// A straight move to machine position `target` (nm).
    Move {
        target: [Nm; N],
        feed_mm_min: Option<f32>,
        ramp: bool,
    },
    /// An arc; chords follow from the cutter.
    Arc {
        cutter: ArcCutter<N>,
        feed_mm_min: f32,
        ramp: bool,
    },
    /// Wait at rest.
    Dwell { ms: u32 },
    /// Home these axes.
    Home { mask: u8 },
    /// Report the position.
    Report,
    /// New steps per unit for some axes.
    SetStepsPerMm([Option<f32>; N]),
    /// New planner limits for the moves planned after the line.
    SetLimits(LimitChange<N>),
    /// For the controller.
    Effect(Effect<'l>),
    /// `G10`, `G28.1`, `G30.1`: new positions for a slot of the coordinate table.
    SetCoordinates { slot: Slot, values: [Nm; N] },
    /// `M0` / `M112`.
    Stop(StopKind),
    /// `M226`, grbl's `M0`.
    Pause,
    /// `M6`: pause for a manual tool change.
    ToolChange(Option<u8>),
    /// grbl's `G28`/`G30`: a rapid to `via`, then to `target`.
    Via { via: [Nm; N], target: [Nm; N] },
    /// `G38.2`–`G38.5`: a move towards `target` that the probe ends.
    Probe {
        target: [Nm; N],
        feed_mm_min: f32,
        /// `G38.4`/`G38.5`: until the probe loses contact (else until it touches).
        away: bool,
        /// `G38.2`/`G38.4`: reaching the target without the probe changing is an alarm.
        must_trip: bool,
    },
    /// `G81`–`G83`: one hole's canned cycle.
    Drill {
        cycle: DrillCycle<N>,
        feed_mm_min: f32,
    },
}

/// A change of the planner's limits (`M201`, `M203`, `M204`, `M205`); `None` leaves a value as
/// it is. Values are checked for their form (finite, positive or not negative) by the
/// interpreter, against the machine by the kernel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum LimitChange<const N: usize> {
    /// `M201`: maximum acceleration of the named axes, mm/s².
    AxisAccel([Option<f32>; N]),
    /// `M203`: maximum rate of the named axes, mm/min (converted from Marlin's mm/s).
    AxisRate([Option<f32>; N]),
    /// `M204`: acceleration along the path by kind of move, mm/s².
    PathAccel {
        /// `P`, or `S`: printing moves.
        print: Option<f32>,
        /// `R`: retracting moves.
        retract: Option<f32>,
        /// `T`, or `S`: travel moves.
        travel: Option<f32>,
    },
    /// `M205`: junction deviation and the slowest feeds.
    Junction {
        /// `J`, mm.
        deviation_mm: Option<f32>,
        /// `S`: the slowest feed of extruding moves, mm/s.
        min_extruding_feed_mm_s: Option<f32>,
        /// `T`: the slowest feed of travel moves, mm/s.
        min_travel_feed_mm_s: Option<f32>,
    },
}

impl<const N: usize> LimitChange<N> {
    /// The change made to `config` and `limits` (the caller validates the configuration it
    /// makes). An `M203` rate below an axis's homing speeds lowers them to it (Marlin's planner
    /// caps homing moves the same way).
    pub(crate) fn apply(&self, config: &mut MachineConfig<N>, limits: &mut PathLimits) {
        match *self {
            LimitChange::AxisAccel(values) => {
                for (a, v) in config.axes.iter_mut().zip(values) {
                    if let Some(v) = v {
                        a.accel_mm_s2 = v;
                    }
                }
            }
            LimitChange::AxisRate(values) => {
                for (a, v) in config.axes.iter_mut().zip(values) {
                    if let Some(v) = v {
                        a.max_rate_mm_min = v;
                        if let Some(h) = a.homing.as_mut() {
                            h.seek_mm_min = h.seek_mm_min.min(v);
                            h.locate_mm_min = h.locate_mm_min.min(h.seek_mm_min);
                        }
                    }
                }
            }
            LimitChange::PathAccel {
                print,
                retract,
                travel,
            } => {
                limits.print_accel_mm_s2 = print.or(limits.print_accel_mm_s2);
                limits.retract_accel_mm_s2 = retract.or(limits.retract_accel_mm_s2);
                limits.travel_accel_mm_s2 = travel.or(limits.travel_accel_mm_s2);
            }
            LimitChange::Junction {
                deviation_mm,
                min_extruding_feed_mm_s,
                min_travel_feed_mm_s,
            } => {
                if let Some(d) = deviation_mm {
                    config.junction_deviation_mm = d;
                }
                if let Some(f) = min_extruding_feed_mm_s {
                    limits.min_extruding_feed_mm_s = f;
                }
                if let Some(f) = min_travel_feed_mm_s {
                    limits.min_travel_feed_mm_s = f;
                }
            }
        }
    }
}

/// Active plane for arcs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Plane {
    Xy,
    Zx,
    Yz,
}

/// Modal motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Motion {
    Rapid,
    Linear,
    Cw,
    Ccw,
    /// `G38.2`–`G38.5`.
    Probe {
        away: bool,
        must_trip: bool,
    },
    /// `G81`–`G83`.
    Cycle(DrillKind),
    /// `G80`: none; a line of axis words alone is refused.
    Cancelled,
}

/// The words of the drilling cycles, kept from line to line while a cycle is the motion mode
/// (LinuxCNC's and grblHAL's sticky `R`, `Z`, `P`, `Q`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct CycleWords {
    /// `G99`: retract to the `R` plane; else (`G98`, the default) to the higher of it and the
    /// Z where the cycle began.
    to_r_plane: bool,
    /// Where Z was (machine nm) when the cycle mode began.
    initial_z: Nm,
    /// `R`, nm, as given (work Z under `G90`, from the Z before the hole under `G91`).
    retract: Option<Nm>,
    /// `Z`, nm, as given (work Z under `G90`, from `R` under `G91`).
    bottom: Option<Nm>,
    /// `Q`: the depth of one `G83` peck, nm.
    peck: Option<Nm>,
    /// `P`: the `G82` dwell, ms.
    dwell_ms: u32,
}

/// The interpreter's state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Interpreter<const N: usize> {
    /// Commanded machine position, nm.
    pub(crate) pos: [Nm; N],
    /// The `G92` offset: work = machine − origin of the active system − tool length offset +
    /// `offset`.
    offset: [Nm; N],
    /// The active work coordinate system, 0 for `G54`.
    wcs_index: u8,
    /// Its origin, machine nm.
    wcs: [Nm; N],
    /// The tool length offset (`G43.1`), nm, on the Z axis.
    tlo_nm: Nm,
    /// `G61`: every move ends at rest.
    pub(crate) exact_stop: bool,
    /// `G93`: a feed move's `F` is the inverse of its duration in minutes.
    inverse_time: bool,
    /// grbl's meanings where the dialects differ: `G28`/`G30` go to the stored positions,
    /// `G4 P` is in seconds, `M0` pauses until cycle start.
    pub(crate) grbl: bool,
    absolute: bool,
    extruder_relative: Option<bool>,
    inches: bool,
    motion: Motion,
    /// The drilling cycles' words.
    cycle: CycleWords,
    plane: Plane,
    pub(crate) feed_mm_min: f32,
    /// The last `F` word taken.
    feed_word: Option<FeedWord>,
    /// The spindle speed (`S`), rpm: of `M3`/`M4` without `S`, and carried by the moves
    /// planned while it is in force (an `S` on a motion line changes it with that motion).
    spindle_rpm: u32,
    /// Feed-rate override (`M220`), percent.
    feed_percent: u16,
    /// What `M220 B` backed up and `M220 R` restores, percent.
    feed_percent_backup: u16,
    /// Flow override (`M221`) of each axis, percent: only an extruder's is ever other than 100.
    flow_percent: [u16; N],
}

/// The interpreter's state in force beside a spare that a line is interpreted into
/// ([`Staged::stage`]). Taking the line makes the spare the state in force
/// ([`Staged::commit`]), with no copy back; refusing it leaves the state in force as it was.
/// A line costs one copy of the state, where a copy to work on and a copy to keep made two.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Staged<const N: usize> {
    slots: [Interpreter<N>; 2],
    /// The slot of the state in force (0 or 1); the other is the spare.
    live: usize,
}

impl<const N: usize> Staged<N> {
    /// `state` in force.
    pub(crate) const fn new(state: Interpreter<N>) -> Self {
        Self {
            slots: [state, state],
            live: 0,
        }
    }

    /// The state in force.
    pub(crate) const fn live(&self) -> &Interpreter<N> {
        &self.slots[self.live & 1]
    }

    /// The state in force, to change in place (outside a line's interpretation).
    pub(crate) const fn live_mut(&mut self) -> &mut Interpreter<N> {
        &mut self.slots[self.live & 1]
    }

    /// The spare, made a copy of the state in force: the state a line is interpreted into.
    pub(crate) const fn stage(&mut self) -> &mut Interpreter<N> {
        let live = self.live & 1;
        self.slots[live ^ 1] = self.slots[live];
        &mut self.slots[live ^ 1]
    }

    /// The spare as the last [`Staged::stage`] left it: the state after the line.
    pub(crate) const fn staged(&self) -> &Interpreter<N> {
        &self.slots[(self.live & 1) ^ 1]
    }

    /// The spare becomes `state` (a state interpreted apart), without the copy of the state in
    /// force that [`Staged::stage`] makes.
    pub(crate) const fn stage_as(&mut self, state: &Interpreter<N>) {
        self.slots[(self.live & 1) ^ 1] = *state;
    }

    /// The staged state is taken: it is the state in force from now on.
    pub(crate) const fn commit(&mut self) {
        self.live ^= 1;
    }
}

/// A number in nm from a decimal in the current unit, rounded to the nearest nm (halves away
/// from zero), exact, in 64-bit integers: a multiplication when the decimal has at most six
/// digits after the point (five in inches), else a division into whole nm and the rest. A
/// value beyond [`MAX_NM`] is refused, as is one whose rest the integers cannot hold (only
/// beyond [`forja_protocol::gcode::MAX_SCALE`] digits, which no line carries).
pub(crate) fn to_nm(v: Decimal, inches: bool, letter: u8) -> Result<Nm, CommandError> {
    let bad = CommandError::BadValue { letter };
    // nm per unit = factor × 10^exponent: 10^6 for a mm, 254 × 10^5 for an inch.
    let (factor, exponent) = if inches { (254u64, 5u8) } else { (1, 6) };
    let magnitude = v.mantissa().unsigned_abs();
    let pow10 = |k: u8| pow10(k).map(i64::unsigned_abs);
    let nm = if v.scale() <= exponent {
        pow10(exponent - v.scale()).and_then(|up| magnitude.checked_mul(factor * up))
    } else {
        // Whole nm and the rest, which rounds half up: the rest times the factor is below
        // 10^13 × 254 for any decimal of a line.
        pow10(v.scale() - exponent).and_then(|den| {
            let whole = (magnitude / den).checked_mul(factor)?;
            let rest = (magnitude % den).checked_mul(factor)?;
            whole.checked_add((rest + den / 2) / den)
        })
    };
    match nm {
        Some(nm) if nm <= MAX_NM.unsigned_abs() => {
            let nm = nm.cast_signed();
            Ok(if v.is_negative() { -nm } else { nm })
        }
        _ => Err(bad),
    }
}

/// [`to_nm`] in `i128`, the reference its tests compare with.
#[cfg(test)]
fn wide_to_nm(v: Decimal, inches: bool) -> Option<Nm> {
    let per_unit: i128 = if inches { 25_400_000 } else { 1_000_000 };
    let num = i128::from(v.mantissa()) * per_unit;
    let den = 10i128.checked_pow(u32::from(v.scale()))?;
    let half = den / 2;
    let q = if num >= 0 {
        (num + half) / den
    } else {
        (num - half) / den
    };
    i64::try_from(q).ok()
}

/// Steps for a machine position in nm: `nm × steps_per_mm / 10⁶`, rounded half away from zero.
///
/// Computed exactly in integers over the float's exact value `m × 2^e` (a 24-bit `m`), which
/// a 32-bit core does in a few dozen instructions where software double precision takes
/// hundreds; a value the integers cannot hold (beyond any machine's travel) goes through
/// double precision.
pub(crate) fn nm_to_steps(nm: Nm, steps_per_mm: f32) -> i32 {
    exact_nm_to_steps(nm, steps_per_mm).unwrap_or_else(|| {
        let s = libm::round(nm as f64 * f64::from(steps_per_mm) / NM_PER_MM);
        s.clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
    })
}

/// [`nm_to_steps`] in integers, `None` when they cannot hold the product or the rate is not a
/// positive normal float.
fn exact_nm_to_steps(nm: Nm, steps_per_mm: f32) -> Option<i32> {
    /// Nanometres per millimetre, as the divisor.
    const NM: u64 = 1_000_000;
    let bits = steps_per_mm.to_bits();
    let biased = (bits >> 23) & 0xFF;
    if bits >> 31 != 0 || biased == 0 || biased == 0xFF {
        return None;
    }
    // steps_per_mm = m × 2^e exactly; trailing zeros moved into e keep the product small.
    let raw = (bits & 0x7F_FFFF) | 0x80_0000;
    let zeros = raw.trailing_zeros();
    let m = u64::from(raw >> zeros);
    let e = biased.cast_signed() - 150 + zeros.cast_signed();
    let product = nm.unsigned_abs().checked_mul(m)?;
    // round(p × 2^e / 10⁶) = floor((p × 2^e + 10⁶/2) / 10⁶), and for e < 0
    // floor(floor((p + 10⁶/2 × 2^-e) / 2^-e) / 10⁶): nested floors of a non-negative value.
    let shifted = if e >= 0 {
        let up = product.checked_shl(e.cast_unsigned())?;
        (up >> e.cast_unsigned() == product)
            .then_some(up)?
            .checked_add(NM / 2)?
    } else {
        let k = e.unsigned_abs();
        if k >= 40 {
            return None;
        }
        product.checked_add((NM / 2) << k)? >> k
    };
    if shifted >= (1u64 << 31) * NM {
        return None;
    }
    let steps = millionths(shifted).cast_signed();
    Some(if nm < 0 { -steps } else { steps })
}

/// `t / 10⁶` for a `t` below `2³¹ × 10⁶`, in two 32-bit divisions, where a 64-bit division is
/// a library call of a hundred instructions or more on a 32-bit core: `10⁶ = 2⁶ × 15,625`,
/// and the quotient by 15,625 (below 2¹⁴) is long division in two digits of base 2¹⁴.
fn millionths(t: u64) -> u32 {
    const ODD: u32 = 15_625;
    // Below 2³¹ × 15,625 < 2⁴⁵: its top digit is below 2³¹.
    let u = t >> 6;
    let top = (u >> 14) as u32;
    let (q1, r1) = (top / ODD, top % ODD);
    // Below 15,625 × 2¹⁴ < 2²⁸.
    let low = (r1 << 14) | (u as u32 & 0x3FFF);
    (q1 << 14) + low / ODD
}

/// Nanometres for a step count.
pub(crate) fn steps_to_nm(steps: i32, steps_per_mm: f32) -> Nm {
    libm::round(f64::from(steps) / f64::from(steps_per_mm) * NM_PER_MM) as Nm
}

/// An `F` word converted to mm/min in the unit it was read in, kept: programs repeat the same
/// `F` move after move, and its conversion is a division and a comparison in software on
/// RISC-V. A cache of a pure function, holding a valid feed only: it needs no clearing.
#[derive(Debug, Clone, Copy, PartialEq)]
struct FeedWord {
    word: Decimal,
    inches: bool,
    mm_min: f32,
}

/// What a G code with one decimal is numbered as in the interpreter: ten times the code plus
/// the decimal, after this (so that `G28.1` is not `G281`).
const DECIMAL_CODE: u32 = 100_000;
/// `G28.1`.
const G28_1: u32 = DECIMAL_CODE + 281;
/// `G30.1`.
const G30_1: u32 = DECIMAL_CODE + 301;
/// `G38.2`.
const G38_2: u32 = DECIMAL_CODE + 382;
/// `G38.4`.
const G38_4: u32 = DECIMAL_CODE + 384;
/// `G38.5`.
const G38_5: u32 = DECIMAL_CODE + 385;
/// `G43.1`.
const G43_1: u32 = DECIMAL_CODE + 431;
/// `G59.1`.
const G59_1: u32 = DECIMAL_CODE + 591;
/// `G59.3`.
const G59_3: u32 = DECIMAL_CODE + 593;
/// `G61.1`.
const G61_1: u32 = DECIMAL_CODE + 611;
/// `G92.1`.
const G92_1: u32 = DECIMAL_CODE + 921;

/// The straight distance from `a` to `b`, mm, over every axis.
fn distance_mm<const N: usize>(a: &[Nm; N], b: &[Nm; N]) -> f64 {
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(a, b)| {
            let d = b.saturating_sub(*a) as f64 / NM_PER_MM;
            d * d
        })
        .sum();
    libm::sqrt(sum)
}

fn set_once<T>(slot: &mut Option<T>, v: T) -> Result<(), CommandError> {
    if slot.is_some() {
        return Err(CommandError::ModalConflict);
    }
    *slot = Some(v);
    Ok(())
}

/// The `S` of `M3`/`M4`: a speed, never negative. Above the spindle's maximum, the spindle
/// driver caps it, as grbl does.
fn spindle_speed(s: Option<Decimal>) -> Result<Option<Decimal>, CommandError> {
    match s {
        Some(v) if v.mantissa() < 0 || v.to_f64() > f64::from(u32::MAX) => {
            Err(CommandError::BadValue { letter: b'S' })
        }
        other => Ok(other),
    }
}

/// The rpm of a checked `S` word ([`spindle_speed`]), rounded.
fn rpm_of(s: Decimal) -> u32 {
    libm::round(s.to_f64()).clamp(0.0, f64::from(u32::MAX)) as u32
}

/// The `G28` flags that are not axes and change nothing here: Prusa's `W` (home without mesh
/// levelling; there is no mesh).
const HOMING_FLAGS: &[u8] = b"W";

/// Refuse a word that is neither an axis of the machine, `G`/`F`, nor one of `flags` (for
/// `G28`, `G92`).
fn only_axis_words<const N: usize>(
    line: &Line<'_>,
    config: &MachineConfig<N>,
    flags: &[u8],
) -> Result<(), CommandError> {
    for w in line.words() {
        let flag = w.bare && flags.contains(&w.letter);
        if !matches!(w.letter, b'G' | b'F') && !flag && config.axis_index(w.letter).is_none() {
            return Err(CommandError::UnknownAxis { letter: w.letter });
        }
    }
    Ok(())
}

/// The mask of every axis of an `N`-axis machine (`N` ≤ 8).
fn all_axes<const N: usize>() -> u8 {
    ((1u16 << N.min(8)) - 1) as u8
}

fn small_int(v: Decimal, letter: u8, max: u32) -> Result<u32, CommandError> {
    v.as_u32()
        .filter(|n| *n <= max)
        .ok_or(CommandError::BadValue { letter })
}

/// An `M220`/`M221` percentage: an integer from 1 to [`MAX_PERCENT`].
fn percent(v: Decimal, letter: u8) -> Result<u16, CommandError> {
    match small_int(v, letter, MAX_PERCENT)? {
        0 => Err(CommandError::BadValue { letter }),
        p => Ok(p as u16),
    }
}

/// A setting in millimetres (or mm/s, mm/s²) from a decimal in the current unit, refused as
/// `letter` unless finite and above 0 (`positive`) or not below 0.
fn setting(v: Decimal, inches: bool, letter: u8, positive: bool) -> Result<f32, CommandError> {
    let x = v.to_f32() * if inches { 25.4 } else { 1.0 };
    let ok = x.is_finite() && if positive { x > 0.0 } else { x >= 0.0 };
    if ok {
        Ok(x)
    } else {
        Err(CommandError::BadValue { letter })
    }
}

/// Refuse a word other than `G`, `M` and the letters of `allowed`.
fn only_words(line: &Line<'_>, allowed: &[u8]) -> Result<(), CommandError> {
    match line
        .words()
        .iter()
        .find(|w| !matches!(w.letter, b'G' | b'M') && !allowed.contains(&w.letter))
    {
        Some(w) => Err(CommandError::UnknownAxis { letter: w.letter }),
        None => Ok(()),
    }
}

/// `nm × percent / 100`, rounded to the nearest nanometre (halves away from zero), saturating.
/// In 64-bit integers (an `i128` division costs a thousand bytes of code on a 32-bit core):
/// whole hundreds of nm scale exactly, and the rest (below 100) is rounded.
fn scale_nm(nm: Nm, percent: u16) -> Nm {
    let p = i64::from(percent);
    // Both parts have the sign of `nm`, so rounding the rest rounds the sum.
    let (hundreds, rest) = (nm / 100, nm % 100 * p);
    let rest = (rest + if rest < 0 { -50 } else { 50 }) / 100;
    hundreds
        .checked_mul(p)
        .map_or(if nm < 0 { i64::MIN } else { i64::MAX }, |whole| {
            whole.saturating_add(rest)
        })
}

impl<const N: usize> Interpreter<N> {
    /// Power-on state: absolute, millimetres, XY plane, rapid, the default feed.
    pub(crate) fn new(config: &MachineConfig<N>) -> Self {
        Self {
            pos: [0; N],
            offset: [0; N],
            wcs_index: 0,
            wcs: [0; N],
            tlo_nm: 0,
            exact_stop: false,
            inverse_time: false,
            grbl: false,
            absolute: true,
            extruder_relative: None,
            inches: false,
            motion: Motion::Rapid,
            cycle: CycleWords::default(),
            plane: Plane::Xy,
            feed_mm_min: config.default_feed_mm_min,
            feed_word: None,
            spindle_rpm: 0,
            feed_percent: 100,
            feed_percent_backup: 100,
            flow_percent: [100; N],
        }
    }

    /// The spindle speed in force (`S`), rpm.
    pub(crate) fn spindle_rpm(&self) -> u32 {
        self.spindle_rpm
    }

    /// The feed-rate override (`M220`), percent.
    pub(crate) fn feed_percent(&self) -> u16 {
        self.feed_percent
    }

    /// The modal state a parser-state report names.
    pub(crate) fn modal(&self) -> crate::kernel::ModalReport<N> {
        crate::kernel::ModalReport {
            motion: match self.motion {
                Motion::Rapid => "G0",
                Motion::Linear => "G1",
                Motion::Cw => "G2",
                Motion::Ccw => "G3",
                Motion::Probe {
                    away: false,
                    must_trip: true,
                } => "G38.2",
                Motion::Probe {
                    away: false,
                    must_trip: false,
                } => "G38.3",
                Motion::Probe {
                    away: true,
                    must_trip: true,
                } => "G38.4",
                Motion::Probe {
                    away: true,
                    must_trip: false,
                } => "G38.5",
                Motion::Cycle(DrillKind::Drill) => "G81",
                Motion::Cycle(DrillKind::Dwell) => "G82",
                Motion::Cycle(DrillKind::Peck) => "G83",
                Motion::Cancelled => "G80",
            },
            plane: match self.plane {
                Plane::Xy => 17,
                Plane::Zx => 18,
                Plane::Yz => 19,
            },
            inches: self.inches,
            absolute: self.absolute,
            feed_mm_min: self.feed_mm_min,
            coordinate_system: self.wcs_index,
            exact_stop: self.exact_stop,
            tool_length_nm: self.tlo_nm,
            g92_nm: core::array::from_fn(|i| -self.offset[i]),
        }
    }

    /// The machine position of work zero on axis `i`: work = machine − origin.
    fn origin(&self, i: usize, z: Option<usize>) -> Nm {
        let tlo = if z == Some(i) { self.tlo_nm } else { 0 };
        self.wcs[i]
            .saturating_add(tlo)
            .saturating_sub(self.offset[i])
    }

    /// Take the origins of `coords` for the active system (after they changed or were loaded).
    pub(crate) fn use_coordinates(&mut self, coords: &Coordinates<N>) {
        self.wcs = coords.system(usize::from(self.wcs_index));
    }

    /// The feed-rate override as a factor, for the moves of the lines interpreted now.
    #[inline]
    pub(crate) fn feed_scale(&self) -> f32 {
        // 100 % (no override, nearly always) without the division, a call where floats are
        // software: the same 1.0.
        if self.feed_percent == 100 {
            1.0
        } else {
            f32::from(self.feed_percent) / 100.0
        }
    }

    /// The flow override (`M221`) of each axis, percent (100 for axes that are not extruders).
    pub(crate) fn flow_percent(&self) -> [u16; N] {
        self.flow_percent
    }

    /// End of program (`M2`, `M30`): the modal groups that grbl and LinuxCNC reset go back to
    /// their defaults — linear motion (`G1`), the XY plane (`G17`), absolute distances
    /// (`G90`), units-per-minute feed (`G94`, the only mode) — while units (`G20`/`G21`), the
    /// feed rate, the extruder mode and the `G92` offsets are kept, as grbl keeps them. The
    /// spindle is stopped by the controller ([`Effect::ProgramEnd`]).
    fn end_program(&mut self) {
        self.motion = Motion::Linear;
        self.plane = Plane::Xy;
        self.absolute = true;
    }

    /// Back to the power-on modal state, keeping the position and clearing offsets; the
    /// overrides go back to 100 %.
    pub(crate) fn reset_modal(&mut self, config: &MachineConfig<N>, coords: &Coordinates<N>) {
        let (pos, grbl) = (self.pos, self.grbl);
        *self = Self::new(config);
        self.pos = pos;
        self.grbl = grbl;
        self.use_coordinates(coords);
    }

    /// The commanded position in work coordinates, nm, on a machine whose Z axis (for the tool
    /// length offset) is `z`.
    pub(crate) fn work_position(&self, z: Option<usize>) -> [Nm; N] {
        core::array::from_fn(|i| self.pos[i].saturating_sub(self.origin(i, z)))
    }

    /// Interpret one line, updating the modal state of `self` (the caller works on a copy and
    /// keeps it only when the action is accepted).
    pub(crate) fn interpret<'l>(
        &mut self,
        line: &Line<'l>,
        config: &MachineConfig<N>,
        coords: &Coordinates<N>,
    ) -> Result<Action<'l, N>, CommandError> {
        let mut command: Option<(u8, u32)> = None;
        let mut system: Option<u8> = None;
        let mut machine_coords = false;
        let mut path: Option<bool> = None;
        let mut tool_length: Option<()> = None;
        let mut motion: Option<Motion> = None;
        let mut units: Option<bool> = None;
        let mut distance: Option<bool> = None;
        let mut plane: Option<Plane> = None;
        let mut feed_mode: Option<bool> = None;
        let mut retract_mode: Option<bool> = None;
        // A word given twice (`X5 X50`, or `X0x10` read as `X0 X10`) has no single meaning;
        // G and M words may repeat across modal groups (checked below).
        for (i, w) in line.words().iter().enumerate() {
            let earlier = line.words().get(..i).unwrap_or(&[]);
            if !matches!(w.letter, b'G' | b'M') && earlier.iter().any(|e| e.letter == w.letter) {
                return Err(CommandError::RepeatedWord { letter: w.letter });
            }
        }
        // `T` beside an `M` word is that command's tool (`M104 T0 S0`, `M204 P R T`).
        let has_m = line.words().iter().any(|w| w.letter == b'M');
        for w in line.words() {
            if !matches!(w.letter, b'G' | b'M' | b'T') || (w.letter == b'T' && has_m) {
                continue;
            }
            // A G code may have one decimal (`G59.1`, `G28.1`, `G43.1`): `n` is then ten times
            // the code plus it (591, 281, 431), an integer code as it is.
            let number = match (w.letter, w.value.scale()) {
                (_, 0) => w.value.as_u32(),
                (b'G', 1) => u32::try_from(w.value.mantissa())
                    .ok()
                    .filter(|m| m % 10 != 0)
                    .map(|m| DECIMAL_CODE + m),
                _ => None,
            };
            let Some(n) = number else {
                return Err(CommandError::Unsupported {
                    letter: w.letter,
                    number: None,
                });
            };
            match (w.letter, n) {
                (b'G', 54..=59) => set_once(&mut system, (n - 54) as u8)?,
                (b'G', G59_1..=G59_3) => set_once(&mut system, (n - G59_1 + 6) as u8)?,
                (b'G', 53) => machine_coords = true,
                (b'G', 40) => {}
                (b'G', 80) => set_once(&mut motion, Motion::Cancelled)?,
                (b'G', 81) => set_once(&mut motion, Motion::Cycle(DrillKind::Drill))?,
                (b'G', 82) => set_once(&mut motion, Motion::Cycle(DrillKind::Dwell))?,
                (b'G', 83) => set_once(&mut motion, Motion::Cycle(DrillKind::Peck))?,
                (b'G', 98) => set_once(&mut retract_mode, false)?,
                (b'G', 99) => set_once(&mut retract_mode, true)?,
                (b'G', G38_2..=G38_5) => set_once(
                    &mut motion,
                    Motion::Probe {
                        away: n >= G38_4,
                        must_trip: n == G38_2 || n == G38_4,
                    },
                )?,
                (b'G', 64) => set_once(&mut path, false)?,
                (b'G', 61) => set_once(&mut path, true)?,
                (b'G', G61_1) => set_once(&mut path, true)?,
                (b'G', 49) => set_once(&mut tool_length, ())?,
                (b'G', 0) => set_once(&mut motion, Motion::Rapid)?,
                (b'G', 1) => set_once(&mut motion, Motion::Linear)?,
                (b'G', 2) => set_once(&mut motion, Motion::Cw)?,
                (b'G', 3) => set_once(&mut motion, Motion::Ccw)?,
                (b'G', 17) => set_once(&mut plane, Plane::Xy)?,
                (b'G', 18) => set_once(&mut plane, Plane::Zx)?,
                (b'G', 19) => set_once(&mut plane, Plane::Yz)?,
                (b'G', 20) => set_once(&mut units, true)?,
                (b'G', 21) => set_once(&mut units, false)?,
                (b'G', 90) => set_once(&mut distance, true)?,
                (b'G', 91) => set_once(&mut distance, false)?,
                // Units per minute: the only feed mode, so stating it changes nothing. Inverse
                // time (`G93`) and units per revolution (`G95`) fall through as unsupported.
                (b'G', 93) => set_once(&mut feed_mode, true)?,
                (b'G', 94) => set_once(&mut feed_mode, false)?,
                (b'G', 4 | 10 | 28 | 30 | 92) | (b'M', _) | (b'T', _) => {
                    set_once(&mut command, (w.letter, n))?;
                }
                (b'G', G28_1 | G30_1 | G43_1 | G92_1) => set_once(&mut command, (w.letter, n))?,
                (letter, n) => {
                    return Err(CommandError::Unsupported {
                        letter,
                        // A code with a decimal is named by its letter alone.
                        number: (n < DECIMAL_CODE).then_some(n),
                    });
                }
            }
        }
        if motion.is_some() && command.is_some() {
            return Err(CommandError::ModalConflict);
        }
        // `G53` moves in machine coordinates, and only with `G0` or `G1`.
        let moving = motion.unwrap_or(self.motion);
        if machine_coords
            && (command.is_some() || !matches!(moving, Motion::Rapid | Motion::Linear))
        {
            return Err(CommandError::ModalConflict);
        }
        // A letter alone is a flag only to the commands that take flags.
        if let Some(letter) = line.bare_letter()
            && !matches!(command, Some((b'G', 28) | (b'M', 18 | 84 | 220)))
        {
            return Err(CommandError::MissingValue { letter });
        }
        // Modal settings take effect first, for the whole line.
        if let Some(u) = units {
            self.inches = u;
        }
        if let Some(d) = distance {
            // Marlin's rule: `G90`/`G91` set every axis, the extruder's included; an `M82`/`M83`
            // after them sets the extruder alone.
            self.absolute = d;
            self.extruder_relative = None;
        }
        if let Some(p) = plane {
            self.plane = p;
        }
        if let Some(k) = system {
            self.wcs_index = k;
            self.use_coordinates(coords);
        }
        if let Some(exact) = path {
            self.exact_stop = exact;
        }
        if tool_length.is_some() {
            self.tlo_nm = 0;
        }
        if let Some(inverse) = feed_mode {
            self.inverse_time = inverse;
        }
        if let Some(to_r) = retract_mode {
            self.cycle.to_r_plane = to_r;
        }
        // In inverse time (`G93`) `F` is the line's own: moves per minute, not a modal rate.
        if let Some(f) = line.get(b'F').filter(|_| !self.inverse_time) {
            self.feed_mm_min = match self.feed_word {
                Some(kept) if kept.word == f && kept.inches == self.inches => kept.mm_min,
                _ => {
                    let per_min = times(f.to_f32(), if self.inches { 25.4 } else { 1.0 });
                    if !(per_min.is_finite() && per_min >= MIN_FEED_MM_MIN) {
                        return Err(CommandError::BadValue { letter: b'F' });
                    }
                    self.feed_word = Some(FeedWord {
                        word: f,
                        inches: self.inches,
                        mm_min: per_min,
                    });
                    per_min
                }
            };
        }
        match command {
            Some((letter, n)) => self.command(letter, n, line, config, coords),
            None => {
                // `S` without a command: the spindle speed, alone or with the line's motion.
                let speed = match spindle_speed(line.get(b'S'))? {
                    Some(s) => {
                        self.spindle_rpm = rpm_of(s);
                        Some(s)
                    }
                    None => None,
                };
                if let Some(m) = motion {
                    let was_cycle = matches!(self.motion, Motion::Cycle(_));
                    if let (Motion::Cycle(_), false) = (m, was_cycle) {
                        // A new cycle mode: its words start afresh, from where Z is now.
                        let z = config.axis_index(b'Z');
                        self.cycle = CycleWords {
                            to_r_plane: self.cycle.to_r_plane,
                            initial_z: z.map_or(0, |z| self.pos[z]),
                            ..CycleWords::default()
                        };
                    }
                    self.motion = m;
                }
                let has_axis = config.axes.iter().any(|a| line.has(a.letter));
                // An arc or a cycle stated on a line without axis words still acts (a full
                // circle, a hole where the tool is); a probing move without them is refused.
                let acts_alone = matches!(
                    self.motion,
                    Motion::Cw | Motion::Ccw | Motion::Cycle(_) | Motion::Probe { .. }
                );
                if has_axis || (motion.is_some() && acts_alone) {
                    self.motion_line(line, config, machine_coords)
                } else if let (Some(rpm), None) = (speed, motion) {
                    only_words(line, b"FS")?;
                    Ok(Action::Effect(Effect::Spindle(Spindle::Speed { rpm })))
                } else {
                    // Unknown letters on a line without a command are reported.
                    for w in line.words() {
                        let known =
                            matches!(w.letter, b'G' | b'F' | b'I' | b'J' | b'K' | b'R' | b'S');
                        if !known && config.axis_index(w.letter).is_none() {
                            return Err(CommandError::UnknownAxis { letter: w.letter });
                        }
                    }
                    Ok(Action::None)
                }
            }
        }
    }

    /// `G10 L2 P<n>` / `G10 L20 P<n>`: the new origin of system `n` (1–9; 0: the active one),
    /// to the values given (`L2`, machine coordinates) or such that the position now reads as
    /// them (`L20`); axes not named keep theirs. The active system's origin changes at once.
    fn set_origin<'l>(
        &mut self,
        line: &Line<'l>,
        config: &MachineConfig<N>,
        coords: &Coordinates<N>,
    ) -> Result<Action<'l, N>, CommandError> {
        for w in line.words() {
            let word = matches!(w.letter, b'G' | b'L' | b'P');
            if !word && config.axis_index(w.letter).is_none() {
                return Err(CommandError::UnknownAxis { letter: w.letter });
            }
        }
        let l = line
            .get(b'L')
            .ok_or(CommandError::MissingValue { letter: b'L' })?;
        let l20 = match l.as_integer() {
            Some(2) => false,
            Some(20) => true,
            _ => return Err(CommandError::BadValue { letter: b'L' }),
        };
        let p = line
            .get(b'P')
            .ok_or(CommandError::MissingValue { letter: b'P' })?;
        let index = match small_int(p, b'P', SYSTEMS as u32)? {
            0 => self.wcs_index,
            n => (n - 1) as u8,
        };
        let z = config.axis_index(b'Z');
        let mut values = coords.system(usize::from(index));
        for (i, a) in config.axes.iter().enumerate() {
            let Some(v) = line.get(a.letter) else {
                continue;
            };
            let nm = to_nm(v, self.inches, a.letter)?;
            values[i] = if l20 {
                // pos − (origin' + tlo − offset) = nm
                let tlo = if z == Some(i) { self.tlo_nm } else { 0 };
                self.pos[i]
                    .saturating_sub(tlo)
                    .saturating_add(self.offset[i])
                    .saturating_sub(nm)
            } else {
                nm
            };
        }
        if index == self.wcs_index {
            self.wcs = values;
        }
        Ok(Action::SetCoordinates {
            slot: Slot::System(index),
            values,
        })
    }

    fn is_relative(&self, kind: AxisKind) -> bool {
        match (kind, self.extruder_relative) {
            (AxisKind::Extruder, Some(r)) => r,
            _ => !self.absolute,
        }
    }

    /// The target machine position of the axis words on the line. An extruder under a flow
    /// override (`M221`) moves by its commanded distance × flow while its work position
    /// advances by the commanded distance: its `G92` offset takes the difference, here (the
    /// caller works on a copy of the state and drops it when the line is refused). Written
    /// into `target` rather than returned: a position moved through a `Result` is copied twice,
    /// which costs on a core that copies with `memcpy`.
    fn target(
        &mut self,
        line: &Line<'_>,
        config: &MachineConfig<N>,
        machine_coords: bool,
        target: &mut [Nm; N],
    ) -> Result<(), CommandError> {
        *target = self.pos;
        let z = config.axis_index(b'Z');
        for (i, a) in config.axes.iter().enumerate() {
            if let Some(v) = line.get(a.letter) {
                let nm = to_nm(v, self.inches, a.letter)?;
                let relative = self.is_relative(a.kind) && !machine_coords;
                let flow = self.flow_percent[i];
                let origin = if machine_coords { 0 } else { self.origin(i, z) };
                target[i] = if flow != 100 {
                    let work = self.pos[i].saturating_sub(origin);
                    let work_target = if relative {
                        work.saturating_add(nm)
                    } else {
                        nm
                    };
                    let fed = scale_nm(work_target.saturating_sub(work), flow);
                    let machine = self.pos[i].saturating_add(fed);
                    // The `G92` offset takes the difference: machine − origin' = work target.
                    let behind = work_target.saturating_sub(machine.saturating_sub(origin));
                    self.offset[i] = self.offset[i].saturating_add(behind);
                    machine
                } else if relative {
                    self.pos[i].saturating_add(nm)
                } else {
                    nm.saturating_add(origin)
                };
                // An extruder's position grows with the filament fed (a long print feeds more
                // than 100 m); the kernel bounds it by its step count instead.
                if a.kind != AxisKind::Extruder && target[i].abs() > MAX_NM {
                    return Err(CommandError::BadValue { letter: a.letter });
                }
            }
        }
        let cycle = matches!(self.motion, Motion::Cycle(_));
        for w in line.words() {
            let known = matches!(w.letter, b'G' | b'F' | b'I' | b'J' | b'K' | b'R' | b'S')
                || (cycle && matches!(w.letter, b'P' | b'Q' | b'L'));
            if !known && config.axis_index(w.letter).is_none() {
                return Err(CommandError::UnknownAxis { letter: w.letter });
            }
        }
        Ok(())
    }

    /// One hole of the drilling cycle `kind` (the motion mode), at the X and Y of the line's
    /// words; its sticky words (`R`, `Z`, `P`, `Q`) are taken from the line or kept from the
    /// lines before. See [`crate::drill`] for the moves.
    fn drill_line<'l>(
        &mut self,
        kind: DrillKind,
        line: &Line<'l>,
        config: &MachineConfig<N>,
    ) -> Result<Action<'l, N>, CommandError> {
        let z = config
            .axis_index(b'Z')
            .ok_or(CommandError::UnknownAxis { letter: b'Z' })?;
        // The cycles drill along Z: the XY plane only, and at a feed in units per minute.
        if self.plane != Plane::Xy || self.inverse_time {
            return Err(CommandError::ModalConflict);
        }
        if let Some(l) = line.get(b'L')
            && l.as_integer() != Some(1)
        {
            return Err(CommandError::BadValue { letter: b'L' });
        }
        let mut hole = [0; N];
        self.target(line, config, false, &mut hole)?;
        let mut words = self.cycle;
        if let Some(r) = line.get(b'R') {
            words.retract = Some(to_nm(r, self.inches, b'R')?);
        }
        if let Some(v) = line.get(b'Z') {
            words.bottom = Some(to_nm(v, self.inches, b'Z')?);
        }
        if let Some(q) = line.get(b'Q') {
            let q = to_nm(q, self.inches, b'Q')?;
            if q <= 0 {
                return Err(CommandError::BadValue { letter: b'Q' });
            }
            words.peck = Some(q);
        }
        if let Some(p) = line.get(b'P') {
            let ms = p.to_f64() * 1000.0;
            if !(0.0..=4.0e9).contains(&ms) {
                return Err(CommandError::BadValue { letter: b'P' });
            }
            words.dwell_ms = libm::round(ms) as u32;
        }
        let retract = words
            .retract
            .ok_or(CommandError::MissingValue { letter: b'R' })?;
        let bottom = words
            .bottom
            .ok_or(CommandError::MissingValue { letter: b'Z' })?;
        let peck = match (kind, words.peck) {
            (DrillKind::Peck, None) => return Err(CommandError::MissingValue { letter: b'Q' }),
            (_, peck) => peck.unwrap_or(0),
        };
        let (retract_nm, bottom_nm) = if self.is_relative(AxisKind::Linear) {
            let r = self.pos[z].saturating_add(retract);
            (r, r.saturating_add(bottom))
        } else {
            let origin = self.origin(z, Some(z));
            (
                retract.saturating_add(origin),
                bottom.saturating_add(origin),
            )
        };
        if bottom_nm >= retract_nm {
            return Err(CommandError::BadValue { letter: b'R' });
        }
        let clearance_nm = if words.to_r_plane {
            retract_nm
        } else {
            retract_nm.max(words.initial_z)
        };
        let cycle = DrillCycle::new(
            kind,
            z,
            self.pos,
            hole,
            retract_nm,
            bottom_nm,
            clearance_nm,
            peck,
            words.dwell_ms,
        );
        self.cycle = words;
        self.pos = cycle.end();
        Ok(Action::Drill {
            cycle,
            feed_mm_min: self.feed_mm_min,
        })
    }

    fn motion_line<'l>(
        &mut self,
        line: &Line<'l>,
        config: &MachineConfig<N>,
        machine_coords: bool,
    ) -> Result<Action<'l, N>, CommandError> {
        match self.motion {
            Motion::Cycle(kind) => return self.drill_line(kind, line, config),
            // `G80`: no motion mode for axis words to follow.
            Motion::Cancelled => return Err(CommandError::NoMotionMode),
            _ => {}
        }
        let mut target = [0; N];
        self.target(line, config, machine_coords, &mut target)?;
        let ramp = line.has(b'F') && !self.inverse_time;
        // `G93`: every feed move carries its `F`, moves per minute.
        let per_minute = match line.get(b'F') {
            _ if !self.inverse_time || self.motion == Motion::Rapid => None,
            Some(f) if f.to_f64() > 0.0 => Some(f.to_f64()),
            Some(_) => return Err(CommandError::BadValue { letter: b'F' }),
            None => return Err(CommandError::MissingValue { letter: b'F' }),
        };
        let inverse =
            |length_mm: f64| per_minute.map(|p| ((length_mm * p) as f32).max(MIN_FEED_MM_MIN));
        let action = match self.motion {
            Motion::Probe { away, must_trip } => {
                if target == self.pos {
                    return Err(CommandError::MissingValue { letter: b'Z' });
                }
                Action::Probe {
                    target,
                    feed_mm_min: inverse(distance_mm(&self.pos, &target))
                        .unwrap_or(self.feed_mm_min),
                    away,
                    must_trip,
                }
            }
            Motion::Cycle(_) | Motion::Cancelled => return Err(CommandError::ModalConflict),
            Motion::Rapid => Action::Move {
                target,
                feed_mm_min: None,
                ramp: false,
            },
            Motion::Linear => Action::Move {
                target,
                // The length only in inverse time: its square root is the line's dearest step.
                feed_mm_min: Some(match per_minute {
                    Some(_) => inverse(distance_mm(&self.pos, &target)).unwrap_or(self.feed_mm_min),
                    None => self.feed_mm_min,
                }),
                ramp,
            },
            Motion::Cw | Motion::Ccw => {
                let (l0, l1, o0, o1) = match self.plane {
                    Plane::Xy => (b'X', b'Y', b'I', b'J'),
                    Plane::Zx => (b'Z', b'X', b'K', b'I'),
                    Plane::Yz => (b'Y', b'Z', b'J', b'K'),
                };
                let ax0 = config
                    .axis_index(l0)
                    .ok_or(CommandError::UnknownAxis { letter: l0 })?;
                let ax1 = config
                    .axis_index(l1)
                    .ok_or(CommandError::UnknownAxis { letter: l1 })?;
                let center = match line.get(b'R') {
                    Some(r) => ArcCenter::Radius(to_nm(r, self.inches, b'R')?),
                    None => {
                        let i = line.get(o0);
                        let j = line.get(o1);
                        if i.is_none() && j.is_none() {
                            return Err(CommandError::MissingValue { letter: o0 });
                        }
                        let i = i.map_or(Ok(0), |v| to_nm(v, self.inches, o0))?;
                        let j = j.map_or(Ok(0), |v| to_nm(v, self.inches, o1))?;
                        ArcCenter::Offset(i, j)
                    }
                };
                let cutter = ArcCutter::new(
                    self.pos,
                    target,
                    (ax0, ax1),
                    center,
                    self.motion == Motion::Cw,
                    f64::from(config.arc_tolerance_mm),
                )?;
                let feed_mm_min = match per_minute {
                    Some(_) => inverse(cutter.length_mm()).unwrap_or(self.feed_mm_min),
                    None => self.feed_mm_min,
                };
                Action::Arc {
                    cutter,
                    feed_mm_min,
                    ramp,
                }
            }
        };
        self.pos = target;
        Ok(action)
    }

    fn command<'l>(
        &mut self,
        letter: u8,
        n: u32,
        line: &Line<'l>,
        config: &MachineConfig<N>,
        coords: &Coordinates<N>,
    ) -> Result<Action<'l, N>, CommandError> {
        let s = line.get(b'S');
        let z = config.axis_index(b'Z');
        Ok(match (letter, n) {
            (b'G', 10) => self.set_origin(line, config, coords)?,
            (b'G', G28_1 | G30_1) => {
                only_axis_words(line, config, b"")?;
                let slot = if n == G28_1 { Slot::G28 } else { Slot::G30 };
                Action::SetCoordinates {
                    slot,
                    values: self.pos,
                }
            }
            (b'G', G43_1) => {
                only_axis_words(line, config, b"")?;
                let z = z.ok_or(CommandError::UnknownAxis { letter: b'Z' })?;
                let v = line
                    .get(b'Z')
                    .ok_or(CommandError::MissingValue { letter: b'Z' })?;
                if config
                    .axes
                    .iter()
                    .any(|a| a.letter != b'Z' && line.has(a.letter))
                {
                    return Err(CommandError::BadValue { letter: b'G' });
                }
                let _ = z;
                self.tlo_nm = to_nm(v, self.inches, b'Z')?;
                Action::None
            }
            (b'G', G92_1) => {
                only_axis_words(line, config, b"")?;
                self.offset = [0; N];
                Action::None
            }
            (b'G', 4) => {
                let ms = match (line.get(b'P'), s) {
                    (Some(p), _) if self.grbl => p.to_f64() * 1000.0,
                    (Some(p), _) => p.to_f64(),
                    (None, Some(sec)) => sec.to_f64() * 1000.0,
                    (None, None) => 0.0,
                };
                if !(0.0..=4.0e9).contains(&ms) {
                    return Err(CommandError::BadValue { letter: b'P' });
                }
                Action::Dwell {
                    ms: libm::round(ms) as u32,
                }
            }
            (b'G', 28 | 30) if self.grbl => {
                only_axis_words(line, config, b"")?;
                let mut via = [0; N];
                self.target(line, config, false, &mut via)?;
                let stored = if n == 28 { coords.g28 } else { coords.g30 };
                let named = config.axes.iter().any(|a| line.has(a.letter));
                let mut target = via;
                for (i, a) in config.axes.iter().enumerate() {
                    if !named || line.has(a.letter) {
                        target[i] = stored[i];
                    }
                }
                self.pos = target;
                Action::Via { via, target }
            }
            (b'G', 28) => {
                only_axis_words(line, config, HOMING_FLAGS)?;
                let mut mask = 0u8;
                let named = config.axes.iter().any(|a| line.mentions(a.letter));
                for (i, a) in config.axes.iter().enumerate() {
                    if named && !line.mentions(a.letter) {
                        continue;
                    }
                    match a.homing {
                        Some(_) => mask |= 1 << i,
                        None if named => {
                            return Err(CommandError::BadValue { letter: a.letter });
                        }
                        None => {}
                    }
                }
                Action::Home { mask }
            }
            (b'G', 92) => {
                // `G92 E0` on a machine without E must not act as a bare `G92` (all axes to 0).
                only_axis_words(line, config, b"")?;
                let named = config.axes.iter().any(|a| line.has(a.letter));
                for (i, a) in config.axes.iter().enumerate() {
                    let value = match line.get(a.letter) {
                        Some(v) => to_nm(v, self.inches, a.letter)?,
                        None if named => continue,
                        None => 0,
                    };
                    // The offset that makes the position now read as `value`.
                    let without = self.pos[i].saturating_sub(self.origin(i, z) + self.offset[i]);
                    self.offset[i] = value.saturating_sub(without);
                }
                Action::None
            }
            (b'M', 0) if self.grbl => Action::Pause,
            (b'M', 0) => Action::Stop(StopKind::Program),
            // The optional stop: no switch asks for it, so the program goes on (grbl's `M1`).
            (b'M', 1) => Action::None,
            (b'M', 6) => {
                let tool = match line.get(b'T') {
                    Some(t) => Some(small_int(t, b'T', 255)? as u8),
                    None => None,
                };
                Action::ToolChange(tool)
            }
            (b'M', 2) => {
                self.end_program();
                Action::Effect(Effect::ProgramEnd)
            }
            // Bare `M30` ends the program (CNC); `M30 <file>` is RepRap's delete file.
            (b'M', 30) if line.text_arg().is_none() => {
                self.end_program();
                Action::Effect(Effect::ProgramEnd)
            }
            (b'M', 112) => Action::Stop(StopKind::Emergency),
            (b'M', 226) => Action::Pause,
            (b'M', 82) => {
                self.extruder_relative = Some(false);
                Action::None
            }
            (b'M', 83) => {
                self.extruder_relative = Some(true);
                Action::None
            }
            (b'M', 17) => Action::Effect(Effect::Motors {
                enabled: true,
                axes: all_axes::<N>(),
            }),
            (b'M', 18 | 84) => {
                // `M84 X Y E`: those axes; `M84` alone: all. (`S`, Marlin's idle time-out, is
                // not a setting here: the motors stay energised until released.)
                let named = config.axes.iter().any(|a| line.mentions(a.letter));
                let mut axes = 0u8;
                for (i, a) in config.axes.iter().enumerate() {
                    if !named || line.mentions(a.letter) {
                        axes |= 1 << i;
                    }
                }
                for w in line.words() {
                    if w.letter != b'M' && config.axis_index(w.letter).is_none() {
                        return Err(CommandError::UnknownAxis { letter: w.letter });
                    }
                }
                Action::Effect(Effect::Motors {
                    enabled: false,
                    axes,
                })
            }
            (b'M', 92) => {
                let mut out = [None; N];
                for (i, a) in config.axes.iter().enumerate() {
                    if let Some(v) = line.get(a.letter) {
                        let spm = v.to_f32() / if self.inches { 25.4 } else { 1.0 };
                        if !(spm.is_finite() && spm > 0.0) {
                            return Err(CommandError::BadValue { letter: a.letter });
                        }
                        out[i] = Some(spm);
                    }
                }
                Action::SetStepsPerMm(out)
            }
            (b'M', 201 | 203) => {
                // `M201`/`M203` alone ask for a report: nothing changes.
                let mut values = [None; N];
                for w in line.words() {
                    if matches!(w.letter, b'G' | b'M') {
                        continue;
                    }
                    let i = config
                        .axis_index(w.letter)
                        .ok_or(CommandError::UnknownAxis { letter: w.letter })?;
                    let v = setting(w.value, self.inches, w.letter, true)?;
                    // Marlin's `M203` is in mm/s; the configuration keeps mm/min.
                    values[i] = Some(if n == 203 { v * 60.0 } else { v });
                }
                match (values.iter().any(Option::is_some), n) {
                    (false, _) => Action::None,
                    (true, 201) => Action::SetLimits(LimitChange::AxisAccel(values)),
                    (true, _) => Action::SetLimits(LimitChange::AxisRate(values)),
                }
            }
            (b'M', 204) => {
                only_words(line, b"PRST")?;
                let value = |l: u8| {
                    line.get(l)
                        .map(|v| setting(v, self.inches, l, true))
                        .transpose()
                };
                // Marlin reads `S` first: `P` and `T` on the same line win over it.
                let both = value(b'S')?;
                let print = value(b'P')?.or(both);
                let travel = value(b'T')?.or(both);
                let retract = value(b'R')?;
                if print.is_none() && travel.is_none() && retract.is_none() {
                    Action::None
                } else {
                    Action::SetLimits(LimitChange::PathAccel {
                        print,
                        retract,
                        travel,
                    })
                }
            }
            (b'M', 205) => {
                let mut deviation_mm = None;
                let mut min_extruding_feed_mm_s = None;
                let mut min_travel_feed_mm_s = None;
                for w in line.words() {
                    let slot = match w.letter {
                        b'G' | b'M' => continue,
                        b'J' => &mut deviation_mm,
                        b'S' => &mut min_extruding_feed_mm_s,
                        b'T' => &mut min_travel_feed_mm_s,
                        // The shortest segment time, µs, and the classic jerks: checked, left
                        // out (see the module documentation).
                        b'B' => {
                            setting(w.value, false, b'B', false)?;
                            continue;
                        }
                        l if config.axis_index(l).is_some() => {
                            setting(w.value, self.inches, l, false)?;
                            continue;
                        }
                        l => return Err(CommandError::UnknownAxis { letter: l }),
                    };
                    *slot = Some(setting(w.value, self.inches, w.letter, false)?);
                }
                if deviation_mm.is_none()
                    && min_extruding_feed_mm_s.is_none()
                    && min_travel_feed_mm_s.is_none()
                {
                    Action::None
                } else {
                    Action::SetLimits(LimitChange::Junction {
                        deviation_mm,
                        min_extruding_feed_mm_s,
                        min_travel_feed_mm_s,
                    })
                }
            }
            (b'M', 220) => {
                // `B` and `R` are flags (their values, if any, are not read, as in Marlin).
                for w in line.words() {
                    match w.letter {
                        b'G' | b'M' | b'B' | b'R' => {}
                        b'S' if w.bare => return Err(CommandError::MissingValue { letter: b'S' }),
                        b'S' => {}
                        l => return Err(CommandError::UnknownAxis { letter: l }),
                    }
                }
                let set = s.map(|v| percent(v, b'S')).transpose()?;
                // Marlin's order: restore, back up what was in force before the line, set.
                let before = self.feed_percent;
                if line.mentions(b'R') {
                    self.feed_percent = self.feed_percent_backup;
                }
                if line.mentions(b'B') {
                    self.feed_percent_backup = before;
                }
                if let Some(p) = set {
                    self.feed_percent = p;
                }
                Action::None
            }
            (b'M', 221) => {
                only_words(line, b"ST")?;
                // `T<n>`: the `n`-th extruder axis, in axis order; without it, every extruder.
                let extruder = match line.get(b'T') {
                    Some(t) => {
                        let n = small_int(t, b'T', u32::from(u8::MAX))? as usize;
                        let i = config
                            .axes
                            .iter()
                            .enumerate()
                            .filter(|(_, a)| a.kind == AxisKind::Extruder)
                            .nth(n)
                            .map(|(i, _)| i)
                            .ok_or(CommandError::BadValue { letter: b'T' })?;
                        Some(i)
                    }
                    None => None,
                };
                if let Some(v) = s {
                    let p = percent(v, b'S')?;
                    for (i, a) in config.axes.iter().enumerate() {
                        if a.kind == AxisKind::Extruder && extruder.is_none_or(|e| e == i) {
                            self.flow_percent[i] = p;
                        }
                    }
                }
                Action::None
            }
            (b'M', 114) => Action::Report,
            (b'M', 3 | 4) => {
                let rpm = spindle_speed(s)?;
                if let Some(v) = rpm {
                    self.spindle_rpm = rpm_of(v);
                }
                Action::Effect(Effect::Spindle(if n == 3 {
                    Spindle::Clockwise { rpm }
                } else {
                    Spindle::CounterClockwise { rpm }
                }))
            }
            (b'M', 5) => Action::Effect(Effect::Spindle(Spindle::Off)),
            (b'M', 7) => Action::Effect(Effect::Coolant(Coolant::Mist)),
            (b'M', 8) => Action::Effect(Effect::Coolant(Coolant::Flood)),
            (b'M', 9) => Action::Effect(Effect::Coolant(Coolant::Off)),
            (b'M', 42) => {
                let index = line
                    .get(b'P')
                    .ok_or(CommandError::MissingValue { letter: b'P' })?;
                let value = match s {
                    Some(v) => small_int(v, b'S', 255)?,
                    None => return Err(CommandError::MissingValue { letter: b'S' }),
                };
                Action::Effect(Effect::Output {
                    index: small_int(index, b'P', 255)? as u8,
                    on: value > 0,
                    synced: false,
                })
            }
            // grblHAL's digital outputs: `M62`/`M63` on/off with the motion (after the moves
            // before them), `M64`/`M65` at once.
            (b'M', 62..=65) => {
                let index = line
                    .get(b'P')
                    .ok_or(CommandError::MissingValue { letter: b'P' })?;
                Action::Effect(Effect::Output {
                    index: small_int(index, b'P', 255)? as u8,
                    on: matches!(n, 62 | 64),
                    synced: matches!(n, 62 | 63),
                })
            }
            (b'M', 80 | 81) => Action::Effect(Effect::PowerSupply { on: n == 80 }),
            (b'M', 300) => {
                let frequency_hz = match s {
                    Some(v) => small_int(v, b'S', MAX_TONE_HZ)? as u16,
                    None => TONE_HZ,
                };
                let duration_ms = match line.get(b'P').map(Decimal::as_integer) {
                    Some(Some(ms)) if ms >= 0 => ms.min(MAX_TONE_MS) as u16,
                    Some(_) => return Err(CommandError::BadValue { letter: b'P' }),
                    None => TONE_MS,
                };
                Action::Effect(Effect::Tone {
                    frequency_hz,
                    duration_ms,
                })
            }
            (b'M', 104 | 109 | 140 | 141 | 190) => {
                let waits = matches!(n, 109 | 190);
                let (celsius, wait) = match (s, line.get(b'R')) {
                    (Some(s), _) if waits => (s, TemperatureWait::Heating),
                    (Some(s), _) => (s, TemperatureWait::No),
                    (None, Some(r)) if waits => (r, TemperatureWait::Reach),
                    _ => return Err(CommandError::MissingValue { letter: b'S' }),
                };
                let heater = if n == 141 {
                    Heater::Chamber
                } else if matches!(n, 140 | 190) {
                    Heater::Bed
                } else {
                    let t = match line.get(b'T') {
                        Some(t) => Some(small_int(t, b'T', 255)? as u8),
                        None => None,
                    };
                    Heater::Extruder(t)
                };
                Action::Effect(Effect::SetTemperature {
                    heater,
                    celsius,
                    wait,
                })
            }
            (b'M', 105) => Action::Effect(Effect::ReportTemperatures),
            (b'M', 400) => Action::Effect(Effect::MotionDone),
            (b'M', 410) => Action::Effect(Effect::QuickStop),
            (b'M', 73) => {
                let word = |l: u8, max: u32| line.get(l).map(|v| small_int(v, l, max)).transpose();
                Action::Effect(Effect::Progress {
                    percent: word(b'P', 100)?.map(|p| p as u8),
                    remaining_min: word(b'R', u32::MAX)?,
                    layer: word(b'L', u32::MAX)?,
                })
            }
            (b'M', 117) => Action::Effect(Effect::Message(line.text_arg().unwrap_or(&[]))),
            (b'M', 118) => Action::Effect(Effect::HostMessage(line.text_arg().unwrap_or(&[]))),
            (b'M', 155) => {
                let seconds = small_int(
                    s.ok_or(CommandError::MissingValue { letter: b'S' })?,
                    b'S',
                    60,
                )?;
                Action::Effect(Effect::AutoReport {
                    seconds: seconds as u8,
                })
            }
            (b'M', 113) => {
                let seconds = s.map(|v| small_int(v, b'S', 60)).transpose()?;
                Action::Effect(Effect::BusyInterval(seconds.map(|v| v as u8)))
            }
            // Linear advance: `K0` (off) is what this planner does; a factor is refused.
            (b'M', 900) => match line.get(b'K') {
                Some(k) if k.mantissa() != 0 => {
                    return Err(CommandError::BadValue { letter: b'K' });
                }
                _ => Action::None,
            },
            (b'M', 106) => {
                let duty = match s {
                    Some(v) => {
                        let d = v.to_f32();
                        if !(0.0..=255.0).contains(&d) {
                            return Err(CommandError::BadValue { letter: b'S' });
                        }
                        libm::roundf(d) as u8
                    }
                    None => 255,
                };
                let index = match line.get(b'P') {
                    Some(p) => small_int(p, b'P', 255)? as u8,
                    None => 0,
                };
                Action::Effect(Effect::Fan { index, duty })
            }
            (b'M', 107) => {
                let index = match line.get(b'P') {
                    Some(p) => small_int(p, b'P', 255)? as u8,
                    None => 0,
                };
                Action::Effect(Effect::Fan { index, duty: 0 })
            }
            (b'M', 110) => {
                let number = match line.get(b'N') {
                    Some(v) => small_int(v, b'N', u32::MAX)?,
                    None => line.number().unwrap_or(0),
                };
                Action::Effect(Effect::SetLineNumber(number))
            }
            (b'M', 115) => Action::Effect(Effect::ReportFirmware),
            (b'M', 116) => Action::Effect(Effect::WaitForTemperatures),
            (b'M', 119) => Action::Effect(Effect::ReportEndstops),
            (b'M', 20..=29) => {
                let text = line.text_arg();
                let name = || text.ok_or(CommandError::MissingValue { letter: b'M' });
                Action::Effect(Effect::Storage(match n {
                    20 => Storage::List,
                    21 => Storage::Init,
                    22 => Storage::Release,
                    23 => Storage::Select(name()?),
                    24 => Storage::Start,
                    25 => Storage::Pause,
                    26 => Storage::SetPosition(small_int(
                        s.ok_or(CommandError::MissingValue { letter: b'S' })?,
                        b'S',
                        u32::MAX,
                    )?),
                    27 => match s {
                        Some(v) => Storage::ReportEvery(small_int(v, b'S', 255)? as u8),
                        None => Storage::Report,
                    },
                    28 => Storage::BeginWrite(name()?),
                    _ => Storage::EndWrite(text),
                }))
            }
            // `M30` with a name (without one it is program end, above).
            (b'M', 30) => Action::Effect(Effect::Storage(Storage::Delete(
                line.text_arg().unwrap_or(&[]),
            ))),
            (b'M', 32) => {
                let name = line
                    .text_arg()
                    .ok_or(CommandError::MissingValue { letter: b'M' })?;
                Action::Effect(Effect::Storage(Storage::SelectAndStart(name)))
            }
            (b'T', t) => {
                let t = u8::try_from(t).map_err(|_| CommandError::BadValue { letter: b'T' })?;
                Action::Effect(Effect::SelectTool(t))
            }
            (letter, number) => {
                return Err(CommandError::Unsupported {
                    letter,
                    number: Some(number),
                });
            }
        })
    }

    /// After a stop or a homing: the commanded position is where the machine is.
    pub(crate) fn set_machine_position(&mut self, pos: [Nm; N]) {
        self.pos = pos;
    }

    /// Take `pos` as the commanded machine position of axis `axis` while keeping its work
    /// position, as `G92` does (a resumed job's extruder, which is not moved back).
    pub(crate) fn rebase_axis(&mut self, axis: usize, pos: Nm) {
        if let (Some(p), Some(o)) = (self.pos.get_mut(axis), self.offset.get_mut(axis)) {
            *o += *p - pos;
            *p = pos;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::AxisConfig;
    use crate::testing::xorshift;
    const MM: Nm = 1_000_000;

    fn cfg() -> MachineConfig<4> {
        let mut e = AxisConfig::linear(b'E', 100.0, 3000.0, 1000.0, 1000.0);
        e.kind = AxisKind::Extruder;
        e.min_mm = -1000.0;
        MachineConfig::new([
            AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 200.0),
            AxisConfig::linear(b'Y', 80.0, 6000.0, 500.0, 200.0),
            AxisConfig::linear(b'Z', 400.0, 600.0, 100.0, 100.0),
            e,
        ])
    }

    fn run<'l>(it: &mut Interpreter<4>, text: &'l [u8]) -> Result<Action<'l, 4>, CommandError> {
        run_on(&cfg(), it, text)
    }

    fn run_on<'l>(
        c: &MachineConfig<4>,
        it: &mut Interpreter<4>,
        text: &'l [u8],
    ) -> Result<Action<'l, 4>, CommandError> {
        let line = Line::parse(text).expect("parses");
        let mut next = *it;
        let a = next.interpret(&line, c, &Coordinates::ZERO)?;
        *it = next;
        Ok(a)
    }

    #[test]
    fn moves_in_absolute_relative_and_inches() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        assert_eq!(
            run(&mut it, b"G1 X10.5 Y-2 F1500"),
            Ok(Action::Move {
                target: [10_500_000, -2_000_000, 0, 0],
                feed_mm_min: Some(1500.0),
                ramp: true
            })
        );
        run(&mut it, b"G91").expect("ok");
        assert_eq!(
            run(&mut it, b"X0.1"),
            Ok(Action::Move {
                target: [10_600_000, -2_000_000, 0, 0],
                feed_mm_min: Some(1500.0),
                ramp: false
            })
        );
        run(&mut it, b"G90 G20").expect("ok");
        assert_eq!(
            run(&mut it, b"G0 Z1"),
            Ok(Action::Move {
                target: [10_600_000, -2_000_000, 25_400_000, 0],
                feed_mm_min: None,
                ramp: false
            })
        );
    }

    #[test]
    fn g92_offsets_and_extruder_modes() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        run(&mut it, b"G1 X10 E5").expect("ok");
        run(&mut it, b"G92 X0 E0").expect("ok");
        assert_eq!(it.work_position(Some(2)), [0, 0, 0, 0]);
        run(&mut it, b"M83").expect("ok");
        let a = run(&mut it, b"G1 X1 E1").expect("ok");
        // X is absolute in work coordinates (machine 11), E relative (machine 6).
        assert!(matches!(
            a,
            Action::Move {
                target: [11_000_000, 0, 0, 6_000_000],
                ..
            }
        ));
        run(&mut it, b"G92").expect("ok");
        assert_eq!(it.work_position(Some(2)), [0; 4]);
    }

    #[test]
    fn g90_and_g91_set_the_extruder_too_and_m82_m83_after_them_the_extruder_alone() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        run(&mut it, b"G1 X10 E5").expect("ok");
        // Cura's end code: `M82`, then `G91` and a retraction of 2 mm.
        run(&mut it, b"M82").expect("ok");
        run(&mut it, b"G91").expect("ok");
        let a = run(&mut it, b"G1 E-2").expect("ok");
        assert!(matches!(
            a,
            Action::Move {
                target: [10_000_000, 0, 0, 3_000_000],
                ..
            }
        ));
        // `G90` then `M83` (PrusaSlicer's start): X absolute, E relative.
        run(&mut it, b"G90").expect("ok");
        run(&mut it, b"M83").expect("ok");
        let a = run(&mut it, b"G1 X1 E1").expect("ok");
        assert!(matches!(
            a,
            Action::Move {
                target: [1_000_000, 0, 0, 4_000_000],
                ..
            }
        ));
        // A later `G90` makes E absolute again.
        run(&mut it, b"G90").expect("ok");
        let a = run(&mut it, b"G1 E1").expect("ok");
        assert!(matches!(
            a,
            Action::Move {
                target: [1_000_000, 0, 0, 1_000_000],
                ..
            }
        ));
    }

    #[test]
    fn letters_alone_are_flags_for_homing_and_motor_release_only() {
        let mut c = cfg();
        for (i, a) in c.axes.iter_mut().take(3).enumerate() {
            a.homing = Some(crate::config::HomingConfig {
                direction: crate::config::HomeDirection::Min,
                seek_mm_min: 1500.0,
                locate_mm_min: 100.0,
                pull_off_mm: 1.0,
                switch: i as u8,
                order: 0,
            });
        }
        let mut it = Interpreter::new(&c);
        assert_eq!(
            run_on(&c, &mut it, b"G28 X Y"),
            Ok(Action::Home { mask: 0b0011 })
        );
        // Prusa's `W` (no mesh levelling) changes nothing: every axis with homing.
        assert_eq!(
            run_on(&c, &mut it, b"G28 W"),
            Ok(Action::Home { mask: 0b0111 })
        );
        assert_eq!(
            run_on(&c, &mut it, b"G28 Z W"),
            Ok(Action::Home { mask: 0b0100 })
        );
        assert_eq!(
            run_on(&c, &mut it, b"M84 X Y E"),
            Ok(Action::Effect(Effect::Motors {
                enabled: false,
                axes: 0b1011
            }))
        );
        assert_eq!(
            run_on(&c, &mut it, b"M18"),
            Ok(Action::Effect(Effect::Motors {
                enabled: false,
                axes: 0b1111
            }))
        );
        assert_eq!(
            run_on(&c, &mut it, b"M84 Q"),
            Err(CommandError::UnknownAxis { letter: b'Q' })
        );
        // Anywhere else a letter needs its number: `G1 X` is not a move to 0.
        assert_eq!(
            run_on(&c, &mut it, b"G1 X"),
            Err(CommandError::MissingValue { letter: b'X' })
        );
        assert_eq!(
            run_on(&c, &mut it, b"M104 S"),
            Err(CommandError::MissingValue { letter: b'S' })
        );
        assert_eq!(
            run_on(&c, &mut it, b"G92 X"),
            Err(CommandError::MissingValue { letter: b'X' })
        );
    }

    #[test]
    fn t_beside_an_m_word_is_its_tool_not_a_tool_change() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        assert!(matches!(
            run(&mut it, b"M104 T0 S0"),
            Ok(Action::Effect(Effect::SetTemperature {
                heater: Heater::Extruder(Some(0)),
                ..
            }))
        ));
        assert_eq!(
            run(&mut it, b"T1"),
            Ok(Action::Effect(Effect::SelectTool(1)))
        );
        assert_eq!(run(&mut it, b"T1 M104 S0").map(|_| ()), Ok(()));
    }

    /// Run `text` with the table `coords`, applying what it sets to the table.
    fn run_coords<'l>(
        c: &MachineConfig<4>,
        coords: &mut Coordinates<4>,
        it: &mut Interpreter<4>,
        text: &'l [u8],
    ) -> Result<Action<'l, 4>, CommandError> {
        let line = Line::parse(text).expect("parses");
        let mut next = *it;
        let a = next.interpret(&line, c, coords)?;
        if let Action::SetCoordinates { slot, values } = a {
            coords.set(slot, values);
        }
        *it = next;
        Ok(a)
    }

    fn target_of(a: Result<Action<'_, 4>, CommandError>) -> [Nm; 4] {
        match a {
            Ok(Action::Move { target, .. }) => target,
            other => panic!("not a move: {other:?}"),
        }
    }

    #[test]
    fn work_coordinate_systems_g10_g53_g92_and_tool_length() {
        let c = cfg();
        let mut coords = Coordinates::ZERO;
        let mut it = Interpreter::new(&c);
        // `G10 L2 P2`: G55's origin at machine X10 Y20; selecting it moves work zero there.
        assert!(matches!(
            run_coords(&c, &mut coords, &mut it, b"G10 L2 P2 X10 Y20"),
            Ok(Action::SetCoordinates {
                slot: Slot::System(1),
                ..
            })
        ));
        assert_eq!(
            target_of(run_coords(&c, &mut coords, &mut it, b"G55 G0 X0 Y0")),
            [10 * MM, 20 * MM, 0, 0]
        );
        assert_eq!(it.work_position(Some(2)), [0; 4]);
        // `G53`: this move in machine coordinates; the system stays.
        assert_eq!(
            target_of(run_coords(&c, &mut coords, &mut it, b"G53 G0 X1")),
            [MM, 20 * MM, 0, 0]
        );
        assert_eq!(
            target_of(run_coords(&c, &mut coords, &mut it, b"G0 X1")),
            [11 * MM, 20 * MM, 0, 0]
        );
        assert_eq!(
            run_coords(&c, &mut coords, &mut it, b"G53 G2 X1 I1"),
            Err(CommandError::ModalConflict)
        );
        // `G10 L20 P0`: the active system's origin such that here reads X5.
        run_coords(&c, &mut coords, &mut it, b"G10 L20 P0 X5").unwrap();
        assert_eq!(it.work_position(Some(2))[0], 5 * MM);
        assert_eq!(coords.system(1)[0], 6 * MM);
        // `G92` on top, `G92.1` clears it.
        run_coords(&c, &mut coords, &mut it, b"G92 X0").unwrap();
        assert_eq!(it.work_position(Some(2))[0], 0);
        assert_eq!(
            target_of(run_coords(&c, &mut coords, &mut it, b"G0 X2")),
            [13 * MM, 20 * MM, 0, 0]
        );
        run_coords(&c, &mut coords, &mut it, b"G92.1").unwrap();
        assert_eq!(it.work_position(Some(2))[0], 7 * MM);
        // `G43.1 Z2`: work Z reads 2 mm below the machine's; `G49` ends it.
        run_coords(&c, &mut coords, &mut it, b"G43.1 Z2").unwrap();
        assert_eq!(it.work_position(Some(2))[2], -2 * MM);
        assert_eq!(
            target_of(run_coords(&c, &mut coords, &mut it, b"G0 Z0")),
            [13 * MM, 20 * MM, 2 * MM, 0]
        );
        run_coords(&c, &mut coords, &mut it, b"G49").unwrap();
        assert_eq!(it.work_position(Some(2))[2], 2 * MM);
        // `G59.1` is the seventh system; `G54` back to the first.
        run_coords(&c, &mut coords, &mut it, b"G10 L2 P7 X-3").unwrap();
        assert_eq!(
            target_of(run_coords(&c, &mut coords, &mut it, b"G59.1 G0 X0")),
            [-3 * MM, 20 * MM, 2 * MM, 0]
        );
        assert_eq!(
            target_of(run_coords(&c, &mut coords, &mut it, b"G54 G0 X0")),
            [0, 20 * MM, 2 * MM, 0]
        );
        // `G28.1` stores the position; a bad `G10` changes nothing.
        assert!(matches!(
            run_coords(&c, &mut coords, &mut it, b"G28.1"),
            Ok(Action::SetCoordinates { slot: Slot::G28, values }) if values[1] == 20 * MM
        ));
        assert_eq!(
            run_coords(&c, &mut coords, &mut it, b"G10 L3 P1 X0"),
            Err(CommandError::BadValue { letter: b'L' })
        );
        assert_eq!(
            run_coords(&c, &mut coords, &mut it, b"G10 L2 P10 X0"),
            Err(CommandError::BadValue { letter: b'P' })
        );
        // `G61` makes every move start from rest until `G64`; `G40` and `G80` are taken.
        run_coords(&c, &mut coords, &mut it, b"G61 G40 G80").unwrap();
        assert!(it.exact_stop);
        run_coords(&c, &mut coords, &mut it, b"G64").unwrap();
        assert!(!it.exact_stop);
    }

    #[test]
    fn unsupported_and_unknown_are_named() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        assert_eq!(
            run(&mut it, b"G38.6 X1"),
            Err(CommandError::Unsupported {
                letter: b'G',
                number: None
            })
        );
        assert_eq!(
            run(&mut it, b"M999"),
            Err(CommandError::Unsupported {
                letter: b'M',
                number: Some(999)
            })
        );
        assert_eq!(
            run(&mut it, b"G1 A3"),
            Err(CommandError::UnknownAxis { letter: b'A' })
        );
        assert_eq!(run(&mut it, b"G20 G21"), Err(CommandError::ModalConflict));
        assert_eq!(
            run(&mut it, b"G1 X1 G4 P1"),
            Err(CommandError::ModalConflict)
        );
    }

    #[test]
    fn other_subsystems_come_back_as_effects() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        assert_eq!(
            run(&mut it, b"M109 S210"),
            Ok(Action::Effect(Effect::SetTemperature {
                heater: Heater::Extruder(None),
                celsius: Decimal::new(210, 0),
                wait: TemperatureWait::Heating
            }))
        );
        assert_eq!(
            run(&mut it, b"M190 R40"),
            Ok(Action::Effect(Effect::SetTemperature {
                heater: Heater::Bed,
                celsius: Decimal::new(40, 0),
                wait: TemperatureWait::Reach
            }))
        );
        assert_eq!(
            run(&mut it, b"M140 R40"),
            Err(CommandError::MissingValue { letter: b'S' })
        );
        assert_eq!(
            run(&mut it, b"M400"),
            Ok(Action::Effect(Effect::MotionDone))
        );
        assert_eq!(
            run(&mut it, b"M73 P42 R7"),
            Ok(Action::Effect(Effect::Progress {
                percent: Some(42),
                remaining_min: Some(7),
                layer: None
            }))
        );
        assert_eq!(
            run(&mut it, b"M73 P101"),
            Err(CommandError::BadValue { letter: b'P' })
        );
        assert_eq!(
            run(&mut it, b"M117 Hello; c"),
            Ok(Action::Effect(Effect::Message(b"Hello")))
        );
        assert_eq!(
            run(&mut it, b"M118 E1 Hi"),
            Ok(Action::Effect(Effect::HostMessage(b"E1 Hi")))
        );
        assert_eq!(
            run(&mut it, b"M155 S2"),
            Ok(Action::Effect(Effect::AutoReport { seconds: 2 }))
        );
        assert_eq!(
            run(&mut it, b"M113"),
            Ok(Action::Effect(Effect::BusyInterval(None)))
        );
        assert_eq!(run(&mut it, b"M900 K0"), Ok(Action::None));
        assert_eq!(
            run(&mut it, b"M900 K0.05"),
            Err(CommandError::BadValue { letter: b'K' })
        );
        assert_eq!(
            run(&mut it, b"M106 S127"),
            Ok(Action::Effect(Effect::Fan {
                index: 0,
                duty: 127
            }))
        );
        assert_eq!(
            run(&mut it, b"M23 part.gco"),
            Ok(Action::Effect(Effect::Storage(Storage::Select(
                b"part.gco"
            ))))
        );
        assert_eq!(
            run(&mut it, b"M110 N41"),
            Ok(Action::Effect(Effect::SetLineNumber(41)))
        );
        assert_eq!(
            run(&mut it, b"T1"),
            Ok(Action::Effect(Effect::SelectTool(1)))
        );
        assert_eq!(
            run(&mut it, b"M3 S12000"),
            Ok(Action::Effect(Effect::Spindle(Spindle::Clockwise {
                rpm: Some(Decimal::new(12000, 0))
            })))
        );
    }

    #[test]
    fn m300_is_a_tone_with_marlins_defaults_and_checked_values() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        let tone = |frequency_hz, duration_ms| {
            Ok(Action::Effect(Effect::Tone {
                frequency_hz,
                duration_ms,
            }))
        };
        assert_eq!(run(&mut it, b"M300 S440 P200"), tone(440, 200));
        assert_eq!(run(&mut it, b"M300"), tone(260, 1000));
        assert_eq!(run(&mut it, b"M300 S1000"), tone(1000, 1000));
        assert_eq!(run(&mut it, b"M300 P50"), tone(260, 50));
        // `S0`: silence for `P`, a pause between tones.
        assert_eq!(run(&mut it, b"M300 S0 P300"), tone(0, 300));
        assert_eq!(run(&mut it, b"M300 S20000 P0"), tone(20_000, 0));
        // Longer than 5 s: cut to 5 s, as Marlin cuts it.
        assert_eq!(run(&mut it, b"M300 S440 P60000"), tone(440, 5000));
        assert_eq!(run(&mut it, b"M300 S440 P5000000000"), tone(440, 5000));
        for (line, letter) in [
            (&b"M300 S20001"[..], b'S'),
            (b"M300 S-440", b'S'),
            (b"M300 S440.5", b'S'),
            (b"M300 S440 P-1", b'P'),
            (b"M300 S440 P0.5", b'P'),
        ] {
            assert_eq!(
                run(&mut it, line),
                Err(CommandError::BadValue { letter }),
                "{}",
                core::str::from_utf8(line).unwrap()
            );
        }
        assert_eq!(
            run(&mut it, b"M300 S"),
            Err(CommandError::MissingValue { letter: b'S' })
        );
        // Sounded as the line is read: the moves before it go on, as in Marlin.
        assert_eq!(
            Effect::Tone {
                frequency_hz: 440,
                duration_ms: 200
            }
            .sync(),
            crate::effect::Sync::Now
        );
    }

    #[test]
    fn coolant_commands_are_effects_after_the_motion_before_them() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        for (line, coolant) in [
            (&b"M7"[..], Coolant::Mist),
            (b"M8", Coolant::Flood),
            (b"M9", Coolant::Off),
        ] {
            let effect = Effect::Coolant(coolant);
            assert_eq!(run(&mut it, line), Ok(Action::Effect(effect)));
            assert_eq!(effect.sync(), crate::effect::Sync::AfterMotion);
        }
    }

    #[test]
    fn program_end_resets_the_modal_groups_grbl_resets() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        run(&mut it, b"G21 G91 G18 F900").expect("ok");
        run(&mut it, b"G0 X1").expect("ok");
        run(&mut it, b"G92 X0").expect("ok");
        assert_eq!(run(&mut it, b"M2"), Ok(Action::Effect(Effect::ProgramEnd)));
        // Absolute, XY plane, linear motion at the feed kept; G92 offsets and units kept.
        assert_eq!(
            run(&mut it, b"X2 Y1"),
            Ok(Action::Move {
                target: [3_000_000, 1_000_000, 0, 0],
                feed_mm_min: Some(900.0),
                ramp: false
            })
        );
        run(&mut it, b"G91 G20").expect("ok");
        assert_eq!(run(&mut it, b"M30"), Ok(Action::Effect(Effect::ProgramEnd)));
        assert!(it.absolute && it.inches && it.plane == Plane::Xy);
        // `M30 <file>` is RepRap's delete file.
        assert_eq!(
            run(&mut it, b"M30 part.gco"),
            Ok(Action::Effect(Effect::Storage(Storage::Delete(
                b"part.gco"
            ))))
        );
    }

    #[test]
    fn g94_and_g93_are_the_feed_modes_and_g95_is_refused() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        let before = it;
        assert_eq!(run(&mut it, b"G94"), Ok(Action::None));
        assert_eq!(it, before);
        assert!(matches!(
            run(&mut it, b"G94 G1 X1 F600"),
            Ok(Action::Move { .. })
        ));
        assert_eq!(
            run(&mut it, b"G95 G1 X2 F1"),
            Err(CommandError::Unsupported {
                letter: b'G',
                number: Some(95)
            })
        );
        // `G93`: `F2` on a 10 mm move is half a minute: 20 mm/min; the modal feed stays.
        assert!(matches!(
            run(&mut it, b"G93 G1 X11 F2"),
            Ok(Action::Move { feed_mm_min: Some(f), .. }) if (f - 20.0).abs() < 1e-3
        ));
        assert_eq!(
            run(&mut it, b"G1 X12"),
            Err(CommandError::MissingValue { letter: b'F' }),
            "each feed move carries its F"
        );
        assert!(matches!(
            run(&mut it, b"G0 X0"),
            Ok(Action::Move {
                feed_mm_min: None,
                ..
            })
        ));
        // A half circle of radius 5 (15.708 mm) in one minute.
        assert!(matches!(
            run(&mut it, b"G2 X10 I5 F1"),
            Ok(Action::Arc { feed_mm_min, .. }) if (feed_mm_min - 15.708).abs() < 1e-2
        ));
        assert!(matches!(
            run(&mut it, b"G94 G1 X0"),
            Ok(Action::Move { feed_mm_min: Some(f), .. }) if f == 600.0
        ));
    }

    #[test]
    fn homing_dwell_and_steps_per_unit() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        assert_eq!(run(&mut it, b"G4 P200"), Ok(Action::Dwell { ms: 200 }));
        assert_eq!(run(&mut it, b"G4 S1.5"), Ok(Action::Dwell { ms: 1500 }));
        // No axis of this configuration has homing.
        assert_eq!(run(&mut it, b"G28"), Ok(Action::Home { mask: 0 }));
        assert_eq!(
            run(&mut it, b"G28 X0"),
            Err(CommandError::BadValue { letter: b'X' })
        );
        assert_eq!(
            run(&mut it, b"M92 E93"),
            Ok(Action::SetStepsPerMm([None, None, None, Some(93.0)]))
        );
    }

    #[test]
    fn axis_limits_are_read_in_marlins_units_and_checked() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        assert_eq!(
            run(&mut it, b"M201 X1000 E5000"),
            Ok(Action::SetLimits(LimitChange::AxisAccel([
                Some(1000.0),
                None,
                None,
                Some(5000.0)
            ])))
        );
        // `M203` is in mm/s; the configuration keeps mm/min.
        assert_eq!(
            run(&mut it, b"M203 X200 Z12"),
            Ok(Action::SetLimits(LimitChange::AxisRate([
                Some(12_000.0),
                None,
                Some(720.0),
                None
            ])))
        );
        // Inches, as Marlin reads axis units.
        run(&mut it, b"G20").expect("ok");
        assert_eq!(
            run(&mut it, b"M203 Y1"),
            Ok(Action::SetLimits(LimitChange::AxisRate([
                None,
                Some(25.4 * 60.0),
                None,
                None
            ])))
        );
        run(&mut it, b"G21").expect("ok");
        // Alone: a report, nothing changes.
        assert_eq!(run(&mut it, b"M201"), Ok(Action::None));
        assert_eq!(run(&mut it, b"M203"), Ok(Action::None));
        let before = it;
        for (text, error) in [
            (&b"M201 X0"[..], CommandError::BadValue { letter: b'X' }),
            (b"M201 X100 Y-5", CommandError::BadValue { letter: b'Y' }),
            (b"M203 E0", CommandError::BadValue { letter: b'E' }),
            (b"M203 A10", CommandError::UnknownAxis { letter: b'A' }),
            (b"M201 T0 E100", CommandError::UnknownAxis { letter: b'T' }),
            (b"M201 X", CommandError::MissingValue { letter: b'X' }),
        ] {
            assert_eq!(run(&mut it, text), Err(error), "{}", text.escape_ascii());
        }
        assert_eq!(it, before);
    }

    #[test]
    fn m204_sets_the_path_accelerations_s_first_then_p_and_t() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        assert_eq!(
            run(&mut it, b"M204 P1250 R1250 T1500"),
            Ok(Action::SetLimits(LimitChange::PathAccel {
                print: Some(1250.0),
                retract: Some(1250.0),
                travel: Some(1500.0)
            }))
        );
        assert_eq!(
            run(&mut it, b"M204 S1000 P500"),
            Ok(Action::SetLimits(LimitChange::PathAccel {
                print: Some(500.0),
                retract: None,
                travel: Some(1000.0)
            }))
        );
        assert_eq!(run(&mut it, b"M204"), Ok(Action::None));
        for (text, error) in [
            (&b"M204 R0"[..], CommandError::BadValue { letter: b'R' }),
            (b"M204 S-1000", CommandError::BadValue { letter: b'S' }),
            (b"M204 X1000", CommandError::UnknownAxis { letter: b'X' }),
            (b"M204 P", CommandError::MissingValue { letter: b'P' }),
        ] {
            assert_eq!(run(&mut it, text), Err(error), "{}", text.escape_ascii());
        }
    }

    #[test]
    fn m205_takes_junction_deviation_and_the_slowest_feeds_and_checks_the_rest() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        assert_eq!(
            run(&mut it, b"M205 J0.02 S0 T2.5 B20000"),
            Ok(Action::SetLimits(LimitChange::Junction {
                deviation_mm: Some(0.02),
                min_extruding_feed_mm_s: Some(0.0),
                min_travel_feed_mm_s: Some(2.5)
            }))
        );
        // PrusaSlicer's classic jerks: accepted, nothing to change on this planner.
        assert_eq!(run(&mut it, b"M205 X8 Y8 Z0.4 E4.5"), Ok(Action::None));
        assert_eq!(run(&mut it, b"M205"), Ok(Action::None));
        for (text, error) in [
            (&b"M205 J-0.01"[..], CommandError::BadValue { letter: b'J' }),
            (b"M205 X-1", CommandError::BadValue { letter: b'X' }),
            (b"M205 B-1", CommandError::BadValue { letter: b'B' }),
            (b"M205 S-2", CommandError::BadValue { letter: b'S' }),
            (b"M205 Q1", CommandError::UnknownAxis { letter: b'Q' }),
        ] {
            assert_eq!(run(&mut it, text), Err(error), "{}", text.escape_ascii());
        }
    }

    #[test]
    fn m220_sets_backs_up_and_restores_the_feed_override() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        assert_eq!(it.feed_percent(), 100);
        assert_eq!(run(&mut it, b"M220 S50"), Ok(Action::None));
        assert_eq!(it.feed_percent(), 50);
        assert_eq!(it.feed_scale(), 0.5);
        // Back up 50 and set 80 on one line (the backup is what was in force before it).
        run(&mut it, b"M220 B S80").expect("ok");
        assert_eq!(it.feed_percent(), 80);
        run(&mut it, b"M220 R").expect("ok");
        assert_eq!(it.feed_percent(), 50);
        // `R B` swaps: restore 50 from the backup, back up the 120 in force.
        run(&mut it, b"M220 S120").expect("ok");
        run(&mut it, b"M220 R B").expect("ok");
        assert_eq!(it.feed_percent(), 50);
        run(&mut it, b"M220 R").expect("ok");
        assert_eq!(it.feed_percent(), 120);
        assert_eq!(run(&mut it, b"M220"), Ok(Action::None));
        // The feed of the moves is left as given: the kernel scales it when it plans them.
        assert!(matches!(
            run(&mut it, b"G1 X1 F600"),
            Ok(Action::Move {
                feed_mm_min: Some(600.0),
                ..
            })
        ));
        let before = it;
        for (text, error) in [
            (&b"M220 S0"[..], CommandError::BadValue { letter: b'S' }),
            (b"M220 S1000", CommandError::BadValue { letter: b'S' }),
            (b"M220 S50.5", CommandError::BadValue { letter: b'S' }),
            (b"M220 B S-5", CommandError::BadValue { letter: b'S' }),
            (b"M220 S", CommandError::MissingValue { letter: b'S' }),
            (b"M220 X", CommandError::UnknownAxis { letter: b'X' }),
        ] {
            assert_eq!(run(&mut it, text), Err(error), "{}", text.escape_ascii());
        }
        assert_eq!(it, before);
        // A soft reset goes back to 100 %.
        it.reset_modal(&c, &Coordinates::ZERO);
        assert_eq!(it.feed_percent(), 100);
    }

    #[test]
    fn flow_scales_the_filament_fed_not_the_reported_extruder_position() {
        let c = cfg();
        let mut it = Interpreter::new(&c);
        run(&mut it, b"M221 S50").expect("ok");
        assert_eq!(it.flow_percent(), [100, 100, 100, 50]);
        // Absolute extrusion: E10 feeds 5 mm; the work position is the commanded 10.
        let a = run(&mut it, b"G1 X5 E10 F600").expect("ok");
        assert!(matches!(a, Action::Move { target, .. } if target == [5 * MM, 0, 0, 5 * MM]));
        assert_eq!(it.work_position(Some(2)), [5 * MM, 0, 0, 10 * MM]);
        // A retraction to E9 pulls back 0.5 mm.
        let a = run(&mut it, b"G1 E9").expect("ok");
        assert!(matches!(a, Action::Move { target, .. } if target[3] == 4_500_000));
        // `G92 E0` sets the reported position; the motor goes on from where it is.
        run(&mut it, b"G92 E0").expect("ok");
        assert_eq!(it.work_position(Some(2))[3], 0);
        let a = run(&mut it, b"G1 E2").expect("ok");
        assert!(matches!(a, Action::Move { target, .. } if target[3] == 5_500_000));
        assert_eq!(it.work_position(Some(2))[3], 2 * MM);
        // Relative extrusion alike.
        run(&mut it, b"M83").expect("ok");
        let a = run(&mut it, b"G1 E3").expect("ok");
        assert!(matches!(a, Action::Move { target, .. } if target[3] == 7 * MM));
        assert_eq!(it.work_position(Some(2))[3], 5 * MM);
        // Back to 100 %: the commanded distance again.
        run(&mut it, b"M221 T0 S100").expect("ok");
        let a = run(&mut it, b"G1 E1").expect("ok");
        assert!(matches!(a, Action::Move { target, .. } if target[3] == 8 * MM));
        assert_eq!(it.work_position(Some(2))[3], 6 * MM);
        // Only the extruders: X is not scaled.
        run(&mut it, b"M221 S200").expect("ok");
        let a = run(&mut it, b"G1 X6").expect("ok");
        assert!(matches!(a, Action::Move { target, .. } if target[0] == 6 * MM));
        let before = it;
        for (text, error) in [
            (&b"M221 S0"[..], CommandError::BadValue { letter: b'S' }),
            (b"M221 S1000", CommandError::BadValue { letter: b'S' }),
            (b"M221 T1 S90", CommandError::BadValue { letter: b'T' }),
            (b"M221 E90", CommandError::UnknownAxis { letter: b'E' }),
        ] {
            assert_eq!(run(&mut it, text), Err(error), "{}", text.escape_ascii());
        }
        assert_eq!(it, before);
        assert_eq!(run(&mut it, b"M221"), Ok(Action::None));
        assert_eq!(run(&mut it, b"M221 T0"), Ok(Action::None));
        assert_eq!(it, before);
    }

    #[test]
    fn nanometres_in_i64_agree_with_the_wide_conversion() {
        for text in [
            "0",
            "1",
            "-1",
            "0.5",
            "1.0000005",
            "-1.0000005",
            "0.0000004",
            "123.456789",
            "99999.9999",
            "-0.000000000000000001",
            "0.123456789012345678",
            "12345678901234.5678",
            "1.23456789012345678",
        ] {
            let v = Decimal::parse(text.as_bytes()).unwrap();
            for inches in [false, true] {
                let wide = wide_to_nm(v, inches).filter(|q| q.abs() <= MAX_NM);
                assert_eq!(to_nm(v, inches, b'X').ok(), wide, "{text} inches {inches}");
            }
        }
        // Every scale a line can carry, mantissas of every size, halves of a nm included.
        let mut x = 0x853C_49E6_748F_EA9Bu64;
        for i in 0..200_000u64 {
            xorshift(&mut x);
            let digits = (i % 19) as u32;
            let mantissa = (x % 10u64.pow(digits).max(2)) as i64;
            let mantissa = if i % 3 == 0 { -mantissa } else { mantissa };
            let scale = ((x >> 40) % 19) as u8;
            let v = Decimal::new(mantissa, scale);
            for inches in [false, true] {
                let wide = wide_to_nm(v, inches).filter(|q| q.abs() <= MAX_NM);
                assert_eq!(to_nm(v, inches, b'X').ok(), wide, "{v:?} inches {inches}");
            }
        }
        assert_eq!(to_nm(Decimal::new(5, 7), false, b'X'), Ok(1));
        assert_eq!(to_nm(Decimal::new(-5, 7), false, b'X'), Ok(-1));
        assert_eq!(
            to_nm(Decimal::new(i64::MAX, 18), true, b'X'),
            Ok(234_273_650)
        );
    }

    #[test]
    fn exact_decimal_conversion() {
        assert_eq!(
            to_nm(Decimal::new(123_456_789, 7), false, b'X'),
            Ok(12_345_679)
        );
        assert_eq!(to_nm(Decimal::new(-15, 1), true, b'X'), Ok(-38_100_000));
        assert_eq!(nm_to_steps(12_345_679, 80.0), 988);
        assert_eq!(steps_to_nm(988, 80.0), 12_350_000);
    }

    /// `nm × steps_per_mm / 10⁶` rounded half away from zero, in exact rational arithmetic.
    fn reference_steps(nm: Nm, steps_per_mm: f32) -> i128 {
        let bits = steps_per_mm.to_bits();
        let m = i128::from((bits & 0x7F_FFFF) | 0x80_0000);
        let e = ((bits >> 23) & 0xFF) as i32 - 150;
        let (num, den) = if e >= 0 {
            (i128::from(nm) * (m << e), 1_000_000i128)
        } else {
            (i128::from(nm) * m, 1_000_000i128 << -e)
        };
        let q = (num.abs() * 2 + den) / (den * 2);
        if num < 0 { -q } else { q }
    }

    #[test]
    fn millionths_divides_every_range() {
        let mut x = 0x2545_F491_4F6C_DD1Du64;
        for t in [0, 1, 999_999, 1_000_000, (1u64 << 31) * 1_000_000 - 1] {
            assert_eq!(u64::from(millionths(t)), t / 1_000_000, "{t}");
        }
        for _ in 0..100_000 {
            xorshift(&mut x);
            let t = x % ((1u64 << 31) * 1_000_000);
            assert_eq!(u64::from(millionths(t)), t / 1_000_000, "{t}");
        }
    }

    #[test]
    fn steps_of_a_position_are_exact_at_half_steps_and_beyond_double_precision() {
        // Half a step rounds away from zero, either way.
        assert_eq!(nm_to_steps(6_250, 80.0), 1);
        assert_eq!(nm_to_steps(-6_250, 80.0), -1);
        assert_eq!(nm_to_steps(6_249, 80.0), 0);
        assert_eq!(nm_to_steps(0, 93.7), 0);
        // Beyond `i32` steps, clamped as before.
        assert_eq!(nm_to_steps(MAX_NM, 100_000.0), i32::MAX);
        assert_eq!(nm_to_steps(-MAX_NM, 100_000.0), i32::MIN);
        let rates = [
            80.0f32, 93.7, 400.0, 415.3, 3200.0, 0.5, 12.3456, 1e-3, 5_000.25,
        ];
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        for i in 0..200_000u64 {
            xorshift(&mut x);
            let nm = (x % (2 * MAX_NM as u64)) as i64 - MAX_NM;
            let nm = if i % 2 == 0 { nm / 100_000 } else { nm };
            let spm = rates[(i % rates.len() as u64) as usize];
            let want = reference_steps(nm, spm).clamp(i32::MIN.into(), i32::MAX.into());
            assert_eq!(
                i128::from(nm_to_steps(nm, spm)),
                want,
                "{nm} nm at {spm} steps/mm"
            );
        }
    }

    #[test]
    fn a_flow_percentage_scales_to_the_nearest_nanometre_and_saturates() {
        let reference = |nm: Nm, p: u16| {
            let q = i128::from(nm) * i128::from(p);
            let r = if q >= 0 {
                (q + 50) / 100
            } else {
                (q - 50) / 100
            };
            i64::try_from(r).unwrap_or(if r < 0 { i64::MIN } else { i64::MAX })
        };
        let mut x = 0x5eed_0ff1_0e00_u64;
        for _ in 0..200_000 {
            let r = xorshift(&mut x);
            let nm = r.cast_signed() >> (r % 64);
            let p = (xorshift(&mut x) % 1_001) as u16;
            assert_eq!(scale_nm(nm, p), reference(nm, p), "{nm} × {p} %");
        }
        for nm in [i64::MAX, i64::MIN, 50, -50, 49, -49, 150, -150, 1, -1] {
            for p in [0, 1, 50, 99, 100, 101, 999, 1000, u16::MAX] {
                assert_eq!(scale_nm(nm, p), reference(nm, p), "{nm} × {p} %");
            }
        }
    }
}
