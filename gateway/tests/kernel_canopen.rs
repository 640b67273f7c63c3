//! `hwgw` as a CANopen manager, in the kernel rig: Python canopen `LocalNode`s (an
//! implementation we did not write) on a real vcan act as CiA 401 IO modules, each over
//! the EDS the tests ship, with `peers/canopen_nodes.py` as their device application; the
//! real binary configures them by SDO and reads and writes them by PDO, checked through
//! the CLI on one side and the nodes' object dictionaries on the other.
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Trial, sh};
use serde_json::{Value, json};
use std::process::Command;
use testkit::jsonlines::JsonPeer;
use testkit::wait::wait_ok;
use testkit::{Candump, Service};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const PEER: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/peers/canopen_nodes.py");
const EDS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../drivers/canopen/tests/eds");

/// The nodes `ids` (each a CiA 401 module over io401.eds) on `iface`, booted.
fn nodes(iface: &str, ids: &[u8]) -> JsonPeer {
    let specs: Vec<String> = ids
        .iter()
        .map(|id| format!("{id}:{EDS}/io401.eds"))
        .collect();
    peer(iface, &specs)
}

/// Python canopen's nodes `specs` (`ID:EDS[:402]`) on `iface`, booted.
fn peer(iface: &str, specs: &[String]) -> JsonPeer {
    let path = testkit::pypi::canopen()
        .unwrap_or_else(|e| panic!("cannot install canopen from PyPI (pip, python3-pip): {e}"));
    let mut cmd = Command::new("python3");
    cmd.arg(PEER).arg(iface).args(specs);
    cmd.env("PYTHONPATH", path);
    let mut peer = JsonPeer::spawn(cmd, "python canopen's nodes");
    assert_eq!(peer.answer(), json!({"ready": true}));
    peer
}

/// One IO module's section: TPDO1 carries the 8 inputs and analog input 1, RPDO1 the 8
/// outputs and analog output 1.
fn node_section(id: u8, name: &str) -> String {
    format!(
        r#"
[[card.canopen.node]]
id = {id}
name = "{name}"
eds = "{EDS}/io401.eds"
heartbeat_ms = 100

[[card.canopen.node.tpdo]]
number = 1
transmission = "event"
objects = [{{ object = "0x6000:1", name = "{name}_di" }}, {{ object = "0x6401:1", name = "{name}_ai", factor = 0.01, unit = "V" }}]

[[card.canopen.node.rpdo]]
number = 1
transmission = "event"
objects = [{{ object = "0x6200:1", name = "{name}_do" }}, {{ object = "0x6411:1", name = "{name}_ao", factor = 0.001, unit = "V" }}]
"#
    )
}

fn deployment(iface: &str, nodes: &str, safe: &str) -> String {
    format!(
        r#"
[[card]]
name = "io"
driver = "canopen"
sample_period_ms = 10
{safe}

[card.canopen]
interface = "{iface}"
sync_ms = 50
sdo_timeout_ms = 1000
at_stop = "pre_operational"
{nodes}
"#
    )
}

fn counters(gw: &Service) -> Result<Value, Failed> {
    Ok(serde_json::from_str(&gw.out(&["call", "io", "counters"])?)?)
}

/// Node `id`'s status in the counters.
fn node(gw: &Service, id: u8) -> Result<Value, Failed> {
    let c = counters(gw)?;
    Ok(c["nodes"]
        .as_array()
        .and_then(|n| n.iter().find(|n| n["id"] == json!(id)).cloned())
        .ok_or_else(|| format!("no node {id} in {c}"))?)
}

fn wait_state(gw: &Service, id: u8, state: &str) -> Result<(), Failed> {
    let waited = wait_ok(&format!("node {id} {state}"), || {
        Ok(node(gw, id)?["state"] == json!(state))
    });
    waited.map_err(|e| {
        format!(
            "{e:?}: {}\n{}",
            counters(gw).unwrap_or_default(),
            gw.log_text()
        )
        .into()
    })
}

/// Waits for three SYNCs on `iface` (time for a PDO sent at a SYNC to have come).
fn three_syncs(iface: &str) -> Result<(), Failed> {
    let syncs = Candump::start(&["-n", "3", "-T", "3000", &format!("{iface},080:7FF")])?;
    assert_eq!(syncs.frames()?.len(), 3);
    Ok(())
}

fn get(gw: &Service, device: &str, port: &str) -> Result<String, Failed> {
    Ok(gw.out(&["get", &format!("io.{device}"), port])?)
}

fn od(peer: &mut JsonPeer, id: u8, index: u16, sub: u8) -> Value {
    peer.ask(&json!({"get": [id, index, sub]}))["value"].clone()
}

fn an_io_module_is_configured_read_written_and_left_safe() -> Result<(), Failed> {
    sh("ip link add vcan0 type vcan && ip link set vcan0 up")?;
    let mut peer = nodes("vcan0", &[5]);
    let gw = Service::run_text(
        HWGW,
        "canopen-io",
        &deployment(
            "vcan0",
            &node_section(5, "m"),
            "outputs = { safe = { m_ao = 0.0, m_do_0 = false, m_do_1 = false, m_do_2 = false, m_do_3 = false } }",
        ),
    )?;
    wait_state(&gw, 5, "operational")?;

    // The node's dictionary shows the configuration, as canopen's PDO reader reads it.
    let tpdo = peer.ask(&json!({"pdo": [5, "tpdo", 1]}));
    assert_eq!(
        tpdo,
        json!({"cob_id": 0x185, "enabled": true, "trans_type": 255,
               "mapped": [[0x6000, 1, 8], [0x6401, 1, 16]]})
    );
    let rpdo = peer.ask(&json!({"pdo": [5, "rpdo", 1]}));
    assert_eq!(
        rpdo,
        json!({"cob_id": 0x205, "enabled": true, "trans_type": 255,
               "mapped": [[0x6200, 1, 8], [0x6411, 1, 16]]})
    );
    assert_eq!(
        peer.ask(&json!({"nmt": 5})),
        json!({"state": "OPERATIONAL", "heartbeat_ms": 100})
    );

    // Outputs start as the node has them (0x6411:1 defaults to -100): nothing written,
    // seen after three SYNCs of the node operational.
    assert_eq!(get(&gw, "ao", "m_ao")?, "-0.1");
    three_syncs("vcan0")?;
    assert_eq!(peer.ask(&json!({"rpdos": 5})), json!({"count": 0}));

    // Inputs: the node's TPDO, as hwgw decodes it.
    peer.ask(&json!({"set": [5, 0x6000, 1, 0xA5]}));
    peer.ask(&json!({"set": [5, 0x6401, 1, -1234]}));
    wait_ok("the analog input", || {
        Ok(get(&gw, "ai", "m_ai")? == "-12.34")
    })?;
    let bits: Vec<String> = (0..8)
        .map(|k| get(&gw, "di", &format!("m_di_{k}")))
        .collect::<Result<_, _>>()?;
    assert_eq!(
        bits,
        [
            "true", "false", "true", "false", "false", "true", "false", "true"
        ]
    );

    // Outputs: hwgw's RPDO, as the node's dictionary takes it.
    gw.out(&["set", "io.ao", "m_ao", "1.5"])?;
    gw.out(&["set", "io.do", "m_do_3", "true"])?;
    let arrived = wait_ok("the outputs at the node", || {
        Ok(od(&mut peer, 5, 0x6411, 1) == json!(1500) && od(&mut peer, 5, 0x6200, 1) == json!(8))
    });
    if let Err(e) = arrived {
        let at_node = [od(&mut peer, 5, 0x6411, 1), od(&mut peer, 5, 0x6200, 1)];
        let rpdos = peer.ask(&json!({"rpdos": 5}));
        return Err(format!(
            "{e:?}: the node has {at_node:?} after {rpdos}; hwgw: {}",
            counters(&gw)?
        )
        .into());
    }

    // SYNC every 50 ms: candump's kernel timestamps.
    let syncs = Candump::start(&["-n", "21", "-T", "3000", "vcan0,080:7FF"])?.frames()?;
    assert_eq!(syncs.len(), 21, "{syncs:?}");
    let mean = (syncs[20].0 - syncs[0].0) / 20.0;
    assert!((mean - 0.050).abs() < 0.001, "mean SYNC period {mean} s");
    assert!(syncs.iter().all(|(_, f)| f == "080#"), "{syncs:?}");

    // Emergencies counted with their codes.
    peer.ask(&json!({"emcy": [5, 0x8130, 0x11]}));
    wait_ok("the emergency", || {
        Ok(node(&gw, 5)?["emergencies"] == json!(1))
    })?;
    assert_eq!(
        node(&gw, 5)?["last_emergencies"][0],
        json!({"code": 0x8130, "register": 0x11, "data": [0, 0, 0, 0, 0]})
    );

    // Heartbeat stops: offline, its channels too; it boots again: configured again.
    peer.ask(&json!({"silence": 5}));
    wait_state(&gw, 5, "offline")?;
    assert_eq!(node(&gw, 5)?["heartbeats_lost"], json!(1));
    // The device itself refuses the read (`get` reads the last sample's port).
    let read = gw.cli(&["call", "io.ai", "read", "0"]);
    let err = String::from_utf8_lossy(&read.stderr);
    assert!(!read.status.success() && err.contains("offline"), "{err}");
    let dump = Candump::start(&[
        "-n",
        "100",
        "-T",
        "3000",
        "vcan0,000:7FF,705:7FF,585:7FF,605:7FF",
    ])?;
    peer.ask(&json!({"power_on": 5}));
    if let Err(e) = wait_state(&gw, 5, "operational") {
        return Err(format!("{e:?} {:?}", dump.frames()?).into());
    }
    let n = node(&gw, 5)?;
    assert_eq!(n["configured"], json!(2), "{n}");
    assert!(n["boot_ups"].as_u64() >= Some(2), "{n}");
    // Its power-on reset the PDO configuration: hwgw wrote it again.
    assert_eq!(peer.ask(&json!({"pdo": [5, "tpdo", 1]})), tpdo);
    peer.ask(&json!({"set": [5, 0x6401, 1, 777]}));
    // raw × factor in f64, as CiA 401 scaling and every DBC tool compute it.
    let expected = (777.0 * 0.01f64).to_string();
    let again = wait_ok("the analog input again", || {
        Ok(get(&gw, "ai", "m_ai")? == expected)
    });
    if let Err(e) = again {
        let read = gw.cli(&["call", "io.ai", "read", "0"]);
        return Err(format!(
            "{e:?}: get {:?}, read {:?} {:?}; hwgw: {}",
            get(&gw, "ai", "m_ai"),
            String::from_utf8_lossy(&read.stdout),
            String::from_utf8_lossy(&read.stderr),
            counters(&gw)?
        )
        .into());
    }

    // Stop: the safe values reach the node, then it is left pre-operational.
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    // The node applies a PDO on its own thread: waited for, not raced.
    wait_ok("the safe values at the node", || {
        Ok(od(&mut peer, 5, 0x6411, 1) == json!(0) && od(&mut peer, 5, 0x6200, 1) == json!(0))
    })?;
    wait_ok("pre-operational", || {
        Ok(peer.ask(&json!({"nmt": 5}))["state"] == json!("PRE-OPERATIONAL"))
    })?;
    Ok(())
}

fn aborts_are_named_and_hostile_frames_counted() -> Result<(), Failed> {
    // An interface that is not there: `hwgw run` fails naming it (it exits by itself).
    let dir = testkit::TempDir::new("canopen-missing");
    let file = dir.path().join("deployment.toml");
    std::fs::write(&file, deployment("vcan9", &node_section(5, "m"), ""))?;
    let run = Command::new(HWGW)
        .arg("run")
        .arg(&file)
        .arg("--socket")
        .arg(dir.path().join("hwgw.sock"))
        .output()?;
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success(), "{err}");
    assert!(
        err.contains("interface \"vcan9\": no such network interface"),
        "{err}"
    );
    sh("ip link add vcan1 type vcan && ip link set vcan1 up")?;
    let mut peer = nodes("vcan1", &[5, 6, 7]);
    // Node 6 refuses its TPDO mapping: "object cannot be mapped to the PDO".
    peer.ask(&json!({"refuse": [6, 0x1A00, 1, 0x0604_0041u32]}));
    let sections = [
        node_section(5, "a"),
        node_section(6, "b"),
        node_section(7, "c"),
    ]
    .concat();
    let gw = Service::run_text(HWGW, "canopen-hostile", &deployment("vcan1", &sections, ""))?;
    wait_state(&gw, 5, "operational")?;
    wait_state(&gw, 7, "operational")?;
    wait_state(&gw, 6, "failed")?;
    let error = node(&gw, 6)?["error"]
        .as_str()
        .unwrap_or_default()
        .to_string();
    assert!(
        error.contains("0x1a00 sub 1") && error.contains("0x06040041"),
        "{error}"
    );
    assert!(error.contains("cannot be mapped"), "{error}");

    // Node 5 works; node 7 is flooded with bad frames on its ids.
    peer.ask(&json!({"set": [5, 0x6401, 1, 4242]}));
    wait_ok("node 5's input", || Ok(get(&gw, "ai", "a_ai")? == "42.42"))?;
    sh("cansend vcan1 187#01")?; // a TPDO shorter than its mapping
    sh("cansend vcan1 587#4300100000000000")?; // an SDO response nobody asked for
    sh("cansend vcan1 707#0505")?; // a heartbeat of two bytes
    sh("cansend vcan1 087#0110")?; // a short emergency
    sh("cangen vcan1 -I 087 -L 8 -D r -n 300 -g 0")?; // an emergency flood
    sh("cangen vcan1 -I 587 -L r -D r -n 100 -g 0")?; // random SDO responses
    wait_ok("the flood counted", || {
        let c = counters(&gw)?;
        let n7 = node(&gw, 7)?;
        Ok(c["short_pdos"].as_u64() >= Some(1)
            && n7["bad_frames"].as_u64() >= Some(2)
            && n7["sdo_unexpected"].as_u64() >= Some(1)
            && n7["emergencies"].as_u64().unwrap_or(0) + c["dropped"].as_u64().unwrap_or(0) >= 300)
    })?;
    assert_eq!(
        node(&gw, 7)?["last_emergencies"].as_array().map(Vec::len),
        Some(8)
    );
    // The other nodes are unaffected: node 5's values exact both ways, both operational.
    peer.ask(&json!({"set": [5, 0x6401, 1, -5]}));
    wait_ok("node 5's input after", || {
        Ok(get(&gw, "ai", "a_ai")? == "-0.05")
    })?;
    gw.out(&["set", "io.ao", "a_ao", "-2.5"])?;
    wait_ok("node 5's output", || {
        Ok(od(&mut peer, 5, 0x6411, 1) == json!(-2500))
    })?;
    assert_eq!(node(&gw, 5)?["state"], json!("operational"));
    assert_eq!(node(&gw, 7)?["state"], json!("operational"));
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    Ok(())
}

/// A CiA 402 drive (Python canopen node 9 over drive402.eds, its state machine in the
/// peer) as the card's drive `io.axis`: profile velocity mode set by SDO, enabled through
/// shutdown, switch on, enable operation; moved; a fault seen, reset by disable, enabled
/// again; quick-stopped and enabled again; at stop shut down at zero velocity.
fn a_cia402_drive_is_enabled_moved_and_shut_down() -> Result<(), Failed> {
    sh("ip link add vcan3 type vcan && ip link set vcan3 up")?;
    let mut peer = peer("vcan3", &[format!("9:{EDS}/drive402.eds:402")]);
    let section = format!(
        r#"
[[card.canopen.node]]
id = 9
eds = "{EDS}/drive402.eds"
heartbeat_ms = 100
drive = {{ name = "axis", velocity_factor = 0.1, unit = "rpm" }}

[[card.canopen.node.tpdo]]
number = 1
objects = [{{ object = "0x6041:0", name = "status", type = "analog" }}, {{ object = "0x606C:0", name = "speed", factor = 0.1, unit = "rpm" }}]

[[card.canopen.node.rpdo]]
number = 1
objects = [{{ object = "0x6040:0" }}, {{ object = "0x60FF:0" }}]
"#
    );
    let gw = Service::run_text(HWGW, "canopen-402", &deployment("vcan3", &section, ""))?;
    wait_state(&gw, 9, "operational")?;
    // Profile velocity mode, written at configuration.
    assert_eq!(od(&mut peer, 9, 0x6060, 0), json!(3));
    let sw = |peer: &mut JsonPeer| od(peer, 9, 0x6041, 0).as_u64().unwrap_or(0) & 0x6F;
    // Disabled, nothing written: the drive is as it booted.
    assert_eq!(gw.out(&["call", "io.axis", "enabled"])?, "false");
    assert_eq!(sw(&mut peer), 0x40);
    wait_ok("the drive operational", || {
        Ok(peer.ask(&json!({"nmt": 9}))["state"] == json!("OPERATIONAL"))
    })?;
    three_syncs("vcan3")?;
    assert_eq!(peer.ask(&json!({"rpdos": 9})), json!({"count": 0}));

    gw.out(&["call", "io.axis", "enable"])?;
    wait_ok("operation enabled", || Ok(sw(&mut peer) == 0x27))?;
    gw.out(&["call", "io.axis", "set_velocity", "150"])?;
    wait_ok("the target velocity at the drive", || {
        Ok(od(&mut peer, 9, 0x60FF, 0) == json!(1500))
    })?;
    // raw × factor in f64, bit for bit.
    let speed = 1500.0 * 0.1f64;
    let number = |s: String| s.parse::<f64>().map(f64::to_bits).ok();
    wait_ok("the velocity actual", || {
        Ok(number(get(&gw, "ai", "speed")?) == Some(speed.to_bits()))
    })?;
    let set = number(gw.out(&["call", "io.axis", "velocity"])?);
    assert_eq!(set, Some(speed.to_bits()));

    // A fault: enabled no more, enable refused; disable resets it; enabled again.
    peer.ask(&json!({"fault": 9}));
    wait_ok("the fault seen", || {
        Ok(gw.out(&["call", "io.axis", "faulted"])? == "true")
    })?;
    assert_eq!(gw.out(&["call", "io.axis", "enabled"])?, "false");
    assert!(!gw.cli(&["call", "io.axis", "enable"]).status.success());
    gw.out(&["call", "io.axis", "disable"])?;
    wait_ok("the fault reset", || Ok(sw(&mut peer) == 0x40))?;
    gw.out(&["call", "io.axis", "enable"])?;
    wait_ok("operation enabled again", || Ok(sw(&mut peer) == 0x27))?;
    gw.out(&["call", "io.axis", "set_velocity", "-20"])?;
    wait_ok("the new velocity", || {
        Ok(od(&mut peer, 9, 0x60FF, 0) == json!(-200))
    })?;

    // Quick stop: the quick-stop command (controlword 0x0002) with target 0; the drive
    // brakes to quick stop active (and, by its option code, may go on to switch on
    // disabled); enabled again after.
    gw.out(&["call", "io.axis", "quick_stop"])?;
    wait_ok("the quick stop at the drive", || {
        let s = sw(&mut peer);
        Ok(od(&mut peer, 9, 0x6040, 0) == json!(2)
            && od(&mut peer, 9, 0x60FF, 0) == json!(0)
            && (s == 0x07 || s == 0x40))
    })?;
    assert_eq!(gw.out(&["call", "io.axis", "enabled"])?, "false");
    gw.out(&["call", "io.axis", "enable"])?;
    wait_ok("operation enabled after the quick stop", || {
        Ok(sw(&mut peer) == 0x27)
    })?;
    gw.out(&["call", "io.axis", "set_velocity", "-20"])?;
    wait_ok("the velocity again", || {
        Ok(od(&mut peer, 9, 0x60FF, 0) == json!(-200))
    })?;

    // Stop: zero velocity, shut down (ready to switch on).
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    wait_ok("zero velocity, shut down", || {
        Ok(od(&mut peer, 9, 0x60FF, 0) == json!(0) && sw(&mut peer) == 0x21)
    })?;
    Ok(())
}

fn main() -> std::process::ExitCode {
    if !kernel_rig::in_guest()
        && let Err(e) = testkit::pypi::canopen()
    {
        eprintln!("cannot install canopen from PyPI (pip, python3-pip): {e}");
    }
    // python-can sends the nodes' heartbeats through CAN_BCM.
    let rig = testkit::rig::vcan().module("can_bcm");
    kernel_rig::harness(
        &rig,
        vec![
            Trial::test(
                "an_io_module_is_configured_read_written_and_left_safe",
                an_io_module_is_configured_read_written_and_left_safe,
            ),
            Trial::test(
                "aborts_are_named_and_hostile_frames_counted",
                aborts_are_named_and_hostile_frames_counted,
            ),
            Trial::test(
                "a_cia402_drive_is_enabled_moved_and_shut_down",
                a_cia402_drive_is_enabled_moved_and_shut_down,
            ),
        ],
    )
}
