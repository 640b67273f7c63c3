//! The connection to the broker, MQTT 3.1.1 or 5 (rumqttc's two clients behind one
//! face), over TCP or TLS (rustls with the ring provider: the CA, and a client
//! certificate and key, from files).
//!
//! A session is one connection: a new client and event loop each time, so nothing queued
//! for a connection that broke is sent on the next (a Sparkplug session begins with its
//! NBIRTH, never with an old DDATA).

use crate::config::{Settings, TlsFiles, Version};
use bytes::Bytes;
use rumqttc::v5::mqttbytes::v5 as v5b;
use std::sync::Arc;

/// Why a TLS configuration could not be made.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A file could not be read or holds no PEM of its kind.
    #[error("{path}: {why}")]
    File {
        /// The file.
        path: String,
        /// What is wrong.
        why: String,
    },
    /// rustls refused the certificates or key.
    #[error("TLS: {0}")]
    Rustls(#[from] rustls::Error),
}

/// A rustls client configuration from `files`.
pub fn tls(files: &TlsFiles) -> Result<Arc<rustls::ClientConfig>, TlsError> {
    use rustls_pki_types::pem::PemObject;
    use rustls_pki_types::{CertificateDer, PrivateKeyDer};
    let file = |p: &std::path::Path, why: String| TlsError::File {
        path: p.display().to_string(),
        why,
    };
    let certs = |p: &std::path::Path| -> Result<Vec<CertificateDer<'static>>, TlsError> {
        let c: Vec<_> = CertificateDer::pem_file_iter(p)
            .map_err(|e| file(p, e.to_string()))?
            .collect::<Result<_, _>>()
            .map_err(|e| file(p, e.to_string()))?;
        if c.is_empty() {
            return Err(file(p, "no PEM certificate in it".into()));
        }
        Ok(c)
    };
    let mut roots = rustls::RootCertStore::empty();
    for c in certs(&files.ca)? {
        roots.add(c)?;
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()?
        .with_root_certificates(roots);
    let config = match &files.client {
        None => builder.with_no_client_auth(),
        Some((cert, key)) => {
            let key = PrivateKeyDer::from_pem_file(key).map_err(|e| file(key, e.to_string()))?;
            builder.with_client_auth_cert(certs(cert)?, key)?
        }
    };
    Ok(Arc::new(config))
}

/// What a session's connection is told at connect.
pub struct Will {
    /// Its topic.
    pub topic: String,
    /// Its payload.
    pub payload: Vec<u8>,
    /// Published with QoS 1 and retained.
    pub retain: bool,
}

/// Largest message hwgw sends (an NBIRTH of many channels) and takes: what comes is
/// commands and STATE, small; MQTT 5 tells the broker, which then keeps bigger ones
/// from hwgw (with 3.1.1 a bigger one ends the connection: see docs/mqtt.md).
const MAX_OUT: usize = 64 << 20;
const MAX_IN: usize = 256 << 10;

/// Why a session's connection ended.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// MQTT 3.1.1's client said why.
    #[error(transparent)]
    V4(#[from] rumqttc::ConnectionError),
    /// MQTT 5's client said why.
    #[error(transparent)]
    V5(#[from] rumqttc::v5::ConnectionError),
}

/// A session's client: where messages are queued.
#[derive(Clone)]
pub enum Client {
    /// MQTT 3.1.1.
    V4(rumqttc::AsyncClient),
    /// MQTT 5.
    V5(rumqttc::v5::AsyncClient),
}

/// A session's event loop: what carries the messages.
pub enum Events {
    /// MQTT 3.1.1.
    V4(Box<rumqttc::EventLoop>),
    /// MQTT 5.
    V5(Box<rumqttc::v5::EventLoop>),
}

/// What the event loop saw.
#[derive(Debug)]
pub enum Seen {
    /// The broker took the connection.
    Connected,
    /// A message came: its topic, payload, and whether it was retained (a broker sends
    /// the retained message of a topic to every new subscriber).
    Message(String, Bytes, bool),
    /// A message went out to the broker.
    Published,
    /// A subscription was acknowledged; how many of its topics the broker refused.
    Subscribed(usize),
    /// Anything else.
    Other,
}

/// A new session's client and event loop, its will registered.
pub fn session(
    s: &Settings,
    tls: Option<&Arc<rustls::ClientConfig>>,
    will: Option<Will>,
) -> (Client, Events) {
    let transport = || match tls {
        Some(c) => {
            rumqttc::Transport::tls_with_config(rumqttc::TlsConfiguration::Rustls(c.clone()))
        }
        None => rumqttc::Transport::tcp(),
    };
    match s.version {
        Version::V311 => {
            let mut o = rumqttc::MqttOptions::new(&s.client_id, &s.host, s.port);
            o.set_keep_alive(s.keep_alive)
                .set_clean_session(true)
                .set_max_packet_size(MAX_IN, MAX_OUT)
                .set_transport(transport());
            if let Some((u, p)) = &s.credentials {
                o.set_credentials(u, p);
            }
            if let Some(w) = will {
                o.set_last_will(rumqttc::LastWill::new(
                    w.topic,
                    w.payload,
                    rumqttc::QoS::AtLeastOnce,
                    w.retain,
                ));
            }
            let (c, e) = rumqttc::AsyncClient::new(o, s.queue);
            (Client::V4(c), Events::V4(Box::new(e)))
        }
        Version::V5 => {
            let mut o = rumqttc::v5::MqttOptions::new(&s.client_id, &s.host, s.port);
            o.set_keep_alive(s.keep_alive)
                .set_clean_start(true)
                .set_max_packet_size(Some(MAX_IN as u32))
                .set_transport(transport());
            if let Some((u, p)) = &s.credentials {
                o.set_credentials(u, p);
            }
            if let Some(w) = will {
                o.set_last_will(v5b::LastWill::new(
                    w.topic,
                    w.payload,
                    rumqttc::v5::mqttbytes::QoS::AtLeastOnce,
                    w.retain,
                    None,
                ));
            }
            let (c, e) = rumqttc::v5::AsyncClient::new(o, s.queue);
            (Client::V5(c), Events::V5(Box::new(e)))
        }
    }
}

impl Client {
    /// Queues a message (QoS 1 when `qos1`, else 0); false when the queue is full or the
    /// session is over.
    fn publish(&self, topic: String, qos1: bool, retain: bool, payload: Vec<u8>) -> bool {
        match self {
            Client::V4(c) => {
                let q = if qos1 {
                    rumqttc::QoS::AtLeastOnce
                } else {
                    rumqttc::QoS::AtMostOnce
                };
                c.try_publish(topic, q, retain, payload).is_ok()
            }
            Client::V5(c) => {
                let q = if qos1 {
                    rumqttc::v5::mqttbytes::QoS::AtLeastOnce
                } else {
                    rumqttc::v5::mqttbytes::QoS::AtMostOnce
                };
                c.try_publish(topic, q, retain, payload).is_ok()
            }
        }
    }

    /// Subscribes to `topics` with QoS 1; false when the session is over.
    pub fn subscribe(&self, topics: &[String]) -> bool {
        if topics.is_empty() {
            return true;
        }
        match self {
            Client::V4(c) => c
                .try_subscribe_many(
                    topics.iter().map(|t| {
                        rumqttc::SubscribeFilter::new(t.clone(), rumqttc::QoS::AtLeastOnce)
                    }),
                )
                .is_ok(),
            Client::V5(c) => c
                .try_subscribe_many(
                    topics.iter().map(|t| {
                        v5b::Filter::new(t.clone(), rumqttc::v5::mqttbytes::QoS::AtLeastOnce)
                    }),
                )
                .is_ok(),
        }
    }

    /// Asks for a clean disconnect (no will) once what is queued is sent.
    pub fn disconnect(&self) {
        let _ = match self {
            Client::V4(c) => c.try_disconnect().is_ok(),
            Client::V5(c) => c.try_disconnect().is_ok(),
        };
    }
}

/// Events of a session's connection, from the task that runs its event loop.
pub type Seeing = tokio::sync::mpsc::Receiver<Result<Seen, LinkError>>;

impl Events {
    /// Runs the event loop on a task of its own (polled without pause, so no write is
    /// ever cut off halfway), each event sent to the returned receiver, the error that
    /// ends the connection last; abort the task to drop the connection.
    pub fn spawn(mut self) -> (Seeing, tokio::task::JoinHandle<()>) {
        let (tx, rx) = tokio::sync::mpsc::channel(256);
        let task = tokio::spawn(async move {
            loop {
                let r = self.poll().await;
                let end = r.is_err();
                if tx.send(r).await.is_err() || end {
                    break;
                }
            }
        });
        (rx, task)
    }

    async fn poll(&mut self) -> Result<Seen, LinkError> {
        match self {
            Events::V4(e) => {
                use rumqttc::{Event, Outgoing, Packet, SubscribeReasonCode};
                Ok(match e.poll().await? {
                    Event::Incoming(Packet::ConnAck(_)) => Seen::Connected,
                    Event::Incoming(Packet::Publish(p)) => {
                        Seen::Message(p.topic, p.payload, p.retain)
                    }
                    Event::Incoming(Packet::SubAck(a)) => Seen::Subscribed(
                        a.return_codes
                            .iter()
                            .filter(|c| matches!(c, SubscribeReasonCode::Failure))
                            .count(),
                    ),
                    Event::Outgoing(Outgoing::Publish(_)) => Seen::Published,
                    _ => Seen::Other,
                })
            }
            Events::V5(e) => {
                use rumqttc::v5::Event;
                use rumqttc::{Outgoing, v5::mqttbytes::v5::Packet};
                Ok(match e.poll().await? {
                    Event::Incoming(Packet::ConnAck(_)) => Seen::Connected,
                    Event::Incoming(Packet::Publish(p)) => Seen::Message(
                        String::from_utf8_lossy(&p.topic).into_owned(),
                        p.payload,
                        p.retain,
                    ),
                    Event::Incoming(Packet::SubAck(a)) => Seen::Subscribed(
                        a.return_codes
                            .iter()
                            .filter(|c| !matches!(c, v5b::SubscribeReasonCode::Success(_)))
                            .count(),
                    ),
                    Event::Outgoing(Outgoing::Publish(_)) => Seen::Published,
                    _ => Seen::Other,
                })
            }
        }
    }
}

/// A session's client with its queue bounded in bytes as well as in messages: a message
/// is queued when the queue is empty or the bytes under way stay within the budget, so a
/// slow broker holds at most the budget (and one message), never minutes of old data.
pub struct Outbox {
    client: Client,
    sizes: std::collections::VecDeque<usize>,
    bytes: usize,
    budget: usize,
}

impl Outbox {
    /// `client`'s outbox with `budget` bytes.
    pub fn new(client: Client, budget: usize) -> Outbox {
        Outbox {
            client,
            sizes: Default::default(),
            bytes: 0,
            budget,
        }
    }

    /// The client.
    pub fn client(&self) -> &Client {
        &self.client
    }

    /// Queues a message; false when it does not fit (the budget, or the client's queue).
    pub fn publish(&mut self, topic: String, qos1: bool, retain: bool, payload: Vec<u8>) -> bool {
        let size = topic.len() + payload.len();
        if self.bytes > 0 && self.bytes + size > self.budget {
            return false;
        }
        self.publish_now(topic, qos1, retain, payload)
    }

    /// Queues a message whatever the budget (births and deaths: bounded in size, and
    /// what a host must have); false when the client's queue is full.
    pub fn publish_now(
        &mut self,
        topic: String,
        qos1: bool,
        retain: bool,
        payload: Vec<u8>,
    ) -> bool {
        let size = topic.len() + payload.len();
        if !self.client.publish(topic, qos1, retain, payload) {
            return false;
        }
        self.sizes.push_back(size);
        self.bytes += size;
        true
    }

    /// A message went out (the oldest queued: they go in order).
    pub fn published(&mut self) {
        if let Some(size) = self.sizes.pop_front() {
            self.bytes -= size;
        }
    }
}
