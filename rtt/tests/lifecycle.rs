//! Every lifecycle transition, legal and refused, and what failing or panicking hooks do.
//! Deterministic: slave activities, stepped by hand.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::Registry;
use rtt::component::{LifecycleError, TaskState};
use rtt::{
    ActivitySpec, Component, Context, HookError, HookResult, Runtime, RuntimeOptions, TaskContext,
};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// What the scripted component should do, and what it did.
#[derive(Default)]
struct Script {
    fail_configure: AtomicBool,
    fail_start: AtomicBool,
    panic_configure: AtomicBool,
    fail_update: AtomicBool,
    held_update: AtomicBool,
    panic_update: AtomicBool,
    request_error: AtomicBool,
    recover_in_error_hook: AtomicBool,
    panic_exception: AtomicBool,
    log: Mutex<Vec<&'static str>>,
}

impl Script {
    fn log(&self, s: &'static str) {
        self.log.lock().unwrap().push(s);
    }
    fn take(&self) -> Vec<&'static str> {
        std::mem::take(&mut *self.log.lock().unwrap())
    }
    fn flag(&self, f: &AtomicBool) -> bool {
        f.load(Ordering::SeqCst)
    }
}

struct Scripted(Arc<Script>);

impl Component for Scripted {
    fn configure_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.0.log("configure");
        if self.0.flag(&self.0.panic_configure) {
            panic!("configure exploded");
        }
        if self.0.flag(&self.0.fail_configure) {
            return Err(HookError::new("no such device"));
        }
        Ok(())
    }
    fn start_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.0.log("start");
        if self.0.flag(&self.0.fail_start) {
            return Err(HookError::new("not ready"));
        }
        Ok(())
    }
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        self.0.log("update");
        if self.0.flag(&self.0.panic_update) {
            panic!("update exploded");
        }
        if self.0.flag(&self.0.fail_update) {
            return Err(HookError::new("sensor gone"));
        }
        if self.0.flag(&self.0.held_update) {
            // What a device write answers while the gateway stops.
            return Err(device_interface::DeviceError::Held { reason: "stopping" }.into());
        }
        if self.0.flag(&self.0.request_error) {
            ctx.error();
        }
        Ok(())
    }
    fn error_hook(&mut self, ctx: &mut Context<'_>) {
        self.0.log("error");
        if self.0.flag(&self.0.recover_in_error_hook) {
            ctx.recover();
        }
    }
    fn stop_hook(&mut self, _: &mut Context<'_>) {
        self.0.log("stop");
    }
    fn cleanup_hook(&mut self, _: &mut Context<'_>) {
        self.0.log("cleanup");
    }
    fn exception_hook(&mut self, _: &mut Context<'_>) {
        self.0.log("exception");
        if self.0.flag(&self.0.panic_exception) {
            panic!("exception handling exploded");
        }
    }
}

fn runtime() -> Runtime {
    Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap()
}

fn scripted(rt: &Runtime, name: &str) -> (TaskContext, Arc<Script>) {
    let script = Arc::new(Script::default());
    let s = script.clone();
    let task = rt
        .add(
            name,
            ActivitySpec::Slave,
            rtt::InitialState::PreOperational,
            move |_| Ok(Scripted(s)),
        )
        .unwrap();
    (task, script)
}

/// Brings a fresh component to `state`.
fn in_state(rt: &Runtime, name: &str, state: TaskState) -> (TaskContext, Arc<Script>) {
    let (t, s) = scripted(rt, name);
    match state {
        TaskState::PreOperational => {}
        TaskState::Stopped => t.configure().unwrap(),
        TaskState::Running => {
            t.configure().unwrap();
            t.start().unwrap();
        }
        TaskState::RunTimeError => {
            t.configure().unwrap();
            t.start().unwrap();
            t.error().unwrap();
        }
        TaskState::Exception => {
            t.configure().unwrap();
            t.start().unwrap();
            s.fail_update.store(true, Ordering::SeqCst);
            t.step().unwrap();
            s.fail_update.store(false, Ordering::SeqCst);
        }
        TaskState::FatalError => {
            t.configure().unwrap();
            t.start().unwrap();
            s.fail_update.store(true, Ordering::SeqCst);
            s.panic_exception.store(true, Ordering::SeqCst);
            t.step().unwrap();
        }
        TaskState::Init => unreachable!("Init is only seen while building"),
    }
    assert_eq!(t.state(), state, "setting up {state}");
    s.take();
    (t, s)
}

type Command = (&'static str, fn(&TaskContext) -> Result<(), LifecycleError>);

const COMMANDS: [Command; 6] = [
    ("configure", |t| t.configure()),
    ("start", |t| t.start()),
    ("stop", |t| t.stop()),
    ("cleanup", |t| t.cleanup()),
    ("recover", |t| t.recover()),
    ("error", |t| t.error()),
];

#[test]
fn every_command_in_every_state() {
    use TaskState::*;
    // (state, command) -> the state it leads to; absent: refused.
    let legal: &[(TaskState, &str, TaskState)] = &[
        (PreOperational, "configure", Stopped),
        (Stopped, "configure", Stopped),
        (Stopped, "start", Running),
        (Stopped, "cleanup", PreOperational),
        (Running, "stop", Stopped),
        (Running, "error", RunTimeError),
        (RunTimeError, "stop", Stopped),
        (RunTimeError, "recover", Running),
        (Exception, "recover", Stopped),
    ];
    let rt = runtime();
    let mut n = 0;
    for state in [
        PreOperational,
        Stopped,
        Running,
        RunTimeError,
        Exception,
        FatalError,
    ] {
        for (command, f) in COMMANDS {
            n += 1;
            let (t, _) = in_state(&rt, &format!("c{n}"), state);
            let result = f(&t);
            match legal.iter().find(|(s, c, _)| *s == state && *c == command) {
                Some((_, _, to)) => {
                    assert!(result.is_ok(), "{command} in {state}: {result:?}");
                    assert_eq!(t.state(), *to, "{command} in {state}");
                }
                None => {
                    let err = result.unwrap_err();
                    assert!(
                        matches!(err, LifecycleError::Illegal { state: s, command: c, .. } if s == state && c == command),
                        "{command} in {state}: {err:?}"
                    );
                    assert_eq!(
                        err.to_string(),
                        format!("component \"c{n}\": cannot {command} in state {state}")
                    );
                    assert_eq!(t.state(), state, "a refused {command} changes nothing");
                }
            }
        }
    }
}

#[test]
fn hooks_run_in_lifecycle_order() {
    let rt = runtime();
    let (t, s) = scripted(&rt, "c");
    assert_eq!(t.state(), TaskState::PreOperational);
    t.configure().unwrap();
    t.start().unwrap();
    t.step().unwrap();
    t.step().unwrap();
    t.stop().unwrap();
    t.step().unwrap(); // stopped: no update
    t.cleanup().unwrap();
    assert_eq!(
        s.take(),
        vec!["configure", "start", "update", "update", "stop", "cleanup"]
    );
}

#[test]
fn failing_configure_and_start_refuse_the_transition() {
    let rt = runtime();
    let (t, s) = scripted(&rt, "c");
    s.fail_configure.store(true, Ordering::SeqCst);
    let e = t.configure().unwrap_err();
    assert_eq!(
        e.to_string(),
        "component \"c\": configure_hook failed: no such device"
    );
    assert_eq!(t.state(), TaskState::PreOperational);
    s.fail_configure.store(false, Ordering::SeqCst);
    t.configure().unwrap();
    s.fail_start.store(true, Ordering::SeqCst);
    assert!(matches!(
        t.start(),
        Err(LifecycleError::HookFailed {
            hook: "start_hook",
            ..
        })
    ));
    assert_eq!(t.state(), TaskState::Stopped);
    assert_eq!(t.counters().failed_hooks, 2);
}

#[test]
fn a_panicking_hook_goes_to_exception_and_others_keep_running() {
    let rt = runtime();
    let (healthy, hs) = in_state(&rt, "healthy", TaskState::Running);
    let (t, s) = scripted(&rt, "fragile");
    s.panic_configure.store(true, Ordering::SeqCst);
    match t.configure() {
        Err(LifecycleError::HookPanicked {
            hook,
            message,
            state,
            ..
        }) => {
            assert_eq!(
                (hook, message.as_str(), state),
                ("configure_hook", "configure exploded", TaskState::Exception)
            );
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(t.state(), TaskState::Exception);
    assert_eq!(
        s.take(),
        vec!["configure", "exception"],
        "no stop hook: it was not running"
    );
    healthy.step().unwrap();
    assert_eq!(hs.take(), vec!["update"]);
    assert_eq!(healthy.state(), TaskState::Running);
    let c = t.counters();
    assert_eq!(c.exceptions, 1);
    assert!(c.last_error.unwrap().contains("configure exploded"));
}

#[test]
fn update_failure_and_panic_go_to_exception_with_stop_hook() {
    let rt = runtime();
    for (flag, text) in [
        ("fail", "update failed: sensor gone"),
        ("panic", "update panicked: update exploded"),
    ] {
        let (t, s) = in_state(&rt, flag, TaskState::Running);
        if flag == "fail" {
            s.fail_update.store(true, Ordering::SeqCst);
        } else {
            s.panic_update.store(true, Ordering::SeqCst);
        }
        t.step().unwrap();
        assert_eq!(t.state(), TaskState::Exception);
        assert_eq!(s.take(), vec!["update", "exception", "stop"]);
        assert_eq!(t.counters().last_error.as_deref(), Some(text));
        t.step().unwrap();
        assert!(s.take().is_empty(), "nothing runs in Exception");
        t.recover().unwrap();
        assert_eq!(t.state(), TaskState::Stopped);
    }
}

#[test]
fn an_update_refused_by_held_outputs_is_no_failure() {
    // The gateway holds its outputs while it stops, before it stops the components: a
    // component's write refused then is skipped, not an Exception (nor an ERROR line).
    let rt = runtime();
    let (t, s) = in_state(&rt, "held", TaskState::Running);
    s.held_update.store(true, Ordering::SeqCst);
    t.step().unwrap();
    assert_eq!(t.state(), TaskState::Running);
    assert_eq!(s.take(), vec!["update"]);
    assert_eq!(t.counters().exceptions, 0);
    assert_eq!(t.counters().last_error, None);
    t.stop().unwrap();
    assert_eq!(t.state(), TaskState::Stopped);
}

#[test]
fn a_panic_while_handling_an_exception_is_fatal() {
    let rt = runtime();
    let (t, s) = in_state(&rt, "c", TaskState::FatalError);
    for (name, f) in COMMANDS {
        assert!(f(&t).is_err(), "{name} must be refused in FatalError");
    }
    t.step().unwrap();
    assert!(s.take().is_empty());
    assert_eq!(t.state(), TaskState::FatalError);
}

#[test]
fn runtime_error_runs_the_error_hook_until_recovered() {
    let rt = runtime();
    let (t, s) = in_state(&rt, "c", TaskState::Running);
    s.request_error.store(true, Ordering::SeqCst);
    t.step().unwrap();
    assert_eq!(t.state(), TaskState::RunTimeError);
    s.request_error.store(false, Ordering::SeqCst);
    t.step().unwrap();
    t.step().unwrap();
    s.recover_in_error_hook.store(true, Ordering::SeqCst);
    t.step().unwrap();
    assert_eq!(t.state(), TaskState::Running);
    t.step().unwrap();
    assert_eq!(
        s.take(),
        vec!["update", "error", "error", "error", "update"]
    );
    assert_eq!(t.counters().runtime_errors, 1);
}

#[test]
fn component_names_are_unique_and_listed() {
    let rt = runtime();
    scripted(&rt, "a");
    let s = Arc::new(Script::default());
    let e = rt
        .add(
            "a",
            ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            move |_| Ok(Scripted(s)),
        )
        .unwrap_err();
    assert_eq!(e.to_string(), "a component named \"a\" already exists");
    let e = rt.component("b").unwrap_err();
    assert_eq!(e.to_string(), "no component named \"b\"; there are: a");
}
