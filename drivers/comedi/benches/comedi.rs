//! Samples per second through the comedi card beside a bare comedilib loop reading the
//! same channels, in the same guest run.
//!
//! `cargo bench -p driver-comedi --bench comedi` boots the kernel rig and runs this inside
//! on comedi_test (8 analog inputs). hwgw's side is the card's bus side polling all eight
//! channels (what its thread does each period: the calls under the board's mutex, the
//! packed samples, the counters) followed by a `read` of each channel through the
//! AnalogIn device (physical units); the reference calls `comedi_data_read` for the same
//! channels through the wrapper with nothing around it. Outputs likewise: a `write` of
//! each of the eight analog outputs through the AnalogOut device (the scale, the check,
//! the call) beside bare `comedi_data_write`s. Rounds are interleaved; the figures are
//! samples per second and their ratio.
#![allow(clippy::unwrap_used, reason = "benchmark code")]

use device_interface::time::MonotonicClock;
use device_interface::{AnalogIn, AnalogOut};
use driver_comedi::board::{Board, Daq};
use driver_comedi::config::ComediConfig;
use kernel_rig::{Failed, Trial};
use std::hint::black_box;
use std::sync::Arc;
use std::time::{Duration, Instant};
use testkit::ComediBoard;
use testkit::bench::{mean, rate};

const DEVICE: &str = "/dev/comedi0";

fn bench(quick: bool) -> Result<u64, Failed> {
    let cycles = if quick { 100 } else { 20_000 };
    let _board = ComediBoard::comedi_test(DEVICE)?;
    let config: ComediConfig = toml::from_str(&format!(
        "device = \"{DEVICE}\"\nanalog_in = [{{}}]\nanalog_out = [{{}}]"
    ))?;
    let built = driver_comedi::plugin::card(&config, Arc::new(MonotonicClock))
        .map_err(|e| Failed::from(e.message))?;
    let card = built.card.clone();
    let mut bus = built.bus();
    let mut now = Instant::now();
    let mut step = || {
        now += Duration::from_millis(1);
        bus.step(now);
    };
    step();
    if !card.is_online() {
        return Err(format!("the board did not open: {:?}", card.counters()).into());
    }
    let n = AnalogIn::channel_count(card.as_ref());
    // Samples counted by the card's own polls (each reads every channel once).
    let mut hwgw_in = || -> u64 {
        let before = card.polls();
        step();
        for ch in 0..n {
            black_box(card.read(ch).unwrap());
        }
        (card.polls() - before) * u64::from(n)
    };
    let mut bare = Board::open(DEVICE)?;
    let mut bare_in = || -> u64 {
        for ch in 0..n {
            black_box(bare.data_read(0, ch, 0, 0).unwrap());
        }
        u64::from(n)
    };
    let mut value = 0.0;
    let mut hwgw_out = || -> u64 {
        value = if value > 0.0 { -1.0 } else { 1.0 };
        for ch in 0..n {
            card.write(ch, value).unwrap();
        }
        u64::from(n)
    };
    let mut bare_out_handle = Board::open(DEVICE)?;
    let mut raw = 0;
    let mut bare_out = || -> u64 {
        raw = if raw > 30_000 { 29_000 } else { 36_000 };
        for ch in 0..n {
            bare_out_handle.data_write(1, ch, 0, 0, raw).unwrap();
        }
        u64::from(n)
    };
    // Interleaved rounds so a noisy moment hits both alike.
    let (mut rounds, per) = (Vec::new(), cycles / 10);
    for _ in 0..10 {
        rounds.push([
            rate(per, &mut hwgw_in),
            rate(per, &mut bare_in),
            rate(per, &mut hwgw_out),
            rate(per, &mut bare_out),
        ]);
    }
    let m = |i: usize, j: usize| mean(rounds.iter().map(|r| if j == 0 { r[i].0 } else { r[i].1 }));
    println!("comedi_test, {n} channels, {cycles} cycles each:");
    println!(
        "  inputs:  hwgw poll + read  {:9.0} samples/s  {:7.1} µs a cycle",
        m(0, 0),
        m(0, 1)
    );
    println!(
        "           bare data_read    {:9.0} samples/s  {:7.1} µs a cycle",
        m(1, 0),
        m(1, 1)
    );
    println!(
        "  outputs: hwgw write        {:9.0} samples/s  {:7.1} µs a cycle",
        m(2, 0),
        m(2, 1)
    );
    println!(
        "           bare data_write   {:9.0} samples/s  {:7.1} µs a cycle",
        m(3, 0),
        m(3, 1)
    );
    println!(
        "  hwgw / bare samples/s: inputs {:.2}, outputs {:.2}",
        m(0, 0) / m(1, 0),
        m(2, 0) / m(3, 0)
    );
    if card.counters().errors != 0 {
        return Err(format!("failed calls: {:?}", card.counters()).into());
    }
    Ok((m(0, 1) * 1000.0) as u64)
}

fn main() -> std::process::ExitCode {
    kernel_rig::harness(
        &testkit::rig::comedi(),
        vec![Trial::bench("samples", |test_mode| {
            let ns = bench(test_mode)?;
            Ok((!test_mode).then_some(kernel_rig::Measurement {
                avg: ns,
                variance: 0,
            }))
        })],
    )
}
