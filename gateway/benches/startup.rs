//! Start-up time and memory of the real binary (`cargo bench -p hwgw --bench startup`):
//! how soon `hwgw run` answers `status`, and its resident memory then and once settled.
//!
//! Three deployments, in turn each round (`STARTUP_RUNS`, default 5), so a machine that
//! gets busier or quieter weighs on all alike:
//!
//! - **default**: `hwgw run` with no file, the embedded default (`config/demo.toml`);
//! - **1 × 1**: one simulated card of one analog input (the floor: a runtime, one card);
//! - **10 × 100**: ten simulated cards of 100 analog inputs each, new noise every 100 ms,
//!   each card's channels sampled into ports every 100 ms (the goal: ≤ 20 MB and
//!   ≤ 50 ms).
//!
//! Time to `status`: from spawning the process to the first complete `status` reply over
//! its control socket, tried every 0.5 ms. Memory: `VmRSS` when `status` first answers, and
//! after `STARTUP_SETTLE_MS` (default 2000) of running, when every card has cycled and every
//! port has been written. Prints each round and the median of each figure.

#![allow(
    clippy::unwrap_used,
    reason = "bench code: a failed unwrap is a failed run"
)]

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use testkit::bench::proc_usage;
use testkit::service::TempDir;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// `cards` simulated cards of `channels` analog inputs each.
fn cards(cards: u32, channels: u32) -> String {
    let one = testkit::bench::noise_card(channels);
    assert!(
        one.contains("name = \"big\""),
        "noise_card's card is no longer `big`"
    );
    (0..cards)
        .map(|i| one.replace("name = \"big\"", &format!("name = \"big{i}\"")))
        .collect()
}

/// One `status` request; true when a whole reply line came.
fn status(socket: &Path) -> bool {
    let Ok(mut c) = UnixStream::connect(socket) else {
        return false;
    };
    let _ = c.set_read_timeout(Some(Duration::from_secs(10)));
    if c.write_all(b"{\"cmd\":\"status\"}\n").is_err() {
        return false;
    }
    let mut reply = String::new();
    BufReader::new(c).read_line(&mut reply).is_ok() && reply.contains("\"ok\"")
}

struct Figures {
    /// Spawn to the first `status` reply.
    answered: Duration,
    /// Resident memory then, KiB.
    rss_start_kib: u64,
    /// Resident memory once settled, KiB.
    rss_settled_kib: u64,
}

/// Runs `hwgw run [file]` in `dir` until it answered and settled; its figures.
fn run(dir: &Path, file: Option<&Path>, settle: Duration) -> Figures {
    let socket = dir.join("hwgw.sock");
    let _ = std::fs::remove_file(&socket);
    let log = std::fs::File::create(dir.join("hwgw.log")).unwrap();
    let t0 = Instant::now();
    let mut cmd = Command::new(HWGW);
    cmd.arg("run");
    if let Some(f) = file {
        cmd.arg(f);
    }
    let child = cmd
        .arg("--socket")
        .arg(&socket)
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap();
    let mut child = Stopper(child);
    while !status(&socket) {
        if let Ok(Some(s)) = child.0.try_wait() {
            panic!(
                "hwgw exited ({s}): {}",
                std::fs::read_to_string(dir.join("hwgw.log")).unwrap_or_default()
            );
        }
        assert!(t0.elapsed() < Duration::from_secs(30), "no status in 30 s");
        std::thread::sleep(Duration::from_micros(500));
    }
    let answered = t0.elapsed();
    let pid = child.0.id();
    let rss_start_kib = proc_usage(pid).unwrap().rss_kib;
    std::thread::sleep(settle);
    let rss_settled_kib = proc_usage(pid).unwrap().rss_kib;
    Figures {
        answered,
        rss_start_kib,
        rss_settled_kib,
    }
}

/// Stops the gateway (SIGTERM, then waits) however the run ends.
struct Stopper(Child);

impl Drop for Stopper {
    fn drop(&mut self) {
        if let Ok(pid) = i32::try_from(self.0.id()) {
            let _ = nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(pid),
                nix::sys::signal::Signal::SIGTERM,
            );
        }
        let _ = self.0.wait();
    }
}

fn median<T: Copy + Ord>(mut v: Vec<T>) -> T {
    v.sort();
    v[v.len() / 2]
}

fn main() {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return; // `cargo test --benches` lists or smoke-runs: nothing to do.
    }
    let env = |k: &str, d: u64| {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(d)
    };
    let runs = env("STARTUP_RUNS", 5).max(1);
    let settle = Duration::from_millis(env("STARTUP_SETTLE_MS", 2000));
    let dir = TempDir::new("startup-bench");
    let small = dir.path().join("one.toml");
    std::fs::write(&small, cards(1, 1)).unwrap();
    let large = dir.path().join("large.toml");
    std::fs::write(&large, cards(10, 100)).unwrap();
    let deployments: [(&str, Option<&Path>); 3] = [
        ("default", None),
        ("1 x 1", Some(&small)),
        ("10 x 100", Some(&large)),
    ];
    println!(
        "hwgw start-up: spawn to first `status` reply, VmRSS then and after {} ms",
        settle.as_millis()
    );
    println!(
        "{:<6} {:<10} {:>12} {:>14} {:>16}",
        "round", "deployment", "status ms", "RSS start MiB", "RSS settled MiB"
    );
    let mut all: Vec<Vec<Figures>> = deployments.iter().map(|_| Vec::new()).collect();
    for round in 1..=runs {
        for (i, (name, file)) in deployments.iter().enumerate() {
            let f = run(dir.path(), *file, settle);
            println!(
                "{round:<6} {name:<10} {:>12.1} {:>14.1} {:>16.1}",
                f.answered.as_secs_f64() * 1e3,
                f.rss_start_kib as f64 / 1024.0,
                f.rss_settled_kib as f64 / 1024.0
            );
            all[i].push(f);
        }
    }
    println!("medians over {runs} rounds:");
    for ((name, _), figs) in deployments.iter().zip(&all) {
        let answered = median(figs.iter().map(|f| f.answered).collect());
        let start = median(figs.iter().map(|f| f.rss_start_kib).collect());
        let settled = median(figs.iter().map(|f| f.rss_settled_kib).collect());
        println!(
            "{name:<10} status {:.1} ms, RSS {:.1} MiB at status, {:.1} MiB ({:.1} MB) settled",
            answered.as_secs_f64() * 1e3,
            start as f64 / 1024.0,
            settled as f64 / 1024.0,
            settled as f64 * 1024.0 / 1e6
        );
    }
}
