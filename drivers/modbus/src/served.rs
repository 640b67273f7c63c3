//! The `[modbus_server]` section of a deployment: which registry devices hwgw serves as a
//! Modbus TCP register table, and where it listens.
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
use crate::plan::Table;
use crate::server::{Entry, ModbusServer, RegisterTable, Source};
use device_interface::{Interface, Registry};
use serde::Deserialize;
use std::net::{SocketAddr, ToSocketAddrs};
use std::sync::Mutex;

/// hwgw as a Modbus TCP server.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerConfig {
    /// `address:port` to listen on (e.g. 127.0.0.1:5502; 0.0.0.0 only on purpose).
    pub listen: String,
    /// The register table.
    #[serde(default, rename = "register")]
    pub registers: Vec<ServedRegister>,
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
    /// The listening address and the register table over the devices in `registry`, or
    /// every problem found.
    pub fn table(
        &self,
        registry: &Registry,
    ) -> Result<(SocketAddr, RegisterTable), Vec<ServerConfigError>> {
        let mut problems = Vec::new();
        let listen = self
            .listen
            .to_socket_addrs()
            .ok()
            .and_then(|mut a| a.next());
        if listen.is_none() {
            problems.push(ServerConfigError {
                key: "listen".into(),
                message: format!("{:?}: expected address:port", self.listen),
            });
        }
        let mut entries = Vec::new();
        for (i, r) in self.registers.iter().enumerate() {
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
        match (listen, table) {
            (Some(addr), Ok(table)) if problems.is_empty() => Ok((addr, table)),
            (_, table) => {
                problems.extend(table.err());
                Err(problems)
            }
        }
    }
}

/// The served table as a gateway [`Server`](driver_api::Server): started with the
/// gateway, stopped first at its stop.
pub struct TableServer {
    listen: SocketAddr,
    table: RegisterTable,
    running: Mutex<Option<ModbusServer>>,
}

impl TableServer {
    /// A server of `table` on `listen`, not started.
    pub fn new(listen: SocketAddr, table: RegisterTable) -> TableServer {
        TableServer {
            listen,
            table,
            running: Mutex::new(None),
        }
    }
}

impl driver_api::Server for TableServer {
    fn name(&self) -> &str {
        "modbus_server"
    }

    fn start(&self) -> Result<String, String> {
        let server =
            ModbusServer::start(self.listen, self.table.clone()).map_err(|e| e.to_string())?;
        let addr = server.addr().to_string();
        *rtt::lock(&self.running) = Some(server);
        Ok(addr)
    }

    fn stop(&self) {
        // Dropping the server stops it and waits for its thread.
        rtt::lock(&self.running).take();
    }

    fn address(&self) -> Option<String> {
        rtt::lock(&self.running)
            .as_ref()
            .map(|s| s.addr().to_string())
    }
}

impl ServedRegister {
    /// The device channel this entry serves; errors are (key, message).
    fn source(&self, registry: &Registry) -> Result<Source, (&'static str, String)> {
        let ch = self.channel;
        let found = match self.interface {
            Interface::AnalogIn => registry
                .analog_in()
                .lookup(&self.device)
                .map(|d| Source::AnalogIn(d, ch)),
            Interface::AnalogOut => registry
                .analog_out()
                .lookup(&self.device)
                .map(|d| Source::AnalogOut(d, ch)),
            Interface::DigitalIn => registry
                .digital_in()
                .lookup(&self.device)
                .map(|d| Source::DigitalIn(d, ch)),
            Interface::DigitalOut => registry
                .digital_out()
                .lookup(&self.device)
                .map(|d| Source::DigitalOut(d, ch)),
            Interface::Encoder => {
                return Err((
                    "interface",
                    "encoders are not served yet; serve their IO component's ports instead".into(),
                ));
            }
        };
        found.map_err(|e| ("device", e.to_string()))
    }
}
