//! Reload: the deployment read again, checked whole as `hwgw check` checks it, and only
//! what changed rebuilt in the running gateway (SIGHUP, `systemctl reload hwgw`, the
//! control request `reload` behind `hwgw reload`).
//!
//! - A card whose section changed is stopped as at a stop — its outputs held, its IO
//!   components stopped, its safe values driven and settled, its bus side stopped — then
//!   built again and started; a card whose section is equal is not touched (its bus, its
//!   outputs, its counters and its IO components run on). Cards that share something
//!   through their driver (units on one Modbus line) are rebuilt together.
//! - Components, connections and aliases added, removed or changed are made, removed or
//!   made again; a component whose type, activity, properties or start changed is
//!   rebuilt, and so is one whose properties name a device of a rebuilt card (it looked
//!   the old device up). The servers are made again when their section or any card or
//!   alias changed; the output watchdog whenever anything did.
//! - One error in the new deployment and nothing changes. What cannot change while hwgw
//!   runs (runtime settings, the control socket, `[zenoh]`, what Zenoh exports or feeds
//!   from another gateway, `[[logical]]` and the cards a logical device is built on) is named in the report and left as it runs; the rest is
//!   applied.

use crate::build::{Selection, rebuild};
use crate::config::{ComponentConfig, Deployment, split_port};
use crate::deploy::{
    CardRt, Gateway, Link, Parts, settle_cards, start_servers, start_tasks, stop_task,
};
use crate::protocol::ReloadReport;
use crate::watchdog::{OUTPUT_WATCHDOG, Watched, output_watchdog};
use rtt::TaskContext;
use std::collections::{BTreeSet, HashMap, HashSet};

/// What a reload changes, worked out before anything is touched.
#[derive(Default)]
struct Plan {
    /// Cards taken down (rebuilt or removed), by name.
    cards_down: BTreeSet<String>,
    /// User components taken down (rebuilt or removed), by name.
    components_down: BTreeSet<String>,
    /// What is built from the new deployment.
    build: Selection,
    /// Aliases removed or changed (their names), and to be made (indices in the new list).
    aliases_down: Vec<String>,
    aliases_up: Vec<usize>,
    /// Report lines.
    applied: Vec<String>,
    restart: Vec<String>,
}

impl Gateway {
    /// Reads the deployment file again and applies what changed (see the module doc).
    pub fn reload(&self) -> ReloadReport {
        let file = self.running().file.clone();
        let Some(file) = file else {
            return ReloadReport::refused(vec![
                "running the embedded default: there is no file to read again".into(),
            ]);
        };
        match std::fs::read_to_string(&file) {
            Ok(text) => {
                let mut running = self.running();
                let report =
                    self.reload_locked(&mut running, &text, &file.display().to_string(), false);
                if report.errors.is_empty() {
                    // The file is what runs now: the run-time changes are gone with it.
                    running.changes.clear();
                    running.changes_dropped = 0;
                }
                report
            }
            Err(e) => ReloadReport::refused(vec![format!("{}: {e}", file.display())]),
        }
    }

    /// Applies deployment `text` (read from `file`) to the running gateway: what changed
    /// and only that, or nothing when it has an error.
    pub fn reload_text(&self, text: &str, file: &str) -> ReloadReport {
        let mut running = self.running();
        self.reload_locked(&mut running, text, file, false)
    }

    /// [`reload_text`](Self::reload_text) with the running deployment held (a run-time
    /// change edits it and applies the result under one lock). With `whole_or_nothing` (a
    /// run-time change) a change that needs a restart is refused, not half applied.
    pub(crate) fn reload_locked(
        &self,
        running: &mut crate::deploy::Running,
        text: &str,
        file: &str,
        whole_or_nothing: bool,
    ) -> ReloadReport {
        if running.stopping || self.is_stopping() {
            return ReloadReport::refused(vec!["the gateway is stopping".into()]);
        }
        // The whole deployment built as `check` builds it (nothing started), then let go;
        // what its cards share is kept for the plan.
        let (new, new_keys) = match Gateway::from_text(text, file, &self.types) {
            Ok((checked, d)) => {
                let keys = checked
                    .parts()
                    .cards
                    .iter()
                    .map(|c| (c.name.clone(), c.shares.clone()))
                    .collect();
                (d, keys)
            }
            Err(errors) => {
                return ReloadReport::refused(errors.lines().map(String::from).collect());
            }
        };
        let plan = self.plan(&running.deployment, &new, new_keys);
        if whole_or_nothing && !plan.restart.is_empty() {
            return ReloadReport::refused(
                plan.restart
                    .iter()
                    .map(|l| format!("{l} (it cannot change while hwgw runs)"))
                    .collect(),
            );
        }
        let mut report = ReloadReport {
            applied: plan.applied.clone(),
            restart: plan.restart.clone(),
            errors: Vec::new(),
        };
        if let Err(errors) = self.apply(plan, &new, text, file) {
            report.errors = errors;
        }
        running.deployment = applied_part(&running.deployment, new, &report);
        if report.errors.is_empty() {
            running.text = text.to_string();
        }
        if report.applied.is_empty() && report.errors.is_empty() {
            report.applied.push("nothing changed".into());
        } else {
            self.generation
                .fetch_add(1, std::sync::atomic::Ordering::Release);
        }
        report
    }

    /// Compares the running deployment `old` with `new` (`new_keys`: the bus each of its
    /// cards shares, from its check build).
    fn plan(
        &self,
        old: &Deployment,
        new: &Deployment,
        new_keys: HashMap<String, Option<String>>,
    ) -> Plan {
        let mut plan = Plan::default();
        restart_settings(old, new, &mut plan.restart);
        let parts = self.parts();
        let remote_fed = parts
            .links
            .iter()
            .filter(|l| l.made.is_none())
            .filter_map(|l| split_port(&l.config.to).map(|(c, _)| c.to_string()))
            .collect();
        let diff = Diff {
            old,
            new,
            parts: &parts,
            exported: crate::remote::exported_components(self.zenoh(), old),
            remote_fed,
            new_keys,
            zenoh: self.zenoh().is_some(),
        };
        diff.cards(&mut plan);
        let lost = diff.lost_names(&plan, self.runtime().registry());
        let alias_names = diff.aliases(&mut plan, &lost);
        diff.components(&mut plan, &lost, &alias_names);
        diff.connections(&mut plan);
        let sections = server_sections(old) != server_sections(new);
        plan.build.servers = sections
            || !plan.cards_down.is_empty()
            || !plan.build.cards.is_empty()
            || !plan.aliases_down.is_empty()
            || !plan.aliases_up.is_empty();
        if plan.build.servers && !diff.parts.servers.is_empty() || sections {
            plan.applied
                .push("servers made again (their clients reconnect)".into());
        }
        plan
    }

    /// Carries out `plan`: takes down what it names, builds what it selects from `new`,
    /// starts it. Errors past the check (a device gone between check and build) are
    /// returned; what was built stays.
    fn apply(
        &self,
        plan: Plan,
        new: &Deployment,
        text: &str,
        file: &str,
    ) -> Result<(), Vec<String>> {
        if plan.cards_down.is_empty()
            && plan.components_down.is_empty()
            && plan.build.cards.is_empty()
            && plan.build.components.is_empty()
            && plan.build.connections.is_empty()
            && plan.aliases_down.is_empty()
            && plan.aliases_up.is_empty()
            && !plan.build.servers
            && self
                .parts()
                .links
                .iter()
                .all(|l| new.connections.contains(&l.config))
        {
            return Ok(());
        }
        let down = self.take_out(&plan, new);
        // A driver panicking while its card goes down must not lose the card: put back,
        // the final stop drives and settles its outputs.
        let taken = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            self.take_down(&plan, &down);
        }));
        if taken.is_err() {
            let mut parts = self.parts_mut();
            parts.cards.extend(down.cards);
            parts
                .order
                .extend(down.components.into_iter().map(|t| (t, true)));
            return Err(vec![
                "a driver panicked while its card went down: the reload stopped there; \
                 restart hwgw"
                    .into(),
            ]);
        }
        drop(down);
        self.bring_up(&plan, new, text, file)
    }

    /// Out of the gateway's parts: what goes down.
    fn take_out(&self, plan: &Plan, new: &Deployment) -> Down {
        let mut parts = self.parts_mut();
        let (cards, kept): (Vec<CardRt>, Vec<CardRt>) = std::mem::take(&mut parts.cards)
            .into_iter()
            .partition(|c| plan.cards_down.contains(&c.name));
        parts.cards = kept;
        let card_tasks: HashSet<String> = cards
            .iter()
            .flat_map(|c| c.io.iter().chain(&c.bus))
            .map(|t| t.name().to_string())
            .collect();
        let going = |t: &TaskContext| {
            plan.components_down.contains(t.name()) || card_tasks.contains(t.name())
        };
        let (gone, kept): (Vec<_>, Vec<_>) = std::mem::take(&mut parts.order)
            .into_iter()
            .partition(|(t, _)| going(t));
        parts.order = kept;
        let is_component = |name: &str| self.runtime().component(name).is_ok();
        let touches = |a: &str| {
            crate::config::split_port_among(a, &is_component)
                .is_some_and(|(c, _)| plan.components_down.contains(c) || card_tasks.contains(c))
        };
        let (links, kept): (Vec<Link>, Vec<Link>) =
            std::mem::take(&mut parts.links).into_iter().partition(|l| {
                l.made.is_some()
                    && (!new.connections.contains(&l.config)
                        || touches(&l.config.from)
                        || touches(&l.config.to))
            });
        parts.links = kept;
        let servers = if plan.build.servers {
            std::mem::take(&mut parts.servers)
        } else {
            Vec::new()
        };
        Down {
            cards,
            components: gone.into_iter().map(|(t, _)| t).collect(),
            links,
            servers,
        }
    }

    /// Takes down what `take_out` took, as at a stop: servers (no client writes into what
    /// goes), outputs held, the writers stopped, the connections closed, the safe values
    /// driven and settled while the bus sides run, then the bus sides stopped; all of it
    /// out of the runtime and the registry.
    fn take_down(&self, plan: &Plan, down: &Down) {
        let runtime = self.runtime();
        for s in &down.servers {
            s.stop();
        }
        for c in &down.cards {
            c.hold.retire();
        }
        let is_bus = |t: &TaskContext| {
            down.cards
                .iter()
                .any(|c| c.bus.iter().any(|b| b.name() == t.name()))
        };
        for t in down.components.iter().rev().filter(|t| !is_bus(t)) {
            stop_task(t);
        }
        for l in &down.links {
            if let Some((from, id)) = &l.made {
                from.disconnect(Some(*id));
            }
        }
        // Stops the bus sides last, the safe values at the hardware.
        settle_cards(&down.cards);
        for c in &down.cards {
            tracing::info!("reload: {}", c.outputs_line());
        }
        for t in &down.components {
            if let Err(e) = runtime.remove(t.name()) {
                tracing::warn!("reload: {e}");
            }
        }
        let registry = runtime.registry();
        for c in &down.cards {
            registry.unregister_owner(&c.name);
        }
        for name in &plan.aliases_down {
            unregister_alias(registry, name);
        }
    }

    /// Up: what `plan` selects built from `new` (read from `file` as `text`) and
    /// started, then put among the gateway's parts; the output watchdog's cards and every
    /// output's writers worked out again.
    fn bring_up(
        &self,
        plan: &Plan,
        new: &Deployment,
        text: &str,
        file: &str,
    ) -> Result<(), Vec<String>> {
        let runtime = self.runtime();
        let mut errors = Vec::new();
        let aliases = |registry: &device_interface::Registry| {
            let mut problems = Vec::new();
            for &i in &plan.aliases_up {
                let a = &new.aliases[i];
                if let Err(e) = registry.alias(a.interface, &a.name, &a.target) {
                    problems.push(format!("alias[{i}]: {e}"));
                }
            }
            problems
        };
        let built = match rebuild(
            new,
            file,
            text,
            &self.types,
            (runtime, self.zenoh.clone(), self.control.clone()),
            &plan.build,
            aliases,
        ) {
            Ok(b) => b,
            Err((b, problems)) => {
                errors.extend(problems);
                b
            }
        };
        // Started before they join the parts: status and health never wait for a start.
        errors.extend(start_servers(&built.servers));
        if let Err(e) = start_tasks(&built.order) {
            errors.push(e.to_string());
        }
        let new_cards: Vec<String> = built.cards.iter().map(|c| c.name.clone()).collect();
        {
            let mut parts = self.parts_mut();
            parts.cards.extend(built.cards);
            parts.order.extend(built.order);
            parts.links.extend(built.links);
            parts.servers.extend(built.servers);
            set_writers(&parts);
            let watched = Watched::new(runtime, parts.cards.iter().map(|c| &c.outputs));
            let first = !watched.is_empty() && runtime.component(OUTPUT_WATCHDOG).is_err();
            parts.watch.store(std::sync::Arc::new(watched));
            if first {
                match output_watchdog(runtime, &parts.watch) {
                    Ok(Some(w)) => {
                        if let Err(e) = w.start() {
                            errors.push(e.to_string());
                        }
                        parts.order.push((w, true));
                    }
                    Ok(None) => {}
                    Err(e) => errors.push(e.to_string()),
                }
            }
        }
        // A stop that began meanwhile held the cards it found; these it may not have.
        if self.is_stopping() {
            for c in self
                .parts()
                .cards
                .iter()
                .filter(|c| new_cards.contains(&c.name))
            {
                c.hold.hold();
            }
        }
        if errors.is_empty() {
            Ok(())
        } else {
            Err(errors)
        }
    }
}

/// Logs what a reload did, each line under `what` (`SIGHUP`).
pub(crate) fn log_reload(what: &str, report: &crate::protocol::ReloadReport) {
    for line in &report.applied {
        tracing::info!("{what}: {line}");
    }
    for line in &report.restart {
        tracing::warn!("{what}: {line}");
    }
    if report.errors.is_empty() {
        return;
    }
    if report.applied.is_empty() {
        tracing::error!(
            "{what}: not applied, still running the previous version:\n{}",
            report.errors.join("\n")
        );
    } else {
        tracing::error!(
            "{what}: applied as above, but:\n{}",
            report.errors.join("\n")
        );
    }
}

/// Every card output's writers as the connections now say (a reload adds and removes
/// connections; a writer no longer connected must not trip an output).
fn set_writers(parts: &Parts) {
    for c in &parts.cards {
        let mut writers: Vec<(&str, &str)> = Vec::new();
        let is_component = |name: &str| parts.has_component(name);
        for l in &parts.links {
            let (Some((writer, _)), Some((component, port))) = (
                crate::config::split_port_among(&l.config.from, &is_component),
                split_port(&l.config.to),
            ) else {
                continue;
            };
            let ours = component
                .strip_suffix(".ao")
                .or_else(|| component.strip_suffix(".do"))
                .is_some_and(|card| card == c.name);
            if ours {
                writers.push((port, writer));
            }
        }
        for (card, port, writer) in &parts.logical_writers {
            if *card == c.name {
                writers.push((port, writer));
            }
        }
        c.outputs.set_writers(&writers);
    }
}

/// What a reload takes down, out of the gateway's parts.
struct Down {
    cards: Vec<CardRt>,
    /// User components and the cards' IO and bus components.
    components: Vec<TaskContext>,
    /// Connections closed.
    links: Vec<Link>,
    servers: Vec<Box<dyn driver_api::Server>>,
}

/// The running deployment, the new one, and what the gateway is made of now.
struct Diff<'a> {
    old: &'a Deployment,
    new: &'a Deployment,
    parts: &'a Parts,
    /// What Zenoh exports (components, `component.port`s): left as it runs.
    exported: HashSet<String>,
    /// Components another gateway feeds through Zenoh (a connection made once): left as
    /// they run.
    remote_fed: HashSet<String>,
    /// The bus key of each card of the new deployment, from its check build.
    new_keys: HashMap<String, Option<String>>,
    /// The gateway has a Zenoh node (a connection may come from another gateway).
    zenoh: bool,
}

impl Diff<'_> {
    /// The card whose digital output ThreadScope pulses (the runtime took the device at
    /// its start and keeps it), if ThreadScope is on.
    fn scope_card(&self) -> Option<&str> {
        let alias = self
            .old
            .aliases
            .iter()
            .find(|a| self.old.thread_scope && a.name == "ThreadScope")?;
        Some(
            split_port(&alias.target)
                .filter(|(card, _)| self.old.cards.iter().any(|c| c.name == *card))
                .map_or(alias.target.as_str(), |(card, _)| card),
        )
    }

    /// The cards going down and coming up.
    fn cards(&self, plan: &mut Plan) {
        let (old, new, parts, exported) = (self.old, self.new, self.parts, &self.exported);
        let old_card = |name: &str| old.cards.iter().find(|c| c.name == name);
        let mut down: BTreeSet<String> = BTreeSet::new();
        for c in &old.cards {
            if new.cards.iter().find(|n| n.name == c.name) != Some(c) {
                down.insert(c.name.clone());
            }
        }
        // Cards on one shared bus (Modbus units on one line) go down together, with any
        // card added to it: the bus key each has now, and in the new deployment.
        let key_of =
            |driver: &str, key: Option<&String>| key.map(|k| (driver.to_string(), k.clone()));
        let mut keys: HashSet<(String, String)> = HashSet::new();
        for c in &parts.cards {
            if down.contains(&c.name) {
                keys.extend(key_of(&c.driver, c.shares.as_ref()));
            }
        }
        for n in &new.cards {
            if old_card(&n.name).is_none() || down.contains(&n.name) {
                keys.extend(key_of(
                    &n.driver,
                    self.new_keys.get(&n.name).and_then(Option::as_ref),
                ));
            }
        }
        for c in &parts.cards {
            if key_of(&c.driver, c.shares.as_ref()).is_some_and(|k| keys.contains(&k)) {
                down.insert(c.name.clone());
            }
        }
        // What must run on as it is (Zenoh exports it, ThreadScope pulses on it) keeps its
        // whole bus group, and cards new to that bus wait for the restart with it.
        let mut held: HashSet<(String, String)> = HashSet::new();
        let mut stays: Vec<(String, String)> = Vec::new();
        for c in parts.cards.iter().filter(|c| down.contains(&c.name)) {
            let io: Vec<&str> = c.io.iter().chain(&c.bus).map(|t| t.name()).collect();
            let why = if let Some(e) = io
                .iter()
                .find(|t| exported.contains(**t) || self.remote_fed.contains(**t))
            {
                format!("Zenoh exports or feeds {e}")
            } else if self.scope_card() == Some(c.name.as_str()) {
                "ThreadScope pulses its output".to_string()
            } else if let Some(l) = self.old.logical.iter().find(|l| {
                crate::logical::devices_named(l).iter().any(|d| {
                    // An alias stands for its target's card.
                    let d = self
                        .old
                        .aliases
                        .iter()
                        .find(|a| a.name == *d)
                        .map_or(*d, |a| a.target.as_str());
                    on_card(d, &BTreeSet::from([c.name.clone()]))
                })
            }) {
                format!("the logical device {:?} is built on it", l.name())
            } else {
                continue;
            };
            held.extend(key_of(&c.driver, c.shares.as_ref()));
            stays.push((c.name.clone(), why));
        }
        for c in parts.cards.iter().filter(|c| down.contains(&c.name)) {
            if stays.iter().any(|(n, _)| *n == c.name) {
                continue;
            }
            if key_of(&c.driver, c.shares.as_ref()).is_some_and(|k| held.contains(&k)) {
                stays.push((c.name.clone(), "a card on its bus must run on".to_string()));
                continue;
            }
            plan.cards_down.insert(c.name.clone());
        }
        for n in new.cards.iter().filter(|n| old_card(&n.name).is_none()) {
            if key_of(
                &n.driver,
                self.new_keys.get(&n.name).and_then(Option::as_ref),
            )
            .is_some_and(|k| held.contains(&k))
            {
                stays.push((n.name.clone(), "a card on its bus must run on".to_string()));
            }
        }
        for (name, why) in &stays {
            plan.restart.push(format!(
                "card {name:?} changed, but {why}: restart hwgw to apply"
            ));
        }
        down.extend(stays.iter().map(|(n, _)| n.clone()));
        // Cards kept as they run: never built from the new deployment.
        let kept_cards: HashSet<&str> = down
            .iter()
            .filter(|n| !plan.cards_down.contains(*n))
            .map(String::as_str)
            .collect();
        for (i, c) in new.cards.iter().enumerate() {
            if kept_cards.contains(c.name.as_str()) {
                continue;
            }
            match old_card(&c.name) {
                None => plan.applied.push(format!("card {:?} added", c.name)),
                Some(_) if plan.cards_down.contains(&c.name) => plan.applied.push(format!(
                    "card {:?} rebuilt (its outputs went to their safe values first)",
                    c.name
                )),
                Some(_) => continue,
            }
            plan.build.cards.insert(i);
        }
        for c in &old.cards {
            if plan.cards_down.contains(&c.name) && new.cards.iter().all(|n| n.name != c.name) {
                plan.applied.push(format!(
                    "card {:?} removed (its outputs at their safe values)",
                    c.name
                ));
            }
        }
    }

    /// The names going down with the cards: their devices and aliases, and their IO and
    /// bus components (a component naming one in its properties looked it up, or reads
    /// its ports).
    fn lost_names(&self, plan: &Plan, registry: &device_interface::Registry) -> HashSet<String> {
        let mut lost: HashSet<String> = registry
            .entries()
            .into_iter()
            .filter(|e| {
                plan.cards_down.contains(&e.info.owner)
                    || e.info
                        .alias_of
                        .as_ref()
                        .is_some_and(|t| on_card(t, &plan.cards_down))
            })
            .map(|e| e.info.name)
            .collect();
        for c in self
            .parts
            .cards
            .iter()
            .filter(|c| plan.cards_down.contains(&c.name))
        {
            lost.extend(c.io.iter().chain(&c.bus).map(|t| t.name().to_string()));
        }
        lost
    }

    /// The aliases removed, changed or lost with what they stand for (an alias of an
    /// alias too); returns the names changed or lost. `lost`: the names going down.
    fn aliases(&self, plan: &mut Plan, lost: &HashSet<String>) -> HashSet<String> {
        let (old, new) = (self.old, self.new);
        let scope = |a: &crate::config::AliasConfig| old.thread_scope && a.name == "ThreadScope";
        for a in &old.aliases {
            if !new.aliases.contains(a) {
                if scope(a) {
                    plan.restart.push(
                        "alias \"ThreadScope\" changed, but ThreadScope pulses the device it \
                         took at start: restart hwgw to apply"
                            .into(),
                    );
                    continue;
                }
                plan.aliases_down.push(a.name.clone());
                if new.aliases.iter().all(|n| n.name != a.name) {
                    plan.applied.push(format!("alias {:?} removed", a.name));
                }
            }
        }
        // Changed, or standing for a name that goes (to a fixpoint: aliases of aliases).
        let mut gone: HashSet<String> = lost.clone();
        gone.extend(plan.aliases_down.iter().cloned());
        let mut up: BTreeSet<usize> = BTreeSet::new();
        loop {
            let before = up.len();
            for (i, a) in new.aliases.iter().enumerate() {
                let changed = !old.aliases.contains(a) && !scope(a);
                if (changed || gone.contains(&a.target)) && up.insert(i) {
                    gone.insert(a.name.clone());
                    if changed {
                        plan.applied
                            .push(format!("alias {:?} -> {:?} made", a.name, a.target));
                    }
                }
            }
            if up.len() == before {
                break;
            }
        }
        // Made in the order of the file: an alias of an alias after the one it names.
        plan.aliases_up = up.into_iter().collect();
        for &i in &plan.aliases_up {
            let name = &new.aliases[i].name;
            if !plan.aliases_down.contains(name) && old.aliases.iter().any(|a| a.name == *name) {
                plan.aliases_down.push(name.clone());
            }
        }
        gone.retain(|n| !lost.contains(n));
        gone
    }

    /// The components going down and coming up. `lost`: the names going down with the
    /// cards; `aliases`: the alias names changed or lost.
    fn components(&self, plan: &mut Plan, lost: &HashSet<String>, aliases: &HashSet<String>) {
        let (old, new) = (self.old, self.new);
        let old_component = |name: &str| old.components.iter().find(|c| c.name == name);
        // Those changed or removed go, and with them every component naming one of them
        // (its ports) in its properties.
        let mut going: HashSet<String> = lost.iter().chain(aliases).cloned().collect();
        going.extend(
            old.components
                .iter()
                .filter(|o| new.components.iter().find(|n| n.name == o.name) != Some(*o))
                .map(|o| o.name.clone()),
        );
        let hit =
            |s: &str| going.contains(s) || split_port(s).is_some_and(|(c, _)| going.contains(c));
        let stays = |name: &str| self.exported.contains(name) || self.remote_fed.contains(name);
        for (i, c) in new.components.iter().enumerate() {
            let names_lost = names_any(c, hit);
            match old_component(&c.name) {
                None => plan.applied.push(format!("component {:?} added", c.name)),
                Some(o) if o == c && !names_lost => continue,
                Some(_) if stays(&c.name) => {
                    plan.restart.push(format!(
                        "component {:?} changed, but Zenoh exports or feeds it: restart hwgw to apply",
                        c.name
                    ));
                    continue;
                }
                Some(o) => {
                    plan.components_down.insert(c.name.clone());
                    plan.applied.push(if o == c {
                        format!(
                            "component {:?} rebuilt (it uses what was rebuilt or removed)",
                            c.name
                        )
                    } else {
                        format!("component {:?} rebuilt", c.name)
                    });
                }
            }
            plan.build.components.insert(i);
        }
        for c in &old.components {
            if new.components.iter().all(|n| n.name != c.name) {
                if stays(&c.name) {
                    plan.restart.push(format!(
                        "component {:?} removed, but Zenoh exports or feeds it: restart hwgw to apply",
                        c.name
                    ));
                    continue;
                }
                plan.components_down.insert(c.name.clone());
                plan.applied.push(format!("component {:?} removed", c.name));
            }
        }
    }

    /// The connections closed and made: those touching anything going down are made
    /// again.
    fn connections(&self, plan: &mut Plan) {
        let (new, parts) = (self.new, self.parts);
        let is_component = |name: &str| parts.has_component(name);
        let down_component = |address: &str| {
            crate::config::split_port_among(address, &is_component).is_some_and(|(component, _)| {
                plan.components_down.contains(component)
                    || parts
                        .cards
                        .iter()
                        .filter(|c| plan.cards_down.contains(&c.name))
                        .any(|c| c.io.iter().chain(&c.bus).any(|t| t.name() == component))
            })
        };
        let touches =
            |c: &crate::config::ConnectionConfig| down_component(&c.from) || down_component(&c.to);
        for (i, c) in new.connections.iter().enumerate() {
            let was = parts.links.iter().find(|l| l.config == *c);
            match was {
                Some(l) if !touches(c) && l.made.is_some() => continue,
                Some(l) if l.made.is_none() => continue,
                Some(_) => {}
                None if self.zenoh
                    && split_port(&c.from).is_some_and(|(from, _)| from.contains('/')) =>
                {
                    plan.restart.push(format!(
                        "connection {} -> {} (from another gateway) added: restart hwgw to apply",
                        c.from, c.to
                    ));
                    continue;
                }
                None => plan
                    .applied
                    .push(format!("connection {} -> {} made", c.from, c.to)),
            }
            plan.build.connections.insert(i);
        }
        for l in &parts.links {
            if !new.connections.contains(&l.config) {
                if l.made.is_none() {
                    plan.restart.push(format!(
                        "connection {} -> {} (from another gateway) removed: restart hwgw to apply",
                        l.config.from, l.config.to
                    ));
                } else {
                    plan.applied.push(format!(
                        "connection {} -> {} closed",
                        l.config.from, l.config.to
                    ));
                }
            }
        }
    }
}

/// The settings a running gateway keeps until it restarts, named in `restart` when they
/// changed.
fn restart_settings(old: &Deployment, new: &Deployment, restart: &mut Vec<String>) {
    let mut changed = |what: &str, same: bool| {
        if !same {
            restart.push(format!("{what} changed: restart hwgw to apply"));
        }
    };
    changed("thread_scope", old.thread_scope == new.thread_scope);
    changed(
        "thread_scope_vcd",
        old.thread_scope_vcd == new.thread_scope_vcd,
    );
    changed(
        "thread_scope_vcd_keep",
        old.thread_scope_vcd_keep == new.thread_scope_vcd_keep,
    );
    changed(
        "cpu_dma_latency_us",
        old.cpu_dma_latency_us == new.cpu_dma_latency_us,
    );
    changed("control_socket", old.control_socket == new.control_socket);
    changed(
        "control_clients",
        old.control_clients == new.control_clients,
    );
    changed("control_idle_s", old.control_idle_s == new.control_idle_s);
    changed("[zenoh]", old.zenoh == new.zenoh);
    changed("[[logical]]", old.logical == new.logical);
}

/// The deployment's server sections: everything but the cards, aliases, components,
/// connections, runtime settings and `[zenoh]`.
fn server_sections(d: &Deployment) -> Deployment {
    Deployment {
        cards: Vec::new(),
        logical: Vec::new(),
        aliases: Vec::new(),
        components: Vec::new(),
        connections: Vec::new(),
        zenoh: None,
        thread_scope: false,
        thread_scope_vcd: None,
        thread_scope_vcd_keep: None,
        cpu_dma_latency_us: None,
        control_socket: None,
        control_clients: None,
        control_idle_s: None,
        ..d.clone()
    }
}

/// The deployment as it now runs: `new`, but with what needs a restart as it was.
fn applied_part(old: &Deployment, mut new: Deployment, report: &ReloadReport) -> Deployment {
    if !report.errors.is_empty() && report.applied.is_empty() {
        return old.clone();
    }
    new.thread_scope = old.thread_scope;
    new.thread_scope_vcd.clone_from(&old.thread_scope_vcd);
    new.thread_scope_vcd_keep = old.thread_scope_vcd_keep;
    new.cpu_dma_latency_us = old.cpu_dma_latency_us;
    new.control_socket.clone_from(&old.control_socket);
    new.control_clients = old.control_clients;
    new.control_idle_s = old.control_idle_s;
    new.zenoh.clone_from(&old.zenoh);
    new.logical.clone_from(&old.logical);
    let kept = |name: &str| {
        report
            .restart
            .iter()
            .any(|r| r.starts_with(&format!("card {name:?} ")))
    };
    // A card kept as it runs is as it was: changed back, put back if removed, taken out
    // if it was new (the next reload adds it).
    new.cards
        .retain(|c| !kept(&c.name) || old.cards.iter().any(|o| o.name == c.name));
    for c in new.cards.iter_mut() {
        if kept(&c.name)
            && let Some(o) = old.cards.iter().find(|o| o.name == c.name)
        {
            *c = o.clone();
        }
    }
    for o in &old.cards {
        if kept(&o.name) && new.cards.iter().all(|c| c.name != o.name) {
            new.cards.push(o.clone());
        }
    }
    if report
        .restart
        .iter()
        .any(|r| r.starts_with("alias \"ThreadScope\" "))
    {
        new.aliases.retain(|a| a.name != "ThreadScope");
        new.aliases.extend(
            old.aliases
                .iter()
                .filter(|a| a.name == "ThreadScope")
                .cloned(),
        );
    }
    let kept = |name: &str| {
        report
            .restart
            .iter()
            .any(|r| r.starts_with(&format!("component {name:?} ")))
    };
    for c in new.components.iter_mut() {
        if kept(&c.name)
            && let Some(o) = old.components.iter().find(|o| o.name == c.name)
        {
            *c = o.clone();
        }
    }
    for o in &old.components {
        if kept(&o.name) && new.components.iter().all(|c| c.name != o.name) {
            new.components.push(o.clone());
        }
    }
    new
}

/// True when `name` is one of `cards` or a device of one (`card.suffix`).
fn on_card(name: &str, cards: &BTreeSet<String>) -> bool {
    cards.iter().any(|c| {
        name == c
            || name
                .strip_prefix(c.as_str())
                .is_some_and(|r| r.starts_with('.'))
    })
}

/// Removes alias `name` (whichever interface has it; gone with its card already is fine).
fn unregister_alias(registry: &device_interface::Registry, name: &str) {
    for e in registry.entries() {
        if e.info.name != name || e.info.alias_of.is_none() {
            continue;
        }
        let _ = registry.unregister(e.interface, name);
    }
}

/// True when a string anywhere in `c`'s properties is one `hit` accepts.
fn names_any(c: &ComponentConfig, hit: impl Fn(&str) -> bool) -> bool {
    fn walk(v: &toml::Value, hit: &dyn Fn(&str) -> bool) -> bool {
        match v {
            toml::Value::String(s) => hit(s),
            toml::Value::Array(a) => a.iter().any(|v| walk(v, hit)),
            toml::Value::Table(t) => t.values().any(|v| walk(v, hit)),
            _ => false,
        }
    }
    // Its properties may name devices, and so may its required devices' bindings.
    c.properties.values().any(|v| walk(v, &hit))
        || c.requires.values().any(|b| match b {
            crate::config::Binding::One(name) => hit(name),
            crate::config::Binding::Many(names) => names.iter().any(|n| hit(n)),
        })
}
