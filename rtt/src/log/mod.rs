//! Logging from real-time code (road map L712–736): a log call on a real-time thread
//! allocates nothing, takes no lock and makes no system call.
//!
//! Code logs through an [`Area`] (one per component or card, made when it is built, by
//! name). [`Area::log`] checks the area's level (one atomic load), fills a fixed-size
//! record on the stack — the wall-clock time, the level, the area, a `&'static str`
//! message with a `{}` for each argument, and up to [`MAX_ARGS`] arguments kept by value
//! ([`Arg`]: numbers, flags, static text, or a short copy of a text) — and pushes it on a
//! bounded queue that never waits for another thread ([`crate::bounded`];
//! [`QUEUE_CAPACITY`] records). A full queue drops the record and counts it. The logger thread ([`spawn_writer`]) takes the records every
//! [`WRITE_EVERY`], formats them and writes them through `tracing` (target
//! [`TARGET`], with the area as field `component` and the push time as field `at`), so they
//! reach the journal or standard error as everything else the gateway logs, and reports the
//! records dropped since it last looked.
//!
//! Levels are per area and change while the program runs ([`set_level`]; `hwgw log
//! COMPONENT LEVEL`). An area starts at [`DEFAULT_LEVEL`].

mod record;

use record::Record;
pub use record::{Arg, MAX_ARGS, TEXT_BYTES};

use crate::bounded::Bounded;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// Records the queue holds; more are dropped and counted until the logger thread takes
/// them.
pub const QUEUE_CAPACITY: usize = 512;

/// How often the logger thread takes the queued records.
pub const WRITE_EVERY: Duration = Duration::from_millis(10);

/// The level an area starts at.
pub const DEFAULT_LEVEL: Level = Level::Info;

/// The `tracing` target the logger thread writes under.
pub const TARGET: &str = "hwgw_rt";

/// How grave a record is; an area writes the records at its level and graver.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Level {
    /// Nothing is written.
    Off = 0,
    /// Failures.
    Error = 1,
    /// Something is wrong but it goes on.
    Warn = 2,
    /// State changes worth knowing.
    Info = 3,
    /// Detail for finding a fault.
    Debug = 4,
    /// Everything.
    Trace = 5,
}

impl Level {
    /// Every level, least grave last.
    pub const ALL: [Level; 6] = [
        Level::Off,
        Level::Error,
        Level::Warn,
        Level::Info,
        Level::Debug,
        Level::Trace,
    ];

    fn from_u8(v: u8) -> Level {
        Level::ALL
            .get(usize::from(v))
            .copied()
            .unwrap_or(Level::Trace)
    }

    /// Its name (`warn`).
    pub fn name(self) -> &'static str {
        match self {
            Level::Off => "off",
            Level::Error => "error",
            Level::Warn => "warn",
            Level::Info => "info",
            Level::Debug => "debug",
            Level::Trace => "trace",
        }
    }
}

impl std::fmt::Display for Level {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Why a level or an area was not found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum LogError {
    /// Not a level's name.
    #[error("{given:?} is not a log level; the levels are off, error, warn, info, debug, trace")]
    UnknownLevel {
        /// What was given.
        given: String,
    },
    /// No area of that name logs in this process.
    #[error("nothing logs as {given:?}; what does: {}", known.join(", "))]
    UnknownArea {
        /// What was given.
        given: String,
        /// The areas there are.
        known: Vec<String>,
    },
}

impl std::str::FromStr for Level {
    type Err = LogError;
    fn from_str(s: &str) -> Result<Level, LogError> {
        Level::ALL
            .into_iter()
            .find(|l| {
                l.name().eq_ignore_ascii_case(s)
                    || (s.eq_ignore_ascii_case("warning") && *l == Level::Warn)
            })
            .ok_or_else(|| LogError::UnknownLevel {
                given: s.to_string(),
            })
    }
}

struct AreaCell {
    name: String,
    index: u32,
    level: AtomicU8,
}

/// Where records come from: a component or a card, by name. Cheap to clone; made (and
/// looked up) when its owner is built, not on the real-time path.
#[derive(Clone)]
pub struct Area(Arc<AreaCell>);

impl std::fmt::Debug for Area {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Area({:?}, {})", self.0.name, self.level())
    }
}

struct Logger {
    queue: Bounded<Record>,
    areas: Mutex<Vec<Arc<AreaCell>>>,
    dropped: AtomicU64,
    /// Drops already reported.
    reported: AtomicU64,
    written: AtomicU64,
    writer: Mutex<bool>,
}

fn logger() -> &'static Logger {
    static LOGGER: OnceLock<Logger> = OnceLock::new();
    LOGGER.get_or_init(|| Logger {
        queue: Bounded::new(QUEUE_CAPACITY),
        areas: Mutex::new(Vec::new()),
        dropped: AtomicU64::new(0),
        reported: AtomicU64::new(0),
        written: AtomicU64::new(0),
        writer: Mutex::new(false),
    })
}

impl Area {
    /// The area `name`, made at [`DEFAULT_LEVEL`] the first time it is asked for. Takes a
    /// lock and may allocate: call it when building, and keep the area. An area nothing
    /// holds any more (its component or card removed) is gone from [`levels`] and
    /// [`set_level`]; asked for again, it starts again at [`DEFAULT_LEVEL`]. (Its name is
    /// kept, for the records still queued under it: a name costs its bytes once, however
    /// often it comes and goes.)
    pub fn named(name: &str) -> Area {
        let mut areas = crate::lock::lock(&logger().areas);
        if let Some(a) = areas.iter().find(|a| a.name == name) {
            if !held(a) {
                a.level.store(DEFAULT_LEVEL as u8, Ordering::Relaxed);
            }
            return Area(a.clone());
        }
        let cell = Arc::new(AreaCell {
            name: name.to_string(),
            index: u32::try_from(areas.len()).unwrap_or(u32::MAX),
            level: AtomicU8::new(DEFAULT_LEVEL as u8),
        });
        areas.push(cell.clone());
        Area(cell)
    }

    /// Its name.
    pub fn name(&self) -> &str {
        &self.0.name
    }

    /// Its level now.
    pub fn level(&self) -> Level {
        Level::from_u8(self.0.level.load(Ordering::Relaxed))
    }

    /// Whether a record of `level` would be written.
    #[inline]
    pub fn enabled(&self, level: Level) -> bool {
        level != Level::Off && level as u8 <= self.0.level.load(Ordering::Relaxed)
    }

    /// Logs `message` with `args` in place of its `{}`s, if the area's level lets
    /// `level` through. Real-time safe: no allocation, no lock, no system call; when the
    /// queue is full the record is dropped and counted. Arguments beyond [`MAX_ARGS`] are
    /// left out (the text says how many).
    pub fn log(&self, level: Level, message: &'static str, args: &[Arg]) {
        if !self.enabled(level) {
            return;
        }
        let mut record = Record {
            at_ns: SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
                .unwrap_or(0),
            level,
            area: self.0.index,
            message,
            args: [None; MAX_ARGS],
            left_out: u8::try_from(args.len().saturating_sub(MAX_ARGS)).unwrap_or(u8::MAX),
        };
        for (slot, a) in record.args.iter_mut().zip(args) {
            *slot = Some(*a);
        }
        let l = logger();
        if l.queue.push(record).is_err() {
            l.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// Logs through an [`Area`] from real-time code, the arguments turned into [`Arg`]s
/// (numbers, flags and `&'static str` as they are; `Arg::text(s)` or `Arg::display(&e)`
/// for the others): `rt_log!(area, Warn, "unit {} failed {} times", unit, n)`. Nothing
/// is built when the area's level leaves the record out.
#[macro_export]
macro_rules! rt_log {
    ($area:expr, $level:ident, $message:literal $(, $arg:expr)* $(,)?) => {{
        let area: &$crate::log::Area = &$area;
        if area.enabled($crate::log::Level::$level) {
            area.log(
                $crate::log::Level::$level,
                $message,
                &[$($crate::log::Arg::from($arg)),*],
            );
        }
    }};
}

/// Sets area `name`'s level; its level before.
pub fn set_level(name: &str, level: Level) -> Result<Level, LogError> {
    let areas = crate::lock::lock(&logger().areas);
    match areas.iter().find(|a| a.name == name && held(a)) {
        Some(a) => Ok(Level::from_u8(a.level.swap(level as u8, Ordering::Relaxed))),
        None => Err(unknown(name, &areas)),
    }
}

/// Area `name`'s level.
pub fn level(name: &str) -> Result<Level, LogError> {
    let areas = crate::lock::lock(&logger().areas);
    match areas.iter().find(|a| a.name == name && held(a)) {
        Some(a) => Ok(Level::from_u8(a.level.load(Ordering::Relaxed))),
        None => Err(unknown(name, &areas)),
    }
}

/// True while something besides the logger's list holds the area.
fn held(a: &Arc<AreaCell>) -> bool {
    Arc::strong_count(a) > 1
}

fn unknown(name: &str, areas: &[Arc<AreaCell>]) -> LogError {
    let mut known: Vec<String> = areas
        .iter()
        .filter(|a| held(a))
        .map(|a| a.name.clone())
        .collect();
    known.sort();
    LogError::UnknownArea {
        given: name.to_string(),
        known,
    }
}

/// Every area and its level, by name.
pub fn levels() -> Vec<(String, Level)> {
    let mut all: Vec<(String, Level)> = crate::lock::lock(&logger().areas)
        .iter()
        .filter(|a| held(a))
        .map(|a| {
            (
                a.name.clone(),
                Level::from_u8(a.level.load(Ordering::Relaxed)),
            )
        })
        .collect();
    all.sort();
    all
}

/// The logger's counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LogStats {
    /// Records written so far.
    pub written: u64,
    /// Records dropped so far because the queue was full.
    pub dropped: u64,
    /// Records waiting in the queue.
    pub queued: u64,
}

/// The logger's counters now.
pub fn stats() -> LogStats {
    let l = logger();
    LogStats {
        written: l.written.load(Ordering::Relaxed),
        dropped: l.dropped.load(Ordering::Relaxed),
        queued: u64::try_from(l.queue.len()).unwrap_or(u64::MAX),
    }
}

/// A record as written.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    /// Its area's name.
    pub area: String,
    /// Its level.
    pub level: Level,
    /// When it was logged.
    pub at: SystemTime,
    /// The message with its arguments.
    pub text: String,
}

/// Takes every queued record, in order, and hands each to `sink` formatted (what the
/// logger thread does, with `tracing` as its sink).
pub fn drain(mut sink: impl FnMut(Entry)) {
    let l = logger();
    let all = || -> Vec<String> {
        crate::lock::lock(&l.areas)
            .iter()
            .map(|a| a.name.clone())
            .collect()
    };
    let mut names: Vec<String> = Vec::new();
    while let Some(r) = l.queue.pop() {
        let i = usize::try_from(r.area).unwrap_or(usize::MAX);
        if i >= names.len() {
            // An area made since the names were taken.
            names = all();
        }
        let area = names.get(i).cloned().unwrap_or_default();
        l.written.fetch_add(1, Ordering::Relaxed);
        sink(Entry {
            area,
            level: r.level,
            at: UNIX_EPOCH + Duration::from_nanos(r.at_ns),
            text: r.text(),
        });
    }
}

/// Writes `entry` through `tracing`.
fn write(entry: Entry) {
    let at = entry
        .at
        .duration_since(UNIX_EPOCH)
        .map(|d| format!("{}.{:06}", d.as_secs(), d.subsec_micros()))
        .unwrap_or_default();
    let (component, text) = (entry.area.as_str(), entry.text.as_str());
    match entry.level {
        Level::Error => tracing::error!(target: TARGET, component, at, "{text}"),
        Level::Warn => tracing::warn!(target: TARGET, component, at, "{text}"),
        Level::Info => tracing::info!(target: TARGET, component, at, "{text}"),
        Level::Debug => tracing::debug!(target: TARGET, component, at, "{text}"),
        Level::Trace | Level::Off => tracing::trace!(target: TARGET, component, at, "{text}"),
    }
}

/// Writes what is queued now through `tracing`, on this thread (at a stop, so that the
/// last records are out before the process ends), and reports drops since last time.
pub fn flush() {
    drain(write);
    let l = logger();
    let dropped = l.dropped.load(Ordering::Relaxed);
    let before = l.reported.swap(dropped, Ordering::Relaxed);
    if dropped > before {
        tracing::warn!(
            target: TARGET,
            "{} real-time log records dropped: the queue of {QUEUE_CAPACITY} was full",
            dropped - before
        );
    }
}

/// Starts the logger thread (`hwgw-log`, normal scheduling) once per process: it
/// [`flush`]es every [`WRITE_EVERY`]. Without it, records wait in the queue (and are
/// dropped once it is full) until someone flushes.
pub fn spawn_writer() -> std::io::Result<()> {
    let mut started = crate::lock::lock(&logger().writer);
    if *started {
        return Ok(());
    }
    std::thread::Builder::new()
        .name("hwgw-log".into())
        .spawn(|| {
            loop {
                flush();
                std::thread::sleep(WRITE_EVERY);
            }
        })?;
    *started = true;
    Ok(())
}
