//! A Firmata card's devices: its digital inputs and outputs, analog inputs, PWM and servo
//! outputs (one AnalogOut: the PWM pins, then the servo pins) and encoders.
//!
//! Inputs are what the board last reported (DIGITAL_MESSAGE on a change of a reported
//! port, ANALOG_MESSAGE every sampling interval, encoder positions): reads take the image,
//! no system call, no lock. Outputs go into the output image and mark their port or pin to
//! be sent; the write wakes the bus side, which sends what is marked on its next step.
//! Until the board has answered and been set up, and after it went away, every call fails
//! with [`DeviceError::Offline`]; an analog input, or a digital input whose port, not
//! reported since is [`DeviceError::Stale`].

use crate::board::BoardInfo;
use crate::config::FirmataConfig;
use crate::protocol::LineCounts;
use device_interface::bits::{BitImage, BitSpan, DigitalInputImage, DigitalOutputImage, Written};
use device_interface::channel::nth;
use device_interface::encoder::{CardEncoder, EncoderCounter, EncoderHost, WrappingCounter};
use device_interface::time::{Clock, Timestamp};
use device_interface::{
    AnalogIn, AnalogOut, CardDevices, Device, DeviceError, Health, RawRange, Scale, Unit,
};
use driver_api::SettleError;
use rtt::activity::Waker;
use serde::Serialize;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

/// A reported sample: valid bit and raw value.
const VALID: u64 = 1 << 63;

/// The settle check's states ([`FirmataCard::settle`]): not asked for, asked for, the pin
/// states queried, every output confirmed, an output found otherwise.
pub(crate) const CHECK_NONE: u8 = 0;
pub(crate) const CHECK_ASKED: u8 = 1;
pub(crate) const CHECK_QUERYING: u8 = 2;
pub(crate) const CHECK_OK: u8 = 3;
pub(crate) const CHECK_FAILED: u8 = 4;

/// An AnalogOut channel: its pin, what it is, its value and whether it is to be sent.
#[derive(Debug)]
pub struct AoChan {
    /// The pin.
    pub pin: u8,
    /// A servo (angle), else PWM (duty).
    pub servo: bool,
    /// The raw value (PWM: duty in `pwm_bits`; servo: degrees).
    pub raw: AtomicU32,
    /// To be sent.
    pub dirty: AtomicBool,
}

/// The card's line diagnostics and state, for `hwgw status`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct FirmataCounters {
    /// The port as configured.
    pub port: String,
    /// Where the link is: "closed", "opening", "online", "refused".
    pub link: String,
    /// The board, once it described itself.
    pub board: Option<String>,
    /// The decoder's counts (bytes, messages, framing errors, unknown commands, resyncs).
    #[serde(flatten)]
    pub line: LineCounts,
    /// Bytes sent.
    pub bytes_sent: u64,
    /// Times the port was opened and the board answered.
    pub opens: u64,
    /// Times the link was lost (read error, hang-up, silence) and reopened.
    pub reopens: u64,
    /// Failed opens and handshakes.
    pub open_failures: u64,
    /// Liveness probes sent (version queries on a quiet line).
    pub probes: u64,
    /// Analog reports above the channel's resolution (a corrupted message), dropped.
    pub bad_values: u64,
    /// The last error, if any.
    pub last_error: Option<String>,
}

/// State shared with the bus side that is not on a real-time path.
#[derive(Debug, Default)]
pub(crate) struct Shared {
    pub(crate) link: &'static str,
    pub(crate) board: Option<BoardInfo>,
    pub(crate) line: LineCounts,
    pub(crate) last_error: Option<String>,
    /// Why the settle check failed.
    pub(crate) check_error: Option<String>,
}

/// A Firmata card.
pub struct FirmataCard {
    pub(crate) config: FirmataConfig,
    clock: Arc<dyn Clock>,
    inputs: BitImage,
    outputs: BitImage,
    /// Analog inputs: VALID | raw.
    ai: Vec<AtomicU64>,
    pub(crate) ao: Vec<AoChan>,
    encoders: Vec<WrappingCounter>,
    ai_scale: Scale,
    pwm_scale: Scale,
    servo_scale: Scale,
    /// Ports (pins 8·n … 8·n+7) with outputs to send, one bit each (16 ports).
    pub(crate) dirty_ports: AtomicU32,
    /// Ports whose levels the board reported since it came online, one bit each.
    reported: AtomicU32,
    /// The port of each digital input bit.
    in_ports: Vec<u8>,
    pub(crate) online: AtomicBool,
    pub(crate) closing: AtomicBool,
    /// The settle check ([`CHECK_NONE`] …).
    pub(crate) check: AtomicU8,
    last_good: AtomicU64,
    /// Output writes accepted, and sent (for settle).
    pub(crate) written: AtomicU64,
    pub(crate) sent: AtomicU64,
    pub(crate) bytes_sent: AtomicU64,
    pub(crate) opens: AtomicU64,
    pub(crate) reopens: AtomicU64,
    pub(crate) open_failures: AtomicU64,
    pub(crate) probes: AtomicU64,
    bad_values: AtomicU64,
    pub(crate) shared: Mutex<Shared>,
    waker: OnceLock<Arc<dyn Waker>>,
}

/// Why a checked section made no card.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FirmataCardError {
    /// A channel's scale could not be made.
    #[error("cannot make the card's scales: {0}")]
    Scale(String),
    /// An encoder's counter could not be made.
    #[error("encoder: {0}")]
    Encoder(String),
}

fn scale_error(e: impl std::fmt::Display) -> FirmataCardError {
    FirmataCardError::Scale(e.to_string())
}

impl FirmataCard {
    /// The card of a checked section; offline until its bus side has set the board up.
    pub fn new(
        config: &FirmataConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<FirmataCard, FirmataCardError> {
        let unit = |u: &str| Unit::new(u).map_err(scale_error);
        let bits = |b: u8| RawRange::unsigned_bits(u32::from(b)).map_err(scale_error);
        let ai_scale = Scale::fraction(
            bits(config.analog_bits)?,
            0.0,
            config.reference_volts,
            unit("V")?,
        )
        .map_err(scale_error)?;
        let pwm_scale = Scale::fraction(bits(config.pwm_bits)?, 0.0, 1.0, unit("duty")?)
            .map_err(scale_error)?;
        let servo_scale = Scale::from_factor(
            RawRange::new(0, 180).map_err(scale_error)?,
            1.0,
            0.0,
            unit("deg")?,
        )
        .map_err(scale_error)?;
        let outputs = BitImage::new(config.digital_out.len() as u32);
        for (i, p) in config.digital_out.iter().enumerate() {
            let _ = outputs.set(i as u32, p.initial.unwrap_or(false));
        }
        let mut ao = Vec::new();
        for p in &config.pwm {
            ao.push(AoChan {
                pin: p.pin,
                servo: false,
                raw: AtomicU32::new(pwm_scale.to_raw_saturating(p.initial.unwrap_or(0.0)) as u32),
                dirty: AtomicBool::new(false),
            });
        }
        for p in &config.servo {
            ao.push(AoChan {
                pin: p.pin,
                servo: true,
                raw: AtomicU32::new(servo_scale.to_raw_saturating(p.initial.unwrap_or(90.0)) as u32),
                dirty: AtomicBool::new(false),
            });
        }
        let encoders = config
            .encoder
            .iter()
            .map(|e| WrappingCounter::new(e.resolution, true, 29))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| FirmataCardError::Encoder(e.to_string()))?;
        Ok(FirmataCard {
            config: config.clone(),
            clock,
            inputs: BitImage::new(config.digital_in.len() as u32),
            outputs,
            ai: config.analog_in.iter().map(|_| AtomicU64::new(0)).collect(),
            ao,
            encoders,
            ai_scale,
            pwm_scale,
            servo_scale,
            dirty_ports: AtomicU32::new(0),
            reported: AtomicU32::new(0),
            in_ports: config.digital_in.iter().map(|p| p.pin / 8).collect(),
            online: AtomicBool::new(false),
            closing: AtomicBool::new(false),
            check: AtomicU8::new(CHECK_NONE),
            last_good: AtomicU64::new(0),
            written: AtomicU64::new(0),
            sent: AtomicU64::new(0),
            bytes_sent: AtomicU64::new(0),
            opens: AtomicU64::new(0),
            reopens: AtomicU64::new(0),
            open_failures: AtomicU64::new(0),
            probes: AtomicU64::new(0),
            bad_values: AtomicU64::new(0),
            shared: Mutex::new(Shared {
                link: "closed",
                ..Shared::default()
            }),
            waker: OnceLock::new(),
        })
    }

    /// Its devices.
    pub fn devices(self: &Arc<Self>) -> CardDevices {
        let c = self.config.clone();
        CardDevices {
            analog_in: (!c.analog_in.is_empty()).then(|| self.clone() as Arc<dyn AnalogIn>),
            analog_out: (!self.ao.is_empty()).then(|| self.clone() as Arc<dyn AnalogOut>),
            digital_in: (!c.digital_in.is_empty())
                .then(|| self.clone() as Arc<dyn device_interface::DigitalIn>),
            digital_out: (!c.digital_out.is_empty())
                .then(|| self.clone() as Arc<dyn device_interface::DigitalOut>),
            drives: Vec::new(),
            encoders: CardEncoder::all(self, self.encoders.len()),
        }
    }

    /// The section it was made from.
    pub fn config(&self) -> &FirmataConfig {
        &self.config
    }

    /// True while the board is set up and answering.
    pub fn is_online(&self) -> bool {
        self.online.load(Ordering::Acquire)
    }

    /// The clock's now.
    pub fn now(&self) -> Timestamp {
        self.clock.now()
    }

    /// Called by the bus side's start: output writes wake it.
    pub fn set_waker(&self, waker: Arc<dyn Waker>) {
        let _ = self.waker.set(waker);
    }

    fn wake(&self) {
        self.written.fetch_add(1, Ordering::AcqRel);
        if let Some(w) = self.waker.get() {
            w.wake();
        }
    }

    /// Its counters and state now.
    pub fn counters(&self) -> FirmataCounters {
        let s = self.shared.lock().unwrap_or_else(PoisonError::into_inner);
        FirmataCounters {
            port: self.config.port.clone(),
            link: s.link.to_string(),
            board: s.board.as_ref().map(BoardInfo::describe),
            line: s.line,
            bytes_sent: self.bytes_sent.load(Ordering::Relaxed),
            opens: self.opens.load(Ordering::Relaxed),
            reopens: self.reopens.load(Ordering::Relaxed),
            open_failures: self.open_failures.load(Ordering::Relaxed),
            probes: self.probes.load(Ordering::Relaxed),
            bad_values: self.bad_values.load(Ordering::Relaxed),
            last_error: s.last_error.clone(),
        }
    }

    // --- the bus side's view ---

    /// The board answered: its inputs are current as of now.
    pub(crate) fn alive(&self, now: Timestamp) {
        self.last_good
            .store(now.as_nanos().max(1), Ordering::Release);
    }

    /// A DIGITAL_MESSAGE: the inputs on `port` take their levels (and are current from
    /// now on).
    pub(crate) fn digital_report(&self, port: u8, value: u8) {
        for (i, p) in self.config.digital_in.iter().enumerate() {
            if p.pin / 8 == port {
                let _ = self.inputs.set(i as u32, value >> (p.pin % 8) & 1 == 1);
            }
        }
        if let Some(bit) = 1u32.checked_shl(u32::from(port)) {
            self.reported.fetch_or(bit, Ordering::AcqRel);
        }
    }

    /// An ANALOG_MESSAGE of channel `channel`; a value above the channel's resolution (a
    /// message corrupted on the line) is dropped and counted.
    pub(crate) fn analog_report(&self, channel: u8, value: u16) {
        if i64::from(value) > self.ai_scale.raw_range().max {
            self.bad_values.fetch_add(1, Ordering::Relaxed);
            return;
        }
        for (i, c) in self.config.analog_in.iter().enumerate() {
            if c.channel == channel {
                self.ai[i].store(VALID | u64::from(value), Ordering::Release);
            }
        }
    }

    /// An encoder's position report.
    pub(crate) fn encoder_report(&self, index: u8, position: i64) {
        if let Some(e) = self.encoders.get(usize::from(index)) {
            e.sample(position.rem_euclid(1 << 29));
        }
    }

    /// The link went down (or came up): inputs are forgotten until reported anew; the
    /// encoders' next reports start new baselines.
    pub(crate) fn set_online(&self, online: bool) {
        if !online {
            self.reported.store(0, Ordering::Release);
            for a in &self.ai {
                a.store(0, Ordering::Release);
            }
            for e in &self.encoders {
                e.rebase();
            }
        }
        self.online.store(online, Ordering::Release);
    }

    /// The output bit of digital_out[i].
    pub(crate) fn output(&self, i: usize) -> bool {
        self.outputs.get(i as u32).unwrap_or(false)
    }

    /// Settles at stop: waits until every accepted write was sent, then has the board say
    /// what each output pin is (PIN_STATE_QUERY: the level or value its firmware last set)
    /// and compares; until `deadline` at the latest. Then refuses further writes.
    pub fn settle(&self, deadline: std::time::Instant) -> Result<(), SettleError> {
        let result = self.sent_and_confirmed(deadline);
        self.closing.store(true, Ordering::Release);
        result
    }

    fn sent_and_confirmed(&self, deadline: std::time::Instant) -> Result<(), SettleError> {
        let port = &self.config.port;
        let wait = |done: &dyn Fn() -> bool, what: &str| -> Result<(), SettleError> {
            while !done() {
                if !self.is_online() {
                    return Err(SettleError::Offline(port.clone()));
                }
                if std::time::Instant::now() > deadline {
                    return Err(SettleError::Late(format!("{port}: {what}")));
                }
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
            Ok(())
        };
        wait(
            &|| self.sent.load(Ordering::Acquire) >= self.written.load(Ordering::Acquire),
            "outputs sent",
        )?;
        if self.config.digital_out.is_empty() && self.ao.is_empty() {
            return Ok(());
        }
        self.check.store(CHECK_ASKED, Ordering::Release);
        if let Some(w) = self.waker.get() {
            w.wake();
        }
        wait(
            &|| self.check.load(Ordering::Acquire) >= CHECK_OK,
            "outputs confirmed by the board",
        )?;
        if self.check.load(Ordering::Acquire) == CHECK_FAILED {
            let s = self.shared.lock().unwrap_or_else(PoisonError::into_inner);
            return Err(SettleError::Refused(
                s.check_error.iter().cloned().collect(),
            ));
        }
        Ok(())
    }

    /// The output pins and the state each must have: digital outputs their level, PWM and
    /// servo pins their value.
    pub(crate) fn expected_states(&self, into: &mut Vec<(u8, u32)>) {
        into.clear();
        for (i, p) in self.config.digital_out.iter().enumerate() {
            into.push((p.pin, u32::from(self.output(i))));
        }
        for a in &self.ao {
            into.push((a.pin, a.raw.load(Ordering::Acquire)));
        }
    }

    fn writable(&self) -> Result<(), DeviceError> {
        if self.closing.load(Ordering::Acquire) || !self.is_online() {
            return Err(DeviceError::Offline);
        }
        Ok(())
    }

    fn check_online(&self) -> Result<(), DeviceError> {
        if !self.is_online() {
            return Err(DeviceError::Offline);
        }
        Ok(())
    }
}

impl Device for FirmataCard {
    fn health(&self) -> Health {
        Health::online_if(
            self.is_online(),
            self.last_good.load(Ordering::Acquire),
            self.clock.now(),
        )
    }
}

impl AnalogIn for FirmataCard {
    fn channel_count(&self) -> u32 {
        self.ai.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        nth(&self.ai, channel)?;
        Ok(self.ai_scale)
    }

    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let word = nth(&self.ai, channel)?.load(Ordering::Acquire);
        self.check_online()?;
        if word & VALID == 0 {
            let last = self.last_good.load(Ordering::Acquire);
            let age =
                (last != 0).then(|| self.clock.now().duration_since(Timestamp::from_nanos(last)));
            return Err(DeviceError::Stale { age });
        }
        Ok((word & 0xffff) as i64)
    }
}

impl AnalogOut for FirmataCard {
    fn channel_count(&self) -> u32 {
        self.ao.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        let c = nth(&self.ao, channel)?;
        Ok(if c.servo {
            self.servo_scale
        } else {
            self.pwm_scale
        })
    }

    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        let c = nth(&self.ao, channel)?;
        AnalogOut::scale(self, channel)?.check_raw(channel, raw)?;
        self.writable()?;
        c.raw.store(raw as u32, Ordering::Release);
        c.dirty.store(true, Ordering::Release);
        self.wake();
        Ok(())
    }

    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        Ok(i64::from(
            nth(&self.ao, channel)?.raw.load(Ordering::Acquire),
        ))
    }
}

impl DigitalInputImage for FirmataCard {
    fn inputs(&self) -> &BitImage {
        &self.inputs
    }

    /// Online, and every port under `span` reported since (a port the board did not
    /// report yet reads as stale, not as the levels of before).
    fn check_inputs(&self, span: BitSpan) -> Result<(), DeviceError> {
        self.check_online()?;
        let reported = self.reported.load(Ordering::Acquire);
        let all = span.bits().all(|(bit, _)| {
            self.in_ports
                .get(bit as usize)
                .is_some_and(|p| reported >> p & 1 == 1)
        });
        if all {
            return Ok(());
        }
        let last = self.last_good.load(Ordering::Acquire);
        let age = (last != 0).then(|| self.clock.now().duration_since(Timestamp::from_nanos(last)));
        Err(DeviceError::Stale { age })
    }
}

impl DigitalOutputImage for FirmataCard {
    fn outputs(&self) -> &BitImage {
        &self.outputs
    }

    fn check_outputs_writable(&self) -> Result<(), DeviceError> {
        self.writable()
    }

    fn outputs_written(&self, written: Written) {
        let pins = &self.config.digital_out;
        let mark = |i: u32| pins.get(i as usize).map_or(0, |p| 1u32 << (p.pin / 8));
        let ports = match written {
            Written::Bit { bit, .. } => mark(bit),
            Written::Span { span, .. } => span.bits().fold(0, |m, (bit, _)| m | mark(bit)),
        };
        self.dirty_ports.fetch_or(ports, Ordering::AcqRel);
        self.wake();
    }
}

impl EncoderHost for FirmataCard {
    /// `index` is one this card handed to [`CardEncoder`] (the trait's contract), so it is
    /// in range, as every card indexes.
    fn encoder_counter(&self, index: usize) -> &EncoderCounter {
        self.encoders[index].counter()
    }

    fn check_encoder(&self, index: usize) -> Result<(), DeviceError> {
        nth(&self.encoders, index as u32)?;
        self.check_online()
    }

    fn check_writable(&self) -> Result<(), DeviceError> {
        self.writable()
    }
}
