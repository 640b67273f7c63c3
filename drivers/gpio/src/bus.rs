//! A GPIO card's bus side: requesting its lines, and reading their edge events.
//!
//! [`GpioBus::open`] requests the card's lines (one request per chip) and reads the
//! starting state of inputs and encoders. [`GpioBus::service`] then reads every edge event
//! the kernel has queued, without blocking: it keeps the inputs' state, counts lost events
//! (gaps in each line's sequence numbers), decodes the encoders and hands each input's
//! edge to the caller to publish.

use crate::card::{GpioCard, Opened, Setup, Slot};
use crate::config::{Bias, Drive, Edges};
use crate::quad::{Quadrature, Step};
use gpiocdev::line::{self, EdgeDetection, Value};
use gpiocdev_uapi::v2::LineEdgeEvent;
use std::fs::File;
use std::os::fd::AsFd;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

/// One edge of an input, as published on the bus component's `edges` port.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct GpioEdge {
    /// The DigitalIn bit.
    pub bit: u32,
    /// The line's offset on its chip.
    pub offset: u32,
    /// True for a rising edge of the bit (a falling line when it is active low).
    pub rising: bool,
    /// When the kernel saw it (CLOCK_MONOTONIC, ns).
    pub kernel_ns: u64,
    /// Its number among the events of its chip's request.
    pub seqno: u32,
    /// Its number among the events of its line.
    pub line_seqno: u32,
}

/// What an event on a line of the card is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Route {
    Input(u32),
    A(usize),
    B(usize),
    Index(usize),
    Nothing,
}

/// Events read per `read(2)`.
const BATCH: usize = 64;
/// Reads per chip and wake-up at most, so one chatty chip cannot starve the others.
const READS_PER_WAKE: usize = 16;

/// The card's bus side.
pub struct GpioBus {
    card: Arc<GpioCard>,
    routes: Vec<Vec<Route>>,
    last_seq: Vec<Vec<u32>>,
    quads: Vec<Quadrature>,
    buf: Vec<u64>,
}

fn bias(b: Bias) -> Option<line::Bias> {
    match b {
        Bias::AsIs => None,
        Bias::PullUp => Some(line::Bias::PullUp),
        Bias::PullDown => Some(line::Bias::PullDown),
        Bias::Disabled => Some(line::Bias::Disabled),
    }
}

fn edges(e: Edges) -> Option<EdgeDetection> {
    match e {
        Edges::Both => Some(EdgeDetection::BothEdges),
        Edges::Rising => Some(EdgeDetection::RisingEdge),
        Edges::Falling => Some(EdgeDetection::FallingEdge),
        Edges::None => None,
    }
}

impl GpioBus {
    /// The bus side of `card` (nothing requested yet).
    pub fn new(card: Arc<GpioCard>) -> GpioBus {
        let mut routes: Vec<Vec<Route>> = card
            .chips
            .iter()
            .map(|c| vec![Route::Nothing; c.lines.len()])
            .collect();
        let mut put = |s: Slot, r: Route| {
            if let Some(x) = routes
                .get_mut(s.chip)
                .and_then(|c| c.get_mut(s.bit as usize))
            {
                *x = r;
            }
        };
        for (i, (s, _)) in card.inputs.iter().enumerate() {
            put(*s, Route::Input(i as u32));
        }
        for (i, e) in card.encoders.iter().enumerate() {
            put(e.a, Route::A(i));
            put(e.b, Route::B(i));
            if let Some(x) = e.index {
                put(x, Route::Index(i));
            }
        }
        let last_seq = card.chips.iter().map(|c| vec![0; c.lines.len()]).collect();
        let quads = vec![Quadrature::new(false, false); card.encoders.len()];
        GpioBus {
            card,
            routes,
            last_seq,
            quads,
            buf: vec![0; BATCH * LineEdgeEvent::u64_size()],
        }
    }

    /// The card.
    pub fn card(&self) -> &Arc<GpioCard> {
        &self.card
    }

    /// The descriptors to watch (one per chip), once open.
    pub fn fds(&self) -> Vec<std::os::fd::BorrowedFd<'_>> {
        self.card
            .opened
            .get()
            .map(|o| o.iter().map(|x| x.file.as_fd()).collect())
            .unwrap_or_default()
    }

    /// Requests the card's lines (the first time only; outputs at their initial values
    /// from the request on) and reads where inputs and encoders start. An error names the
    /// line and, when another consumer holds it, that consumer.
    pub fn open(&mut self) -> Result<(), String> {
        let card = self.card.clone();
        if card.opened.get().is_none() {
            let mut opened = Vec::new();
            for c in &card.chips {
                opened.push(request(&card, c)?);
            }
            // Only this thread opens: the set cannot fail.
            let _ = card.opened.set(opened);
        }
        card.online.store(true, Ordering::Release);
        for (i, (s, e)) in card.inputs.iter().enumerate() {
            if *e == Edges::Both {
                let v = card.get(s.chip, 1 << s.bit).map_err(|e| e.to_string())?;
                card.input_state[i].store(v != 0, Ordering::Release);
            }
        }
        for (i, e) in card.encoders.iter().enumerate() {
            let a = card
                .get(e.a.chip, 1 << e.a.bit)
                .map_err(|e| e.to_string())?
                != 0;
            let b = card
                .get(e.b.chip, 1 << e.b.bit)
                .map_err(|e| e.to_string())?
                != 0;
            self.quads[i] = Quadrature::new(a, b);
        }
        Ok(())
    }

    /// Reads what the kernel has queued, without blocking, calling `edge` for each input
    /// edge. Real-time: no allocation.
    pub fn service(&mut self, edge: &mut dyn FnMut(&GpioEdge)) {
        let card = self.card.clone();
        let Some(opened) = card.opened.get() else {
            return;
        };
        let size = LineEdgeEvent::u64_size();
        for (chip, o) in opened.iter().enumerate() {
            for _ in 0..READS_PER_WAKE {
                let words = match gpiocdev_uapi::read_event(&o.file, &mut self.buf) {
                    Ok(n) => n,
                    Err(gpiocdev_uapi::Error::Os(gpiocdev_uapi::Errno(e)))
                        if e == libc_eagain() =>
                    {
                        break;
                    }
                    Err(_) => {
                        // The chip is gone (ENODEV) or the read failed: offline.
                        self.card
                            .counters
                            .read_errors
                            .fetch_add(1, Ordering::Relaxed);
                        self.card.online.store(false, Ordering::Release);
                        break;
                    }
                };
                let mut at = 0;
                while at + size <= words {
                    if let Ok(ev) = LineEdgeEvent::from_slice(&self.buf[at..at + size]) {
                        let ev = ev.clone();
                        self.event(chip, &ev, edge);
                    }
                    at += size;
                }
                if words < self.buf.len() {
                    break;
                }
            }
        }
    }

    fn event(&mut self, chip: usize, ev: &LineEdgeEvent, edge: &mut dyn FnMut(&GpioEdge)) {
        let card = &self.card;
        let Some(bit) = card.chips[chip]
            .lines
            .iter()
            .position(|l| l.id.offset == ev.offset)
        else {
            return;
        };
        card.counters.events.fetch_add(1, Ordering::Relaxed);
        card.last_event
            .store(ev.timestamp_ns.max(1), Ordering::Release);
        let last = &mut self.last_seq[chip][bit];
        if *last != 0 && ev.line_seqno > last.wrapping_add(1) {
            card.counters
                .lost_events
                .fetch_add(u64::from(ev.line_seqno - *last - 1), Ordering::Relaxed);
        }
        *last = ev.line_seqno;
        // GPIO_V2_LINE_EVENT_RISING_EDGE = 1, FALLING = 2.
        let rising = ev.kind == 1;
        match self.routes[chip][bit] {
            Route::Input(i) => {
                card.input_state[i as usize].store(rising, Ordering::Release);
                edge(&GpioEdge {
                    bit: i,
                    offset: ev.offset,
                    rising,
                    kernel_ns: ev.timestamp_ns,
                    seqno: ev.seqno,
                    line_seqno: ev.line_seqno,
                });
            }
            Route::A(e) | Route::B(e) => {
                let line = u8::from(matches!(self.routes[chip][bit], Route::B(_)));
                match self.quads[e].edge(line, rising) {
                    Step::Moved(d) => card.encoders[e].counter.advance(d),
                    Step::Error => {
                        card.counters.encoder_errors.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
            Route::Index(e) => {
                if rising {
                    card.counters.index_pulses.fetch_add(1, Ordering::Relaxed);
                    // Cannot fail: 0 is a position of every resolution.
                    let _ = card.encoders[e].counter.set_position(0);
                }
            }
            Route::Nothing => {}
        }
    }
}

fn libc_eagain() -> i32 {
    nix::errno::Errno::EAGAIN as i32
}

/// Requests the lines of one chip.
fn request(card: &GpioCard, c: &crate::card::ChipLines) -> Result<Opened, String> {
    let Some(first) = c.lines.first() else {
        return Err("a chip with no lines".into());
    };
    let chip = &first.id.chip;
    let mut b = gpiocdev::Request::builder();
    b.on_chip(&chip.path).with_consumer(card.consumer.as_str());
    let inputs_with_edges = c
        .lines
        .iter()
        .filter(|l| matches!(l.setup, Setup::Input { edges, .. } if edges != Edges::None))
        .count() as u32;
    let depth = card
        .event_buffer
        .unwrap_or((16 * inputs_with_edges).clamp(16, crate::config::MAX_EVENT_BUFFER));
    b.with_kernel_event_buffer_size(depth);
    for l in &c.lines {
        b.with_line(l.id.offset);
        match l.setup {
            Setup::Input {
                bias: bi,
                active_low,
                debounce_us,
                edges: e,
            } => {
                b.as_input()
                    .with_bias(bias(bi))
                    .with_edge_detection(edges(e));
                if active_low {
                    b.as_active_low();
                }
                if debounce_us > 0 {
                    b.with_debounce_period(Duration::from_micros(u64::from(debounce_us)));
                }
            }
            Setup::Output {
                drive,
                bias: bi,
                active_low,
                initial,
            } => {
                b.as_output(if initial {
                    Value::Active
                } else {
                    Value::Inactive
                })
                .with_bias(bias(bi))
                .with_drive(match drive {
                    Drive::PushPull => line::Drive::PushPull,
                    Drive::OpenDrain => line::Drive::OpenDrain,
                    Drive::OpenSource => line::Drive::OpenSource,
                });
                if active_low {
                    b.as_active_low();
                }
            }
        }
    }
    let request = b.request().map_err(|e| {
        // Name who holds a line, when one is held.
        for l in &c.lines {
            if let Ok(now) = crate::chips::line(
                Some(&chip.path.to_string_lossy()),
                &crate::config::LineRef::Offset(l.id.offset),
            ) && let Some(who) = &now.used_by
            {
                return format!("{now} is used by {who:?}: it cannot be requested ({e})");
            }
        }
        format!(
            "{} ({}): requesting lines {:?}: {e}",
            chip.name,
            chip.label,
            c.lines.iter().map(|l| l.id.offset).collect::<Vec<_>>()
        )
    })?;
    // Line values address the lines by their index in the request: it must be ours.
    let order: Vec<u32> = c.lines.iter().map(|l| l.id.offset).collect();
    if request.config().lines() != &order {
        return Err(format!(
            "{}: the request has lines {:?}, the card expected {order:?}",
            chip.name,
            request.config().lines()
        ));
    }
    let fd = request
        .as_fd()
        .try_clone_to_owned()
        .map_err(|e| format!("{}: {e}", chip.name))?;
    let flags = nix::fcntl::fcntl(&fd, nix::fcntl::FcntlArg::F_GETFL)
        .map_err(|e| format!("{}: {e}", chip.name))?;
    let flags = nix::fcntl::OFlag::from_bits_truncate(flags) | nix::fcntl::OFlag::O_NONBLOCK;
    nix::fcntl::fcntl(&fd, nix::fcntl::FcntlArg::F_SETFL(flags))
        .map_err(|e| format!("{}: {e}", chip.name))?;
    Ok(Opened {
        _request: request,
        file: File::from(fd),
    })
}
