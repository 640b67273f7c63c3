//! [`Gateway::build`](crate::deploy::Gateway::build) in phases: cards, aliases, runtime,
//! bus sides and IO components, user components, connections, servers. Each phase reports
//! through one [`Problems`] collector, keyed by the path of what is wrong.

use crate::config::{CARD_KEYS, CardConfig, ChannelNames, Deployment, millis, split_port};
use crate::deploy::{CardRt, Gateway};
use crate::drivers::SectionError;
use crate::outputs::{CardOutputs, Hold, OutputDevices, OutputSpec};
use crate::problems::{KeyPath, Problem, Problems, Source};
use crate::types::Types;
use crate::{checks, io};
use device_interface::Registry;
use driver_api::CardContext;
use rtt::component::DynPort;
use rtt::{ActivitySpec, InitialState, Runtime, RuntimeOptions, TaskContext, TaskState};
use std::any::{Any, TypeId};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

/// The output watchdog's component name.
pub const OUTPUT_WATCHDOG: &str = "output_watchdog";

/// Applies the output policy's watchdog to the cards that need it, every 10 ms.
struct OutputWatchdog {
    cards: Vec<Arc<CardOutputs>>,
    components: HashMap<String, TaskContext>,
}

impl rtt::Component for OutputWatchdog {
    fn update_hook(&mut self, ctx: &mut rtt::Context<'_>) -> rtt::HookResult {
        let now = ctx.timing().started.as_nanos();
        let state = |name: &str| self.components.get(name).map(TaskContext::state);
        for c in &self.cards {
            c.watch(now, &state);
        }
        Ok(())
    }
}

/// Notes the component of `from` (`component.port`) as a writer of the card output behind
/// `to`, when `to` is a port of a card's output IO component (`card.ao.*`, `card.do.*`).
fn note_writer(cards: &mut [CardRt], from: &str, to: &str) {
    let (Some((writer, _)), Some((component, port))) = (split_port(from), split_port(to)) else {
        return;
    };
    let Some(card) = component
        .strip_suffix(".ao")
        .or_else(|| component.strip_suffix(".do"))
    else {
        return;
    };
    if let Some(c) = cards.iter_mut().find(|c| c.name == card)
        && let Some(outputs) = Arc::get_mut(&mut c.outputs)
    {
        outputs.add_writer(port, writer);
    }
}

/// One build under way.
struct Build<'d, 's, 'a> {
    d: &'d Deployment,
    types: &'d Types,
    problems: Problems<'s, 'a>,
    /// Files a card names (DBC) are relative to the deployment file.
    base: &'d Path,
    /// The gateway's stop gate: once held, the guarded outputs refuse writes.
    hold: Arc<Hold>,
}

impl Gateway {
    /// Builds everything in `deployment` (from `file`, whose `text` locates errors) with
    /// the component and driver `types`. Nothing is started. Returns every problem found.
    pub fn build(
        deployment: &Deployment,
        file: &str,
        text: &str,
        types: &Types,
    ) -> Result<Gateway, Vec<Problem>> {
        build(deployment, file, text, types)
    }

    /// Parses a deployment's `text` (read from `file`) and builds it, as `hwgw check` and
    /// `hwgw run` do: the gateway and the deployment, or every problem, one a line.
    pub fn from_text(
        text: &str,
        file: &str,
        types: &Types,
    ) -> Result<(Gateway, Deployment), String> {
        let d = Deployment::parse(text, file).map_err(|e| e.to_string())?;
        let gw = build(&d, file, text, types).map_err(|problems| {
            problems
                .iter()
                .map(|p| p.to_string())
                .collect::<Vec<_>>()
                .join("\n")
        })?;
        Ok((gw, d))
    }
}

fn build(d: &Deployment, file: &str, text: &str, types: &Types) -> Result<Gateway, Vec<Problem>> {
    let source = Source::new(file, text);
    let base = Path::new(file).parent().unwrap_or(Path::new(""));
    let mut b = Build {
        d,
        types,
        problems: Problems::new(&source),
        base,
        hold: Arc::new(Hold::default()),
    };
    for (key, message) in checks::control(d) {
        b.problems.at(&KeyPath::top(&key), message);
    }
    let registry = Arc::new(Registry::new());
    let mut cards = b.cards(&registry);
    b.aliases(&registry);
    let zenoh = b.zenoh(&registry);
    let Some(runtime) = b.runtime(registry) else {
        return Err(b.problems.into_vec());
    };
    let mut order = b.bus_and_io(&runtime, &mut cards);
    if let Some(node) = &zenoh {
        order.extend(b.remote_io(&runtime, node));
    }
    let mut start = vec![true; order.len()];
    b.components(&runtime, &mut order, &mut start);
    b.connections(&runtime, &mut cards, zenoh.as_deref());
    if let (Some(node), Some(section)) = (&zenoh, &d.zenoh) {
        for (key, message) in crate::remote::exports(node, section, &runtime) {
            b.problems.at(&KeyPath::top("zenoh").join(&key), message);
        }
    }
    if let Some(w) = b.output_watchdog(&runtime, &cards) {
        order.push(w);
        start.push(true);
    }
    let mut servers = b.servers(&runtime);
    servers.extend(zenoh.as_ref().map(crate::remote::server));
    let scope_vcd = b.scope_vcd();
    for (key, message) in checks::shared_files(d, base) {
        b.problems.at(&key, message);
    }
    if !b.problems.is_empty() {
        return Err(b.problems.into_vec());
    }
    let mut gw = Gateway::new(runtime, cards, servers, order, start, b.hold);
    gw.scope_vcd = scope_vcd;
    gw.zenoh = zenoh;
    Ok(gw)
}

impl Build<'_, '_, '_> {
    /// Every card: checked, built by its driver, its devices registered.
    fn cards(&mut self, registry: &Registry) -> Vec<CardRt> {
        let mut shared: HashMap<TypeId, Box<dyn Any + Send>> = HashMap::new();
        let mut cards = Vec::new();
        for (i, c) in self.d.cards.iter().enumerate() {
            let at = KeyPath::top("card").index(i);
            if let Some(first) = self.d.cards[..i].iter().position(|o| o.name == c.name) {
                let msg = format!(
                    "card {:?} is defined twice (first as card[{first}])",
                    c.name
                );
                self.problems.at(&at.key("name"), msg);
                continue;
            }
            if let Err(msg) = checks::period(c.period_ms) {
                self.problems.at(&at.key("period_ms"), msg);
                continue;
            }
            if let Some(Err(msg)) = c.sample_period_ms.map(checks::period) {
                self.problems.at(&at.key("sample_period_ms"), msg);
                continue;
            }
            if let Err(msg) = c.thread.check() {
                self.problems.at(&at.key("thread"), msg);
                continue;
            }
            let Some(card) = self.card(&at, c, &mut shared) else {
                continue;
            };
            if let Some(rt) = self.register(&at, c, card, registry) {
                cards.push(rt);
            }
        }
        cards
    }

    /// Builds card `c` from its driver section.
    fn card(
        &mut self,
        at: &KeyPath,
        c: &CardConfig,
        shared: &mut HashMap<TypeId, Box<dyn Any + Send>>,
    ) -> Option<Box<dyn driver_api::Card>> {
        let drivers = &self.types.drivers;
        let Some(driver) = drivers.get(&c.driver) else {
            let msg = format!(
                "unknown driver {:?}; this build has: {}",
                c.driver,
                drivers.names().join(", ")
            );
            self.problems.at(&at.key("driver"), msg);
            return None;
        };
        let mut ok = true;
        for key in c.sections.keys().filter(|k| **k != c.driver) {
            ok = false;
            let msg = if drivers.contains(key) {
                format!(
                    "card {:?} uses driver {:?}: a [card.{key}] section belongs to driver {key:?}",
                    c.name, c.driver
                )
            } else {
                format!(
                    "unknown key {key:?}; a card has {}, and its driver's section [card.{}]",
                    CARD_KEYS.join(", "),
                    c.driver
                )
            };
            self.problems.at_key(&at.key(key), msg);
        }
        let section_path = at.key(&c.driver);
        let Some(section) = self.problems.source().value(&section_path) else {
            let msg = format!(
                "card {:?} uses driver {:?} but has no [card.{}] section",
                c.name, c.driver, c.driver
            );
            self.problems.at(at, msg);
            return None;
        };
        if !ok {
            return None;
        }
        let mut ctx = CardContext::new(
            &c.name,
            millis(c.period_ms),
            &c.thread,
            self.base,
            Arc::new(rtt::time::MonotonicClock),
            shared,
        );
        match driver.build(section.clone(), &mut ctx) {
            Ok(card) => Some(card),
            Err(SectionError::Parse {
                path,
                span,
                message,
            }) => {
                self.problems
                    .at_span(&section_path.join(&path), span, message);
                None
            }
            Err(SectionError::Card(e)) => {
                let path = match &e.key {
                    Some(k) => section_path.join(k),
                    None => section_path,
                };
                self.problems
                    .at(&path, format!("card {:?}: {}", c.name, e.message));
                None
            }
        }
    }

    /// Registers a built card's devices and settles its channel names and safe values.
    fn register(
        &mut self,
        at: &KeyPath,
        c: &CardConfig,
        card: Box<dyn driver_api::Card>,
        registry: &Registry,
    ) -> Option<CardRt> {
        let devices = card.devices();
        let count = |n: Option<u32>| n.unwrap_or(0);
        let counts = [
            count(devices.analog_in.as_ref().map(|d| d.channel_count())),
            count(devices.analog_out.as_ref().map(|d| d.channel_count())),
            count(devices.digital_in.as_ref().map(|d| d.input_count())),
            count(devices.digital_out.as_ref().map(|d| d.output_count())),
        ];
        let names = c.names.clone().or(card.channel_names());
        if let Err(e) = names.check(counts) {
            self.problems.at(&at.key("names").join(&e.key), e.message);
            return None;
        }
        let ports = |list: &[String], prefix: &str, n: u32| -> Vec<String> {
            (0..n)
                .map(|i| ChannelNames::port(list, prefix, i))
                .collect()
        };
        let spec = OutputSpec {
            config: &c.outputs,
            safe_analog_out: c.safe_analog_out.as_deref(),
            safe_digital_out_on: c.safe_digital_out_on.as_deref(),
            analog_ports: ports(&names.analog_out, "ch", counts[1]),
            digital_ports: ports(&names.digital_out, "bit", counts[3]),
        };
        let mut devices = devices;
        let outputs = match CardOutputs::new(
            &c.name,
            OutputDevices {
                analog: devices.analog_out.take(),
                digital: devices.digital_out.take(),
                read_back: card.read_back(),
            },
            &spec,
            &self.hold,
        ) {
            Ok(o) => o,
            Err(problems) => {
                for (key, message) in problems {
                    self.problems.at(&at.join(&key), message);
                }
                return None;
            }
        };
        // The registry hands out the guarded outputs: every write is seen, none after stop.
        devices.analog_out = outputs.analog_device();
        devices.digital_out = outputs.digital_device();
        if let Err(e) = registry.register_card(&c.name, devices) {
            self.problems.at(&at.key("name"), e);
            return None;
        }
        Some(CardRt {
            name: c.name.clone(),
            index: self
                .d
                .cards
                .iter()
                .position(|k| std::ptr::eq(k, c))
                .unwrap_or(0),
            config: at.clone(),
            driver: c.driver.clone(),
            card,
            outputs: Arc::new(outputs),
            names,
            bus: Vec::new(),
        })
    }

    fn aliases(&mut self, registry: &Registry) {
        for (i, a) in self.d.aliases.iter().enumerate() {
            if let Err(e) = registry.alias(a.interface, &a.name, &a.target) {
                self.problems.at(&KeyPath::top("alias").index(i), e);
            }
        }
    }

    /// The ThreadScope recording's name, resolved against the deployment's folder, and how
    /// many of its numbered files to keep; checked as `run` will create the next one (not
    /// created here: `check` makes no file).
    fn scope_vcd(&mut self) -> Option<(std::path::PathBuf, u32)> {
        use rtt::scope::vcd::files::{DEFAULT_KEEP, MAX_KEEP};
        let keep = self.d.thread_scope_vcd_keep;
        if let Some(n) = keep
            && !(1..=MAX_KEEP).contains(&n)
        {
            let msg = format!("{n}: expected 1 to {MAX_KEEP} files");
            self.problems
                .at(&KeyPath::top("thread_scope_vcd_keep"), msg);
        }
        let Some(file) = self.d.thread_scope_vcd.as_ref() else {
            if keep.is_some() {
                self.problems.at(
                    &KeyPath::top("thread_scope_vcd_keep"),
                    "there is no thread_scope_vcd to keep files of: name one",
                );
            }
            return None;
        };
        let path = self.base.join(file);
        let show = path.display().to_string();
        if path.file_name().is_none() || path.as_os_str().as_encoded_bytes().ends_with(b"/") {
            let msg = format!("{show:?}: expected a file name");
            self.problems.at(&KeyPath::top("thread_scope_vcd"), msg);
            return None;
        }
        // Each run makes a new numbered file beside the name (which may exist): its folder
        // must take new files.
        if let Err(msg) = checks::creatable(&path) {
            self.problems.at(&KeyPath::top("thread_scope_vcd"), msg);
            return None;
        }
        Some((path, keep.unwrap_or(DEFAULT_KEEP).clamp(1, MAX_KEEP)))
    }

    fn runtime(&mut self, registry: Arc<Registry>) -> Option<Runtime> {
        let options = RuntimeOptions {
            thread_scope: self.d.thread_scope,
            cpu_dma_latency_us: self.d.cpu_dma_latency_us,
            ..RuntimeOptions::default()
        };
        match Runtime::new(registry, options) {
            Ok(r) => Some(r),
            Err(e) => {
                let msg = format!(
                    "{e} (add an [[alias]] with interface = \"digital_out\" and name = \"ThreadScope\")"
                );
                self.problems.at(&KeyPath::top("thread_scope"), msg);
                None
            }
        }
    }

    /// The Zenoh node of the `[zenoh]` section, if any: its imported devices registered.
    fn zenoh(&mut self, registry: &Arc<Registry>) -> Option<Arc<crate::remote::Node>> {
        let section = self.d.zenoh.as_ref()?;
        match crate::remote::node(section, self.base, registry) {
            Ok(n) => Some(n),
            Err(problems) => {
                let at = KeyPath::top("zenoh");
                for (key, message) in problems {
                    self.problems.at(&at.join(&key), message);
                }
                None
            }
        }
    }

    /// The IO components of the imported devices, as a card's: ports sampled (inputs) at
    /// the publication period or written (outputs) on new data.
    fn remote_io(&mut self, runtime: &Runtime, node: &crate::remote::Node) -> Vec<TaskContext> {
        let period = millis(
            self.d
                .zenoh
                .as_ref()
                .and_then(crate::remote::publish_ms)
                .unwrap_or(10.0),
        );
        let mut out = Vec::new();
        for owner in crate::remote::import_owners(node) {
            let (names, details) = (ChannelNames::default(), Default::default());
            match io::build(runtime, &owner, period, &names, &details) {
                Ok(ts) => out.extend(ts),
                Err(e) => self.problems.at(&KeyPath::top("zenoh").key("import"), e),
            }
        }
        out
    }

    /// Each card's bus side, then its IO components; returns them in start order.
    fn bus_and_io(&mut self, runtime: &Runtime, cards: &mut [CardRt]) -> Vec<TaskContext> {
        let mut order = Vec::new();
        for c in cards.iter_mut() {
            let Some(cfg) = self.d.cards.get(c.index) else {
                continue;
            };
            match c.card.add_bus(runtime, &c.name) {
                Ok(tasks) => {
                    c.bus = tasks.clone();
                    order.extend(tasks);
                }
                Err(e) => self.problems.at(&c.config, e),
            }
            let sample = millis(cfg.sample_period_ms.unwrap_or(cfg.period_ms));
            let details = c.card.channel_details();
            match io::build(runtime, &c.name, sample, &c.names, &details) {
                Ok(ts) => order.extend(ts),
                Err(e) => self.problems.at(&c.config, e),
            }
        }
        order
    }

    /// User components: built, properties set, configured.
    fn components(
        &mut self,
        runtime: &Runtime,
        order: &mut Vec<TaskContext>,
        start: &mut Vec<bool>,
    ) {
        let types = &self.types.components;
        for (i, c) in self.d.components.iter().enumerate() {
            let at = KeyPath::top("component").index(i);
            if let crate::config::ActivityConfig::Periodic { period_ms, .. } = c.activity
                && let Err(msg) = checks::period(period_ms)
            {
                self.problems.at(&at.key("activity").key("period_ms"), msg);
                continue;
            }
            if let ActivitySpec::Periodic { thread, .. } | ActivitySpec::NonPeriodic { thread } =
                &c.activity.spec()
                && let Err(msg) = thread.check()
            {
                self.problems.at(&at.key("activity"), msg);
                continue;
            }
            let task = match types.build(runtime, &c.name, &c.kind, c.activity.spec()) {
                Ok(Some(t)) => t,
                Ok(None) => {
                    let msg = format!(
                        "unknown component type {:?}; this build has: {}",
                        c.kind,
                        types.names().join(", ")
                    );
                    self.problems.at(&at.key("type"), msg);
                    continue;
                }
                Err(e) => {
                    self.problems.at(&at.key("name"), e);
                    continue;
                }
            };
            if let Err(e) = task.properties().load_toml(&c.properties) {
                for line in e.to_string().lines() {
                    self.problems.at(&at.key("properties"), line);
                }
                continue;
            }
            if task.state() == TaskState::PreOperational
                && let Err(e) = task.configure()
            {
                self.problems.at(&at, e);
                continue;
            }
            order.push(task);
            start.push(c.start);
        }
    }

    fn connections(
        &mut self,
        runtime: &Runtime,
        cards: &mut [CardRt],
        node: Option<&crate::remote::Node>,
    ) {
        for (i, msg) in checks::spin_loops(&self.d.connections, runtime) {
            self.problems.at(&KeyPath::top("connection").index(i), msg);
        }
        let local = |c: &str| runtime.component(c).is_ok();
        for (i, c) in self.d.connections.iter().enumerate() {
            let at = KeyPath::top("connection").index(i);
            if let Some(source) = crate::remote::remote_source(node, &local, &c.from)
                && let Some(node) = node
            {
                // From another gateway's port: fed through Zenoh with this policy.
                let to = self.port_end(runtime, &at.key("to"), &c.to);
                match to.map(|p| p.writer(c.policy)) {
                    Some(Ok(w)) => {
                        let label = format!("{} -> {}", c.from, c.to);
                        crate::remote::link(node, source, w, label);
                    }
                    Some(Err(e)) => self.problems.at(&at.key("to"), e),
                    None => {}
                }
                continue;
            }
            let from = self.port_end(runtime, &at.key("from"), &c.from);
            let to = self.port_end(runtime, &at.key("to"), &c.to);
            if let (Some(from), Some(to)) = (from, to) {
                match from.connect_to(&*to, c.policy) {
                    Err(e) => self
                        .problems
                        .at(&at, format!("{} -> {}: {e}", c.from, c.to)),
                    Ok(_) => note_writer(cards, &c.from, &c.to),
                }
            }
        }
    }

    /// The output watchdog, when some card's outputs need one: a periodic component that
    /// applies [`CardOutputs::watch`].
    fn output_watchdog(&mut self, runtime: &Runtime, cards: &[CardRt]) -> Option<TaskContext> {
        let watched: Vec<Arc<CardOutputs>> = cards
            .iter()
            .filter(|c| c.outputs.watched())
            .map(|c| c.outputs.clone())
            .collect();
        if watched.is_empty() {
            return None;
        }
        let components: HashMap<String, TaskContext> = runtime
            .components()
            .into_iter()
            .map(|t| (t.name().to_string(), t))
            .collect();
        let spec = ActivitySpec::periodic(std::time::Duration::from_millis(10));
        let task = runtime.add(OUTPUT_WATCHDOG, spec, InitialState::Stopped, move |_| {
            Ok(OutputWatchdog {
                cards: watched,
                components,
            })
        });
        match task {
            Ok(t) => Some(t),
            Err(e) => {
                self.problems.at(&KeyPath::root(), e);
                None
            }
        }
    }

    /// The port `address` (`component.port`) names, or a problem at `at`.
    fn port_end(
        &mut self,
        runtime: &Runtime,
        at: &KeyPath,
        address: &str,
    ) -> Option<Arc<dyn DynPort>> {
        let Some((comp, port)) = split_port(address) else {
            self.problems
                .at(at, format!("{address:?}: expected \"component.port\""));
            return None;
        };
        let found = runtime
            .component(comp)
            .map_err(|e| e.to_string())
            .and_then(|t| t.port(port).map_err(|e| e.to_string()));
        match found {
            Ok(p) => Some(p),
            Err(e) => {
                self.problems.at(at, e);
                None
            }
        }
    }

    /// The servers: the Modbus server's table, over the devices registered above.
    fn servers(&mut self, runtime: &Runtime) -> Vec<Box<dyn driver_api::Server>> {
        let Some(ms) = self.d.modbus_server.as_ref() else {
            return Vec::new();
        };
        match ms.table(runtime.registry()) {
            Ok((listen, table, limits)) => vec![Box::new(driver_modbus::served::TableServer::new(
                listen, table, limits,
            ))],
            Err(problems) => {
                let at = KeyPath::top("modbus_server");
                for p in problems {
                    self.problems.at(&at.join(&p.key), p.message);
                }
                Vec::new()
            }
        }
    }
}
