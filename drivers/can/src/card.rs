//! A CAN card's devices: the mapped signals as AnalogIn/Out, DigitalIn/Out and Encoder
//! channels, with no I/O of its own.
//!
//! The bus side ([`crate::bus`]) hands every received frame to [`CanCard::receive`] and
//! asks [`CanCard::compose`] for the payload of each frame it sends; device calls from any
//! thread read and write lock-free images in between. Status is per received frame: a
//! frame not seen within its timeout makes exactly its channels stale; a link that is
//! down makes the whole card offline. Every odd frame and every bus error is counted
//! ([`CanCard::counters`]).
//!
//! ```
//! use device_interface::{AnalogIn, time::{Clock, SimClock, Timestamp}};
//! use driver_can::{card::CanCard, map::{CanConfig, CanMap}};
//! use std::sync::Arc;
//!
//! let config: CanConfig = toml::from_str(r#"
//!     interface = "vcan0"
//!     [[rx]]
//!     id = 0x100
//!     length = 2
//!     signal = [{ name = "t", start = 0, length = 16, factor = 0.1, offset = -40 }]
//! "#)?;
//! let clock = Arc::new(SimClock::new(Timestamp::from_nanos(1)));
//! let card = CanCard::new(CanMap::new(&config, ".".as_ref())?, clock.clone());
//! card.set_link(true, None);
//! card.receive(0x100, false, false, &[0xF4, 0x01], clock.now()); // raw 500
//! assert_eq!(card.read(0)?, 10.0);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use crate::map::{CanMap, MappedFrame, SignalRole};
use arc_swap::ArcSwapOption;
use device_interface::bits::{BitImage, BitSpan};
use device_interface::encoder::WrappingCounter;
use device_interface::time::{Clock, Timestamp};
use device_interface::{
    AnalogIn, AnalogOut, Device, DeviceError, DigitalIn, DigitalOut, Health, Scale, Status,
};
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};

/// The controller's error state, as error frames report it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum BusState {
    /// Normal operation (also the state before any error frame).
    ErrorActive,
    /// An error counter passed 96.
    ErrorWarning,
    /// An error counter passed 127: the controller no longer sends active error flags.
    ErrorPassive,
    /// The transmit error counter passed 255: the controller is off the bus.
    BusOff,
}

impl BusState {
    fn from_u8(v: u8) -> BusState {
        match v {
            1 => BusState::ErrorWarning,
            2 => BusState::ErrorPassive,
            3 => BusState::BusOff,
            _ => BusState::ErrorActive,
        }
    }
}

/// What an error frame reported, decoded by the bus side.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ErrorReport {
    /// The controller went bus-off.
    pub bus_off: bool,
    /// The controller was restarted (back to error-active).
    pub restarted: bool,
    /// Controller reached error-warning.
    pub warning: bool,
    /// Controller reached error-passive.
    pub passive: bool,
    /// Controller is back to error-active.
    pub active: bool,
    /// RX or TX buffer overflow in the controller.
    pub overflow: bool,
    /// No acknowledgement of a sent frame.
    pub no_ack: bool,
    /// Arbitration lost.
    pub lost_arbitration: bool,
    /// A protocol violation (bit, form, stuff, CRC …).
    pub protocol: bool,
    /// A transceiver (wiring) fault.
    pub transceiver: bool,
    /// The driver timed out sending.
    pub tx_timeout: bool,
}

/// A snapshot of a card's counters.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct CanCounters {
    /// Mapped frames received and decoded.
    pub rx_frames: u64,
    /// Frames with an id the card does not map (the kernel filters should drop these).
    pub rx_unknown_id: u64,
    /// Mapped frames with the wrong payload length (not decoded).
    pub rx_bad_length: u64,
    /// Mapped frames of the wrong kind (classic for FD or the reverse, remote frames).
    pub rx_bad_kind: u64,
    /// Received signal values outside their declared [min|max] (decoded anyway).
    pub rx_out_of_range: u64,
    /// Frames the kernel dropped because the socket's queue was full.
    pub rx_dropped: u64,
    /// Frames sent.
    pub tx_frames: u64,
    /// Sends that failed (buffer full, link down, controller off).
    pub tx_errors: u64,
    /// Cycles of cyclic frames left out because the bus thread woke too late for them
    /// (the schedule keeps its phase instead of sending a burst).
    pub tx_skipped_cycles: u64,
    /// Times a received frame went stale.
    pub stale_events: u64,
    /// Times the link went down.
    pub link_down_events: u64,
    /// Error frames.
    pub error_frames: u64,
    /// Bus-off events.
    pub bus_off: u64,
    /// Error-passive events.
    pub error_passive: u64,
    /// Error-warning events.
    pub error_warning: u64,
    /// Controller restarts.
    pub restarted: u64,
    /// Controller buffer overflows.
    pub controller_overflow: u64,
    /// Missing acknowledgements.
    pub no_ack: u64,
    /// Lost arbitrations.
    pub lost_arbitration: u64,
    /// Protocol violations.
    pub protocol_violations: u64,
    /// Transceiver faults.
    pub transceiver_faults: u64,
    /// Driver transmit timeouts.
    pub tx_timeouts: u64,
    /// The controller state now.
    pub bus_state: Option<BusState>,
    /// The link is up.
    pub link_up: bool,
}

#[derive(Default)]
struct Counters {
    rx_frames: AtomicU64,
    rx_unknown_id: AtomicU64,
    rx_bad_length: AtomicU64,
    rx_bad_kind: AtomicU64,
    rx_out_of_range: AtomicU64,
    rx_dropped: AtomicU64,
    tx_frames: AtomicU64,
    tx_errors: AtomicU64,
    tx_skipped_cycles: AtomicU64,
    stale_events: AtomicU64,
    link_down_events: AtomicU64,
    error_frames: AtomicU64,
    bus_off: AtomicU64,
    error_passive: AtomicU64,
    error_warning: AtomicU64,
    restarted: AtomicU64,
    controller_overflow: AtomicU64,
    no_ack: AtomicU64,
    lost_arbitration: AtomicU64,
    protocol_violations: AtomicU64,
    transceiver_faults: AtomicU64,
    tx_timeouts: AtomicU64,
}

fn bump(c: &AtomicU64) {
    c.fetch_add(1, Ordering::Relaxed);
}

/// Per received frame.
struct RxState {
    /// Receive time in ns plus one; 0: never.
    last: AtomicU64,
    /// Counted as stale (so each episode counts once).
    stale: AtomicBool,
}

/// What [`CanCard::receive`] made of a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Received {
    /// Decoded: the index of the rx frame.
    Decoded(usize),
    /// Not a mapped id (counted).
    UnknownId,
    /// A mapped id with the wrong payload length (counted, not decoded).
    BadLength,
    /// A mapped id as a CAN FD frame where a classic one is mapped, or the reverse
    /// (counted, not decoded).
    BadKind,
}

/// The devices of one CAN interface.
pub struct CanCard {
    map: CanMap,
    clock: Arc<dyn Clock>,
    rx: Box<[RxState]>,
    ai: Box<[AtomicI64]>,
    /// The (rx frame, signal) of each analog input; the rx frame of each digital input
    /// bit and encoder; the (tx frame, signal) of each analog output, the tx frame of
    /// each digital output bit.
    ai_at: Box<[(u32, u32)]>,
    di: BitImage,
    di_frame: Box<[u32]>,
    encoders: Box<[WrappingCounter]>,
    enc_frame: Box<[u32]>,
    ao: Box<[AtomicI64]>,
    ao_at: Box<[(u32, u32)]>,
    dout: BitImage,
    do_frame: Box<[u32]>,
    tx_dirty: Box<[AtomicBool]>,
    waker: OnceLock<Box<dyn Fn() + Send + Sync>>,
    link_up: AtomicBool,
    bus_state: AtomicU8,
    counters: Counters,
    last_error: ArcSwapOption<DeviceError>,
}

impl CanCard {
    /// The devices of `map`; offline until the bus side reports the link up.
    pub fn new(map: CanMap, clock: Arc<dyn Clock>) -> Arc<CanCard> {
        let [ai, ao, di, dout] = map.counts();
        let mut ai_at = vec![(0, 0); ai as usize];
        let mut di_frame = vec![0; di as usize];
        let mut enc_frame = vec![0; map.encoder_count() as usize];
        let mut ao_at = vec![(0, 0); ao as usize];
        let mut do_frame = vec![0; dout as usize];
        let ao_init: Vec<AtomicI64> = (0..ao).map(|_| AtomicI64::new(0)).collect();
        let dout_image = BitImage::new(dout);
        for (dir, frames) in [(false, map.rx()), (true, map.tx())] {
            for (f, frame) in frames.iter().enumerate() {
                for (k, s) in frame.signals.iter().enumerate() {
                    let (from, to) = (s.channel as usize, (s.channel + s.width()) as usize);
                    let table = match (s.role, dir) {
                        (SignalRole::Analog, false) => {
                            ai_at[from] = (f as u32, k as u32);
                            continue;
                        }
                        (SignalRole::Analog, true) => {
                            ao_at[from] = (f as u32, k as u32);
                            ao_init[from].store(s.initial_raw, Ordering::Relaxed);
                            continue;
                        }
                        (SignalRole::Digital, false) => &mut di_frame,
                        (SignalRole::Encoder, _) => &mut enc_frame,
                        (SignalRole::Digital, true) => {
                            for k in 0..s.width() {
                                let _ = dout_image.set(s.channel + k, s.initial_raw >> k & 1 == 1);
                            }
                            &mut do_frame
                        }
                    };
                    table[from..to].fill(f as u32);
                }
            }
        }
        let encoders = map
            .encoders()
            .filter_map(|s| {
                let (res, up) = s.encoder?;
                WrappingCounter::new(res, up, s.signal.layout().1).ok()
            })
            .collect();
        Arc::new(CanCard {
            rx: map
                .rx()
                .iter()
                .map(|_| RxState {
                    last: AtomicU64::new(0),
                    stale: AtomicBool::new(false),
                })
                .collect(),
            ai: (0..ai).map(|_| AtomicI64::new(0)).collect(),
            ai_at: ai_at.into(),
            di: BitImage::new(di),
            di_frame: di_frame.into(),
            encoders,
            enc_frame: enc_frame.into(),
            ao: ao_init.into(),
            ao_at: ao_at.into(),
            dout: dout_image,
            do_frame: do_frame.into(),
            tx_dirty: map.tx().iter().map(|_| AtomicBool::new(false)).collect(),
            waker: OnceLock::new(),
            link_up: AtomicBool::new(false),
            bus_state: AtomicU8::new(0),
            counters: Counters::default(),
            last_error: ArcSwapOption::empty(),
            map,
            clock,
        })
    }

    /// The card's map.
    pub fn map(&self) -> &CanMap {
        &self.map
    }

    /// The card's devices, for registration.
    pub fn devices(self: &Arc<Self>) -> device_interface::CardDevices {
        let [ai, ao, di, dout] = self.map.counts();
        device_interface::CardDevices {
            analog_in: (ai > 0).then(|| self.clone() as Arc<dyn AnalogIn>),
            analog_out: (ao > 0).then(|| self.clone() as Arc<dyn AnalogOut>),
            digital_in: (di > 0).then(|| self.clone() as Arc<dyn DigitalIn>),
            digital_out: (dout > 0).then(|| self.clone() as Arc<dyn DigitalOut>),
            encoders: self
                .map
                .encoders()
                .enumerate()
                .map(|(i, s)| {
                    (
                        s.name.clone(),
                        Arc::new(CanEncoder::new(self.clone(), i))
                            as Arc<dyn device_interface::Encoder>,
                    )
                })
                .collect(),
        }
    }

    /// Sets what is called when an on-change frame needs sending (the bus side's wake-up).
    /// Only the first call takes effect.
    pub fn set_waker(&self, wake: Box<dyn Fn() + Send + Sync>) {
        let _ = self.waker.set(wake);
    }

    /// Decodes a received frame's payload into the channels, timestamped `at`; `fd` says
    /// whether it came as a CAN FD frame.
    pub fn receive(
        &self,
        id: u32,
        extended: bool,
        fd: bool,
        data: &[u8],
        at: Timestamp,
    ) -> Received {
        self.receive_into(id, extended, fd, data, at, None)
    }

    /// As [`receive`](Self::receive), and for a decoded frame also the physical value of each
    /// of its signals, in map order, into `values` (cleared first; NaN for a signal that
    /// cannot be read): each signal is extracted once, for the image and the values alike.
    /// Allocation-free once `values` holds the widest frame's signals.
    pub fn receive_with_values(
        &self,
        id: u32,
        extended: bool,
        fd: bool,
        data: &[u8],
        at: Timestamp,
        values: &mut Vec<f64>,
    ) -> Received {
        values.clear();
        self.receive_into(id, extended, fd, data, at, Some(values))
    }

    fn receive_into(
        &self,
        id: u32,
        extended: bool,
        fd: bool,
        data: &[u8],
        at: Timestamp,
        mut values: Option<&mut Vec<f64>>,
    ) -> Received {
        let Some(f) = self
            .map
            .rx()
            .iter()
            .position(|f| f.id == id && f.extended == extended)
        else {
            bump(&self.counters.rx_unknown_id);
            return Received::UnknownId;
        };
        let frame = &self.map.rx()[f];
        if frame.fd != fd {
            bump(&self.counters.rx_bad_kind);
            return Received::BadKind;
        }
        if data.len() != frame.length {
            bump(&self.counters.rx_bad_length);
            return Received::BadLength;
        }
        for s in &frame.signals {
            // The length was checked against the map, which checked every signal fits.
            let Ok(raw) = s.signal.extract(data) else {
                if let Some(v) = values.as_deref_mut() {
                    v.push(f64::NAN);
                }
                continue;
            };
            if let Some(v) = values.as_deref_mut() {
                v.push(s.signal.scale().to_physical(raw));
            }
            if !s.signal.scale().raw_range().contains(raw) {
                bump(&self.counters.rx_out_of_range);
            }
            match s.role {
                SignalRole::Analog => self.ai[s.channel as usize].store(raw, Ordering::Release),
                SignalRole::Digital => {
                    for k in 0..s.width() {
                        let _ = self.di.set(s.channel + k, raw >> k & 1 == 1);
                    }
                }
                SignalRole::Encoder => self.encoders[s.channel as usize].sample(raw),
            }
        }
        self.rx[f]
            .last
            .store(at.as_nanos().saturating_add(1), Ordering::Release);
        if self.rx[f].stale.swap(false, Ordering::AcqRel) {
            tracing::info!(frame = %frame.name, "fresh again");
        }
        bump(&self.counters.rx_frames);
        Received::Decoded(f)
    }

    /// Counts a frame of a kind the card never decodes (a remote frame, an unknown size).
    pub fn wrong_kind(&self) {
        bump(&self.counters.rx_bad_kind);
    }

    /// Counts frames the kernel dropped for a full receive queue.
    pub fn dropped(&self, frames: u64) {
        self.counters
            .rx_dropped
            .fetch_add(frames, Ordering::Relaxed);
    }

    /// Writes tx frame `tx`'s payload into `buf` (at least the frame's length) and clears
    /// its on-change mark. Returns the payload length.
    pub fn compose(&self, tx: usize, buf: &mut [u8]) -> usize {
        let Some(frame) = self.map.tx().get(tx) else {
            return 0;
        };
        self.tx_dirty[tx].store(false, Ordering::Release);
        let payload = &mut buf[..frame.length];
        payload.fill(0);
        for s in &frame.signals {
            let raw = match s.role {
                SignalRole::Analog => self.ao[s.channel as usize].load(Ordering::Acquire),
                SignalRole::Digital => (0..s.width()).fold(0i64, |v, k| {
                    v | i64::from(self.dout.get(s.channel + k).unwrap_or(false)) << k
                }),
                SignalRole::Encoder => continue,
            };
            // Values were range-checked when written.
            let _ = s.signal.insert(payload, raw);
        }
        frame.length
    }

    /// True while some tx frame waits to be sent (after an on-change write or a flush).
    pub fn sends_pending(&self) -> bool {
        self.tx_dirty.iter().any(|d| d.load(Ordering::Acquire))
    }

    /// True when tx frame `tx` waits to be sent because an output of it changed.
    pub fn is_dirty(&self, tx: usize) -> bool {
        self.tx_dirty
            .get(tx)
            .is_some_and(|d| d.load(Ordering::Acquire))
    }

    /// Counts a frame sent, or a send that failed.
    pub fn sent(&self, ok: bool) {
        bump(if ok {
            &self.counters.tx_frames
        } else {
            &self.counters.tx_errors
        });
    }

    /// Counts cyclic sends left out after a late wake-up.
    pub fn skipped(&self, cycles: u64) {
        self.counters
            .tx_skipped_cycles
            .fetch_add(cycles, Ordering::Relaxed);
    }

    /// Reports the link state; `why` is kept as the last error when it goes down.
    pub fn set_link(&self, up: bool, why: Option<DeviceError>) {
        let was = self.link_up.swap(up, Ordering::AcqRel);
        if was && !up {
            bump(&self.counters.link_down_events);
        }
        if let Some(e) = why {
            self.last_error.store(Some(Arc::new(e)));
        }
    }

    /// True while the link is up.
    pub fn link_up(&self) -> bool {
        self.link_up.load(Ordering::Acquire)
    }

    /// Counts what an error frame reported and follows the controller state.
    pub fn error_frame(&self, r: ErrorReport) {
        let c = &self.counters;
        bump(&c.error_frames);
        let flags = [
            (r.bus_off, &c.bus_off),
            (r.restarted, &c.restarted),
            (r.warning, &c.error_warning),
            (r.passive, &c.error_passive),
            (r.overflow, &c.controller_overflow),
            (r.no_ack, &c.no_ack),
            (r.lost_arbitration, &c.lost_arbitration),
            (r.protocol, &c.protocol_violations),
            (r.transceiver, &c.transceiver_faults),
            (r.tx_timeout, &c.tx_timeouts),
        ];
        for (set, counter) in flags {
            if set {
                bump(counter);
            }
        }
        let state = if r.bus_off {
            Some(BusState::BusOff)
        } else if r.passive {
            Some(BusState::ErrorPassive)
        } else if r.warning {
            Some(BusState::ErrorWarning)
        } else if r.active || r.restarted {
            Some(BusState::ErrorActive)
        } else {
            None
        };
        if let Some(s) = state {
            let old = BusState::from_u8(self.bus_state.swap(s as u8, Ordering::AcqRel));
            if old != s {
                tracing::warn!(interface = %self.map.interface(), "bus state {old:?} -> {s:?}");
                self.last_error
                    .store(Some(Arc::new(DeviceError::bus(BusStateError(s)))));
            }
        }
    }

    /// The controller state.
    pub fn bus_state(&self) -> BusState {
        BusState::from_u8(self.bus_state.load(Ordering::Acquire))
    }

    /// Counts received frames that went stale since the last call (for the bus side's
    /// periodic check; reads see staleness at once either way).
    pub fn check_stale(&self) {
        let now = self.clock.now();
        for (f, frame) in self.map.rx().iter().enumerate() {
            if self.frame_age_error(f, frame, now).is_some()
                && self.rx[f].last.load(Ordering::Acquire) != 0
                && !self.rx[f].stale.swap(true, Ordering::AcqRel)
            {
                bump(&self.counters.stale_events);
                tracing::warn!(frame = %frame.name, "stale: not received within {:?}", frame.timeout.unwrap_or_default());
            }
        }
    }

    /// The counters now.
    pub fn counters(&self) -> CanCounters {
        let c = &self.counters;
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        CanCounters {
            rx_frames: l(&c.rx_frames),
            rx_unknown_id: l(&c.rx_unknown_id),
            rx_bad_length: l(&c.rx_bad_length),
            rx_bad_kind: l(&c.rx_bad_kind),
            rx_out_of_range: l(&c.rx_out_of_range),
            rx_dropped: l(&c.rx_dropped),
            tx_frames: l(&c.tx_frames),
            tx_errors: l(&c.tx_errors),
            tx_skipped_cycles: l(&c.tx_skipped_cycles),
            stale_events: l(&c.stale_events),
            link_down_events: l(&c.link_down_events),
            error_frames: l(&c.error_frames),
            bus_off: l(&c.bus_off),
            error_passive: l(&c.error_passive),
            error_warning: l(&c.error_warning),
            restarted: l(&c.restarted),
            controller_overflow: l(&c.controller_overflow),
            no_ack: l(&c.no_ack),
            lost_arbitration: l(&c.lost_arbitration),
            protocol_violations: l(&c.protocol_violations),
            transceiver_faults: l(&c.transceiver_faults),
            tx_timeouts: l(&c.tx_timeouts),
            bus_state: Some(self.bus_state()),
            link_up: self.link_up(),
        }
    }

    /// Why frame `f`'s channels cannot be read now, if they cannot.
    fn frame_age_error(
        &self,
        f: usize,
        frame: &MappedFrame,
        now: Timestamp,
    ) -> Option<DeviceError> {
        match self.rx[f].last.load(Ordering::Acquire) {
            0 => Some(DeviceError::Stale { age: None }),
            t => {
                let age = now.duration_since(Timestamp::from_nanos(t - 1));
                match frame.timeout {
                    Some(limit) if age > limit => Some(DeviceError::Stale { age: Some(age) }),
                    _ => None,
                }
            }
        }
    }

    fn check_link(&self) -> Result<(), DeviceError> {
        if self.link_up() {
            Ok(())
        } else {
            Err(DeviceError::Offline)
        }
    }

    /// `Ok` when rx frame `f`'s channels are fresh and the link is up.
    fn check_frame(&self, f: u32) -> Result<(), DeviceError> {
        self.check_link()?;
        let f = f as usize;
        match self.map.rx().get(f) {
            Some(frame) => match self.frame_age_error(f, frame, self.clock.now()) {
                Some(e) => Err(e),
                None => Ok(()),
            },
            None => Ok(()),
        }
    }

    /// An output of tx frame `tx` changed: an on-change frame is marked and the bus woken
    /// (a cyclic-only frame just carries the new value at its next cycle).
    fn output(&self, tx: u32) {
        if self.map.tx().get(tx as usize).is_some_and(|f| f.on_change) {
            self.tx_dirty[tx as usize].store(true, Ordering::Release);
            if let Some(w) = self.waker.get() {
                w();
            }
        }
    }

    /// Asks the bus side to send every tx frame now (at shutdown, after the safe values).
    pub fn flush(&self) {
        for d in self.tx_dirty.iter() {
            d.store(true, Ordering::Release);
        }
        if let Some(w) = self.waker.get() {
            w();
        }
    }

    /// Where analog `channel` sits: (frame, signal) in the rx or tx frames.
    fn analog_at(&self, tx: bool, channel: u32) -> Result<(u32, u32), DeviceError> {
        let at = if tx { &self.ao_at } else { &self.ai_at };
        device_interface::channel::nth(at, channel).copied()
    }

    fn scale_of(&self, tx: bool, channel: u32) -> Result<Scale, DeviceError> {
        let (f, k) = self.analog_at(tx, channel)?;
        let frames = if tx { self.map.tx() } else { self.map.rx() };
        Ok(*frames[f as usize].signals[k as usize].signal.scale())
    }
}

/// A bus state as a device error cause.
#[derive(Debug, thiserror::Error)]
#[error("CAN controller is {0:?}")]
struct BusStateError(BusState);

impl Device for CanCard {
    fn health(&self) -> Health {
        let now = self.clock.now();
        let mut status = Status::Online;
        let mut oldest: Option<u64> = None;
        for (f, frame) in self.map.rx().iter().enumerate() {
            if self.frame_age_error(f, frame, now).is_some() {
                status = Status::Stale;
            }
            let t = self.rx[f].last.load(Ordering::Acquire);
            oldest = Some(oldest.map_or(t, |o| o.min(t)));
        }
        if !self.link_up() || self.bus_state() == BusState::BusOff {
            status = Status::Offline;
        }
        Health {
            status,
            last_good: oldest
                .filter(|&t| t != 0)
                .map(|t| Timestamp::from_nanos(t - 1)),
            checked_at: now,
            last_error: self.last_error.load().as_deref().cloned(),
        }
    }
}

impl AnalogIn for CanCard {
    fn channel_count(&self) -> u32 {
        self.map.counts()[0]
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.scale_of(false, channel)
    }

    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let (f, _) = self.analog_at(false, channel)?;
        self.check_frame(f)?;
        Ok(self.ai[channel as usize].load(Ordering::Acquire))
    }
}

impl AnalogOut for CanCard {
    fn channel_count(&self) -> u32 {
        self.map.counts()[1]
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.scale_of(true, channel)
    }

    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        let scale = self.scale_of(true, channel)?;
        scale.check_raw(channel, raw)?;
        self.check_link()?;
        self.ao[channel as usize].store(raw, Ordering::Release);
        self.output(self.ao_at[channel as usize].0);
        Ok(())
    }

    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.analog_at(true, channel)?;
        Ok(self.ao[channel as usize].load(Ordering::Acquire))
    }
}

impl device_interface::bits::DigitalInputImage for CanCard {
    fn inputs(&self) -> &BitImage {
        &self.di
    }

    fn check_inputs(&self, span: BitSpan) -> Result<(), DeviceError> {
        // Each bit is as fresh as the frame it came in.
        for b in span.start()..=span.stop() {
            self.check_frame(self.di_frame[b as usize])?;
        }
        Ok(())
    }
}

impl device_interface::bits::DigitalOutputImage for CanCard {
    fn outputs(&self) -> &BitImage {
        &self.dout
    }

    fn check_outputs_writable(&self) -> Result<(), DeviceError> {
        self.check_link()
    }

    fn outputs_written(&self, written: device_interface::bits::Written) {
        use device_interface::bits::Written;
        let (start, stop) = match written {
            Written::Bit { bit, .. } => (bit, bit),
            Written::Span { span, .. } => (span.start(), span.stop()),
        };
        let mut last = None;
        for b in start..=stop {
            let f = self.do_frame[b as usize];
            if last != Some(f) {
                self.output(f);
                last = Some(f);
            }
        }
    }
}

/// One position-counter signal of a [`CanCard`], as a device of its own.
pub type CanEncoder = device_interface::encoder::CardEncoder<CanCard>;

impl device_interface::encoder::EncoderHost for CanCard {
    fn encoder_counter(&self, index: usize) -> &device_interface::encoder::EncoderCounter {
        self.encoders[index].counter()
    }

    fn check_encoder(&self, index: usize) -> Result<(), DeviceError> {
        self.check_frame(self.enc_frame[index])
    }

    fn check_writable(&self) -> Result<(), DeviceError> {
        self.check_link()
    }
}
