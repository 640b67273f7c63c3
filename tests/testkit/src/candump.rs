//! can-utils' `candump` as a capture that is listening before it returns: the third-party
//! peer of every CAN test.
//!
//! Started, candump opens its socket, sets its filters, binds, and only then waits in
//! `select`; [`Candump::start`] returns once the kernel shows it blocked in that wait
//! (`/proc/PID/syscall`), so no frame sent after it returns can be missed.

use crate::peers::{CAN_UTILS, require};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// System calls a listening candump waits in: select, poll, ppoll, pselect6, epoll_wait,
/// epoll_pwait, epoll_pwait2 (x86-64 numbers).
const WAITS: [u64; 7] = [23, 7, 271, 270, 232, 281, 441];

/// How long candump may take to start listening.
const START: Duration = Duration::from_secs(10);

/// `candump -L` running in the background.
pub struct Candump(Option<Child>);

/// True when process `pid` is blocked in one of [`WAITS`].
fn waiting(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/syscall"))
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<u64>().ok())
        .is_some_and(|n| WAITS.contains(&n))
}

impl Candump {
    /// Starts `candump -L ARGS` (e.g. `["-n", "5", "-T", "2000", "vcan0,200:7FF"]`) and
    /// returns once it is listening; [`frames`](Self::frames) collects what it dumped.
    pub fn start(args: &[&str]) -> Result<Candump, String> {
        Self::start_into(args, Stdio::piped())
    }

    /// As [`start`](Self::start), its log going to `log` (a file: a flood must not stall
    /// candump on a full pipe); [`finish`](Self::finish) waits for it.
    pub fn start_logging(args: &[&str], log: std::fs::File) -> Result<Candump, String> {
        Self::start_into(args, Stdio::from(log))
    }

    fn start_into(args: &[&str], out: Stdio) -> Result<Candump, String> {
        require(&CAN_UTILS).map_err(|e| e.to_string())?;
        let child = Command::new("candump")
            .arg("-L")
            .args(args)
            .stdout(out)
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| format!("candump: {e}"))?;
        let mut child = child;
        let end = Instant::now() + START;
        while !waiting(child.id()) {
            if let Ok(Some(status)) = child.try_wait() {
                if status.success() {
                    // It listened, and already got all it was asked for.
                    break;
                }
                let mut err = String::new();
                if let Some(e) = child.stderr.as_mut() {
                    let _ = std::io::Read::read_to_string(e, &mut err);
                }
                return Err(format!(
                    "candump {args:?} exited ({status}) before listening: {err}"
                ));
            }
            if Instant::now() > end {
                let _ = child.kill();
                let _ = child.wait();
                return Err(format!(
                    "candump {args:?} did not start listening within {START:?}"
                ));
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        Ok(Candump(Some(child)))
    }

    /// Waits for candump to end (a capture started with a log file).
    pub fn finish(mut self) -> Result<(), String> {
        let mut child = self.0.take().ok_or("candump: already collected")?;
        let status = child.wait().map_err(|e| format!("candump: {e}"))?;
        if status.success() {
            Ok(())
        } else {
            Err(format!("candump exited with {status}"))
        }
    }

    /// Waits for candump to end; each frame as (timestamp in s, `ID#DATA`).
    pub fn frames(mut self) -> Result<Vec<(f64, String)>, String> {
        let child = self.0.take().ok_or("candump: already collected")?;
        let out = child
            .wait_with_output()
            .map_err(|e| format!("candump: {e}"))?;
        Ok(String::from_utf8_lossy(&out.stdout)
            .lines()
            .filter_map(|l| {
                let mut parts = l.split_whitespace();
                let t = parts
                    .next()?
                    .trim_matches(|c| c == '(' || c == ')')
                    .parse()
                    .ok()?;
                let _interface = parts.next()?;
                Some((t, parts.next()?.to_string()))
            })
            .collect())
    }
}

impl Drop for Candump {
    fn drop(&mut self) {
        if let Some(mut c) = self.0.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}
