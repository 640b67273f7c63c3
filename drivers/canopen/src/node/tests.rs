//! The node state machine driven frame by frame: a small in-memory dictionary answers its
//! SDO requests (expedited only, as CiA 301 writes them; the SDO client itself is checked
//! against Python canopen in `tests/sdo_python.rs`).
#![allow(clippy::unwrap_used, reason = "test code")]

use super::*;
use crate::section::CanopenConfig;
use std::collections::BTreeMap;

const MS: u64 = 1_000_000;
const EDS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/eds");

fn run(extra: &str) -> NodeRun {
    let config: CanopenConfig = toml::from_str(&format!(
        r#"interface = "vcan0"
sdo_timeout_ms = 100
[[node]]
id = 5
eds = "io401.eds"
heartbeat_ms = 100
{extra}
[[node.tpdo]]
number = 1
objects = [{{ object = "0x6000:1" }}, {{ object = "0x6401:1" }}]
[[node.rpdo]]
number = 1
objects = [{{ object = "0x6411:1" }}]
"#
    ))
    .unwrap();
    let map = crate::map::CanopenMap::new(&config, EDS.as_ref()).unwrap();
    NodeRun::new(map.nodes[0].clone(), map.sdo_timeout)
}

/// A node's dictionary answering expedited SDO requests; `refuse` aborts writes of one
/// object with a code.
#[derive(Default)]
struct Server {
    od: BTreeMap<(u16, u8), Vec<u8>>,
    refuse: Option<((u16, u8), u32)>,
}

impl Server {
    fn answer(&mut self, req: &[u8; 8]) -> [u8; 8] {
        let index = u16::from_le_bytes([req[1], req[2]]);
        let key = (index, req[3]);
        let mut r = [0u8; 8];
        r[1..4].copy_from_slice(&req[1..4]);
        match req[0] >> 5 {
            1 => {
                if let Some((k, code)) = self.refuse
                    && k == key
                {
                    r[0] = 0x80;
                    r[4..].copy_from_slice(&code.to_le_bytes());
                    return r;
                }
                let n = 4 - usize::from((req[0] >> 2) & 3);
                self.od.insert(key, req[4..4 + n].to_vec());
                r[0] = 0x60;
            }
            2 => {
                let data = self.od.get(&key).cloned().unwrap_or(vec![0; 2]);
                r[0] = 0x43 | (((4 - data.len()) as u8) << 2);
                r[4..4 + data.len()].copy_from_slice(&data);
            }
            _ => panic!("unexpected request {req:02x?}"),
        }
        r
    }
}

/// Answers every SDO request `out` holds (and those the answers cause) until none is
/// left; returns the other frames sent.
fn serve(node: &mut NodeRun, server: &mut Server, out: &mut Vec<Tx>, now: u64) -> Vec<Tx> {
    serve_with(node, server, out, now, |_, _| {})
}

/// [`serve`], `tweak` changing the dictionary or the response after each answer.
fn serve_with(
    node: &mut NodeRun,
    server: &mut Server,
    out: &mut Vec<Tx>,
    now: u64,
    mut tweak: impl FnMut(&mut Server, &mut [u8; 8]),
) -> Vec<Tx> {
    let mut other = Vec::new();
    while let Some(tx) = out.pop() {
        if tx.id == 0x605 {
            let mut r = server.answer(&tx.data);
            tweak(server, &mut r);
            node.on_sdo(&r, now, out);
        } else {
            other.push(tx);
        }
    }
    other
}

#[test]
fn boot_up_configures_reads_back_and_starts() {
    let mut node = run("");
    let mut out = Vec::new();
    node.start(0, &mut out);
    assert_eq!(out, [Tx::nmt(nmt::RESET_COMMUNICATION, 5)]);
    out.clear();
    let mut server = Server::default();
    server
        .od
        .insert((0x6411, 1), (-100i16).to_le_bytes().to_vec());
    node.on_heartbeat(&[0], 0, &mut out);
    assert_eq!(node.status().state, NodeState::Configuring);
    let other = serve(&mut node, &mut server, &mut out, 0);
    assert_eq!(other, [Tx::nmt(nmt::START, 5)]);
    assert!(node.is_operational());
    // What the dictionary holds: the heartbeat, the TPDO valid with its COB-ID and two
    // entries, the RPDO with one.
    assert_eq!(server.od[&(0x1017, 0)], 100u16.to_le_bytes());
    assert_eq!(server.od[&(0x1800, 1)], 0x185u32.to_le_bytes());
    assert_eq!(server.od[&(0x1A00, 0)], [2]);
    assert_eq!(server.od[&(0x1A00, 1)], 0x6000_0108u32.to_le_bytes());
    assert_eq!(server.od[&(0x1A00, 2)], 0x6401_0110u32.to_le_bytes());
    assert_eq!(server.od[&(0x1600, 1)], 0x6411_0110u32.to_le_bytes());
    assert_eq!(server.od[&(0x1400, 1)], 0x205u32.to_le_bytes());
    // The output as the node has it, for the card to start from.
    assert_eq!(
        node.outputs_read,
        [(0x6411, 1, (-100i16).to_le_bytes().to_vec())]
    );
    assert_eq!(node.status().configured, 1);
}

#[test]
fn a_lost_heartbeat_is_offline_and_a_boot_up_configures_again() {
    let mut node = run("");
    let (mut out, mut server) = (Vec::new(), Server::default());
    node.on_heartbeat(&[0], 0, &mut out);
    serve(&mut node, &mut server, &mut out, 0);
    node.on_heartbeat(&[5], 100 * MS, &mut out);
    node.tick(399 * MS, &mut out);
    assert!(node.is_operational(), "3 periods not yet over");
    assert_eq!(node.next_deadline(), Some(400 * MS));
    node.tick(400 * MS, &mut out);
    assert_eq!(node.status().state, NodeState::Offline);
    assert_eq!(node.status().heartbeats_lost, 1);
    node.on_heartbeat(&[0], 900 * MS, &mut out);
    let other = serve(&mut node, &mut server, &mut out, 900 * MS);
    assert_eq!(other, [Tx::nmt(nmt::START, 5)]);
    assert_eq!(node.status().configured, 2);
    assert_eq!(node.status().boot_ups, 2);
}

#[test]
fn a_node_heard_without_its_boot_up_is_configured_from_pre_operational() {
    let mut node = run("");
    let (mut out, mut server) = (Vec::new(), Server::default());
    node.on_heartbeat(&[5], 0, &mut out);
    assert_eq!(out[0], Tx::nmt(nmt::PRE_OPERATIONAL, 5));
    out.remove(0);
    serve(&mut node, &mut server, &mut out, 0);
    assert!(node.is_operational());
}

#[test]
fn an_abort_names_the_object_and_its_meaning() {
    let mut node = run("");
    let mut server = Server {
        refuse: Some(((0x1A00, 1), 0x0604_0041)),
        ..Server::default()
    };
    let mut out = Vec::new();
    node.on_heartbeat(&[0], 0, &mut out);
    serve(&mut node, &mut server, &mut out, 0);
    assert_eq!(node.status().state, NodeState::Failed);
    let error = node.status().error.clone().unwrap();
    assert!(
        error.starts_with("configuring: writing 0x1a00 sub 1 (")
            && error.contains("0x06040041")
            && error.contains("cannot be mapped"),
        "{error}"
    );
    assert_eq!(node.status().sdo_aborts, 1);
}

#[test]
fn a_silent_node_times_out_with_an_abort() {
    let mut node = run("");
    let mut out = Vec::new();
    node.on_heartbeat(&[0], 0, &mut out);
    out.clear();
    node.tick(100 * MS, &mut out);
    assert_eq!(out.len(), 1);
    assert_eq!(out[0].id, 0x605);
    assert_eq!(out[0].data[0], 0x80);
    assert_eq!(&out[0].data[4..], &0x0504_0000u32.to_le_bytes());
    let error = node.status().error.clone().unwrap();
    assert!(error.contains("no response in 100 ms"), "{error}");
}

#[test]
fn a_read_back_that_differs_fails() {
    let mut node = run("");
    let mut out = Vec::new();
    node.on_heartbeat(&[0], 0, &mut out);
    // The dictionary keeps the heartbeat time at 50 whatever is written.
    let mut server = Server::default();
    serve_with(&mut node, &mut server, &mut out, 0, |server, _| {
        server.od.insert((0x1017, 0), 50u16.to_le_bytes().to_vec());
    });
    let error = node.status().error.clone().unwrap();
    assert_eq!(
        error,
        "read back 0x1017 sub 0 (Producer heartbeat time): 32 00 after writing 64 00"
    );
}

#[test]
fn bad_frames_and_stray_responses_are_counted_and_emergencies_bounded() {
    let mut node = run("");
    let mut out = Vec::new();
    node.on_sdo(&[0x60, 0, 0x10, 0, 0, 0, 0, 0], 0, &mut out);
    node.on_heartbeat(&[5, 5], 0, &mut out);
    node.on_emcy(&[1, 2]);
    for k in 0..20u8 {
        node.on_emcy(&[k, 0x81, 0x11, 1, 2, 3, 4, 5]);
    }
    let s = node.status();
    assert_eq!((s.sdo_unexpected, s.bad_frames, s.emergencies), (1, 2, 20));
    assert_eq!(s.last_emergencies.len(), EMERGENCIES_KEPT);
    assert_eq!(s.last_emergencies.back().unwrap().code, 0x8113);
    assert!(out.is_empty());
}

#[test]
fn a_boot_up_during_a_transfer_waits_for_its_answer_then_starts_over() {
    let mut node = run("");
    let (mut out, mut server) = (Vec::new(), Server::default());
    node.on_heartbeat(&[0], 0, &mut out);
    let first = out.pop().unwrap();
    // It boots again before answering: the answer to the old request comes after.
    node.on_heartbeat(&[0], MS, &mut out);
    assert!(out.is_empty(), "nothing new before the old answer: {out:?}");
    let late = server.answer(&first.data);
    node.on_sdo(&late, 2 * MS, &mut out);
    assert_eq!(out.len(), 1, "the configuration started over");
    let other = serve(&mut node, &mut server, &mut out, 2 * MS);
    assert_eq!(other, [Tx::nmt(nmt::START, 5)]);
    assert_eq!(node.status().sdo_aborts, 0);
}

#[test]
fn a_heartbeat_before_the_boot_up_after_the_reset_is_the_old_life() {
    let mut node = run("");
    let mut out = Vec::new();
    node.start(0, &mut out);
    out.clear();
    node.on_heartbeat(&[127], MS, &mut out);
    assert!(out.is_empty());
    assert_eq!(node.status().state, NodeState::Waiting);
    // No boot-up within one SDO timeout: configured from what it says.
    node.on_heartbeat(&[127], 100 * MS, &mut out);
    assert_eq!(out[0], Tx::nmt(nmt::PRE_OPERATIONAL, 5));
}

#[test]
fn a_node_that_leaves_operational_is_configured_and_started_again() {
    let mut node = run("");
    let (mut out, mut server) = (Vec::new(), Server::default());
    node.on_heartbeat(&[0], 0, &mut out);
    serve(&mut node, &mut server, &mut out, 0);
    // A heartbeat sent before the START took effect: the old state, not a departure.
    node.on_heartbeat(&[127], MS, &mut out);
    assert!(node.is_operational() && out.is_empty());
    node.on_heartbeat(&[5], 100 * MS, &mut out);
    // Later it drops to pre-operational on its own: not operational, configured again.
    node.on_heartbeat(&[127], 300 * MS, &mut out);
    assert_eq!(node.status().state, NodeState::Configuring);
    assert_eq!(out.remove(0), Tx::nmt(nmt::PRE_OPERATIONAL, 5));
    let other = serve(&mut node, &mut server, &mut out, 300 * MS);
    assert_eq!(other, [Tx::nmt(nmt::START, 5)]);
    assert_eq!(node.status().configured, 2);
}

#[test]
fn an_expedited_read_back_without_its_size_is_the_objects_bytes() {
    let mut node = run("");
    let mut out = Vec::new();
    node.on_heartbeat(&[0], 0, &mut out);
    let mut server = Server::default();
    serve_with(&mut node, &mut server, &mut out, 0, |_, r| {
        if r[0] & 0xE0 == 0x40 {
            // Expedited, size not indicated: four bytes, zero-padded.
            r[0] = 0x42;
        }
    });
    assert!(node.is_operational(), "{:?}", node.status().error);
}

#[test]
fn a_slow_configuration_is_not_a_lost_heartbeat() {
    // The heartbeat would be lost after 50 ms; the node answers its SDOs 70 ms late.
    let mut node = run("heartbeat_timeout_ms = 50");
    let (mut out, mut server) = (Vec::new(), Server::default());
    node.on_heartbeat(&[0], 0, &mut out);
    assert_eq!(
        node.next_deadline(),
        Some(100 * MS),
        "the SDO timeout alone"
    );
    node.tick(60 * MS, &mut out);
    assert_eq!(node.status().state, NodeState::Configuring);
    let other = serve(&mut node, &mut server, &mut out, 70 * MS);
    assert_eq!(other, [Tx::nmt(nmt::START, 5)]);
    assert!(node.is_operational());
    assert_eq!(node.status().heartbeats_lost, 0);
    // Watched from its start on.
    assert_eq!(node.next_deadline(), Some(120 * MS));
    node.tick(120 * MS, &mut out);
    assert_eq!(node.status().heartbeats_lost, 1);
}
