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
//! window of 32 channels, and each counter. A call failing because the board is gone
//! (`ENODEV`, `ENXIO`, `EBADF`, `EIO`) takes the card offline at once, three other failures
//! in a row too; an offline board is closed and opened again after 100 ms, doubling to 5 s.

use crate::board::{BoardDesc, ComediError, Daq};
use crate::card::ComediCard;
use crate::layout::listing;
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
        if self.card.lock().take().is_some() {
            self.next_open = Some(now + self.backoff);
        }
        if self.next_open.is_some_and(|t| now < t) {
            return;
        }
        match self.open_board() {
            Ok(()) => {
                self.backoff = FIRST_BACKOFF;
                self.fails = 0;
                self.next_open = None;
                tracing::info!(board = %self.card.path(), "comedi board open");
            }
            Err(e) => {
                self.card.failed(&e);
                self.next_open = Some(now + self.backoff);
                self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
            }
        }
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
                    self.card.lock().take();
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
                Ok(raw) => a
                    .sample
                    .store(crate::card::pack(raw, range), Ordering::Release),
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
        *self.card.lock() = Some(board);
        self.card.opened.fetch_add(1, Ordering::Relaxed);
        self.card.online.store(true, Ordering::Release);
        Ok(())
    }

    fn set_up(&self, b: &mut dyn Daq) -> Result<(), ComediError> {
        let card = &self.card;
        for (bit, o) in card.dout.iter().enumerate() {
            let (sub, base) = (o.chan.subdevice, o.chan.channel & !31);
            let shift = o.chan.channel - base;
            let bit = bit as u32;
            if o.asked.load(Ordering::Acquire) {
                let on = card.outputs.get(bit).unwrap_or(false);
                b.bitfield(sub, base, 1 << shift, u32::from(on) << shift)?;
            } else {
                let word = b.bitfield(sub, base, 0, 0)?;
                let _ = card.outputs.set(bit, word >> shift & 1 == 1);
                o.known.store(true, Ordering::Release);
            }
        }
        let dio_out = card.dout.iter().map(|o| (o.chan, true));
        let dio_in = card.di.iter().map(|c| (*c, false));
        let dio: Vec<_> = dio_out.chain(dio_in).filter(|(c, _)| c.dio).collect();
        for (c, out) in &dio {
            b.dio_config(c.subdevice, c.channel, *out)?;
        }
        for (c, out) in &dio {
            if b.dio_get_config(c.subdevice, c.channel)? != *out {
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
                        "DIO subdevice {} channel {} did not stay an {}: the board sets the direction of its channels together{other}",
                        c.subdevice,
                        c.channel,
                        if *out { "output" } else { "input" }
                    ),
                });
            }
        }
        for a in &card.ao {
            let c = &a.chan;
            if a.asked.load(Ordering::Acquire) {
                if let Some((raw, _)) = crate::card::unpack(a.value.load(Ordering::Acquire)) {
                    b.data_write(c.subdevice, c.channel, c.range, c.aref.raw(), raw)?;
                }
            } else if let Ok(raw) = b.data_read(c.subdevice, c.channel, c.range, c.aref.raw()) {
                // A board that reads its outputs back; one that cannot leaves them unknown.
                a.value
                    .store(crate::card::pack(raw, c.range), Ordering::Release);
            }
        }
        Ok(())
    }
}
