//! `hwgw` with a SocketCAN card, in the kernel rig: the real binary on `config/can.toml`
//! over a real vcan, can-utils on the other end, the CLI in between.
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Trial, sh};
use testkit::Candump;
use testkit::Service;
use testkit::wait::wait_ok;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/can.toml");

/// `hwgw run config/can.toml` on a socket of its own.
fn start() -> Result<Service, Failed> {
    Ok(Service::start(HWGW, "can", &[CONFIG], &[])?)
}

/// `hwgw ARGS`, which must succeed: its standard output.
fn out(gw: &Service, args: &[&str]) -> Result<String, Failed> {
    Ok(gw.out(args)?)
}

/// SIGTERM; the log of a clean exit.
fn terminate(gw: Service) -> Result<String, Failed> {
    let stopped = gw.terminate();
    if !stopped.status.success() {
        return Err(format!("hwgw exited with {}: {}", stopped.status, stopped.log).into());
    }
    Ok(stopped.log)
}

/// `candump -L` of the frames matching `filter` (`id:mask`), until `n` or 3 s of silence.
fn candump(filter: &str, n: usize) -> Result<Candump, Failed> {
    Ok(Candump::start(&[
        "-n",
        &n.to_string(),
        "-T",
        "3000",
        &format!("vcan0,{filter}"),
    ])?)
}

fn frames(c: Candump) -> Result<Vec<String>, Failed> {
    Ok(c.frames()?.into_iter().map(|(_, f)| f).collect())
}

fn hwgw_reads_writes_and_leaves_safe_frames() -> Result<(), Failed> {
    sh("ip link add vcan0 type vcan && ip link set vcan0 up")?;
    let gw = start()?;

    // cansend -> the DBC-decoded values, through the CLI.
    let mirror = candump("210:7FF", 1)?;
    sh("cansend vcan0 100#3930F9C00B00FAFF && cansend vcan0 18FEEE05#822EFB00")?;
    wait_ok("Speed decoded", || {
        Ok(out(&gw, &["get", "can.ai", "Speed"])? == "123.45")
    })?;
    assert_eq!(out(&gw, &["get", "can.ai", "Torque"])?, "-60.0");
    assert_eq!(out(&gw, &["get", "can.ai", "Delta"])?, "-123.4");
    assert_eq!(out(&gw, &["get", "can.ai", "Coolant"])?, "90.0");
    assert_eq!(out(&gw, &["get", "can.di", "Enabled"])?, "true");
    assert_eq!(out(&gw, &["get", "can.di", "Mode_0"])?, "true");
    assert_eq!(out(&gw, &["get", "can.di", "Mode_1"])?, "false");

    // The follow component wrote Speed to Mirror: sent on change, 12345 little endian.
    assert_eq!(frames(mirror)?, ["210#3930"]);

    // hwgw set -> the Command frame, every 10 ms, with the exact bytes.
    out(&gw, &["set", "can.ao", "Setpoint", "-12.3"])?;
    out(&gw, &["set", "can.do", "Run", "true"])?;
    // Both reached the card (read back through the ports) before the capture starts.
    wait_ok("the setpoint and Run on the card", || {
        Ok(out(&gw, &["get", "can.ao", "Setpoint"])? == "-12.3"
            && out(&gw, &["get", "can.do", "Run"])? == "true")
    })?;
    let got = frames(candump("200:7FF", 5)?)?;
    assert_eq!(got, vec!["200#FF850100"; 5]);

    // Counters and status.
    let counters = out(&gw, &["call", "can", "counters"])?;
    assert!(counters.contains("\"rx_frames\": 2"), "{counters}");
    assert!(counters.contains("\"link_up\": true"), "{counters}");
    let status = out(&gw, &["status"])?;
    assert!(
        status.contains("socketcan") && status.contains("vcan0"),
        "{status}"
    );

    // SIGTERM: the safe values go out before the bus stops.
    let command = candump("200:7FF", 1000)?;
    let mirror = candump("210:7FF", 10)?;
    let log = terminate(gw)?;
    let command = frames(command)?;
    assert_eq!(
        command.last().map(String::as_str),
        Some("200#00000000"),
        "{log}"
    );
    assert_eq!(
        frames(mirror)?.last().map(String::as_str),
        Some("210#0000"),
        "{log}"
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    let rig = testkit::rig::vcan();
    kernel_rig::harness(
        &rig,
        vec![Trial::test(
            "hwgw_reads_writes_and_leaves_safe_frames",
            hwgw_reads_writes_and_leaves_safe_frames,
        )],
    )
}
