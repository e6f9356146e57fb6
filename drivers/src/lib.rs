//! # Forja drivers
//!
//! Concrete drivers for the traits of [`forja_hal_abstraction`], written against
//! `embedded-hal` 1.0, `embedded-io` and `embedded-storage` only: no chip, no vendor HAL, no
//! executor, no Forja crate but the traits' own. A board crate builds them from its HAL's pins,
//! PWM channels, ADC, UART and flash, and lists them for the application layer (`forja-app`).
//! The machine's devices (temperature zones, fans, the spindle, coolant, outputs) implement
//! the object-safe traits of `forja_hal_abstraction::device` and apply exactly what they are
//! told: the G-code rules (an `M3` without `S` keeps the last speed, how close to its target a
//! heater must be for `M109` to go on) are the application's.
//!
//! ## Drivers and their execution contexts
//!
//! | module | driver | implements | context |
//! |---|---|---|---|
//! | [`stepper`] | [`StepDir`](stepper::StepDir) | `Stepper` (interrupt), `StepperEnable` (thread) | step edges in the step interrupt: one pin write each |
//! | [`limit`] | [`LimitInput`](limit::LimitInput) | `LimitSwitch` | either: polled by the step interrupt, one pin read |
//! | [`uart`] | [`UartBuffers`](uart::UartBuffers), [`UartLink`](uart::UartLink) | `embedded_io::{Read, ReadReady, Write, WriteReady}` | RX/TX interrupts push and pop; the protocol task reads and writes |
//! | [`port_link`] | [`PortLink`](port_link::PortLink): what a link a board serves as a port must do; [`Admission`](port_link::Admission): the session rules a connection-oriented link asks about its clients (the application's) | (contract) `embedded_io::{Read, ReadReady, Write}`, `LinkStatus` | thread: the board's host task |
//! | `tcp` (feature `embassy-net`) | `TcpServer`, `TcpLink` | `embedded_io::{Read, ReadReady, Write, WriteReady}`, `LinkStatus` | thread: listening tasks serve the sockets; the controller's task reads and writes |
//! | `web` (feature `embassy-net`) | `TcpServer::listen_web`, `Mirror`, `WebCounters` | the same `TcpServer` | thread: web tasks serve the page (`forja-web`'s assets) and the link over a WebSocket, controlling or watching |
//! | [`thermistor`] | [`Thermistor`](thermistor::Thermistor) | `TemperatureSensor` | thread: may block for one ADC conversion |
//! | [`max31855`] | [`Max31855`](max31855::Max31855) | `TemperatureSensor` | thread: one SPI transfer |
//! | [`heater`] | [`PidHeater`](heater::PidHeater) (sans-IO controller), [`HeaterChannel`](heater::HeaterChannel) | `TemperatureControl` (for `HeaterChannel`) | thread: the temperature loop |
//! | [`pwm`] | [`Fan`](pwm::Fan), [`Spindle`](pwm::Spindle), [`PwmHeater`](pwm::PwmHeater) | `FanControl`, `SpindleControl`, `Heater` | thread |
//! | [`output`] | [`Output`](output::Output) | `DigitalOutput` | thread: one pin write |
//! | [`coolant`] | [`Coolant`](coolant::Coolant) | `CoolantControl` (mist and flood over two `Output`s) | thread: one pin write |
//! | [`storage`] | [`FlashRecordStorage`](storage::FlashRecordStorage), [`Records`](storage::Records) | `RecordStorage` | thread: may block for a flash erase |
//! | [`program_flash`] | [`SlotProgramStore`](program_flash::SlotProgramStore) | `ProgramStore` | thread: one flash read per line read; may block for a sector erase while a program is loaded |
//! | [`flash_files`] | [`FlashFileStore`](flash_files::FlashFileStore) | `FileStore` | thread: one map-entry read and one read per 256 bytes per file read; may block for a sector erase while a file is written or removed |
//! | [`ram_flash`] | [`RamNorFlash`](ram_flash::RamNorFlash) | `embedded_storage::nor_flash::NorFlash` | a simulated flash for the host simulator and tests |
//! | `sd_card` (feature `sd-card`) | `SdFileStore`: files on a FAT16/FAT32 SD card (embedded-sdmmc's block device, over SPI) | `FileStore` | thread: blocks for the card's block transfers |
//! | [`shared_store`] | [`StoreSlot`](shared_store::StoreSlot), [`SharedStore`](shared_store::SharedStore) | `RecordStorage` | thread: one store (settings and program) shared by two users through a `static` slot |
//!
//! "Interrupt" methods are integer-only, allocation-free, panic-free and constant-time: a pin
//! write or read and a few instructions. "Thread" methods may use `f32` (the heater and the
//! thermistor do) and may block where their documentation says so. Nothing in this crate
//! panics outside tests, nothing allocates, and there is no `unsafe` code.
//!
//! ## Errors
//!
//! Each driver has one small `#[non_exhaustive]` error type with `Display`, mapped onto
//! [`forja_hal_abstraction::ErrorKind`] through [`forja_hal_abstraction::Error::kind`]: a pin
//! or bus failure is `Hardware`, an open or shorted sensor is `SensorFault`, a full store is
//! `Full`. Through the device traits they become the one
//! [`DeviceError`](forja_hal_abstraction::device::DeviceError) (a heater fault keeps its code
//! and name in `DeviceError::Thermal`). Errors that are reported to the host have stable numeric codes, from
//! `code()`, in 200..=299:
//!
//! | codes | errors |
//! |---|---|
//! | 210–215 | [`HeaterFault`](heater::HeaterFault) |
//! | 230–236 | [`StorageError`](storage::StorageError) |
//! | 237–238 | [`RecordError`](storage::RecordError) (encoding and decoding typed records) |
//!
//! ## Board requirements
//!
//! The UART queues and the TCP link coordinate through the `critical-section` crate, so that
//! they also run on targets without compare-and-swap atomics (RISC-V `imc`). The firmware
//! binary provides the implementation: `cortex-m`'s `critical-section-single-core` feature, or
//! the one built into esp-hal.
//!
//! ## Features
//!
//! | feature | adds |
//! |---|---|
//! | `alloc` | `PortLink` for `Box<T>` (with `embedded-io`'s and `LinkStatus`'s own), for a board that serves links of several types; it allocates nothing itself |
//! | `embassy-net` | the `tcp` module: a TCP host link over an `embassy-net` stack (embassy-sync queues, embassy-time time-outs), for boards with a network; no executor is named; and the `web` module beside it (the operator's page, `forja-web`) |
//! | `sd-card` | the `sd_card` module: the named-file store (`FileStore`) on a FAT16/FAT32 SD card, over embedded-sdmmc's SD-over-SPI block device (without its logging) |
//!
//! ## Writing a driver
//!
//! `docs/writing-a-driver.md` explains how a driver plugs in, with [`max31855`] as its worked
//! example.
#![cfg_attr(not(test), no_std)]
#![forbid(unsafe_code)]
#![cfg_attr(
    not(test),
    deny(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::indexing_slicing,
        clippy::unreachable,
        clippy::todo
    )
)]

pub mod coolant;
pub mod flash_files;
pub mod heater;
pub mod limit;
pub mod max31855;
pub mod output;
pub mod pin;
pub mod port_link;
pub mod program_flash;
pub mod pwm;
pub mod ram_flash;
#[cfg(feature = "sd-card")]
pub mod sd_card;
pub mod shared_store;
pub mod stepper;
pub mod storage;
#[cfg(feature = "embassy-net")]
pub mod tcp;
pub mod thermistor;
pub mod uart;
#[cfg(feature = "embassy-net")]
pub mod web;

#[cfg(test)]
mod test_fakes;
