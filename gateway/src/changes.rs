//! A deployment that changes while it runs: the Orocos deployment component's loading,
//! connecting and unloading of components at run time (seed 000, manual L38–41, L197–200,
//! L1881–1920).
//!
//! Each change edits the running deployment — the text the gateway was built from, with
//! the changes made so far — and applies the result as a reload does
//! ([`Gateway::reload_text`](crate::deploy::Gateway::reload_text)): checked whole by the same code as `hwgw check`, then only what
//! changed is built (a component loaded touches no card; an unloaded one is stopped,
//! cleaned up and its connections closed). One error and nothing changes; the reply lists
//! the errors. `hwgw ls --changes` lists what was changed since the file was read;
//! `hwgw save FILE` writes the running deployment, a new file, never over one. A `reload`
//! (SIGHUP) reads the file again: the run-time changes are undone unless saved into it.

use crate::deploy::Gateway;
use crate::protocol::ReloadReport;
use serde_json::Value;

/// How many run-time changes `ls --changes` keeps (the newest).
pub const KEPT: usize = 1000;

/// One run-time change.
#[derive(Debug, Clone, PartialEq)]
pub enum Change {
    /// A component: a `[[component]]` table (`name`, `type`, `activity`, `properties`,
    /// `start`, `requires`).
    Load(toml::Table),
    /// A component of the deployment, and its connections.
    Unload(String),
    /// A connection from output port `from` to input port `to` (`component.port`), with a
    /// policy table (default: data).
    Connect {
        /// `component.port` of the output.
        from: String,
        /// `component.port` of the input.
        to: String,
        /// The policy, as in a `[[connection]]`.
        policy: Option<toml::Value>,
    },
    /// The connection with this id (as `connect` answered it, or `describe` lists it).
    Disconnect(u64),
}

/// Why a change was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ChangeError {
    /// The deployment with the change has errors; nothing changed.
    #[error("nothing changed; the deployment would have errors:\n{}", .0.join("\n"))]
    Refused(Vec<String>),
    /// The change passed the check but did not all apply: what did and what failed.
    #[error("applied in part:\n{}\nfailed:\n{}", .applied.join("\n"), .errors.join("\n"))]
    Partly {
        /// What was applied.
        applied: Vec<String>,
        /// What failed.
        errors: Vec<String>,
    },
    /// No component of the deployment by that name.
    #[error("no component {name:?} in the deployment (an IO component goes with its card); there are: {}", if .known.is_empty() { "none".to_string() } else { .known.join(", ") })]
    NoComponent {
        /// The name asked for.
        name: String,
        /// The deployment's components.
        known: Vec<String>,
    },
    /// A component by that name exists.
    #[error("a component named {0:?} exists already")]
    Exists(String),
    /// No connection made by the deployment has that id.
    #[error("no connection of the deployment has id {id}; there are: {}", if .known.is_empty() { "none".to_string() } else { .known.join(", ") })]
    NoConnection {
        /// The id asked for.
        id: u64,
        /// `id: from -> to` of each.
        known: Vec<String>,
    },
    /// A name a component cannot have.
    #[error(
        "{0:?} cannot name a component: it must not be empty, hold '/', white space or control characters, or begin or end with '.'"
    )]
    BadName(String),
    /// What was given is not a component table or a policy.
    #[error("{0}")]
    Invalid(String),
}

/// The `[[component]]` tables of `doc`, made when missing.
fn tables<'a>(
    doc: &'a mut toml::Table,
    key: &str,
) -> Result<&'a mut Vec<toml::Value>, ChangeError> {
    let v = doc
        .entry(key.to_string())
        .or_insert_with(|| toml::Value::Array(Vec::new()));
    v.as_array_mut()
        .ok_or_else(|| ChangeError::Invalid(format!("the deployment's {key:?} is not a list")))
}

fn name_of(t: &toml::Value) -> Option<&str> {
    t.get("name").and_then(toml::Value::as_str)
}

/// What a change applied.
#[derive(Debug, Clone, PartialEq)]
pub struct Changed {
    /// The reload's report: what was built and removed.
    pub report: ReloadReport,
    /// The connection made by a `connect` (none for one fed from another gateway).
    pub id: Option<u64>,
}

/// Whether `name` may name a component loaded at run time (`B/x` is another gateway's).
fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && !name.starts_with('.')
        && !name.ends_with('.')
        && !name
            .chars()
            .any(|c| c == '/' || c.is_whitespace() || c.is_control())
}

impl Gateway {
    /// Applies `change` to the running deployment (see the module doc): what it applied,
    /// or why nothing changed.
    pub fn change(&self, change: Change) -> Result<Changed, ChangeError> {
        let mut running = self.running();
        let mut doc: toml::Table = toml::from_str(&running.text)
            .map_err(|e| ChangeError::Invalid(format!("the running deployment: {e}")))?;
        let what = self.edit(&mut doc, &change)?;
        let text = toml::to_string(&doc)
            .map_err(|e| ChangeError::Invalid(format!("the changed deployment: {e}")))?;
        let file = match &running.file {
            Some(f) => format!("{} (with run-time changes)", f.display()),
            None => "<embedded demo> (with run-time changes)".to_string(),
        };
        let report = self.reload_locked(&mut running, &text, &file, true);
        if !report.errors.is_empty() {
            let applied: Vec<String> = report
                .applied
                .iter()
                .filter(|l| *l != "nothing changed")
                .cloned()
                .collect();
            if applied.is_empty() {
                return Err(ChangeError::Refused(report.errors));
            }
            note(&mut running, format!("{what} (in part)"));
            return Err(ChangeError::Partly {
                applied,
                errors: report.errors,
            });
        }
        let id = match &change {
            Change::Connect { from, to, .. } => self.connection_id(from, to),
            _ => None,
        };
        note(&mut running, what);
        Ok(Changed { report, id })
    }

    /// Edits `doc` as `change` says; the line `ls --changes` shows for it.
    fn edit(&self, doc: &mut toml::Table, change: &Change) -> Result<String, ChangeError> {
        match change {
            Change::Load(table) => {
                let name = table
                    .get("name")
                    .and_then(toml::Value::as_str)
                    .ok_or_else(|| ChangeError::Invalid("a component needs a \"name\"".into()))?
                    .to_string();
                if !valid_name(&name) {
                    return Err(ChangeError::BadName(name));
                }
                let kind = table
                    .get("type")
                    .and_then(toml::Value::as_str)
                    .unwrap_or("?");
                let line = format!("load {name} (type {kind})");
                let list = tables(doc, "component")?;
                if list.iter().any(|c| name_of(c) == Some(&name)) {
                    return Err(ChangeError::Exists(name));
                }
                list.push(toml::Value::Table(table.clone()));
                Ok(line)
            }
            Change::Unload(name) => {
                let list = tables(doc, "component")?;
                let Some(i) = list.iter().position(|c| name_of(c) == Some(name)) else {
                    return Err(ChangeError::NoComponent {
                        name: name.clone(),
                        known: list.iter().filter_map(name_of).map(String::from).collect(),
                    });
                };
                list.remove(i);
                let ports: Vec<String> = self
                    .runtime()
                    .component(name)
                    .map(|t| {
                        t.ports()
                            .into_iter()
                            .map(|p| format!("{name}.{}", p.name))
                            .collect()
                    })
                    .unwrap_or_default();
                let on_it = |c: &toml::Value| {
                    ["from", "to"].iter().any(|k| {
                        c.get(*k)
                            .and_then(toml::Value::as_str)
                            .is_some_and(|e| ports.iter().any(|p| p == e))
                    })
                };
                tables(doc, "connection")?.retain(|c| !on_it(c));
                Ok(format!("unload {name}"))
            }
            Change::Connect { from, to, policy } => {
                if let Some(id) = self.connection_id(from, to) {
                    return Err(ChangeError::Invalid(format!(
                        "{from} -> {to} is connected already (id {id})"
                    )));
                }
                let mut t = toml::Table::new();
                t.insert("from".into(), toml::Value::String(from.clone()));
                t.insert("to".into(), toml::Value::String(to.clone()));
                if let Some(p) = policy {
                    t.insert("policy".into(), p.clone());
                }
                tables(doc, "connection")?.push(toml::Value::Table(t));
                Ok(format!("connect {from} -> {to}"))
            }
            Change::Disconnect(id) => {
                let config = self.connection(*id)?;
                let list = tables(doc, "connection")?;
                // The entry that made this very connection: same ends, same policy.
                let Some(i) = list.iter().position(|c| {
                    c.clone()
                        .try_into::<crate::config::ConnectionConfig>()
                        .ok()
                        .as_ref()
                        == Some(&config)
                }) else {
                    return Err(ChangeError::Invalid(format!(
                        "connection {id} ({} -> {}) is in no [[connection]] of the deployment",
                        config.from, config.to
                    )));
                };
                list.remove(i);
                Ok(format!(
                    "disconnect {} -> {} (id {id})",
                    config.from, config.to
                ))
            }
        }
    }

    /// The configuration of the deployment's connection `id`.
    fn connection(&self, id: u64) -> Result<crate::config::ConnectionConfig, ChangeError> {
        let parts = self.parts();
        let made = || {
            parts
                .links
                .iter()
                .filter_map(|l| l.made.as_ref().map(|m| (l, m.1)))
        };
        made()
            .find(|(_, i)| *i == id)
            .map(|(l, _)| l.config.clone())
            .ok_or_else(|| ChangeError::NoConnection {
                id,
                known: made()
                    .map(|(l, i)| format!("{i}: {} -> {}", l.config.from, l.config.to))
                    .collect(),
            })
    }

    /// The id of the deployment's newest connection from `from` to `to`.
    pub fn connection_id(&self, from: &str, to: &str) -> Option<u64> {
        self.parts()
            .links
            .iter()
            .rev()
            .filter(|l| l.config.from == from && l.config.to == to)
            .find_map(|l| l.made.as_ref().map(|m| m.1))
    }

    /// The run-time changes since the deployment file was last read: the newest
    /// [`KEPT`], after a line counting the older ones when there were more.
    pub fn changes(&self) -> Vec<String> {
        let running = self.running();
        let older = (running.changes_dropped > 0)
            .then(|| format!("({} earlier changes not kept)", running.changes_dropped));
        older
            .into_iter()
            .chain(running.changes.iter().cloned())
            .collect()
    }

    /// The running deployment as TOML: the file's, with the run-time changes.
    pub fn deployment_text(&self) -> String {
        self.running().text.clone()
    }
}

/// A change of a stopped component's activity (RTT's `setPeriod`, `setPriority`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ActivityChange {
    /// A new period, ms (a periodic activity).
    Period(f64),
    /// A new scheduling policy and priority (an activity with a thread).
    Thread(rtt::SchedPolicy, i32),
}

impl Gateway {
    /// Changes stopped component `name`'s activity, taken at its next start; a component
    /// of the deployment has its `activity` edited too, so that `save` writes it.
    pub fn set_activity(&self, name: &str, change: ActivityChange) -> Result<(), ChangeError> {
        let mut running = self.running();
        let task = self
            .runtime()
            .component(name)
            .map_err(|_| ChangeError::NoComponent {
                name: name.to_string(),
                known: self
                    .runtime()
                    .components()
                    .iter()
                    .map(|t| t.name().to_string())
                    .collect(),
            })?;
        let refused = |e: String| ChangeError::Refused(vec![format!("{name}: {e}")]);
        let (key, line) = match change {
            ActivityChange::Period(ms) => {
                crate::checks::period(ms).map_err(refused)?;
                task.set_period(crate::config::millis(ms))
                    .map_err(|e| refused(e.to_string()))?;
                (
                    vec![("period_ms", toml::Value::Float(ms))],
                    format!("set_period {name} {ms} ms"),
                )
            }
            ActivityChange::Thread(policy, priority) => {
                let mut thread = match task.activity().current() {
                    rtt::ActivitySpec::Periodic { thread, .. }
                    | rtt::ActivitySpec::NonPeriodic { thread }
                    | rtt::ActivitySpec::FileDescriptor { thread, .. } => thread,
                    rtt::ActivitySpec::Slave => {
                        return Err(refused("a slave activity has no thread of its own".into()));
                    }
                };
                thread.policy = policy;
                thread.priority = priority;
                task.set_thread(thread)
                    .map_err(|e| refused(e.to_string()))?;
                let policy_name = match policy {
                    rtt::SchedPolicy::Other => "other",
                    rtt::SchedPolicy::Fifo => "fifo",
                };
                (
                    vec![
                        ("policy", toml::Value::String(policy_name.into())),
                        ("priority", toml::Value::Integer(i64::from(priority))),
                    ],
                    format!("set_priority {name} {policy_name} {priority}"),
                )
            }
        };
        // The deployment's own components keep the change in the running deployment.
        if let Ok(mut doc) = toml::from_str::<toml::Table>(&running.text)
            && let Ok(list) = tables(&mut doc, "component")
            && let Some(activity) = list
                .iter_mut()
                .find(|c| name_of(c) == Some(name))
                .and_then(|c| c.get_mut("activity"))
                .and_then(toml::Value::as_table_mut)
        {
            for (k, v) in key {
                activity.insert(k.to_string(), v);
            }
            if let Ok(text) = toml::to_string(&doc)
                && let Ok(d) = crate::config::Deployment::parse(&text, "(run-time changes)")
            {
                running.text = text;
                running.deployment = d;
            }
        }
        note(&mut running, line);
        Ok(())
    }
}

/// Notes a change for `ls --changes`, keeping the newest [`KEPT`].
fn note(running: &mut crate::deploy::Running, line: String) {
    if running.changes.len() >= KEPT {
        running.changes.pop_front();
        running.changes_dropped += 1;
    }
    running.changes.push_back(line);
}

/// A JSON object as the TOML table it stands for (`load`'s component, `connect`'s policy).
pub fn table(v: &Value, what: &str) -> Result<toml::Table, ChangeError> {
    toml::Table::try_from(v).map_err(|e| ChangeError::Invalid(format!("{what}: {e}")))
}
