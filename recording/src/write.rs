//! The MCAP file of a recording: created new (an existing name, a link included, is never
//! touched: see [`crate::file`]), one channel per port and per activity, chunks without
//! compression (any MCAP reader opens them with no codec installed), and at the end a
//! `hwgw.recording` metadata record with what was recorded, what was lost and why, and the
//! clock offset.
//!
//! A chunk is built in memory and written whole: when it holds [`CHUNK_BYTES`], and at a
//! [`Recorder::checkpoint`] once [`CHECKPOINT_NS`] have passed (a capture takes one at each
//! batch), so the file on the disk is whole chunks but for the one being written. When a
//! write fails — a full disk (`ENOSPC`), an I/O error — the file is cut back at once to the
//! end of its last complete chunk, and [`Recorder::finish`] completes it there (metadata,
//! data end, footer) when there is room for that, or leaves it cut there: what was written
//! before stays readable. The messages that did not reach the file are counted
//! (`unwritten`, part of `lost`).

use crate::item::PortSpec;
use crate::item::{
    Item, STEP_SCHEMA, SampleMessage, StepMessage, activity_topic, sample_schema,
    sample_schema_name, step_schema,
};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Cursor, Seek, SeekFrom, Write};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// Why a recording could not be made or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RecordError {
    /// The file could not be created (it exists, it is a link, its folder is missing, …).
    #[error("cannot create the recording: {0}")]
    File(#[from] crate::file::FileError),
    /// Writing failed (a full disk, an I/O error): the file is cut back to the end of its
    /// last complete chunk, which holds `kept` messages.
    #[error(
        "{file}: writing the recording failed: {}; the file is cut back to its last complete chunk ({kept} messages)",
        crate::file::describe(source)
    )]
    Write {
        /// The file (or what was written to).
        file: String,
        /// Messages in the file's complete chunks.
        kept: u64,
        /// Why.
        source: std::io::Error,
    },
    /// A write after a failed one.
    #[error("{file}: the recording stopped at an earlier write error")]
    Stopped {
        /// The file.
        file: String,
    },
    /// The MCAP writer refused something other than I/O.
    #[error("{file}: writing the recording: {source}")]
    Mcap {
        /// The file.
        file: String,
        /// Why.
        source: mcap::McapError,
    },
    /// More channels than MCAP's 65 535.
    #[error("{0} channels: an MCAP file holds at most 65 535")]
    TooManyChannels(usize),
    /// A message could not be serialised.
    #[error("serialising a message: {0}")]
    Json(#[from] serde_json::Error),
}

/// Where a recording is written: a stream that can be cut back to a length, dropping what
/// it holds past it (buffered bytes included), so that a failed write leaves no half chunk.
pub trait Sink: Write + Sized {
    /// Drops every byte from `len` on; the next write lands at `len`.
    fn cut(self, len: u64) -> std::io::Result<Self>;
}

impl Sink for File {
    fn cut(mut self, len: u64) -> std::io::Result<Self> {
        self.set_len(len)?;
        self.seek(SeekFrom::Start(len))?;
        Ok(self)
    }
}

impl<W: Sink> Sink for BufWriter<W> {
    fn cut(self, len: u64) -> std::io::Result<Self> {
        // What is still buffered is let go of, never written.
        let (inner, _) = self.into_parts();
        Ok(BufWriter::new(inner.cut(len)?))
    }
}

impl Sink for Cursor<Vec<u8>> {
    fn cut(mut self, len: u64) -> std::io::Result<Self> {
        self.get_mut().truncate(len as usize);
        self.set_position(len);
        Ok(self)
    }
}

impl Sink for &mut Cursor<Vec<u8>> {
    fn cut(self, len: u64) -> std::io::Result<Self> {
        self.get_mut().truncate(len as usize);
        self.set_position(len);
        Ok(self)
    }
}

/// A sink that counts what went into it, and answers the MCAP writer's only question of
/// position (it never seeks otherwise: chunks are built in memory).
struct Counted<W> {
    inner: W,
    /// Bytes written so far, read by the recorder while the writer owns this.
    at: Arc<AtomicU64>,
}

impl<W: Write> Write for Counted<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.at.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

impl<W> Seek for Counted<W> {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        match pos {
            SeekFrom::Current(0) => Ok(self.at.load(Ordering::Relaxed)),
            _ => Err(std::io::Error::new(
                std::io::ErrorKind::Unsupported,
                "a recording is written straight through",
            )),
        }
    }

    fn stream_position(&mut self) -> std::io::Result<u64> {
        Ok(self.at.load(Ordering::Relaxed))
    }
}

/// The most a chunk holds before it is written (it is built in memory).
pub const CHUNK_BYTES: u64 = 1 << 20;

/// How long a message waits at most in the chunk being built, ns, once
/// [`Recorder::checkpoint`] is called: what a crash or a full disk can take.
pub const CHECKPOINT_NS: u64 = 1_000_000_000;

/// How a recording is written.
#[derive(Debug, Clone)]
pub struct Options {
    /// UNIX time minus the runtime clock's time, ns, taken when the recording began: added
    /// to every item's time.
    pub wall_offset_ns: i128,
    /// The file stops growing here: items past it are counted (`over_limit`), not written.
    pub max_bytes: u64,
    /// Free-form facts kept in the metadata (the trigger, the command line, …).
    pub notes: BTreeMap<String, String>,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            wall_offset_ns: 0,
            max_bytes: DEFAULT_MAX_BYTES,
            notes: BTreeMap::new(),
        }
    }
}

/// The default size limit of a recording: 1 GiB.
pub const DEFAULT_MAX_BYTES: u64 = 1 << 30;

/// What is known only at the end: losses counted by the sources.
#[derive(Debug, Clone, Default)]
pub struct Closing {
    /// Samples each port's buffer dropped (index as the ports given at creation).
    pub ports_lost: Vec<u64>,
    /// Steps each activity's tap dropped.
    pub steps_lost: Vec<u64>,
    /// Samples whose value could not be serialised (lost too).
    pub unserialisable: u64,
    /// More facts for the metadata.
    pub notes: BTreeMap<String, String>,
}

struct Channel {
    id: u16,
    sequence: u32,
    written: u64,
}

/// A recording being written.
pub struct Recorder<W: Sink = BufWriter<File>> {
    /// `None` once a write failed.
    mcap: Option<mcap::Writer<Counted<W>>>,
    /// Bytes written to the output.
    at: Arc<AtomicU64>,
    /// After a failed write: the output cut back to the end of the last complete chunk
    /// (`None` when even that failed).
    cut: Option<W>,
    /// Why writing failed, for the metadata.
    failure: Option<String>,
    /// The file, for messages.
    file: String,
    ports: Vec<PortSpec>,
    activities: Vec<String>,
    port_channels: Vec<Channel>,
    step_channels: Vec<Channel>,
    options: Options,
    bytes: u64,
    /// Bytes in the chunk being built.
    chunk_bytes: u64,
    /// When the last chunk was written (runtime clock), once a checkpoint came.
    last_checkpoint_ns: Option<u64>,
    /// The end of the last complete chunk, and the messages up to it.
    good: (u64, u64),
    /// Messages taken that are not in the file (a failed write).
    unwritten: u64,
    over_limit: u64,
    unknown: u64,
    scratch: Vec<u8>,
}

impl Recorder {
    /// Creates `path` new (see [`crate::file::create_new`]: never an existing name) for
    /// `ports` and `activities`. A file that could not be started is removed again.
    pub fn create(
        path: &Path,
        ports: Vec<PortSpec>,
        activities: Vec<String>,
        options: Options,
    ) -> Result<Recorder, RecordError> {
        let file = crate::file::create_new(path)?;
        let name = path.display().to_string();
        Recorder::start(BufWriter::new(file), name, ports, activities, options).inspect_err(|_| {
            // Made new above, and holding no recording: not left to block the next.
            let _ = std::fs::remove_file(path);
        })
    }
}

/// Bytes a message adds to the file besides its data: the record's opcode, length and
/// header, and its message index entry.
const MESSAGE_OVERHEAD: u64 = 1 + 8 + 22 + 16;

impl<W: Sink> Recorder<W> {
    /// A recording into `out`.
    pub fn new(
        out: W,
        ports: Vec<PortSpec>,
        activities: Vec<String>,
        options: Options,
    ) -> Result<Recorder<W>, RecordError> {
        Recorder::start(out, "the recording".into(), ports, activities, options)
    }

    fn start(
        out: W,
        file: String,
        ports: Vec<PortSpec>,
        activities: Vec<String>,
        options: Options,
    ) -> Result<Recorder<W>, RecordError> {
        let channels = ports.len() + activities.len();
        if channels > usize::from(u16::MAX) {
            return Err(RecordError::TooManyChannels(channels));
        }
        let fail = |e| match e {
            mcap::McapError::Io(source) => RecordError::Write {
                file: file.clone(),
                kept: 0,
                source,
            },
            source => RecordError::Mcap {
                file: file.clone(),
                source,
            },
        };
        let at = Arc::new(AtomicU64::new(0));
        // Chunks are built in memory and written whole when this recorder says so
        // (`flush`): the file is whole chunks but for the one being written.
        let mut mcap = mcap::WriteOptions::new()
            .compression(None)
            .profile("")
            .library(concat!("hwgw-recording ", env!("CARGO_PKG_VERSION")))
            .disable_seeking(true)
            .chunk_size(None)
            .create(Counted {
                inner: out,
                at: at.clone(),
            })
            .map_err(fail)?;
        let mut schemas: BTreeMap<String, u16> = BTreeMap::new();
        let mut port_channels = Vec::with_capacity(ports.len());
        for p in &ports {
            let name = sample_schema_name(&p.type_name);
            let schema = match schemas.get(&name) {
                Some(id) => *id,
                None => {
                    let data = serde_json::to_vec(&sample_schema(&p.type_name))?;
                    let id = mcap.add_schema(&name, "jsonschema", &data).map_err(fail)?;
                    schemas.insert(name, id);
                    id
                }
            };
            let meta = BTreeMap::from([
                ("port".to_string(), p.name.clone()),
                ("type".to_string(), p.type_name.clone()),
            ]);
            let id = mcap
                .add_channel(schema, &p.topic(), "json", &meta)
                .map_err(fail)?;
            port_channels.push(Channel::new(id));
        }
        let mut step_channels = Vec::with_capacity(activities.len());
        if !activities.is_empty() {
            let data = serde_json::to_vec(&step_schema())?;
            let schema = mcap
                .add_schema(STEP_SCHEMA, "jsonschema", &data)
                .map_err(fail)?;
            for a in &activities {
                let meta = BTreeMap::from([("activity".to_string(), a.clone())]);
                let id = mcap
                    .add_channel(schema, &activity_topic(a), "json", &meta)
                    .map_err(fail)?;
                step_channels.push(Channel::new(id));
            }
        }
        // The schemas and channels in a chunk of their own: on the disk from the start.
        mcap.flush().map_err(fail)?;
        let good = (at.load(Ordering::Relaxed), 0);
        Ok(Recorder {
            mcap: Some(mcap),
            at,
            cut: None,
            failure: None,
            file,
            ports,
            activities,
            port_channels,
            step_channels,
            options,
            bytes: 0,
            chunk_bytes: 0,
            last_checkpoint_ns: None,
            good,
            unwritten: 0,
            over_limit: 0,
            unknown: 0,
            scratch: Vec::with_capacity(256),
        })
    }

    /// Writes one item; `now_ns` (runtime clock) is when the recorder took it, kept as the
    /// message's publish time. An item of an unknown port or activity is counted. After a
    /// failed write, every item is counted as unwritten and refused
    /// ([`RecordError::Stopped`]).
    pub fn write(&mut self, item: &Item, now_ns: u64) -> Result<(), RecordError> {
        if self.mcap.is_none() {
            self.unwritten += 1;
            return Err(RecordError::Stopped {
                file: self.file.clone(),
            });
        }
        self.scratch.clear();
        let (channel, time) = match item {
            Item::Sample { port, at_ns, value } => {
                serde_json::to_writer(&mut self.scratch, &SampleMessage { value })?;
                (self.port_channels.get_mut(*port as usize), *at_ns)
            }
            Item::Step { activity, step } => {
                serde_json::to_writer(&mut self.scratch, &StepMessage::from(step))?;
                (
                    self.step_channels.get_mut(*activity as usize),
                    step.started_ns,
                )
            }
        };
        let Some(channel) = channel else {
            self.unknown += 1;
            return Ok(());
        };
        let size = self.scratch.len() as u64 + MESSAGE_OVERHEAD;
        if self.bytes.saturating_add(size) > self.options.max_bytes {
            self.over_limit += 1;
            return Ok(());
        }
        let header = mcap::records::MessageHeader {
            channel_id: channel.id,
            sequence: channel.sequence,
            log_time: wall(self.options.wall_offset_ns, time),
            publish_time: wall(self.options.wall_offset_ns, now_ns),
        };
        let Some(mcap) = &mut self.mcap else {
            // Not reached: a failed recorder refuses at the top.
            self.unwritten += 1;
            return Err(RecordError::Stopped {
                file: self.file.clone(),
            });
        };
        let written = mcap.write_to_known_channel(&header, &self.scratch);
        if let Err(e) = written {
            // The message that failed is not in the file either.
            self.unwritten += 1;
            return Err(self.fail(e));
        }
        channel.sequence = channel.sequence.wrapping_add(1);
        channel.written += 1;
        self.bytes += size;
        self.chunk_bytes += size;
        if self.chunk_bytes >= CHUNK_BYTES {
            self.write_chunk(now_ns)?;
        }
        Ok(())
    }

    /// Writes the chunk being built if it holds anything and [`CHECKPOINT_NS`] have passed
    /// since the last one (the first call only starts the count): at most that much is
    /// lost to a crash or a full disk. `now_ns` is on the items' clock.
    pub fn checkpoint(&mut self, now_ns: u64) -> Result<(), RecordError> {
        let Some(last) = self.last_checkpoint_ns else {
            self.last_checkpoint_ns = Some(now_ns);
            return Ok(());
        };
        if self.chunk_bytes > 0 && now_ns.saturating_sub(last) >= CHECKPOINT_NS {
            self.write_chunk(now_ns)?;
        }
        Ok(())
    }

    /// Writes the chunk being built, and flushes it to the file.
    fn write_chunk(&mut self, now_ns: u64) -> Result<(), RecordError> {
        let Some(mcap) = &mut self.mcap else {
            return Err(RecordError::Stopped {
                file: self.file.clone(),
            });
        };
        if let Err(e) = mcap.flush() {
            return Err(self.fail(e));
        }
        self.good = (self.at.load(Ordering::Relaxed), self.taken());
        self.chunk_bytes = 0;
        self.last_checkpoint_ns = Some(now_ns);
        Ok(())
    }

    /// Messages taken into the file, its chunk being built included.
    fn taken(&self) -> u64 {
        self.port_channels
            .iter()
            .chain(&self.step_channels)
            .map(|c| c.written)
            .sum()
    }

    /// A write failed: the output is cut back to the end of the last complete chunk now,
    /// what was taken since counted as unwritten; the error to give.
    fn fail(&mut self, e: mcap::McapError) -> RecordError {
        let out = self.mcap.take().map(|m| m.into_inner().inner);
        let error = match e {
            mcap::McapError::Io(source) => RecordError::Write {
                file: self.file.clone(),
                kept: self.good.1,
                source,
            },
            source => RecordError::Mcap {
                file: self.file.clone(),
                source,
            },
        };
        self.cut_back(out, &error);
        error
    }

    /// Cuts `out` back to the end of the last complete chunk after `error`.
    fn cut_back(&mut self, out: Option<W>, error: &RecordError) {
        let (good, kept) = self.good;
        self.unwritten += self.taken().saturating_sub(kept);
        let mut cut_failed = None;
        self.cut = out.and_then(|out| {
            out.cut(good)
                .map_err(|c| cut_failed = Some(crate::file::describe(&c)))
                .ok()
        });
        self.failure = Some(match cut_failed {
            Some(c) => format!("{error} (cutting it back failed: {c})"),
            None => error.to_string(),
        });
    }

    /// UNIX time minus the items' clock, ns, as given in the options.
    pub fn wall_offset_ns(&self) -> i128 {
        self.options.wall_offset_ns
    }

    /// Messages written so far (after a failed write: those the file kept).
    pub fn written(&self) -> u64 {
        if self.mcap.is_some() {
            self.taken()
        } else {
            self.good.1
        }
    }

    /// True once a write failed (the file is cut back to its last complete chunk).
    pub fn failed(&self) -> bool {
        self.mcap.is_none()
    }

    /// Writes the metadata and the summary, and flushes: the file is complete. When a
    /// write fails (now or before), the file — cut back to its last complete chunk — is
    /// completed there with the metadata, or with no metadata when that does not fit, and
    /// the metadata returned says why it ended (`error`) and what did not reach the file
    /// (`unwritten`). An error only when not even that could be written: the file then
    /// ends at its last complete chunk (readable up to there, without a footer).
    pub fn finish(mut self, closing: &Closing) -> Result<BTreeMap<String, String>, RecordError> {
        if self.mcap.is_some() {
            // The last chunk first: a failure there is a failed write like any other.
            let _ = self.write_chunk(self.last_checkpoint_ns.unwrap_or(0));
        }
        if self.mcap.is_some() {
            let meta = self.metadata(closing);
            let done = match &mut self.mcap {
                Some(mcap) => mcap
                    .write_metadata(&meta)
                    .and_then(|()| mcap.finish().map(drop)),
                None => Ok(()),
            };
            match done {
                Err(e) => {
                    self.fail(e);
                }
                Ok(()) => {
                    let mut out = self.mcap.take().map(|m| m.into_inner().inner);
                    match out.as_mut().map(Write::flush) {
                        Some(Err(source)) => {
                            let error = RecordError::Write {
                                file: self.file.clone(),
                                kept: self.good.1,
                                source,
                            };
                            self.cut_back(out, &error);
                        }
                        _ => return Ok(meta.metadata),
                    }
                }
            }
        }
        let meta = self.metadata(closing);
        self.complete_cut(&meta)?;
        Ok(meta.metadata)
    }

    /// The `hwgw.recording` metadata record.
    fn metadata(&self, closing: &Closing) -> mcap::records::Metadata {
        let mut meta = self.options.notes.clone();
        meta.insert(
            "wall_minus_clock_ns".into(),
            self.options.wall_offset_ns.to_string(),
        );
        meta.insert("messages".into(), self.written().to_string());
        meta.insert("over_limit".into(), self.over_limit.to_string());
        meta.insert("max_bytes".into(), self.options.max_bytes.to_string());
        meta.insert("unknown".into(), self.unknown.to_string());
        let mut lost = 0;
        for (i, p) in self.ports.iter().enumerate() {
            let n = closing.ports_lost.get(i).copied().unwrap_or(0);
            lost += n;
            meta.insert(format!("lost.{}", p.name), n.to_string());
        }
        for (i, a) in self.activities.iter().enumerate() {
            let n = closing.steps_lost.get(i).copied().unwrap_or(0);
            lost += n;
            meta.insert(format!("lost_steps.{a}"), n.to_string());
        }
        lost += closing.unserialisable;
        meta.insert("unserialisable".into(), closing.unserialisable.to_string());
        lost += self.unwritten;
        meta.insert("unwritten".into(), self.unwritten.to_string());
        if let Some(why) = &self.failure {
            meta.insert("error".into(), why.clone());
        }
        meta.extend(closing.notes.clone());
        meta.insert("lost".into(), lost.to_string());
        mcap::records::Metadata {
            name: METADATA.into(),
            metadata: meta,
        }
    }

    /// Completes a file cut back after a failed write: the metadata, the data end and a
    /// footer without a summary (MCAP's summary is optional); without the metadata when
    /// that does not fit; cut back again when not even the end fits.
    fn complete_cut(&mut self, metadata: &mcap::records::Metadata) -> Result<(), RecordError> {
        let (good, kept) = self.good;
        let file = self.file.clone();
        let error = |source| RecordError::Write {
            file: file.clone(),
            kept,
            source,
        };
        let Some(mut out) = self.cut.take() else {
            return Err(error(std::io::Error::other(
                "the file could not be cut back to its last complete chunk",
            )));
        };
        let mut first = None;
        for with_metadata in [true, false] {
            let mut end = Vec::new();
            if with_metadata {
                metadata_record(&mut end, metadata);
            }
            ending(&mut end);
            match out.write_all(&end).and_then(|()| out.flush()) {
                Ok(()) => return Ok(()),
                Err(e) => {
                    first.get_or_insert(e);
                    out = out.cut(good).map_err(error)?;
                }
            }
        }
        Err(error(
            first.unwrap_or_else(|| std::io::Error::other("no room")),
        ))
    }
}

/// An MCAP metadata record: opcode, length, the name and the map (both length-prefixed,
/// as the MCAP specification lays them out).
fn metadata_record(out: &mut Vec<u8>, m: &mcap::records::Metadata) {
    fn string(out: &mut Vec<u8>, s: &str) {
        out.extend_from_slice(&(s.len() as u32).to_le_bytes());
        out.extend_from_slice(s.as_bytes());
    }
    let mut map = Vec::new();
    for (k, v) in &m.metadata {
        string(&mut map, k);
        string(&mut map, v);
    }
    let mut body = Vec::new();
    string(&mut body, &m.name);
    body.extend_from_slice(&(map.len() as u32).to_le_bytes());
    body.extend_from_slice(&map);
    out.push(mcap::records::op::METADATA);
    out.extend_from_slice(&(body.len() as u64).to_le_bytes());
    out.extend_from_slice(&body);
}

/// The end of an MCAP file without a summary: the data end (no CRC), a footer that points
/// at no summary, and the closing magic.
fn ending(out: &mut Vec<u8>) {
    out.push(mcap::records::op::DATA_END);
    out.extend_from_slice(&4u64.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out.push(mcap::records::op::FOOTER);
    out.extend_from_slice(&20u64.to_le_bytes());
    out.extend_from_slice(&[0; 20]);
    out.extend_from_slice(mcap::MAGIC);
}

/// A runtime clock time as UNIX ns.
fn wall(offset: i128, ns: u64) -> u64 {
    u64::try_from((i128::from(ns) + offset).max(0)).unwrap_or(u64::MAX)
}

/// The name of the metadata record hwgw writes.
pub const METADATA: &str = "hwgw.recording";

impl Channel {
    fn new(id: u16) -> Self {
        Channel {
            id,
            sequence: 0,
            written: 0,
        }
    }
}
