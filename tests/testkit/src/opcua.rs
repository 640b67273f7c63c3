//! An independent OPC UA client as a peer: Python asyncua ([`crate::pypi::ASYNCUA`],
//! installed by the tests when missing) running `gateway/tests/peers/opcua_client.py`, one
//! session a client, driven by JSON lines (see the script for its commands).

use crate::jsonlines::JsonPeer;
use crate::peers::PYTHON;
use serde_json::Value;
use std::process::Command;

/// The client script.
pub const CLIENT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../gateway/tests/peers/opcua_client.py"
);

/// A connected asyncua session; its process killed when dropped.
pub struct UaClient {
    peer: JsonPeer,
    /// The namespace index of hwgw's nodes.
    pub ns: u64,
}

impl UaClient {
    /// Connects as `conf` says (`url`, and optionally `policy`, `mode`, `cert`, `key`,
    /// `app_uri`, `user`, `password`); the client's error text when it was refused.
    pub fn connect(conf: &Value) -> Result<UaClient, String> {
        let path = crate::pypi::asyncua()
            .unwrap_or_else(|e| panic!("cannot install asyncua from PyPI (pip, python3-pip): {e}"));
        let mut cmd = Command::new(PYTHON);
        cmd.arg(CLIENT)
            .arg(conf.to_string())
            .env("PYTHONPATH", path);
        let mut c = UaClient {
            peer: JsonPeer::spawn(cmd, "the OPC UA client"),
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
        self.peer.answer()
    }

    /// Sends `command`, returns its answer.
    pub fn ask(&mut self, command: Value) -> Value {
        self.peer.ask(&command)
    }
}
