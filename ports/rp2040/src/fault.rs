//! What happens when the firmware cannot go on: a panic, a hard fault, or a board that fails
//! to set up ([`reset`]): a watchdog reset of the whole chip but its oscillators, at once.
//! Every GPIO then returns to an input, so the STEP lines stop; the host sees `start` again.
//! This crate defines the firmware's panic handler and `HardFault` handler: a board links no
//! other.

/// Reset the chip now.
pub fn reset() -> ! {
    cortex_m::interrupt::disable();
    // SAFETY: the power-on state machine's watchdog selection (every block but the two
    // oscillators, as `rp2040_hal::Watchdog::start` sets it) and the watchdog's trigger bit.
    unsafe {
        let psm = &*rp2040_hal::pac::PSM::ptr();
        psm.wdsel().write(|w| w.bits(0x0001_fffc));
        let watchdog = &*rp2040_hal::pac::WATCHDOG::ptr();
        watchdog.ctrl().write(|w| w.trigger().set_bit());
    }
    loop {
        cortex_m::asm::nop();
    }
}

#[panic_handler]
fn panic(_info: &core::panic::PanicInfo) -> ! {
    reset()
}

#[cortex_m_rt::exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    reset()
}
