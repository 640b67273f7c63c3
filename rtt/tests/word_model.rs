//! The one-word register behind data connections of `f64`, `bool` and the integers
//! (`rtt::port::word`), checked under loom's model of the C11 memory model: the
//! interleavings of a writer making several writes (enough to reuse its four slots) and
//! a reader making three reads, with every value the weak orderings allow a load to
//! return. What holds in all of them: a read returns a value that was written, with its own
//! version (never another write's value: no torn or mismatched pair); versions read only
//! grow; a read never returns the same version twice; and once the writer is done, a read
//! returns the last write (or nothing, if that was already taken).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use loom::sync::Arc;
use loom::sync::atomic::AtomicU64;
use rtt::port::word::{Found, Word, WordCell};
use std::sync::atomic::{AtomicUsize, Ordering};

/// loom's atomic as the register's word.
struct LoomWord(AtomicU64);

impl Word for LoomWord {
    fn new(v: u64) -> Self {
        LoomWord(AtomicU64::new(v))
    }
    fn load(&self, order: Ordering) -> u64 {
        self.0.load(order)
    }
    fn store(&self, v: u64, order: Ordering) {
        self.0.store(v, order)
    }
}

/// The value of write `v` (distinct from every other write's and from the initial 0).
fn value(v: u64) -> u64 {
    v * 1000 + 7
}

/// Runs the model with `writes` writes and three reads, within `preemptions` (None: every
/// interleaving); the number of executions explored.
fn model(writes: u64, preemptions: Option<usize>) -> usize {
    let executions = std::sync::Arc::new(AtomicUsize::new(0));
    let counted = executions.clone();
    let mut builder = loom::model::Builder::new();
    builder.preemption_bound = preemptions;
    builder.check(move || {
        counted.fetch_add(1, Ordering::Relaxed);
        let cell: Arc<WordCell<LoomWord>> = Arc::new(WordCell::new());
        let writer = {
            let cell = cell.clone();
            loom::thread::spawn(move || {
                for v in 1..=writes {
                    cell.write(v, value(v));
                }
            })
        };
        let mut seen = 0;
        for _ in 0..3 {
            if let Found::New { version, value: x } = cell.read(seen) {
                assert!((1..=writes).contains(&version), "version {version}");
                assert_eq!(x, value(version), "version {version} read with {x}");
                assert!(version > seen, "version {version} after {seen}");
                seen = version;
            }
        }
        writer.join().unwrap();
        match cell.read(seen) {
            Found::New { version, value: x } => {
                assert_eq!((version, x), (writes, value(writes)));
            }
            Found::Nothing => assert_eq!(seen, writes, "the last write never read"),
        }
    });
    executions.load(Ordering::Relaxed)
}

/// Five writes (the first slot reused by the fifth), every interleaving.
#[test]
fn every_interleaving_reads_whole_values_in_order() {
    let n = model(5, None);
    println!("loom: 5 writes, 3 reads, every interleaving: {n} executions");
    assert!(n > 10_000, "{n} executions: the model did not branch");
}

/// Eight writes (each slot reused) within three preemptions.
#[test]
fn many_writes_within_three_preemptions() {
    let n = model(8, Some(3));
    println!("loom: 8 writes, 3 reads, up to 3 preemptions: {n} executions");
    assert!(n > 10_000, "{n} executions: the model did not branch");
}

/// A word whose every load is followed by what a test makes happen then (a writer that
/// overtakes the reader between its looks, on cue).
struct Hooked(std::sync::atomic::AtomicU64);

thread_local! {
    static AFTER_LOAD: std::cell::RefCell<Option<Box<dyn FnMut()>>> =
        const { std::cell::RefCell::new(None) };
}

impl Word for Hooked {
    fn new(v: u64) -> Self {
        Hooked(std::sync::atomic::AtomicU64::new(v))
    }
    fn load(&self, order: Ordering) -> u64 {
        let v = self.0.load(order);
        AFTER_LOAD.with(|h| {
            if let Some(f) = h.borrow_mut().as_mut() {
                f();
            }
        });
        v
    }
    fn store(&self, v: u64, order: Ordering) {
        self.0.store(v, order)
    }
}

/// A reader overtaken by two writes at every look, on each of its tries, reports nothing
/// new (not a value of another version); the next read, left alone, takes the latest.
#[test]
fn a_reader_overtaken_on_every_try_reports_nothing() {
    let cell: std::sync::Arc<WordCell<Hooked>> = std::sync::Arc::new(WordCell::new());
    cell.write(1, value(1));
    let (c, mut v) = (cell.clone(), 1);
    AFTER_LOAD.with(|h| {
        *h.borrow_mut() = Some(Box::new(move || {
            for _ in 0..2 {
                v += 1;
                c.write(v, value(v));
            }
        }))
    });
    assert_eq!(cell.read(0), Found::Nothing);
    AFTER_LOAD.with(|h| *h.borrow_mut() = None);
    let last = cell.version();
    // Each try's three loads each let two writes through.
    assert_eq!(last, 1 + 2 * 3 * rtt::port::word::TRIES as u64);
    assert_eq!(
        cell.read(0),
        Found::New {
            version: last,
            value: value(last)
        }
    );
}
