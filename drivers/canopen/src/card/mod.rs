//! The card: its nodes' PDO images as devices. The bus side stores each received TPDO's
//! payload and the nodes' states; reads decode the channel's object from its PDO and fail
//! while its node is not operational; writes store the output and mark its RPDO to be
//! sent. No I/O of its own.

use crate::map::{CanopenMap, Channel};
use crate::node::NodeStatus;
use arc_swap::ArcSwap;
use can_socket::signal::{Signal, ValueKind};
use device_interface::DeviceError;
use device_interface::bits::BitImage;
use device_interface::time::{Clock, Timestamp};
use serde::Serialize;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};

/// One received PDO: its payload (little endian in a u64) and when it came (ns + 1; 0:
/// never since its node was last started).
#[derive(Default)]
struct RxPdo {
    payload: AtomicU64,
    at: AtomicU64,
}

/// What one drive is asked to be.
#[derive(Debug, Default)]
pub struct Wanted {
    pub(crate) enable: AtomicBool,
    /// A fault reset was asked (by `disable` while faulted).
    pub(crate) reset: AtomicBool,
    /// Target velocity, counts.
    pub(crate) velocity: AtomicI64,
    /// A quick stop was asked (until the next enable or disable).
    pub(crate) quick_stop: AtomicBool,
}

impl Wanted {
    /// Disabled at zero velocity (a drive started again).
    pub(crate) fn reset(&self) {
        self.enable.store(false, Ordering::Release);
        self.reset.store(false, Ordering::Release);
        self.velocity.store(0, Ordering::Release);
        self.quick_stop.store(false, Ordering::Release);
    }
}

/// The card's counters.
#[derive(Debug, Default)]
pub struct Counters {
    /// Frames received.
    pub rx_frames: AtomicU64,
    /// TPDOs decoded.
    pub tpdos: AtomicU64,
    /// PDOs shorter than their mapping (not decoded).
    pub short_pdos: AtomicU64,
    /// RPDOs sent.
    pub rpdos: AtomicU64,
    /// SYNCs sent.
    pub syncs: AtomicU64,
    /// Frames the kernel refused to send.
    pub send_errors: AtomicU64,
    /// Frames dropped by the socket's full buffer.
    pub dropped: AtomicU64,
    /// Error frames.
    pub error_frames: AtomicU64,
    /// Remote frames and frames of no known kind.
    pub wrong_kind: AtomicU64,
}

/// The card's status snapshot.
#[derive(Debug, Serialize)]
pub struct CardSnapshot {
    /// Whether the link is up.
    pub link_up: bool,
    /// The nodes.
    pub nodes: Vec<NodeStatus>,
    /// Frames received.
    pub rx_frames: u64,
    /// TPDOs decoded.
    pub tpdos: u64,
    /// PDOs shorter than their mapping.
    pub short_pdos: u64,
    /// RPDOs sent.
    pub rpdos: u64,
    /// SYNCs sent.
    pub syncs: u64,
    /// Frames the kernel refused to send.
    pub send_errors: u64,
    /// Frames dropped by the socket.
    pub dropped: u64,
    /// Error frames.
    pub error_frames: u64,
    /// Frames of no known kind.
    pub wrong_kind: u64,
}

/// A CANopen card.
pub struct CanopenCard {
    map: CanopenMap,
    clock: Arc<dyn Clock>,
    link_up: AtomicBool,
    operational: Vec<AtomicBool>,
    status: Vec<ArcSwap<NodeStatus>>,
    rx: Vec<RxPdo>,
    /// Each TPDO's digital input bits: (channel, …).
    rx_digital: Vec<Vec<u32>>,
    dirty: Vec<AtomicBool>,
    di: BitImage,
    dout: BitImage,
    ao: Vec<AtomicI64>,
    /// The drives' controlwords and target velocities, as `map.drive_out`.
    drive_out: Vec<AtomicI64>,
    /// What each drive is asked to be.
    pub(crate) drives: Vec<Wanted>,
    waker: OnceLock<Box<dyn Fn() + Send + Sync>>,
    /// Its counters.
    pub counters: Counters,
}

impl CanopenCard {
    /// A card over `map`, every node waiting.
    pub fn new(map: CanopenMap, clock: Arc<dyn Clock>, statuses: Vec<NodeStatus>) -> Arc<Self> {
        let mut rx_digital = vec![Vec::new(); map.tpdos.len()];
        for (k, c) in map.digital_in.iter().enumerate() {
            rx_digital[c.pdo].push(k as u32);
        }
        let dout = BitImage::new(map.digital_out.len() as u32);
        let ao = map
            .analog_out
            .iter()
            .map(|c| AtomicI64::new(initial_bits(&c.signal)))
            .collect();
        Arc::new(CanopenCard {
            clock,
            link_up: AtomicBool::new(false),
            operational: map.nodes.iter().map(|_| AtomicBool::new(false)).collect(),
            status: statuses.into_iter().map(ArcSwap::from_pointee).collect(),
            rx: map.tpdos.iter().map(|_| RxPdo::default()).collect(),
            rx_digital,
            dirty: map.rpdos.iter().map(|_| AtomicBool::new(false)).collect(),
            di: BitImage::new(map.digital_in.len() as u32),
            dout,
            ao,
            drive_out: map.drive_out.iter().map(|_| AtomicI64::new(0)).collect(),
            drives: map.drives.iter().map(|_| Default::default()).collect(),
            waker: OnceLock::new(),
            counters: Counters::default(),
            map,
        })
    }

    /// The resolved section.
    pub fn map(&self) -> &CanopenMap {
        &self.map
    }

    /// Sets the call that wakes the bus side when an output changed (once).
    pub fn set_waker(&self, wake: Box<dyn Fn() + Send + Sync>) {
        let _ = self.waker.set(wake);
    }

    fn wake(&self) {
        if let Some(w) = self.waker.get() {
            w();
        }
    }

    /// The link state, from the bus side.
    pub fn set_link(&self, up: bool) {
        self.link_up.store(up, Ordering::Release);
    }

    /// Whether the link is up.
    pub fn link_up(&self) -> bool {
        self.link_up.load(Ordering::Acquire)
    }

    /// Node `n`'s status, from the bus side; its PDOs are live while it is operational.
    pub fn set_node(&self, n: usize, status: &NodeStatus, operational: bool) {
        let was = self.operational[n].swap(operational, Ordering::AcqRel);
        if operational && !was {
            // Freshly started: old inputs are not its values now. Its outputs were
            // seeded from the node: nothing goes out until somebody writes (a synchronous
            // RPDO goes out at each SYNC, carrying what the node has).
            for (p, pdo) in self.map.tpdos.iter().enumerate() {
                if pdo.node == n {
                    self.rx[p].at.store(0, Ordering::Release);
                }
            }
            for (p, pdo) in self.map.rpdos.iter().enumerate() {
                if pdo.node == n {
                    self.dirty[p].store(false, Ordering::Release);
                }
            }
            // A drive (re)started is disabled until somebody enables it.
            for (d, drive) in self.map.drives.iter().enumerate() {
                if drive.node == n {
                    self.drives[d].reset();
                }
            }
        }
        self.status[n].store(Arc::new(status.clone()));
    }

    /// Node `n`'s object `index`:`sub` holds `data` (read at its configuration): the
    /// outputs mapped from it start there.
    pub fn seed(&self, n: usize, index: u16, sub: u8, data: &[u8]) {
        let mut b = [0u8; 8];
        let len = data.len().min(8);
        b[..len].copy_from_slice(&data[..len]);
        let raw = u64::from_le_bytes(b);
        let of_node = |c: &Channel| c.object == (index, sub) && self.map.rpdos[c.pdo].node == n;
        for (k, c) in self.map.analog_out.iter().enumerate() {
            if of_node(c) {
                self.ao[k].store(object_bits(c, raw), Ordering::Release);
            }
        }
        for (k, c) in self.map.digital_out.iter().enumerate() {
            if of_node(c) {
                let _ = self.dout.set(k as u32, (raw >> c.bit) & 1 != 0);
            }
        }
        // A drive's controlword and target velocity too: its RPDO carries what the
        // drive has until the drive is stepped.
        for (k, c) in self.map.drive_out.iter().enumerate() {
            if of_node(c) {
                self.drive_out[k].store(object_bits(c, raw), Ordering::Release);
            }
        }
    }

    /// Whether node `n` is operational.
    pub fn node_operational(&self, n: usize) -> bool {
        self.operational[n].load(Ordering::Acquire)
    }

    /// TPDO `p` received with `data` at `at`: stored, or counted as short.
    pub fn receive(&self, p: usize, data: &[u8], at: Timestamp) {
        let pdo = &self.map.tpdos[p];
        if data.len() < pdo.len {
            self.counters.short_pdos.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let mut b = [0u8; 8];
        let n = data.len().min(8);
        b[..n].copy_from_slice(&data[..n]);
        let payload = u64::from_le_bytes(b);
        self.rx[p].payload.store(payload, Ordering::Release);
        for &k in &self.rx_digital[p] {
            let c = &self.map.digital_in[k as usize];
            if let Ok(raw) = c.signal.extract(&b) {
                let _ = self.di.set(k, (raw >> c.bit) & 1 != 0);
            }
        }
        self.rx[p].at.store(at.as_nanos() + 1, Ordering::Release);
        self.counters.tpdos.fetch_add(1, Ordering::Relaxed);
    }

    /// RPDO `p`'s payload now, clearing its dirty mark.
    pub fn compose(&self, p: usize, out: &mut [u8; 8]) -> usize {
        self.dirty[p].store(false, Ordering::Release);
        *out = [0; 8];
        for (k, c) in self.map.drive_out.iter().enumerate() {
            if c.pdo == p {
                let _ = c
                    .signal
                    .insert(out, self.drive_out[k].load(Ordering::Acquire));
            }
        }
        for (k, c) in self.map.analog_out.iter().enumerate() {
            if c.pdo == p {
                let _ = c.signal.insert(out, self.ao[k].load(Ordering::Acquire));
            }
        }
        // A digital object's bits are channels of their own, in order: each object is
        // inserted whole once its bits are gathered.
        let mut object: Option<(&Channel, i64)> = None;
        for (k, c) in self.map.digital_out.iter().enumerate() {
            if c.pdo != p {
                continue;
            }
            let on = self.dout.get(k as u32).unwrap_or(false);
            let bit = i64::from(on) << c.bit;
            match &mut object {
                Some((first, raw)) if first.object == c.object => *raw |= bit,
                _ => {
                    if let Some((first, raw)) = object.replace((c, bit)) {
                        let _ = first.signal.insert(out, raw);
                    }
                }
            }
        }
        if let Some((first, raw)) = object {
            let _ = first.signal.insert(out, raw);
        }
        self.map.rpdos[p].len
    }

    /// Drive output `k` (`map.drive_out`): its value now.
    pub(crate) fn drive_out(&self, k: usize) -> i64 {
        self.drive_out[k].load(Ordering::Acquire)
    }

    /// Sets drive output `k` and marks its RPDO, when it changes.
    pub(crate) fn set_drive_out(&self, k: usize, value: i64) {
        if self.drive_out[k].swap(value, Ordering::AcqRel) != value {
            self.dirty[self.map.drive_out[k].pdo].store(true, Ordering::Release);
        }
    }

    /// Analog input `channel`'s bits and signal, its node operational and its PDO
    /// received.
    pub(crate) fn input_bits(&self, channel: u32) -> Result<(i64, &Signal), DeviceError> {
        let c = Self::channel(&self.map.analog_in, channel)?;
        let bits = c
            .signal
            .extract(&self.input(c)?)
            .map_err(DeviceError::bus)?;
        Ok((bits, &c.signal))
    }

    /// Wakes the bus side (a drive was asked something).
    pub(crate) fn wake_bus(&self) {
        self.wake();
    }

    /// Whether RPDO `p` has changed since it was last composed.
    pub fn is_dirty(&self, p: usize) -> bool {
        self.dirty[p].load(Ordering::Acquire)
    }

    /// Marks every RPDO to be sent again (the safe values at stop).
    pub fn flush(&self) {
        for d in &self.dirty {
            d.store(true, Ordering::Release);
        }
        self.wake();
    }

    /// Whether any RPDO of an operational node waits to be sent.
    pub fn sends_pending(&self) -> bool {
        self.map
            .rpdos
            .iter()
            .enumerate()
            .any(|(p, pdo)| self.is_dirty(p) && self.node_operational(pdo.node))
    }

    /// The nodes with outputs or a drive that are not operational (their ids).
    pub fn outputs_unreachable(&self) -> Vec<u8> {
        self.map
            .nodes
            .iter()
            .enumerate()
            .filter(|(n, _)| {
                !self.node_operational(*n) && self.map.rpdos.iter().any(|p| p.node == *n)
            })
            .map(|(_, node)| node.id)
            .collect()
    }

    /// The status snapshot.
    pub fn snapshot(&self) -> CardSnapshot {
        let c = &self.counters;
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        CardSnapshot {
            link_up: self.link_up(),
            nodes: self.status.iter().map(|s| (**s.load()).clone()).collect(),
            rx_frames: l(&c.rx_frames),
            tpdos: l(&c.tpdos),
            short_pdos: l(&c.short_pdos),
            rpdos: l(&c.rpdos),
            syncs: l(&c.syncs),
            send_errors: l(&c.send_errors),
            dropped: l(&c.dropped),
            error_frames: l(&c.error_frames),
            wrong_kind: l(&c.wrong_kind),
        }
    }

    /// The input channel's PDO payload, its node operational and the PDO received.
    fn input(&self, c: &Channel) -> Result<[u8; 8], DeviceError> {
        if !self.link_up() || !self.node_operational(self.map.tpdos[c.pdo].node) {
            return Err(DeviceError::Offline);
        }
        let rx = &self.rx[c.pdo];
        if rx.at.load(Ordering::Acquire) == 0 {
            return Err(DeviceError::Stale { age: None });
        }
        Ok(rx.payload.load(Ordering::Acquire).to_le_bytes())
    }

    fn check_output(&self, pdo: usize) -> Result<(), DeviceError> {
        if self.link_up() && self.node_operational(self.map.rpdos[pdo].node) {
            Ok(())
        } else {
            Err(DeviceError::Offline)
        }
    }

    fn channel(list: &[Channel], channel: u32) -> Result<&Channel, DeviceError> {
        list.get(channel as usize)
            .ok_or(DeviceError::ChannelOutOfRange {
                channel,
                count: list.len() as u32,
            })
    }
}

/// An object's value read by SDO (`raw`, little endian) as its channel's bits: a signed
/// integer sign-extended, anything else as it is.
fn object_bits(c: &Channel, raw: u64) -> i64 {
    let (_, bits, _, signed) = c.signal.layout();
    if signed && bits < 64 && c.signal.kind() == ValueKind::Integer {
        let shift = 64 - bits;
        ((raw << shift) as i64) >> shift
    } else {
        raw as i64
    }
}

/// A float output's bits for 0.0; 0 for an integer.
fn initial_bits(s: &Signal) -> i64 {
    match s.kind() {
        ValueKind::Integer => 0,
        _ => s.raw_of(0.0).unwrap_or(0),
    }
}

mod devices;
