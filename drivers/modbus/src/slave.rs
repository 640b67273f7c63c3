//! hwgw's Modbus server as an RTU slave on a serial port: the same register table, request
//! checks and exceptions as on TCP, RTU frames ([`framing`](crate::framing)), its own unit
//! ids, broadcasts (unit 0) applied without a reply, other units' frames ignored.
//!
//! - A reply goes out 3.5 character times after the request's last byte (the
//!   specification's silence; 1.75 ms above 19200 baud) plus the configured turnaround.
//! - RS-485: with `rs485` set, the port is put in the kernel's RS-485 mode
//!   (`TIOCSRS485`): the driver raises RTS while sending (or lowers it, as configured)
//!   with the delays given. A port that does not support it (a USB adapter whose driver
//!   has no RS-485 mode, a pty) refuses with ENOTTY or EINVAL: the server does not serve
//!   on it, logs why and says so in its health, since a half-duplex line driven without
//!   direction control would garble every reply.
//! - A port that cannot be opened (unplugged) or fails while served is opened again after
//!   1 s, doubling up to 30 s (starting over after a port that stayed open 5 s); each
//!   failure is counted (`port_errors`), and the server's health says so once it has not
//!   served for 5 s (a port that opens and fails at once has not served).

use crate::conn::Conn;
use crate::framing::Framing;
use crate::shared::{PORT_UP, Shared, Units};
use crate::transport::Serial;
use serde::Deserialize;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::Duration;

/// The kernel's RS-485 settings for a port (`struct serial_rs485`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rs485 {
    /// RTS high while sending (the usual wiring of a transceiver's driver enable); false:
    /// low while sending.
    pub rts_on_send: bool,
    /// Delay after raising RTS before the first bit, ms.
    pub delay_before_send_ms: u32,
    /// Delay after the last bit before dropping RTS, ms.
    pub delay_after_send_ms: u32,
    /// Receive while sending (a full-duplex transceiver, or to see the own echo).
    pub rx_during_tx: bool,
}

/// An RTU slave's port.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SerialSlave {
    /// The port and its settings (the turnaround is waited before each reply too).
    pub serial: Serial,
    /// RS-485 direction control by the kernel, if wanted.
    pub rs485: Option<Rs485>,
}

/// The RTU slave's port.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SerialConfig {
    /// The port, best a stable udev name (`/dev/hwgw/rs485`).
    pub device: std::path::PathBuf,
    /// Bits per second (default 19200).
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Parity (default even).
    #[serde(default)]
    pub parity: crate::transport::Parity,
    /// Stop bits, 1 or 2 (default 1).
    #[serde(default = "default_stop_bits")]
    pub stop_bits: u8,
    /// Extra quiet time before each reply, ms, beyond the 3.5 character times (0-10000;
    /// default 0).
    #[serde(default)]
    pub turnaround_ms: u32,
    /// The kernel's RS-485 direction control (TIOCSRS485), for ports that have it.
    #[serde(default)]
    pub rs485: Option<Rs485Config>,
}

/// RS-485 settings of the slave's port.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rs485Config {
    /// RTS high while sending (default true); false: low while sending.
    #[serde(default = "yes")]
    pub rts_on_send: bool,
    /// Delay after switching RTS before sending, ms (0-1000; default 0).
    #[serde(default)]
    pub delay_before_send_ms: u32,
    /// Delay after sending before switching RTS back, ms (0-1000; default 0).
    #[serde(default)]
    pub delay_after_send_ms: u32,
    /// Receive while sending (default false).
    #[serde(default)]
    pub rx_during_tx: bool,
}

fn default_baud() -> u32 {
    19200
}
fn default_stop_bits() -> u8 {
    1
}
fn yes() -> bool {
    true
}

impl SerialConfig {
    /// The slave's port, checked: (key under `serial`, message) when out of bounds.
    pub fn slave(&self) -> Result<SerialSlave, (&'static str, String)> {
        if !(50..=4_000_000).contains(&self.baud) {
            return Err((
                "baud",
                format!("{}: expected 50 to 4000000 bits per second", self.baud),
            ));
        }
        if !matches!(self.stop_bits, 1 | 2) {
            return Err(("stop_bits", format!("{}: expected 1 or 2", self.stop_bits)));
        }
        if self.turnaround_ms > 10_000 {
            return Err((
                "turnaround_ms",
                format!("{}: expected 0 to 10000 ms", self.turnaround_ms),
            ));
        }
        if let Ok(node) = driver_api::node::Node::of(&self.device)
            && let Some(why) = node.never_serial()
        {
            return Err((
                "device",
                format!("{} is not a serial port: {why}", self.device.display()),
            ));
        }
        let rs485 = match self.rs485 {
            None => None,
            Some(r) => {
                for (key, v) in [
                    ("rs485.delay_before_send_ms", r.delay_before_send_ms),
                    ("rs485.delay_after_send_ms", r.delay_after_send_ms),
                ] {
                    if v > 1000 {
                        return Err((key, format!("{v}: expected 0 to 1000 ms")));
                    }
                }
                Some(Rs485 {
                    rts_on_send: r.rts_on_send,
                    delay_before_send_ms: r.delay_before_send_ms,
                    delay_after_send_ms: r.delay_after_send_ms,
                    rx_during_tx: r.rx_during_tx,
                })
            }
        };
        Ok(SerialSlave {
            serial: crate::transport::Serial {
                device: self.device.clone(),
                baud: self.baud,
                parity: self.parity,
                stop_bits: self.stop_bits,
                turnaround_us: self.turnaround_ms * 1000,
            },
            rs485,
        })
    }
}

/// Serves the port until dropped (at the server's stop), opening it again after failures.
pub(crate) async fn serve(slave: SerialSlave, shared: Arc<Shared>) {
    const FIRST: Duration = Duration::from_secs(1);
    let port = &shared.stats.port;
    let device = slave.serial.device.display().to_string();
    let timing = crate::client::RtuTiming::serial(
        slave.serial.baud,
        Duration::from_micros(u64::from(slave.serial.turnaround_us)),
    );
    let last = AtomicU64::new(0);
    // Unset, the units are every one on TCP but unit 1 here: a slave on a multi-drop line
    // answering every unit would answer (and take the writes of) the other units.
    let units = match &shared.units {
        Units::Any => Units::Only(vec![1]),
        only => only.clone(),
    };
    let conn = Conn {
        table: &shared.table,
        stats: &shared.stats,
        limits: shared.limits,
        units: &units,
        routes: &[],
        framing: Framing::Rtu {
            gap: crate::framing::rtu_gap(Some(slave.serial.baud)),
            tcp: false,
        },
        reply_delay: timing.silence + timing.turnaround,
        idle_close: false,
        echo: slave.rs485.is_some_and(|r| r.rx_during_tx),
        last: &last,
        epoch: shared.epoch,
    };
    let mut backoff = FIRST;
    loop {
        let why = match open(&slave) {
            Ok(mut stream) => {
                port.opened(shared.epoch);
                tracing::info!("modbus server: RTU slave on {device}");
                match conn.serve(&mut stream).await {
                    Ok(()) => format!("{device} closed"),
                    Err(e) => format!("{device}: {e}"),
                }
            }
            Err(e) => e,
        };
        // The backoff starts over only after a port that served for a while.
        if port.up(shared.epoch).is_some_and(|u| u >= PORT_UP) {
            backoff = FIRST;
        }
        if port.failed(shared.epoch, why.clone()) {
            tracing::warn!("modbus server: {why} (opening it again in {backoff:?})");
        }
        tokio::time::sleep(backoff).await;
        backoff = (backoff * 2).min(Duration::from_secs(30));
    }
}

/// Opens the port with its settings and RS-485 mode; the error names the port and step.
fn open(slave: &SerialSlave) -> Result<tokio_serial::SerialStream, String> {
    let device = slave.serial.device.display();
    let stream = crate::transport::open_serial(&slave.serial)
        .map_err(|e| format!("cannot open {device}: {e}"))?;
    if let Some(rs) = slave.rs485 {
        set_rs485(&stream, rs).map_err(|e| {
            format!(
                "{device} refuses RS-485 mode (TIOCSRS485: {e}); its driver has none, or it is not a UART: serve it without rs485, or use a port that has it"
            )
        })?;
    }
    Ok(stream)
}

/// The kernel's `struct serial_rs485` (include/uapi/linux/serial.h).
#[repr(C)]
#[derive(Default)]
struct SerialRs485 {
    flags: u32,
    delay_rts_before_send: u32,
    delay_rts_after_send: u32,
    padding: [u32; 5],
}

const SER_RS485_ENABLED: u32 = 1;
const SER_RS485_RTS_ON_SEND: u32 = 1 << 1;
const SER_RS485_RTS_AFTER_SEND: u32 = 1 << 2;
const SER_RS485_RX_DURING_TX: u32 = 1 << 4;

fn rs485_flags(rs: Rs485) -> u32 {
    let mut flags = SER_RS485_ENABLED;
    flags |= if rs.rts_on_send {
        SER_RS485_RTS_ON_SEND
    } else {
        SER_RS485_RTS_AFTER_SEND
    };
    if rs.rx_during_tx {
        flags |= SER_RS485_RX_DURING_TX;
    }
    flags
}

#[allow(
    unsafe_code,
    reason = "TIOCSRS485 on the port's own open descriptor with a struct of the kernel's layout"
)]
fn set_rs485(stream: &tokio_serial::SerialStream, rs: Rs485) -> std::io::Result<()> {
    use std::os::fd::AsRawFd;
    let mut conf = SerialRs485 {
        flags: rs485_flags(rs),
        delay_rts_before_send: rs.delay_before_send_ms,
        delay_rts_after_send: rs.delay_after_send_ms,
        ..SerialRs485::default()
    };
    // SAFETY: the descriptor is the stream's, open while borrowed; `conf` is a live
    // struct serial_rs485 the kernel reads and may update in place.
    let r = unsafe {
        libc::ioctl(
            stream.as_raw_fd(),
            libc::TIOCSRS485,
            &mut conf as *mut SerialRs485,
        )
    };
    if r < 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rs485_flags_as_the_kernel_has_them() {
        let rs = Rs485 {
            rts_on_send: true,
            delay_before_send_ms: 0,
            delay_after_send_ms: 0,
            rx_during_tx: false,
        };
        assert_eq!(rs485_flags(rs), 0b011);
        let low = Rs485 {
            rts_on_send: false,
            rx_during_tx: true,
            ..rs
        };
        assert_eq!(rs485_flags(low), 0b1_0101);
        assert_eq!(std::mem::size_of::<SerialRs485>(), 32);
    }
}
