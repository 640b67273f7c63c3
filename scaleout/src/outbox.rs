//! The sender's side of one imported device's writes: what goes out, under which sequence
//! number, when it is sent again, and when it has failed.
//!
//! Every output written since the last acknowledgement goes out with its newest value in
//! one [`Write`] under a new sequence number. With no answer after the retry interval the
//! same message — same sequence number, same values — goes again; the remote gateway
//! applies a sequence number once and acknowledges repeats without writing them, so a
//! repeat never feeds its output watchdog. A newer write to any of those outputs makes a
//! new message. An output that has waited `request_timeout_ms` for an acknowledgement —
//! none of its writes delivered since the first of them went unacknowledged — is failed
//! ([`Image::undelivered`]), counted, and its writer hears so; nothing more is sent once
//! the gateway stops.

use crate::remote::Image;
use crate::wire::{self, Write};
use std::collections::HashMap;
use std::time::{Duration, Instant};

/// A message on its way.
#[derive(Debug, Clone)]
struct InFlight {
    seq: u64,
    /// `(channel, number of the write carried)`.
    numbers: Vec<(u32, u64)>,
    values: Vec<(u32, i64)>,
    sent: Instant,
}

/// What to send now, from [`Outbox::next`].
#[derive(Debug, Clone, PartialEq)]
pub struct Outgoing {
    /// The message.
    pub write: Write,
    /// `(channel, number of the write carried)`, for [`Image::answered`].
    pub numbers: Vec<(u32, u64)>,
    /// True when this is the same message sent again.
    pub retry: bool,
}

/// One imported device's writes on their way (owned by the sender thread).
#[derive(Debug)]
pub struct Outbox {
    writer: String,
    session: u64,
    next_seq: u64,
    inflight: Option<InFlight>,
    /// Since when each output has waited for an acknowledgement, and the newest of its
    /// writes delivered then: a newer delivery (B acknowledged meanwhile) starts the wait
    /// again, so a writer faster than the acknowledgements never times out while they come.
    since: HashMap<u32, (Instant, u64)>,
    timeout: Duration,
    retry: Duration,
}

impl Outbox {
    /// The outbox of gateway `writer` (this run's `session` number, so the remote
    /// gateway tells a restarted writer from a repeat) with writes failing after `timeout`
    /// and sent again every `retry` until then.
    pub fn new(writer: &str, session: u64, timeout: Duration, retry: Duration) -> Self {
        Outbox {
            writer: writer.to_string(),
            session,
            next_seq: 0,
            inflight: None,
            since: HashMap::new(),
            timeout,
            retry,
        }
    }

    /// The retry interval for writes failing after `timeout`: an eighth of it, between
    /// 20 ms and 500 ms.
    pub fn retry_for(timeout: Duration) -> Duration {
        (timeout / 8).clamp(Duration::from_millis(20), Duration::from_millis(500))
    }

    /// What to send for `img` at `now`, if anything; fails the writes that waited too long.
    pub fn next(&mut self, img: &Image, now: Instant) -> Option<Outgoing> {
        if img.is_held() {
            // The gateway is stopping: nothing more goes out (what was on its way failed).
            self.inflight = None;
            return None;
        }
        let mut pending = img.pending();
        self.since
            .retain(|c, _| pending.iter().any(|(p, _)| p == c));
        pending.retain(|&(c, n)| {
            let delivered = img.delivery(c).delivered;
            let wait = self.since.entry(c).or_insert((now, delivered));
            if delivered > wait.1 {
                *wait = (now, delivered);
            }
            if now.saturating_duration_since(wait.0) < self.timeout {
                return true;
            }
            img.undelivered(
                c,
                n,
                &format!(
                    "no acknowledgement of channel {c} within {} ms",
                    self.timeout.as_millis()
                ),
            );
            self.since.remove(&c);
            false
        });
        if pending.is_empty() {
            self.inflight = None;
            return None;
        }
        let fresh = self.inflight.as_ref().is_none_or(|f| {
            pending.iter().any(|(c, n)| {
                f.numbers
                    .iter()
                    .find(|(fc, _)| fc == c)
                    .is_none_or(|(_, fnum)| n > fnum)
            })
        });
        if fresh {
            self.next_seq += 1;
            let values = pending.iter().map(|&(c, _)| (c, img.written(c))).collect();
            self.inflight = Some(InFlight {
                seq: self.next_seq,
                numbers: pending,
                values,
                sent: now,
            });
        } else if let Some(f) = &mut self.inflight {
            if now.saturating_duration_since(f.sent) < self.retry {
                return None;
            }
            f.sent = now;
        }
        let f = self.inflight.as_ref()?;
        Some(Outgoing {
            write: Write {
                protocol: wire::PROTOCOL,
                writer: self.writer.clone(),
                interface: img.interface(),
                device: img.device().to_string(),
                values: f.values.clone(),
                seq: f.seq,
                session: self.session,
            },
            numbers: f.numbers.clone(),
            retry: !fresh,
        })
    }
}
