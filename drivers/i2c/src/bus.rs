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
//! A chip is online from its first fresh sample: a chip whose model waits for a
//! conversion ([`Outcome::Pending`]) keeps the state it has — an offline one is polled on
//! its period but stays offline, an online one's last good sample grows old — and its
//! failures in a row are not forgiven until a sample comes (so a converter that stopped,
//! [`ChipError::NotConverting`], takes it offline, and keeps it offline while it stays
//! stopped).
//!
//! A device's output write wakes the bus side, which polls that chip at once (its
//! schedule unchanged). A chip found not set up as its model left it — by the poll itself
//! ([`Outcome::Reset`], nothing of that poll published) or by the model's check, every
//! [`CHECK_PERIOD`] — is set up again at once, counted (`resets`, what differed in
//! `last_reset`) and logged at most once a [`RESET_LOG_PERIOD`] (the next message says how
//! many were not).

use crate::card::{ChipIo, ChipSlot, I2cCard};
use crate::chips::{ChipError, ChipModel, Outcome};
use crate::smbus::{LinuxChip, OpenError, Smbus, Transfer, find_bus};
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
/// The shortest time between two logged resets of one chip.
pub const RESET_LOG_PERIOD: Duration = Duration::from_secs(10);

/// Opens the transfers to the chip at an address.
pub type Opener = Box<dyn FnMut(u16) -> Result<Box<dyn Smbus>, OpenError> + Send>;

struct Polled {
    model: Box<dyn ChipModel>,
    bus: Option<Box<dyn Smbus>>,
    next: Timestamp,
    next_check: Timestamp,
    backoff: Duration,
    fails: u32,
    resets: ResetLog,
}

/// When a chip's resets are logged: the first at once, then at most one a
/// [`RESET_LOG_PERIOD`], the rest counted.
#[derive(Debug, Default)]
struct ResetLog {
    last: Option<Timestamp>,
    unlogged: u64,
}

impl ResetLog {
    /// A reset at `now`: `Some(n)` to log it, with `n` not logged since the last message.
    fn note(&mut self, now: Timestamp) -> Option<u64> {
        if let Some(last) = self.last
            && now < last.saturating_add(RESET_LOG_PERIOD)
        {
            self.unlogged += 1;
            return None;
        }
        self.last = Some(now);
        Some(std::mem::take(&mut self.unlogged))
    }
}

/// " (N more since the last message)" when N is not 0.
struct More(u64);

impl std::fmt::Display for More {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            0 => Ok(()),
            n => write!(f, " ({n} more since the last message)"),
        }
    }
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
                resets: ResetLog::default(),
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
                Ok(outcome) => p.answered(slot, outcome == Outcome::Fresh, online, early, now),
                Err(e) => p.failed(slot, &e, online, early, now),
            }
        }
        chips.iter().map(|p| p.next).min()
    }
}

/// What `start` answered, as a poll's outcome (it never finds a reset: it sets up).
fn from_start(outcome: Outcome) -> Outcome {
    match outcome {
        Outcome::Reset(_) => Outcome::Pending,
        o => o,
    }
}

impl Polled {
    /// The chip's transfers for this step: a poll (and, every [`CHECK_PERIOD`] when it is
    /// online, its check) once it is set up; else a probe that sets it up from scratch.
    /// Answers [`Outcome::Fresh`] or [`Outcome::Pending`]: a reset found is dealt with
    /// here.
    fn exchange(
        &mut self,
        open: &mut Opener,
        slot: &ChipSlot,
        io: &ChipIo<'_>,
        online: bool,
        now: Timestamp,
    ) -> Result<Outcome, ChipError> {
        let Polled {
            model,
            bus,
            next_check,
            resets,
            ..
        } = self;
        let bus = match bus {
            Some(bus) => bus,
            None => {
                let opened = open(slot.address).map_err(|e| Transfer::Failed(e.to_string()))?;
                let bus = bus.insert(opened);
                *next_check = now.saturating_add(CHECK_PERIOD);
                return model.start(bus.as_mut(), io).map(from_start);
            }
        };
        let lost = match model.poll(bus.as_mut(), io)? {
            Outcome::Reset(lost) => lost,
            outcome if !online || now < *next_check => return Ok(outcome),
            outcome => {
                *next_check = now.saturating_add(CHECK_PERIOD);
                match model.check(bus.as_mut(), io)? {
                    None => return Ok(outcome),
                    Some(lost) => lost,
                }
            }
        };
        io.count_reset(lost);
        if let Some(more) = resets.note(now) {
            tracing::warn!(
                "I2C chip {} at {:#04x}: {lost}: not set up as hwgw left it (a reset, a power \
                 loss or another master); setting it up again{}",
                slot.model,
                slot.address,
                More(more)
            );
        }
        *next_check = now.saturating_add(CHECK_PERIOD);
        match model.start(bus.as_mut(), io) {
            Ok(outcome) => Ok(from_start(outcome)),
            Err(e) => {
                // What start took to send may not have reached the chip: send it again,
                // and check again at the next poll.
                io.mark_dirty();
                *next_check = now;
                Err(e)
            }
        }
    }

    /// Every transfer answered: a `fresh` sample, or one still to come.
    fn answered(
        &mut self,
        slot: &ChipSlot,
        fresh: bool,
        online: bool,
        early: bool,
        now: Timestamp,
    ) {
        // What this poll took to send is sent.
        slot.sent
            .store(slot.taken.load(Ordering::Acquire), Ordering::Release);
        slot.polls.fetch_add(1, Ordering::Relaxed);
        if fresh {
            self.fails = 0;
            self.backoff = FIRST_BACKOFF;
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

    fn failed(
        &mut self,
        slot: &ChipSlot,
        e: &ChipError,
        online: bool,
        early: bool,
        now: Timestamp,
    ) {
        slot.errors.fetch_add(1, Ordering::Relaxed);
        self.fails += 1;
        let gone = matches!(e, ChipError::Transfer(Transfer::NoAnswer(_)))
            || self.fails >= FAILS_TO_OFFLINE;
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
    use device_interface::DeviceError;
    use device_interface::time::SimClock;
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

    /// A bus of the one chip `table` describes on `chip`, and the clock its card (and so
    /// its model) reads.
    fn one(table: &str, chip: impl Smbus + Clone + 'static) -> (I2cBus, Arc<SimClock>) {
        let config: crate::config::I2cConfig =
            toml::from_str(&format!("bus = \"/dev/i2c-0\"\n[[chip]]\n{table}")).unwrap();
        config.check().unwrap();
        let model = crate::chips::model(&config.chip[0]);
        let clock = Arc::new(SimClock::new(Timestamp::from_nanos(0)));
        let card = crate::chips::tests::one_chip_on(&config.chip[0], model.as_ref(), clock.clone());
        let bus = I2cBus::with_opener(
            card,
            vec![model],
            Box::new(move |_| Ok(Box::new(chip.clone()) as Box<dyn Smbus>)),
        );
        (bus, clock)
    }

    /// Steps `b` each time a chip is due, from `from` ms, until `done` holds (at most
    /// `until` ms); the time it held.
    fn run(
        b: &mut I2cBus,
        clock: &SimClock,
        from: u64,
        until: u64,
        mut done: impl FnMut(&I2cBus) -> bool,
    ) -> Option<u64> {
        let mut t = Timestamp::from_nanos(from * 1_000_000);
        while t.as_nanos() <= until * 1_000_000 {
            clock.set(t);
            let next = b.step(t);
            if done(b) {
                return Some(t.as_nanos() / 1_000_000);
            }
            t = next
                .unwrap_or(t)
                .max(t.saturating_add(Duration::from_micros(1)));
        }
        None
    }

    #[test]
    fn a_stuck_converter_goes_offline_stays_offline_and_comes_back_when_it_converts() {
        use crate::smbus::fake::Registers;
        use device_interface::{AnalogIn, Device};
        let regs = Registers::new();
        // 8 conversions/s: one takes at most 137.5 ms, and is given 276 ms.
        let (mut b, clock) = one(
            "model = \"ads1115\"\naddress = 0x48\npoll_ms = 5\ndata_rate = 8\n\
             channel = [{ input = \"a0\", range_v = 4.096 }]",
            regs.clone(),
        );
        let card = b.card.clone();
        let chip = |b: &I2cBus| b.card.counters().chips[0].clone();
        regs.set(0x00, 0x1234u16.swap_bytes());
        // Set up at 0 (a conversion started), online with the first result at 5 ms.
        assert_eq!(
            b.step(Timestamp::ZERO),
            Some(Timestamp::from_nanos(5_000_000))
        );
        assert!(!chip(&b).online, "online with its first sample, not before");
        assert_eq!(run(&mut b, &clock, 5, 5, |b| chip(b).online), Some(5));
        assert_eq!(card.read_raw(0).unwrap(), 0x1234);
        // Stuck: OS stays 0 with hwgw's config (the conversion started at 5 ms).
        let config = regs.get(0x01).swap_bytes();
        regs.set(0x01, (config & 0x7fff).swap_bytes());
        let first = run(&mut b, &clock, 10, 10_000, |b| chip(b).errors == 1).unwrap();
        assert_eq!(first, 285, "the first poll past 5 + 276 ms");
        // Still online for now, the old value answered, its age growing.
        assert!(chip(&b).online);
        assert_eq!(card.read_raw(0).unwrap(), 0x1234);
        let age = card.health().last_good.unwrap();
        assert_eq!(
            age,
            Timestamp::from_nanos(5_000_000),
            "no fresh sample since"
        );
        // Three overdue spans in a row: offline, saying why.
        let off = run(&mut b, &clock, first + 5, 10_000, |b| !chip(b).online).unwrap();
        assert_eq!(off, 845);
        let c = chip(&b);
        assert_eq!((c.errors, c.went_offline), (3, 1));
        let why = c.last_error.unwrap();
        assert!(
            why.contains("not converting") && why.contains("OS stays 0"),
            "{why}"
        );
        assert!(matches!(card.read_raw(0), Err(DeviceError::Offline)));
        // Probed again and again (backing off) it stays offline: never started again.
        assert_eq!(
            run(&mut b, &clock, off + 1, 20_000, |b| chip(b).online),
            None
        );
        assert_eq!(chip(&b).went_offline, 1);
        assert!(chip(&b).errors > 6, "{:?}", chip(&b));
        assert_eq!(
            regs.get(0x01).swap_bytes(),
            config & 0x7fff,
            "OS never written"
        );
        // It converts again: online with the result.
        regs.set(0x00, 0x0777u16.swap_bytes());
        regs.set(0x01, config.swap_bytes());
        assert!(run(&mut b, &clock, 20_001, 40_000, |b| chip(b).online).is_some());
        assert_eq!(card.read_raw(0).unwrap(), 0x0777);
    }

    #[test]
    fn a_reset_a_poll_finds_is_counted_set_up_again_and_not_published() {
        use crate::chips::tests::{Ina219Chip, converted};
        use crate::smbus::fake::Registers;
        use device_interface::AnalogIn;
        let regs = Registers::new();
        let (mut b, clock) = one(
            "model = \"ina219\"\naddress = 0x40\npoll_ms = 10\nshunt_ohms = 0.1\n\
             max_current_a = 3.2",
            Ina219Chip(regs.clone()),
        );
        let card = b.card.clone();
        let chip = |b: &I2cBus| b.card.counters().chips[0].clone();
        b.step(Timestamp::ZERO);
        converted(&regs, 2000);
        assert!(run(&mut b, &clock, 10, 10, |b| chip(b).online).is_some());
        assert_eq!(card.read_raw(2).unwrap(), 2000);
        // A brown-out: calibration 0, the current 0, the chip converting on.
        regs.set(0x05, 0);
        regs.set(0x04, 0);
        run(&mut b, &clock, 20, 20, |_| true);
        let c = chip(&b);
        assert_eq!(c.resets, 1);
        assert_eq!(
            c.last_reset.as_deref(),
            Some("calibration reads 0x0000, not 0x1062")
        );
        assert_eq!(regs.get(0x05), 0x1062u16.swap_bytes(), "set up again");
        assert_eq!(card.read_raw(2).unwrap(), 2000, "the 0 not published");
        // The current the chip worked out before is not read until it converted again;
        // this register file does not convert, so the next poll, past the deadline, fails.
        run(&mut b, &clock, 30, 30, |_| true);
        assert_eq!(card.read_raw(2).unwrap(), 2000);
        let why = chip(&b).last_error.unwrap();
        assert!(why.contains("CNVR stays 0"), "{why}");
        converted(&regs, 1999);
        run(&mut b, &clock, 40, 40, |_| true);
        assert_eq!(card.read_raw(2).unwrap(), 1999);
        let c = chip(&b);
        assert_eq!((c.online, c.errors, c.resets), (true, 1, 1));
    }

    #[test]
    fn resets_are_logged_at_most_once_a_period_and_the_next_message_counts_the_rest() {
        let mut log = ResetLog::default();
        let t = |s: u64| Timestamp::from_nanos(s * 1_000_000_000);
        assert_eq!(log.note(t(1)), Some(0));
        assert_eq!(log.note(t(2)), None);
        assert_eq!(log.note(t(10)), None);
        assert_eq!(log.note(t(11)), Some(2));
        assert_eq!(log.note(t(30)), Some(0));
        assert_eq!(More(2).to_string(), " (2 more since the last message)");
        assert_eq!(More(0).to_string(), "");
    }
}
