//! The runtime: the components, the device registry they share, the clock and ThreadScope.

use crate::activity::ActivitySpec;
use crate::component::{Component, InterfaceBuilder, TaskContext, TaskSetup};
use crate::error::{IntrospectError, RuntimeError};
use crate::lock::lock;
use crate::scope::{self, ThreadScope};
use crate::state::{InitialState, TaskState};
use device_interface::Registry;
use device_interface::time::{Clock, MonotonicClock};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};

/// How the runtime runs.
#[derive(Clone)]
pub struct RuntimeOptions {
    /// Pulse each runtime thread's bit on the DigitalOut named "ThreadScope".
    pub thread_scope: bool,
    /// Record each runtime thread's bit into this VCD file (created new, never
    /// overwritten; see [`crate::scope::vcd`]), with or without `thread_scope`.
    pub thread_scope_vcd: Option<std::path::PathBuf>,
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
            thread_scope_vcd: None,
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
    /// [`shared`](Runtime::shared) state, one value per type.
    shared: Mutex<SharedState>,
    _cpu_latency: Option<std::fs::File>,
}

/// One value per type, each shared as an `Arc`.
type SharedState =
    std::collections::HashMap<std::any::TypeId, Arc<dyn std::any::Any + Send + Sync>>;

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
        if let Some(path) = &options.thread_scope_vcd {
            scope.record_vcd(path)?;
        }
        scope::set_thread_number(0);
        // What real-time threads log is written by the logger thread.
        if let Err(e) = crate::log::spawn_writer() {
            tracing::warn!("no logger thread: {e}; real-time log records wait and drop");
        }
        Ok(Runtime {
            registry,
            clock: options.clock,
            scope: Arc::new(scope),
            next_thread: Arc::new(AtomicU32::new(1)),
            components: Arc::new(Mutex::new(Vec::new())),
            shared: Mutex::new(SharedState::new()),
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

    /// State the parts of one deployment share beyond ports, operations and devices, one
    /// value of each type, made (`T::default()`) on first use and kept as long as the
    /// runtime: a driver's lines that its server forwards requests to, say, registered by
    /// the lines as they are added and found by the server when it is built after them or
    /// when it serves. Takes a lock: not for real-time paths.
    ///
    /// ```
    /// use std::sync::atomic::{AtomicU32, Ordering};
    /// let registry = std::sync::Arc::new(device_interface::Registry::new());
    /// let rt = rtt::Runtime::new(registry, Default::default())?;
    /// rt.shared::<AtomicU32>().store(7, Ordering::Relaxed);
    /// assert_eq!(rt.shared::<AtomicU32>().load(Ordering::Relaxed), 7);
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn shared<T: Default + Send + Sync + 'static>(&self) -> Arc<T> {
        let mut map = crate::lock(&self.shared);
        let slot = map
            .entry(std::any::TypeId::of::<T>())
            .or_insert_with(|| Arc::new(T::default()));
        match slot.clone().downcast::<T>() {
            Ok(t) => t,
            Err(_) => {
                // Never: the entry for TypeId::of::<T>() is only ever given a T.
                let t = Arc::new(T::default());
                *slot = t.clone();
                t
            }
        }
    }

    /// The ThreadScope (on or off).
    pub fn thread_scope(&self) -> &ThreadScope {
        &self.scope
    }

    /// Builds component `name` with activity `spec`: `build` gets the interface to add
    /// ports, operations and properties to, and returns the component. It starts in
    /// `initial`: Stopped, or PreOperational when it must be configured first.
    pub fn add<C: Component>(
        &self,
        name: &str,
        spec: ActivitySpec,
        initial: InitialState,
        build: impl FnOnce(&mut InterfaceBuilder<C>) -> Result<C, IntrospectError>,
    ) -> Result<TaskContext, RuntimeError> {
        let mut components = lock(&self.components);
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
        let task = TaskContext::build(name, spec, initial, setup, build)?;
        components.push(task.clone());
        Ok(task)
    }

    /// The component `name`.
    pub fn component(&self, name: &str) -> Result<TaskContext, RuntimeError> {
        let components = lock(&self.components);
        components
            .iter()
            .find(|c| c.name() == name)
            .cloned()
            .ok_or_else(|| RuntimeError::NotFound {
                name: name.to_string(),
                known: components.iter().map(|c| c.name().to_string()).collect(),
            })
    }

    /// Takes component `name` out of the runtime (a deployment changed while it runs): it
    /// is stopped first if running, and its activity ends once the last handle to it is
    /// dropped. Its ports' connections are the caller's to close. Returns it, or
    /// [`RuntimeError::NotFound`] listing the components.
    pub fn remove(&self, name: &str) -> Result<TaskContext, RuntimeError> {
        let task = {
            let mut components = lock(&self.components);
            let Some(i) = components.iter().position(|c| c.name() == name) else {
                return Err(RuntimeError::NotFound {
                    name: name.to_string(),
                    known: components.iter().map(|c| c.name().to_string()).collect(),
                });
            };
            let task = components.remove(i);
            // No master steps it any more.
            for c in components.iter() {
                c.remove_slave(name);
            }
            task
        };
        if matches!(task.state(), TaskState::Running | TaskState::RunTimeError)
            && let Err(e) = task.stop()
        {
            tracing::warn!("{e}");
        }
        Ok(task)
    }

    /// Every component, in the order added.
    pub fn components(&self) -> Vec<TaskContext> {
        lock(&self.components).clone()
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
        // The last records of its threads, out before the process ends.
        crate::log::flush();
    }
}
