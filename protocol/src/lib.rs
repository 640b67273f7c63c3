//! The control protocol's messages, typed: one [`Request`] and one [`Reply`] for the
//! server, the one-shot CLI and `hwgw browse`, and the typed answers of the commands
//! that list things. The wire format is line-delimited JSON (the gateway's `control` module documents it);
//! the command table of the documentation and the "unknown command" error both come from
//! [`COMMANDS`], so they cannot drift from the code.

mod reports;

use device_interface::{Interface, RegistryEntry, Status};
pub use reports::{CardReport, OutputReport, ServerReport};
use rtt::TaskState;
use rtt::activity::ActivityStats;
use rtt::component::{PortInfo, TaskCounters};
use rtt::operation::OperationInfo;
use rtt::port::FlowStatus;
use rtt::property::PropertyInfo;
use serde::{Deserialize, Serialize};
use serde_json::Value;

/// A port or a property of a component.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Target {
    /// A port, by name.
    Port(String),
    /// A property, by its dotted path.
    Property(String),
    /// An attribute (a run-time value, not saved) or a constant, by its dotted path.
    Attribute(String),
}

impl Target {
    /// A name as people write it: `NAME` is a port, `property:NAME` a property,
    /// `attribute:NAME` an attribute or a constant.
    pub fn from_name(name: &str) -> Target {
        if let Some(p) = name.strip_prefix("property:") {
            Target::Property(p.to_string())
        } else if let Some(a) = name.strip_prefix("attribute:") {
            Target::Attribute(a.to_string())
        } else {
            Target::Port(name.to_string())
        }
    }
}

/// A value as people type it: JSON, or text when it is not JSON (`set x on` sets "on").
pub fn json_arg(s: &str) -> Value {
    serde_json::from_str(s).unwrap_or_else(|_| Value::String(s.to_string()))
}

/// One request, tagged by `cmd` on the wire.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "snake_case")]
pub enum Request {
    /// Every component and its state; with `all`, of every gateway of the Zenoh name
    /// space too, each name under its gateway's (`B/follow`).
    Ls {
        /// Every gateway's, not only this one's.
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        all: bool,
    },
    /// One component's interface, state and timing.
    Describe {
        /// The component.
        component: String,
    },
    /// Every name in the device registry.
    Devices,
    /// Device health, cards' bus counters, component states and timing.
    Status,
    /// A port's current value or a property's value.
    Get {
        /// The component.
        component: String,
        /// `"port": NAME` or `"property": PATH`.
        #[serde(flatten)]
        target: Target,
    },
    /// Writes an input port or a property.
    Set {
        /// The component.
        component: String,
        /// `"port": NAME` or `"property": PATH`.
        #[serde(flatten)]
        target: Target,
        /// The value, as JSON.
        value: Value,
    },
    /// Calls an operation.
    Call {
        /// The component.
        component: String,
        /// The operation.
        operation: String,
        /// Its arguments, as JSON.
        #[serde(default)]
        args: Vec<Value>,
    },
    /// Lifecycle: configure.
    Configure {
        /// The component.
        component: String,
    },
    /// Lifecycle: start.
    Start {
        /// The component.
        component: String,
    },
    /// Lifecycle: stop.
    Stop {
        /// The component.
        component: String,
    },
    /// Lifecycle: cleanup.
    Cleanup {
        /// The component.
        component: String,
    },
    /// Lifecycle: recover.
    Recover {
        /// The component.
        component: String,
    },
    /// Streams the new values of an output port.
    Watch {
        /// The component.
        component: String,
        /// The output port.
        port: String,
        /// At most this many values (default: until the client closes).
        #[serde(default)]
        count: Option<u64>,
    },
    /// Streams stamped samples of output ports and activity steps, for a recording.
    Record {
        /// `component.port`, or `component` for all its output ports.
        #[serde(default)]
        ports: Vec<String>,
        /// Every device's channels too (the output ports of every card's components).
        #[serde(default)]
        devices: bool,
        /// Every activity's steps too.
        #[serde(default)]
        steps: bool,
        /// Samples each port may hold between two batches (default 4096).
        #[serde(default)]
        buffer: Option<usize>,
    },
    /// Reads the deployment file again and applies what changed (as SIGHUP does).
    Reload,
    /// Loads a component into the running deployment.
    Load {
        /// Its `[[component]]` table as JSON: `name`, `type`, `activity`, and optionally
        /// `properties`, `start`, `requires`.
        component: Value,
    },
    /// Unloads a component of the deployment: stopped, cleaned up, its connections closed.
    Unload {
        /// The component.
        component: String,
    },
    /// Connects an output port to an input port of the running deployment.
    Connect {
        /// `component.port` of the output.
        from: String,
        /// `component.port` of the input.
        to: String,
        /// The policy, as in a `[[connection]]` (default: data).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        policy: Option<Value>,
    },
    /// Closes a connection of the deployment.
    Disconnect {
        /// Its id, as `connect` answered it (`id` is the request's own).
        connection: u64,
    },
    /// A new period for a stopped component's periodic activity.
    SetPeriod {
        /// The component.
        component: String,
        /// The period, ms.
        period_ms: f64,
    },
    /// A new scheduling policy and priority for a stopped component's thread.
    SetPriority {
        /// The component.
        component: String,
        /// `"other"` or `"fifo"`.
        policy: rtt::SchedPolicy,
        /// 1..=99 for fifo, 0 for other.
        #[serde(default)]
        priority: i32,
    },
    /// A component's properties as TOML text (`hwgw save-properties`).
    Properties {
        /// The component.
        component: String,
    },
    /// Sets a component's properties from a table, all or none (`hwgw load-properties`).
    LoadProperties {
        /// The component.
        component: String,
        /// The values, as a (nested) JSON object of property names.
        properties: Value,
    },
    /// The run-time changes since the deployment file was read.
    Changes,
    /// The running deployment as TOML (`hwgw save`).
    Deployment,
    /// The real-time log's levels (every area, or `component`'s), after setting
    /// `component`'s to `level` when both are given (`hwgw log`).
    Log {
        /// The component (or card) that logs; none: every one.
        #[serde(default)]
        component: Option<String>,
        /// Its new level.
        #[serde(default)]
        level: Option<rtt::log::Level>,
    },
}

/// The answer to `log`: levels and the real-time logger's counters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LogLevels {
    /// Each area (a component or card that logs) and its level, by name.
    pub areas: Vec<LogArea>,
    /// Records written, dropped (queue full) and waiting, since the gateway started.
    pub counters: rtt::log::LogStats,
}

/// One area of the real-time log.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LogArea {
    /// The component or card.
    pub name: String,
    /// Its level.
    pub level: rtt::log::Level,
}

/// What a reload did: applied line by line, what needs a restart, and the errors that
/// kept the new deployment from being applied (then nothing changed) or that came past
/// its check.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ReloadReport {
    /// One line per change applied (`nothing changed` when none).
    pub applied: Vec<String>,
    /// What changed but applies only at a restart, each named.
    pub restart: Vec<String>,
    /// Why the new deployment was refused (every problem, one a line), or what went wrong
    /// applying it.
    pub errors: Vec<String>,
}

impl ReloadReport {
    /// Nothing applied, for these reasons.
    pub fn refused(errors: Vec<String>) -> ReloadReport {
        ReloadReport {
            errors,
            ..ReloadReport::default()
        }
    }
}

/// What a `record` stream carries first: what it records, and how to make its times UNIX
/// times.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecordStart {
    /// The ports, in the order of the samples' `port` numbers.
    pub ports: Vec<recording::PortSpec>,
    /// The activities (component names), in the order of the steps' `activity` numbers.
    pub activities: Vec<String>,
    /// UNIX time minus the monotonic clock's, ns, when the stream began.
    pub wall_minus_clock_ns: i128,
    /// The monotonic clock when the stream began, ns: samples from here on are recorded.
    pub now_ns: u64,
}

/// One batch of a `record` stream.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecordBatch {
    /// Samples and steps since the last batch.
    pub items: Vec<recording::Item>,
    /// Samples each port's buffer dropped so far.
    pub ports_lost: Vec<u64>,
    /// Steps each activity's tap dropped so far.
    pub steps_lost: Vec<u64>,
    /// Samples so far whose value could not be serialised.
    #[serde(default)]
    pub unserialisable: u64,
    /// The monotonic clock before the batch was drained, ns: samples stamped before it
    /// are in this batch or an earlier one, but for those of a step under way then (a
    /// sample takes its step's start). 0 on a batch split in several lines but the last.
    pub now_ns: u64,
}

/// One command of the protocol: its name, its fields, and what `ok` holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Command {
    /// `cmd`.
    pub cmd: &'static str,
    /// The other fields.
    pub fields: &'static str,
    /// The reply.
    pub ok: &'static str,
}

/// Every command, in the order the documentation lists them.
pub const COMMANDS: [Command; 26] = [
    Command {
        cmd: "ls",
        fields: "optional `all`",
        ok: "`[{\"name\", \"state\"}]` of every component; with `all`, of every gateway's, named `gateway/component`",
    },
    Command {
        cmd: "describe",
        fields: "`component`",
        ok: "ports, operations, properties, attributes, state, counters, activity statistics",
    },
    Command {
        cmd: "devices",
        fields: "—",
        ok: "every registry name: interface, name, owner, alias_of",
    },
    Command {
        cmd: "status",
        fields: "—",
        ok: "health, every device's health, every card's bus counters, every component's state and timing",
    },
    Command {
        cmd: "get",
        fields: "`component` and `port` or `property`",
        ok: "an output port's last value, an input port's read-back (a device output) or last value read, or the property's value",
    },
    Command {
        cmd: "set",
        fields: "`component`, `port` or `property`, `value`",
        ok: "`null`; a port must be an input port",
    },
    Command {
        cmd: "call",
        fields: "`component`, `operation`, `args` (array)",
        ok: "the result",
    },
    Command {
        cmd: "configure",
        fields: "`component`",
        ok: "the new state",
    },
    Command {
        cmd: "start",
        fields: "`component`",
        ok: "the new state",
    },
    Command {
        cmd: "stop",
        fields: "`component`",
        ok: "the new state",
    },
    Command {
        cmd: "cleanup",
        fields: "`component`",
        ok: "the new state",
    },
    Command {
        cmd: "recover",
        fields: "`component`",
        ok: "the new state",
    },
    Command {
        cmd: "watch",
        fields: "`component`, `port`, optional `count`",
        ok: "`\"watching\"`, then a stream: one `{\"id\", \"event\": {\"status\", \"value\"}}` line per new value (all of them, `count` at most), and `{\"id\", \"heartbeat\": ns}` after each second without one, until the client closes",
    },
    Command {
        cmd: "record",
        fields: "`ports` (`component.port` or `component`), optional `devices`, `steps`, `buffer`",
        ok: "`{\"ports\", \"activities\", \"wall_minus_clock_ns\"}`, then a stream of `{\"id\", \"records\": {\"items\", \"ports_lost\", \"steps_lost\", \"now_ns\"}}` batches until the client closes",
    },
    Command {
        cmd: "reload",
        fields: "—",
        ok: "`{\"applied\", \"restart\", \"errors\"}`: the deployment file read again and what changed rebuilt; when the new deployment has errors they are listed and nothing changed",
    },
    Command {
        cmd: "load",
        fields: "`component`: a `[[component]]` table as JSON (`name`, `type`, `activity`, optional `properties`, `start`, `requires`)",
        ok: "the reload's report: the component built, configured and started as the deployment file's are; with an error, nothing changed and the error lists why",
    },
    Command {
        cmd: "unload",
        fields: "`component`",
        ok: "the reload's report: the component stopped, cleaned up and removed, its connections closed",
    },
    Command {
        cmd: "connect",
        fields: "`from`, `to` (`component.port`), optional `policy` (as in a `[[connection]]`)",
        ok: "`{\"id\", \"applied\"}`: the new connection's id",
    },
    Command {
        cmd: "disconnect",
        fields: "`connection`: its id",
        ok: "the reload's report: the connection closed",
    },
    Command {
        cmd: "set_period",
        fields: "`component`, `period_ms`",
        ok: "`null`: the stopped component's periodic activity takes the period at its next start",
    },
    Command {
        cmd: "set_priority",
        fields: "`component`, `policy` (`\"other\"`, `\"fifo\"`), `priority`",
        ok: "`null`: the stopped component's thread takes them at its next start",
    },
    Command {
        cmd: "properties",
        fields: "`component`",
        ok: "its properties as TOML text (what `save-properties` writes)",
    },
    Command {
        cmd: "load_properties",
        fields: "`component`, `properties` (an object of property names, nested for bags)",
        ok: "`null`: every value set, or none when one is refused",
    },
    Command {
        cmd: "changes",
        fields: "—",
        ok: "the run-time changes (load, unload, connect, disconnect) since the deployment file was read, a line each",
    },
    Command {
        cmd: "deployment",
        fields: "—",
        ok: "the running deployment as TOML text: the file's with the run-time changes",
    },
    Command {
        cmd: "log",
        fields: "optional `component`, optional `level` (`off`, `error`, `warn`, `info`, `debug`, `trace`)",
        ok: "`{\"areas\": [{\"name\", \"level\"}], \"counters\": {\"written\", \"dropped\", \"queued\"}}`: the real-time log's levels (`component`'s only when given), after setting `component`'s to `level`",
    },
];

impl Request {
    /// The command's name on the wire.
    pub fn cmd(&self) -> &'static str {
        match self {
            Request::Ls { .. } => "ls",
            Request::Describe { .. } => "describe",
            Request::Devices => "devices",
            Request::Status => "status",
            Request::Get { .. } => "get",
            Request::Set { .. } => "set",
            Request::Call { .. } => "call",
            Request::Configure { .. } => "configure",
            Request::Start { .. } => "start",
            Request::Stop { .. } => "stop",
            Request::Cleanup { .. } => "cleanup",
            Request::Recover { .. } => "recover",
            Request::Watch { .. } => "watch",
            Request::Record { .. } => "record",
            Request::Reload => "reload",
            Request::Load { .. } => "load",
            Request::Unload { .. } => "unload",
            Request::Connect { .. } => "connect",
            Request::Disconnect { .. } => "disconnect",
            Request::SetPeriod { .. } => "set_period",
            Request::SetPriority { .. } => "set_priority",
            Request::Properties { .. } => "properties",
            Request::LoadProperties { .. } => "load_properties",
            Request::Changes => "changes",
            Request::Deployment => "deployment",
            Request::Log { .. } => "log",
        }
    }

    /// Whether only this host's operator may ask it: a reload, a change of the running
    /// deployment, or its text. Never served to (nor forwarded to) another gateway.
    pub fn is_local_only(&self) -> bool {
        matches!(
            self,
            Request::Reload
                | Request::Load { .. }
                | Request::Unload { .. }
                | Request::Connect { .. }
                | Request::Disconnect { .. }
                | Request::SetPeriod { .. }
                | Request::SetPriority { .. }
                | Request::Changes
                | Request::Deployment
                | Request::Log { .. }
        )
    }

    /// The command names, comma-separated (for errors and help).
    pub fn names() -> String {
        COMMANDS
            .iter()
            .map(|c| c.cmd)
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// The documentation's command table, in Markdown.
    pub fn table() -> String {
        let mut t = String::from("| cmd | fields | ok |\n|---|---|---|\n");
        for c in COMMANDS {
            t.push_str(&format!("| `{}` | {} | {} |\n", c.cmd, c.fields, c.ok));
        }
        t
    }
}

/// Error reply kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorKind {
    /// The line is not JSON.
    Parse,
    /// The line is longer than the server takes.
    TooLong,
    /// A field is missing or of the wrong type.
    BadRequest,
    /// `cmd` names no command.
    UnknownCommand,
    /// No such component, port, property or operation.
    NotFound,
    /// The command was refused or failed.
    Failed,
    /// The gateway serves as many clients as it takes; try again later.
    Busy,
    /// The gateway is stopping: no request is carried out any more.
    Stopping,
}

impl std::fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = serde_json::to_value(self)
            .ok()
            .and_then(|v| v.as_str().map(String::from))
            .unwrap_or_default();
        f.write_str(&s)
    }
}

/// An error reply's body.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ErrorBody {
    /// What kind of error.
    pub kind: ErrorKind,
    /// What is wrong, naming what exists where something was not found.
    pub message: String,
}

/// One value of a watched port.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Event {
    /// Always new data.
    pub status: FlowStatus,
    /// The value.
    pub value: Value,
}

/// What a reply carries.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Body {
    /// The answer.
    Ok(Value),
    /// Why there is none.
    Error(ErrorBody),
    /// A watched value.
    Event(Event),
    /// A batch of a `record` stream.
    Records(RecordBatch),
    /// A stream's sign of life while it has nothing to send (every
    /// [`HEARTBEAT`]): the gateway's monotonic time, ns. A
    /// client that hears nothing for longer than its timeout takes the gateway for stuck.
    Heartbeat(u64),
}

/// How often a stream with nothing to send says it is alive.
pub const HEARTBEAT: std::time::Duration = std::time::Duration::from_secs(1);

/// One reply line: the request's `id` echoed, and the body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reply {
    /// The request's `id` (null when the request had none or was not JSON).
    #[serde(default)]
    pub id: Value,
    /// The answer, error or event.
    #[serde(flatten)]
    pub body: Body,
}

impl Reply {
    /// An error reply.
    pub fn error(id: Value, kind: ErrorKind, message: impl Into<String>) -> Reply {
        Reply {
            id,
            body: Body::Error(ErrorBody {
                kind,
                message: message.into(),
            }),
        }
    }
}

/// A component in `ls`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ComponentEntry {
    /// Its name.
    pub name: String,
    /// Its state.
    pub state: TaskState,
    /// Its warning flag is up (it still runs).
    #[serde(default)]
    pub warning: bool,
}

/// A component in `describe`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Description {
    /// Its name.
    pub name: String,
    /// Its state.
    pub state: TaskState,
    /// Its ports.
    pub ports: Vec<PortEntry>,
    /// Its operations.
    pub operations: Vec<OperationInfo>,
    /// Its properties.
    pub properties: Vec<PropertyInfo>,
    /// Its attributes.
    pub attributes: Vec<PropertyInfo>,
    /// Error counters.
    pub counters: TaskCounters,
    /// Activity statistics.
    pub activity: ActivityStats,
    /// The services it provides.
    #[serde(default)]
    pub provides: Vec<rtt::service::ProvidedInfo>,
    /// The services and devices it requires, each with its binding.
    #[serde(default)]
    pub requires: Vec<rtt::service::RequiredInfo>,
    /// Names it knows other components by: (alias, component).
    #[serde(default)]
    pub peers: Vec<(String, String)>,
}

/// A port in `describe`: what it is, and how many connections it has now.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PortEntry {
    /// Name, doc, direction, type.
    #[serde(flatten)]
    pub info: PortInfo,
    /// Live connections.
    pub connections: usize,
}

impl std::ops::Deref for PortEntry {
    type Target = PortInfo;
    fn deref(&self) -> &PortInfo {
        &self.info
    }
}

/// The control server's counters in `status`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ControlReport {
    /// Clients connected now.
    pub connected: u64,
    /// Clients accepted since start.
    pub clients: u64,
    /// Clients turned away for the client limit.
    pub refused: u64,
    /// Clients disconnected for staying silent.
    pub idle_closed: u64,
    /// Requests answered.
    pub requests: u64,
    /// Requests answered with an error.
    pub errors: u64,
    /// Requests being carried out now (this `status` among them).
    #[serde(default)]
    pub under_way: u64,
    /// Clients that could not be taken for want of file descriptors, memory or threads.
    pub accept_failures: u64,
}

/// A device in `status`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DeviceStatus {
    /// The interface it is served under.
    pub interface: Interface,
    /// Its name.
    pub name: String,
    /// Online, stale or offline.
    pub status: Status,
    /// Age of its last good sample, s.
    pub age_s: Option<f64>,
    /// Its last error.
    pub last_error: Option<String>,
}

/// A component in `status`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ComponentStatus {
    /// Its name.
    pub name: String,
    /// Its state.
    pub state: TaskState,
    /// Steps run.
    pub steps: u64,
    /// Overruns.
    pub overruns: u64,
    /// False while its activity overruns more than it may.
    pub healthy: bool,
    /// Times its activity turned unhealthy (more overruns in a row than it may).
    #[serde(default)]
    pub unhealthy_spells: u64,
    /// Time its activity spent unhealthy, ns (the spell on now included).
    #[serde(default)]
    pub unhealthy_ns: u64,
    /// True when its thread got real-time scheduling.
    pub realtime: bool,
    /// 99th percentile of wake-up lateness, µs.
    pub lateness_p99_us: f64,
    /// Mean step duration, µs.
    pub step_mean_us: f64,
    /// Wake-up lateness histogram: bucket `i` counts wake-ups `2^i..2^(i+1)` ns late (the
    /// last bucket everything beyond), up to the last one that counted any.
    #[serde(default)]
    pub lateness_histogram: Vec<u64>,
    /// Sum of the wake-ups' lateness, ns.
    #[serde(default)]
    pub lateness_total_ns: u64,
    /// Step duration histogram, bucketed as `lateness_histogram`.
    #[serde(default)]
    pub step_histogram: Vec<u64>,
    /// Time spent in steps, ns.
    #[serde(default)]
    pub step_total_ns: u64,
    /// Error counters.
    pub counters: TaskCounters,
}

/// The answer to `status`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StatusReport {
    /// `ok`, or what is wrong (what the systemd watchdog is fed by).
    pub health: String,
    /// Every device (aliases left out).
    pub devices: Vec<DeviceStatus>,
    /// Every card's bus and counters.
    pub cards: Vec<CardReport>,
    /// Every server's (the Modbus server's) address, state and counters.
    #[serde(default)]
    pub servers: Vec<ServerReport>,
    /// Every component.
    pub components: Vec<ComponentStatus>,
    /// The control server.
    #[serde(default)]
    pub control: ControlReport,
}

/// The answer to `devices`.
pub type DeviceList = Vec<RegistryEntry>;

/// A reply's body: its `ok` value, or its error's kind and message (a reply of another
/// gateway is not trusted to be well formed: what is missing is `Failed` and empty).
pub fn reply_body(mut reply: Value) -> Result<Value, (ErrorKind, String)> {
    if let Some(ok) = reply.get_mut("ok") {
        return Ok(ok.take());
    }
    let kind = serde_json::from_value(reply["error"]["kind"].clone()).unwrap_or(ErrorKind::Failed);
    let message = reply["error"]["message"].as_str().unwrap_or("").to_string();
    Err((kind, message))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// A request of each documented command, as a client would send it.
    fn sample(cmd: &str) -> Value {
        match cmd {
            "ls" | "devices" | "status" | "reload" | "changes" | "deployment" => {
                json!({"cmd": cmd})
            }
            "load" => json!({"cmd": cmd, "component": {"name": "c", "type": "follow"}}),
            "connect" => json!({"cmd": cmd, "from": "a.out", "to": "b.in"}),
            "disconnect" => json!({"cmd": cmd, "connection": 3}),
            "load_properties" => json!({"cmd": cmd, "component": "c", "properties": {"gain": 1.0}}),
            "set_period" => json!({"cmd": cmd, "component": "c", "period_ms": 5.0}),
            "set_priority" => {
                json!({"cmd": cmd, "component": "c", "policy": "fifo", "priority": 5})
            }
            "get" | "watch" => json!({"cmd": cmd, "component": "c", "port": "p"}),
            "set" => json!({"cmd": cmd, "component": "c", "port": "p", "value": 1}),
            "call" => json!({"cmd": cmd, "component": "c", "operation": "o", "args": [1]}),
            _ => json!({"cmd": cmd, "component": "c"}),
        }
    }

    #[test]
    fn every_command_parses_and_names_itself() {
        let mut seen = std::collections::BTreeSet::new();
        for c in COMMANDS {
            let r: Request =
                serde_json::from_value(sample(c.cmd)).unwrap_or_else(|e| panic!("{}: {e}", c.cmd));
            assert_eq!(r.cmd(), c.cmd);
            assert!(seen.insert(c.cmd), "{} twice", c.cmd);
        }
    }

    #[test]
    fn replies_keep_their_wire_format() {
        let ok = Reply {
            id: json!(7),
            body: Body::Ok(json!(2.5)),
        };
        assert_eq!(
            serde_json::to_value(&ok).unwrap(),
            json!({"id": 7, "ok": 2.5})
        );
        let e = Reply::error(json!(1), ErrorKind::NotFound, "no");
        assert_eq!(
            serde_json::to_value(&e).unwrap(),
            json!({"id": 1, "error": {"kind": "not_found", "message": "no"}})
        );
        let back: Reply = serde_json::from_value(
            json!({"id": 1, "error": {"kind": "not_found", "message": "no"}}),
        )
        .unwrap();
        assert_eq!(back, e);
        let get: Request =
            serde_json::from_value(json!({"cmd": "get", "component": "a", "property": "gain"}))
                .unwrap();
        assert_eq!(
            get,
            Request::Get {
                component: "a".into(),
                target: Target::Property("gain".into())
            }
        );
    }
}
