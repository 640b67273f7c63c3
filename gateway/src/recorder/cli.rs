//! `hwgw record`, `hwgw plot` and `hwgw status --plot`: the command-line ends of recording
//! and pictures.

use crate::client::{Client, ClientError};
use crate::protocol::{Body, Description, RecordStart, Request, StatusReport};
use recording::{Capture, Closing, Options, Recorder, Trigger, Window};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The longest duration a command takes: a day.
const MAX_DURATION: Duration = Duration::from_secs(86_400);

/// A duration as people write it: a number and `ns`, `us`, `ms`, `s` or `min`, e.g.
/// `200ms`, `1.5s`; at most a day.
pub fn parse_duration(text: &str) -> Result<Duration, String> {
    let t = text.trim();
    let split = t
        .find(|c: char| c.is_ascii_alphabetic())
        .ok_or_else(|| format!("{text:?}: expected a number and a unit (ns, us, ms, s, min)"))?;
    let (num, unit) = t.split_at(split);
    let n: f64 = num
        .trim()
        .parse()
        .map_err(|_| format!("{text:?}: {num:?} is not a number"))?;
    let scale = match unit {
        "ns" => 1e-9,
        "us" | "µs" => 1e-6,
        "ms" => 1e-3,
        "s" => 1.0,
        "min" => 60.0,
        _ => {
            return Err(format!(
                "{text:?}: unit {unit:?}: expected ns, us, ms, s or min"
            ));
        }
    };
    let secs = n * scale;
    if !(secs.is_finite() && secs >= 0.0) || secs > MAX_DURATION.as_secs_f64() {
        return Err(format!("{text:?}: expected 0 to a day"));
    }
    Ok(Duration::from_secs_f64(secs))
}

/// What `hwgw record` was asked.
#[derive(Debug, Clone, clap::Args)]
pub struct RecordArgs {
    /// The new MCAP file (an existing file is never overwritten).
    pub file: PathBuf,
    /// An output port (`component.port`), or every output of a component
    /// (`component`); repeat for more.
    #[arg(long = "port", value_name = "PORT")]
    pub ports: Vec<String>,
    /// Every device's channels.
    #[arg(long)]
    pub devices: bool,
    /// Leave the activities' steps (start, end, lateness) out.
    #[arg(long)]
    pub no_steps: bool,
    /// How long to record (e.g. 10s), or with --trigger how long to wait for it.
    #[arg(long, value_parser = parse_duration)]
    pub duration: Option<Duration>,
    /// Record only the window around `component.port OP number` becoming true
    /// (OP: > >= < <= == !=).
    #[arg(long, allow_hyphen_values = true)]
    pub trigger: Option<String>,
    /// With --trigger: kept before it.
    #[arg(long, default_value = "200ms", value_parser = parse_duration)]
    pub pre: Duration,
    /// With --trigger: recorded after it.
    #[arg(long, default_value = "1s", value_parser = parse_duration)]
    pub post: Duration,
    /// Samples each port may hold between two batches (more are counted as lost).
    #[arg(long, default_value_t = 4096)]
    pub buffer: usize,
    /// The file stops growing at this size, MiB.
    #[arg(long, default_value_t = 1024)]
    pub max_mb: u64,
}

/// Why `hwgw record` stopped or failed.
#[derive(Debug, thiserror::Error)]
pub enum RecordCliError {
    /// The gateway refused or could not be reached.
    #[error(transparent)]
    Client(#[from] ClientError),
    /// The file could not be made or written.
    #[error(transparent)]
    Record(#[from] recording::RecordError),
    /// A bad argument.
    #[error("{0}")]
    Usage(String),
    /// The recording ended at an error (a full disk, say); the file was completed with
    /// what it held.
    #[error("{error}; the file is complete: {messages} messages, {lost} lost")]
    Ended {
        /// Why it ended.
        error: Box<RecordCliError>,
        /// Messages it holds.
        messages: String,
        /// What was lost, what did not reach the file included.
        lost: String,
    },
}

/// Records from the gateway behind `client` into a new file: until `duration`, the
/// trigger's window, SIGINT/SIGTERM, or the gateway's end. What it wrote, for people.
pub fn record(client: &Client, args: RecordArgs) -> Result<String, RecordCliError> {
    use nix::sys::signal::{SigSet, Signal};
    use nix::sys::signalfd::{SfdFlags, SignalFd};
    let usage = RecordCliError::Usage;
    let trigger: Option<Trigger> = match &args.trigger {
        Some(t) => Some(t.parse().map_err(|e| usage(format!("{e}")))?),
        None => None,
    };
    if !(1..=1 << 20).contains(&args.max_mb) {
        return Err(usage(format!(
            "--max-mb {}: expected 1 to 1048576",
            args.max_mb
        )));
    }
    crate::checks::new_file(&args.file).map_err(usage)?;
    let mut ports = args.ports.clone();
    if let Some(t) = &trigger
        && !ports.contains(&t.port)
    {
        ports.push(t.port.clone());
    }
    let mut signals = SigSet::empty();
    signals.add(Signal::SIGINT);
    signals.add(Signal::SIGTERM);
    signals
        .thread_block()
        .map_err(|e| usage(format!("cannot block SIGINT/SIGTERM: {e}")))?;
    let sigfd = SignalFd::with_flags(&signals, SfdFlags::SFD_NONBLOCK | SfdFlags::SFD_CLOEXEC)
        .map_err(|e| usage(format!("signalfd: {e}")))?;
    let (mut stream, mut capture, start) = open(client, &args, ports, trigger)?;
    let mut losses = Closing::default();
    let ended = pump(
        &mut stream,
        &mut capture,
        &args,
        (&sigfd, start.now_ns),
        &mut losses,
    );
    let file = args.file.display().to_string();
    let get = |meta: &BTreeMap<String, String>, k: &str| {
        meta.get(k).map_or("?", String::as_str).to_string()
    };
    let ended = match ended {
        Ok(ended) => ended,
        Err(e) => {
            // What was recorded stays readable: the file is completed first.
            losses.notes.insert("ended".into(), format!("error: {e}"));
            return Err(match capture.finish(losses) {
                Ok(meta) => RecordCliError::Ended {
                    error: Box::new(e),
                    messages: get(&meta, "messages"),
                    lost: get(&meta, "lost"),
                },
                Err(f) => RecordCliError::Usage(format!("{e}; completing {file} failed too: {f}")),
            });
        }
    };
    losses.notes.insert("ended".into(), ended.into());
    let meta = capture.finish(losses)?;
    if let Some(error) = meta.get("error") {
        // Writing its last part failed: the file was completed before it.
        return Err(RecordCliError::Ended {
            error: Box::new(RecordCliError::Usage(error.clone())),
            messages: get(&meta, "messages"),
            lost: get(&meta, "lost"),
        });
    }
    Ok(format!(
        "{file}: {} messages ({} ports, {} activities), {} lost, {} over the size limit; ended: {ended}",
        get(&meta, "messages"),
        start.ports.len(),
        start.activities.len(),
        get(&meta, "lost"),
        get(&meta, "over_limit"),
    ))
}

/// Asks for the stream and creates the file: the stream, the capture and what is recorded.
fn open(
    client: &Client,
    args: &RecordArgs,
    ports: Vec<String>,
    trigger: Option<Trigger>,
) -> Result<(crate::client::Stream, Capture, RecordStart), RecordCliError> {
    let usage = RecordCliError::Usage;
    let req = Request::Record {
        ports,
        devices: args.devices,
        steps: !args.no_steps,
        buffer: Some(args.buffer),
    };
    let (ack, stream) = client.stream(&req)?;
    let start: RecordStart = serde_json::from_value(ack)
        .map_err(|e| usage(format!("unexpected acknowledgement: {e}")))?;
    let window = match trigger {
        Some(t) => {
            let index = start
                .ports
                .iter()
                .position(|p| p.name == t.port)
                .ok_or_else(|| usage(format!("the trigger port {:?} is not recorded", t.port)))?;
            let (pre, post) = (args.pre.as_nanos() as u64, args.post.as_nanos() as u64);
            Some(Window::new(
                t,
                index as u32,
                pre,
                post,
                recording::trigger::MAX_RING,
            ))
        }
        None => None,
    };
    let notes = BTreeMap::from([
        (
            "command".to_string(),
            std::env::args().collect::<Vec<_>>().join(" "),
        ),
        (
            "trigger".to_string(),
            args.trigger.clone().unwrap_or_default(),
        ),
        ("pre_ns".to_string(), args.pre.as_nanos().to_string()),
        ("post_ns".to_string(), args.post.as_nanos().to_string()),
    ]);
    let options = Options {
        wall_offset_ns: start.wall_minus_clock_ns,
        max_bytes: args.max_mb << 20,
        notes,
    };
    let recorder = Recorder::create(
        &args.file,
        start.ports.clone(),
        start.activities.clone(),
        options,
    )?;
    let capture = Capture::new(recorder, window);
    Ok((stream, capture, start))
}

/// Writes the stream's batches until the recording is over: why it ended, or the
/// stream's error. `losses` follows the gateway's counts; untriggered, the items of a
/// drain whose last line never came (the recording ended between its lines: a signal, a
/// silent gateway, an error) that fall within the recording's span are counted as lost
/// too. (Triggered, whether they fell within the window is not known: not counted.)
fn pump(
    stream: &mut crate::client::Stream,
    capture: &mut Capture,
    args: &RecordArgs,
    sigfd_t0: (&nix::sys::signalfd::SignalFd, u64),
    losses: &mut Closing,
) -> Result<&'static str, RecordCliError> {
    // A drain split in several lines is offered whole, once its last line came.
    let mut items = Vec::new();
    let ended = take_batches(stream, capture, args, sigfd_t0, losses, &mut items);
    if args.trigger.is_none() {
        if let Some(d) = args.duration {
            let t0 = sigfd_t0.1;
            let end = t0.saturating_add(d.as_nanos() as u64);
            items.retain(|i| (t0..=end).contains(&i.time_ns()));
        }
        count_lost(&items, losses);
    }
    ended
}

/// Items taken from the stream but never offered: each counted as lost to its port or
/// activity.
fn count_lost(items: &[recording::Item], losses: &mut Closing) {
    for item in items {
        let (counts, i) = match item {
            recording::Item::Sample { port, .. } => (&mut losses.ports_lost, *port),
            recording::Item::Step { activity, .. } => (&mut losses.steps_lost, *activity),
        };
        let i = i as usize;
        if counts.len() <= i {
            counts.resize(i + 1, 0);
        }
        counts[i] += 1;
    }
}

fn take_batches(
    stream: &mut crate::client::Stream,
    capture: &mut Capture,
    args: &RecordArgs,
    (sigfd, t0): (&nix::sys::signalfd::SignalFd, u64),
    losses: &mut Closing,
    items: &mut Vec<recording::Item>,
) -> Result<&'static str, RecordCliError> {
    let triggered = args.trigger.is_some();
    let began = Instant::now();
    // Untriggered, the recording spans exactly [t0, t0 + duration] on the gateway's clock.
    let end = args
        .duration
        .map(|d| t0.saturating_add(d.as_nanos() as u64));
    let mut now = t0;
    // When the gateway was last heard from, or this side last finished writing: silence
    // is time spent waiting for the gateway, never time spent writing what it sent.
    let mut last_batch = Instant::now();
    let silence = stream.patience();
    loop {
        if matches!(sigfd.read_signal(), Ok(Some(_))) {
            return Ok("stopped by a signal");
        }
        // A gateway that sends nothing at all any more (it sends at least once a second):
        // stuck or frozen, after --timeout.
        if last_batch.elapsed() > silence && began.elapsed() > silence {
            return Err(stream.silent_for(silence).into());
        }
        let b = match stream.next(Some(Duration::from_millis(200))) {
            Ok(Some(Body::Records(b))) => b,
            Ok(Some(_)) => {
                last_batch = Instant::now();
                continue;
            }
            Err(ClientError::Timeout { .. }) => continue,
            Ok(None) => return Ok("the gateway ended the stream"),
            Err(e) => return Err(e.into()),
        };
        last_batch = Instant::now();
        items.extend(b.items);
        if b.now_ns == 0 {
            continue;
        }
        now = now.max(b.now_ns);
        losses.ports_lost = b.ports_lost;
        losses.steps_lost = b.steps_lost;
        losses.unserialisable = b.unserialisable;
        let mut whole = std::mem::take(items);
        if !triggered && let Some(end) = end {
            whole.retain(|i| (t0..=end).contains(&i.time_ns()));
        }
        capture.offer(whole, now)?;
        last_batch = Instant::now();
        if capture.done() {
            return Ok("the trigger window is complete");
        }
        // Past the end by a guard, every sample stamped before the end has come (a sample
        // takes its step's start, and is written during the step).
        if end.is_some_and(|end| now >= end.saturating_add(END_GUARD_NS)) && !capture.triggered() {
            return Ok(if triggered { NEVER } else { "duration" });
        }
    }
}

const NEVER: &str = "the trigger never came";

/// How long past the end of `--duration` the stream is read on: samples of a step that
/// began before the end and took longer than this to write them are left out.
const END_GUARD_NS: u64 = 500_000_000;

/// What `hwgw plot` draws.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PlotKind {
    /// Port values over time.
    Values,
    /// Each activity's steps (the ThreadScope view).
    Timing,
    /// Each activity's wake-up lateness histogram.
    Lateness,
}

/// `hwgw plot`.
pub fn plot(
    recording: &Path,
    kind: PlotKind,
    ports: &[String],
    span: plot::Span,
    frame: &plot::Frame<'_>,
) -> Result<String, String> {
    let rec = recording::read::Recording::read(recording).map_err(|e| e.to_string())?;
    match kind {
        PlotKind::Values => plot::values(&rec, ports, span, frame),
        PlotKind::Timing => plot::timing(&rec, span, frame),
        PlotKind::Lateness => plot::lateness(&rec, frame),
    }
    .map_err(|e| e.to_string())?;
    let cut = match &rec.truncated {
        Some(_) => format!(" ({}; drawn up to there)", rec.condition()),
        None => String::new(),
    };
    Ok(format!(
        "{}: {kind:?} of {}{cut}",
        frame.path.display(),
        recording.display()
    ))
}

/// `hwgw status --plot FILE`: every running activity's live lateness histogram.
pub fn status_plot(client: &Client, frame: &plot::Frame<'_>) -> Result<String, String> {
    let s: StatusReport = client.typed(&Request::Status).map_err(|e| e.to_string())?;
    let mut live = Vec::new();
    for c in &s.components {
        let d: Description = client
            .typed(&Request::Describe {
                component: c.name.clone(),
            })
            .map_err(|e| e.to_string())?;
        let ns = |q: f64| d.activity.lateness_quantile(q).as_nanos() as u64;
        let (p50_ns, p99_ns) = (ns(0.5), ns(0.99));
        live.push(plot::LiveHistogram {
            name: c.name.clone(),
            buckets: d.activity.lateness_histogram,
            max_ns: d.activity.lateness_max_ns,
            p50_ns,
            p99_ns,
        });
    }
    plot::live_lateness(&live, frame).map_err(|e| e.to_string())?;
    Ok(format!(
        "{}: lateness of {} activities",
        frame.path.display(),
        live.len()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// What came of a drain whose last line never came is lost to its ports and
    /// activities, counted beside what the gateway counted.
    #[test]
    fn items_never_offered_are_counted_as_lost() {
        let mut losses = Closing {
            ports_lost: vec![4],
            ..Closing::default()
        };
        let sample = |port| recording::Item::Sample {
            port,
            at_ns: 1,
            value: json!(1.0),
        };
        let step = recording::Item::Step {
            activity: 1,
            step: recording::Step::default(),
        };
        count_lost(&[sample(0), sample(2), sample(2), step], &mut losses);
        assert_eq!(losses.ports_lost, [5, 0, 2]);
        assert_eq!(losses.steps_lost, [0, 1]);
    }
}
