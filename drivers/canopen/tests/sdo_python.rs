//! hwgw's SDO client against Python canopen's SDO server (PyPI, pinned, installed by the
//! test when missing), with no bus between them: a `canopen.LocalNode` over the test IO
//! module's EDS is handed each request frame and its response frames come back. Expedited
//! and segmented reads and writes, the writes seen in the node's own dictionary, and the
//! node's aborts named.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use driver_canopen::sdo::{Download, SdoError, Step, Upload};
use serde_json::json;
use std::process::Command;
use testkit::jsonlines::JsonPeer;
use testkit::peers::PYTHON;

const DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests");
const NODE: u8 = 5;

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

fn bytes(h: &str) -> Vec<u8> {
    (0..h.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&h[i..i + 2], 16).unwrap())
        .collect()
}

/// The node: Python canopen's LocalNode with the IO module's EDS.
fn node() -> JsonPeer {
    let path = testkit::pypi::canopen()
        .unwrap_or_else(|e| panic!("cannot install canopen from PyPI (pip, python3-pip): {e}"));
    let mut cmd = Command::new(PYTHON);
    cmd.arg(format!("{DIR}/peers/sdo_server.py"))
        .arg(format!("{DIR}/eds/io401.eds"))
        .arg(NODE.to_string())
        .env("PYTHONPATH", path);
    let mut peer = JsonPeer::spawn(cmd, "python canopen's SDO server");
    assert_eq!(peer.answer(), json!({"ready": true}));
    peer
}

/// The server's one response to `request`.
fn exchange(node: &mut JsonPeer, request: [u8; 8]) -> Vec<u8> {
    let a = node.ask(&json!({ "request": hex(&request) }));
    let r = a["responses"].as_array().unwrap();
    assert_eq!(r.len(), 1, "one response to {request:02x?}: {a}");
    bytes(r[0].as_str().unwrap())
}

/// Runs a transfer to its end: its data, or its error; the frames it took.
fn run(
    node: &mut JsonPeer,
    first: [u8; 8],
    mut on: impl FnMut(&[u8]) -> Result<Step, SdoError>,
) -> (Result<Vec<u8>, SdoError>, usize) {
    let (mut request, mut frames) = (first, 0);
    loop {
        frames += 1;
        match on(&exchange(node, request)) {
            Ok(Step::Send(next)) => request = next,
            Ok(Step::Done(data)) => return (Ok(data), frames),
            Err(e) => return (Err(e), frames),
        }
    }
}

fn upload(node: &mut JsonPeer, index: u16, sub: u8) -> (Result<Vec<u8>, SdoError>, usize) {
    let (mut up, first) = Upload::start(index, sub);
    run(node, first, |r| up.on_response(r))
}

fn download(
    node: &mut JsonPeer,
    index: u16,
    sub: u8,
    data: &[u8],
) -> (Result<Vec<u8>, SdoError>, usize) {
    let (mut down, first) = Download::start(index, sub, data);
    run(node, first, |r| down.on_response(r))
}

fn stored(node: &mut JsonPeer, index: u16, sub: u8) -> Vec<u8> {
    bytes(
        node.ask(&json!({ "get": [index, sub] }))["data"]
            .as_str()
            .unwrap(),
    )
}

#[test]
fn expedited_and_segmented_reads_and_writes_against_python_canopens_server() {
    let mut node = node();
    // Segmented read: the device name, 10 bytes in two segments after the initiate.
    assert_eq!(
        upload(&mut node, 0x1008, 0),
        (Ok(b"hwgw IO401".to_vec()), 3)
    );
    // Expedited read: the TPDO's COB-ID, its node id added (0x180 + 5).
    assert_eq!(
        upload(&mut node, 0x1800, 1),
        (Ok(0x185u32.to_le_bytes().to_vec()), 1)
    );
    // Expedited write (analog output 1, an INTEGER16), seen in the node's dictionary and
    // read back.
    let v = (-1234i16).to_le_bytes();
    assert_eq!(download(&mut node, 0x6411, 1, &v), (Ok(Vec::new()), 1));
    assert_eq!(stored(&mut node, 0x6411, 1), v);
    assert_eq!(upload(&mut node, 0x6411, 1).0, Ok(v.to_vec()));
    // Segmented write of 20 bytes (3 segments), seen whole in the node's dictionary.
    let key: Vec<u8> = (0..20).map(|i| i * 13 + 1).collect();
    assert_eq!(download(&mut node, 0x2002, 0, &key), (Ok(Vec::new()), 4));
    assert_eq!(stored(&mut node, 0x2002, 0), key);
    assert_eq!(upload(&mut node, 0x2002, 0).0, Ok(key));
}

#[test]
fn the_nodes_aborts_are_errors_naming_the_object_and_the_reason() {
    let mut node = node();
    let (e, _) = upload(&mut node, 0x3000, 0);
    assert_eq!(
        e.unwrap_err().to_string(),
        "SDO 0x3000 sub 0: the node aborted with 0x06020000: object does not exist in the object dictionary"
    );
    let (e, _) = download(&mut node, 0x1000, 0, &[1, 2, 3, 4]);
    assert_eq!(
        e.unwrap_err().to_string(),
        "SDO 0x1000 sub 0: the node aborted with 0x06010002: attempt to write a read only object"
    );
}

#[test]
fn pdo_mappings_written_by_sdo_are_what_python_canopen_reads_back() {
    use driver_canopen::pdo::{Direction, Mapped, Pdo};
    let mut node = node();
    let text = std::fs::read_to_string(format!("{DIR}/eds/io401.eds")).unwrap();
    let od = driver_canopen::eds::parse(&text, Some(NODE)).unwrap();
    let m = |index, sub, bits| Mapped { index, sub, bits };
    // The EDS maps TPDO1 as digital inputs and analog input 2; map analog input 1 and the
    // digital inputs instead, sent on event every 50 ms. RPDO1: both analog outputs.
    let tpdo = Pdo {
        direction: Direction::Tpdo,
        number: 1,
        cob_id: 0x185,
        transmission: 255,
        event_timer_ms: Some(50),
        inhibit_100us: None,
        mapped: vec![m(0x6401, 1, 16), m(0x6000, 1, 8)],
    };
    let rpdo = Pdo {
        direction: Direction::Rpdo,
        number: 1,
        cob_id: 0x205,
        transmission: 1,
        event_timer_ms: None,
        inhibit_100us: None,
        mapped: vec![m(0x6411, 1, 16), m(0x6411, 2, 16)],
    };
    for pdo in [&tpdo, &rpdo] {
        for w in pdo.writes(&od).unwrap() {
            let (r, _) = download(&mut node, w.index, w.sub, &w.data);
            assert_eq!(r, Ok(Vec::new()), "{w:?}");
        }
    }
    let seen = |node: &mut JsonPeer, kind: &str| node.ask(&json!({"pdo": kind, "number": 1}));
    assert_eq!(
        seen(&mut node, "tpdo"),
        json!({"cob_id": 0x185, "enabled": true, "trans_type": 255, "event_timer": 50,
               "mapped": [[0x6401, 1, 16], [0x6000, 1, 8]]})
    );
    let r = seen(&mut node, "rpdo");
    assert_eq!(
        (&r["cob_id"], &r["enabled"], &r["trans_type"], &r["mapped"]),
        (
            &json!(0x205),
            &json!(true),
            &json!(1),
            &json!([[0x6411, 1, 16], [0x6411, 2, 16]])
        )
    );
}
