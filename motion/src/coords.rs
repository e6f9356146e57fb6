//! Work coordinate systems and stored positions: the parameters of grbl's `$#` and of
//! LinuxCNC's parameter file.
//!
//! A program's coordinates are work coordinates: work = machine − the origin of the active
//! system (`G54`–`G59.3`, set with `G10 L2`/`L20`) − the `G92` offset − the tool length offset
//! (`G43.1`, on Z). The kernel keeps the table; the application stores it with the settings so
//! that it survives a power cut (grbl keeps it in EEPROM), and gives it back at start-up.

/// Positions in nanometres.
pub type Nm = i64;

/// The number of work coordinate systems: `G54`–`G59`, `G59.1`–`G59.3`.
pub const SYSTEMS: usize = 9;

/// The work coordinate systems and the stored positions, machine nanometres per axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Coordinates<const N: usize> {
    /// The origin of each system, `G54` first: the machine position of its work zero.
    pub systems: [[Nm; N]; SYSTEMS],
    /// `G28.1`'s stored position (where a grbl `G28` goes).
    pub g28: [Nm; N],
    /// `G30.1`'s stored position (where a grbl `G30` goes).
    pub g30: [Nm; N],
}

impl<const N: usize> Coordinates<N> {
    /// Every origin and stored position at machine zero.
    pub const ZERO: Self = Self {
        systems: [[0; N]; SYSTEMS],
        g28: [0; N],
        g30: [0; N],
    };

    /// The origin of system `index` (0 for `G54`), zero past the last.
    pub fn system(&self, index: usize) -> [Nm; N] {
        self.systems.get(index).copied().unwrap_or([0; N])
    }
}

impl<const N: usize> Default for Coordinates<N> {
    fn default() -> Self {
        Self::ZERO
    }
}

/// A change of the table, for the kernel to make and the application to store.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Slot {
    /// A work coordinate system, 0 for `G54`.
    System(u8),
    /// `G28.1`.
    G28,
    /// `G30.1`.
    G30,
}

impl Slot {
    /// The slot's place in a record numbering: 0–8 the systems, 9 `G28`, 10 `G30`.
    pub const fn index(self) -> u8 {
        match self {
            Self::System(i) => i,
            Self::G28 => 9,
            Self::G30 => 10,
        }
    }

    /// The slot of [`Slot::index`] `i`.
    pub const fn from_index(i: u8) -> Option<Self> {
        match i {
            0..=8 => Some(Self::System(i)),
            9 => Some(Self::G28),
            10 => Some(Self::G30),
            _ => None,
        }
    }

    /// Every slot, in [`Slot::index`] order.
    pub fn all() -> impl Iterator<Item = Slot> {
        (0..11).filter_map(Self::from_index)
    }
}

impl<const N: usize> Coordinates<N> {
    /// The positions of `slot`.
    pub fn get(&self, slot: Slot) -> [Nm; N] {
        match slot {
            Slot::System(i) => self.system(usize::from(i)),
            Slot::G28 => self.g28,
            Slot::G30 => self.g30,
        }
    }

    /// Set the positions of `slot`.
    pub fn set(&mut self, slot: Slot, values: [Nm; N]) {
        match slot {
            Slot::System(i) => {
                if let Some(s) = self.systems.get_mut(usize::from(i)) {
                    *s = values;
                }
            }
            Slot::G28 => self.g28 = values,
            Slot::G30 => self.g30 = values,
        }
    }
}
