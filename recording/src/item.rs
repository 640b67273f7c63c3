//! What a recording holds: samples of ports and steps of activities, and the JSON
//! messages and schemas they are written as.

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

/// A port to record: `component.port` and its Rust type name (as the runtime lists it).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PortSpec {
    /// `component.port`.
    pub name: String,
    /// The port's data type, e.g. `f64`, `bool`, `u32`.
    pub type_name: String,
}

impl PortSpec {
    /// The MCAP topic: the name with `/` for `.`, so `sim0.ai.ch0` is `/sim0/ai/ch0`
    /// (viewers show topics as a tree).
    pub fn topic(&self) -> String {
        port_topic(&self.name)
    }
}

/// The topic of port `component.port`: `/component/port`, every `.` a `/`.
pub fn port_topic(name: &str) -> String {
    format!("/{}", name.replace('.', "/"))
}

/// One step of an activity, ns on the runtime's monotonic clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Step {
    /// When it was due.
    pub scheduled_ns: u64,
    /// When it began.
    pub started_ns: u64,
    /// When it ended.
    pub ended_ns: u64,
}

/// One thing recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Item {
    /// A sample of port number `port` (its index among the recording's ports), written at
    /// `at_ns` on the runtime's clock.
    Sample {
        /// Index of the port.
        port: u32,
        /// When it was written.
        at_ns: u64,
        /// The value, as the runtime serialises it.
        value: Value,
    },
    /// A step of activity number `activity`.
    Step {
        /// Index of the activity.
        activity: u32,
        /// Its times.
        step: Step,
    },
}

impl Item {
    /// The time the item belongs at: a sample's write, a step's start.
    pub fn time_ns(&self) -> u64 {
        match self {
            Item::Sample { at_ns, .. } => *at_ns,
            Item::Step { step, .. } => step.started_ns,
        }
    }
}

/// The topic of activity `name`'s steps: `/activity/<name>`.
pub fn activity_topic(name: &str) -> String {
    format!("/activity/{name}")
}

/// The name of the schema of a port of type `type_name`: `hwgw.sample.<type>`.
pub fn sample_schema_name(type_name: &str) -> String {
    format!("hwgw.sample.{type_name}")
}

/// The name of the schema of an activity's steps.
pub const STEP_SCHEMA: &str = "hwgw.step";

/// A sample's message: `{"value": …}`.
#[derive(Serialize)]
pub struct SampleMessage<'a> {
    /// The value, as the runtime serialises it.
    pub value: &'a Value,
}

/// A step's message.
#[derive(Serialize, Deserialize)]
pub struct StepMessage {
    /// When it was due, ns on the runtime's clock.
    pub scheduled_ns: u64,
    /// When it began.
    pub started_ns: u64,
    /// When it ended.
    pub ended_ns: u64,
    /// How late it began, µs.
    pub lateness_us: f64,
    /// How long it took, µs.
    pub duration_us: f64,
}

impl From<&Step> for StepMessage {
    fn from(s: &Step) -> Self {
        StepMessage {
            scheduled_ns: s.scheduled_ns,
            started_ns: s.started_ns,
            ended_ns: s.ended_ns,
            lateness_us: s.started_ns.saturating_sub(s.scheduled_ns) as f64 / 1e3,
            duration_us: s.ended_ns.saturating_sub(s.started_ns) as f64 / 1e3,
        }
    }
}

/// The JSON schema of a value of type `type_name` (the control protocol's name,
/// `rtt::typename`; Rust's spelling of a string is taken too). A float may also be the string
/// `"NaN"`, `"inf"` or `"-inf"` (JSON has no such numbers); a type not known here is left
/// unconstrained.
pub fn value_schema(type_name: &str) -> Value {
    match type_name {
        "f32" | "f64" => json!({"type": ["number", "string"]}),
        "bool" => json!({"type": "boolean"}),
        "i8" | "i16" | "i32" | "i64" | "isize" | "u8" | "u16" | "u32" | "u64" | "usize" => {
            json!({"type": "integer"})
        }
        "char" | "string" | "alloc::string::String" | "String" => json!({"type": "string"}),
        _ => json!({}),
    }
}

/// The schema of a port's messages.
pub fn sample_schema(type_name: &str) -> Value {
    json!({
        "title": format!("hwgw sample of {type_name}"),
        "type": "object",
        "properties": {"value": value_schema(type_name)},
        "required": ["value"],
    })
}

/// The schema of an activity's messages.
pub fn step_schema() -> Value {
    let int = json!({"type": "integer", "minimum": 0});
    let num = json!({"type": "number", "minimum": 0});
    json!({
        "title": "hwgw activity step",
        "type": "object",
        "properties": {
            "scheduled_ns": int, "started_ns": int, "ended_ns": int,
            "lateness_us": num, "duration_us": num,
        },
        "required": ["scheduled_ns", "started_ns", "ended_ns", "lateness_us", "duration_us"],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_split_the_component_from_the_port() {
        let p = |n: &str| PortSpec {
            name: n.into(),
            type_name: "f64".into(),
        };
        assert_eq!(p("sim0.ai.ch0").topic(), "/sim0/ai/ch0");
        assert_eq!(p("follow.out").topic(), "/follow/out");
    }

    #[test]
    fn a_step_message_says_how_late_and_how_long() {
        let m = StepMessage::from(&Step {
            scheduled_ns: 1_000,
            started_ns: 3_500,
            ended_ns: 13_500,
        });
        assert_eq!((m.lateness_us, m.duration_us), (2.5, 10.0));
    }
}
