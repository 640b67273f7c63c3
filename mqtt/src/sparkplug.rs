//! Sparkplug B messages: the payload types generated from `proto/sparkplug_b.proto`, the
//! topics, and the births, data, deaths and commands of an edge node (Sparkplug 3.0).
//!
//! A metric is named in its birth (`ai/ch0`) with an alias, its datatype and the
//! properties hosts show — `engUnit`, `engLow`, `engHigh` from the channel's scale, and
//! `readOnly` — and is sent by alias alone afterwards. Integers travel as the
//! specification says: an Int64 in `long_value` as its two's complement.

use crate::model::{DataType, Group, Kind, Metric, Value};
use prost::Message;

use crate::pb;
use pb::payload::{self, metric, property_value};

/// Sparkplug B's topic namespace.
pub const NAMESPACE: &str = "spBv1.0";
/// The node's rebirth request metric.
pub const REBIRTH: &str = "Node Control/Rebirth";
/// The session's birth/death sequence number metric.
pub const BD_SEQ: &str = "bdSeq";
/// The node's count of refused commands.
pub const REFUSED: &str = "hwgw/Commands Refused";
/// The node's last refusal, what and why.
pub const LAST_REFUSAL: &str = "hwgw/Last Refusal";

/// Aliases of the node's own metrics (the channels' start at 1 and stay below these).
const ALIAS_REBIRTH: u64 = u64::MAX - 1;
const ALIAS_REFUSED: u64 = u64::MAX - 2;
const ALIAS_LAST_REFUSAL: u64 = u64::MAX - 3;

/// The topics of edge node `node` in group `group`.
#[derive(Debug, Clone)]
pub struct Topics {
    group: String,
    node: String,
}

impl Topics {
    /// The topics of `node` in `group`.
    pub fn new(group: &str, node: &str) -> Topics {
        Topics {
            group: group.into(),
            node: node.into(),
        }
    }

    /// A node message's topic (`NBIRTH`, `NDEATH`, `NDATA`, `NCMD`).
    pub fn node(&self, kind: &str) -> String {
        format!("{NAMESPACE}/{}/{kind}/{}", self.group, self.node)
    }

    /// A device message's topic (`DBIRTH`, `DDEATH`, `DDATA`, `DCMD`).
    pub fn device(&self, kind: &str, device: &str) -> String {
        format!("{NAMESPACE}/{}/{kind}/{}/{device}", self.group, self.node)
    }

    /// The primary host application's STATE topic.
    pub fn state(host: &str) -> String {
        format!("{NAMESPACE}/STATE/{host}")
    }

    /// The device of a DCMD topic of this node, if it is one.
    pub fn dcmd_device<'a>(&self, topic: &'a str) -> Option<&'a str> {
        let prefix = format!("{NAMESPACE}/{}/DCMD/{}/", self.group, self.node);
        topic.strip_prefix(&prefix).filter(|d| !d.contains('/'))
    }
}

/// Milliseconds since the UNIX epoch.
pub fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

fn encode(timestamp: u64, seq: Option<u8>, metrics: Vec<payload::Metric>) -> Vec<u8> {
    pb::Payload {
        timestamp: Some(timestamp),
        metrics,
        seq: seq.map(u64::from),
        ..Default::default()
    }
    .encode_to_vec()
}

fn value(v: Value) -> metric::Value {
    match v {
        Value::F64(f) => metric::Value::DoubleValue(f),
        Value::Bool(b) => metric::Value::BooleanValue(b),
        Value::I64(i) => metric::Value::LongValue(i as u64),
    }
}

fn simple(name: &str, alias: u64, datatype: DataType, v: metric::Value, t: u64) -> payload::Metric {
    payload::Metric {
        name: Some(name.into()),
        alias: Some(alias),
        timestamp: Some(t),
        datatype: Some(datatype as u32),
        value: Some(v),
        ..Default::default()
    }
}

/// The NDEATH of session `bd_seq` (the MQTT will; also sent when hwgw leaves).
pub fn ndeath(bd_seq: u8) -> Vec<u8> {
    let t = now_ms();
    let bd = simple(
        BD_SEQ,
        0,
        DataType::Int64,
        metric::Value::LongValue(bd_seq.into()),
        t,
    );
    encode(t, None, vec![payload::Metric { alias: None, ..bd }])
}

/// The NBIRTH of session `bd_seq` (seq 0): `bdSeq`, the rebirth control, the refusal
/// counters.
pub fn nbirth(bd_seq: u8, refused: u64, last_refusal: &str) -> Vec<u8> {
    let t = now_ms();
    let bd = simple(
        BD_SEQ,
        0,
        DataType::Int64,
        metric::Value::LongValue(bd_seq.into()),
        t,
    );
    let metrics = vec![
        payload::Metric { alias: None, ..bd },
        simple(
            REBIRTH,
            ALIAS_REBIRTH,
            DataType::Boolean,
            metric::Value::BooleanValue(false),
            t,
        ),
        simple(
            REFUSED,
            ALIAS_REFUSED,
            DataType::UInt64,
            metric::Value::LongValue(refused),
            t,
        ),
        simple(
            LAST_REFUSAL,
            ALIAS_LAST_REFUSAL,
            DataType::String,
            metric::Value::StringValue(last_refusal.into()),
            t,
        ),
    ];
    encode(t, Some(0), metrics)
}

/// An NDATA of the refusal counters.
pub fn ndata_refusal(seq: u8, refused: u64, last_refusal: &str) -> Vec<u8> {
    let t = now_ms();
    let metrics = vec![
        payload::Metric {
            alias: Some(ALIAS_REFUSED),
            timestamp: Some(t),
            datatype: Some(DataType::UInt64 as u32),
            value: Some(metric::Value::LongValue(refused)),
            ..Default::default()
        },
        payload::Metric {
            alias: Some(ALIAS_LAST_REFUSAL),
            timestamp: Some(t),
            datatype: Some(DataType::String as u32),
            value: Some(metric::Value::StringValue(last_refusal.into())),
            ..Default::default()
        },
    ];
    encode(t, Some(seq), metrics)
}

fn property(key: &str, v: property_value::Value, t: DataType) -> (String, payload::PropertyValue) {
    (
        key.into(),
        payload::PropertyValue {
            r#type: Some(t as u32),
            is_null: None,
            value: Some(v),
        },
    )
}

/// A channel's properties: unit and range from its scale, and whether hosts may write it.
fn properties(m: &Metric, writes: bool) -> payload::PropertySet {
    let mut p = Vec::new();
    if let Some(r) = &m.range {
        if !r.unit.as_str().is_empty() {
            let unit = property_value::Value::StringValue(r.unit.as_str().into());
            p.push(property("engUnit", unit, DataType::String));
        }
        p.push(property(
            "engLow",
            property_value::Value::DoubleValue(r.lowest),
            DataType::Double,
        ));
        p.push(property(
            "engHigh",
            property_value::Value::DoubleValue(r.highest),
            DataType::Double,
        ));
    }
    let read_only = !(m.kind != Kind::Input && writes);
    p.push(property(
        "readOnly",
        property_value::Value::BooleanValue(read_only),
        DataType::Boolean,
    ));
    let (keys, values) = p.into_iter().unzip();
    payload::PropertySet { keys, values }
}

/// The DBIRTH of `group` with each metric's value now (`None`: could not be read, sent
/// as null).
pub fn dbirth(seq: u8, group: &Group, values: &[Option<Value>], writes: bool) -> Vec<u8> {
    let t = now_ms();
    let metrics = group
        .metrics
        .iter()
        .zip(values)
        .map(|(m, v)| payload::Metric {
            name: Some(m.name.clone()),
            alias: Some(m.alias),
            timestamp: Some(t),
            datatype: Some(crate::model::datatype(&m.source) as u32),
            is_null: v.is_none().then_some(true),
            properties: Some(properties(m, writes)),
            value: v.map(value),
            ..Default::default()
        })
        .collect();
    encode(t, Some(seq), metrics)
}

/// A DDATA of `changes`: (metric, value, when read in UNIX ms), by alias.
pub fn ddata(seq: u8, changes: &[(&Metric, Value, u64)]) -> Vec<u8> {
    let metrics = changes
        .iter()
        .map(|(m, v, t)| payload::Metric {
            alias: Some(m.alias),
            timestamp: Some(*t),
            datatype: Some(crate::model::datatype(&m.source) as u32),
            value: Some(value(*v)),
            ..Default::default()
        })
        .collect();
    encode(now_ms(), Some(seq), metrics)
}

/// A DDEATH.
pub fn ddeath(seq: u8) -> Vec<u8> {
    encode(now_ms(), Some(seq), Vec::new())
}

/// What an NCMD asks.
#[derive(Debug, PartialEq)]
pub enum NodeCommand {
    /// A rebirth.
    Rebirth,
    /// Nothing hwgw does (another control, or `Rebirth` false).
    Other(String),
}

/// Decodes an NCMD payload.
pub fn ncmd(payload: &[u8]) -> Result<Vec<NodeCommand>, prost::DecodeError> {
    let p = pb::Payload::decode(payload)?;
    Ok(p.metrics
        .iter()
        .map(|m| {
            let rebirth = m.name.as_deref() == Some(REBIRTH) || m.alias == Some(ALIAS_REBIRTH);
            match (&m.value, rebirth) {
                (Some(metric::Value::BooleanValue(true)), true) => NodeCommand::Rebirth,
                _ => NodeCommand::Other(
                    m.name
                        .clone()
                        .unwrap_or_else(|| format!("alias {:?}", m.alias)),
                ),
            }
        })
        .collect())
}

/// One metric a DCMD writes: by name or alias, its value as sent.
#[derive(Debug, Clone, PartialEq)]
pub struct Write {
    /// The metric's name, if given.
    pub name: Option<String>,
    /// The metric's alias, if given.
    pub alias: Option<u64>,
    /// The datatype the host declared.
    pub datatype: Option<u32>,
    /// The value: `None` when null or of a kind hwgw does not write.
    pub value: Option<Value>,
}

/// Decodes a DCMD payload into its writes.
pub fn dcmd(payload: &[u8]) -> Result<Vec<Write>, prost::DecodeError> {
    let p = pb::Payload::decode(payload)?;
    Ok(p.metrics
        .into_iter()
        .map(|m| {
            let value = match (m.value, m.is_null) {
                (_, Some(true)) | (None, _) => None,
                (Some(v), _) => command_value(v, m.datatype),
            };
            Write {
                name: m.name,
                alias: m.alias,
                datatype: m.datatype,
                value,
            }
        })
        .collect())
}

/// A command's value as hwgw writes it: a number as a double (an integer datatype's
/// value sign-extended as the specification's two's complement), a boolean as itself.
fn command_value(v: metric::Value, datatype: Option<u32>) -> Option<Value> {
    let signed = |d: Option<u32>| matches!(d, Some(1..=4));
    Some(match v {
        metric::Value::DoubleValue(f) => Value::F64(f),
        metric::Value::FloatValue(f) => Value::F64(f.into()),
        metric::Value::BooleanValue(b) => Value::Bool(b),
        metric::Value::IntValue(i) if signed(datatype) => Value::I64(i64::from(i as i32)),
        metric::Value::IntValue(i) => Value::I64(i.into()),
        metric::Value::LongValue(l) if signed(datatype) => Value::I64(l as i64),
        metric::Value::LongValue(l) => Value::I64(i64::try_from(l).ok()?),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ndeath_and_nbirth_carry_bd_seq() {
        let d = pb::Payload::decode(ndeath(7).as_slice()).unwrap_or_default();
        assert_eq!(d.seq, None);
        assert_eq!(d.metrics[0].name.as_deref(), Some(BD_SEQ));
        assert_eq!(d.metrics[0].value, Some(metric::Value::LongValue(7)));
        let b = pb::Payload::decode(nbirth(7, 0, "").as_slice()).unwrap_or_default();
        assert_eq!(b.seq, Some(0));
        assert_eq!(b.metrics[0].value, Some(metric::Value::LongValue(7)));
        assert_eq!(b.metrics[1].name.as_deref(), Some(REBIRTH));
    }

    #[test]
    fn commands_decode() {
        let rebirth = simple(
            REBIRTH,
            ALIAS_REBIRTH,
            DataType::Boolean,
            metric::Value::BooleanValue(true),
            1,
        );
        let p = encode(1, None, vec![rebirth]);
        assert_eq!(ncmd(&p).ok(), Some(vec![NodeCommand::Rebirth]));
        let w = payload::Metric {
            name: Some("ao/ch0".into()),
            datatype: Some(4),
            value: Some(metric::Value::LongValue(-3i64 as u64)),
            ..Default::default()
        };
        let d = dcmd(&encode(1, None, vec![w])).unwrap_or_default();
        assert_eq!(d[0].value, Some(Value::I64(-3)));
        assert!(dcmd(&[0xff, 0xff]).is_err());
    }

    #[test]
    fn dcmd_topic() {
        let t = Topics::new("g", "n");
        assert_eq!(t.dcmd_device("spBv1.0/g/DCMD/n/sim0"), Some("sim0"));
        assert_eq!(t.dcmd_device("spBv1.0/g/DCMD/n/a/b"), None);
        assert_eq!(t.dcmd_device("spBv1.0/g/DCMD/m/sim0"), None);
    }
}
