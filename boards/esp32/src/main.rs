//! # Forja on the ESP32 family
//!
//! The firmware of the ESP32 boards: esp-hal 1.2 with esp-rtos tasks, the host link over WiFi.
//! This crate is wiring only: the pin map ([`board`]), the parts it hands to the application
//! layer ([`hardware`]), which interrupt runs each body at which priority, and which task owns
//! which part. The chip support every ESP32 board shares (step timer and clock, the step and
//! switch interrupts' bodies, flash stores, WiFi, link, watchdog, faults) is
//! `forja_port_esp32`.
//!
//! | context | bound to | priority | does |
//! |---|---|---|---|
//! | `step_interrupt` | the step alarm (SYSTIMER comparator 0; TIMG1 on the ESP32) | `Priority::max()` | `StepGenerator::on_alarm`, re-arms the alarm (`StepCell::on_step_interrupt`) |
//! | `switch_interrupt` | the GPIO interrupt, on either edge of a limit switch input | `Priority2` | acknowledges the inputs, reports the edge to the step interrupt (`StepCell::on_switch_interrupt`) |
//! | WiFi driver, esp-rtos scheduler | their own interrupts | esp-radio's | the radio |
//! | `wifi_task` | esp-rtos executor | thread | joins the network, falls back to an access point (`wifi::run`) |
//! | `net_task` (×2) | esp-rtos executor | thread | the station and access point IP stacks (`net::run`) |
//! | `dhcp_task` | esp-rtos executor | thread | DHCP server of the access point (`net::serve_dhcp`) |
//! | `link_task` (×4) | esp-rtos executor | thread | TCP listeners, session (`link::listen`) |
//! | `web_task` (×6) | esp-rtos executor | thread | the operator's page on port 80, the link over its WebSocket (`link::listen_web`) |
//! | `controller_task` | esp-rtos executor | thread | 54/55, `Controller::poll`, arms the step alarm, feeds the watchdog (`controller::run`) |
//!
//! RTIC's ESP32-C3 backend does not work with esp-hal 1.x, so the step interrupt is a plain
//! esp-hal interrupt handler at the highest priority, and everything else is an async task
//! of esp-rtos's executor, which never preempts the step interrupt. The switch interrupt sits
//! between them: above esp-radio's and esp-rtos's interrupts (priority 1) and the tasks, below
//! the step interrupt (priority 2 exists on every chip; the Xtensa chips' highest is 3).
//!
//! The step interrupt shares the step context ([`STEP`]: timer, STEP/DIR lines, switches,
//! step generator) with the controller task and the switch interrupt through a critical
//! section; the controller task only takes it to arm the alarm, the switch interrupt to
//! acknowledge the switch inputs. The kernel and the step generator talk through their
//! lock-free step queue.
#![no_std]
#![no_main]

pub mod board;
pub mod hardware;

use embassy_executor::Spawner;
use forja_app::session::LinkSession;
use forja_app::wifi::{CredentialWatch, Credentials};
use forja_port_esp32::controller;
use forja_port_esp32::fault::reset;
use forja_port_esp32::link::{self, LINK, WifiLink};
use forja_port_esp32::net::{self, Stack, StackRunner};
use forja_port_esp32::timer::StepClock;
use forja_port_esp32::watchdog::Watchdog;
use forja_port_esp32::wifi::{self, ApSsid, WifiController};

use crate::hardware::{BoardFirmware, BoardStep};

esp_bootloader_esp_idf::esp_app_desc!();

/// The step context, shared by the step interrupt, the switch interrupt and the controller
/// task.
pub static STEP: BoardStep = BoardStep::new();

/// The step interrupt.
#[esp_hal::handler(priority = esp_hal::interrupt::Priority::max())]
fn step_interrupt() {
    STEP.on_step_interrupt();
}

/// The switch interrupt: esp-hal's GPIO interrupt, raised by an edge of a limit switch input.
#[esp_hal::handler(priority = esp_hal::interrupt::Priority::Priority2)]
fn switch_interrupt() {
    STEP.on_switch_interrupt();
}

#[esp_rtos::main]
async fn main(spawner: Spawner) -> ! {
    let hw = hardware::init(step_interrupt, switch_interrupt).unwrap_or_else(|_| reset());
    STEP.install(hw.step);
    if STEP.self_test(hw.clock).await.is_err() {
        reset();
    }

    // The kernel from the machine and the stored settings; its step generator goes to the
    // step interrupt.
    let firmware = hardware::firmware(hw.clock, hw.stores, hw.enable, hw.limits, &STEP)
        .unwrap_or_else(|_| reset());
    let stored = firmware.controller().settings();
    LINK.admission(|session| *session = LinkSession::new(stored.keep_alive_ms()));
    let network = CredentialWatch::new(stored, wifi::default_network());
    let credentials = network.current().cloned();
    let ap_ssid = wifi::ap_ssid(hw.radio.access_point.mac_address());
    let radio = hw.radio;
    let stacks =
        net::stacks(radio.station, radio.access_point, radio.seed).unwrap_or_else(|| reset());

    spawner.spawn(
        controller_task(firmware, hw.link, hw.clock, hw.watchdog, network)
            .unwrap_or_else(|_| reset()),
    );
    spawner.spawn(wifi_task(radio.controller, credentials, ap_ssid).unwrap_or_else(|_| reset()));
    spawner.spawn(net_task(stacks.station_runner).unwrap_or_else(|_| reset()));
    spawner.spawn(net_task(stacks.access_point_runner).unwrap_or_else(|_| reset()));
    spawner.spawn(dhcp_task(stacks.access_point).unwrap_or_else(|_| reset()));
    for stack in [stacks.station, stacks.access_point] {
        for _ in 0..link::LISTENERS {
            spawner.spawn(link_task(stack).unwrap_or_else(|_| reset()));
        }
        for _ in 0..link::WEB_LISTENERS {
            spawner.spawn(web_task(stack).unwrap_or_else(|_| reset()));
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
    network: CredentialWatch,
) -> ! {
    controller::run(firmware, link, clock, &STEP, watchdog, network).await
}

#[embassy_executor::task]
async fn wifi_task(
    controller: WifiController<'static>,
    credentials: Option<Credentials>,
    ap_ssid: ApSsid,
) -> ! {
    wifi::run(controller, credentials, ap_ssid).await
}

#[embassy_executor::task(pool_size = 2)]
async fn net_task(runner: StackRunner) -> ! {
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

#[embassy_executor::task(pool_size = 6)]
async fn web_task(stack: Stack<'static>) -> ! {
    link::listen_web(stack).await
}
