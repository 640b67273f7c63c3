//! The system calls of hwgw's real-time threads, in the steady state
//! (`cargo bench -p hwgw --bench rt_syscalls`).
//!
//! A SCHED_FIFO thread should make only its own I/O calls and its wait for the next step:
//! no futex on a lock another thread can hold, no `write` to the log, no `mmap`/`brk`, no
//! `sched_yield`. This bench runs the real binary in two deployments with their real-time
//! threads on SCHED_FIFO:
//!
//! - **demo**: the embedded default (`config/demo.toml`) with the card `sim0`'s thread at
//!   FIFO 60, `follow` (woken by each new sample) at FIFO 70 and `blink` at FIFO 50, every
//!   10 ms;
//! - **modbus**: a card polling a Modbus TCP unit on loopback every 10 ms (the unit: a
//!   second hwgw serving a simulated card with `[modbus_server]`) on FIFO 60, and `follow`
//!   at FIFO 70 from the unit's input to its holding register, so an output is written on
//!   every sample;
//! - **scan**: a `scan` component every 1 ms at FIFO 80 reading a simulated card's input
//!   and the unit's, and writing both cards' outputs at every step, the unit's line polling
//!   every 1 ms at FIFO 70 (the `io_loop` bench's deployment).
//!
//! Once each has run for a second, it attaches `strace -y` to each real-time thread (one
//! strace a thread, no `-f`) for `RT_SYSCALLS_SECONDS` (default 30), while this process asks
//! the gateway for `status` every 100 ms, as a monitoring client does: a lock a real-time
//! thread shares with `status` then shows up as a futex wait. Every call is put in a class:
//!
//! - *wait*: `clock_nanosleep`, `epoll_wait`, and — for a thread that waits for its steps
//!   on a futex (an event-driven activity, no timed wait) — a futex wait on the one word it
//!   parks on (the most frequent address it waits on);
//! - *I/O*: calls on sockets, timerfds and eventfds (`-y` names each descriptor);
//! - *wake*: a futex wake of another thread (a port's reader, an operation's caller);
//! - *stray*: anything else — a futex wait on another word (a lock another thread held),
//!   `write` to a file, pipe or terminal (the log), `mmap`, `munmap`, `brk`, `madvise`,
//!   `sched_yield`, any call not named above.
//!
//! Prints a table per thread and the stray calls with an example line each; exits 1 when
//! any thread made a stray call. `RT_SYSCALLS_BIN` runs another hwgw binary (an older
//! build, for a before/after comparison).

#![allow(
    clippy::unwrap_used,
    reason = "bench code: a failed unwrap is a failed run"
)]

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, ExitCode};
use std::time::{Duration, Instant};
use testkit::Service;

mod common;
use common::UNIT;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// The embedded default with its three activities on SCHED_FIFO.
fn demo() -> String {
    let text = include_str!("../../config/demo.toml");
    let mut out = text.to_string();
    for (from, to) in [
        (
            "sample_period_ms = 20     # inputs sampled into ports\n",
            "sample_period_ms = 20\nthread = { policy = \"fifo\", priority = 60 }\n",
        ),
        (
            "activity = { type = \"non_periodic\" }",
            "activity = { type = \"non_periodic\", policy = \"fifo\", priority = 70 }",
        ),
        (
            "activity = { type = \"periodic\", period_ms = 250 }",
            "activity = { type = \"periodic\", period_ms = 10, policy = \"fifo\", priority = 50 }",
        ),
    ] {
        assert!(
            out.contains(from),
            "config/demo.toml no longer has {from:?}"
        );
        out = out.replace(from, to);
    }
    out
}

/// The Modbus client: its line on SCHED_FIFO, polled every 10 ms, and `follow` writing the
/// unit's holding register from each sample of its input.
fn client(port: u16) -> String {
    format!(
        r#"{}
[[component]]
name = "follow"
type = "follow"
activity = {{ type = "non_periodic", policy = "fifo", priority = 70 }}
properties = {{ gain = 0.5, offset = 0.0 }}

[[connection]]
from = "meter.ai.voltage"
to = "follow.in"

[[connection]]
from = "follow.out"
to = "meter.ao.setpoint"
"#,
        common::meter(port, 10, 60)
    )
}

/// The calls a thread waits for its next step in, its timer or descriptors with it.
const TIMED_WAITS: &[&str] = &[
    "clock_nanosleep",
    "epoll_wait",
    "epoll_pwait",
    "epoll_pwait2",
];

/// One traced call: its name, and for futexes the operation and the word.
struct Call {
    name: String,
    args: String,
}

fn parse(line: &str) -> Option<Call> {
    let open = line.find('(')?;
    let name = &line[..open];
    if name.is_empty() || !name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
        return None; // `--- SIGxxx ---`, `+++ exited`, strace's own notes
    }
    Some(Call {
        name: name.to_string(),
        args: line[open + 1..].to_string(),
    })
}

/// A descriptor that is the thread's own I/O: a socket, a timerfd, an eventfd, an epoll.
fn io_descriptor(args: &str) -> bool {
    let fd = args.split([',', ')']).next().unwrap_or("");
    ["<socket:", "<TCP", "<UDP", "<UNIX", "<anon_inode:", "<CAN"]
        .iter()
        .any(|k| fd.contains(k))
}

fn futex_word(args: &str) -> &str {
    args.split(',').next().unwrap_or("").trim()
}

#[derive(Default)]
struct Thread {
    /// (call, class) → count.
    counts: BTreeMap<(String, &'static str), u64>,
    /// A stray call's first line, by call.
    examples: BTreeMap<String, String>,
}

/// Puts each call of a thread's trace in its class.
fn classify(trace: &str) -> Thread {
    let calls: Vec<(Call, &str)> = trace
        .lines()
        .filter_map(|l| parse(l).map(|c| (c, l)))
        .collect();
    // The word the thread parks on: the one it waits on most, for a thread that waits for
    // its steps on a futex (an event-driven activity). A thread that waits in
    // `clock_nanosleep` or `epoll_wait` parks on nothing: each of its futex waits is a lock.
    let timed = calls
        .iter()
        .any(|(c, _)| TIMED_WAITS.contains(&c.name.as_str()));
    let mut waits: BTreeMap<&str, u64> = BTreeMap::new();
    for (c, _) in &calls {
        if c.name == "futex" && c.args.contains("FUTEX_WAIT") {
            *waits.entry(futex_word(&c.args)).or_default() += 1;
        }
    }
    let park = waits
        .iter()
        .filter(|_| !timed)
        .max_by_key(|(_, n)| **n)
        .map(|(w, _)| w.to_string());
    let mut t = Thread::default();
    for (c, line) in &calls {
        let class = match c.name.as_str() {
            name if TIMED_WAITS.contains(&name) => "wait",
            "futex" if c.args.contains("FUTEX_WAKE") => "wake",
            "futex" if park.as_deref() == Some(futex_word(&c.args)) => "wait",
            "read" | "write" | "readv" | "writev" | "sendto" | "recvfrom" | "sendmsg"
            | "recvmsg" | "sendmmsg" | "recvmmsg" | "timerfd_settime" | "timerfd_gettime"
            | "ioctl" | "epoll_ctl" | "connect" | "close" | "socket" | "setsockopt"
            | "getsockopt" | "shutdown"
                if io_descriptor(&c.args) =>
            {
                "I/O"
            }
            _ => "stray",
        };
        *t.counts.entry((c.name.clone(), class)).or_default() += 1;
        if class == "stray" {
            t.examples
                .entry(c.name.clone())
                .or_insert_with(|| line.chars().take(160).collect());
        }
    }
    t
}

/// The thread of `svc` named `comm` (an activity's name, cut to 15 bytes).
fn tid(svc: &Service, comm: &str) -> u32 {
    let pid = svc.pid().unwrap();
    for entry in std::fs::read_dir(format!("/proc/{pid}/task")).unwrap() {
        let dir = entry.unwrap().path();
        let name = std::fs::read_to_string(dir.join("comm")).unwrap_or_default();
        if name.trim_end() == comm {
            return dir.file_name().unwrap().to_str().unwrap().parse().unwrap();
        }
    }
    panic!("hwgw {pid} has no thread {comm}");
}

/// Traces `threads` of `svc` for `seconds`, asking for `status` meanwhile; prints each
/// thread's table; the number of stray calls.
fn trace(deployment: &str, svc: &Service, threads: &[&str], seconds: u64, dir: &Path) -> u64 {
    // The steady state: past the start, its connections and first polls.
    std::thread::sleep(Duration::from_secs(1));
    let mut tracers = Vec::new();
    for comm in threads {
        let tid = tid(svc, comm);
        let out = dir.join(format!("{deployment}-{comm}.strace"));
        let child = Command::new("timeout")
            .args([
                "-s",
                "INT",
                &seconds.to_string(),
                "strace",
                "-qq",
                "-y",
                "-p",
            ])
            .arg(tid.to_string())
            .arg("-o")
            .arg(&out)
            .spawn()
            .unwrap();
        tracers.push((comm, out, child));
    }
    let end = Instant::now() + Duration::from_secs(seconds);
    let mut asked = 0u64;
    while Instant::now() < end {
        svc.ok(serde_json::json!({"cmd": "status"}));
        asked += 1;
        std::thread::sleep(Duration::from_millis(100));
    }
    let mut stray = 0;
    println!("\n## {deployment} ({seconds} s, `status` asked {asked} times meanwhile)");
    for (comm, out, mut child) in tracers {
        // `timeout` ends strace with SIGINT and answers 124; anything else means strace did
        // not trace for the whole window (refused to attach: ptrace_scope, no
        // CAP_SYS_PTRACE), and an empty trace would pass for a clean one.
        let status = child.wait().unwrap();
        let text = std::fs::read_to_string(&out).unwrap_or_default();
        let t = classify(&text);
        assert!(
            status.code() == Some(124) && !t.counts.is_empty(),
            "strace of {comm} ended with {status} after {} calls: not a trace of {seconds} s",
            t.counts.values().sum::<u64>()
        );
        println!("\n{comm}: {:<18} {:>8} {:>8}", "call", "class", "calls");
        for ((name, class), n) in &t.counts {
            println!("{comm}: {name:<18} {class:>8} {n:>8}");
            if *class == "stray" {
                stray += n;
            }
        }
        for (name, line) in &t.examples {
            println!("{comm}: stray {name}: {line}");
        }
    }
    stray
}

fn main() -> ExitCode {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return ExitCode::SUCCESS; // `cargo test --benches` lists or smoke-runs: nothing to do.
    }
    testkit::peers::require(&testkit::peers::STRACE).unwrap();
    let bin = std::env::var("RT_SYSCALLS_BIN").unwrap_or_else(|_| HWGW.to_string());
    let seconds: u64 = std::env::var("RT_SYSCALLS_SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(30);
    if !testkit::bench::can_fifo(70) {
        eprintln!("SCHED_FIFO is refused here: the bench needs it (root or CAP_SYS_NICE)");
        return ExitCode::FAILURE;
    }
    println!("system calls of SCHED_FIFO threads in the steady state, {bin}");
    let dir = testkit::service::TempDir::new("rt-syscalls");
    let mut stray = 0;
    {
        let svc = Service::run_text(&bin, "rt-syscalls-demo", &demo()).unwrap();
        stray += trace(
            "demo",
            &svc,
            &["sim0", "follow", "blink"],
            seconds,
            dir.path(),
        );
    }
    {
        let unit = Service::run_text(&bin, "rt-syscalls-unit", UNIT).unwrap();
        let port = unit.wait_listening("modbus_server").port();
        let svc = Service::run_text(&bin, "rt-syscalls-client", &client(port)).unwrap();
        stray += trace("modbus", &svc, &["meter", "follow"], seconds, dir.path());
    }
    {
        let unit = Service::run_text(&bin, "rt-syscalls-unit-scan", UNIT).unwrap();
        let port = unit.wait_listening("modbus_server").port();
        let text = common::scan_loop(port, 80);
        let svc = Service::run_text(&bin, "rt-syscalls-scan", &text).unwrap();
        stray += trace("scan", &svc, &["loop", "meter"], seconds, dir.path());
    }
    println!("\nstray calls on real-time threads: {stray}");
    if stray > 0 {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    }
}
