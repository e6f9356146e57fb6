//! Single precision's square root and conversions, by the FPU's instructions where the core
//! has them.
//!
//! `libm::sqrtf` is a software routine on every target it has no `arch` code for, the
//! Cortex-M4F among them, although its FPU computes the same correctly rounded root in one
//! instruction (`VSQRT.F32`). Every hard-float Arm target (`eabihf`) has that instruction; the
//! others (the ESP32-C3's RISC-V, the Cortex-M0+, hosts) take `libm`'s, whose result is the
//! same to the bit (IEEE 754's square root is correctly rounded).

/// `√x`, correctly rounded (NaN below zero).
#[cfg(all(target_arch = "arm", target_abi = "eabihf"))]
#[inline(always)]
pub(crate) fn sqrtf(x: f32) -> f32 {
    vsqrt::vsqrtf(x)
}

/// The instruction, as a function of the hard-float ABI (which passes and returns an `f32` in
/// `s0`): three instructions with the call, where `libm`'s routine runs a few dozen.
#[cfg(all(target_arch = "arm", target_abi = "eabihf"))]
#[allow(unsafe_code)]
mod vsqrt {
    core::arch::global_asm!(
        ".section .text.forja_motion_vsqrtf,\"ax\",%progbits",
        ".global forja_motion_vsqrtf",
        ".type forja_motion_vsqrtf,%function",
        ".fpu vfpv2",
        ".thumb_func",
        "forja_motion_vsqrtf:",
        "vsqrt.f32 s0, s0",
        "bx lr",
        ".size forja_motion_vsqrtf, . - forja_motion_vsqrtf",
    );

    unsafe extern "C" {
        /// `VSQRT.F32` on the argument: touches no memory, no stack, no register but `s0`.
        #[link_name = "forja_motion_vsqrtf"]
        pub(super) safe fn vsqrtf(x: f32) -> f32;
    }
}

/// `√x`, correctly rounded (NaN below zero).
#[cfg(not(all(target_arch = "arm", target_abi = "eabihf")))]
#[inline(always)]
pub(crate) fn sqrtf(x: f32) -> f32 {
    libm::sqrtf(x)
}

/// `w` in single precision, within 2⁻²² of it (three roundings): for estimates. On hard-float
/// Arm, two of the FPU's 32-bit conversions, a multiplication and an addition
/// (`split_f32`), where the exact 64-bit conversion is a software routine of about 30
/// instructions; elsewhere that routine, which the FPU-less cores need for 32 bits too.
#[inline(always)]
pub(crate) fn approx_f32(w: u64) -> f32 {
    #[cfg(all(target_arch = "arm", target_abi = "eabihf"))]
    {
        split_f32(w)
    }
    #[cfg(not(all(target_arch = "arm", target_abi = "eabihf")))]
    {
        w as f32
    }
}

/// `w` in single precision from its two 32-bit halves.
#[cfg(any(test, all(target_arch = "arm", target_abi = "eabihf")))]
#[inline(always)]
pub(crate) fn split_f32(w: u64) -> f32 {
    (w >> 32) as u32 as f32 * 4_294_967_296.0 + w as u32 as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_split_conversion_is_within_its_bound() {
        let mut x = 0x9e37_79b9_7f4a_7c15_u64;
        for k in 0..100_000u32 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // Every magnitude up to 2^62, the root estimate's range.
            let w = x >> (2 + k % 62);
            let error = (f64::from(split_f32(w)) - w as f64).abs();
            assert!(error <= w as f64 * 2f64.powi(-22), "{w}");
        }
        assert_eq!(sqrtf(approx_f32(1 << 40)), 1_048_576.0);
    }
}
