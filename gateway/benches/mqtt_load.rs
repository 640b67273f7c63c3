//! What `[server.mqtt]` costs and carries (`cargo bench -p hwgw --bench mqtt_load`): the
//! real binary runs a simulated card of 10 000 analog inputs, each new noise every
//! 100 ms (10 000 metrics changing at 10 Hz), against a real Mosquitto on 127.0.0.1,
//! through three runs of `MQTT_BENCH_SECONDS` each (default 20):
//!
//! 1. the reference: the same deployment without `[server.mqtt]`;
//! 2. Sparkplug B: the card one Sparkplug device, read every 100 ms, deadband 0; a
//!    receiver here (rumqttc, every message decoded with prost) counts what it gets.
//!    The tests' independent host application (paho-mqtt and pure-Python protobuf) was
//!    measured too: it decodes about 10 000 metrics a second, a tenth of this stream, and
//!    the broker drops the rest for it — it is a check of contents, not of rate;
//! 3. JSON topics: a message per changed channel, counted by `mosquitto_sub`.
//!
//! For each: hwgw's CPU (user and system, all its threads, as a % of one core) and
//! resident memory at the end, Mosquitto's CPU, the receiver's (this process for
//! Sparkplug, `mosquitto_sub` for JSON), what the receiver got per second, and what hwgw
//! counted as published and dropped.

#![allow(
    clippy::unwrap_used,
    reason = "bench code: a failed unwrap is a failed run"
)]

use serde_json::{Value, json};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use testkit::Service;
use testkit::bench::proc_usage;
use testkit::mosquitto::{Broker, Sub};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const CHANNELS: u32 = 10_000;

fn card() -> String {
    testkit::bench::noise_card(CHANNELS)
}

/// One run's figures.
struct Figures {
    cpu_percent: f64,
    rss_mib: f64,
    broker_cpu_percent: f64,
    receiver_cpu_percent: f64,
    received_per_s: f64,
    metrics_per_s: f64,
    bytes_per_s: f64,
    published: Value,
    dropped: Value,
}

/// Measures `svc` and the broker for `seconds`, `count` telling the receiver's totals
/// (messages, metrics, bytes) at the time it is asked.
fn measure(
    svc: &Service,
    (broker, receiver): (u32, u32),
    seconds: f64,
    mut count: impl FnMut() -> (u64, u64, u64),
) -> Figures {
    let pid = svc.pid().unwrap();
    let usage = |p: u32| proc_usage(p).unwrap();
    let (a, ba, ra, ca, t0) = (
        usage(pid),
        usage(broker),
        usage(receiver),
        count(),
        Instant::now(),
    );
    std::thread::sleep(Duration::from_secs_f64(seconds));
    let (b, bb, rb, cb) = (usage(pid), usage(broker), usage(receiver), count());
    let s = t0.elapsed().as_secs_f64();
    let status = svc.ok(json!({"cmd": "status"}));
    let mqtt = status["servers"]
        .as_array()
        .and_then(|l| l.iter().find(|v| v["name"] == "server.mqtt"))
        .map(|v| v["counters"].clone())
        .unwrap_or_default();
    Figures {
        cpu_percent: b.cpu_percent_since(a, s),
        rss_mib: b.rss_kib as f64 / 1024.0,
        broker_cpu_percent: bb.cpu_percent_since(ba, s),
        receiver_cpu_percent: rb.cpu_percent_since(ra, s),
        received_per_s: (cb.0 - ca.0) as f64 / s,
        metrics_per_s: (cb.1 - ca.1) as f64 / s,
        bytes_per_s: (cb.2 - ca.2) as f64 / s,
        published: mqtt["published"].clone(),
        dropped: mqtt["dropped"].clone(),
    }
}

/// A Sparkplug receiver on the broker at `port`: every DDATA decoded, its (messages,
/// metrics, bytes) added to `counted`; its thread ends when its client disconnects.
fn receiver(
    port: u16,
    counted: Arc<Mutex<(u64, u64, u64)>>,
) -> (std::thread::JoinHandle<()>, rumqttc::Client) {
    use prost::Message;
    let mut o = rumqttc::MqttOptions::new("bench-receiver", "127.0.0.1", port);
    o.set_max_packet_size(64 << 20, 1 << 20);
    let (client, mut connection) = rumqttc::Client::new(o, 64);
    client
        .subscribe("spBv1.0/bench/DDATA/#", rumqttc::QoS::AtMostOnce)
        .unwrap();
    let thread = std::thread::spawn(move || {
        for event in connection.iter() {
            match event {
                Ok(rumqttc::Event::Incoming(rumqttc::Packet::Publish(p))) => {
                    let payload = mqtt::pb::Payload::decode(p.payload.as_ref()).unwrap();
                    let mut c = counted.lock().unwrap();
                    c.0 += 1;
                    c.1 += payload.metrics.len() as u64;
                    c.2 += p.payload.len() as u64;
                }
                Ok(rumqttc::Event::Outgoing(rumqttc::Outgoing::Disconnect)) | Err(_) => break,
                Ok(_) => {}
            }
        }
    });
    (thread, client)
}

fn print(name: &str, f: &Figures, reference: Option<&Figures>) {
    let ratio = reference.map_or(String::new(), |r| {
        format!(
            " ({:.2}x CPU, {:.2}x RSS of the reference)",
            f.cpu_percent / r.cpu_percent,
            f.rss_mib / r.rss_mib
        )
    });
    println!(
        "{name}: hwgw {:.1}% CPU, {:.1} MiB RSS{ratio}; mosquitto {:.1}% CPU; the receiver {:.1}% CPU; received {:.0} messages/s, \
         {:.0} metrics/s, {:.2} MB/s; hwgw published {} dropped {}",
        f.cpu_percent,
        f.rss_mib,
        f.broker_cpu_percent,
        f.receiver_cpu_percent,
        f.received_per_s,
        f.metrics_per_s,
        f.bytes_per_s / 1e6,
        f.published,
        f.dropped
    );
}

fn main() {
    let seconds: f64 = std::env::var("MQTT_BENCH_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20.0);
    let broker = Broker::start();
    let broker_pid = broker.pid();
    let warm = Duration::from_secs(3);

    // 1. The reference: no MQTT.
    let svc = Service::run_text(HWGW, "mqtt-bench-ref", &card()).unwrap();
    std::thread::sleep(warm);
    let me = std::process::id();
    let reference = measure(&svc, (broker_pid, me), seconds, || (0, 0, 0));
    drop(svc.terminate());
    print("reference (no [server.mqtt])", &reference, None);

    // 2. Sparkplug B to a receiver decoding every message.
    let counted = Arc::new(Mutex::new((0u64, 0u64, 0u64)));
    let receiving = receiver(broker.port, counted.clone());
    let text = format!(
        "{}\n[server.mqtt]\nbroker = \"127.0.0.1:{}\"\nsample_period_ms = 100\n[server.mqtt.sparkplug]\ngroup = \"bench\"\nnode = \"hwgw\"\n",
        card(),
        broker.port
    );
    let svc = Service::run_text(HWGW, "mqtt-bench-spb", &text).unwrap();
    testkit::wait_until("the first DDATA", || counted.lock().unwrap().0 > 2);
    std::thread::sleep(warm);
    let spb = measure(&svc, (broker_pid, me), seconds, || *counted.lock().unwrap());
    drop(svc.terminate());
    receiving.1.disconnect().unwrap();
    receiving.0.join().unwrap();
    print("Sparkplug B", &spb, Some(&reference));

    // 3. JSON topics to mosquitto_sub.
    let mut sub = Sub::start(broker.port, &["big/#"], None);
    let sub_pid = sub.pid();
    let text = format!(
        "{}\n[server.mqtt]\nbroker = \"127.0.0.1:{}\"\nsample_period_ms = 100\n[server.mqtt.json]\nprefix = \"big\"\n",
        card(),
        broker.port
    );
    let svc = Service::run_text(HWGW, "mqtt-bench-json", &text).unwrap();
    sub.until("the first value", Duration::from_secs(30), |t, _| {
        t.starts_with("big/")
    });
    std::thread::sleep(warm);
    let (mut n, mut bytes) = (0u64, 0u64);
    let json_figures = {
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let counted = std::sync::Arc::new(std::sync::Mutex::new((0u64, 0u64)));
        let (s2, c2) = (stop.clone(), counted.clone());
        let reader = std::thread::spawn(move || {
            while !s2.load(std::sync::atomic::Ordering::Relaxed) {
                if let Some((t, p)) = sub.next(Duration::from_millis(200)) {
                    let mut c = c2.lock().unwrap();
                    c.0 += 1;
                    c.1 += (t.len() + p.len()) as u64;
                }
            }
        });
        let f = measure(&svc, (broker_pid, sub_pid), seconds, || {
            let c = *counted.lock().unwrap();
            (n, bytes) = c;
            (n, n, bytes)
        });
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        reader.join().unwrap();
        f
    };
    drop(svc.terminate());
    print("JSON topics", &json_figures, Some(&reference));
}
