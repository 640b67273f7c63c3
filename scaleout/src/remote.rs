//! Devices of another gateway, used here exactly as local ones.
//!
//! An imported device is registered as `<gateway>/<device>` under each interface the
//! deployment declares, as an `Arc<dyn AnalogIn>` (…) backed by an [`Image`]: the latest
//! sample received, the outputs this gateway wrote, and the times that make it stale or
//! offline.
//!
//! # The real-time contract
//!
//! Every trait method is a handful of atomic loads and stores: reads answer from the
//! latest sample (never waiting for the wire), writes store the value and wake the
//! node's sender with a `try_send` on a bounded channel (at most one futex call to wake
//! it; never a wait). Nothing allocates or blocks. Each channel is one atomic, so a reader
//! may see channels of two consecutive samples.
//!
//! A write is stored and its number taken (a [`DeliveryTracker`]); the node's sender
//! ([`crate::outbox`]) carries the newest value of every output written since the last
//! acknowledgement, under a sequence number, and sends that same message again until the
//! remote gateway acknowledges it or `request_timeout_ms` passes — then the write failed,
//! and its writer hears so through [`AnalogOut::delivery`] (the control socket's `set`
//! waits for it). The remote gateway applies a sequence number once: a repeat is
//! acknowledged, not written again, so its output watchdog sees what its writer here does
//! — a component that stops writing, stops, fails, or loses the link lets it expire,
//! exactly as a local writer would.
//!
//! Health: offline until the first sample of a device whose shape matched the remote
//! gateway's catalogue; stale when the last sample is older than `stale_ms`, offline when
//! older than `offline_ms` (its age is the remote age at publication plus the time since it
//! arrived: no clock is shared between hosts). As for a local card, inputs of a stale
//! device fail with [`DeviceError::Stale`], of an offline one with
//! [`DeviceError::Offline`]; writes to an offline device fail and change nothing.

use crate::config::Times;
use crate::wire::{DeviceShape, Sample};
use device_interface::time::{Clock, MonotonicClock, Timestamp};
use device_interface::{
    AnalogIn, AnalogOut, DeliveryTracker, Device, DeviceError, DigitalIn, DigitalOut, Encoder,
    Health, Interface, Scale, Status,
};
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU8, AtomicU64, Ordering};
use std::sync::{Mutex, OnceLock};

/// Counters of one imported interface, for `hwgw status`.
#[derive(Debug, Default)]
pub struct ImageCounters {
    /// Samples taken.
    pub received: AtomicU64,
    /// Samples missing from the sequence (published there, never arrived here).
    pub lost: AtomicU64,
    /// Samples refused (wrong shape, or arriving before the shape was known).
    pub refused: AtomicU64,
    /// Writes sent to the remote gateway.
    pub writes_sent: AtomicU64,
    /// Writes it answered with every value written.
    pub writes_acked: AtomicU64,
    /// Writes it answered refusing some value (see the image's problem).
    pub writes_refused: AtomicU64,
    /// Writes that got no answer in time, or could not be sent (one a channel).
    pub writes_failed: AtomicU64,
    /// Messages sent again because no answer had come yet.
    pub writes_retried: AtomicU64,
}

/// Why a write is refused once the gateway stops.
const STOPPING: &str = "the gateway is stopping";

/// Why an image is not usable beyond silence.
const OK: u8 = 0;
/// The remote device's shape is not the declared one.
const MISMATCH: u8 = 1;

/// One interface of an imported device.
pub struct Image {
    interface: Interface,
    gateway: String,
    device: String,
    count: u32,
    times: Times,
    values: Box<[AtomicI64]>,
    valid: Box<[AtomicBool]>,
    out: Box<[AtomicI64]>,
    /// The number of each output's writes, and their fate.
    delivery: DeliveryTracker,
    /// Set when the gateway stops: writes are refused from then on.
    held: AtomicBool,
    /// Set when the remote gateway restarted (its sequence went back): its catalogue is
    /// asked for again.
    refetch: AtomicBool,
    /// Our monotonic time when the last sample arrived, ns; 0: none yet.
    rx_ns: AtomicU64,
    /// The remote gateway's monotonic time when it read the last sample, ns.
    read_ns: AtomicU64,
    /// The remote age at publication of the last sample, ns; `u64::MAX`: none.
    age_ns: AtomicU64,
    status: AtomicU8,
    seq: AtomicU64,
    problem: AtomicU8,
    /// The remote shape, once it matched.
    shape: OnceLock<DeviceShape>,
    /// The text of the last problem (shape, refused write), for status; never touched on
    /// the real-time path.
    problem_text: Mutex<Option<String>>,
    wake: OnceLock<crossbeam_channel::Sender<()>>,
    /// Counters.
    pub counters: ImageCounters,
}

fn status_code(s: Status) -> u8 {
    match s {
        Status::Online => 0,
        Status::Stale => 1,
        Status::Offline => 2,
    }
}

fn code_status(c: u8) -> Status {
    match c {
        0 => Status::Online,
        1 => Status::Stale,
        _ => Status::Offline,
    }
}

fn atomics<T>(n: u32, f: impl Fn() -> T) -> Box<[T]> {
    (0..n).map(|_| f()).collect()
}

impl Image {
    /// The image of interface `interface` of device `device` of gateway `gateway`, with
    /// `count` channels (2 for an encoder: position and turn).
    pub fn new(
        interface: Interface,
        gateway: &str,
        device: &str,
        count: u32,
        times: Times,
    ) -> Self {
        Image {
            interface,
            gateway: gateway.to_string(),
            device: device.to_string(),
            count,
            times,
            values: atomics(count, || AtomicI64::new(0)),
            valid: atomics(count, || AtomicBool::new(false)),
            out: atomics(count, || AtomicI64::new(0)),
            delivery: DeliveryTracker::new(count),
            held: AtomicBool::new(false),
            refetch: AtomicBool::new(false),
            rx_ns: AtomicU64::new(0),
            read_ns: AtomicU64::new(0),
            age_ns: AtomicU64::new(u64::MAX),
            status: AtomicU8::new(status_code(Status::Offline)),
            seq: AtomicU64::new(0),
            problem: AtomicU8::new(OK),
            shape: OnceLock::new(),
            problem_text: Mutex::new(None),
            wake: OnceLock::new(),
            counters: ImageCounters::default(),
        }
    }

    /// Its interface.
    pub fn interface(&self) -> Interface {
        self.interface
    }

    /// The remote gateway.
    pub fn gateway(&self) -> &str {
        &self.gateway
    }

    /// The device's name there.
    pub fn device(&self) -> &str {
        &self.device
    }

    /// Channels declared.
    pub fn count(&self) -> u32 {
        self.count
    }

    /// The last problem's text (shape mismatch, refused write), if any.
    pub fn problem(&self) -> Option<String> {
        self.problem_text
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Our monotonic time of the last sample, ns (0: none yet).
    pub fn received_at_ns(&self) -> u64 {
        self.rx_ns.load(Ordering::Acquire)
    }

    /// The last sample's times: `(read there, arrived here)`, both monotonic ns (on one
    /// host, their difference is the sample's way from the remote device to here); `None`
    /// before the first or while one is being taken.
    pub fn sample_times(&self) -> Option<(u64, u64)> {
        let rx = self.rx_ns.load(Ordering::Acquire);
        let read = self.read_ns.load(Ordering::Relaxed);
        (rx != 0 && self.rx_ns.load(Ordering::Acquire) == rx).then_some((read, rx))
    }

    pub(crate) fn set_wake(&self, tx: crossbeam_channel::Sender<()>) {
        let _ = self.wake.set(tx);
    }

    fn set_problem(&self, code: u8, text: String) {
        tracing::warn!("zenoh: {}/{}: {text}", self.gateway, self.device);
        *self.problem_text.lock().unwrap_or_else(|p| p.into_inner()) = Some(text);
        self.problem.store(code, Ordering::Release);
    }

    /// Takes the remote gateway's shape of this device, if it is the declared one;
    /// otherwise the device stays offline and says why.
    pub fn adopt(&self, shape: &DeviceShape) {
        let analog = matches!(self.interface, Interface::AnalogIn | Interface::AnalogOut);
        let why = if shape.channels != self.count {
            Some(format!(
                "{} has {} channels there, this deployment declares {}",
                self.interface, shape.channels, self.count
            ))
        } else if analog && shape.scales.len() != self.count as usize {
            Some(format!(
                "the catalogue gives {} scales for {} channels",
                shape.scales.len(),
                self.count
            ))
        } else if self.interface == Interface::Encoder && shape.encoder.is_none() {
            Some("the catalogue gives no encoder resolution".to_string())
        } else {
            None
        };
        match (why, self.shape.get()) {
            (Some(why), _) => self.set_problem(MISMATCH, why),
            (None, Some(old)) if old != shape => self.set_problem(
                MISMATCH,
                format!(
                    "its {} changed shape at {}: restart this gateway to take the new one",
                    self.interface, self.gateway
                ),
            ),
            (None, _) => {
                let _ = self.shape.set(shape.clone());
            }
        }
    }

    /// Takes sample `s`, received at our monotonic time `now_ns`.
    pub fn take(&self, s: &Sample, now_ns: u64) {
        if self.shape.get().is_none() || self.problem.load(Ordering::Acquire) != OK {
            self.counters.refused.fetch_add(1, Ordering::Relaxed);
            return;
        }
        if s.values.len() != self.count as usize {
            // Refused and counted; the device stays usable for the next good sample.
            if self.counters.refused.fetch_add(1, Ordering::Relaxed) == 0 {
                tracing::warn!(
                    "zenoh: {}/{}: a sample of {} values for {} channels refused",
                    self.gateway,
                    self.device,
                    s.values.len(),
                    self.count
                );
            }
            return;
        }
        let last = self.seq.swap(s.seq, Ordering::AcqRel);
        if last != 0 && s.seq <= last {
            // The remote gateway started again: its shape may have changed.
            self.refetch.store(true, Ordering::Release);
        } else if last != 0 {
            let gap = s.seq.saturating_sub(last).saturating_sub(1);
            self.counters.lost.fetch_add(gap, Ordering::Relaxed);
        }
        for ((v, slot), ok) in s.values.iter().zip(&self.values).zip(&self.valid) {
            if let Some(v) = v {
                slot.store(*v, Ordering::Relaxed);
            }
            ok.store(v.is_some(), Ordering::Relaxed);
        }
        self.age_ns
            .store(s.age_ns.unwrap_or(u64::MAX), Ordering::Relaxed);
        self.status.store(status_code(s.status), Ordering::Relaxed);
        self.read_ns.store(s.read_ns, Ordering::Relaxed);
        self.rx_ns.store(now_ns.max(1), Ordering::Release);
        self.counters.received.fetch_add(1, Ordering::Relaxed);
    }

    /// Status and age (when known) now.
    fn state(&self, now: u64) -> (Status, Option<u64>) {
        let rx = self.rx_ns.load(Ordering::Acquire);
        if rx == 0 || self.problem.load(Ordering::Acquire) != OK {
            return (Status::Offline, None);
        }
        let since = now.saturating_sub(rx);
        let age = match self.age_ns.load(Ordering::Relaxed) {
            u64::MAX => since,
            a => a.saturating_add(since),
        };
        let status = if since >= self.times.offline.as_nanos() as u64 {
            Status::Offline
        } else if since >= self.times.stale.as_nanos() as u64 {
            Status::Stale
        } else {
            code_status(self.status.load(Ordering::Relaxed))
        };
        (status, Some(age))
    }

    fn health(&self) -> Health {
        let now = MonotonicClock.now();
        let (status, age) = self.state(now.as_nanos());
        let last_good = age.map(|a| Timestamp::from_nanos(now.as_nanos().saturating_sub(a)));
        Health {
            status,
            last_good,
            checked_at: now,
            last_error: match status {
                Status::Online => None,
                Status::Stale => Some(DeviceError::Stale {
                    age: age.map(std::time::Duration::from_nanos),
                }),
                Status::Offline => Some(DeviceError::Offline),
            },
        }
    }

    fn check(&self, ch: u32) -> Result<(), DeviceError> {
        if ch >= self.count {
            return Err(match self.interface {
                Interface::DigitalIn | Interface::DigitalOut => DeviceError::BitOutOfRange {
                    bit: ch,
                    count: self.count,
                },
                _ => DeviceError::ChannelOutOfRange {
                    channel: ch,
                    count: self.count,
                },
            });
        }
        Ok(())
    }

    fn readable(&self) -> Result<(), DeviceError> {
        match self.state(MonotonicClock.now().as_nanos()) {
            (Status::Online, _) => Ok(()),
            (Status::Stale, age) => Err(DeviceError::Stale {
                age: age.map(std::time::Duration::from_nanos),
            }),
            (Status::Offline, _) => Err(DeviceError::Offline),
        }
    }

    /// The latest remote value of channel `ch`.
    fn read(&self, ch: u32) -> Result<i64, DeviceError> {
        self.check(ch)?;
        self.readable()?;
        if !self.valid[ch as usize].load(Ordering::Relaxed) {
            return Err(DeviceError::Offline);
        }
        Ok(self.values[ch as usize].load(Ordering::Relaxed))
    }

    /// The remote gateway's read-back of output `ch`, from its latest sample: what the
    /// device has, not what was asked of it here.
    fn read_back(&self, ch: u32) -> Result<i64, DeviceError> {
        self.read(ch)
    }

    /// Writes `raw` to channel `ch`: stored, numbered, and sent by the node.
    fn write(&self, ch: u32, raw: i64) -> Result<(), DeviceError> {
        self.check(ch)?;
        if self.held.load(Ordering::Acquire) {
            return Err(DeviceError::Held { reason: STOPPING });
        }
        if self.state(MonotonicClock.now().as_nanos()).0 == Status::Offline {
            return Err(DeviceError::Offline);
        }
        self.out[ch as usize].store(raw, Ordering::Release);
        let n = self.delivery.take(ch);
        if self.held.load(Ordering::Acquire) {
            // The gateway began stopping meanwhile: this write is never sent.
            self.delivery
                .failed(ch, n, DeviceError::Held { reason: STOPPING });
            return Err(DeviceError::Held { reason: STOPPING });
        }
        if let Some(w) = self.wake.get() {
            let _ = w.try_send(());
        }
        Ok(())
    }

    /// The outputs with writes not yet settled (delivered or failed): `(channel, number of
    /// the newest write)`.
    pub fn pending(&self) -> Vec<(u32, u64)> {
        (0..self.count)
            .filter_map(|c| {
                let d = self.delivery.get(c);
                (d.taken > d.settled).then_some((c, d.taken))
            })
            .collect()
    }

    /// The raw value last written to output `ch` here (what a write message carries).
    pub fn written(&self, ch: u32) -> i64 {
        self.out
            .get(ch as usize)
            .map_or(0, |v| v.load(Ordering::Acquire))
    }

    /// Where the writes to output `ch` stand.
    pub fn delivery(&self, ch: u32) -> device_interface::Delivery {
        self.delivery.get(ch)
    }

    /// True once the gateway is stopping: no write is taken or sent.
    pub fn is_held(&self) -> bool {
        self.held.load(Ordering::Acquire)
    }

    /// Refuses every write from now on (the gateway is stopping); the writes still on
    /// their way are failed.
    pub fn hold(&self) {
        self.held.store(true, Ordering::Release);
        let n = self.delivery.fail_pending(&DeviceError::Undelivered {
            reason: "this gateway stopped before the remote gateway acknowledged it",
        });
        self.counters
            .writes_failed
            .fetch_add(n as u64, Ordering::Relaxed);
    }

    /// True once after the remote gateway restarted: its catalogue should be asked again.
    pub fn take_refetch(&self) -> bool {
        self.refetch.swap(false, Ordering::AcqRel)
    }

    /// Records the remote gateway's answer to a write that carried writes `numbers`
    /// (`(channel, number)`): each delivered, or failed where it was refused.
    pub fn answered(&self, numbers: &[(u32, u64)], refused: &[(u32, String)]) {
        for &(c, n) in numbers {
            if refused.iter().any(|(r, _)| *r == c) {
                self.delivery.failed(
                    c,
                    n,
                    DeviceError::Undelivered {
                        reason: "refused by the remote gateway (its status says why)",
                    },
                );
            } else {
                self.delivery.delivered(c, n);
            }
        }
        if refused.is_empty() {
            self.counters.writes_acked.fetch_add(1, Ordering::Relaxed);
            // A write problem is over once a write goes through.
            let mut p = self.problem_text.lock().unwrap_or_else(|p| p.into_inner());
            if p.as_deref().is_some_and(|t| t.starts_with("write ")) {
                *p = None;
            }
            return;
        }
        self.counters.writes_refused.fetch_add(1, Ordering::Relaxed);
        let text = refused
            .iter()
            .take(4)
            .map(|(c, e)| format!("channel {c}: {e}"))
            .collect::<Vec<_>>()
            .join("; ");
        *self.problem_text.lock().unwrap_or_else(|p| p.into_inner()) =
            Some(format!("write refused by {}: {text}", self.gateway));
    }

    /// Records that write `n` of output `ch` got no acknowledgement in time (or could not
    /// be sent): it failed, for `why`.
    pub fn undelivered(&self, ch: u32, n: u64, why: &str) {
        self.delivery.failed(
            ch,
            n,
            DeviceError::Undelivered {
                reason: "no acknowledgement from the remote gateway within request_timeout_ms",
            },
        );
        self.counters.writes_failed.fetch_add(1, Ordering::Relaxed);
        *self.problem_text.lock().unwrap_or_else(|p| p.into_inner()) =
            Some(format!("write to {} failed: {why}", self.gateway));
    }

    fn scale(&self, ch: u32) -> Result<Scale, DeviceError> {
        self.check(ch)?;
        self.shape
            .get()
            .and_then(|s| s.scales.get(ch as usize).copied())
            .ok_or(DeviceError::Offline)
    }
}

/// One imported interface as a device of that interface.
pub struct Proxy(pub std::sync::Arc<Image>);

impl Device for Proxy {
    fn health(&self) -> Health {
        self.0.health()
    }
}

impl AnalogIn for Proxy {
    fn channel_count(&self) -> u32 {
        self.0.count
    }
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.0.scale(channel)
    }
    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.0.read(channel)
    }
}

impl AnalogOut for Proxy {
    fn channel_count(&self) -> u32 {
        self.0.count
    }
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.0.scale(channel)
    }
    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        self.0.scale(channel)?.check_raw(channel, raw)?;
        self.0.write(channel, raw)
    }
    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.0.read_back(channel)
    }
    fn delivery(&self, channel: u32) -> Option<device_interface::Delivery> {
        Some(self.0.delivery(channel))
    }
}

impl DigitalIn for Proxy {
    fn input_count(&self) -> u32 {
        self.0.count
    }
    fn read_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.0.read(bit).map(|v| v != 0)
    }
}

impl DigitalOut for Proxy {
    fn output_count(&self) -> u32 {
        self.0.count
    }
    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        self.0.write(bit, i64::from(value))
    }
    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.0.read_back(bit).map(|v| v != 0)
    }
    fn delivery(&self, bit: u32) -> Option<device_interface::Delivery> {
        Some(self.0.delivery(bit))
    }
}

impl Encoder for Proxy {
    fn position(&self) -> Result<i64, DeviceError> {
        self.0.read(0)
    }
    fn turn(&self) -> Result<i64, DeviceError> {
        self.0.read(1)
    }
    fn set_position(&self, position: i64) -> Result<(), DeviceError> {
        self.0.write(0, position)
    }
    fn set_turn(&self, turn: i64) -> Result<(), DeviceError> {
        self.0.write(1, turn)
    }
    fn resolution(&self) -> i64 {
        self.0
            .shape
            .get()
            .and_then(|s| s.encoder)
            .map_or(1, |e| e.resolution)
    }
    fn upcounting(&self) -> bool {
        self.0
            .shape
            .get()
            .and_then(|s| s.encoder)
            .is_none_or(|e| e.upcounting)
    }
}
