//! The simulated beeper (`M300`).
//!
//! [`SimBeeper`] implements [`Beeper`] as the contract asks: each tone sounds once the tones
//! handed over before it have played, for its duration, then stops; a frequency of 0 is a
//! pause. It keeps the machine file's [`BeeperConfig::waiting_tones`] waiting behind the one it
//! sounds and does not play a tone beyond them. It records every tone it plays with the virtual
//! times it starts and ends ([`SimMachine::tones`]), and counts those it did not play
//! ([`SimMachine::dropped_tones`]).

use core::fmt;

use forja_hal_abstraction::device::{Beeper, DeviceError};

use crate::config::BeeperConfig;
use crate::machine::{NoSuchDevice, SimMachine};

/// A tone the beeper plays, or a pause (`frequency_hz` 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Tone {
    /// Virtual time it starts, in ticks since start.
    pub start_ticks: u64,
    /// Virtual time it ends, in ticks since start.
    pub end_ticks: u64,
    /// The pitch, Hz; 0 for a pause.
    pub frequency_hz: u16,
    /// How long, ms.
    pub duration_ms: u16,
}

/// The beeper's queue and what it played.
pub(crate) struct BeeperState {
    waiting_tones: usize,
    tones: Vec<Tone>,
    dropped: u64,
}

impl BeeperState {
    pub(crate) fn new(config: &BeeperConfig) -> Self {
        Self {
            waiting_tones: config.waiting_tones,
            tones: Vec::new(),
            dropped: 0,
        }
    }
}

impl SimMachine {
    /// The beeper.
    ///
    /// Errors: [`NoSuchDevice::Beeper`] when the machine file has none.
    pub fn beeper(&self) -> Result<SimBeeper, NoSuchDevice> {
        if self.state.borrow().beeper.is_none() {
            return Err(NoSuchDevice::Beeper);
        }
        Ok(SimBeeper {
            machine: self.clone(),
        })
    }

    /// Every tone and pause the beeper was handed and plays, in order, with the times it
    /// sounds (those still waiting included); empty without a beeper.
    pub fn tones(&self) -> Vec<Tone> {
        let s = self.state.borrow();
        s.beeper.as_ref().map_or_else(Vec::new, |b| b.tones.clone())
    }

    /// The tones the beeper was handed while its queue was full, and did not play.
    pub fn dropped_tones(&self) -> u64 {
        self.state.borrow().beeper.as_ref().map_or(0, |b| b.dropped)
    }

    /// The pitch the beeper sounds now, Hz; `None` when it is silent (or in a pause).
    pub fn sounding_hz(&self) -> Option<u16> {
        let s = self.state.borrow();
        let now = s.now;
        s.beeper
            .as_ref()?
            .tones
            .iter()
            .find(|t| t.start_ticks <= now && now < t.end_ticks && t.frequency_hz > 0)
            .map(|t| t.frequency_hz)
    }
}

/// The simulated beeper: implements [`Beeper`]. Never fails.
#[derive(Clone)]
pub struct SimBeeper {
    machine: SimMachine,
}

impl fmt::Debug for SimBeeper {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimBeeper").finish_non_exhaustive()
    }
}

impl Beeper for SimBeeper {
    fn tone(&mut self, frequency_hz: u16, duration_ms: u16) -> Result<(), DeviceError> {
        let mut s = self.machine.state.borrow_mut();
        let (now, tick_hz) = (s.now, s.tick_hz);
        let Some(b) = s.beeper.as_mut() else {
            return Ok(());
        };
        let waiting = b.tones.iter().filter(|t| t.start_ticks > now).count();
        if waiting >= b.waiting_tones {
            b.dropped += 1;
            return Ok(());
        }
        let start_ticks = b.tones.last().map_or(now, |t| t.end_ticks.max(now));
        let length = u64::from(duration_ms) * u64::from(tick_hz) / 1000;
        b.tones.push(Tone {
            start_ticks,
            end_ticks: start_ticks + length,
            frequency_hz,
            duration_ms,
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MachineConfig;

    fn printer() -> SimMachine {
        let text = MachineConfig::bundled_toml("printer").unwrap();
        SimMachine::new(&MachineConfig::from_toml_str(text).unwrap())
    }

    #[test]
    fn tones_play_one_after_another_with_their_pauses() {
        let m = printer();
        let mut beeper = m.beeper().unwrap();
        m.advance_to(1_000);
        beeper.tone(440, 200).unwrap();
        beeper.tone(0, 100).unwrap();
        beeper.tone(880, 50).unwrap();
        let tone = |start_ticks, end_ticks, frequency_hz, duration_ms| Tone {
            start_ticks,
            end_ticks,
            frequency_hz,
            duration_ms,
        };
        assert_eq!(
            m.tones(),
            [
                tone(1_000, 201_000, 440, 200),
                tone(201_000, 301_000, 0, 100),
                tone(301_000, 351_000, 880, 50)
            ]
        );
        assert_eq!(m.sounding_hz(), Some(440));
        m.advance_to(250_000);
        assert_eq!(m.sounding_hz(), None, "the pause");
        m.advance_to(320_000);
        assert_eq!(m.sounding_hz(), Some(880));
        // Silent again: the next tone sounds at once.
        m.advance_to(2_000_000);
        assert_eq!(m.sounding_hz(), None);
        beeper.tone(660, 10).unwrap();
        assert_eq!(m.tones()[3], tone(2_000_000, 2_010_000, 660, 10));
    }

    #[test]
    fn a_tone_beyond_the_waiting_ones_is_not_played() {
        let m = printer();
        let mut beeper = m.beeper().unwrap();
        // One sounding and the machine file's four waiting.
        for _ in 0..5 {
            beeper.tone(440, 100).unwrap();
        }
        beeper.tone(880, 100).unwrap();
        assert_eq!(m.tones().len(), 5);
        assert_eq!(m.dropped_tones(), 1);
        // Once the first has played, one more waits.
        m.advance_to(100_000);
        beeper.tone(880, 100).unwrap();
        assert_eq!(m.tones().len(), 6);
        assert_eq!(m.tones()[5].start_ticks, 500_000);
    }

    #[test]
    fn a_machine_without_a_beeper_has_none() {
        let m = SimMachine::new(&MachineConfig::default_router());
        assert_eq!(m.beeper().unwrap_err(), NoSuchDevice::Beeper);
        assert!(m.tones().is_empty());
        assert_eq!((m.dropped_tones(), m.sounding_hz()), (0, None));
    }
}
