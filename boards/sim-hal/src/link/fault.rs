//! A fault injector for links, in the manner of smoltcp's `phy/fault_injector.rs`.
//!
//! [`FaultInjector`] wraps any [`PortLink`] and, at configured rates, **drops** and
//! **corrupts** (flips one bit of) the bytes received from the host. It is seeded and
//! reproducible: the same seed and the same received bytes give the same faults, run after
//! run, so a failure found with `--seed 42` can be replayed.
//!
//! # Only the host → controller direction
//!
//! Faults are injected only into what the firmware receives. That is the direction the
//! firmware's own protocol code must survive (line checksums, resend requests, frame CRCs),
//! and what this tool exists to test. Replies to the host are left intact because the hosts
//! Forja talks to are not all robust to a lost reply: a RepRap-style sender that loses an
//! `ok` waits for it forever, so a corrupted reply direction would test the host, not the
//! firmware.
//!
//! # Algorithm
//!
//! A ChaCha8 generator seeded with [`FaultConfig::seed`] (`SeedableRng::seed_from_u64`). For
//! each received byte, one 64-bit draw `u` (as `(u >> 11) / 2⁵³`, uniform in [0, 1)) drops it
//! when below `drop_rate`; otherwise a second draw corrupts it when below `corrupt_rate`, and
//! a third picks the bit to flip (`draw % 8`). The counts are in [`FaultStats`].

use core::fmt;
use std::collections::VecDeque;

use embedded_io::{ErrorType, Read, ReadReady, Write, WriteReady};
use forja_drivers::port_link::Admission;
use forja_hal_abstraction::link::{LinkState, LinkStatus};
use rand_chacha::ChaCha8Rng;
use rand_core::{Rng, SeedableRng};

use super::{PortLink, RX_CAPACITY};

/// Fault rates and seed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FaultConfig {
    /// Probability that a received byte is corrupted (one bit flipped), 0..=1.
    pub corrupt_rate: f64,
    /// Probability that a received byte is dropped, 0..=1.
    pub drop_rate: f64,
    /// Seed of the generator.
    pub seed: u64,
}

impl FaultConfig {
    /// No faults.
    pub const NONE: FaultConfig = FaultConfig {
        corrupt_rate: 0.0,
        drop_rate: 0.0,
        seed: 0,
    };

    /// Whether the rates are probabilities.
    ///
    /// Errors: the first rate outside 0..=1 (or not a number).
    pub fn validate(&self) -> Result<(), FaultConfigError> {
        if !(0.0..=1.0).contains(&self.corrupt_rate) {
            return Err(FaultConfigError::CorruptRate(self.corrupt_rate));
        }
        if !(0.0..=1.0).contains(&self.drop_rate) {
            return Err(FaultConfigError::DropRate(self.drop_rate));
        }
        Ok(())
    }

    /// Whether any fault is configured.
    pub fn is_active(&self) -> bool {
        self.corrupt_rate > 0.0 || self.drop_rate > 0.0
    }
}

/// A fault rate outside 0..=1.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum FaultConfigError {
    /// The corruption rate.
    CorruptRate(f64),
    /// The drop rate.
    DropRate(f64),
}

impl fmt::Display for FaultConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::CorruptRate(r) => write!(f, "corrupt rate {r} is not in 0..=1"),
            Self::DropRate(r) => write!(f, "drop rate {r} is not in 0..=1"),
        }
    }
}

impl std::error::Error for FaultConfigError {}

/// What the injector did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct FaultStats {
    /// Bytes received from the host.
    pub bytes: u64,
    /// Bytes dropped.
    pub dropped: u64,
    /// Bytes corrupted.
    pub corrupted: u64,
}

/// The fault generator on its own, without a link: feeds bytes through the faults.
#[derive(Debug, Clone)]
pub struct FaultyBytes {
    config: FaultConfig,
    rng: ChaCha8Rng,
    stats: FaultStats,
}

impl FaultyBytes {
    /// A generator for `config`.
    ///
    /// Errors: a rate outside 0..=1.
    pub fn new(config: FaultConfig) -> Result<Self, FaultConfigError> {
        config.validate()?;
        Ok(Self {
            config,
            rng: ChaCha8Rng::seed_from_u64(config.seed),
            stats: FaultStats::default(),
        })
    }

    fn unit(&mut self) -> f64 {
        (self.rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// One received byte through the faults: `None` when dropped.
    pub fn apply(&mut self, byte: u8) -> Option<u8> {
        self.stats.bytes += 1;
        if self.config.drop_rate > 0.0 && self.unit() < self.config.drop_rate {
            self.stats.dropped += 1;
            return None;
        }
        if self.config.corrupt_rate > 0.0 && self.unit() < self.config.corrupt_rate {
            self.stats.corrupted += 1;
            let bit = (self.rng.next_u64() % 8) as u8;
            return Some(byte ^ (1 << bit));
        }
        Some(byte)
    }

    /// Bytes through the faults, appended to `out`.
    pub fn apply_all(&mut self, bytes: &[u8], out: &mut impl Extend<u8>) {
        out.extend(bytes.iter().filter_map(|&b| self.apply(b)));
    }

    /// What it did so far.
    pub fn stats(&self) -> FaultStats {
        self.stats
    }

    /// Its configuration.
    pub fn config(&self) -> FaultConfig {
        self.config
    }
}

/// A link whose received bytes go through [`FaultyBytes`]; everything else passes through.
/// Implements [`PortLink`], and [`WriteReady`] over a link that does.
#[derive(Debug)]
pub struct FaultInjector<L> {
    inner: L,
    faults: FaultyBytes,
    rx: VecDeque<u8>,
}

impl<L: PortLink> FaultInjector<L> {
    /// Wrap `inner` with the faults of `config`.
    ///
    /// Errors: a rate outside 0..=1.
    pub fn new(inner: L, config: FaultConfig) -> Result<Self, FaultConfigError> {
        Ok(Self {
            inner,
            faults: FaultyBytes::new(config)?,
            rx: VecDeque::new(),
        })
    }

    /// What it did so far.
    pub fn stats(&self) -> FaultStats {
        self.faults.stats()
    }

    /// The wrapped link.
    pub fn inner(&self) -> &L {
        &self.inner
    }

    /// The wrapped link, mutably (bytes read from it directly bypass the faults).
    pub fn inner_mut(&mut self) -> &mut L {
        &mut self.inner
    }

    /// The wrapped link back; bytes already received and not read are lost.
    pub fn into_inner(self) -> L {
        self.inner
    }

    /// Move what the inner link has received through the faults, without blocking.
    fn pull(&mut self) -> Result<(), L::Error> {
        let mut chunk = [0u8; 1024];
        while self.rx.len() < RX_CAPACITY && self.inner.read_ready()? {
            let n = self.inner.read(&mut chunk)?;
            if n == 0 {
                break;
            }
            self.faults.apply_all(&chunk[..n], &mut self.rx);
        }
        Ok(())
    }
}

impl<L: PortLink> ErrorType for FaultInjector<L> {
    type Error = L::Error;
}

impl<L: PortLink> ReadReady for FaultInjector<L> {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        if self.rx.is_empty() {
            self.pull()?;
        }
        Ok(!self.rx.is_empty())
    }
}

impl<L: PortLink> Read for FaultInjector<L> {
    /// Blocks like the inner link's `read` until a byte survives the faults; `Ok(0)` when the
    /// inner link reaches its end.
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        if buf.is_empty() {
            return Ok(0);
        }
        let mut chunk = [0u8; 1024];
        while self.rx.is_empty() {
            self.pull()?;
            if !self.rx.is_empty() {
                break;
            }
            let n = self.inner.read(&mut chunk)?;
            if n == 0 {
                return Ok(0);
            }
            self.faults.apply_all(&chunk[..n], &mut self.rx);
        }
        let n = buf.len().min(self.rx.len());
        for (dst, src) in buf.iter_mut().zip(self.rx.drain(..n)) {
            *dst = src;
        }
        Ok(n)
    }
}

impl<L: PortLink + WriteReady> WriteReady for FaultInjector<L> {
    fn write_ready(&mut self) -> Result<bool, Self::Error> {
        self.inner.write_ready()
    }
}

impl<L: PortLink> Write for FaultInjector<L> {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.inner.write(buf)
    }

    fn flush(&mut self) -> Result<(), Self::Error> {
        self.inner.flush()
    }
}

impl<L: PortLink> LinkStatus for FaultInjector<L> {
    fn state(&self) -> LinkState {
        self.inner.state()
    }
}

impl<L: PortLink> PortLink for FaultInjector<L> {
    fn poll(&mut self) -> Result<(), Self::Error> {
        self.inner.poll()?;
        self.pull()
    }

    fn connections(&self) -> u64 {
        self.inner.connections()
    }

    fn admit(&mut self, gate: &mut dyn Admission, now_ms: u32) -> Result<bool, Self::Error> {
        self.inner.admit(gate, now_ms)
    }

    fn discard_input(&mut self) -> Result<usize, Self::Error> {
        let mine = self.rx.len();
        self.rx.clear();
        Ok(mine + self.inner.discard_input()?)
    }

    fn hang_up(&mut self) {
        self.inner.hang_up();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::MemoryLink;

    fn run(config: FaultConfig, input: &[u8]) -> (Vec<u8>, FaultStats) {
        let mut f = FaultyBytes::new(config).unwrap();
        let mut out = Vec::new();
        f.apply_all(input, &mut out);
        (out, f.stats())
    }

    fn input(n: usize) -> Vec<u8> {
        (0..n).map(|i| b"G1 X10 Y20 F3000\n"[i % 17]).collect()
    }

    #[test]
    fn same_seed_same_faults() {
        let c = FaultConfig {
            corrupt_rate: 0.01,
            drop_rate: 0.005,
            seed: 42,
        };
        let data = input(50_000);
        let (a, sa) = run(c, &data);
        let (b, sb) = run(c, &data);
        assert_eq!(a, b);
        assert_eq!(sa, sb);
        let (c2, _) = run(FaultConfig { seed: 43, ..c }, &data);
        assert_ne!(a, c2, "another seed gives other faults");
    }

    #[test]
    fn rates_are_hit_within_tolerance() {
        let c = FaultConfig {
            corrupt_rate: 0.01,
            drop_rate: 0.005,
            seed: 7,
        };
        let n = 200_000;
        let data = input(n);
        let (out, s) = run(c, &data);
        assert_eq!(s.bytes, n as u64);
        assert_eq!(out.len() as u64, s.bytes - s.dropped);
        // Binomial: 1000 expected drops (sd ~32), ~1990 corruptions (sd ~44): 5 sd bounds.
        assert!((840..=1160).contains(&s.dropped), "{s:?}");
        assert!((1770..=2210).contains(&s.corrupted), "{s:?}");
        // A corrupted byte differs from the original in exactly one bit. Without drops the
        // output lines up with the input.
        let (out, s) = run(
            FaultConfig {
                drop_rate: 0.0,
                ..c
            },
            &data,
        );
        let flipped: Vec<u32> = out
            .iter()
            .zip(&data)
            .map(|(a, b)| (a ^ b).count_ones())
            .filter(|&d| d != 0)
            .collect();
        assert_eq!(flipped.len() as u64, s.corrupted);
        assert!(flipped.iter().all(|&d| d == 1));
    }

    #[test]
    fn no_faults_pass_everything() {
        let data = input(10_000);
        let (out, s) = run(FaultConfig::NONE, &data);
        assert_eq!(out, data);
        assert_eq!((s.dropped, s.corrupted), (0, 0));
        assert!(!FaultConfig::NONE.is_active());
    }

    #[test]
    fn rates_are_checked() {
        let bad = FaultConfig {
            corrupt_rate: 1.5,
            ..FaultConfig::NONE
        };
        assert_eq!(
            FaultyBytes::new(bad).unwrap_err(),
            FaultConfigError::CorruptRate(1.5)
        );
        let bad = FaultConfig {
            drop_rate: f64::NAN,
            ..FaultConfig::NONE
        };
        assert!(bad.validate().is_err());
        assert_eq!(
            FaultConfigError::DropRate(-1.0).to_string(),
            "drop rate -1 is not in 0..=1"
        );
    }

    #[test]
    fn wraps_a_link_and_leaves_replies_alone() {
        let (fw, host) = MemoryLink::pair();
        let config = FaultConfig {
            corrupt_rate: 0.05,
            drop_rate: 0.05,
            seed: 1,
        };
        let mut link = FaultInjector::new(fw, config).unwrap();
        let data = input(20_000);
        host.send(&data);
        link.poll().unwrap();
        let mut got = Vec::new();
        let mut buf = [0u8; 333];
        while link.read_ready().unwrap() {
            let n = link.read(&mut buf).unwrap();
            got.extend_from_slice(&buf[..n]);
        }
        // The link sees exactly what the bare generator produces for the same bytes.
        let (expected, stats) = run(config, &data);
        assert_eq!(got, expected);
        assert_eq!(link.stats(), stats);
        assert!(stats.dropped > 0 && stats.corrupted > 0);

        // The reply direction is untouched.
        let reply = input(20_000);
        link.write_all(&reply).unwrap();
        assert_eq!(host.take_received(), reply);
        assert_eq!(link.state(), LinkState::Connected);
        assert_eq!(link.connections(), 1);

        // Blocking read ends with the inner link's end of file.
        drop(host);
        assert_eq!(link.read(&mut buf).unwrap(), 0);
    }
}
