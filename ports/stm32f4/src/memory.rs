//! The ARM EABI's memory helpers, each variant over one loop.
//!
//! The compiler calls `__aeabi_memset`, `__aeabi_memclr` and `__aeabi_memcpy` in variants for
//! destinations aligned to 1, 4 and 8 bytes. `compiler-builtins` gives each variant its own
//! copy of the loop (weak symbols, about 170 to 220 bytes each, unrolled), and its unaligned
//! copy shifts words for sources and destinations that share no word boundary (0.7 KiB). The
//! strong definitions here replace them, 1.9 KiB less code:
//! - setting is one word loop (`__aeabi_memset4`), which the unaligned variant reaches after
//!   the bytes up to the first word boundary; the 8-byte variant is the 4-byte one, which its
//!   alignment satisfies; clearing is setting zero;
//! - copying is one loop of four words a turn (`__aeabi_memcpy4`), which the unaligned variant
//!   reaches when source and destination share a word boundary, after the bytes up to it;
//!   otherwise it copies byte by byte.
//!
//! The loops go through `read_volatile` and `write_volatile`, so that the compiler does not
//! recognise them as a memset or memcpy and turn them back into a call to one. The kernel's
//! bench counts them where the kernel calls them (the planner copies lines), on this port's
//! image.

/// Set `n` bytes at `dest` to `c`.
///
/// # Safety
///
/// `dest` is valid for `n` bytes of writes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memset(mut dest: *mut u8, mut n: usize, c: i32) {
    // Bytes up to a word boundary, and a tail of fewer than four (`__aeabi_memset4` ends by
    // calling this function for its tail, which must not call it back).
    while n != 0 && (!(dest as usize).is_multiple_of(4) || n < 4) {
        // SAFETY: `dest` is within the `n` bytes the caller lent.
        unsafe {
            core::ptr::write_volatile(dest, c as u8);
            dest = dest.add(1);
        }
        n -= 1;
    }
    if n != 0 {
        // SAFETY: `dest` is now 4-byte aligned, with `n` bytes of the caller's left.
        unsafe { __aeabi_memset4(dest, n, c) }
    }
}

/// Set `n` bytes at `dest`, 4-byte aligned, to `c`.
///
/// # Safety
///
/// `dest` is valid for `n` bytes of writes and 4-byte aligned.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memset4(dest: *mut u8, mut n: usize, c: i32) {
    let word = u32::from(c as u8) * 0x0101_0101;
    let mut at = dest.cast::<u32>();
    while n >= 4 {
        // SAFETY: an aligned word within the `n` bytes the caller lent.
        unsafe {
            core::ptr::write_volatile(at, word);
            at = at.add(1);
        }
        n -= 4;
    }
    // SAFETY: the last `n` (< 4) bytes the caller lent: set byte by byte.
    unsafe { __aeabi_memset(at.cast(), n, c) }
}

/// Set `n` bytes at `dest`, 8-byte aligned, to `c`.
///
/// # Safety
///
/// `dest` is valid for `n` bytes of writes and 8-byte aligned (the EABI's contract).
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memset8(dest: *mut u8, n: usize, c: i32) {
    // SAFETY: 8-byte alignment is 4-byte alignment; the rest is the caller's contract.
    unsafe { __aeabi_memset4(dest, n, c) }
}

/// Clear `n` bytes at `dest`.
///
/// # Safety
///
/// `dest` is valid for `n` bytes of writes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memclr(dest: *mut u8, n: usize) {
    // SAFETY: the caller's contract.
    unsafe { __aeabi_memset(dest, n, 0) }
}

/// Clear `n` bytes at `dest`, 4-byte aligned.
///
/// # Safety
///
/// `dest` is valid for `n` bytes of writes and 4-byte aligned.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memclr4(dest: *mut u8, n: usize) {
    // SAFETY: the caller's contract.
    unsafe { __aeabi_memset4(dest, n, 0) }
}

/// Clear `n` bytes at `dest`, 8-byte aligned.
///
/// # Safety
///
/// `dest` is valid for `n` bytes of writes and 8-byte aligned.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memclr8(dest: *mut u8, n: usize) {
    // SAFETY: 8-byte alignment is 4-byte alignment; the rest is the caller's contract.
    unsafe { __aeabi_memset4(dest, n, 0) }
}

/// Copy `n` bytes from `src` to `dest`, not overlapping.
///
/// # Safety
///
/// `src` is valid for `n` bytes of reads, `dest` for `n` bytes of writes, and they do not
/// overlap.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memcpy(mut dest: *mut u8, mut src: *const u8, mut n: usize) {
    // When both share a word boundary: the bytes up to it, then words. Otherwise, and for a
    // tail of fewer than four (`__aeabi_memcpy4` ends by calling this function for its tail,
    // which must not call it back), byte by byte.
    let together = ((dest as usize) ^ (src as usize)).is_multiple_of(4);
    while n != 0 && (!together || !(dest as usize).is_multiple_of(4) || n < 4) {
        // SAFETY: within the `n` bytes the caller lent on each side.
        unsafe {
            core::ptr::write_volatile(dest, core::ptr::read_volatile(src));
            dest = dest.add(1);
            src = src.add(1);
        }
        n -= 1;
    }
    if n != 0 {
        // SAFETY: both are now 4-byte aligned, with `n` bytes of the caller's left.
        unsafe { __aeabi_memcpy4(dest, src, n) }
    }
}

/// Copy `n` bytes from `src` to `dest`, both 4-byte aligned, not overlapping.
///
/// # Safety
///
/// `src` is valid for `n` bytes of reads, `dest` for `n` bytes of writes, both 4-byte aligned,
/// and they do not overlap.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memcpy4(dest: *mut u8, src: *const u8, mut n: usize) {
    let (mut to, mut from) = (dest.cast::<u32>(), src.cast::<u32>());
    // SAFETY (both loops): aligned words within the `n` bytes the caller lent on each side.
    // Four words a turn, loaded before they are stored: the planner copies lines of hundreds
    // of bytes.
    while n >= 16 {
        unsafe {
            let a = core::ptr::read_volatile(from);
            let b = core::ptr::read_volatile(from.add(1));
            let c = core::ptr::read_volatile(from.add(2));
            let d = core::ptr::read_volatile(from.add(3));
            core::ptr::write_volatile(to, a);
            core::ptr::write_volatile(to.add(1), b);
            core::ptr::write_volatile(to.add(2), c);
            core::ptr::write_volatile(to.add(3), d);
            to = to.add(4);
            from = from.add(4);
        }
        n -= 16;
    }
    while n >= 4 {
        unsafe {
            core::ptr::write_volatile(to, core::ptr::read_volatile(from));
            to = to.add(1);
            from = from.add(1);
        }
        n -= 4;
    }
    // SAFETY: the last `n` (< 4) bytes the caller lent: copied byte by byte.
    unsafe { __aeabi_memcpy(to.cast(), from.cast(), n) }
}

/// Copy `n` bytes from `src` to `dest`, both 8-byte aligned, not overlapping.
///
/// # Safety
///
/// `src` is valid for `n` bytes of reads, `dest` for `n` bytes of writes, both 8-byte aligned,
/// and they do not overlap.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memcpy8(dest: *mut u8, src: *const u8, n: usize) {
    // SAFETY: 8-byte alignment is 4-byte alignment; the rest is the caller's contract.
    unsafe { __aeabi_memcpy4(dest, src, n) }
}
