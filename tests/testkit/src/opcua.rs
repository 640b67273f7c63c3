//! An independent OPC UA client as a peer: Python asyncua ([`crate::pypi::ASYNCUA`],
//! installed by the tests when missing) running `gateway/tests/peers/opcua_client.py`, one
//! session a client, driven by JSON lines (see the script for its commands).

use crate::peers::PYTHON;
use serde_json::Value;
use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::time::Duration;

/// The client script.
pub const CLIENT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../gateway/tests/peers/opcua_client.py"
);

/// Longest wait for one answer (a subscription's notifications wait less, by their own
/// timeout; a loaded machine is slow).
const ANSWER: Duration = Duration::from_secs(120);

/// A connected asyncua session; its process killed when dropped.
pub struct UaClient {
    child: Child,
    stdin: ChildStdin,
    lines: Receiver<String>,
    /// The namespace index of hwgw's nodes.
    pub ns: u64,
}

impl Drop for UaClient {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl UaClient {
    /// Connects as `conf` says (`url`, and optionally `policy`, `mode`, `cert`, `key`,
    /// `app_uri`, `user`, `password`); the client's error text when it was refused.
    pub fn connect(conf: &Value) -> Result<UaClient, String> {
        let path = crate::pypi::asyncua()
            .unwrap_or_else(|e| panic!("cannot install asyncua from PyPI (pip, python3-pip): {e}"));
        let mut child = Command::new(PYTHON)
            .arg(CLIENT)
            .arg(conf.to_string())
            .env("PYTHONPATH", path)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run {PYTHON} {CLIENT}: {e}"));
        let stdin = child.stdin.take().expect("piped");
        let stdout = child.stdout.take().expect("piped");
        let (tx, lines) = channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut c = UaClient {
            child,
            stdin,
            lines,
            ns: 0,
        };
        let hello = c.answer();
        if let Some(e) = hello.get("error") {
            return Err(e.as_str().unwrap_or_default().to_string());
        }
        c.ns = hello["ns"].as_u64().expect("a namespace index");
        Ok(c)
    }

    /// Connects to `url` without security, anonymous; panics when refused.
    pub fn open(url: &str) -> UaClient {
        UaClient::connect(&serde_json::json!({ "url": url }))
            .unwrap_or_else(|e| panic!("asyncua could not connect to {url}: {e}"))
    }

    fn answer(&mut self) -> Value {
        match self.lines.recv_timeout(ANSWER) {
            Ok(line) => serde_json::from_str(&line)
                .unwrap_or_else(|e| panic!("the OPC UA client said {line:?}: {e}")),
            Err(RecvTimeoutError::Timeout) => panic!("the OPC UA client did not answer"),
            Err(RecvTimeoutError::Disconnected) => {
                let status = self.child.wait();
                panic!("the OPC UA client ended ({status:?})")
            }
        }
    }

    /// Sends `command`, returns its answer.
    pub fn ask(&mut self, command: Value) -> Value {
        writeln!(self.stdin, "{command}").expect("the OPC UA client's stdin");
        self.stdin.flush().expect("flushed");
        self.answer()
    }
}
