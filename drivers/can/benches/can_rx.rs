//! Frames per second decoded into ports without loss, side by side with candump on the
//! same vcan in the same guest run; and receive-to-port latency.
//!
//! `cargo bench -p driver-can --bench can_rx` boots the kernel rig and runs this inside.
//! For each offered rate (cangen with a fixed gap), both hwgw (a CAN card whose `rx`
//! message port is connected by a buffer to a counting component) and candump (writing
//! its log to a tmpfs file) receive the same frames; each reports how many arrived. The
//! figure of merit is the highest offered rate each takes without losing a frame.
#![allow(clippy::unwrap_used, reason = "benchmark code")]

use device_interface::time::{Clock, MonotonicClock};
use driver_can::bus::CanBus;
use driver_can::card::CanCard;
use driver_can::component::{CanIo, CanMessage};
use driver_can::map::{CanConfig, CanMap};
use kernel_rig::{Failed, Trial, sh};
use rtt::port::{ConnPolicy, FlowStatus, InputPort};
use rtt::{ActivitySpec, Component, Context, HookResult, Runtime, RuntimeOptions};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Counts messages and keeps (received -> published, received -> read) latencies in ns.
struct Sink {
    input: InputPort<CanMessage>,
    sample: CanMessage,
    count: Arc<AtomicU64>,
    latency: Arc<Mutex<Vec<(u64, u64)>>>,
}

impl Component for Sink {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        while self.input.read(&mut self.sample) == FlowStatus::NewData {
            self.count.fetch_add(1, Ordering::Relaxed);
            let now = MonotonicClock.now().as_nanos();
            if let Ok(mut l) = self.latency.try_lock()
                && l.len() < l.capacity()
            {
                l.push((
                    self.sample
                        .published_ns
                        .saturating_sub(self.sample.received_ns),
                    now.saturating_sub(self.sample.received_ns),
                ));
            }
        }
        Ok(())
    }
}

fn quantile(v: &mut [u64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_unstable();
    v[((v.len() - 1) as f64 * q).round() as usize] as f64 / 1000.0
}

/// Runs the measurement; returns the nanoseconds per frame at hwgw's highest lossless
/// rate (libtest's bench figure).
fn rx_bench(quick: bool) -> Result<u64, Failed> {
    let iface = "bench0";
    sh(&format!(
        "ip link add {iface} type vcan && ip link set {iface} up"
    ))?;
    let config: CanConfig = toml::from_str(&format!(
        r#"
interface = "{iface}"
[[rx]]
id = 0x100
signal = [
    {{ name = "a", start = 0, length = 16 }},
    {{ name = "b", start = 16, length = 16, signed = true, factor = 0.1 }},
    {{ name = "c", start = 39, length = 16, byte_order = "motorola" }},
    {{ name = "d", start = 48, length = 16, factor = 0.01, offset = -100 }},
]
"#
    ))?;
    let card = CanCard::new(
        CanMap::new(&config, ".".as_ref())?,
        Arc::new(MonotonicClock),
    );
    let bus = CanBus::open(card.clone())?;
    let rt = Runtime::new(
        Arc::new(device_interface::Registry::new()),
        RuntimeOptions::default(),
    )?;
    let can = CanIo::add(&rt, "can", bus, Default::default())?;
    let count = Arc::new(AtomicU64::new(0));
    let latency = Arc::new(Mutex::new(Vec::with_capacity(200_000)));
    let (c2, l2) = (count.clone(), latency.clone());
    let sink = rt.add(
        "sink",
        ActivitySpec::non_periodic(),
        rtt::InitialState::Stopped,
        move |i| {
            Ok(Sink {
                input: i.event_input("in", "messages")?,
                sample: CanMessage {
                    values: Vec::with_capacity(4),
                    ..CanMessage::default()
                },
                count: c2,
                latency: l2,
            })
        },
    )?;
    can.port("rx.0x100")?
        .connect_to(&*sink.port("in")?, ConnPolicy::buffer(65_536))?;
    sink.start()?;
    can.start()?;

    let frames: u64 = if quick { 500 } else { 20_000 };
    // Offered rates in frames/s; 0 is as fast as the sender can go.
    let rates: &[u64] = if quick {
        &[1000]
    } else {
        &[1000, 2000, 4000, 6000, 8000, 10_000, 12_000, 16_000, 0]
    };
    let sender = <socketcan::CanSocket as socketcan::Socket>::open(iface)?;
    println!(
        " asked frames/s | offered frames/s | hwgw received (kernel drops) | candump received"
    );
    let (mut best_ours, mut best_candump) = (0.0f64, 0.0f64);
    for &rate in rates {
        count.store(0, Ordering::Relaxed);
        let drops_before = card.counters().rx_dropped;
        latency.lock().unwrap().clear();
        let log = "/tmp/candump.log";
        let dump = testkit::Candump::start_logging(
            &["-n", &frames.to_string(), "-T", "3000", iface],
            std::fs::File::create(log)?,
        )?;
        // The reference reader: a bare blocking socket read, timestamps as ours.
        let reference = if rate == 1000 {
            Some(reference_reader(iface, frames)?)
        } else {
            None
        };
        let start = Instant::now();
        send(&sender, rate, frames)?;
        let offered = frames as f64 / start.elapsed().as_secs_f64();
        dump.finish()?;
        let theirs = std::fs::read_to_string(log)?.lines().count() as u64;
        let end = Instant::now() + Duration::from_secs(3);
        while count.load(Ordering::Relaxed) < frames && Instant::now() < end {
            std::thread::sleep(Duration::from_millis(10));
        }
        let ours = count.load(Ordering::Relaxed);
        let drops = card.counters().rx_dropped - drops_before;
        println!("{rate:>15} | {offered:>16.0} | {ours:>18} ({drops:>5}) | {theirs:>16}");
        if ours == frames {
            best_ours = best_ours.max(offered);
        }
        if theirs == frames {
            best_candump = best_candump.max(offered);
        }
        if let Some(r) = reference {
            let mut bare = r.join().map_err(|_| "reference reader panicked")??;
            let l = latency.lock().unwrap();
            let (mut to_port, mut to_reader): (Vec<u64>, Vec<u64>) = l.iter().copied().unzip();
            let (p50, p99) = (quantile(&mut to_port, 0.5), quantile(&mut to_port, 0.99));
            let (b50, b99) = (quantile(&mut bare, 0.5), quantile(&mut bare, 0.99));
            println!(
                "latency at 1000 frames/s, {} frames: kernel receive -> port write p50 {p50:.1} us, p99 {p99:.1} us \
                 (-> the connected reader p50 {:.1} us, p99 {:.1} us); a bare blocking socket read in the same run: \
                 p50 {b50:.1} us, p99 {b99:.1} us; ratio p50 {:.2}, p99 {:.2}",
                to_port.len(),
                quantile(&mut to_reader, 0.5),
                quantile(&mut to_reader, 0.99),
                p50 / b50,
                p99 / b99,
            );
        }
    }
    println!(
        "highest offered rate without loss: hwgw {best_ours:.0} frames/s, candump {best_candump:.0} frames/s, ratio {:.2}",
        best_ours / best_candump
    );
    let s = can.stats();
    println!(
        "bus component: {} steps, mean step {:?}",
        s.steps,
        s.step_mean()
    );
    can.stop()?;
    sink.stop()?;
    Ok((1e9 / best_ours.max(1.0)) as u64)
}

/// Sends `n` frames at `rate` frames/s (0: flat out), in 1 ms bursts on an absolute
/// schedule; a full socket buffer is retried, not skipped, so `n` frames are offered.
fn send(socket: &socketcan::CanSocket, rate: u64, n: u64) -> Result<(), Failed> {
    use socketcan::{EmbeddedFrame, Socket, StandardId};
    let id = StandardId::new(0x100).ok_or("id")?;
    let per_ms = if rate == 0 { n } else { rate.div_ceil(1000) };
    let start = Instant::now();
    let mut sent = 0u64;
    let mut tick = 0u32;
    while sent < n {
        for _ in 0..per_ms.min(n - sent) {
            let frame = socketcan::CanFrame::new(id, &sent.to_le_bytes()).ok_or("frame")?;
            loop {
                match socket.write_frame(&frame) {
                    Ok(()) => break,
                    Err(e) if e.raw_os_error() == Some(105) => std::thread::yield_now(), // ENOBUFS
                    Err(e) => return Err(e.into()),
                }
            }
            sent += 1;
        }
        tick += 1;
        if let Some(wait) =
            (start + Duration::from_millis(u64::from(tick))).checked_duration_since(Instant::now())
        {
            std::thread::sleep(wait);
        }
    }
    Ok(())
}

/// A thread reading `n` frames from a plain blocking socket, returning each frame's
/// kernel-receive-to-read latency in ns (the reference for ours).
fn reference_reader(
    iface: &str,
    n: u64,
) -> Result<std::thread::JoinHandle<Result<Vec<u64>, Failed>>, Failed> {
    use socketcan::{Socket, SocketOptions};
    let s = socketcan::CanSocket::open(iface)?;
    s.set_recv_timestamp(true)?;
    s.set_read_timeout(Duration::from_secs(3))?;
    Ok(std::thread::spawn(move || {
        let mut v = Vec::with_capacity(n as usize);
        for _ in 0..n {
            let Ok((_, at)) = s.read_frame_with_timestamp() else {
                break;
            };
            let now = std::time::SystemTime::now();
            v.push(now.duration_since(at).map_or(0, |d| d.as_nanos() as u64));
        }
        Ok(v)
    }))
}

fn main() -> std::process::ExitCode {
    let rig = testkit::rig::vcan();
    kernel_rig::harness(
        &rig,
        vec![Trial::bench("can_rx", |test_mode| {
            let ns = rx_bench(test_mode)?;
            Ok((!test_mode).then_some(kernel_rig::Measurement {
                avg: ns,
                variance: 0,
            }))
        })],
    )
}
