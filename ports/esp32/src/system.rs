//! The chip at reset: clocks and heap, then the esp-rtos scheduler.
//!
//! | step | call | what |
//! |---|---|---|
//! | 1 | [`init`] | esp-hal at the highest CPU clock; the heap for the WiFi driver |
//! | 2 | [`start_rtos`] | esp-rtos on TIMG0's timer 0; TIMG0's watchdog, not yet running |
//! | last | [`Watchdog::start`] | from then on the controller task must feed it (see [`crate::watchdog`]) |

use esp_hal::clock::CpuClock;
use esp_hal::peripherals::{FROM_CPU_INTR0, Peripherals, TIMG0};
use esp_hal::timer::timg::TimerGroup;

use crate::watchdog::Watchdog;

/// Heap for the WiFi driver: in the RAM the ROM bootloader used (free once the app runs),
/// and in main RAM.
const HEAP_RECLAIMED: usize = 64 * 1024;
const HEAP_MAIN: usize = 48 * 1024;

/// Bring the chip up from reset: esp-hal at the highest CPU clock, then the heap. Returns the
/// peripherals, for the board to hand out.
///
/// Context: the start of `main`, once.
pub fn init() -> Peripherals {
    let p = esp_hal::init(esp_hal::Config::default().with_cpu_clock(CpuClock::max()));
    esp_alloc::heap_allocator!(#[esp_hal::ram(reclaimed)] size: HEAP_RECLAIMED);
    esp_alloc::heap_allocator!(size: HEAP_MAIN);
    p
}

/// Start esp-rtos's scheduler on TIMG0's timer 0 and `FROM_CPU_INTR0`; returns TIMG0's
/// watchdog, not yet running.
///
/// Context: init, after [`init`], before any task is spawned.
pub fn start_rtos(timg0: TIMG0<'static>, interrupt: FROM_CPU_INTR0<'static>) -> Watchdog {
    let group = TimerGroup::new(timg0);
    esp_rtos::start(group.timer0, interrupt);
    Watchdog::new(group.wdt)
}
