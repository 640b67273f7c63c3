//! A built gateway: the runtime with its components, the cards, the servers; started,
//! watched, and stopped with every output at its safe value.
//!
//! [`Gateway::build`] (in phases, in the `build` module) does everything short of starting
//! threads, so `hwgw check` runs the very code `hwgw run` does and finds every error it
//! would, each located in the file.

use crate::config::{ChannelNames, Deployment};
use crate::outputs::{CardOutputs, Hold, OutputReport};
use crate::problems::KeyPath;
use driver_api::{Card, CardStatus, Server};
use rtt::{Runtime, TaskContext, TaskState};
use serde::{Deserialize, Serialize};
use std::sync::Arc;
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
    pub(crate) card: Box<dyn Card>,
    /// Its outputs under the output policy.
    pub(crate) outputs: Arc<CardOutputs>,
    /// Port names of its channels (given, or from the driver).
    pub(crate) names: ChannelNames,
    /// Its bus-side components.
    pub(crate) bus: Vec<TaskContext>,
}

/// One card in `hwgw status`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CardReport {
    /// The card.
    pub name: String,
    /// Its driver.
    pub driver: String,
    /// Its bus and counters.
    #[serde(flatten)]
    pub status: CardStatus,
    /// Its outputs: how many hwgw wrote, watchdog trips.
    pub outputs: OutputReport,
}

/// A server's state, for `status`.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ServerReport {
    /// Its deployment key (`modbus_server`).
    pub name: String,
    /// Where it listens, and its counters.
    #[serde(flatten)]
    pub status: CardStatus,
}

/// A built (and possibly running) gateway.
pub struct Gateway {
    runtime: Runtime,
    cards: Vec<CardRt>,
    /// What is served beside the cards (the Modbus server), if configured.
    servers: Vec<Box<dyn Server>>,
    /// Components in start order.
    order: Vec<TaskContext>,
    /// Which components the deployment asked to start.
    start: Vec<bool>,
    /// Held when the stop begins: the guarded outputs refuse every write from then on.
    hold: Arc<Hold>,
    /// Where ThreadScope records each thread's bit once started ([`Self::record_thread_scope`]):
    /// the name its numbered files are made after, and how many of them are kept.
    pub(crate) scope_vcd: Option<(std::path::PathBuf, u32)>,
    /// The Zenoh node of the `[zenoh]` section (also among the servers).
    pub(crate) zenoh: Option<Arc<crate::remote::Node>>,
}

impl Gateway {
    pub(crate) fn new(
        runtime: Runtime,
        cards: Vec<CardRt>,
        servers: Vec<Box<dyn Server>>,
        order: Vec<TaskContext>,
        start: Vec<bool>,
        hold: Arc<Hold>,
    ) -> Gateway {
        Gateway {
            runtime,
            cards,
            servers,
            order,
            start,
            hold,
            scope_vcd: None,
            zenoh: None,
        }
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

    /// Applies the properties of `new` (the deployment file read again) to the running
    /// components: all-or-nothing per component. Anything else that changed — cards,
    /// aliases, components, activities, connections — is refused: it needs a restart.
    /// Returns one line per change, applied or refused, and the components whose new
    /// properties were applied.
    pub fn reload(&self, old: &Deployment, new: &Deployment) -> (Vec<String>, Vec<String>) {
        let mut report = Vec::new();
        let mut applied_to = Vec::new();
        let refuse = |what: &str| format!("{what} changed: restart hwgw to apply");
        if old.cards != new.cards {
            report.push(refuse("cards"));
        }
        if old.aliases != new.aliases {
            report.push(refuse("aliases"));
        }
        if old.connections != new.connections {
            report.push(refuse("connections"));
        }
        if old.zenoh != new.zenoh {
            report.push(refuse("[zenoh]"));
        }
        if (
            old.thread_scope,
            &old.thread_scope_vcd,
            old.thread_scope_vcd_keep,
            old.cpu_dma_latency_us,
            &old.control_socket,
        ) != (
            new.thread_scope,
            &new.thread_scope_vcd,
            new.thread_scope_vcd_keep,
            new.cpu_dma_latency_us,
            &new.control_socket,
        ) {
            report.push(refuse("runtime settings"));
        }
        let shape = |c: &crate::config::ComponentConfig| {
            (c.name.clone(), c.kind.clone(), c.activity.clone(), c.start)
        };
        if old.components.iter().map(shape).collect::<Vec<_>>()
            != new.components.iter().map(shape).collect::<Vec<_>>()
        {
            report.push(refuse("components (names, types, activities or start)"));
            return (report, applied_to);
        }
        for (o, n) in old.components.iter().zip(&new.components) {
            if o.properties == n.properties {
                continue;
            }
            let applied = self
                .runtime
                .component(&n.name)
                .map_err(|e| e.to_string())
                .and_then(|t| {
                    t.properties()
                        .load_toml(&n.properties)
                        .map_err(|e| e.to_string())
                });
            if applied.is_ok() {
                applied_to.push(n.name.clone());
            }
            report.push(match applied {
                Ok(()) => format!(
                    "component {:?}: properties reloaded (those read at configure take effect at the next configure)",
                    n.name
                ),
                Err(e) => format!("component {:?}: properties not reloaded: {}", n.name, e.replace('\n', "; ")),
            });
        }
        if report.is_empty() {
            report.push("nothing changed".into());
        }
        (report, applied_to)
    }

    /// Starts the servers (the Modbus server), if configured, then the components the
    /// deployment asks to start, in order (each card's bus side before its IO components).
    pub fn start(&self) -> Result<(), rtt::component::LifecycleError> {
        for s in &self.servers {
            match s.start() {
                Ok(addr) => tracing::info!("{} listening on {addr}", s.name()),
                Err(e) => tracing::error!("{}: cannot start: {e}", s.name()),
            }
        }
        for (t, start) in self.order.iter().zip(&self.start) {
            if *start && t.state() == TaskState::Stopped {
                t.start()?;
            }
        }
        Ok(())
    }

    /// `Ok` while every component that should run is running and every periodic activity
    /// keeps its period; else what is wrong. This is what feeds the systemd watchdog. A
    /// component in RunTimeError (waiting out a device that is offline, stepping on time)
    /// counts as running: restarting the service would not bring the device back; its
    /// state shows in `hwgw ls` and `status`.
    pub fn health(&self) -> Result<(), String> {
        self.health_since(&mut Vec::new())
    }

    /// [`health`](Self::health), and also wrong when a periodic activity overran its
    /// period since the last call with the same `seen` (a spell over by now still counts:
    /// the watchdog is fed only after an interval the gateway was healthy throughout);
    /// `seen` keeps each activity's count of unhealthy spells between calls.
    pub fn health_since(&self, seen: &mut Vec<u64>) -> Result<(), String> {
        seen.resize(self.order.len(), 0);
        let mut wrong = Vec::new();
        for ((t, start), seen) in self.order.iter().zip(&self.start).zip(seen.iter_mut()) {
            let stats = t.stats();
            let spells = std::mem::replace(seen, stats.unhealthy_spells);
            match t.state() {
                TaskState::Running | TaskState::RunTimeError => {}
                s if *start => wrong.push(format!("{} is {s}", t.name())),
                _ => continue,
            }
            if !stats.healthy || stats.unhealthy_spells > spells {
                wrong.push(format!("{} overruns its period", t.name()));
            }
        }
        for s in &self.servers {
            if let Err(e) = s.health() {
                wrong.push(e);
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
        self.servers
            .iter()
            .find(|s| s.name() == name)
            .and_then(|s| s.address())
    }

    /// Every card's bus and counters, for `status`.
    pub fn card_status(&self) -> Vec<CardReport> {
        self.cards
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
        self.servers
            .iter()
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
        for c in &self.cards {
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
        for t in &self.order {
            s.push_str(&format!(
                "component {:?}: {} ports, {} operations, {}\n",
                t.name(),
                t.ports().len(),
                t.operations().len(),
                t.state()
            ));
        }
        s
    }

    fn is_bus(&self, t: &TaskContext) -> bool {
        self.cards
            .iter()
            .any(|c| c.bus.iter().any(|b| b.name() == t.name()))
    }

    /// Refuses every write to an output from now on ([`device_interface::DeviceError::Held`]);
    /// returns once the writes under way have reached their cards. The first step of a
    /// stop, before anything else can hang; [`shutdown`](Self::shutdown) does it too.
    pub fn hold_outputs(&self) {
        self.hold.hold();
    }

    /// Stops every component but the cards' bus sides in reverse start order, drives every
    /// output to its safe value, lets each card get them to the hardware, then stops the bus
    /// sides. Returns a line per card with the outputs as left.
    pub fn shutdown(&self) -> Vec<String> {
        // ThreadScope first, its pulses under way ended: the hold below would refuse their
        // lows and leave their bits high. A step is given SCOPE_CLOSE to end: on a loaded
        // host (a test rig's emulated CPU beside a build) one second was not always enough.
        if !self
            .runtime
            .thread_scope()
            .close(Instant::now() + SCOPE_CLOSE)
        {
            tracing::warn!(
                "ThreadScope: a step still under way after {SCOPE_CLOSE:?}; its bit may stay high"
            );
        }
        // From here on only the safe values are written: every other write is refused.
        self.hold_outputs();
        for s in &self.servers {
            s.stop();
        }
        let stop = |t: &TaskContext| {
            if matches!(t.state(), TaskState::Running | TaskState::RunTimeError)
                && let Err(e) = t.stop()
            {
                tracing::warn!("{e}");
            }
        };
        for t in self.order.iter().rev().filter(|t| !self.is_bus(t)) {
            stop(t);
        }
        // A card whose driver panics must not keep the next cards from their safe values.
        let each_card = |what: &str, f: &dyn Fn(&CardRt)| {
            for c in &self.cards {
                if std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(c))).is_err() {
                    tracing::error!("card {:?}: its driver panicked while {what}", c.name);
                }
            }
        };
        each_card("driving its safe values", &|c| c.outputs.drive_safe());
        let deadline = Instant::now() + SETTLE;
        each_card("settling its safe values", &|c| {
            if let Err(e) = c.card.settle(deadline) {
                tracing::error!("card {:?}: {e}", c.name);
            }
        });
        for t in self.order.iter().rev().filter(|t| self.is_bus(t)) {
            stop(t);
        }
        // Last, the outputs safe: the ThreadScope recording, complete since its close
        // above (finish logs its counts; a disk that hangs holds the stop 5 s at most).
        if let Some(vcd) = self.runtime.thread_scope().vcd() {
            let _ = vcd.finish();
        }
        self.cards.iter().map(CardRt::outputs_line).collect()
    }
}

impl CardRt {
    /// `card "x" outputs at stop: analog [..], digital on [..]`.
    fn outputs_line(&self) -> String {
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
