//! hwgw's EDS reader against Python `canopen`'s (PyPI, pinned in `testkit::pypi::CANOPEN`,
//! installed by the test when missing): the test EDS files of a CiA 401 IO module and a
//! CiA 402 drive, read for two node ids — every object, sub-index, name, data type,
//! access type, PDO mapping, default (the node id added to COB-IDs), and limit equal.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use driver_canopen::eds::{Kind, ObjectDictionary, Value, Variable};
use serde_json::{Value as Json, json};
use std::process::Command;
use testkit::peers::PYTHON;

const DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests");

/// Python canopen's reading of `file` for `node_id`, as the script prints it.
fn python(file: &str, node_id: u8) -> Json {
    let path = testkit::pypi::canopen()
        .unwrap_or_else(|e| panic!("cannot install canopen from PyPI (pip, python3-pip): {e}"));
    let out = Command::new(PYTHON)
        .arg(format!("{DIR}/peers/canopen_od.py"))
        .arg(file)
        .arg(node_id.to_string())
        .env("PYTHONPATH", path)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {PYTHON}: {e}"));
    assert!(
        out.status.success(),
        "canopen_od.py: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

fn value(v: &Option<Value>) -> Json {
    match v {
        None => Json::Null,
        Some(Value::Int(i)) => match (i64::try_from(*i), u64::try_from(*i)) {
            (Ok(i), _) => json!(i),
            (_, Ok(u)) => json!(u),
            _ => panic!("{i} is beyond JSON's integers"),
        },
        Some(Value::Float(f)) => json!(f),
        Some(Value::Text(t)) => json!(t),
        Some(Value::Bytes(b)) => {
            json!({ "bytes": b.iter().map(|x| format!("{x:02x}")).collect::<String>() })
        }
    }
}

fn variable(v: &Variable) -> Json {
    json!({
        "sub": v.sub,
        "name": v.name,
        "data_type": v.data_type,
        "access": v.access.as_str(),
        "pdo_mappable": v.pdo_mappable,
        "default": value(&v.default),
        "relative": v.relative,
        "min": value(&v.min),
        "max": value(&v.max),
    })
}

/// hwgw's reading in the script's shape.
fn ours(od: &ObjectDictionary) -> Json {
    let objects: Vec<Json> = od
        .objects
        .values()
        .map(|o| {
            json!({
                "index": o.index,
                "name": o.name,
                "kind": match o.kind {
                    Kind::Variable => "variable",
                    Kind::Array => "array",
                    Kind::Record => "record",
                },
                "subs": o.subs.values().map(variable).collect::<Vec<_>>(),
            })
        })
        .collect();
    json!({ "objects": objects })
}

#[test]
fn the_test_eds_files_read_as_python_canopen_reads_them() {
    for file in ["io401.eds", "drive402.eds"] {
        let path = format!("{DIR}/eds/{file}");
        let text = std::fs::read_to_string(&path).unwrap();
        for node_id in [5u8, 0x7F] {
            let od = driver_canopen::eds::parse(&text, Some(node_id))
                .unwrap_or_else(|e| panic!("{file}: {e}"));
            let (theirs, mine) = (python(&path, node_id), ours(&od));
            let (t, m) = (
                theirs["objects"].as_array().unwrap(),
                mine["objects"].as_array().unwrap(),
            );
            assert_eq!(t.len(), m.len(), "{file}: objects");
            for (a, b) in t.iter().zip(m) {
                assert_eq!(a, b, "{file}, node {node_id}");
            }
            // Not vacuous: the COB-IDs carry the node id.
            let cob = if file == "io401.eds" { 0x1800 } else { 0x1014 };
            let sub = u8::from(file == "io401.eds");
            let v = od.variable(cob, sub).unwrap();
            assert!(v.relative, "{file}: {v:?}");
        }
    }
}
