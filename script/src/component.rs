//! The `script` component: one Lua state, on the component's own activity, running the
//! script's hooks (`configure`, `start`, `update`, `stop`, `cleanup`, `error_update`),
//! its programs and its root state machine; operations to drive them and to reload the
//! script; the collector stepped between steps; every step bounded in time and memory.

use crate::error::{ScriptError, message};
use crate::host::{Host, Requests};
use crate::load::{Loaded, Setup};
use crate::operations::Glue;
use crate::ports::PortMap;
use mlua::{Function, IntoLuaMulti, Value as LuaValue};
use rtt::component::{IntrospectError, SelfRef};
use rtt::port::OutputPort;
use rtt::property::Property;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};
use serde_json::Value;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// Hook indices in [`HOOKS`].
const CONFIGURE: usize = 0;
const START: usize = 1;
const UPDATE: usize = 2;
const STOP: usize = 3;
const CLEANUP: usize = 4;
const ERROR_UPDATE: usize = 5;

/// A full collection runs between steps once Lua memory passes this share of `memory_kb`.
const FULL_GC_AT: f64 = 0.75;

/// Time spent collecting between steps.
#[derive(Default)]
struct GcTime {
    total_ns: u64,
    max_ns: u64,
    /// Bytes allocated by the steps since the collector last ran.
    pending: usize,
}

/// The script component.
pub struct Script {
    file: Property<String>,
    base_dir: Property<String>,
    data_dir: Property<String>,
    vars: Property<Value>,
    memory_kb: Property<u32>,
    max_step_us: Property<u32>,
    gc_step_kb: Property<u32>,
    overruns: Property<u64>,
    memory_used_kb: Property<u64>,
    full_collections: Property<u64>,
    gc_ns_total: Property<u64>,
    gc_ns_max: Property<u64>,
    gc: GcTime,
    ports: PortMap,
    name: String,
    me: Option<SelfRef>,
    reload: crate::operations::Reload,
    /// What operations and the start's glue asked of the error model, carried out at
    /// the next hook that has a context.
    pending: Requests,
    /// An operation moved the machine since the last step: that was the step's one
    /// transition.
    requested: bool,
    registry: Option<std::sync::Arc<device_interface::Registry>>,
    loaded: Option<Loaded>,
    state: OutputPort<String>,
    last_state: String,
    steps: u64,
    overrun_count: u64,
    full_count: u64,
}

impl Script {
    /// Declares the component's interface: properties, the `state` port, operations.
    pub fn new(iface: &mut InterfaceBuilder<Script>) -> Result<Script, IntrospectError> {
        let p = iface.properties();
        let script = Script {
            file: p.add(
                "file",
                String::new(),
                "the Lua script, relative to base_dir",
            )?,
            base_dir: p.add(
                "base_dir",
                String::new(),
                "the folder a relative file is found in (the gateway sets the deployment's)",
            )?,
            data_dir: p.add(
                "data_dir",
                String::new(),
                "the folder io.open may reach, relative to base_dir (empty: none)",
            )?,
            vars: p.add(
                "vars",
                Value::Object(Default::default()),
                "values passed in: the script's global table `vars`",
            )?,
            memory_kb: p.add("memory_kb", 8192u32, "Lua memory limit, KiB")?,
            max_step_us: p.add(
                "max_step_us",
                100_000u32,
                "a call into the script running longer is stopped (an overrun; 0: no limit and no \
                 instruction hook, read at configure)",
            )?,
            gc_step_kb: p.add(
                "gc_step_kb",
                0u32,
                "collector work between steps, KiB, once the steps allocated 1 KiB (0: twice what they allocated)",
            )?,
            overruns: iface
                .attributes()
                .add("overruns", 0u64, "calls stopped by max_step_us")?,
            memory_used_kb: iface.attributes().add(
                "memory_used_kb",
                0u64,
                "Lua memory in use (every 1000 steps)",
            )?,
            full_collections: iface.attributes().add(
                "full_collections",
                0u64,
                "full collections run because memory passed 3/4 of memory_kb",
            )?,
            gc_ns_total: iface.attributes().add(
                "gc_ns_total",
                0u64,
                "time spent collecting between steps, ns (every 1000 steps)",
            )?,
            gc_ns_max: iface.attributes().add(
                "gc_ns_max",
                0u64,
                "the longest collection between two steps, ns (every 1000 steps)",
            )?,
            gc: GcTime::default(),
            ports: PortMap::default(),
            name: iface.name().to_string(),
            me: None,
            reload: Default::default(),
            pending: Requests::default(),
            requested: false,
            registry: None,
            loaded: None,
            state: iface.output("state", "the root machine's state (empty: none)")?,
            last_state: String::new(),
            steps: 0,
            overrun_count: 0,
            full_count: 0,
        };
        crate::operations::declare(iface, &script.reload)?;
        Ok(script)
    }

    fn budget(&self) -> Option<Duration> {
        match self.max_step_us.get() {
            0 => None,
            us => Some(Duration::from_micros(u64::from(us))),
        }
    }

    fn budget_text(loaded: &Loaded) -> String {
        loaded
            .budget
            .map_or("none".into(), |b| format!("{} µs", b.as_micros()))
    }

    /// Loads the script afresh (it is not kept: see [`Self::install`]).
    pub(crate) fn load(&self) -> Result<Loaded, ScriptError> {
        let (Some(me), Some(registry)) = (&self.me, &self.registry) else {
            return Err(ScriptError::Lua("the component is not configured".into()));
        };
        let base = PathBuf::from(self.base_dir.get());
        let data = self.data_dir.get();
        let data_dir = (!data.is_empty()).then(|| crate::load::resolve(&base, &data));
        let file = self.file.get();
        let vars = self.vars.get();
        let memory = usize::try_from(self.memory_kb.get())
            .unwrap_or(usize::MAX)
            .saturating_mul(1024);
        crate::load::load(Setup {
            name: &self.name,
            file: &file,
            base_dir: &base,
            data_dir,
            vars: &vars,
            memory,
            me: me.clone(),
            ports: self.ports.clone(),
            registry: registry.clone(),
            budget: self.budget(),
        })
    }

    /// Calls hook `i` of `loaded` (if it defines it) within the step budget.
    fn call_hook(&mut self, loaded: &Loaded, i: usize) -> Result<Requests, HookError> {
        let Some(f) = &loaded.hooks[i] else {
            return Ok(Requests::default());
        };
        let f = f.clone();
        self.call::<_, ()>(loaded, &f, ()).map(|((), r)| r)
    }

    /// Calls `f` within the step budget: its result and what it asked of the error model;
    /// an error (an overrun among them) with the script's file:line.
    fn call<A: IntoLuaMulti, R: mlua::FromLuaMulti>(
        &mut self,
        loaded: &Loaded,
        f: &Function,
        args: A,
    ) -> Result<(R, Requests), HookError> {
        loaded.sandbox.arm(loaded.budget);
        let r = f.call::<R>(args);
        loaded.sandbox.disarm();
        let requests = if loaded
            .asked
            .swap(false, std::sync::atomic::Ordering::Relaxed)
        {
            loaded
                .sandbox
                .lua
                .app_data_mut::<Host>()
                .map(|mut h| std::mem::take(&mut h.requests))
                .unwrap_or_default()
        } else {
            Requests::default()
        };
        if loaded.sandbox.overran() {
            // Stopped by its deadline: with the hook's error, or after catching it (pcall)
            // and returning — stopped all the same.
            let what = match &r {
                Ok(_) => format!("{}: stopped: it ran past its time", self.file.get()),
                Err(e) => message(e),
            };
            self.overrun_count += 1;
            self.overruns.set(self.overrun_count);
            return Err(HookError::new(format!(
                "{what} (overrun {}: max_step_us = {})",
                self.overrun_count,
                Self::budget_text(loaded),
            )));
        }
        r.map(|v| (v, requests))
            .map_err(|e| HookError::new(message(&e)))
    }

    /// The loaded script's hook `i`, its requests applied to `ctx`.
    fn hook(&mut self, ctx: &mut Context<'_>, i: usize) -> HookResult {
        let Some(loaded) = self.loaded.take() else {
            return Ok(());
        };
        let r = self.call_hook(&loaded, i);
        self.loaded = Some(loaded);
        apply(ctx, r?);
        Ok(())
    }

    /// Runs the collector between steps: at least what the step allocated, and a full
    /// collection when memory nears the limit.
    fn collect(&mut self, loaded: &Loaded, before: usize) {
        let lua = &loaded.sandbox.lua;
        let used = lua.used_memory();
        // What the steps allocated since the collector last ran: a script whose steps
        // allocate nothing is never collected, and pays nothing for it.
        self.gc.pending += used.saturating_sub(before);
        self.steps += 1;
        // Published every 1000 steps: setting an attribute allocates.
        if self.steps % 1000 == 1 {
            self.memory_used_kb.set((used / 1024) as u64);
            self.gc_ns_total.set(self.gc.total_ns);
            self.gc_ns_max.set(self.gc.max_ns);
        }
        if self.gc.pending < 1024 {
            return;
        }
        let kb = match self.gc_step_kb.get() {
            0 => self.gc.pending / 1024 * 2,
            k => k as usize,
        };
        self.gc.pending = 0;
        let began = Instant::now();
        let _ = lua.gc_step_kbytes(i32::try_from(kb).unwrap_or(i32::MAX));
        let limit = loaded.memory;
        if used as f64 > limit as f64 * FULL_GC_AT {
            let _ = lua.gc_collect();
            self.full_count += 1;
            self.full_collections.set(self.full_count);
        }
        let took = began.elapsed().as_nanos() as u64;
        self.gc.total_ns += took;
        self.gc.max_ns = self.gc.max_ns.max(took);
    }

    /// One step of the script: `update`, the programs, the machine; the state port.
    fn step(&mut self, ctx: &mut Context<'_>, loaded: &Loaded) -> HookResult {
        let before = loaded.sandbox.lua.used_memory();
        let step = loaded.step.clone();
        let update = loaded.hooks[UPDATE].clone();
        let requested = std::mem::take(&mut self.requested);
        let ((state, failed), mut requests) = self
            .call::<_, (Option<mlua::String>, Option<mlua::Table>)>(
                loaded,
                &step,
                (update, requested),
            )?;
        requests.merge(std::mem::take(&mut self.pending));
        for f in failed
            .iter()
            .flat_map(|t| t.sequence_values::<mlua::Table>().flatten())
        {
            let name: String = f.get("name").unwrap_or_default();
            let error: String = f.get("error").unwrap_or_default();
            tracing::warn!("script {:?}: program {name:?} failed: {error}", ctx.name());
        }
        // Compared in place: a step whose state did not change allocates nothing here.
        let same = match &state {
            Some(s) => *s.as_bytes() == *self.last_state.as_bytes(),
            None => self.last_state.is_empty(),
        };
        if !same {
            self.last_state = state.map(|s| s.to_string_lossy()).unwrap_or_default();
            self.state.write(&self.last_state);
        }
        apply(ctx, requests);
        self.collect(loaded, before);
        Ok(())
    }

    /// Replaces the loaded script with `new` (configured already), the old one cleaned up.
    pub(crate) fn install(&mut self, new: Loaded) -> Result<Requests, HookError> {
        let asked = self.call_hook(&new, CONFIGURE)?;
        if let Some(old) = self.loaded.take() {
            let _ = self.call_hook(&old, CLEANUP);
        }
        self.loaded = Some(new);
        Ok(asked)
    }
}

impl crate::operations::Glue for Script {
    /// Calls glue function `name` with `args` within the budget, for an operation.
    fn glue(&mut self, name: &str, args: (String, Option<String>)) -> Result<Value, String> {
        let loaded = self
            .loaded
            .take()
            .ok_or_else(|| "no script is loaded: configure the component".to_string())?;
        let f: Result<Function, _> = loaded.sandbox.lua.globals().raw_get(name);
        // One transition per step: a second request before the next step waits for it.
        let moves = name == "__hwgw_machine" && matches!(args.0.as_str(), "request_state" | "step");
        if moves && self.requested {
            self.loaded = Some(loaded);
            return Err(
                "the machine made a transition this step already: ask again after the \
                        next step"
                    .into(),
            );
        }
        let r = match f {
            Ok(f) => match self.call::<_, mlua::MultiValue>(&loaded, &f, args) {
                Ok((v, asked)) => {
                    self.pending.merge(asked);
                    result(&loaded, v)
                }
                Err(e) => Err(e.to_string()),
            },
            Err(e) => Err(message(&e)),
        };
        if moves && r.is_ok() {
            self.requested = true;
        }
        self.loaded = Some(loaded);
        r
    }
}

/// An operation's Lua results as its answer: `false, reason` is the reason as an error.
fn result(loaded: &Loaded, v: mlua::MultiValue) -> Result<Value, String> {
    use mlua::LuaSerdeExt;
    let mut it = v.into_iter();
    let first = it.next().unwrap_or(LuaValue::Nil);
    if first == LuaValue::Boolean(false)
        && let Some(reason) = it.next()
    {
        return Err(reason.to_string().unwrap_or_else(|_| format!("{reason:?}")));
    }
    loaded
        .sandbox
        .lua
        .from_value(first)
        .map_err(|e| message(&e))
}

/// Carries out what a call into the script asked of the error model.
fn apply(ctx: &mut Context<'_>, r: Requests) {
    if r.warning {
        ctx.warning();
    }
    if r.recovered {
        ctx.recovered();
    }
    if r.error {
        ctx.error();
    }
    if r.recover {
        ctx.recover();
    }
    if let Some(reason) = r.exception {
        ctx.exception(reason);
    }
}

impl Component for Script {
    fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let me = ctx.self_ref();
        *rtt::lock(&self.reload) = Some((self.name.clone(), me.clone()));
        self.me = Some(me);
        self.registry = Some(ctx.registry().clone());
        // Configured again while stopped (reload_script): a script that fails to load
        // leaves the loaded one in place.
        let new = self.load().map_err(|e| HookError::new(e.to_string()))?;
        let asked = self.install(new)?;
        apply(ctx, asked);
        Ok(())
    }

    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        self.hook(ctx, START)?;
        let _ = self
            .glue("__hwgw_start", (String::new(), None))
            .map_err(HookError::new)?;
        apply(ctx, std::mem::take(&mut self.pending));
        Ok(())
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let Some(loaded) = self.loaded.take() else {
            return Ok(());
        };
        let r = self.step(ctx, &loaded);
        self.loaded = Some(loaded);
        r
    }

    fn error_hook(&mut self, ctx: &mut Context<'_>) {
        if let Err(e) = self.hook(ctx, ERROR_UPDATE) {
            ctx.exception(e.to_string());
        }
    }

    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        if let Err(e) = self.glue("__hwgw_stop", (String::new(), None)) {
            tracing::warn!("script {:?}: its machine at stop: {e}", ctx.name());
        }
        if let Err(e) = self.hook(ctx, STOP) {
            tracing::warn!("script {:?}: stop: {e}", ctx.name());
        }
    }

    fn cleanup_hook(&mut self, ctx: &mut Context<'_>) {
        if let Err(e) = self.hook(ctx, CLEANUP) {
            tracing::warn!("script {:?}: cleanup: {e}", ctx.name());
        }
        self.loaded = None;
    }
}
