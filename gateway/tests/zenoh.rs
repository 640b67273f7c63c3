//! Two gateways, each in a network namespace of the test's own joined by a veth pair,
//! sharing one name space on Zenoh: A's components drive B's outputs and read B's inputs
//! by name, A's CLI reaches B, and a cut link makes A's view of B stale then offline and
//! puts B's outputs driven from A to their safe values, until the link is back.
//!
//! And the other side of the contract: a deployment without `[zenoh]` opens no network
//! socket at all.

use serde_json::{Value, json};
use std::collections::HashSet;
use std::path::Path;
use std::time::{Duration, Instant};
use testkit::netns::{ADDR_B, Pair};
use testkit::service::{Service, TempDir};
use testkit::wait::{PATIENCE, wait_until};

const BIN: &str = env!("CARGO_BIN_EXE_hwgw");

/// B: the example (a card, a component of its own exported), with analog input 3
/// reading back analog output 1 (so a value A sets is read back by A through B), and
/// listening on its veth address.
fn config_b(listen: &str) -> String {
    include_str!("../../config/zenoh-b.toml")
        .replace("tcp/127.0.0.1:7448", listen)
        .replace(
            "waveform = { kind = \"loopback\", analog_out = 0 }",
            "waveform = { kind = \"loopback\", analog_out = 1 }",
        )
}

/// A: the example, connecting to B's address, its follower fed from B's noise input (so
/// what it drives on B has a known value), a component holding B's analog output 1 at
/// 3.25 (written at every sample of B's input 0), and importing a device B does not have
/// and one of a gateway that never comes (A starts anyway; they stay offline).
fn config_a(connect: &str) -> String {
    let text = include_str!("../../config/zenoh-a.toml")
        .replace("tcp/127.0.0.1:7448", connect)
        .replace("from = \"B/sim0.ai.ch0\"", "from = \"B/sim0.ai.ch2\"");
    format!(
        "{text}\n[[component]]\nname = \"hold\"\ntype = \"follow\"\nactivity = {{ type = \"non_periodic\" }}\n\
         properties = {{ gain = 0.0, offset = 3.25 }}\n\
         [[connection]]\nfrom = \"B/sim0.ai.ch0\"\nto = \"hold.in\"\n\
         [[connection]]\nfrom = \"hold.out\"\nto = \"B/sim0.ao.ch1\"\n\
         [[zenoh.import]]\ngateway = \"B\"\ndevice = \"nosuch\"\ndigital_in = 1\n\
         [[zenoh.import]]\ngateway = \"C\"\ndevice = \"sim0\"\ndigital_in = 4\n"
    )
}

/// B's card's watchdog trips so far.
fn trips(b: &Service) -> u64 {
    let s = b.ok(json!({"cmd": "status"}));
    s["cards"][0]["outputs"]["watchdog_trips"]
        .as_u64()
        .unwrap_or_else(|| panic!("no watchdog_trips in {}", s["cards"]))
}

fn near(v: Value, want: f64) -> bool {
    v.as_f64().is_some_and(|v| (v - want).abs() < 0.001)
}

fn write(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    p.display().to_string()
}

/// `(status, age_s)` of device `name` under `interface` in `svc`'s status.
fn device(svc: &Service, name: &str, interface: &str) -> (String, Option<f64>) {
    let s = svc.ok(json!({"cmd": "status"}));
    let d = s["devices"]
        .as_array()
        .and_then(|a| {
            a.iter()
                .find(|d| d["name"] == name && d["interface"] == interface)
        })
        .unwrap_or_else(|| panic!("no {interface} {name} in {s}"))
        .clone();
    (
        d["status"].as_str().unwrap_or("").to_string(),
        d["age_s"].as_f64(),
    )
}

fn get(svc: &Service, component: &str, port: &str) -> Value {
    svc.ok(json!({"cmd": "get", "component": component, "port": port}))
}

/// Sets `component`'s `port` to `value` from `svc` until the write is acknowledged: a set
/// answers once the remote gateway has the value, or with the error that it failed (a busy
/// machine may delay a write past the request timeout; then it is made again).
fn set_acknowledged(svc: &Service, component: &str, port: &str, value: Value) {
    let req = json!({"cmd": "set", "component": component, "port": port, "value": value});
    let mut last = Value::Null;
    let done = testkit::wait::wait_for(&format!("{req} acknowledged"), PATIENCE, || {
        last = svc.request(req.clone());
        last.get("ok").is_some()
    });
    if let Err(e) = done {
        panic!("{e}: the last answer was {last}");
    }
}

fn state(svc: &Service, component: &str) -> String {
    let list = svc.ok(json!({"cmd": "ls"}));
    list.as_array()
        .and_then(|a| a.iter().find(|c| c["name"] == component))
        .and_then(|c| c["state"].as_str())
        .unwrap_or_else(|| panic!("no component {component} in {list}"))
        .to_string()
}

#[test]
fn two_gateways_share_devices_by_name_and_survive_a_cut_link() {
    let net = Pair::new("zn").unwrap_or_else(|e| panic!("{e}"));
    let dir = TempDir::new("zenoh-pair");
    let endpoint = format!("tcp/{ADDR_B}:7448");
    let b_file = write(dir.path(), "b.toml", &config_b(&endpoint));
    let a_file = write(dir.path(), "a.toml", &config_a(&endpoint));
    let b = Service::start_in(&net.exec_b(), BIN, "zenoh-b", &[&b_file], &[])
        .unwrap_or_else(|e| panic!("{e}"));
    let a = Service::start_in(&net.exec_a(), BIN, "zenoh-a", &[&a_file], &[])
        .unwrap_or_else(|e| panic!("{e}"));

    // B's devices come online in A, each with its age.
    wait_until("B/sim0 online in A", || {
        Interface::ALL
            .iter()
            .all(|i| device(&a, "B/sim0", i).0 == "online")
    });
    let (_, age) = device(&a, "B/sim0", "analog_in");
    let age = age.unwrap_or_else(|| panic!("an online remote device has an age"));
    assert!(age > 0.0 && age < 0.5, "age {age} s");

    // A value a component of A holds on B's analog output 1 is read back, equal, by A
    // through B's input 3 and B's read-back, and by B itself (the same raw value on both
    // sides: the same scale).
    wait_until("B's analog output 1 at A's value", || {
        near(get(&b, "sim0.ao", "ch1"), 3.25)
    });
    let on_b = get(&b, "sim0.ao", "ch1");
    wait_until("A reads B's input 3 equal to B's", || {
        get(&a, "B/sim0.ai", "ch3") == get(&b, "sim0.ai", "ch3")
    });
    wait_until("A's read-back of B's output 1 equal to B's", || {
        get(&a, "B/sim0.ao", "ch1") == on_b
    });

    // A's follower drives B's analog output 0 from B's noise input (1 V ± 0.05, gain 0.5).
    wait_until("A's follower drives B's output 0", || {
        get(&b, "sim0.ao", "ch0")
            .as_f64()
            .is_some_and(|v| (v - 0.5).abs() < 0.05)
    });
    // A value set once from A is written once: B's watchdog takes it back to its safe
    // value, as it would a value set once on B (never written again when nobody asks).
    let before = trips(&b);
    set_acknowledged(&a, "B/sim0.do", "bit3", json!(true));
    wait_until("B's bit 3 set from A", || {
        get(&b, "sim0.do", "bit3") == json!(true)
    });
    wait_until("B's bit 3 back to safe", || {
        get(&b, "sim0.do", "bit3") == json!(false)
    });
    assert!(trips(&b) > before);
    // A's blinker toggles B's digital output 15: B sees both values.
    let mut seen = HashSet::new();
    wait_until("B's bit 15 toggled by A", || {
        seen.insert(get(&b, "sim0.do", "bit15").to_string());
        seen.len() == 2
    });

    // A's CLI reaches B: a component only B has, and every gateway's components.
    let half = a
        .out(&["get", "B/half", "out"])
        .unwrap_or_else(|e| panic!("{e}"));
    let half: f64 = half.parse().unwrap_or_else(|e| panic!("{half:?}: {e}"));
    assert!((half - 0.5).abs() < 0.05, "B/half.out through A: {half}");
    // B's exported port feeds A's mirror through its connection, every sample counted.
    wait_until("B/half.out mirrored on A", || {
        get(&a, "mirror", "out")
            .as_f64()
            .is_some_and(|v| (v - 0.5).abs() < 0.05)
    });
    // (Samples are published with Zenoh's drop-on-congestion: a batch lost on a loaded
    // host is counted, not hidden.)
    let s = a.ok(json!({"cmd": "status"}));
    let links = s["servers"][0]["counters"]["links"].to_string();
    let received: u64 = links
        .split("mirror.in: ")
        .nth(1)
        .and_then(|r| r.split(' ').next()?.parse().ok())
        .unwrap_or(0);
    assert!(received > 0 && links.contains(", 0 refused"), "{links}");
    // A's own components under its own name too, as ls --all lists them.
    assert_eq!(a.out(&["get", "A/mirror", "out"]).map(|_| ()), Ok(()));
    let mut all = String::new();
    let listed =
        testkit::wait::wait_for("every gateway's components in ls --all", PATIENCE, || {
            all = a.out(&["ls", "--all"]).unwrap_or_else(|e| e);
            ["A/follow", "A/B/sim0.ao", "B/half", "B/output_watchdog"]
                .iter()
                .all(|name| all.contains(name))
        });
    if let Err(e) = listed {
        panic!("{e}:\n{all}\nA's log:\n{}", a.log_text());
    }
    let missing = a.cli(&["get", "B/nosuch", "out"]);
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(
        !missing.status.success() && err.contains("B: ") && err.contains("nosuch"),
        "{err}"
    );

    // What does not match B, or never comes, stays offline and says why.
    assert_eq!(device(&a, "B/nosuch", "digital_in").0, "offline");
    assert_eq!(device(&a, "C/sim0", "digital_in").0, "offline");
    wait_until("A logs B has no nosuch", || {
        a.log_text()
            .contains("gateway B has no digital_in device \"nosuch\"")
    });

    // The link cut: A sees B stale, then offline; A's components keep running.
    let trips_before = trips(&b);
    let cut = Instant::now();
    net.link(false).unwrap_or_else(|e| panic!("{e}"));
    let mut saw = Vec::new();
    wait_until("B/sim0 offline in A", || {
        let s = device(&a, "B/sim0", "analog_in").0;
        if saw.last() != Some(&s) {
            saw.push(s.clone());
        }
        s == "offline"
    });
    // (A late sample may bring it back for a moment; stale always comes before offline.)
    let first_stale = saw.iter().position(|s| s == "stale");
    assert!(
        saw[0] == "online" && first_stale.is_some_and(|i| i + 1 < saw.len()),
        "A's view of B after the cut: {saw:?}"
    );
    let offline_after = cut.elapsed();
    assert!(
        offline_after >= Duration::from_millis(900),
        "offline after {offline_after:?}: offline_ms is 1000"
    );
    assert_eq!(state(&a, "follow"), "running");
    assert!(["running", "run_time_error"].contains(&state(&a, "blink").as_str()));

    // B's outputs driven from A go to their safe values once B's watchdog expires.
    wait_until("B's outputs at their safe values", || {
        near(get(&b, "sim0.ao", "ch0"), 0.0)
            && near(get(&b, "sim0.ao", "ch1"), 0.0)
            && get(&b, "sim0.do", "bit15") == json!(false)
    });
    assert!(trips(&b) >= trips_before + 2, "B's watchdog tripped");

    // Zenoh itself gives the link up once its lease (2 s) runs out with no word.
    wait_until("A's session to B closed", || {
        let s = a.ok(json!({"cmd": "status"}));
        s["servers"][0]["counters"]["peers"] == json!([])
    });

    // The link back: everything resumes without a restart, as A's components write again.
    net.link(true).unwrap_or_else(|e| panic!("{e}"));
    wait_until("B/sim0 online again in A", || {
        device(&a, "B/sim0", "analog_in").0 == "online"
    });
    wait_until("A's value back on B", || {
        near(get(&b, "sim0.ao", "ch1"), 3.25)
    });
    wait_until("A's follower drives B again", || {
        get(&b, "sim0.ao", "ch0")
            .as_f64()
            .is_some_and(|v| (v - 0.5).abs() < 0.05)
    });

    // A stopped: nothing writes B's outputs any more, and B's watchdog takes them safe.
    assert_eq!(
        get(&b, "sim0.do", "bit3"),
        json!(false),
        "never written again"
    );
    let stopped = a.terminate();
    assert!(stopped.status.success(), "A: {}", stopped.log);
    wait_until("B's outputs safe once A stopped", || {
        near(get(&b, "sim0.ao", "ch0"), 0.0) && near(get(&b, "sim0.ao", "ch1"), 0.0)
    });
    let stopped = b.terminate();
    assert!(stopped.status.success(), "B: {}", stopped.log);
}

/// The interfaces as `status` names them.
struct Interface;
impl Interface {
    const ALL: [&'static str; 4] = ["analog_in", "analog_out", "digital_in", "digital_out"];
}

/// The inodes of the network sockets of process `pid` (TCP, UDP, raw, over IPv4 and IPv6):
/// those of its descriptors that its network namespace's tables list.
fn network_sockets(pid: u32) -> Vec<String> {
    let fds = std::fs::read_dir(format!("/proc/{pid}/fd"))
        .unwrap_or_else(|e| panic!("/proc/{pid}/fd: {e}"));
    let sockets: HashSet<String> = fds
        .filter_map(|e| std::fs::read_link(e.ok()?.path()).ok())
        .filter_map(|l| {
            let l = l.display().to_string();
            Some(l.strip_prefix("socket:[")?.strip_suffix(']')?.to_string())
        })
        .collect();
    assert!(!sockets.is_empty(), "hwgw has its control socket at least");
    let mut out = Vec::new();
    for table in ["tcp", "tcp6", "udp", "udp6", "raw", "raw6"] {
        let text = std::fs::read_to_string(format!("/proc/{pid}/net/{table}")).unwrap_or_default();
        for line in text.lines().skip(1) {
            // The inode is the tenth column.
            if let Some(inode) = line.split_whitespace().nth(9)
                && sockets.contains(inode)
            {
                out.push(format!("{table}: {}", line.trim()));
            }
        }
    }
    out
}

#[test]
fn a_deployment_without_zenoh_opens_no_network_socket() {
    // The embedded default, running: Unix sockets only.
    let svc =
        Service::start(BIN, "zenoh-none", &[] as &[&str], &[]).unwrap_or_else(|e| panic!("{e}"));
    let pid = svc.pid().unwrap_or_else(|| panic!("no pid"));
    wait_until("the demo running", || state(&svc, "blink") == "running");
    let open = network_sockets(pid);
    assert!(open.is_empty(), "without [zenoh]: {open:#?}");
    drop(svc);

    // The same check sees the socket of a deployment with [zenoh] (so it can fail).
    let dir = TempDir::new("zenoh-one");
    let file = write(
        dir.path(),
        "z.toml",
        "[zenoh]\nname = \"solo\"\nlisten = [\"tcp/127.0.0.1:0\"]\n",
    );
    let svc = Service::start(BIN, "zenoh-one-run", &[&file], &[]).unwrap_or_else(|e| panic!("{e}"));
    let pid = svc.pid().unwrap_or_else(|| panic!("no pid"));
    let end = Instant::now() + PATIENCE;
    while network_sockets(pid).is_empty() {
        assert!(Instant::now() < end, "no TCP socket with [zenoh]");
        std::thread::sleep(Duration::from_millis(10));
    }
    let open = network_sockets(pid);
    assert!(
        open.iter().all(|l| l.starts_with("tcp")),
        "only TCP on loopback with [zenoh] listen = tcp/127.0.0.1:0 and no scouting: {open:#?}"
    );
}

/// `[zenoh]` of example `text` with its endpoint line replaced by `endpoint` and `tls`
/// added.
fn over_tls(text: &str, line: &str, endpoint: &str, tls: &str) -> String {
    let old = text
        .lines()
        .find(|l| l.starts_with(line))
        .unwrap_or_else(|| panic!("no {line} line"));
    text.replacen(old, &format!("{line} = [\"{endpoint}\"]\ntls = {tls}"), 1)
}

#[test]
fn gateways_meet_over_tls_and_a_stranger_is_refused() {
    let dir = TempDir::new("zenoh-tls");
    let d = dir.path();
    // A CA, B's certificate signed by it (for 127.0.0.1), and a CA that signed nothing
    // of B's.
    let certs = testkit::certs::Certs::make();
    let file = |name: &str| certs.path(name).display().to_string();
    let endpoint = format!("tls/127.0.0.1:{}", testkit::free_port());
    let b_text = over_tls(
        include_str!("../../config/zenoh-b.toml"),
        "listen",
        &endpoint,
        &format!(
            "{{ root_ca = \"{}\", cert = \"{}\", key = \"{}\" }}",
            file("ca.pem"),
            file("server.pem"),
            file("server.key")
        ),
    );
    let a_text = over_tls(
        include_str!("../../config/zenoh-a.toml"),
        "connect",
        &endpoint,
        &format!("{{ root_ca = \"{}\" }}", file("ca.pem")),
    );
    let stranger = over_tls(
        include_str!("../../config/zenoh-a.toml"),
        "connect",
        &endpoint,
        &format!("{{ root_ca = \"{}\" }}", file("other-ca.pem")),
    )
    .replace("name = \"A\"", "name = \"S\"");
    let b_file = write(d, "b.toml", &b_text);
    let a_file = write(d, "a.toml", &a_text);
    let s_file = write(d, "s.toml", &stranger);
    let b = Service::start(BIN, "zenoh-tls-b", &[&b_file], &[]).unwrap_or_else(|e| panic!("{e}"));
    // Zenoh retries in the background and says why at debug level.
    let debug = [("RUST_LOG", "info,zenoh::net::runtime::orchestrator=debug")];
    let s =
        Service::start(BIN, "zenoh-tls-s", &[&s_file], &debug).unwrap_or_else(|e| panic!("{e}"));
    let a = Service::start(BIN, "zenoh-tls-a", &[&a_file], &[]).unwrap_or_else(|e| panic!("{e}"));
    wait_until("B/sim0 online in A over TLS", || {
        device(&a, "B/sim0", "analog_in").0 == "online"
    });
    // A write is acknowledged once B has it, or A says it failed: then it is made again
    // (a busy machine may delay the first past the request timeout).
    set_acknowledged(&a, "B/sim0.ao", "ch1", json!(-2.5));
    wait_until("B's analog output 1 at A's value", || {
        get(&b, "sim0.ao", "ch1")
            .as_f64()
            .is_some_and(|v| (v + 2.5).abs() < 0.001)
    });
    // The stranger, trusting another CA, has had as long as A and retries every second:
    // B's certificate is refused, so it has no peer and B's devices stay offline there.
    let tried = Instant::now();
    while tried.elapsed() < Duration::from_secs(3) {
        let st = s.ok(json!({"cmd": "status"}));
        assert_eq!(
            st["servers"][0]["counters"]["peers"],
            json!([]),
            "the stranger got through"
        );
        assert_eq!(device(&s, "B/sim0", "analog_in").0, "offline");
        std::thread::sleep(Duration::from_millis(100));
    }
    let refused = testkit::wait::wait_for(
        "the stranger's log naming the refused certificate",
        PATIENCE,
        || s.log_text().contains("UnknownIssuer"),
    );
    if let Err(e) = refused {
        panic!("{e}: {}", s.log_text());
    }
}
