//! Periodic wake-up jitter of an rtt periodic activity, side by side with cyclictest: the
//! worst case as much as the middle.
//!
//! Runs a periodic activity at 1 kHz for 10 s (`JITTER_SECONDS` to change), recording when
//! each step began and how late, then runs `cyclictest -v` (Debian rt-tests, with `-m`:
//! memory locked, as the activity locks it) for the same number of loops at the same
//! interval, priority and policy, one latency a loop. Each round prints p50, p99, p99.9 and
//! max of both, their ratios, and how many periods of each were longer than 1.2× nominal
//! (Machinekit's overrun: the interval between two wake-ups — hwgw's from its steps' start
//! times, cyclictest's rebuilt from its latencies with its own rule for missed wake-ups).
//! It also prints the host's steal time during each half (`/proc/stat`, CPU-ms summed
//! over the CPUs), so a round where the hypervisor stalled the machine says so, and for
//! each half's longest period the steal within 20 ms of it (a thread of the bench samples
//! the counter every 2 ms during both halves, `JITTER_STEAL_EVERY_MS` to change, 0 for no
//! such thread; cyclictest's wake-up times are rebuilt from
//! its start) and, for hwgw's thread, its page faults and involuntary context switches over
//! the half: a long period with steal around it is the host's; one without, and without a
//! fault or switch of the thread's, is the guest kernel's or a stall the counter missed. Five
//! rounds (`JITTER_RUNS`), then the median of the max and p99 ratios and the rounds where
//! hwgw had long periods and cyclictest had none.
//!
//! Both halves run on the same CPU (`JITTER_CPU`, by default the number of CPUs the process
//! may use less one; `JITTER_PIN=0`: where the scheduler puts them — on the machine of
//! 2026-12-01 that was hwgw's thread on CPU 1 and cyclictest's on CPU 0 in each half
//! watched, so each met another CPU's stalls). Pinned, that CPU runs the measured threads
//! alone: the bench's other threads and cyclictest's main thread (`--mainaffinity`) are
//! kept on the others, since on a kernel that does not preempt kernel code a thread in a
//! system call on the measured CPU holds a real-time wake-up until it leaves the kernel.
//!
//! A third piece of each round runs the two together on that CPU, half a period apart, for
//! the same number of cyclictest's wake-ups (`JITTER_TOGETHER=0` leaves it out, `2` runs it
//! alone): a stall of that CPU delays both, and each late wake-up of one is set beside what
//! the other did meanwhile (`together.rs`). Its figures count only the seconds both ran;
//! the summary gives the median of its max ratios and how many late wake-ups of each were
//! its own.
//!
//! Both hold `/dev/cpu_dma_latency` at 0 while they run (cyclictest's default; the runtime's
//! `cpu_dma_latency_us` option). Both ask for SCHED_FIFO at `JITTER_PRIORITY` (default 80);
//! when the machine refuses it, both run SCHED_OTHER, and the output says so.
//!
//! The probe records into arrays made and written through before the activity starts, with
//! relaxed stores: no lock, no allocation and no first-touch page fault on the measured
//! thread.
//!
//! Run: `cargo bench -p rtt --bench jitter`; the run is
//! `JITTER_RUNS=10 JITTER_SECONDS=60 cargo bench -p rtt --bench jitter`.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

#[path = "jitter/report.rs"]
mod report;
#[path = "jitter/together.rs"]
mod together;

use report::{Settings, Tally, print_rows, print_together, print_worst};

use device_interface::Registry;
use hdrhistogram::Histogram;
use rtt::activity::{ActivitySpec, SchedPolicy, ThreadOptions, Timing};
use rtt::{Component, Context, HookResult, Runtime, RuntimeOptions};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::time::Duration;

const PERIOD_US: u64 = 1000;
/// A wake-up this late after an on-time one makes a period over 1.2× nominal, µs.
const LATE_US: u64 = PERIOD_US / 5;
/// A period longer than this is an overrun (1.2× nominal).
const LONG_US: u64 = PERIOD_US * 6 / 5;

/// Each step's lateness in µs, floored as cyclictest reports it, its start and when it was
/// due (monotonic ns).
struct Trace {
    late_us: Vec<AtomicU64>,
    start_ns: Vec<AtomicU64>,
    due_ns: Vec<AtomicU64>,
    len: AtomicUsize,
}

impl Trace {
    fn new(loops: usize) -> Self {
        Trace {
            late_us: touched(loops),
            start_ns: touched(loops),
            due_ns: touched(loops),
            len: AtomicUsize::new(0),
        }
    }

    /// The recorded steps so far: (lateness µs, start ns, due ns).
    fn steps(&self) -> Vec<(u64, u64, u64)> {
        let n = self.len.load(Ordering::Acquire);
        (0..n)
            .map(|i| {
                (
                    self.late_us[i].load(Ordering::Relaxed),
                    self.start_ns[i].load(Ordering::Relaxed),
                    self.due_ns[i].load(Ordering::Relaxed),
                )
            })
            .collect()
    }
}

/// `n` zeroed atomics whose pages are written here, not on the measured thread. Zeroes
/// collected into a vector may become one `calloc`, whose fresh pages stay unmapped
/// until first written: the first round's hwgw thread took 117 page faults over its
/// half that way (a 480 KB array is 117 pages). A volatile store to each element cannot
/// be left out.
fn touched(n: usize) -> Vec<AtomicU64> {
    let v: Vec<AtomicU64> = (0..n).map(|_| AtomicU64::new(0)).collect();
    for a in &v {
        // SAFETY: the pointer is to an element of `v`, alive and not shared yet.
        #[allow(unsafe_code, reason = "a volatile store to touch the element's page")]
        unsafe {
            std::ptr::write_volatile(a.as_ptr(), 0);
        }
    }
    v
}

struct Probe {
    trace: Arc<Trace>,
    /// The activity thread's id, stored at its first step.
    tid: Arc<std::sync::atomic::AtomicU32>,
}

impl Component for Probe {
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let t = ctx.timing();
        if self.tid.load(Ordering::Relaxed) == 0 {
            // The first step: before its record, so the record's release publishes it.
            let tid = nix::unistd::gettid().as_raw() as u32;
            self.tid.store(tid, Ordering::Relaxed);
        }
        let i = self.trace.len.load(Ordering::Relaxed);
        if i < self.trace.late_us.len() {
            let us = t.lateness().as_micros() as u64;
            self.trace.late_us[i].store(us, Ordering::Relaxed);
            self.trace.start_ns[i].store(t.started.as_nanos(), Ordering::Relaxed);
            self.trace.due_ns[i].store(t.scheduled.as_nanos(), Ordering::Relaxed);
            self.trace.len.store(i + 1, Ordering::Release);
        }
        Ok(())
    }
}

struct Figures {
    p50: u64,
    p99: u64,
    p999: u64,
    max: u64,
    count: u64,
    /// Intervals between wake-ups longer than 1.2× the period.
    long: u64,
    /// The longest interval between two wake-ups, µs.
    longest: u64,
    /// The host's steal time while it ran, ms.
    steal_ms: u64,
    /// What was seen around the longest period.
    worst: Worst,
}

/// The longest period of a half and what was seen around it.
#[derive(Default)]
struct Worst {
    /// When it began, seconds into the half.
    at_s: f64,
    /// The host's steal time in the window around it (the period and
    /// [`WITNESS_MARGIN_MS`] on each side), ms; None when not sampled.
    steal_ms: Option<u64>,
    /// The measured thread's page faults (minor + major) and involuntary context switches
    /// over the whole half, when known (hwgw's thread; not cyclictest's).
    thread: Option<(u64, u64)>,
}

/// How far on each side of the longest period the steal around it is summed: the steal
/// counter moves in 10 ms ticks, and cyclictest's wake-up times are rebuilt from its start
/// (a few ms off).
const WITNESS_MARGIN_MS: u64 = 20;

/// The host's steal time sampled every `JITTER_STEAL_EVERY_MS` (default 2; 0: not
/// sampled, no thread) on a thread of its own while a half runs, so that the half's longest
/// period can be set beside the steal around it. Both halves run with it.
struct StealWatch {
    stop: Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<Vec<(u64, u64)>>>,
}

impl StealWatch {
    fn start() -> StealWatch {
        let every: u64 = std::env::var("JITTER_STEAL_EVERY_MS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(2);
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let s = stop.clone();
        let thread = (every > 0).then(|| {
            std::thread::spawn(move || {
                let mut samples = Vec::with_capacity(64 * 1024);
                while !s.load(Ordering::Relaxed) {
                    samples.push((now_ns(), testkit::bench::steal_ms()));
                    std::thread::sleep(Duration::from_millis(every));
                }
                samples.push((now_ns(), testkit::bench::steal_ms()));
                samples
            })
        });
        StealWatch { stop, thread }
    }

    /// The samples: (monotonic ns, steal ms so far); none when not sampled.
    fn finish(self) -> Vec<(u64, u64)> {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.map_or_else(Vec::new, |t| t.join().unwrap())
    }
}

/// Steal between the last sample at or before `from` and the first at or after `to`, ms;
/// None when the window is not within the samples.
fn steal_between(samples: &[(u64, u64)], from: u64, to: u64) -> Option<u64> {
    let before = samples.iter().rev().find(|s| s.0 <= from)?;
    let after = samples.iter().find(|s| s.0 >= to)?;
    Some(after.1.saturating_sub(before.1))
}

fn now_ns() -> u64 {
    use device_interface::time::{Clock, MonotonicClock};
    MonotonicClock.now().as_nanos()
}

/// The longest period of a half from its wake-up times (ns), with the steal around it.
fn worst(wakes: &[u64], samples: &[(u64, u64)], thread: Option<(u64, u64)>) -> Worst {
    let Some(i) = (1..wakes.len()).max_by_key(|&i| wakes[i] - wakes[i - 1]) else {
        return Worst::default();
    };
    let margin = WITNESS_MARGIN_MS * 1_000_000;
    Worst {
        at_s: (wakes[i - 1] - wakes[0]) as f64 / 1e9,
        steal_ms: steal_between(
            samples,
            wakes[i - 1].saturating_sub(margin),
            wakes[i] + margin,
        ),
        thread,
    }
}

/// The page faults (minor + major) and involuntary context switches of this process's
/// thread `tid` so far.
fn thread_counts(tid: u32) -> Option<(u64, u64)> {
    let stat = std::fs::read_to_string(format!("/proc/self/task/{tid}/stat")).ok()?;
    // Fields after the command's closing parenthesis: state is field 3, minflt 10, majflt 12.
    let rest: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let faults = rest.get(7)?.parse::<u64>().ok()? + rest.get(9)?.parse::<u64>().ok()?;
    let status = std::fs::read_to_string(format!("/proc/self/task/{tid}/status")).ok()?;
    let switches = status
        .lines()
        .find_map(|l| l.strip_prefix("nonvoluntary_ctxt_switches:"))?
        .trim()
        .parse()
        .ok()?;
    Some((faults, switches))
}

/// Figures of a run from its latencies (µs) and the intervals between its wake-ups (µs).
fn figures(
    late: &[u64],
    intervals: impl Iterator<Item = u64>,
    steal_ms: u64,
    worst: Worst,
) -> Figures {
    let mut h = Histogram::<u64>::new_with_bounds(1, 10_000_000, 3).unwrap();
    for &us in late {
        h.record(us.clamp(1, 10_000_000)).unwrap();
    }
    let (mut long, mut longest) = (0, 0);
    for i in intervals {
        long += u64::from(i > LONG_US);
        longest = longest.max(i);
    }
    Figures {
        p50: h.value_at_quantile(0.5),
        p99: h.value_at_quantile(0.99),
        p999: h.value_at_quantile(0.999),
        max: late.iter().copied().max().unwrap_or(0),
        count: late.len() as u64,
        long,
        longest,
        steal_ms,
        worst,
    }
}

/// A running probe: the periodic activity recording into its trace.
struct Running {
    /// Kept alive while the activity runs.
    _rt: Runtime,
    task: rtt::TaskContext,
    trace: Arc<Trace>,
    /// The activity thread's id, as its first step said.
    tid: Option<u32>,
}

/// Starts the probe at 1 kHz with room for `capacity` steps, on `cpus` (empty: any), and
/// returns after its first step.
fn start_probe(capacity: u64, fifo: bool, priority: i32, cpus: Vec<usize>) -> Running {
    let trace = Arc::new(Trace::new(usize::try_from(capacity).unwrap()));
    // The same CPU-latency request cyclictest makes by default (/dev/cpu_dma_latency = 0).
    let options = RuntimeOptions {
        cpu_dma_latency_us: Some(0),
        ..RuntimeOptions::default()
    };
    let rt = Runtime::new(Arc::new(Registry::new()), options).unwrap();
    let spec = ActivitySpec::Periodic {
        period: Duration::from_micros(PERIOD_US),
        thread: ThreadOptions {
            policy: if fifo {
                SchedPolicy::Fifo
            } else {
                SchedPolicy::Other
            },
            priority,
            cpus,
            ..ThreadOptions::default()
        },
        timing: Timing::Absolute,
        max_overruns: None,
    };
    let tr = trace.clone();
    let thread = Arc::new(std::sync::atomic::AtomicU32::new(0));
    let th = thread.clone();
    let task = rt
        .add("jitter", spec, rtt::InitialState::Stopped, move |_| {
            Ok(Probe { trace: tr, tid: th })
        })
        .unwrap();
    task.start().unwrap();
    while trace.len.load(Ordering::Acquire) == 0 {
        std::thread::sleep(Duration::from_millis(1));
    }
    if fifo && !task.stats().realtime {
        eprintln!("warning: the activity did not get SCHED_FIFO");
    }
    // The activity's thread, as its first step (published with its record) said.
    let tid = Some(thread.load(Ordering::Relaxed)).filter(|&t| t != 0);
    Running {
        _rt: rt,
        task,
        trace,
        tid,
    }
}

/// hwgw's half of a round, on `cpu` or (None) where the scheduler puts it.
fn run_rtt(loops: u64, fifo: bool, priority: i32, cpu: Option<usize>) -> Figures {
    let steal = testkit::bench::steal_ms();
    let watch = StealWatch::start();
    let run = start_probe(loops, fifo, priority, cpu.into_iter().collect());
    let counts_before = run.tid.and_then(thread_counts);
    while run.trace.len.load(Ordering::Acquire) < run.trace.late_us.len() {
        std::thread::sleep(Duration::from_millis(50));
    }
    let counts = match (counts_before, run.tid.and_then(thread_counts)) {
        (Some(b), Some(a)) => Some((a.0 - b.0, a.1 - b.1)),
        _ => None,
    };
    run.task.stop().unwrap();
    let samples = watch.finish();
    let steal = testkit::bench::steal_ms().saturating_sub(steal);
    let steps = run.trace.steps();
    let late: Vec<u64> = steps.iter().map(|s| s.0).collect();
    let starts: Vec<u64> = steps.iter().map(|s| s.1).collect();
    // The runtime skips wake-ups it missed (keeping the grid), so its intervals are taken
    // from the starts themselves; in µs, floored like the latencies.
    let intervals = starts.windows(2).map(|w| (w[1] - w[0]) / 1000);
    let worst = worst(&starts, &samples, counts);
    figures(&late, intervals, steal, worst)
}

/// cyclictest's half of a round, on the settings' CPU or where the scheduler puts it.
fn run_cyclictest(set: &Settings) -> Result<Figures, String> {
    let (loops, fifo, priority) = (set.loops, set.fifo, set.priority);
    let prio = if fifo { priority } else { 0 };
    let watch = StealWatch::start();
    let spawned = now_ns();
    let pin = set.apart_cpu.map(|c| format!("-a{c}"));
    let main = set.cyclictest_main();
    let mut extra = vec!["-v"];
    extra.extend(pin.as_deref());
    extra.extend(main.as_deref());
    let (text, steal) = testkit::bench::cyclictest(prio, PERIOD_US, loops, &extra)?;
    let samples = watch.finish();
    // `-v` prints `thread: loop: latency` for every loop.
    let late = testkit::stalls::cyclictest_latencies(&text);
    if late.len() as u64 != loops {
        return Err(format!(
            "cyclictest -v printed {} latencies for {loops} loops",
            late.len()
        ));
    }
    // cyclictest's wake-up k was due at its grid point plus `late[k]`; after it, the next
    // grid point is one period on, or — when it woke a period or more late — the first
    // point not before its wake-up (its loop moves `next` on while `now` is past it). So
    // the interval is the points moved over plus the change in lateness: the rebuilt
    // wake-up times, as the runtime's (which skips missed wake-ups too) are taken.
    let intervals: Vec<u64> = late
        .windows(2)
        .map(|w| {
            let moved = w[0].div_ceil(PERIOD_US).max(1) * PERIOD_US;
            (moved + w[1]).saturating_sub(w[0])
        })
        .collect();
    // Its wake-up times, rebuilt from its start: the first a period after the spawn (its
    // set-up, a few ms, is the error), then the intervals.
    let mut wakes = vec![spawned + PERIOD_US * 1000 + late[0] * 1000];
    for i in &intervals {
        wakes.push(wakes[wakes.len() - 1] + i * 1000);
    }
    let worst = worst(&wakes, &samples, None);
    Ok(figures(&late, intervals.into_iter(), steal, worst))
}

fn main() -> ExitCode {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return ExitCode::SUCCESS; // `cargo test --benches` lists or smoke-runs: nothing to do.
    }
    let set = match Settings::from_env() {
        Ok(s) => s,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    set.print_header();
    if let Err(e) = set.keep_off_measured_cpu() {
        eprintln!("{e}");
        return ExitCode::FAILURE;
    }
    let (mut apart, mut joint) = (Tally::default(), Tally::default());
    for run in 1..=set.runs.max(1) {
        if set.apart {
            // The two in turn, each round: a machine that gets busier or quieter over the
            // rounds weighs on both alike.
            let ours = run_rtt(set.loops, set.fifo, set.priority, set.apart_cpu);
            let theirs = match run_cyclictest(&set) {
                Ok(f) => f,
                Err(e) => {
                    eprintln!("{e}");
                    return ExitCode::FAILURE;
                }
            };
            print_rows(run, &ours, &theirs);
            print_worst(run, &ours, &theirs);
            apart.add(run, &ours, &theirs);
        }
        if set.together {
            match together::run(&set) {
                Ok(t) => {
                    print_together(run, &t);
                    joint.add(run, &t.ours, &t.theirs);
                    joint.seen.push((t.ours_seen, t.theirs_seen));
                }
                Err(e) => println!("{run:<5} together: not measured: {e}"),
            }
        }
    }
    if set.apart {
        apart.print("in turn");
    }
    if set.together {
        joint.print("together");
    }
    ExitCode::SUCCESS
}
