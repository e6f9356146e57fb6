//! Single precision's square root, by the FPU's instruction where the core has one.
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
