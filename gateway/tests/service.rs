//! The real `hwgw` binary, over its real control socket: values flowing, one-shot
//! commands, robustness against bad clients, and a SIGTERM that leaves safe outputs.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};
use testkit::wait_until;
use testkit::{Service, TempDir};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// `hwgw run` on the embedded default (or `config`), on a socket of its own.
fn start(tag: &str, config: Option<&Path>) -> Service {
    start_with(tag, config, &[])
}

/// As [`start`], with extra environment variables.
fn start_with(tag: &str, config: Option<&Path>, env: &[(&str, &str)]) -> Service {
    let args: Vec<&Path> = config.into_iter().collect();
    Service::start(HWGW, tag, &args, env).unwrap()
}

#[test]
fn values_flow_and_sigterm_leaves_outputs_safe() {
    let svc = start("flow", None);
    let names: Vec<String> = svc
        .ok(json!({"cmd": "ls"}))
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["name"].as_str().unwrap().to_string())
        .collect();
    for want in [
        "sim0",
        "sim0.ai",
        "sim0.ao",
        "sim0.di",
        "sim0.do",
        "sim0.encoder0",
        "follow",
        "blink",
    ] {
        assert!(
            names.contains(&want.to_string()),
            "{want} missing from {names:?}"
        );
    }
    // A sim input flows through the follow component to the analog output.
    wait_until("follow wrote", || {
        svc.ok(json!({"cmd": "get", "component": "follow", "port": "out"})) != Value::Null
    });
    let mut matched = 0;
    for _ in 0..50 {
        let out = svc
            .ok(json!({"cmd": "get", "component": "follow", "port": "out"}))
            .as_f64()
            .unwrap();
        let back = svc.ok(
            json!({"cmd": "call", "component": "sim0.ao", "operation": "read_back", "args": [0]}),
        )["Ok"]
            .as_f64()
            .unwrap();
        // Equal up to one 16-bit step over 20 V, unless a sample arrived between the reads.
        if (out - back).abs() <= 20.0 / 65535.0 {
            matched += 1;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(
        matched >= 25,
        "follow.out and the analog output agreed only {matched} of 50 times"
    );
    let follow_in = svc.ok(json!({"cmd": "describe", "component": "follow"}));
    assert_eq!(follow_in["properties"][0]["path"], "gain");

    // Set an output through the socket and see it loop back into an input.
    svc.ok(json!({"cmd": "set", "component": "sim0.do", "port": "bit12", "value": true}));
    wait_until("DO 12 loops back to DI 12", || {
        svc.ok(json!({"cmd": "get", "component": "sim0.di", "port": "bit12"})) == json!(true)
    });
    // One-shot CLI forms, printed for people: `call` prints the value, not `{"Ok": …}`
    // (`--json` keeps the gateway's answer); an operation answering nothing prints nothing.
    let stdout = |out: &std::process::Output| String::from_utf8_lossy(&out.stdout).to_string();
    let out = svc.cli(&["call", "sim0.do", "check_bit", "12"]);
    assert!(out.status.success(), "{out:?}");
    assert_eq!(stdout(&out).trim(), "true");
    let out = svc.cli(&["--json", "call", "sim0.do", "check_bit", "12"]);
    assert_eq!(
        serde_json::from_str::<Value>(&stdout(&out)).unwrap(),
        json!({"Ok": true})
    );
    let out = svc.cli(&["call", "sim0.do", "set_bit", "11", "true"]);
    assert!(out.status.success(), "{out:?}");
    assert_eq!(stdout(&out), "", "a write prints nothing");
    let out = svc.cli(&["call", "sim0.do", "check_bit", "99"]);
    assert!(!out.status.success(), "{out:?}");
    assert!(stdout(&out).is_empty(), "{out:?}");
    assert!(
        String::from_utf8_lossy(&out.stderr).starts_with("hwgw: sim0.do.check_bit: "),
        "{out:?}"
    );
    // `set` prints nothing, or one line with -v.
    let out = svc.cli(&["set", "sim0.do", "bit11", "false"]);
    assert!(out.status.success() && out.stdout.is_empty(), "{out:?}");
    let out = svc.cli(&["-v", "set", "sim0.do", "bit11", "true"]);
    assert_eq!(stdout(&out), "sim0.do.bit11 = true\n", "{out:?}");
    // Operation signatures in the protocol's types, never Rust paths.
    let ls = stdout(&svc.cli(&["ls", "sim0.ao"]));
    for want in [
        "read_back(channel: u32) -> f64",
        "write(channel: u32, value: f64)  ",
        "health() -> (string, f64?, string?)",
    ] {
        assert!(ls.contains(want), "{want:?} not in:\n{ls}");
    }
    assert!(!ls.contains("::"), "a Rust path in:\n{ls}");
    let out = svc.cli(&["get", "follow", "property:gain"]);
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "0.5");
    let out = svc.cli(&["set", "follow", "property:gain", "0.25"]);
    assert!(out.status.success());
    assert_eq!(
        svc.ok(json!({"cmd": "get", "component": "follow", "property": "gain"})),
        json!(0.25)
    );
    let out = svc.cli(&["get", "follow", "nope"]);
    assert!(!out.status.success());
    assert_eq!(
        String::from_utf8_lossy(&out.stderr).trim(),
        "hwgw: \"follow\" has no port \"nope\"; it has: in, out"
    );

    let out = svc.terminate();
    assert!(out.status.success(), "exit status {:?}", out.status);
    let log = out.log.clone();
    // 0 V is not a 16-bit step of -10..10 V: the nearest one is 0.000153 V.
    assert!(
        log.contains("card \"sim0\" outputs at stop: analog [0.00015259021896696368, 0.00015259021896696368], digital on []"),
        "{log}"
    );
    assert!(
        log.contains("SIGTERM: stopping") && log.contains("stopped"),
        "{log}"
    );
    // A clean stop is no error: writes refused because the outputs are held are not
    // failures (the blinker's, the follow loop's).
    assert!(!log.contains(" ERROR "), "{log}");
}

#[test]
fn the_socket_survives_bad_clients() {
    let svc = start("robust", None);
    let mut c = UnixStream::connect(&svc.socket).unwrap();
    let mut r = BufReader::new(c.try_clone().unwrap());
    let mut ask = |text: &[u8]| -> Value {
        c.write_all(text).unwrap();
        let mut line = String::new();
        r.read_line(&mut line).unwrap();
        serde_json::from_str(&line).unwrap()
    };
    let e = ask(b"{not json\n");
    assert_eq!(e["error"]["kind"], "parse");
    let e = ask(b"{\"id\": 7, \"cmd\": \"explode\"}\n");
    assert_eq!(
        (e["id"].clone(), e["error"]["kind"].clone()),
        (json!(7), json!("unknown_command"))
    );
    let e = ask(b"{\"id\": 8, \"cmd\": \"get\"}\n");
    assert_eq!(e["error"]["kind"], "bad_request");
    let e = ask(b"{\"id\": 9, \"cmd\": \"call\", \"component\": \"sim0.ao\", \"operation\": \"write\", \"args\": [0, \"high\"]}\n");
    assert_eq!(e["error"]["kind"], "failed");
    let mut huge = vec![b'x'; 200_000];
    huge.push(b'\n');
    let e = ask(&huge);
    assert_eq!(e["error"]["kind"], "too_long");
    // The same connection still works after all that.
    let ok = ask(b"{\"id\": 10, \"cmd\": \"ls\"}\n");
    assert_eq!(ok["id"], 10);
    assert!(ok["ok"].is_array());

    // A client that disconnects mid-request.
    let connected = || {
        svc.ok(json!({"cmd": "status"}))["control"]["connected"]
            .as_u64()
            .unwrap()
    };
    let before = connected();
    for _ in 0..20 {
        let mut half = UnixStream::connect(&svc.socket).unwrap();
        half.write_all(b"{\"id\": 1, \"cmd\": \"l").unwrap();
        drop(half);
    }
    // Gone once the server saw them go: until then they count against its 64 clients, and
    // the 50 below would be turned away as busy on a loaded machine.
    wait_until("the half clients closed", || connected() <= before);

    // 50 concurrent clients, 20 requests each.
    let start = Instant::now();
    let clients: Vec<_> = (0..50)
        .map(|i| {
            let socket = svc.socket.clone();
            std::thread::spawn(move || {
                let mut c = UnixStream::connect(&socket).unwrap();
                let mut r = BufReader::new(c.try_clone().unwrap());
                for n in 0..20 {
                    let id = i * 100 + n;
                    c.write_all(format!("{{\"id\": {id}, \"cmd\": \"get\", \"component\": \"sim0.ai\", \"port\": \"ch0\"}}\n").as_bytes()).unwrap();
                    let mut line = String::new();
                    r.read_line(&mut line).unwrap();
                    let v: Value = serde_json::from_str(&line).unwrap();
                    assert_eq!(v["id"], id);
                    assert!(v["ok"].is_f64(), "{v}");
                }
            })
        })
        .collect();
    for c in clients {
        c.join().unwrap();
    }
    let elapsed = start.elapsed();
    eprintln!(
        "50 clients x 20 requests answered in {elapsed:?} ({:.0} requests/s)",
        1000.0 / elapsed.as_secs_f64()
    );
    assert!(svc.ok(json!({"cmd": "ls"})).is_array(), "still serving");
    let out = svc.terminate();
    assert!(out.status.success());
}

#[test]
fn check_accepts_the_demo_and_reports_every_error() {
    let demo = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/demo.toml");
    let out = Command::new(HWGW).args(["check", demo]).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains(": ok"));

    let dir = TempDir::new("check");
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "[[card]]\nname = \"x\"\ndriver = \"sim\"\n[card.sim]\n[[alias]]\ninterface = \"encoder\"\nname = \"e\"\ntarget = \"none\"\n[[component]]\nname = \"c\"\ntype = \"nope\"\nactivity = { type = \"non_periodic\" }\n").unwrap();
    let out = Command::new(HWGW)
        .args(["check"])
        .arg(&bad)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    let lines: Vec<&str> = err.lines().filter(|l| l.contains("bad.toml:")).collect();
    assert_eq!(lines.len(), 2, "both problems reported: {err}");
    assert!(
        lines[0].ends_with("bad.toml:5:1: alias[0]: no Encoder named \"none\"; registered: none"),
        "{err}"
    );
    assert!(lines[1].ends_with("bad.toml:11:8: component[0].type: unknown component type \"nope\"; this build has: blinker, follow, recorder, reporter, scan, script"), "{err}");

    let out = Command::new(HWGW)
        .args(["check", "/nonexistent.toml"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent.toml: cannot read"));
}

#[test]
fn a_second_gateway_on_the_same_socket_is_refused() {
    let svc = start("twice", None);
    let out = Command::new(HWGW)
        .args(["run", "--socket"])
        .arg(&svc.socket)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("another hwgw is serving this socket"));
    assert!(
        svc.ok(json!({"cmd": "ls"})).is_array(),
        "the first one still serves"
    );
}

/// A client pointed at something that is not a socket says so, not "connection refused
/// (is hwgw running?)": the file is named as what it is.
#[test]
fn a_client_socket_that_is_no_socket_is_named() {
    let dir = TempDir::new("not-a-socket");
    let file = dir.path().join("hwgw.sock");
    std::fs::write(&file, "not a socket").unwrap();
    for (path, kind) in [
        (file.as_path(), "a regular file"),
        (dir.path(), "a directory"),
    ] {
        let out = Command::new(HWGW)
            .arg("--socket")
            .arg(path)
            .arg("ls")
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(1), "{out:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains(&format!(
                "{} is not a socket (it is {kind}): give the control socket of a running hwgw",
                path.display()
            )),
            "{err}"
        );
        assert!(!err.contains("Connection refused"), "{err}");
    }
    // A stale socket is still "not running".
    let stale = dir.path().join("stale.sock");
    drop(std::os::unix::net::UnixListener::bind(&stale).unwrap());
    let out = Command::new(HWGW)
        .arg("--socket")
        .arg(&stale)
        .arg("ls")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("is hwgw running?"), "{err}");
    assert_eq!(
        std::fs::read_to_string(&file).unwrap(),
        "not a socket",
        "left as it was"
    );
}

/// A datagram socket standing in for systemd's notify socket.
struct Notify {
    sock: std::os::unix::net::UnixDatagram,
    path: PathBuf,
    _dir: TempDir,
}

impl Notify {
    fn new(tag: &str) -> Notify {
        let dir = TempDir::new(tag);
        let path = dir.path().join("notify.sock");
        let sock = std::os::unix::net::UnixDatagram::bind(&path).unwrap();
        sock.set_read_timeout(Some(Duration::from_millis(100)))
            .unwrap();
        Notify {
            sock,
            path,
            _dir: dir,
        }
    }

    /// Messages received within `d`.
    fn collect(&self, d: Duration) -> Vec<String> {
        self.collect_until(d, |_| false)
            .into_iter()
            .map(|(_, m)| m)
            .collect()
    }

    /// Messages with the times they came, until `done` says so of those so far or `d` has
    /// passed.
    fn collect_until(
        &self,
        d: Duration,
        mut done: impl FnMut(&[(Instant, String)]) -> bool,
    ) -> Vec<(Instant, String)> {
        let end = Instant::now() + d;
        let mut out = Vec::new();
        let mut buf = [0u8; 4096];
        while Instant::now() < end && !done(&out) {
            if let Ok(n) = self.sock.recv(&mut buf) {
                out.push((
                    Instant::now(),
                    String::from_utf8_lossy(&buf[..n]).to_string(),
                ));
            }
        }
        out
    }
}

/// A deployment (in its directory, and its file) whose blinker `name` overruns its 1 µs
/// period on purpose, started with the gateway when `start`.
fn overrunning(tag: &str, name: &str, start: bool) -> (TempDir, PathBuf) {
    let dir = TempDir::new(&format!("{tag}-cfg"));
    let cfg = dir.path().join(format!("{tag}.toml"));
    std::fs::write(
        &cfg,
        format!(
            "[[card]]\nname = \"sim0\"\ndriver = \"sim\"\n[card.sim]\ndigital_outputs = 4\n\
             [[component]]\nname = \"{name}\"\ntype = \"blinker\"\n\
             activity = {{ type = \"periodic\", period_ms = 0.001, max_overruns = 1 }}\n\
             properties = {{ device = \"sim0\", bit = 0 }}\nstart = {start}\n"
        ),
    )
    .unwrap();
    (dir, cfg)
}

/// A deployment (in its directory, and its file) of one script component `name` running
/// `lua` every 10 ms with no step budget, unhealthy after `max_overruns`.
fn script(name: &str, lua: &str, max_overruns: u32) -> (TempDir, PathBuf) {
    let dir = TempDir::new(&format!("{name}-cfg"));
    std::fs::write(dir.path().join(format!("{name}.lua")), lua).unwrap();
    let cfg = dir.path().join(format!("{name}.toml"));
    std::fs::write(
        &cfg,
        format!(
            "[[component]]\nname = \"{name}\"\ntype = \"script\"\n\
             activity = {{ type = \"periodic\", period_ms = 10, max_overruns = {max_overruns} }}\n\
             properties = {{ file = \"{name}.lua\", max_step_us = 0 }}\n"
        ),
    )
    .unwrap();
    (dir, cfg)
}

/// Overrunning for a look — a component that overruns on purpose, stopped as soon as a
/// look of the watchdog saw it overrunning for at least half the time since the look
/// before — costs the gateway a feed of the watchdog (two when the stop comes after the
/// next look), not a restart: with looks four times an interval, the feeds around the
/// spell stay at most three quarters of an interval apart (at a look every half interval
/// they were a whole interval apart, and systemd restarted hwgw when the next look came a
/// little late), and they go on.
#[test]
fn overrunning_for_a_look_costs_a_watchdog_feed_not_a_restart() {
    let (_dir, cfg) = overrunning("spell", "stall", false);
    let notify = Notify::new("notify-spell");
    let interval = Duration::from_secs(2);
    let svc = start_with(
        "spell",
        Some(&cfg),
        &[
            ("NOTIFY_SOCKET", notify.path.to_str().unwrap()),
            ("WATCHDOG_USEC", &interval.as_micros().to_string()),
        ],
    );
    let fed = |m: &str| m.contains("WATCHDOG=1");
    let spell = |m: &str| m.contains("STATUS=unhealthy: stall overruns its period");
    let (seen_tx, seen) = std::sync::mpsc::channel();
    let msgs = std::thread::scope(|s| {
        // Until three feeds after the look that saw the spell, or 30 s.
        let collector = s.spawn(|| {
            notify.collect_until(Duration::from_secs(30), |msgs| {
                let Some(i) = msgs.iter().position(|(_, m)| spell(m)) else {
                    return false;
                };
                let _ = seen_tx.send(());
                msgs[i..].iter().filter(|(_, m)| fed(m)).count() >= 3
            })
        });
        svc.ok(json!({"cmd": "start", "component": "stall"}));
        let told = seen.recv_timeout(Duration::from_secs(20));
        svc.ok(json!({"cmd": "stop", "component": "stall"}));
        told.expect("no look of the watchdog saw the spell in 20 s");
        collector.join().unwrap()
    });
    let at = msgs.iter().position(|(_, m)| spell(m)).unwrap();
    let after = msgs[at..].iter().filter(|(_, m)| fed(m)).count();
    assert!(after >= 3, "the feeds did not go on: {msgs:?}");
    let feeds: Vec<Instant> = msgs
        .iter()
        .filter(|(_, m)| fed(m))
        .map(|(t, _)| *t)
        .collect();
    let longest = feeds
        .windows(2)
        .map(|w| w[1] - w[0])
        .max()
        .unwrap_or_default();
    // Half an interval with one feed withheld, three quarters with two (when the stop
    // came after the next look: the stall takes a core of a loaded machine), and an
    // eighth left for a look that comes late. At a look every half interval the gap was
    // the whole interval, and one late look got hwgw restarted.
    assert!(
        longest <= interval * 7 / 8,
        "{longest:?} without a feed at an interval of {interval:?}: a late look and systemd \
         restarts hwgw"
    );
    assert!(svc.terminate().status.success());
}

/// Moments of overrun in a component that runs on — three spells, each a step of a
/// script held up until the test lets it go (an overrun, and with `max_overruns = 0` a
/// spell) — cost no feed of the watchdog: each is far shorter than half the time between
/// two looks, and a look judges that time, not the moment it is taken. A look that
/// withholds its feed says why in STATUS, and none does after the first feed (the first
/// look judges the moment it is taken: a start on a loaded machine may cost it). (Seen in
/// the kernel rig before: three short spells of the demo's activities while apt ran, each
/// seen by a look, withheld three feeds in a row and systemd restarted hwgw.) The spells
/// are counted, and logged by the activity's thread; a loaded machine may add spells of
/// its own (a wake-up more than a period late), never fewer.
#[test]
fn moments_of_overrun_cost_no_watchdog_feed() {
    // `held` counts the steps held up, written before the hold.
    let (_dir, cfg) = script(
        "busy",
        "local hold = port.input(\"hold\", \"bool\")\n\
         local held = port.output(\"held\", \"i64\")\n\
         local n = 0\n\
         function update()\n  if hold:read() then\n    n = n + 1\n    held:write(n)\n\
         \x20   while hold:read() do end\n  end\nend\n",
        0,
    );
    let notify = Notify::new("notify-moments");
    // Looks every 2 s: a spell costs a feed only when it takes 1 s of the 2.
    let svc = start_with(
        "moments",
        Some(&cfg),
        &[
            ("NOTIFY_SOCKET", notify.path.to_str().unwrap()),
            ("WATCHDOG_USEC", "8000000"),
        ],
    );
    let fed = |m: &str| m.contains("WATCHDOG=1");
    let activity = || svc.ok(json!({"cmd": "describe", "component": "busy"}))["activity"].take();
    let spells = || activity()["unhealthy_spells"].as_u64().unwrap();
    let held = || {
        svc.ok(json!({"cmd": "get", "component": "busy", "port": "held"}))
            .as_i64()
            .unwrap_or(0)
    };
    let hold = |on: &str| {
        let out = svc.cli(&["set", "busy", "hold", on]);
        assert!(out.status.success(), "{out:?}");
    };
    let msgs = std::thread::scope(|s| {
        let (spells_tx, spells_done) = std::sync::mpsc::channel();
        let (first_tx, first_fed) = std::sync::mpsc::channel();
        let collector = s.spawn(move || {
            // Until two feeds after the last spell, or 60 s.
            let mut done_at = None;
            notify.collect_until(Duration::from_secs(60), |msgs| {
                if msgs.iter().any(|(_, m)| fed(m)) {
                    let _ = first_tx.send(());
                }
                if done_at.is_none() && spells_done.try_recv().is_ok() {
                    done_at = Some(msgs.len());
                }
                done_at.is_some_and(|i| msgs[i..].iter().filter(|(_, m)| fed(m)).count() >= 2)
            })
        });
        first_fed
            .recv_timeout(Duration::from_secs(20))
            .expect("no feed in 20 s");
        for n in 1..=3i64 {
            let before = spells();
            hold("true");
            wait_until("a step held up", || held() == n);
            // Held for three periods: only "false" lets it go, so it overruns.
            std::thread::sleep(Duration::from_millis(30));
            hold("false");
            // Over before the next hold: a step held again before one on time would
            // keep this spell on, not start another.
            wait_until("the spell, then health back", || {
                let a = activity();
                a["unhealthy_spells"].as_u64().unwrap() > before && a["healthy"] == true
            });
        }
        spells_tx.send(()).unwrap();
        collector.join().unwrap()
    });
    let first = msgs.iter().position(|(_, m)| fed(m)).unwrap();
    let withheld: Vec<_> = msgs[first..]
        .iter()
        .filter(|(_, m)| m.contains("unhealthy"))
        .collect();
    assert!(withheld.is_empty(), "a moment cost a feed: {msgs:?}");
    assert!(
        msgs[first..].iter().filter(|(_, m)| fed(m)).count() >= 3,
        "{msgs:?}"
    );
    assert!(spells() >= 3);
    let stopped = svc.terminate();
    assert!(stopped.status.success());
    let logged = stopped
        .log
        .lines()
        .filter(|l| l.contains("overruns in a row: activity unhealthy"))
        .count();
    assert!(logged >= 3, "{}", stopped.log);
}

/// A component stuck in a step — a script looping for ever with no step budget — ends no
/// step, so it never overruns by the count; the looks see its step count stand still
/// for longer than its overruns allow and stop feeding the watchdog.
#[test]
fn a_component_stuck_in_a_step_starves_the_watchdog() {
    let (_dir, cfg) = script("stuck", "function update()\n  while true do end\nend\n", 1);
    let notify = Notify::new("notify-stuck");
    let svc = start_with(
        "stuck",
        Some(&cfg),
        &[
            ("NOTIFY_SOCKET", notify.path.to_str().unwrap()),
            ("WATCHDOG_USEC", "400000"),
        ],
    );
    let why = "STATUS=unhealthy: stuck ended no step for more than 30 ms";
    let msgs = notify.collect_until(Duration::from_secs(30), |msgs| {
        msgs.iter()
            .position(|(_, m)| m.contains(why))
            .is_some_and(|i| msgs[i..].len() > 1 || msgs[i].0.elapsed() > Duration::from_secs(2))
    });
    let at = msgs
        .iter()
        .position(|(_, m)| m.contains(why))
        .unwrap_or_else(|| panic!("no look said it: {msgs:?}"));
    assert!(
        !msgs[at..].iter().any(|(_, m)| m.contains("WATCHDOG=1")),
        "the watchdog was fed while it was stuck: {msgs:?}"
    );
    let described = svc.ok(json!({"cmd": "describe", "component": "stuck"}));
    assert_eq!(described["activity"]["steps"], 0, "{described}");
    // Healthy by the count of overruns (no step ended to count one) ...
    assert!(
        described["activity"]["healthy"].as_bool().unwrap(),
        "{described}"
    );
    // ... and `status` says what the watchdog says, from its second answer on.
    wait_until("status to say it", || {
        svc.ok(json!({"cmd": "status"}))["health"]
            .as_str()
            .is_some_and(|h| h.contains("stuck ended no step for more than 30 ms"))
    });
    // Its thread cannot be stopped: the test's end kills the gateway.
}

#[test]
fn systemd_notify_ready_watchdog_and_stopping() {
    let notify = Notify::new("notify");
    let svc = start_with(
        "notify-svc",
        None,
        &[
            ("NOTIFY_SOCKET", notify.path.to_str().unwrap()),
            ("WATCHDOG_USEC", "200000"),
        ],
    );
    let msgs = notify.collect(Duration::from_millis(1500));
    assert!(
        msgs.iter()
            .any(|m| m.contains("READY=1") && m.contains("STATUS=running")),
        "{msgs:?}"
    );
    let fed = msgs.iter().filter(|m| m.contains("WATCHDOG=1")).count();
    assert!(
        fed >= 5,
        "watchdog fed {fed} times in 1.5 s at a 200 ms interval: {msgs:?}"
    );
    let (tx, rx) = std::sync::mpsc::channel();
    let out = std::thread::scope(|s| {
        s.spawn(|| {
            tx.send(notify.collect(Duration::from_millis(1500)))
                .unwrap()
        });
        svc.terminate()
    });
    assert!(out.status.success());
    let msgs = rx.recv().unwrap();
    assert!(msgs.iter().any(|m| m.contains("STOPPING=1")), "{msgs:?}");
}

#[test]
fn an_overrunning_activity_starves_the_watchdog() {
    let (_dir, cfg) = overrunning("overrun", "fast", true);
    let notify = Notify::new("notify-overrun");
    let svc = start_with(
        "overrun",
        Some(&cfg),
        &[
            ("NOTIFY_SOCKET", notify.path.to_str().unwrap()),
            ("WATCHDOG_USEC", "200000"),
        ],
    );
    let msgs = notify.collect(Duration::from_millis(2000));
    let unhealthy = msgs
        .iter()
        .position(|m| m.contains("STATUS=unhealthy: fast overruns its period"))
        .unwrap_or_else(|| panic!("no unhealthy status: {msgs:?}"));
    assert!(
        !msgs[unhealthy..].iter().any(|m| m.contains("WATCHDOG=1")),
        "the watchdog was fed while unhealthy: {msgs:?}"
    );
    let described = svc.ok(json!({"cmd": "describe", "component": "fast"}));
    // It may be on time for a step at the moment it is described (a 1 µs period, now and
    // then met): the spells it had say it overran.
    assert!(
        described["activity"]["unhealthy_spells"].as_u64().unwrap() >= 1,
        "{described}"
    );
    assert!(described["activity"]["overruns"].as_u64().unwrap() > 0);
    let stopped = svc.terminate();
    assert!(stopped.status.success());
    // Said by the activity's real-time thread through the real-time logger, written by
    // the logger thread.
    assert!(
        stopped.log.lines().any(|l| l.contains("ERROR hwgw_rt:")
            && l.contains("overruns in a row: activity unhealthy")
            && l.contains("component=\"fast\"")),
        "{}",
        stopped.log
    );
}

/// `hwgw log` lists every component's real-time log level and the logger's counters, and
/// sets one; an unknown component or level is an error that says what there is.
#[test]
fn real_time_log_levels_are_listed_and_set_while_it_runs() {
    let svc = start("log-levels", None);
    let all = svc.ok(json!({"cmd": "log"}));
    let names: Vec<&str> = all["areas"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["name"].as_str().unwrap())
        .collect();
    for want in ["follow", "blink", "sim0"] {
        assert!(names.contains(&want), "{want} not in {all}");
    }
    assert!(all["counters"]["dropped"].is_u64(), "{all}");

    let out = svc.cli(&["log", "follow", "debug"]);
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.lines()
            .any(|l| l.split_whitespace().eq(["follow", "debug"])),
        "{text}"
    );
    let one = svc.ok(json!({"cmd": "log", "component": "follow"}));
    assert_eq!(one["areas"], json!([{"name": "follow", "level": "debug"}]));

    let out = svc.cli(&["log", "nosuch", "debug"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("nothing logs as \"nosuch\"; what does: ") && err.contains("follow"),
        "{err}"
    );
    let r = svc.request(json!({"cmd": "log", "level": "debug"}));
    assert_eq!(r["error"]["kind"], "bad_request", "{r}");
    let out = svc.cli(&["log", "follow", "loud"]);
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("\"loud\" is not a log level"),
        "{out:?}"
    );
    assert!(svc.terminate().status.success());
}

#[test]
fn watch_streams_new_values_and_status_reports() {
    let svc = start("watch", None);
    // The ramp on analog input 1 changes at every sample: five new values arrive in order.
    let out = Command::new(HWGW)
        .args(["watch", "sim0.ai", "ch1", "--count", "5", "--socket"])
        .arg(&svc.socket)
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let values: Vec<f64> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| l.parse().unwrap())
        .collect();
    assert_eq!(values.len(), 5);
    assert!(
        values.windows(2).all(|w| w[1] != w[0]),
        "new values each time: {values:?}"
    );

    // A watcher that goes away frees its server thread; the service keeps serving.
    for _ in 0..10 {
        let mut c = UnixStream::connect(&svc.socket).unwrap();
        c.write_all(
            b"{\"id\": 1, \"cmd\": \"watch\", \"component\": \"blink\", \"port\": \"state\"}\n",
        )
        .unwrap();
        let mut line = String::new();
        BufReader::new(c.try_clone().unwrap())
            .read_line(&mut line)
            .unwrap();
        assert!(line.contains("watching"), "{line}");
    }
    let e = svc.request(json!({"cmd": "watch", "component": "sim0.ao", "port": "ch0"}));
    assert_eq!(
        e["error"]["message"],
        "port \"ch0\" is an input port; watching needs an output port"
    );

    let st = svc.ok(json!({"cmd": "status"}));
    assert_eq!(st["health"], "ok");
    let devices = st["devices"].as_array().unwrap();
    assert!(
        devices.iter().all(|d| d["status"] == "online"),
        "{devices:?}"
    );
    let sim0 = st["components"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == "sim0")
        .unwrap();
    assert!(sim0["steps"].as_u64().unwrap() > 0);
    // A lifecycle command prints nothing when it succeeds, one line with -v.
    let out = svc.cli(&["lifecycle", "stop", "blink"]);
    assert!(out.status.success() && out.stdout.is_empty(), "{out:?}");
    let st = svc.ok(json!({"cmd": "status"}));
    assert_eq!(st["health"], "blink is Stopped");
    let out = svc.cli(&["--verbose", "lifecycle", "start", "blink"]);
    assert_eq!(String::from_utf8_lossy(&out.stdout), "blink: running\n");
    let out = svc.cli(&["lifecycle", "stop", "blink"]);
    assert!(out.status.success() && out.stdout.is_empty(), "{out:?}");
    assert!(svc.terminate().status.success());
}

#[test]
fn the_browser_navigates_reads_writes_calls_and_completes() {
    use hwgw::browse::Browser;
    let svc = start("browse", None);
    let mut b = Browser::new(svc.socket.clone());
    assert_eq!(b.prompt(), "hwgw:/> ");
    assert!(
        b.execute("ls")
            .unwrap()
            .lines()
            .any(|l| l.starts_with("follow "))
    );
    assert_eq!(b.complete("cd fo", 5), (3, vec!["follow".to_string()]));
    assert_eq!(
        b.complete("st", 2),
        (
            0,
            vec![
                "start".to_string(),
                "status".to_string(),
                "stop".to_string()
            ]
        )
    );
    assert_eq!(
        b.execute("cd nowhere").unwrap(),
        "error: no component named \"nowhere\"; there are: sim0, sim0.ai, sim0.ao, sim0.di, sim0.do, sim0.encoder0, follow, blink, output_watchdog"
    );
    assert_eq!(b.execute("cd follow").unwrap(), "");
    assert_eq!(b.prompt(), "hwgw:/follow> ");
    let ls = b.execute("ls").unwrap();
    for want in [
        "follow [running]",
        "ports:",
        "operations:",
        "properties:",
        "gain: f64",
    ] {
        assert!(ls.contains(want), "{want:?} not in:\n{ls}");
    }
    for port in [["in", "in", "f64"], ["out", "out", "f64"]] {
        assert!(
            ls.lines()
                .any(|l| l.split_whitespace().take(3).eq(port.iter().copied())),
            "{port:?} not in:\n{ls}"
        );
    }
    assert_eq!(b.complete("get g", 5), (4, vec!["gain".to_string()]));
    assert_eq!(
        b.complete("set o", 5),
        (4, vec!["offset".to_string(), "out".to_string()])
    );
    assert_eq!(b.execute("get gain").unwrap(), "0.5");
    assert_eq!(b.execute("set gain 0.75").unwrap(), "");
    assert_eq!(b.execute("get gain").unwrap(), "0.75");
    assert_eq!(b.execute("watch out 3").unwrap().lines().count(), 3);
    assert_eq!(b.execute("cd ..").unwrap(), "");
    b.execute("cd sim0.ao");
    let v = b.execute("call read_back 0").unwrap();
    assert!(v.parse::<f64>().is_ok(), "{v}");
    assert!(
        b.execute("read_back 0").unwrap().parse::<f64>().is_ok(),
        "a bare operation name calls it"
    );
    assert!(
        b.execute("read_back 99")
            .unwrap()
            .starts_with("error: sim0.ao.read_back: channel 99"),
        "an operation's error is an error"
    );
    assert_eq!(
        b.complete("call rea", 8),
        (5, vec!["read_back".to_string()])
    );
    assert!(
        b.execute("call write 0 \"high\"")
            .unwrap()
            .starts_with("error: operation \"write\" takes (u32, f64)")
    );
    assert!(b.execute("help").unwrap().contains("watch PORT [N]"));
    assert_eq!(b.execute("quit"), None);
    assert!(svc.terminate().status.success());
}

#[test]
fn sighup_rebuilds_what_changed_and_keeps_what_needs_a_restart() {
    let dir = TempDir::new("reload-cfg");
    let cfg = dir.path().join("gw.toml");
    let demo = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../config/demo.toml"))
        .unwrap();
    std::fs::write(&cfg, &demo).unwrap();
    let svc = start("reload", Some(&cfg));
    let pid = nix::unistd::Pid::from_raw(svc.pid().unwrap() as i32);
    let hup = || nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGHUP).unwrap();
    let gain = || {
        svc.request(json!({"cmd": "get", "component": "follow", "property": "gain"}))["ok"].clone()
    };

    // A property change rebuilds the component.
    std::fs::write(
        &cfg,
        demo.replace(
            "properties = { gain = 0.5, offset = 0.0 }",
            "properties = { gain = 0.9, offset = 0.0 }",
        ),
    )
    .unwrap();
    hup();
    wait_until("gain reloaded", || gain() == json!(0.9));

    // A wrong value is refused whole and changes nothing.
    std::fs::write(
        &cfg,
        demo.replace(
            "properties = { gain = 0.5, offset = 0.0 }",
            "properties = { gain = \"fast\", offset = 1.0 }",
        ),
    )
    .unwrap();
    hup();
    wait_until("the refusal logged", || {
        svc.log_text()
            .contains("SIGHUP: not applied, still running the previous version")
    });
    assert_eq!(gain(), json!(0.9));
    assert_eq!(
        svc.ok(json!({"cmd": "get", "component": "follow", "property": "offset"})),
        json!(0.0)
    );

    // The card ThreadScope pulses on changes: kept until a restart. An unparsable file is
    // refused; the gateway runs on.
    std::fs::write(&cfg, demo.replace("period_ms = 10 ", "period_ms = 20 ")).unwrap();
    hup();
    wait_until("the card change named", || {
        svc.log_text().contains("restart hwgw to apply")
    });
    std::fs::write(&cfg, "this is not toml [").unwrap();
    hup();
    wait_until("the unparsable file refused", || {
        svc.log_text()
            .matches("not applied, still running the previous version")
            .count()
            == 2
    });
    assert!(svc.ok(json!({"cmd": "ls"})).is_array());
    let out = svc.terminate();
    assert!(out.status.success());
    let log = out.log.clone();
    for want in [
        "SIGHUP: component \"follow\" rebuilt",
        "gain: expected f64: invalid type: string \"fast\", expected f64",
        "SIGHUP: card \"sim0\" changed, but ThreadScope pulses its output: restart hwgw to apply",
    ] {
        assert!(log.contains(want), "{want:?} not in the log:\n{log}");
    }
}

#[test]
fn the_example_deployment_runs_with_named_channels() {
    let example = Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../config/example.toml"
    ));
    let svc = start("example", Some(example));
    let ports: Vec<String> = svc.ok(json!({"cmd": "describe", "component": "press.ai"}))["ports"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["name"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(ports, vec!["pressure", "temperature"]);
    wait_until("valve written", || {
        svc.ok(json!({"cmd": "get", "component": "valve_loop", "port": "out"})) != Value::Null
    });
    // valve = 1.6 mA/bar * pressure + 4 mA, pressure a 5 +- 3 bar sine: 7.2 .. 16.8 mA.
    let valve = svc
        .ok(json!({"cmd": "call", "component": "press.ao", "operation": "read_back", "args": [0]}))
        ["Ok"]
        .as_f64()
        .unwrap();
    assert!((7.0..=17.0).contains(&valve), "valve {valve} mA");
    // [card.outputs]: valve = 4.0 and pump = false are driven at stop; lamp = "keep"
    // stays on.
    svc.ok(json!({"cmd": "set", "component": "press.do", "port": "lamp", "value": true}));
    wait_until("lamp on", || {
        svc.ok(
            json!({"cmd": "call", "component": "press.do", "operation": "check_bit", "args": [1]}),
        )["Ok"]
            == Value::Bool(true)
    });
    let out = svc.terminate();
    assert!(out.status.success());
    assert!(
        out.log
            .clone()
            .contains("card \"press\" outputs at stop: analog [4], digital on [1]"),
        "{}",
        out.log
    );
}
