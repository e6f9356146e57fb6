//! The two IP stacks (station and access point) over the WiFi interfaces, and the access
//! point's DHCP server.
//!
//! | stack | interface | address | sockets |
//! |---|---|---|---|
//! | station | `Interface::station()` | from the network's DHCP server | DHCP client, [`crate::link::LISTENERS`] TCP, [`crate::link::WEB_LISTENERS`] web |
//! | access point | `Interface::access_point()` | [`AP_ADDRESS`]/24 | DHCP server (UDP), [`crate::link::LISTENERS`] TCP, [`crate::link::WEB_LISTENERS`] web |
//!
//! Both stacks exist from boot; a stack whose interface is down simply has no link. Each
//! needs its runner task ([`run`]), and the access point its DHCP server task ([`serve_dhcp`]),
//! spawned by the board.

use core::net::{Ipv4Addr, SocketAddr, SocketAddrV4};

use edge_dhcp::io::{DEFAULT_SERVER_PORT, server as dhcp_io};
use edge_dhcp::server::{Server, ServerOptions};
use edge_nal::UdpBind;
use edge_nal_embassy::{Udp, UdpBuffers};
pub use embassy_net::Stack;
use embassy_net::{Config, Ipv4Cidr, Runner, StackResources, StaticConfigV4};
use embassy_time::{Duration, Timer};
use esp_radio::wifi::Interface;
use static_cell::StaticCell;

use crate::link::{LISTENERS, WEB_LISTENERS};
use crate::wifi::{AP_ADDRESS, AP_PREFIX_LEN};

/// Sockets of the station stack: the TCP listeners, the web page's and the DHCP client.
const STATION_SOCKETS: usize = LISTENERS + WEB_LISTENERS + 1;
/// Sockets of the access point stack: the TCP listeners, the web page's and the DHCP server.
const AP_SOCKETS: usize = LISTENERS + WEB_LISTENERS + 1;

/// Leases the access point's DHCP server keeps (clients at once).
const DHCP_LEASES: usize = 4;

static STATION_RESOURCES: StaticCell<StackResources<STATION_SOCKETS>> = StaticCell::new();
static AP_RESOURCES: StaticCell<StackResources<AP_SOCKETS>> = StaticCell::new();

/// What runs a stack: its task calls [`run`] on it.
pub type StackRunner = Runner<'static, Interface>;

/// The two stacks and their runners.
pub struct Stacks {
    /// The station stack.
    pub station: Stack<'static>,
    /// Its runner, for [`run`].
    pub station_runner: StackRunner,
    /// The access point stack.
    pub access_point: Stack<'static>,
    /// Its runner, for [`run`].
    pub access_point_runner: StackRunner,
}

/// Build both stacks; `seed` randomises their TCP sequence numbers and ports.
///
/// Context: init; call once (the resources are static).
pub fn stacks(station: Interface, access_point: Interface, seed: u64) -> Option<Stacks> {
    let station_config = Config::dhcpv4(Default::default());
    let ap_config = Config::ipv4_static(StaticConfigV4 {
        address: Ipv4Cidr::new(AP_ADDRESS, AP_PREFIX_LEN),
        gateway: None,
        dns_servers: Default::default(),
    });
    let (station_stack, station_runner) = embassy_net::new(
        station,
        station_config,
        STATION_RESOURCES.try_init(StackResources::new())?,
        seed,
    );
    let (ap_stack, ap_runner) = embassy_net::new(
        access_point,
        ap_config,
        AP_RESOURCES.try_init(StackResources::new())?,
        seed.rotate_left(32),
    );
    Some(Stacks {
        station: station_stack,
        station_runner,
        access_point: ap_stack,
        access_point_runner: ap_runner,
    })
}

/// Run one stack for ever.
///
/// Context: a task.
pub async fn run(mut runner: StackRunner) -> ! {
    runner.run().await
}

/// Serve DHCP on the access point: clients get an address in `192.168.4.0/24` and no gateway
/// (the board routes nowhere).
///
/// Context: a task. Never returns; a failing server is restarted after a second.
pub async fn serve_dhcp(stack: Stack<'static>) -> ! {
    let buffers = UdpBuffers::<1, 1024, 1024, 4>::new();
    let udp = Udp::new(stack, &buffers);
    let mut buf = [0u8; 1024];
    loop {
        let any = SocketAddr::V4(SocketAddrV4::new(
            Ipv4Addr::UNSPECIFIED,
            DEFAULT_SERVER_PORT,
        ));
        if let Ok(mut socket) = udp.bind(any).await {
            let mut server = Server::<_, DHCP_LEASES>::new_with_et(AP_ADDRESS);
            // No gateway and no DNS: the access point is a local link to the board only.
            let options = ServerOptions::new(AP_ADDRESS, None);
            let _ = dhcp_io::run(&mut server, &options, &mut socket, &mut buf).await;
        }
        Timer::after(Duration::from_secs(1)).await;
    }
}
