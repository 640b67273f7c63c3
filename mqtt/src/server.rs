//! `[server.mqtt]` as a server of the deployment: a thread of its own running the
//! session (a tokio runtime on one thread), another carrying out commands, both started
//! and stopped with the gateway's servers; its counters in `hwgw status` and the metrics.

use crate::commands::{self, Book, Job};
use crate::session::{Counters, Node};
use driver_api::{CardStatus, ControlLink, Server, ServerError};
use serde_json::Value;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

/// Makes the node of a start.
pub(crate) type MakeNode =
    Box<dyn Fn(Arc<Counters>, Arc<Book>, std::sync::mpsc::SyncSender<Job>) -> Node + Send + Sync>;

/// The MQTT server.
pub struct MqttServer {
    name: String,
    address: String,
    control: ControlLink,
    counters: Arc<Counters>,
    book: Arc<Book>,
    make: MakeNode,
    running: Mutex<Option<Running>>,
}

struct Running {
    stop: tokio::sync::watch::Sender<bool>,
    session: JoinHandle<()>,
    worker: JoinHandle<()>,
}

impl MqttServer {
    pub(crate) fn new(
        name: &str,
        address: String,
        control: ControlLink,
        make: MakeNode,
    ) -> MqttServer {
        MqttServer {
            name: name.into(),
            address,
            control,
            counters: Arc::default(),
            book: Arc::default(),
            make,
            running: Mutex::new(None),
        }
    }
}

impl Server for MqttServer {
    fn name(&self) -> &str {
        &self.name
    }

    fn start(&self) -> Result<String, ServerError> {
        let mut running = rtt::lock(&self.running);
        if running.is_some() {
            return Ok(self.address.clone());
        }
        self.book.stopping.store(false, Ordering::Release);
        let listen = |source| ServerError::Listen {
            address: self.address.clone(),
            source,
        };
        let (tx, rx) = std::sync::mpsc::sync_channel(commands::QUEUE);
        let (control, book) = (self.control.clone(), self.book.clone());
        let worker = std::thread::Builder::new()
            .name("hwgw-mqtt-cmd".into())
            .spawn(move || commands::worker(rx, control, book))
            .map_err(listen)?;
        let node = (self.make)(self.counters.clone(), self.book.clone(), tx);
        let (stop, stopped) = tokio::sync::watch::channel(false);
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(listen)?;
        let session = std::thread::Builder::new()
            .name("hwgw-mqtt".into())
            .spawn(move || rt.block_on(node.run(stopped)))
            .map_err(listen)?;
        *running = Some(Running {
            stop,
            session,
            worker,
        });
        Ok(self.address.clone())
    }

    fn stop(&self) {
        let Some(r) = rtt::lock(&self.running).take() else {
            return;
        };
        // Commands not begun are refused from now on; the one under way finishes whole.
        self.book.stopping.store(true, Ordering::Release);
        let _ = r.stop.send(true);
        if r.session.join().is_err() {
            tracing::error!("the MQTT session thread panicked");
        }
        // The session held the jobs' sender: the worker refuses what is left and ends.
        if r.worker.join().is_err() {
            tracing::error!("the MQTT command thread panicked");
        }
    }

    fn address(&self) -> Option<String> {
        rtt::lock(&self.running)
            .as_ref()
            .map(|_| self.address.clone())
    }

    fn status(&self) -> Option<CardStatus> {
        let c = &self.counters;
        let n = |a: &AtomicU64| Value::from(a.load(Ordering::Relaxed));
        let mut m = serde_json::Map::new();
        m.insert(
            "connected".into(),
            c.connected.load(Ordering::Relaxed).into(),
        );
        m.insert(
            "host_online".into(),
            c.host_online.load(Ordering::Relaxed).into(),
        );
        m.insert("published".into(), n(&c.published));
        m.insert("dropped".into(), n(&c.dropped));
        m.insert("reconnects".into(), n(&c.reconnects));
        m.insert("births".into(), n(&c.births));
        m.insert("bd_seq".into(), n(&c.bd_seq));
        m.insert("bad_messages".into(), n(&c.bad_messages));
        m.insert("subscriptions_refused".into(), n(&c.subscriptions_refused));
        m.insert("commands_accepted".into(), n(&self.book.accepted));
        m.insert("commands_refused".into(), n(&self.book.refused));
        m.insert("outcomes_lost".into(), n(&self.book.outcomes_lost));
        if let Some(e) = rtt::lock(&c.last_error).clone() {
            m.insert("last_error".into(), e.into());
        }
        let last = rtt::lock(&self.book.last_refusal).clone();
        if !last.is_empty() {
            m.insert("last_refusal".into(), last.into());
        }
        Some(CardStatus {
            bus: self.address.clone(),
            counters: m,
        })
    }

    fn health(&self) -> Result<(), ServerError> {
        match rtt::lock(&self.running).as_ref() {
            Some(r) if !r.session.is_finished() => Ok(()),
            Some(_) => Err(ServerError::NotStarted(format!(
                "{} (its thread ended)",
                self.name
            ))),
            None => Err(ServerError::NotStarted(self.name.clone())),
        }
    }
}

impl Drop for MqttServer {
    fn drop(&mut self) {
        self.stop();
    }
}
