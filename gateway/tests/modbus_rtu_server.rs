//! hwgw's Modbus server on RTU transports, against masters we did not write: pymodbus
//! (Debian's python3-pymodbus) with its RTU framer over TCP and on a serial port, and
//! mbpoll (libmodbus) on a serial port. The serial port is one end of a socat pty pair.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use driver_modbus::codec::{ByteOrder, Layout, Number, ValueType, WordOrder};
use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use serde_json::{Value, json};
use testkit::pty::PtyPair;
use testkit::pymodbus::PyMaster;
use testkit::rng::Rng;
use testkit::wait_until;

/// Sixteen analog outputs whose physical value is their raw value (a 32-bit converter
/// over ±2^31): every integer register value is held exactly.
const OUTPUTS: &str = r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 5
[card.sim]
digital_inputs = 4
digital_outputs = 4
digital_loopback = true
[[card.sim.analog_out]]
count = 16
range = { lowest = -2147483648.0, highest = 2147483647.0, unit = "V" }
raw = { min = -2147483648, max = 2147483647 }
"#;

fn start(text: &str) -> Gateway {
    let d = Deployment::parse(text, "srv.toml").unwrap();
    let gw = Gateway::build(&d, "srv.toml", text, &hwgw::types::Types::builtin()).unwrap();
    gw.start().unwrap();
    gw
}

/// The modbus server's counters.
fn counters(gw: &Gateway) -> Value {
    let s = gw.server_status();
    let r = s.iter().find(|r| r.name == "modbus_server").unwrap();
    serde_json::to_value(&r.status.counters).unwrap()
}

/// One served holding register entry of the random table and the value written to it.
struct Served {
    address: u16,
    layout: Layout,
    value: i64,
}

/// A random table over the sixteen outputs: 4 to 16 entries at random addresses below 300
/// (none overlapping), random integer types and word and byte orders; a random value for
/// each.
fn random_table(rng: &mut Rng) -> (String, Vec<Served>) {
    const TYPES: [ValueType; 4] = [
        ValueType::U16,
        ValueType::I16,
        ValueType::U32,
        ValueType::I32,
    ];
    let (mut toml, mut served) = (String::new(), Vec::new());
    let mut used = Vec::new();
    for channel in 0..4 + rng.below(13) as u32 {
        let ty = *rng.pick(&TYPES).unwrap();
        let n = ty.registers() as u16;
        let address = loop {
            let a = rng.below(300) as u16;
            if (a..a + n).all(|x| !used.contains(&x)) {
                break a;
            }
        };
        used.extend(address..address + n);
        let words = *rng
            .pick(&[WordOrder::HighFirst, WordOrder::LowFirst])
            .unwrap();
        let bytes = *rng.pick(&[ByteOrder::Normal, ByteOrder::Swapped]).unwrap();
        let value = match ty {
            ValueType::U16 => rng.below(65536) as i64,
            ValueType::I16 => rng.below(65536) as i64 - 32768,
            ValueType::U32 => rng.below(1 << 31) as i64,
            _ => rng.below(1 << 32) as i64 - (1 << 31),
        };
        let name = |d: String| d.to_lowercase();
        toml += &format!(
            "[[modbus_server.register]]\ntable = \"holding_registers\"\naddress = {address}\n\
             device = \"sim0\"\ninterface = \"analog_out\"\nchannel = {channel}\ntype = \"{}\"\n\
             words = \"{}\"\nbytes = \"{}\"\n",
            name(format!("{ty:?}")),
            if words == WordOrder::HighFirst {
                "high_first"
            } else {
                "low_first"
            },
            name(format!("{bytes:?}")),
        );
        served.push(Served {
            address,
            layout: Layout { ty, words, bytes },
            value,
        });
    }
    (toml, served)
}

#[test]
fn rtu_frames_over_tcp_write_and_read_random_tables_as_modbus_tcp_does() {
    let mut rng = Rng::new(0x395e_17e5);
    for round in 0..4 {
        let (table, served) = random_table(&mut rng);
        let text = format!(
            "{OUTPUTS}\n[modbus_server]\nlisten = \"127.0.0.1:0\"\nrtu_over_tcp = \"127.0.0.1:0\"\n{table}"
        );
        let gw = start(&text);
        let tcp_port: std::net::SocketAddr =
            gw.server_address("modbus_server").unwrap().parse().unwrap();
        // Where it serves, as `hwgw status` shows: "127.0.0.1:P, rtu_over_tcp 127.0.0.1:Q".
        let bus = gw.server_status()[0].status.bus.clone();
        let rtu_port: std::net::SocketAddr = bus
            .split_once("rtu_over_tcp ")
            .map(|(_, a)| a.parse().unwrap())
            .unwrap_or_else(|| panic!("{bus}"));
        let rtu_port = rtu_port.port();
        let mut rtu = PyMaster::connect("rtu_over_tcp", &rtu_port.to_string());
        let mut tcp = PyMaster::connect("tcp", &tcp_port.port().to_string());
        for s in &served {
            let regs = s.layout.encode(Number::Int(s.value)).unwrap();
            let regs = regs.as_slice().to_vec();
            let why = format!(
                "round {round}: {:?} at {} = {}\n{table}",
                s.layout, s.address, s.value
            );
            let write = if regs.len() == 1 {
                json!({"fn": 6, "address": s.address, "value": regs[0]})
            } else {
                json!({"fn": 16, "address": s.address, "values": regs})
            };
            assert_eq!(rtu.ask(&write), json!({"ok": []}), "{why}");
            let read = json!({"fn": 3, "address": s.address, "count": regs.len()});
            assert_eq!(
                rtu.ask(&read),
                json!({"ok": regs}),
                "over RTU frames: {why}"
            );
            assert_eq!(
                tcp.ask(&read),
                json!({"ok": regs}),
                "over Modbus TCP: {why}"
            );
        }
        let c = counters(&gw);
        assert_eq!(
            (
                c["crc_errors"].as_u64(),
                c["exceptions"].as_u64(),
                c["malformed"].as_u64()
            ),
            (Some(0), Some(0), Some(0)),
            "{c}"
        );
        assert_eq!(c["requests"].as_u64(), Some(3 * served.len() as u64), "{c}");
        drop((rtu, tcp));
        gw.shutdown();
    }
}

/// The RTU slave's deployment on `device`: units 7 and 8, the outputs served.
fn slave(device: &std::path::Path, extra: &str) -> String {
    format!(
        r#"{OUTPUTS}
[modbus_server]
units = [7, 8]
{extra}
[modbus_server.serial]
device = "{}"
baud = 19200
parity = "none"  # a pty refuses parity
[[modbus_server.register]]
table = "holding_registers"
address = 0
device = "sim0"
interface = "analog_out"
channel = 0
type = "i32"
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
"#,
        device.display()
    )
}

#[test]
fn an_rtu_slave_on_a_serial_port_serves_pymodbus_and_mbpoll() {
    let pty = PtyPair::new("rtu-slave");
    let gw = start(&slave(&pty.line(), ""));
    wait_until("the serial port open", || {
        counters(&gw)["port_opens"].as_u64() >= Some(1)
    });
    let mut master = PyMaster::connect("serial", &format!("{} 19200 N", pty.unit().display()));
    // Unit 7 writes and reads; unit 8 is the same table.
    let write = json!({"fn": 16, "unit": 7, "address": 0, "values": [0xFFFE, 0x1DC0]});
    assert_eq!(master.ask(&write), json!({"ok": []}));
    let read = |unit: u8| json!({"fn": 3, "unit": unit, "address": 0, "count": 2});
    assert_eq!(master.ask(&read(8)), json!({"ok": [0xFFFE, 0x1DC0]}));
    assert_eq!(
        master.ask(&json!({"fn": 5, "unit": 7, "address": 0, "value": true})),
        json!({"ok": []})
    );
    // The coil drives digital output 2, looped back to digital input 2.
    wait_until("the coil's output looped back", || {
        master.ask(&json!({"fn": 2, "unit": 7, "address": 0, "count": 1})) == json!({"ok": [true]})
    });
    // An address not served: IllegalDataAddress, as on TCP.
    assert_eq!(
        master.ask(&json!({"fn": 3, "unit": 7, "address": 5, "count": 1})),
        json!({"exception": 2})
    );
    // Another unit's request: not answered, counted.
    let other = master.ask(&read(9));
    assert_eq!(other["error"], "no reply", "{other}");
    // A broadcast: applied, not answered.
    let broadcast = json!({"fn": 16, "unit": 0, "address": 0, "values": [0, 42]});
    assert_eq!(master.ask(&broadcast), json!({"broadcast": true}));
    wait_until("the broadcast applied", || {
        master.ask(&read(7)) == json!({"ok": [0, 42]})
    });
    // A frame with a bad CRC: ignored (no reply), counted; the next one answered.
    let mut bad = vec![7u8, 3, 0, 0, 0, 2];
    let crc = driver_modbus::client::crc16(&bad) ^ 0x0101;
    bad.extend_from_slice(&crc.to_le_bytes());
    let hex: String = bad.iter().map(|b| format!("{b:02x}")).collect();
    assert_eq!(master.ask(&json!({"raw": hex})), json!({"ok": []}));
    wait_until("the bad frame counted", || {
        counters(&gw)["crc_errors"].as_u64() == Some(1)
    });
    assert_eq!(master.ask(&read(7)), json!({"ok": [0, 42]}));
    drop(master);
    // mbpoll (libmodbus) on the same port: reads and writes unit 8.
    // 70000 as an i32, high word first: 1, 4464.
    let out = testkit::mbpoll::rtu(&pty.unit(), (19200, "none"), 8, ("4", 0, 2), &["1", "4464"]);
    assert!(out.contains("Written 2 references"), "{out}");
    let out = testkit::mbpoll::rtu(&pty.unit(), (19200, "none"), 8, ("4", 0, 2), &[]);
    assert!(
        out.contains("[0]: \t1\n") && out.contains("[1]: \t4464"),
        "{out}"
    );
    let mut master = PyMaster::connect("serial", &format!("{} 19200 N", pty.unit().display()));
    assert_eq!(
        master.ask(&read(7)),
        json!({"ok": [1, 4464]}),
        "pymodbus sees mbpoll's write"
    );
    drop(master);
    let c = counters(&gw);
    assert_eq!(
        (
            c["broadcasts"].as_u64(),
            c["other_units"].as_u64(),
            c["crc_errors"].as_u64()
        ),
        (Some(1), Some(1), Some(1)),
        "{c}"
    );
    gw.shutdown();
}

#[test]
fn on_a_multi_drop_line_other_units_traffic_is_skipped_and_the_next_request_answered() {
    let pty = PtyPair::new("rtu-multidrop");
    let gw = start(&slave(&pty.line(), ""));
    wait_until("the serial port open", || {
        counters(&gw)["port_opens"].as_u64() >= Some(1)
    });
    let mut master = PyMaster::connect("serial", &format!("{} 19200 N", pty.unit().display()));
    let frame = |unit: u8, pdu: &[u8]| {
        let mut f = vec![unit];
        f.extend_from_slice(pdu);
        let crc = driver_modbus::client::crc16(&f);
        f.extend_from_slice(&crc.to_le_bytes());
        f.iter().map(|b| format!("{b:02x}")).collect::<String>()
    };
    // Unit 2's exchange as another master and unit 2 put it on the line — its request and
    // its 7-byte reply, shorter than a request — and the request to unit 7 right after
    // (no pause on the line to find the frame by).
    let others = frame(2, &[3, 0, 0, 0, 1]) + &frame(2, &[3, 2, 0, 42]);
    assert_eq!(master.ask(&json!({"raw": others})), json!({"ok": []}));
    let read = json!({"fn": 3, "unit": 7, "address": 0, "count": 2});
    assert_eq!(master.ask(&read), json!({"ok": [0, 0]}));
    let c = counters(&gw);
    assert_eq!(
        (c["other_units"].as_u64(), c["crc_errors"].as_u64()),
        (Some(2), Some(0)),
        "unit 2's request and reply skipped, no error: {c}"
    );
    gw.shutdown();
}

#[test]
fn a_slave_beside_tcp_answers_unit_1_alone_when_units_are_unset() {
    let pty = PtyPair::new("rtu-default-unit");
    let text = slave(&pty.line(), "listen = \"127.0.0.1:0\"\n").replace("units = [7, 8]\n", "");
    let gw = start(&text);
    wait_until("the serial port open", || {
        counters(&gw)["port_opens"].as_u64() >= Some(1)
    });
    let mut master = PyMaster::connect("serial", &format!("{} 19200 N", pty.unit().display()));
    let write = |unit: u8| json!({"fn": 16, "unit": unit, "address": 0, "values": [0, 5]});
    // Unit 3 is another device on the line: its writes are not hwgw's.
    assert_eq!(master.ask(&write(3))["error"], "no reply");
    assert_eq!(master.ask(&write(1)), json!({"ok": []}));
    drop(master);
    // Over TCP every unit id is the server's (unset units).
    let port = gw.server_address("modbus_server").unwrap();
    let mut tcp = PyMaster::connect("tcp", port.rsplit(':').next().unwrap());
    let read = json!({"fn": 3, "unit": 3, "address": 0, "count": 2});
    assert_eq!(tcp.ask(&read), json!({"ok": [0, 5]}));
    gw.shutdown();
}

#[test]
fn rs485_mode_on_a_port_without_it_is_a_clear_fault() {
    let pty = PtyPair::new("rtu-rs485");
    let text = slave(&pty.line(), "").replace(
        "baud = 19200\n",
        "baud = 19200\nrs485 = { rts_on_send = true, delay_after_send_ms = 1 }\n",
    );
    let gw = start(&text);
    wait_until("the port refused RS-485", || {
        counters(&gw)["port_errors"].as_u64() >= Some(1)
    });
    wait_until("the server unhealthy", || gw.health().is_err());
    let e = gw.health().unwrap_err();
    assert!(
        e.contains("TIOCSRS485") && e.contains(&pty.line().display().to_string()),
        "{e}"
    );
    assert_eq!(counters(&gw)["port_opens"].as_u64(), Some(0));
    gw.shutdown();
}
