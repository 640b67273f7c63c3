//! The MCAP file of a recording: created new (an existing file is never touched), one
//! channel per port and per activity, chunks without compression (any MCAP reader opens
//! them with no codec installed), and at the end a `hwgw.recording` metadata record with
//! what was recorded, what was lost and why, and the clock offset.

use crate::item::PortSpec;
use crate::item::{Item, SampleMessage, StepMessage, sample_schema, step_schema};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};

/// Why a recording could not be made or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RecordError {
    /// The file could not be created.
    #[error("{path}: cannot create the recording: {source}")]
    Create {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Writing MCAP failed (a full disk, an I/O error).
    #[error("writing the recording: {0}")]
    Mcap(#[from] mcap::McapError),
    /// The finished file could not be flushed to the disk.
    #[error("flushing the recording: {0}")]
    Flush(std::io::Error),
    /// More channels than MCAP's 65 535.
    #[error("{0} channels: an MCAP file holds at most 65 535")]
    TooManyChannels(usize),
    /// A message could not be serialised.
    #[error("serialising a message: {0}")]
    Json(#[from] serde_json::Error),
}

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
pub struct Recorder<W: Write + Seek = BufWriter<File>> {
    mcap: mcap::Writer<W>,
    ports: Vec<PortSpec>,
    activities: Vec<String>,
    port_channels: Vec<Channel>,
    step_channels: Vec<Channel>,
    options: Options,
    bytes: u64,
    over_limit: u64,
    unknown: u64,
    scratch: Vec<u8>,
}

impl Recorder {
    /// Creates `path` (never an existing file) for `ports` and `activities`.
    pub fn create(
        path: &Path,
        ports: Vec<PortSpec>,
        activities: Vec<String>,
        options: Options,
    ) -> Result<Recorder, RecordError> {
        let file = File::create_new(path).map_err(|source| RecordError::Create {
            path: path.to_path_buf(),
            source,
        })?;
        Recorder::new(BufWriter::new(file), ports, activities, options)
    }
}

/// Bytes a message adds to the file besides its data: the record's opcode, length and
/// header, and its message index entry.
const MESSAGE_OVERHEAD: u64 = 1 + 8 + 22 + 16;

impl<W: Write + Seek> Recorder<W> {
    /// A recording into `out`.
    pub fn new(
        out: W,
        ports: Vec<PortSpec>,
        activities: Vec<String>,
        options: Options,
    ) -> Result<Recorder<W>, RecordError> {
        let channels = ports.len() + activities.len();
        if channels > usize::from(u16::MAX) {
            return Err(RecordError::TooManyChannels(channels));
        }
        let mut mcap = mcap::WriteOptions::new()
            .compression(None)
            .profile("")
            .library(concat!("hwgw-recording ", env!("CARGO_PKG_VERSION")))
            .create(out)?;
        let mut schemas: BTreeMap<String, u16> = BTreeMap::new();
        let mut port_channels = Vec::with_capacity(ports.len());
        for p in &ports {
            let name = format!("hwgw.sample.{}", p.type_name);
            let schema = match schemas.get(&name) {
                Some(id) => *id,
                None => {
                    let data = serde_json::to_vec(&sample_schema(&p.type_name))?;
                    let id = mcap.add_schema(&name, "jsonschema", &data)?;
                    schemas.insert(name, id);
                    id
                }
            };
            let meta = BTreeMap::from([
                ("port".to_string(), p.name.clone()),
                ("type".to_string(), p.type_name.clone()),
            ]);
            let id = mcap.add_channel(schema, &p.topic(), "json", &meta)?;
            port_channels.push(Channel::new(id));
        }
        let mut step_channels = Vec::with_capacity(activities.len());
        if !activities.is_empty() {
            let data = serde_json::to_vec(&step_schema())?;
            let schema = mcap.add_schema("hwgw.step", "jsonschema", &data)?;
            for a in &activities {
                let meta = BTreeMap::from([("activity".to_string(), a.clone())]);
                let id = mcap.add_channel(schema, &format!("/activity/{a}"), "json", &meta)?;
                step_channels.push(Channel::new(id));
            }
        }
        Ok(Recorder {
            mcap,
            ports,
            activities,
            port_channels,
            step_channels,
            options,
            bytes: 0,
            over_limit: 0,
            unknown: 0,
            scratch: Vec::with_capacity(256),
        })
    }

    /// Writes one item; `now_ns` (runtime clock) is when the recorder took it, kept as the
    /// message's publish time. An item of an unknown port or activity is counted.
    pub fn write(&mut self, item: &Item, now_ns: u64) -> Result<(), RecordError> {
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
            log_time: 0,
            publish_time: 0,
        };
        channel.sequence = channel.sequence.wrapping_add(1);
        channel.written += 1;
        let header = mcap::records::MessageHeader {
            log_time: wall(self.options.wall_offset_ns, time),
            publish_time: wall(self.options.wall_offset_ns, now_ns),
            ..header
        };
        self.mcap.write_to_known_channel(&header, &self.scratch)?;
        self.bytes += size;
        Ok(())
    }

    /// UNIX time minus the items' clock, ns, as given in the options.
    pub fn wall_offset_ns(&self) -> i128 {
        self.options.wall_offset_ns
    }

    /// Messages written so far.
    pub fn written(&self) -> u64 {
        self.port_channels
            .iter()
            .chain(&self.step_channels)
            .map(|c| c.written)
            .sum()
    }

    /// Writes the metadata and the summary, and flushes: the file is complete.
    pub fn finish(mut self, closing: &Closing) -> Result<BTreeMap<String, String>, RecordError> {
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
        meta.extend(closing.notes.clone());
        meta.insert("lost".into(), lost.to_string());
        self.mcap.write_metadata(&mcap::records::Metadata {
            name: METADATA.into(),
            metadata: meta.clone(),
        })?;
        self.mcap.finish()?;
        self.mcap.into_inner().flush().map_err(RecordError::Flush)?;
        Ok(meta)
    }
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
