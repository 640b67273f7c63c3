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

mod devices;
mod j1939;
mod sides;
mod status;
mod tx;

pub use j1939::J1939Report;

pub use devices::CanEncoder;
pub use sides::{CanAnalogIn, CanAnalogOut, CanDigitalIn, CanDigitalOut};
pub use status::{BusState, CanCounters, ErrorReport, MessageState};

use crate::map::{CanMap, MappedFrame, SignalRole};
use arc_swap::ArcSwapOption;
use device_interface::bits::BitImage;
use device_interface::encoder::WrappingCounter;
use device_interface::time::{Clock, Timestamp};
use device_interface::{AnalogIn, AnalogOut, DeviceError, DigitalIn, DigitalOut, Scale};
use rtt::log::{Area, Arg};
use rtt::rt_log;
use status::{BusStateError, Counters, bump};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU8, AtomicU64, Ordering};

/// Per received frame.
struct RxState {
    /// Receive time in ns plus one; 0: never.
    last: AtomicU64,
    /// Counted as stale (so each episode counts once).
    stale: AtomicBool,
    /// Frames received.
    count: AtomicU64,
    /// A multiplexed frame's: when each signal last came (as `last`; only multiplexed
    /// signals use theirs). Empty for a frame without multiplexing.
    signals: Box<[AtomicU64]>,
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
    di_at: Box<[(u32, u32)]>,
    encoders: Box<[WrappingCounter]>,
    enc_at: Box<[(u32, u32)]>,
    ao: Box<[AtomicI64]>,
    ao_at: Box<[(u32, u32)]>,
    dout: BitImage,
    do_frame: Box<[u32]>,
    tx_dirty: Box<[AtomicBool]>,
    /// The received frames the whole card, its analog and its digital inputs come from.
    feeds: sides::Feeding,
    /// The bus side's wake-up (replaced when a new bus opens the card).
    waker: ArcSwapOption<Box<dyn Fn() + Send + Sync>>,
    link_up: AtomicBool,
    bus_state: AtomicU8,
    /// What netlink last said of a real controller (none for vcan).
    controller: ArcSwapOption<crate::netlink::Controller>,
    counters: Counters,
    last_error: ArcSwapOption<DeviceError>,
    /// The node's address claiming, as the bus side last reported it (J1939 cards).
    claim: ArcSwapOption<J1939Report>,
    /// Why the card's J1939 groups cannot be sent now (no address), if they cannot.
    no_address: ArcSwapOption<DeviceError>,
    /// Where the card and its bus side log (real-time safe).
    log: Area,
}

impl CanCard {
    /// The devices of `map`; offline until the bus side reports the link up. It logs as
    /// its interface.
    pub fn new(map: CanMap, clock: Arc<dyn Clock>) -> Arc<CanCard> {
        let log = Area::named(map.interface());
        CanCard::with_log(map, clock, log)
    }

    /// [`new`](Self::new), logging as `log` (the card's name in a deployment).
    pub fn with_log(map: CanMap, clock: Arc<dyn Clock>, log: Area) -> Arc<CanCard> {
        let [ai, ao, di, dout] = map.counts();
        let mut ai_at = vec![(0, 0); ai as usize];
        let mut di_at = vec![(0, 0); di as usize];
        let mut enc_at = vec![(0, 0); map.encoder_count() as usize];
        let mut ao_at = vec![(0, 0); ao as usize];
        let mut do_frame = vec![0; dout as usize];
        let ao_init: Vec<AtomicI64> = (0..ao).map(|_| AtomicI64::new(0)).collect();
        let dout_image = BitImage::new(dout);
        for (dir, frames) in [(false, map.rx()), (true, map.tx())] {
            for (f, frame) in frames.iter().enumerate() {
                for (k, s) in frame.signals.iter().enumerate() {
                    let (from, to) = (s.channel as usize, (s.channel + s.width()) as usize);
                    let at = (f as u32, k as u32);
                    match (s.role, dir) {
                        (SignalRole::Analog, false) => ai_at[from] = at,
                        (SignalRole::Analog, true) => {
                            ao_at[from] = at;
                            ao_init[from].store(s.initial_raw, Ordering::Relaxed);
                        }
                        (SignalRole::Digital, false) => di_at[from..to].fill(at),
                        (SignalRole::Encoder, _) => enc_at[from..to].fill(at),
                        (SignalRole::Digital, true) => {
                            for k in 0..s.width() {
                                let _ = dout_image.set(s.channel + k, s.initial_raw >> k & 1 == 1);
                            }
                            do_frame[from..to].fill(f as u32);
                        }
                    }
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
        let feeds = sides::Feeding::new(map.rx().len(), &ai_at, &di_at);
        Arc::new(CanCard {
            log,
            feeds,
            rx: map
                .rx()
                .iter()
                .map(|f| RxState {
                    last: AtomicU64::new(0),
                    stale: AtomicBool::new(false),
                    count: AtomicU64::new(0),
                    signals: if f.signals.iter().any(|s| s.mux.is_some()) {
                        f.signals.iter().map(|_| AtomicU64::new(0)).collect()
                    } else {
                        Box::new([])
                    },
                })
                .collect(),
            ai: (0..ai).map(|_| AtomicI64::new(0)).collect(),
            ai_at: ai_at.into(),
            di: BitImage::new(di),
            di_at: di_at.into(),
            encoders,
            enc_at: enc_at.into(),
            ao: ao_init.into(),
            ao_at: ao_at.into(),
            dout: dout_image,
            do_frame: do_frame.into(),
            tx_dirty: map.tx().iter().map(|_| AtomicBool::new(false)).collect(),
            waker: ArcSwapOption::empty(),
            link_up: AtomicBool::new(false),
            bus_state: AtomicU8::new(0),
            controller: ArcSwapOption::empty(),
            counters: Counters::default(),
            last_error: ArcSwapOption::empty(),
            claim: ArcSwapOption::empty(),
            no_address: ArcSwapOption::empty(),
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
        // Each a view of its own, so that its health is judged by its own messages.
        device_interface::CardDevices {
            analog_in: (ai > 0).then(|| Arc::new(CanAnalogIn::new(self)) as Arc<dyn AnalogIn>),
            analog_out: (ao > 0).then(|| Arc::new(CanAnalogOut::new(self)) as Arc<dyn AnalogOut>),
            digital_in: (di > 0).then(|| Arc::new(CanDigitalIn::new(self)) as Arc<dyn DigitalIn>),
            digital_out: (dout > 0)
                .then(|| Arc::new(CanDigitalOut::new(self)) as Arc<dyn DigitalOut>),
            drives: Vec::new(),
            encoders: self
                .map
                .encoders()
                .enumerate()
                .map(|(i, s)| {
                    (
                        s.port.clone(),
                        Arc::new(CanEncoder::new(self.clone(), i))
                            as Arc<dyn device_interface::Encoder>,
                    )
                })
                .collect(),
        }
    }

    /// Sets what is called when an on-change frame needs sending (the bus side's wake-up);
    /// a bus opened anew on the card replaces the old one's.
    pub fn set_waker(&self, wake: Box<dyn Fn() + Send + Sync>) {
        self.waker.store(Some(Arc::new(wake)));
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
        values: Option<&mut Vec<f64>>,
    ) -> Received {
        let Some(f) = self
            .map
            .rx()
            .iter()
            .position(|f| f.j1939.is_none() && f.id == id && f.extended == extended)
        else {
            bump(&self.counters.rx_unknown_id);
            return Received::UnknownId;
        };
        if self.map.rx()[f].fd != fd {
            bump(&self.counters.rx_bad_kind);
            return Received::BadKind;
        }
        self.decode(f, data, at, values)
    }

    /// Decodes rx frame `f`'s payload into the channels (a payload of another length is
    /// counted, not decoded).
    fn decode(
        &self,
        f: usize,
        data: &[u8],
        at: Timestamp,
        mut values: Option<&mut Vec<f64>>,
    ) -> Received {
        let frame = &self.map.rx()[f];
        if data.len() != frame.length {
            bump(&self.counters.rx_bad_length);
            return Received::BadLength;
        }
        // A multiplexed message carries the signals of its multiplexer's value only.
        let mux = frame
            .signals
            .iter()
            .find(|s| s.multiplexer)
            .and_then(|s| s.signal.extract(data).ok())
            .map(|raw| raw as u64);
        let stamp = at.as_nanos().saturating_add(1);
        for (k, s) in frame.signals.iter().enumerate() {
            if s.mux.is_some() && s.mux != mux {
                if let Some(v) = values.as_deref_mut() {
                    v.push(f64::NAN);
                }
                continue;
            }
            // The length was checked against the map, which checked every signal fits.
            let Ok(raw) = s.signal.extract(data) else {
                if let Some(v) = values.as_deref_mut() {
                    v.push(f64::NAN);
                }
                continue;
            };
            if let Some(v) = values.as_deref_mut() {
                v.push(s.signal.physical(raw));
            }
            if !s.signal.in_range(raw) {
                bump(&self.counters.rx_out_of_range);
            }
            if s.mux.is_some()
                && let Some(t) = self.rx[f].signals.get(k)
            {
                t.store(stamp, Ordering::Release);
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
        self.rx[f].last.store(stamp, Ordering::Release);
        bump(&self.rx[f].count);
        if self.rx[f].stale.swap(false, Ordering::AcqRel) {
            rt_log!(
                self.log,
                Info,
                "frame {} fresh again",
                Arg::text(&frame.name)
            );
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
            self.follow_state(s);
        }
    }

    /// Takes `s` as the controller state, saying so when it changed.
    fn follow_state(&self, s: BusState) {
        let old = BusState::from_u8(self.bus_state.swap(s as u8, Ordering::AcqRel));
        if old != s {
            rt_log!(
                self.log,
                Warn,
                "{}: bus state {} -> {}",
                Arg::text(self.map.interface()),
                Arg::display(&format_args!("{old:?}")),
                Arg::display(&format_args!("{s:?}"))
            );
            self.last_error
                .store(Some(Arc::new(DeviceError::bus(BusStateError(s)))));
        }
    }

    /// Where the card and its bus side log.
    pub fn log(&self) -> &Area {
        &self.log
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
                rt_log!(
                    self.log,
                    Warn,
                    "frame {} stale: not received within {} ms",
                    Arg::text(&frame.name),
                    frame.timeout.unwrap_or_default().as_secs_f64() * 1e3
                );
            }
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

    /// `Ok` when signal `k` of rx frame `f` is fresh and the link is up: its frame came
    /// within the frame's timeout, and — a multiplexed signal — its own multiplexer value
    /// did too (a frame that keeps coming with other values leaves it stale).
    fn check_signal(&self, (f, k): (u32, u32)) -> Result<(), DeviceError> {
        self.check_link()?;
        let (f, k) = (f as usize, k as usize);
        let Some(frame) = self.map.rx().get(f) else {
            return Ok(());
        };
        let now = self.clock.now();
        if let Some(e) = self.frame_age_error(f, frame, now) {
            return Err(e);
        }
        let Some(seen) = self.rx[f].signals.get(k) else {
            return Ok(());
        };
        if frame.signals.get(k).is_none_or(|s| s.mux.is_none()) {
            return Ok(());
        }
        match seen.load(Ordering::Acquire) {
            0 => Err(DeviceError::Stale { age: None }),
            t => {
                let age = now.duration_since(Timestamp::from_nanos(t - 1));
                match frame.timeout {
                    Some(limit) if age > limit => Err(DeviceError::Stale { age: Some(age) }),
                    _ => Ok(()),
                }
            }
        }
    }

    /// Where analog `channel` sits: (frame, signal) in the rx or tx frames.
    fn analog_at(&self, tx: bool, channel: u32) -> Result<(u32, u32), DeviceError> {
        let at = if tx { &self.ao_at } else { &self.ai_at };
        device_interface::channel::nth(at, channel).copied()
    }

    fn scale_of(&self, tx: bool, channel: u32) -> Result<Scale, DeviceError> {
        let at = self.analog_at(tx, channel)?;
        Ok(*self.signal_at(tx, at).scale())
    }

    /// The signal at (frame, signal) of the rx or tx frames (a place the map made).
    fn signal_at(&self, tx: bool, (f, k): (u32, u32)) -> &crate::signal::Signal {
        let frames = if tx { self.map.tx() } else { self.map.rx() };
        &frames[f as usize].signals[k as usize].signal
    }

    /// Stores analog output `channel`'s bits (checked by the caller) and sends its frame
    /// when it goes on change.
    fn store_output(&self, channel: u32, bits: i64) -> Result<(), DeviceError> {
        self.check_link()?;
        self.check_sendable(self.ao_at[channel as usize].0)?;
        self.ao[channel as usize].store(bits, Ordering::Release);
        self.output(self.ao_at[channel as usize].0);
        Ok(())
    }
}
