//! The script component in a runtime, stepped by hand: its ports, hooks, machine and
//! programs; errors with the script's file:line; the sandbox (each escape refused or
//! stopped with a clear error while the other components run on); reload.

use device_interface::Registry;
use rtt::component::DynWriter;
use rtt::port::ConnPolicy;
use rtt::{ActivitySpec, Runtime, RuntimeOptions, TaskContext, TaskState};
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::sync::Arc;

struct Rig {
    rt: Runtime,
    dir: PathBuf,
}

impl Rig {
    fn new(test: &str) -> Rig {
        let dir = std::env::temp_dir().join(format!("hwgw-script-{test}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("a temp dir");
        let rt =
            Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).expect("a runtime");
        Rig { rt, dir }
    }

    /// Script component `name` running `text` (as `name.lua`), configured or not.
    fn script(&self, name: &str, text: &str) -> (TaskContext, Result<(), String>) {
        let file = format!("{name}.lua");
        std::fs::write(self.dir.join(&file), text).expect("the script");
        let task = script::add(&self.rt, name, ActivitySpec::Slave).expect("built");
        let p = task.properties();
        p.set_value("file", json!(file)).expect("file");
        p.set_value("base_dir", json!(self.dir)).expect("base_dir");
        let r = task.configure().map_err(|e| e.to_string());
        (task, r)
    }

    fn write(&self, name: &str, text: &str) {
        std::fs::write(self.dir.join(format!("{name}.lua")), text).expect("the script");
    }
}

impl Drop for Rig {
    fn drop(&mut self) {
        self.rt.stop_all();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn writer(task: &TaskContext, port: &str) -> Box<dyn DynWriter> {
    task.port(port)
        .expect("the port")
        .writer(ConnPolicy::data())
        .expect("a writer")
}

fn value(task: &TaskContext, port: &str) -> Option<Value> {
    task.port(port)
        .expect("the port")
        .last_value()
        .expect("a value")
}

/// Calls an own-thread operation of a hand-stepped component: sent, then stepped until
/// its answer is there (a stopped component answers at once).
fn try_call(task: &TaskContext, op: &str, args: Vec<Value>) -> Result<Value, String> {
    let mut h = task.send_value(op, args).map_err(|e| e.to_string())?;
    for _ in 0..100 {
        if let Some(r) = h.collect_if_done() {
            // An answer that can fail comes as {"Ok": …} or {"Err": …}.
            return match r.map_err(|e| e.to_string())? {
                Value::Object(m) if m.len() == 1 && m.contains_key("Ok") => Ok(m["Ok"].clone()),
                Value::Object(m) if m.len() == 1 && m.contains_key("Err") => {
                    Err(m["Err"].as_str().unwrap_or_default().to_string())
                }
                v => Ok(v),
            };
        }
        if task.state() == TaskState::Running {
            task.step().map_err(|e| e.to_string())?;
        }
    }
    Err(format!("{op}: no answer in 100 steps"))
}

fn call(task: &TaskContext, op: &str, args: Vec<Value>) -> Value {
    try_call(task, op, args).expect("the call")
}

const LATCH: &str = r#"
local limit = port.input("limit", "bool")
local alarm = port.output("alarm", "bool")
local count = port.output("count", "i64")
local n = 0
function update()
  n = n + 1
  count:write(n)
  local v = limit:read()
  if v then alarm:write(true) end
end
"#;

#[test]
fn declared_ports_carry_values_each_step() {
    let rig = Rig::new("ports");
    let (task, r) = rig.script("latch", LATCH);
    r.expect("configures");
    let names: Vec<String> = task.ports().into_iter().map(|p| p.name).collect();
    for p in ["state", "limit", "alarm", "count"] {
        assert!(names.contains(&p.to_string()), "{p} in {names:?}");
    }
    task.start().expect("starts");
    let mut limit = writer(&task, "limit");
    task.step().expect("a step");
    assert_eq!(value(&task, "count"), Some(json!(1)));
    assert_eq!(
        value(&task, "alarm"),
        None,
        "nothing written before the limit"
    );
    limit.write(json!(true)).expect("written");
    task.step().expect("a step");
    assert_eq!(value(&task, "alarm"), Some(json!(true)));
    assert_eq!(value(&task, "count"), Some(json!(2)));
}

#[test]
fn a_syntax_error_names_the_file_and_line() {
    let rig = Rig::new("syntax");
    let (task, r) = rig.script("broken", "local x = 1\nfunction update(\n  x = 2\nend\n");
    let e = r.expect_err("refused");
    assert!(e.contains("broken.lua:3:"), "{e}");
    assert_eq!(task.state(), TaskState::PreOperational);
}

#[test]
fn an_undefined_name_called_at_top_level_is_an_error_with_its_line() {
    let rig = Rig::new("undefined");
    let (_, r) = rig.script("typo", "local p = port.input('a', 'bool')\nstatemachin{}\n");
    let e = r.expect_err("refused");
    assert!(
        e.contains("typo.lua:2:") && e.contains("statemachin"),
        "{e}"
    );
}

#[test]
fn an_error_in_update_is_an_exception_with_file_and_line() {
    let rig = Rig::new("update");
    let (task, r) = rig.script("fails", "function update()\n  error('valve stuck')\nend\n");
    r.expect("configures");
    task.start().expect("starts");
    let _ = task.step();
    assert_eq!(task.state(), TaskState::Exception);
    let last = task.counters().last_error.unwrap_or_default();
    assert!(last.contains("fails.lua:2: valve stuck"), "{last}");
}

#[test]
fn the_error_model_from_a_script() {
    let rig = Rig::new("errmodel");
    let text = r#"
local bad = port.input("bad", "bool")
function update() if bad:read() then rtt.error() end end
function error_update() if not bad:read() then rtt.recover() end end
"#;
    let (task, r) = rig.script("model", text);
    r.expect("configures");
    task.start().expect("starts");
    let mut bad = writer(&task, "bad");
    bad.write(json!(true)).expect("written");
    task.step().expect("a step");
    assert_eq!(task.state(), TaskState::RunTimeError);
    bad.write(json!(false)).expect("written");
    task.step().expect("a step");
    assert_eq!(task.state(), TaskState::Running);
}

/// Each escape from the sandbox, with what it must say; another component steps on.
#[test]
fn the_sandbox_refuses_or_stops_each_escape_and_the_others_run_on() {
    let rig = Rig::new("sandbox");
    let (other, r) = rig.script("other", LATCH);
    r.expect("configures");
    other.start().expect("starts");
    let cases: [(&str, &str, &str); 6] = [
        (
            "exec",
            "os.execute('touch /tmp/hwgw-escaped')",
            "os.execute is not available",
        ),
        ("open", "assert(io.open('/etc/passwd'))", "no data_dir"),
        ("req", "require('socket.core')", "require is not available"),
        (
            "mem",
            "local t = {} for i = 1, 100 do t[i] = string.rep('x', 1 << 20) end",
            "memory",
        ),
        ("loop", "while true do end", "max_step_us"),
        (
            "load",
            "assert(load(string.char(27) .. 'Lua'))",
            "binary chunk",
        ),
    ];
    for (name, body, says) in cases {
        let text = format!("function update()\n  {body}\nend\n");
        let (task, r) = rig.script(name, &text);
        r.expect("configures");
        if name == "loop" {
            task.properties()
                .set_value("max_step_us", json!(20_000))
                .expect("set");
        }
        task.start().expect("starts");
        let _ = task.step();
        assert_eq!(task.state(), TaskState::Exception, "{name}");
        let last = task.counters().last_error.unwrap_or_default();
        assert!(last.contains(says), "{name}: {last}");
        assert!(
            last.contains(&format!("{name}.lua:2")) || name == "mem",
            "{name}: {last}"
        );
        other.step().expect("the other steps");
        assert_eq!(other.state(), TaskState::Running);
    }
    assert!(!Path::new("/tmp/hwgw-escaped").exists());
    let overruns = rig
        .rt
        .component("loop")
        .expect("loop")
        .attributes()
        .get_value("overruns");
    assert_eq!(overruns.expect("overruns"), json!(1));
}

#[test]
fn io_open_reaches_data_dir_and_nothing_outside() {
    let rig = Rig::new("io");
    std::fs::create_dir_all(rig.dir.join("data")).expect("data");
    std::fs::write(rig.dir.join("data/in.txt"), "12.5\nsecond\n").expect("in");
    let text = r#"
local out = port.output("out", "f64")
local f = assert(io.open("in.txt"))
local x = f:read("n")
f:close()
local w = assert(io.open("out.txt", "w"))
w:write("got ", x, "\n")
w:close()
local ok, err = io.open("../escape.txt", "w")
assert(ok == nil and err:find("no '..'"), err)
ok, err = io.open("/tmp/abs.txt", "w")
assert(ok == nil and err:find("relative"), err)
function update() out:write(x) end
"#;
    std::fs::write(rig.dir.join("files.lua"), text).expect("script");
    let task = script::add(&rig.rt, "files", ActivitySpec::Slave).expect("built");
    let p = task.properties();
    p.set_value("file", json!("files.lua")).expect("file");
    p.set_value("base_dir", json!(rig.dir)).expect("base");
    p.set_value("data_dir", json!("data")).expect("data");
    task.configure().expect("configures");
    assert_eq!(
        std::fs::read_to_string(rig.dir.join("data/out.txt")).expect("written"),
        "got 12.5\n"
    );
    assert!(!rig.dir.join("escape.txt").exists());
}

const MACHINE: &str = r#"
local go = port.input("go", "bool", { event = true })
local busy = port.output("busy", "bool")
rootmachine {
  initial = "idle", final = "off",
  states = {
    idle = { entry = function() busy:write(false) end,
             transitions = { { event = go, guard = function(_, v) return v end, to = "running" } } },
    running = { entry = function() busy:write(true) end,
                transitions = { { event = "halt", to = "idle" } } },
    homing = { transitions = { { to = "idle" } } },
    off = {},
  },
}
"#;

#[test]
fn the_root_machine_through_ports_events_and_operations() {
    let rig = Rig::new("machine");
    let (task, r) = rig.script("sup", MACHINE);
    r.expect("configures");
    task.start().expect("starts");
    assert_eq!(call(&task, "get_state", vec![]), json!("idle"));
    let mut go = writer(&task, "go");
    go.write(json!(true)).expect("go");
    task.step().expect("a step");
    assert_eq!(value(&task, "state"), Some(json!("running")));
    assert_eq!(value(&task, "busy"), Some(json!(true)));
    call(&task, "emit", vec![json!("halt")]);
    task.step().expect("a step");
    assert_eq!(call(&task, "get_state", vec![]), json!("idle"));
    let refused = try_call(&task, "request_state", vec![json!("homing")]);
    let e = refused.expect_err("idle has no transition to homing");
    assert!(e.contains("homing"), "{e}");
    assert_eq!(call(&task, "in_state", vec![json!("idle")]), json!(true));
    task.stop().expect("stops");
    assert_eq!(
        value(&task, "state"),
        Some(json!("idle")),
        "the port keeps the last step's"
    );
}

#[test]
fn programs_run_a_step_at_a_time_and_are_operations() {
    let rig = Rig::new("programs");
    let text = r#"
local out = port.output("out", "i64")
program("count", function()
  for i = 1, 3 do out:write(i); yield() end
end)
"#;
    let (task, r) = rig.script("prog", text);
    r.expect("configures");
    task.start().expect("starts");
    // The call is answered at a step, before its update: the program runs there once.
    call(&task, "program.start", vec![json!("count")]);
    assert_eq!(value(&task, "out"), Some(json!(1)));
    for i in 2..=3 {
        task.step().expect("a step");
        assert_eq!(value(&task, "out"), Some(json!(i)));
    }
    task.step().expect("a step");
    assert_eq!(
        call(&task, "program.is_running", vec![json!("count")]),
        json!(false)
    );
    let e = try_call(&task, "program.start", vec![json!("nope")]).expect_err("unknown");
    assert!(e.contains("count"), "{e}");
}

#[test]
fn reload_replaces_a_stopped_script_and_keeps_the_old_one_on_failure() {
    let rig = Rig::new("reload");
    let (task, r) = rig.script(
        "r",
        "local o = port.output('o', 'i64')\nfunction update() o:write(1) end\n",
    );
    r.expect("configures");
    rig.write(
        "r",
        "local o = port.output('o', 'i64')\nfunction update() o:write(2) end\n",
    );
    task.start().expect("starts");
    assert!(
        try_call(&task, "reload_script", vec![]).is_err(),
        "refused while running"
    );
    task.stop().expect("stops");
    call(&task, "reload_script", vec![]);
    task.start().expect("starts");
    task.step().expect("a step");
    assert_eq!(value(&task, "o"), Some(json!(2)));
    task.stop().expect("stops");
    rig.write(
        "r",
        "local o = port.output('o', 'i64')\nfunction update( o:write(3) end\n",
    );
    let e = try_call(&task, "reload_script", vec![]).expect_err("broken");
    assert!(e.contains("r.lua:2:") && e.contains("stays"), "{e}");
    rig.write("r", "local o = port.output('o', 'bool')\n");
    let e = try_call(&task, "reload_script", vec![]).expect_err("retyped");
    assert!(e.contains("declared before as an output of i64"), "{e}");
    task.start().expect("starts");
    task.step().expect("a step");
    assert_eq!(value(&task, "o"), Some(json!(2)), "the old script runs on");
}

struct Limits;
impl rtt::Component for Limits {}

#[test]
fn services_peers_calls_and_sends_from_a_script() {
    let rig = Rig::new("services");
    let thr = rig
        .rt
        .add(
            "thr",
            ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            |i: &mut rtt::InterfaceBuilder<Limits>| {
                i.provides("limit")
                    .client_operation("max", "the limit", &[], |(): ()| 42.5f64)?;
                i.client_operation("twice", "", &[("x", "")], |(x,): (f64,)| 2.0 * x)?;
                Ok(Limits)
            },
        )
        .expect("the provider");
    thr.start().expect("starts");
    let text = r#"
local called = port.output("called", "f64")
local sent = port.output("sent", "f64")
local limit = service("limit")
assert(limit:provider() == "thr" and limit:ready())
program("ask", function()
  sent:write(wait(component("thr"):send("twice", 4)))
end)
function update() called:write(limit:call("max")) end
"#;
    let (task, r) = rig.script("svc", text);
    r.expect("configures");
    task.start().expect("starts");
    call(&task, "program.start", vec![json!("ask")]);
    for _ in 0..3 {
        task.step().expect("a step");
    }
    assert_eq!(value(&task, "called"), Some(json!(42.5)));
    assert_eq!(value(&task, "sent"), Some(json!(8.0)));
    let (_, r) = rig.script("nosvc", "service('camera')\n");
    let e = r.expect_err("no provider");
    assert!(e.contains("nosvc.lua:1:") && e.contains("camera"), "{e}");
}

/// Escapes the first review found: a protected-call loop past the deadline, C functions
/// the hook cannot stop, finalizers, a script lifting its own bounds or reloading itself.
#[test]
fn the_sandbox_holds_against_protected_loops_c_functions_and_its_own_component() {
    let rig = Rig::new("escapes");
    let (task, r) = rig.script(
        "ploop",
        "function update()\n  while true do pcall(function() for i = 1, 1e15 do end end) end\nend\n",
    );
    r.expect("configures");
    task.properties()
        .set_value("max_step_us", json!(20_000))
        .expect("set");
    task.lifecycle_reconfigure();
    task.start().expect("starts");
    let _ = task.step();
    assert_eq!(
        task.state(),
        TaskState::Exception,
        "a pcall loop is stopped too"
    );
    let last = task.counters().last_error.unwrap_or_default();
    assert!(last.contains("ran past its time"), "{last}");

    let text = r##"
assert(string.rep("", math.maxinteger) == "")
assert(not pcall(string.rep, "x", 1 << 50))
local ok, e = pcall(string.find, ("a"):rep(80), (".-"):rep(20) .. "b")
assert(not ok and e:find("too costly"), e)
ok, e = pcall(setmetatable, {}, { __gc = function() while true do end end })
assert(not ok and e:find("__gc"), e)
assert(load("return math.pi")() == math.pi)
assert(select("#", ("x"):find("x", 1, true)) == 2)
local me = component(rtt.name())
ok, e = pcall(me.call, me, "get_state")
assert(not ok and tostring(e):find("own component"), tostring(e))
local other = component("ploop")
ok, e = pcall(other.set_property, other, "data_dir", "/")
assert(not ok and tostring(e):find("does not set"), tostring(e))
ok, e = pcall(other.call, other, "reload_script")
assert(not ok and tostring(e):find("not from a script"), tostring(e))
"##;
    let (_, r) = rig.script("guards", text);
    r.expect("every guard holds");
}

trait Reconfigure {
    fn lifecycle_reconfigure(&self);
}

impl Reconfigure for TaskContext {
    /// Configures again (properties read at configure take effect).
    fn lifecycle_reconfigure(&self) {
        self.configure().expect("configures again");
    }
}

#[test]
fn a_call_to_a_peer_that_does_not_answer_ends_with_the_steps_time() {
    let rig = Rig::new("callwait");
    // A slave nobody steps: its own-thread operations are never answered.
    let (mute, r) = rig.script(
        "mute",
        "rootmachine { initial = 'a', final = 'b', states = { a = {}, b = {} } }\n",
    );
    r.expect("configures");
    mute.start().expect("starts");
    let (task, r) = rig.script(
        "caller",
        "function update()\n  component('mute'):call('get_state')\nend\n",
    );
    r.expect("configures");
    task.properties()
        .set_value("max_step_us", json!(50_000))
        .expect("set");
    task.lifecycle_reconfigure();
    task.start().expect("starts");
    let began = std::time::Instant::now();
    let _ = task.step();
    assert!(
        began.elapsed() < std::time::Duration::from_secs(5),
        "bounded"
    );
    assert_eq!(task.state(), TaskState::Exception);
    let last = task.counters().last_error.unwrap_or_default();
    assert!(
        last.contains("caller.lua:2:") && last.contains("no answer"),
        "{last}"
    );
}

struct SelfStopper {
    me: Option<rtt::component::SelfRef>,
    said: Arc<std::sync::Mutex<String>>,
}

impl rtt::Component for SelfStopper {
    fn configure_hook(&mut self, ctx: &mut rtt::Context<'_>) -> rtt::HookResult {
        self.me = Some(ctx.self_ref());
        Ok(())
    }
    fn update_hook(&mut self, _: &mut rtt::Context<'_>) -> rtt::HookResult {
        if let Some(t) = self.me.as_ref().and_then(|m| m.task()) {
            *self.said.lock().expect("said") = format!("{:?}", t.stop());
        }
        Ok(())
    }
}

/// A component stopping itself from its own step is refused, not dead-locked.
#[test]
fn a_lifecycle_command_from_the_components_own_step_is_refused() {
    let rig = Rig::new("reentrant");
    let said = Arc::new(std::sync::Mutex::new(String::new()));
    let s = said.clone();
    let task = rig
        .rt
        .add(
            "selfstop",
            ActivitySpec::Slave,
            rtt::InitialState::PreOperational,
            move |_| Ok(SelfStopper { me: None, said: s }),
        )
        .expect("built");
    task.configure().expect("configures");
    task.start().expect("starts");
    task.step().expect("a step");
    let said = said.lock().expect("said").clone();
    assert!(said.contains("Reentrant"), "{said}");
    assert_eq!(task.state(), TaskState::Running);
}
