//! From a deployment to a running gateway: cards, registry, aliases, runtime, IO
//! components, user components, connections; and back down to safe outputs.
//!
//! [`Gateway::build`] does everything short of starting threads, so `hwgw check` runs the
//! very code `hwgw run` does and finds every error it would, each located in the file.

use crate::config::{AliasInterface, Deployment, Location, Problem, locate, millis, split_port};
use crate::{components, io};
use device_interface::{AnalogIn, AnalogOut, DigitalIn, DigitalOut, Registry};
use driver_modbus::card::ModbusCard;
use driver_modbus::line::{Line, LineUnit, Transport, UnitStats, UnitTiming};
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

/// What drives a card's bus I/O.
enum Driver {
    /// A simulated card, stepped by a periodic cycle component.
    Sim(Arc<SimCard>),
    /// A Modbus unit, polled by the line of its transport (started with the gateway).
    Modbus {
        card: Arc<ModbusCard>,
        transport: Transport,
        timing: UnitTiming,
        stats: Arc<UnitStats>,
    },
    /// A SocketCAN interface, serviced by its bus component (named after the card).
    Can(Arc<driver_can::card::CanCard>),
}

/// A card of the deployment, with what it needs at shutdown.
struct CardRt {
    name: String,
    /// Its index in the deployment's `[[card]]` list.
    config: usize,
    driver: Driver,
    safe_analog_out: Vec<f64>,
    safe_digital_out_on: Vec<u32>,
    /// Port names of its channels (given, or from the driver's signal names).
    names: crate::config::ChannelNames,
}

impl CardRt {
    fn analog_out(&self) -> &dyn AnalogOut {
        match &self.driver {
            Driver::Sim(c) => &**c,
            Driver::Modbus { card, .. } => &**card,
            Driver::Can(card) => &**card,
        }
    }

    fn digital_out(&self) -> &dyn DigitalOut {
        match &self.driver {
            Driver::Sim(c) => &**c,
            Driver::Modbus { card, .. } => &**card,
            Driver::Can(card) => &**card,
        }
    }

    fn counts(&self) -> [u32; 4] {
        match &self.driver {
            Driver::Sim(c) => [
                AnalogIn::channel_count(&**c),
                AnalogOut::channel_count(&**c),
                c.input_count(),
                DigitalOut::output_count(&**c),
            ],
            Driver::Modbus { card, .. } => card.map().counts(),
            Driver::Can(card) => card.map().counts(),
        }
    }
}

/// Fills the channel names a CAN card's deployment left out with its signal names
/// (`signal` for one channel, `signal_k` for bit k of a multi-bit digital signal), where
/// those make port names.
fn can_names(card: &driver_can::card::CanCard, names: &mut crate::config::ChannelNames) {
    use driver_can::map::SignalRole;
    let ok = |n: &str| !n.is_empty() && !n.contains('.') && !n.chars().any(char::is_whitespace);
    let fill = |list: &mut Vec<String>, frames: &[driver_can::map::MappedFrame], role| {
        let mut all = Vec::new();
        for s in frames
            .iter()
            .flat_map(|f| &f.signals)
            .filter(|s| s.role == role)
        {
            match s.width() {
                1 => all.push(s.name.clone()),
                w => all.extend((0..w).map(|k| format!("{}_{k}", s.name))),
            }
        }
        if list.is_empty() && all.iter().all(|n| ok(n)) && {
            let mut u = all.clone();
            u.sort();
            u.dedup();
            u.len() == all.len()
        } {
            *list = all;
        }
    };
    let map = card.map();
    fill(&mut names.analog_in, map.rx(), SignalRole::Analog);
    fill(&mut names.digital_in, map.rx(), SignalRole::Digital);
    fill(&mut names.analog_out, map.tx(), SignalRole::Analog);
    fill(&mut names.digital_out, map.tx(), SignalRole::Digital);
}

fn frame_list(frames: &[driver_can::map::MappedFrame]) -> String {
    if frames.is_empty() {
        return "nothing".into();
    }
    frames
        .iter()
        .map(|f| {
            let when = match (f.cycle, f.on_change) {
                (Some(c), true) => format!("every {c:?} and on change"),
                (Some(c), false) => format!("every {c:?}"),
                (None, _) => "on change".to_string(),
            };
            format!(
                "{} (id {:#x}, {} signals, {when})",
                f.name,
                f.id,
                f.signals.len()
            )
        })
        .collect::<Vec<_>>()
        .join(", ")
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
    cards: Vec<CardRt>,
    /// Running Modbus lines (empty until start).
    lines: std::sync::Mutex<Vec<Line>>,
    /// The Modbus server's address and table, if configured.
    server_table: Option<(std::net::SocketAddr, driver_modbus::server::RegisterTable)>,
    /// The running Modbus server.
    server: std::sync::Mutex<Option<driver_modbus::server::ModbusServer>>,
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
        // Opened CAN buses, by card index, until their components take them.
        let mut buses: Vec<(usize, driver_can::bus::CanBus)> = Vec::new();
        // Files a card names (DBC) are relative to the deployment file.
        let base = std::path::Path::new(file)
            .parent()
            .unwrap_or(std::path::Path::new(""));
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
            let section = |key: &str, span: Option<std::ops::Range<usize>>| {
                let location = span.map(|sp| locate(file, text, sp.start)).or_else(here);
                (location, format!("{path}.{key}"))
            };
            let built: Result<
                (Driver, device_interface::CardDevices),
                (Option<Location>, String, String),
            > = match (c.driver.as_str(), &c.sim, &c.modbus, &c.socketcan) {
                ("socketcan", _, _, Some(sec)) => {
                    let (cfg, span) = (sec.get_ref(), sec.span());
                    let (l, p) = section("socketcan", Some(span));
                    let problem =
                        |e: String| (l.clone(), p.clone(), format!("card {:?}: {e}", c.name));
                    driver_can::map::CanMap::new(cfg, base)
                        .map_err(|e| problem(e.to_string()))
                        .and_then(|map| {
                            let card = driver_can::card::CanCard::new(
                                map,
                                Arc::new(rtt::time::MonotonicClock),
                            );
                            let bus = driver_can::bus::CanBus::open(card.clone())
                                .map_err(|e| problem(e.to_string()))?;
                            buses.push((i, bus));
                            let devices = card.devices();
                            Ok((Driver::Can(card), devices))
                        })
                }
                ("sim", Some(sec), _, _) => {
                    SimCard::new(sec.get_ref(), Arc::new(rtt::time::MonotonicClock))
                        .map(|card| {
                            let devices = card.devices();
                            (Driver::Sim(card), devices)
                        })
                        .map_err(|e| {
                            let (l, p) = section("sim", Some(sec.span()));
                            (l, p, format!("card {:?}: {e}", c.name))
                        })
                }
                ("modbus", _, Some(sec), _) => {
                    let m = sec.get_ref();
                    let (l, p) = section("modbus", Some(sec.span()));
                    let problem =
                        |e: String| (l.clone(), p.clone(), format!("card {:?}: {e}", c.name));
                    m.transport()
                        .and_then(|t| m.timing().map(|timing| (t, timing)))
                        .map_err(problem)
                        .and_then(|(transport, timing)| {
                            let card = m
                                .card(Arc::new(rtt::time::MonotonicClock))
                                .map_err(|e| problem(e.to_string()))?;
                            let devices = card.devices();
                            Ok((
                                Driver::Modbus {
                                    card,
                                    transport,
                                    timing,
                                    stats: Arc::new(UnitStats::default()),
                                },
                                devices,
                            ))
                        })
                }
                (d @ ("sim" | "modbus" | "socketcan"), _, _, _) => Err((
                    here(),
                    path.clone(),
                    format!(
                        "card {:?} uses driver {d:?} but has no [card.{d}] section",
                        c.name
                    ),
                )),
                (other, _, _, _) => Err((
                    at(&[Seg::Key("card"), Seg::Index(i), Seg::Key("driver")]),
                    format!("{path}.driver"),
                    format!("unknown driver {other:?}; this build has: modbus, sim, socketcan"),
                )),
            };
            let (driver, devices) = match built {
                Ok(b) => b,
                Err((location, key, message)) => {
                    add(&mut problems, location, key, message);
                    continue;
                }
            };
            let mut card = CardRt {
                name: c.name.clone(),
                config: i,
                driver,
                safe_analog_out: Vec::new(),
                safe_digital_out_on: c.safe_digital_out_on.clone(),
                names: crate::config::ChannelNames::default(),
            };
            let mut names = c.names.clone();
            if let Driver::Can(can) = &card.driver {
                can_names(can, &mut names);
            }
            if let Err((key, message)) = names.check(card.counts()) {
                add(
                    &mut problems,
                    at(&[Seg::Key("card"), Seg::Index(i), Seg::Key("names")]),
                    format!("{path}.{key}"),
                    message,
                );
                continue;
            }
            card.names = names;
            if let Err(e) = registry.register_card(&c.name, devices) {
                add(&mut problems, here(), format!("{path}.name"), e.to_string());
                continue;
            }
            card.safe_analog_out = c.safe_analog_out.clone().unwrap_or_else(|| {
                let ao = card.analog_out();
                (0..ao.channel_count())
                    .map(|ch| ao.read_back(ch).unwrap_or(0.0))
                    .collect()
            });
            cards.push(card);
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

        // Card cycles (sim cards; a Modbus card's line is its activity), then each card's
        // IO components.
        let mut order = Vec::new();
        for c in &cards {
            let i = c.config;
            let cfg = &deployment.cards[i];
            if let Driver::Sim(sim) = &c.driver {
                let card = sim.clone();
                match runtime.add(
                    &c.name,
                    ActivitySpec::Periodic {
                        period: millis(cfg.period_ms),
                        thread: cfg.thread.clone(),
                        timing: rtt::Timing::Absolute,
                        max_overruns: None,
                    },
                    rtt::InitialState::Stopped,
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
            }
            let sample = millis(cfg.sample_period_ms.unwrap_or(cfg.period_ms));
            if let Some(k) = buses.iter().position(|(ci, _)| *ci == i) {
                let (_, bus) = buses.swap_remove(k);
                match driver_can::component::CanIo::add(&runtime, &c.name, bus, cfg.thread.clone())
                {
                    Ok(t) => order.push(t),
                    Err(e) => add(
                        &mut problems,
                        at(&[Seg::Key("card"), Seg::Index(i)]),
                        format!("card[{i}]"),
                        e.to_string(),
                    ),
                }
            }
            match io::build(&runtime, &c.name, sample, &c.names) {
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

        // The Modbus server's table, over the devices registered above.
        let mut server_table = None;
        if let Some(ms) = &deployment.modbus_server {
            let here = |path: &[Seg<'_>]| {
                let mut full = vec![Seg::Key("modbus_server")];
                full.extend(path.iter().map(|s| match s {
                    Seg::Key(k) => Seg::Key(k),
                    Seg::Index(i) => Seg::Index(*i),
                }));
                at(&full)
            };
            use std::net::ToSocketAddrs;
            let listen = ms.listen.to_socket_addrs().ok().and_then(|mut a| a.next());
            if listen.is_none() {
                add(
                    &mut problems,
                    here(&[Seg::Key("listen")]),
                    "modbus_server.listen".into(),
                    format!("{:?}: expected address:port", ms.listen),
                );
            }
            let reg = runtime.registry();
            let mut entries = Vec::new();
            for (i, r) in ms.registers.iter().enumerate() {
                use driver_modbus::server::Source;
                let found = match r.interface {
                    AliasInterface::AnalogIn => reg
                        .analog_in()
                        .lookup(&r.device)
                        .map(|d| Source::AnalogIn(d, r.channel)),
                    AliasInterface::AnalogOut => reg
                        .analog_out()
                        .lookup(&r.device)
                        .map(|d| Source::AnalogOut(d, r.channel)),
                    AliasInterface::DigitalIn => reg
                        .digital_in()
                        .lookup(&r.device)
                        .map(|d| Source::DigitalIn(d, r.channel)),
                    AliasInterface::DigitalOut => reg
                        .digital_out()
                        .lookup(&r.device)
                        .map(|d| Source::DigitalOut(d, r.channel)),
                    AliasInterface::Encoder => {
                        add(
                            &mut problems,
                            here(&[Seg::Key("register"), Seg::Index(i), Seg::Key("interface")]),
                            format!("modbus_server.register[{i}].interface"),
                            "encoders are not served yet; serve their IO component's ports instead"
                                .into(),
                        );
                        continue;
                    }
                };
                match found {
                    Ok(source) => entries.push(driver_modbus::server::Entry {
                        table: r.table,
                        address: r.address,
                        layout: driver_modbus::codec::Layout {
                            ty: r.ty,
                            words: r.words,
                            bytes: r.bytes,
                        },
                        scale: r.scale,
                        offset: r.offset,
                        source,
                    }),
                    Err(e) => add(
                        &mut problems,
                        here(&[Seg::Key("register"), Seg::Index(i), Seg::Key("device")]),
                        format!("modbus_server.register[{i}].device"),
                        e.to_string(),
                    ),
                }
            }
            match driver_modbus::server::RegisterTable::new(entries) {
                Ok(table) => server_table = listen.map(|a| (a, table)),
                Err(e) => add(
                    &mut problems,
                    here(&[Seg::Key("register")]),
                    "modbus_server.register".into(),
                    e.to_string(),
                ),
            }
        }

        if problems.is_empty() {
            Ok(Gateway {
                runtime,
                cards,
                lines: std::sync::Mutex::new(Vec::new()),
                server_table,
                server: std::sync::Mutex::new(None),
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

    /// Starts the Modbus lines (cards with the same transport share one), then the
    /// components the deployment asks to start, in order.
    pub fn start(&self) -> Result<(), rtt::component::LifecycleError> {
        let mut groups: Vec<(Transport, Vec<LineUnit>)> = Vec::new();
        for c in &self.cards {
            if let Driver::Modbus {
                card,
                transport,
                timing,
                stats,
            } = &c.driver
            {
                let unit = LineUnit {
                    card: card.clone(),
                    timing: *timing,
                    stats: stats.clone(),
                };
                match groups.iter_mut().find(|(t, _)| t == transport) {
                    Some((_, units)) => units.push(unit),
                    None => groups.push((transport.clone(), vec![unit])),
                }
            }
        }
        let mut lines = rtt::lock(&self.lines);
        for (n, (transport, units)) in groups.into_iter().enumerate() {
            match Line::spawn(&format!("modbus{n}"), transport.clone(), units) {
                Ok(line) => lines.push(line),
                // The cards stay offline and say so; the rest of the gateway runs.
                Err(e) => tracing::error!("modbus line {transport:?}: cannot start: {e}"),
            }
        }
        drop(lines);
        if let Some((addr, table)) = &self.server_table {
            match driver_modbus::server::ModbusServer::start(*addr, table.clone()) {
                Ok(server) => *rtt::lock(&self.server) = Some(server),
                Err(e) => tracing::error!("modbus server on {addr}: cannot start: {e}"),
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

    /// Where the Modbus server listens, once started.
    pub fn modbus_server_addr(&self) -> Option<std::net::SocketAddr> {
        rtt::lock(&self.server).as_ref().map(|s| s.addr())
    }

    /// Per-card bus diagnostics (Modbus line counters), for `status`.
    pub fn card_diagnostics(&self) -> serde_json::Value {
        let load = |a: &std::sync::atomic::AtomicU64| a.load(std::sync::atomic::Ordering::Relaxed);
        self.cards
            .iter()
            .map(|c| match &c.driver {
                Driver::Sim(_) => serde_json::json!({"name": c.name, "driver": "sim"}),
                Driver::Can(card) => serde_json::json!({
                    "name": c.name,
                    "driver": "socketcan",
                    "interface": card.map().interface(),
                    "counters": card.counters(),
                }),
                Driver::Modbus { stats, timing, .. } => serde_json::json!({
                    "name": c.name,
                    "driver": "modbus",
                    "unit": timing.unit,
                    "polls": load(&stats.polls),
                    "requests": load(&stats.requests),
                    "replies": load(&stats.replies),
                    "timeouts": load(&stats.timeouts),
                    "exceptions": load(&stats.exceptions),
                    "transport_errors": load(&stats.transport_errors),
                    "bad_replies": load(&stats.bad_replies),
                    "write_retries": load(&stats.write_retries),
                }),
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
            let driver = match &c.driver {
                Driver::Sim(_) => "sim".to_string(),
                Driver::Can(card) => format!(
                    "socketcan {}: receives {}; sends {}",
                    card.map().interface(),
                    frame_list(card.map().rx()),
                    frame_list(card.map().tx()),
                ),
                Driver::Modbus {
                    transport,
                    timing,
                    card,
                    ..
                } => format!(
                    "modbus {transport:?} unit {}, {} reads per poll: {}",
                    timing.unit,
                    card.map().reads().len(),
                    card.map()
                        .reads()
                        .iter()
                        .map(|r| r.to_string())
                        .collect::<Vec<_>>()
                        .join("; ")
                ),
            };
            s.push_str(&format!("card {:?} ({driver})\n", c.name));
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
        // No client writes may race the safe values.
        rtt::lock(&self.server).take();
        // A CAN card's bus component is what sends its safe values: it stops last.
        let is_bus = |t: &TaskContext| {
            self.cards
                .iter()
                .any(|c| matches!(c.driver, Driver::Can(_)) && c.name == t.name())
        };
        let stop = |t: &TaskContext| {
            if matches!(t.state(), TaskState::Running | TaskState::RunTimeError)
                && let Err(e) = t.stop()
            {
                tracing::warn!("{e}");
            }
        };
        for t in self.order.iter().rev().filter(|t| !is_bus(t)) {
            stop(t);
        }
        for c in &self.cards {
            let (ao, dout) = (c.analog_out(), c.digital_out());
            for (ch, v) in c.safe_analog_out.iter().enumerate() {
                if let Err(e) = ao.write(ch as u32, *v) {
                    tracing::error!(
                        "card {:?}: analog output {ch} not at its safe value {v}: {e}",
                        c.name
                    );
                }
            }
            for b in 0..dout.output_count() {
                if let Err(e) = dout.set_bit(b, c.safe_digital_out_on.contains(&b)) {
                    tracing::error!(
                        "card {:?}: digital output {b} not at its safe value: {e}",
                        c.name
                    );
                }
            }
        }
        // A bus card's safe values only count once its line has sent them.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(3);
        for c in &self.cards {
            if let Driver::Modbus { card, stats, .. } = &c.driver {
                let polls = stats.polls.load(std::sync::atomic::Ordering::Relaxed);
                while (card.writes_pending()
                    || stats.polls.load(std::sync::atomic::Ordering::Relaxed) <= polls)
                    && std::time::Instant::now() < deadline
                    && !rtt::lock(&self.lines).is_empty()
                {
                    std::thread::sleep(std::time::Duration::from_millis(5));
                }
                if card.writes_pending() {
                    tracing::error!(
                        "card {:?}: safe values not confirmed by the unit before stopping",
                        c.name
                    );
                }
            }
        }
        rtt::lock(&self.lines).clear();
        for c in &self.cards {
            if let Driver::Can(card) = &c.driver {
                card.flush();
                while card.link_up()
                    && card.sends_pending()
                    && std::time::Instant::now() < deadline
                    && self
                        .order
                        .iter()
                        .any(|t| t.name() == c.name && t.state() == TaskState::Running)
                {
                    std::thread::sleep(std::time::Duration::from_millis(2));
                }
                if !card.link_up() {
                    tracing::error!("card {:?}: link down, safe values not sent", c.name);
                }
            }
        }
        for t in self.order.iter().rev().filter(|t| is_bus(t)) {
            stop(t);
        }
        let mut lines = Vec::new();
        for c in &self.cards {
            let (ao, dout) = (c.analog_out(), c.digital_out());
            let analog: Vec<String> = (0..ao.channel_count())
                .map(|ch| {
                    ao.read_back(ch)
                        .map_or_else(|e| e.to_string(), |v| format!("{v}"))
                })
                .collect();
            let on: Vec<String> = (0..dout.output_count())
                .filter(|b| dout.check_bit(*b).unwrap_or(false))
                .map(|b| b.to_string())
                .collect();
            lines.push(format!(
                "card {:?} outputs at stop: analog [{}], digital on [{}]",
                c.name,
                analog.join(", "),
                on.join(", ")
            ));
        }
        lines
    }
}
