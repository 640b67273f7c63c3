//! The state-machine and program semantics of the manual, as Lua tests (one transition
//! per step, entry/exit order in nested machines, `handle` when no transition is taken,
//! failing guards, reactive mode and `request_state`, event transitions from events and
//! ports, programs), run in the sandbox every script gets: the libraries, then the test
//! file. The same files run on a stock interpreter with `tests/lua/standalone.lua`.

use script::load::LIBRARIES;
use script::sandbox::{STRICT, Sandbox};
use std::path::Path;

fn run(file: &str) {
    let sb = Sandbox::new(64 << 20).expect("a sandbox");
    for (name, lib) in LIBRARIES {
        sb.lua.load(lib).set_name(name).exec().expect(name);
    }
    sb.lua.load(STRICT).exec().expect("strict");
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/lua")
        .join(file);
    let text = std::fs::read_to_string(&path).expect("the test file");
    sb.lua
        .load(&text)
        .set_name(format!("@{file}"))
        .exec()
        .unwrap_or_else(|e| panic!("{file}: {}", script::error::message(&e)));
}

#[test]
fn one_transition_per_step() {
    run("test_one_transition.lua");
}

#[test]
fn entry_and_exit_order_in_nested_machines() {
    run("test_nested_order.lua");
}

#[test]
fn handle_runs_when_no_transition_is_taken() {
    run("test_handle.lua");
}

#[test]
fn a_guard_that_fails_and_a_precondition_that_blocks() {
    run("test_guard_fails.lua");
}

#[test]
fn reactive_mode_waits_for_request_state() {
    run("test_reactive.lua");
}

#[test]
fn event_transitions_from_events_and_event_ports() {
    run("test_events.lua");
}

#[test]
fn programs_yield_wait_pause_step_stop() {
    run("test_programs.lua");
}

#[test]
fn bad_machine_definitions_are_refused_with_their_line() {
    run("test_validation.lua");
}

/// Every test file in the folder is run above: a new one cannot be forgotten.
#[test]
fn every_lua_test_file_is_run() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/lua");
    let this = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/lua_semantics.rs"),
    )
    .expect("this file");
    for e in std::fs::read_dir(dir).expect("tests/lua") {
        let name = e
            .expect("an entry")
            .file_name()
            .to_string_lossy()
            .into_owned();
        if name.starts_with("test_") {
            assert!(
                this.contains(&format!("run(\"{name}\")")),
                "{name} is not run"
            );
        }
    }
}
