//! What a script reaches, as Lua globals, all through the by-name layer `browse` uses:
//! `port` (its own ports), `component(name)` (another component's ports, properties,
//! operations and lifecycle), `service(name)` (a service another component provides), `device` (devices from the registry by name and
//! interface), `log` (and `print`), `rtt` (the error model's requests and the time),
//! `vars` (values the deployment passes in), `io.open` within `data_dir`.

use crate::host::Host;
use crate::peers::LuaPeer;
use crate::ports::{Declaration, LuaPort};
use mlua::{Lua, LuaSerdeExt, Table, Value, Variadic};

fn host<R>(lua: &Lua, f: impl FnOnce(&mut Host) -> R) -> mlua::Result<R> {
    let mut h = lua
        .app_data_mut::<Host>()
        .ok_or_else(|| mlua::Error::runtime("the script's host is gone"))?;
    Ok(f(&mut h))
}

/// Installs the globals in `lua`, `vars` among them.
pub fn install(lua: &Lua, vars: &serde_json::Value) -> mlua::Result<()> {
    let g = lua.globals();
    g.set("port", ports(lua)?)?;
    g.set("log", log(lua)?)?;
    g.set("rtt", rtt_table(lua)?)?;
    g.set("device", crate::devices::table(lua)?)?;
    g.set(
        "component",
        lua.create_function(|lua, name: String| {
            let peer = host(lua, |h| h.me.peer(&name))?.map_err(mlua::Error::external)?;
            let own = host(lua, |h| h.name.clone())?;
            Ok(LuaPeer::new(peer, own))
        })?,
    )?;
    g.set(
        "service",
        lua.create_function(|lua, name: String| {
            let (me, own) = host(lua, |h| (h.me.clone(), h.name.clone()))?;
            let task = me.provider(&name).map_err(mlua::Error::external)?;
            Ok(crate::peers::LuaService::new(task, own, name))
        })?,
    )?;
    g.set(
        "now",
        lua.create_function(|_, ()| {
            use device_interface::time::Clock;
            Ok(device_interface::time::MonotonicClock.now().as_secs_f64())
        })?,
    )?;
    let info: mlua::Function = g.get::<Table>("log")?.get("info")?;
    g.set("print", info)?;
    g.set("vars", lua.to_value(vars)?)?;
    crate::files::install(lua)?;
    Ok(())
}

fn ports(lua: &Lua) -> mlua::Result<Table> {
    let t = lua.create_table()?;
    for (key, input) in [("input", true), ("output", false)] {
        let f = lua.create_function(
            move |lua, (name, type_name, opts): (String, String, Option<Table>)| {
                let event = match &opts {
                    Some(o) => o.get::<Option<bool>>("event")?.unwrap_or(false),
                    None => false,
                };
                let doc = match &opts {
                    Some(o) => o.get::<Option<String>>("doc")?.unwrap_or_default(),
                    None => String::new(),
                };
                if event && !input {
                    return Err(mlua::Error::runtime(format!(
                        "port {name:?}: only an input can be an event port"
                    )));
                }
                let d = Declaration {
                    name: &name,
                    type_name: &type_name,
                    input,
                    event,
                    doc: &doc,
                };
                let port = host(lua, |h| {
                    if !h.declaring {
                        return Err(mlua::Error::runtime(format!(
                            "port.{}({name:?}): ports are declared at the script's top level, \
                             when it loads",
                            if input { "input" } else { "output" }
                        )));
                    }
                    crate::ports::declare(&h.ports, &h.me, &d).map_err(mlua::Error::external)
                })??;
                Ok(LuaPort(port))
            },
        )?;
        t.set(key, f)?;
    }
    Ok(t)
}

fn log(lua: &Lua) -> mlua::Result<Table> {
    let t = lua.create_table()?;
    for level in ["debug", "info", "warn", "error"] {
        let f = lua.create_function(move |lua, args: Variadic<Value>| {
            let text = args
                .iter()
                .map(|v| v.to_string().unwrap_or_else(|_| format!("{v:?}")))
                .collect::<Vec<_>>()
                .join("\t");
            let at = where_called(lua);
            let name = host(lua, |h| h.name.clone())?;
            match level {
                "debug" => tracing::debug!("script {name:?} {at}{text}"),
                "info" => tracing::info!("script {name:?} {at}{text}"),
                "warn" => tracing::warn!("script {name:?} {at}{text}"),
                _ => tracing::error!("script {name:?} {at}{text}"),
            }
            Ok(())
        })?;
        t.set(level, f)?;
    }
    Ok(t)
}

/// `file:line: ` of the script code that called the running function, or nothing.
fn where_called(lua: &Lua) -> String {
    lua.inspect_stack(1, |d| {
        let src = d.source();
        let file = src.short_src.map(|s| s.to_string()).unwrap_or_default();
        match d.current_line() {
            Some(line) => format!("{file}:{line}: "),
            None => String::new(),
        }
    })
    .unwrap_or_default()
}

fn rtt_table(lua: &Lua) -> mlua::Result<Table> {
    let t = lua.create_table()?;
    t.set(
        "error",
        lua.create_function(|lua, ()| host(lua, |h| h.ask(|r| r.error = true)))?,
    )?;
    t.set(
        "recover",
        lua.create_function(|lua, ()| host(lua, |h| h.ask(|r| r.recover = true)))?,
    )?;
    t.set(
        "warning",
        lua.create_function(|lua, ()| host(lua, |h| h.ask(|r| r.warning = true)))?,
    )?;
    t.set(
        "recovered",
        lua.create_function(|lua, ()| host(lua, |h| h.ask(|r| r.recovered = true)))?,
    )?;
    t.set(
        "exception",
        lua.create_function(|lua, reason: String| {
            let at = where_called(lua);
            host(lua, |h| {
                h.ask(|r| r.exception = Some(format!("{at}{reason}")))
            })
        })?,
    )?;
    t.set(
        "name",
        lua.create_function(|lua, ()| host(lua, |h| h.name.clone()))?,
    )?;
    Ok(t)
}
