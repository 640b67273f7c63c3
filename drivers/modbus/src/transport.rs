//! Where a Modbus line goes — a TCP address, a serial port, RTU frames over TCP — and
//! opening it: the connection a line's poller ([`line`](crate::line)) sends on.

use crate::client::{Client, RtuPort, RtuTiming};
use std::net::SocketAddr;
use std::time::Duration;

/// Parity of a serial line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Parity {
    /// Even parity (the Modbus RTU default).
    #[default]
    Even,
    /// Odd parity.
    Odd,
    /// No parity (then two stop bits, by the specification; many devices use one).
    None,
}

/// A serial line's settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Serial {
    /// The device, e.g. a stable udev name such as /dev/hwgw/line1.
    pub device: std::path::PathBuf,
    /// Bits per second.
    pub baud: u32,
    /// Parity.
    pub parity: Parity,
    /// Stop bits: 1 or 2.
    pub stop_bits: u8,
    /// Extra quiet time after each frame before the next request, µs (slow RS-485
    /// bridges; 0: the 3.5 character times alone).
    pub turnaround_us: u32,
}

/// RTU frames over TCP: where, and the turnaround.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RtuOverTcp {
    /// The serial device server's address.
    pub addr: SocketAddr,
    /// Extra quiet time after each frame before the next request, µs (0: none).
    pub turnaround_us: u32,
}

/// Where the line goes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Transport {
    /// Modbus TCP to this address; several units behind a gateway by unit id.
    Tcp(SocketAddr),
    /// Modbus RTU on a serial port; several units multi-dropped by unit id.
    Rtu(Serial),
    /// Modbus RTU frames on a TCP stream to a serial device server; the units on its
    /// serial side by unit id.
    RtuOverTcp(RtuOverTcp),
}

impl Transport {
    /// Where the line goes: the address, or the serial device's path.
    pub fn describe(&self) -> String {
        match self {
            Transport::Tcp(a) => a.to_string(),
            Transport::Rtu(s) => s.device.display().to_string(),
            Transport::RtuOverTcp(r) => r.addr.to_string(),
        }
    }

    /// True when both go to the same address or serial device (whatever their settings or
    /// framing).
    pub fn same_place(&self, other: &Transport) -> bool {
        match (self.address(), other.address()) {
            (Some(a), Some(b)) => a == b,
            _ => match (self, other) {
                (Transport::Rtu(a), Transport::Rtu(b)) => a.device == b.device,
                _ => false,
            },
        }
    }

    /// The TCP address, for the transports over TCP.
    fn address(&self) -> Option<SocketAddr> {
        match self {
            Transport::Tcp(a) => Some(*a),
            Transport::RtuOverTcp(r) => Some(r.addr),
            Transport::Rtu(_) => None,
        }
    }

    /// True for RTU framing (a serial line, or RTU over TCP): no transaction id, so a
    /// late reply cannot be told from the next request's.
    pub fn rtu_framed(&self) -> bool {
        !matches!(self, Transport::Tcp(_))
    }

    /// The line's settings, for messages: "19200 baud, even parity, 1 stop bit, turnaround
    /// 0 µs".
    pub fn settings(&self) -> String {
        match self {
            Transport::Tcp(a) => format!("TCP to {a}"),
            Transport::Rtu(s) => format!(
                "{} baud, {:?} parity, {} stop bits, turnaround {} µs",
                s.baud, s.parity, s.stop_bits, s.turnaround_us
            ),
            Transport::RtuOverTcp(r) => format!(
                "RTU over TCP to {}, turnaround {} µs",
                r.addr, r.turnaround_us
            ),
        }
    }

    /// Opens the connection (or the port).
    pub(crate) async fn open(&self) -> std::io::Result<Client> {
        match self {
            Transport::Tcp(addr) => {
                let stream = tokio::net::TcpStream::connect(addr).await?;
                let _ = stream.set_nodelay(true);
                Ok(crate::client::tcp_client(stream))
            }
            Transport::RtuOverTcp(r) => {
                let stream = tokio::net::TcpStream::connect(r.addr).await?;
                let _ = stream.set_nodelay(true);
                let timing = RtuTiming::tcp(Duration::from_micros(u64::from(r.turnaround_us)));
                Ok(Client::Rtu {
                    port: RtuPort::Tcp(stream),
                    timing,
                    quiet_from: tokio::time::Instant::now(),
                })
            }
            Transport::Rtu(s) => {
                let port = open_serial(s)?;
                let timing =
                    RtuTiming::serial(s.baud, Duration::from_micros(u64::from(s.turnaround_us)));
                Ok(Client::Rtu {
                    port: RtuPort::Serial(port),
                    timing,
                    // A port just opened: the line may be mid-frame; wait a silence.
                    quiet_from: tokio::time::Instant::now() + timing.silence + timing.turnaround,
                })
            }
        }
    }
}

/// Opens serial port `s` with its settings (8 data bits).
pub(crate) fn open_serial(s: &Serial) -> std::io::Result<tokio_serial::SerialStream> {
    use tokio_serial::SerialPortBuilderExt;
    tokio_serial::new(s.device.to_string_lossy(), s.baud)
        .parity(match s.parity {
            Parity::Even => tokio_serial::Parity::Even,
            Parity::Odd => tokio_serial::Parity::Odd,
            Parity::None => tokio_serial::Parity::None,
        })
        .stop_bits(if s.stop_bits == 2 {
            tokio_serial::StopBits::Two
        } else {
            tokio_serial::StopBits::One
        })
        .data_bits(tokio_serial::DataBits::Eight)
        .open_native_async()
        .map_err(std::io::Error::other)
}
