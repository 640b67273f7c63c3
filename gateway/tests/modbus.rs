//! A Modbus card in a deployment, against a Modbus TCP server: decoded values in IO ports,
//! port writes to registers, and safe values reaching the unit when the gateway stops.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use driver_modbus::testing::TestServer;
use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use rtt::port::ConnPolicy;
use serde_json::json;
use testkit::mbpoll::Mbpoll;
use testkit::wait_until;

#[test]
fn a_modbus_card_in_a_deployment() {
    let server = TestServer::start();
    {
        let mut m = server.memory().lock().unwrap();
        m.input[0] = (-215i16) as u16; // -21.5 degC
        m.discrete[2] = true;
    }
    let text = format!(
        r#"
[[card]]
name = "plc"
driver = "modbus"
sample_period_ms = 10
safe_analog_out = [1.5]
safe_digital_out_on = [1]

[card.names]
analog_in = ["temperature"]
analog_out = ["setpoint"]
digital_in = ["door"]
digital_out = ["pump", "fan"]

[card.modbus]
transport = {{ type = "tcp", address = "{}" }}
unit = 1
poll_ms = 10
timeout_ms = 200

[[card.modbus.point]]
table = "input_registers"
address = 0
type = "i16"
scale = 0.1
unit = "degC"
[[card.modbus.point]]
table = "holding_registers"
address = 10
scale = 0.1
unit = "bar"
[[card.modbus.point]]
table = "discrete_inputs"
address = 2
[[card.modbus.point]]
table = "coils"
address = 0
[[card.modbus.point]]
table = "coils"
address = 1
"#,
        server.addr()
    );
    let d = Deployment::parse(&text, "plc.toml").unwrap();
    let gw = Gateway::build(&d, "plc.toml", &text, &hwgw::types::Types::builtin()).unwrap();
    assert!(
        gw.summary().contains("card \"plc\" (modbus Tcp("),
        "{}",
        gw.summary()
    );
    gw.start().unwrap();
    let rt = gw.runtime();
    let temperature = rt.component("plc.ai").unwrap().port("temperature").unwrap();
    wait_until("the temperature arrives", || {
        temperature.last_value().unwrap() == Some(json!(-21.5))
    });
    let door = rt.component("plc.di").unwrap().port("door").unwrap();
    wait_until("the door arrives", || {
        door.last_value().unwrap() == Some(json!(true))
    });

    let mut setpoint = rt
        .component("plc.ao")
        .unwrap()
        .port("setpoint")
        .unwrap()
        .writer(ConnPolicy::data())
        .unwrap();
    setpoint.write(json!(4.2)).unwrap();
    let mut pump = rt
        .component("plc.do")
        .unwrap()
        .port("pump")
        .unwrap()
        .writer(ConnPolicy::data())
        .unwrap();
    pump.write(json!(true)).unwrap();
    wait_until("the unit's registers change", || {
        let m = server.memory().lock().unwrap();
        m.holding[10] == 42 && m.coils[0]
    });
    // `hwgw get` on the output ports: their current values, by name.
    let value = |c: &str, p: &str| {
        rt.component(c)
            .unwrap()
            .port(p)
            .unwrap()
            .last_value()
            .unwrap()
    };
    assert_eq!(value("plc.ao", "setpoint"), Some(json!(4.2)));
    assert_eq!(value("plc.do", "pump"), Some(json!(true)));
    assert_eq!(value("plc.do", "fan"), Some(json!(false)));
    let diag = gw.card_status();
    let counters = &diag[0].status.counters;
    assert!(
        counters["polls"].as_u64().unwrap() > 0 && counters["timeouts"] == 0,
        "{diag:?}"
    );

    // Stopping drives the outputs to their safe values *on the unit*: 1.5 bar, pump off,
    // fan on.
    let lines = gw.shutdown();
    assert_eq!(
        lines,
        vec!["card \"plc\" outputs at stop: analog [1.5], digital on [1]"]
    );
    let m = server.memory().lock().unwrap();
    assert_eq!(
        (m.holding[10], m.coils[0], m.coils[1]),
        (15, false, true),
        "the unit holds the safe values"
    );
}

/// mbpoll (a libmodbus master) against `port`: table 0 coils, 1 discrete inputs, 3 input
/// registers, 4 holding registers; 0-based `address`; `write` values, if any.
fn mbpoll(port: u16, table: &str, address: u16, write: &[&str]) -> String {
    Mbpoll {
        port,
        table,
        address,
        count: None,
        write,
    }
    .run()
}

#[test]
fn mbpoll_reads_and_writes_the_gateways_registers() {
    let text = SERVED;
    let d = Deployment::parse(text, "srv.toml").unwrap();
    let gw = Gateway::build(&d, "srv.toml", text, &hwgw::types::Types::builtin()).unwrap();
    gw.start().unwrap();
    let addr: std::net::SocketAddr = gw.server_address("modbus_server").unwrap().parse().unwrap();
    let port = addr.port();
    mbpoll_checks(&gw, port);
    gw.shutdown();
}

/// A sim card with loopbacks, served on a port of its own.
const SERVED: &str = r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 5
[card.sim]
digital_inputs = 4
digital_outputs = 4
digital_loopback = true
[[card.sim.analog_in]]
range = { lowest = -10.0, highest = 10.0, unit = "V" }
waveform = { kind = "loopback", analog_out = 0 }
[[card.sim.analog_out]]
range = { lowest = -10.0, highest = 10.0, unit = "V" }

[modbus_server]
listen = "127.0.0.1:0"
[[modbus_server.register]]       # the loopback input, in mV
table = "input_registers"
address = 0
device = "sim0"
interface = "analog_in"
channel = 0
type = "i16"
scale = 0.001
[[modbus_server.register]]       # the output, in mV
table = "holding_registers"
address = 10
device = "sim0"
interface = "analog_out"
channel = 0
type = "i16"
scale = 0.001
[[modbus_server.register]]
table = "coils"
address = 0
device = "sim0"
interface = "digital_out"
channel = 2
[[modbus_server.register]]
table = "discrete_inputs"
address = 0
device = "sim0"
interface = "digital_in"
channel = 2
"#;

fn mbpoll_checks(gw: &Gateway, port: u16) {
    let w = mbpoll(port, "4", 10, &["2500"]);
    assert!(w.contains("Written 1 references"), "{w}");
    let ao = gw.runtime().registry().analog_out().lookup("sim0").unwrap();
    assert!(
        (ao.read_back(0).unwrap() - 2.5).abs() < 0.001,
        "the write reached the device"
    );
    wait_until("the loopback input follows", || {
        mbpoll(port, "3", 0, &[]).contains("[0]: \t2500")
    });
    let r = mbpoll(port, "4", 10, &[]);
    assert!(
        r.contains("[10]: \t2500"),
        "holding register reads back: {r}"
    );

    let w = mbpoll(port, "0", 0, &["1"]);
    assert!(w.contains("Written 1 references"), "{w}");
    wait_until("the coil loops back to the discrete input", || {
        mbpoll(port, "1", 0, &[]).contains("[0]: \t1")
    });

    let e = mbpoll(port, "3", 5, &[]);
    assert!(
        e.contains("Illegal data address"),
        "an unmapped address is an exception: {e}"
    );
    let e = mbpoll(port, "4", 10, &["20000"]);
    assert!(
        e.contains("Illegal data value"),
        "20 V is outside -10..10 V: {e}"
    );
    assert!(
        (ao.read_back(0).unwrap() - 2.5).abs() < 0.001,
        "a refused write changes nothing"
    );
}

/// One request over `s` (transaction id `tid`, unit 1); the reply's PDU, or None when the
/// server closed the connection.
fn exchange(s: &mut std::net::TcpStream, tid: u16, pdu: &[u8]) -> Option<Vec<u8>> {
    use std::io::{Read, Write};
    let mut frame = tid.to_be_bytes().to_vec();
    frame.extend_from_slice(&[0, 0]);
    frame.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
    frame.push(1);
    frame.extend_from_slice(pdu);
    s.write_all(&frame).ok()?;
    let mut head = [0u8; 7];
    s.read_exact(&mut head).ok()?;
    assert_eq!(
        u16::from_be_bytes([head[0], head[1]]),
        tid,
        "the transaction id echoed"
    );
    let len = usize::from(u16::from_be_bytes([head[4], head[5]]));
    let mut body = vec![0u8; len - 1];
    s.read_exact(&mut body).ok()?;
    Some(body)
}

fn connect(addr: std::net::SocketAddr) -> std::net::TcpStream {
    let s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(std::time::Duration::from_secs(10)))
        .unwrap();
    s
}

/// True when the server closed `s` (a read gets end of file or a reset); false when the
/// read times out (10 s: the connection is still open) or returns data.
fn closed(s: &mut std::net::TcpStream) -> bool {
    use std::io::{ErrorKind, Read};
    let mut b = [0u8; 1];
    match s.read(&mut b) {
        Ok(0) => true,
        Ok(_) => false,
        Err(e) => matches!(
            e.kind(),
            ErrorKind::ConnectionReset | ErrorKind::ConnectionAborted | ErrorKind::BrokenPipe
        ),
    }
}

/// A client that sends requests and never reads the replies (its receive buffer made
/// small), until the server stops taking them: its writes time out.
fn flood_without_reading(addr: std::net::SocketAddr) -> std::net::TcpStream {
    use std::io::Write;
    let s = connect(addr);
    nix::sys::socket::setsockopt(&s, nix::sys::socket::sockopt::RcvBuf, &4096).unwrap();
    s.set_write_timeout(Some(std::time::Duration::from_millis(300)))
        .unwrap();
    let batch: Vec<u8> = (0..1000u16)
        .flat_map(|i| {
            let [a, b] = i.to_be_bytes();
            [a, b, 0, 0, 0, 6, 1, 3, 0, 10, 0, 1]
        })
        .collect();
    let t0 = std::time::Instant::now();
    let mut s = s;
    while s.write_all(&batch).is_ok() {
        assert!(
            t0.elapsed() < std::time::Duration::from_secs(60),
            "the server kept taking requests nobody reads the replies of"
        );
    }
    s
}

#[test]
fn hostile_requests_get_the_specifications_exceptions_and_the_server_survives() {
    let text = SERVED.replace(
        "listen = \"127.0.0.1:0\"\n",
        "listen = \"127.0.0.1:0\"\nmax_clients = 4\nidle_timeout_s = 1\n",
    );
    assert_ne!(text, SERVED);
    let d = Deployment::parse(&text, "srv.toml").unwrap();
    let gw = Gateway::build(&d, "srv.toml", &text, &hwgw::types::Types::builtin()).unwrap();
    gw.start().unwrap();
    let addr: std::net::SocketAddr = gw.server_address("modbus_server").unwrap().parse().unwrap();
    let mut s = connect(addr);
    for (pdu, want, why) in [
        (
            &[15u8, 0, 0, 0, 100, 1, 0xFF][..],
            [0x8F, 3],
            "FC15 quantity over 8 x byte count (panics tokio-modbus 0.17)",
        ),
        (
            &[16, 0, 10, 0x80, 0, 0],
            [0x90, 3],
            "FC16 quantity 0x8000 (overflows tokio-modbus 0.17)",
        ),
        (&[3, 0, 10, 0, 0], [0x83, 3], "quantity 0"),
        (&[3, 0, 10, 0, 126], [0x83, 3], "126 registers"),
        (&[4, 0, 0, 0, 126], [0x84, 3], "126 input registers"),
        (&[1, 0, 0, 0x07, 0xD1], [0x81, 3], "2001 coils"),
        (
            &[5, 0, 0, 0x12, 0x34],
            [0x85, 3],
            "FC5 value neither 0xFF00 nor 0",
        ),
        (&[43, 14, 1, 0], [0xAB, 1], "an unserved function"),
        (&[3, 0, 5, 0, 1], [0x83, 2], "an unmapped register"),
    ] {
        let got = exchange(&mut s, 7, pdu);
        assert_eq!(got.as_deref(), Some(&want[..]), "{why}");
    }
    // The connection still serves: the holding register at 10 (sim output 0 V).
    assert_eq!(
        exchange(&mut s, 8, &[3, 0, 10, 0, 1]).unwrap(),
        [3, 2, 0, 0]
    );
    // A frame that is not Modbus TCP (protocol id 1) closes the connection.
    {
        use std::io::Write;
        s.write_all(&[0, 9, 0, 1, 0, 6, 1, 3, 0, 10, 0, 1]).unwrap();
        assert!(
            closed(&mut s),
            "a foreign protocol id closes the connection"
        );
    }
    // At most 4 clients: a fifth is served, and the one idle longest (the first, whose
    // request is the oldest) is closed for it (or, on a slow run, by the 1 s idle timeout
    // already: hwgw_status_counts_evictions_and_refusals checks the count).
    let mut four: Vec<_> = (0..4).map(|_| connect(addr)).collect();
    for (i, c) in four.iter_mut().enumerate() {
        assert!(exchange(c, i as u16, &[3, 0, 10, 0, 1]).is_some());
    }
    let mut fifth = connect(addr);
    assert_eq!(
        exchange(&mut fifth, 5, &[3, 0, 10, 0, 1]).unwrap(),
        [3, 2, 0, 0]
    );
    assert!(closed(&mut four[0]), "the idle-longest client is closed");
    drop(four);
    drop(fifth);
    wait_until("the server sees its clients gone", || {
        gw.server_status()[0].status.counters["clients"] == json!(0)
    });
    // A client quiet for idle_timeout_s is closed.
    let mut quiet = connect(addr);
    let t0 = std::time::Instant::now();
    assert!(closed(&mut quiet), "an idle client is closed");
    assert!(
        t0.elapsed() >= std::time::Duration::from_millis(900),
        "{:?}",
        t0.elapsed()
    );
    // A client that sends and never reads is closed: once its replies waited idle_timeout
    // (the server's send buffer full), or — when its last write timed out in the middle
    // of a request and the server reached that half request before its buffer filled —
    // after frame_timeout. Which comes first depends on the kernel's buffer sizes and the
    // machine's load; both close it, each counted.
    let counter = |gw: &Gateway, name: &str| {
        gw.server_status()[0].status.counters[name]
            .as_u64()
            .unwrap()
    };
    let closings = |gw: &Gateway| counter(gw, "idle_closed") + counter(gw, "frame_timeouts");
    let before = closings(&gw);
    let flood_began = std::time::Instant::now();
    let greedy = flood_without_reading(addr);
    let flooded = flood_began.elapsed();
    let closed_in_time = testkit::wait_for(
        "the client that never reads closed",
        testkit::wait::PATIENCE,
        || closings(&gw) > before && gw.server_status()[0].status.counters["clients"] == json!(0),
    );
    if let Err(e) = closed_in_time {
        panic!(
            "timed out: {e}; the flood took {flooded:?}; server: {}",
            serde_json::to_value(gw.server_status()).unwrap()
        );
    }
    drop(greedy);
    let status = serde_json::to_value(gw.server_status()).unwrap();
    let c = &status[0]["counters"];
    assert_eq!(c["running"], json!(true), "{status}");
    assert_eq!(c["panics"], json!(0), "{status}");
    assert!(c["exceptions"].as_u64().unwrap() >= 9, "{status}");
    assert!(c["malformed"].as_u64().unwrap() >= 1, "{status}");
    assert!(
        c["evicted"].as_u64().unwrap() + c["idle_closed"].as_u64().unwrap() >= 2,
        "{status}"
    );
    assert!(c["idle_closed"].as_u64().unwrap() >= 1, "{status}");
    assert!(gw.health().is_ok(), "{:?}", gw.health());
    // And it serves a new client after all that.
    let mut again = connect(addr);
    assert_eq!(
        exchange(&mut again, 1, &[3, 0, 10, 0, 1]).unwrap(),
        [3, 2, 0, 0]
    );
    gw.shutdown();
}

/// The two requests that panic tokio-modbus 0.17's server decoder, sent to the real `hwgw`
/// binary: answered with exception 03, and nothing about a panic in its output.
#[test]
fn the_requests_that_panic_tokio_modbus_leave_no_trace_in_hwgws_output() {
    let dir = testkit::TempDir::new("modbus-hostile-config");
    let config = dir.path().join("srv.toml");
    std::fs::write(&config, SERVED).unwrap();
    let gw = testkit::Service::start(
        env!("CARGO_BIN_EXE_hwgw"),
        "modbus-hostile",
        &[&config],
        &[],
    )
    .unwrap();
    let addr = gw.wait_listening("modbus_server");
    let mut s = connect(addr);
    assert_eq!(
        exchange(&mut s, 1, &[15, 0, 0, 0, 100, 1, 0xFF]).unwrap(),
        [0x8F, 3]
    );
    assert_eq!(
        exchange(&mut s, 2, &[16, 0, 10, 0x80, 0, 0]).unwrap(),
        [0x90, 3]
    );
    assert_eq!(
        exchange(&mut s, 3, &[3, 0, 10, 0, 1]).unwrap(),
        [3, 2, 0, 0]
    );
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(
        !stopped.log.contains("panicked") && !stopped.log.contains("backtrace"),
        "hwgw's output mentions a panic:\n{}",
        stopped.log
    );
}

/// A connection to `to` from the loopback address 127.0.0.`host` (mbpoll's is 127.0.0.1).
fn connect_from(host: u8, to: std::net::SocketAddr) -> std::net::TcpStream {
    use nix::sys::socket::{AddressFamily, SockFlag, SockType, SockaddrIn, bind, socket};
    let std::net::SocketAddr::V4(to) = to else {
        panic!("{to}: not IPv4")
    };
    let fd = socket(
        AddressFamily::Inet,
        SockType::Stream,
        SockFlag::SOCK_CLOEXEC,
        None,
    )
    .unwrap();
    bind(
        std::os::fd::AsRawFd::as_raw_fd(&fd),
        &SockaddrIn::new(127, 0, 0, host, 0),
    )
    .unwrap();
    nix::sys::socket::connect(std::os::fd::AsRawFd::as_raw_fd(&fd), &SockaddrIn::from(to)).unwrap();
    let s = std::net::TcpStream::from(fd);
    s.set_read_timeout(Some(std::time::Duration::from_secs(10)))
        .unwrap();
    s
}

/// The real `hwgw` binary with a full table of idle connections: mbpoll is served (the
/// connection idle longest closed for it), an address past its share is refused, and
/// `hwgw status` counts both.
#[test]
fn hwgw_status_counts_evictions_and_refusals() {
    let text = SERVED.replace(
        "listen = \"127.0.0.1:0\"\n",
        "listen = \"127.0.0.1:0\"\nmax_clients = 3\nmax_clients_per_address = 2\n",
    );
    assert_ne!(text, SERVED);
    let dir = testkit::TempDir::new("modbus-evict-config");
    let config = dir.path().join("srv.toml");
    std::fs::write(&config, &text).unwrap();
    let gw = testkit::Service::start(env!("CARGO_BIN_EXE_hwgw"), "modbus-evict", &[&config], &[])
        .unwrap();
    let status = || -> serde_json::Value {
        gw.out(&["status", "--json"])
            .ok()
            .and_then(|s| serde_json::from_str(&s).ok())
            .unwrap_or_default()
    };
    let addr = gw.wait_listening("modbus_server");
    let clients = |n: u64| {
        wait_until("the server counts its clients", || {
            status()["servers"][0]["counters"]["clients"] == json!(n)
        })
    };
    // Every slot taken by idle connections: two from 127.0.0.2, one from 127.0.0.3.
    let mut idle = Vec::new();
    for (i, host) in [2, 2, 3].into_iter().enumerate() {
        idle.push(connect_from(host, addr));
        clients(i as u64 + 1);
    }
    // A third from 127.0.0.2: past its share, refused (no one is closed for it).
    let mut third = connect_from(2, addr);
    assert!(closed(&mut third), "the third from one address is refused");
    // mbpoll writes and reads: served, the connection idle longest closed for it.
    let port = addr.port();
    let w = mbpoll(port, "4", 10, &["2500"]);
    assert!(w.contains("Written 1 references"), "{w}");
    assert!(
        closed(&mut idle[0]),
        "the idle-longest connection is closed"
    );
    let r = mbpoll(port, "4", 10, &[]);
    assert!(r.contains("[10]: \t2500"), "{r}");
    let c = &status()["servers"][0]["counters"];
    assert!(c["evicted"].as_u64().unwrap() >= 1, "{c}");
    assert_eq!(c["refused_per_address"], json!(1), "{c}");
    let human = gw.out(&["status"]).unwrap();
    assert!(
        human.contains("evicted=") && human.contains("refused_per_address=1"),
        "{human}"
    );
    drop(idle);
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
}

/// A Modbus card's outputs set with the real `hwgw` binary: `hwgw set` answers once the
/// unit has the value (exit 0, the server holds it), and fails with the reason when the
/// write cannot reach the unit — never 0 for a value that is not there.
#[test]
fn hwgw_set_on_a_modbus_output_says_whether_the_unit_took_it() {
    let server = TestServer::start();
    let dir = testkit::TempDir::new("modbus-set-config");
    let config = dir.path().join("plc.toml");
    std::fs::write(
        &config,
        format!(
            r#"
[[card]]
name = "plc"
driver = "modbus"
sample_period_ms = 10

[card.modbus]
transport = {{ type = "tcp", address = "{}" }}
unit = 1
poll_ms = 10
timeout_ms = 200
stale_after = 2
offline_after = 3

[[card.modbus.point]]
table = "holding_registers"
address = 10
[[card.modbus.point]]
table = "coils"
address = 0
"#,
            server.addr()
        ),
    )
    .unwrap();
    let gw =
        testkit::Service::start(env!("CARGO_BIN_EXE_hwgw"), "modbus-set", &[&config], &[]).unwrap();
    let status = || -> serde_json::Value {
        gw.out(&["--json", "status"])
            .ok()
            .and_then(|s| serde_json::from_str(&s).ok())
            .unwrap_or_default()
    };
    let online = || {
        status()["devices"].as_array().is_some_and(|d| {
            d.iter().any(|d| {
                d["name"] == "plc" && d["interface"] == "analog_out" && d["status"] == "online"
            })
        })
    };
    wait_until("the unit online", online);

    // A unit that answers: exit 0, and the value is on the unit when `set` returns.
    gw.out(&["set", "plc.ao", "ch0", "1234"]).unwrap();
    gw.out(&["set", "plc.do", "bit0", "true"]).unwrap();
    {
        let m = server.memory().lock().unwrap();
        assert_eq!(
            (m.holding[10], m.coils[0]),
            (1234, true),
            "delivered means there"
        );
    }

    // A unit that stops taking writes (it still answers reads: online when the write is
    // taken): the write is retried until the unit is declared offline, then fails.
    server.memory().lock().unwrap().silent_writes = true;
    let set = gw.cli(&["set", "plc.ao", "ch0", "4321"]);
    let stderr = String::from_utf8_lossy(&set.stderr);
    assert!(!set.status.success(), "exit 0 for an undelivered write");
    assert!(stderr.contains("offline"), "{stderr}");
    eprintln!("unit down: {}", stderr.trim());
    assert_eq!(server.memory().lock().unwrap().holding[10], 1234);
    wait_until("the failed write counted", || {
        status()["cards"][0]["counters"]["writes_failed"]
            .as_u64()
            .is_some_and(|n| n >= 1)
    });

    // The unit back: the write its writer was told failed is never sent later (nobody
    // asks for it any more); a new one goes through. Then gone: every `set` fails, whether
    // the write was taken before the unit was declared offline or refused after.
    server.memory().lock().unwrap().silent_writes = false;
    wait_until("the unit online again", online);
    gw.out(&["set", "plc.do", "bit0", "false"]).unwrap();
    assert_eq!(
        server.memory().lock().unwrap().holding[10],
        1234,
        "the failed write was sent later"
    );
    gw.out(&["set", "plc.ao", "ch0", "4321"]).unwrap();
    assert_eq!(server.memory().lock().unwrap().holding[10], 4321);
    let mem = server.memory().clone();
    drop(server);
    for v in 0..5 {
        let set = gw.cli(&["set", "plc.ao", "ch0", &v.to_string()]);
        let stderr = String::from_utf8_lossy(&set.stderr);
        assert!(!set.status.success(), "exit 0 for a unit that is gone");
        assert!(stderr.contains("offline"), "{stderr}");
    }
    assert_eq!(mem.lock().unwrap().holding[10], 4321);
    drop(gw.terminate());
}
