//! # Forja on the ESP32 family
//!
//! The firmware of the ESP32 boards: esp-hal 1.2 with esp-rtos tasks, the host link over WiFi.
//! This module is wiring only: which interrupt runs the step context at which priority, and
//! which task owns which part. The plumbing lives in the modules below it, the pin maps in
//! [`board`].
//!
//! | context | bound to | priority | does |
//! |---|---|---|---|
//! | `step_interrupt` | the step alarm (SYSTIMER comparator 0; TIMG1 on the ESP32) | `Priority::max()` | `StepGenerator::on_alarm`, re-arms the alarm ([`step`]) |
//! | `switch_interrupt` | the GPIO interrupt, on either edge of a limit switch input | `Priority2` | acknowledges the inputs, reports the edge to the step interrupt (`SwitchAlert`, [`limits`]) |
//! | WiFi driver, esp-rtos scheduler | their own interrupts | esp-radio's | the radio |
//! | `wifi_task` | esp-rtos executor | thread | joins the network, falls back to an access point ([`wifi`]) |
//! | `net_task` (×2) | esp-rtos executor | thread | the station and access point IP stacks ([`net`]) |
//! | `dhcp_task` | esp-rtos executor | thread | DHCP server of the access point ([`net`]) |
//! | `link_task` (×4) | esp-rtos executor | thread | TCP listeners, session ([`link`]) |
//! | `controller_task` | esp-rtos executor | thread | 54/55, `Controller::poll`, arms the step alarm, feeds the watchdog ([`controller`]) |
//!
//! RTIC's ESP32-C3 backend does not work with esp-hal 1.x, so the step interrupt is a plain
//! esp-hal interrupt handler at the highest priority, and everything else is an async task
//! of esp-rtos's executor, which never preempts the step interrupt. The switch interrupt sits
//! between them: above esp-radio's and esp-rtos's interrupts (priority 1) and the tasks, below
//! the step interrupt (priority 2 exists on every chip; the Xtensa chips' highest is 3).
//!
//! The step interrupt shares the step context (timer, STEP/DIR lines, switches, step
//! generator) with the controller task and the switch interrupt through a
//! `critical_section::Mutex`; the controller task only takes it to arm the alarm, the switch
//! interrupt to acknowledge the switch inputs. The step interrupt samples the switches only
//! from each motion's start until they are all released and settled, during homing, and after
//! the switch interrupt reports an edge. The kernel and the step generator talk through their
//! lock-free step queue.
#![no_std]
#![no_main]

pub mod board;
pub mod controller;
pub mod fault;
pub mod hardware;
pub mod limits;
pub mod link;
pub mod net;
pub mod settings;
pub mod step;
pub mod storage;
pub mod timer;
pub mod wifi;

use embassy_executor::Spawner;
use embassy_net::Stack;
use esp_radio::wifi::{Interface, WifiController};
use heapless::String;

use crate::controller::BoardFirmware;
use crate::hardware::Watchdog;
use crate::link::WifiLink;
use crate::settings::Credentials;
use crate::timer::StepClock;

esp_bootloader_esp_idf::esp_app_desc!();

/// The step interrupt.
#[esp_hal::handler(priority = esp_hal::interrupt::Priority::max())]
fn step_interrupt() {
    step::on_interrupt();
}

/// The switch interrupt: esp-hal's GPIO interrupt, raised by an edge of a limit switch input.
#[esp_hal::handler(priority = esp_hal::interrupt::Priority::Priority2)]
fn switch_interrupt() {
    limits::on_interrupt();
}

#[esp_rtos::main]
async fn main(spawner: Spawner) -> ! {
    let hw = hardware::init(step_interrupt, switch_interrupt).unwrap_or_else(|_| fault::reset());
    let clock = hw.clock;
    step::install(hw.step);
    if step::self_test(clock).await.is_err() {
        fault::reset();
    }

    // The kernel from the machine and the stored settings; its step generator goes to the
    // step interrupt.
    let firmware = controller::build(clock, hw.stores, hw.enable, hw.limits)
        .unwrap_or_else(|_| fault::reset());
    let stored = firmware.controller().settings();
    link::configure(stored.keep_alive_ms());
    let credentials = settings::credentials(stored.ssid(), stored.password());
    let ap_ssid = wifi::ap_ssid(hw.access_point.mac_address());
    let stacks =
        net::stacks(hw.station, hw.access_point, hw.seed).unwrap_or_else(|| fault::reset());

    spawner.spawn(
        controller_task(firmware, hw.link, clock, hw.watchdog, credentials.clone())
            .unwrap_or_else(|_| fault::reset()),
    );
    spawner.spawn(wifi_task(hw.wifi, credentials, ap_ssid).unwrap_or_else(|_| fault::reset()));
    spawner.spawn(net_task(stacks.station_runner).unwrap_or_else(|_| fault::reset()));
    spawner.spawn(net_task(stacks.access_point_runner).unwrap_or_else(|_| fault::reset()));
    spawner.spawn(dhcp_task(stacks.access_point).unwrap_or_else(|_| fault::reset()));
    for stack in [stacks.station, stacks.access_point] {
        for _ in 0..link::LISTENERS {
            spawner.spawn(link_task(stack).unwrap_or_else(|_| fault::reset()));
        }
    }
    core::future::pending().await
}

#[embassy_executor::task]
async fn controller_task(
    firmware: BoardFirmware,
    link: WifiLink,
    clock: StepClock,
    watchdog: Watchdog,
    credentials: Option<Credentials>,
) -> ! {
    controller::run(firmware, link, clock, watchdog, credentials).await
}

#[embassy_executor::task]
async fn wifi_task(
    controller: WifiController<'static>,
    credentials: Option<Credentials>,
    ap_ssid: String<32>,
) -> ! {
    wifi::run(controller, credentials, ap_ssid).await
}

#[embassy_executor::task(pool_size = 2)]
async fn net_task(runner: embassy_net::Runner<'static, Interface>) -> ! {
    net::run(runner).await
}

#[embassy_executor::task]
async fn dhcp_task(stack: Stack<'static>) -> ! {
    net::serve_dhcp(stack).await
}

#[embassy_executor::task(pool_size = 4)]
async fn link_task(stack: Stack<'static>) -> ! {
    link::listen(stack).await
}
