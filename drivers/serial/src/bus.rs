//! A Firmata card's bus side: the serial line opened, the board's hand-shake, its set-up,
//! then reports decoded into the card and marked outputs sent — one step at a time on the
//! card's file-descriptor activity, never blocking.
//!
//! The hand-shake: the port is opened (an Uno resets on DTR), the board's version is
//! awaited for `banner_ms` — nothing is sent meanwhile, so no command is lost to a
//! resetting board — then asked for; the firmware, capabilities and analog mapping are
//! queried; the section is checked against them (a mismatch *refuses* the board: the
//! error says what and where, and the port is closed). The set-up then sends the pin
//! modes, the outputs (as the card holds them: initial values, or the last written), the
//! sampling interval and the reports, and the card goes online once every reported port
//! has sent its levels (or after [`REPORT_WAIT`]).
//!
//! Online, a line quiet for [`PROBE_AFTER`] is probed with a version query; quiet for
//! [`SILENCE_LIMIT`], or a read error or hang-up (the port unplugged), takes the card
//! offline and the port is opened again after [`FIRST_BACKOFF`], doubling up to
//! [`MAX_BACKOFF`]; a port that comes back (at its path, or its stable name pointing
//! elsewhere) is set up again from scratch.

mod setup;

use crate::board::BoardInfo;
use crate::card::FirmataCard;
use crate::line::{Line, Opener, open_port, send};
use crate::protocol::{Decoder, Frame, sysex, write};
use device_interface::time::Timestamp;
use std::io;
use std::os::fd::BorrowedFd;
use std::sync::atomic::Ordering;
use std::sync::{Arc, PoisonError};
use std::time::Duration;

/// The first wait before opening a port again.
pub const FIRST_BACKOFF: Duration = Duration::from_millis(100);
/// The longest wait between opens.
pub const MAX_BACKOFF: Duration = Duration::from_secs(5);
/// How long each of the version, description and report phases may take.
pub const REPLY_WAIT: Duration = Duration::from_secs(2);
/// How long the set-up waits for the first reports of the digital inputs' ports.
pub const REPORT_WAIT: Duration = Duration::from_secs(1);
/// A quiet line is probed after this.
pub const PROBE_AFTER: Duration = Duration::from_secs(1);
/// A line quiet this long is lost.
pub const SILENCE_LIMIT: Duration = Duration::from_millis(3500);
/// The most bytes one step takes off the line: a flood (a board gone mad, a fast native
/// USB port) cannot keep the bus side from its timers and outputs; it is called again at
/// once for the rest.
pub const MAX_RX_PER_STEP: usize = 16 * 1024;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Waiting for the version the board sends when it starts.
    Banner,
    /// The version was asked for.
    Version,
    /// Capabilities and mapping asked for.
    Describe,
    /// Set up; waiting for the first reports of these ports (bit mask).
    Reports(u32),
}

enum Link {
    Closed {
        retry_at: Timestamp,
    },
    Handshake {
        line: Box<dyn Line>,
        phase: Phase,
        deadline: Timestamp,
        board: BoardInfo,
        caps: bool,
        map: bool,
    },
    Online {
        line: Box<dyn Line>,
        last_rx: Timestamp,
        probe_at: Timestamp,
    },
}

/// How a step left the link, for the start hook.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    /// Online.
    Online,
    /// Still shaking hands.
    Pending,
    /// Closed after a failure (retrying later).
    Closed,
    /// The board does not have what the section asks for.
    Refused(String),
}

/// The card's bus side.
pub struct FirmataBus {
    card: Arc<FirmataCard>,
    open: Opener,
    link: Link,
    decoder: Decoder,
    backoff: Duration,
    /// Bumped at each open: the component watches the new descriptor.
    generation: u64,
    tx: Vec<u8>,
    rx: Vec<u8>,
    /// The last sysex payload (capacity [`MAX_SYSEX`](crate::protocol::MAX_SYSEX), made once).
    sysex: Vec<u8>,
    /// Output pins whose state the settle check still waits for, and the state.
    checks: Vec<(u8, u32)>,
    refused: Option<String>,
    /// The refused port's device (see [`identity`](crate::line::identity)): it is not
    /// opened again (an Uno resets when opened) until its path leads to another.
    refused_port: Option<(u64, u64, u64, i64)>,
    /// The board takes SET_DIGITAL_PIN_VALUE (protocol 2.5 on): outputs pin by pin.
    pin_writes: bool,
    /// The last step stopped reading at [`MAX_RX_PER_STEP`]: more is waiting.
    more: bool,
    was_online: bool,
}

fn after(t: Timestamp, d: Duration) -> Timestamp {
    Timestamp::from_nanos(t.as_nanos().saturating_add(d.as_nanos() as u64))
}

impl FirmataBus {
    /// The bus side of `card`, opening real ports.
    pub fn new(card: Arc<FirmataCard>) -> FirmataBus {
        FirmataBus::with_opener(card, Box::new(open_port))
    }

    /// The same over lines `open` makes (a test's).
    pub fn with_opener(card: Arc<FirmataCard>, open: Opener) -> FirmataBus {
        let now = card.now();
        FirmataBus {
            card,
            open,
            link: Link::Closed { retry_at: now },
            decoder: Decoder::new(),
            backoff: FIRST_BACKOFF,
            generation: 0,
            tx: Vec::with_capacity(1024),
            rx: vec![0; 4096],
            sysex: Vec::with_capacity(crate::protocol::MAX_SYSEX),
            checks: Vec::with_capacity(crate::board::MAX_PINS),
            refused: None,
            refused_port: None,
            pin_writes: false,
            more: false,
            was_online: false,
        }
    }

    /// The card.
    pub fn card(&self) -> &Arc<FirmataCard> {
        &self.card
    }

    /// The open line's descriptor and its generation (bumped at each open).
    pub fn fd(&self) -> Option<(BorrowedFd<'_>, u64)> {
        match &self.link {
            Link::Closed { .. } => None,
            Link::Handshake { line, .. } | Link::Online { line, .. } => {
                Some((line.fd(), self.generation))
            }
        }
    }

    /// Closes the line (the bus side stops); the next step opens it again, a refused board
    /// too. An online board is asked to stop its reports first (its outputs stay as they
    /// are): a quiet line for whoever opens the port next.
    pub fn release(&mut self) {
        if let Link::Online { line, .. } = &mut self.link {
            self.tx.clear();
            let c = &self.card.config;
            for ch in &c.analog_in {
                write::report_analog(&mut self.tx, ch.channel, false);
            }
            let ports = c.digital_in.iter().fold(0u32, |m, p| m | 1 << (p.pin / 8));
            for port in (0..16).filter(|p| ports & 1 << p != 0) {
                write::report_digital(&mut self.tx, port, false);
            }
            if !c.encoder.is_empty() {
                write::encoder(&mut self.tx, crate::protocol::encoder::REPORT_AUTO, &[0]);
            }
            // Best effort: the port is closed next whatever happens.
            let _ = send(line.as_mut(), &self.tx, &self.card.bytes_sent);
        }
        self.close(None);
        self.forget_refusal();
        self.backoff = FIRST_BACKOFF;
        self.link = Link::Closed {
            retry_at: self.card.now(),
        };
    }

    /// Forgets that the board was refused: the next step opens its port (a start asked
    /// for again tries it again).
    pub fn forget_refusal(&mut self) {
        self.refused = None;
        self.refused_port = None;
        if let Link::Closed { retry_at } = &mut self.link {
            *retry_at = (*retry_at).min(self.card.now());
        }
    }

    fn set_link(&self, link: &'static str, error: Option<String>) {
        let mut s = self
            .card
            .shared
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        s.link = link;
        s.line = self.decoder.counts();
        if let Some(e) = error {
            if s.last_error.as_deref() != Some(e.as_str()) {
                tracing::warn!(port = %self.card.config.port, "{e}");
            }
            s.last_error = Some(e);
        }
    }

    /// Closes after `why` (None: asked to), and waits the backoff.
    fn close(&mut self, why: Option<String>) {
        let now = self.card.now();
        if self.card.is_online() {
            self.card.set_online(false);
            self.card.reopens.fetch_add(1, Ordering::Relaxed);
        } else if why.is_some() {
            self.card.open_failures.fetch_add(1, Ordering::Relaxed);
        }
        self.link = Link::Closed {
            retry_at: after(now, self.backoff),
        };
        self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
        self.decoder.reset();
        let refused = self.refused.is_some();
        self.set_link(if refused { "refused" } else { "closed" }, why);
    }

    /// Services the line at `now`; returns when to be called again at the latest.
    pub fn step(&mut self, now: Timestamp) -> (Outcome, Timestamp) {
        if let Link::Closed { retry_at } = self.link {
            if now < retry_at {
                return (self.outcome(), retry_at);
            }
            if self.refused_port.is_some()
                && crate::line::identity(&self.card.config.port) == self.refused_port
            {
                // Still the board that was refused: looked at again later, not opened.
                let retry_at = after(now, MAX_BACKOFF);
                self.link = Link::Closed { retry_at };
                return (self.outcome(), retry_at);
            }
            self.open_line(now);
        }
        match self.receive(now) {
            Ok(more) => self.more = more,
            Err(e) => {
                self.close(Some(e));
                return (self.outcome(), self.deadline(now));
            }
        }
        if let Err(e) = self.timers(now) {
            self.close(Some(e));
        } else if let Err(e) = self.send_outputs().and_then(|()| self.query_states()) {
            self.close(Some(e));
        }
        (self.outcome(), self.deadline(now))
    }

    fn outcome(&self) -> Outcome {
        match (&self.link, &self.refused) {
            (Link::Online { .. }, _) => Outcome::Online,
            (Link::Handshake { .. }, _) => Outcome::Pending,
            (Link::Closed { .. }, Some(e)) => Outcome::Refused(e.clone()),
            (Link::Closed { .. }, None) => Outcome::Closed,
        }
    }

    fn deadline(&self, now: Timestamp) -> Timestamp {
        if self.more && !matches!(self.link, Link::Closed { .. }) {
            return now;
        }
        match &self.link {
            Link::Closed { retry_at } => *retry_at,
            Link::Handshake { deadline, .. } => *deadline,
            Link::Online {
                probe_at, last_rx, ..
            } => (*probe_at).min(after(*last_rx, SILENCE_LIMIT)).max(now),
        }
    }

    fn open_line(&mut self, now: Timestamp) {
        let port = self.card.config.port.clone();
        match (self.open)(&port, self.card.config.baud) {
            Ok(line) => {
                self.generation += 1;
                self.decoder.reset();
                self.link = Link::Handshake {
                    line,
                    phase: Phase::Banner,
                    deadline: after(
                        now,
                        Duration::from_millis(u64::from(self.card.config.banner_ms)),
                    ),
                    board: BoardInfo::default(),
                    caps: false,
                    map: false,
                };
                self.set_link("opening", None);
            }
            Err(e) => self.close(Some(format!("cannot open {port}: {e}"))),
        }
    }

    /// Reads what the line has, up to [`MAX_RX_PER_STEP`] bytes, and takes each frame;
    /// true when it stopped at that bound with more waiting.
    fn receive(&mut self, now: Timestamp) -> Result<bool, String> {
        let mut taken = 0;
        loop {
            if taken >= MAX_RX_PER_STEP {
                return Ok(true);
            }
            let n = match &mut self.link {
                Link::Closed { .. } => return Ok(false),
                Link::Handshake { line, .. } | Link::Online { line, .. } => match line
                    .read(&mut self.rx)
                {
                    Ok(0) => return Err(format!("{}: the port hung up", self.card.config.port)),
                    Ok(n) => n,
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(false),
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                    Err(e) => {
                        return Err(format!("{}: read: {e} (unplugged?)", self.card.config.port));
                    }
                },
            };
            taken += n;
            for i in 0..n {
                let byte = self.rx[i];
                let frame = match self.decoder.push(byte) {
                    None => continue,
                    Some(Frame::Version { major, minor }) => Owned::Version { major, minor },
                    Some(Frame::Digital { port, value }) => Owned::Digital { port, value },
                    Some(Frame::Analog { channel, value }) => Owned::Analog { channel, value },
                    Some(Frame::Sysex { command, data }) => {
                        self.sysex.clear();
                        self.sysex.extend_from_slice(data);
                        Owned::Sysex { command }
                    }
                };
                self.take(frame, now)?;
            }
            self.set_link_counts();
        }
    }

    fn set_link_counts(&self) {
        let mut s = self
            .card
            .shared
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        s.line = self.decoder.counts();
    }

    /// Takes one frame.
    fn take(&mut self, frame: Owned, now: Timestamp) -> Result<(), String> {
        match &mut self.link {
            Link::Closed { .. } => Ok(()),
            Link::Online {
                last_rx, probe_at, ..
            } => {
                *last_rx = now;
                *probe_at = after(now, PROBE_AFTER);
                self.card.alive(now);
                self.report(&frame);
                Ok(())
            }
            Link::Handshake { .. } => self.handshake(frame, now),
        }
    }

    fn report(&mut self, frame: &Owned) {
        match frame {
            Owned::Digital { port, value } => self.card.digital_report(*port, *value),
            Owned::Analog { channel, value } => self.card.analog_report(*channel, *value),
            Owned::Sysex { command } if *command == sysex::PIN_STATE_RESPONSE => {
                self.pin_state();
            }
            Owned::Sysex { command } if *command == sysex::ENCODER_DATA => {
                let (positions, _) = crate::protocol::encoder_positions(&self.sysex);
                for (i, p) in positions {
                    self.card.encoder_report(i, p);
                }
            }
            _ => {}
        }
    }

    /// A frame during the hand-shake.
    fn handshake(&mut self, frame: Owned, now: Timestamp) -> Result<(), String> {
        let Link::Handshake {
            line,
            phase,
            deadline,
            board,
            caps,
            map,
        } = &mut self.link
        else {
            return Ok(());
        };
        match (&frame, *phase) {
            (Owned::Version { major, minor }, Phase::Banner | Phase::Version) => {
                board.protocol = (*major, *minor);
                self.tx.clear();
                write::query(&mut self.tx, sysex::REPORT_FIRMWARE);
                write::query(&mut self.tx, sysex::CAPABILITY_QUERY);
                write::query(&mut self.tx, sysex::ANALOG_MAPPING_QUERY);
                send(line.as_mut(), &self.tx, &self.card.bytes_sent)?;
                *phase = Phase::Describe;
                *deadline = after(now, REPLY_WAIT);
            }
            (Owned::Sysex { command }, Phase::Describe) => {
                let data = self.sysex.as_slice();
                match *command {
                    sysex::REPORT_FIRMWARE => board.set_firmware(data),
                    sysex::CAPABILITY_RESPONSE => {
                        board.set_capabilities(data).map_err(|e| e.to_string())?;
                        *caps = true;
                    }
                    sysex::ANALOG_MAPPING_RESPONSE => {
                        board.set_mapping(data).map_err(|e| e.to_string())?;
                        *map = true;
                    }
                    _ => {}
                }
                if *caps && *map {
                    return self.set_up(now);
                }
            }
            (Owned::Digital { port, value }, Phase::Reports(waiting)) => {
                self.card.digital_report(*port, *value);
                let left = waiting & !(1 << port);
                *phase = Phase::Reports(left);
                if left == 0 {
                    self.go_online(now);
                }
            }
            (other, Phase::Reports(_)) => self.report(other),
            _ => {}
        }
        Ok(())
    }

    fn go_online(&mut self, now: Timestamp) {
        let link = std::mem::replace(&mut self.link, Link::Closed { retry_at: now });
        let Link::Handshake { line, .. } = link else {
            self.link = link;
            return;
        };
        self.link = Link::Online {
            line,
            last_rx: now,
            probe_at: after(now, PROBE_AFTER),
        };
        self.backoff = FIRST_BACKOFF;
        self.card.opens.fetch_add(1, Ordering::Relaxed);
        self.card.alive(now);
        self.card.set_online(true);
        if self.was_online {
            tracing::info!(port = %self.card.config.port, "board back online");
        }
        self.was_online = true;
        self.set_link("online", None);
    }

    /// Deadlines: the hand-shake's phases, the online line's probes and silence.
    fn timers(&mut self, now: Timestamp) -> Result<(), String> {
        let port = &self.card.config.port;
        match &mut self.link {
            Link::Closed { .. } => Ok(()),
            Link::Handshake {
                line,
                phase,
                deadline,
                ..
            } => {
                if now < *deadline {
                    return Ok(());
                }
                match *phase {
                    Phase::Banner => {
                        self.tx.clear();
                        write::version_query(&mut self.tx);
                        send(line.as_mut(), &self.tx, &self.card.bytes_sent)?;
                        *phase = Phase::Version;
                        *deadline = after(now, REPLY_WAIT);
                        Ok(())
                    }
                    Phase::Version => Err(format!(
                        "{port}: no Firmata board answers (no version within {} ms of opening, nor when asked)",
                        self.card.config.banner_ms + REPLY_WAIT.as_millis() as u32
                    )),
                    Phase::Describe => Err(format!(
                        "{port}: the board did not describe itself (capability and analog mapping queries unanswered)"
                    )),
                    Phase::Reports(_) => {
                        self.go_online(now);
                        Ok(())
                    }
                }
            }
            Link::Online {
                line,
                last_rx,
                probe_at,
                ..
            } => {
                if now >= after(*last_rx, SILENCE_LIMIT) {
                    return Err(format!(
                        "{port}: the board fell silent (no answer for {} ms)",
                        SILENCE_LIMIT.as_millis()
                    ));
                }
                if now >= *probe_at {
                    self.tx.clear();
                    write::version_query(&mut self.tx);
                    send(line.as_mut(), &self.tx, &self.card.bytes_sent)?;
                    self.card.probes.fetch_add(1, Ordering::Relaxed);
                    *probe_at = after(now, PROBE_AFTER);
                }
                Ok(())
            }
        }
    }

    /// Sends the outputs the devices marked: the marked ports whole (protocol 2.4), or
    /// each output pin of them (2.5 on, SET_DIGITAL_PIN_VALUE: pins hwgw does not drive
    /// are not written).
    fn send_outputs(&mut self) -> Result<(), String> {
        let Link::Online { line, .. } = &mut self.link else {
            return Ok(());
        };
        let written = self.card.written.load(Ordering::Acquire);
        let ports = self.card.dirty_ports.swap(0, Ordering::AcqRel);
        self.tx.clear();
        if self.pin_writes {
            for (i, p) in self.card.config.digital_out.iter().enumerate() {
                if ports >> (p.pin / 8) & 1 == 1 {
                    write::digital_pin(&mut self.tx, p.pin, self.card.output(i));
                }
            }
        } else {
            for port in 0..16u8 {
                if ports & 1 << port != 0 {
                    write::digital_port(&mut self.tx, port, setup::port_value(&self.card, port));
                }
            }
        }
        for a in &self.card.ao {
            if a.dirty.swap(false, Ordering::AcqRel) {
                write::analog(&mut self.tx, a.pin, a.raw.load(Ordering::Acquire));
            }
        }
        if !self.tx.is_empty() {
            send(line.as_mut(), &self.tx, &self.card.bytes_sent)?;
        }
        self.card.sent.fetch_max(written, Ordering::AcqRel);
        Ok(())
    }
}

/// A frame taken off the decoder (a sysex's payload is copied into the bus's own buffer,
/// made once: the decoder's is reused by the next byte).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Owned {
    Version { major: u8, minor: u8 },
    Digital { port: u8, value: u8 },
    Analog { channel: u8, value: u16 },
    Sysex { command: u8 },
}
