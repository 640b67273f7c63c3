//! [`Gateway::build`](crate::deploy::Gateway::build) in phases: cards, aliases, runtime,
//! bus sides and IO components, user components, connections, servers. Each phase reports
//! through one [`Problems`] collector, keyed by the path of what is wrong.

use crate::config::{CARD_KEYS, CardConfig, ChannelNames, Deployment, millis, split_port};
use crate::deploy::{CardRt, Gateway, Link, Parts};
use crate::drivers::SectionError;
use crate::outputs::{CardOutputs, Hold, OutputDevices, OutputSpec};
use crate::problems::{KeyPath, Problem, Problems, Source};
use crate::types::Types;
use crate::{checks, io};
use device_interface::Registry;
use driver_api::CardContext;
use rtt::component::DynPort;
use rtt::{ActivitySpec, Runtime, RuntimeOptions, TaskContext, TaskState};
use std::any::{Any, TypeId};
use std::collections::{BTreeSet, HashMap};
use std::path::Path;
use std::sync::Arc;

use crate::watchdog::{WatchSet, Watched, output_watchdog};

/// Notes the component of `from` (`component.port`; `is_component` tells where its name
/// ends) as a writer of the card output behind `to`, when `to` is a port of a card's
/// output IO component (`card.ao.*`, `card.do.*`).
pub(crate) fn note_writer(
    cards: &[CardRt],
    from: &str,
    to: &str,
    is_component: &dyn Fn(&str) -> bool,
) {
    let (Some((writer, _)), Some((component, port))) = (
        crate::config::split_port_among(from, is_component),
        split_port(to),
    ) else {
        return;
    };
    let Some(card) = component
        .strip_suffix(".ao")
        .or_else(|| component.strip_suffix(".do"))
    else {
        return;
    };
    if let Some(c) = cards.iter().find(|c| c.name == card) {
        c.outputs.add_writer(port, writer);
    }
}

/// What a reload builds into a running gateway: cards, components and connections by
/// their index in the new deployment, and whether the servers are made anew.
#[derive(Debug, Default)]
pub(crate) struct Selection {
    pub(crate) cards: BTreeSet<usize>,
    pub(crate) components: BTreeSet<usize>,
    pub(crate) connections: BTreeSet<usize>,
    pub(crate) servers: bool,
}

/// What a reload built: not started.
pub(crate) struct Rebuilt {
    pub(crate) cards: Vec<CardRt>,
    /// The cards' bus sides and IO components, then the components, in start order.
    pub(crate) order: Vec<(TaskContext, bool)>,
    pub(crate) links: Vec<Link>,
    pub(crate) servers: Vec<Box<dyn driver_api::Server>>,
}

/// One build under way.
struct Build<'d, 's, 'a> {
    d: &'d Deployment,
    types: &'d Types,
    problems: Problems<'s, 'a>,
    /// Files a card names (DBC) are relative to the deployment file.
    base: &'d Path,
    /// A reload's: only these; `None`: everything.
    only: Option<&'d Selection>,
    /// The bus sides of the cards built, by card name, until `bus_and_io` adds them.
    buses: HashMap<String, driver_api::BusSide>,
    /// The Zenoh node, for services of other gateways.
    zenoh: Option<Arc<crate::remote::Node>>,
    /// The gateway's control protocol, for its servers (joined when it serves).
    control: driver_api::ControlLink,
}

impl<'d, 's, 'a> Build<'d, 's, 'a> {
    /// A build of `d` (or of what `only` selects of it) from `file`, whose `source`
    /// locates problems; files it names are relative to the file's folder.
    fn new(
        d: &'d Deployment,
        types: &'d Types,
        source: &'s Source<'a>,
        file: &'d str,
        only: Option<&'d Selection>,
    ) -> Self {
        Build {
            d,
            types,
            problems: Problems::new(source),
            base: Path::new(file).parent().unwrap_or(Path::new("")),
            only,
            buses: HashMap::new(),
            zenoh: None,
            control: driver_api::ControlLink::new(),
        }
    }

    fn card_wanted(&self, i: usize) -> bool {
        self.only.is_none_or(|s| s.cards.contains(&i))
    }

    fn component_wanted(&self, i: usize) -> bool {
        self.only.is_none_or(|s| s.components.contains(&i))
    }

    fn connection_wanted(&self, i: usize) -> bool {
        self.only.is_none_or(|s| s.connections.contains(&i))
    }
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
    let mut b = Build::new(d, types, &source, file, None);
    let base = b.base;
    for (key, message) in checks::control(d) {
        b.problems.at(&KeyPath::top(&key), message);
    }
    crate::servers::unknown_keys(d, &types.servers, &mut b.problems);
    let registry = Arc::new(Registry::new());
    let mut cards = b.cards(&registry);
    b.aliases(&registry);
    let zenoh = b.zenoh(&registry);
    b.zenoh.clone_from(&zenoh);
    let Some(runtime) = b.runtime(registry) else {
        return Err(b.problems.into_vec());
    };
    let mut order = b.bus_and_io(&runtime, &mut cards);
    let logical = crate::logical::build(&d.logical, &runtime, &cards, &mut b.problems);
    order.extend(logical.tasks);
    if let Some(node) = &zenoh {
        order.extend(b.remote_io(&runtime, node));
    }
    let mut order: Vec<(TaskContext, bool)> = order.into_iter().map(|t| (t, true)).collect();
    b.components(&runtime, &mut order);
    let links = b.connections(&runtime, &mut cards, zenoh.as_deref());
    if let (Some(node), Some(section)) = (&zenoh, &d.zenoh) {
        for (key, message) in crate::remote::exports(node, section, &runtime) {
            b.problems.at(&KeyPath::top("zenoh").join(&key), message);
        }
    }
    let watch: WatchSet = Arc::new(arc_swap::ArcSwap::from_pointee(Watched::new(
        &runtime,
        cards.iter().map(|c| &c.outputs),
    )));
    if let Some(w) = b.output_watchdog(&runtime, &watch) {
        order.push((w, true));
    }
    let servers = b.servers(&runtime);
    let zenoh_server = zenoh.as_ref().map(crate::remote::server);
    let scope_vcd = b.scope_vcd();
    for (key, message) in checks::shared_files(d, base) {
        b.problems.at(&key, message);
    }
    if !b.problems.is_empty() {
        return Err(b.problems.into_vec());
    }
    let parts = Parts {
        logical_writers: logical.writers,
        cards,
        servers,
        order,
        links,
        watch,
        zenoh_server,
    };
    let mut gw = Gateway::new(runtime, parts, d.clone(), types.clone());
    gw.running
        .get_mut()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .text = text.to_string();
    gw.scope_vcd = scope_vcd;
    gw.zenoh = zenoh;
    gw.control = b.control;
    Ok(gw)
}

/// Builds what `only` selects of deployment `d` (from `file`, whose `text` locates errors)
/// into the running `runtime`, nothing started: a reload's cards (their devices
/// registered), then `between` (the aliases: it returns its problems), their bus sides
/// and IO components, components, connections (ends found among everything the runtime
/// has now) and servers. `d` was checked whole before; problems past that come with what
/// was built all the same.
pub(crate) fn rebuild(
    d: &Deployment,
    file: &str,
    text: &str,
    types: &Types,
    (runtime, zenoh, control): (
        &Runtime,
        Option<Arc<crate::remote::Node>>,
        driver_api::ControlLink,
    ),
    only: &Selection,
    between: impl FnOnce(&Registry) -> Vec<String>,
) -> Result<Rebuilt, (Rebuilt, Vec<String>)> {
    let source = Source::new(file, text);
    let mut b = Build::new(d, types, &source, file, Some(only));
    b.zenoh = zenoh;
    b.control = control;
    let mut cards = b.cards(runtime.registry());
    let mut problems = between(runtime.registry());
    let order = b.bus_and_io(runtime, &mut cards);
    let mut order: Vec<(TaskContext, bool)> = order.into_iter().map(|t| (t, true)).collect();
    b.components(runtime, &mut order);
    let links = b.connections(runtime, &mut cards, None);
    let servers = if only.servers {
        b.servers(runtime)
    } else {
        Vec::new()
    };
    let rebuilt = Rebuilt {
        cards,
        order,
        links,
        servers,
    };
    problems.extend(b.problems.into_vec().iter().map(ToString::to_string));
    if problems.is_empty() {
        Ok(rebuilt)
    } else {
        Err((rebuilt, problems))
    }
}

impl Build<'_, '_, '_> {
    /// Every card: checked, built by its driver, its devices registered.
    fn cards(&mut self, registry: &Registry) -> Vec<CardRt> {
        let mut shared: HashMap<TypeId, Box<dyn Any + Send>> = HashMap::new();
        let mut cards = Vec::new();
        for (i, c) in self.d.cards.iter().enumerate() {
            if !self.card_wanted(i) {
                continue;
            }
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
            if let Some(Err(e)) = c.faults.map(|f| f.check()) {
                self.problems.at(&at.key("faults"), e);
                continue;
            }
            if let Err(msg) = c.thread.check() {
                self.problems.at(&at.key("thread"), msg);
                continue;
            }
            let Some((built, shares)) = self.card(&at, c, &mut shared) else {
                continue;
            };
            if let Some(mut rt) = self.register(&at, c, built.card, registry) {
                rt.shares = shares;
                if let Some(bus) = built.bus {
                    self.buses.insert(c.name.clone(), bus);
                }
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
    ) -> Option<(driver_api::BuiltCard, Option<String>)> {
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
            self.base,
            Arc::new(rtt::time::MonotonicClock),
            shared,
        );
        match driver.build(section.clone(), &mut ctx) {
            Ok(card) => Some((card, ctx.bus_key().map(String::from))),
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
        let hold = Arc::new(Hold::default());
        let outputs = match CardOutputs::new(
            &c.name,
            OutputDevices {
                analog: devices.analog_out.take(),
                digital: devices.digital_out.take(),
                read_back: card.read_back(),
            },
            &spec,
            &hold,
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
            hold,
            shares: None,
            card,
            outputs: Arc::new(outputs),
            names,
            bus: Vec::new(),
            io: Vec::new(),
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
            // A stale import is the import's health to tell (and a required service's).
            let faults = rtt::faults::FaultPolicy::NEVER;
            match io::build(runtime, &owner, (period, faults), &names, &details) {
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
            // Its bus side, handed over by the driver's build: added once, here.
            let bus = self.buses.remove(&c.name).map(|bus| {
                let ctx = driver_api::BusContext::new(runtime, &c.name, &cfg.thread);
                bus.add_to(&ctx)
            });
            match bus {
                Some(Ok(tasks)) => {
                    c.bus = tasks.clone();
                    order.extend(tasks);
                }
                Some(Err(e)) => self.problems.at(&c.config, e),
                None => {}
            }
            let sample = millis(cfg.sample_period_ms.unwrap_or(cfg.period_ms));
            let details = c.card.channel_details();
            let faults = cfg.faults.unwrap_or(rtt::faults::FaultPolicy::NEVER);
            match io::build(runtime, &c.name, (sample, faults), &c.names, &details) {
                Ok(ts) => {
                    c.io = ts.clone();
                    order.extend(ts);
                }
                Err(e) => self.problems.at(&c.config, e),
            }
        }
        order
    }

    /// User components: built with their properties set, their requirements bound (to
    /// any component, so all are built first), configured; started providers first.
    fn components(&mut self, runtime: &Runtime, order: &mut Vec<(TaskContext, bool)>) {
        let mut built = Vec::new();
        for (i, c) in self.d.components.iter().enumerate() {
            if self.component_wanted(i)
                && let Some(task) = self.component(runtime, i, c)
            {
                built.push((i, task));
            }
        }
        let names: Vec<String> = built.iter().map(|(_, t)| t.name().to_string()).collect();
        let mut bound = Vec::new();
        for (i, task) in built {
            let c = &self.d.components[i];
            let at = KeyPath::top("component").index(i);
            let mut ok = crate::bindings::bind(
                runtime,
                &task,
                (c, &at),
                self.zenoh.as_ref(),
                &mut self.problems,
            );
            if ok
                && task.state() == TaskState::PreOperational
                && let Err(e) = task.configure()
            {
                self.problems.at(&at, e);
                ok = false;
            }
            if ok {
                bound.push((task, c.start));
            } else if self.only.is_some() {
                // A reload's failure leaves no half-made component under the name.
                let _ = runtime.remove(&c.name);
            }
        }
        if self.only.is_some() {
            // A reload: the components it kept are bound again as the new deployment
            // says — to a provider rebuilt or added, away from one removed.
            for (i, c) in self.d.components.iter().enumerate() {
                if names.contains(&c.name) {
                    continue;
                }
                if let Ok(task) = runtime.component(&c.name)
                    && !task.required().is_empty()
                {
                    let at = KeyPath::top("component").index(i);
                    crate::bindings::bind(
                        runtime,
                        &task,
                        (c, &at),
                        self.zenoh.as_ref(),
                        &mut self.problems,
                    );
                }
            }
        }
        self.slaves(runtime, &bound);
        self.peers(runtime, &bound);
        order.extend(crate::bindings::providers_first(bound));
    }

    /// Gives each component built the aliases its `peers` name, each to a component that
    /// exists.
    fn peers(&mut self, runtime: &Runtime, built: &[(TaskContext, bool)]) {
        for (i, c) in self.d.components.iter().enumerate() {
            let Some((task, _)) = built.iter().find(|(t, _)| t.name() == c.name) else {
                continue;
            };
            for (alias, target) in &c.peers {
                match runtime.component(target) {
                    Ok(_) => task.set_peer_alias(alias, target),
                    Err(e) => self.problems.at(
                        &KeyPath::top("component").index(i).key("peers").key(alias),
                        e,
                    ),
                }
            }
        }
    }

    /// Gives each slave component its master; after a reload, the slaves of a master
    /// rebuilt (a new component under the name) too.
    fn slaves(&mut self, runtime: &Runtime, built: &[(TaskContext, bool)]) {
        let is_built = |name: &str| built.iter().any(|(t, _)| t.name() == name);
        for (i, c) in self.d.components.iter().enumerate() {
            let crate::config::ActivityConfig::Slave { master } = &c.activity else {
                continue;
            };
            if !is_built(&c.name) && !is_built(master) {
                continue;
            }
            let at = KeyPath::top("component")
                .index(i)
                .key("activity")
                .key("master");
            let result = runtime
                .component(master)
                .map_err(|e| e.to_string())
                .and_then(|m| {
                    let slave = runtime.component(&c.name).map_err(|e| e.to_string())?;
                    m.add_slave(&slave).map_err(|e| e.to_string())
                });
            if let Err(e) = result {
                self.problems.at(&at, e);
            }
        }
    }

    /// Component `i`, `c`: built, its properties set; `None` after a problem.
    fn component(
        &mut self,
        runtime: &Runtime,
        i: usize,
        c: &crate::config::ComponentConfig,
    ) -> Option<TaskContext> {
        let types = &self.types.components;
        let at = KeyPath::top("component").index(i);
        if let crate::config::ActivityConfig::Periodic { period_ms, .. } = c.activity
            && let Err(msg) = checks::period(period_ms)
        {
            self.problems.at(&at.key("activity").key("period_ms"), msg);
            return None;
        }
        if let crate::config::ActivityConfig::FileDescriptor {
            timeout_ms: Some(ms),
            ..
        } = c.activity
            && let Err(msg) = checks::period(ms)
        {
            self.problems.at(&at.key("activity").key("timeout_ms"), msg);
            return None;
        }
        if let ActivitySpec::Periodic { thread, .. }
        | ActivitySpec::NonPeriodic { thread }
        | ActivitySpec::FileDescriptor { thread, .. } = &c.activity.spec()
            && let Err(msg) = thread.check()
        {
            self.problems.at(&at.key("activity"), msg);
            return None;
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
                return None;
            }
            Err(e) => {
                self.problems.at(&at.key("name"), e);
                return None;
            }
        };
        if task.properties().get_value("base_dir").is_ok() {
            let base = std::path::absolute(self.base).unwrap_or_else(|_| self.base.to_path_buf());
            let _ = task
                .properties()
                .set_value("base_dir", serde_json::json!(base));
        }
        let files_ok = c.properties_file.iter().enumerate().all(|(j, f)| {
            let at = at.key("properties_file").index(j);
            crate::propfiles::load(&task, &self.base.join(f), &at, &mut self.problems)
        });
        let inline = if files_ok {
            task.properties().load_toml(&c.properties)
        } else {
            Ok(())
        };
        if !files_ok || inline.is_err() {
            if let Err(e) = inline {
                for line in e.to_string().lines() {
                    self.problems.at(&at.key("properties"), line);
                }
            }
            // A reload's failure leaves no half-made component under the name.
            if self.only.is_some() {
                let _ = runtime.remove(&c.name);
            }
            return None;
        }
        Some(task)
    }

    /// The connections: made, with what closes each again.
    fn connections(
        &mut self,
        runtime: &Runtime,
        cards: &mut [CardRt],
        node: Option<&crate::remote::Node>,
    ) -> Vec<Link> {
        if self.only.is_none() {
            for (i, msg) in checks::spin_loops(&self.d.connections, runtime) {
                self.problems.at(&KeyPath::top("connection").index(i), msg);
            }
        }
        let local = |c: &str| runtime.component(c).is_ok();
        let mut links = Vec::new();
        for (i, c) in self.d.connections.iter().enumerate() {
            if !self.connection_wanted(i) {
                continue;
            }
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
                        links.push(Link {
                            config: c.clone(),
                            made: None,
                        });
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
                    Ok(info) => {
                        note_writer(cards, &c.from, &c.to, &local);
                        links.push(Link {
                            config: c.clone(),
                            made: Some((from, info.id)),
                        });
                    }
                }
            }
        }
        links
    }

    /// The output watchdog, when some card's outputs need one: a periodic component that
    /// applies [`CardOutputs::watch`].
    fn output_watchdog(&mut self, runtime: &Runtime, set: &WatchSet) -> Option<TaskContext> {
        output_watchdog(runtime, set).unwrap_or_else(|e| {
            self.problems.at(&KeyPath::root(), e);
            None
        })
    }

    /// The port `address` (`component.port`) names, or a problem at `at`. Both names may
    /// hold dots (`sim0.ai.ch0`, a service's port `cam0.camera.frames`): the first split
    /// from the right whose component has the port is it.
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
        let find = |comp: &str, port: &str| {
            runtime
                .component(comp)
                .map_err(|e| e.to_string())
                .and_then(|t| t.port(port).map_err(|e| e.to_string()))
        };
        let first = match find(comp, port) {
            Ok(p) => return Some(p),
            Err(e) => e,
        };
        for (i, _) in address[..comp.len()].rmatch_indices('.') {
            if let Ok(p) = find(&address[..i], &address[i + 1..]) {
                return Some(p);
            }
        }
        self.problems.at(at, first);
        None
    }

    /// The servers of the deployment's server sections, by their types, over the devices
    /// registered above.
    fn servers(&mut self, runtime: &Runtime) -> Vec<Box<dyn driver_api::Server>> {
        let types = &self.types.servers;
        let control = &self.control;
        crate::servers::build(
            self.d,
            types,
            (runtime, control),
            self.base,
            &mut self.problems,
        )
    }
}
