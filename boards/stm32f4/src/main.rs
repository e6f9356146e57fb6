//! # Forja on STM32F4
//!
//! The firmware of the STM32F4 boards: RTIC 2 tasks over `stm32f4xx-hal` 0.23 and the family's
//! chip support (`forja-port-stm32f4`: step timer, host UART, limit lines, flash store,
//! watchdog, faults), with the host link on an interrupt-driven UART. This crate is wiring
//! only: the pin maps ([`board`]), the bring-up that joins the pins to the port's drivers and
//! hands the parts to the application layer ([`hardware`], [`machine`]), and here which
//! interrupt runs which task at which priority, and which task owns which part.
//!
//! | task | bound to | priority | does |
//! |---|---|---|---|
//! | `step_tim2` (`step_systick` under `qemu`) | TIM2 (SysTick) | 4 | step alarm: `StepGenerator::on_alarm`, re-armed from its return; service tick (the port's `StepTimer::serve`, [`machine::StepSide`]) |
//! | `host_usart1` (`host_usart6` under `qemu`) | the pin map's UART | 3 | moves bytes between the UART and its queues (the port's `HostUart`) |
//! | `limit_lines_5_9`, `limit_lines_10_15` | EXTI9_5, EXTI15_10 | 3 | acknowledges limit switch edges, reports them to the step interrupt (the port's `Limits`) |
//! | `controller` | SDIO (no SD card: a free vector) | 1 | `Controller::poll` on the host link; arms the step alarm; publishes the link counters ([`machine::Firmware`]) |
//! | `status` | I2C3_EV (free vector) | 1 | every 100 ms: feeds the watchdog |
//! | `idle` | — | 0 | sleeps until the next interrupt |
//!
//! The controller and status tasks are pended by interrupts (the UART on received bytes, the
//! limit inputs on an edge, the step timer's 1 kHz service tick), never spawned: a pend while
//! running makes them run again, so no wake-up is lost. The controller task polls the
//! controller when bytes wait, a switch changed or the controller's `wake_at` has come. The
//! step timer is shared by the step task and the controller task, which arms the alarm under
//! its lock (the step interrupt is held off for those few instructions).
#![no_std]
#![no_main]

pub mod board;
pub mod hardware;
pub mod machine;

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
pub const STATUS_EVERY: u32 = forja_port_stm32f4::timer::SERVICE_HZ / 10;

#[rtic::app(device = stm32f4xx_hal::pac, peripherals = true)]
mod app {
    use forja_hal_abstraction::clock::{Alarm as _, Clock as _};
    use forja_port_stm32f4::limits::{self, Limits};
    use forja_port_stm32f4::timer::{StepClock, StepTimer};
    use forja_port_stm32f4::uart::{HostUart, LINK_COUNTERS};
    use forja_port_stm32f4::{fault, watchdog::Watchdog};

    use crate::board::HostUsart;
    use crate::machine::{Firmware, Queue, StepSide};
    use crate::{STATUS_EVERY, hardware, vectors};

    // The timer is shared by the step task and the controller task (which arms the alarm).
    // The step side and the UART are shared only because the two builds bind them from
    // differently named tasks, the limit lines because two tasks at one priority use them:
    // one priority uses each, so their locks cost nothing.
    #[shared]
    struct Shared {
        timer: StepTimer,
        step: StepSide,
        limits: Limits,
        uart: HostUart<HostUsart>,
    }

    #[local]
    struct Local {
        firmware: Firmware,
        clock: StepClock,
        watchdog: Watchdog,
    }

    #[init(local = [queue: Queue = Queue::new()])]
    fn init(cx: init::Context) -> (Shared, Local) {
        let hw =
            hardware::init(cx.device, cx.core, cx.local.queue).unwrap_or_else(|_| fault::reset());
        let mut firmware = hw.firmware;
        let clock = hw.timer.clock();
        // The UART is enabled: announce the boot. Sent by the UART interrupt once init returns.
        firmware.boot();
        (
            Shared {
                step: hw.step,
                limits: hw.limits,
                uart: hw.uart,
                timer: hw.timer,
            },
            Local {
                firmware,
                clock,
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
    #[task(binds = TIM2, priority = 4, shared = [timer, step], local = [ticks: u32 = 0])]
    fn step_tim2(cx: step_tim2::Context) {
        let ticks = cx.local.ticks;
        (cx.shared.timer, cx.shared.step).lock(|timer, step| on_step(timer, step, ticks));
    }

    /// The step interrupt.
    #[cfg(feature = "qemu")]
    #[task(binds = SysTick, priority = 4, shared = [timer, step], local = [ticks: u32 = 0])]
    fn step_systick(cx: step_systick::Context) {
        let ticks = cx.local.ticks;
        (cx.shared.timer, cx.shared.step).lock(|timer, step| on_step(timer, step, ticks));
    }

    fn on_step(timer: &mut StepTimer, step: &mut StepSide, ticks: &mut u32) {
        if timer.serve(|now| step.on_alarm(now)) {
            rtic::pend(vectors::CONTROLLER);
            *ticks += 1;
            if *ticks >= STATUS_EVERY {
                *ticks = 0;
                rtic::pend(vectors::STATUS);
            }
        }
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

    fn on_uart(uart: &mut HostUart<HostUsart>) {
        if uart.on_interrupt() {
            rtic::pend(vectors::CONTROLLER);
        }
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

    /// The protocol and planner task: polled when bytes wait, a limit line fired, or the
    /// firmware's `wake_at` has come, and again at once while it has steps to prepare.
    #[task(binds = SDIO, priority = 1, shared = [timer], local = [firmware, clock])]
    fn controller(mut cx: controller::Context) {
        let now = cx.local.clock.now();
        let firmware = cx.local.firmware;
        if let Some(at) = firmware.poll(now, limits::take_fired() != 0) {
            cx.shared.timer.lock(|timer| {
                let _ = timer.set_alarm(at);
            });
        }
        if firmware.needs_poll() {
            rtic::pend(vectors::CONTROLLER);
        }
        LINK_COUNTERS.publish(firmware.link(), &firmware.firmware().controller().stats());
    }

    /// Periodic status.
    #[task(binds = I2C3_EV, priority = 1, local = [watchdog])]
    fn status(cx: status::Context) {
        cx.local.watchdog.feed();
    }
}
