//! Component types built into the binary, chosen by `type` in the deployment file.
//!
//! - `blinker`: toggles one bit of a DigitalOut device at each step (properties `device`,
//!   `bit`); while the device is offline or stale it waits in RunTimeError, trying the
//!   write at each step, and runs on when the device is back.
//! - `follow`: `out = in * gain + offset`, from an input port to an output port (connect
//!   an analog input's port to `in` and `out` to an analog output's port).
//! - `scan`: at every step reads analog input channels of any cards and writes analog
//!   outputs from them, as a PLC scans (see [`crate::scan`]).
//! - `reporter`: writes chosen ports to a CSV file at its period, every step or only when a
//!   port has new data (OCL's ReportingComponent); the file is rewritten at each start,
//!   never through a link and only when it is this process's own regular file.
//! - `recorder`: records ports and activity steps into an MCAP file, whole or the window
//!   around a trigger (see [`crate::recorder::component`]).
//! - `script`: a Lua 5.4 script — hooks, programs, a state machine — sandboxed and bounded
//!   (the `script` crate; `docs/scripts.md`).
//!
//! A component with a `base_dir` property is given the deployment's folder there before
//! its properties are set (a script finds its file relative to it).
//!
//! A user's own types go into a [`ComponentTypes`] beside these, in a binary of their own
//! that calls [`cli::main`](crate::cli::main) (see `examples/custom-component`).

use device_interface::{DeviceError, DigitalOut};
use rtt::component::DynReader;
use rtt::component::IntrospectError;
use rtt::port::ConnPolicy;
use rtt::port::{FlowStatus, InputPort, OutputPort};
use rtt::property::Property;
use rtt::{
    ActivitySpec, Component, Context, HookError, HookResult, InterfaceBuilder, Runtime,
    RuntimeError, TaskContext,
};
use std::collections::BTreeMap;
use std::io::Write;
use std::sync::Arc;

/// Builds a component of one type: `(runtime, name, activity)` to the new component.
pub type Constructor = fn(&Runtime, &str, ActivitySpec) -> Result<TaskContext, RuntimeError>;

/// Component types by name: what `type = "…"` in a deployment may say.
#[derive(Clone)]
pub struct ComponentTypes {
    types: BTreeMap<String, Constructor>,
}

impl ComponentTypes {
    /// No types.
    pub fn empty() -> Self {
        ComponentTypes {
            types: BTreeMap::new(),
        }
    }

    /// The types built into hwgw: blinker, follow, scan, reporter, recorder, script.
    pub fn builtin() -> Self {
        let mut t = Self::empty();
        t.types.insert("blinker".into(), |rt, name, spec| {
            rt.add(name, spec, rtt::InitialState::PreOperational, Blinker::new)
        });
        t.types.insert("follow".into(), |rt, name, spec| {
            rt.add(name, spec, rtt::InitialState::PreOperational, Follow::new)
        });
        t.types.insert("scan".into(), |rt, name, spec| {
            rt.add(
                name,
                spec,
                rtt::InitialState::PreOperational,
                crate::scan::Scan::new,
            )
        });
        t.types.insert("reporter".into(), |rt, name, spec| {
            rt.add(name, spec, rtt::InitialState::PreOperational, Reporter::new)
        });
        t.types.insert(script::TYPE.into(), script::add);
        t.types.insert("recorder".into(), |rt, name, spec| {
            rt.add(
                name,
                spec,
                rtt::InitialState::PreOperational,
                crate::recorder::component::McapRecorder::new,
            )
        });
        t
    }

    /// Adds type `name`; a name already taken is refused (returns false).
    pub fn register(&mut self, name: &str, constructor: Constructor) -> bool {
        if self.types.contains_key(name) {
            return false;
        }
        self.types.insert(name.to_string(), constructor);
        true
    }

    /// The type names, sorted.
    pub fn names(&self) -> Vec<&str> {
        self.types.keys().map(String::as_str).collect()
    }

    /// Builds component `name` of type `kind`; `Ok(None)` when the type is unknown.
    pub fn build(
        &self,
        runtime: &Runtime,
        name: &str,
        kind: &str,
        spec: ActivitySpec,
    ) -> Result<Option<TaskContext>, RuntimeError> {
        match self.types.get(kind) {
            Some(ctor) => ctor(runtime, name, spec).map(Some),
            None => Ok(None),
        }
    }
}

/// Whether `path` can be written at start without touching it now (`hwgw check` never
/// creates or truncates a report): a regular file of this process's own that it may write
/// and that has no other name (see [`recording::file::replace_own`]: never a link, a FIFO,
/// a device or another's file), or a new file in an existing folder this process may
/// write to.
fn writable(path: &std::path::Path) -> Result<(), HookError> {
    match recording::file::check_replace_own(path) {
        Ok(true) => Ok(()),
        Ok(false) => crate::checks::creatable(path).map_err(HookError::new),
        Err(e) => Err(HookError::new(format!(
            "{e} (the report is rewritten at each start)"
        ))),
    }
}

/// Toggles a digital output bit each step.
pub struct Blinker {
    device_name: Property<String>,
    bit: Property<u32>,
    device: Option<Arc<dyn DigitalOut>>,
    state: bool,
    toggles: OutputPort<bool>,
    warn_after: Property<u32>,
    error_after: Property<u32>,
    faults: rtt::faults::FaultCounter,
    log: rtt::log::Area,
}

impl Blinker {
    fn new(iface: &mut InterfaceBuilder<Blinker>) -> Result<Blinker, IntrospectError> {
        Ok(Blinker {
            device_name: iface.properties().add(
                "device",
                String::new(),
                "DigitalOut device to blink",
            )?,
            bit: iface.properties().add("bit", 0u32, "the bit to toggle")?,
            device: None,
            state: false,
            toggles: iface.output("state", "the state just written")?,
            warn_after: iface.properties().add(
                "warn_after",
                rtt::faults::FaultPolicy::default().warn_after,
                "failed writes in a row that raise the warning (0: never)",
            )?,
            error_after: iface.properties().add(
                "error_after",
                rtt::faults::FaultPolicy::default().error_after,
                "failed writes in a row that go to RunTimeError (0: never)",
            )?,
            faults: rtt::faults::FaultCounter::default(),
            log: rtt::log::Area::named(iface.name()),
        })
    }
}

impl Component for Blinker {
    fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let name = self.device_name.get();
        let device = ctx.registry().digital_out().lookup(&name)?;
        let bit = self.bit.get();
        if bit >= device.output_count() {
            return Err(HookError::new(format!(
                "bit {bit} does not exist on {name:?} ({} outputs)",
                device.output_count()
            )));
        }
        let policy = rtt::faults::FaultPolicy {
            warn_after: self.warn_after.get(),
            error_after: self.error_after.get(),
        };
        policy.check()?;
        self.faults = rtt::faults::FaultCounter::new(policy);
        self.device = Some(device);
        Ok(())
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        if let Some(d) = &self.device {
            match d.set_bit(self.bit.get(), !self.state) {
                Ok(()) => {
                    self.state = !self.state;
                    self.toggles.write(&self.state);
                    self.faults.good(ctx);
                }
                Err(e) if e.is_transient() => {
                    if self.faults.run() == 0 {
                        rtt::rt_log!(
                            self.log,
                            Warn,
                            "{}: waiting for the device",
                            rtt::log::Arg::display(&e)
                        );
                    }
                    self.faults.missed(ctx);
                }
                // The gateway is stopping and holds its outputs at their safe values: a
                // step due meanwhile has nothing to do (and is no failure).
                Err(DeviceError::Held { .. }) => {}
                Err(e) => return Err(e.into()),
            }
        }
        Ok(())
    }

    fn error_hook(&mut self, ctx: &mut Context<'_>) {
        if let Some(d) = &self.device
            && d.set_bit(self.bit.get(), self.state).is_ok()
        {
            rtt::rt_log!(self.log, Info, "the device is back");
            self.faults.good(ctx);
        }
    }

    fn stop_hook(&mut self, _: &mut Context<'_>) {
        if let Some(d) = &self.device {
            let _ = d.set_bit(self.bit.get(), false);
        }
    }
}

/// `out = in * gain + offset`.
pub struct Follow {
    input: InputPort<f64>,
    output: OutputPort<f64>,
    gain: Property<f64>,
    offset: Property<f64>,
}

impl Follow {
    fn new(iface: &mut InterfaceBuilder<Follow>) -> Result<Follow, IntrospectError> {
        Ok(Follow {
            input: iface.event_input("in", "the value followed")?,
            output: iface.output("out", "in * gain + offset")?,
            gain: iface.properties().add("gain", 1.0, "multiplier")?,
            offset: iface
                .properties()
                .add("offset", 0.0, "added after the gain")?,
        })
    }
}

impl Component for Follow {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let mut x = 0.0;
        while self.input.read(&mut x) == FlowStatus::NewData {
            self.output
                .write(&(x * self.gain.get() + self.offset.get()));
        }
        Ok(())
    }
}

/// Writes chosen ports to a CSV file: a header, then one row per step (or per step with
/// new data) with the time and every port's latest value. File I/O blocks, so give it a
/// SCHED_OTHER activity, never a real-time one.
pub struct Reporter {
    ports: Property<Vec<String>>,
    file: Property<String>,
    only_new: Property<bool>,
    sources: Vec<Box<dyn DynReader>>,
    last: Vec<String>,
    out: Option<std::io::BufWriter<std::fs::File>>,
    rows: OutputPort<u64>,
    written: u64,
}

impl Reporter {
    fn new(iface: &mut InterfaceBuilder<Reporter>) -> Result<Reporter, IntrospectError> {
        Ok(Reporter {
            ports: iface.properties().add(
                "ports",
                Vec::new(),
                "output ports to record, each \"component.port\"",
            )?,
            file: iface.properties().add(
                "file",
                String::new(),
                "the CSV file, created or rewritten at start (only a regular file of this process's own: never a link, a device or another's file)",
            )?,
            only_new: iface.properties().add(
                "only_new",
                false,
                "write a row only when some port has new data",
            )?,
            sources: Vec::new(),
            last: Vec::new(),
            out: None,
            rows: iface.output("rows", "rows written so far")?,
            written: 0,
        })
    }
}

impl Component for Reporter {
    fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let ports = self.ports.get();
        if ports.is_empty() {
            return Err(HookError::new(
                "property ports is empty: name at least one \"component.port\"",
            ));
        }
        self.sources.clear();
        for address in &ports {
            let (comp, port) = crate::config::split_port(address).ok_or_else(|| {
                HookError::new(format!("{address:?}: expected \"component.port\""))
            })?;
            let reader = ctx
                .peer(comp)?
                .port(port)?
                .reader(ConnPolicy::buffer(1024))?;
            self.sources.push(reader);
        }
        if self.file.get().is_empty() {
            return Err(HookError::new(
                "property file is empty: name the CSV file to write",
            ));
        }
        writable(std::path::Path::new(&self.file.get()))?;
        self.last = vec![String::new(); ports.len()];
        Ok(())
    }

    fn start_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        // Opened at start, not configure, so `hwgw check` never truncates a report. The
        // report is rewritten at each start (a restarted service writes it anew), so an
        // existing file is taken — but only one of this process's own, checked on the open
        // descriptor: a link, a FIFO or another's file planted since configure is refused.
        let path = self.file.get();
        let file = recording::file::replace_own(std::path::Path::new(&path))
            .map_err(|e| HookError::new(e.to_string()))?;
        let mut out = std::io::BufWriter::new(file);
        writeln!(out, "time_s,{}", self.ports.get().join(","))?;
        self.out = Some(out);
        Ok(())
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let mut any_new = false;
        for (src, last) in self.sources.iter_mut().zip(self.last.iter_mut()) {
            // Drain to the newest sample; a row shows the latest value of each port.
            while let (rtt::port::FlowStatus::NewData, Some(v)) = src.read() {
                *last = v.to_string();
                any_new = true;
            }
        }
        if self.only_new.get() && !any_new {
            return Ok(());
        }
        if let Some(out) = &mut self.out {
            writeln!(out, "{},{}", ctx.now(), self.last.join(","))?;
            self.written += 1;
            self.rows.write(&self.written);
        }
        Ok(())
    }

    fn stop_hook(&mut self, _: &mut Context<'_>) {
        if let Some(out) = &mut self.out
            && let Err(e) = out.flush()
        {
            tracing::error!("reporter: flushing {}: {e}", self.file.get());
        }
    }

    fn cleanup_hook(&mut self, _: &mut Context<'_>) {
        self.out = None;
        self.sources.clear();
    }
}
