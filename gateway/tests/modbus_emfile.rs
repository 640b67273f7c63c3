//! The Modbus server when the process runs out of file descriptors: `accept` fails with
//! EMFILE, the server counts it and retries with a backoff (unhealthy to the watchdog once
//! it has failed for 5 s), and serves again once descriptors are free. A test binary of its own: it lowers this process's descriptor
//! limit.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use serde_json::json;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;
use testkit::wait_until;

const TEXT: &str = r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 5
[card.sim]
[[card.sim.analog_out]]
range = { lowest = -10.0, highest = 10.0, unit = "V" }

[modbus_server]
listen = "127.0.0.1:0"
max_clients = 1024
# Every client here comes from 127.0.0.1: the per-address limit would close them at once
# and keep the descriptors free this test runs out of.
max_clients_per_address = 1024
[[modbus_server.register]]
table = "holding_registers"
address = 10
device = "sim0"
interface = "analog_out"
channel = 0
type = "i16"
scale = 0.001
"#;

/// Reads holding register 10 on a new connection.
fn read_hr10(addr: SocketAddr) -> Option<Vec<u8>> {
    let mut s = TcpStream::connect(addr).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    s.write_all(&[0, 1, 0, 0, 0, 6, 1, 3, 0, 10, 0, 1]).ok()?;
    let mut reply = [0u8; 11];
    s.read_exact(&mut reply).ok()?;
    Some(reply[7..].to_vec())
}

fn open_fds() -> u64 {
    std::fs::read_dir("/proc/self/fd").map_or(0, |d| d.count() as u64)
}

#[test]
fn the_server_survives_running_out_of_descriptors() {
    let d = Deployment::parse(TEXT, "emfile.toml").unwrap();
    let gw = Gateway::build(&d, "emfile.toml", TEXT, &hwgw::types::Types::builtin()).unwrap();
    gw.start().unwrap();
    let addr: SocketAddr = gw.server_address("modbus_server").unwrap().parse().unwrap();
    assert_eq!(read_hr10(addr).unwrap(), [3, 2, 0, 0]);
    let counters = || gw.server_status()[0].status.counters.clone();

    // Leave room for a few dozen descriptors and take them all with files, then give them
    // back one at a time to a client until one waits in the backlog while the server's
    // accept has no descriptor left. Filling with clients alone raced: when a client took
    // the last descriptor with no connection pending, accept never failed.
    let accepted = || counters()["connections"].as_u64().unwrap();
    let before = accepted();
    let soft = testkit::set_fd_limit(Some(open_fds() + 40)).unwrap();
    let mut fillers = Vec::new();
    while let Ok(f) = std::fs::File::open("/dev/null") {
        fillers.push(f);
        assert!(fillers.len() < 10_000, "the descriptor limit did not hold");
    }
    let mut clients = Vec::new();
    wait_until("accept failing", || {
        if counters()["accept_errors"].as_u64().unwrap() > 0 {
            return true;
        }
        // Every client accepted (another thread had let a descriptor go): give one more.
        let pending = clients.len() as u64 > accepted() - before;
        if !pending
            && fillers.pop().is_some()
            && let Ok(c) = TcpStream::connect(addr)
        {
            clients.push(c);
        }
        false
    });
    assert_eq!(counters()["running"], json!(true));
    // A short spell of failures is not yet unhealthy (the limit is 5 s); a long one is, and
    // says why (the connection left in the backlog keeps accept failing).
    assert!(gw.health().is_ok(), "{:?}", gw.health());
    wait_until(
        "the watchdog's health fails after 5 s of failing accepts",
        || gw.health().is_err(),
    );
    let why = format!("{:?}", gw.health());
    assert!(why.contains("accepted no connection"), "{why}");

    // Descriptors back: the server serves again.
    drop(clients);
    drop(fillers);
    testkit::set_fd_limit(Some(soft)).unwrap();
    wait_until("the server answers again", || {
        read_hr10(addr).as_deref() == Some(&[3, 2, 0, 0])
    });
    let c = counters();
    assert_eq!(c["running"], json!(true), "{c:?}");
    assert_eq!(c["panics"], json!(0), "{c:?}");
    assert!(gw.health().is_ok(), "healthy again: {:?}", gw.health());
    gw.shutdown();
}
