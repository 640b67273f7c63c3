//! hwgw's Modbus client framing, for the line's poller: one request, its reply.
//!
//! - **TCP** (MBAP): each request gets the next transaction id; a reply with another id (a
//!   late answer to a request that timed out) is read whole, dropped and counted, and the
//!   wait goes on for the right one. A header that is not Modbus TCP breaks the connection.
//! - **RTU**: frames are separated by the 3.5 character times of silence the specification
//!   requires at the line's baud rate (11 bits a character; 1.75 ms above 19200 baud),
//!   plus a configurable turnaround delay for slow RS-485 bridges: a request is not sent
//!   before the line has been quiet that long since the last frame on it. A reply is read to
//!   the length its function code gives, its CRC and unit checked. A broadcast (unit 0) is
//!   sent and not answered: the line waits its transmission time and the turnaround instead.
//! - **RTU over TCP**: the same frames, CRC and all, on a TCP stream, as serial device
//!   servers (Moxa NPort, USR-TCP232 and the like in their "TCP server" mode) carry them to
//!   their serial side. The device server keeps the serial line's silences; hwgw keeps only
//!   the turnaround. Like RTU it has no transaction id: a late reply cannot be told from the
//!   next one's, so a timeout reconnects.

use std::io;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;

/// A read reply's values.
pub(crate) enum Data {
    /// Coils or discrete inputs.
    Bits(Vec<bool>),
    /// Registers.
    Words(Vec<u16>),
}

/// What a request came back with.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reply {
    /// The reply PDU (function code first), in the client's buffer.
    Pdu,
    /// An exception code.
    Exception(u8),
    /// A broadcast: no reply by design.
    Broadcast,
}

/// Why a request got no usable reply.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The connection failed or closed.
    #[error("{0}")]
    Io(#[from] io::Error),
    /// A reply that is not one (bad CRC, wrong unit or function, impossible length).
    #[error("bad reply: {0}")]
    Bad(String),
}

pub use crate::framing::crc16;

/// The silence between RTU frames at `baud`: 3.5 characters of 11 bits, 1.75 ms above
/// 19200 baud (the specification's fixed value there).
pub fn t35(baud: u32) -> Duration {
    if baud > 19_200 {
        Duration::from_micros(1750)
    } else {
        Duration::from_secs_f64(3.5 * 11.0 / f64::from(baud.max(1)))
    }
}

/// A connection to a line.
pub enum Client {
    /// Modbus TCP.
    Tcp {
        /// The connection.
        stream: tokio::net::TcpStream,
        /// The last transaction id used.
        tid: u16,
        /// A request is partly sent: cancelled now (its timeout), the stream is in the
        /// middle of a frame, so the connection is no longer usable.
        mid_frame: bool,
        /// Bytes received and not yet taken (a reply read in part when its request was
        /// cancelled is completed by the next request's reads and dropped by its id).
        rx: Vec<u8>,
    },
    /// Modbus RTU on a serial port, or RTU frames on a TCP stream.
    Rtu {
        /// The port.
        port: RtuPort,
        /// The line's silences.
        timing: RtuTiming,
        /// The line is quiet enough for a request from then on.
        quiet_from: Instant,
    },
}

/// Where RTU frames go.
pub enum RtuPort {
    /// A serial port.
    Serial(tokio_serial::SerialStream),
    /// A TCP stream to a serial device server.
    Tcp(tokio::net::TcpStream),
}

/// The silences of an RTU line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RtuTiming {
    /// Between frames: 3.5 character times on a serial line ([`t35`]), none on TCP.
    pub silence: Duration,
    /// One character's time on the wire (11 bits at the baud rate); none on TCP.
    pub char_time: Duration,
    /// Extra wait after each frame before the next request (slow RS-485 bridges).
    pub turnaround: Duration,
}

impl RtuTiming {
    /// A serial line at `baud` with `turnaround`.
    pub fn serial(baud: u32, turnaround: Duration) -> RtuTiming {
        RtuTiming {
            silence: t35(baud),
            char_time: Duration::from_secs_f64(11.0 / f64::from(baud.max(1))),
            turnaround,
        }
    }

    /// RTU frames on TCP with `turnaround`: the device server keeps the serial silences.
    pub fn tcp(turnaround: Duration) -> RtuTiming {
        RtuTiming {
            silence: Duration::ZERO,
            char_time: Duration::ZERO,
            turnaround,
        }
    }
}

impl Client {
    /// A TCP connection whose last request was cancelled while it was being sent: the
    /// stream is out of step and must be closed. A request cancelled while its reply was
    /// awaited or read in part leaves the connection usable: what arrived stays buffered,
    /// and the late reply is told apart by its transaction id.
    pub fn out_of_step(&self) -> bool {
        matches!(
            self,
            Client::Tcp {
                mid_frame: true,
                ..
            }
        )
    }

    /// Sends `pdu` to `unit` and reads the reply PDU into `out` (cleared first). Replies to
    /// other transactions are dropped and counted in `stale`. No timeout of its own: the
    /// caller bounds it (and drops the connection when [`out_of_step`](Self::out_of_step)).
    pub async fn request(
        &mut self,
        unit: u8,
        pdu: &[u8],
        out: &mut Vec<u8>,
        stale: &mut u64,
    ) -> Result<Reply, ClientError> {
        out.clear();
        match self {
            Client::Tcp {
                stream,
                tid,
                mid_frame,
                rx,
            } => tcp(stream, tid, mid_frame, rx, unit, pdu, out, stale).await,
            Client::Rtu {
                port: RtuPort::Serial(port),
                timing,
                quiet_from,
            } => rtu(port, *timing, quiet_from, unit, pdu, out).await,
            Client::Rtu {
                port: RtuPort::Tcp(stream),
                timing,
                quiet_from,
            } => rtu(stream, *timing, quiet_from, unit, pdu, out).await,
        }
    }
}

/// A TCP client's connection state (see [`Client::Tcp`]).
pub fn tcp_client(stream: tokio::net::TcpStream) -> Client {
    Client::Tcp {
        stream,
        tid: 0,
        mid_frame: false,
        rx: Vec::with_capacity(2 * TCP_FRAME_MAX),
    }
}

/// The longest Modbus TCP frame: a 7-byte header and a 253-byte PDU.
const TCP_FRAME_MAX: usize = 260;

#[allow(
    clippy::too_many_arguments,
    reason = "the fields of Client::Tcp, borrowed apart, and the request's own"
)]
async fn tcp(
    stream: &mut tokio::net::TcpStream,
    tid: &mut u16,
    mid_frame: &mut bool,
    rx: &mut Vec<u8>,
    unit: u8,
    pdu: &[u8],
    out: &mut Vec<u8>,
    stale: &mut u64,
) -> Result<Reply, ClientError> {
    *tid = tid.wrapping_add(1);
    let mut frame = Vec::with_capacity(7 + pdu.len());
    frame.extend_from_slice(&tid.to_be_bytes());
    frame.extend_from_slice(&[0, 0]);
    frame.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
    frame.push(unit);
    frame.extend_from_slice(pdu);
    *mid_frame = true;
    stream.write_all(&frame).await?;
    *mid_frame = false;
    loop {
        // A whole frame buffered? (At most one frame and a read's worth are ever kept.)
        if rx.len() >= 7 {
            let len = usize::from(u16::from_be_bytes([rx[4], rx[5]]));
            if rx[2..4] != [0, 0] || !(2..=254).contains(&len) {
                let head = &rx[..7];
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!("not a Modbus TCP header: {head:02x?}"),
                )
                .into());
            }
            if rx.len() >= 6 + len {
                let (id, from) = (u16::from_be_bytes([rx[0], rx[1]]), rx[6]);
                out.clear();
                out.extend_from_slice(&rx[7..6 + len]);
                rx.drain(..6 + len);
                if id != *tid {
                    // A late answer to an earlier request: not this one's.
                    *stale += 1;
                    continue;
                }
                if from != unit {
                    return Err(ClientError::Bad(format!(
                        "unit {from} answered, not {unit}"
                    )));
                }
                return pdu_reply(pdu, out);
            }
        }
        // Cancel-safe: what a read returns is in `rx` before the next await.
        rx.reserve(TCP_FRAME_MAX);
        if stream.read_buf(rx).await? == 0 {
            return Err(io::Error::from(io::ErrorKind::UnexpectedEof).into());
        }
    }
}

/// Reads a reply PDU to `request`: an exception, or the function's own reply — a write's
/// (FC5, 6, 15, 16) echoing the request's address and value or quantity.
fn pdu_reply(request: &[u8], out: &[u8]) -> Result<Reply, ClientError> {
    let function = request[0];
    match out {
        [f, code] if *f == function | 0x80 => Ok(Reply::Exception(*code)),
        [f, ..] if *f == function => {
            if matches!(function, 5 | 6 | 15 | 16) && out.get(..5) != request.get(..5) {
                return Err(ClientError::Bad(format!(
                    "the write {:02x?} answered {out:02x?}: not its echo",
                    request.get(..5).unwrap_or(request)
                )));
            }
            Ok(Reply::Pdu)
        }
        _ => Err(ClientError::Bad(format!(
            "function {function} answered {out:02x?}"
        ))),
    }
}

async fn rtu<P: AsyncRead + AsyncWrite + Unpin>(
    port: &mut P,
    timing: RtuTiming,
    quiet_from: &mut Instant,
    unit: u8,
    pdu: &[u8],
    out: &mut Vec<u8>,
) -> Result<Reply, ClientError> {
    let mut frame = Vec::with_capacity(pdu.len() + 3);
    frame.push(unit);
    frame.extend_from_slice(pdu);
    frame.extend_from_slice(&crc16(&frame).to_le_bytes());
    tokio::time::sleep_until(*quiet_from).await;
    // Whatever a late unit sent since is not this request's reply.
    let mut junk = [0u8; 256];
    while let Ok(Ok(n)) = tokio::time::timeout(Duration::ZERO, port.read(&mut junk)).await {
        if n == 0 {
            // A closed TCP peer: the reply's read says so.
            break;
        }
    }
    port.write_all(&frame).await?;
    let sent = Instant::now();
    // The frame's own time on the wire (the port's buffer empties at the baud rate).
    let on_wire = timing.char_time * frame.len() as u32;
    if unit == 0 {
        *quiet_from = sent + on_wire + timing.silence + timing.turnaround;
        return Ok(Reply::Broadcast);
    }
    // unit, function, then: an exception code; a byte count and that many bytes; or the
    // echoed address and value (writes). Then the CRC.
    let mut head = [0u8; 3];
    port.read_exact(&mut head).await?;
    // The reply's whole length from its function (and byte count).
    let rest = match crate::framing::reply_length(&head) {
        Some(Ok(n)) => n - head.len(),
        _ => {
            let f = head[1];
            return Err(ClientError::Bad(format!("unknown function {f} in a reply")));
        }
    };
    let mut tail = vec![0u8; rest];
    port.read_exact(&mut tail).await?;
    *quiet_from = Instant::now() + timing.silence + timing.turnaround;
    let mut whole = head.to_vec();
    whole.extend_from_slice(&tail);
    let n = whole.len();
    if crc16(&whole[..n - 2]).to_le_bytes() != [whole[n - 2], whole[n - 1]] {
        return Err(ClientError::Bad("CRC error".into()));
    }
    if whole[0] != unit {
        return Err(ClientError::Bad(format!(
            "unit {} answered, not {unit}",
            whole[0]
        )));
    }
    out.extend_from_slice(&whole[1..n - 2]);
    pdu_reply(pdu, out)
}

/// The request PDU of `read` into `pdu` (cleared first).
pub fn read_request(read: &crate::plan::Read, pdu: &mut Vec<u8>) {
    pdu.clear();
    pdu.push(read.table.read_function());
    pdu.extend_from_slice(&read.start.to_be_bytes());
    pdu.extend_from_slice(&read.count.to_be_bytes());
}

/// The request PDU of `w` into `pdu` (cleared first); a run longer than one request may
/// carry (1968 coils, 123 registers: [`ModbusCard::take_writes`](crate::card::ModbusCard::take_writes)
/// never makes one) is refused.
pub fn write_request(w: &crate::card::Write, pdu: &mut Vec<u8>) -> Result<(), ClientError> {
    use crate::card::Write;
    use crate::pdu::{MAX_WRITE_COILS, MAX_WRITE_REGISTERS};
    let too_long = |n: usize, max: u16, what: &str| {
        ClientError::Bad(format!("{n} {what} in one request: at most {max}"))
    };
    pdu.clear();
    match w {
        Write::Coil { address, value } => {
            pdu.push(5);
            pdu.extend_from_slice(&address.to_be_bytes());
            pdu.extend_from_slice(&[if *value { 0xFF } else { 0 }, 0]);
        }
        Write::Register { address, value } => {
            pdu.push(6);
            pdu.extend_from_slice(&address.to_be_bytes());
            pdu.extend_from_slice(&value.to_be_bytes());
        }
        Write::Coils { address, values } => {
            let n = u16::try_from(values.len())
                .ok()
                .filter(|n| (1..=MAX_WRITE_COILS).contains(n))
                .ok_or_else(|| too_long(values.len(), MAX_WRITE_COILS, "coils"))?;
            pdu.push(15);
            pdu.extend_from_slice(&address.to_be_bytes());
            pdu.extend_from_slice(&n.to_be_bytes());
            let bytes = values.len().div_ceil(8);
            pdu.push(
                u8::try_from(bytes)
                    .map_err(|_| too_long(values.len(), MAX_WRITE_COILS, "coils"))?,
            );
            let at = pdu.len();
            pdu.resize(at + bytes, 0);
            for (i, v) in values.iter().enumerate() {
                pdu[at + i / 8] |= u8::from(*v) << (i % 8);
            }
        }
        Write::Registers { address, values } => {
            let n = u16::try_from(values.len())
                .ok()
                .filter(|n| (1..=MAX_WRITE_REGISTERS).contains(n))
                .ok_or_else(|| too_long(values.len(), MAX_WRITE_REGISTERS, "registers"))?;
            pdu.push(16);
            pdu.extend_from_slice(&address.to_be_bytes());
            pdu.extend_from_slice(&n.to_be_bytes());
            // n <= 123: 2n fits a byte.
            pdu.push((2 * n) as u8);
            for v in values {
                pdu.extend_from_slice(&v.to_be_bytes());
            }
        }
    }
    Ok(())
}

/// The values of a read's reply PDU (function, byte count, data), checked against the read.
pub(crate) fn read_data(read: &crate::plan::Read, reply: &[u8]) -> Result<Data, String> {
    let count = usize::from(read.count);
    let [_, bytes, data @ ..] = reply else {
        return Err(format!("a reply of {} bytes", reply.len()));
    };
    let want = if read.table.is_bits() {
        count.div_ceil(8)
    } else {
        2 * count
    };
    if usize::from(*bytes) != want || data.len() != want {
        return Err(format!(
            "{} data bytes (byte count {bytes}) for {count} {}, {want} expected",
            data.len(),
            if read.table.is_bits() {
                "bits"
            } else {
                "registers"
            }
        ));
    }
    Ok(if read.table.is_bits() {
        Data::Bits(
            (0..count)
                .map(|i| data[i / 8] >> (i % 8) & 1 == 1)
                .collect(),
        )
    } else {
        Data::Words(
            data.chunks_exact(2)
                .map(|w| u16::from_be_bytes([w[0], w[1]]))
                .collect(),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_and_silence() {
        // The specification's example: 01 03 00 00 00 0A -> CRC C5 CD (low byte first).
        assert_eq!(
            crc16(&[0x01, 0x03, 0x00, 0x00, 0x00, 0x0A]).to_le_bytes(),
            [0xC5, 0xCD]
        );
        assert_eq!(t35(9600), Duration::from_secs_f64(38.5 / 9600.0));
        assert_eq!(t35(115_200), Duration::from_micros(1750));
    }
}
