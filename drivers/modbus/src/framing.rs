//! How hwgw's Modbus server cuts requests out of a byte stream and frames its replies:
//! MBAP on TCP, or RTU (unit, PDU, CRC) on a serial port or a TCP stream.
//!
//! - **MBAP**: a 7-byte header (transaction id, protocol 0, length 2-254, unit) and the
//!   PDU. A header that is not Modbus cannot be resynchronised on a stream: the connection
//!   is closed.
//! - **RTU**: a request's length follows from its function code (8 bytes for FC1-6 and 8,
//!   9 plus the byte count for FC15 and 16, and so on), a reply's too (5 plus its byte
//!   count for reads, 8 for a write's echo, 5 for an exception). Bytes that are a request
//!   with a good CRC are one; bytes that are a reply with a good CRC — another unit's, on a
//!   multi-drop line — are skipped ([`Event::Other`]). Bytes that are neither are dropped
//!   one at a time until a good frame starts (counted once, [`Event::BadCrc`]): the reader
//!   finds the next frame at once, with no pause on the line needed, however busy the
//!   line. A frame whose function gives no length ends at a gap of [`rtu_gap`] with no
//!   byte: if what arrived has a good CRC it is a request (an unknown function, answered
//!   IllegalFunction). A partial frame waits at most a gap on a serial line, the frame
//!   timeout on TCP (where a frame may come in two segments).

use std::io;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt};
use tokio::time::Instant;

/// The CRC-16/MODBUS of `data` (polynomial 0xA001 reflected, initial 0xFFFF).
pub fn crc16(data: &[u8]) -> u16 {
    let mut crc = 0xFFFFu16;
    for b in data {
        crc ^= u16::from(*b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
        }
    }
    crc
}

/// How a stream frames requests.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Framing {
    /// Modbus TCP (MBAP header).
    Mbap,
    /// Modbus RTU (unit, PDU, CRC), ending frames of no known length after `gap` with no
    /// byte.
    Rtu {
        /// The longest pause within a frame of no known length (and on a serial line
        /// within any frame).
        gap: Duration,
        /// On TCP: a frame of known length may take the frame timeout to come whole.
        tcp: bool,
    },
}

/// The longest pause within an RTU frame the server waits for: 50 ms, or four character
/// times at slow rates. The specification's 1.5 characters cannot be kept by a Linux tty
/// (USB adapters deliver in bursts up to 16 ms apart); a stalled frame still costs no more.
pub fn rtu_gap(baud: Option<u32>) -> Duration {
    let chars = baud.map_or(Duration::ZERO, |b| {
        Duration::from_secs_f64(4.0 * 11.0 / f64::from(b.max(1)))
    });
    chars.max(Duration::from_millis(50))
}

/// A request cut from the stream: its PDU is [`Reader::pdu`] until [`Reader::consume`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Request {
    /// The MBAP transaction id (0 on RTU).
    pub tid: u16,
    /// The unit id.
    pub unit: u8,
    /// Where the PDU starts in the reader's buffer.
    start: usize,
    /// Where the frame ends.
    end: usize,
}

/// What the stream gave.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event {
    /// A whole request.
    Request(Request),
    /// The peer closed the stream.
    Closed,
    /// Nothing for the idle timeout.
    Idle,
    /// A frame begun and not whole in time (MBAP: the frame timeout; RTU: a gap). MBAP
    /// closes the connection; RTU drops the bytes and goes on.
    FrameTimeout,
    /// An MBAP header that is not Modbus: the connection is closed.
    Malformed,
    /// RTU bytes that are no frame (a bad CRC, noise), dropped until a good frame starts;
    /// said once for a run of them.
    BadCrc,
    /// Another unit's RTU reply (a multi-drop line), skipped.
    Other,
}

/// The most bytes a reader keeps: two whole frames.
const KEEP: usize = 2 * 260;

/// Cuts requests out of a stream.
pub struct Reader {
    framing: Framing,
    buf: Vec<u8>,
    /// Dropping bytes that are no frame (said once a run).
    skipping: bool,
    /// The own reply a serial port that receives while it sends will read back.
    echo: Vec<u8>,
}

impl Reader {
    /// A reader of `framing`.
    pub fn new(framing: Framing) -> Reader {
        Reader {
            framing,
            buf: Vec::with_capacity(KEEP),
            skipping: false,
            echo: Vec::new(),
        }
    }

    /// Bytes just sent that come back (a port receiving while it sends): skipped when they
    /// arrive first.
    pub fn expect_echo(&mut self, sent: &[u8]) {
        self.echo.clear();
        self.echo.extend_from_slice(sent);
    }

    /// The PDU of `r` (function code first).
    pub fn pdu(&self, r: &Request) -> &[u8] {
        &self.buf[r.start..r.end - self.trailer()]
    }

    /// Drops request `r`'s bytes: the next call to [`next`](Self::next) looks past it.
    pub fn consume(&mut self, r: &Request) {
        self.buf.drain(..r.end);
    }

    fn trailer(&self) -> usize {
        match self.framing {
            Framing::Mbap => 0,
            Framing::Rtu { .. } => 2,
        }
    }

    /// The next request, or why there is none. `idle` bounds the wait for a frame's first
    /// byte (None: forever); `frame` the wait for the rest of an MBAP frame.
    pub async fn next<S: AsyncRead + Unpin>(
        &mut self,
        stream: &mut S,
        idle: Option<Duration>,
        frame: Duration,
    ) -> io::Result<Event> {
        let mut deadline: Option<Instant> = None;
        loop {
            self.skip_echo();
            match self.cut() {
                Cut::Whole(r) => {
                    self.skipping = false;
                    return Ok(Event::Request(r));
                }
                Cut::Malformed => return Ok(Event::Malformed),
                Cut::Other(n) => {
                    self.skipping = false;
                    self.buf.drain(..n);
                    return Ok(Event::Other);
                }
                Cut::Skip(n) => {
                    self.buf.drain(..n);
                    if !std::mem::replace(&mut self.skipping, true) {
                        return Ok(Event::BadCrc);
                    }
                    continue;
                }
                Cut::More { known } => {
                    // The first byte of a frame waits for `idle`; the rest for the frame
                    // timeout (MBAP, and RTU of a known length on TCP) or a gap (RTU).
                    let wait = match (self.buf.is_empty(), self.framing) {
                        (true, _) => idle.map(|i| Instant::now() + i),
                        (false, Framing::Rtu { gap, tcp }) if !(tcp && known) => {
                            Some(Instant::now() + gap)
                        }
                        (false, _) => Some(*deadline.get_or_insert_with(|| Instant::now() + frame)),
                    };
                    self.buf.reserve(260);
                    let read = stream.read_buf(&mut self.buf);
                    let n = match wait {
                        None => read.await?,
                        Some(at) => match tokio::time::timeout_at(at, read).await {
                            Ok(n) => n?,
                            Err(_) if self.buf.is_empty() => return Ok(Event::Idle),
                            Err(_) => return Ok(self.stalled()),
                        },
                    };
                    if n == 0 {
                        // A last RTU frame whose length was not known is whole at the end.
                        if matches!(self.framing, Framing::Rtu { .. }) && !self.buf.is_empty() {
                            return Ok(self.stalled());
                        }
                        return Ok(Event::Closed);
                    }
                }
            }
        }
    }

    /// Drops the own reply's echo from the front of the buffer once it is there whole.
    fn skip_echo(&mut self) {
        if self.echo.is_empty() || self.buf.is_empty() {
            return;
        }
        let n = self.echo.len().min(self.buf.len());
        if self.buf[..n] != self.echo[..n] {
            self.echo.clear();
        } else if n == self.echo.len() {
            self.buf.drain(..n);
            self.echo.clear();
        }
    }

    /// A frame that stopped coming: on RTU, a request if its CRC is good (a function whose
    /// length the reader does not know); else dropped.
    fn stalled(&mut self) -> Event {
        if let Framing::Rtu { .. } = self.framing
            && self.buf.len() >= 4
            && crc_ok(&self.buf)
        {
            let end = self.buf.len();
            return Event::Request(Request {
                tid: 0,
                unit: self.buf[0],
                start: 1,
                end,
            });
        }
        self.buf.clear();
        self.echo.clear();
        Event::FrameTimeout
    }

    fn cut(&self) -> Cut {
        match self.framing {
            Framing::Mbap => cut_mbap(&self.buf),
            Framing::Rtu { .. } => cut_rtu(&self.buf),
        }
    }
}

enum Cut {
    /// A request.
    Whole(Request),
    /// Not whole yet (`known`: its length is known).
    More { known: bool },
    /// An MBAP header that is not Modbus.
    Malformed,
    /// Another unit's RTU reply of this many bytes.
    Other(usize),
    /// This many bytes that start no frame.
    Skip(usize),
}

fn cut_mbap(b: &[u8]) -> Cut {
    if b.len() < 7 {
        return Cut::More { known: true };
    }
    let (pid, len) = (
        u16::from_be_bytes([b[2], b[3]]),
        usize::from(u16::from_be_bytes([b[4], b[5]])),
    );
    if pid != 0 || !(2..=254).contains(&len) {
        return Cut::Malformed;
    }
    if b.len() < 6 + len {
        return Cut::More { known: true };
    }
    Cut::Whole(Request {
        tid: u16::from_be_bytes([b[0], b[1]]),
        unit: b[6],
        start: 7,
        end: 6 + len,
    })
}

/// An RTU request's whole length from its first bytes: Some(Ok(n)), Some(Err(k)) when byte
/// k (a byte count) is needed first, None for a function whose length is not known.
fn rtu_length(b: &[u8]) -> Option<Result<usize, usize>> {
    let count_at =
        |k: usize, fixed: usize| Some(b.get(k).map(|c| fixed + usize::from(*c)).ok_or(k));
    match *b.get(1)? {
        1..=6 | 8 => Some(Ok(8)),
        7 | 11 | 12 | 17 => Some(Ok(4)),
        15 | 16 => count_at(6, 9),
        20 | 21 => count_at(2, 5),
        22 => Some(Ok(10)),
        23 => count_at(10, 13),
        24 => Some(Ok(6)),
        _ => None,
    }
}

fn crc_ok(frame: &[u8]) -> bool {
    let n = frame.len();
    n >= 4 && crc16(&frame[..n - 2]).to_le_bytes() == [frame[n - 2], frame[n - 1]]
}

/// An RTU reply's whole length from its first bytes, as [`rtu_length`] gives a request's
/// (the client reads its replies by it too).
pub(crate) fn reply_length(b: &[u8]) -> Option<Result<usize, usize>> {
    let count_at =
        |k: usize, fixed: usize| Some(b.get(k).map(|c| fixed + usize::from(*c)).ok_or(k));
    match *b.get(1)? {
        f if f & 0x80 != 0 => Some(Ok(5)),
        1..=4 | 12 | 17 | 20 | 21 | 23 => count_at(2, 5),
        5 | 6 | 8 | 11 | 15 | 16 => Some(Ok(8)),
        7 => Some(Ok(5)),
        22 => Some(Ok(10)),
        _ => None,
    }
}

/// What the bytes at the start of a buffer are, read as a request and as a reply.
enum At {
    /// A request with a good CRC, this long.
    Request(usize),
    /// A reply with a good CRC, this long.
    Reply(usize),
    /// Not whole yet as one of them (`known`: as a request of known length).
    More { known: bool },
    /// Neither.
    Nothing,
}

fn at(b: &[u8]) -> At {
    let whole = |l: Option<Result<usize, usize>>| match l {
        Some(Ok(n)) if b.len() >= n => crc_ok(&b[..n]).then_some(n),
        _ => None,
    };
    let (req, rep) = (rtu_length(b), reply_length(b));
    if let Some(n) = whole(req) {
        return At::Request(n);
    }
    if let Some(n) = whole(rep) {
        return At::Reply(n);
    }
    let waiting = |l: Option<Result<usize, usize>>| match l {
        Some(Ok(n)) => b.len() < n,
        Some(Err(_)) => true,
        None => false,
    };
    if b.len() < 2 || waiting(req) || waiting(rep) || (req.is_none() && rep.is_none()) {
        return At::More {
            known: matches!(req, Some(Ok(_))),
        };
    }
    At::Nothing
}

fn cut_rtu(b: &[u8]) -> Cut {
    match at(b) {
        At::Request(end) => Cut::Whole(Request {
            tid: 0,
            unit: b[0],
            start: 1,
            end,
        }),
        At::Reply(n) => Cut::Other(n),
        // Waiting may be waiting on noise: a good frame after it is taken now instead, and
        // nothing is kept past the longest frame.
        At::More { known } => {
            let good = (1..b.len()).find(|&k| matches!(at(&b[k..]), At::Request(_) | At::Reply(_)));
            match good {
                Some(k) => Cut::Skip(k),
                None if b.len() >= 260 => Cut::Skip(1),
                None => Cut::More { known },
            }
        }
        At::Nothing => Cut::Skip(1),
    }
}

/// Starts a reply to `r` in `out` (cleared): the header the PDU follows.
pub fn begin_reply(framing: Framing, r: &Request, out: &mut Vec<u8>) {
    out.clear();
    match framing {
        Framing::Mbap => {
            out.extend_from_slice(&r.tid.to_be_bytes());
            out.extend_from_slice(&[0, 0, 0, 0, r.unit]);
        }
        Framing::Rtu { .. } => out.push(r.unit),
    }
}

/// Ends the reply begun by [`begin_reply`] once its PDU is in `out`: the MBAP length, or
/// the CRC.
pub fn end_reply(framing: Framing, out: &mut Vec<u8>) {
    match framing {
        Framing::Mbap => {
            let n = (out.len() - 6) as u16;
            out[4..6].copy_from_slice(&n.to_be_bytes());
        }
        Framing::Rtu { .. } => {
            let crc = crc16(out);
            out.extend_from_slice(&crc.to_le_bytes());
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    fn rtu(unit: u8, pdu: &[u8]) -> Vec<u8> {
        let mut f = vec![unit];
        f.extend_from_slice(pdu);
        let crc = crc16(&f);
        f.extend_from_slice(&crc.to_le_bytes());
        f
    }

    async fn events(framing: Framing, bytes: &[u8]) -> Vec<(Event, Vec<u8>)> {
        let (mut a, mut b) = tokio::io::duplex(4096);
        tokio::io::AsyncWriteExt::write_all(&mut a, bytes)
            .await
            .unwrap();
        drop(a);
        let mut r = Reader::new(framing);
        let mut out = Vec::new();
        loop {
            let e = r.next(&mut b, None, Duration::from_secs(1)).await.unwrap();
            let pdu = match e {
                Event::Request(q) => {
                    let p = r.pdu(&q).to_vec();
                    r.consume(&q);
                    p
                }
                Event::Closed => break,
                Event::Malformed => {
                    out.push((e, Vec::new()));
                    break;
                }
                _ => Vec::new(),
            };
            out.push((e, pdu));
        }
        out
    }

    #[tokio::test]
    async fn rtu_frames_are_cut_by_function_and_checked_by_crc() {
        let gap = Framing::Rtu {
            gap: Duration::from_millis(20),
            tcp: false,
        };
        let mut bytes = rtu(1, &[3, 0, 0, 0, 10]);
        bytes.extend(rtu(2, &[16, 0, 1, 0, 2, 4, 0, 7, 0, 8]));
        let got = events(gap, &bytes).await;
        assert_eq!(got.len(), 2);
        assert_eq!(got[0].1, [3, 0, 0, 0, 10]);
        assert!(matches!(got[0].0, Event::Request(Request { unit: 1, .. })));
        assert_eq!(got[1].1, [16, 0, 1, 0, 2, 4, 0, 7, 0, 8]);
        // A bad CRC: dropped, said once, and the request right after it found.
        let mut bad = rtu(1, &[3, 0, 0, 0, 10]);
        bad[6] ^= 1;
        bad.extend(rtu(1, &[3, 0, 0, 0, 1]));
        let got = events(gap, &bad).await;
        assert_eq!(got.len(), 2, "{got:?}");
        assert_eq!(got[0].0, Event::BadCrc);
        assert_eq!(got[1].1, [3, 0, 0, 0, 1]);
    }

    #[tokio::test]
    async fn other_units_replies_on_a_multi_drop_line_are_skipped_not_errors() {
        let gap = Framing::Rtu {
            gap: Duration::from_millis(20),
            tcp: false,
        };
        // Unit 2 asked for one register and answered (7 bytes: shorter than a request),
        // unit 2 written (its echo is the request), then a request to unit 7 at once.
        let mut bytes = rtu(2, &[3, 0, 0, 0, 1]);
        bytes.extend(rtu(2, &[3, 2, 0, 42]));
        bytes.extend(rtu(2, &[16, 0, 1, 0, 1, 2, 0, 7]));
        bytes.extend(rtu(2, &[16, 0, 1, 0, 1]));
        bytes.extend(rtu(2, &[0x83, 2]));
        bytes.extend(rtu(7, &[4, 0, 0, 0, 2]));
        let got = events(gap, &bytes).await;
        let kinds: Vec<_> = got
            .iter()
            .map(|(e, _)| match e {
                Event::Request(r) => format!("request to {}", r.unit),
                other => format!("{other:?}"),
            })
            .collect();
        assert_eq!(
            kinds,
            [
                "request to 2",
                "Other",
                "request to 2",
                "Other",
                "Other",
                "request to 7"
            ]
        );
        // Noise before a request: said once, the request found.
        let mut noisy = vec![0x55, 0xAA, 0x01, 0x03, 0xFF];
        noisy.extend(rtu(7, &[4, 0, 0, 0, 2]));
        let got = events(gap, &noisy).await;
        assert_eq!(got.len(), 2, "{got:?}");
        assert_eq!(
            (got[0].0, &got[1].1[..]),
            (Event::BadCrc, &[4u8, 0, 0, 0, 2][..])
        );
    }

    #[tokio::test]
    async fn a_reader_keeps_no_more_than_a_frame_of_noise() {
        let gap = Framing::Rtu {
            gap: Duration::from_secs(10),
            tcp: false,
        };
        // 4 KiB of an unknown function's noise, arriving without a pause.
        let noise: Vec<u8> = (0..4096u32)
            .map(|i| if i % 2 == 0 { 1 } else { 0x41 })
            .collect();
        let (mut a, mut b) = tokio::io::duplex(64);
        let writer = tokio::spawn(async move {
            // Ends when the reader is dropped.
            let _ = tokio::io::AsyncWriteExt::write_all(&mut a, &noise).await;
        });
        let mut r = Reader::new(gap);
        let e = r.next(&mut b, None, Duration::from_secs(1)).await.unwrap();
        assert!(r.buf.len() <= KEEP, "{}", r.buf.len());
        assert_eq!(e, Event::BadCrc);
        drop(b);
        writer.await.unwrap();
    }

    #[tokio::test]
    async fn an_unknown_function_is_a_frame_at_the_gap_if_its_crc_is_good() {
        let gap = Framing::Rtu {
            gap: Duration::from_millis(20),
            tcp: false,
        };
        let got = events(gap, &rtu(1, &[0x2B, 0x0E, 1, 0])).await;
        assert_eq!(got[0].1, [0x2B, 0x0E, 1, 0]);
        let got = events(gap, &[1, 0x2B, 0x0E, 1, 0, 0]).await;
        assert_eq!(got[0].0, Event::FrameTimeout);
        // Too short to be a frame: dropped at the gap.
        let got = events(gap, &[1, 3, 0]).await;
        assert_eq!(got[0].0, Event::FrameTimeout);
    }

    #[tokio::test]
    async fn mbap_frames_and_replies() {
        let bytes = [0, 7, 0, 0, 0, 6, 9, 3, 0, 0, 0, 2];
        let got = events(Framing::Mbap, &bytes).await;
        let Event::Request(r) = got[0].0 else {
            panic!("{got:?}")
        };
        assert_eq!((r.tid, r.unit), (7, 9));
        let mut out = Vec::new();
        begin_reply(Framing::Mbap, &r, &mut out);
        out.extend_from_slice(&[3, 2, 0, 1]);
        end_reply(Framing::Mbap, &mut out);
        assert_eq!(out, [0, 7, 0, 0, 0, 5, 9, 3, 2, 0, 1]);
        let got = events(Framing::Mbap, &[0, 7, 0, 1, 0, 6, 9, 3]).await;
        assert_eq!(got[0].0, Event::Malformed);
    }
}
