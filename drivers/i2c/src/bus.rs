//! An I2C card's bus side: every chip polled on its own period, one transfer at a time,
//! on the card's bus thread.
//!
//! A chip that does not answer (a NAK) goes offline at once; other failed transfers are
//! counted and the chip goes offline after [`FAILS_TO_OFFLINE`] in a row. An offline chip
//! is probed — configured again from scratch, its outputs written — after
//! [`FIRST_BACKOFF`], doubling up to [`MAX_BACKOFF`], through a newly opened bus file (an
//! adapter that went away and came back, at its path or under its name, is found); one
//! dead chip costs the others one failed transfer per probe, never a wait.
//!
//! A device's output write wakes the bus side, which polls that chip at once (its
//! schedule unchanged). Every [`CHECK_PERIOD`] an online chip's model checks that the
//! chip is still set up as it left it, and sets it up again (counted) when not.

use crate::card::{ChipIo, ChipSlot, I2cCard};
use crate::chips::ChipModel;
use crate::smbus::{LinuxChip, Smbus, Transfer, find_bus};
use device_interface::time::Timestamp;
use std::sync::atomic::Ordering;
use std::sync::{Arc, PoisonError};
use std::time::Duration;

/// Failed transfers in a row (other than a NAK) that take a chip offline.
pub const FAILS_TO_OFFLINE: u32 = 3;
/// The first wait before probing a chip that stopped answering.
pub const FIRST_BACKOFF: Duration = Duration::from_millis(100);
/// The longest wait between probes.
pub const MAX_BACKOFF: Duration = Duration::from_secs(5);
/// How often an online chip's set-up is checked ([`ChipModel::check`]), after a poll.
pub const CHECK_PERIOD: Duration = Duration::from_millis(500);

/// Opens the transfers to the chip at an address.
pub type Opener = Box<dyn FnMut(u16) -> Result<Box<dyn Smbus>, String> + Send>;

struct Polled {
    model: Box<dyn ChipModel>,
    bus: Option<Box<dyn Smbus>>,
    next: Timestamp,
    next_check: Timestamp,
    backoff: Duration,
    fails: u32,
}

/// The card's bus side.
pub struct I2cBus {
    card: Arc<I2cCard>,
    chips: Vec<Polled>,
    open: Opener,
}

impl I2cBus {
    /// The bus side of `card` over the i2c-dev bus `bus` names (a path, or an adapter's
    /// name, found again at each open: an adapter that comes back under another number is
    /// found by its name); `models` in the card's chip order.
    pub fn new(card: Arc<I2cCard>, models: Vec<Box<dyn ChipModel>>, bus: String) -> I2cBus {
        let open: Opener = Box::new(move |address| {
            let path = find_bus(&bus)?;
            LinuxChip::open(&path, address).map(|c| Box::new(c) as Box<dyn Smbus>)
        });
        I2cBus::with_opener(card, models, open)
    }

    /// The same over transfers `open` makes (a test's bus).
    pub fn with_opener(
        card: Arc<I2cCard>,
        models: Vec<Box<dyn ChipModel>>,
        open: Opener,
    ) -> I2cBus {
        let now = card.now();
        let chips = models
            .into_iter()
            .map(|model| Polled {
                model,
                bus: None,
                next: now,
                next_check: now,
                backoff: FIRST_BACKOFF,
                fails: 0,
            })
            .collect();
        I2cBus { card, chips, open }
    }

    /// The card.
    pub fn card(&self) -> &Arc<I2cCard> {
        &self.card
    }

    /// Closes every chip's bus file and takes the chips offline (the bus side stops: a
    /// card that is not polled holds no adapter, so its module can be unloaded). The next
    /// step probes them all again.
    pub fn release(&mut self) {
        let now = self.card.now();
        for (p, slot) in self.chips.iter_mut().zip(&self.card.chips) {
            p.bus = None;
            p.next = now;
            p.backoff = FIRST_BACKOFF;
            slot.online.store(false, Ordering::Release);
        }
    }

    /// Polls (or probes) every chip that is due at `now` — on its period, or at once when
    /// a device wrote one of its outputs — and returns when the next one is.
    pub fn step(&mut self, now: Timestamp) -> Option<Timestamp> {
        let I2cBus { card, chips, open } = self;
        for (i, p) in chips.iter_mut().enumerate() {
            let (Some(slot), Some(io)) = (card.chips.get(i), card.io(i)) else {
                continue;
            };
            let online = slot.online.load(Ordering::Acquire);
            let early = p.next > now;
            // Early only while it answers: a chip whose last transfer failed waits for its
            // period, so its failures in a row span periods.
            if early && !(online && p.fails == 0 && p.bus.is_some() && slot.unsent()) {
                continue;
            }
            match p.exchange(open, slot, &io, online, now) {
                Ok(()) => p.succeeded(slot, online, early, now),
                Err(e) => p.failed(slot, &e, online, early, now),
            }
        }
        chips.iter().map(|p| p.next).min()
    }
}

impl Polled {
    /// The chip's transfers for this step: a poll (and, every [`CHECK_PERIOD`], its check)
    /// when it is online; else a probe that sets it up from scratch.
    fn exchange(
        &mut self,
        open: &mut Opener,
        slot: &ChipSlot,
        io: &ChipIo<'_>,
        online: bool,
        now: Timestamp,
    ) -> Result<(), Transfer> {
        let bus = match &mut self.bus {
            Some(bus) if online => {
                self.model.poll(bus.as_mut(), io)?;
                if now < self.next_check {
                    return Ok(());
                }
                self.next_check = now.saturating_add(CHECK_PERIOD);
                if self.model.check(bus.as_mut(), io)? {
                    return Ok(());
                }
                io.count_reset();
                tracing::warn!(
                    "I2C chip {} at {:#04x}: not set up as hwgw left it (a reset, a power \
                     loss or another master); setting it up again",
                    slot.model,
                    slot.address
                );
                let r = self.model.start(bus.as_mut(), io);
                if r.is_err() {
                    // What start took to send may not have reached the chip: send it
                    // again, and check again at the next poll.
                    io.mark_dirty();
                    self.next_check = now;
                }
                return r;
            }
            Some(bus) => bus,
            None => self
                .bus
                .insert(open(slot.address).map_err(Transfer::Failed)?),
        };
        self.next_check = now.saturating_add(CHECK_PERIOD);
        self.model.start(bus.as_mut(), io)
    }

    fn succeeded(&mut self, slot: &ChipSlot, online: bool, early: bool, now: Timestamp) {
        // What this poll took to send is sent.
        slot.sent
            .store(slot.taken.load(Ordering::Acquire), Ordering::Release);
        self.fails = 0;
        self.backoff = FIRST_BACKOFF;
        slot.polls.fetch_add(1, Ordering::Relaxed);
        slot.last_good
            .store(now.as_nanos().max(1), Ordering::Release);
        if !online {
            tracing::info!(
                "I2C chip {} at {:#04x}: answering",
                slot.model,
                slot.address
            );
            slot.online.store(true, Ordering::Release);
        }
        if !early {
            // The next period after now (missed periods are skipped, not caught up); a
            // poll made early for a write keeps the schedule.
            let period = slot.period();
            self.next = self
                .next
                .saturating_add(period)
                .max(now.saturating_add(period / 2));
        }
    }

    fn failed(&mut self, slot: &ChipSlot, e: &Transfer, online: bool, early: bool, now: Timestamp) {
        slot.errors.fetch_add(1, Ordering::Relaxed);
        self.fails += 1;
        let gone = matches!(e, Transfer::NoAnswer(_)) || self.fails >= FAILS_TO_OFFLINE;
        if online && gone {
            slot.online.store(false, Ordering::Release);
            slot.went_offline.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(
                "I2C chip {} at {:#04x}: offline ({e}); probing with backoff",
                slot.model,
                slot.address
            );
        }
        let changed = {
            let mut last = slot
                .last_error
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            let text = e.to_string();
            let changed = last.as_deref() != Some(text.as_str());
            if changed {
                *last = Some(text);
            }
            changed
        };
        if !online && changed {
            tracing::warn!("I2C chip {} at {:#04x}: {e}", slot.model, slot.address);
        }
        if online && !gone {
            if !early {
                self.next = now.saturating_add(slot.period());
            }
        } else {
            // Probed through a new open: an adapter that was removed and came back (a
            // reloaded module, a replugged USB adapter) has a new file.
            self.bus = None;
            self.next = now.saturating_add(self.backoff);
            self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;
    use crate::config::Mcp23017Config;
    use std::sync::Mutex;

    /// An MCP23017 whose transfers fail as the test says: each call pops the next
    /// outcome (none left: success).
    struct Scripted(Arc<Mutex<Vec<Option<Transfer>>>>);

    impl Scripted {
        fn next(&mut self) -> Result<(), Transfer> {
            match self.0.lock().unwrap().pop() {
                Some(Some(e)) => Err(e),
                _ => Ok(()),
            }
        }
    }

    impl Smbus for Scripted {
        fn read_byte(&mut self, _: u8) -> Result<u8, Transfer> {
            self.next().map(|()| 0)
        }
        fn write_byte(&mut self, _: u8, _: u8) -> Result<(), Transfer> {
            self.next()
        }
        fn read_word(&mut self, _: u8) -> Result<u16, Transfer> {
            self.next().map(|()| 0)
        }
        fn write_word(&mut self, _: u8, _: u16) -> Result<(), Transfer> {
            self.next()
        }
    }

    fn bus(script: Arc<Mutex<Vec<Option<Transfer>>>>) -> I2cBus {
        let config = Mcp23017Config {
            address: 0x20,
            poll_ms: 10,
            inputs: vec![0],
            outputs: vec![],
            pull_up: vec![],
            invert: vec![],
            initial_on: vec![],
        };
        let config = crate::config::ChipConfig::Mcp23017(config);
        let model = crate::chips::model(&config);
        let card = crate::chips::tests::one_chip(&config, model.as_ref());
        I2cBus::with_opener(
            card,
            vec![model],
            Box::new(move |_| Ok(Box::new(Scripted(script.clone())) as Box<dyn Smbus>)),
        )
    }

    #[test]
    fn transient_errors_are_counted_a_nak_takes_the_chip_offline_and_probes_back_off() {
        let script = Arc::new(Mutex::new(Vec::new()));
        let mut b = bus(script.clone());
        let t = |ms: u64| Timestamp::from_nanos(ms * 1_000_000);
        let chip = |b: &I2cBus| b.card.counters().chips[0].clone();
        assert_eq!(b.step(t(0)), Some(t(10)));
        assert!(chip(&b).online);
        // Two failed polls in a row: counted, still online, polled on its period.
        let failed = || Some(Transfer::Failed("timeout".into()));
        *script.lock().unwrap() = vec![failed(), failed()];
        assert_eq!(b.step(t(10)), Some(t(20)));
        assert_eq!(b.step(t(20)), Some(t(30)));
        assert!(chip(&b).online);
        assert_eq!(chip(&b).errors, 2);
        // A NAK: offline at once, probed after 100 ms, then 200, 400 …
        *script.lock().unwrap() = vec![Some(Transfer::NoAnswer("ENXIO".into())); 3];
        assert_eq!(b.step(t(30)), Some(t(130)));
        assert!(!chip(&b).online);
        assert_eq!(chip(&b).went_offline, 1);
        assert_eq!(b.step(t(130)), Some(t(330)));
        assert_eq!(b.step(t(330)), Some(t(730)));
        // It answers again: configured anew, online, polled on its period.
        assert_eq!(b.step(t(730)), Some(t(740)));
        assert!(chip(&b).online);
        assert!(chip(&b).last_error.unwrap().contains("ENXIO"));
    }

    /// Counts its wakes.
    #[derive(Default)]
    struct Wakes(std::sync::atomic::AtomicU32);

    impl rtt::activity::Waker for Wakes {
        fn wake(&self) {
            self.0.fetch_add(1, Ordering::Relaxed);
        }
    }

    #[test]
    fn a_write_is_sent_at_once_and_a_chip_found_reset_is_set_up_again() {
        use crate::smbus::fake::Registers;
        use device_interface::DigitalOut;
        let config: crate::config::I2cConfig = toml::from_str(
            "bus = \"/dev/i2c-0\"\n[[chip]]\nmodel = \"mcp23017\"\naddress = 0x20\n\
             poll_ms = 100\noutputs = [0]",
        )
        .unwrap();
        let model = crate::chips::model(&config.chip[0]);
        let card = crate::chips::tests::one_chip(&config.chip[0], model.as_ref());
        let wakes = Arc::new(Wakes::default());
        card.set_waker(wakes.clone());
        let regs = Registers::new();
        let r = regs.clone();
        let mut b = I2cBus::with_opener(
            card.clone(),
            vec![model],
            Box::new(move |_| Ok(Box::new(r.clone()) as Box<dyn Smbus>)),
        );
        let t = |ms: u64| Timestamp::from_nanos(ms * 1_000_000);
        assert_eq!(b.step(t(0)), Some(t(100)));
        regs.writes();
        // A write between polls: a wake, and the step it makes sends it, the schedule kept.
        card.set_bit(0, true).unwrap();
        assert_eq!(wakes.0.load(Ordering::Relaxed), 1);
        assert_eq!(b.step(t(30)), Some(t(100)));
        assert_eq!(regs.writes(), [(0x14, 1)]);
        assert!(card.settle(std::time::Instant::now()).is_ok());
        // A step with nothing written and nothing due transfers nothing.
        assert_eq!(b.step(t(40)), Some(t(100)));
        assert!(regs.writes().is_empty());
        // Reset (all inputs, latch 0) between checks: the check after 0.5 s finds it, and
        // the chip is set up again with the latch as asked.
        regs.set(0x00, 0xffff);
        regs.set(0x14, 0);
        for ms in [100, 200, 300, 400] {
            b.step(t(ms));
        }
        assert_eq!(regs.get(0x00), 0xffff, "not checked before 0.5 s");
        b.step(t(500));
        assert_eq!((regs.get(0x00), regs.get(0x14)), (0xfffe, 1));
        let counters = card.counters().chips[0].clone();
        assert_eq!((counters.resets, counters.online), (1, true));
    }
}
