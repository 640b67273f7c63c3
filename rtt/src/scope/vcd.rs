//! ThreadScope as a waveform: each runtime thread's bit recorded into a Value Change Dump
//! (IEEE 1364 VCD, nanosecond timescale, one 1-bit signal per thread) that PulseView,
//! GTKWave and `sigrok-cli` open — a logic analyser on the ThreadScope without the
//! hardware.
//!
//! Real-time contract: a thread stepping records an edge with one clock read and one push
//! on a bounded lock-free queue ([`EDGE_QUEUE`] edges): no lock, no allocation, no system
//! call. A writer thread of its own drains the queue every [`DRAIN_PERIOD`] into the file
//! (buffered), so the file's I/O never reaches a stepping thread. What cannot be recorded
//! is counted, never silently lost: an edge that found the queue full (`dropped`), one of a
//! thread numbered [`MAX_THREADS`] or more (`unmapped`), one that reached the writer after
//! later edges were written (`late`: written at the latest time written, since VCD times
//! only go forward). The counts are written into the file's closing comment and returned
//! by [`VcdTrace::finish`].
//!
//! The file is created new: an existing file is never overwritten.

use crossbeam_queue::ArrayQueue;
use device_interface::time::{Clock, MonotonicClock};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

/// Threads with a signal in the file: thread numbers 0 to 63 (VCD identifiers of one
/// printable character each). A runtime with more threads records the first 64 and
/// counts the others' edges as unmapped.
pub const MAX_THREADS: u32 = 64;

/// Edges the queue holds between two drains (a 1 kHz step on 64 threads fills 1 280 in
/// the 10 ms between drains).
pub const EDGE_QUEUE: usize = 1 << 16;

/// How often the writer drains the queue.
pub const DRAIN_PERIOD: Duration = Duration::from_millis(10);

/// How long the writer holds edges back before writing them, so that an edge stamped just
/// before another thread's later one, but pushed after it, is still written in order.
const HOLD_BACK_NS: u64 = 5_000_000;

/// Longest activity name kept in a signal's name (`t<n>_<name>`; longer ones are cut).
const MAX_NAME: usize = 48;

/// One change of a thread's bit.
#[derive(Clone, Copy)]
struct Edge {
    at_ns: u64,
    thread: u32,
    high: bool,
}

/// What a recording counted.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct VcdCounts {
    /// Edges written.
    pub written: u64,
    /// Edges lost to a full queue.
    pub dropped: u64,
    /// Edges of threads numbered [`MAX_THREADS`] or more.
    pub unmapped: u64,
    /// Edges that came after later ones were written (written at the later time).
    pub late: u64,
}

/// Errors of a ThreadScope recording.
#[derive(Debug, thiserror::Error)]
pub enum VcdError {
    /// The file could not be created (it exists already, or its folder does not).
    #[error("ThreadScope VCD file {}: {source}", path.display())]
    Create {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The ThreadScope records into a file already.
    #[error("ThreadScope VCD file {}: ThreadScope records into a file already", path.display())]
    AlreadyRecording {
        /// The file asked for.
        path: PathBuf,
    },
    /// Writing the file failed; what was written before stays.
    #[error("ThreadScope VCD file {}: writing failed: {message}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
}

/// The activity threads' names, as the activities are made: at most one per thread number
/// below [`MAX_THREADS`], each cut to 48 characters of `[A-Za-z0-9_]`.
#[derive(Clone, Default)]
pub struct ThreadNames(Arc<Mutex<BTreeMap<u32, String>>>);

impl ThreadNames {
    /// Names thread `thread` (ignored from [`MAX_THREADS`] on).
    pub fn set(&self, thread: u32, name: &str) {
        if thread >= MAX_THREADS {
            return;
        }
        let clean: String = name
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
            .take(MAX_NAME)
            .collect();
        crate::lock::lock(&self.0).insert(thread, clean);
    }

    fn get(&self, thread: u32) -> Option<String> {
        crate::lock::lock(&self.0).get(&thread).cloned()
    }
}

/// The part the stepping threads and the writer share.
struct Shared {
    edges: ArrayQueue<Edge>,
    names: ThreadNames,
    start_ns: u64,
    stop: AtomicBool,
    dropped: AtomicU64,
    unmapped: AtomicU64,
}

/// A ThreadScope recording into a VCD file; ends (drained, flushed, closed) at
/// [`finish`](Self::finish) or when dropped.
pub struct VcdTrace {
    shared: Arc<Shared>,
    path: PathBuf,
    writer: Mutex<Option<JoinHandle<Result<VcdCounts, String>>>>,
    result: Mutex<Option<Result<VcdCounts, VcdError>>>,
}

impl VcdTrace {
    /// Creates `path` (never overwriting a file) and starts the writer thread. Time 0 in
    /// the file is now.
    pub fn create(path: &Path, names: ThreadNames) -> Result<VcdTrace, VcdError> {
        let file = File::options()
            .write(true)
            .create_new(true)
            .open(path)
            .map_err(|source| VcdError::Create {
                path: path.to_path_buf(),
                source,
            })?;
        let shared = Arc::new(Shared {
            edges: ArrayQueue::new(EDGE_QUEUE),
            names,
            start_ns: MonotonicClock.now().as_nanos(),
            stop: AtomicBool::new(false),
            dropped: AtomicU64::new(0),
            unmapped: AtomicU64::new(0),
        });
        let writer = {
            let shared = shared.clone();
            std::thread::Builder::new()
                .name("scope-vcd".into())
                .spawn(move || write_loop(&shared, BufWriter::new(file)))
                .map_err(|source| VcdError::Create {
                    path: path.to_path_buf(),
                    source,
                })?
        };
        tracing::info!(file = %path.display(), "ThreadScope: recording each thread's bit into {}", path.display());
        Ok(VcdTrace {
            shared,
            path: path.to_path_buf(),
            writer: Mutex::new(Some(writer)),
            result: Mutex::new(None),
        })
    }

    /// Records thread `thread`'s bit going `high` or low, now. Real-time safe (see the
    /// module's contract).
    pub fn record(&self, thread: u32, high: bool) {
        if thread >= MAX_THREADS {
            self.shared.unmapped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let edge = Edge {
            at_ns: MonotonicClock.now().as_nanos(),
            thread,
            high,
        };
        if self.shared.edges.push(edge).is_err() {
            self.shared.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Ends the recording: every edge recorded so far written, the counts in the file's
    /// closing comment, the file flushed and closed. Idempotent: later calls return the
    /// first one's result.
    pub fn finish(&self) -> Result<VcdCounts, VcdError> {
        let mut result = crate::lock::lock(&self.result);
        if let Some(r) = result.as_ref() {
            return match r {
                Ok(c) => Ok(*c),
                Err(e) => Err(VcdError::Write {
                    path: self.path.clone(),
                    message: e.to_string(),
                }),
            };
        }
        self.shared.stop.store(true, Ordering::Release);
        let handle = crate::lock::lock(&self.writer).take();
        if let Some(h) = &handle {
            // Out of its wait between drains at once.
            h.thread().unpark();
        }
        let r = match handle.map(JoinHandle::join) {
            Some(Ok(Ok(counts))) => Ok(counts),
            Some(Ok(Err(message))) => Err(message),
            Some(Err(_)) => Err("the writer thread panicked".to_string()),
            None => Err("the writer thread is gone".to_string()),
        }
        .map_err(|message| VcdError::Write {
            path: self.path.clone(),
            message,
        });
        match &r {
            Ok(c) => {
                tracing::info!(file = %self.path.display(), "ThreadScope recording ended: {} edges written, {} dropped, {} unmapped, {} late", c.written, c.dropped, c.unmapped, c.late)
            }
            Err(e) => tracing::error!("{e}"),
        }
        let copy = match &r {
            Ok(c) => Ok(*c),
            Err(e) => Err(VcdError::Write {
                path: self.path.clone(),
                message: e.to_string(),
            }),
        };
        *result = Some(r);
        copy
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for VcdTrace {
    fn drop(&mut self) {
        let _ = self.finish();
    }
}

/// The writer thread: drains the queue every [`DRAIN_PERIOD`], writes what is older than
/// [`HOLD_BACK_NS`] in time order, and everything once stopped.
fn write_loop(shared: &Shared, out: BufWriter<File>) -> Result<VcdCounts, String> {
    let mut file = VcdFile {
        out,
        header: false,
        last_ns: 0,
        counts: VcdCounts::default(),
    };
    // At most one queue's worth held back, plus what one drain takes.
    let mut pending: Vec<Edge> = Vec::with_capacity(EDGE_QUEUE * 2);
    loop {
        let stopping = shared.stop.load(Ordering::Acquire);
        while pending.len() < pending.capacity() {
            match shared.edges.pop() {
                Some(e) => pending.push(e),
                None => break,
            }
        }
        pending.sort_by_key(|e| e.at_ns);
        let horizon = if stopping {
            u64::MAX
        } else {
            MonotonicClock.now().as_nanos().saturating_sub(HOLD_BACK_NS)
        };
        let ready = pending.partition_point(|e| e.at_ns <= horizon);
        if ready > 0 || stopping {
            file.write_edges(shared, &pending[..ready])
                .map_err(|e| e.to_string())?;
            pending.drain(..ready);
        }
        if stopping && shared.edges.is_empty() {
            let end = MonotonicClock.now().as_nanos();
            file.close(shared, end).map_err(|e| e.to_string())?;
            return Ok(file.counts);
        }
        if !stopping {
            std::thread::park_timeout(DRAIN_PERIOD);
        }
    }
}

/// The file as written so far.
struct VcdFile {
    out: BufWriter<File>,
    header: bool,
    /// The last time written (ns since the start).
    last_ns: u64,
    counts: VcdCounts,
}

/// Thread `n`'s VCD identifier: one printable character from `!`.
fn ident(n: u32) -> char {
    char::from(b'!' + n as u8)
}

impl VcdFile {
    /// The declarations, with the thread names known now, and every signal low at 0.
    fn write_header(&mut self, shared: &Shared) -> std::io::Result<()> {
        let o = &mut self.out;
        writeln!(o, "$version hwgw ThreadScope $end")?;
        writeln!(
            o,
            "$comment each runtime thread's bit: high while it steps a component; t0 is the thread that made the runtime, then activity threads in the order they were made $end"
        )?;
        writeln!(o, "$timescale 1 ns $end")?;
        writeln!(o, "$scope module threadscope $end")?;
        for n in 0..MAX_THREADS {
            match (n, shared.names.get(n)) {
                (_, Some(name)) => writeln!(o, "$var wire 1 {} t{n}_{name} $end", ident(n))?,
                (0, None) => writeln!(o, "$var wire 1 {} t0_main $end", ident(n))?,
                (_, None) => writeln!(o, "$var wire 1 {} t{n} $end", ident(n))?,
            }
        }
        writeln!(o, "$upscope $end")?;
        writeln!(o, "$enddefinitions $end")?;
        writeln!(o, "#0")?;
        writeln!(o, "$dumpvars")?;
        for n in 0..MAX_THREADS {
            writeln!(o, "0{}", ident(n))?;
        }
        writeln!(o, "$end")?;
        self.header = true;
        Ok(())
    }

    fn write_edges(&mut self, shared: &Shared, edges: &[Edge]) -> std::io::Result<()> {
        if !self.header {
            if edges.is_empty() {
                return Ok(());
            }
            self.write_header(shared)?;
        }
        // The header wrote #0: a time is written when it moves on.
        for e in edges {
            let mut t = e.at_ns.saturating_sub(shared.start_ns);
            if t < self.last_ns {
                self.counts.late += 1;
                t = self.last_ns;
            }
            if t > self.last_ns {
                writeln!(self.out, "#{t}")?;
                self.last_ns = t;
            }
            writeln!(self.out, "{}{}", u8::from(e.high), ident(e.thread))?;
            self.counts.written += 1;
        }
        self.out.flush()
    }

    /// The end time and the counts, then flushed.
    fn close(&mut self, shared: &Shared, end_ns: u64) -> std::io::Result<()> {
        if !self.header {
            self.write_header(shared)?;
        }
        self.counts.dropped = shared.dropped.load(Ordering::Relaxed);
        self.counts.unmapped = shared.unmapped.load(Ordering::Relaxed);
        let end = end_ns.saturating_sub(shared.start_ns).max(self.last_ns);
        let c = self.counts;
        writeln!(
            self.out,
            "$comment edges written {}, dropped (queue full) {}, unmapped (thread {MAX_THREADS} or more) {}, late (written at a later time) {} $end",
            c.written, c.dropped, c.unmapped, c.late
        )?;
        writeln!(self.out, "#{end}")?;
        self.out.flush()?;
        self.out.get_ref().sync_data()
    }
}
