//! `hwgw watch` and a gateway that stops answering: a quiet port keeps the watch alive
//! (the gateway's heartbeat comes every second), and a frozen gateway (SIGSTOP) ends it —
//! and a `hwgw record` — with an error after `--timeout` instead of hanging for as long as
//! the freeze lasts.

use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use testkit::service::{Service, TempDir};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// The demo and a follower nothing feeds: its output never changes.
fn config(dir: &TempDir) -> std::path::PathBuf {
    let p = dir.path().join("quiet.toml");
    let text = format!(
        "{}\n[[component]]\nname = \"quiet\"\ntype = \"follow\"\nactivity = {{ type = \"non_periodic\" }}\n",
        include_str!("../../config/demo.toml")
    );
    std::fs::write(&p, text).unwrap_or_else(|e| panic!("{e}"));
    p
}

/// Waits for `child` to exit, at most `limit`; its status, or `None`.
fn exit_within(
    child: &mut std::process::Child,
    limit: Duration,
) -> Option<std::process::ExitStatus> {
    let end = Instant::now() + limit;
    while Instant::now() < end {
        if let Ok(Some(s)) = child.try_wait() {
            return Some(s);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    None
}

#[test]
fn a_quiet_watch_lives_and_a_frozen_gateway_ends_it_after_the_timeout() {
    let dir = TempDir::new("watch-timeout-cfg");
    let svc = Service::start(HWGW, "watch-timeout", &[config(&dir)], &[])
        .unwrap_or_else(|e| panic!("{e}"));
    let socket = svc.socket.display().to_string();
    let watch = |port: &[&str]| {
        Command::new(HWGW)
            .args(["--timeout", "4", "watch"])
            .args(port)
            .args(["--socket", &socket])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("{e}"))
    };

    // A port that never changes: the watch is still there well past its timeout (7 s against 4 s).
    let mut quiet = watch(&["quiet", "out"]);
    assert!(
        exit_within(&mut quiet, Duration::from_secs(7)).is_none(),
        "a quiet watch ended: {:?}",
        quiet.wait_with_output()
    );
    let _ = quiet.kill();
    let _ = quiet.wait();

    // A moving port: once a value came, freeze the gateway; the watch ends in error.
    let mut moving = watch(&["sim0.ai", "ch1"]);
    let out = moving.stdout.take().unwrap_or_else(|| panic!("no stdout"));
    let mut first = String::new();
    BufReader::new(out)
        .read_line(&mut first)
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(first.trim().parse::<f64>().is_ok(), "{first:?}");
    let pid = Pid::from_raw(svc.pid().unwrap_or_else(|| panic!("no pid")) as i32);
    kill(pid, Signal::SIGSTOP).unwrap_or_else(|e| panic!("{e}"));
    let ended = exit_within(&mut moving, Duration::from_secs(60));
    kill(pid, Signal::SIGCONT).unwrap_or_else(|e| panic!("{e}"));
    let status = ended.unwrap_or_else(|| panic!("the watch hung on a frozen gateway"));
    let mut err = String::new();
    if let Some(mut e) = moving.stderr.take() {
        let _ = std::io::Read::read_to_string(&mut e, &mut err);
    }
    assert!(!status.success(), "{status:?}");
    assert!(err.contains("no reply within 4s"), "{err}");

    // A recording of a gateway that freezes ends with the same error after --timeout,
    // its file completed.
    let file = dir.path().join("frozen.mcap");
    let mut record = Command::new(HWGW)
        .args(["--timeout", "4", "record"])
        .arg(&file)
        .args(["--port", "sim0.ai", "--socket", &socket])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{e}"));
    testkit::wait_until("the recording under way", || {
        std::fs::metadata(&file).is_ok_and(|m| m.len() > 0)
    });
    kill(pid, Signal::SIGSTOP).unwrap_or_else(|e| panic!("{e}"));
    let ended = exit_within(&mut record, Duration::from_secs(60));
    kill(pid, Signal::SIGCONT).unwrap_or_else(|e| panic!("{e}"));
    let status = ended.unwrap_or_else(|| panic!("the recording hung on a frozen gateway"));
    let out = record.wait_with_output().unwrap_or_else(|e| panic!("{e}"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!status.success(), "{status:?}: {err}");
    assert!(err.contains("no reply within 4s"), "{err}");
    assert!(svc.terminate().status.success());
}
