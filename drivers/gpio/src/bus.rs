//! A GPIO card's bus side: requesting its lines, and reading their edge events.
//!
//! [`GpioBus::open`] requests the card's lines (one request per chip) and reads the
//! starting state of inputs and encoders. [`GpioBus::service`] then reads every edge event
//! the kernel has queued, without blocking: it keeps the inputs' state, counts lost events
//! (gaps in each line's sequence numbers), decodes the encoders and hands each input's
//! edge to the caller to publish.
//!
//! A chip that goes away takes the card offline. The loss is seen when a read fails with
//! `ENODEV` — the rig's 6.12 kernel wakes the request's descriptor when its chip is
//! removed — or, where no wake comes (older kernels may not send one), by
//! [`GpioBus::check_alive`] every [`CHECK_PERIOD`]. [`GpioBus::close_lost`] then closes the
//! request and [`GpioBus::reopen`], every [`CHECK_PERIOD`], looks for the chip — at its old
//! path or under a new number, by label and number of lines, our lines free and their
//! names unchanged — and requests its lines anew, outputs at the level last written to
//! them. Inputs and encoders start again from where their lines stand then; edges while
//! the chip was away are not seen (an encoder's count keeps its value from before).

use crate::card::{GpioCard, Opened, Slot};
use crate::chips::ChipId;
use crate::config::Edges;
use crate::quad::{Quadrature, Step};
use crate::request::{LinesError, request};
use gpiocdev_uapi::v2::LineEdgeEvent;
use rtt::activity::ActivityError;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, RawFd};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

/// How often the bus side checks that its chips are there, and looks for one that went
/// away.
pub const CHECK_PERIOD: Duration = Duration::from_millis(500);

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
    /// Per chip: its reads failed (it went away) and its request is still to be closed
    /// or made anew.
    lost: Vec<bool>,
    /// Per chip: where it was last found.
    was: Vec<ChipId>,
    /// Why the last look for a lost chip failed (logged when it changes).
    why_not: Option<String>,
    /// The chips are requested but where the lines stand could not be read yet.
    unsettled: bool,
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
        let was = card
            .chips
            .iter()
            .map(|c| c.lines[0].id.chip.clone())
            .collect();
        GpioBus {
            lost: vec![false; card.chips.len()],
            card,
            routes,
            last_seq,
            quads,
            buf: vec![0; BATCH * LineEdgeEvent::u64_size()],
            was,
            why_not: None,
            unsettled: false,
        }
    }

    /// The card.
    pub fn card(&self) -> &Arc<GpioCard> {
        &self.card
    }

    /// Calls `f` with each chip's request descriptor (one per chip that is open).
    pub fn for_each_fd<E>(
        &self,
        mut f: impl FnMut(BorrowedFd<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        for i in 0..self.card.chips.len() {
            if let Some(slot) = self.card.request(i)
                && let Some(o) = slot.as_ref()
            {
                f(o.file.as_fd())?;
            }
        }
        Ok(())
    }

    /// True while a chip of the card is lost (gone, or not found again yet) or its lines
    /// could not be read since it came back.
    pub fn is_missing(&self) -> bool {
        self.unsettled || self.lost.iter().any(|l| *l)
    }

    /// Requests the card's lines on every chip not requested yet, or whose request's chip
    /// went away while the bus side was stopped (outputs at their initial values, or the
    /// level last written, from the request on), reads where inputs and encoders start and
    /// puts the card online. An error names the line and, when another consumer holds it,
    /// that consumer.
    pub fn open(&mut self) -> Result<(), LinesError> {
        self.check_alive();
        self.close_lost(&mut |_| ());
        for i in 0..self.card.chips.len() {
            if self.card.with_request(i, |_| ()).is_ok() {
                continue;
            }
            let o = self.find(i)?;
            self.put(i, o);
        }
        Ok(self.settle()?)
    }

    /// Reads one line of every chip that is requested and not known lost (one ioctl
    /// each); a chip that is gone is marked lost and the card offline. True when one was.
    pub fn check_alive(&mut self) -> bool {
        let mut newly = false;
        for i in 0..self.card.chips.len() {
            if self.lost[i] {
                continue;
            }
            let probe = self.card.with_request(i, |f| {
                let mut lv = gpiocdev_uapi::v2::LineValues { bits: 0, mask: 1 };
                gpiocdev_uapi::v2::get_line_values(f, &mut lv)
            });
            if let Ok(Err(e)) = probe
                && crate::card::is_gone(&e)
            {
                self.mark_lost(i);
                newly = true;
            }
        }
        newly
    }

    fn mark_lost(&mut self, chip: usize) {
        let counters = &self.card.counters;
        counters.chips_lost.fetch_add(1, Ordering::Relaxed);
        self.card.online.store(false, Ordering::Release);
        self.lost[chip] = true;
    }

    /// Finds chip `i` where it is now and requests its lines.
    fn find(&self, i: usize) -> Result<Opened, LinesError> {
        let named: Vec<(u32, &str)> = self.card.chips[i]
            .lines
            .iter()
            .filter(|l| !l.id.name.is_empty())
            .map(|l| (l.id.offset, l.id.name.as_str()))
            .collect();
        let offsets: Vec<u32> = self.card.chips[i]
            .lines
            .iter()
            .map(|l| l.id.offset)
            .collect();
        let id = crate::chips::again(&self.was[i], &offsets, &named)?;
        request(&self.card, i, id)
    }

    fn put(&mut self, i: usize, o: Opened) {
        self.was[i] = o.chip.clone();
        self.lost[i] = false;
        // A new request numbers its lines' events from 1 again.
        self.last_seq[i].iter_mut().for_each(|s| *s = 0);
        if let Some(mut slot) = self.card.request(i) {
            *slot = Some(o);
        }
    }

    /// Reads where the inputs and encoders stand and puts the card online.
    fn settle(&mut self) -> Result<(), device_interface::DeviceError> {
        self.unsettled = true;
        let card = self.card.clone();
        for (i, (s, e)) in card.inputs.iter().enumerate() {
            if *e == Edges::Both {
                let v = card.get_unchecked(s.chip, 1 << s.bit)?;
                card.input_state[i].store(v != 0, Ordering::Release);
            }
        }
        for (i, e) in card.encoders.iter().enumerate() {
            let a = card.get_unchecked(e.a.chip, 1 << e.a.bit)? != 0;
            let b = card.get_unchecked(e.b.chip, 1 << e.b.bit)? != 0;
            self.quads[i] = Quadrature::new(a, b);
        }
        self.unsettled = false;
        card.online.store(true, Ordering::Release);
        Ok(())
    }

    /// Closes the requests of the chips that went away, calling `unwatch` with each one's
    /// descriptor first.
    pub fn close_lost(&mut self, unwatch: &mut dyn FnMut(RawFd)) {
        for i in 0..self.lost.len() {
            if !self.lost[i] {
                continue;
            }
            let Some(o) = self.card.request(i).and_then(|mut slot| slot.take()) else {
                continue;
            };
            unwatch(o.file.as_raw_fd());
            tracing::warn!(
                "GPIO chip {} ({}) went away: its card is offline; looking for it every {:?}",
                o.chip.name,
                o.chip.label,
                CHECK_PERIOD
            );
        }
    }

    /// Looks for the chips that went away and requests their lines anew, calling `watch`
    /// with each new descriptor; the card is online again when all are back. True when
    /// none is missing any more.
    pub fn reopen(
        &mut self,
        watch: &mut dyn FnMut(BorrowedFd<'_>) -> Result<(), ActivityError>,
    ) -> bool {
        for i in 0..self.lost.len() {
            if !self.lost[i] {
                continue;
            }
            let found = self
                .find(i)
                .and_then(|o| watch(o.file.as_fd()).map(|()| o).map_err(LinesError::from));
            match found {
                Ok(o) => {
                    tracing::info!(
                        "GPIO chip {} ({}) is back as {}: its lines are requested again",
                        o.chip.name,
                        o.chip.label,
                        o.chip.path.display()
                    );
                    self.put(i, o);
                    self.card
                        .counters
                        .chips_back
                        .fetch_add(1, Ordering::Relaxed);
                }
                Err(why) => {
                    let why = why.to_string();
                    if self.why_not.as_ref() != Some(&why) {
                        tracing::warn!("GPIO chip {}: not back yet: {why}", self.was[i].label);
                        self.why_not = Some(why);
                    }
                    return false;
                }
            }
        }
        self.why_not = None;
        match self.settle() {
            Ok(()) => true,
            Err(e) => {
                tracing::warn!("GPIO card: its chips are back but its lines cannot be read: {e}");
                false
            }
        }
    }

    /// Reads what the kernel has queued, without blocking, calling `edge` for each input
    /// edge. True when a chip went away this time (then call
    /// [`close_lost`](Self::close_lost)). Real-time: no allocation.
    pub fn service(&mut self, edge: &mut dyn FnMut(&GpioEdge)) -> bool {
        let card = self.card.clone();
        let mut newly_lost = false;
        let size = LineEdgeEvent::u64_size();
        for chip in 0..card.chips.len() {
            if self.lost[chip] {
                continue;
            }
            for _ in 0..READS_PER_WAKE {
                let read = card.with_request(chip, |f| gpiocdev_uapi::read_event(f, &mut self.buf));
                let Ok(read) = read else {
                    break;
                };
                let words = match read {
                    Ok(n) => n,
                    Err(gpiocdev_uapi::Error::Os(gpiocdev_uapi::Errno(e)))
                        if e == libc_eagain() =>
                    {
                        break;
                    }
                    Err(e) => {
                        card.counters.read_errors.fetch_add(1, Ordering::Relaxed);
                        // The chip is gone: offline until it is found again. Another
                        // error is counted, the request kept (closing it would let go
                        // of the outputs).
                        if crate::card::is_gone(&e) {
                            self.mark_lost(chip);
                            newly_lost = true;
                        }
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
        newly_lost
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
