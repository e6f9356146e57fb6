//! # Forja on the RP2040
//!
//! The firmware of the RP2040 boards (the BigTreeTech SKR Pico): RTIC 2 tasks over
//! `rp2040-hal` 0.12 and the chip support (`forja-port-rp2040`: step clock and alarms, host
//! UART, limit interrupt, flash stores, watchdog, faults), with the host link on an
//! interrupt-driven UART. This crate is wiring only: the pin map ([`board`]), the bring-up that
//! joins the pins to the port's drivers and hands the parts to the application layer
//! ([`hardware`], [`machine`]), and here which interrupt runs which task at which priority, and
//! which task owns which part.
//!
//! | task | bound to | priority | does |
//! |---|---|---|---|
//! | `step` | TIMER_IRQ_0 | 4 | step alarm: `StepGenerator::on_alarm`, re-armed from its return (the port's `TimerAlarm`, [`machine::StepSide`]) |
//! | `host_uart` | UART0_IRQ | 3 | moves bytes between the UART and its queues (the port's `HostUart`) |
//! | `limit_edges` | IO_IRQ_BANK0 | 3 | acknowledges limit switch edges, reports them to the step interrupt (the port's `limits`) |
//! | `controller` | TIMER_IRQ_1 | 1 | `Controller::poll` on the host link, arms the step alarm, feeds the watchdog ([`machine::Firmware`]) |
//! | `idle` | — | 0 | sleeps until the next interrupt |
//!
//! The controller task runs when its own alarm (TIMER alarm 1) fires, at the controller's
//! `wake_at` and at least every [`CONTROLLER_MAX_SLEEP_MS`], and when the UART or a switch
//! pends it. The step alarm is shared by the step task and the controller task, which arms it
//! under its lock (the step interrupt is held off for those few instructions).
#![no_std]
#![no_main]

pub mod board;
pub mod hardware;
pub mod machine;

/// The second-stage boot loader, the first 256 bytes of the flash: it sets the W25Q16 up for
/// quad-SPI execute-in-place and jumps to the vector table.
#[unsafe(link_section = ".boot2")]
#[unsafe(no_mangle)]
#[used]
pub static BOOT2_FIRMWARE: [u8; 256] = rp2040_boot2::BOOT_LOADER_W25Q080;

/// The longest the controller task sleeps, so that the watchdog is fed.
pub const CONTROLLER_MAX_SLEEP_MS: u32 = 100;

#[rtic::app(device = rp2040_hal::pac, peripherals = true)]
mod app {
    use forja_hal_abstraction::clock::{Alarm as _, Clock as _};
    use forja_hal_abstraction::time::Duration;
    use forja_motion::SwitchAlert;
    use forja_port_rp2040::fault::reset;
    use forja_port_rp2040::limits::{self, Edges};
    use forja_port_rp2040::timer::{TICK_HZ, TimerAlarm, TimerClock};
    use forja_port_rp2040::uart::HostUart;
    use rp2040_hal::Watchdog;
    use rp2040_hal::pac::{Interrupt, UART0};

    use crate::board::HostUartPins;
    use crate::machine::{Firmware, Queue, StepSide};
    use crate::{CONTROLLER_MAX_SLEEP_MS, hardware};

    #[shared]
    struct Shared {
        step_alarm: TimerAlarm<0>,
    }

    #[local]
    struct Local {
        step: StepSide,
        uart: HostUart<UART0, HostUartPins>,
        alert: SwitchAlert<'static>,
        firmware: Firmware,
        edges: Edges,
        wake_alarm: TimerAlarm<1>,
        watchdog: Watchdog,
    }

    #[init(local = [queue: Queue = Queue::new()])]
    fn init(cx: init::Context) -> (Shared, Local) {
        // SAFETY: nothing holds a spinlock yet; one may be left taken by a reset that kept
        // the SIO (a debugger's), and the critical-section implementation uses one.
        unsafe { rp2040_hal::sio::spinlock_reset() };
        let hw = hardware::init(cx.device, cx.local.queue).unwrap_or_else(|_| reset());
        let alert = hw.step.switch_alert();
        let mut firmware = hw.firmware;
        // The UART is enabled: announce the boot. Sent by the UART interrupt once init returns.
        firmware.boot();
        rtic::pend(Interrupt::TIMER_IRQ_1);
        (
            Shared {
                step_alarm: hw.step_alarm,
            },
            Local {
                step: hw.step,
                uart: hw.uart,
                alert,
                firmware,
                edges: Edges::new(),
                wake_alarm: hw.wake_alarm,
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
    #[task(binds = TIMER_IRQ_0, priority = 4, shared = [step_alarm], local = [step])]
    fn step(mut cx: step::Context) {
        let step = cx.local.step;
        cx.shared.step_alarm.lock(|alarm| {
            if alarm.take()
                && let Some(at) = step.on_alarm(TimerClock.now())
            {
                let _ = alarm.set_alarm(at);
            }
        });
    }

    /// The host UART.
    #[task(binds = UART0_IRQ, priority = 3, local = [uart])]
    fn host_uart(cx: host_uart::Context) {
        if cx.local.uart.on_interrupt() {
            rtic::pend(Interrupt::TIMER_IRQ_1);
        }
    }

    /// The limit switch inputs.
    #[task(binds = IO_IRQ_BANK0, priority = 3, local = [alert])]
    fn limit_edges(cx: limit_edges::Context) {
        limits::on_interrupt(cx.local.alert);
        rtic::pend(Interrupt::TIMER_IRQ_1);
    }

    /// The protocol and planner task: polled when bytes wait, a switch changed, or the
    /// firmware's `wake_at` has come.
    #[task(binds = TIMER_IRQ_1, priority = 1, shared = [step_alarm], local = [firmware, edges, wake_alarm, watchdog])]
    fn controller(mut cx: controller::Context) {
        cx.local.watchdog.feed();
        cx.local.wake_alarm.take();
        let now = TimerClock.now();
        if let Some(at) = cx.local.firmware.poll(now, cx.local.edges.take()) {
            cx.shared.step_alarm.lock(|alarm| {
                let _ = alarm.set_alarm(at);
            });
        }
        let latest = now.wrapping_add(Duration::from_ticks(
            CONTROLLER_MAX_SLEEP_MS * (TICK_HZ / 1000),
        ));
        let wake = cx.local.firmware.wake_at();
        let at = wake
            .filter(|at| latest.is_at_or_after(*at))
            .unwrap_or(latest);
        let _ = cx.local.wake_alarm.set_alarm(at);
    }
}
