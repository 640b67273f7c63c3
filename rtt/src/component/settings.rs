//! What changes of a component's activity while it does not run (manual L747–752,
//! L4786–4803: RTT's `setPeriod`, `setPriority`/`setScheduler`), and slave components
//! stepped by a master (manual L4690–4700, L4725–4768: a slave activity "executes when
//! its master executes" — deterministic sub-components in their master's thread).

use super::TaskContext;
use crate::activity::{ActivityError, ActivitySpec, ThreadOptions};
use crate::error::LifecycleError;
use crate::state::TaskState;
use std::sync::Arc;
use std::time::Duration;

impl TaskContext {
    fn not_running(&self, command: &'static str) -> Result<(), LifecycleError> {
        match self.state() {
            TaskState::Running | TaskState::RunTimeError => Err(LifecycleError::Illegal {
                component: self.name().to_string(),
                command,
                state: self.state(),
            }),
            _ => Ok(()),
        }
    }

    fn activity_error(&self, e: ActivityError) -> LifecycleError {
        LifecycleError::Activity {
            component: self.name().to_string(),
            source: Arc::new(e),
        }
    }

    /// A new period for a component with a periodic activity, which must not be running
    /// (stop, set the period, start).
    pub fn set_period(&self, period: Duration) -> Result<(), LifecycleError> {
        self.not_running("set_period")?;
        self.activity()
            .set_period(period)
            .map_err(|e| self.activity_error(e))
    }

    /// New thread options (scheduling policy, priority, CPUs) for a component with a thread
    /// of its own, which must not be running.
    pub fn set_thread(&self, options: ThreadOptions) -> Result<(), LifecycleError> {
        self.not_running("set_thread")?;
        self.activity()
            .set_thread(options)
            .map_err(|e| self.activity_error(e))
    }

    /// Makes `slave` (a component with a slave activity) step right after each step of
    /// this one, on this one's thread, after the slaves added before it.
    pub fn add_slave(&self, slave: &TaskContext) -> Result<(), LifecycleError> {
        if !matches!(slave.activity().spec(), ActivitySpec::Slave) {
            return Err(self.activity_error(ActivityError::NotSlave));
        }
        if slave.name() == self.name() {
            return Err(LifecycleError::Illegal {
                component: self.name().to_string(),
                command: "add_slave (itself)",
                state: self.state(),
            });
        }
        if slave.steps(self.name()) {
            return Err(LifecycleError::Illegal {
                component: self.name().to_string(),
                command: "add_slave (its own master, through its slaves)",
                state: self.state(),
            });
        }
        self.core.slaves.rcu(|list| {
            let mut list = Vec::clone(list);
            list.retain(|t| t.name() != slave.name());
            list.push(slave.clone());
            list
        });
        Ok(())
    }

    /// Whether this component steps `name`, directly or through its slaves.
    fn steps(&self, name: &str) -> bool {
        self.core
            .slaves
            .load()
            .iter()
            .any(|t| t.name() == name || t.steps(name))
    }

    /// Stops stepping slave `name`; whether it was one.
    pub fn remove_slave(&self, name: &str) -> bool {
        let mut found = false;
        self.core.slaves.rcu(|list| {
            let mut list = Vec::clone(list);
            let before = list.len();
            list.retain(|t| t.name() != name);
            found = list.len() != before;
            list
        });
        found
    }

    /// Lets this component find component `target` as `alias` ([`Context::peer`](super::Context::peer)).
    pub fn set_peer_alias(&self, alias: &str, target: &str) {
        let mut aliases = crate::lock::lock(&self.core.peer_aliases);
        aliases.retain(|(a, _)| a != alias);
        aliases.push((alias.to_string(), target.to_string()));
    }

    /// The aliases this component knows its peers by: (alias, component).
    pub fn peer_aliases(&self) -> Vec<(String, String)> {
        crate::lock::lock(&self.core.peer_aliases).clone()
    }

    /// The slaves stepped after this component, in order.
    pub fn slaves(&self) -> Vec<String> {
        self.core
            .slaves
            .load()
            .iter()
            .map(|t| t.name().to_string())
            .collect()
    }
}
