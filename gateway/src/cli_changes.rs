//! The command line's run-time changes of a deployment ([`crate::changes`]): `load`,
//! `unload`, `connect`, `disconnect`, and `save`, which writes the running deployment into
//! a new file.

use crate::client::{Client, ClientError};
use crate::protocol::{ErrorBody, ErrorKind, ReloadReport, Request, json_arg};
use clap::Subcommand;
use serde_json::{Map, Value, json};
use std::path::{Path, PathBuf};

/// A change of the running deployment (undone by a reload of the file unless saved).
#[derive(Subcommand)]
pub enum ChangeCommand {
    /// Load a component into the running deployment, as a `[[component]]` of the file
    /// would be: built, configured, started.
    Load {
        /// Its name.
        name: String,
        /// Its type (`hwgw check` on a deployment lists those of this build).
        #[arg(value_name = "TYPE")]
        kind: String,
        /// A periodic activity of this period; without it, non-periodic.
        #[arg(long, value_name = "MS")]
        period_ms: Option<f64>,
        /// A property value (JSON, or text); repeat for more.
        #[arg(long = "property", value_name = "KEY=VALUE")]
        properties: Vec<String>,
        /// A required service's or devices' binding (`camera=cam0.camera`); repeat for
        /// more.
        #[arg(long = "requires", value_name = "NAME=BINDING")]
        requires: Vec<String>,
        /// Configure it but do not start it.
        #[arg(long)]
        stopped: bool,
    },
    /// Unload a component of the deployment: stopped, cleaned up, its connections closed.
    Unload {
        /// The component.
        component: String,
    },
    /// Connect an output port to an input port (`component.port`); prints the id.
    Connect {
        /// The output port.
        from: String,
        /// The input port.
        to: String,
        /// The policy as JSON, as in a `[[connection]]`:
        /// `{"kind": {"type": "buffer", "size": 8}}` (default: data).
        #[arg(long)]
        policy: Option<String>,
    },
    /// Close the connection with this id (as `connect` printed it, or `ls COMPONENT` lists).
    Disconnect {
        /// The connection's id.
        id: u64,
    },
    /// A new period for a stopped component's periodic activity, taken at its next start.
    SetPeriod {
        /// The component.
        component: String,
        /// The period, ms.
        period_ms: f64,
    },
    /// A new scheduling policy (`other`, `fifo`) and priority for a stopped component's
    /// thread, taken at its next start.
    SetPriority {
        /// The component.
        component: String,
        /// `other` or `fifo`.
        #[arg(value_enum)]
        policy: Policy,
        /// 1..=99 for fifo, 0 for other.
        #[arg(default_value_t = 0)]
        priority: i32,
    },
    /// Write a component's properties into a TOML file (the manual's writeProperties):
    /// whole and at once, a new file unless --replace.
    SaveProperties {
        /// The component.
        component: String,
        /// The file.
        file: PathBuf,
        /// Replace the file if it exists (never a link or another's file).
        #[arg(long)]
        replace: bool,
    },
    /// Set a component's properties from a TOML file (the manual's readProperties): all
    /// of them, or none when one is refused.
    LoadProperties {
        /// The component.
        component: String,
        /// The file.
        file: PathBuf,
    },
    /// Write the running deployment (the file's, with the run-time changes) into FILE, a
    /// new file: never over an existing one.
    Save {
        /// The new file.
        file: PathBuf,
    },
}

/// The change commands as words (`browse`'s `load f2 follow --period-ms 10`), parsed as
/// the command line parses them.
pub(crate) fn parse(words: &[&str]) -> Result<ChangeCommand, String> {
    #[derive(clap::Parser)]
    #[command(name = "browse", no_binary_name = true)]
    struct Line {
        #[command(subcommand)]
        command: ChangeCommand,
    }
    <Line as clap::Parser>::try_parse_from(words)
        .map(|l| l.command)
        .map_err(|e| e.to_string().trim_end().to_string())
}

/// A scheduling policy as the command line takes it.
#[derive(Clone, Copy, clap::ValueEnum)]
pub enum Policy {
    /// SCHED_OTHER.
    Other,
    /// SCHED_FIFO.
    Fifo,
}

fn refused(kind: ErrorKind, message: String) -> ClientError {
    ClientError::Refused(ErrorBody { kind, message })
}

/// `KEY=VALUE` pairs as a JSON object, values as `set` takes them.
fn pairs(list: &[String], what: &str) -> Result<Map<String, Value>, ClientError> {
    let mut out = Map::new();
    for item in list {
        let (k, v) = item.split_once('=').ok_or_else(|| {
            refused(
                ErrorKind::BadRequest,
                format!("{what} {item:?}: expected KEY=VALUE"),
            )
        })?;
        out.insert(k.to_string(), json_arg(v));
    }
    Ok(out)
}

/// Carries out `command`: what to print, if anything (`verbose`: the lines applied).
pub(crate) fn run(
    client: &Client,
    command: ChangeCommand,
    verbose: bool,
) -> Result<Option<String>, ClientError> {
    let req = match command {
        ChangeCommand::Load {
            name,
            kind,
            period_ms,
            properties,
            requires,
            stopped,
        } => {
            let activity = match period_ms {
                Some(ms) => json!({"type": "periodic", "period_ms": ms}),
                None => json!({"type": "non_periodic"}),
            };
            let mut c = json!({"name": name, "type": kind, "activity": activity});
            let props = pairs(&properties, "--property")?;
            if !props.is_empty() {
                c["properties"] = Value::Object(props);
            }
            let reqs = pairs(&requires, "--requires")?;
            if !reqs.is_empty() {
                c["requires"] = Value::Object(reqs);
            }
            if stopped {
                c["start"] = Value::Bool(false);
            }
            Request::Load { component: c }
        }
        ChangeCommand::Unload { component } => Request::Unload { component },
        ChangeCommand::Connect { from, to, policy } => {
            let policy = match policy {
                Some(p) => Some(serde_json::from_str(&p).map_err(|e| {
                    refused(
                        ErrorKind::BadRequest,
                        format!("--policy {p:?}: not JSON: {e}"),
                    )
                })?),
                None => None,
            };
            let answer = client.request(&Request::Connect { from, to, policy })?;
            // A connection fed from another gateway has no id here.
            return Ok(answer["id"].as_u64().map(|id| id.to_string()));
        }
        ChangeCommand::Disconnect { id } => Request::Disconnect { connection: id },
        ChangeCommand::Save { file } => return save(client, &file, verbose),
        ChangeCommand::SaveProperties {
            component,
            file,
            replace,
        } => {
            let text: String = client.typed(&Request::Properties { component })?;
            write_whole(&file, &text, replace)?;
            return Ok(verbose.then(|| format!("saved in {}", file.display())));
        }
        ChangeCommand::LoadProperties { component, file } => {
            let text = crate::propfiles::read(&file).map_err(|e| refused(ErrorKind::Failed, e))?;
            let table: toml::Table = text.parse().map_err(|e: toml::de::Error| {
                refused(
                    ErrorKind::BadRequest,
                    format!("{}: {}", file.display(), e.message()),
                )
            })?;
            let properties = serde_json::to_value(&table)
                .map_err(|e| refused(ErrorKind::BadRequest, e.to_string()))?;
            client.request(&Request::LoadProperties {
                component,
                properties,
            })?;
            return Ok(None);
        }
        ChangeCommand::SetPeriod {
            component,
            period_ms,
        } => {
            client.request(&Request::SetPeriod {
                component,
                period_ms,
            })?;
            return Ok(None);
        }
        ChangeCommand::SetPriority {
            component,
            policy,
            priority,
        } => {
            let policy = match policy {
                Policy::Other => rtt::SchedPolicy::Other,
                Policy::Fifo => rtt::SchedPolicy::Fifo,
            };
            client.request(&Request::SetPriority {
                component,
                policy,
                priority,
            })?;
            return Ok(None);
        }
    };
    let report: ReloadReport = client.typed(&req)?;
    Ok(verbose.then(|| report.applied.join("\n")))
}

/// Writes `text` into `file` whole: into a new file beside it first, then in its place —
/// a reader sees the old file or the new one, never half of it. Without `replace` an
/// existing file is refused; with it, only a regular file of this user's is replaced.
fn write_whole(file: &Path, text: &str, replace: bool) -> Result<(), ClientError> {
    use std::io::Write;
    let fail = |e: String| refused(ErrorKind::Failed, format!("{}: {e}", file.display()));
    if std::fs::symlink_metadata(file).is_ok() {
        if !replace {
            return Err(fail("exists; --replace to write over it".into()));
        }
        recording::file::check_replace_own(file).map_err(|e| fail(e.to_string()))?;
    }
    let name = file
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_default();
    let tmp = file.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
    let written = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&tmp)
        .and_then(|mut f| f.write_all(text.as_bytes()).and_then(|()| f.sync_all()));
    let placed = written.and_then(|()| {
        if replace {
            std::fs::rename(&tmp, file)
        } else {
            // A link fails when the name exists: never over a file made meanwhile.
            std::fs::hard_link(&tmp, file).and_then(|()| std::fs::remove_file(&tmp))
        }
    });
    placed.map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        fail(e.to_string())
    })
}

/// `save FILE`: the running deployment into a new file.
fn save(client: &Client, file: &Path, verbose: bool) -> Result<Option<String>, ClientError> {
    let text: String = client.typed(&Request::Deployment)?;
    if std::fs::symlink_metadata(file).is_ok() {
        return Err(refused(
            ErrorKind::Failed,
            format!(
                "{}: exists; save writes a new file, never over one",
                file.display()
            ),
        ));
    }
    // Whole or not at all: a failed write leaves no half file under the name.
    write_whole(file, &text, false)?;
    Ok(verbose.then(|| format!("saved the running deployment in {}", file.display())))
}
