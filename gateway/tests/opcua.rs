//! `[server.opcua]` with the real binary against an independent client, Python asyncua
//! (FreeOpcUa, pinned, installed by the tests): the address space browsed (every channel
//! of the demo and of a Modbus deployment served by pymodbus, with units and ranges),
//! values read equal to `hwgw get` bit for bit, a subscription with a deadband getting
//! exactly the changes beyond it, outputs written and read back with `hwgw get`, an
//! operation called, refused writes answered with their status codes and nothing written,
//! a card offline Bad and back Good.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::collections::BTreeMap;
use testkit::Service;
use testkit::opcua::UaClient;
use testkit::pymodbus::PyModbus;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

use testkit::fixtures::SIM_CARD as CARD;

/// A `[server.opcua]` section on a free loopback port, `extra` lines added; its URL.
fn section(extra: &str) -> (String, String) {
    let port = testkit::free_port();
    (
        format!("\n[server.opcua]\nlisten = \"127.0.0.1:{port}\"\npki_dir = \"pki\"\n{extra}\n"),
        format!("opc.tcp://127.0.0.1:{port}/"),
    )
}

fn get(svc: &Service, component: &str, port: &str) -> Value {
    svc.ok(json!({"cmd": "get", "component": component, "port": port}))
}

/// The variables browsed, by node id.
fn browse(c: &mut UaClient) -> BTreeMap<String, Value> {
    let a = c.ask(json!({"cmd": "browse"}));
    a["variables"]
        .as_array()
        .unwrap_or_else(|| panic!("{a}"))
        .iter()
        .map(|v| (v["id"].as_str().unwrap().to_string(), v.clone()))
        .collect()
}

fn read(c: &mut UaClient, id: &str) -> Value {
    let a = c.ask(json!({"cmd": "read", "ids": [id]}));
    a["values"][0].clone()
}

fn write(c: &mut UaClient, id: &str, ty: &str, value: Value) -> String {
    let a = c.ask(json!({"cmd": "write", "id": id, "type": ty, "value": value}));
    a["status"]
        .as_str()
        .unwrap_or_else(|| panic!("{a}"))
        .to_string()
}

/// The channels the control protocol lists: each IO component's channel ports
/// (`component.port`).
fn listed_channels(svc: &Service) -> Vec<String> {
    let mut out = Vec::new();
    for (component, dir) in [
        ("sim0.ai", "output"),
        ("sim0.ao", "input"),
        ("sim0.di", "output"),
        ("sim0.do", "input"),
        ("sim0.encoder0", "output"),
    ] {
        let d = svc.ok(json!({"cmd": "describe", "component": component}));
        for p in d["ports"].as_array().unwrap() {
            if p["direction"] == dir {
                out.push(format!("{component}.{}", p["name"].as_str().unwrap()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn the_demo_browsed_every_channel_with_units_and_ranges() {
    let demo = include_str!("../../config/demo.toml");
    let (section, url) = section("");
    let svc = Service::run_text(HWGW, "opcua-demo", &format!("{demo}{section}")).unwrap();
    let mut c = UaClient::open(&url);
    let vars = browse(&mut c);
    let mut channels: Vec<String> = vars
        .keys()
        .filter(|k| !k.contains('/') && !k.contains(':'))
        .cloned()
        .collect();
    channels.sort();
    assert_eq!(channels, listed_channels(&svc));
    for id in &channels {
        let v = &vars[id];
        let analog = id.starts_with("sim0.ai.") || id.starts_with("sim0.ao.");
        if analog {
            assert_eq!(v["type"], "Double", "{v}");
            assert_eq!(v["range"], json!([-10.0, 10.0]), "{v}");
            assert_eq!(v["unit"], "V", "{v}");
        } else if id.starts_with("sim0.encoder0.") {
            assert_eq!(v["type"], "Int64", "{v}");
        } else {
            assert_eq!(v["type"], "Boolean", "{v}");
        }
        assert_eq!(v["status"], "Good", "{v}");
        let path = v["path"].as_str().unwrap();
        assert!(path.starts_with("sim0/"), "{path}");
    }
    // The channel's place: hwgw/<card>/<device>/<channel>.
    assert_eq!(vars["sim0.ai.ch0"]["path"], "sim0/ai/ch0");
    assert_eq!(vars["sim0.encoder0.turn"]["path"], "sim0/encoder0/turn");
}

#[test]
fn values_writes_and_calls() {
    let (section, url) =
        section("allow_writes = true\nallow_calls = true\nanonymous = \"operator\"");
    let svc = Service::run_text(HWGW, "opcua-values", &format!("{CARD}{section}")).unwrap();
    let mut c = UaClient::open(&url);

    // Values equal to `hwgw get`, bit for bit (both JSON numbers that round-trip).
    for (component, port) in [("sim0.ai", "ch0"), ("sim0.ai", "ch1"), ("sim0.di", "bit2")] {
        let id = format!("{component}.{port}");
        testkit::wait_until(&format!("{id} read"), || {
            let v = read(&mut c, &id);
            v["status"] == "Good" && v["value"] == get(&svc, component, port)
        });
    }
    // (The sim's 16-bit converter: 1.25 V reads 1.249866483558403.)
    let ch0 = get(&svc, "sim0.ai", "ch0");
    assert!((ch0.as_f64().unwrap() - 1.25).abs() < 1e-3, "{ch0}");

    // An output written, read back with `hwgw get` and by its loopback input.
    assert_eq!(write(&mut c, "sim0.ao.ch0", "Double", json!(2.5)), "Good");
    let near = |v: &Value, x: f64| v.as_f64().is_some_and(|v| (v - x).abs() < 1e-3);
    testkit::wait_until("ao.ch0 read back", || {
        let g = get(&svc, "sim0.ai", "ch2");
        near(&g, 2.5) && read(&mut c, "sim0.ai.ch2")["value"] == g
    });
    assert_eq!(
        write(&mut c, "sim0.do.bit1", "Boolean", json!(true)),
        "Good"
    );
    testkit::wait_until("do.bit1 looped back", || {
        get(&svc, "sim0.di", "bit1") == json!(true)
            && read(&mut c, "sim0.di.bit1")["value"] == json!(true)
    });

    // Refused writes: their status codes, nothing written.
    let refusals = [
        ("sim0.ao.ch0", "Double", json!(11.0), "BadOutOfRange"),
        ("sim0.ao.ch0", "Boolean", json!(true), "BadTypeMismatch"),
        ("sim0.ai.ch0", "Double", json!(1.0), "BadNotWritable"),
        ("sim0.do.bit1", "Double", json!(0.0), "BadTypeMismatch"),
    ];
    for (id, ty, value, code) in refusals {
        assert_eq!(
            write(&mut c, id, ty, value.clone()),
            code,
            "{id} {ty} {value}"
        );
    }
    assert!(near(&read(&mut c, "sim0.ao.ch0")["value"], 2.5));
    assert!(near(&get(&svc, "sim0.ai", "ch2"), 2.5));
    assert_eq!(get(&svc, "sim0.di", "bit1"), json!(true));
    let counters = svc.server_status("server.opcua")["counters"].clone();
    assert_eq!(counters["writes"], 2, "{counters}");
    assert_eq!(counters["writes_refused"], 4, "{counters}");

    // An operation called with its typed argument; a wrong call refused.
    let a = c.ask(json!({"cmd": "call", "object": "component:sim0.ai", "method": "call:sim0.ai.read", "args": [["UInt32", 0]]}));
    assert_eq!(a["outputs"], ch0, "{a}");
    let a = c.ask(json!({"cmd": "call", "object": "component:sim0.ai", "method": "call:sim0.ai.read", "args": []}));
    assert_eq!(a["status"], "BadArgumentsMissing", "{a}");
    let a = c.ask(json!({"cmd": "call", "object": "component:sim0.ai", "method": "call:sim0.ai.read", "args": [["UInt32", 99]]}));
    assert!(a["status"].as_str().unwrap().starts_with("Bad"), "{a}");
    c.ask(json!({"cmd": "close"}));
}

/// Writes `v` to `id` and waits until a read of it gives it back (the sampler has seen it;
/// the sim's 16-bit converter reads it back within a step); returns the value read back.
fn settle(c: &mut UaClient, id: &str, v: f64) -> Value {
    assert_eq!(write(c, id, "Double", json!(v)), "Good");
    let mut back = Value::Null;
    testkit::wait_until(&format!("{id} = {v}"), || {
        back = read(c, id)["value"].clone();
        back.as_f64().is_some_and(|b| (b - v).abs() < 1e-3)
    });
    back
}

/// Writes each of `values` to `id`; after one that `crosses` the deadband, waits for its
/// notification (and only it), so each arrives before the next write.
fn walk(c: &mut UaClient, id: &str, values: &[(f64, bool)]) {
    for &(v, crosses) in values {
        let back = settle(c, id, v);
        if crosses {
            let got = c.ask(json!({"cmd": "notifications", "count": 1, "timeout": 30}));
            assert_eq!(
                got["changes"],
                json!([{"id": id, "value": back, "status": "Good"}]),
                "{id} = {v}"
            );
        }
    }
}

#[test]
fn a_subscription_with_a_deadband_gets_exactly_the_changes_beyond_it() {
    let (section, url) = section("allow_writes = true\nanonymous = \"operator\"");
    let _svc = Service::run_text(HWGW, "opcua-deadband", &format!("{CARD}{section}")).unwrap();
    let mut c = UaClient::open(&url);
    // Absolute deadband 0.5 on ao.ch1; percent 10 % of its 20 V range (2 V) on ao.ch0.
    let a = c.ask(
        json!({"cmd": "subscribe", "ids": ["sim0.ao.ch1"], "interval": 20,
        "deadband": {"type": "absolute", "value": 0.5}, "queue": 10}),
    );
    assert_eq!(a["items"], json!(["Good"]), "{a}");
    let a = c.ask(
        json!({"cmd": "subscribe", "ids": ["sim0.ao.ch0"], "interval": 20,
        "deadband": {"type": "percent", "value": 10.0}, "queue": 10}),
    );
    assert_eq!(a["items"], json!(["Good"]), "{a}");
    let first = c.ask(json!({"cmd": "notifications", "count": 2, "timeout": 30}));
    assert_eq!(first["changes"].as_array().unwrap().len(), 2, "{first}");
    // Beyond 0.5 from the last reported: 1.0 (from 0), 1.6, 3.0; not 1.2, 1.7, 2.6.
    let ch1 = [
        (1.0, true),
        (1.2, false),
        (1.6, true),
        (1.7, false),
        (3.0, true),
        (2.6, false),
    ];
    walk(&mut c, "sim0.ao.ch1", &ch1);
    // Beyond 2 V: 2.5 (from 0), 5.0; not 1.5, 4.0.
    let ch0 = [(1.5, false), (2.5, true), (4.0, false), (5.0, true)];
    walk(&mut c, "sim0.ao.ch0", &ch0);
    // Nothing more comes: the values that did not cross were sampled before those that
    // did were notified.
    let more = c.ask(json!({"cmd": "notifications", "count": 1, "timeout": 1}));
    assert_eq!(more["changes"], json!([]), "{more}");
}

#[test]
fn a_modbus_card_browsed_offline_bad_and_back_good() {
    let plc = PyModbus::start("tcp");
    let card = format!(
        "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\nsample_period_ms = 10\n\
         [card.modbus]\ntransport = {{ type = \"tcp\", address = \"{}\" }}\nunit = 1\npoll_ms = 20\n\
         timeout_ms = 200\nstale_after = 2\noffline_after = 3\nbackoff_max_ms = 200\n\
         [[card.modbus.point]]\ntable = \"input_registers\"\naddress = 0\ntype = \"i16\"\nscale = 0.1\nunit = \"bar\"\n\
         [[card.modbus.point]]\ntable = \"input_registers\"\naddress = 30\ntype = \"f64\"\nunit = \"m3/h\"\n\
         [[card.modbus.point]]\ntable = \"discrete_inputs\"\naddress = 3\n",
        plc.addr
    );
    let (section, url) = section("");
    let svc = Service::run_text(HWGW, "opcua-modbus", &format!("{card}{section}")).unwrap();
    let mut c = UaClient::open(&url);
    testkit::wait_until("the unit's values", || {
        read(&mut c, "plc.ai.ch0")["status"] == "Good"
            && read(&mut c, "plc.ai.ch1")["status"] == "Good"
    });
    let vars = browse(&mut c);
    let (p, f) = (&vars["plc.ai.ch0"], &vars["plc.ai.ch1"]);
    assert_eq!(
        (p["path"].as_str(), p["unit"].as_str()),
        (Some("plc/ai/ch0"), Some("bar")),
        "{p}"
    );
    assert_eq!(
        (f["unit"].as_str(), f["type"].as_str()),
        (Some("m3/h"), Some("Double")),
        "{f}"
    );
    assert!(p["range"].is_array(), "{p}");
    assert_eq!(vars["plc.di.bit0"]["type"], "Boolean");
    // The values pymodbus holds, as `hwgw get` reads them.
    assert_eq!(read(&mut c, "plc.ai.ch0")["value"], json!(-12.3));
    assert_eq!(
        read(&mut c, "plc.ai.ch0")["value"],
        get(&svc, "plc.ai", "ch0")
    );
    assert_eq!(read(&mut c, "plc.ai.ch1")["value"], json!(1.25));
    assert_eq!(read(&mut c, "plc.di.bit0")["value"], json!(true));

    // The unit hung: Bad, with the device's error; answering again: Good.
    plc.pause();
    testkit::wait_until("Bad while the unit hangs", || {
        read(&mut c, "plc.ai.ch0")["status"]
            .as_str()
            .unwrap()
            .starts_with("Bad")
    });
    let error = read(&mut c, "plc.ai/Error")["value"].clone();
    assert!(!error.as_str().unwrap().is_empty(), "{error}");
    plc.resume();
    testkit::wait_until("Good once it is back", || {
        read(&mut c, "plc.ai.ch0")["status"] == "Good"
    });
    assert_eq!(read(&mut c, "plc.ai.ch0")["value"], json!(-12.3));
}

#[test]
fn the_example_serves_and_takes_writes() {
    let example = include_str!("../../config/opcua.toml");
    let port = testkit::free_port();
    let text = example.replace("127.0.0.1:4840", &format!("127.0.0.1:{port}"));
    assert_ne!(text, example, "the example's listen address moved");
    let svc = Service::run_text(HWGW, "opcua-example", &text).unwrap();
    let mut c = UaClient::open(&format!("opc.tcp://127.0.0.1:{port}/"));
    assert_eq!(write(&mut c, "sim0.ao.ch0", "Double", json!(-4.0)), "Good");
    testkit::wait_until("analog output 0 read back on input 1", || {
        let g = get(&svc, "sim0.ai", "ch1");
        g.as_f64().is_some_and(|v| (v + 4.0).abs() < 1e-3)
            && read(&mut c, "sim0.ai.ch1")["value"] == g
    });
    assert!(svc.dir().join("opcua-pki/own/cert.der").exists());
}
