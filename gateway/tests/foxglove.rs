//! `[server.foxglove]` with the real binary, against a client written here from the
//! Foxglove WebSocket protocol's published specification (`foxglove.websocket.v1`: JSON
//! operations as text, message data as binary frames): it subscribes to two channels and
//! receives the very values `hwgw get` reads; a client that does not read loses samples,
//! counted for it, while another goes on receiving; a client publishes to an input port
//! when the deployment allows it and is refused when not; floods, oversized messages and
//! handshakes without the subprotocol are bounded and counted.
#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::collections::HashMap;
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use testkit::{Service, wait_until};
use tungstenite::client::IntoClientRequest;
use tungstenite::{Message, WebSocket};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const DEMO: &str = include_str!("../../config/demo.toml");

/// A Foxglove client.
struct Client {
    ws: WebSocket<TcpStream>,
    /// Channel ids by topic, with their schema names.
    channels: HashMap<String, (u32, String)>,
    server_info: Value,
}

impl Client {
    /// Connects to `addr` at `path` asking for `subprotocol`, with `headers`; the
    /// handshake's error when refused.
    fn try_connect(
        addr: SocketAddr,
        path: &str,
        subprotocol: &str,
        headers: &[(&'static str, &str)],
    ) -> Result<Client, tungstenite::Error> {
        let tcp = TcpStream::connect(addr).unwrap();
        tcp.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
        let mut req = format!("ws://{addr}{path}").into_client_request().unwrap();
        req.headers_mut()
            .insert("sec-websocket-protocol", subprotocol.parse().unwrap());
        for (k, v) in headers {
            req.headers_mut().insert(*k, v.parse().unwrap());
        }
        let (ws, resp) = tungstenite::client::client(req, tcp).map_err(|e| match e {
            tungstenite::HandshakeError::Failure(e) => e,
            tungstenite::HandshakeError::Interrupted(_) => panic!("handshake interrupted"),
        })?;
        assert_eq!(
            resp.headers().get("sec-websocket-protocol").unwrap(),
            subprotocol
        );
        let mut c = Client {
            ws,
            channels: HashMap::new(),
            server_info: Value::Null,
        };
        c.server_info = c.next_op("serverInfo");
        Ok(c)
    }

    fn connect(addr: SocketAddr) -> Client {
        Client::try_connect(addr, "/", "foxglove.websocket.v1", &[]).unwrap()
    }

    /// The next text operation `op`, taking in advertisements on the way.
    fn next_op(&mut self, op: &str) -> Value {
        loop {
            match self.ws.read().unwrap() {
                Message::Text(t) => {
                    let v: Value = serde_json::from_str(t.as_str()).unwrap();
                    self.take(&v);
                    if v["op"] == op {
                        return v;
                    }
                }
                Message::Binary(_) | Message::Ping(_) | Message::Pong(_) => {}
                m => panic!("unexpected {m:?}"),
            }
        }
    }

    fn take(&mut self, v: &Value) {
        if v["op"] == "advertise" {
            for c in v["channels"].as_array().unwrap() {
                let id = c["id"].as_u64().unwrap() as u32;
                let schema = c["schemaName"].as_str().unwrap().to_string();
                self.channels
                    .insert(c["topic"].as_str().unwrap().to_string(), (id, schema));
            }
        }
    }

    /// Waits for `topic` to be advertised; its channel id.
    fn channel(&mut self, topic: &str) -> u32 {
        while !self.channels.contains_key(topic) {
            self.next_op("advertise");
        }
        self.channels[topic].0
    }

    fn send_json(&mut self, v: Value) {
        self.ws.send(Message::text(v.to_string())).unwrap();
    }

    /// Message data until `until`: (subscription, time ns, payload) each.
    fn data_until(&mut self, until: Instant) -> Vec<(u32, u64, Value)> {
        let mut out = Vec::new();
        while Instant::now() < until {
            match self.ws.read().unwrap() {
                Message::Binary(b) => {
                    assert_eq!(b[0], 1, "message data opcode");
                    let sub = u32::from_le_bytes(b[1..5].try_into().unwrap());
                    let t = u64::from_le_bytes(b[5..13].try_into().unwrap());
                    out.push((sub, t, serde_json::from_slice(&b[13..]).unwrap()));
                }
                Message::Text(t) => {
                    let v: Value = serde_json::from_str(t.as_str()).unwrap();
                    self.take(&v);
                }
                _ => {}
            }
        }
        out
    }
}

fn counters(svc: &Service) -> Value {
    svc.server_status("server.foxglove")["counters"].clone()
}

fn run(tag: &str, section: &str) -> (Service, SocketAddr) {
    let text = format!("{DEMO}\n[server.foxglove]\nlisten = \"127.0.0.1:0\"\n{section}\n");
    let svc = Service::run_text(HWGW, tag, &text).unwrap();
    let addr = svc.server_address("server.foxglove");
    (svc, addr)
}

#[test]
fn two_channels_carry_what_hwgw_get_reads() {
    let (svc, addr) = run("fox-values", "ports = [\"sim0.ai.ch0\", \"sim0.ai.ch3\"]");
    let mut c = Client::connect(addr);
    assert_eq!(c.server_info["supportedEncodings"], json!(["json"]));
    assert_eq!(c.server_info["capabilities"], json!([]));
    let ch0 = c.channel("/sim0/ai/ch0");
    let ch3 = c.channel("/sim0/ai/ch3");
    assert_eq!(c.channels["/sim0/ai/ch0"].1, "hwgw.sample.f64");
    c.send_json(json!({"op": "subscribe", "subscriptions": [
        {"id": 10, "channelId": ch0}, {"id": 13, "channelId": ch3}]}));
    let mut data = c.data_until(Instant::now() + Duration::from_secs(1));
    let get = |port: &str| svc.ok(json!({"cmd": "get", "component": "sim0.ai", "port": port}));
    let (got0, got3) = (get("ch0"), get("ch3"));
    data.extend(c.data_until(Instant::now() + Duration::from_millis(500)));
    let values = |sub: u32| -> Vec<Value> {
        data.iter()
            .filter(|d| d.0 == sub)
            .map(|d| d.2["value"].clone())
            .collect()
    };
    let (v0, v3) = (values(10), values(13));
    assert!(
        v0.len() > 20 && v3.len() > 20,
        "{} and {} samples",
        v0.len(),
        v3.len()
    );
    // Every value written came (the stream is the recorder's): the one get read among them,
    // bit for bit.
    assert!(v0.contains(&got0), "hwgw get read {got0}, not among {v0:?}");
    assert!(v3.contains(&got3), "hwgw get read {got3}, not among {v3:?}");
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64;
    for (_, t, _) in &data {
        assert!(
            t.abs_diff(now) < 60_000_000_000,
            "log time {t} against now {now}"
        );
    }
    let times: Vec<u64> = data.iter().filter(|d| d.0 == 10).map(|d| d.1).collect();
    assert!(times.windows(2).all(|w| w[0] < w[1]), "times rise");
    // Stopped with the client connected and subscribed: the gateway stops as always.
    let stopped = svc.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
}

#[test]
fn a_client_that_does_not_read_loses_samples_counted_and_slows_nobody() {
    let fast = DEMO
        .replace("period_ms = 10 ", "period_ms = 1 ")
        .replace("sample_period_ms = 20 ", "sample_period_ms = 1 ");
    let text = format!(
        "{fast}\n[server.foxglove]\nlisten = \"127.0.0.1:0\"\ndevices = true\nsteps = true\nqueue = 2\n"
    );
    let svc = Service::run_text(HWGW, "fox-slow", &text).unwrap();
    let addr = svc.server_address("server.foxglove");
    let subscribe_all = |c: &mut Client| {
        c.channel("/sim0/ai/ch0");
        let subs: Vec<Value> = c
            .channels
            .values()
            .map(|(id, _)| json!({"id": id, "channelId": id}))
            .collect();
        c.send_json(json!({"op": "subscribe", "subscriptions": subs}));
    };
    let mut slow = Client::connect(addr);
    subscribe_all(&mut slow);
    let mut reader = Client::connect(addr);
    let (ch0, steps) = (
        reader.channel("/sim0/ai/ch0"),
        reader.channel("/activity/sim0"),
    );
    reader.send_json(json!({"op": "subscribe", "subscriptions": [
        {"id": 1, "channelId": ch0}, {"id": 2, "channelId": steps}]}));
    // The slow one never reads again; the other reads on.
    let mut got = 0;
    let end = Instant::now() + Duration::from_secs(60);
    loop {
        got += reader
            .data_until(Instant::now() + Duration::from_millis(200))
            .len();
        let c = counters(&svc);
        let dropped: Vec<u64> = c["clients"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x["dropped"].as_u64().unwrap())
            .collect();
        if dropped.iter().any(|d| *d > 0) {
            assert_eq!(
                dropped.iter().filter(|d| **d > 0).count(),
                1,
                "only the slow client loses: {c}"
            );
            break;
        }
        assert!(Instant::now() < end, "nothing lost yet: {c}");
    }
    let before = got;
    got += reader
        .data_until(Instant::now() + Duration::from_secs(1))
        .len();
    assert!(
        got > before + 100,
        "the reading client still receives ({before} → {got})"
    );
    drop(slow);
}

#[test]
fn a_client_publishes_to_an_input_port_only_when_allowed() {
    let ports = "ports = [\"sim0.ai.ch0\"]";
    let token = "a-token-for-the-foxglove-clients";
    let writes = format!("allow_writes = true\ninputs = [\"sim0.ao.ch1\"]\ntoken = \"{token}\"");
    let (svc, addr) = run("fox-write", &format!("{ports}\n{writes}"));
    // Without the token: no publishing.
    let mut c = Client::connect(addr);
    assert_eq!(c.server_info["capabilities"], json!([]));
    c.send_json(json!({"op": "advertise", "channels": [
        {"id": 7, "topic": "/sim0/ao/ch1", "encoding": "json", "schemaName": "hwgw.sample.f64"}]}));
    let status = c.next_op("status");
    assert!(
        status["message"].as_str().unwrap().contains("token"),
        "{status}"
    );
    let path = format!("/?token={token}");
    let mut c = Client::try_connect(addr, &path, "foxglove.websocket.v1", &[]).unwrap();
    assert_eq!(c.server_info["capabilities"], json!(["clientPublish"]));
    c.send_json(json!({"op": "advertise", "channels": [
        {"id": 7, "topic": "/sim0/ao/ch1", "encoding": "json", "schemaName": "hwgw.sample.f64"}]}));
    let publish = |c: &mut Client, channel: u32, payload: &[u8]| {
        let mut frame = vec![1u8];
        frame.extend(channel.to_le_bytes());
        frame.extend(payload);
        c.ws.send(Message::binary(frame)).unwrap();
    };
    publish(&mut c, 7, br#"{"value": 2.25}"#);
    let read = || svc.ok(json!({"cmd": "get", "component": "sim0.ao", "port": "ch1"}));
    wait_until("the published value reached the output", || {
        (read().as_f64().unwrap() - 2.25).abs() < 1e-3
    });
    wait_until("the write counted", || counters(&svc)["writes"] == 1);
    // A streamed output is no input: the client is told, nothing is written.
    c.send_json(json!({"op": "advertise", "channels": [
        {"id": 8, "topic": "/sim0/ai/ch0", "encoding": "json", "schemaName": "hwgw.sample.f64"}]}));
    let status = c.next_op("status");
    assert_eq!(status["level"], 2, "{status}");
    // A value hwgw set refuses is refused the same way, and the client told.
    publish(&mut c, 7, br#"{"value": "high"}"#);
    let status = c.next_op("status");
    assert!(
        status["message"].as_str().unwrap().contains("/sim0/ao/ch1"),
        "{status}"
    );
    assert!(counters(&svc)["writes_refused"].as_u64().unwrap() >= 1);
    assert_eq!(counters(&svc)["writes"], 1);

    let (svc, addr) = run("fox-readonly", ports);
    let mut c = Client::connect(addr);
    assert_eq!(c.server_info["capabilities"], json!([]));
    let before = read_of(&svc);
    c.send_json(json!({"op": "advertise", "channels": [
        {"id": 7, "topic": "/sim0/ao/ch1", "encoding": "json", "schemaName": "hwgw.sample.f64"}]}));
    let status = c.next_op("status");
    assert!(
        status["message"].as_str().unwrap().contains("allow_writes"),
        "{status}"
    );
    publish(&mut c, 7, br#"{"value": 2.25}"#);
    c.next_op("status");
    assert_eq!(read_of(&svc), before);
}

fn read_of(svc: &Service) -> Value {
    svc.ok(json!({"cmd": "get", "component": "sim0.ao", "port": "ch1"}))
}

#[test]
fn floods_big_messages_and_strangers_are_bounded_and_counted() {
    let section = "ports = [\"sim0.ai.ch0\"]\norigins = [\"https://app.foxglove.dev\"]";
    let (svc, addr) = run("fox-flood", section);
    let listed = [("origin", "https://app.foxglove.dev")];
    assert!(Client::try_connect(addr, "/", "foxglove.websocket.v1", &listed).is_ok());
    // Not a Foxglove client; a page of another site; a name that is not this host's.
    let fox = "foxglove.websocket.v1";
    assert!(Client::try_connect(addr, "/", "chat", &[]).is_err());
    let evil = [("origin", "http://evil.example")];
    assert!(Client::try_connect(addr, "/", fox, &evil).is_err());
    let rebound = [("host", "evil.example:8765")];
    assert!(Client::try_connect(addr, "/", fox, &rebound).is_err());
    wait_until("the strangers counted", || {
        counters(&svc)["handshakes_refused"].as_u64().unwrap() >= 3
    });
    // Ten thousand messages that are not the protocol: closed after a hundred.
    let mut c = Client::connect(addr);
    let mut closed = false;
    for i in 0..10_000 {
        if c.ws.send(Message::text(format!("garbage {i}"))).is_err() {
            closed = true;
            break;
        }
    }
    if !closed {
        let end = Instant::now() + Duration::from_secs(30);
        while Instant::now() < end {
            match c.ws.read() {
                Ok(_) => {}
                Err(_) => {
                    closed = true;
                    break;
                }
            }
        }
    }
    assert!(closed, "the flooding client was not closed");
    // One message of a megabyte: closed before it is whole.
    let mut big = Client::connect(addr);
    let _ = big.ws.send(Message::text("x".repeat(1 << 20)));
    let end = Instant::now() + Duration::from_secs(30);
    while Instant::now() < end && big.ws.read().is_ok() {}
    // Each closed: for its garbage, or — when it did not read the errors it was sent —
    // for being too far behind to be told.
    wait_until("both counted", || {
        let c = counters(&svc);
        let closed = c["closed_misbehaving"].as_u64().unwrap() + c["closed_slow"].as_u64().unwrap();
        closed >= 2 && c["bad_messages"].as_u64().unwrap() >= 30
    });
    // And the server goes on.
    let mut ok = Client::connect(addr);
    let ch = ok.channel("/sim0/ai/ch0");
    ok.send_json(json!({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": ch}]}));
    assert!(
        !ok.data_until(Instant::now() + Duration::from_secs(1))
            .is_empty()
    );
}
