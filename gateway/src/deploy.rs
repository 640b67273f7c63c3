//! A built gateway: the runtime with its components, the cards, the servers; started,
//! watched, and stopped with every output at its safe value.
//!
//! [`Gateway::build`] (in phases, in the `build` module) does everything short of starting
//! threads, so `hwgw check` runs the very code `hwgw run` does and finds every error it
//! would, each located in the file.

use crate::config::{ChannelNames, Deployment};
use crate::health::Looks;
use crate::outputs::{CardOutputs, Hold};
use crate::problems::KeyPath;
use driver_api::{Card, Server};
use rtt::{Runtime, TaskContext, TaskState};
use std::sync::{Arc, Mutex, PoisonError, RwLock, RwLockReadGuard, RwLockWriteGuard};
use std::time::{Duration, Instant};

/// How long the cards may take at stop to get their safe values to the hardware.
const SETTLE: Duration = Duration::from_secs(3);

/// How long a stop waits for the ThreadScope pulses under way to end (their steps to
/// finish) before it holds the outputs.
const SCOPE_CLOSE: Duration = Duration::from_secs(5);

/// A card of the deployment, with what it needs at stop.
pub(crate) struct CardRt {
    pub(crate) name: String,
    /// Its key path in the deployment (`card[i]`).
    pub(crate) config: KeyPath,
    pub(crate) driver: String,
    /// Its index in the deployment's `[[card]]` list.
    pub(crate) index: usize,
    /// Its gate: once held, its guarded outputs refuse every write (at the gateway's stop,
    /// or when a reload rebuilds or removes the card).
    pub(crate) hold: Arc<Hold>,
    /// The bus it shares with other cards of its driver (one Modbus line), as the driver
    /// named it: a reload that rebuilds or adds one such card rebuilds them all.
    pub(crate) shares: Option<String>,
    pub(crate) card: Box<dyn Card>,
    /// Its outputs under the output policy.
    pub(crate) outputs: Arc<CardOutputs>,
    /// Port names of its channels (given, or from the driver).
    pub(crate) names: ChannelNames,
    /// Its bus-side components.
    pub(crate) bus: Vec<TaskContext>,
    /// Its IO components (`card.ai`, `card.ao`, …).
    pub(crate) io: Vec<TaskContext>,
}

/// The reports `status` carries, defined with the control protocol.
pub use crate::protocol::{CardReport, ServerReport};

/// A local connection as made: its deployment entry, and the output port with the id
/// that closes it again (a reload that removes it, or rebuilds one of its ends).
pub(crate) struct Link {
    pub(crate) config: crate::config::ConnectionConfig,
    /// `None` for a connection fed from another gateway through Zenoh (made once).
    pub(crate) made: Option<(Arc<dyn rtt::component::DynPort>, u64)>,
}

impl Parts {
    /// Whether `name` is one of its components (a card's too).
    pub(crate) fn has_component(&self, name: &str) -> bool {
        self.order.iter().any(|(t, _)| t.name() == name)
            || self
                .cards
                .iter()
                .any(|c| c.io.iter().chain(&c.bus).any(|t| t.name() == name))
    }
}

/// What a gateway is made of; changed by a reload, read by everything else.
pub(crate) struct Parts {
    pub(crate) cards: Vec<CardRt>,
    /// What is served beside the cards (the Modbus server), if configured.
    pub(crate) servers: Vec<Box<dyn Server>>,
    /// Components in start order, each with whether the deployment asked to start it.
    pub(crate) order: Vec<(TaskContext, bool)>,
    /// The connections made.
    pub(crate) links: Vec<Link>,
    /// What the output watchdog watches (swapped by a reload).
    pub(crate) watch: crate::watchdog::WatchSet,
    /// The Zenoh node as a server (`[zenoh]`): started first and stopped first like the
    /// others, never made again by a reload.
    pub(crate) zenoh_server: Option<Box<dyn Server>>,
    /// (card, port, writer): card outputs the logical devices write, for the output
    /// watchdog (never rebuilt by a reload: neither are they nor their cards).
    pub(crate) logical_writers: Vec<(String, String, String)>,
}

impl Parts {
    /// Every server: the deployment's, then the Zenoh node's.
    pub(crate) fn all_servers(&self) -> impl Iterator<Item = &Box<dyn Server>> {
        self.servers.iter().chain(&self.zenoh_server)
    }
}

/// The deployment the gateway runs, for a reload, and whether its stop began.
pub(crate) struct Running {
    /// The deployment as applied.
    pub(crate) deployment: Deployment,
    /// The file it was read from (`None`: the embedded demo, nothing to read again).
    pub(crate) file: Option<std::path::PathBuf>,
    /// Set by the stop: no reload from then on.
    pub(crate) stopping: bool,
    /// The deployment's text as applied: the file's, then as run-time changes edited it.
    pub(crate) text: String,
    /// The run-time changes since the file was last read (`hwgw ls --changes`): the
    /// newest [`crate::changes::KEPT`], and how many older ones were let go.
    pub(crate) changes: std::collections::VecDeque<String>,
    pub(crate) changes_dropped: u64,
}

/// A built (and possibly running) gateway.
pub struct Gateway {
    runtime: Runtime,
    parts: RwLock<Parts>,
    /// Held by a reload throughout and by the stop's first step: the two never overlap.
    pub(crate) running: Mutex<Running>,
    /// The component and driver types it was built with (a reload builds with them).
    pub(crate) types: crate::types::Types,
    /// Set by the stop's first step, without a lock.
    stopping: std::sync::atomic::AtomicBool,
    /// How many reloads changed something: a client's cached writers into ports made
    /// before the last one are let go.
    pub(crate) generation: std::sync::atomic::AtomicU64,
    /// Where ThreadScope records each thread's bit once started ([`Self::record_thread_scope`]):
    /// the name its numbered files are made after, and how many of them are kept.
    pub(crate) scope_vcd: Option<(std::path::PathBuf, u32)>,
    /// The Zenoh node of the `[zenoh]` section (also among the servers).
    pub(crate) zenoh: Option<Arc<crate::remote::Node>>,
    /// The control protocol for the servers (see [`Self::control_link`]).
    pub(crate) control: driver_api::ControlLink,
    /// What [`Self::health`] saw at its last call (the watchdog keeps looks of its own).
    health_looks: Mutex<Looks>,
}

impl Gateway {
    pub(crate) fn new(
        runtime: Runtime,
        parts: Parts,
        deployment: Deployment,
        types: crate::types::Types,
    ) -> Gateway {
        Gateway {
            runtime,
            types,
            stopping: std::sync::atomic::AtomicBool::new(false),
            generation: std::sync::atomic::AtomicU64::new(0),
            parts: RwLock::new(parts),
            running: Mutex::new(Running {
                deployment,
                file: None,
                stopping: false,
                text: String::new(),
                changes: std::collections::VecDeque::new(),
                changes_dropped: 0,
            }),
            scope_vcd: None,
            zenoh: None,
            control: driver_api::ControlLink::new(),
            health_looks: Mutex::new(Looks::new()),
        }
    }

    /// Where the gateway's servers reach its control protocol: joined by the control
    /// server when it starts ([`crate::control::ControlServer::start`]).
    pub fn control_link(&self) -> &driver_api::ControlLink {
        &self.control
    }

    /// What the gateway is made of, to read.
    pub(crate) fn parts(&self) -> RwLockReadGuard<'_, Parts> {
        self.parts.read().unwrap_or_else(PoisonError::into_inner)
    }

    /// What the gateway is made of, to change (a reload).
    pub(crate) fn parts_mut(&self) -> RwLockWriteGuard<'_, Parts> {
        self.parts.write().unwrap_or_else(PoisonError::into_inner)
    }

    /// The deployment as running and whether the stop began.
    pub(crate) fn running(&self) -> std::sync::MutexGuard<'_, Running> {
        self.running.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Names the file the deployment was read from: a reload reads it again.
    pub fn set_file(&self, file: std::path::PathBuf) {
        self.running().file = Some(file);
    }

    /// Starts the ThreadScope recording the deployment asks for (`thread_scope_vcd`), if
    /// any: its next numbered file is created here, at `run`, never at `check`, and the
    /// oldest beyond `thread_scope_vcd_keep` removed. Before [`start`](Self::start), so
    /// that every step is recorded.
    pub fn record_thread_scope(&self) -> Result<(), rtt::scope::vcd::VcdError> {
        if let Some((base, keep)) = &self.scope_vcd {
            self.runtime
                .thread_scope()
                .record_vcd_numbered(base, *keep)?;
        }
        Ok(())
    }

    /// Starts the servers (the Modbus server), if configured, then the components the
    /// deployment asks to start, in order (each card's bus side before its IO components).
    pub fn start(&self) -> Result<(), rtt::component::LifecycleError> {
        let parts = self.parts();
        let _ = start_servers(parts.all_servers());
        start_tasks(&parts.order)
    }

    /// `Ok` while every component that should run is running and no periodic activity
    /// overran or stalled since the last call (the first call: none overrunning now);
    /// else what is wrong, as the watchdog judges it (see [`health_since`](Self::health_since)).
    /// What `status` and `GET /health` say. The error model's warning is healthy (the
    /// component runs, its flag shows in `ls` and `status`); RunTimeError is not (manual
    /// L832–884: an error the component waits out, not a state to run in).
    pub fn health(&self) -> Result<(), String> {
        let mut looks = self
            .health_looks
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        self.health_since(&mut looks)
    }

    /// [`health`](Self::health) as the systemd watchdog's looks judge it, `looks` kept
    /// between them: a periodic activity is wrong when it spent at least half the time
    /// since the look before overrunning, or ended no step since then and for longer than
    /// its overruns allow (see the `health` module). A look that finds anything wrong
    /// withholds its feed of the watchdog; none for a whole interval and systemd restarts
    /// the service. A component deployed not to start (`start = false`) and found stopped
    /// is not judged.
    pub fn health_since(&self, looks: &mut Looks) -> Result<(), String> {
        let parts = self.parts();
        looks.retain(|name| parts.order.iter().any(|(t, _)| t.name() == name));
        let now = Instant::now();
        let mut wrong = Vec::new();
        for (t, start) in &parts.order {
            let running = match t.state() {
                TaskState::Running => true,
                TaskState::RunTimeError => {
                    wrong.push(format!("{} is in RunTimeError", t.name()));
                    true
                }
                s if *start => {
                    wrong.push(format!("{} is {s}", t.name()));
                    false
                }
                _ => false,
            };
            wrong.extend(looks.judge(t, running, now));
        }
        for s in parts.all_servers() {
            if let Err(e) = s.health() {
                wrong.push(e.to_string());
            }
        }
        if wrong.is_empty() {
            Ok(())
        } else {
            Err(wrong.join("; "))
        }
    }

    /// The Zenoh node, when the deployment has a `[zenoh]` section.
    pub fn zenoh(&self) -> Option<&crate::remote::Node> {
        self.zenoh.as_deref()
    }

    /// Where the server configured under deployment key `name` (`modbus_server`) listens,
    /// once started.
    pub fn server_address(&self, name: &str) -> Option<String> {
        self.parts()
            .all_servers()
            .find(|s| s.name() == name)
            .and_then(|s| s.address())
    }

    /// Every card's bus and counters, for `status`.
    pub fn card_status(&self) -> Vec<CardReport> {
        self.parts()
            .cards
            .iter()
            .map(|c| CardReport {
                name: c.name.clone(),
                driver: c.driver.clone(),
                status: c.card.status(),
                outputs: c.outputs.report(),
            })
            .collect()
    }

    /// Every server's state and counters, for `status`.
    pub fn server_status(&self) -> Vec<ServerReport> {
        self.parts()
            .all_servers()
            .filter_map(|s| {
                s.status().map(|status| ServerReport {
                    name: s.name().to_string(),
                    status,
                })
            })
            .collect()
    }

    /// The runtime.
    pub fn runtime(&self) -> &Runtime {
        &self.runtime
    }

    /// A summary of what was loaded, for the start-up log.
    pub fn summary(&self) -> String {
        let mut s = String::new();
        let parts = self.parts();
        for c in &parts.cards {
            let summary = c.card.summary();
            let sep = if summary.is_empty() { "" } else { " " };
            s.push_str(&format!("card {:?} ({}{sep}{summary})\n", c.name, c.driver));
        }
        for e in self.runtime.registry().entries() {
            let alias = e
                .info
                .alias_of
                .as_ref()
                .map(|a| format!(" -> {a}"))
                .unwrap_or_default();
            s.push_str(&format!(
                "  device {} {:?}{alias}\n",
                e.interface, e.info.name
            ));
        }
        for (t, _) in &parts.order {
            s.push_str(&format!(
                "component {:?}: {} ports, {} operations, {}\n",
                t.name(),
                t.ports().len(),
                t.operations().len(),
                t.state()
            ));
            for p in t.provided() {
                s.push_str(&format!("  provides {}\n", p.name));
            }
            for r in t.required() {
                let to = if r.bound_to.is_empty() {
                    "unbound".to_string()
                } else {
                    r.bound_to.join(", ")
                };
                s.push_str(&format!("  requires {} -> {to}\n", r.name));
            }
        }
        s
    }

    /// Refuses every write to an output from now on ([`device_interface::DeviceError::Held`]);
    /// returns once the writes under way have reached their cards. The first step of a
    /// stop, before anything else can hang; [`shutdown`](Self::shutdown) does it too.
    pub fn hold_outputs(&self) {
        // Never waits for a reload under way: a card it adds after this sees the flag and
        // holds itself (see `reload`); the cards it took out it holds itself.
        self.stopping
            .store(true, std::sync::atomic::Ordering::SeqCst);
        // ThreadScope first, its pulses under way ended: the hold below would refuse their
        // lows and leave their bits high (the stop's first step is this call, so the close
        // is here, not later in `shutdown`). A step is given SCOPE_CLOSE to end: on a
        // loaded host (a test rig's emulated CPU beside a build) one second was not
        // always enough. Idempotent: a second call finds no pulse under way.
        if !self
            .runtime
            .thread_scope()
            .close(Instant::now() + SCOPE_CLOSE)
        {
            tracing::warn!(
                "ThreadScope: a step still under way after {SCOPE_CLOSE:?}; its bit may stay high"
            );
        }
        for c in &self.parts().cards {
            c.hold.hold();
        }
    }

    /// True once the stop began ([`hold_outputs`](Self::hold_outputs)).
    pub(crate) fn is_stopping(&self) -> bool {
        self.stopping.load(std::sync::atomic::Ordering::SeqCst)
    }

    /// Stops every component but the cards' bus sides in reverse start order, drives every
    /// output to its safe value, lets each card get them to the hardware, then stops the bus
    /// sides. Returns a line per card with the outputs as left.
    pub fn shutdown(&self) -> Vec<String> {
        // From here on only the safe values are written: every other write is refused.
        self.hold_outputs();
        // A reload under way ends first (its cards held as they come); none begins after.
        let mut running = self.running();
        running.stopping = true;
        let parts = self.parts();
        for s in parts.all_servers() {
            s.stop();
        }
        let is_bus = |t: &TaskContext| {
            parts
                .cards
                .iter()
                .any(|c| c.bus.iter().any(|b| b.name() == t.name()))
        };
        for (t, _) in parts.order.iter().rev().filter(|(t, _)| !is_bus(t)) {
            stop_task(t);
        }
        settle_cards(&parts.cards);
        // Last, the outputs safe: the ThreadScope recording, complete since its close
        // above (finish logs its counts; a disk that hangs holds the stop 5 s at most).
        if let Some(vcd) = self.runtime.thread_scope().vcd() {
            let _ = vcd.finish();
        }
        parts.cards.iter().map(CardRt::outputs_line).collect()
    }
}

/// Stops `t` if it runs (a refusal is logged).
pub(crate) fn stop_task(t: &TaskContext) {
    if matches!(t.state(), TaskState::Running | TaskState::RunTimeError)
        && let Err(e) = t.stop()
    {
        tracing::warn!("{e}");
    }
}

/// Starts the servers; one that cannot start is logged (and returned), the others start.
pub(crate) fn start_servers<'s>(
    servers: impl IntoIterator<Item = &'s Box<dyn Server>>,
) -> Vec<String> {
    let mut failed = Vec::new();
    for s in servers {
        match s.start() {
            Ok(addr) => tracing::info!("{} listening on {addr}", s.name()),
            Err(e) => {
                tracing::error!("{}: cannot start: {e}", s.name());
                failed.push(format!("{}: cannot start: {e}", s.name()));
            }
        }
    }
    failed
}

/// Starts, in order, the stopped components the deployment asks to start.
pub(crate) fn start_tasks(
    order: &[(TaskContext, bool)],
) -> Result<(), rtt::component::LifecycleError> {
    for (t, start) in order {
        if *start && t.state() == TaskState::Stopped {
            t.start()?;
        }
    }
    Ok(())
}

/// The end of every card's life, at stop or when a reload rebuilds or removes it, its
/// outputs held and every writer but its bus side stopped: drives each output to its safe
/// value, lets each card get them to the hardware, then stops the bus sides.
pub(crate) fn settle_cards(cards: &[CardRt]) {
    // A card whose driver panics must not keep the next cards from their safe values.
    let each_card = |what: &str, f: &dyn Fn(&CardRt)| {
        for c in cards {
            if std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(c))).is_err() {
                tracing::error!("card {:?}: its driver panicked while {what}", c.name);
            }
        }
    };
    each_card("driving its safe values", &|c| c.outputs.drive_safe());
    let deadline = Instant::now() + SETTLE;
    each_card("settling its safe values", &|c| {
        // A bus side that is not running carries nothing: the card does not wait for it.
        let bus_running = c
            .bus
            .iter()
            .all(|t| matches!(t.state(), TaskState::Running | TaskState::RunTimeError));
        if let Err(e) = c.card.settle(deadline, bus_running) {
            tracing::error!("card {:?}: {e}", c.name);
        }
    });
    for c in cards.iter().rev() {
        for t in c.bus.iter().rev() {
            stop_task(t);
        }
    }
}

impl CardRt {
    /// `card "x" outputs at stop: analog [..], digital on [..]`.
    pub(crate) fn outputs_line(&self) -> String {
        let analog: Vec<String> = self.outputs.analog_device().map_or_else(Vec::new, |ao| {
            (0..ao.channel_count())
                .map(|ch| {
                    ao.read_back(ch)
                        .map_or_else(|e| e.to_string(), |v| format!("{v}"))
                })
                .collect()
        });
        let on: Vec<String> = self.outputs.digital_device().map_or_else(Vec::new, |d| {
            (0..d.output_count())
                .filter(|b| d.check_bit(*b).unwrap_or(false))
                .map(|b| b.to_string())
                .collect()
        });
        format!(
            "card {:?} outputs at stop: analog [{}], digital on [{}]",
            self.name,
            analog.join(", "),
            on.join(", ")
        )
    }
}
