//! `[server.opcua]` as a server of the deployment: at start it takes its address, makes
//! its certificate when there is none, builds the address space and runs async-opcua on
//! a tokio runtime of two threads of its own, beside the sampler; at stop nothing more is
//! written or called, the sessions are closed and the threads end. Its counters (and
//! async-opcua's session and request counts) are in `hwgw status` and under
//! `Diagnostics`.

use crate::auth::{self, Users};
use crate::calls::Book;
use crate::config::Settings;
use crate::nodes::HwgwNodeManager;
use crate::plan::Plan;
use crate::space::Build;
use crate::values::Sampler;
use driver_api::{CardStatus, ControlLink, Server, ServerError};
use serde_json::Value;
use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use ua::server::{ServerBuilder, ServerHandle};
use ua::types::ServerDiagnosticsSummaryDataType;

/// The namespace of hwgw's nodes.
pub const NAMESPACE: &str = "urn:hwgw:io";

/// Why the server could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// Half a certificate pair is in the store: hwgw makes no new one over it.
    #[error(
        "{dir}: {present} is there but {missing} is not; hwgw makes a new pair only when \
         neither is there (never over one): put the missing file back, or remove both"
    )]
    HalfPair {
        /// The store.
        dir: String,
        /// The file that is there.
        present: String,
        /// The file that is not.
        missing: String,
    },
    /// async-opcua refused the configuration.
    #[error("OPC UA server: {0}")]
    Build(String),
    /// The signed endpoints have no certificate.
    #[error(
        "{0}: no certificate and key could be read or made, and the signed endpoints need them"
    )]
    NoCertificate(String),
}

/// The OPC UA server.
pub struct OpcuaServer {
    name: String,
    settings: Settings,
    plan: Plan,
    registry: Arc<device_interface::Registry>,
    control: ControlLink,
    book: Arc<Book>,
    users: Arc<Users>,
    running: Mutex<Option<Running>>,
}

struct Running {
    handle: ServerHandle,
    thread: JoinHandle<()>,
}

impl OpcuaServer {
    pub(crate) fn new(
        name: &str,
        settings: Settings,
        plan: Plan,
        registry: Arc<device_interface::Registry>,
        control: ControlLink,
    ) -> OpcuaServer {
        let users = Arc::new(Users::new(settings.anonymous, settings.users.clone()));
        OpcuaServer {
            name: name.into(),
            settings,
            plan,
            registry,
            control,
            book: Arc::default(),
            users,
            running: Mutex::new(None),
        }
    }

    fn address(&self) -> String {
        format!("opc.tcp://{}/", self.settings.listen)
    }

    fn builder(&self) -> ServerBuilder {
        let s = &self.settings;
        let l = &s.limits;
        let mut b = ServerBuilder::new()
            .application_name("hwgw")
            .application_uri(s.application_uri.as_str())
            .product_uri("urn:hwgw")
            .create_sample_keypair(true)
            .pki_dir(&s.pki_dir)
            .trust_client_certs(false)
            .host(advertised_host(s.listen.ip()))
            .port(s.listen.port())
            .discovery_urls(vec![format!(
                "opc.tcp://{}:{}/",
                advertised_host(s.listen.ip()),
                s.listen.port()
            )])
            .with_authenticator(self.users.clone())
            .diagnostics_enabled(true)
            .max_sessions(l.sessions)
            .max_session_timeout_ms(l.session_timeout_s * 1000)
            .max_message_size(l.message_kib << 10)
            // A secure channel's token lives at most a minute (clients renew it): a
            // connection that opened a channel and went quiet is closed after 80 s, not
            // the library's 400.
            .max_secure_channel_token_lifetime_ms(60_000)
            .with_node_manager(crate::nodes::builder(NAMESPACE, self.book.clone()));
        let limits = b.limits_mut();
        // A message may take `message_kib` in chunks of the send buffer (async-opcua's
        // default is 5 chunks, 320 KiB), and a publish carries at most as many
        // notifications as fit in one at 256 bytes each (its default is no bound: a
        // subscription of many items then makes responses too big to send, and its
        // client never hears a thing).
        let message = l.message_kib << 10;
        limits.max_chunk_count = message.div_ceil(limits.send_buffer_size) + 1;
        limits.subscriptions.max_notifications_per_publish =
            l.notifications_per_publish.unwrap_or(message / 256) as u64;
        limits.subscriptions.max_subscriptions_per_session = l.subscriptions_per_session;
        limits.subscriptions.max_monitored_items_per_sub = l.monitored_items_per_subscription;
        limits.subscriptions.max_monitored_item_queue_size = l.queue_size;
        limits.subscriptions.max_queued_notifications = l.queued_notifications;
        limits.subscriptions.min_sampling_interval_ms = s.sample.as_secs_f64() * 1000.0;
        for sec in &s.security {
            b = b.add_endpoint(sec.name(), auth::endpoint(*sec));
        }
        b
    }

    /// The counters of this server and of async-opcua's diagnostics, by name.
    fn counters(book: &Book, users: &Users, handle: Option<&ServerHandle>) -> Vec<(String, u64)> {
        let n = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
        let mut c = vec![
            ("writes".to_string(), n(&book.writes)),
            ("writes_refused".into(), n(&book.writes_refused)),
            ("calls".into(), n(&book.calls)),
            ("calls_refused".into(), n(&book.calls_refused)),
            ("logins_refused".into(), n(&users.refused)),
        ];
        let d = handle.and_then(|h| {
            h.info()
                .diagnostics
                .summary
                .sample()
                .value
                .and_then(|v| match v {
                    ua::types::Variant::ExtensionObject(e) => {
                        e.into_inner_as::<ServerDiagnosticsSummaryDataType>()
                    }
                    _ => None,
                })
        });
        let d = d.map(|d| *d).unwrap_or_default();
        for (k, v) in [
            ("sessions", d.current_session_count),
            ("sessions_total", d.cumulated_session_count),
            ("sessions_rejected", d.rejected_session_count),
            (
                "sessions_security_rejected",
                d.security_rejected_session_count,
            ),
            ("sessions_timed_out", d.session_timeout_count),
            ("sessions_aborted", d.session_abort_count),
            ("subscriptions", d.current_subscription_count),
            ("requests_rejected", d.rejected_requests_count),
            (
                "requests_security_rejected",
                d.security_rejected_requests_count,
            ),
        ] {
            c.push((k.to_string(), u64::from(v)));
        }
        c
    }
}

/// The host name endpoints are advertised with: the listening address, or the host's
/// name when it listens on every address (`0.0.0.0` is nowhere to connect to).
fn advertised_host(ip: std::net::IpAddr) -> String {
    if ip.is_unspecified() {
        std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "localhost".into())
    } else {
        ip.to_string()
    }
}

/// Makes the store's `private/` readable by its owner only (made so, or its mode set
/// when it is there without a key yet) before async-opcua makes a key in it; returns the
/// key's path when there is none yet. A key others may read is refused.
fn private_dir(dir: &Path) -> std::io::Result<Option<std::path::PathBuf>> {
    use std::os::unix::fs::{DirBuilderExt, PermissionsExt};
    let private = dir.join("private");
    let key = private.join("private.pem");
    if !private.exists() {
        std::fs::DirBuilder::new()
            .recursive(true)
            .mode(0o700)
            .create(&private)?;
    }
    if key.exists() {
        let mode = std::fs::metadata(&key)?.permissions().mode() & 0o777;
        if mode & 0o077 != 0 {
            return Err(std::io::Error::new(
                std::io::ErrorKind::PermissionDenied,
                format!(
                    "{} is readable by others (mode {mode:04o}): make it readable by its \
                     owner only (chmod 600)",
                    key.display()
                ),
            ));
        }
        return Ok(None);
    }
    std::fs::set_permissions(&private, std::fs::Permissions::from_mode(0o700))?;
    Ok(Some(key))
}

/// Refuses a store holding one of its certificate and key without the other.
fn check_pair(dir: &Path) -> Result<(), StartError> {
    let cert = dir.join("own/cert.der");
    let key = dir.join("private/private.pem");
    let half = |present: &Path, missing: &Path| StartError::HalfPair {
        dir: dir.display().to_string(),
        present: present.display().to_string(),
        missing: missing.display().to_string(),
    };
    match (cert.exists(), key.exists()) {
        (true, false) => Err(half(&cert, &key)),
        (false, true) => Err(half(&key, &cert)),
        _ => Ok(()),
    }
}

impl Server for OpcuaServer {
    fn name(&self) -> &str {
        &self.name
    }

    fn start(&self) -> Result<String, ServerError> {
        let mut running = rtt::lock(&self.running);
        if running.is_some() {
            return Ok(self.address());
        }
        self.book.stopping.store(false, Ordering::Release);
        let listen = |source| ServerError::Listen {
            address: self.settings.listen.to_string(),
            source,
        };
        check_pair(&self.settings.pki_dir).map_err(ServerError::failed)?;
        let new_key = private_dir(&self.settings.pki_dir).map_err(listen)?;
        let socket = std::net::TcpListener::bind(self.settings.listen).map_err(listen)?;
        socket.set_nonblocking(true).map_err(listen)?;
        // async-opcua spawns its tasks as it is built: within the runtime.
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("hwgw-opcua")
            .enable_all()
            .build()
            .map_err(listen)?;
        let entered = rt.enter();
        let (server, handle) = self
            .builder()
            .build()
            .map_err(|e| ServerError::failed(StartError::Build(e)))?;
        if let Some(key) = new_key.filter(|k| k.exists()) {
            // async-opcua writes the key it made with the process's umask.
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600))
                .map_err(listen)?;
            tracing::info!(
                "{}: made its certificate {} and key {}",
                self.name,
                self.settings.pki_dir.join("own/cert.der").display(),
                key.display()
            );
        }
        let secured = self
            .settings
            .security
            .iter()
            .any(|s| *s != crate::config::Security::None);
        if secured && handle.info().server_certificate.is_none() {
            return Err(ServerError::failed(StartError::NoCertificate(
                self.settings.pki_dir.display().to_string(),
            )));
        }
        let nm = handle
            .node_managers()
            .get_of_type::<HwgwNodeManager>()
            .ok_or_else(|| ServerError::failed(StartError::Build("no node manager".into())))?;
        let ns = handle
            .get_namespace_index(NAMESPACE)
            .ok_or_else(|| ServerError::failed(StartError::Build("no namespace".into())))?;
        let (book, users, h) = (self.book.clone(), self.users.clone(), handle.clone());
        Build {
            nm: &nm,
            ns,
            plan: &self.plan,
            allow_writes: self.settings.allow_writes,
            allow_calls: self.settings.allow_calls,
            sample_ms: self.settings.sample.as_secs_f64() * 1000.0,
            registry: self.registry.clone(),
            control: self.control.clone(),
            book: self.book.clone(),
            counters: Arc::new(move || OpcuaServer::counters(&book, &users, Some(&h))),
        }
        .run();
        let mut sampler = Sampler::new(&self.plan, ns, self.registry.clone());
        drop(entered);
        let (subs, token, period) = (
            handle.subscriptions().clone(),
            handle.token().clone(),
            self.settings.sample,
        );
        let thread = std::thread::Builder::new()
            .name("hwgw-opcua".into())
            .spawn(move || {
                rt.block_on(async move {
                    let listener = match tokio::net::TcpListener::from_std(socket) {
                        Ok(l) => l,
                        Err(e) => {
                            tracing::error!("OPC UA: the listening socket: {e}");
                            return;
                        }
                    };
                    let stop = token.clone();
                    tokio::spawn(async move {
                        let mut tick = tokio::time::interval(period);
                        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
                        loop {
                            tokio::select! {
                                _ = tick.tick() => {}
                                _ = stop.cancelled() => break,
                            }
                            sampler.tick(&nm, &subs);
                        }
                    });
                    if let Err(e) = server.run_with(listener).await {
                        tracing::error!("OPC UA server ended: {e}");
                    }
                });
                rt.shutdown_timeout(std::time::Duration::from_secs(2));
            })
            .map_err(listen)?;
        *running = Some(Running { handle, thread });
        Ok(self.address())
    }

    fn stop(&self) {
        let Some(r) = rtt::lock(&self.running).take() else {
            return;
        };
        self.book.stopping.store(true, Ordering::Release);
        r.handle.cancel();
        if r.thread.join().is_err() {
            tracing::error!("the OPC UA server thread panicked");
        }
    }

    fn address(&self) -> Option<String> {
        rtt::lock(&self.running).as_ref().map(|_| self.address())
    }

    fn status(&self) -> Option<CardStatus> {
        let running = rtt::lock(&self.running);
        let handle = running.as_ref().map(|r| &r.handle);
        let mut m = serde_json::Map::new();
        for (k, v) in OpcuaServer::counters(&self.book, &self.users, handle) {
            m.insert(k, v.into());
        }
        let l = &self.settings.limits;
        m.insert("channels".into(), self.plan.channel_count().into());
        m.insert("max_sessions".into(), l.sessions.into());
        m.insert(
            "max_monitored_items_per_subscription".into(),
            l.monitored_items_per_subscription.into(),
        );
        let last = rtt::lock(&self.book.last_refusal).clone();
        if !last.is_empty() {
            m.insert("last_refusal".into(), Value::from(last));
        }
        Some(CardStatus {
            bus: self.address(),
            counters: m,
        })
    }

    fn health(&self) -> Result<(), ServerError> {
        match rtt::lock(&self.running).as_ref() {
            Some(r) if !r.thread.is_finished() => Ok(()),
            Some(_) => Err(ServerError::NotStarted(format!(
                "{} (its thread ended)",
                self.name
            ))),
            None => Err(ServerError::NotStarted(self.name.clone())),
        }
    }
}

impl Drop for OpcuaServer {
    fn drop(&mut self) {
        self.stop();
    }
}
