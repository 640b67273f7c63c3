//! The GPIO card on gpio-sim, each figure beside a reference measured in the same guest run.
//!
//! `cargo bench -p driver-gpio --bench gpio` boots the kernel rig (gpio-sim loaded) and runs
//! this inside:
//!
//! - **thread_scope_pulse**: what ThreadScope adds to a step when its DigitalOut is a GPIO
//!   card — a `set_bit(b, true)` then `set_bit(b, false)` — beside the floor, the same two
//!   `GPIO_V2_LINE_SET_VALUES` ioctls made straight through gpiocdev on another line of the
//!   same chip, and beside a DigitalOut in memory (ThreadScope on a simulated card).
//! - **encoder_rate**: quadrature edges driven from outside through the simulator's pulls
//!   at rising offered rates; at each, hwgw's software decoder (a card with an encoder) and
//!   libgpiod's `gpiomon` on the same two lines take the same number of edges in turn. The
//!   figure of merit is the highest offered rate each takes without losing an edge.
#![allow(clippy::unwrap_used, reason = "benchmark code")]

use device_interface::{Device, DeviceError, DigitalOut, Health};
use kernel_rig::{Failed, Trial, sh};
use std::hint::black_box;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use testkit::{SimChip, wait_for};

#[path = "../tests/common/mod.rs"]
mod common;
use common::card;

/// A DigitalOut in memory: the cheapest ThreadScope there is.
struct Memory(AtomicU64);

impl Device for Memory {
    fn health(&self) -> Health {
        Health {
            status: device_interface::Status::Online,
            last_good: None,
            checked_at: device_interface::time::Timestamp::from_nanos(0),
            last_error: None,
        }
    }
}

impl DigitalOut for Memory {
    fn output_count(&self) -> u32 {
        64
    }
    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        if value {
            self.0.fetch_or(1 << bit, Ordering::Relaxed);
        } else {
            self.0.fetch_and(!(1 << bit), Ordering::Relaxed);
        }
        Ok(())
    }
    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        Ok(self.0.load(Ordering::Relaxed) >> bit & 1 == 1)
    }
}

/// Mean ns of `n` runs of `f` (timed as one batch), and the 99th percentile of the same
/// runs timed one by one (which adds a clock read, measured beside them).
fn timed(n: usize, mut f: impl FnMut()) -> (f64, u64) {
    let s = Instant::now();
    for _ in 0..n {
        f();
    }
    let mean = s.elapsed().as_nanos() as f64 / n as f64;
    let mut t = Vec::with_capacity(n);
    for _ in 0..n {
        let s = Instant::now();
        f();
        t.push(s.elapsed().as_nanos() as u64);
    }
    t.sort_unstable();
    (mean, t[(n - 1) * 99 / 100])
}

/// The ns of a pulse through the GPIO card (libtest's figure).
fn pulse_bench(quick: bool) -> Result<u64, Failed> {
    let n = if quick { 1_000 } else { 100_000 };
    let chip = SimChip::new("bench-scope", 2, &[])?;
    let card = card(&chip, "output = [{ line = 0 }]")?;
    let _rt = common::running(&card)?;
    let raw = gpiocdev::Request::builder()
        .on_chip(chip.path())
        .with_consumer("bench-raw")
        .with_line(1)
        .as_output(gpiocdev::line::Value::Inactive)
        .request()?;
    let memory = Memory(AtomicU64::new(0));
    let out: &dyn DigitalOut = &*card;
    let mem: &dyn DigitalOut = &memory;
    // Interleaved rounds, so a noisy moment hits all three alike.
    let (mut g, mut r, mut m, mut c) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for _ in 0..10 {
        c.push(timed(n / 10, || {
            black_box(Instant::now());
        }));
        g.push(timed(n / 10, || {
            out.set_bit(0, true).unwrap();
            out.set_bit(0, false).unwrap();
        }));
        r.push(timed(n / 10, || {
            raw.set_value(1, gpiocdev::line::Value::Active).unwrap();
            raw.set_value(1, gpiocdev::line::Value::Inactive).unwrap();
        }));
        m.push(timed(n / 10, || {
            mem.set_bit(black_box(3), true).unwrap();
            mem.set_bit(black_box(3), false).unwrap();
        }));
    }
    let summary = |v: &[(f64, u64)]| {
        let mean = v.iter().map(|x| x.0).sum::<f64>() / v.len() as f64;
        let p99 = v.iter().map(|x| x.1).max().unwrap_or(0);
        (mean, p99)
    };
    let (g, r, m, c) = (summary(&g), summary(&r), summary(&m), summary(&c));
    println!(
        "ThreadScope pulse (bit high, bit low), {n} pulses each (p99: the worst of 10 rounds, timed one by one):"
    );
    println!(
        "  GPIO card (hwgw)        mean {:8.0} ns   p99 {:8} ns",
        g.0, g.1
    );
    println!(
        "  raw gpiocdev ioctls     mean {:8.0} ns   p99 {:8} ns",
        r.0, r.1
    );
    println!(
        "  DigitalOut in memory    mean {:8.1} ns   p99 {:8} ns",
        m.0, m.1
    );
    println!(
        "  a clock read            mean {:8.1} ns   p99 {:8} ns",
        c.0, c.1
    );
    println!(
        "  GPIO card / raw ioctls: {:.2}; the pulse costs {:.1} µs per step",
        g.0 / r.0,
        g.0 / 1000.0
    );
    Ok(g.0 as u64)
}

/// Waits until `lines` of `chip` are used by nobody.
fn released(chip: &SimChip, lines: &[u32]) -> Result<(), Failed> {
    wait_for("the lines released", Duration::from_secs(10), || {
        sh(&format!("gpioinfo {}", chip.chip_name)).is_ok_and(|info| {
            lines.iter().all(|o| {
                info.lines().any(|l| {
                    l.trim_start().starts_with(&format!("line {o:>3}:")) && l.contains("unused")
                })
            })
        })
    })
    .map_err(Failed::from)
}

/// Waits until `count()` stops changing for 300 ms (at most 10 s); its last value.
fn settled(mut count: impl FnMut() -> u64) -> u64 {
    let mut last = count();
    let mut since = Instant::now();
    let end = Instant::now() + Duration::from_secs(10);
    while Instant::now() < end && since.elapsed() < Duration::from_millis(300) {
        std::thread::sleep(Duration::from_millis(20));
        let now = count();
        if now != last {
            last = now;
            since = Instant::now();
        }
    }
    last
}

/// hwgw decodes `edges` edges offered every `gap`: (edges decoded, offered edges/s).
fn hwgw_pass(chip: &SimChip, edges: i64, gap: Duration) -> Result<(u64, f64), Failed> {
    let card = card(
        chip,
        "event_buffer = 1024\nencoder = [{ a = 0, b = 1, resolution = 1000000 }]",
    )?;
    let rt = common::running(&card)?;
    let enc = card.devices().encoders.remove(0).1;
    let mut q = chip.quadrature(0, 1)?;
    let took = q.paced(edges, gap)?;
    let total = |e: &dyn device_interface::Encoder| {
        (e.turn().unwrap_or(0) * 1_000_000 + e.position().unwrap_or(0)) as u64
    };
    let decoded = settled(|| card.counters().events);
    let c = card.counters();
    let count = total(&*enc);
    // Lossless: every edge read, none lost, none illegal, the exact count.
    let good = if c.lost_events == 0 && c.encoder_errors == 0 && decoded == edges as u64 {
        count
    } else {
        decoded.saturating_sub(c.lost_events + c.encoder_errors)
    };
    // Back to phase 0 (both low) for the next pass, then release the lines.
    q.step(-(edges % 4))?;
    drop((rt, enc, card));
    released(chip, &[0, 1])?;
    Ok((good, edges as f64 / took.as_secs_f64()))
}

/// gpiomon on the same lines takes `edges` edges offered every `gap`: (edges printed,
/// offered edges/s).
fn gpiomon_pass(chip: &SimChip, edges: i64, gap: Duration) -> Result<(u64, f64), Failed> {
    let log = "/dev/shm/gpiomon.txt";
    let out = std::fs::File::create(log)?;
    let mut mon = Command::new("gpiomon")
        .args([
            "-n",
            &edges.to_string(),
            "-F",
            "%o",
            &chip.chip_name,
            "0",
            "1",
        ])
        .stdout(out)
        .stderr(Stdio::inherit())
        .spawn()?;
    // Listening once the kernel shows the lines as gpiomon's.
    wait_for("gpiomon holds the lines", Duration::from_secs(10), || {
        sh(&format!("gpioinfo {}", chip.chip_name))
            .is_ok_and(|i| i.matches("\"gpiomon\"").count() == 2)
    })?;
    let mut q = chip.quadrature(0, 1)?;
    let took = q.paced(edges, gap)?;
    let printed = || {
        std::fs::read_to_string(log)
            .map(|t| t.lines().count() as u64)
            .unwrap_or(0)
    };
    // It exits after `edges` events; one that lost some waits on: interrupt it.
    let end = Instant::now() + Duration::from_secs(2);
    while Instant::now() < end && mon.try_wait()?.is_none() {
        std::thread::sleep(Duration::from_millis(10));
    }
    if mon.try_wait()?.is_none() {
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(mon.id() as i32),
            nix::sys::signal::Signal::SIGINT,
        );
    }
    mon.wait()?;
    let got = printed();
    q.step(-(edges % 4))?;
    released(chip, &[0, 1])?;
    Ok((got, edges as f64 / took.as_secs_f64()))
}

/// The ns per edge at hwgw's highest lossless rate (libtest's figure).
fn rate_bench(quick: bool) -> Result<u64, Failed> {
    let edges: i64 = if quick { 400 } else { 20_000 };
    // Gaps between edges, µs; 0: as fast as the simulator's pull files take writes.
    let gaps: &[u64] = if quick {
        &[100, 0]
    } else {
        &[200, 100, 50, 20, 10, 5, 2, 0]
    };
    let chip = SimChip::new("bench-enc", 2, &[])?;
    println!("quadrature edges through gpio-sim pulls, {edges} per pass:");
    println!("  gap µs | offered edges/s | hwgw decoded | offered edges/s | gpiomon printed");
    let (mut best_ours, mut best_mon) = (0.0f64, 0.0f64);
    for &gap in gaps {
        let gap = Duration::from_micros(gap);
        let (ours, ours_rate) = hwgw_pass(&chip, edges, gap)?;
        let (mon, mon_rate) = gpiomon_pass(&chip, edges, gap)?;
        println!(
            "  {:6} | {ours_rate:15.0} | {ours:12} | {mon_rate:15.0} | {mon:15}",
            gap.as_micros()
        );
        if ours == edges as u64 {
            best_ours = best_ours.max(ours_rate);
        }
        if mon == edges as u64 {
            best_mon = best_mon.max(mon_rate);
        }
    }
    println!(
        "highest offered rate without loss: hwgw {best_ours:.0} edges/s, gpiomon {best_mon:.0} edges/s, ratio {:.2}",
        best_ours / best_mon
    );
    Ok(if best_ours > 0.0 {
        (1e9 / best_ours) as u64
    } else {
        0
    })
}

fn main() -> std::process::ExitCode {
    let figure = |ns: u64, test_mode: bool| {
        (!test_mode).then_some(kernel_rig::Measurement {
            avg: ns,
            variance: 0,
        })
    };
    kernel_rig::harness(
        &kernel_rig::Rig::new().gpio_sim(),
        vec![
            Trial::bench("thread_scope_pulse", move |test_mode| {
                Ok(figure(pulse_bench(test_mode)?, test_mode))
            }),
            Trial::bench("encoder_rate", move |test_mode| {
                Ok(figure(rate_bench(test_mode)?, test_mode))
            }),
        ],
    )
}
