//! The modal state a program leaves after some of its lines, worked out without moving: what a
//! job resumed after a power cut takes before it goes on.
//!
//! A [`Replay`] starts from the power-on modal state (mm, absolute, no offsets) at the
//! kernel's position and runs the program's lines through the kernel's interpreter, moving
//! nothing: a homing line leaves the homed axes where they are now (the machine has just been
//! homed), and a line the kernel would refuse changes nothing, as when it ran. The application
//! then brings the machine to [`Replay::position`] and hands the state to the kernel
//! ([`Kernel::take_modal_state`](crate::Kernel::take_modal_state)).
//!
//! Context: thread.

use forja_protocol::gcode::Line;

use crate::config::MachineConfig;
use crate::coords::Coordinates;
use crate::interp::{Action, Interpreter};
use crate::kernel::Kernel;

/// The modal state after some of a program's lines. See the [module documentation](self).
#[derive(Clone, Copy)]
pub struct Replay<const N: usize> {
    pub(crate) interp: Interpreter<N>,
    here: [i64; N],
    coords: Coordinates<N>,
}

impl<const N: usize> Replay<N> {
    /// The power-on modal state at the position `kernel`'s last queued move ends.
    pub fn new<const B: usize, const Q: usize>(kernel: &Kernel<'_, N, B, Q>) -> Self {
        let here = kernel.commanded_position_nm();
        let mut interp = Interpreter::new(kernel.config());
        interp.pos = here;
        let coords = *kernel.coordinates();
        interp.use_coordinates(&coords);
        Self {
            interp,
            here,
            coords,
        }
    }

    /// Take the program's next line into the state.
    pub fn line(&mut self, line: &Line<'_>, config: &MachineConfig<N>) {
        let mut next = self.interp;
        match next.interpret(line, config, &self.coords) {
            Ok(Action::Home { mask }) => {
                for (i, h) in self.here.iter().enumerate() {
                    if mask & (1 << i) != 0 {
                        next.pos[i] = *h;
                    }
                }
                self.interp = next;
            }
            Ok(_) => self.interp = next,
            Err(_) => {}
        }
    }

    /// Where the lines taken so far leave the machine, in machine nanometres per axis.
    pub fn position(&self) -> [i64; N] {
        self.interp.pos
    }
}
