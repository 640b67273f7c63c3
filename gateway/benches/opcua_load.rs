//! What `[server.opcua]` costs and carries (`cargo bench -p hwgw --bench opcua_load`): the
//! real binary runs a simulated card of 10 000 analog inputs, each new noise every
//! 100 ms (10 000 channels changing at 10 Hz), through four runs of
//! `OPCUA_BENCH_SECONDS` each (default 20):
//!
//! 1. the reference: the same deployment without `[server.opcua]`;
//! 2. `[server.opcua]` with its default sample period (10 ms), one client here
//!    (async-opcua's client, a process of its own would add nothing but noise) with one
//!    subscription of 10 000 monitored items, one per channel, sampled every 100 ms,
//!    published every 100 ms, each item's queue one value, every notification counted;
//! 3. the same with queues of 10 values: a queue of one keeps only the newest value of
//!    each publishing interval (OPC UA's rule), and as the card's 100 ms and the
//!    subscription's drift apart, two changes of a channel often fall in one interval;
//! 4. queues of 10 and `sample_period_ms = 100`: channels read as often as they change.
//!
//! For each: hwgw's CPU (user and system, all its threads, as a % of one core) and
//! resident memory at the end, this process's CPU (the client), the notifications a
//! second the client got, and the share of the channels' changes that makes
//! (10 000 channels × 10 changes a second).

#![allow(
    clippy::unwrap_used,
    reason = "bench code: a failed unwrap is a failed run"
)]

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use testkit::Service;
use testkit::bench::proc_usage;
use ua_client::client::{ClientBuilder, DataChangeCallback, IdentityToken};
use ua_client::types::{
    MessageSecurityMode, MonitoredItemCreateRequest, NodeId, TimestampsToReturn, UserTokenPolicy,
};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const CHANNELS: u32 = 10_000;

fn card() -> String {
    testkit::bench::noise_card(CHANNELS)
}

/// One run's figures.
struct Figures {
    cpu_percent: f64,
    rss_mib: f64,
    client_cpu_percent: f64,
    notifications_per_s: f64,
}

fn measure(svc: &Service, seconds: f64, count: &AtomicU64) -> Figures {
    let (pid, me) = (svc.pid().unwrap(), std::process::id());
    let usage = |p: u32| proc_usage(p).unwrap();
    let (a, ma, na, t0) = (
        usage(pid),
        usage(me),
        count.load(Ordering::Relaxed),
        Instant::now(),
    );
    std::thread::sleep(Duration::from_secs_f64(seconds));
    let (b, mb, nb) = (usage(pid), usage(me), count.load(Ordering::Relaxed));
    let s = t0.elapsed().as_secs_f64();
    Figures {
        cpu_percent: b.cpu_percent_since(a, s),
        rss_mib: b.rss_kib as f64 / 1024.0,
        client_cpu_percent: mb.cpu_percent_since(ma, s),
        notifications_per_s: (nb - na) as f64 / s,
    }
}

fn print(name: &str, f: &Figures, reference: Option<&Figures>) {
    let ratio = reference.map_or(String::new(), |r| {
        format!(
            " ({:.2}x CPU, {:.2}x RSS of the reference)",
            f.cpu_percent / r.cpu_percent,
            f.rss_mib / r.rss_mib
        )
    });
    let share = f.notifications_per_s / (f64::from(CHANNELS) * 10.0) * 100.0;
    println!(
        "{name}: hwgw {:.1}% CPU, {:.1} MiB RSS{ratio}; the client {:.1}% CPU; \
         {:.0} notifications/s ({share:.1}% of the channels' changes)",
        f.cpu_percent, f.rss_mib, f.client_cpu_percent, f.notifications_per_s,
    );
}

/// A client on `url` with one subscription of a monitored item per channel, sampled and
/// published every 100 ms, each notification counted in `count`; runs until dropped.
fn client(
    url: String,
    count: Arc<AtomicU64>,
    pki: std::path::PathBuf,
    queue: u32,
) -> tokio::runtime::Runtime {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async move {
        let mut client = ClientBuilder::new()
            .application_name("hwgw bench")
            .application_uri("urn:hwgw:bench")
            .pki_dir(pki)
            .create_sample_keypair(false)
            .trust_server_certs(true)
            .session_retry_limit(3)
            .max_message_size(64 << 20)
            .max_chunk_count(1024)
            .max_array_length(100_000)
            .client()
            .unwrap();
        let endpoint = (
            url.as_str(),
            "None",
            MessageSecurityMode::None,
            UserTokenPolicy::anonymous(),
        );
        let (session, event_loop) = client
            .connect_to_matching_endpoint(endpoint, IdentityToken::Anonymous)
            .await
            .unwrap();
        tokio::spawn(event_loop.run());
        session.wait_for_connection().await;
        let ns = session.get_namespace_index("urn:hwgw:io").await.unwrap();
        let counted = count.clone();
        let sub = session
            .create_subscription(
                Duration::from_millis(100),
                100,
                10,
                0,
                0,
                true,
                DataChangeCallback::new(move |_, _| {
                    counted.fetch_add(1, Ordering::Relaxed);
                }),
            )
            .await
            .unwrap();
        let ids: Vec<u32> = (0..CHANNELS).collect();
        for chunk in ids.chunks(1000) {
            let items: Vec<MonitoredItemCreateRequest> = chunk
                .iter()
                .map(|c| {
                    let mut r: MonitoredItemCreateRequest =
                        NodeId::new(ns, format!("big.ai.ch{c}")).into();
                    r.requested_parameters.sampling_interval = 100.0;
                    r.requested_parameters.queue_size = queue;
                    r
                })
                .collect();
            let made = session
                .create_monitored_items(sub, TimestampsToReturn::Both, items)
                .await
                .unwrap();
            let bad = made
                .iter()
                .filter(|m| !m.result.status_code.is_good())
                .count();
            assert_eq!(bad, 0, "monitored items refused");
        }
        // The session stays with the runtime.
        std::mem::forget(session);
    });
    rt
}

fn main() {
    let seconds: f64 = std::env::var("OPCUA_BENCH_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20.0);
    tracing_subscriber::fmt().with_env_filter("warn").init();
    let warm = Duration::from_secs(3);
    let none = AtomicU64::new(0);

    // 1. The reference: no OPC UA.
    let svc = Service::run_text(HWGW, "opcua-bench-ref", &card()).unwrap();
    std::thread::sleep(warm);
    let reference = measure(&svc, seconds, &none);
    drop(svc.terminate());
    print("reference (no [server.opcua])", &reference, None);

    // 2.-4. A client of 10 000 monitored items at 100 ms.
    for (sample, queue) in [(10, 1), (10, 10), (100, 10)] {
        let port = testkit::free_port();
        let text = format!(
            "{}\n[server.opcua]\nlisten = \"127.0.0.1:{port}\"\npki_dir = \"pki\"\nsample_period_ms = {sample}\n",
            card()
        );
        let svc = Service::run_text(HWGW, &format!("opcua-bench-{sample}-{queue}"), &text).unwrap();
        let count = Arc::new(AtomicU64::new(0));
        let rt = client(
            format!("opc.tcp://127.0.0.1:{port}/"),
            count.clone(),
            svc.dir().join("client-pki"),
            queue,
        );
        testkit::wait_until("the first notifications", || {
            count.load(Ordering::Relaxed) >= u64::from(CHANNELS)
        });
        std::thread::sleep(warm);
        let f = measure(&svc, seconds, &count);
        rt.shutdown_background();
        let counters = svc.server_status("server.opcua")["counters"].clone();
        drop(svc.terminate());
        let name = format!("[server.opcua] sample period {sample} ms, items' queue {queue}");
        print(&name, &f, Some(&reference));
        println!("  its counters: {counters}");
    }
}
