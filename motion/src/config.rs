//! Machine configuration: per-axis mechanics, limits and homing, and machine-wide settings.
//!
//! A [`MachineConfig`] is plain data, serialisable with `postcard` ([`MachineConfig::to_slice`],
//! [`MachineConfig::from_bytes`]) so that a board can keep it in its record storage. It is
//! checked by [`MachineConfig::validate`] before the kernel uses it; the kernel refuses an
//! invalid one with the [`ConfigError`] that names the bad field.

use serde::{Deserialize, Serialize};

use crate::error::ConfigError;

/// What an axis moves, which decides how feeds and modes apply to it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum AxisKind {
    /// A linear axis: part of the tool path length that the feed rate applies to.
    #[default]
    Linear,
    /// A rotary axis (degrees count as millimetres, as in grbl).
    Rotary,
    /// An extruder: follows `M82`/`M83` and is left out of the path length unless it moves alone.
    Extruder,
}

/// Which end of the travel the homing switch sits at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum HomeDirection {
    /// The switch is at `min_mm`; homing moves towards negative positions.
    #[default]
    Min,
    /// The switch is at `max_mm`; homing moves towards positive positions.
    Max,
}

impl HomeDirection {
    /// The sign of a move towards the switch: `-1.0` for [`HomeDirection::Min`], `1.0` for
    /// [`HomeDirection::Max`].
    #[inline]
    pub fn sign(self) -> f32 {
        match self {
            Self::Min => -1.0,
            Self::Max => 1.0,
        }
    }
}

/// Homing of one axis (the RepRap `G28` cycle).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HomingConfig {
    /// Which end the switch is at.
    pub direction: HomeDirection,
    /// Fast approach to the switch, mm/min.
    pub seek_mm_min: f32,
    /// Slow approach after the back-off, mm/min.
    pub locate_mm_min: f32,
    /// Back-off and final pull-off distance, mm.
    pub pull_off_mm: f32,
    /// Index of the limit switch (into the switch slice given to the step interrupt).
    pub switch: u8,
    /// Homing order: lower first; axes are homed one after another.
    pub order: u8,
}

/// One axis.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AxisConfig {
    /// The G-code letter, ASCII upper case (`b'X'`, `b'E'`, …).
    pub letter: u8,
    /// What the axis moves.
    pub kind: AxisKind,
    /// Motor steps per millimetre (or per degree for a rotary axis); `M92` sets it.
    pub steps_per_mm: f32,
    /// Maximum rate, mm/min. `G0` moves at this rate; `M203` sets it (in mm/s, Marlin's unit).
    pub max_rate_mm_min: f32,
    /// Maximum acceleration, mm/s²; `M201` sets it.
    pub accel_mm_s2: f32,
    /// Lowest machine position, mm.
    pub min_mm: f32,
    /// Highest machine position, mm.
    pub max_mm: f32,
    /// Homing, when the axis has a switch. An axis without one is never homed, has no hard
    /// limit, and soft limits apply to it only under [`SoftLimits::Always`].
    pub homing: Option<HomingConfig>,
}

impl AxisConfig {
    /// A linear axis with the given letter and mechanics, travel `0..=travel_mm`, no homing.
    pub const fn linear(
        letter: u8,
        steps_per_mm: f32,
        max_rate_mm_min: f32,
        accel_mm_s2: f32,
        travel_mm: f32,
    ) -> Self {
        Self {
            letter,
            kind: AxisKind::Linear,
            steps_per_mm,
            max_rate_mm_min,
            accel_mm_s2,
            min_mm: 0.0,
            max_mm: travel_mm,
            homing: None,
        }
    }

    /// The same axis with homing to `direction` through `switch`, at the given rates.
    pub const fn with_homing(mut self, homing: HomingConfig) -> Self {
        self.homing = Some(homing);
        self
    }

    /// The travel length, mm.
    pub fn travel_mm(&self) -> f32 {
        self.max_mm - self.min_mm
    }

    /// The maximum rate in mm/s.
    pub fn max_rate_mm_s(&self) -> f32 {
        self.max_rate_mm_min / 60.0
    }

    /// The end of the travel a homing switch towards `direction` sits at, mm: what the axis's
    /// position is set to when its switch is found.
    #[inline]
    pub fn end_mm(&self, direction: HomeDirection) -> f32 {
        match direction {
            HomeDirection::Min => self.min_mm,
            HomeDirection::Max => self.max_mm,
        }
    }
}

impl Default for AxisConfig {
    fn default() -> Self {
        Self::linear(b'X', 80.0, 6000.0, 500.0, 200.0)
    }
}

/// When soft limits reject a move that would leave an axis's travel.
///
/// The default is [`SoftLimits::WhenHomed`], as in grblHAL: before homing, the machine does not
/// know where it is, so travel limits mean nothing; after homing they are enforced on every
/// axis that has been homed. [`SoftLimits::Always`] trusts the power-on position (a machine
/// that is parked at a known place when switched off, or one without switches).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum SoftLimits {
    /// Never check travel.
    Off,
    /// Check the axes that have been homed since power-on or the last alarm.
    #[default]
    WhenHomed,
    /// Check every axis, homed or not.
    Always,
}

/// The whole machine: `N` axes and the settings of the kernel.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MachineConfig<const N: usize> {
    /// The axes, in step-output order: axis `i` drives stepper `i`.
    #[serde(with = "array_serde")]
    pub axes: [AxisConfig; N],
    /// Junction deviation, mm: how far the path may (virtually) cut a corner. Larger is faster
    /// through corners. `0` stops at every corner that is not a straight continuation.
    /// `M205 J` sets it.
    pub junction_deviation_mm: f32,
    /// Largest distance between an arc and the chords that approximate it, mm.
    pub arc_tolerance_mm: f32,
    /// Soft limit policy.
    pub soft_limits: SoftLimits,
    /// Stop all motion when a limit switch trips during motion (not during homing).
    pub hard_limits: bool,
    /// The touch probe, if the machine has one: its index in the switches the step interrupt
    /// reads ([`crate::StepGenerator::on_alarm`]), beside the homing switches. `G38.2`–`G38.5`
    /// need it.
    #[serde(default)]
    pub probe_switch: Option<u8>,
    /// Feed of jog moves (frame message 01), mm/min.
    pub jog_feed_mm_min: f32,
    /// Feed of `G1` before any `F` word, mm/min.
    pub default_feed_mm_min: f32,
    /// How much motion the kernel keeps prepared in the step queue, ms
    /// ([`DEFAULT_QUEUE_LEAD_MS`] by default). It bounds how long a feed hold takes to start
    /// decelerating (to five quarters of it: a top-up of the queue runs on to the end of a
    /// block that ends within a quarter of the lead after it); the thread side must poll
    /// again within half of it, or sooner when the queue fills up first
    /// (`Kernel::poll_within_ms`).
    pub queue_lead_ms: u16,
}

/// The [`MachineConfig::queue_lead_ms`] of a new configuration.
pub const DEFAULT_QUEUE_LEAD_MS: u16 = 20;

impl<const N: usize> MachineConfig<N> {
    /// Machine-wide defaults around the given axes: 0.01 mm junction deviation, 0.002 mm arc
    /// tolerance, soft limits when homed, hard limits on, no probe, jog at 1000 mm/min, 20 ms lead.
    pub const fn new(axes: [AxisConfig; N]) -> Self {
        Self {
            axes,
            junction_deviation_mm: 0.01,
            arc_tolerance_mm: 0.002,
            soft_limits: SoftLimits::WhenHomed,
            hard_limits: true,
            probe_switch: None,
            jog_feed_mm_min: 1000.0,
            default_feed_mm_min: 1000.0,
            queue_lead_ms: DEFAULT_QUEUE_LEAD_MS,
        }
    }

    /// The index of the axis with this letter (upper case).
    pub fn axis_index(&self, letter: u8) -> Option<usize> {
        self.axes.iter().position(|a| a.letter == letter)
    }

    /// Check every field. The kernel calls this on construction and on every line that changes
    /// the configuration (`M92`, `M201`, `M203`, `M205 J`).
    pub fn validate(&self) -> Result<(), ConfigError> {
        if N == 0 || N > crate::MAX_AXES {
            return Err(ConfigError::AxisCount);
        }
        for (i, a) in self.axes.iter().enumerate() {
            let ix = i as u8;
            let reserved = b"FGIJKMNPRST";
            if !a.letter.is_ascii_uppercase()
                || reserved.contains(&a.letter)
                || self.axes[..i].iter().any(|b| b.letter == a.letter)
            {
                return Err(ConfigError::Letter(ix));
            }
            if !positive(a.steps_per_mm) {
                return Err(ConfigError::StepsPerMm(ix));
            }
            if !positive(a.max_rate_mm_min) {
                return Err(ConfigError::MaxRate(ix));
            }
            if !positive(a.accel_mm_s2) {
                return Err(ConfigError::Acceleration(ix));
            }
            if !a.min_mm.is_finite() || !a.max_mm.is_finite() || a.min_mm >= a.max_mm {
                return Err(ConfigError::Travel(ix));
            }
            if let Some(h) = a.homing {
                if !positive(h.seek_mm_min) || h.seek_mm_min > a.max_rate_mm_min {
                    return Err(ConfigError::SeekRate(ix));
                }
                if !positive(h.locate_mm_min) || h.locate_mm_min > h.seek_mm_min {
                    return Err(ConfigError::LocateRate(ix));
                }
                if !h.pull_off_mm.is_finite()
                    || h.pull_off_mm < 0.0
                    || h.pull_off_mm >= a.travel_mm()
                {
                    return Err(ConfigError::PullOff(ix));
                }
                if h.switch > 31 {
                    return Err(ConfigError::LimitSwitch(ix));
                }
            }
        }
        if !self.junction_deviation_mm.is_finite() || self.junction_deviation_mm < 0.0 {
            return Err(ConfigError::JunctionDeviation);
        }
        if !positive(self.arc_tolerance_mm) {
            return Err(ConfigError::ArcTolerance);
        }
        let min_feed = crate::interp::MIN_FEED_MM_MIN;
        if !(self.jog_feed_mm_min >= min_feed && self.default_feed_mm_min >= min_feed) {
            return Err(ConfigError::JogFeed);
        }
        if !(2..=1000).contains(&self.queue_lead_ms) {
            return Err(ConfigError::QueueLead);
        }
        Ok(())
    }

    /// Check the step rates against a clock and a driver: at the maximum rate, consecutive
    /// steps of an axis must be at least three pulse widths (plus the direction set-up) apart
    /// and at least two ticks apart.
    pub fn validate_timing(
        &self,
        tick_hz: u32,
        timing: forja_hal_abstraction::stepper::StepTiming,
    ) -> Result<(), ConfigError> {
        if tick_hz == 0 {
            return Err(ConfigError::TickRate);
        }
        let pulse_s = timing.min_pulse_ns as f32 * 1e-9;
        let min_interval_s = (3.0 * pulse_s).max(2.0 / tick_hz as f32);
        for (i, a) in self.axes.iter().enumerate() {
            let step_hz = a.max_rate_mm_s() * a.steps_per_mm;
            if step_hz * min_interval_s > 1.0 {
                return Err(ConfigError::StepRate(i as u8));
            }
        }
        Ok(())
    }

    /// Serialise with `postcard` into `buf`, returning the used part.
    pub fn to_slice<'b>(&self, buf: &'b mut [u8]) -> Result<&'b mut [u8], ConfigError> {
        postcard::to_slice(self, buf).map_err(|_| ConfigError::Encoding)
    }

    /// Decode a `postcard` image written by [`MachineConfig::to_slice`] and validate it.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, ConfigError> {
        let c: Self = postcard::from_bytes(bytes).map_err(|_| ConfigError::Encoding)?;
        c.validate()?;
        Ok(c)
    }
}

fn positive(x: f32) -> bool {
    x.is_finite() && x > 0.0
}

/// Serde for `[T; N]` with any `N` (serde's own impls stop at 32 and are not const-generic).
mod array_serde {
    use core::fmt;
    use core::marker::PhantomData;

    use serde::de::{Error, SeqAccess, Visitor};
    use serde::ser::SerializeTuple;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer, T: Serialize, const N: usize>(
        a: &[T; N],
        s: S,
    ) -> Result<S::Ok, S::Error> {
        let mut t = s.serialize_tuple(N)?;
        for x in a {
            t.serialize_element(x)?;
        }
        t.end()
    }

    struct ArrayVisitor<T, const N: usize>(PhantomData<T>);

    impl<'de, T: Deserialize<'de> + Default + Copy, const N: usize> Visitor<'de>
        for ArrayVisitor<T, N>
    {
        type Value = [T; N];

        fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            write!(f, "an array of {N} elements")
        }

        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<[T; N], A::Error> {
            let mut out = [T::default(); N];
            for (i, slot) in out.iter_mut().enumerate() {
                *slot = seq
                    .next_element()?
                    .ok_or_else(|| A::Error::invalid_length(i, &self))?;
            }
            Ok(out)
        }
    }

    pub fn deserialize<
        'de,
        D: Deserializer<'de>,
        T: Deserialize<'de> + Default + Copy,
        const N: usize,
    >(
        d: D,
    ) -> Result<[T; N], D::Error> {
        d.deserialize_tuple(N, ArrayVisitor::<T, N>(PhantomData))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use forja_hal_abstraction::stepper::StepTiming;

    fn homing(switch: u8) -> HomingConfig {
        HomingConfig {
            direction: HomeDirection::Min,
            seek_mm_min: 1500.0,
            locate_mm_min: 100.0,
            pull_off_mm: 1.0,
            switch,
            order: 0,
        }
    }

    fn cfg() -> MachineConfig<3> {
        MachineConfig::new([
            AxisConfig::linear(b'X', 80.0, 6000.0, 500.0, 200.0).with_homing(homing(0)),
            AxisConfig::linear(b'Y', 80.0, 6000.0, 500.0, 200.0).with_homing(homing(1)),
            AxisConfig::linear(b'Z', 400.0, 600.0, 100.0, 100.0),
        ])
    }

    #[test]
    fn default_config_is_valid() {
        assert_eq!(cfg().validate(), Ok(()));
        assert_eq!(
            cfg().validate_timing(1_000_000, StepTiming::CONSERVATIVE),
            Ok(())
        );
    }

    #[test]
    fn each_bad_field_is_named() {
        let mut c = cfg();
        c.axes[1].steps_per_mm = 0.0;
        assert_eq!(c.validate(), Err(ConfigError::StepsPerMm(1)));
        let mut c = cfg();
        c.axes[2].letter = b'X';
        assert_eq!(c.validate(), Err(ConfigError::Letter(2)));
        let mut c = cfg();
        c.axes[0].letter = b'F';
        assert_eq!(c.validate(), Err(ConfigError::Letter(0)));
        let mut c = cfg();
        c.axes[0].accel_mm_s2 = f32::NAN;
        assert_eq!(c.validate(), Err(ConfigError::Acceleration(0)));
        let mut c = cfg();
        c.axes[2].min_mm = 100.0;
        assert_eq!(c.validate(), Err(ConfigError::Travel(2)));
        let mut c = cfg();
        if let Some(h) = c.axes[0].homing.as_mut() {
            h.locate_mm_min = 2000.0;
        }
        assert_eq!(c.validate(), Err(ConfigError::LocateRate(0)));
        let mut c = cfg();
        if let Some(h) = c.axes[1].homing.as_mut() {
            h.seek_mm_min = 9000.0;
        }
        assert_eq!(c.validate(), Err(ConfigError::SeekRate(1)));
        let mut c = cfg();
        if let Some(h) = c.axes[1].homing.as_mut() {
            h.pull_off_mm = 500.0;
        }
        assert_eq!(c.validate(), Err(ConfigError::PullOff(1)));
        let mut c = cfg();
        c.queue_lead_ms = 0;
        assert_eq!(c.validate(), Err(ConfigError::QueueLead));
        let mut c = cfg();
        c.axes[0].max_rate_mm_min = 600_000.0;
        if let Some(h) = c.axes[0].homing.as_mut() {
            h.seek_mm_min = 1000.0;
        }
        assert_eq!(c.validate(), Ok(()));
        assert_eq!(
            c.validate_timing(1_000_000, StepTiming::CONSERVATIVE),
            Err(ConfigError::StepRate(0))
        );
    }

    #[test]
    fn postcard_round_trip() {
        let c = cfg();
        let mut buf = [0u8; 512];
        let bytes = c.to_slice(&mut buf).expect("fits");
        let len = bytes.len();
        let back = MachineConfig::<3>::from_bytes(&buf[..len]).expect("decodes");
        assert_eq!(back, c);
        assert_eq!(
            MachineConfig::<3>::from_bytes(&buf[..len / 2]),
            Err(ConfigError::Encoding)
        );
    }
}
