//! The ARM EABI's memory helpers, each variant over one implementation.
//!
//! The compiler calls `__aeabi_memset`, `__aeabi_memclr` and `__aeabi_memcpy` in variants for
//! destinations aligned to 1, 4 and 8 bytes. `compiler-builtins` gives each variant its own
//! copy of the loop (weak symbols, about 170 to 220 bytes each, unrolled). The strong
//! definitions here replace them:
//! - setting is one word loop (`__aeabi_memset4`), which the unaligned variant reaches after
//!   the bytes up to the first word boundary; the 8-byte variant is the 4-byte one, which its
//!   alignment satisfies; clearing is setting zero;
//! - copying 8-byte aligned data is the 4-byte aligned copy.
//!
//! 1.2 KiB less code. Nothing that runs per step sets or copies memory through them (the
//! kernel's bench counts it), so the plain loops cost only the controller's rarer work.
//!
//! The loops write through `write_volatile`, so that the compiler does not recognise them as a
//! memset and turn them back into a call to one.

/// `compiler-builtins`' implementation that remains.
mod builtins {
    unsafe extern "C" {
        pub fn __aeabi_memcpy4(dest: *mut u8, src: *const u8, n: usize);
    }
}

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

/// Copy `n` bytes from `src` to `dest`, both 8-byte aligned, not overlapping.
///
/// # Safety
///
/// `src` is valid for `n` bytes of reads, `dest` for `n` bytes of writes, both 8-byte aligned,
/// and they do not overlap.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn __aeabi_memcpy8(dest: *mut u8, src: *const u8, n: usize) {
    // SAFETY: 8-byte alignment is 4-byte alignment; the rest is the caller's contract.
    unsafe { builtins::__aeabi_memcpy4(dest, src, n) }
}
