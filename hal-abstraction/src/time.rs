//! The one time type of the kernel.
//!
//! An [`Instant`] is a 32-bit tick count of a free-running clock whose rate the board states
//! (see [`crate::clock::Clock::tick_hz`]). It wraps; two instants compare correctly while they
//! are less than 2³¹ ticks apart (35 minutes at 1 MHz, 12.7 s at 168 MHz). The step generator
//! never schedules further ahead than that: long waits are cut into shorter alarms.

/// A point in time, in ticks of the board's clock. Compare with the wrapping methods, not `<`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Instant {
    ticks: u32,
}

/// A span of time, in ticks of the board's clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Duration {
    ticks: u32,
}

impl Instant {
    /// The instant at `ticks`.
    pub const fn from_ticks(ticks: u32) -> Self {
        Self { ticks }
    }

    /// The raw tick count.
    pub const fn ticks(self) -> u32 {
        self.ticks
    }

    /// This instant moved forward by `d`, wrapping.
    #[must_use]
    pub const fn wrapping_add(self, d: Duration) -> Self {
        Self {
            ticks: self.ticks.wrapping_add(d.ticks),
        }
    }

    /// Signed distance `self - earlier` in ticks: positive when `self` is later.
    pub const fn signed_ticks_since(self, earlier: Instant) -> i32 {
        self.ticks.wrapping_sub(earlier.ticks) as i32
    }

    /// `true` when `self` is at or after `other` (within 2³¹ ticks).
    pub const fn is_at_or_after(self, other: Instant) -> bool {
        self.signed_ticks_since(other) >= 0
    }

    /// The time elapsed from `earlier` to `self`, or zero when `earlier` is later.
    pub const fn saturating_duration_since(self, earlier: Instant) -> Duration {
        let d = self.signed_ticks_since(earlier);
        Duration {
            ticks: if d < 0 { 0 } else { d as u32 },
        }
    }
}

impl Duration {
    /// Zero ticks.
    pub const ZERO: Duration = Duration { ticks: 0 };

    /// A span of `ticks`.
    pub const fn from_ticks(ticks: u32) -> Self {
        Self { ticks }
    }

    /// The raw tick count.
    pub const fn ticks(self) -> u32 {
        self.ticks
    }

    /// `ns` nanoseconds at `tick_hz`, rounded up so that a minimum time is always honoured.
    pub const fn from_nanos_ceil(ns: u32, tick_hz: u32) -> Self {
        let t = (ns as u64 * tick_hz as u64).div_ceil(1_000_000_000);
        Self {
            ticks: if t > u32::MAX as u64 {
                u32::MAX
            } else {
                t as u32
            },
        }
    }

    /// `us` microseconds at `tick_hz`, rounded up.
    pub const fn from_micros_ceil(us: u32, tick_hz: u32) -> Self {
        let t = (us as u64 * tick_hz as u64).div_ceil(1_000_000);
        Self {
            ticks: if t > u32::MAX as u64 {
                u32::MAX
            } else {
                t as u32
            },
        }
    }

    /// This span in whole microseconds at `tick_hz`, rounded down.
    pub const fn to_micros(self, tick_hz: u32) -> u64 {
        self.ticks as u64 * 1_000_000 / tick_hz as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn comparison_survives_wrap() {
        let a = Instant::from_ticks(u32::MAX - 5);
        let b = a.wrapping_add(Duration::from_ticks(10));
        assert_eq!(b.ticks(), 4);
        assert!(b.is_at_or_after(a));
        assert!(!a.is_at_or_after(b));
        assert_eq!(b.signed_ticks_since(a), 10);
        assert_eq!(a.saturating_duration_since(b), Duration::ZERO);
        assert_eq!(b.saturating_duration_since(a).ticks(), 10);
    }

    #[test]
    fn conversions_round_up() {
        assert_eq!(Duration::from_nanos_ceil(1_000, 1_000_000).ticks(), 1);
        assert_eq!(Duration::from_nanos_ceil(1_001, 1_000_000).ticks(), 2);
        assert_eq!(Duration::from_nanos_ceil(2_000, 168_000_000).ticks(), 336);
        assert_eq!(Duration::from_micros_ceil(3, 1_000_000).ticks(), 3);
        assert_eq!(Duration::from_ticks(2_500).to_micros(1_000_000), 2_500);
    }
}
