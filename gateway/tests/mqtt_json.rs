//! `[server.mqtt]`'s plain JSON topics and its TLS, with the real binary against a real
//! Mosquitto (Debian's, started by the test on a free loopback port) and its own
//! command-line clients: `mosquitto_sub` sees the values `hwgw get` reads, retained;
//! `mosquitto_pub` to a set topic writes an output; malformed set messages (not JSON, a
//! wrong type, out of range, an unknown channel, an input) are refused, each answered on
//! its `/result` topic and counted, nothing written. Over TLS with certificates the test
//! makes, hwgw's client certificate is taken and one of another CA refused.
#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::time::Duration;
use testkit::certs::Certs;
use testkit::mosquitto::{Broker, Sub, publish};
use testkit::{Service, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const WAIT: Duration = Duration::from_secs(30);

use testkit::fixtures::SIM_CARD as CARD;

fn get(svc: &Service, component: &str, port: &str) -> Value {
    svc.ok(json!({"cmd": "get", "component": component, "port": port}))
}

fn counters(svc: &Service) -> Value {
    svc.server_status("server.mqtt")["counters"].clone()
}

/// The value of the next message on `topic`.
fn next_value(sub: &mut Sub, topic: &str) -> Value {
    let (_, p) = sub.until(topic, WAIT, |t, _| t == topic);
    serde_json::from_str::<Value>(&p).unwrap()["value"].clone()
}

#[test]
fn json_topics_carry_values_and_checked_writes() {
    let broker = Broker::start();
    let mut sub = Sub::start(broker.port, &["hwgw/#"], None);
    let metrics = testkit::free_port();
    let text = format!(
        "{CARD}\n[server.metrics]\nlisten = \"127.0.0.1:{metrics}\"\n\
         [server.mqtt]\nbroker = \"127.0.0.1:{}\"\nallow_writes = true\n[server.mqtt.json]\nprefix = \"hwgw\"\n",
        broker.port
    );
    let svc = Service::run_text(HWGW, "mqtt-json", &text).unwrap();

    // The values, as `hwgw get` reads them, bit for bit; outputs read back.
    let v = next_value(&mut sub, "hwgw/sim0.ai/ch1");
    assert_eq!(v, get(&svc, "sim0.ai", "ch1"));
    assert!((v.as_f64().unwrap() - 1.25).abs() < 1e-3, "{v}");
    sub.latest("hwgw/status", WAIT, |p| p == "online");

    // A set topic writes the output, with the checks of `hwgw set`.
    publish(
        broker.port,
        "hwgw/sim0.ao/ch1/set",
        br#"{"value": 2.5}"#,
        None,
    );
    let r = sub.latest("hwgw/sim0.ao/ch1/set/result", WAIT, |_| true);
    assert_eq!(
        serde_json::from_str::<Value>(&r).unwrap(),
        json!({"ok": true})
    );
    let written_value = get(&svc, "sim0.ao", "ch1");
    assert!(
        (written_value.as_f64().unwrap() - 2.5).abs() < 1e-3,
        "{written_value}"
    );
    let value_of = |p: &str| serde_json::from_str::<Value>(p).unwrap()["value"].clone();
    sub.latest("hwgw/sim0.ao/ch1", WAIT, |p| value_of(p) == written_value);
    // A bare value, and a digital output looped back to its input.
    publish(broker.port, "hwgw/sim0.do/bit2/set", b"true", None);
    sub.latest("hwgw/sim0.di/bit2", WAIT, |p| value_of(p) == json!(true));
    assert_eq!(get(&svc, "sim0.do", "bit2"), json!(true));

    // Malformed writes: each refused with why, counted, nothing written.
    let written =
        |svc: &Service| svc.ok(json!({"cmd": "status"}))["cards"][0]["outputs"]["written"].clone();
    let before = written(&svc);
    let bad: &[(&str, &[u8], &str)] = &[
        ("hwgw/sim0.ao/ch1/set", b"{\"value\": ", "not JSON"),
        ("hwgw/sim0.ao/ch1/set", b"true", "analog"),
        (
            "hwgw/sim0.ao/ch1/set",
            b"\"3\"",
            "neither a number nor a boolean",
        ),
        (
            "hwgw/sim0.ao/ch1/set",
            b"{\"value\": 11.0}",
            "out of its range",
        ),
        (
            "hwgw/sim0.ao/ch1/set",
            b"{\"value\": 1, \"x\": 2}",
            "must be",
        ),
        ("hwgw/sim0.do/bit2/set", b"1", "write a boolean"),
        ("hwgw/sim0.ao/ch7/set", b"1.0", "no channel sim0.ao.ch7"),
        ("hwgw/sim0.ai/ch0/set", b"1.0", "is an input"),
    ];
    for (topic, payload, why) in bad {
        publish(broker.port, topic, payload, None);
        let result = format!("{topic}/result");
        sub.forget(&result);
        let r = sub.latest(&result, WAIT, |_| true);
        let r: Value = serde_json::from_str(&r).unwrap();
        assert_eq!(r["ok"], false, "{topic} {payload:?}: {r}");
        assert!(
            r["error"].as_str().unwrap().contains(why),
            "{topic}: {r} should say {why:?}"
        );
    }
    let c = counters(&svc);
    assert_eq!(c["commands_refused"], bad.len(), "{c}");
    assert_eq!(c["commands_accepted"], 2, "{c}");
    assert_eq!(written(&svc), before, "a refused write reached an output");
    assert_eq!(get(&svc, "sim0.ao", "ch1"), written_value);
    assert_eq!(get(&svc, "sim0.do", "bit2"), json!(true));
    assert_eq!(c["connected"], true, "{c}");
    assert!(c["published"].as_u64().unwrap() > 10, "{c}");
    // The counters in the metrics too.
    let scrape = testkit::http::get(([127, 0, 0, 1], metrics).into(), "/metrics");
    let line = format!(
        "hwgw_server_status{{server=\"server.mqtt\",field=\"commands_refused\"}} {}.0",
        bad.len()
    );
    let body = String::from_utf8_lossy(&scrape.body);
    assert!(
        body.lines().any(|l| l == line),
        "no {line:?} in the metrics:\n{}",
        body.lines()
            .filter(|l| l.contains("mqtt"))
            .collect::<Vec<_>>()
            .join("\n")
    );

    // At stop: the status says so, retained.
    drop(svc.terminate());
    sub.until("the status offline", WAIT, |t, p| {
        t == "hwgw/status" && p == "offline"
    });
}

#[test]
fn writes_are_refused_unless_allowed() {
    let broker = Broker::start();
    let mut sub = Sub::start(broker.port, &["hwgw/#"], None);
    let text = format!(
        "{CARD}\n[server.mqtt]\nbroker = \"127.0.0.1:{}\"\n[server.mqtt.json]\n",
        broker.port
    );
    let svc = Service::run_text(HWGW, "mqtt-readonly", &text).unwrap();
    sub.until("the status", WAIT, |t, p| {
        t == "hwgw/status" && p == "online"
    });
    let before = get(&svc, "sim0.ao", "ch1");
    publish(broker.port, "hwgw/sim0.ao/ch1/set", b"2.0", None);
    let (_, r) = sub.until("the result", WAIT, |t, _| {
        t == "hwgw/sim0.ao/ch1/set/result"
    });
    assert!(r.contains("not allowed"), "{r}");
    assert_eq!(get(&svc, "sim0.ao", "ch1"), before);
    assert_eq!(counters(&svc)["commands_refused"], 1);
}

#[test]
fn tls_with_client_certificates() {
    let certs = Certs::make();
    let broker = Broker::start_tls(certs.broker());
    let client = certs.client("client");
    let mut sub = Sub::start(broker.port, &["#"], Some(&client));
    let deployment = |name: &str| {
        format!(
            "{CARD}\n[server.mqtt]\nbroker = \"127.0.0.1:{}\"\nclient_id = \"hwgw-{name}\"\n\
             [server.mqtt.tls]\nca = \"{}\"\ncert = \"{}\"\nkey = \"{}\"\n[server.mqtt.json]\nprefix = \"{name}\"\n",
            broker.port,
            certs.path("ca.pem").display(),
            certs.path(&format!("{name}.pem")).display(),
            certs.path(&format!("{name}.key")).display(),
        )
    };
    let svc = Service::run_text(HWGW, "mqtt-tls", &deployment("client")).unwrap();
    assert_eq!(
        svc.server_status("server.mqtt")["bus"],
        format!("mqtts://127.0.0.1:{}", broker.port)
    );
    wait_until("connected over TLS", || counters(&svc)["connected"] == true);
    let v = serde_json::from_str::<Value>(
        &sub.until("a value over TLS", WAIT, |t, _| t == "client/sim0.ai/ch0")
            .1,
    )
    .unwrap();
    assert_eq!(v["value"], get(&svc, "sim0.ai", "ch0"));

    // A certificate of another CA: the broker refuses the handshake; hwgw says why and
    // tries again, publishing nothing.
    let stranger = Service::run_text(HWGW, "mqtt-tls-stranger", &deployment("stranger")).unwrap();
    wait_until("the refusal in status", || {
        let c = counters(&stranger);
        c["connected"] == false && c["last_error"].as_str().is_some_and(|e| !e.is_empty())
    });
    let c = counters(&stranger);
    eprintln!("refused: {}", c["last_error"]);
    assert_eq!(c["published"], 0, "{c}");
    let end = std::time::Instant::now() + Duration::from_secs(2);
    while let Some((t, _)) = sub.next(end.saturating_duration_since(std::time::Instant::now())) {
        assert!(
            !t.starts_with("stranger/"),
            "{t} published with a refused certificate"
        );
    }
    drop(stranger.terminate());
    assert_eq!(counters(&svc)["connected"], true);
}

#[test]
fn mqtt_5_carries_the_same() {
    let broker = Broker::start();
    let mut sub = Sub::start(broker.port, &["v5/#"], None);
    let text = format!(
        "{CARD}\n[server.mqtt]\nbroker = \"127.0.0.1:{}\"\nversion = \"5\"\nallow_writes = true\n\
         [server.mqtt.json]\nprefix = \"v5\"\n",
        broker.port
    );
    let svc = Service::run_text(HWGW, "mqtt-v5", &text).unwrap();
    assert_eq!(
        next_value(&mut sub, "v5/sim0.ai/ch0"),
        get(&svc, "sim0.ai", "ch0")
    );
    publish(broker.port, "v5/sim0.do/bit3/set", b"true", None);
    let r = sub.latest("v5/sim0.do/bit3/set/result", WAIT, |_| true);
    assert_eq!(
        serde_json::from_str::<Value>(&r).unwrap(),
        json!({"ok": true})
    );
    assert_eq!(get(&svc, "sim0.do", "bit3"), json!(true));
    assert!(
        broker.log().contains("as hwgw (p5"),
        "not MQTT 5:\n{}",
        broker.log()
    );
}

#[test]
fn a_retained_set_is_not_carried_out() {
    // A retained set message waits on the broker: it would be handed to every session
    // hwgw makes, and the old value written again at each reconnection.
    let broker = Broker::start();
    testkit::mosquitto::publish_retained(broker.port, "hwgw/sim0.ao/ch1/set", b"-3.0", None);
    let mut sub = Sub::start(broker.port, &["hwgw/#"], None);
    let text = format!(
        "{CARD}\n[server.mqtt]\nbroker = \"127.0.0.1:{}\"\nallow_writes = true\n[server.mqtt.json]\n",
        broker.port
    );
    let svc = Service::run_text(HWGW, "mqtt-retained", &text).unwrap();
    let r = sub.latest("hwgw/sim0.ao/ch1/set/result", WAIT, |_| true);
    assert!(r.contains("\"ok\":false") && r.contains("retained"), "{r}");
    let v = get(&svc, "sim0.ao", "ch1").as_f64().unwrap();
    assert!(v.abs() < 1e-3, "written: {v}");
    assert_eq!(counters(&svc)["commands_refused"], 1);
}

#[test]
fn user_and_password_from_a_file() {
    let broker = Broker::start_with_users(&[("hwgw", "a secret of the plant")]);
    let mut sub = Sub::start(broker.port, &["#"], None);
    let run = |name: &str, password: &str| {
        let dir = testkit::TempDir::new(&format!("mqtt-password-{name}"));
        std::fs::write(dir.path().join("mqtt.pass"), format!("{password}\n")).unwrap();
        let text = format!(
            "{CARD}\n[server.mqtt]\nbroker = \"127.0.0.1:{}\"\nclient_id = \"hwgw-{name}\"\n\
             username = \"hwgw\"\npassword_file = \"{}\"\n[server.mqtt.json]\nprefix = \"{name}\"\n",
            broker.port,
            dir.path().join("mqtt.pass").display()
        );
        (
            Service::run_text(HWGW, &format!("mqtt-user-{name}"), &text).unwrap(),
            dir,
        )
    };
    let (good, _d1) = run("good", "a secret of the plant");
    sub.latest("good/status", WAIT, |p| p == "online");
    assert_eq!(counters(&good)["connected"], true);
    // A wrong password: refused by the broker, said in status, retried.
    let (bad, _d2) = run("bad", "not the secret");
    wait_until("the refusal in status", || {
        counters(&bad)["last_error"]
            .as_str()
            .is_some_and(|e| e.contains("refused"))
    });
    let c = counters(&bad);
    assert_eq!(
        (&c["connected"], &c["published"]),
        (&json!(false), &json!(0)),
        "{c}"
    );
    eprintln!("refused: {}", c["last_error"]);
}
