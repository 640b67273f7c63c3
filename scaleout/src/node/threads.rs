//! The node's threads: publishing, serving other gateways' writes and control requests,
//! sending this gateway's writes, and asking for the catalogues of the gateways imported
//! from. Each waits in slices of at most [`SLICE`], so a stop is never held up longer
//! (the gateway's outputs go to their safe values right after the node stops).

use super::{ControlHandler, Counters, lock};
use crate::config::Times;
use crate::local;
use crate::outbox::Outbox;
use crate::ports::Export;
use crate::remote::Image;
use crate::session::{self, Session};
use crate::wire::{self, Catalogue, Write, WriteReply};
use device_interface::time::{Clock, MonotonicClock};
use device_interface::{Interface, Registry};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The longest a thread waits before it looks at the stop flag again.
pub(super) const SLICE: Duration = Duration::from_millis(50);

/// Sleeps until `until`, in slices; false when stopped meanwhile.
fn sleep_until(until: Instant, stop: &AtomicBool) -> bool {
    loop {
        if stop.load(Ordering::Acquire) {
            return false;
        }
        let left = until.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return true;
        }
        std::thread::sleep(left.min(SLICE));
    }
}

/// Takes a sample that arrived on `key` into the images of that device.
pub(super) fn take_sample(
    by_key: &HashMap<String, Vec<Arc<Image>>>,
    key: &str,
    bytes: &[u8],
    c: &Counters,
) {
    let Some(images) = by_key.get(key) else {
        return;
    };
    match wire::parse::<wire::Sample>(bytes) {
        Ok(s) => {
            let now = MonotonicClock.now().as_nanos();
            for img in images {
                img.take(&s, now);
            }
        }
        Err(e) => {
            if c.bad_messages.fetch_add(1, Ordering::Relaxed) == 0 {
                tracing::warn!("zenoh: a sample on {key} does not parse: {e}");
            }
        }
    }
}

/// Every period: each exported port's batch, then each local device's sample.
pub(super) fn publish(
    gw: &str,
    s: &Session,
    registry: &Registry,
    exports: &[Arc<Export>],
    period: Duration,
    c: &Counters,
    stop: &AtomicBool,
) {
    let mut seq: HashMap<(Interface, String), u64> = HashMap::new();
    let mut publishers = s.publishers();
    let mut next = Instant::now();
    let mut put = |key: &str, bytes: Vec<u8>| match publishers.put(key, bytes) {
        Ok(()) => {
            c.published.fetch_add(1, Ordering::Relaxed);
        }
        Err(e) => {
            if c.publish_failed.fetch_add(1, Ordering::Relaxed) == 0 {
                tracing::warn!("zenoh: publishing {key}: {e}");
            }
        }
    };
    while !stop.load(Ordering::Acquire) {
        for e in exports {
            if let Some(batch) = e.drain() {
                put(e.key(), wire::to_bytes(&batch));
            }
        }
        for (i, name) in local::local_devices(registry) {
            let n = seq.entry((i, name.clone())).or_insert(0);
            *n += 1;
            if let Some(sample) = local::sample(registry, i, &name, *n) {
                put(&wire::sample_key(gw, i, &name), wire::to_bytes(&sample));
            }
        }
        next += period;
        if next <= Instant::now() {
            // Behind (a slow host): skip the missed periods rather than burst.
            next = Instant::now() + period;
        }
        if !sleep_until(next, stop) {
            return;
        }
    }
}

/// Answers other gateways' control requests with the handler set at the time.
pub(super) fn serve_control(
    handler: &Mutex<Option<ControlHandler>>,
    queue: &session::Queue,
    c: &Counters,
    stop: &AtomicBool,
) {
    serve(queue, stop, |bytes| {
        let h = lock(handler).clone();
        match (h, wire::parse::<serde_json::Value>(bytes)) {
            (None, _) => Err("this gateway takes no control requests over zenoh".to_string()),
            (_, Err(e)) => {
                c.bad_messages.fetch_add(1, Ordering::Relaxed);
                Err(format!("not a control request: {e}"))
            }
            (Some(h), Ok(req)) => {
                c.controls_served.fetch_add(1, Ordering::Relaxed);
                Ok(wire::to_bytes(&h(req)))
            }
        }
    });
}

/// Answers each request of `queue` with `answer(payload)` until stopped.
fn serve(
    queue: &session::Queue,
    stop: &AtomicBool,
    mut answer: impl FnMut(&[u8]) -> Result<Vec<u8>, String>,
) {
    while !stop.load(Ordering::Acquire) {
        if let Some((query, bytes)) = queue.next(SLICE) {
            session::answer(&query, answer(&bytes));
        }
    }
}

/// Sends the writes of this gateway's components to the gateways whose outputs they are,
/// as soon as they are made, and again until each is acknowledged or times out (see
/// [`crate::outbox`]); counts the answers.
pub(super) fn send_writes(
    me: &str,
    session: u64,
    s: &Session,
    images: &[Arc<Image>],
    wake: &crossbeam_channel::Receiver<()>,
    times: Times,
    stop: &AtomicBool,
) {
    let retry = Outbox::retry_for(times.request);
    let mut boxes: Vec<Outbox> = images
        .iter()
        .map(|_| Outbox::new(me, session, times.request, retry))
        .collect();
    while !stop.load(Ordering::Acquire) {
        let _ = wake.recv_timeout(retry.min(SLICE));
        let now = Instant::now();
        for (img, outbox) in images.iter().zip(&mut boxes) {
            let Some(out) = outbox.next(img, now) else {
                continue;
            };
            let key = wire::service_key(img.gateway(), "write");
            let answered = img.clone();
            let numbers = out.numbers;
            // No answer (a timeout, no route) is not a failure yet: the outbox sends the
            // message again until request_timeout_ms has passed.
            let sent = s.ask_then(
                &key,
                wire::to_bytes(&out.write),
                retry.max(Duration::from_millis(100)),
                move |answer| {
                    if let Ok(r) = answer.map(wire::parse::<WriteReply>)
                        && let Ok(r) = r
                    {
                        answered.answered(&numbers, &r.refused);
                    }
                },
            );
            let counter = match (&sent, out.retry) {
                (Err(_), _) => None,
                (Ok(()), false) => Some(&img.counters.writes_sent),
                (Ok(()), true) => Some(&img.counters.writes_retried),
            };
            if let Some(c) = counter {
                c.fetch_add(1, Ordering::Relaxed);
            } else if let Err(e) = sent {
                tracing::debug!("zenoh: sending a write to {}: {e}", img.gateway());
            }
        }
    }
}

/// A number for this run of the gateway, different from the last run's (the remote
/// gateway applies each of a writer's sequence numbers once per run).
pub(super) fn run_number() -> u64 {
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    t ^ (u64::from(std::process::id()) << 48) | 1
}

/// Carries out other gateways' writes to this gateway's outputs, each message once (see
/// [`local::Writes`]).
pub(super) fn serve_writes(
    gw: &str,
    registry: &Registry,
    queue: &session::Queue,
    c: &Counters,
    stop: &AtomicBool,
) {
    let mut writes = local::Writes::default();
    serve(queue, stop, |bytes| {
        let w = match wire::parse::<Write>(bytes) {
            Err(e) => {
                c.bad_messages.fetch_add(1, Ordering::Relaxed);
                return Err(format!("not a write: {e}"));
            }
            Ok(w) => w,
        };
        let (r, repeated) = writes.apply(gw, registry, &w);
        let counter = if repeated {
            &c.writes_repeated
        } else {
            &c.writes_served
        };
        counter.fetch_add(1, Ordering::Relaxed);
        if !repeated && !r.refused.is_empty() {
            c.writes_refused.fetch_add(1, Ordering::Relaxed);
        }
        Ok(wire::to_bytes(&r))
    });
}

/// How often a gateway asks whether another answers to its name.
const NAME_CHECK: Duration = Duration::from_secs(5);

/// Asks, now and every [`NAME_CHECK`], for the catalogue of gateway `me`: one answering
/// with another run is a second gateway with this name (their devices, writes and
/// control requests would mix). Says so once per such gateway, and keeps it in `twin` for
/// the status.
pub(super) fn watch_name(
    s: &Session,
    me: &str,
    run: u64,
    twin: &Mutex<Option<String>>,
    times: Times,
    stop: &AtomicBool,
) {
    let mut told: Vec<u64> = Vec::new();
    loop {
        let replies = s
            .ask(
                &wire::service_key(me, "catalogue"),
                Vec::new(),
                times.request.min(Duration::from_secs(2)),
                16,
            )
            .unwrap_or_default();
        for c in replies
            .iter()
            .filter_map(|b| wire::parse::<Catalogue>(b).ok())
        {
            if c.gateway != me || c.run == run || told.contains(&c.run) {
                continue;
            }
            let text = format!(
                "another gateway answers to the name {me:?} on this Zenoh network (with {} \
                 devices): names must be unique, or devices, writes and requests of the two mix; \
                 rename one ([zenoh] name)",
                c.devices.len()
            );
            tracing::error!("zenoh: {text}");
            *super::lock(twin) = Some(text);
            if told.len() < 64 {
                told.push(c.run);
            }
        }
        if !sleep_until(Instant::now() + NAME_CHECK, stop) {
            return;
        }
    }
}

/// Asks each imported gateway for its catalogue until it answers, and again after it
/// restarted; matches each imported device's shape against it.
pub(super) fn import(
    s: &Session,
    gateways: &[String],
    images: &[Arc<Image>],
    times: Times,
    stop: &AtomicBool,
) {
    let mut missing: Vec<&String> = gateways.iter().collect();
    let started = Instant::now();
    let mut reported = false;
    while !stop.load(Ordering::Acquire) {
        for img in images {
            if img.take_refetch()
                && !missing.iter().any(|g| *g == img.gateway())
                && let Some(g) = gateways.iter().find(|g| *g == img.gateway())
            {
                tracing::info!("zenoh: gateway {g} started again: asking its catalogue");
                missing.push(g);
            }
        }
        let mut answered = Vec::new();
        for gw in &missing {
            if stop.load(Ordering::Acquire) {
                return;
            }
            let key = wire::service_key(gw, "catalogue");
            let reply = s
                .ask(
                    &key,
                    Vec::new(),
                    times.request.min(Duration::from_secs(2)),
                    1,
                )
                .unwrap_or_default();
            if let Some(cat) = reply.iter().find_map(|b| wire::parse::<Catalogue>(b).ok()) {
                adopt(gw, &cat, images);
                answered.push(gw.to_string());
            }
        }
        missing.retain(|g| !answered.contains(g));
        if !missing.is_empty() && !reported && started.elapsed() >= times.offline {
            reported = true;
            let names: Vec<&str> = missing.iter().map(|s| s.as_str()).collect();
            tracing::warn!(
                "zenoh: no answer yet from gateway(s) {}: their devices stay offline until they are up",
                names.join(", ")
            );
        }
        if !sleep_until(Instant::now() + Duration::from_millis(500), stop) {
            return;
        }
    }
}

/// Matches the images of gateway `gw` against its catalogue `cat`.
fn adopt(gw: &str, cat: &Catalogue, images: &[Arc<Image>]) {
    if cat.protocol != wire::PROTOCOL {
        tracing::error!(
            "zenoh: gateway {gw} speaks protocol {}, this one {}: its devices stay offline",
            cat.protocol,
            wire::PROTOCOL
        );
        return;
    }
    for img in images.iter().filter(|i| i.gateway() == gw) {
        let found = cat
            .devices
            .iter()
            .find(|d| d.interface == img.interface() && d.name == img.device());
        match found {
            Some(shape) => img.adopt(shape),
            None => {
                let names: Vec<&str> = cat
                    .devices
                    .iter()
                    .filter(|d| d.interface == img.interface())
                    .map(|d| d.name.as_str())
                    .collect();
                tracing::error!(
                    "zenoh: gateway {gw} has no {} device {:?} (it has: {}); {gw}/{} stays offline",
                    wire::interface_key(img.interface()),
                    img.device(),
                    if names.is_empty() {
                        "none".into()
                    } else {
                        names.join(", ")
                    },
                    img.device()
                );
            }
        }
    }
    tracing::info!("zenoh: imported the devices of gateway {gw}");
}
