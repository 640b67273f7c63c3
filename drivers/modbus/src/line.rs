//! A Modbus line: one connection, one or more units on it, one request outstanding.
//!
//! A line is a TCP connection (several units behind one gateway are addressed by unit id)
//! or an RTU serial port (several units multi-dropped on it). Its poller (the
//! [`LineIo`](crate::component::LineIo) component, on an rtt activity of its own) polls each
//! unit at its period, feeds the replies to the unit's [`ModbusCard`], sends the unit's
//! changed outputs, and judges the unit's health:
//!
//! - a failed poll keeps the unit online but records why; after `stale_after` failures in a
//!   row its inputs are stale, after `offline_after` it is offline;
//! - an offline unit is probed with a backoff that starts at four timeouts and doubles up
//!   to `backoff_max`, so a dead unit takes at most a quarter of the line's time (less as
//!   its backoff grows) and the healthy units keep their poll rate;
//! - a transport error drops the connection and the line reconnects on the next poll; so
//!   does a timeout on RTU (a late reply there cannot be told from the next request's) or
//!   one that cut a TCP request short while it was being sent; a late TCP reply is dropped
//!   by its transaction id ([`client`](crate::client));
//! - an exception reply surfaces with its code;
//! - a write that fails in transit (timeout, broken connection, a busy unit) is sent again
//!   at the next poll, never dropped; a write the unit refuses with an exception is not
//!   sent again (it would be refused again) and its writers hear so through the card's
//!   delivery ([`ModbusCard::write_refused`]); a unit that goes offline, or a line that
//!   stops, fails the writes still on their way ([`ModbusCard::fail_pending`]).

use crate::card::{ModbusCard, ReadData};
use crate::client::{Client, ClientError, Data, Reply};
use crate::plan::{Barrier, Read};
pub use crate::transport::{Parity, RtuOverTcp, Serial, Transport};
use device_interface::time::Timestamp;
use device_interface::{DeviceError, Status};
use rtt::log::{Area, Arg};
use rtt::rt_log;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// How a unit is polled.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UnitTiming {
    /// The unit id (1..=247; 255 or 0 for a device addressed directly over TCP).
    pub unit: u8,
    /// Poll period.
    pub poll: Duration,
    /// Per-request timeout.
    pub timeout: Duration,
    /// Failed polls in a row before the inputs are stale.
    pub stale_after: u32,
    /// Failed polls in a row before the unit is offline and backed off.
    pub offline_after: u32,
    /// Longest wait between probes of an offline unit.
    pub backoff_max: Duration,
}

/// Line diagnostics per unit: what proves a cabling or device fault.
#[derive(Debug, Default)]
pub struct UnitStats {
    /// Requests sent.
    pub requests: AtomicU64,
    /// Good replies.
    pub replies: AtomicU64,
    /// Requests that timed out.
    pub timeouts: AtomicU64,
    /// Exception replies.
    pub exceptions: AtomicU64,
    /// Connection failures and broken connections.
    pub transport_errors: AtomicU64,
    /// Replies that did not fit their request (short, wrong kind, bad value, wrong unit).
    pub bad_replies: AtomicU64,
    /// Writes that failed and will be sent again.
    pub write_retries: AtomicU64,
    /// Output writes reported failed to their writers, one per output: refused by the unit
    /// (an exception reply, also counted in `exceptions`; not sent again), or still on
    /// their way when the unit went offline or the line stopped.
    pub writes_failed: AtomicU64,
    /// Complete good polls.
    pub polls: AtomicU64,
    /// Holes learned: gaps of the map where the unit refuses reads (found after an
    /// IllegalDataAddress by reading parts of the refused read; see [`holes`](crate::holes)).
    pub splits: AtomicU64,
    /// TCP replies to another transaction (late answers), dropped.
    pub stale_replies: AtomicU64,
    /// How late each poll started after it was due, µs (its first request waited for the
    /// line: the units before it, forwarded requests, a slow wake-up).
    pub lateness: PollLateness,
}

/// Poll lateness, µs (within 1/32 above 32 µs); recorded by the line's thread without a
/// lock, read by `status` while it records.
#[derive(Debug, Default)]
pub struct PollLateness(rtt::histogram::AtomicHistogram);

impl PollLateness {
    /// Records a poll `late` after its due time.
    pub fn record(&self, late: Duration) {
        let us = u64::try_from(late.as_micros()).unwrap_or(u64::MAX);
        self.0.record(us.max(1));
    }

    /// (p99, max) so far, µs; 0 before the first poll.
    pub fn p99_max_us(&self) -> (u64, u64) {
        (self.0.quantile(0.99), self.0.max())
    }
}

/// A snapshot of one unit's [`UnitStats`], for status reports and the line's `counters`
/// operation.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct UnitCounters {
    /// The unit id.
    pub unit: u8,
    /// Complete good polls.
    pub polls: u64,
    /// Requests sent.
    pub requests: u64,
    /// Good replies.
    pub replies: u64,
    /// Requests that timed out.
    pub timeouts: u64,
    /// Exception replies.
    pub exceptions: u64,
    /// Connection failures and broken connections.
    pub transport_errors: u64,
    /// Replies that did not fit their request.
    pub bad_replies: u64,
    /// Writes that failed and will be sent again.
    pub write_retries: u64,
    /// Output writes reported failed to their writers (refused, or pending when the unit
    /// went offline or the line stopped).
    pub writes_failed: u64,
    /// Holes learned: gaps of the map where the unit refuses reads.
    pub splits: u64,
    /// TCP replies to another transaction, dropped.
    pub stale_replies: u64,
    /// 99th percentile of how late polls started after they were due, µs (since start).
    #[serde(default)]
    pub poll_lateness_p99_us: u64,
    /// The latest a poll started after it was due, µs (since start).
    #[serde(default)]
    pub poll_lateness_max_us: u64,
}

impl UnitCounters {
    /// The counters of unit `unit` now.
    pub fn from_stats(unit: u8, s: &UnitStats) -> UnitCounters {
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let (p99, max) = s.lateness.p99_max_us();
        UnitCounters {
            poll_lateness_p99_us: p99,
            poll_lateness_max_us: max,
            unit,
            polls: load(&s.polls),
            requests: load(&s.requests),
            replies: load(&s.replies),
            timeouts: load(&s.timeouts),
            exceptions: load(&s.exceptions),
            transport_errors: load(&s.transport_errors),
            bad_replies: load(&s.bad_replies),
            write_retries: load(&s.write_retries),
            writes_failed: load(&s.writes_failed),
            splits: load(&s.splits),
            stale_replies: load(&s.stale_replies),
        }
    }

    /// The counters of a unit on a line.
    pub fn of(u: &LineUnit) -> UnitCounters {
        Self::from_stats(u.timing.unit, &u.stats)
    }
}

/// A unit on a line.
pub struct LineUnit {
    /// Its devices.
    pub card: Arc<ModbusCard>,
    /// How it is polled.
    pub timing: UnitTiming,
    /// Its diagnostics.
    pub stats: Arc<UnitStats>,
}

#[derive(Debug, thiserror::Error)]
enum PollError {
    #[error("unit {unit}: no reply to {what} within {timeout:?}")]
    Timeout {
        unit: u8,
        what: String,
        timeout: Duration,
        /// Cancelled while the request was being sent: the stream is out of step.
        out_of_step: bool,
    },
    #[error("unit {unit}: {what}: {source}")]
    Transport {
        unit: u8,
        what: String,
        source: std::io::Error,
    },
    #[error("unit {unit}: {what}: Modbus exception {} ({code:#04x})", exception_name(*.code))]
    Exception { unit: u8, what: String, code: u8 },
    #[error("unit {unit}: {what}: {why}")]
    Garbled { unit: u8, what: String, why: String },
    #[error("unit {unit}: {what}: {source}")]
    BadReply {
        unit: u8,
        what: String,
        source: crate::card::ReplyError,
    },
}

impl PollError {
    /// Whether the connection must be dropped. On TCP a late reply is told apart by its
    /// transaction id, so only a broken connection, or one a timeout left in the middle of
    /// sending a request, is dropped; RTU has no transaction id, so a timeout or a garbled
    /// reply reopens the port too (discarding what a late unit may still send).
    fn breaks_connection(&self, rtu: bool) -> bool {
        match self {
            PollError::Transport { .. } => true,
            PollError::Timeout { out_of_step, .. } => rtu || *out_of_step,
            PollError::Garbled { .. } => rtu,
            PollError::Exception { .. } | PollError::BadReply { .. } => false,
        }
    }
}

/// Where a unit is in its schedule.
pub(crate) struct UnitState {
    /// When its next poll is due (CLOCK_MONOTONIC).
    pub(crate) next: Timestamp,
    /// Failed polls in a row.
    pub(crate) failures: u32,
    /// The wait before the next probe while offline.
    pub(crate) backoff: Duration,
    /// The unit's own plan once holes were found (None: the map's).
    pub(crate) plan: Option<Vec<Read>>,
    /// The gaps where the unit has holes, found so far.
    pub(crate) holes: Vec<Barrier>,
    /// When a refused write was last logged (refusals are logged at most once a second).
    refusal_logged: Option<Timestamp>,
    /// Refused writes not logged since.
    refusals_unlogged: u64,
    /// Where the line logs (its card's name): real-time safe.
    pub(crate) log: Area,
}

impl UnitState {
    pub(crate) fn new(t: &UnitTiming, now: Timestamp, log: Area) -> Self {
        UnitState {
            log,
            next: now,
            failures: 0,
            backoff: first_backoff(t),
            plan: None,
            holes: Vec::new(),
            refusal_logged: None,
            refusals_unlogged: 0,
        }
    }
}

fn bump(c: &AtomicU64) {
    c.fetch_add(1, Ordering::Relaxed);
}

/// Polls `unit` once (reads, then its pending writes) and moves its schedule on: the next
/// poll one period after the due time (from now after a stall, never a burst), or a
/// growing backoff once the unit is offline. `due` is when this poll was due.
pub(crate) async fn poll_and_schedule(
    ctx: &mut Option<Client>,
    transport: &Transport,
    unit: &LineUnit,
    state: &mut UnitState,
    due: Timestamp,
    now: &dyn Fn() -> Timestamp,
) {
    let t = unit.timing;
    unit.stats.lateness.record(Duration::from_nanos(
        now().as_nanos().saturating_sub(due.as_nanos()),
    ));
    match poll_unit(ctx, transport, unit, state).await {
        Ok(refused) => {
            if let Some(e) = refused {
                log_refusal(state, &e, now());
            }
            unit.card.poll_succeeded();
            bump(&unit.stats.polls);
            if state.failures >= t.offline_after {
                rt_log!(state.log, Info, "modbus unit {}: back online", t.unit);
            }
            state.failures = 0;
            state.backoff = first_backoff(&t);
            // Keep the grid; after a long stall start from now rather than bursting.
            state.next = due.saturating_add(t.poll).max(now());
        }
        Err(e) => {
            if e.breaks_connection(transport.rtu_framed()) {
                *ctx = None;
            }
            state.failures += 1;
            let status = if state.failures >= t.offline_after {
                Status::Offline
            } else if state.failures >= t.stale_after {
                Status::Stale
            } else {
                Status::Online
            };
            // Log on change, not on every failed poll.
            if state.failures == 1
                || state.failures == t.stale_after
                || state.failures == t.offline_after
            {
                let [a, b] = Arg::chunks(&e);
                rt_log!(
                    state.log,
                    Warn,
                    "modbus {}{} (failure {} in a row: {})",
                    a,
                    b,
                    state.failures,
                    Arg::display(&status)
                );
            }
            unit.card.poll_failed(DeviceError::bus(e), status);
            if status == Status::Offline {
                // Nothing carries a write to an offline unit: its writers hear so now
                // (again at each failed probe, for a write taken as the unit went offline).
                fail_pending(unit, &DeviceError::Offline, &state.log);
                state.next = now().saturating_add(state.backoff);
                state.backoff = (state.backoff * 2).min(t.backoff_max);
            } else {
                state.next = due.saturating_add(t.poll).max(now());
            }
        }
    }
}

/// Fails the writes on their way to `unit` for `why` (see [`ModbusCard::fail_pending`]),
/// counted.
pub(crate) fn fail_pending(unit: &LineUnit, why: &DeviceError, log: &Area) {
    let n = unit.card.fail_pending(why);
    if n > 0 {
        unit.stats
            .writes_failed
            .fetch_add(n as u64, Ordering::Relaxed);
        rt_log!(
            log,
            Warn,
            "modbus unit {}: {} output write(s) not delivered: {}",
            unit.timing.unit,
            n,
            Arg::display(why)
        );
    }
}

/// Logs a write the unit refused, at most once a second (a writer may repeat a value the
/// unit refuses at every cycle); the refusals in between are counted in the next line.
fn log_refusal(state: &mut UnitState, e: &PollError, now: Timestamp) {
    let quiet = state
        .refusal_logged
        .is_some_and(|t| now.duration_since(t) < Duration::from_secs(1));
    if quiet {
        state.refusals_unlogged += 1;
        return;
    }
    let more = std::mem::take(&mut state.refusals_unlogged);
    let [a, b] = Arg::chunks(e);
    if more > 0 {
        rt_log!(
            state.log,
            Warn,
            "modbus {}{}: the write is not sent again ({} more refused since the last report)",
            a,
            b,
            more
        );
    } else {
        rt_log!(
            state.log,
            Warn,
            "modbus {}{}: the write is not sent again",
            a,
            b
        );
    }
    state.refusal_logged = Some(now);
}

/// The first wait before probing an offline unit again: four timeouts (a probe of a dead
/// unit costs one), at least a poll period, at most `backoff_max`.
fn first_backoff(t: &UnitTiming) -> Duration {
    (t.timeout * 4).max(t.poll).min(t.backoff_max.max(t.poll))
}

fn describe_read(r: &Read) -> String {
    r.to_string()
}

/// Whether an exception answering a write means the unit refused it (sending it again
/// would be refused again) rather than "not now": Acknowledge (5) and ServerDeviceBusy (6)
/// ask for a later try, GatewayPathUnavailable (10) and GatewayTargetDevice (11) say a
/// gateway could not reach the unit behind it — those are retried like a timeout.
fn refuses(code: u8) -> bool {
    !matches!(code, 5 | 6 | 10 | 11)
}

/// Why a write answered with exception `code` was not delivered.
fn refusal(code: u8) -> DeviceError {
    DeviceError::Undelivered {
        reason: match code {
            1 => "the Modbus unit refused it: exception IllegalFunction (0x01)",
            2 => "the Modbus unit refused it: exception IllegalDataAddress (0x02)",
            3 => "the Modbus unit refused it: exception IllegalDataValue (0x03)",
            4 => "the Modbus unit refused it: exception ServerDeviceFailure (0x04)",
            8 => "the Modbus unit refused it: exception MemoryParityError (0x08)",
            _ => "the Modbus unit refused it with an exception (see the card's log)",
        },
    }
}

/// One poll: the reads, then the writes. `Ok(Some(e))`: a good poll in which the unit
/// refused a write (`e`, the first refusal), which is not sent again.
async fn poll_unit(
    ctx: &mut Option<Client>,
    transport: &Transport,
    unit: &LineUnit,
    state: &mut UnitState,
) -> Result<Option<PollError>, PollError> {
    let t = unit.timing;
    let stats = &unit.stats;
    if ctx.is_none() {
        // Opening anew also discards whatever a timed-out unit may still send.
        let what = || format!("opening {}", transport.describe());
        match tokio::time::timeout(t.timeout, transport.open()).await {
            Ok(Ok(c)) => *ctx = Some(c),
            Ok(Err(source)) => {
                bump(&stats.transport_errors);
                return Err(PollError::Transport {
                    unit: t.unit,
                    what: what(),
                    source,
                });
            }
            Err(_) => {
                bump(&stats.timeouts);
                return Err(PollError::Timeout {
                    unit: t.unit,
                    what: what(),
                    timeout: t.timeout,
                    out_of_step: false,
                });
            }
        }
    }
    let Some(c) = ctx.as_mut() else {
        return Err(PollError::Transport {
            unit: t.unit,
            what: "connection".into(),
            source: std::io::Error::from(std::io::ErrorKind::NotConnected),
        });
    };
    let map = unit.card.map();
    let (mut pdu, mut out) = (Vec::with_capacity(260), Vec::with_capacity(260));
    let mut ri = 0;
    while let Some(read) = state.plan.as_deref().unwrap_or(map.reads()).get(ri) {
        let what = || describe_read(read);
        crate::client::read_request(read, &mut pdu);
        let reply = exchange(c, t, stats, &pdu, &mut out, what).await;
        if let Err(PollError::Exception { code: 2, .. }) = &reply
            && map.learns_holes()
        {
            let read = read.clone();
            let found = crate::holes::find(map, &read, async |part: &Read| {
                let mut pdu = Vec::with_capacity(12);
                crate::client::read_request(part, &mut pdu);
                match exchange(c, t, stats, &pdu, &mut out, || describe_read(part)).await {
                    Ok(()) => Ok(true),
                    Err(PollError::Exception { code: 2, .. }) => Ok(false),
                    Err(e) => Err(e),
                }
            })
            .await?;
            let new: Vec<Barrier> = found
                .into_iter()
                .filter(|b| !state.holes.contains(b))
                .collect();
            if !new.is_empty() {
                // The unit has holes in this read's gaps: the plan is made anew around
                // them, and this poll starts over on it (so no point misses it).
                stats.splits.fetch_add(new.len() as u64, Ordering::Relaxed);
                state.holes.extend_from_slice(&new);
                let reads = map.reads_around(&state.holes);
                rt_log!(
                    state.log,
                    Info,
                    "modbus unit {}: {} refused (IllegalDataAddress): holes in {}; {} reads a poll now",
                    t.unit,
                    rtt::log::Arg::display(&read),
                    rtt::log::Arg::display(&crate::plan::Listed(&new)),
                    reads.len()
                );
                state.plan = Some(reads);
                ri = 0;
                continue;
            }
        }
        reply?;
        let applied = match crate::client::read_data(read, &out) {
            Ok(Data::Bits(b)) => unit.card.apply(ri, read, ReadData::Bits(&b)),
            Ok(Data::Words(w)) => unit.card.apply(ri, read, ReadData::Registers(&w)),
            Err(why) => {
                bump(&stats.bad_replies);
                return Err(PollError::Garbled {
                    unit: t.unit,
                    what: what(),
                    why,
                });
            }
        };
        if let Err(source) = applied {
            bump(&stats.bad_replies);
            return Err(PollError::BadReply {
                unit: t.unit,
                what: what(),
                source,
            });
        }
        ri += 1;
    }
    let writes = unit.card.take_writes();
    let mut refused = None;
    for (k, w) in writes.iter().enumerate() {
        let sent = match crate::client::write_request(w, &mut pdu) {
            Ok(()) => exchange(c, t, stats, &pdu, &mut out, || format!("{w:?}")).await,
            Err(e) => Err(PollError::Garbled {
                unit: t.unit,
                what: format!("{w:?}"),
                why: e.to_string(),
            }),
        };
        match sent {
            Ok(()) => unit.card.write_delivered(w),
            Err(e @ PollError::Exception { code, .. }) if refuses(code) => {
                // The unit answered: the connection is fine and the next writes go on.
                let n = unit.card.write_refused(w, &refusal(code));
                stats.writes_failed.fetch_add(n as u64, Ordering::Relaxed);
                refused.get_or_insert(e);
            }
            Err(e) => {
                // This write and the ones not yet sent go out again at the next poll.
                for w in &writes[k..] {
                    unit.card.retry(w);
                    bump(&stats.write_retries);
                }
                return Err(e);
            }
        }
    }
    Ok(refused)
}

/// The name of an exception code, for messages.
fn exception_name(code: u8) -> &'static str {
    match code {
        1 => "IllegalFunction",
        2 => "IllegalDataAddress",
        3 => "IllegalDataValue",
        4 => "ServerDeviceFailure",
        5 => "Acknowledge",
        6 => "ServerDeviceBusy",
        8 => "MemoryParityError",
        10 => "GatewayPathUnavailable",
        11 => "GatewayTargetDevice",
        _ => "unknown",
    }
}

/// One request and its reply within the unit's timeout, each failure counted: the reply
/// PDU is in `out`.
async fn exchange(
    c: &mut Client,
    t: UnitTiming,
    stats: &UnitStats,
    pdu: &[u8],
    out: &mut Vec<u8>,
    what: impl Fn() -> String,
) -> Result<(), PollError> {
    bump(&stats.requests);
    let mut stale = 0;
    let reply = tokio::time::timeout(t.timeout, c.request(t.unit, pdu, out, &mut stale)).await;
    stats.stale_replies.fetch_add(stale, Ordering::Relaxed);
    match reply {
        Err(_) => {
            bump(&stats.timeouts);
            Err(PollError::Timeout {
                unit: t.unit,
                what: what(),
                timeout: t.timeout,
                out_of_step: c.out_of_step(),
            })
        }
        Ok(Err(ClientError::Io(source))) => {
            bump(&stats.transport_errors);
            Err(PollError::Transport {
                unit: t.unit,
                what: what(),
                source,
            })
        }
        Ok(Err(ClientError::Bad(why))) => {
            bump(&stats.bad_replies);
            Err(PollError::Garbled {
                unit: t.unit,
                what: what(),
                why,
            })
        }
        Ok(Ok(Reply::Exception(code))) => {
            bump(&stats.exceptions);
            Err(PollError::Exception {
                unit: t.unit,
                what: what(),
                code,
            })
        }
        Ok(Ok(Reply::Pdu | Reply::Broadcast)) => {
            bump(&stats.replies);
            Ok(())
        }
    }
}
