//! Lua scripts with the real binary: `config/interlock.toml` driven through the CLI step
//! by step (the sim card's inputs set through its digital loopback, the outputs and the
//! machine's states read back), a script error with its file:line in `hwgw status` and
//! the journal, `hwgw check` catching a script's syntax error, and a deployment reload
//! replacing a changed script.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use testkit::{Service, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const INTERLOCK: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/interlock.toml");

fn state(svc: &Service) -> String {
    svc.out(&["get", "sup", "state"])
        .unwrap_or_else(|e| panic!("{e}"))
}

fn wait_state(svc: &Service, want: &str) {
    let quoted = format!("{want:?}");
    wait_until(&format!("the interlock in {want}"), || state(svc) == quoted);
}

#[test]
fn the_interlock_starts_trips_resets_and_refuses_a_start_without_pressure() {
    // The shipped deployment with a 3 s warning instead of 0.3 s: a loaded machine's CLI
    // polls see the starting state and the program running.
    let dir = testkit::TempDir::new("interlock-files");
    let text = std::fs::read_to_string(INTERLOCK).unwrap();
    assert!(text.contains("warn_s = 0.3"));
    let toml = dir.path().join("interlock.toml");
    std::fs::write(&toml, text.replace("warn_s = 0.3", "warn_s = 3.0")).unwrap();
    let lua = INTERLOCK.replace(".toml", ".lua");
    std::fs::copy(lua, dir.path().join("interlock.lua")).unwrap();
    let svc = Service::start(HWGW, "interlock", &[&toml], &[]).unwrap_or_else(|e| panic!("{e}"));
    let ok = |args: &[&str]| svc.out(args).unwrap_or_else(|e| panic!("{args:?}: {e}"));
    let bit = |b: &str| ok(&["get", "sim0.do", b]);
    wait_until("the supervisor running", || {
        ok(&["ls", "sup"]).starts_with("sup [running]")
    });
    wait_state(&svc, "idle");
    assert_eq!(bit("bit4"), "false", "the pump is off");

    // A start: pressure there, the button pressed; the lamp warns, then the pump runs.
    ok(&["call", "sim0.do", "set_bit", "2", "true"]);
    ok(&["call", "sim0.do", "set_bit", "0", "true"]);
    wait_state(&svc, "starting");
    assert_eq!(
        ok(&["call", "sup", "program.is_running", "startup"]),
        "true"
    );
    wait_state(&svc, "running");
    ok(&["call", "sim0.do", "set_bit", "0", "false"]);
    assert_eq!(bit("bit4"), "true", "the pump runs");
    assert_eq!(bit("bit6"), "false", "the lamp is off again");
    assert_eq!(
        ok(&["call", "sup", "program.is_running", "startup"]),
        "false"
    );

    // A request the machine cannot take: running has no transition to starting.
    let e = svc
        .out(&["call", "sup", "request_state", "starting"])
        .unwrap_err();
    assert!(e.contains("starting"), "{e}");
    assert_eq!(state(&svc), "\"running\"");

    // The limit switch: fault, pump off, alarm on; reset refused while it is on.
    ok(&["call", "sim0.do", "set_bit", "1", "true"]);
    wait_state(&svc, "fault");
    assert_eq!(bit("bit4"), "false", "the pump stopped");
    assert_eq!(bit("bit5"), "true", "the alarm sounds");
    // A reset while the limit switch is on: the event is taken at the supervisor's next
    // step, its guard false. `in_state` answers at a later step, so it sees the outcome.
    ok(&["call", "sup", "emit", "reset"]);
    assert_eq!(
        ok(&["call", "sup", "in_state", "fault"]),
        "true",
        "the reset was refused"
    );
    ok(&["call", "sim0.do", "set_bit", "1", "false"]);
    wait_until("the limit switch clear on the input", || {
        ok(&["get", "sim0.di", "bit1"]) == "false"
    });
    ok(&["call", "sup", "emit", "reset"]);
    wait_state(&svc, "idle");
    assert_eq!(bit("bit5"), "false", "the alarm is off");

    // No pressure: the start-up program fails and the machine goes to fault, the
    // program's error with the script's line.
    ok(&["call", "sim0.do", "set_bit", "2", "false"]);
    wait_until("the pressure input off", || {
        ok(&["get", "sim0.di", "bit2"]) == "false"
    });
    ok(&["call", "sim0.do", "set_bit", "0", "true"]);
    wait_state(&svc, "fault");
    let e = ok(&["call", "sup", "program.error_of", "startup"]);
    assert!(
        e.contains("interlock.lua:") && e.contains("no supply pressure"),
        "{e}"
    );
    assert_eq!(bit("bit4"), "false");

    let stopped = svc.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(stopped.log.contains("interlock fault"), "{}", stopped.log);
}

/// A deployment of one sim card and one script component `s` running `bad.lua`.
const ONE_SCRIPT: &str = r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 10
[card.sim]
digital_inputs = 2
digital_outputs = 2

[[component]]
name = "s"
type = "script"
activity = { type = "periodic", period_ms = 10 }
properties = { file = "bad.lua" }

[[component]]
name = "blink"
type = "blinker"
activity = { type = "periodic", period_ms = 10 }
properties = { device = "sim0", bit = 1 }
"#;

#[test]
fn a_script_error_is_in_status_and_the_journal_with_its_file_and_line() {
    let dir = testkit::TempDir::new("script-error-files");
    let toml = dir.path().join("d.toml");
    std::fs::write(&toml, ONE_SCRIPT).unwrap();
    let lua = "local n = 0\nfunction update()\n  n = n + 1\n  if n == 3 then error('valve 7 stuck') end\nend\n";
    std::fs::write(dir.path().join("bad.lua"), lua).unwrap();
    let svc = Service::start(HWGW, "script-error", &[&toml], &[]).unwrap_or_else(|e| panic!("{e}"));
    let ok = |args: &[&str]| svc.out(args).unwrap_or_else(|e| panic!("{args:?}: {e}"));
    wait_until("the script in exception", || {
        ok(&["ls", "s"]).starts_with("s [exception]")
    });
    let status = ok(&["status"]);
    assert!(status.contains("bad.lua:4: valve 7 stuck"), "{status}");
    // The other component runs on.
    assert!(ok(&["ls", "blink"]).starts_with("blink [running]"));
    let stopped = svc.terminate();
    assert!(
        stopped.log.contains("bad.lua:4: valve 7 stuck"),
        "{}",
        stopped.log
    );
}

#[test]
fn check_names_a_scripts_syntax_error_beside_the_deployments_line() {
    let dir = testkit::TempDir::new("script-check-files");
    let toml = dir.path().join("d.toml");
    std::fs::write(&toml, ONE_SCRIPT).unwrap();
    std::fs::write(
        dir.path().join("bad.lua"),
        "function update()\n  if x then\nend\n",
    )
    .unwrap();
    let out = std::process::Command::new(HWGW)
        .arg("check")
        .arg(&toml)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    // The component's entry in the deployment (line 10), and the script's own line.
    assert!(err.contains("d.toml:10:1: component[0]"), "{err}");
    assert!(err.contains("bad.lua:4:"), "{err}");
}

#[test]
fn a_deployment_reload_replaces_a_changed_script_and_keeps_it_when_the_new_one_fails() {
    let dir = testkit::TempDir::new("script-reload-files");
    let toml = dir.path().join("d.toml");
    std::fs::write(&toml, ONE_SCRIPT).unwrap();
    let script = dir.path().join("bad.lua");
    let version = |v: &str| {
        format!(
            "local o = port.output('version', 'String')\nfunction update() o:write('{v}') end\n"
        )
    };
    std::fs::write(&script, version("one")).unwrap();
    let svc =
        Service::start(HWGW, "script-reload", &[&toml], &[]).unwrap_or_else(|e| panic!("{e}"));
    let ok = |args: &[&str]| svc.out(args).unwrap_or_else(|e| panic!("{args:?}: {e}"));
    wait_until("version one", || ok(&["get", "s", "version"]) == "\"one\"");

    std::fs::write(&script, version("two")).unwrap();
    let report = ok(&["reload"]);
    assert!(report.contains("component \"s\" rebuilt"), "{report}");
    assert!(
        !report.contains("blink"),
        "only the script's component: {report}"
    );
    wait_until("version two", || ok(&["get", "s", "version"]) == "\"two\"");

    std::fs::write(&script, "function update(\n").unwrap();
    let e = svc.out(&["reload"]).unwrap_err();
    assert!(e.contains("bad.lua:2:"), "{e}");
    assert!(ok(&["ls", "s"]).starts_with("s [running]"));
    assert_eq!(ok(&["get", "s", "version"]), "\"two\"");
}
