//! # Forja on STM32F4
//!
//! The firmware of the STM32F4 boards: RTIC 2 tasks over `stm32f4xx-hal` 0.23, with the host
//! link on an interrupt-driven UART. This module is wiring only: which interrupt runs which
//! task at which priority, and which task owns which part. The plumbing lives in the modules
//! below it, the pin maps in [`board`].
//!
//! | task | bound to | priority | does |
//! |---|---|---|---|
//! | `step_tim2` (`step_systick` under `qemu`) | TIM2 (SysTick) | 4 | step alarm and service tick ([`timer`]) |
//! | `host_usart1` (`host_usart6` under `qemu`) | the pin map's UART | 3 | moves bytes between the UART and its queues ([`uart`]) |
//! | `limit_lines_5_9`, `limit_lines_10_15` | EXTI9_5, EXTI15_10 | 3 | acknowledges limit switch edges ([`limits`]) |
//! | `controller` | SDIO (no SD card: a free vector) | 1 | reads the link, feeds the decoder ([`link`]) |
//! | `status` | I2C3_EV (free vector) | 1 | every 100 ms: feeds the watchdog |
//! | `idle` | — | 0 | sleeps until the next interrupt |
//!
//! The controller and status tasks are pended by interrupts (the UART on received bytes, the
//! step timer's 1 kHz service tick), never spawned: a pend while running makes them run again,
//! so no wake-up is lost.
#![no_std]
#![no_main]

pub mod board;
pub mod enable;
pub mod fault;
pub mod hardware;
pub mod limits;
pub mod link;
pub mod storage;
pub mod timer;
pub mod uart;
pub mod watchdog;

/// Interrupt vectors that no peripheral of these boards raises, used to run the thread-side
/// tasks.
pub mod vectors {
    use stm32f4xx_hal::pac::Interrupt;

    /// Runs the controller task.
    pub const CONTROLLER: Interrupt = Interrupt::SDIO;
    /// Runs the status task.
    pub const STATUS: Interrupt = Interrupt::I2C3_EV;
}

/// Service ticks between two runs of the status task (100 ms).
pub const STATUS_EVERY: u32 = timer::SERVICE_HZ / 10;

#[rtic::app(device = stm32f4xx_hal::pac, peripherals = true)]
mod app {
    use forja_drivers::uart::{UartReader, UartWriter};
    use forja_protocol::reply::Reply;
    use forja_protocol::stream::Decoder;

    use crate::hardware::{self, Stepper};
    use crate::limits::Limits;
    use crate::storage::Store;
    use crate::timer::StepTimer;
    use crate::uart::{HostUart, RX_LEN, TX_LEN};
    use crate::watchdog::Watchdog;
    use crate::{STATUS_EVERY, board, fault, link, vectors};

    // The UART is shared only because the two builds bind it from differently named tasks;
    // one task at one priority uses it, so its lock costs nothing.
    #[shared]
    struct Shared {
        timer: StepTimer,
        limits: Limits,
        uart: HostUart,
    }

    #[local]
    struct Local {
        reader: UartReader<'static, RX_LEN>,
        writer: UartWriter<'static, TX_LEN>,
        decoder: Decoder,
        steppers: [Stepper; board::AXES],
        store: Store,
        watchdog: Watchdog,
    }

    #[init]
    fn init(cx: init::Context) -> (Shared, Local) {
        let hw = hardware::init(cx.device, cx.core).unwrap_or_else(|_| fault::reset());
        let mut writer = hw.writer;
        // The UART is enabled: announce the boot. Sent by the UART interrupt once init returns.
        let mut start = [0u8; 8];
        if let Ok(n) = Reply::Start.encode(&mut start) {
            writer.try_write(start.get(..n).unwrap_or_default());
        }
        (
            Shared {
                timer: hw.timer,
                limits: hw.limits,
                uart: hw.uart,
            },
            Local {
                reader: hw.reader,
                writer,
                decoder: Decoder::new(),
                steppers: hw.steppers,
                store: hw.store,
                watchdog: hw.watchdog,
            },
        )
    }

    #[idle]
    fn idle(_: idle::Context) -> ! {
        loop {
            cortex_m::asm::wfi();
        }
    }

    /// The step interrupt.
    #[cfg(not(feature = "qemu"))]
    #[task(binds = TIM2, priority = 4, shared = [timer], local = [ticks: u32 = 0])]
    fn step_tim2(mut cx: step_tim2::Context) {
        let ticks = cx.local.ticks;
        cx.shared.timer.lock(|timer| on_step(timer, ticks));
    }

    /// The step interrupt.
    #[cfg(feature = "qemu")]
    #[task(binds = SysTick, priority = 4, shared = [timer], local = [ticks: u32 = 0])]
    fn step_systick(mut cx: step_systick::Context) {
        let ticks = cx.local.ticks;
        cx.shared.timer.lock(|timer| on_step(timer, ticks));
    }

    fn on_step(timer: &mut StepTimer, ticks: &mut u32) {
        let events = timer.on_interrupt();
        if events.service {
            rtic::pend(vectors::CONTROLLER);
            *ticks += 1;
            if *ticks >= STATUS_EVERY {
                *ticks = 0;
                rtic::pend(vectors::STATUS);
            }
        }
        timer.finish();
    }

    /// The host UART interrupt.
    #[cfg(not(feature = "qemu"))]
    #[task(binds = USART1, priority = 3, shared = [uart])]
    fn host_usart1(mut cx: host_usart1::Context) {
        cx.shared.uart.lock(on_uart);
    }

    /// The host UART interrupt.
    #[cfg(feature = "qemu")]
    #[task(binds = USART6, priority = 3, shared = [uart])]
    fn host_usart6(mut cx: host_usart6::Context) {
        cx.shared.uart.lock(on_uart);
    }

    fn on_uart(uart: &mut HostUart) {
        if uart.on_interrupt() {
            rtic::pend(vectors::CONTROLLER);
        }
        link::note_uart_errors(uart.errors());
    }

    /// Limit switch lines 5–9.
    #[task(binds = EXTI9_5, priority = 3, shared = [limits])]
    fn limit_lines_5_9(mut cx: limit_lines_5_9::Context) {
        cx.shared.limits.lock(Limits::on_interrupt);
        rtic::pend(vectors::CONTROLLER);
    }

    /// Limit switch lines 10–15.
    #[task(binds = EXTI15_10, priority = 3, shared = [limits])]
    fn limit_lines_10_15(mut cx: limit_lines_10_15::Context) {
        cx.shared.limits.lock(Limits::on_interrupt);
        rtic::pend(vectors::CONTROLLER);
    }

    /// The protocol and planner task.
    #[task(binds = SDIO, priority = 1, local = [reader, writer, decoder, steppers, store])]
    fn controller(cx: controller::Context) {
        link::pump(cx.local.reader, cx.local.decoder);
    }

    /// Periodic status.
    #[task(binds = I2C3_EV, priority = 1, local = [watchdog])]
    fn status(cx: status::Context) {
        cx.local.watchdog.feed();
    }
}
