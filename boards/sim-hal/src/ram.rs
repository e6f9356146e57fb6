//! The simulated board's static RAM.
//!
//! A firmware board keeps what its interrupt and its thread share for its whole life in a
//! `static` (the step queue between the kernel and the step interrupt, split into two
//! `'static` halves). The simulator starts and stops boards in one process, so [`StaticRam`]
//! puts the value on the heap, lends it out as `'static`, and frees it when the board that
//! owns it is dropped.

use core::ptr::NonNull;

/// A value in static RAM: lent out as `'static` once, freed on drop. See the
/// [module documentation](self).
pub struct StaticRam<T>(NonNull<T>);

impl<T> StaticRam<T> {
    /// `value` in static RAM, and the one reference to it.
    ///
    /// # Safety
    ///
    /// Neither the reference nor anything made from it may be used once the `StaticRam` is
    /// dropped. Keep the `StaticRam` in the last field of the struct that holds its borrowers:
    /// fields drop in declaration order, so they are gone before it frees the value.
    #[allow(unsafe_code)]
    pub unsafe fn new(value: T) -> (Self, &'static mut T) {
        let ptr = NonNull::from(Box::leak(Box::new(value)));
        // SAFETY: the allocation lives until `drop`, which the caller runs after the last use
        // of this reference; no other reference to it is made.
        (Self(ptr), unsafe { &mut *ptr.as_ptr() })
    }
}

impl<T> Drop for StaticRam<T> {
    #[allow(unsafe_code)]
    fn drop(&mut self) {
        // SAFETY: the pointer comes from `Box::leak` in `new`, and its reference is no longer
        // used (the contract of `new`).
        drop(unsafe { Box::from_raw(self.0.as_ptr()) });
    }
}

impl<T> core::fmt::Debug for StaticRam<T> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("StaticRam")
    }
}

#[cfg(test)]
mod tests {
    use std::rc::Rc;

    use super::*;

    #[test]
    fn the_value_lives_until_the_ram_is_dropped() {
        let alive = Rc::new(());
        #[allow(unsafe_code)]
        // SAFETY: `value` is last used before `ram` is dropped.
        let (ram, value) = unsafe { StaticRam::new(Rc::clone(&alive)) };
        assert_eq!(Rc::strong_count(value), 2);
        drop(ram);
        assert_eq!(Rc::strong_count(&alive), 1, "freed with the RAM");
    }
}
