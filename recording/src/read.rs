//! A recording read back: each port's samples as numbers over time, each activity's
//! steps, and hwgw's metadata. For pictures (`hwgw plot`), not for real-time use: the file
//! is read whole, so its size is bounded ([`MAX_FILE`]).

use crate::item::{Step, StepMessage};
use crate::trigger::number;
use crate::write::METADATA;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The largest recording read back: 4 GiB.
pub const MAX_FILE: u64 = 4 << 30;

/// Why a recording could not be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReadError {
    /// The file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The file is larger than [`MAX_FILE`].
    #[error("{path}: {size} bytes; recordings over {max} bytes are not read back")]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Its size.
        size: u64,
        /// The limit.
        max: u64,
    },
    /// The file is not valid MCAP.
    #[error("{path}: not a readable MCAP file: {source}")]
    Mcap {
        /// The file.
        path: PathBuf,
        /// Why.
        source: mcap::McapError,
    },
}

/// One port's samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// `component.port`.
    pub port: String,
    /// The port's data type, as recorded.
    pub type_name: String,
    /// (UNIX ns, value) in file order; samples that are not numbers are left out (and
    /// counted in [`Recording::not_numbers`]).
    pub points: Vec<(u64, f64)>,
}

/// One activity's steps (UNIX ns).
#[derive(Debug, Clone, PartialEq)]
pub struct Steps {
    /// The activity's name.
    pub activity: String,
    /// Its steps, in file order.
    pub steps: Vec<Step>,
}

/// A recording read back.
#[derive(Debug, Clone, Default)]
pub struct Recording {
    /// Ports, in the order their channels appear.
    pub ports: Vec<Series>,
    /// Activities, likewise.
    pub activities: Vec<Steps>,
    /// hwgw's metadata (empty when the recording was never finished).
    pub metadata: BTreeMap<String, String>,
    /// Samples whose value is not a number.
    pub not_numbers: u64,
    /// Messages of other channels, or that did not decode.
    pub skipped: u64,
    /// Messages read, of every kind (those above included).
    pub messages: u64,
    /// Why the file is not whole — reading stopped at a record cut short or corrupt, or
    /// the file ends before its footer (a recording cut by a crash, a kill or a full
    /// disk): what came before is kept. `None` for a complete file.
    pub truncated: Option<String>,
}

impl Recording {
    /// Reads `path`.
    pub fn read(path: &Path) -> Result<Recording, ReadError> {
        let io = |source| ReadError::Io {
            path: path.to_path_buf(),
            source,
        };
        // Opened first, without blocking (a FIFO would wait for a writer), then looked at.
        let file = std::os::unix::fs::OpenOptionsExt::custom_flags(
            std::fs::OpenOptions::new().read(true),
            nix::libc::O_NONBLOCK,
        )
        .open(path)
        .map_err(io)?;
        let meta = file.metadata().map_err(io)?;
        if !meta.is_file() {
            return Err(io(std::io::Error::other("not a regular file")));
        }
        let size = meta.len();
        if size > MAX_FILE {
            return Err(ReadError::TooLarge {
                path: path.to_path_buf(),
                size,
                max: MAX_FILE,
            });
        }
        // At most what the size said: a file that grows meanwhile is read up to it.
        let mut bytes = Vec::with_capacity(size as usize);
        std::io::Read::read_to_end(&mut std::io::Read::take(file, size), &mut bytes).map_err(io)?;
        Recording::parse(&bytes).map_err(|source| ReadError::Mcap {
            path: path.to_path_buf(),
            source,
        })
    }

    /// Reads a recording held in memory: an error only when it is not MCAP at all; a file
    /// cut short gives what it holds, with [`truncated`](Self::truncated) saying why.
    pub fn parse(bytes: &[u8]) -> Result<Recording, mcap::McapError> {
        let mut rec = Recording::default();
        let mut ports: BTreeMap<u16, usize> = BTreeMap::new();
        let mut activities: BTreeMap<u16, usize> = BTreeMap::new();
        if !bytes.starts_with(mcap::MAGIC) {
            if mcap::MAGIC.starts_with(bytes) {
                // Cut before anything but (part of) the opening magic reached the disk.
                rec.truncated = Some(format!(
                    "the file ends at byte {} of its opening: nothing was written into it",
                    bytes.len()
                ));
                return Ok(rec);
            }
            return Err(mcap::McapError::BadMagic);
        }
        let options = mcap::read::Options::IgnoreEndMagic.into();
        for message in mcap::MessageStream::new_with_options(bytes, options)? {
            let m = match message {
                Ok(m) => m,
                Err(e) => {
                    rec.truncated = Some(e.to_string());
                    break;
                }
            };
            rec.messages += 1;
            let ch = &m.channel;
            if let Some(port) = ch.metadata.get("port") {
                let i = *ports.entry(ch.id).or_insert_with(|| {
                    rec.ports.push(Series {
                        port: port.clone(),
                        type_name: ch.metadata.get("type").cloned().unwrap_or_default(),
                        points: Vec::new(),
                    });
                    rec.ports.len() - 1
                });
                let value = serde_json::from_slice::<serde_json::Value>(&m.data)
                    .ok()
                    .and_then(|v| v.get("value").cloned());
                match value.as_ref().and_then(number) {
                    Some(x) => rec.ports[i].points.push((m.log_time, x)),
                    None if value.is_some() => rec.not_numbers += 1,
                    None => rec.skipped += 1,
                }
            } else if let Some(name) = ch.metadata.get("activity") {
                let i = *activities.entry(ch.id).or_insert_with(|| {
                    rec.activities.push(Steps {
                        activity: name.clone(),
                        steps: Vec::new(),
                    });
                    rec.activities.len() - 1
                });
                match serde_json::from_slice::<StepMessage>(&m.data) {
                    Ok(s) => {
                        // Steps are kept as UNIX ns: the start is the message's time.
                        let shift = |t: u64| {
                            (i128::from(t) - i128::from(s.started_ns) + i128::from(m.log_time))
                                .clamp(0, i128::from(u64::MAX)) as u64
                        };
                        rec.activities[i].steps.push(Step {
                            scheduled_ns: shift(s.scheduled_ns),
                            started_ns: m.log_time,
                            ended_ns: shift(s.ended_ns),
                        });
                    }
                    Err(_) => rec.skipped += 1,
                }
            } else {
                rec.skipped += 1;
            }
        }
        let mut footer = false;
        for record in mcap::read::LinearReader::new_with_options(bytes, options)? {
            match record {
                Ok(mcap::records::Record::Metadata(m)) if m.name == METADATA => {
                    rec.metadata = m.metadata;
                }
                Ok(mcap::records::Record::Footer(_)) => footer = true,
                Ok(_) => {}
                Err(e) => {
                    // Said above when the messages stopped there too.
                    rec.truncated.get_or_insert_with(|| e.to_string());
                    break;
                }
            }
        }
        if !footer && rec.truncated.is_none() {
            rec.truncated =
                Some("the file ends before its footer: its writing stopped before the end".into());
        }
        Ok(rec)
    }

    /// The recording's state for people: `cut after N messages: why` for a file that is
    /// not whole, `no messages` for a whole one that holds none, `N messages` otherwise.
    pub fn condition(&self) -> String {
        match (&self.truncated, self.messages) {
            (Some(why), n) => format!("cut after {n} messages: {why}"),
            (None, 0) => "no messages: the recording is complete and empty".into(),
            (None, n) => format!("{n} messages"),
        }
    }
}
