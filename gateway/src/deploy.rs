//! From a deployment to a running gateway: cards, registry, aliases, runtime, IO
//! components, user components, connections; and back down to safe outputs.
//!
//! [`Gateway::build`] does everything short of starting threads, so `hwgw check` runs the
//! very code `hwgw run` does and finds every error it would, each located in the file.

use crate::config::{AliasInterface, Deployment, Location, Problem, locate, millis, split_port};
use crate::{components, io};
use device_interface::{AnalogIn, AnalogOut, DigitalIn, DigitalOut, Registry};
use driver_sim::SimCard;
use rtt::{
    ActivitySpec, Component, Context, HookResult, Runtime, RuntimeOptions, TaskContext, TaskState,
};
use std::sync::Arc;

/// A path segment: a table key or an array index.
enum Seg<'a> {
    Key(&'a str),
    Index(usize),
}

/// Where the value at `path` starts in `text`.
fn locate_path(file: &str, text: &str, path: &[Seg<'_>]) -> Option<Location> {
    let root = toml::de::DeTable::parse(text).ok()?;
    let mut span = root.span();
    let mut value: Option<toml::de::DeValue<'_>> =
        Some(toml::de::DeValue::Table(root.into_inner()));
    for seg in path {
        let next = match (value.take()?, seg) {
            (toml::de::DeValue::Table(t), Seg::Key(k)) => t
                .into_iter()
                .find(|(key, _)| key.get_ref() == k)
                .map(|(_, v)| v),
            (toml::de::DeValue::Array(a), Seg::Index(i)) => a.into_iter().nth(*i),
            _ => None,
        }?;
        span = next.span();
        value = Some(next.into_inner());
    }
    Some(locate(file, text, span.start))
}

fn add(problems: &mut Vec<Problem>, location: Option<Location>, path: String, message: String) {
    problems.push(Problem {
        location,
        path,
        message,
    });
}

/// The sim card of a deployment, with what it needs at shutdown.
struct SimCardRt {
    name: String,
    card: Arc<SimCard>,
    safe_analog_out: Vec<f64>,
    safe_digital_out_on: Vec<u32>,
}

/// Runs a card's bus cycle.
struct CardCycle(Arc<SimCard>);

impl Component for CardCycle {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.0.step();
        Ok(())
    }
}

/// A built (and possibly running) gateway.
pub struct Gateway {
    runtime: Runtime,
    cards: Vec<SimCardRt>,
    /// Components in start order.
    order: Vec<TaskContext>,
    /// Which components the deployment asked to start.
    start: Vec<bool>,
}

impl Gateway {
    /// Builds everything in `deployment` (from `file`, whose `text` locates errors). Nothing
    /// is started. Returns every problem found.
    pub fn build(
        deployment: &Deployment,
        file: &str,
        text: &str,
        types: &components::ComponentTypes,
    ) -> Result<Gateway, Vec<Problem>> {
        let mut problems = Vec::new();
        let at = |path: &[Seg<'_>]| locate_path(file, text, path);

        // Cards and their devices.
        let registry = Arc::new(Registry::new());
        let mut cards = Vec::new();
        for (i, c) in deployment.cards.iter().enumerate() {
            let here = || at(&[Seg::Key("card"), Seg::Index(i)]);
            let path = format!("card[{i}]");
            if let Some(first) = deployment.cards[..i].iter().position(|o| o.name == c.name) {
                add(
                    &mut problems,
                    here(),
                    format!("{path}.name"),
                    format!(
                        "card {:?} is defined twice (first as card[{first}])",
                        c.name
                    ),
                );
                continue;
            }
            if !(c.period_ms.is_finite() && c.period_ms > 0.0) {
                add(
                    &mut problems,
                    here(),
                    format!("{path}.period_ms"),
                    format!("{} ms: expected a period above 0", c.period_ms),
                );
                continue;
            }
            match (c.driver.as_str(), &c.sim) {
                ("sim", Some(section)) => {
                    match SimCard::new(section.get_ref(), Arc::new(rtt::time::MonotonicClock)) {
                        Ok(card) => {
                            let counts = [
                                AnalogIn::channel_count(&*card),
                                AnalogOut::channel_count(&*card),
                                card.input_count(),
                                DigitalOut::output_count(&*card),
                            ];
                            if let Err((key, message)) = c.names.check(counts) {
                                add(
                                    &mut problems,
                                    at(&[Seg::Key("card"), Seg::Index(i), Seg::Key("names")]),
                                    format!("{path}.{key}"),
                                    message,
                                );
                                continue;
                            }
                            if let Err(e) = card.register(&registry, &c.name) {
                                add(&mut problems, here(), format!("{path}.name"), e.to_string());
                            }
                            let safe = c.safe_analog_out.clone().unwrap_or_else(|| {
                                (0..AnalogOut::channel_count(&*card))
                                    .map(|ch| AnalogOut::read_back(&*card, ch).unwrap_or(0.0))
                                    .collect()
                            });
                            cards.push(SimCardRt {
                                name: c.name.clone(),
                                card,
                                safe_analog_out: safe,
                                safe_digital_out_on: c.safe_digital_out_on.clone(),
                            });
                        }
                        Err(e) => add(
                            &mut problems,
                            Some(locate(file, text, section.span().start)),
                            format!("{path}.sim"),
                            format!("card {:?}: {e}", c.name),
                        ),
                    }
                }
                ("sim", None) => add(
                    &mut problems,
                    here(),
                    path.clone(),
                    format!(
                        "card {:?} uses driver \"sim\" but has no [card.sim] section",
                        c.name
                    ),
                ),
                (other, _) => add(
                    &mut problems,
                    at(&[Seg::Key("card"), Seg::Index(i), Seg::Key("driver")]),
                    format!("{path}.driver"),
                    format!("unknown driver {other:?}; this build has: sim"),
                ),
            }
        }

        for (i, a) in deployment.aliases.iter().enumerate() {
            let r = match a.interface {
                AliasInterface::AnalogIn => registry.analog_in().alias(&a.name, &a.target),
                AliasInterface::AnalogOut => registry.analog_out().alias(&a.name, &a.target),
                AliasInterface::DigitalIn => registry.digital_in().alias(&a.name, &a.target),
                AliasInterface::DigitalOut => registry.digital_out().alias(&a.name, &a.target),
                AliasInterface::Encoder => registry.encoder().alias(&a.name, &a.target),
            };
            if let Err(e) = r {
                add(
                    &mut problems,
                    at(&[Seg::Key("alias"), Seg::Index(i)]),
                    format!("alias[{i}]"),
                    e.to_string(),
                );
            }
        }

        let options = RuntimeOptions {
            thread_scope: deployment.thread_scope,
            cpu_dma_latency_us: deployment.cpu_dma_latency_us,
            ..RuntimeOptions::default()
        };
        let runtime = match Runtime::new(registry, options) {
            Ok(r) => r,
            Err(e) => {
                add(
                    &mut problems,
                    at(&[Seg::Key("thread_scope")]),
                    "thread_scope".into(),
                    format!(
                        "{e} (add an [[alias]] with interface = \"digital_out\" and name = \"ThreadScope\")"
                    ),
                );
                return Err(problems);
            }
        };

        // Card cycles, then each card's IO components.
        let mut order = Vec::new();
        for (i, c) in cards.iter().enumerate() {
            let cfg = &deployment.cards[i];
            let card = c.card.clone();
            match runtime.add(
                &c.name,
                ActivitySpec::periodic(millis(cfg.period_ms)),
                false,
                move |_| Ok(CardCycle(card)),
            ) {
                Ok(t) => order.push(t),
                Err(e) => add(
                    &mut problems,
                    at(&[Seg::Key("card"), Seg::Index(i)]),
                    format!("card[{i}]"),
                    e.to_string(),
                ),
            }
            let sample = millis(cfg.sample_period_ms.unwrap_or(cfg.period_ms));
            match io::build(&runtime, &c.name, sample, &cfg.names) {
                Ok(ts) => order.extend(ts),
                Err(e) => add(
                    &mut problems,
                    at(&[Seg::Key("card"), Seg::Index(i)]),
                    format!("card[{i}]"),
                    e.to_string(),
                ),
            }
        }
        let mut start = vec![true; order.len()];

        // User components: build, set properties, configure.
        for (i, c) in deployment.components.iter().enumerate() {
            let here = |key: &str| at(&[Seg::Key("component"), Seg::Index(i), Seg::Key(key)]);
            let path = format!("component[{i}]");
            if let crate::config::ActivityConfig::Periodic { period_ms, .. } = c.activity
                && !(period_ms.is_finite() && period_ms > 0.0)
            {
                add(
                    &mut problems,
                    here("activity"),
                    format!("{path}.activity.period_ms"),
                    format!("{period_ms} ms: expected a period above 0"),
                );
                continue;
            }
            let task = match types.build(&runtime, &c.name, &c.kind, c.activity.spec()) {
                Ok(Some(t)) => t,
                Ok(None) => {
                    add(
                        &mut problems,
                        here("type"),
                        format!("{path}.type"),
                        format!(
                            "unknown component type {:?}; this build has: {}",
                            c.kind,
                            types.names().join(", ")
                        ),
                    );
                    continue;
                }
                Err(e) => {
                    add(
                        &mut problems,
                        here("name"),
                        format!("{path}.name"),
                        e.to_string(),
                    );
                    continue;
                }
            };
            if let Err(e) = task.properties().load_toml(&c.properties) {
                for line in e.to_string().lines() {
                    add(
                        &mut problems,
                        here("properties"),
                        format!("{path}.properties"),
                        line.to_string(),
                    );
                }
                continue;
            }
            if task.state() == TaskState::PreOperational
                && let Err(e) = task.configure()
            {
                add(&mut problems, here("name"), path.clone(), e.to_string());
                continue;
            }
            order.push(task);
            start.push(c.start);
        }

        // Connections.
        for (i, c) in deployment.connections.iter().enumerate() {
            let here = |key: &str| at(&[Seg::Key("connection"), Seg::Index(i), Seg::Key(key)]);
            let path = format!("connection[{i}]");
            let end =
                |key: &str, address: &str| -> Result<Arc<dyn rtt::component::DynPort>, Problem> {
                    let (comp, port) = split_port(address).ok_or_else(|| Problem {
                        location: here(key),
                        path: format!("{path}.{key}"),
                        message: format!("{address:?}: expected \"component.port\""),
                    })?;
                    let task = runtime.component(comp).map_err(|e| Problem {
                        location: here(key),
                        path: format!("{path}.{key}"),
                        message: e.to_string(),
                    })?;
                    task.port(port).map_err(|e| Problem {
                        location: here(key),
                        path: format!("{path}.{key}"),
                        message: e.to_string(),
                    })
                };
            match (end("from", &c.from), end("to", &c.to)) {
                (Ok(from), Ok(to)) => {
                    if let Err(e) = from.connect_to(&*to, c.policy) {
                        add(
                            &mut problems,
                            here("from"),
                            path,
                            format!("{} -> {}: {e}", c.from, c.to),
                        );
                    }
                }
                (a, b) => {
                    problems.extend(a.err());
                    problems.extend(b.err());
                }
            }
        }

        if problems.is_empty() {
            Ok(Gateway {
                runtime,
                cards,
                order,
                start,
            })
        } else {
            Err(problems)
        }
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
        if (
            old.thread_scope,
            old.cpu_dma_latency_us,
            &old.control_socket,
        ) != (
            new.thread_scope,
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

    /// Starts the components the deployment asks to start, in order.
    pub fn start(&self) -> Result<(), rtt::component::LifecycleError> {
        for (t, start) in self.order.iter().zip(&self.start) {
            if *start && t.state() == TaskState::Stopped {
                t.start()?;
            }
        }
        Ok(())
    }

    /// `Ok` while every component that should run is running and every periodic activity
    /// keeps its period; else what is wrong. This is what feeds the systemd watchdog.
    pub fn health(&self) -> Result<(), String> {
        let mut wrong = Vec::new();
        for (t, start) in self.order.iter().zip(&self.start) {
            match t.state() {
                TaskState::Running => {}
                s if *start => wrong.push(format!("{} is {s}", t.name())),
                _ => continue,
            }
            if !t.stats().healthy {
                wrong.push(format!("{} overruns its period", t.name()));
            }
        }
        if wrong.is_empty() {
            Ok(())
        } else {
            Err(wrong.join("; "))
        }
    }

    /// The runtime.
    pub fn runtime(&self) -> &Runtime {
        &self.runtime
    }

    /// A summary of what was loaded, for the start-up log.
    pub fn summary(&self) -> String {
        let mut s = String::new();
        for c in &self.cards {
            s.push_str(&format!("card {:?} (sim)\n", c.name));
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

    /// Stops every component in reverse start order, then drives every output to its safe
    /// value. Returns a line per card with the outputs as left.
    pub fn shutdown(&self) -> Vec<String> {
        for t in self.order.iter().rev() {
            if matches!(t.state(), TaskState::Running | TaskState::RunTimeError)
                && let Err(e) = t.stop()
            {
                tracing::warn!("{e}");
            }
        }
        let mut lines = Vec::new();
        for c in &self.cards {
            let card = &*c.card;
            for (ch, v) in c.safe_analog_out.iter().enumerate() {
                if let Err(e) = AnalogOut::write(card, ch as u32, *v) {
                    tracing::error!(
                        "card {:?}: analog output {ch} not at its safe value {v}: {e}",
                        c.name
                    );
                }
            }
            for b in 0..DigitalOut::output_count(card) {
                if let Err(e) = card.set_bit(b, c.safe_digital_out_on.contains(&b)) {
                    tracing::error!(
                        "card {:?}: digital output {b} not at its safe value: {e}",
                        c.name
                    );
                }
            }
            let ao: Vec<String> = (0..AnalogOut::channel_count(card))
                .map(|ch| {
                    AnalogOut::read_back(card, ch)
                        .map_or_else(|e| e.to_string(), |v| format!("{v}"))
                })
                .collect();
            let on: Vec<String> = (0..DigitalOut::output_count(card))
                .filter(|b| card.check_bit(*b).unwrap_or(false))
                .map(|b| b.to_string())
                .collect();
            lines.push(format!(
                "card {:?} outputs at stop: analog [{}], digital on [{}]",
                c.name,
                ao.join(", "),
                on.join(", ")
            ));
        }
        lines
    }
}
