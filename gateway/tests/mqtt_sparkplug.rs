//! `[server.mqtt]` as a Sparkplug B edge node, with the real binary against a real
//! Mosquitto and an independent host application (`peers/sparkplug_host.py`: paho-mqtt,
//! and mqtt-spb-wrapper's protobuf module to decode): the births name every channel of
//! the deployment with its datatype, unit and range; data equals `hwgw get` bit for bit;
//! a DCMD writes an output `hwgw get` reads back, a bad one is refused whole and
//! reported; a rebirth is answered; `seq` runs on without a gap across hundreds of
//! messages; a broker restart shows the host the NDEATH (the will) and then a birth with
//! `bdSeq` one more; a card gone offline is a DDEATH and back a DBIRTH; the primary
//! host's STATE holds the data while it is offline.
#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use driver_modbus::testing::TestServer;
use serde_json::{Value, json};
use std::path::Path;
use std::time::Duration;
use testkit::Service;
use testkit::mosquitto::{Broker, SparkplugHost};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const EXAMPLE: &str = include_str!("../../config/mqtt.toml");
const HOST: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/peers/sparkplug_host.py");
const IDS: (&str, &str, &str) = ("plant1", "hwgw1", "scada");

/// The shipped example on the test's broker, read every 20 ms, with `sparkplug` added to
/// its Sparkplug section and `more` after it.
fn deployment(port: u16, sparkplug: &str, more: &str) -> String {
    let text = EXAMPLE
        .replace("127.0.0.1:1883", &format!("127.0.0.1:{port}"))
        .replace("sample_period_ms = 100 ", "sample_period_ms = 20 ")
        .replace(
            "node = \"hwgw1\"\n",
            &format!("node = \"hwgw1\"\n{sparkplug}"),
        );
    format!("{more}\n{text}")
}

fn host(broker: &Broker) -> SparkplugHost {
    SparkplugHost::start(Path::new(HOST), broker.port, IDS, &[])
}

/// Metric `name` of message `m`.
fn metric<'a>(m: &'a Value, name: &str) -> &'a Value {
    m["metrics"]
        .as_array()
        .and_then(|l| l.iter().find(|x| x["name"] == name))
        .unwrap_or_else(|| panic!("no metric {name} in {m}"))
}

fn has(m: &Value, name: &str) -> bool {
    m["metrics"]
        .as_array()
        .is_some_and(|l| l.iter().any(|x| x["name"] == name))
}

fn get(svc: &Service, component: &str, port: &str) -> Value {
    svc.ok(json!({"cmd": "get", "component": component, "port": port}))
}

fn counters(svc: &Service) -> Value {
    svc.server_status("server.mqtt")["counters"].clone()
}

fn dcmd(host: &mut SparkplugHost, metrics: Value) {
    host.command(json!({"cmd": "dcmd", "device": "sim0", "metrics": metrics}));
}

/// The next DDATA of sim0 carrying `name` at a value satisfying `f`.
fn ddata(host: &mut SparkplugHost, name: &str, mut f: impl FnMut(&Value) -> bool) -> Value {
    host.until(&format!("DDATA {name}"), |e| {
        e["type"] == "DDATA"
            && e["device"] == "sim0"
            && has(e, name)
            && f(&metric(e, name)["value"])
    })
}

/// The births name every channel with its datatype, unit, range and whether it may be
/// written, at the value `hwgw get` reads.
fn check_birth(svc: &Service, dbirth: &Value) {
    let mut names: Vec<String> = dbirth["metrics"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["name"].as_str().unwrap().to_string())
        .collect();
    names.sort();
    let mut want: Vec<String> = (0..4).map(|c| format!("ai/ch{c}")).collect();
    want.extend((0..2).map(|c| format!("ao/ch{c}")));
    want.extend((0..4).map(|b| format!("di/bit{b}")));
    want.extend((0..4).map(|b| format!("do/bit{b}")));
    want.sort();
    assert_eq!(names, want);
    for m in dbirth["metrics"].as_array().unwrap() {
        let name = m["name"].as_str().unwrap();
        let (kind, port) = name.split_once('/').unwrap();
        let p = &m["properties"];
        let output = kind == "ao" || kind == "do";
        assert_eq!(p["readOnly"], !output, "{m}");
        if kind.starts_with('a') {
            assert_eq!(m["datatype"], 10, "{m}");
            assert_eq!(
                (&p["engUnit"], &p["engLow"], &p["engHigh"]),
                (&json!("V"), &json!(-10.0), &json!(10.0)),
                "{m}"
            );
        } else {
            assert_eq!(m["datatype"], 11, "{m}");
            assert!(p.get("engUnit").is_none(), "{m}");
        }
        assert!(m["alias"].as_u64().is_some(), "{m}");
        if name != "ai/ch3" {
            // ai/ch3 is noise: read again by the time `get` asks.
            assert_eq!(
                m["value"],
                get(svc, &format!("sim0.{kind}"), port),
                "{name}"
            );
        }
    }
}

/// The node's messages from its last NBIRTH on (the host's own commands left out).
fn since_birth(host: &SparkplugHost) -> Vec<Value> {
    let node: Vec<&Value> = host
        .seen
        .iter()
        .filter(|e| {
            e["event"] == "message"
                && !["NCMD", "DCMD", "NDEATH"].contains(&e["type"].as_str().unwrap())
        })
        .collect();
    let start = node.iter().rposition(|e| e["type"] == "NBIRTH").unwrap();
    node[start..].iter().map(|e| (*e).clone()).collect()
}

#[test]
fn births_data_commands_rebirth_and_seq() {
    let broker = Broker::start();
    let mut host = host(&broker);
    let svc = Service::run_text(HWGW, "mqtt-spb", &deployment(broker.port, "", "")).unwrap();
    let nbirth = host.message("NBIRTH", None);
    assert_eq!(nbirth["seq"], 0);
    assert_eq!(metric(&nbirth, "bdSeq")["value"], 0);
    assert_eq!(metric(&nbirth, "Node Control/Rebirth")["value"], false);
    let dbirth = host.message("DBIRTH", Some("sim0"));
    assert_eq!(dbirth["seq"], 1);
    check_birth(&svc, &dbirth);

    // Data as `hwgw get` reads it; a DCMD writes an output, with the checks of `hwgw set`.
    dcmd(
        &mut host,
        json!([{"name": "ao/ch0", "datatype": 10, "value": 3.5}]),
    );
    let d = ddata(&mut host, "ao/ch0", |v| {
        v.as_f64().is_some_and(|v| (v - 3.5).abs() < 1e-3)
    });
    assert_eq!(metric(&d, "ao/ch0")["value"], get(&svc, "sim0.ao", "ch0"));
    let looped = ddata(&mut host, "ai/ch2", |v| {
        v.as_f64().is_some_and(|v| (v - 3.5).abs() < 1e-3)
    });
    assert_eq!(
        metric(&looped, "ai/ch2")["value"],
        get(&svc, "sim0.ai", "ch2")
    );
    dcmd(
        &mut host,
        json!([{"name": "do/bit1", "datatype": 11, "value": true}]),
    );
    ddata(&mut host, "di/bit1", |v| v == &json!(true));
    assert_eq!(get(&svc, "sim0.do", "bit1"), json!(true));

    // Refused whole, reported as the node's metrics, nothing written.
    let (ao0, ao1) = (get(&svc, "sim0.ao", "ch0"), get(&svc, "sim0.ao", "ch1"));
    let refused: [(Value, &str); 5] = [
        (
            json!([{"name": "ao/ch0", "datatype": 10, "value": 20.0}]),
            "out of its range",
        ),
        (
            json!([{"name": "ao/ch1", "datatype": 10, "value": 1.0}, {"name": "ao/ch0", "datatype": 10, "value": 99.0}]),
            "out of its range",
        ),
        (
            json!([{"name": "ao/ch9", "datatype": 10, "value": 1.0}]),
            "no metric",
        ),
        (
            json!([{"name": "ai/ch0", "datatype": 10, "value": 1.0}]),
            "is an input",
        ),
        (
            json!([{"name": "do/bit0", "datatype": 10, "value": 1.0}]),
            "write a boolean",
        ),
    ];
    for (n, (metrics, why)) in refused.iter().enumerate() {
        dcmd(&mut host, metrics.clone());
        let nd = host.until("the refusal", |e| {
            e["type"] == "NDATA" && has(e, "hwgw/Commands Refused")
        });
        assert_eq!(
            metric(&nd, "hwgw/Commands Refused")["value"],
            n as u64 + 1,
            "{nd}"
        );
        let last = metric(&nd, "hwgw/Last Refusal")["value"]
            .as_str()
            .unwrap()
            .to_string();
        assert!(last.contains(why), "{last:?} should say {why:?}");
    }
    // An output whose IO component is stopped: the whole command refused, the other
    // output of it not written.
    svc.ok(json!({"cmd": "stop", "component": "sim0.do"}));
    dcmd(
        &mut host,
        json!([{"name": "ao/ch1", "datatype": 10, "value": 1.0}, {"name": "do/bit0", "datatype": 11, "value": true}]),
    );
    let nd = host.until("the refusal", |e| {
        e["type"] == "NDATA" && has(e, "hwgw/Commands Refused")
    });
    assert_eq!(metric(&nd, "hwgw/Commands Refused")["value"], 6, "{nd}");
    assert!(
        metric(&nd, "hwgw/Last Refusal")["value"]
            .as_str()
            .unwrap()
            .contains("sim0.do is not running"),
        "{nd}"
    );
    svc.ok(json!({"cmd": "start", "component": "sim0.do"}));

    // Not a Sparkplug payload at all.
    let topic = "spBv1.0/plant1/DCMD/hwgw1/sim0";
    testkit::mosquitto::publish(broker.port, topic, b"\xff\xff\xff not protobuf", None);
    let nd = host.until("the refusal", |e| {
        e["type"] == "NDATA" && has(e, "hwgw/Commands Refused")
    });
    assert_eq!(metric(&nd, "hwgw/Commands Refused")["value"], 7, "{nd}");
    assert!(
        metric(&nd, "hwgw/Last Refusal")["value"]
            .as_str()
            .unwrap()
            .contains("not a Sparkplug B payload")
    );
    assert_eq!(
        (get(&svc, "sim0.ao", "ch0"), get(&svc, "sim0.ao", "ch1")),
        (ao0, ao1),
        "half applied"
    );
    let c = counters(&svc);
    assert_eq!(
        (&c["commands_accepted"], &c["commands_refused"]),
        (&json!(2), &json!(7)),
        "{c}"
    );

    // A rebirth: the same session (bdSeq), seq from 0 again, the values now.
    host.command(json!({"cmd": "rebirth"}));
    let again = host.message("NBIRTH", None);
    assert_eq!(
        (&again["seq"], &metric(&again, "bdSeq")["value"]),
        (&json!(0), &json!(0))
    );
    let dbirth = host.message("DBIRTH", Some("sim0"));
    assert_eq!(
        metric(&dbirth, "ao/ch0")["value"],
        get(&svc, "sim0.ao", "ch0")
    );
    assert!(
        !has(&dbirth, "hwgw/Commands Refused"),
        "a node metric in a device birth"
    );

    // seq: one more each message, wrapping at 255, across 300 messages.
    let mut count = 0;
    host.until("300 messages", |e| {
        count += u32::from(
            e["event"] == "message"
                && ["DBIRTH", "DDATA", "NDATA", "DDEATH"].contains(&e["type"].as_str().unwrap()),
        );
        count >= 300
    });
    let messages = since_birth(&host);
    assert!(messages.len() > 300, "{}", messages.len());
    for w in messages.windows(2) {
        let (a, b) = (w[0]["seq"].as_u64().unwrap(), w[1]["seq"].as_u64().unwrap());
        assert_eq!(b, (a + 1) % 256, "{} then {}", w[0], w[1]);
    }
    assert_eq!(counters(&svc)["dropped"], 0);
}

#[test]
fn broker_restart_and_a_card_offline() {
    let plc = TestServer::start();
    let card = format!(
        "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\nsample_period_ms = 10\n\
         [card.modbus]\ntransport = {{ type = \"tcp\", address = \"{}\" }}\nunit = 1\npoll_ms = 10\n\
         timeout_ms = 100\nstale_after = 2\noffline_after = 3\n\
         [[card.modbus.point]]\ntable = \"holding_registers\"\naddress = 10\n\
         [[card.modbus.point]]\ntable = \"input_registers\"\naddress = 0\n",
        plc.addr()
    );
    let mut broker = Broker::start();
    let mut host = host(&broker);
    let svc = Service::run_text(
        HWGW,
        "mqtt-spb-restart",
        &deployment(broker.port, "", &card),
    )
    .unwrap();
    assert_eq!(metric(&host.message("NBIRTH", None), "bdSeq")["value"], 0);
    let birth = host.message("DBIRTH", Some("plc"));
    assert!(has(&birth, "ao/ch0"), "{birth}");

    // The unit stops answering: its card is offline, a DDEATH; back, a DBIRTH.
    plc.memory().lock().unwrap().silent.insert(1);
    let plc_status = || {
        svc.ok(json!({"cmd": "status"}))["devices"]
            .as_array()
            .unwrap()
            .iter()
            .find(|d| d["name"] == "plc")
            .unwrap()["status"]
            .clone()
    };
    testkit::wait_until("the unit offline", || plc_status() == "offline");
    host.message("DDEATH", Some("plc"));
    plc.memory().lock().unwrap().silent.remove(&1);
    host.message("DBIRTH", Some("plc"));

    // The broker stopped and started: the host sees the NDEATH of the session (the will
    // Mosquitto publishes as it stops, kept for the host's session), then a new birth.
    broker.restart();
    let death = host.message("NDEATH", None);
    assert_eq!(metric(&death, "bdSeq")["value"], 0, "{death}");
    let nbirth = host.message("NBIRTH", None);
    assert_eq!(
        (&nbirth["seq"], &metric(&nbirth, "bdSeq")["value"]),
        (&json!(0), &json!(1))
    );
    host.message("DBIRTH", Some("sim0"));
    let c = counters(&svc);
    assert_eq!(
        (&c["reconnects"], &c["bd_seq"], &c["connected"]),
        (&json!(1), &json!(1), &json!(true)),
        "{c}"
    );
}

#[test]
fn the_primary_host_state_holds_the_data() {
    let broker = Broker::start();
    let mut host = host(&broker);
    let text = deployment(broker.port, "primary_host = \"scada\"\n", "");
    let svc = Service::run_text(HWGW, "mqtt-spb-state", &text).unwrap();
    // The host's STATE (retained) is online: births.
    assert_eq!(metric(&host.message("NBIRTH", None), "bdSeq")["value"], 0);
    host.message("DDATA", Some("sim0"));

    // Offline: the node leaves (its NDEATH) and publishes nothing while the host is away.
    host.command(json!({"cmd": "state", "online": false}));
    let death = host.message("NDEATH", None);
    assert_eq!(metric(&death, "bdSeq")["value"], 0);
    // Meanwhile an output changes: the birth at the host's return carries it.
    svc.ok(json!({"cmd": "set", "component": "sim0.ao", "port": "ch0", "value": -4.0}));
    let mut quiet = Vec::new();
    let end = std::time::Instant::now() + Duration::from_secs(2);
    while let Some(e) = host.next(end.saturating_duration_since(std::time::Instant::now())) {
        quiet.push(e);
    }
    assert!(
        !quiet
            .iter()
            .any(|e| e["event"] == "message" && e["type"] != "NDEATH"),
        "published while the host was offline: {quiet:?}"
    );
    assert_eq!(counters(&svc)["host_online"], false);

    // Back: a new session, its birth with the newest values.
    host.command(json!({"cmd": "state", "online": true}));
    let nbirth = host.message("NBIRTH", None);
    assert_eq!(metric(&nbirth, "bdSeq")["value"], 1);
    let dbirth = host.message("DBIRTH", Some("sim0"));
    assert_eq!(
        metric(&dbirth, "ao/ch0")["value"],
        get(&svc, "sim0.ao", "ch0")
    );
    let v = metric(&dbirth, "ao/ch0")["value"].as_f64().unwrap();
    assert!(
        (v + 4.0).abs() < 1e-3,
        "the birth's ao/ch0 is {v}, not the -4 set meanwhile"
    );
    let looped = metric(&dbirth, "ai/ch2")["value"].as_f64().unwrap();
    assert!(
        (looped + 4.0).abs() < 1e-3,
        "the birth's ai/ch2 is {looped}"
    );
}
