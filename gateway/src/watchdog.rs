//! The output watchdog: one periodic component (every 10 ms) applying
//! [`CardOutputs::watch`] to the cards whose outputs need it, over a set a reload swaps
//! whole while it runs.

use crate::outputs::CardOutputs;
use rtt::{ActivitySpec, InitialState, Runtime, TaskContext};
use std::collections::HashMap;
use std::sync::Arc;

/// The output watchdog's component name.
pub const OUTPUT_WATCHDOG: &str = "output_watchdog";

/// What the output watchdog watches: the cards whose outputs need it, and every
/// component by name (a writer's state trips its outputs).
#[derive(Default)]
pub(crate) struct Watched {
    cards: Vec<Arc<CardOutputs>>,
    components: HashMap<String, TaskContext>,
}

impl Watched {
    /// Over the cards' `outputs` that need a watchdog, and the runtime's components now.
    pub(crate) fn new<'o>(
        runtime: &Runtime,
        outputs: impl IntoIterator<Item = &'o Arc<CardOutputs>>,
    ) -> Watched {
        Watched {
            cards: outputs
                .into_iter()
                .filter(|o| o.watched())
                .cloned()
                .collect(),
            components: runtime
                .components()
                .into_iter()
                .map(|t| (t.name().to_string(), t))
                .collect(),
        }
    }

    /// True when no card needs the watchdog.
    pub(crate) fn is_empty(&self) -> bool {
        self.cards.is_empty()
    }
}

/// What the output watchdog watches, swapped whole by a reload while it runs (so it never
/// stops watching the cards that run on).
pub(crate) type WatchSet = Arc<arc_swap::ArcSwap<Watched>>;

/// Applies the output policy's watchdog to the cards that need it, every 10 ms.
struct OutputWatchdog(WatchSet);

impl rtt::Component for OutputWatchdog {
    fn update_hook(&mut self, ctx: &mut rtt::Context<'_>) -> rtt::HookResult {
        let now = ctx.timing().started.as_nanos();
        let watched = self.0.load();
        let state = |name: &str| watched.components.get(name).map(TaskContext::state);
        for c in &watched.cards {
            c.watch(now, &state);
        }
        Ok(())
    }
}

/// The output watchdog's component over `set` (not started), when it watches a card.
pub(crate) fn output_watchdog(
    runtime: &Runtime,
    set: &WatchSet,
) -> Result<Option<TaskContext>, rtt::RuntimeError> {
    if set.load().is_empty() {
        return Ok(None);
    }
    let spec = ActivitySpec::periodic(std::time::Duration::from_millis(10));
    let set = set.clone();
    let task = runtime.add(OUTPUT_WATCHDOG, spec, InitialState::Stopped, move |_| {
        Ok(OutputWatchdog(set))
    })?;
    Ok(Some(task))
}
