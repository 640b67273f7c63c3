//! Reload with the real binary: a simulated card and a Modbus card against pymodbus (a
//! Modbus server we did not write), with components. `hwgw reload` after a change to the
//! Modbus card's section rebuilds that card alone — the sim card takes no write and its IO
//! component steps on without a pause; a component and a connection added and one
//! removed are applied without touching a card; a broken deployment changes nothing and
//! the reply lists its errors.
#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::path::Path;
use std::process::{Command, Stdio};
use testkit::pymodbus::PyModbus;
use testkit::{Service, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// The sim card samples its inputs every 10 ms.
const SAMPLE_MS: u64 = 10;

/// The deployment: `poll_ms` of the Modbus card, and `extra` appended.
fn deployment(modbus: &PyModbus, poll_ms: u32, extra: &str) -> String {
    format!(
        r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 5
sample_period_ms = {SAMPLE_MS}
safe_analog_out = [0.0]

[card.sim]
record_capacity = 64

[[card.sim.analog_in]]
range = {{ lowest = -10.0, highest = 10.0, unit = "V" }}
waveform = {{ kind = "ramp", from = -10.0, to = 10.0, period = 4.0 }}

[[card.sim.analog_in]]
range = {{ lowest = -10.0, highest = 10.0, unit = "V" }}
waveform = {{ kind = "sine", amplitude = 5.0, frequency = 0.5 }}

[[card.sim.analog_out]]
range = {{ lowest = -10.0, highest = 10.0, unit = "V" }}

[[card]]
name = "plc"
driver = "modbus"
sample_period_ms = 10
safe_analog_out = [0.0, 0.0]

[card.modbus]
transport = {{ type = "tcp", address = "{}" }}
unit = 1
poll_ms = {poll_ms}
timeout_ms = 500

[[card.modbus.point]]
table = "input_registers"
address = 0
type = "i16"
scale = 0.1

[[card.modbus.point]]
table = "holding_registers"
address = 10

[[card.modbus.point]]
table = "holding_registers"
address = 11

[[component]]
name = "follow"
type = "follow"
activity = {{ type = "non_periodic" }}
properties = {{ gain = 0.001, offset = 0.0 }}

[[connection]]
from = "sim0.ai.ch0"
to = "follow.in"

[[connection]]
from = "follow.out"
to = "plc.ao.ch1"
{extra}"#,
        modbus.addr
    )
}

/// Card `name`'s entry in `status`.
fn card(svc: &Service, name: &str) -> Value {
    let s = svc.ok(json!({"cmd": "status"}));
    s["cards"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == name)
        .unwrap_or_else(|| panic!("no card {name} in {s}"))
        .clone()
}

fn sim_writes(svc: &Service) -> u64 {
    card(svc, "sim0")["counters"]["output_writes"]
        .as_u64()
        .unwrap()
}

fn polls(svc: &Service) -> u64 {
    card(svc, "plc")["counters"]["polls"].as_u64().unwrap()
}

/// Holding register `address` of the pymodbus unit, as mbpoll (a libmodbus master) reads
/// it.
fn holding(modbus: &PyModbus, address: u16) -> String {
    testkit::mbpoll::Mbpoll {
        port: modbus.addr.port(),
        table: "4",
        address,
        count: None,
        write: &[],
    }
    .run()
}

/// Every component's name and state.
fn components(svc: &Service) -> Vec<(String, String)> {
    svc.ok(json!({"cmd": "ls"}))
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let s = |k: &str| c[k].as_str().unwrap().to_string();
            (s("name"), s("state"))
        })
        .collect()
}

/// `hwgw reload` on `svc`: its exit status and what it printed.
fn reload(svc: &Service) -> (bool, String) {
    let out = svc.cli(&["reload"]);
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// The longest gaps between the scheduled starts of activity `topic`'s recorded steps,
/// ns: (among the steps logged inside `window`, UNIX ns, and the step before; among the
/// others).
fn step_gaps(file: &Path, topic: &str, window: (u64, u64)) -> (u64, u64, usize) {
    let d = testkit::mcapread::read(file).unwrap();
    let t = d
        .topics
        .get(topic)
        .unwrap_or_else(|| panic!("no {topic} in the recording: {:?}", d.topics.keys()));
    let steps: Vec<(u64, u64)> = t
        .messages
        .iter()
        .zip(&t.times)
        .map(|(m, &logged)| (logged, m["scheduled_ns"].as_u64().unwrap()))
        .collect();
    let (mut inside, mut outside) = (0, 0);
    for w in steps.windows(2) {
        let gap = w[1].1 - w[0].1;
        if (window.0..=window.1).contains(&w[1].0) {
            inside = inside.max(gap);
        } else {
            outside = outside.max(gap);
        }
    }
    (inside, outside, steps.len())
}

fn unix_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64
}

#[test]
fn reload_rebuilds_what_changed_and_only_that() {
    let modbus = PyModbus::start("tcp");
    let dir = testkit::TempDir::new("reload-files");
    let file = dir.path().join("gw.toml");
    std::fs::write(&file, deployment(&modbus, 10, "")).unwrap();
    let svc = Service::start(HWGW, "reload", &[file.to_str().unwrap()], &[]).unwrap();
    wait_until("the Modbus card polls", || polls(&svc) > 5);
    // An output of each card away from its safe value: the sim card's must stay, the
    // Modbus card's must go to its safe value (0) at the unit when the card is rebuilt.
    svc.out(&["set", "sim0.ao", "ch0", "3"]).unwrap();
    svc.out(&["set", "plc.ao", "ch0", "5"]).unwrap();
    wait_until("the unit holds 5", || {
        holding(&modbus, 10).contains("[10]: \t5")
    });
    let writes = sim_writes(&svc);
    assert_eq!(writes, 1, "the sim card records the write");
    let sim_out = || svc.ok(json!({"cmd": "get", "component": "sim0.ao", "port": "ch0"}));
    let held = sim_out();

    // Only the Modbus card's section changes, while sim0.ai's steps are recorded.
    let rec = dir.path().join("steps.mcap");
    let mut recorder = Command::new(HWGW)
        .args(["record", rec.to_str().unwrap(), "--port", "sim0.ai"])
        .args(["--duration", "3s", "--socket"])
        .arg(&svc.socket)
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    wait_until("the recording file", || rec.exists());
    std::fs::write(&file, deployment(&modbus, 20, "")).unwrap();
    let begun = unix_ns();
    let (ok, said) = reload(&svc);
    let ended = unix_ns();
    assert!(ok, "{said}");
    assert!(said.contains("card \"plc\" rebuilt"), "{said}");
    assert!(!said.contains("sim0"), "the sim card was touched: {said}");
    assert!(recorder.wait().unwrap().success());
    let (inside, outside, steps) = step_gaps(&rec, "/activity/sim0.ai", (begun, ended));
    assert!(steps > 100, "{steps} steps recorded");
    // Two periods at most; on a loaded machine that stalls the thread anyway, no longer
    // than it stalled it outside the reload (the reload adds no pause).
    let period = SAMPLE_MS * 1_000_000;
    eprintln!("longest step gap: {inside} ns during the reload, {outside} ns outside");
    assert!(
        inside <= (2 * period).max(outside),
        "sim0.ai paused {inside} ns during the reload ({outside} ns at most outside)"
    );
    assert_eq!(sim_writes(&svc), writes, "the sim card took a write");
    assert_eq!(sim_out(), held, "the sim card's output moved");
    // At the unit, not just in hwgw: the safe value went over the wire before the old
    // card's bus stopped.
    let reg = holding(&modbus, 10);
    assert!(
        reg.contains("[10]: \t0"),
        "mbpoll sees holding 10 at its safe value 0:\n{reg}"
    );
    let log = svc.log_text();
    assert!(!log.contains("ERROR"), "an error while reloading:\n{log}");
    // The Modbus card is new: stopped as at a stop (its safe value first), and it polls.
    assert!(
        svc.log_text()
            .contains("reload: card \"plc\" outputs at stop: analog [0, "),
        "the safe value first: {}",
        svc.log_text()
    );
    wait_until("the rebuilt Modbus card polls", || polls(&svc) > 3);

    // A component and a connection added, the connection to the Modbus card removed.
    let polls_before = polls(&svc);
    let extra = r#"
[[component]]
name = "twice"
type = "follow"
activity = { type = "non_periodic" }
properties = { gain = 2.0, offset = 0.0 }

[[connection]]
from = "sim0.ai.ch1"
to = "twice.in"
"#;
    // `follow` goes, with both its connections.
    let text = deployment(&modbus, 20, extra)
        .replace(
            "[[component]]\nname = \"follow\"\ntype = \"follow\"\nactivity = { type = \"non_periodic\" }\nproperties = { gain = 0.001, offset = 0.0 }\n",
            "",
        )
        .replace("[[connection]]\nfrom = \"sim0.ai.ch0\"\nto = \"follow.in\"\n", "")
        .replace("[[connection]]\nfrom = \"follow.out\"\nto = \"plc.ao.ch1\"\n", "");
    std::fs::write(&file, &text).unwrap();
    let (ok, said) = reload(&svc);
    assert!(ok, "{said}");
    for line in [
        "component \"twice\" added",
        "component \"follow\" removed",
        "connection sim0.ai.ch1 -> twice.in made",
        "connection follow.out -> plc.ao.ch1 closed",
        "connection sim0.ai.ch0 -> follow.in closed",
    ] {
        assert!(said.contains(line), "{line:?} not in {said}");
    }
    assert!(!said.contains("card"), "a card was touched: {said}");
    let now = components(&svc);
    assert!(now.contains(&("twice".into(), "running".into())), "{now:?}");
    assert!(now.iter().all(|(n, _)| n != "follow"), "{now:?}");
    wait_until("follow's log area gone with it", || {
        !svc.ok(json!({"cmd": "log"}))["areas"]
            .as_array()
            .is_some_and(|a| a.iter().any(|a| a["name"] == "follow"))
    });
    wait_until("twice follows sim0.ai.ch1", || {
        svc.request(json!({"cmd": "get", "component": "twice", "port": "out"}))["ok"]
            .as_f64()
            .is_some_and(|v| v != 0.0)
    });
    assert!(polls(&svc) >= polls_before, "the Modbus card was rebuilt");
    assert_eq!(sim_writes(&svc), writes, "the sim card took a write");

    // A setting only a restart applies is named; the rest is applied all the same.
    let text = format!(
        "control_idle_s = 100.0\n{}",
        text.replace("gain = 2.0", "gain = 3.0")
    );
    std::fs::write(&file, &text).unwrap();
    let (ok, said) = reload(&svc);
    assert!(ok, "{said}");
    assert!(
        said.contains("not applied: control_idle_s changed: restart hwgw to apply"),
        "{said}"
    );
    assert!(said.contains("component \"twice\" rebuilt"), "{said}");
    assert_eq!(
        svc.ok(json!({"cmd": "get", "component": "twice", "property": "gain"})),
        json!(3.0)
    );

    // A broken deployment: nothing changes, the errors are listed.
    let before = components(&svc);
    std::fs::write(&file, text.replace("type = \"follow\"", "type = \"folow\"")).unwrap();
    let (ok, said) = reload(&svc);
    assert!(!ok, "{said}");
    assert!(said.contains("nothing changed"), "{said}");
    assert!(said.contains("unknown component type \"folow\""), "{said}");
    assert!(said.contains("gw.toml:"), "errors are located: {said}");
    assert_eq!(components(&svc), before);
    // Back to the running version: nothing to do.
    std::fs::write(&file, &text).unwrap();
    let (ok, said) = reload(&svc);
    assert!(
        ok && said.trim()
            == "nothing changed\nnot applied: control_idle_s changed: restart hwgw to apply",
        "{said}"
    );
    let stopped = svc.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
}

/// Two sim cards; an alias of the second and a blinker driving it through the alias.
fn aliased(sim1_seed: u32) -> String {
    format!(
        r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 10
[card.sim]
digital_outputs = 4

[[card]]
name = "sim1"
driver = "sim"
period_ms = 10
safe_digital_out_on = []
[card.sim]
seed = {sim1_seed}
digital_outputs = 4

[[alias]]
interface = "digital_out"
name = "lamp"
target = "sim1"

[[alias]]
interface = "digital_out"
name = "lamp2"
target = "lamp"

[[component]]
name = "blink"
type = "blinker"
activity = {{ type = "periodic", period_ms = 20 }}
properties = {{ device = "lamp2", bit = 1 }}
"#
    )
}

#[test]
fn what_uses_a_rebuilt_card_is_made_again_with_it() {
    let dir = testkit::TempDir::new("reload-alias-files");
    let file = dir.path().join("gw.toml");
    std::fs::write(&file, aliased(1)).unwrap();
    let svc = Service::start(HWGW, "reload-alias", &[file.to_str().unwrap()], &[]).unwrap();
    std::fs::write(&file, aliased(2)).unwrap();
    let (ok, said) = reload(&svc);
    assert!(ok, "{said}");
    assert!(said.contains("card \"sim1\" rebuilt"), "{said}");
    assert!(!said.contains("sim0"), "{said}");
    assert!(
        said.contains("component \"blink\" rebuilt (it uses what was rebuilt or removed)"),
        "{said}"
    );
    // The aliases stand for the new card's device again, the alias of the alias too.
    let devices = svc.ok(json!({"cmd": "devices"}));
    for name in ["lamp", "lamp2"] {
        assert!(
            devices
                .as_array()
                .unwrap()
                .iter()
                .any(|d| d["name"] == name && d["interface"] == "digital_out"),
            "{name} not in {devices}"
        );
    }
    // The blinker drives the new card: its bit 1 toggles there.
    let bit = || {
        svc.ok(json!({"cmd": "get", "component": "sim1.do", "port": "bit1"}))
            .as_bool()
            .unwrap()
    };
    let first = bit();
    wait_until("the blinker toggles the rebuilt card", || bit() != first);
    assert!(
        components(&svc).contains(&("blink".into(), "running".into())),
        "{:?}",
        components(&svc)
    );
    let stopped = svc.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
}
