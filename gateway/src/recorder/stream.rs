//! The control socket's `record` stream: the gateway side taps the runtime and sends
//! batches; `hwgw record` on the client side writes them into an MCAP file of its own (the
//! file belongs to whoever runs the command, never to the service).

use super::taps::{Taps, now_ns, resolve, wall_offset};
use crate::deploy::Gateway;
use crate::protocol::{ErrorKind, RecordBatch, RecordStart};
use recording::Item;
use std::time::{Duration, Instant};

/// How often the gateway sends a batch.
pub const BATCH_EVERY: Duration = Duration::from_millis(20);

/// How often a batch goes out even when nothing came (so losses and a stopped gateway are
/// seen).
const IDLE_BATCH: Duration = Duration::from_secs(1);

/// What a `record` request asks for.
pub struct Ask<'a> {
    /// Port selectors.
    pub ports: &'a [String],
    /// Every card's output ports too.
    pub devices: bool,
    /// Every activity's steps too.
    pub steps: bool,
    /// Buffer per port.
    pub buffer: Option<usize>,
}

/// The default buffer of a recorded port, in samples.
pub const DEFAULT_BUFFER: usize = 4096;

/// The most items one batch line carries: a longer drain goes out in several.
pub const MAX_BATCH_ITEMS: usize = 20_000;

/// The most bytes of items (as JSON) one batch line carries: a larger drain goes out in
/// several lines, so that none reaches the client's line limit
/// ([`MAX_STREAM_LINE`](crate::client::MAX_STREAM_LINE)); the other half is room for the
/// rest of the line (the id, each port's and activity's loss count). A sample larger than
/// this alone cannot be carried: it is left out and counted with the unserialisable ones.
pub const MAX_BATCH_BYTES: usize = (crate::client::MAX_STREAM_LINE / 2) as usize;

/// Opens the taps a request asks for; an error says what kind it is for the reply.
pub fn open(gw: &Gateway, ask: &Ask<'_>) -> Result<(Taps, RecordStart), (ErrorKind, String)> {
    let not_found = |e: String| (ErrorKind::NotFound, e);
    let rt = gw.runtime();
    let mut selectors = ask.ports.to_vec();
    if ask.devices {
        // A card's devices are its components: `card.ai`, `card.do`, … (and `card`).
        let cards: Vec<String> = gw.card_status().into_iter().map(|c| c.name).collect();
        selectors.extend(
            rt.components()
                .iter()
                .map(|t| t.name().to_string())
                .filter(|n| {
                    cards.iter().any(|c| {
                        n == c
                            || n.strip_prefix(c.as_str())
                                .is_some_and(|r| r.starts_with('.'))
                    })
                }),
        );
    }
    if selectors.is_empty() && !ask.steps {
        return Err((
            ErrorKind::BadRequest,
            "nothing to record: name ports, devices or steps".into(),
        ));
    }
    let peer = |n: &str| rt.component(n).map_err(|e| e.to_string());
    let ports = resolve(&peer, &selectors).map_err(not_found)?;
    let activities: Vec<String> = if ask.steps {
        rt.components()
            .iter()
            .filter(|t| t.activity().thread_number().is_some())
            .map(|t| t.name().to_string())
            .collect()
    } else {
        Vec::new()
    };
    let taps = Taps::open(
        &peer,
        ports,
        &activities,
        ask.buffer.unwrap_or(DEFAULT_BUFFER),
    )
    .map_err(|e| (ErrorKind::Failed, e))?;
    let start = RecordStart {
        ports: taps.ports().to_vec(),
        activities: taps.activities().to_vec(),
        wall_minus_clock_ns: wall_offset(),
        now_ns: now_ns(),
    };
    Ok((taps, start))
}

/// Sends batches from `taps` through `send` every [`BATCH_EVERY`] until `send` fails (the
/// client went away) or `stop` says so — then one last batch with what came meanwhile and
/// the losses up to then, so that a recording the gateway ends counts all it lost.
pub fn pump(mut taps: Taps, mut send: impl FnMut(RecordBatch) -> bool, stop: impl Fn() -> bool) {
    let mut last_sent = Instant::now();
    // Samples too large for a line, so far.
    let mut too_large = 0;
    loop {
        let last = stop();
        if !last {
            std::thread::sleep(BATCH_EVERY);
        }
        let now = now_ns();
        let mut items = Vec::new();
        taps.drain(&mut items);
        if !last && items.is_empty() && last_sent.elapsed() < IDLE_BATCH {
            continue;
        }
        let losses = taps.losses();
        let (lines, left_out) = split(items, MAX_BATCH_BYTES);
        too_large += left_out;
        // The last line carries the time: the client knows all up to it has come.
        let end = lines.len() - 1;
        for (i, items) in lines.into_iter().enumerate() {
            let batch = RecordBatch {
                items,
                ports_lost: losses.ports_lost.clone(),
                steps_lost: losses.steps_lost.clone(),
                unserialisable: losses.unserialisable + too_large,
                now_ns: if i == end { now } else { 0 },
            };
            if !send(batch) {
                return;
            }
        }
        if last {
            return;
        }
        last_sent = Instant::now();
    }
}

/// Splits a drain into the items of its lines: each line's items take at most `limit`
/// bytes as JSON (separators included) and are at most [`MAX_BATCH_ITEMS`]; an item larger
/// than `limit` alone is left out (the count is returned). Always one line at least (it may
/// be empty: it carries the time). In O(n) and without serialising: an item is measured by
/// an upper bound of its JSON ([`json_bound`]), exactly only when that bound is over the
/// limit.
pub fn split(items: Vec<Item>, limit: usize) -> (Vec<Vec<Item>>, u64) {
    let mut lines: Vec<Vec<Item>> = vec![Vec::new()];
    let mut bytes = 0;
    let mut left_out = 0;
    for item in items {
        let mut size = json_bound(&item);
        if size > limit {
            let mut exact = Counter(0);
            size = match serde_json::to_writer(&mut exact, &item) {
                Ok(()) => exact.0,
                Err(_) => usize::MAX,
            };
        }
        // Its comma.
        let size = size.saturating_add(1);
        if size > limit {
            left_out += 1;
            continue;
        }
        let line = lines.last().map_or(0, Vec::len);
        if line > 0 && (bytes + size > limit || line >= MAX_BATCH_ITEMS) {
            lines.push(Vec::new());
            bytes = 0;
        }
        bytes += size;
        if let Some(line) = lines.last_mut() {
            line.push(item);
        }
    }
    (lines, left_out)
}

/// At least the length of `item`'s JSON, in bytes, without writing it: the fields around
/// a sample's value or a step's times, and for the value, every string byte as an escape
/// (`\u00XX`, 6 bytes) and every number at its longest.
pub fn json_bound(item: &Item) -> usize {
    // `{"kind":"sample","port":4294967295,"at_ns":18446744073709551615,"value":}` and
    // `{"kind":"step","activity":4294967295,"step":{"scheduled_ns":…,"started_ns":…,
    // "ended_ns":…}}` with every number at its longest, and room to spare.
    match item {
        Item::Sample { value, .. } => 128usize.saturating_add(value_bound(value)),
        Item::Step { .. } => 256,
    }
}

fn value_bound(v: &serde_json::Value) -> usize {
    use serde_json::Value;
    let text = |s: &str| s.len().saturating_mul(6).saturating_add(2);
    match v {
        Value::Null => 4,
        Value::Bool(_) => 5,
        // `-1.7976931348623157e308`, `18446744073709551615`.
        Value::Number(_) => 24,
        Value::String(s) => text(s),
        Value::Array(a) => a.iter().fold(2usize, |n, x| {
            n.saturating_add(value_bound(x)).saturating_add(1)
        }),
        Value::Object(o) => o.iter().fold(2usize, |n, (k, x)| {
            n.saturating_add(text(k))
                .saturating_add(value_bound(x))
                .saturating_add(2)
        }),
    }
}

/// Counts the bytes written into it.
struct Counter(usize);

impl std::io::Write for Counter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0 += buf.len();
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(
        clippy::unwrap_used,
        reason = "test code: a failed unwrap is a failed test"
    )]

    use super::*;
    use serde_json::json;

    fn sample(port: u32, len: usize) -> Item {
        Item::Sample {
            port,
            at_ns: 1,
            value: json!("x".repeat(len)),
        }
    }

    /// Each line's items stay within the limit and the lines hold every item in order,
    /// but one too large for any line, which is counted.
    #[test]
    fn a_drain_is_split_by_size_and_what_cannot_be_carried_is_counted() {
        let limit = 10_000;
        let mut items: Vec<Item> = (0..200).map(|k| sample(k, 97 * (k as usize % 7))).collect();
        items.insert(50, sample(999, limit));
        // Within the limit exactly, beyond its bound: measured, and carried alone.
        items.insert(120, sample(998, limit - 100));
        let (lines, left_out) = split(items.clone(), limit);
        assert_eq!(left_out, 1);
        assert!(lines.len() > 5, "{} lines", lines.len());
        for line in &lines {
            let json = serde_json::to_string(line).unwrap();
            assert!(json.len() <= limit + 2, "{} bytes", json.len());
            assert!(!line.is_empty());
        }
        items.remove(50);
        assert_eq!(lines.concat(), items);
        // Nothing drained: one empty line still carries the time.
        assert_eq!(split(Vec::new(), limit), (vec![Vec::new()], 0));
        // Many small items: at most MAX_BATCH_ITEMS a line.
        let (lines, _) = split((0..45_000).map(|k| sample(k, 0)).collect(), usize::MAX);
        let counts: Vec<usize> = lines.iter().map(Vec::len).collect();
        assert_eq!(counts, [MAX_BATCH_ITEMS, MAX_BATCH_ITEMS, 5_000]);
    }

    struct Writes5 {
        out: rtt::port::OutputPort<f64>,
        n: f64,
    }

    impl rtt::Component for Writes5 {
        fn update_hook(&mut self, _: &mut rtt::Context<'_>) -> rtt::HookResult {
            for _ in 0..5 {
                self.out.write(&self.n);
                self.n += 1.0;
            }
            Ok(())
        }
    }

    /// A stream the gateway ends (it is closing) still sends what came since the last
    /// batch and the losses up to then: the end of a recording counts all it lost.
    #[test]
    fn a_stream_the_gateway_ends_sends_its_last_batch() {
        let rt = rtt::Runtime::new(
            std::sync::Arc::new(device_interface::Registry::new()),
            rtt::RuntimeOptions::default(),
        )
        .unwrap();
        let t = rt
            .add(
                "w",
                rtt::ActivitySpec::Slave,
                rtt::InitialState::Stopped,
                |i| {
                    Ok(Writes5 {
                        out: i.output("out", "numbers")?,
                        n: 0.0,
                    })
                },
            )
            .unwrap();
        t.start().unwrap();
        let peer = |n: &str| rt.component(n).map_err(|e| e.to_string());
        let ports = resolve(&peer, &["w.out".to_string()]).unwrap();
        // A buffer of 3: a step's 5 samples are 3 kept and 2 dropped.
        let taps = Taps::open(&peer, ports, &[], 3).unwrap();
        t.step().unwrap();
        let mut sent = Vec::new();
        pump(
            taps,
            |b| {
                sent.push(b);
                true
            },
            || true,
        );
        assert_eq!(sent.len(), 1, "one last batch");
        assert_eq!(sent[0].items.len(), 3);
        assert_eq!(sent[0].ports_lost, [2]);
        assert!(sent[0].now_ns > 0, "it carries the time");
    }

    /// The bound is never below the JSON, whatever the value: escapes, the longest
    /// numbers, nesting, steps.
    #[test]
    fn the_size_bound_is_never_below_the_json() {
        let values = [
            json!(null),
            json!(true),
            json!(-1.797_693_134_862_315_7e308),
            json!(u64::MAX),
            json!(i64::MIN),
            json!(5e-324),
            json!("\u{1}\"\\\n\t\u{1f}"),
            json!("\u{0}".repeat(1000)),
            json!("é€𝄞 plain"),
            json!([1, [2.5, [null, "x"]], {"k\"ey": [true, {"": -0.0}]}]),
            json!({"id": 7, "data": [255, 0, 17], "flags": {"ext": false, "rtr": true}}),
        ];
        for value in values {
            let item = Item::Sample {
                port: u32::MAX,
                at_ns: u64::MAX,
                value,
            };
            let exact = serde_json::to_vec(&item).unwrap().len();
            assert!(json_bound(&item) >= exact, "{item:?}: {exact}");
        }
        let step = Item::Step {
            activity: u32::MAX,
            step: recording::Step {
                scheduled_ns: u64::MAX,
                started_ns: u64::MAX,
                ended_ns: u64::MAX,
            },
        };
        assert!(json_bound(&step) >= serde_json::to_vec(&step).unwrap().len());
    }
}
