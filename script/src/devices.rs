//! Devices from the registry, by name and interface: `device.digital_in("press")`,
//! `device.digital_out`, `device.analog_in`, `device.analog_out`, `device.encoder`. A
//! device's error (offline, stale, out of range, held at a stop) is a Lua error with the
//! device's message: a script that expects it catches it with `pcall`.

use crate::host::Host;
use device_interface::{AnalogIn, AnalogOut, DeviceError, DigitalIn, DigitalOut, Encoder};
use mlua::{Lua, Table, UserData, UserDataMethods};
use std::sync::Arc;

fn fail(e: DeviceError) -> mlua::Error {
    mlua::Error::runtime(e.to_string())
}

/// A device as a script holds it.
pub enum LuaDevice {
    /// A DigitalIn.
    DigitalIn(String, Arc<dyn DigitalIn>),
    /// A DigitalOut.
    DigitalOut(String, Arc<dyn DigitalOut>),
    /// An AnalogIn.
    AnalogIn(String, Arc<dyn AnalogIn>),
    /// An AnalogOut.
    AnalogOut(String, Arc<dyn AnalogOut>),
    /// An Encoder.
    Encoder(String, Arc<dyn Encoder>),
}

/// The `device` table.
pub fn table(lua: &Lua) -> mlua::Result<Table> {
    let t = lua.create_table()?;
    let lookup = |lua: &Lua, kind: &'static str, name: String| -> mlua::Result<LuaDevice> {
        let registry = lua
            .app_data_ref::<Host>()
            .map(|h| h.registry.clone())
            .ok_or_else(|| mlua::Error::runtime("the script's host is gone"))?;
        let e = mlua::Error::external;
        Ok(match kind {
            "digital_in" => LuaDevice::DigitalIn(
                name.clone(),
                registry.digital_in().lookup(&name).map_err(e)?,
            ),
            "digital_out" => LuaDevice::DigitalOut(
                name.clone(),
                registry.digital_out().lookup(&name).map_err(e)?,
            ),
            "analog_in" => {
                LuaDevice::AnalogIn(name.clone(), registry.analog_in().lookup(&name).map_err(e)?)
            }
            "analog_out" => LuaDevice::AnalogOut(
                name.clone(),
                registry.analog_out().lookup(&name).map_err(e)?,
            ),
            _ => LuaDevice::Encoder(name.clone(), registry.encoder().lookup(&name).map_err(e)?),
        })
    };
    for kind in [
        "digital_in",
        "digital_out",
        "analog_in",
        "analog_out",
        "encoder",
    ] {
        t.set(
            kind,
            lua.create_function(move |lua, name: String| lookup(lua, kind, name))?,
        )?;
    }
    Ok(t)
}

impl LuaDevice {
    fn name(&self) -> &str {
        match self {
            LuaDevice::DigitalIn(n, _)
            | LuaDevice::DigitalOut(n, _)
            | LuaDevice::AnalogIn(n, _)
            | LuaDevice::AnalogOut(n, _)
            | LuaDevice::Encoder(n, _) => n,
        }
    }

    fn wrong(&self, method: &str) -> mlua::Error {
        let kind = match self {
            LuaDevice::DigitalIn(..) => "DigitalIn",
            LuaDevice::DigitalOut(..) => "DigitalOut",
            LuaDevice::AnalogIn(..) => "AnalogIn",
            LuaDevice::AnalogOut(..) => "AnalogOut",
            LuaDevice::Encoder(..) => "Encoder",
        };
        mlua::Error::runtime(format!(
            "device {:?} is a {kind}: it has no {method}",
            self.name()
        ))
    }
}

impl UserData for LuaDevice {
    fn add_methods<M: UserDataMethods<Self>>(methods: &mut M) {
        methods.add_method("count", |_, this, ()| {
            Ok(match this {
                LuaDevice::DigitalIn(_, d) => d.input_count(),
                LuaDevice::DigitalOut(_, d) => d.output_count(),
                LuaDevice::AnalogIn(_, d) => d.channel_count(),
                LuaDevice::AnalogOut(_, d) => d.channel_count(),
                LuaDevice::Encoder(..) => 1,
            })
        });
        methods.add_method("get", |_, this, bit: u32| match this {
            LuaDevice::DigitalIn(_, d) => d.read_bit(bit).map_err(fail),
            LuaDevice::DigitalOut(_, d) => d.check_bit(bit).map_err(fail),
            _ => Err(this.wrong("get(bit)")),
        });
        methods.add_method("set", |_, this, (bit, on): (u32, bool)| match this {
            LuaDevice::DigitalOut(_, d) => d.set_bit(bit, on).map_err(fail),
            _ => Err(this.wrong("set(bit, on)")),
        });
        methods.add_method("read", |_, this, ch: u32| match this {
            LuaDevice::AnalogIn(_, d) => d.read(ch).map_err(fail),
            LuaDevice::AnalogOut(_, d) => d.read_back(ch).map_err(fail),
            _ => Err(this.wrong("read(channel)")),
        });
        methods.add_method("read_raw", |_, this, ch: u32| match this {
            LuaDevice::AnalogIn(_, d) => d.read_raw(ch).map_err(fail),
            LuaDevice::AnalogOut(_, d) => d.read_back_raw(ch).map_err(fail),
            _ => Err(this.wrong("read_raw(channel)")),
        });
        methods.add_method("write", |_, this, (ch, v): (u32, f64)| match this {
            LuaDevice::AnalogOut(_, d) => d.write(ch, v).map_err(fail),
            _ => Err(this.wrong("write(channel, value)")),
        });
        methods.add_method("position", |_, this, ()| match this {
            LuaDevice::Encoder(_, d) => d.position().map_err(fail),
            _ => Err(this.wrong("position()")),
        });
        methods.add_method("turn", |_, this, ()| match this {
            LuaDevice::Encoder(_, d) => d.turn().map_err(fail),
            _ => Err(this.wrong("turn()")),
        });
        methods.add_method("set_position", |_, this, p: i64| match this {
            LuaDevice::Encoder(_, d) => d.set_position(p).map_err(fail),
            _ => Err(this.wrong("set_position(p)")),
        });
        methods.add_method("health", |_, this, ()| {
            let h = match this {
                LuaDevice::DigitalIn(_, d) => d.health(),
                LuaDevice::DigitalOut(_, d) => d.health(),
                LuaDevice::AnalogIn(_, d) => d.health(),
                LuaDevice::AnalogOut(_, d) => d.health(),
                LuaDevice::Encoder(_, d) => d.health(),
            };
            Ok(h.status.to_string())
        });
    }
}
