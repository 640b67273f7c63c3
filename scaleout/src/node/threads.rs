//! The node's threads: publishing, serving other gateways' writes and control requests,
//! sending this gateway's writes, and asking for the catalogues of the gateways imported
//! from. Each waits in slices of at most [`SLICE`], so a stop is never held up longer
//! (the gateway's outputs go to their safe values right after the node stops).

use super::{ControlHandler, Counters, lock};
use crate::config::Times;
use crate::local;
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

/// Carries out other gateways' writes to this gateway's outputs.
pub(super) fn serve_writes(
    gw: &str,
    registry: &Registry,
    queue: &session::Queue,
    c: &Counters,
    stop: &AtomicBool,
) {
    serve(queue, stop, |bytes| match wire::parse::<Write>(bytes) {
        Err(e) => {
            c.bad_messages.fetch_add(1, Ordering::Relaxed);
            Err(format!("not a write: {e}"))
        }
        Ok(w) => match local::write(gw, registry, &w) {
            Ok(r) => {
                c.writes_served.fetch_add(1, Ordering::Relaxed);
                if !r.refused.is_empty() {
                    c.writes_refused.fetch_add(1, Ordering::Relaxed);
                }
                Ok(wire::to_bytes(&r))
            }
            Err(e) => {
                c.writes_refused.fetch_add(1, Ordering::Relaxed);
                Err(e)
            }
        },
    });
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
/// as soon as they are made; counts the answers.
pub(super) fn send_writes(
    me: &str,
    s: &Session,
    images: &[Arc<Image>],
    wake: &crossbeam_channel::Receiver<()>,
    times: Times,
    stop: &AtomicBool,
) {
    while !stop.load(Ordering::Acquire) {
        let _ = wake.recv_timeout(SLICE);
        for img in images {
            let Some(values) = img.to_send() else {
                continue;
            };
            let w = Write {
                protocol: wire::PROTOCOL,
                writer: me.to_string(),
                interface: img.interface(),
                device: img.device().to_string(),
                values,
            };
            let key = wire::service_key(img.gateway(), "write");
            let answered = img.clone();
            let sent =
                s.ask_then(
                    &key,
                    wire::to_bytes(&w),
                    times.request,
                    move |answer| match answer.and_then(wire::parse::<WriteReply>) {
                        Ok(r) => answered.answered(&r.refused),
                        Err(e) => answered.failed(&e),
                    },
                );
            match sent {
                Ok(()) => img.counters.writes_sent.fetch_add(1, Ordering::Relaxed),
                Err(e) => {
                    img.failed(&e.to_string());
                    0
                }
            };
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
