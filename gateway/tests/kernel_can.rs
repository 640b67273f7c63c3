//! `hwgw` with a SocketCAN card, in the kernel rig: the real binary on `config/can.toml`
//! over a real vcan, can-utils on the other end, the CLI in between.
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Trial, sh};
use std::path::PathBuf;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};
use testkit::Candump;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/can.toml");

struct Gateway {
    child: Option<Child>,
    socket: PathBuf,
    log: PathBuf,
}

impl Gateway {
    fn start() -> Result<Gateway, Failed> {
        let socket = PathBuf::from("/tmp/hwgw-can.sock");
        let log = PathBuf::from("/tmp/hwgw-can.log");
        let child = Command::new(HWGW)
            .args(["run", CONFIG, "--socket"])
            .arg(&socket)
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log)?)
            .spawn()?;
        let mut g = Gateway {
            child: Some(child),
            socket,
            log,
        };
        let end = Instant::now() + Duration::from_secs(20);
        while std::os::unix::net::UnixStream::connect(&g.socket).is_err() {
            if Instant::now() > end {
                return Err(format!("hwgw did not start: {}", g.log_text()).into());
            }
            if let Some(c) = g.child.as_mut()
                && let Ok(Some(status)) = c.try_wait()
            {
                return Err(format!("hwgw exited ({status}): {}", g.log_text()).into());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        Ok(g)
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    fn cli(&self, args: &[&str]) -> Result<Output, Failed> {
        Ok(Command::new(HWGW)
            .args(args)
            .arg("--socket")
            .arg(&self.socket)
            .output()?)
    }

    /// `hwgw ARGS` standard output, which must succeed.
    fn out(&self, args: &[&str]) -> Result<String, Failed> {
        let o = self.cli(args)?;
        if !o.status.success() {
            return Err(format!(
                "hwgw {}: {}",
                args.join(" "),
                String::from_utf8_lossy(&o.stderr)
            )
            .into());
        }
        Ok(String::from_utf8_lossy(&o.stdout).trim().to_string())
    }

    fn terminate(mut self) -> Result<String, Failed> {
        let mut child = self.child.take().ok_or("no child")?;
        let pid = nix::unistd::Pid::from_raw(child.id() as i32);
        nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM)?;
        let status = child.wait()?;
        if !status.success() {
            return Err(format!("hwgw exited with {status}: {}", self.log_text()).into());
        }
        Ok(self.log_text())
    }
}

impl Drop for Gateway {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// Waits until `f` says yes; its errors end the wait.
fn wait_for(what: &str, mut f: impl FnMut() -> Result<bool, Failed>) -> Result<(), Failed> {
    let mut error = None;
    testkit::wait_for(what, testkit::wait::PATIENCE, || match f() {
        Ok(done) => done,
        Err(e) => {
            error = Some(e);
            true
        }
    })?;
    error.map_or(Ok(()), Err)
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
    let gw = Gateway::start()?;

    // cansend -> the DBC-decoded values, through the CLI.
    let mirror = candump("210:7FF", 1)?;
    sh("cansend vcan0 100#3930F9C00B00FAFF && cansend vcan0 18FEEE05#822EFB00")?;
    wait_for("Speed decoded", || {
        Ok(gw.out(&["get", "can.ai", "Speed"])? == "123.45")
    })?;
    assert_eq!(gw.out(&["get", "can.ai", "Torque"])?, "-60.0");
    assert_eq!(gw.out(&["get", "can.ai", "Delta"])?, "-123.4");
    assert_eq!(gw.out(&["get", "can.ai", "Coolant"])?, "90.0");
    assert_eq!(gw.out(&["get", "can.di", "Enabled"])?, "true");
    assert_eq!(gw.out(&["get", "can.di", "Mode_0"])?, "true");
    assert_eq!(gw.out(&["get", "can.di", "Mode_1"])?, "false");

    // The follow component wrote Speed to Mirror: sent on change, 12345 little endian.
    assert_eq!(frames(mirror)?, ["210#3930"]);

    // hwgw set -> the Command frame, every 10 ms, with the exact bytes.
    gw.out(&["set", "can.ao", "Setpoint", "-12.3"])?;
    gw.out(&["set", "can.do", "Run", "true"])?;
    std::thread::sleep(Duration::from_millis(100));
    let got = frames(candump("200:7FF", 5)?)?;
    assert_eq!(got, vec!["200#FF850100"; 5]);

    // Counters and status.
    let counters = gw.out(&["call", "can", "counters"])?;
    assert!(counters.contains("\"rx_frames\": 2"), "{counters}");
    assert!(counters.contains("\"link_up\": true"), "{counters}");
    let status = gw.out(&["status"])?;
    assert!(
        status.contains("socketcan") && status.contains("vcan0"),
        "{status}"
    );

    // SIGTERM: the safe values go out before the bus stops.
    let command = candump("200:7FF", 1000)?;
    let mirror = candump("210:7FF", 10)?;
    let log = gw.terminate()?;
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
