//! A comedi card's bus side: opens the board (and opens it again after it went away),
//! and samples every input each poll period.
//!
//! Opening checks that the board is the one the card was built for (its description,
//! subdevice by subdevice), then sets up the outputs before anything drives them: levels
//! and values hwgw wrote (or the section's `initial`) are written, the others read from
//! the board; DIO channels are then made outputs or inputs, and each direction read back
//! (a board that sets one direction for a whole subdevice, like the parallel port's data
//! lines, cannot have inputs and outputs there: refused, naming the channels).
//!
//! A poll reads each analog input in its selected range and reference (one
//! `comedi_data_read` each), the digital inputs one `comedi_dio_bitfield2` per subdevice
//! window of 32 channels, and each counter (a card with no inputs reads one output back
//! instead, so that it notices a board gone). A call failing because the board is gone
//! (`ENODEV`, `ENXIO`, `EBADF`, `EIO`) takes the card offline at once, three other failures
//! in a row too; an offline board is closed and opened again after 100 ms, doubling to 5 s.

use crate::board::{BoardDesc, ComediError, Daq};
use crate::card::{ComediCard, pack, unpack};
use crate::layout::{BitChan, listing};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Opens a board by path: [`Board::open`](crate::board::Board::open), or a test's stand-in.
pub type Opener = Box<dyn FnMut(&str) -> Result<Box<dyn Daq>, ComediError> + Send>;

/// Failures in a row (other than the board being gone) that take the card offline.
pub const FAILS_TO_OFFLINE: u32 = 3;
/// The first wait before opening a board again.
pub const FIRST_BACKOFF: Duration = Duration::from_millis(100);
/// The longest.
pub const MAX_BACKOFF: Duration = Duration::from_secs(5);

/// Digital inputs read with one bit-field call: subdevice, base channel, and each
/// (input bit, channel - base).
type Window = (u32, u32, Vec<(u32, u32)>);

/// The bus side of a card.
pub struct ComediBus {
    card: Arc<ComediCard>,
    desc: BoardDesc,
    open: Opener,
    next_open: Option<Instant>,
    backoff: Duration,
    fails: u32,
    windows: Vec<Window>,
    /// The board cannot have the section's directions: never opened again.
    refused: bool,
    /// An analog output the board reads back (the liveness read of a card with no inputs).
    probe_ao: Option<usize>,
}

impl ComediBus {
    /// The bus side of `card`, whose board was `desc` at build, opened with `open`.
    pub fn new(card: Arc<ComediCard>, desc: BoardDesc, open: Opener) -> ComediBus {
        let mut windows: Vec<Window> = Vec::new();
        for (bit, c) in card.di.iter().enumerate() {
            let base = c.channel & !31;
            let entry = (bit as u32, c.channel - base);
            match windows
                .iter_mut()
                .find(|w| w.0 == c.subdevice && w.1 == base)
            {
                Some(w) => w.2.push(entry),
                None => windows.push((c.subdevice, base, vec![entry])),
            }
        }
        ComediBus {
            card,
            desc,
            open,
            next_open: None,
            backoff: FIRST_BACKOFF,
            fails: 0,
            windows,
            refused: false,
            probe_ao: None,
        }
    }

    /// Its card.
    pub fn card(&self) -> &Arc<ComediCard> {
        &self.card
    }

    /// One poll period: opens the board when due, or samples the inputs.
    pub fn step(&mut self, now: Instant) {
        if self.card.is_online() {
            self.poll(now);
            return;
        }
        // Gone (here or in a device call): closed before it is opened again.
        if self.close() {
            self.next_open = Some(now + self.backoff);
        }
        let closing = self.card.closing.load(Ordering::Acquire);
        if closing || self.refused || self.next_open.is_some_and(|t| now < t) {
            return;
        }
        match self.open_board() {
            Ok(()) => {
                self.backoff = FIRST_BACKOFF;
                self.fails = 0;
                self.next_open = None;
                tracing::info!(board = %self.card.path(), "comedi board open");
                // Its first poll at once: no input answers from before it was opened.
                self.poll(now);
            }
            Err(e) => {
                self.card.failed(&e);
                self.next_open = Some(now + self.backoff);
                self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
            }
        }
    }

    /// Closes the board if it is open; its inputs' samples are dropped (none is served as
    /// current after it is opened again). True if it was open.
    fn close(&self) -> bool {
        let was_open = self.card.lock().take().is_some();
        self.card.fresh.store(false, Ordering::Release);
        for a in &self.card.ai {
            a.sample.store(0, Ordering::Release);
        }
        was_open
    }

    /// Runs one call on the open board.
    fn call<T>(
        &self,
        f: impl FnOnce(&mut dyn Daq) -> Result<T, ComediError>,
    ) -> Option<Result<T, ComediError>> {
        let mut board = self.card.lock();
        board.as_mut().map(|b| f(b.as_mut()))
    }

    fn poll(&mut self, now: Instant) {
        match self.sample() {
            Some(Ok(())) => {
                self.fails = 0;
                self.card.polls.fetch_add(1, Ordering::AcqRel);
                self.card.fresh.store(true, Ordering::Release);
                self.card
                    .last_good
                    .store(self.card.now().as_nanos().max(1), Ordering::Release);
            }
            Some(Err(e)) => {
                self.card.failed(&e);
                self.fails += 1;
                if !e.gone()
                    && self.fails >= FAILS_TO_OFFLINE
                    && self.card.online.swap(false, Ordering::AcqRel)
                {
                    self.card.went_offline.fetch_add(1, Ordering::Relaxed);
                }
                if !self.card.is_online() {
                    tracing::warn!(board = %self.card.path(), error = %e, "comedi board offline");
                    self.close();
                    self.next_open = Some(now + self.backoff);
                }
            }
            None => {}
        }
    }

    /// Reads every input once; stops at the first failure.
    fn sample(&self) -> Option<Result<(), ComediError>> {
        let card = &self.card;
        for a in &card.ai {
            let range = a.range.load(Ordering::Acquire);
            let aref = a.aref.load(Ordering::Acquire);
            let c = &a.chan;
            match self.call(|b| b.data_read(c.subdevice, c.channel, range, aref))? {
                Ok(raw) => a.sample.store(pack(raw, range, aref), Ordering::Release),
                Err(e) => return Some(Err(e)),
            }
        }
        for (sub, base, bits) in &self.windows {
            match self.call(|b| b.bitfield(*sub, *base, 0, 0))? {
                Ok(word) => {
                    for (bit, shift) in bits {
                        let _ = card.inputs.set(*bit, word >> shift & 1 == 1);
                    }
                }
                Err(e) => return Some(Err(e)),
            }
        }
        for (c, counter) in &card.counters {
            match self.call(|b| b.data_read(c.subdevice, c.channel, 0, 0))? {
                Ok(raw) => counter.sample(i64::from(raw)),
                Err(e) => return Some(Err(e)),
            }
        }
        if card.ai.is_empty() && self.windows.is_empty() && card.counters.is_empty() {
            // Nothing to read: one output read back, so a board that went away is
            // noticed (an analog output only on a board that reads them back).
            let probe = if let Some(o) = card.dout.first() {
                let (sub, base) = (o.chan.subdevice, o.chan.channel & !31);
                self.call(|b| b.bitfield(sub, base, 0, 0).map(|_| ()))?
            } else if let Some(c) = self.probe_ao.and_then(|i| card.ao.get(i)).map(|a| &a.chan) {
                self.call(|b| {
                    b.data_read(c.subdevice, c.channel, c.range, c.aref.raw())
                        .map(|_| ())
                })?
            } else {
                Ok(())
            };
            if let Err(e) = probe {
                return Some(Err(e));
            }
        }
        Some(Ok(()))
    }

    /// Opens the board, checks it is the one built for and sets its outputs up.
    fn open_board(&mut self) -> Result<(), ComediError> {
        let path = self.card.path().to_string();
        let mut board = (self.open)(&path)?;
        let desc = board.describe()?;
        if desc != self.desc {
            return Err(ComediError {
                call: "comedi_open",
                path,
                code: 0,
                message: format!(
                    "the board there is now {} ({}) with subdevices {}, not the {} ({}) with {} the card was built for",
                    desc.board,
                    desc.driver,
                    listing(&desc),
                    self.desc.board,
                    self.desc.driver,
                    listing(&self.desc)
                ),
            });
        }
        self.set_up(board.as_mut())?;
        // Counters restart with the board: each one's next reading is its new baseline.
        for (_, counter) in &self.card.counters {
            counter.rebase();
        }
        *self.card.lock() = Some(board);
        self.card.opened.fetch_add(1, Ordering::Relaxed);
        self.card.online.store(true, Ordering::Release);
        Ok(())
    }

    /// Sets the outputs up: levels, then DIO directions (read back), then analog outputs.
    fn set_up(&mut self, b: &mut dyn Daq) -> Result<(), ComediError> {
        let card = &self.card;
        let dio_out = card.dout.iter().map(|o| (o.chan, true));
        let dio_in = card.di.iter().map(|c| (*c, false));
        let dio: Vec<_> = dio_out.chain(dio_in).filter(|(c, _)| c.dio).collect();
        let mut before = Vec::with_capacity(dio.len());
        for (c, _) in &dio {
            before.push(b.dio_get_config(c.subdevice, c.channel)?);
        }
        self.levels(b, &dio, &before)?;
        for (c, out) in &dio {
            b.dio_config(c.subdevice, c.channel, *out)?;
        }
        for (c, out) in &dio {
            if b.dio_get_config(c.subdevice, c.channel)? != *out {
                // The board sets one direction for channels the section splits: put them
                // back as they were and never try again (the section must change).
                for ((c, _), was) in dio.iter().zip(&before) {
                    let _ = b.dio_config(c.subdevice, c.channel, *was);
                }
                self.refused = true;
                let other = dio
                    .iter()
                    .find(|(o, d)| o.subdevice == c.subdevice && d != out)
                    .map_or(String::new(), |(o, _)| {
                        format!(" (channel {} was made the other)", o.channel)
                    });
                return Err(ComediError {
                    call: "comedi_dio_config",
                    path: card.path().to_string(),
                    code: 0,
                    message: format!(
                        "DIO subdevice {} channel {} did not stay an {}: the board sets the direction of its channels together{other}; directions put back, not opened again until the section changes",
                        c.subdevice,
                        c.channel,
                        if *out { "output" } else { "input" }
                    ),
                });
            }
        }
        self.probe_ao = None;
        for (i, a) in card.ao.iter().enumerate() {
            let c = &a.chan;
            let aref = c.aref.raw();
            if a.asked.load(Ordering::Acquire)
                && let Some((raw, _, _)) = unpack(a.value.load(Ordering::Acquire))
            {
                b.data_write(c.subdevice, c.channel, c.range, aref, raw)?;
            }
            // A board that reads its outputs back; one that cannot leaves them unknown.
            if let Ok(raw) = b.data_read(c.subdevice, c.channel, c.range, aref) {
                self.probe_ao.get_or_insert(i);
                if !a.asked.load(Ordering::Acquire) {
                    a.value.store(pack(raw, c.range, aref), Ordering::Release);
                }
            }
        }
        Ok(())
    }

    /// The outputs' levels before any drives: those hwgw wrote (or `initial`) written,
    /// the others read; a DIO input about to be an output latched at the level its pin
    /// reads, so the line keeps its level when it starts to drive.
    fn levels(
        &self,
        b: &mut dyn Daq,
        dio: &[(BitChan, bool)],
        before: &[bool],
    ) -> Result<(), ComediError> {
        let card = &self.card;
        // Pins of DIO inputs about to be outputs, to latch at the level they read, so the
        // lines keep their level when they start to drive: (subdevice, base, mask, bits).
        let mut latch: Vec<(u32, u32, u32, u32)> = Vec::new();
        for (bit, o) in card.dout.iter().enumerate() {
            let (sub, base) = (o.chan.subdevice, o.chan.channel & !31);
            let shift = o.chan.channel - base;
            let bit = bit as u32;
            if o.asked.load(Ordering::Acquire) {
                let on = card.outputs.get(bit).unwrap_or(false);
                b.bitfield(sub, base, 1 << shift, u32::from(on) << shift)?;
                continue;
            }
            let on = b.bitfield(sub, base, 0, 0)? >> shift & 1 == 1;
            let is_input = o.chan.dio
                && dio
                    .iter()
                    .zip(before)
                    .any(|((c, _), out)| *c == o.chan && !out);
            if is_input {
                let w = match latch.iter().position(|w| (w.0, w.1) == (sub, base)) {
                    Some(w) => w,
                    None => {
                        latch.push((sub, base, 0, 0));
                        latch.len() - 1
                    }
                };
                latch[w].2 |= 1 << shift;
                latch[w].3 |= u32::from(on) << shift;
            }
            let _ = card.outputs.set(bit, on);
            o.known.store(true, Ordering::Release);
        }
        for (sub, base, mask, bits) in latch {
            b.bitfield(sub, base, mask, bits)?;
        }
        Ok(())
    }
}
