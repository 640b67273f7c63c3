//! Frames per second decoded into ports without loss, side by side with candump on the
//! same vcan in the same guest run; and receive-to-port latency.
//!
//! `cargo bench -p driver-can --bench can_rx` boots the kernel rig and runs this inside.
//! For each offered rate (cangen with a fixed gap), both hwgw (a CAN card whose `rx`
//! message port is connected by a buffer to a counting component) and candump (writing
//! its log to a tmpfs file) receive the same frames; each reports how many arrived. The
//! figure of merit is the highest offered rate each takes without losing a frame.
//!
//! Before that, latency: the time from the kernel's receive stamp to the frame's values
//! on the port, against a bare blocking socket read of the same kind of frame and a bare
//! `epoll_wait` + `recvmsg`, each measured in the same seconds as hwgw, their frames
//! interleaved (see [`latency_rounds`]); what hwgw's own work after a frame costs in the
//! guest, piece by piece ([`pieces`]); and the bus thread's system calls under strace
//! ([`trace_bus_thread`]).
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
    let rounds = if quick { 1 } else { 5 };
    pieces(&config)?;
    for fifo in [false, true] {
        set_fifo(thread_id("can")?, fifo)?;
        latency_rounds(iface, &sender, (&count, &latency), rounds, frames / 7, fifo)?;
    }
    trace_bus_thread(&sender, &count, if quick { 50 } else { 500 })?;
    set_fifo(thread_id("can")?, false)?;
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
        let start = Instant::now();
        send(&sender, ID, rate, frames)?;
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

/// What the bus thread's own work after a frame costs in this guest, each piece timed
/// alone on this thread with a monotonic clock read on each side: back to back (warm), and
/// each after a 1 ms sleep (cold, as a frame finds the bus thread, which slept since the
/// last). The pieces are the work between the blocking read's return and the port write
/// that the bare reader does not do.
fn pieces(config: &CanConfig) -> Result<(), Failed> {
    let card = CanCard::new(CanMap::new(config, ".".as_ref())?, Arc::new(MonotonicClock));
    let data = [0x12u8, 0x34, 0x56, 0x78, 0x9a, 0xbc, 0xde, 0xf0];
    let mut values = Vec::with_capacity(4);
    let mut message = CanMessage {
        values: Vec::with_capacity(4),
        ..CanMessage::default()
    };
    let n = 2000;
    let time = |what: &str, piece: &mut dyn FnMut()| {
        let mut runs = [Vec::with_capacity(n), Vec::with_capacity(n)];
        for (cold, run) in runs.iter_mut().enumerate() {
            for _ in 0..n {
                if cold == 1 {
                    std::thread::sleep(Duration::from_millis(1));
                }
                let t0 = MonotonicClock.now().as_nanos();
                piece();
                run.push(MonotonicClock.now().as_nanos() - t0);
            }
        }
        let [mut warm, mut cold] = runs;
        println!(
            "  piece: {what}: warm p50 {:.2} us, p99 {:.2} us; after 1 ms asleep p50 {:.2} us, p99 {:.2} us",
            quantile(&mut warm, 0.5),
            quantile(&mut warm, 0.99),
            quantile(&mut cold, 0.5),
            quantile(&mut cold, 0.99)
        );
    };
    println!("where a frame's time goes, each piece alone ({n} times warm, {n} after a sleep):");
    time("nothing (two monotonic clock reads)", &mut || {});
    time("a monotonic clock read", &mut || {
        std::hint::black_box(MonotonicClock.now());
    });
    time("a realtime clock read", &mut || {
        std::hint::black_box(can_socket::socket::realtime_now());
    });
    let at = device_interface::time::Timestamp::from_nanos(1);
    time(
        "decoding the frame into the card's channels and the values",
        &mut || {
            std::hint::black_box(card.receive_with_values(
                u32::from(ID),
                false,
                false,
                &data,
                at,
                &mut values,
            ));
        },
    );
    time("the message's values copied and stamped", &mut || {
        message.values.clear();
        message.values.extend_from_slice(&[1.0, 2.0, 3.0, 4.0]);
        message.received_ns = 1;
        message.published_ns = MonotonicClock.now().as_nanos();
        std::hint::black_box(&message);
    });
    Ok(())
}

/// The bus thread's system calls while it takes `n` frames at 100 frames/s under
/// SCHED_FIFO 50: `strace -c` of that thread alone. Traced, each call costs the guest
/// milliseconds, so the frames come 10 ms apart, for the thread to take each as it comes
/// rather than from a backlog; the latency under strace is not counted anywhere.
fn trace_bus_thread(
    sender: &socketcan::CanSocket,
    count: &AtomicU64,
    n: u64,
) -> Result<(), Failed> {
    let tid = thread_id("can")?;
    set_fifo(tid, true)?;
    let out = "/tmp/can-bus-thread.strace";
    let mut strace = std::process::Command::new("strace")
        .args(["-qq", "-c", "-o", out, "-p", &tid.to_string()])
        .spawn()
        .map_err(|e| format!("strace (package strace): {e}"))?;
    // Traced once the thread's status names its tracer.
    let status = format!("/proc/self/task/{tid}/status");
    let end = Instant::now() + Duration::from_secs(20);
    while !std::fs::read_to_string(&status)?
        .lines()
        .any(|l| l.starts_with("TracerPid:") && l.split_whitespace().nth(1) != Some("0"))
    {
        if let Some(exit) = strace.try_wait()? {
            return Err(format!("strace ended before it attached: {exit}").into());
        }
        if Instant::now() > end {
            let _ = strace.kill();
            let _ = strace.wait();
            return Err("strace did not attach to the bus thread within 20 s".into());
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    count.store(0, Ordering::Relaxed);
    send_spaced(sender, ID, Duration::from_millis(10), n)?;
    let end = Instant::now() + Duration::from_secs(10);
    while count.load(Ordering::Relaxed) < n && Instant::now() < end {
        std::thread::sleep(Duration::from_millis(10));
    }
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(strace.id() as i32),
        nix::sys::signal::Signal::SIGINT,
    )?;
    strace.wait()?;
    println!(
        "the bus thread's system calls for {n} frames at 100 frames/s, SCHED_FIFO 50 \
         ({} reached the port), strace -c:\n{}",
        count.load(Ordering::Relaxed),
        std::fs::read_to_string(out)?
    );
    set_fifo(tid, false)?;
    Ok(())
}

/// Sends `n` frames at `rate` frames/s (0: flat out), in 1 ms bursts on an absolute
/// schedule; a full socket buffer is retried, not skipped, so `n` frames are offered.
fn send(socket: &socketcan::CanSocket, id: u16, rate: u64, n: u64) -> Result<(), Failed> {
    let per_ms = if rate == 0 { n } else { rate.div_ceil(1000) };
    let start = Instant::now();
    let mut sent = 0u64;
    let mut tick = 0u32;
    while sent < n {
        for _ in 0..per_ms.min(n - sent) {
            write(socket, id, sent)?;
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

/// Sends `n` frames of `id`, `gap` apart, on an absolute schedule.
fn send_spaced(
    socket: &socketcan::CanSocket,
    id: u16,
    gap: Duration,
    n: u64,
) -> Result<(), Failed> {
    let start = Instant::now();
    for k in 0..n {
        write(socket, id, k)?;
        if let Some(wait) = (start + gap * (k as u32 + 1)).checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
    }
    Ok(())
}

/// Sends `n` frames of each of `ids` at 1000 frames/s an id, the ids in turn and evenly
/// spaced within each millisecond, on an absolute schedule.
fn send_interleaved(socket: &socketcan::CanSocket, ids: &[u16], n: u64) -> Result<(), Failed> {
    let gap = Duration::from_micros(1000 / ids.len() as u64);
    let start = Instant::now();
    for (k, id) in ids.iter().cycle().take(n as usize * ids.len()).enumerate() {
        write(socket, *id, (k / ids.len()) as u64)?;
        if let Some(wait) = (start + gap * (k as u32 + 1)).checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
    }
    Ok(())
}

/// Writes one frame of `id` carrying `k`; a full socket buffer is retried, not skipped.
fn write(socket: &socketcan::CanSocket, id: u16, k: u64) -> Result<(), Failed> {
    use socketcan::{EmbeddedFrame, Socket, StandardId};
    let id = StandardId::new(id).ok_or("id")?;
    let frame = socketcan::CanFrame::new(id, &k.to_le_bytes()).ok_or("frame")?;
    loop {
        match socket.write_frame(&frame) {
            Ok(()) => return Ok(()),
            Err(e) if e.raw_os_error() == Some(105) => std::thread::yield_now(), // ENOBUFS
            Err(e) => return Err(e.into()),
        }
    }
}

/// The id of the frames hwgw maps; the reference reader's ([`REFERENCE_ID`]) are
/// filtered out of hwgw's socket by the kernel, so neither reader is woken by the other's.
const ID: u16 = 0x100;
const REFERENCE_ID: u16 = 0x101;

/// Receive-to-port latency against two bare readers, `rounds` times, each round in three
/// passes of `n` frames at 1000 frames/s a reader: hwgw and a bare blocking read together,
/// their frames interleaved (hwgw's [`ID`] on the millisecond, the reader's
/// [`REFERENCE_ID`] half a millisecond later: each frame wakes one reader only, hwgw's
/// kernel filter dropping the other's, and the two are measured in the same seconds, so
/// the guest's round-to-round swings weigh on both alike); then hwgw and a bare
/// `epoll_wait` + non-blocking `recvmsg` the same way; then the ring reader alone. The
/// second reference is how hwgw's bus thread waited until 2026-12-01 (and a J1939 card's
/// still waits): what waiting in epoll costs beside what hwgw adds. A card without J1939
/// now waits in `recvmsg` itself, as the first reference does.
///
/// With `fifo`, the bus thread and the bare reader both run SCHED_FIFO at priority 50 (as
/// a deployment's bus thread would), so each preempts the sender at once; without, both
/// are SCHED_OTHER and the scheduler decides when a woken reader runs.
fn latency_rounds(
    iface: &str,
    sender: &socketcan::CanSocket,
    (count, latency): (&AtomicU64, &Mutex<Vec<(u64, u64)>>),
    rounds: usize,
    n: u64,
    fifo: bool,
) -> Result<(), Failed> {
    let class = if fifo { "SCHED_FIFO 50" } else { "SCHED_OTHER" };
    let mut ratios = Vec::new();
    // hwgw's latencies (to the port, to the connected reader) and the reference's, of
    // one pass beside `wait`.
    type Pass = (Vec<u64>, Vec<u64>, Vec<u64>);
    let beside = |wait: Wait| -> Result<Pass, Failed> {
        count.store(0, Ordering::Relaxed);
        latency.lock().unwrap().clear();
        let reader = reference_reader(iface, n, fifo, wait)?;
        send_interleaved(sender, &[ID, REFERENCE_ID], n)?;
        let theirs = reader.join().map_err(|_| "reference reader panicked")??;
        let end = Instant::now() + Duration::from_secs(3);
        while count.load(Ordering::Relaxed) < n && Instant::now() < end {
            std::thread::sleep(Duration::from_millis(10));
        }
        let (to_port, to_reader) = latency.lock().unwrap().iter().copied().unzip();
        Ok((to_port, to_reader, theirs))
    };
    for round in 1..=rounds {
        let (mut to_port, mut to_reader, mut bare) = beside(Wait::Blocking)?;
        let (mut to_port_e, _, mut polled) = beside(Wait::Epoll)?;
        let mut ringed = reference_pass(iface, sender, n, fifo, Wait::Ring)?;
        println!(
            "  epoll_wait + a TPACKET_V2 ring read (alone): p50 {:.1} us, p99 {:.1} us ({} frames)",
            quantile(&mut ringed, 0.5),
            quantile(&mut ringed, 0.99),
            ringed.len()
        );
        let (p50, p99) = (quantile(&mut to_port, 0.5), quantile(&mut to_port, 0.99));
        let (pe50, pe99) = (
            quantile(&mut to_port_e, 0.5),
            quantile(&mut to_port_e, 0.99),
        );
        let (b50, b99) = (quantile(&mut bare, 0.5), quantile(&mut bare, 0.99));
        let (e50, e99) = (quantile(&mut polled, 0.5), quantile(&mut polled, 0.99));
        println!(
            "latency, {class}, round {round}, {n} frames at 1000 frames/s each: kernel receive -> port write \
             p50 {p50:.1} us, p99 {p99:.1} us ({} frames; -> the connected reader p50 {:.1} us, \
             p99 {:.1} us) beside a bare blocking socket read: p50 {b50:.1} us, p99 {b99:.1} us \
             ({} frames); p50 {pe50:.1} us, p99 {pe99:.1} us ({} frames) beside a bare epoll_wait + \
             recvmsg: p50 {e50:.1} us, p99 {e99:.1} us ({} frames); \
             ratio to the blocking read p50 {:.2}, p99 {:.2}; to epoll + recvmsg p50 {:.2}, p99 {:.2}",
            to_port.len(),
            quantile(&mut to_reader, 0.5),
            quantile(&mut to_reader, 0.99),
            bare.len(),
            to_port_e.len(),
            polled.len(),
            p50 / b50,
            p99 / b99,
            pe50 / e50,
            pe99 / e99,
        );
        ratios.push([p50 / b50, p99 / b99, pe50 / e50, pe99 / e99]);
    }
    let median = |k: usize| {
        let mut v: Vec<f64> = ratios.iter().map(|r| r[k]).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    println!(
        "latency ratio, {class}, median of {rounds} rounds: to the bare blocking read p50 {:.2}, p99 {:.2}; \
         to a bare epoll_wait + recvmsg p50 {:.2}, p99 {:.2}",
        median(0),
        median(1),
        median(2),
        median(3)
    );
    Ok(())
}

/// How a reference reader waits for a frame.
#[derive(Clone, Copy, PartialEq)]
enum Wait {
    /// In the blocking `recvmsg` itself.
    Blocking,
    /// In `epoll_wait` on the socket, then a non-blocking `recvmsg` (as a reader that waits
    /// for a timer and a wake-up in the same call must: a J1939 card's bus thread does so).
    Epoll,
    /// In `epoll_wait` on an AF_PACKET socket with a TPACKET_V2 receive ring, the frame
    /// then read from the ring with no second system call: would a bus thread reading a
    /// ring get within 1.2x of the blocking read? (On vcan a packet socket sees a local
    /// sender's frames only as they are sent, PACKET_OUTGOING, and stamped there rather
    /// than at the loopback's receive: close to, not the same as, the CAN_RAW readers'
    /// stamp. hwgw does not read a ring; this is a reference only.)
    Ring,
}

/// One reference pass: a reader of `n` frames of [`REFERENCE_ID`] waiting as `wait` says,
/// then the frames sent; each frame's kernel-receive-to-read latency in ns.
fn reference_pass(
    iface: &str,
    sender: &socketcan::CanSocket,
    n: u64,
    fifo: bool,
    wait: Wait,
) -> Result<Vec<u64>, Failed> {
    let reader = reference_reader(iface, n, fifo, wait)?;
    send(sender, REFERENCE_ID, 1000, n)?;
    reader.join().map_err(|_| "reference reader panicked")?
}

/// A thread reading `n` frames of [`REFERENCE_ID`] from a plain blocking socket, returning
/// each frame's kernel-receive-to-read latency in ns (the reference for ours). The socket
/// is bound before this returns, so no frame sent after it is missed.
fn reference_reader(
    iface: &str,
    n: u64,
    fifo: bool,
    wait: Wait,
) -> Result<std::thread::JoinHandle<Result<Vec<u64>, Failed>>, Failed> {
    if wait == Wait::Ring {
        let ring = ring::Ring::open(iface)?;
        return Ok(std::thread::spawn(move || {
            set_fifo(0, fifo)?;
            ring.read(n, u32::from(REFERENCE_ID))
        }));
    }
    use nix::sys::epoll::{Epoll, EpollCreateFlags, EpollEvent, EpollFlags, EpollTimeout};
    use socketcan::{Socket, SocketOptions};
    let s = socketcan::CanSocket::open(iface)?;
    s.set_filters(&[socketcan::CanFilter::new(u32::from(REFERENCE_ID), 0x7FF)])?;
    s.set_recv_timestamp(true)?;
    let epoll = Epoll::new(EpollCreateFlags::EPOLL_CLOEXEC)?;
    if wait == Wait::Epoll {
        s.set_nonblocking(true)?;
        epoll.add(&s, EpollEvent::new(EpollFlags::EPOLLIN, 0))?;
    } else {
        s.set_read_timeout(Duration::from_secs(3))?;
    }
    Ok(std::thread::spawn(move || {
        set_fifo(0, fifo)?;
        let mut v = Vec::with_capacity(n as usize);
        let mut ready = [EpollEvent::empty(); 1];
        while (v.len() as u64) < n {
            if wait == Wait::Epoll && epoll.wait(&mut ready, EpollTimeout::from(3000u16))? == 0 {
                break;
            }
            // Every queued frame (one, unless the reader fell behind).
            loop {
                match s.read_frame_with_timestamp() {
                    Ok((_, at)) => {
                        let now = std::time::SystemTime::now();
                        v.push(now.duration_since(at).map_or(0, |d| d.as_nanos() as u64));
                    }
                    // Blocking, this is the 3 s read timeout: a frame lost, the pass over.
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        if wait == Wait::Blocking {
                            return Ok(v);
                        }
                        break;
                    }
                    Err(_) => return Ok(v),
                }
                if wait == Wait::Blocking || v.len() as u64 == n {
                    break;
                }
            }
        }
        Ok(v)
    }))
}

/// The id of this process's thread named `name`.
fn thread_id(name: &str) -> Result<i32, Failed> {
    // The activity's thread names itself once started.
    let end = Instant::now() + Duration::from_secs(2);
    loop {
        match find_thread(name) {
            Err(e) if Instant::now() < end => {
                let _ = e;
                std::thread::sleep(Duration::from_millis(10));
            }
            other => return other,
        }
    }
}

fn find_thread(name: &str) -> Result<i32, Failed> {
    let mut names = Vec::new();
    for t in std::fs::read_dir("/proc/self/task")? {
        let t = t?;
        let comm = std::fs::read_to_string(t.path().join("comm"))?;
        if comm.trim() == name {
            return Ok(t.file_name().to_string_lossy().parse()?);
        }
        names.push(comm.trim().to_string());
    }
    Err(format!("no thread named {name}; there are {}", names.join(", ")).into())
}

/// Puts thread `tid` (0: the caller) in SCHED_FIFO at priority 50, or back in SCHED_OTHER.
fn set_fifo(tid: i32, fifo: bool) -> Result<(), Failed> {
    let (policy, priority) = if fifo {
        (libc::SCHED_FIFO, 50)
    } else {
        (libc::SCHED_OTHER, 0)
    };
    let param = libc::sched_param {
        sched_priority: priority,
    };
    #[allow(
        unsafe_code,
        reason = "sched_setscheduler with a valid parameter block"
    )]
    // SAFETY: `param` is a valid sched_param for the call's duration.
    let r = unsafe { libc::sched_setscheduler(tid, policy, &param) };
    if r != 0 {
        return Err(format!("sched_setscheduler: {}", std::io::Error::last_os_error()).into());
    }
    Ok(())
}

fn main() -> std::process::ExitCode {
    let rig = testkit::rig::with_peer(testkit::rig::vcan(), &testkit::peers::STRACE);
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

/// A bare AF_PACKET reader with a TPACKET_V2 receive ring (the experiment of [`Wait::Ring`]).
mod ring {
    #![allow(
        unsafe_code,
        reason = "AF_PACKET socket, its mmap'd ring and the frames' headers in it"
    )]
    use super::Failed;
    use nix::sys::epoll::{Epoll, EpollCreateFlags, EpollEvent, EpollFlags, EpollTimeout};
    use std::os::fd::{AsFd, FromRawFd, OwnedFd};
    use std::sync::atomic::{AtomicU32, Ordering};

    const FRAME: usize = 256;
    const BLOCK: usize = 4096;
    const BLOCKS: usize = 64;

    pub struct Ring {
        fd: OwnedFd,
        map: *mut u8,
    }

    // SAFETY: the mapping belongs to the Ring alone and is used by one thread at a time.
    unsafe impl Send for Ring {}

    fn check(r: libc::c_int, what: &str) -> Result<(), Failed> {
        if r < 0 {
            return Err(format!("{what}: {}", std::io::Error::last_os_error()).into());
        }
        Ok(())
    }

    /// Sets SOL_PACKET option `name` of socket `fd` to `value`.
    fn packet_option<T>(
        fd: libc::c_int,
        name: libc::c_int,
        value: &T,
        what: &str,
    ) -> Result<(), Failed> {
        // SAFETY: `value` is a valid `T` of the size given for the call's duration.
        let r = unsafe {
            libc::setsockopt(
                fd,
                libc::SOL_PACKET,
                name,
                (value as *const T).cast(),
                size_of::<T>() as u32,
            )
        };
        check(r, what)
    }

    impl Ring {
        pub fn open(iface: &str) -> Result<Ring, Failed> {
            let index = nix::net::if_::if_nametoindex(iface)?;
            let proto = (libc::ETH_P_ALL as u16).to_be();
            // SAFETY: plain socket call; the descriptor is owned at once.
            let raw = unsafe { libc::socket(libc::AF_PACKET, libc::SOCK_RAW, i32::from(proto)) };
            check(raw, "socket(AF_PACKET)")?;
            // SAFETY: `raw` is a new descriptor nobody else owns.
            let fd = unsafe { OwnedFd::from_raw_fd(raw) };
            let version = libc::tpacket_versions::TPACKET_V2 as libc::c_int;
            let req = libc::tpacket_req {
                tp_block_size: BLOCK as u32,
                tp_block_nr: BLOCKS as u32,
                tp_frame_size: FRAME as u32,
                tp_frame_nr: (BLOCK / FRAME * BLOCKS) as u32,
            };
            packet_option(raw, libc::PACKET_VERSION, &version, "PACKET_VERSION")?;
            packet_option(raw, libc::PACKET_RX_RING, &req, "PACKET_RX_RING")?;
            // SAFETY: maps the ring the kernel just made for this socket.
            let map = unsafe {
                libc::mmap(
                    std::ptr::null_mut(),
                    BLOCK * BLOCKS,
                    libc::PROT_READ | libc::PROT_WRITE,
                    libc::MAP_SHARED,
                    raw,
                    0,
                )
            };
            if map == libc::MAP_FAILED {
                return Err(format!("mmap: {}", std::io::Error::last_os_error()).into());
            }
            // SAFETY: a zeroed sockaddr_ll is valid; the fields set are its own.
            let mut addr: libc::sockaddr_ll = unsafe { std::mem::zeroed() };
            addr.sll_family = libc::AF_PACKET as u16;
            addr.sll_protocol = proto;
            addr.sll_ifindex = index as i32;
            // SAFETY: `addr` is a valid sockaddr_ll of the size given.
            check(
                unsafe { libc::bind(raw, (&raw const addr).cast(), size_of_val(&addr) as u32) },
                "bind",
            )?;
            Ok(Ring {
                fd,
                map: map.cast(),
            })
        }

        /// Reads `n` frames of `id` (others are passed over); each one's latency from its
        /// ring timestamp to the read, in ns.
        pub fn read(self, n: u64, id: u32) -> Result<Vec<u64>, Failed> {
            let epoll = Epoll::new(EpollCreateFlags::EPOLL_CLOEXEC)?;
            epoll.add(self.fd.as_fd(), EpollEvent::new(EpollFlags::EPOLLIN, 0))?;
            let frames = BLOCK / FRAME * BLOCKS;
            let mut at = 0usize;
            let mut v = Vec::with_capacity(n as usize);
            let mut ready = [EpollEvent::empty(); 1];
            while (v.len() as u64) < n {
                // SAFETY: frame `at` lies within the mapping; its status word is shared
                // with the kernel, so it is read atomically.
                let hdr = unsafe { self.map.add(at * FRAME) };
                let status = unsafe { &*hdr.cast::<AtomicU32>() };
                if status.load(Ordering::Acquire) & libc::TP_STATUS_USER == 0 {
                    if epoll.wait(&mut ready, EpollTimeout::from(3000u16))? == 0 {
                        break;
                    }
                    continue;
                }
                // SAFETY: the kernel handed the frame to user space (TP_STATUS_USER); its
                // header and data stay put until the status is given back.
                let (stamp, can_id) = unsafe {
                    let h = &*hdr.cast::<libc::tpacket2_hdr>();
                    let data = hdr.add(usize::from(h.tp_mac));
                    (
                        u128::from(h.tp_sec) * 1_000_000_000 + u128::from(h.tp_nsec),
                        data.cast::<u32>().read_unaligned(),
                    )
                };
                let now = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_nanos());
                status.store(libc::TP_STATUS_KERNEL, Ordering::Release);
                at = (at + 1) % frames;
                if can_id & libc::CAN_SFF_MASK == id {
                    v.push(now.saturating_sub(stamp) as u64);
                }
            }
            Ok(v)
        }
    }

    impl Drop for Ring {
        fn drop(&mut self) {
            // SAFETY: unmaps the mapping made in open, used no more.
            unsafe { libc::munmap(self.map.cast(), BLOCK * BLOCKS) };
        }
    }
}
