//! # Forja's STM32F4 chip support
//!
//! What every STM32F4 board of Forja shares, over `stm32f4xx-hal` 0.23: the step timer and its
//! clock, the host UART and its counters, the limit switches' EXTI lines, the settings and
//! program store in flash, the watchdog, and the fault handlers. This is the per-MCU driver of
//! grblHAL (`STM32F4xx/`) or the `src/stm32/` of Klipper: a board crate (`boards/stm32f4`)
//! keeps only its wiring (pin maps, clocks, the choice of UART, interrupt bindings and
//! priorities) and hands the parts this crate makes to the application layer
//! (`forja_app::firmware::assemble_motion`).
//!
//! ## Layer and contract
//!
//! - Depends on the chip HAL, `cortex-m`, and Forja's portable crates: the traits
//!   (`forja-hal-abstraction`), the drivers (`forja-drivers`: `StepDir`, `LimitInput`,
//!   `UartBuffers`, `FlashRecordStorage`, `StoreSlot`), the kernel's `SwitchAlert`, and the
//!   application's start-up errors (`SetupError`) and statistics. Knows no board: it chooses
//!   no pin, no UART instance, no priority, and binds no interrupt.
//! - Every constructor runs in init, once; errors are `forja_app::firmware::SetupError`, on
//!   which the board resets ([`fault::reset`]).
//! - The interrupt entries below are short, allocation-free and never block; the board's
//!   handler for each vector calls exactly one:
//!
//! | module | what | the board's interrupt handler calls |
//! |---|---|---|
//! | [`timer`] | TIM2 as the step clock and alarm, 1 kHz service tick (SysTick under `qemu`) | TIM2 (SysTick): [`StepTimer::serve`](timer::StepTimer::serve) with the step generator |
//! | [`uart`] | the host UART over the drivers' queues, [`HostLink`](uart::HostLink) for the controller, `FORJA_LINK_COUNTERS` | the UART's vector: [`HostUart::on_interrupt`](uart::HostUart::on_interrupt) |
//! | [`limits`] | the switches' EXTI lines and their debounced `LimitInput`s | EXTI9_5 / EXTI15_10 (the lines used): [`Limits::on_interrupt`](limits::Limits::on_interrupt) |
//! | [`flash`] | sectors 1–2 as a `NorFlash`, one record store shared by settings and program | — (thread: may stall for a sector erase) |
//! | [`watchdog`] | the IWDG, 1 s | — (fed by the board's periodic task) |
//! | [`fault`] | panic and `HardFault` handlers: reset at once | — |
//! | [`memory`] | the EABI's memory helpers, one implementation per kind | — (called by compiled code) |
//!
//! ## What a board provides
//!
//! - One chip feature (`stm32f411`, `stm32f405`), and `qemu` for QEMU's `netduinoplus2`.
//! - A linker script that reserves flash sectors 1 and 2 for the store and defines
//!   `_storage_start` and `_storage_end` around them (checked at start, [`flash`]).
//! - A `critical-section` implementation (`cortex-m`'s `critical-section-single-core`).
//! - A kick for the UART's writer: a function that pends the UART's interrupt.
//!
//! ## Features
//!
//! | feature | selects |
//! |---|---|
//! | `stm32f411`, `stm32f405` | the chip, passed to `stm32f4xx-hal` |
//! | `qemu` | the chip as QEMU 7.2 emulates it: SysTick step clock, store in RAM, no watchdog |
#![no_std]

pub mod fault;
pub mod flash;
pub mod limits;
pub mod memory;
pub mod timer;
pub mod uart;
pub mod watchdog;
