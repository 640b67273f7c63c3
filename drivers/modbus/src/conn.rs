//! One stream of requests served: a TCP connection (MBAP or RTU frames) or a serial port
//! (an RTU slave). Each request is cut by its [`framing`](crate::framing), routed by its
//! unit id ([`Units`]), checked by [`pdu`] and answered by the [`RegisterTable`]; a write
//! a bus carries later is answered once it is settled (see
//! [`listener`](crate::listener)).
//!
//! | unit id | MBAP | RTU (serial or TCP) |
//! |---|---|---|
//! | one of `units` | answered | answered |
//! | 0, not in `units` | 0x0A | broadcast: writes applied, no reply |
//! | another, a gateway route's | forwarded | forwarded (over TCP; on a serial port, ignored) |
//! | another | 0x0A (no path to it) | ignored (another unit's), counted |
//!
//! With `units` not given every unit id but RTU's broadcast 0 is the server's own.

use crate::framing::{Event, Framing, Reader, Request, begin_reply, end_reply};
use crate::limits::Limits;
use crate::pdu::{self, Refusal, Resp, exception};
use crate::server::{Answer, ExceptionCode, RegisterTable, Unsettled};
use crate::shared::{Stats, Units, bump, first_of_hundred};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt};

/// What becomes of a request for a unit.
enum Route<'a> {
    /// Answered here.
    Local,
    /// Forwarded on a line (gateway mode).
    Forward(&'a crate::gateway::Route),
    /// An RTU broadcast: applied here, not answered.
    Broadcast,
    /// Another unit's on an RTU line: not answered.
    Ignore,
    /// No path to that unit: 0x0A.
    Unreachable,
}

/// One stream's context.
pub(crate) struct Conn<'a> {
    pub(crate) table: &'a RegisterTable,
    pub(crate) stats: &'a Stats,
    pub(crate) limits: Limits,
    pub(crate) units: &'a Units,
    /// Where requests for other units go (none on a serial port: other units there are
    /// on the same line and answer themselves).
    pub(crate) routes: &'a [crate::gateway::Route],
    pub(crate) framing: Framing,
    /// Wait this long after a request's last byte before its reply (a serial line's
    /// silence and turnaround; zero on TCP).
    pub(crate) reply_delay: Duration,
    /// Close the stream after `idle_timeout` without a request (TCP; a serial line is
    /// never idle-closed).
    pub(crate) idle_close: bool,
    /// The port reads back what it sends (RS-485 `rx_during_tx`): each reply's echo is
    /// skipped.
    pub(crate) echo: bool,
    /// Set to `since(epoch)` at each complete request.
    pub(crate) last: &'a AtomicU64,
    pub(crate) epoch: std::time::Instant,
}

impl Conn<'_> {
    fn route(&self, unit: u8) -> Route<'_> {
        let rtu = matches!(self.framing, Framing::Rtu { .. });
        if self.units.own(unit, rtu) {
            Route::Local
        } else if let Some(r) = self.routes.iter().find(|r| r.takes(unit)) {
            Route::Forward(r)
        } else if !rtu {
            Route::Unreachable
        } else if unit == 0 {
            Route::Broadcast
        } else {
            Route::Ignore
        }
    }

    /// Serves the stream until the peer closes it, it idles out, stops mid-frame (MBAP) or
    /// sends no Modbus (MBAP).
    pub(crate) async fn serve<S: AsyncRead + AsyncWrite + Unpin>(
        &self,
        stream: &mut S,
    ) -> std::io::Result<()> {
        let stats = self.stats;
        let idle = self.limits.idle_timeout;
        let frame = self.limits.frame_timeout.min(idle);
        let mut reader = Reader::new(self.framing);
        let mut out = Vec::with_capacity(260);
        loop {
            let wait = self.idle_close.then_some(idle);
            let r = match reader.next(stream, wait, frame).await? {
                Event::Request(r) => r,
                Event::Closed => return Ok(()),
                Event::Idle => {
                    bump(&stats.idle_closed);
                    return Ok(());
                }
                Event::FrameTimeout => {
                    bump(&stats.frame_timeouts);
                    match self.framing {
                        Framing::Mbap => return Ok(()),
                        Framing::Rtu { .. } => continue,
                    }
                }
                Event::Malformed => {
                    bump(&stats.malformed);
                    return Ok(());
                }
                Event::BadCrc => {
                    bump(&stats.crc_errors);
                    continue;
                }
                Event::Other => {
                    bump(&stats.other_units);
                    continue;
                }
            };
            let got = tokio::time::Instant::now();
            // A complete request: this connection is not idle (eviction goes by this).
            self.last
                .store(self.epoch.elapsed().as_nanos() as u64, Ordering::Relaxed);
            let answered = self.answer(&reader, &r, &mut out).await;
            reader.consume(&r);
            if !answered {
                continue;
            }
            if !self.reply_delay.is_zero() {
                // (A zero sleep would still wait for the timer's next millisecond tick.)
                tokio::time::sleep_until(got + self.reply_delay).await;
            }
            match tokio::time::timeout(idle, stream.write_all(&out)).await {
                Err(_) => {
                    // The client does not take its replies.
                    bump(&stats.idle_closed);
                    return Ok(());
                }
                Ok(r) => r?,
            }
            if self.echo {
                reader.expect_echo(&out);
            }
        }
    }

    /// Answers request `r` into `out` (the whole framed reply); false when it is not
    /// answered (a broadcast, another unit's request on an RTU line).
    async fn answer(&self, reader: &Reader, r: &Request, out: &mut Vec<u8>) -> bool {
        let stats = self.stats;
        let pdu = reader.pdu(r);
        let function = pdu.first().copied().unwrap_or(0);
        let answer = match self.route(r.unit) {
            Route::Ignore => {
                bump(&stats.other_units);
                return false;
            }
            Route::Broadcast => {
                bump(&stats.requests);
                bump(&stats.broadcasts);
                // Writes only (a read has nobody to answer); applied as far as the
                // devices take them at once, nobody told either way.
                if matches!(function, 5 | 6 | 15 | 16) {
                    let _ = take(self.table, stats, pdu);
                }
                return false;
            }
            Route::Unreachable => {
                bump(&stats.requests);
                bump(&stats.unreachable);
                Err(Refusal {
                    function,
                    code: exception::GATEWAY_PATH_UNAVAILABLE,
                })
            }
            Route::Forward(route) => {
                bump(&stats.requests);
                match route.forward(r.unit, pdu).await {
                    Ok(reply) => {
                        bump(&stats.forwarded);
                        begin_reply(self.framing, r, out);
                        out.extend_from_slice(&reply);
                        end_reply(self.framing, out);
                        return true;
                    }
                    Err(failed) => {
                        bump(
                            if failed.exception() == exception::GATEWAY_PATH_UNAVAILABLE {
                                &stats.gateway_unavailable
                            } else {
                                &stats.gateway_no_response
                            },
                        );
                        Err(Refusal {
                            function,
                            code: failed.exception(),
                        })
                    }
                }
            }
            Route::Local => {
                bump(&stats.requests);
                match take(self.table, stats, pdu) {
                    Ok(Answer { reply, unsettled }) if !unsettled.is_empty() => {
                        // Awaited here, in this stream's task: the others are served
                        // meanwhile.
                        self.settle(unsettled)
                            .await
                            .map(|()| reply)
                            .map_err(|code| Refusal { function, code })
                    }
                    other => other.map(|a| a.reply),
                }
            }
        };
        begin_reply(self.framing, r, out);
        encode(stats, answer, out);
        end_reply(self.framing, out);
        true
    }
    /// Waits until the writes of a request are settled, at most `write_confirm`: `Ok` once
    /// every one is delivered, else the exception answering the request (see
    /// [`server::undelivered`](crate::server::undelivered)). Counts the outcome.
    async fn settle(&self, mut writes: Unsettled) -> Result<(), ExceptionCode> {
        const FIRST: Duration = Duration::from_millis(1);
        const MOST: Duration = Duration::from_millis(5);
        let stats = self.stats;
        let deadline = tokio::time::Instant::now() + self.limits.write_confirm;
        let mut pause = FIRST;
        loop {
            let Ok(now) = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| writes.check()))
            else {
                // A device's bug, as a panic while answering.
                bump(&stats.panics);
                return Err(exception::SERVER_DEVICE_FAILURE);
            };
            match now {
                Some(Ok(())) => {
                    bump(&stats.writes_confirmed);
                    return Ok(());
                }
                Some(Err(why)) => {
                    if first_of_hundred(&stats.writes_failed) {
                        tracing::warn!("modbus server: a write was not delivered: {why}");
                    }
                    return Err(crate::server::undelivered(&why));
                }
                None if tokio::time::Instant::now() >= deadline => {
                    if first_of_hundred(&stats.writes_unconfirmed) {
                        tracing::warn!(
                            "modbus server: {} write(s) still on their way after {:?} (write_confirm_ms): answered 0x0B",
                            writes.len(),
                            self.limits.write_confirm
                        );
                    }
                    return Err(exception::GATEWAY_TARGET_FAILED_TO_RESPOND);
                }
                None => {
                    tokio::time::sleep_until(deadline.min(tokio::time::Instant::now() + pause))
                        .await;
                    pause = (pause * 2).min(MOST);
                }
            }
        }
    }
}

/// Checks `pdu` and has the table answer it (its writes made): the reply and the writes
/// it waits for, or the refusal.
fn take(table: &RegisterTable, stats: &Stats, pdu: &[u8]) -> Result<Answer, Refusal> {
    pdu::parse(pdu).and_then(|req| {
        let function = pdu[0];
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| table.answer(req)))
            .unwrap_or_else(|_| {
                bump(&stats.panics);
                Err(exception::SERVER_DEVICE_FAILURE)
            })
            .map_err(|code| Refusal { function, code })
    })
}

/// Appends the reply PDU (or the exception) to `out`.
fn encode(stats: &Stats, answer: Result<Resp, Refusal>, out: &mut Vec<u8>) {
    match answer {
        Ok(resp) => pdu::encode(&resp, out),
        Err(r) => {
            bump(&stats.exceptions);
            pdu::encode_refusal(r, out);
        }
    }
}

/// Answers `pdu` as the server would, into `out` (for tests and the fuzz run: the whole
/// request path but the socket) — except that it does not wait for writes a device's bus
/// carries later: it answers as if they were delivered.
pub fn answer_pdu(table: &RegisterTable, pdu: &[u8], out: &mut Vec<u8>) {
    thread_local! {
        static STATS: Stats = Stats::default();
    }
    STATS.with(|s| encode(s, take(table, s, pdu).map(|a| a.reply), out));
}
