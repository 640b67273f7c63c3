//! The script's own ports: declared by the script (`port.input("limit", "bool")`,
//! `port.output("alarm", "bool")`) while the component configures, typed, and kept by the
//! component across reloads so that connections made to them stay.
//!
//! A port is read and written from Lua without JSON: a step's port access costs a lock
//! that is never contended (only the component's own thread steps the script) and the
//! copy of the value.

use crate::error::ScriptError;
use mlua::{IntoLua, Lua, UserData, UserDataMethods, Value};
use rtt::component::SelfRef;
use rtt::port::{FlowStatus, InputPort, OutputPort};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

/// The types a script's port may carry, by the names `describe` shows.
pub const TYPES: [&str; 7] = ["bool", "f64", "i64", "u64", "i32", "u32", "String"];

/// The most ports one script component declares (over all its reloads).
pub const MAX_PORTS: usize = 256;

/// One typed port of either direction.
enum Typed {
    InBool(InputPort<bool>, bool),
    InF64(InputPort<f64>, f64),
    InI64(InputPort<i64>, i64),
    InU64(InputPort<u64>, u64),
    InI32(InputPort<i32>, i32),
    InU32(InputPort<u32>, u32),
    InString(InputPort<String>, String),
    OutBool(OutputPort<bool>),
    OutF64(OutputPort<f64>),
    OutI64(OutputPort<i64>),
    OutU64(OutputPort<u64>),
    OutI32(OutputPort<i32>),
    OutU32(OutputPort<u32>),
    OutString(OutputPort<String>),
}

/// A declared port: its type name, direction and the port itself.
pub struct Port {
    name: String,
    type_name: &'static str,
    input: bool,
    event: bool,
    typed: Typed,
}

/// The component's ports by name, shared by the component and its Lua state.
pub type PortMap = Arc<Mutex<BTreeMap<String, Arc<Mutex<Port>>>>>;

/// What a declaration asks for.
pub struct Declaration<'a> {
    /// The port's name.
    pub name: &'a str,
    /// Its type, one of [`TYPES`] (`"string"`, `"double"`, `"int"` too).
    pub type_name: &'a str,
    /// An input (else an output).
    pub input: bool,
    /// An event input: data on it wakes a non-periodic activity.
    pub event: bool,
    /// Its documentation.
    pub doc: &'a str,
}

fn canonical(type_name: &str) -> Option<&'static str> {
    Some(match type_name {
        "bool" => "bool",
        "f64" | "double" | "number" => "f64",
        "i64" | "int" | "integer" => "i64",
        "u64" => "u64",
        "i32" => "i32",
        "u32" => "u32",
        "String" | "string" => "String",
        _ => return None,
    })
}

/// The port declared: the one kept from an earlier load when it has the same type and
/// direction, else a new one added to the component.
pub fn declare(
    ports: &PortMap,
    me: &SelfRef,
    d: &Declaration<'_>,
) -> Result<Arc<Mutex<Port>>, ScriptError> {
    let bad = |detail: String| ScriptError::Port {
        port: d.name.to_string(),
        detail,
    };
    let type_name = canonical(d.type_name).ok_or_else(|| {
        bad(format!(
            "unknown type {:?}; a script's port is one of: {}",
            d.type_name,
            TYPES.join(", ")
        ))
    })?;
    if d.name.is_empty()
        || !d
            .name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        return Err(bad(
            "a port's name is letters, digits, '_' and '-' (a '.' would read as a component's)"
                .into(),
        ));
    }
    let mut map = rtt::lock(ports);
    if !map.contains_key(d.name) && map.len() >= MAX_PORTS {
        return Err(bad(format!(
            "a script component has at most {MAX_PORTS} ports (ports stay for the component's life)"
        )));
    }
    if let Some(p) = map.get(d.name) {
        let kept = rtt::lock(p);
        if kept.type_name != type_name || kept.input != d.input || kept.event != d.event {
            return Err(bad(format!(
                "declared before as {}; a port stays what it was declared as for the \
                 component's life (reload the deployment to change it)",
                kept.describe()
            )));
        }
        drop(kept);
        return Ok(p.clone());
    }
    let typed = if d.input {
        new_input(me, d, type_name)
    } else {
        new_output(me, d, type_name)
    }
    .map_err(|e| bad(e.to_string()))?;
    let port = Arc::new(Mutex::new(Port {
        name: d.name.to_string(),
        type_name,
        input: d.input,
        event: d.event,
        typed,
    }));
    map.insert(d.name.to_string(), port.clone());
    Ok(port)
}

fn new_input(
    me: &SelfRef,
    d: &Declaration<'_>,
    type_name: &str,
) -> Result<Typed, rtt::component::IntrospectError> {
    let (n, doc, ev) = (d.name, d.doc, d.event);
    Ok(match type_name {
        "bool" => Typed::InBool(me.add_input(n, doc, ev)?, false),
        "f64" => Typed::InF64(me.add_input(n, doc, ev)?, 0.0),
        "i64" => Typed::InI64(me.add_input(n, doc, ev)?, 0),
        "u64" => Typed::InU64(me.add_input(n, doc, ev)?, 0),
        "i32" => Typed::InI32(me.add_input(n, doc, ev)?, 0),
        "u32" => Typed::InU32(me.add_input(n, doc, ev)?, 0),
        _ => Typed::InString(me.add_input(n, doc, ev)?, String::new()),
    })
}

fn new_output(
    me: &SelfRef,
    d: &Declaration<'_>,
    type_name: &str,
) -> Result<Typed, rtt::component::IntrospectError> {
    let (n, doc) = (d.name, d.doc);
    Ok(match type_name {
        "bool" => Typed::OutBool(me.add_output(n, doc)?),
        "f64" => Typed::OutF64(me.add_output(n, doc)?),
        "i64" => Typed::OutI64(me.add_output(n, doc)?),
        "u64" => Typed::OutU64(me.add_output(n, doc)?),
        "i32" => Typed::OutI32(me.add_output(n, doc)?),
        "u32" => Typed::OutU32(me.add_output(n, doc)?),
        _ => Typed::OutString(me.add_output(n, doc)?),
    })
}

impl Port {
    fn describe(&self) -> String {
        let dir = match (self.input, self.event) {
            (true, true) => "an event input",
            (true, false) => "an input",
            _ => "an output",
        };
        format!("{dir} of {}", self.type_name)
    }

    /// Reads the port: the value (the last one kept when there is no new data) and
    /// "new", "old" or "none".
    fn read(&mut self, lua: &Lua) -> mlua::Result<(Value, &'static str)> {
        fn status(s: FlowStatus) -> &'static str {
            match s {
                FlowStatus::NewData => "new",
                FlowStatus::OldData => "old",
                FlowStatus::NoData => "none",
            }
        }
        let (value, s) = match &mut self.typed {
            Typed::InBool(p, v) => {
                let s = p.read(v);
                (Value::Boolean(*v), s)
            }
            Typed::InF64(p, v) => {
                let s = p.read(v);
                (Value::Number(*v), s)
            }
            Typed::InI64(p, v) => {
                let s = p.read(v);
                (Value::Integer(*v), s)
            }
            Typed::InU64(p, v) => {
                let s = p.read(v);
                (u64_value(*v), s)
            }
            Typed::InI32(p, v) => {
                let s = p.read(v);
                (Value::Integer(i64::from(*v)), s)
            }
            Typed::InU32(p, v) => {
                let s = p.read(v);
                (Value::Integer(i64::from(*v)), s)
            }
            Typed::InString(p, v) => {
                let s = p.read(v);
                (v.as_str().into_lua(lua)?, s)
            }
            _ => return Err(self.wrong_direction("read")),
        };
        Ok((
            if s == FlowStatus::NoData {
                Value::Nil
            } else {
                value
            },
            status(s),
        ))
    }

    /// Writes `value` to the output port, converted exactly or refused.
    fn write(&mut self, value: Value) -> mlua::Result<()> {
        let name = &self.name;
        let refuse = |what: &str| {
            mlua::Error::runtime(format!(
                "port {name:?}: {what} does not fit {}",
                value_kind(&value)
            ))
        };
        match &mut self.typed {
            Typed::OutBool(p) => match value {
                Value::Boolean(b) => p.write(&b),
                _ => return Err(refuse("bool")),
            },
            Typed::OutF64(p) => match value {
                Value::Number(x) => p.write(&x),
                // Integers up to 2^53 in magnitude are exact as f64; larger ones are
                // refused, never rounded.
                Value::Integer(i) if i.unsigned_abs() <= 1 << 53 => p.write(&(i as f64)),
                _ => return Err(refuse("f64")),
            },
            Typed::OutI64(p) => p.write(&integer(&value).ok_or_else(|| refuse("i64"))?),
            Typed::OutU64(p) => {
                let v = integer(&value).and_then(|i| u64::try_from(i).ok());
                p.write(&v.ok_or_else(|| refuse("u64"))?);
            }
            Typed::OutI32(p) => {
                let v = integer(&value).and_then(|i| i32::try_from(i).ok());
                p.write(&v.ok_or_else(|| refuse("i32"))?);
            }
            Typed::OutU32(p) => {
                let v = integer(&value).and_then(|i| u32::try_from(i).ok());
                p.write(&v.ok_or_else(|| refuse("u32"))?);
            }
            Typed::OutString(p) => match &value {
                Value::String(s) => p.write(&s.to_str()?.to_string()),
                _ => return Err(refuse("String")),
            },
            _ => return Err(self.wrong_direction("write")),
        }
        Ok(())
    }

    fn wrong_direction(&self, what: &str) -> mlua::Error {
        mlua::Error::runtime(format!(
            "port {:?} is {}; it cannot {what}",
            self.name,
            self.describe()
        ))
    }
}

/// A u64 as Lua sees it: an integer when it fits i64, else a float only when exact.
fn u64_value(v: u64) -> Value {
    match i64::try_from(v) {
        Ok(i) => Value::Integer(i),
        Err(_) => Value::Number(v as f64),
    }
}

/// An integer value: a Lua integer, or a float with no fraction that fits.
fn integer(v: &Value) -> Option<i64> {
    match v {
        Value::Integer(i) => Some(*i),
        Value::Number(x) if x.fract() == 0.0 && x.abs() < 9.2e18 => Some(*x as i64),
        _ => None,
    }
}

fn value_kind(v: &Value) -> String {
    match v {
        Value::Integer(i) => format!("integer {i}"),
        Value::Number(x) => format!("number {x}"),
        Value::Boolean(b) => format!("boolean {b}"),
        Value::String(s) => format!("string {:?}", s.to_string_lossy()),
        other => other.type_name().to_string(),
    }
}

/// A port as Lua holds it.
pub struct LuaPort(pub Arc<Mutex<Port>>);

impl UserData for LuaPort {
    fn add_methods<M: UserDataMethods<Self>>(methods: &mut M) {
        methods.add_method("read", |lua, this, ()| rtt::lock(&this.0).read(lua));
        methods.add_method("write", |_, this, v: Value| rtt::lock(&this.0).write(v));
        methods.add_method("name", |_, this, ()| Ok(rtt::lock(&this.0).name.clone()));
        methods.add_meta_method("__tostring", |_, this, ()| {
            let p = rtt::lock(&this.0);
            Ok(format!("port {:?} ({})", p.name, p.describe()))
        });
    }
}
