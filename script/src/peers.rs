//! Another component as a script reaches it: `component("pump")` gives its ports
//! (`get`, `set`), properties (`property`, `set_property`), operations (`call`, and
//! `send` with a handle to `collect_if_done`), and its lifecycle (`state`, `configure`,
//! `start`, `stop`, `cleanup`, `recover`). Values cross as JSON, as `hwgw get`/`set`/`call`
//! send them: for configuration and supervision, not for a real-time path (connect ports
//! for that).

use mlua::{Lua, LuaSerdeExt, MultiValue, UserData, UserDataMethods, Value};
use rtt::TaskContext;
use rtt::component::DynWriter;
use rtt::port::ConnPolicy;
use std::collections::BTreeMap;

/// A peer component held by a script.
pub struct LuaPeer {
    task: TaskContext,
    /// The script's own component: its lifecycle is not the script's to change.
    own: String,
    /// Writers to the peer's input ports, made at the first `set`.
    writers: BTreeMap<String, Box<dyn DynWriter>>,
}

impl LuaPeer {
    /// `task` as seen from the script of component `own`.
    pub fn new(task: TaskContext, own: String) -> Self {
        LuaPeer {
            task,
            own,
            writers: BTreeMap::new(),
        }
    }

    /// Calls `op`: sent, then waited for no longer than the step's time left (1 s
    /// without a limit), so that two components calling each other cannot wait forever.
    fn call(&self, lua: &Lua, op: &str, a: Vec<serde_json::Value>) -> mlua::Result<Value> {
        self.not_own(&format!("call({op:?})"))?;
        refuse_operation(op)?;
        let mut h = self.task.send_value(op, a).map_err(mlua::Error::external)?;
        let limit = lua
            .app_data_ref::<crate::host::Host>()
            .and_then(|h| h.deadline.remaining())
            .unwrap_or(CALL_WAIT);
        let began = std::time::Instant::now();
        loop {
            if let Some(r) = h.collect_if_done() {
                return lua.to_value(&r.map_err(mlua::Error::external)?);
            }
            if began.elapsed() >= limit {
                return Err(mlua::Error::runtime(format!(
                    "call({op:?}) of {:?}: no answer within {} µs (the step's time left)",
                    self.task.name(),
                    limit.as_micros()
                )));
            }
            std::thread::yield_now();
        }
    }

    fn send(&self, lua: &Lua, op: &str, a: MultiValue) -> mlua::Result<SendHandle> {
        self.not_own(&format!("send({op:?})"))?;
        refuse_operation(op)?;
        let a = args(lua, a)?;
        let h = self.task.send_value(op, a).map_err(mlua::Error::external)?;
        Ok(SendHandle(Some(h)))
    }

    fn set(&mut self, port: &str, value: serde_json::Value) -> mlua::Result<()> {
        self.not_own("set")?;
        if !self.writers.contains_key(port) {
            let p = self.task.port(port).map_err(mlua::Error::external)?;
            if let Some(r) = p.drive(value.clone()) {
                // A device output: written now, through its checks.
                return r.map_err(mlua::Error::external);
            }
            let w = p
                .writer(ConnPolicy::data())
                .map_err(mlua::Error::external)?;
            self.writers.insert(port.to_string(), w);
        }
        match self.writers.get_mut(port) {
            Some(w) => w.write(value).map_err(mlua::Error::external),
            None => Ok(()),
        }
    }

    /// Refuses what a script may not do to its own component (it runs inside it: a
    /// lifecycle command or an own-thread call would wait for itself).
    fn not_own(&self, what: &str) -> mlua::Result<()> {
        if self.task.name() == self.own {
            return Err(mlua::Error::runtime(format!(
                "{what}: not on the script's own component (use rtt.error(), \
                 rtt.exception(), rtt.recover(), or the script's own functions)"
            )));
        }
        Ok(())
    }

    fn lifecycle(&self, what: &str) -> mlua::Result<()> {
        self.not_own(what)?;
        let r = match what {
            "configure" => self.task.configure(),
            "start" => self.task.start(),
            "stop" => self.task.stop(),
            "cleanup" => self.task.cleanup(),
            _ => self.task.recover(),
        };
        r.map_err(mlua::Error::external)
    }
}

/// How long a script's `call` waits for an answer when the step has no time limit.
const CALL_WAIT: std::time::Duration = std::time::Duration::from_secs(1);

/// Properties a script may not set on any component: where files are and the bounds of
/// a script (set through them, a script would reach outside its sandbox, or lift it).
const GUARDED: [&str; 6] = [
    "file",
    "base_dir",
    "data_dir",
    "memory_kb",
    "max_step_us",
    "gc_step_kb",
];

/// Operations a script may not call: a reload runs another script's configure.
fn refuse_operation(op: &str) -> mlua::Result<()> {
    if op == "reload_script" {
        return Err(mlua::Error::runtime(
            "reload_script: not from a script (the operator's or the deployment's)",
        ));
    }
    Ok(())
}

fn json(lua: &Lua, v: Value) -> mlua::Result<serde_json::Value> {
    lua.from_value(v)
}

fn args(lua: &Lua, args: MultiValue) -> mlua::Result<Vec<serde_json::Value>> {
    args.into_iter().map(|v| json(lua, v)).collect()
}

impl UserData for LuaPeer {
    fn add_methods<M: UserDataMethods<Self>>(methods: &mut M) {
        methods.add_method("name", |_, this, ()| Ok(this.task.name().to_string()));
        methods.add_method("state", |_, this, ()| {
            Ok(format!("{:?}", this.task.state()))
        });
        methods.add_method("get", |lua, this, port: String| {
            let p = this.task.port(&port).map_err(mlua::Error::external)?;
            let v = p.last_value().map_err(mlua::Error::external)?;
            lua.to_value(&v)
        });
        methods.add_method_mut("set", |lua, this, (port, v): (String, Value)| {
            let v = json(lua, v)?;
            this.set(&port, v)
        });
        methods.add_method("property", |lua, this, name: String| {
            let v = this
                .task
                .properties()
                .get_value(&name)
                .map_err(mlua::Error::external)?;
            lua.to_value(&v)
        });
        methods.add_method("set_property", |lua, this, (name, v): (String, Value)| {
            this.not_own("set_property")?;
            if GUARDED.contains(&name.as_str()) {
                return Err(mlua::Error::runtime(format!(
                    "set_property({name:?}): a script does not set where files are or the \
                     bounds of a component ({}): the deployment does",
                    GUARDED.join(", ")
                )));
            }
            let v = json(lua, v)?;
            this.task
                .properties()
                .set_value(&name, v)
                .map_err(mlua::Error::external)
        });
        methods.add_method("call", |lua, this, (op, a): (String, MultiValue)| {
            let a = args(lua, a)?;
            this.call(lua, &op, a)
        });
        methods.add_method("send", |lua, this, (op, a): (String, MultiValue)| {
            this.send(lua, &op, a)
        });
        for what in ["configure", "start", "stop", "cleanup", "recover"] {
            methods.add_method(what, move |_, this, ()| this.lifecycle(what));
        }
        methods.add_meta_method("__tostring", |_, this, ()| {
            Ok(format!("component {:?}", this.task.name()))
        });
    }
}

/// A service of another component as a script reaches it: `service("limit")` finds the
/// component providing it (by the component's `peers` alias of that name, else the one
/// provider); `call(op, ...)` and `send(op, ...)` reach `limit.op`; `ready()` is whether
/// the provider runs.
pub struct LuaService {
    peer: LuaPeer,
    service: String,
}

impl LuaService {
    /// Service `service` of `task`, seen from component `own`.
    pub fn new(task: TaskContext, own: String, service: String) -> Self {
        LuaService {
            peer: LuaPeer::new(task, own),
            service,
        }
    }
}

impl UserData for LuaService {
    fn add_methods<M: UserDataMethods<Self>>(methods: &mut M) {
        methods.add_method("provider", |_, this, ()| {
            Ok(this.peer.task.name().to_string())
        });
        methods.add_method("ready", |_, this, ()| {
            Ok(this.peer.task.state() == rtt::TaskState::Running)
        });
        methods.add_method("call", |lua, this, (op, a): (String, MultiValue)| {
            let a = args(lua, a)?;
            this.peer.call(lua, &format!("{}.{op}", this.service), a)
        });
        methods.add_method("send", |lua, this, (op, a): (String, MultiValue)| {
            this.peer.send(lua, &format!("{}.{op}", this.service), a)
        });
    }
}

/// What `send` gives: `collect_if_done()` is nothing while the call runs, then
/// `true, result` or `false, message` once.
pub struct SendHandle(Option<rtt::operation::ValueHandle>);

impl UserData for SendHandle {
    fn add_methods<M: UserDataMethods<Self>>(methods: &mut M) {
        methods.add_method_mut("collect_if_done", |lua, this, ()| {
            let Some(h) = this.0.as_mut() else {
                return Ok((
                    Value::Boolean(false),
                    Value::String(lua.create_string("collected already")?),
                ));
            };
            match h.collect_if_done() {
                None => Ok((Value::Nil, Value::Nil)),
                Some(Ok(v)) => {
                    this.0 = None;
                    Ok((Value::Boolean(true), lua.to_value(&v)?))
                }
                Some(Err(e)) => {
                    this.0 = None;
                    Ok((
                        Value::Boolean(false),
                        Value::String(lua.create_string(e.to_string())?),
                    ))
                }
            }
        });
    }
}
