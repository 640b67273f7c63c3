//! Eclipse Mosquitto (Debian's `mosquitto`) as a peer: a broker of the test's own on a
//! free loopback port, plain or TLS with client certificates, stopped and started again
//! on the same port; `mosquitto_sub` capturing what is published, subscribed before it
//! returns; `mosquitto_pub`; certificates made with openssl for the TLS tests; and the
//! independent Sparkplug B host application (`gateway/tests/peers/sparkplug_host.py`,
//! on paho-mqtt and mqtt-spb-wrapper's protobuf module).
//!
//! The broker keeps its sessions on disk (`persistence true`): Mosquitto publishes the
//! wills of its clients when it is stopped (SIGTERM), and a subscriber with a session of
//! its own gets them after the restart — as a Sparkplug host sees an edge node's NDEATH
//! across a broker restart. QoS 0 messages are kept for such a session too
//! (`queue_qos0_messages`): an edge node that is back before the host does not publish
//! its birth into the void.

use crate::TempDir;
use crate::certs::Certs;
use crate::peers::{MOSQUITTO, ensure};
use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::time::{Duration, Instant};

/// How long a broker or a subscriber may take to be ready.
const READY: Duration = Duration::from_secs(30);

/// A broker's TLS: its certificate and key, the CA its clients' certificates must chain
/// to (client certificates are required).
#[derive(Debug, Clone)]
pub struct BrokerTls {
    /// The CA of the client certificates (and of the server's).
    pub ca: PathBuf,
    /// The broker's certificate.
    pub cert: PathBuf,
    /// Its key.
    pub key: PathBuf,
}

/// A running broker; killed when dropped.
pub struct Broker {
    child: Option<Child>,
    /// Its port on 127.0.0.1.
    pub port: u16,
    dir: TempDir,
    tls: Option<BrokerTls>,
    /// A password file (`mosquitto_passwd`): a client that names a user must bring its
    /// password; one that names none is anonymous, and allowed.
    users: bool,
}

impl Drop for Broker {
    fn drop(&mut self) {
        self.kill();
    }
}

impl Broker {
    /// A plain broker, anonymous clients allowed, once it listens.
    pub fn start() -> Broker {
        Broker::start_with(None)
    }

    /// A TLS broker requiring client certificates of `tls.ca`, once it listens.
    pub fn start_tls(tls: BrokerTls) -> Broker {
        Broker::start_with(Some(tls))
    }

    /// A plain broker with users `users` (name, password), once it listens.
    pub fn start_with_users(users: &[(&str, &str)]) -> Broker {
        let mut b = Broker::new(None);
        let file = b.dir.path().join("passwords");
        for (i, (user, password)) in users.iter().enumerate() {
            let mut cmd = Command::new("mosquitto_passwd");
            if i == 0 {
                cmd.arg("-c");
            }
            let o = cmd
                .arg("-b")
                .arg(&file)
                .args([user, password])
                .output()
                .unwrap_or_else(|e| panic!("cannot run mosquitto_passwd: {e}"));
            assert!(
                o.status.success(),
                "mosquitto_passwd: {}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
        b.users = true;
        b.spawn();
        b
    }

    fn start_with(tls: Option<BrokerTls>) -> Broker {
        let mut b = Broker::new(tls);
        b.spawn();
        b
    }

    fn new(tls: Option<BrokerTls>) -> Broker {
        ensure(&MOSQUITTO);
        let port = crate::free_port();
        Broker {
            child: None,
            port,
            dir: TempDir::new(&format!("mosquitto-{port}")),
            tls,
            users: false,
        }
    }

    /// `127.0.0.1:PORT`.
    pub fn addr(&self) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], self.port))
    }

    /// Its process id while it runs (0 when stopped).
    pub fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    /// What it logged.
    pub fn log(&self) -> String {
        std::fs::read(self.dir.path().join("mosquitto.log"))
            .map(|b| String::from_utf8_lossy(&b).into_owned())
            .unwrap_or_default()
    }

    fn spawn(&mut self) {
        let mut conf = format!(
            "listener {} 127.0.0.1\nallow_anonymous true\nlog_dest stderr\nlog_type all\n\
             persistence true\npersistence_location {}/\nmax_queued_messages 100000\n\
             queue_qos0_messages true\n",
            self.port,
            self.dir.path().display()
        );
        if self.users {
            conf.push_str(&format!(
                "password_file {}\n",
                self.dir.path().join("passwords").display()
            ));
        }
        if let Some(t) = &self.tls {
            conf.push_str(&format!(
                "cafile {}\ncertfile {}\nkeyfile {}\nrequire_certificate true\n",
                t.ca.display(),
                t.cert.display(),
                t.key.display()
            ));
        }
        // Run as root, a broker would drop to the `mosquitto` user and not read the
        // test's files.
        if nix::unistd::Uid::effective().is_root() {
            conf.push_str("user root\n");
        }
        let path = self.dir.path().join("mosquitto.conf");
        std::fs::write(&path, conf).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.dir.path().join("mosquitto.log"))
            .unwrap_or_else(|e| panic!("mosquitto.log: {e}"));
        let child = Command::new("/usr/sbin/mosquitto")
            .arg("-c")
            .arg(&path)
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run mosquitto: {e}"));
        self.child = Some(child);
        let deadline = Instant::now() + READY;
        while TcpStream::connect(self.addr()).is_err() {
            if let Some(c) = &mut self.child
                && let Ok(Some(status)) = c.try_wait()
            {
                panic!(
                    "mosquitto ended ({status}) before listening:\n{}",
                    self.log()
                );
            }
            assert!(
                Instant::now() < deadline,
                "mosquitto does not listen on {}:\n{}",
                self.addr(),
                self.log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// Stops the broker (SIGTERM, as `systemctl stop` does) and waits for it to end.
    pub fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let pid = nix::unistd::Pid::from_raw(c.id() as i32);
            let _ = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM);
            let _ = c.wait();
        }
    }

    /// Starts it again on the same port, once it listens.
    pub fn restart(&mut self) {
        self.stop();
        self.spawn();
    }
}

/// A client's TLS files for `mosquitto_sub` and `mosquitto_pub`.
#[derive(Debug, Clone)]
pub struct ClientTls {
    /// The CA the broker's certificate chains to.
    pub ca: PathBuf,
    /// The client's certificate.
    pub cert: PathBuf,
    /// Its key.
    pub key: PathBuf,
}

/// The lines `out` gives, read on a thread of their own until it ends.
fn lines_of(out: impl std::io::Read + Send + 'static) -> Receiver<String> {
    let (tx, lines) = channel();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    lines
}

fn client_args(cmd: &mut Command, port: u16, tls: Option<&ClientTls>) {
    cmd.args(["-h", "127.0.0.1", "-p", &port.to_string()]);
    if let Some(t) = tls {
        cmd.arg("--cafile")
            .arg(&t.ca)
            .arg("--cert")
            .arg(&t.cert)
            .arg("--key")
            .arg(&t.key);
    }
}

/// `mosquitto_sub -v` on some topics: each message as (topic, payload).
pub struct Sub {
    child: Child,
    lines: Receiver<String>,
    /// The newest payload of each topic read so far.
    latest: std::collections::HashMap<String, String>,
}

impl Drop for Sub {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Sub {
    /// Subscribed to `topics` on the broker at `port` (QoS 1), once the broker
    /// acknowledged the subscription.
    pub fn start(port: u16, topics: &[&str], tls: Option<&ClientTls>) -> Sub {
        ensure(&MOSQUITTO);
        // Line-buffered: its debug lines (the SUBACK) are not flushed into a pipe.
        let mut cmd = Command::new("stdbuf");
        cmd.args(["-oL", "mosquitto_sub"]);
        client_args(&mut cmd, port, tls);
        // -d prints the SUBACK; -F prints each message as "topic payload" on one line.
        cmd.args(["-d", "-q", "1", "-F", "MQTT %t %p"]);
        for t in topics {
            cmd.args(["-t", t]);
        }
        let mut child = cmd
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run mosquitto_sub: {e}"));
        let out = child
            .stdout
            .take()
            .unwrap_or_else(|| panic!("mosquitto_sub: no stdout"));
        let lines = lines_of(out);
        let deadline = Instant::now() + READY;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match lines.recv_timeout(left) {
                Ok(l) if l.contains("received SUBACK") => break,
                Ok(_) => {}
                Err(e) => panic!("mosquitto_sub on port {port} never subscribed: {e}"),
            }
        }
        Sub {
            child,
            lines,
            latest: Default::default(),
        }
    }

    /// Its process id (`mosquitto_sub`'s: `stdbuf` execs it).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The next message, (topic, payload), within `timeout`.
    pub fn next(&mut self, timeout: Duration) -> Option<(String, String)> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(l) => {
                    if let Some(m) = l.strip_prefix("MQTT ") {
                        let (t, p) = m.split_once(' ').unwrap_or((m, ""));
                        self.latest.insert(t.to_string(), p.to_string());
                        return Some((t.to_string(), p.to_string()));
                    }
                }
                Err(RecvTimeoutError::Timeout | RecvTimeoutError::Disconnected) => return None,
            }
        }
    }

    /// Messages until one satisfies `f` (returned), within `timeout`; panics saying `what`
    /// when none does.
    pub fn until(
        &mut self,
        what: &str,
        timeout: Duration,
        mut f: impl FnMut(&str, &str) -> bool,
    ) -> (String, String) {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.next(left) {
                Some((t, p)) if f(&t, &p) => return (t, p),
                Some(_) => {}
                None => panic!("timed out waiting for {what}"),
            }
        }
    }
}

impl Sub {
    /// The newest payload of `topic` once it satisfies `f` — already read, or read now —
    /// within `timeout`; panics saying so when it does not.
    pub fn latest(
        &mut self,
        topic: &str,
        timeout: Duration,
        mut f: impl FnMut(&str) -> bool,
    ) -> String {
        if let Some(p) = self.latest.get(topic)
            && f(p)
        {
            return p.clone();
        }
        self.until(topic, timeout, |t, p| t == topic && f(p)).1
    }

    /// Forgets what was read of `topic` (to wait for its next message with
    /// [`Sub::latest`]).
    pub fn forget(&mut self, topic: &str) {
        self.latest.remove(topic);
    }
}

/// `mosquitto_pub` of one message (QoS 1), waited for.
pub fn publish(port: u16, topic: &str, payload: &[u8], tls: Option<&ClientTls>) {
    mosquitto_pub(port, topic, payload, tls, &[]);
}

/// [`publish`] retained.
pub fn publish_retained(port: u16, topic: &str, payload: &[u8], tls: Option<&ClientTls>) {
    mosquitto_pub(port, topic, payload, tls, &["-r"]);
}

fn mosquitto_pub(port: u16, topic: &str, payload: &[u8], tls: Option<&ClientTls>, extra: &[&str]) {
    ensure(&MOSQUITTO);
    let mut cmd = Command::new("mosquitto_pub");
    client_args(&mut cmd, port, tls);
    cmd.args(["-q", "1", "-t", topic, "-s"]).args(extra);
    let mut child = cmd
        .stdin(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run mosquitto_pub: {e}"));
    if let Some(mut stdin) = child.stdin.take() {
        use std::io::Write;
        stdin
            .write_all(payload)
            .unwrap_or_else(|e| panic!("mosquitto_pub: {e}"));
    }
    let status = child
        .wait()
        .unwrap_or_else(|e| panic!("mosquitto_pub: {e}"));
    assert!(status.success(), "mosquitto_pub -t {topic}: {status}");
}

impl Certs {
    /// The broker's TLS: the server certificate, client certificates of `ca.pem`.
    pub fn broker(&self) -> BrokerTls {
        BrokerTls {
            ca: self.path("ca.pem"),
            cert: self.path("server.pem"),
            key: self.path("server.key"),
        }
    }

    /// A client's TLS with certificate `name` (`client`, or `stranger` of the other CA).
    pub fn client(&self, name: &str) -> ClientTls {
        ClientTls {
            ca: self.path("ca.pem"),
            cert: self.path(&format!("{name}.pem")),
            key: self.path(&format!("{name}.key")),
        }
    }
}

/// The independent Sparkplug B host application (`sparkplug_host.py`, the script's path
/// given), its events read as JSON lines; its commands written. Killed when dropped.
pub struct SparkplugHost {
    child: Child,
    events: Receiver<String>,
    stdin: std::process::ChildStdin,
    /// Every event read so far, in order.
    pub seen: Vec<serde_json::Value>,
}

impl Drop for SparkplugHost {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl SparkplugHost {
    /// `script` for group `group`, node `node`, as host `host_id`, on the broker at
    /// `port`; `extra` arguments (`--count`, TLS); once it says it is ready.
    pub fn start(
        script: &Path,
        port: u16,
        (group, node, host_id): (&str, &str, &str),
        extra: &[&str],
    ) -> SparkplugHost {
        let path = crate::pypi::sparkplug().unwrap_or_else(|e| panic!("mqtt-spb-wrapper: {e}"));
        let mut child = Command::new(crate::peers::PYTHON)
            .arg(script)
            .args([
                "--broker",
                &format!("127.0.0.1:{port}"),
                "--group",
                group,
                "--node",
                node,
                "--host-id",
                host_id,
            ])
            .args(extra)
            .env("PYTHONPATH", path)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run {}: {e}", script.display()));
        let out = child
            .stdout
            .take()
            .unwrap_or_else(|| panic!("the host: no stdout"));
        let stdin = child
            .stdin
            .take()
            .unwrap_or_else(|| panic!("the host: no stdin"));
        let events = lines_of(out);
        let mut h = SparkplugHost {
            child,
            events,
            stdin,
            seen: Vec::new(),
        };
        h.until("the host ready", |e| e["event"] == "ready");
        h
    }

    /// The next event within `timeout` (kept in [`SparkplugHost::seen`]).
    pub fn next(&mut self, timeout: Duration) -> Option<serde_json::Value> {
        let line = self.events.recv_timeout(timeout).ok()?;
        let e: serde_json::Value = serde_json::from_str(&line)
            .unwrap_or_else(|e| panic!("the host printed {line:?}: {e}"));
        if e["event"] == "error" {
            eprintln!("sparkplug host: {e}");
        }
        self.seen.push(e.clone());
        Some(e)
    }

    /// Events until one satisfies `f` (returned), within 30 s; panics saying `what`.
    pub fn until(
        &mut self,
        what: &str,
        mut f: impl FnMut(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let deadline = Instant::now() + READY;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.next(left) {
                Some(e) if f(&e) => return e,
                Some(_) => {}
                None => panic!("timed out waiting for {what}"),
            }
        }
    }

    /// The next Sparkplug message of `kind` (`NBIRTH`, `DDATA`, …), for device `device`
    /// when given.
    pub fn message(&mut self, kind: &str, device: Option<&str>) -> serde_json::Value {
        self.until(&format!("{kind} {device:?}"), |e| {
            e["event"] == "message" && e["type"] == kind && device.is_none_or(|d| e["device"] == d)
        })
    }

    /// Sends command `cmd` and waits for its `done`.
    pub fn command(&mut self, cmd: serde_json::Value) {
        use std::io::Write;
        let name = cmd["cmd"].clone();
        writeln!(self.stdin, "{cmd}").unwrap_or_else(|e| panic!("the host's stdin: {e}"));
        self.until(&format!("{name} done"), |e| {
            e["event"] == "done" && e["cmd"] == name
        });
    }
}
