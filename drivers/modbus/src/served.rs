//! The `[modbus_server]` section of a deployment: which registry devices hwgw serves as a
//! Modbus TCP register table, and where it listens; [`build`] makes the [`TableServer`]
//! of a section over the device registry, as the gateway's `ServerTypes` registers it.
//!
//! ```
//! use driver_modbus::served::ServerConfig;
//!
//! let c: ServerConfig = toml::from_str(r#"
//!     listen = "127.0.0.1:5502"
//!     [[register]]
//!     table = "holding_registers"
//!     address = 0
//!     device = "press"
//!     interface = "analog_out"
//!     type = "f32"
//! "#)?;
//! assert_eq!(c.registers.len(), 1);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use crate::codec::{ByteOrder, Layout, ValueType, WordOrder};
use crate::gateway::Lines;
use crate::listener::{Endpoints, Limits, ModbusServer};
use crate::plan::Table;
use crate::server::{Entry, RegisterTable, Source};
use crate::shared::Units;
use device_interface::text::{Number, Quoted};
use device_interface::{Interface, Registry};
use driver_api::{CardError, Server, ServerContext, ServerError};
use serde::Deserialize;
use std::net::ToSocketAddrs;
use std::sync::{Arc, Mutex};

/// hwgw as a Modbus server: on TCP, RTU over TCP, a serial port, or all three.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerConfig {
    /// `address:port` to serve Modbus TCP on (e.g. 127.0.0.1:5502; 0.0.0.0 only on
    /// purpose).
    #[serde(default)]
    pub listen: Option<String>,
    /// `address:port` to serve RTU frames over TCP on (for masters that speak to serial
    /// device servers).
    #[serde(default)]
    pub rtu_over_tcp: Option<String>,
    /// An RTU slave on a serial port.
    #[serde(default)]
    pub serial: Option<crate::slave::SerialConfig>,
    /// The unit ids served as the server's own (1-247; and 255 on TCP). Unset: every
    /// unit id on TCP, unit 1 on a serial port.
    #[serde(default)]
    pub units: Option<Vec<u8>>,
    /// Connections served at once, on each TCP listener (1–1024; default 16). With all of them open, a new one
    /// is admitted by closing the one idle longest (no complete request for longest).
    #[serde(default = "default_max_clients")]
    pub max_clients: usize,
    /// Connections from one IP address at once (1–1024; default 8); one more from it is
    /// closed at once, so one device cannot take every slot.
    #[serde(default = "default_max_per_address")]
    pub max_clients_per_address: usize,
    /// A connection quiet this long is closed, seconds (1–86400; default 60).
    #[serde(default = "default_idle_s")]
    pub idle_timeout_s: u64,
    /// A frame (MBAP header and PDU) must be whole this long after its first bytes, ms
    /// (10–86400000, at most `idle_timeout_s`; default 5000, or `idle_timeout_s` when
    /// that is shorter); else the connection is closed.
    #[serde(default)]
    pub frame_timeout_ms: Option<u64>,
    /// The longest a write's reply waits, ms, for a device whose bus carries the write
    /// later (a Modbus unit behind hwgw's client, another gateway's output) to deliver it;
    /// still on its way then, the write is answered 0x0B (10-60000; default 1000).
    #[serde(default = "default_write_confirm_ms")]
    pub write_confirm_ms: u64,
    /// The register table.
    #[serde(default, rename = "register")]
    pub registers: Vec<ServedRegister>,
    /// Gateway mode: where requests for units that are not the server's own go, the
    /// first route that takes a unit (`units` must then be given: the server's own).
    #[serde(default, rename = "gateway")]
    pub gateway: Vec<crate::gateway::GatewayConfig>,
}

fn default_max_clients() -> usize {
    16
}
fn default_max_per_address() -> usize {
    8
}
fn default_idle_s() -> u64 {
    60
}
fn default_write_confirm_ms() -> u64 {
    crate::listener::DEFAULT_WRITE_CONFIRM.as_millis() as u64
}
/// `frame_timeout_ms` when not given (capped at `idle_timeout_s`).
const DEFAULT_FRAME_MS: u64 = 5000;

impl ServerConfig {
    /// Its limits, checked: (key, message) when out of bounds.
    pub fn limits(&self) -> Result<Limits, (&'static str, String)> {
        if !(1..=1024).contains(&self.max_clients) {
            return Err(("max_clients", format!("{}: 1-1024", self.max_clients)));
        }
        if !(1..=1024).contains(&self.max_clients_per_address) {
            return Err((
                "max_clients_per_address",
                format!("{}: 1-1024", self.max_clients_per_address),
            ));
        }
        if !(1..=86_400).contains(&self.idle_timeout_s) {
            return Err((
                "idle_timeout_s",
                format!("{}: 1-86400 s", self.idle_timeout_s),
            ));
        }
        let idle_ms = self.idle_timeout_s * 1000;
        let frame_ms = match self.frame_timeout_ms {
            None => DEFAULT_FRAME_MS.min(idle_ms),
            Some(ms) if !(10..=86_400_000).contains(&ms) => {
                return Err(("frame_timeout_ms", format!("{ms}: 10-86400000 ms")));
            }
            Some(ms) if ms > idle_ms => {
                return Err((
                    "frame_timeout_ms",
                    format!(
                        "{ms} ms: at most idle_timeout_s ({} s)",
                        self.idle_timeout_s
                    ),
                ));
            }
            Some(ms) => ms,
        };
        if !(10..=60_000).contains(&self.write_confirm_ms) {
            return Err((
                "write_confirm_ms",
                format!("{}: 10-60000 ms", self.write_confirm_ms),
            ));
        }
        Ok(Limits {
            max_clients: self.max_clients,
            max_clients_per_address: self.max_clients_per_address,
            idle_timeout: std::time::Duration::from_secs(self.idle_timeout_s),
            frame_timeout: std::time::Duration::from_millis(frame_ms),
            write_confirm: std::time::Duration::from_millis(self.write_confirm_ms),
        })
    }
}

/// One entry of the served register table.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServedRegister {
    /// The table: input_registers, holding_registers, discrete_inputs or coils.
    pub table: Table,
    /// First address (0-based).
    pub address: u16,
    /// The device's registry name.
    pub device: String,
    /// Which of its interfaces.
    pub interface: Interface,
    /// Channel (or bit).
    #[serde(default)]
    pub channel: u32,
    /// Register type (default u16).
    #[serde(default, rename = "type")]
    pub ty: ValueType,
    /// Word order.
    #[serde(default)]
    pub words: WordOrder,
    /// Byte order.
    #[serde(default)]
    pub bytes: ByteOrder,
    /// Register value = (physical - offset) / scale (default 1).
    #[serde(default = "one_f64")]
    pub scale: f64,
    /// See `scale`.
    #[serde(default)]
    pub offset: f64,
}

fn one_f64() -> f64 {
    1.0
}

/// A problem with the section: the key under `[modbus_server]` and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{key}: {message}")]
pub struct ServerConfigError {
    /// Key path under the section, e.g. `register[3].device`.
    pub key: String,
    /// What is wrong.
    pub message: String,
}

impl ServerConfig {
    /// The listening address, the register table over the devices in `registry` and the
    /// limits, or every problem found.
    pub fn table(
        &self,
        registry: &Registry,
        lines: &Arc<Lines>,
    ) -> Result<(Endpoints, RegisterTable, Limits), Vec<ServerConfigError>> {
        let mut problems = Vec::new();
        let endpoints = self.endpoints(lines).map_err(|e| problems.push(e)).ok();
        let mut entries = Vec::new();
        for (i, r) in self.registers.iter().enumerate() {
            if let Some(message) = r.scale_overflow() {
                problems.push(ServerConfigError {
                    key: format!("register[{i}].scale"),
                    message,
                });
                continue;
            }
            match r.source(registry) {
                Ok(source) => entries.push(Entry {
                    table: r.table,
                    address: r.address,
                    layout: Layout {
                        ty: r.ty,
                        words: r.words,
                        bytes: r.bytes,
                    },
                    scale: r.scale,
                    offset: r.offset,
                    source,
                }),
                Err((key, message)) => problems.push(ServerConfigError {
                    key: format!("register[{i}].{key}"),
                    message,
                }),
            }
        }
        let table = RegisterTable::new(entries).map_err(|e| ServerConfigError {
            key: "register".into(),
            message: e.to_string(),
        });
        let limits = self.limits().map_err(|(key, message)| ServerConfigError {
            key: key.into(),
            message,
        });
        match (endpoints, table, limits) {
            (Some(at), Ok(table), Ok(limits)) if problems.is_empty() => Ok((at, table, limits)),
            (_, table, limits) => {
                problems.extend(table.err());
                problems.extend(limits.err());
                Err(problems)
            }
        }
    }
}

impl ServerConfig {
    /// Where it serves, as which units: (key, message) when one is wrong.
    fn endpoints(&self, lines: &Arc<Lines>) -> Result<Endpoints, ServerConfigError> {
        let err = |key: &str, message: String| ServerConfigError {
            key: key.into(),
            message,
        };
        let resolve = |key: &str, at: &Option<String>| match at {
            None => Ok(None),
            Some(text) => text
                .to_socket_addrs()
                .ok()
                .and_then(|mut a| a.next())
                .map(Some)
                .ok_or_else(|| err(key, format!("{}: expected address:port", Quoted(text)))),
        };
        let tcp = resolve("listen", &self.listen)?;
        let rtu_over_tcp = resolve("rtu_over_tcp", &self.rtu_over_tcp)?;
        let serial = match &self.serial {
            None => None,
            Some(s) => Some(
                s.slave()
                    .map_err(|(key, message)| err(&format!("serial.{key}"), message))?,
            ),
        };
        if tcp.is_none() && rtu_over_tcp.is_none() && serial.is_none() {
            return Err(err(
                "listen",
                "missing: give listen (Modbus TCP), rtu_over_tcp or serial (an RTU slave): where to serve".into(),
            ));
        }
        if tcp.is_some_and(|a| a.port() != 0) && tcp == rtu_over_tcp {
            return Err(err(
                "rtu_over_tcp",
                format!(
                    "{}: listen has it already; give each its own port",
                    Quoted(self.rtu_over_tcp.as_deref().unwrap_or(""))
                ),
            ));
        }
        let units = match &self.units {
            None if serial.is_some() && tcp.is_none() && rtu_over_tcp.is_none() => {
                Units::Only(vec![1])
            }
            None => Units::Any,
            Some(v) => {
                if v.is_empty() && self.gateway.is_empty() {
                    return Err(err(
                        "units",
                        "empty: give the unit ids served, or leave units out".into(),
                    ));
                }
                if let Some(bad) = v.iter().find(|u| !(1..=247).contains(*u) && **u != 255) {
                    return Err(err(
                        "units",
                        format!(
                            "{bad}: expected 1 to 247 (or 255, TCP's \"this server\"); 0 is the broadcast"
                        ),
                    ));
                }
                Units::Only(v.clone())
            }
        };
        if !self.gateway.is_empty() && self.units.is_none() {
            return Err(err(
                "units",
                "missing: with gateway routes, give the unit ids the server answers itself \
                 (units = [] for none)"
                    .into(),
            ));
        }
        let gateway = self
            .gateway
            .iter()
            .enumerate()
            .map(|(i, g)| {
                g.route(lines)
                    .map_err(|(key, message)| err(&format!("gateway[{i}].{key}"), message))
            })
            .collect::<Result<Vec<_>, _>>()?;
        if !gateway.is_empty() && tcp.is_none() && rtu_over_tcp.is_none() {
            return Err(err(
                "gateway",
                "a gateway forwards TCP masters' requests: give listen or rtu_over_tcp (on a serial port the other units answer themselves)".into(),
            ));
        }
        if let Units::Only(own) = &units {
            for (i, g) in gateway.iter().enumerate() {
                if let Some(u) = own.iter().find(|u| g.takes(**u) && g.units.is_some()) {
                    return Err(err(
                        &format!("gateway[{i}].units"),
                        format!("unit {u} is the server's own (units): it is never forwarded"),
                    ));
                }
            }
        }
        if let Some(s) = &serial {
            let port = crate::transport::Transport::Rtu(s.serial.clone());
            if !matches!(lines.find(&port), Ok(None)) {
                return Err(err(
                    "serial.device",
                    format!(
                        "{} is a Modbus card's line: one port is either hwgw's line to its units (a master) or its slave's, not both",
                        s.serial.device.display()
                    ),
                ));
            }
        }
        Ok(Endpoints {
            tcp,
            rtu_over_tcp,
            serial,
            units,
            gateway,
        })
    }
}

/// Builds the server of a `[modbus_server]` section (under the key `ctx` names) over the
/// devices in the context's registry: a [`ServerBuildFn`](driver_api::ServerBuildFn).
/// Every problem is at its key under the section.
pub fn build(
    config: &ServerConfig,
    ctx: &mut ServerContext<'_>,
) -> Result<Box<dyn Server>, Vec<CardError>> {
    match config.table(ctx.registry(), &ctx.runtime().shared::<Lines>()) {
        Ok((at, table, limits)) => Ok(Box::new(
            TableServer::new(at, table, limits).named(ctx.name()),
        )),
        Err(problems) => Err(problems
            .into_iter()
            .map(|p| CardError::at(p.key, p.message))
            .collect()),
    }
}

/// The served table as a gateway [`Server`]: started with the gateway, stopped first at
/// its stop.
pub struct TableServer {
    name: String,
    at: Endpoints,
    table: RegisterTable,
    limits: Limits,
    running: Mutex<Option<ModbusServer>>,
}

impl TableServer {
    /// A server of `table` at `at` within `limits`, not started, named `modbus_server`.
    pub fn new(at: Endpoints, table: RegisterTable, limits: Limits) -> TableServer {
        TableServer {
            name: "modbus_server".into(),
            at,
            table,
            limits,
            running: Mutex::new(None),
        }
    }

    /// The same, named `name` (its deployment key).
    pub fn named(self, name: &str) -> TableServer {
        TableServer {
            name: name.to_string(),
            ..self
        }
    }
}

impl Server for TableServer {
    fn name(&self) -> &str {
        &self.name
    }

    fn start(&self) -> Result<String, ServerError> {
        let server = ModbusServer::serve(self.at.clone(), self.table.clone(), self.limits)
            .map_err(|source| ServerError::Listen {
                address: self.at.describe(),
                source,
            })?;
        let addr = server.describe();
        *rtt::lock(&self.running) = Some(server);
        Ok(addr)
    }

    fn stop(&self) {
        // Dropping the server stops it and waits for its thread.
        rtt::lock(&self.running).take();
    }

    fn address(&self) -> Option<String> {
        // The Modbus TCP address as `host:port` (else the RTU-over-TCP one; else the
        // serial port): what a client connects to.
        rtt::lock(&self.running).as_ref().map(|s| {
            let at = s.endpoints();
            match (at.tcp.or(at.rtu_over_tcp), &at.serial) {
                (Some(a), _) => a.to_string(),
                (None, Some(s)) => s.serial.device.display().to_string(),
                (None, None) => String::new(),
            }
        })
    }

    fn status(&self) -> Option<driver_api::CardStatus> {
        let running = rtt::lock(&self.running);
        let counters = running
            .as_ref()
            .map(ModbusServer::counters)
            .unwrap_or_default();
        // Where it serves: the bound addresses once running (a port 0 given is chosen then).
        let at = running
            .as_ref()
            .map_or_else(|| self.at.describe(), ModbusServer::describe);
        Some(driver_api::CardStatus::new(at, &counters))
    }

    fn health(&self) -> Result<(), ServerError> {
        rtt::lock(&self.running)
            .as_ref()
            .map_or(Ok(()), ModbusServer::health)
            .map_err(ServerError::failed)
    }
}

impl ServedRegister {
    /// What is wrong with a scale and offset whose arithmetic overflows, if they do: a
    /// written register value becomes `value × scale + offset`, which for the largest
    /// value of an integer (or f32) register must still be a number.
    fn scale_overflow(&self) -> Option<String> {
        let largest = match self.ty {
            ValueType::U16 => f64::from(u16::MAX),
            ValueType::I16 => -f64::from(i16::MIN),
            ValueType::U32 => f64::from(u32::MAX),
            ValueType::I32 => -f64::from(i32::MIN),
            ValueType::U64 => u64::MAX as f64,
            ValueType::I64 => -(i64::MIN as f64),
            ValueType::F32 => f64::from(f32::MAX),
            // Any factor above 1 overflows at the f64's own extremes: a client writing
            // one gets the device's range error.
            ValueType::F64 => return None,
        };
        let reach = largest * self.scale.abs() + self.offset.abs();
        if self.table.is_bits() || reach.is_finite() {
            return None;
        }
        Some(format!(
            "scale {} and offset {} overflow: a {} register's largest value, {}, times the \
             scale plus the offset is beyond the largest number (about 1.8e308)",
            Number(self.scale),
            Number(self.offset),
            self.ty,
            Number(largest)
        ))
    }

    /// The device channel this entry serves; errors are (key, message).
    fn source(&self, registry: &Registry) -> Result<Source, (&'static str, String)> {
        let ch = self.channel;
        let missing = |e: device_interface::RegistryError| ("device", e.to_string());
        let (source, count, what) = match self.interface {
            Interface::AnalogIn => {
                let d = registry.analog_in().lookup(&self.device).map_err(missing)?;
                let n = d.channel_count();
                (Source::AnalogIn(d, ch), n, "analog inputs")
            }
            Interface::AnalogOut => {
                let d = registry
                    .analog_out()
                    .lookup(&self.device)
                    .map_err(missing)?;
                let n = d.channel_count();
                (Source::AnalogOut(d, ch), n, "analog outputs")
            }
            Interface::DigitalIn => {
                let d = registry
                    .digital_in()
                    .lookup(&self.device)
                    .map_err(missing)?;
                let n = d.input_count();
                (Source::DigitalIn(d, ch), n, "digital inputs")
            }
            Interface::DigitalOut => {
                let d = registry
                    .digital_out()
                    .lookup(&self.device)
                    .map_err(missing)?;
                let n = d.output_count();
                (Source::DigitalOut(d, ch), n, "digital outputs")
            }
            Interface::Encoder => {
                return Err((
                    "interface",
                    "encoders are not served yet; serve their IO component's ports instead".into(),
                ));
            }
            Interface::Sensor | Interface::Drive | Interface::Axis => {
                return Err((
                    "interface",
                    format!(
                        "{} is a logical device: serve the channels under it, or its IO \
                         component's ports",
                        self.interface
                    ),
                ));
            }
        };
        if ch >= count {
            let have = match count {
                0 => String::new(),
                n => format!(": 0..={}", n - 1),
            };
            return Err((
                "channel",
                format!(
                    "channel {ch} does not exist: {} has {count} {what}{have}",
                    Quoted(&self.device)
                ),
            ));
        }
        Ok(source)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]

    use super::*;
    use std::time::Duration;

    fn config(extra: &str) -> ServerConfig {
        toml::from_str(&format!("listen = \"127.0.0.1:0\"\n{extra}")).unwrap()
    }

    #[test]
    fn limits_default_and_bounds() {
        assert_eq!(config("").limits().unwrap(), Limits::default());
        // The default frame timeout never outlasts the idle timeout.
        let short = config("idle_timeout_s = 1").limits().unwrap();
        assert_eq!(short.frame_timeout, Duration::from_secs(1));
        let given = config("max_clients_per_address = 2\nframe_timeout_ms = 250")
            .limits()
            .unwrap();
        assert_eq!(
            (given.max_clients_per_address, given.frame_timeout),
            (2, Duration::from_millis(250))
        );
        let confirm = config("write_confirm_ms = 40").limits().unwrap();
        assert_eq!(confirm.write_confirm, Duration::from_millis(40));
        for (extra, key) in [
            ("max_clients_per_address = 0", "max_clients_per_address"),
            ("max_clients_per_address = 1025", "max_clients_per_address"),
            ("frame_timeout_ms = 5", "frame_timeout_ms"),
            ("write_confirm_ms = 9", "write_confirm_ms"),
            ("write_confirm_ms = 60001", "write_confirm_ms"),
            (
                "idle_timeout_s = 2\nframe_timeout_ms = 2001",
                "frame_timeout_ms",
            ),
        ] {
            assert_eq!(config(extra).limits().unwrap_err().0, key, "{extra}");
        }
    }
}
