//! hwgw as a Modbus TCP→RTU gateway (mbusd's job): Modbus TCP masters reach a pymodbus
//! RTU unit (Debian's python3-pymodbus) on a socat pty pair through hwgw's server, on the
//! line hwgw's own card polls another unit of. mbpoll (libmodbus) is one master; a hundred
//! more are plain Modbus TCP clients of the test's own.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use testkit::mbpoll::Mbpoll;
use testkit::pty::PtyPair;
use testkit::pymodbus::PyRtu;
use testkit::wait_until;

/// The gateway's deployment: a card polling unit 2 of the line at `poll_ms` (its input
/// register 0 holds 77), hwgw's own unit 5 (a sim output), and unit 1 forwarded to the
/// line with `timeout_ms`.
fn deployment(line: &std::path::Path, timeout_ms: u64) -> String {
    format!(
        r#"
[[card]]
name = "rtu"
driver = "modbus"
[card.modbus]
transport = {{ type = "rtu", device = "{line}", baud = 19200 }}
unit = 2
poll_ms = 100
timeout_ms = 500
[[card.modbus.point]]
table = "input_registers"
address = 0

[[card]]
name = "sim0"
driver = "sim"
period_ms = 10
[card.sim]
digital_outputs = 1

[modbus_server]
listen = "127.0.0.1:0"
units = [5]
max_clients = 128
max_clients_per_address = 128
[[modbus_server.register]]
table = "coils"
address = 0
device = "sim0"
interface = "digital_out"
[[modbus_server.gateway]]
units = [1]
transport = {{ type = "rtu", device = "{line}", baud = 19200 }}
timeout_ms = {timeout_ms}
"#,
        line = line.display()
    )
}

fn start(text: &str) -> (Gateway, SocketAddr) {
    let d = Deployment::parse(text, "gw.toml").unwrap();
    let gw = Gateway::build(&d, "gw.toml", text, &hwgw::types::Types::builtin()).unwrap();
    gw.start().unwrap();
    let addr = gw.server_address("modbus_server").unwrap().parse().unwrap();
    (gw, addr)
}

/// The line card's unit counters.
fn unit_counters(gw: &Gateway) -> serde_json::Value {
    let s = gw.card_status();
    let r = s.iter().find(|r| r.name == "rtu").unwrap();
    serde_json::to_value(&r.status.counters).unwrap()
}

fn server_counters(gw: &Gateway) -> serde_json::Value {
    let s = gw.server_status();
    let r = s.iter().find(|r| r.name == "modbus_server").unwrap();
    serde_json::to_value(&r.status.counters).unwrap()
}

/// One Modbus TCP request to `unit` and its reply PDU (None: the connection ended).
fn request(s: &mut TcpStream, tid: u16, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
    let mut frame = tid.to_be_bytes().to_vec();
    frame.extend_from_slice(&[0, 0]);
    frame.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
    frame.push(unit);
    frame.extend_from_slice(pdu);
    s.write_all(&frame).ok()?;
    let mut head = [0u8; 7];
    s.read_exact(&mut head).ok()?;
    assert_eq!(head[..2], tid.to_be_bytes(), "the transaction id echoed");
    let mut body = vec![0u8; usize::from(u16::from_be_bytes([head[4], head[5]])).checked_sub(1)?];
    s.read_exact(&mut body).ok()?;
    Some(body)
}

#[test]
fn mbpoll_reaches_an_rtu_unit_through_the_gateway_and_hwgws_own_unit_beside() {
    let pty = PtyPair::new("mb-gateway");
    let _unit = PyRtu::start(&pty.unit());
    let (gw, addr) = start(&deployment(&pty.line(), 2000));
    wait_until("the card's unit 2 polled", || {
        unit_counters(&gw)["polls"].as_u64() >= Some(1)
    });
    let mbpoll = |unit: u8, table, address, count, write: &[&str]| {
        Mbpoll {
            port: addr.port(),
            table,
            address,
            count,
            write,
        }
        .run_unit(unit)
    };
    // Unit 1's input registers 0-2, as pymodbus holds them: -123, 0x40C8, 0.
    let out = mbpoll(1, "3", 0, Some(3), &[]);
    assert!(
        out.contains("[0]: \t65413 (-123)")
            && out.contains("[1]: \t16584")
            && out.contains("[2]: \t0"),
        "{out}"
    );
    // A write reaches unit 1 and reads back through the gateway; unit 2 is untouched.
    let out = mbpoll(1, "4", 30, None, &["4321"]);
    assert!(out.contains("Written 1 references"), "{out}");
    let out = mbpoll(1, "4", 30, Some(1), &[]);
    assert!(out.contains("[30]: \t4321"), "{out}");
    // hwgw's own unit 5 is served locally.
    let out = mbpoll(5, "0", 0, None, &["1"]);
    assert!(out.contains("Written 1 references"), "{out}");
    let out = mbpoll(5, "0", 0, Some(1), &[]);
    assert!(out.contains("[0]: \t1"), "{out}");
    // A unit neither hwgw's nor routed: 0x0A (mbpoll names it).
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    assert_eq!(
        request(&mut s, 1, 9, &[3, 0, 0, 0, 1]),
        Some(vec![0x83, 0x0A])
    );
    // An exception of unit 1's own comes back as it came: IllegalDataAddress.
    assert_eq!(
        request(&mut s, 2, 1, &[3, 0x10, 0, 0, 1]),
        Some(vec![0x83, 2])
    );
    let c = server_counters(&gw);
    assert_eq!(
        (c["forwarded"].as_u64(), c["unreachable"].as_u64()),
        (Some(4), Some(1)),
        "{c}"
    );
    gw.shutdown();
}

#[test]
fn a_hundred_masters_share_the_line_fairly_and_the_cards_own_polls_keep_their_rate() {
    let pty = PtyPair::new("mb-gateway-fair");
    let _unit = PyRtu::start(&pty.unit());
    let (gw, addr) = start(&deployment(&pty.line(), 20_000));
    wait_until("the card's unit 2 polled", || {
        unit_counters(&gw)["polls"].as_u64() >= Some(1)
    });
    // Every master connected first, then all of them at once.
    let masters: Vec<TcpStream> = (0..100)
        .map(|_| {
            let s = TcpStream::connect(addr).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
            s
        })
        .collect();
    let stop = Arc::new(AtomicBool::new(false));
    let polls_before = unit_counters(&gw)["polls"].as_u64().unwrap();
    let t0 = Instant::now();
    let threads: Vec<_> = masters
        .into_iter()
        .map(|mut s| {
            let stop = stop.clone();
            std::thread::spawn(move || {
                let (mut done, mut tid) = (0u32, 0u16);
                while !stop.load(Ordering::Relaxed) {
                    tid = tid.wrapping_add(1);
                    let reply = request(&mut s, tid, 1, &[4, 0, 0, 0, 1]);
                    assert_eq!(
                        reply,
                        Some(vec![4, 2, 0xFF, 0x85]),
                        "unit 1's input register 0"
                    );
                    done += 1;
                }
                done
            })
        })
        .collect();
    // Until every master has had a few replies (a loaded machine is slow), and at least
    // five seconds.
    std::thread::sleep(Duration::from_secs(5));
    wait_until("a hundred forwarded replies", || {
        server_counters(&gw)["forwarded"].as_u64() >= Some(500)
    });
    stop.store(true, Ordering::Relaxed);
    let done: Vec<u32> = threads.into_iter().map(|t| t.join().unwrap()).collect();
    let elapsed = t0.elapsed();
    let polls = unit_counters(&gw)["polls"].as_u64().unwrap() - polls_before;
    let mean = f64::from(done.iter().sum::<u32>()) / done.len() as f64;
    let (least, most) = (*done.iter().min().unwrap(), *done.iter().max().unwrap());
    eprintln!(
        "{} requests by 100 masters in {elapsed:?}: least {least}, most {most}, mean {mean:.1}; the card's unit polled {polls} times",
        done.iter().sum::<u32>()
    );
    assert!(
        f64::from(least) >= mean / 2.0 && f64::from(most) <= mean * 2.0,
        "each master within 2x of the mean {mean:.1}: {done:?}"
    );
    // The card's unit is polled every 100 ms: its own polls come first when due, each late
    // by one forwarded request at most.
    let expected = elapsed.as_secs_f64() / 0.1;
    assert!(
        polls as f64 >= 0.8 * expected,
        "{polls} polls in {elapsed:?}: {expected:.0} due"
    );
    let c = server_counters(&gw);
    assert_eq!(
        (
            c["gateway_no_response"].as_u64(),
            c["gateway_unavailable"].as_u64()
        ),
        (Some(0), Some(0)),
        "{c}"
    );
    gw.shutdown();
}

#[test]
fn a_dead_rtu_unit_is_answered_0x0b_within_the_timeout() {
    let pty = PtyPair::new("mb-gateway-dead");
    let mut unit = PyRtu::start(&pty.unit());
    let (gw, addr) = start(&deployment(&pty.line(), 300));
    wait_until("the card's unit 2 polled", || {
        unit_counters(&gw)["polls"].as_u64() >= Some(1)
    });
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    assert_eq!(
        request(&mut s, 1, 1, &[4, 0, 0, 0, 1]),
        Some(vec![4, 2, 0xFF, 0x85])
    );
    unit.kill();
    for tid in 2..6 {
        let t = Instant::now();
        let reply = request(&mut s, tid, 1, &[4, 0, 0, 0, 1]);
        let took = t.elapsed();
        assert_eq!(reply, Some(vec![0x84, 0x0B]), "after {took:?}");
        // The timeout runs from the request's arrival: the answer comes at it, or 100 ms
        // after when the line is busy with the card's own polls of the dead line (the
        // server's grace for the line to answer itself); 1 s more for a loaded machine.
        assert!(
            (Duration::from_millis(300)..Duration::from_millis(1400)).contains(&took),
            "{took:?}"
        );
    }
    let c = server_counters(&gw);
    assert_eq!(c["gateway_no_response"].as_u64(), Some(4), "{c}");
    gw.shutdown();
}

#[test]
fn requests_go_through_to_a_modbus_tcp_unit_and_rtu_frames_over_tcp_too() {
    // The line is a card with no points: it keeps the connection and sends nothing of its
    // own. The masters speak Modbus TCP and RTU frames over TCP.
    let unit = testkit::pymodbus::PyModbus::start("tcp");
    let text = format!(
        r#"
[[card]]
name = "plc"
driver = "modbus"
[card.modbus]
transport = {{ type = "tcp", address = "{addr}" }}

[modbus_server]
listen = "127.0.0.1:0"
rtu_over_tcp = "127.0.0.1:0"
units = []
[[modbus_server.gateway]]
transport = {{ type = "tcp", address = "{addr}" }}
"#,
        addr = unit.addr
    );
    let (gw, addr) = start(&text);
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    // Input registers 0-1 of the unit behind: -123 and 0x40C8 (any unit id reaches it).
    assert_eq!(
        request(&mut s, 1, 17, &[4, 0, 0, 0, 2]),
        Some(vec![4, 4, 0xFF, 0x85, 0x40, 0xC8])
    );
    let bus = gw.server_status()[0].status.bus.clone();
    let rtu_port = bus
        .split_once("rtu_over_tcp 127.0.0.1:")
        .map(|(_, p)| p.to_string())
        .unwrap_or_else(|| panic!("{bus}"));
    let mut master = testkit::pymodbus::PyMaster::connect("rtu_over_tcp", &rtu_port);
    let read = serde_json::json!({"fn": 4, "unit": 17, "address": 0, "count": 2});
    assert_eq!(
        master.ask(&read),
        serde_json::json!({"ok": [0xFF85, 0x40C8]})
    );
    assert_eq!(server_counters(&gw)["forwarded"].as_u64(), Some(2));
    gw.shutdown();
}
