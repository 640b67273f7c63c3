//! ThreadScope: every runtime thread as a bit on a digital output, high while it steps.
//!
//! Every runtime thread gets a number: the thread that made the [`Runtime`](crate::Runtime)
//! is 0, then activity threads in the order they are created. With ThreadScope on, just
//! before a thread steps a component its bit on the DigitalOut registered as
//! `"ThreadScope"` goes high, and just after it goes low, so an oscilloscope (or the sim
//! card's output record) shows which thread ran when and for how long. The mapping of
//! threads to bits is logged. With ThreadScope off, a step costs one branch more.
//!
//! The same bits can be recorded into a VCD file instead of, or besides, the output
//! ([`vcd`]): a logic analyser's view without the hardware.

pub mod vcd;

use device_interface::DigitalOut;
use std::cell::Cell;
use std::path::Path;
use std::sync::Arc;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use vcd::{ThreadNames, VcdError, VcdTrace};

thread_local! {
    static THREAD_NUMBER: Cell<Option<u32>> = const { Cell::new(None) };
    static DEPTH: Cell<u32> = const { Cell::new(0) };
}

/// The runtime thread number of the calling thread, if it is a runtime thread.
pub fn current_thread_number() -> Option<u32> {
    THREAD_NUMBER.with(Cell::get)
}

pub(crate) fn set_thread_number(n: u32) {
    THREAD_NUMBER.with(|c| c.set(Some(n)));
}

/// The ThreadScope output, or nothing.
pub struct ThreadScope {
    out: Option<Arc<dyn DigitalOut>>,
    errors: AtomicU64,
    /// No pulse starts once set ([`close`](Self::close)).
    closed: AtomicBool,
    /// Pulses begun and not yet ended (their bit high).
    active: AtomicU32,
    /// The recording of the bits, once started.
    vcd: OnceLock<VcdTrace>,
    /// The activity threads' names, for the recording's signals.
    names: ThreadNames,
}

impl ThreadScope {
    /// ThreadScope off.
    pub fn off() -> Self {
        ThreadScope {
            out: None,
            errors: AtomicU64::new(0),
            closed: AtomicBool::new(false),
            active: AtomicU32::new(0),
            vcd: OnceLock::new(),
            names: ThreadNames::default(),
        }
    }

    /// ThreadScope on `out`.
    pub fn on(out: Arc<dyn DigitalOut>) -> Self {
        ThreadScope {
            out: Some(out),
            ..ThreadScope::off()
        }
    }

    /// Starts recording every thread's bit into a new VCD file at `path` (never
    /// overwriting one, never through a link), besides the output if there is one. Once
    /// per ThreadScope: a second call is refused. Its pulses are recorded from now on; time
    /// 0 in the file is now.
    pub fn record_vcd(&self, path: &Path) -> Result<&VcdTrace, VcdError> {
        self.record(path, |names| VcdTrace::create(path, names))
    }

    /// [`record_vcd`](Self::record_vcd) into a new numbered file beside `base`
    /// (`threads.vcd` gives `threads-<n>.vcd`, one past the highest number there), the
    /// last `keep` of them kept (see [`vcd::files`]): a restart never finds its file taken.
    pub fn record_vcd_numbered(&self, base: &Path, keep: u32) -> Result<&VcdTrace, VcdError> {
        self.record(base, |names| VcdTrace::create_numbered(base, keep, names))
    }

    fn record(
        &self,
        path: &Path,
        create: impl FnOnce(ThreadNames) -> Result<VcdTrace, VcdError>,
    ) -> Result<&VcdTrace, VcdError> {
        let already = || VcdError::AlreadyRecording {
            path: path.to_path_buf(),
        };
        // Checked first, so that a refused call creates no file.
        if self.vcd.get().is_some() {
            return Err(already());
        }
        let trace = create(self.names.clone())?;
        for n in self.names.named() {
            tracing::info!(
                "ThreadScope: thread {n} is signal {} in {}",
                self.names.signal(n),
                trace.path().display()
            );
        }
        self.vcd.set(trace).map_err(|_| already())?;
        self.vcd.get().ok_or_else(already)
    }

    /// True when on: driving an output, recording, or both.
    pub fn is_on(&self) -> bool {
        self.out.is_some() || self.vcd.get().is_some()
    }

    /// The recording, if one was started.
    pub fn vcd(&self) -> Option<&VcdTrace> {
        self.vcd.get()
    }

    /// Gives thread `thread` its activity's name (for a recording's signal names).
    pub(crate) fn name_thread(&self, thread: u32, name: &str) {
        self.names.set(thread, name);
    }

    /// Writes to the output that failed (a bit past its end, an offline card).
    pub fn errors(&self) -> u64 {
        self.errors.load(Ordering::Relaxed)
    }

    /// Runs `f` with the calling thread's bit high. Nested pulses on one thread (a slave
    /// stepped from its master's step) keep the bit high until the outermost ends.
    pub(crate) fn pulse<R>(&self, f: impl FnOnce() -> R) -> R {
        if !self.is_on() {
            return f();
        }
        let Some(bit) = current_thread_number() else {
            return f();
        };
        let outer = DEPTH.with(|d| {
            let v = d.get();
            d.set(v + 1);
            v == 0
        });
        // Counted before `closed` is read: `close` either sees this pulse and waits for its
        // low, or this pulse sees `closed` and writes nothing.
        let write = outer && {
            self.active.fetch_add(1, Ordering::SeqCst);
            let open = !self.closed.load(Ordering::SeqCst);
            if !open {
                self.active.fetch_sub(1, Ordering::SeqCst);
            }
            open
        };
        if write {
            self.set(bit, true);
        }
        let r = f();
        if write {
            self.set(bit, false);
            self.active.fetch_sub(1, Ordering::SeqCst);
        }
        DEPTH.with(|d| d.set(d.get().saturating_sub(1)));
        r
    }

    /// Ends ThreadScope: no pulse starts from now on, and this waits (until `deadline` at
    /// the latest) for the pulses under way to end, so every bit is left low. For a
    /// gateway stopping, before its outputs stop taking writes. False if a pulse was still
    /// under way at the deadline (a step that long).
    pub fn close(&self, deadline: std::time::Instant) -> bool {
        self.closed.store(true, Ordering::SeqCst);
        while self.active.load(Ordering::SeqCst) != 0 {
            if std::time::Instant::now() >= deadline {
                return false;
            }
            std::thread::sleep(std::time::Duration::from_micros(200));
        }
        true
    }

    /// The bit to the output and into the recording. The recording's edge is taken just
    /// after the output's rise and just before its fall, so it lies within the pulse.
    fn set(&self, bit: u32, value: bool) {
        let vcd = self.vcd.get();
        if !value && let Some(v) = vcd {
            v.record(bit, false);
        }
        if let Some(out) = &self.out
            && out.set_bit(bit, value).is_err()
        {
            self.errors.fetch_add(1, Ordering::Relaxed);
        }
        if value && let Some(v) = vcd {
            v.record(bit, true);
        }
    }
}
