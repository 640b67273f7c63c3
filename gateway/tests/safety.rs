//! The service you can trust (issue 12), against the real binary: connections that close
//! when their client goes, a stop that no client write can race, every stopping signal
//! handled, a socket that harms no file and talks to no squatter, bounded clients.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::process::Command;
use std::time::Duration;
use testkit::{Service, TempDir, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// One request line on `c`, its reply (a server that turned the client away may have
/// closed before the request went out: its reply is read all the same).
fn ask(c: &mut UnixStream, req: &Value) -> Value {
    let mut line = req.to_string();
    line.push('\n');
    let _ = c.write_all(line.as_bytes());
    let mut r = BufReader::new(c.try_clone().unwrap());
    let mut reply = String::new();
    r.read_line(&mut reply).unwrap();
    serde_json::from_str(&reply).unwrap()
}

/// Connections of `component`'s port `port`.
fn connections(svc: &Service, component: &str, port: &str) -> u64 {
    let d = svc.ok(json!({"cmd": "describe", "component": component}));
    d["ports"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == port)
        .unwrap()["connections"]
        .as_u64()
        .unwrap()
}

fn rss_kb(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches(" kB").trim().parse().ok())
        .unwrap()
}

/// `component`'s mean step over one second from now, µs.
fn step_mean_us(svc: &Service, component: &str) -> f64 {
    let stats = || {
        let a = &svc.ok(json!({"cmd": "describe", "component": component}))["activity"];
        (
            a["steps"].as_u64().unwrap(),
            a["step_total_ns"].as_u64().unwrap(),
        )
    };
    let (s0, t0) = stats();
    std::thread::sleep(Duration::from_secs(1));
    let (s1, t1) = stats();
    (t1 - t0) as f64 / (s1 - s0).max(1) as f64 / 1000.0
}

#[test]
fn ten_thousand_clients_leave_no_connection_behind() {
    let svc = Service::start(HWGW, "leak", &[] as &[&str], &[]).unwrap();
    let pid = svc.pid().unwrap();
    let (watched, set) = (("sim0.ai", "ch1"), ("sim0.do", "bit12"));
    let base = (
        connections(&svc, watched.0, watched.1),
        connections(&svc, set.0, set.1),
    );
    let (rss0, step0) = (rss_kb(pid), step_mean_us(&svc, "sim0.ai"));
    for i in 0..10_000 {
        let mut c = UnixStream::connect(&svc.socket).unwrap();
        if i % 2 == 0 {
            // A one-shot watch: the acknowledgement, then the client is gone.
            let ack = ask(
                &mut c,
                &json!({"id": i, "cmd": "watch", "component": watched.0, "port": watched.1, "count": 1}),
            );
            assert_eq!(ack["ok"], "watching");
        } else {
            let ok = ask(
                &mut c,
                &json!({"id": i, "cmd": "set", "component": set.0, "port": set.1, "value": i % 4 == 1}),
            );
            assert!(ok.get("ok").is_some(), "{ok}");
        }
    }
    wait_until("every client's connection closed", || {
        (
            connections(&svc, watched.0, watched.1),
            connections(&svc, set.0, set.1),
        ) == base
    });
    let (rss1, step1) = (rss_kb(pid), step_mean_us(&svc, "sim0.ai"));
    eprintln!(
        "10 000 clients (5 000 one-shot watches, 5 000 one-shot sets): RSS {rss0} kB -> {rss1} kB; \
         sim0.ai mean step over a second before and after {step0:.1} us -> {step1:.1} us"
    );
    // The connections are gone; memory does not grow with the number of clients (it grew
    // by about 10 kB per client when every connection stayed).
    assert!(rss1 < rss0 + 16 * 1024, "RSS {rss0} kB -> {rss1} kB");
    assert!(svc.terminate().status.success());
}

/// A deployment whose outputs have exact safe values: analog 0 and 100 (1 unit per raw
/// step), digital 3 on; and a fast blinker on digital output 15.
const RACE: &str = r#"
[[card]]
name = "s"
driver = "sim"
period_ms = 5
safe_analog_out = [0.0, 100.0]
safe_digital_out_on = [3]
[card.sim]
digital_outputs = 16
[[card.sim.analog_out]]
count = 2
range = { lowest = 0.0, highest = 65535.0 }

# A blinker with steps due all through a stop: its writes are held then, which is no
# failure (a normal stop logs no error).
[[component]]
name = "blink"
type = "blinker"
activity = { type = "periodic", period_ms = 2 }
properties = { device = "s", bit = 15 }
"#;

#[test]
fn no_sigterm_of_200_lets_a_racing_client_leave_an_output_unsafe() {
    let dir = TempDir::new("race-cfg");
    let cfg = dir.path().join("race.toml");
    std::fs::write(&cfg, RACE).unwrap();
    let want = "card \"s\" outputs at stop: analog [0, 100], digital on [3]";
    let mut refused = 0u64;
    for run in 0..200 {
        let svc = Service::start(HWGW, &format!("race{run}"), &[&cfg], &[]).unwrap();
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let writers: Vec<_> = (0..8)
            .map(|w| {
                let (socket, stop) = (svc.socket.clone(), stop.clone());
                std::thread::spawn(move || {
                    let Ok(mut c) = UnixStream::connect(&socket) else { return 0 };
                    let _ = c.set_read_timeout(Some(Duration::from_secs(5)));
                    let mut r = BufReader::new(c.try_clone().unwrap());
                    let mut refused = 0;
                    for n in 0u64.. {
                        if stop.load(std::sync::atomic::Ordering::Relaxed) {
                            break;
                        }
                        let v = (w * 1000 + n) % 65_000;
                        let req = match n % 4 {
                            0 => json!({"cmd": "set", "component": "s.ao", "port": "ch0", "value": v as f64}),
                            1 => json!({"cmd": "call", "component": "s.ao", "operation": "write", "args": [1, v as f64]}),
                            2 => json!({"cmd": "call", "component": "s.do", "operation": "set_bit", "args": [n % 16, true]}),
                            _ => json!({"cmd": "set", "component": "s.do", "port": format!("bit{}", n % 16), "value": true}),
                        };
                        let mut line = req.to_string();
                        line.push('\n');
                        if c.write_all(line.as_bytes()).is_err() {
                            break;
                        }
                        let mut reply = String::new();
                        match r.read_line(&mut reply) {
                            Ok(0) | Err(_) => break,
                            Ok(_) if reply.contains("\"stopping\"") || reply.contains("output held") => refused += 1,
                            Ok(_) => {}
                        }
                    }
                    refused
                })
            })
            .collect();
        // Let the writers get going, then stop the gateway under them.
        wait_until("writes landing", || {
            svc.ok(json!({"cmd": "call", "component": "s.do", "operation": "check_sequence", "args": [0, 15]}))["Ok"]
                .as_u64()
                .unwrap_or(0)
                != 0
        });
        let stopped = svc.terminate();
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        for w in writers {
            refused += w.join().unwrap();
        }
        assert!(stopped.status.success(), "run {run}: {}", stopped.log);
        assert!(
            !stopped.log.contains("ERROR"),
            "run {run}: a normal stop logged an error:\n{}",
            stopped.log
        );
        assert!(
            stopped.log.contains(want),
            "run {run}: no {want:?} in:\n{}",
            stopped.log
        );
    }
    eprintln!(
        "200 SIGTERMs under 8 writers: every output safe each time; {refused} requests refused as the stop began"
    );
}

#[test]
fn every_stopping_signal_leaves_the_outputs_safe() {
    let dir = TempDir::new("signals-cfg");
    let cfg = dir.path().join("race.toml");
    std::fs::write(&cfg, RACE).unwrap();
    for sig in [
        nix::sys::signal::Signal::SIGQUIT,
        nix::sys::signal::Signal::SIGUSR1,
        nix::sys::signal::Signal::SIGUSR2,
        nix::sys::signal::Signal::SIGALRM,
        nix::sys::signal::Signal::SIGINT,
    ] {
        let svc = Service::start(HWGW, "signals", &[&cfg], &[]).unwrap();
        svc.ok(json!({"cmd": "call", "component": "s.ao", "operation": "write", "args": [1, 7.0]}));
        let stopped = svc.stop_with(sig);
        assert!(
            stopped.status.success(),
            "{sig}: {:?}\n{}",
            stopped.status,
            stopped.log
        );
        assert!(
            stopped.log.contains(&format!("{sig}: stopping"))
                && stopped
                    .log
                    .contains("card \"s\" outputs at stop: analog [0, 100], digital on [3]"),
            "{sig}:\n{}",
            stopped.log
        );
    }
}

#[test]
fn the_socket_option_never_deletes_a_file() {
    let dir = TempDir::new("socket-file");
    let precious = dir.path().join("x.toml");
    std::fs::write(&precious, RACE).unwrap();
    let out = Command::new(HWGW)
        .args(["run", precious.to_str().unwrap(), "--socket"])
        .arg(&precious)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(
        String::from_utf8_lossy(&out.stderr)
            .trim()
            .lines()
            .last()
            .unwrap(),
        format!(
            "hwgw: control socket: {}: exists and is not a socket; refusing to replace it (choose another --socket)",
            precious.display()
        )
    );
    assert_eq!(
        std::fs::read_to_string(&precious).unwrap(),
        RACE,
        "the file is untouched"
    );
    // A socket directory that is a link could be pointed anywhere later: refused.
    let real = dir.path().join("real");
    std::fs::create_dir(&real).unwrap();
    let link = dir.path().join("link");
    std::os::unix::fs::symlink(&real, &link).unwrap();
    let out = Command::new(HWGW)
        .args(["run", "--socket"])
        .arg(link.join("hwgw.sock"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains(&format!(
            "hwgw: control socket: {}: a symbolic link; a socket directory must be a directory of its own",
            link.display()
        )),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `uid` of the unprivileged user the tests run things as.
const NOBODY: u32 = 65_534;

#[test]
fn another_users_socket_is_neither_replaced_nor_trusted() {
    // A squatter's socket where a gateway would listen: refused, left in place.
    let dir = TempDir::new("squat");
    let squat = dir.path().join("hwgw.sock");
    let listener = std::os::unix::net::UnixListener::bind(&squat).unwrap();
    nix::unistd::chown(&squat, Some(nix::unistd::Uid::from_raw(NOBODY)), None).unwrap();
    let out = Command::new(HWGW)
        .args(["run", "--socket"])
        .arg(&squat)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains(&format!(
            "{}: a socket of uid {NOBODY}, not of this user (uid 0); refusing to replace it",
            squat.display()
        )),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(squat.exists());
    // `check` says the same of a deployment naming it.
    let toml = dir.path().join("squat.toml");
    std::fs::write(
        &toml,
        format!("control_socket = {:?}\n", squat.display().to_string()),
    )
    .unwrap();
    let out = Command::new(HWGW).arg("check").arg(&toml).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains(&format!(
            "squat.toml:1:18: control_socket: {}: a socket of uid {NOBODY}, not of this user (uid 0)",
            squat.display()
        )),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // A client will not talk to it either (it could answer anything).
    std::thread::spawn(move || {
        for c in listener.incoming().flatten() {
            let mut c = c;
            let _ = c.write_all(b"{\"id\":1,\"ok\":42.0}\n");
        }
    });
    let out = Command::new(HWGW)
        .args(["get", "sim0.ai", "ch0", "--socket"])
        .arg(&squat)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(
        String::from_utf8_lossy(&out.stderr).trim(),
        format!(
            "hwgw: {}: owned by uid {NOBODY}, neither this user, root nor hwgw: not talking to it",
            squat.display()
        )
    );
}

/// Runs `hwgw ARGS` as the unprivileged user, without XDG_RUNTIME_DIR.
fn as_nobody(args: &[&str]) -> Command {
    let mut cmd = Command::new("setpriv");
    cmd.args([
        "--reuid",
        &NOBODY.to_string(),
        "--regid",
        &NOBODY.to_string(),
        "--clear-groups",
        "--",
        HWGW,
    ])
    .args(args)
    .env_remove("XDG_RUNTIME_DIR")
    .env_remove("HWGW_SOCKET");
    cmd
}

#[test]
fn a_users_default_socket_sits_in_a_directory_only_that_user_can_write() {
    let dir = Path::new("/tmp/hwgw-65534");
    let _ = std::fs::remove_dir_all(dir);
    // Another user (root here) got there first with a directory everyone may write to.
    std::fs::create_dir(dir).unwrap();
    std::fs::set_permissions(dir, std::os::unix::fs::PermissionsExt::from_mode(0o777)).unwrap();
    let out = as_nobody(&["run"]).output().unwrap();
    assert_eq!(
        out.status.code(),
        Some(1),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("/tmp/hwgw-65534: owned by uid 0 with mode 777; a socket directory must be this user's and writable by no one else"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    std::fs::remove_dir_all(dir).unwrap();
    // Left to itself it makes the directory 0700 and the socket 0600.
    let mut child = as_nobody(&["run"])
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let sock = dir.join("hwgw.sock");
    wait_until("nobody's gateway listening", || {
        UnixStream::connect(&sock).is_ok()
    });
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    let (d, s) = (
        std::fs::metadata(dir).unwrap(),
        std::fs::metadata(&sock).unwrap(),
    );
    assert_eq!((d.uid(), d.permissions().mode() & 0o777), (NOBODY, 0o700));
    assert_eq!((s.uid(), s.permissions().mode() & 0o777), (NOBODY, 0o600));
    let ls = as_nobody(&["ls"]).output().unwrap();
    assert!(
        ls.status.success(),
        "{}",
        String::from_utf8_lossy(&ls.stderr)
    );
    // Root's client trusts a socket file root owns — but not the server behind it, which
    // runs as nobody: what answers is checked, not only what the file says.
    nix::unistd::chown(&sock, Some(nix::unistd::Uid::from_raw(0)), None).unwrap();
    let ls = Command::new(HWGW)
        .args(["ls", "--socket"])
        .arg(&sock)
        .output()
        .unwrap();
    assert_eq!(ls.status.code(), Some(1));
    assert_eq!(
        String::from_utf8_lossy(&ls.stderr).trim(),
        format!(
            "hwgw: {}: served by uid {NOBODY}, neither this user, root nor hwgw: not talking to it",
            sock.display()
        )
    );
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(child.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    assert!(child.wait().unwrap().success());
    assert!(!sock.exists(), "its own socket is removed at stop");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn clients_are_bounded_and_silent_ones_are_let_go() {
    let dir = TempDir::new("limits-cfg");
    let cfg = dir.path().join("limits.toml");
    std::fs::write(
        &cfg,
        format!("control_clients = 4\ncontrol_idle_s = 1\n{RACE}"),
    )
    .unwrap();
    let svc = Service::start(HWGW, "limits", &[&cfg], &[]).unwrap();
    // Four clients, each served once (so each surely holds a place), then silent.
    let held: Vec<UnixStream> = (0..4)
        .map(|i| {
            let mut c = UnixStream::connect(&svc.socket).unwrap();
            let mut served = ask(&mut c, &json!({"id": i, "cmd": "ls"}));
            while served["error"]["kind"] == "busy" {
                // A start-up probe of the harness still held a place: try again.
                c = UnixStream::connect(&svc.socket).unwrap();
                served = ask(&mut c, &json!({"id": i, "cmd": "ls"}));
            }
            assert!(served["ok"].is_array(), "{served}");
            c
        })
        .collect();
    wait_until("four clients connected", || {
        // The status request is a fifth client: turned away while the four stay.
        let mut c = UnixStream::connect(&svc.socket).unwrap();
        let r = ask(&mut c, &json!({"id": 1, "cmd": "ls"}));
        r["error"]["kind"] == "busy"
    });
    // Silent for the idle timeout, the four are let go; then a client is served again.
    for mut c in held {
        let mut buf = [0u8; 1];
        c.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
        assert_eq!(
            std::io::Read::read(&mut c, &mut buf).unwrap(),
            0,
            "closed by the server"
        );
    }
    let st = svc.ok(json!({"cmd": "status"}));
    assert!(
        st["control"]["refused"].as_u64().unwrap() >= 1,
        "{}",
        st["control"]
    );
    assert!(
        st["control"]["idle_closed"].as_u64().unwrap() >= 4,
        "{}",
        st["control"]
    );
    assert!(svc.terminate().status.success());
}

#[test]
fn out_of_file_descriptors_the_server_backs_off_and_recovers() {
    let dir = TempDir::new("emfile-cfg");
    let cfg = dir.path().join("emfile.toml");
    std::fs::write(&cfg, format!("control_clients = 1000\n{RACE}")).unwrap();
    let svc = Service::start(HWGW, "emfile", &[&cfg], &[]).unwrap();
    let pid = nix::unistd::Pid::from_raw(svc.pid().unwrap() as i32);
    // 64 descriptors: a handful of clients exhaust them.
    let status = Command::new("prlimit")
        .args([&format!("--pid={pid}"), "--nofile=64:64"])
        .status()
        .unwrap();
    assert!(status.success());
    let clients: Vec<UnixStream> = (0..80)
        .filter_map(|_| UnixStream::connect(&svc.socket).ok())
        .collect();
    std::thread::sleep(Duration::from_secs(2));
    // None was dropped without a word: each is served, waiting, or told why not.
    let (mut told, mut waiting) = (0, 0);
    for c in &clients {
        c.set_nonblocking(true).unwrap();
        let mut buf = [0u8; 1024];
        match std::io::Read::read(&mut &*c, &mut buf) {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => waiting += 1,
            r => {
                let line = String::from_utf8_lossy(&buf[..*r.as_ref().unwrap_or(&0)]);
                assert!(line.contains("cannot take a client now"), "{r:?}: {line:?}");
                told += 1;
            }
        }
    }
    eprintln!(
        "of {} clients: {told} told to come back, {waiting} served or waiting",
        clients.len()
    );
    drop(clients);
    // Once clients leave, it accepts again.
    wait_until("served again", || {
        UnixStream::connect(&svc.socket)
            .map(|mut c| {
                ask(&mut c, &json!({"id": 1, "cmd": "ls"}))
                    .get("ok")
                    .is_some()
            })
            .unwrap_or(false)
    });
    let failures = svc.ok(json!({"cmd": "status"}))["control"]["accept_failures"]
        .as_u64()
        .unwrap();
    eprintln!("{failures} failed accepts while out of descriptors for 2 s");
    // Backing off (10 ms doubling to 1 s) fails a few times a second, not thousands.
    assert!(failures > 0 && failures < 50, "{failures} failed accepts");
    assert!(svc.terminate().status.success());
}

#[test]
fn a_reader_that_goes_away_ends_the_cli_quietly() {
    let svc = Service::start(HWGW, "pipe", &[] as &[&str], &[]).unwrap();
    let out = Command::new("bash")
        .arg("-c")
        .arg(format!(
            "{HWGW} watch sim0.ai ch1 --socket {} | head -n 2; echo \"rc=${{PIPESTATUS[0]}}\"",
            svc.socket.display()
        ))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(text.lines().count(), 3, "{text}");
    assert_eq!(text.lines().last(), Some("rc=0"), "{text}");
    assert!(
        !String::from_utf8_lossy(&out.stderr).contains("panicked"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(svc.terminate().status.success());
}

#[test]
fn a_set_out_of_range_or_to_a_stopped_component_is_an_error_and_never_replayed() {
    let dir = TempDir::new("range-cfg");
    let cfg = dir.path().join("range.toml");
    std::fs::write(&cfg, RACE).unwrap();
    let svc = Service::start(HWGW, "range", &[&cfg], &[]).unwrap();
    let r =
        svc.request(json!({"cmd": "set", "component": "s.ao", "port": "ch0", "value": 70000.0}));
    assert_eq!(r["error"]["kind"], "failed", "{r}");
    assert_eq!(
        r["error"]["message"],
        "port \"ch0\": value 70000 is outside channel 0's range [0, 65535]"
    );
    // A value set while the component is stopped is refused (it would never be written),
    // and not applied when it starts again.
    let out = svc.cli(&["lifecycle", "stop", "s.ao"]);
    assert!(out.status.success());
    let r = svc.request(json!({"cmd": "set", "component": "s.ao", "port": "ch0", "value": 42.0}));
    assert!(
        r["error"]["message"]
            .as_str()
            .is_some_and(|m| m.contains("is Stopped")),
        "{r}"
    );
    let out = svc.cli(&["set", "s.ao", "ch0", "42"]);
    assert!(!out.status.success(), "the CLI exits non-zero: {out:?}");
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("is Stopped"),
        "{out:?}"
    );
    let out = svc.cli(&["lifecycle", "start", "s.ao"]);
    assert!(out.status.success());
    svc.ok(json!({"cmd": "set", "component": "s.ao", "port": "ch1", "value": 9.0}));
    wait_until("the later write applied", || {
        svc.ok(json!({"cmd": "get", "component": "s.ao", "port": "ch1"})) == json!(9.0)
    });
    assert_eq!(
        svc.ok(json!({"cmd": "get", "component": "s.ao", "port": "ch0"})),
        json!(0.0),
        "the write made while stopped was dropped"
    );
    assert!(svc.terminate().status.success());
}
