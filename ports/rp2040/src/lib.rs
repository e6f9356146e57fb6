//! # Forja's RP2040 chip support
//!
//! What every RP2040 board of Forja shares, over `rp2040-hal` 0.12: the step clock and its
//! alarms on the TIMER, the host link on a UART, the limit switches' GPIO interrupt, the
//! settings and program stores on the QSPI flash the chip runs from, the watchdog, and the
//! fault handlers. This is the per-MCU driver of grblHAL (`RP2040/`) or the `src/rp2040/` of
//! Klipper: a board crate (`boards/rp2040`) keeps only its wiring (the pin map, the crystal,
//! the boot loader for its flash chip, the store regions, interrupt bindings and priorities)
//! and hands the parts this crate makes to the application layer
//! (`forja_app::firmware::assemble_motion`).
//!
//! ## Layer and contract
//!
//! - Depends on the chip HAL, `cortex-m`, and Forja's portable crates: the traits
//!   (`forja-hal-abstraction`), the drivers (`forja-drivers`: `LimitInput`, `UartBuffers`,
//!   `FlashRecordStorage`), the kernel's `SwitchAlert`, and the application's start-up errors
//!   (`SetupError`). Knows no board: it chooses no pin, no UART instance, no store region, no
//!   priority, and binds no interrupt.
//! - Every constructor runs in init, once; errors are `forja_app::firmware::SetupError`, on
//!   which the board resets ([`fault::reset`]).
//! - The interrupt entries below are short, allocation-free and never block; the board's
//!   handler for each vector calls exactly one:
//!
//! | module | what | the board's interrupt handler calls |
//! |---|---|---|
//! | [`timer`] | the TIMER's microsecond counter as the step clock, its alarms | TIMER_IRQ_`N`: [`TimerAlarm::take`](timer::TimerAlarm::take), then the step generator and `set_alarm` |
//! | [`uart`] | the host UART over the drivers' queues, [`HostLink`](uart::HostLink) for the controller | the UART's vector: [`HostUart::on_interrupt`](uart::HostUart::on_interrupt) |
//! | [`limits`] | the switches' edge interrupts and their debounced `LimitInput`s, [`Edges`](limits::Edges) for the thread side | IO_IRQ_BANK0: [`limits::on_interrupt`] |
//! | [`flash`] | a region of the QSPI flash as a `NorFlash`, written through the boot ROM from RAM | — (thread: stalls every interrupt for a sector erase) |
//! | [`watchdog`] | the watchdog, 1 s | — (fed by the board's controller task) |
//! | [`fault`] | panic and `HardFault` handlers: a watchdog reset at once | — |
//!
//! ## What a board provides
//!
//! - A linker script that ends FLASH below the store regions and defines `_storage_start` and
//!   `_storage_end` around them (checked at start, [`flash::store`]); the second-stage boot
//!   loader for its flash chip.
//! - `rp2040-hal`'s `critical-section-impl` (or another `critical-section` implementation);
//!   the spinlocks reset at start (`rp2040_hal::sio::spinlock_reset`).
//! - A kick for the UART's writer: a function that pends the UART's interrupt.
#![no_std]

pub mod fault;
pub mod flash;
pub mod limits;
pub mod timer;
pub mod uart;
pub mod watchdog;
