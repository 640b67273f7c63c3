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

    fn set(&mut self, port: &str, value: serde_json::Value) -> mlua::Result<()> {
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

    fn lifecycle(&self, what: &str) -> mlua::Result<()> {
        if self.task.name() == self.own {
            return Err(mlua::Error::runtime(format!(
                "{what}: a script does not change its own component's lifecycle; \
                 use rtt.error(), rtt.exception() or rtt.recover()"
            )));
        }
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
            let v = json(lua, v)?;
            this.task
                .properties()
                .set_value(&name, v)
                .map_err(mlua::Error::external)
        });
        methods.add_method("call", |lua, this, (op, a): (String, MultiValue)| {
            let a = args(lua, a)?;
            let r = this
                .task
                .call_value(&op, a)
                .map_err(mlua::Error::external)?;
            lua.to_value(&r)
        });
        methods.add_method("send", |lua, this, (op, a): (String, MultiValue)| {
            let a = args(lua, a)?;
            let h = this
                .task
                .send_value(&op, a)
                .map_err(mlua::Error::external)?;
            Ok(SendHandle(Some(h)))
        });
        for what in ["configure", "start", "stop", "cleanup", "recover"] {
            methods.add_method(what, move |_, this, ()| this.lifecycle(what));
        }
        methods.add_meta_method("__tostring", |_, this, ()| {
            Ok(format!("component {:?}", this.task.name()))
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
