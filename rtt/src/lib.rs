//! An Orocos-RTT-2.x-style component runtime: the part of hwgw that hosts drivers and
//! users' components.
//!
//! - [`component`]: the [`Component`] hooks and the [`TaskContext`] lifecycle (Init,
//!   PreOperational, Stopped, Running, RunTimeError, Exception, FatalError), with every
//!   port, operation, property and attribute reachable by name with JSON values;
//! - [`port`]: `OutputPort<T>`/`InputPort<T>` with data, buffer and circular-buffer
//!   connections, lock-free and allocation-free;
//! - [`operation`]: ClientThread and OwnThread operations with `call`, `send` and
//!   `collect`;
//! - [`property`]: typed, documented, nested properties loaded from and saved to TOML;
//! - [`activity`]: periodic, non-periodic, file-descriptor and slave activities with
//!   timing statistics;
//! - [`scope`]: ThreadScope, each runtime thread as a bit on a digital output;
//! - [`time`]: the monotonic clock and its simulated twin.
//!
//! ```
//! use device_interface::Registry;
//! use rtt::{ActivitySpec, Component, Context, HookResult, Runtime, RuntimeOptions};
//! use rtt::port::{FlowStatus, InputPort, OutputPort};
//! use std::sync::Arc;
//!
//! struct Doubler {
//!     input: InputPort<f64>,
//!     output: OutputPort<f64>,
//! }
//!
//! impl Component for Doubler {
//!     fn update_hook(&mut self, _ctx: &mut Context<'_>) -> HookResult {
//!         let mut x = 0.0;
//!         if self.input.read(&mut x) == FlowStatus::NewData {
//!             self.output.write(&(2.0 * x));
//!         }
//!         Ok(())
//!     }
//! }
//!
//! let runtime = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default())?;
//! let task = runtime.add("doubler", ActivitySpec::Slave, false, |iface| {
//!     Ok(Doubler {
//!         input: iface.input("in", "a number")?,
//!         output: iface.output("out", "twice the number")?,
//!     })
//! })?;
//! let mut w = task.port("in")?.writer(Default::default())?;
//! let mut r = task.port("out")?.reader(Default::default())?;
//! task.start()?;
//! w.write(serde_json::json!(21.0))?;
//! task.step()?;
//! assert_eq!(r.read().1, Some(serde_json::json!(42.0)));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod activity;
pub mod component;
pub mod operation;
pub mod port;
pub mod property;
pub mod scope;

/// Monotonic time for the runtime (shared with the device interfaces).
pub mod time {
    pub use device_interface::time::{Clock, MonotonicClock, SimClock, Timestamp};
}

pub use activity::{ActivitySpec, SchedPolicy, ThreadOptions, Timing};
pub use component::{Component, Context, HookError, HookResult, Interface, TaskContext, TaskState};

use component::{IntrospectError, TaskSetup};
use device_interface::{Registry, RegistryError};
use scope::ThreadScope;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use time::{Clock, MonotonicClock};

/// Why the runtime could not do what was asked.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RuntimeError {
    /// ThreadScope is on but no DigitalOut is registered as "ThreadScope".
    #[error("ThreadScope is on, but {0}")]
    ThreadScope(#[source] RegistryError),
    /// Two components with one name.
    #[error("a component named {0:?} already exists")]
    Duplicate(String),
    /// No component of that name.
    #[error("no component named {name:?}; there are: {}", if .known.is_empty() { "none".to_string() } else { .known.join(", ") })]
    NotFound {
        /// The name asked for.
        name: String,
        /// The components that exist.
        known: Vec<String>,
    },
    /// The component's activity could not be made.
    #[error("component {component:?}: {source}")]
    Activity {
        /// The component.
        component: String,
        /// Why.
        #[source]
        source: Arc<activity::ActivityError>,
    },
    /// The component's constructor failed.
    #[error("component {component:?}: {source}")]
    Build {
        /// The component.
        component: String,
        /// Why.
        #[source]
        source: IntrospectError,
    },
}

/// How the runtime runs.
#[derive(Clone)]
pub struct RuntimeOptions {
    /// Pulse each runtime thread's bit on the DigitalOut named "ThreadScope".
    pub thread_scope: bool,
    /// The clock components read through their context.
    pub clock: Arc<dyn Clock>,
    /// Ask the kernel (PM QoS, `/dev/cpu_dma_latency`) to keep CPU wake-up latency at or
    /// below this many µs while the runtime lives: `Some(0)` keeps CPUs out of deep idle
    /// states, as cyclictest does. Needs write access to the device; refused, it is logged
    /// and the runtime runs on.
    pub cpu_dma_latency_us: Option<u32>,
}

impl Default for RuntimeOptions {
    fn default() -> Self {
        RuntimeOptions {
            thread_scope: false,
            clock: Arc::new(MonotonicClock),
            cpu_dma_latency_us: None,
        }
    }
}

/// Holds a PM QoS CPU latency request: the kernel honours it while the file stays open.
fn hold_cpu_latency(us: u32) -> Option<std::fs::File> {
    use std::io::Write;
    let path = "/dev/cpu_dma_latency";
    let result = std::fs::OpenOptions::new()
        .write(true)
        .open(path)
        .and_then(|mut f| {
            f.write_all(&(us.min(i32::MAX as u32) as i32).to_ne_bytes())
                .map(|()| f)
        });
    match result {
        Ok(f) => {
            tracing::info!("holding CPU wake-up latency at {us} µs ({path})");
            Some(f)
        }
        Err(e) => {
            tracing::warn!(
                "cannot hold CPU wake-up latency at {us} µs: {path}: {e}; deep idle states may add \
                 wake-up latency (give the service write access to {path})"
            );
            None
        }
    }
}

/// The runtime: the components, the device registry they share, the clock and ThreadScope.
///
/// The thread that makes it is runtime thread 0; activity threads are numbered from 1 in
/// the order they are made.
pub struct Runtime {
    registry: Arc<Registry>,
    clock: Arc<dyn Clock>,
    scope: Arc<ThreadScope>,
    next_thread: Arc<AtomicU32>,
    components: Arc<Mutex<Vec<TaskContext>>>,
    _cpu_latency: Option<std::fs::File>,
}

impl Runtime {
    /// A runtime over `registry`. With ThreadScope on, a DigitalOut named "ThreadScope"
    /// (usually an alias) must be registered already.
    pub fn new(registry: Arc<Registry>, options: RuntimeOptions) -> Result<Runtime, RuntimeError> {
        let scope = if options.thread_scope {
            let out = registry
                .digital_out()
                .lookup("ThreadScope")
                .map_err(RuntimeError::ThreadScope)?;
            tracing::info!("ThreadScope: main thread is bit 0");
            ThreadScope::on(out)
        } else {
            ThreadScope::off()
        };
        scope::set_thread_number(0);
        Ok(Runtime {
            registry,
            clock: options.clock,
            scope: Arc::new(scope),
            next_thread: Arc::new(AtomicU32::new(1)),
            components: Arc::new(Mutex::new(Vec::new())),
            _cpu_latency: options.cpu_dma_latency_us.and_then(hold_cpu_latency),
        })
    }

    /// The device registry.
    pub fn registry(&self) -> &Arc<Registry> {
        &self.registry
    }

    /// The clock.
    pub fn clock(&self) -> &Arc<dyn Clock> {
        &self.clock
    }

    /// The ThreadScope (on or off).
    pub fn thread_scope(&self) -> &ThreadScope {
        &self.scope
    }

    /// Builds component `name` with activity `spec`: `build` gets the interface to add
    /// ports, operations and properties to, and returns the component. It starts in
    /// PreOperational when `needs_configure`, else in Stopped.
    pub fn add<C: Component>(
        &self,
        name: &str,
        spec: ActivitySpec,
        needs_configure: bool,
        build: impl FnOnce(&mut Interface<C>) -> Result<C, IntrospectError>,
    ) -> Result<TaskContext, RuntimeError> {
        let mut components = port::lock(&self.components);
        if components.iter().any(|c| c.name() == name) {
            return Err(RuntimeError::Duplicate(name.to_string()));
        }
        let next = self.next_thread.clone();
        let setup = TaskSetup {
            registry: self.registry.clone(),
            clock: self.clock.clone(),
            scope: self.scope.clone(),
            thread_number: Box::new(move || next.fetch_add(1, Ordering::Relaxed)),
            peers: Arc::downgrade(&self.components),
        };
        let task = TaskContext::build(name, spec, needs_configure, setup, build)?;
        components.push(task.clone());
        Ok(task)
    }

    /// The component `name`.
    pub fn component(&self, name: &str) -> Result<TaskContext, RuntimeError> {
        let components = port::lock(&self.components);
        components
            .iter()
            .find(|c| c.name() == name)
            .cloned()
            .ok_or_else(|| RuntimeError::NotFound {
                name: name.to_string(),
                known: components.iter().map(|c| c.name().to_string()).collect(),
            })
    }

    /// Every component, in the order added.
    pub fn components(&self) -> Vec<TaskContext> {
        port::lock(&self.components).clone()
    }

    /// Stops every running component, last added first.
    pub fn stop_all(&self) {
        for c in self.components().iter().rev() {
            if matches!(c.state(), TaskState::Running | TaskState::RunTimeError)
                && let Err(e) = c.stop()
            {
                tracing::warn!("{e}");
            }
        }
    }
}

impl Drop for Runtime {
    fn drop(&mut self) {
        self.stop_all();
    }
}
