//! A Modbus card's section of a hwgw deployment: the line, the unit, timing, the map.
//!
//! ```
//! use driver_modbus::config::ModbusConfig;
//!
//! let c: ModbusConfig = toml::from_str(r#"
//!     transport = { type = "tcp", address = "127.0.0.1:502" }
//!     unit = 1
//!     poll_ms = 100
//!     [[point]]
//!     table = "input_registers"
//!     address = 0
//!     type = "i16"
//!     scale = 0.1
//! "#)?;
//! assert_eq!(c.timing()?.poll.as_millis(), 100);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use crate::card::ModbusCard;
use crate::line::UnitTiming;
use crate::map::{Map, MapError, PointConfig};
use crate::transport::{Parity, RtuOverTcp, Serial, Transport};
use device_interface::time::Clock;
use driver_api::CardError;
use serde::Deserialize;
use std::net::ToSocketAddrs;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

/// Where a card's line goes.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum TransportConfig {
    /// Modbus TCP.
    Tcp {
        /// `host:port`.
        address: String,
    },
    /// Modbus RTU on a serial port.
    Rtu {
        /// The port, best a stable udev name (`/dev/hwgw/line1`).
        device: PathBuf,
        /// Bits per second (default 19200).
        #[serde(default = "baud")]
        baud: u32,
        /// Parity (default even).
        #[serde(default)]
        parity: Parity,
        /// Stop bits, 1 or 2 (default 1).
        #[serde(default = "one_u8")]
        stop_bits: u8,
        /// Extra quiet time after every frame before the next request, ms, for slow
        /// RS-485 bridges (0-10000; default 0: the 3.5 character times alone).
        #[serde(default)]
        turnaround_ms: u32,
    },
    /// Modbus RTU frames (with their CRC) on a TCP stream, as serial device servers
    /// (Moxa NPort, USR-TCP232 and the like) carry them to their serial side.
    RtuOverTcp {
        /// `host:port` of the device server.
        address: String,
        /// Extra quiet time after every frame before the next request, ms, for slow
        /// device servers (0-10000; default 0).
        #[serde(default)]
        turnaround_ms: u32,
    },
}

fn baud() -> u32 {
    19200
}
fn one_u8() -> u8 {
    1
}

/// One Modbus unit as a card.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModbusConfig {
    /// The line. Cards with the same transport share one line (one request outstanding).
    pub transport: TransportConfig,
    /// Unit id (default 1).
    #[serde(default = "one_u8")]
    pub unit: u8,
    /// Poll period, ms (default 100).
    #[serde(default = "poll_ms")]
    pub poll_ms: f64,
    /// Per-request timeout, ms (default 500).
    #[serde(default = "timeout_ms")]
    pub timeout_ms: f64,
    /// Failed polls in a row before the inputs are stale (default 3).
    #[serde(default = "stale_after")]
    pub stale_after: u32,
    /// Failed polls in a row before the unit is offline and backed off (default 10).
    #[serde(default = "offline_after")]
    pub offline_after: u32,
    /// Longest wait between probes of an offline unit, ms (default 5000).
    #[serde(default = "backoff_max_ms")]
    pub backoff_max_ms: f64,
    /// Unused addresses a read may span to save a request. Unset (the default): any gap
    /// within the protocol's limits (125 registers, 2000 bits a read), the fewest requests
    /// the protocol allows, and a read the unit refuses with IllegalDataAddress is split
    /// where the unit has holes, remembered for the unit. Set (0 for devices that refuse
    /// reads of unmapped addresses): that gap, nothing learned.
    #[serde(default)]
    pub max_gap: Option<u16>,
    /// Poll the outputs too (coils, holding-register outputs), so read-back shows what the
    /// device holds rather than what was last written (default false). Only then can the
    /// gateway put an output it wrote back as it found it at stop (output policy
    /// "initial"); without, such outputs are left as last written.
    #[serde(default)]
    pub read_back: bool,
    /// The register map.
    #[serde(default, rename = "point")]
    pub points: Vec<PointConfig>,
}

fn poll_ms() -> f64 {
    100.0
}
fn timeout_ms() -> f64 {
    500.0
}
fn stale_after() -> u32 {
    3
}
fn offline_after() -> u32 {
    10
}
fn backoff_max_ms() -> f64 {
    5000.0
}

/// The longest time a section may give, ms (a day).
const MAX_MS: f64 = 86_400_000.0;

fn ms(key: &str, v: f64) -> Result<Duration, CardError> {
    if !(v.is_finite() && v > 0.0) {
        Err(CardError::at(
            key,
            format!("{v} ms: expected a time above 0"),
        ))
    } else if v > MAX_MS {
        Err(CardError::at(
            key,
            format!("{v:e} ms: expected at most {MAX_MS} ms (a day)"),
        ))
    } else {
        Ok(Duration::from_secs_f64(v / 1000.0))
    }
}

impl TransportConfig {
    /// The transport, checked; a TCP address is resolved now. Errors are at keys under
    /// `transport`.
    pub fn resolve(&self) -> Result<Transport, CardError> {
        let key = "transport.address";
        let resolve = |address: &str| {
            address
                .to_socket_addrs()
                .map_err(|e| CardError::at(key, format!("{address:?}: {e}")))?
                .next()
                .ok_or_else(|| CardError::at(key, format!("{address:?} resolves to no address")))
        };
        match self {
            TransportConfig::Tcp { address } => resolve(address).map(Transport::Tcp),
            TransportConfig::RtuOverTcp {
                address,
                turnaround_ms,
            } => Ok(Transport::RtuOverTcp(RtuOverTcp {
                addr: resolve(address)?,
                turnaround_us: turnaround(*turnaround_ms)?,
            })),
            TransportConfig::Rtu {
                device,
                baud,
                parity,
                stop_bits,
                turnaround_ms,
            } => {
                let turnaround_us = turnaround(*turnaround_ms)?;
                if !matches!(stop_bits, 1 | 2) {
                    return Err(CardError::at(
                        "transport.stop_bits",
                        format!("{stop_bits}: expected 1 or 2"),
                    ));
                }
                if !(50..=4_000_000).contains(baud) {
                    return Err(CardError::at(
                        "transport.baud",
                        format!("{baud}: expected 50 to 4000000 bits per second"),
                    ));
                }
                // From `stat`, nothing opened; a line not plugged in yet is looked for at
                // run.
                if let Ok(node) = driver_api::node::Node::of(device)
                    && let Some(why) = node.never_serial()
                {
                    return Err(CardError::at(
                        "transport.device",
                        format!("{} is not a serial port: {why}", device.display()),
                    ));
                }
                Ok(Transport::Rtu(Serial {
                    device: device.clone(),
                    baud: *baud,
                    parity: *parity,
                    stop_bits: *stop_bits,
                    turnaround_us,
                }))
            }
        }
    }
}

/// A turnaround of `ms` in µs, checked (0-10000 ms).
fn turnaround(ms: u32) -> Result<u32, CardError> {
    if ms > 10_000 {
        return Err(CardError::at(
            "transport.turnaround_ms",
            format!("{ms}: expected 0 to 10000 ms"),
        ));
    }
    Ok(ms * 1000)
}

impl ModbusConfig {
    /// The line's transport; a TCP address is resolved now.
    pub fn transport(&self) -> Result<Transport, CardError> {
        self.transport.resolve()
    }

    /// The unit's timing, checked.
    pub fn timing(&self) -> Result<UnitTiming, CardError> {
        if self.stale_after == 0 || self.offline_after < self.stale_after {
            return Err(CardError::at(
                "stale_after",
                format!(
                    "stale_after {} and offline_after {}: expected 1 <= stale_after <= offline_after",
                    self.stale_after, self.offline_after
                ),
            ));
        }
        Ok(UnitTiming {
            unit: self.unit,
            poll: ms("poll_ms", self.poll_ms)?,
            timeout: ms("timeout_ms", self.timeout_ms)?,
            stale_after: self.stale_after,
            offline_after: self.offline_after,
            backoff_max: ms("backoff_max_ms", self.backoff_max_ms)?,
        })
    }

    /// The card for this unit, with its time from `clock` (it polls nothing until a
    /// [`LineIo`](crate::component::LineIo) polls it).
    pub fn card(&self, clock: Arc<dyn Clock>) -> Result<Arc<ModbusCard>, MapError> {
        let gap = self.max_gap.unwrap_or(crate::map::ANY_GAP);
        let map = Map::with_read_back(&self.points, gap, self.read_back)?
            .learning_holes(self.max_gap.is_none());
        Ok(ModbusCard::new(map, clock))
    }
}
