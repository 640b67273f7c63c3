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
/// client went away) or `stop` says so.
pub fn pump(mut taps: Taps, mut send: impl FnMut(RecordBatch) -> bool, stop: impl Fn() -> bool) {
    let mut last_sent = Instant::now();
    while !stop() {
        std::thread::sleep(BATCH_EVERY);
        let now = now_ns();
        let mut items = Vec::new();
        taps.drain(&mut items);
        if items.is_empty() && last_sent.elapsed() < IDLE_BATCH {
            continue;
        }
        let losses = taps.losses();
        // The last chunk carries the time: the client knows all up to it has come.
        let mut all = items.into_iter();
        let mut chunks: Vec<Vec<Item>> = Vec::new();
        loop {
            let chunk: Vec<Item> = all.by_ref().take(MAX_BATCH_ITEMS).collect();
            if chunk.is_empty() && !chunks.is_empty() {
                break;
            }
            chunks.push(chunk);
        }
        let last = chunks.len() - 1;
        for (i, items) in chunks.into_iter().enumerate() {
            let batch = RecordBatch {
                items,
                ports_lost: losses.ports_lost.clone(),
                steps_lost: losses.steps_lost.clone(),
                unserialisable: losses.unserialisable,
                now_ns: if i == last { now } else { 0 },
            };
            if !send(batch) {
                return;
            }
        }
        last_sent = Instant::now();
    }
}
