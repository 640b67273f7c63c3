//! The recording's writer thread: drains the edge queue, puts the edges in time order and
//! writes them as VCD.

use super::{DRAIN_PERIOD, EDGE_QUEUE, Edge, MAX_FILE_BYTES, MAX_THREADS, Shared, VcdCounts};
use device_interface::time::{Clock, MonotonicClock};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::sync::atomic::Ordering;

/// How long the writer holds edges back before writing them, so that an edge stamped just
/// before another thread's later one, but pushed after it, is still written in order.
const HOLD_BACK_NS: u64 = 5_000_000;

/// Drains the queue every [`DRAIN_PERIOD`], writes what is older than [`HOLD_BACK_NS`] in
/// time order, and, once stopped, what was queued then; then closes the file.
pub(super) fn run(shared: &Shared, out: BufWriter<File>) -> Result<VcdCounts, String> {
    let mut file = VcdFile {
        out,
        header: false,
        limit: MAX_FILE_BYTES,
        bytes: 0,
        last_ns: 0,
        last_stamp: 0,
        thread_last: [None; MAX_THREADS as usize],
        counts: VcdCounts::default(),
    };
    // At most one queue's worth held back, plus what one drain takes.
    let mut pending: Vec<Edge> = Vec::with_capacity(EDGE_QUEUE * 2);
    loop {
        let stopping = shared.stop.load(Ordering::Acquire);
        // Taken before the drain: an edge pushed during it is stamped after the horizon.
        let horizon = if stopping {
            u64::MAX
        } else {
            MonotonicClock.now().as_nanos().saturating_sub(HOLD_BACK_NS)
        };
        // Once stopped, what is queued now: threads still pushing cannot keep this going.
        let mut take = if stopping {
            shared.edges.len()
        } else {
            usize::MAX
        };
        while pending.len() < pending.capacity() && take > 0 {
            match shared.edges.pop() {
                Some(e) => pending.push(e),
                None => break,
            }
            take -= 1;
        }
        // Stable: a thread's edges of one stamp keep their order (rise before fall).
        pending.sort_by_key(|e| e.at_ns);
        let ready = pending.partition_point(|e| e.at_ns <= horizon);
        if ready > 0 {
            file.write_edges(shared, &pending[..ready])
                .map_err(|e| e.to_string())?;
            pending.drain(..ready);
        }
        if stopping {
            let end = MonotonicClock.now().as_nanos();
            file.close(shared, end).map_err(|e| e.to_string())?;
            return Ok(file.counts);
        }
        std::thread::park_timeout(DRAIN_PERIOD);
    }
}

/// The file as written so far.
struct VcdFile {
    out: BufWriter<File>,
    header: bool,
    /// The most bytes written ([`MAX_FILE_BYTES`]).
    limit: u64,
    /// Bytes written.
    bytes: u64,
    /// The last time written (ns since the start).
    last_ns: u64,
    /// The largest stamp written (ns since the start), before any adjustment.
    last_stamp: u64,
    /// Each thread's last time written.
    thread_last: [Option<u64>; MAX_THREADS as usize],
    counts: VcdCounts,
}

/// Thread `n`'s VCD identifier: one printable character from `!`.
fn ident(n: u32) -> char {
    char::from(b'!' + n as u8)
}

impl VcdFile {
    /// Writes `text` and counts it.
    fn put(&mut self, text: std::fmt::Arguments<'_>) -> std::io::Result<()> {
        struct Count<'a>(&'a mut BufWriter<File>, u64);
        impl std::fmt::Write for Count<'_> {
            fn write_str(&mut self, s: &str) -> std::fmt::Result {
                self.1 += s.len() as u64;
                self.0.write_all(s.as_bytes()).map_err(|_| std::fmt::Error)
            }
        }
        let mut c = Count(&mut self.out, 0);
        let r = std::fmt::write(&mut c, text);
        self.bytes += c.1;
        r.map_err(|_| std::io::Error::other("write failed"))
    }

    /// The declarations, with the thread names known now, and every signal low at 0.
    fn write_header(&mut self, shared: &Shared) -> std::io::Result<()> {
        self.put(format_args!("$version hwgw ThreadScope $end\n"))?;
        self.put(format_args!(
            "$comment each runtime thread's bit: high while it steps a component; t0 is the thread that made the runtime, then activity threads in the order they were made $end\n"
        ))?;
        self.put(format_args!("$timescale 1 ns $end\n"))?;
        self.put(format_args!("$scope module threadscope $end\n"))?;
        for n in 0..MAX_THREADS {
            let name = shared.names.signal(n);
            self.put(format_args!("$var wire 1 {} {name} $end\n", ident(n)))?;
        }
        self.put(format_args!(
            "$upscope $end\n$enddefinitions $end\n#0\n$dumpvars\n"
        ))?;
        for n in 0..MAX_THREADS {
            self.put(format_args!("0{}\n", ident(n)))?;
        }
        self.put(format_args!("$end\n"))?;
        self.header = true;
        Ok(())
    }

    fn write_edges(&mut self, shared: &Shared, edges: &[Edge]) -> std::io::Result<()> {
        if !self.header {
            self.write_header(shared)?;
        }
        // The header wrote #0: a time is written when it moves on.
        for e in edges {
            if self.bytes >= self.limit {
                self.counts.truncated += 1;
                continue;
            }
            let stamp = e.at_ns.saturating_sub(shared.start_ns);
            let mut t = stamp;
            if stamp < self.last_stamp {
                self.counts.late += 1;
            }
            self.last_stamp = self.last_stamp.max(stamp);
            let slot = &mut self.thread_last[e.thread as usize];
            if slot.is_some_and(|last| t <= last) {
                // The same nanosecond as this thread's previous edge: 1 ns later, so the
                // pulse shows (a viewer keeps only a signal's last value of a time).
                t = slot.map_or(t, |last| last + 1);
                self.counts.widened += 1;
            }
            t = t.max(self.last_ns);
            *slot = Some(t);
            if t > self.last_ns {
                self.put(format_args!("#{t}\n"))?;
                self.last_ns = t;
            }
            self.put(format_args!("{}{}\n", u8::from(e.high), ident(e.thread)))?;
            self.counts.written += 1;
        }
        self.out.flush()
    }

    /// The end time, then the counts (a viewer stops reading a chunk at a comment), then
    /// flushed to the disk.
    fn close(&mut self, shared: &Shared, end_ns: u64) -> std::io::Result<()> {
        if !self.header {
            self.write_header(shared)?;
        }
        self.counts.dropped = shared.dropped.load(Ordering::Relaxed);
        self.counts.unmapped = shared.unmapped.load(Ordering::Relaxed);
        let end = end_ns.saturating_sub(shared.start_ns).max(self.last_ns + 1);
        let (c, limit) = (self.counts, self.limit);
        self.put(format_args!("#{end}\n"))?;
        self.put(format_args!(
            "$comment edges written {}, dropped (queue full) {}, unmapped (thread {MAX_THREADS} or more) {}, late (written at a later time) {}, widened (1 ns after their stamp) {}, truncated (past {} bytes) {} $end\n",
            c.written, c.dropped, c.unmapped, c.late, c.widened, limit, c.truncated
        ))?;
        self.out.flush()?;
        self.out.get_ref().sync_data()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scope::vcd::ThreadNames;
    use std::sync::atomic::{AtomicBool, AtomicU64};

    fn shared() -> Shared {
        Shared {
            edges: crossbeam_queue::ArrayQueue::new(16),
            names: ThreadNames::default(),
            start_ns: 1_000,
            stop: AtomicBool::new(true),
            dropped: AtomicU64::new(0),
            unmapped: AtomicU64::new(0),
        }
    }

    fn file(dir: &std::path::Path, limit: u64) -> (VcdFile, std::path::PathBuf) {
        let path = dir.join(format!("w{limit}.vcd"));
        let out = BufWriter::new(File::create(&path).unwrap());
        let f = VcdFile {
            out,
            header: false,
            limit,
            bytes: 0,
            last_ns: 0,
            last_stamp: 0,
            thread_last: [None; MAX_THREADS as usize],
            counts: VcdCounts::default(),
        };
        (f, path)
    }

    fn edge(at_ns: u64, thread: u32, high: bool) -> Edge {
        Edge {
            at_ns,
            thread,
            high,
        }
    }

    /// The value-change lines after the header's `$dumpvars ... $end`.
    fn body(path: &std::path::Path) -> Vec<String> {
        let text = std::fs::read_to_string(path).unwrap();
        let start = text.find("$dumpvars").unwrap();
        let after = &text[start..];
        let end = after.find("$end\n").unwrap() + 5;
        after[end..].lines().map(str::to_string).collect()
    }

    #[test]
    fn a_pulse_within_one_nanosecond_is_widened_and_a_late_edge_written_at_the_latest_time() {
        let dir = std::env::temp_dir().join(format!("rtt-vcd-writer-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let s = shared();
        let (mut f, path) = file(&dir, MAX_FILE_BYTES);
        // Thread 1 rises and falls at one stamp; thread 2 at 1 000 ns.
        f.write_edges(
            &s,
            &[
                edge(1_500, 1, true),
                edge(1_500, 1, false),
                edge(2_000, 2, true),
            ],
        )
        .unwrap();
        // A batch later: thread 3's edge stamped before what was written.
        f.write_edges(&s, &[edge(1_200, 3, true), edge(2_500, 2, false)])
            .unwrap();
        f.close(&s, 3_000).unwrap();
        assert_eq!(
            (f.counts.written, f.counts.widened, f.counts.late),
            (5, 1, 1)
        );
        let b = body(&path);
        let want = [
            "#500", "1\"", "#501", "0\"", "#1000", "1#", "1$", "#1500", "0#", "#2000",
        ];
        assert_eq!(b[..want.len()], want, "{b:?}");
        assert!(
            b[want.len()].starts_with("$comment edges written 5,"),
            "{b:?}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn edges_past_the_size_limit_are_counted_not_written() {
        let dir = std::env::temp_dir().join(format!("rtt-vcd-limit-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let s = shared();
        // The header alone is past 100 bytes: every edge is truncated.
        let (mut f, path) = file(&dir, 100);
        f.write_edges(&s, &[edge(1_500, 1, true), edge(1_600, 1, false)])
            .unwrap();
        f.close(&s, 2_000).unwrap();
        assert_eq!((f.counts.written, f.counts.truncated), (0, 2));
        let b = body(&path);
        assert_eq!(b[0], "#1000");
        assert!(b[1].contains("truncated (past 100 bytes) 2"), "{b:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
