//! An MCAP file read by the independent reader, the `mcap` package from PyPI ([`pypi::mcap`]):
//! every message decoded as JSON, with its channel's topic, encoding and schema, and the
//! file's metadata records.

use crate::peers::PYTHON;
use crate::pypi;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

/// One topic as the reader saw it.
#[derive(Debug, Clone, Default)]
pub struct Topic {
    /// The channel's message encoding.
    pub encoding: String,
    /// Its schema's name and encoding.
    pub schema: (String, String),
    /// Each message's log time, ns.
    pub times: Vec<u64>,
    /// Each message, decoded.
    pub messages: Vec<Value>,
}

/// What the reader found.
#[derive(Debug, Clone, Default)]
pub struct Dump {
    /// Topics by name.
    pub topics: BTreeMap<String, Topic>,
    /// Metadata records by name.
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// The summary's message count.
    pub message_count: u64,
}

const SCRIPT: &str = r#"
import json, sys
from mcap.reader import make_reader
out = {"topics": {}, "metadata": {}, "count": 0}
with open(sys.argv[1], "rb") as f:
    r = make_reader(f)
    for schema, channel, message in r.iter_messages(log_time_order=False):
        t = out["topics"].setdefault(channel.topic, {
            "encoding": channel.message_encoding,
            "schema": [schema.name, schema.encoding] if schema else ["", ""],
            "times": [], "messages": []})
        t["times"].append(message.log_time)
        t["messages"].append(json.loads(message.data))
    for m in r.iter_metadata():
        out["metadata"][m.name] = dict(m.metadata)
    s = r.get_summary()
    out["count"] = s.statistics.message_count if s and s.statistics else -1
print(json.dumps(out))
"#;

/// Reads `path` with the `mcap` package.
pub fn read(path: &Path) -> Result<Dump, String> {
    let lib = pypi::mcap().map_err(|e| format!("installing the mcap package: {e}"))?;
    let out = Command::new(PYTHON)
        .env("PYTHONPATH", &lib)
        .arg("-c")
        .arg(SCRIPT)
        .arg(path)
        .output()
        .map_err(|e| format!("{PYTHON}: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "the mcap package could not read {}: {}",
            path.display(),
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    let v: Value = serde_json::from_slice(&out.stdout).map_err(|e| e.to_string())?;
    let mut dump = Dump {
        message_count: v["count"].as_u64().unwrap_or(0),
        ..Dump::default()
    };
    if let Some(m) = v["metadata"].as_object() {
        for (name, map) in m {
            let map = map
                .as_object()
                .map(|o| {
                    o.iter()
                        .map(|(k, v)| (k.clone(), v.as_str().unwrap_or_default().to_string()))
                        .collect()
                })
                .unwrap_or_default();
            dump.metadata.insert(name.clone(), map);
        }
    }
    if let Some(t) = v["topics"].as_object() {
        for (name, t) in t {
            let s = |i: usize| t["schema"][i].as_str().unwrap_or_default().to_string();
            dump.topics.insert(
                name.clone(),
                Topic {
                    encoding: t["encoding"].as_str().unwrap_or_default().to_string(),
                    schema: (s(0), s(1)),
                    times: t["times"]
                        .as_array()
                        .map(|a| a.iter().filter_map(Value::as_u64).collect())
                        .unwrap_or_default(),
                    messages: t["messages"].as_array().cloned().unwrap_or_default(),
                },
            );
        }
    }
    Ok(dump)
}
