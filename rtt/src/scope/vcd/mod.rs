//! ThreadScope as a waveform: each runtime thread's bit recorded into a Value Change Dump
//! (IEEE 1364 VCD, nanosecond timescale, one 1-bit signal per thread) that PulseView,
//! GTKWave and `sigrok-cli` open — a logic analyser on the ThreadScope without the
//! hardware.
//!
//! Real-time contract: a thread stepping records an edge with one clock read (the vDSO)
//! and one push on a bounded lock-free queue ([`EDGE_QUEUE`] edges): no lock, no
//! allocation, no wait on the writer (a queue within [`MAX_THREADS`] edges of full counts
//! the edge dropped instead of pushing, so a push never meets the slot the writer is
//! taking; pushes of several threads at once may spin briefly on each other, as any
//! lock-free queue's do). A writer thread of its own drains the queue every
//! [`DRAIN_PERIOD`] into the file (buffered), so the file's I/O never reaches a stepping
//! thread.
//!
//! What cannot be recorded is counted, never silently lost: an edge that found the queue
//! (nearly) full (`dropped`), one of a thread numbered [`MAX_THREADS`] or more
//! (`unmapped`), one that reached the writer after later edges were written (`late`:
//! written at the latest time written, since VCD times only go forward), one past
//! [`MAX_FILE_BYTES`] (`truncated`); a thread's edge stamped at the same nanosecond as its
//! previous one is written 1 ns later (`widened`), so a pulse shorter than the clock's
//! resolution still shows. The counts are written into the file's closing comment, logged,
//! and returned by [`VcdTrace::finish`]. Edges recorded after `finish` are not recorded.
//!
//! The file is created new, never through a symbolic link and never over an existing
//! name ([`files`]): [`VcdTrace::create`] makes exactly the file named, and
//! [`VcdTrace::create_numbered`] a new numbered one per run (`threads.vcd` gives
//! `threads-1.vcd`, `threads-2.vcd`, …), the last `keep` kept — so a restarted service
//! never finds its file taken.

pub mod files;
mod writer;

use crossbeam_queue::ArrayQueue;
use device_interface::time::{Clock, MonotonicClock};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::sync::{Arc, Mutex};
use std::thread::Thread;
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

/// The largest file written (1 GiB: about 8 hours of one thread stepping at 1 kHz);
/// edges past it are counted as truncated.
pub const MAX_FILE_BYTES: u64 = 1 << 30;

/// How long [`VcdTrace::finish`] waits for the writer to write what is left and flush (a
/// file on a hung disk must not hang a stop); past it the writer is left to finish alone.
pub const FINISH_TIMEOUT: Duration = Duration::from_secs(5);

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
    /// Edges lost to a (nearly) full queue.
    pub dropped: u64,
    /// Edges of threads numbered [`MAX_THREADS`] or more.
    pub unmapped: u64,
    /// Edges that came after later ones were written (written at the later time).
    pub late: u64,
    /// Edges written 1 ns after their stamp, which was their thread's previous edge's.
    pub widened: u64,
    /// Edges not written: the file had reached [`MAX_FILE_BYTES`].
    pub truncated: u64,
}

/// Errors of a ThreadScope recording.
#[derive(Debug, thiserror::Error)]
pub enum VcdError {
    /// The path names no file (empty, or a folder).
    #[error("ThreadScope VCD file {:?}: expected a file name", path.display().to_string())]
    NotAFile {
        /// The path given.
        path: PathBuf,
    },
    /// The file could not be created (it exists already, it is a link, its folder does not
    /// exist), or the writer thread could not be started (the file is then removed again).
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
    /// Writing the file failed (what was written before stays), or did not end within
    /// [`FINISH_TIMEOUT`].
    #[error("ThreadScope VCD file {}: {message}", path.display())]
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

    /// Thread `thread`'s signal name: `t<thread>_<name>`, `t0_main`, or `t<thread>`.
    pub fn signal(&self, thread: u32) -> String {
        match (thread, crate::lock::lock(&self.0).get(&thread)) {
            (n, Some(name)) => format!("t{n}_{name}"),
            (0, None) => "t0_main".to_string(),
            (n, None) => format!("t{n}"),
        }
    }

    /// The named threads' numbers.
    pub fn named(&self) -> Vec<u32> {
        crate::lock::lock(&self.0).keys().copied().collect()
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
    writer: Thread,
    /// The writer's result, until taken by `finish`.
    done: Mutex<Option<Receiver<Result<VcdCounts, String>>>>,
    /// `finish`'s result (an error as its message).
    result: Mutex<Option<Result<VcdCounts, String>>>,
}

impl VcdTrace {
    /// Creates `path` (never over an existing name, never through a link: see
    /// [`files`]) and starts the writer thread. Time 0 in the file is now; the signals are
    /// named from `names` as they are when the first edges are written.
    pub fn create(path: &Path, names: ThreadNames) -> Result<VcdTrace, VcdError> {
        let text = path.as_os_str().as_encoded_bytes();
        if path.file_name().is_none() || text.ends_with(b"/") {
            return Err(VcdError::NotAFile {
                path: path.to_path_buf(),
            });
        }
        let file = files::create_new(path)?;
        VcdTrace::start(file, path, names)
    }

    /// Creates the next numbered file of `base` (`threads.vcd` gives `threads-<n>.vcd`, one
    /// past the highest number there), removes the oldest so that the last `keep` remain
    /// (see [`files`]), and starts the writer thread on it, as [`create`](Self::create).
    /// [`path`](Self::path) is the file made.
    pub fn create_numbered(
        base: &Path,
        keep: u32,
        names: ThreadNames,
    ) -> Result<VcdTrace, VcdError> {
        let text = base.as_os_str().as_encoded_bytes();
        if base.file_name().is_none() || text.ends_with(b"/") {
            return Err(VcdError::NotAFile {
                path: base.to_path_buf(),
            });
        }
        let (file, path) = files::create_numbered(base, keep)?;
        VcdTrace::start(file, &path, names)
    }

    /// Starts the writer thread on `file`, just made at `path`.
    fn start(file: File, path: &Path, names: ThreadNames) -> Result<VcdTrace, VcdError> {
        let create_error = |source| VcdError::Create {
            path: path.to_path_buf(),
            source,
        };
        let shared = Arc::new(Shared {
            edges: ArrayQueue::new(EDGE_QUEUE),
            names,
            start_ns: MonotonicClock.now().as_nanos(),
            stop: AtomicBool::new(false),
            dropped: AtomicU64::new(0),
            unmapped: AtomicU64::new(0),
        });
        let (tx, rx) = std::sync::mpsc::channel();
        let spawned = {
            let shared = shared.clone();
            let path = path.to_path_buf();
            std::thread::Builder::new()
                .name("scope-vcd".into())
                .spawn(move || {
                    let r = writer::run(&shared, BufWriter::new(file));
                    if let Err(e) = &r {
                        tracing::error!("ThreadScope VCD file {}: {e}", path.display());
                    }
                    let _ = tx.send(r);
                })
        };
        let handle = match spawned {
            Ok(h) => h,
            Err(e) => {
                // The file this call just created, empty: not left to block the next run.
                let _ = std::fs::remove_file(path);
                return Err(create_error(e));
            }
        };
        tracing::info!(file = %path.display(), "ThreadScope: recording each thread's bit into {}", path.display());
        Ok(VcdTrace {
            shared,
            path: path.to_path_buf(),
            writer: handle.thread().clone(),
            done: Mutex::new(Some(rx)),
            result: Mutex::new(None),
        })
    }

    /// Records thread `thread`'s bit going `high` or low, now. Real-time safe (see the
    /// module's contract).
    pub fn record(&self, thread: u32, high: bool) {
        let s = &*self.shared;
        if thread >= MAX_THREADS {
            s.unmapped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        if s.stop.load(Ordering::Relaxed) {
            return;
        }
        // Near full: dropped without pushing, so a push never meets the slot being taken.
        if s.edges.len() + MAX_THREADS as usize >= EDGE_QUEUE {
            s.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let edge = Edge {
            at_ns: MonotonicClock.now().as_nanos(),
            thread,
            high,
        };
        if s.edges.push(edge).is_err() {
            s.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Ends the recording: the edges recorded so far written, the end time and the counts
    /// (in a closing comment), the file flushed and closed — within [`FINISH_TIMEOUT`],
    /// else an error and the writer left to finish alone. Idempotent: later calls return
    /// the first one's result. Edges recorded from now on are not recorded.
    pub fn finish(&self) -> Result<VcdCounts, VcdError> {
        let mut result = crate::lock::lock(&self.result);
        if result.is_none() {
            self.shared.stop.store(true, Ordering::Release);
            // Out of its wait between drains at once.
            self.writer.unpark();
            let r = match crate::lock::lock(&self.done).take() {
                Some(rx) => match rx.recv_timeout(FINISH_TIMEOUT) {
                    Ok(r) => r.map_err(|e| format!("writing failed: {e}")),
                    Err(RecvTimeoutError::Timeout) => Err(format!(
                        "still writing after {} s; left to finish on its own",
                        FINISH_TIMEOUT.as_secs()
                    )),
                    Err(RecvTimeoutError::Disconnected) => {
                        Err("the writer thread ended without a result".to_string())
                    }
                },
                None => Err("the writer thread is gone".to_string()),
            };
            match &r {
                Ok(c) => tracing::info!(
                    file = %self.path.display(),
                    "ThreadScope recording ended: {} edges written, {} dropped, {} unmapped, {} late, {} widened, {} truncated",
                    c.written, c.dropped, c.unmapped, c.late, c.widened, c.truncated
                ),
                Err(e) => tracing::error!("ThreadScope VCD file {}: {e}", self.path.display()),
            }
            *result = Some(r);
        }
        match result.as_ref() {
            Some(Ok(c)) => Ok(*c),
            Some(Err(message)) => Err(VcdError::Write {
                path: self.path.clone(),
                message: message.clone(),
            }),
            None => Err(VcdError::Write {
                path: self.path.clone(),
                message: "no result".to_string(),
            }),
        }
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
