//! A peer process driven by JSON lines: one command a line on its standard input, one
//! answer a line on its standard output (the OPC UA client, the pymodbus master).

use serde_json::Value;
use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::time::Duration;

/// Longest wait for one answer (a loaded machine is slow).
const ANSWER: Duration = Duration::from_secs(120);

/// A running peer; killed when dropped.
pub struct JsonPeer {
    child: Child,
    stdin: ChildStdin,
    lines: Receiver<String>,
    /// What the peer is, for messages.
    what: String,
}

impl Drop for JsonPeer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl JsonPeer {
    /// Runs `cmd` (its standard error inherited), named `what` in messages.
    pub fn spawn(mut cmd: Command, what: &str) -> JsonPeer {
        let mut child = cmd
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run {what} ({cmd:?}): {e}"));
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
        JsonPeer {
            child,
            stdin,
            lines,
            what: what.to_string(),
        }
    }

    /// The next line the peer says, as JSON; panics when it says nothing for long or ends.
    pub fn answer(&mut self) -> Value {
        match self.lines.recv_timeout(ANSWER) {
            Ok(line) => serde_json::from_str(&line)
                .unwrap_or_else(|e| panic!("{} said {line:?}: {e}", self.what)),
            Err(RecvTimeoutError::Timeout) => panic!("{} did not answer", self.what),
            Err(RecvTimeoutError::Disconnected) => {
                let status = self.child.wait();
                panic!("{} ended ({status:?})", self.what)
            }
        }
    }

    /// Sends `command`, returns its answer.
    pub fn ask(&mut self, command: &Value) -> Value {
        writeln!(self.stdin, "{command}").unwrap_or_else(|e| panic!("{}'s stdin: {e}", self.what));
        self.stdin.flush().expect("flushed");
        self.answer()
    }
}
