//! The Foxglove WebSocket protocol's messages as hwgw speaks them (`foxglove.websocket.v1`,
//! from its published specification): the server's JSON operations, the binary message
//! data frame, and what a client may send.

use serde::Deserialize;
use serde_json::{Value, json};

/// The subprotocols a client may ask for: the specification's name, and the Foxglove
/// SDK's name for the same wire format.
pub const SUBPROTOCOLS: [&str; 2] = ["foxglove.websocket.v1", "foxglove.sdk.v1"];

/// The binary opcode of message data, both ways.
pub const MESSAGE_DATA: u8 = 0x01;

/// A channel the server advertises.
#[derive(Debug, Clone, PartialEq)]
pub struct Channel {
    /// Its id, unique within the server's life.
    pub id: u32,
    /// Its topic, as `hwgw record` names its MCAP channel.
    pub topic: String,
    /// Its schema's name (`hwgw.sample.f64`, `hwgw.step`).
    pub schema_name: String,
    /// Its JSON Schema, as text.
    pub schema: String,
}

/// `serverInfo`.
pub fn server_info(name: &str, publish: bool, session: &str) -> String {
    let capabilities: Vec<&str> = if publish {
        vec!["clientPublish"]
    } else {
        vec![]
    };
    json!({
        "op": "serverInfo",
        "name": name,
        "capabilities": capabilities,
        "supportedEncodings": ["json"],
        "metadata": {},
        "sessionId": session,
    })
    .to_string()
}

/// `advertise` of `channels`.
pub fn advertise<'a>(channels: impl IntoIterator<Item = &'a Channel>) -> String {
    let list: Vec<Value> = channels
        .into_iter()
        .map(|c| {
            json!({
                "id": c.id,
                "topic": c.topic,
                "encoding": "json",
                "schemaName": c.schema_name,
                "schema": c.schema,
                "schemaEncoding": "jsonschema",
            })
        })
        .collect();
    json!({"op": "advertise", "channels": list}).to_string()
}

/// `unadvertise` of channels `ids`.
pub fn unadvertise(ids: &[u32]) -> String {
    json!({"op": "unadvertise", "channelIds": ids}).to_string()
}

/// How grave a status message is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Level {
    /// Information.
    Info = 0,
    /// A warning.
    Warning = 1,
    /// An error.
    Error = 2,
}

/// `status`.
pub fn status(level: Level, message: &str) -> String {
    json!({"op": "status", "level": level as u8, "message": message}).to_string()
}

/// A message data frame of subscription `subscription`, logged at `time_ns` (UNIX ns).
pub fn message_data(subscription: u32, time_ns: u64, payload: &[u8]) -> Vec<u8> {
    let mut frame = Vec::with_capacity(13 + payload.len());
    frame.push(MESSAGE_DATA);
    frame.extend_from_slice(&subscription.to_le_bytes());
    frame.extend_from_slice(&time_ns.to_le_bytes());
    frame.extend_from_slice(payload);
    frame
}

/// A client's JSON operation.
#[derive(Debug, Deserialize)]
#[serde(tag = "op", rename_all = "camelCase")]
pub enum ClientOp {
    /// Subscriptions to server channels.
    Subscribe {
        /// Each: the client's id for it, and the channel.
        subscriptions: Vec<Subscription>,
    },
    /// Subscriptions ended.
    Unsubscribe {
        /// The client's ids of them.
        #[serde(rename = "subscriptionIds")]
        subscription_ids: Vec<u32>,
    },
    /// Channels the client will publish on.
    Advertise {
        /// Its channels.
        channels: Vec<ClientChannel>,
    },
    /// Client channels ended.
    Unadvertise {
        /// Their ids.
        #[serde(rename = "channelIds")]
        channel_ids: Vec<u32>,
    },
}

/// One subscription.
#[derive(Debug, Deserialize)]
pub struct Subscription {
    /// The client's id for it.
    pub id: u32,
    /// The server channel.
    #[serde(rename = "channelId")]
    pub channel_id: u32,
}

/// A channel a client publishes on.
#[derive(Debug, Clone, Deserialize)]
pub struct ClientChannel {
    /// The client's id for it.
    pub id: u32,
    /// Its topic: a port's (`/sim0/ao/ch1`).
    pub topic: String,
    /// Its encoding: hwgw takes `json`.
    pub encoding: String,
}

/// A client's binary message data: (its channel, payload); `None` when the frame is not
/// one.
pub fn client_message(frame: &[u8]) -> Option<(u32, &[u8])> {
    let (&op, rest) = frame.split_first()?;
    if op != MESSAGE_DATA || rest.len() < 4 {
        return None;
    }
    let (id, payload) = rest.split_at(4);
    Some((u32::from_le_bytes(id.try_into().ok()?), payload))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_little_endian_after_their_opcode() {
        let f = message_data(0x0102_0304, 0x0A0B_0C0D_0E0F_1011, b"{}");
        assert_eq!(f[0], 1);
        assert_eq!(&f[1..5], &[4, 3, 2, 1]);
        assert_eq!(&f[5..13], &[0x11, 0x10, 0x0F, 0x0E, 0x0D, 0x0C, 0x0B, 0x0A]);
        assert_eq!(&f[13..], b"{}");
        let mut c = vec![1, 7, 0, 0, 0];
        c.extend_from_slice(b"{\"value\":1}");
        assert_eq!(client_message(&c), Some((7, &b"{\"value\":1}"[..])));
        assert_eq!(client_message(&[1, 0, 0]), None);
        assert_eq!(client_message(&[2, 0, 0, 0, 0]), None);
    }

    #[test]
    fn client_operations_parse_as_the_specification_writes_them() {
        let s: ClientOp =
            serde_json::from_str(r#"{"op":"subscribe","subscriptions":[{"id":0,"channelId":3}]}"#)
                .unwrap();
        assert!(
            matches!(s, ClientOp::Subscribe { subscriptions } if subscriptions[0].channel_id == 3)
        );
        let u: ClientOp =
            serde_json::from_str(r#"{"op":"unsubscribe","subscriptionIds":[0]}"#).unwrap();
        assert!(matches!(u, ClientOp::Unsubscribe { .. }));
    }
}
