//! The client side of the control socket: one typed request and its reply, or a stream of
//! watched values, never waiting without a limit for a reply.

use crate::protocol::{Body, Description, ErrorBody, Reply, Request, Target};
use serde::de::DeserializeOwned;
use serde_json::Value;
use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// How long a client waits for a reply unless told otherwise.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(10);

/// Why a request got no answer.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The socket is not one to trust.
    #[error(transparent)]
    Untrusted(#[from] crate::socket::SocketError),
    /// The socket could not be reached.
    #[error("{path}: {source} (is hwgw running? `hwgw run` starts it)")]
    Connect {
        /// The socket.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// No reply within the timeout.
    #[error("{path}: no reply within {after:?}")]
    Timeout {
        /// The socket.
        path: PathBuf,
        /// The timeout.
        after: Duration,
    },
    /// The connection failed mid-way.
    #[error("{path}: {source}")]
    Io {
        /// The socket.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The reply was not a reply.
    #[error("{path}: unexpected reply: {detail}")]
    BadReply {
        /// The socket.
        path: PathBuf,
        /// What was wrong with it.
        detail: String,
    },
    /// The gateway answered with an error.
    #[error("{}", .0.message)]
    Refused(ErrorBody),
    /// The operation ran and answered with an error of its own (`{"Err": …}`).
    #[error("{operation}: {message}")]
    Operation {
        /// `component.operation`.
        operation: String,
        /// Its error.
        message: String,
    },
}

/// A client of one gateway's control socket.
#[derive(Debug, Clone)]
pub struct Client {
    path: PathBuf,
    timeout: Duration,
}

impl Client {
    /// A client of the socket at `path`, waiting [`DEFAULT_TIMEOUT`] for replies.
    pub fn new(path: impl Into<PathBuf>) -> Client {
        Client {
            path: path.into(),
            timeout: DEFAULT_TIMEOUT,
        }
    }

    /// The same client waiting `timeout` for replies.
    pub fn with_timeout(mut self, timeout: Duration) -> Client {
        self.timeout = timeout;
        self
    }

    /// How long it waits for a reply.
    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    /// The socket.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn io(&self, source: std::io::Error) -> ClientError {
        if matches!(
            source.kind(),
            std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
        ) {
            ClientError::Timeout {
                path: self.path.clone(),
                after: self.timeout,
            }
        } else {
            ClientError::Io {
                path: self.path.clone(),
                source,
            }
        }
    }

    /// Connects and sends `req`; the reading half comes back.
    fn send(&self, req: &Request) -> Result<BufReader<UnixStream>, ClientError> {
        crate::socket::check_owner(&self.path)?;
        let mut conn = UnixStream::connect(&self.path).map_err(|source| ClientError::Connect {
            path: self.path.clone(),
            source,
        })?;
        crate::socket::check_peer(&self.path, &conn)?;
        conn.set_read_timeout(Some(self.timeout))
            .and_then(|()| conn.set_write_timeout(Some(self.timeout)))
            .map_err(|e| self.io(e))?;
        let mut v = serde_json::to_value(req).map_err(|e| self.bad(e))?;
        if let Value::Object(m) = &mut v {
            m.insert("id".into(), Value::from(1));
        }
        let mut line = v.to_string();
        line.push('\n');
        conn.write_all(line.as_bytes()).map_err(|e| self.io(e))?;
        Ok(BufReader::new(conn))
    }

    fn bad(&self, detail: impl std::fmt::Display) -> ClientError {
        ClientError::BadReply {
            path: self.path.clone(),
            detail: detail.to_string(),
        }
    }

    /// Reads one reply line.
    fn reply(&self, r: &mut BufReader<UnixStream>) -> Result<Reply, ClientError> {
        let mut line = String::new();
        let n = r.read_line(&mut line).map_err(|e| self.io(e))?;
        if n == 0 {
            return Err(self.bad("the gateway closed the connection"));
        }
        serde_json::from_str(&line).map_err(|e| self.bad(format!("{e}: {}", line.trim())))
    }

    /// Sends `req` and returns the reply's `ok` value.
    pub fn request(&self, req: &Request) -> Result<Value, ClientError> {
        let mut r = self.send(req)?;
        match self.reply(&mut r)?.body {
            Body::Ok(v) => Ok(v),
            Body::Error(e) => Err(ClientError::Refused(e)),
            Body::Event(_) | Body::Records(_) | Body::Heartbeat(_) => {
                Err(self.bad("a stream where a reply was due"))
            }
        }
    }

    /// Sends `req` and returns the reply's `ok` value as `T`.
    pub fn typed<T: DeserializeOwned>(&self, req: &Request) -> Result<T, ClientError> {
        let v = self.request(req)?;
        serde_json::from_value(v).map_err(|e| self.bad(e))
    }

    /// Sends a streaming request: its acknowledgement (within the timeout), and the
    /// stream of what follows.
    pub fn stream(&self, req: &Request) -> Result<(Value, Stream), ClientError> {
        let mut r = self.send(req)?;
        let ack = match self.reply(&mut r)?.body {
            Body::Ok(v) => v,
            Body::Error(e) => return Err(ClientError::Refused(e)),
            Body::Event(_) | Body::Records(_) | Body::Heartbeat(_) => {
                return Err(self.bad("a stream before the acknowledgement"));
            }
        };
        Ok((
            ack,
            Stream {
                client: self.clone(),
                reader: r,
                line: Vec::new(),
            },
        ))
    }

    /// Watches an output port: `each` gets every new value until it returns false (then
    /// `Ok(false)`) or the gateway ends the stream (`Ok(true)`). The acknowledgement comes
    /// within the timeout; the values come when they come, and the gateway says it is
    /// alive every [`HEARTBEAT`](crate::protocol::HEARTBEAT) between them: with
    /// `event_timeout`, a silence longer than it (a stuck gateway) is
    /// [`ClientError::Timeout`].
    pub fn watch(
        &self,
        component: &str,
        port: &str,
        count: Option<u64>,
        event_timeout: Option<Duration>,
        mut each: impl FnMut(&Value) -> bool,
    ) -> Result<bool, ClientError> {
        let req = Request::Watch {
            component: component.into(),
            port: port.into(),
            count,
        };
        let (_, mut stream) = self.stream(&req)?;
        while let Some(body) = stream.next(event_timeout)? {
            if let Body::Event(ev) = body
                && !each(&ev.value)
            {
                return Ok(false);
            }
        }
        Ok(true)
    }

    /// The current value of each of `d`'s ports (none where it has none yet).
    pub fn port_values(&self, component: &str, d: &Description) -> Vec<Option<Value>> {
        d.ports
            .iter()
            .map(|p| {
                self.request(&Request::Get {
                    component: component.to_string(),
                    target: Target::Port(p.name.clone()),
                })
                .ok()
                .filter(|v| !v.is_null())
            })
            .collect()
    }
}

/// The longest line a stream may send (a `record` batch is split well below it).
pub const MAX_STREAM_LINE: u64 = 64 << 20;

/// What follows a streaming request's acknowledgement.
pub struct Stream {
    client: Client,
    reader: BufReader<UnixStream>,
    /// What came of the next line so far (bytes: a read cut by the timeout may end
    /// inside a character).
    line: Vec<u8>,
}

impl Stream {
    /// How long its reader waits for the gateway: its client's reply timeout, and at
    /// least two heartbeats.
    pub fn patience(&self) -> Duration {
        self.client.timeout.max(crate::protocol::HEARTBEAT * 2)
    }

    /// The error of a gateway silent for `after`.
    pub fn silent_for(&self, after: Duration) -> ClientError {
        ClientError::Timeout {
            path: self.client.path.clone(),
            after,
        }
    }

    /// The next event or batch: `Ok(None)` when the gateway ended the stream; an error
    /// reply is an error; with `timeout`, a wait longer than it is
    /// [`ClientError::Timeout`].
    pub fn next(&mut self, timeout: Option<Duration>) -> Result<Option<Body>, ClientError> {
        let c = &self.client;
        self.reader
            .get_ref()
            .set_read_timeout(timeout)
            .map_err(|e| c.io(e))?;
        loop {
            // A line cut by the timeout stays in `line`: the next call reads on from there.
            let room = MAX_STREAM_LINE.saturating_sub(self.line.len() as u64);
            match (&mut self.reader)
                .take(room)
                .read_until(b'\n', &mut self.line)
            {
                Ok(0) if self.line.len() as u64 >= MAX_STREAM_LINE => {
                    return Err(c.bad(format!("a line over {MAX_STREAM_LINE} bytes")));
                }
                Ok(0) => return Ok(None),
                Ok(_) if !self.line.ends_with(b"\n") => continue,
                Ok(_) => {}
                Err(e) => {
                    return Err(match timeout {
                        Some(after)
                            if matches!(
                                e.kind(),
                                std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                            ) =>
                        {
                            ClientError::Timeout {
                                path: c.path.clone(),
                                after,
                            }
                        }
                        _ => c.io(e),
                    });
                }
            }
            let reply: Result<Reply, _> = serde_json::from_slice(&self.line);
            self.line.clear();
            match reply.map_err(|e| c.bad(e))?.body {
                Body::Error(e) => return Err(ClientError::Refused(e)),
                // Alive: the wait for the next line starts again.
                Body::Ok(_) | Body::Heartbeat(_) => {}
                body => return Ok(Some(body)),
            }
        }
    }
}

/// An operation's answer: the value of `{"Ok": value}`, an error for `{"Err": message}`
/// (a device operation that failed), anything else as it is.
pub fn call_result(operation: &str, answer: Value) -> Result<Value, ClientError> {
    match answer {
        Value::Object(mut m) if m.len() == 1 && m.contains_key("Err") => {
            let e = m.remove("Err").unwrap_or_default();
            Err(ClientError::Operation {
                operation: operation.to_string(),
                message: e.as_str().map_or_else(|| e.to_string(), str::to_string),
            })
        }
        Value::Object(mut m) if m.len() == 1 && m.contains_key("Ok") => {
            Ok(m.remove("Ok").unwrap_or_default())
        }
        other => Ok(other),
    }
}
