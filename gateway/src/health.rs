//! How the systemd watchdog's looks judge a component's periodic activity: overrunning
//! when it spent at least half the time since the look before in unhealthy spells, or
//! stalled when it ended no step since then and for longer than its overruns allowed.
//!
//! A look judges the time between itself and the look before, not the moment it is taken:
//! a gateway whose activity overruns most of the time is restarted after an interval
//! without a feed, and one whose machine was busy for moments (a few short spells, each
//! over before the next look) is fed, the spells counted in the activity's statistics and
//! logged by its thread. Seen in the kernel rig: three spells of the demo's 10 ms
//! activities in 2.4 s while apt ran on the guest's one emulated CPU, each seen by one
//! look, withheld three feeds in a row, and systemd restarted hwgw with its outputs at
//! their safe values for a machine that was busy, not a gateway that was stuck.

use rtt::{ActivitySpec, TaskContext};
use std::collections::HashMap;
use std::time::{Duration, Instant};

/// What the last look saw of each component's activity, by name: kept by the watchdog
/// between its looks.
#[derive(Debug, Default)]
pub struct Looks {
    by_name: HashMap<String, Look>,
}

#[derive(Debug, Clone, Copy)]
struct Look {
    at: Instant,
    unhealthy_ns: u64,
    steps: u64,
    /// When a look last found its step count moved, or found it newly running.
    stepped_at: Instant,
    running: bool,
}

impl Looks {
    /// No look yet: the first judges the activity as it is at that moment.
    pub fn new() -> Looks {
        Looks::default()
    }

    /// Forgets the components `keep` says are gone.
    pub(crate) fn retain(&mut self, keep: impl Fn(&str) -> bool) {
        self.by_name.retain(|name, _| keep(name));
    }

    /// Records what this look sees of `t` at `now` whether or not it is judged (`running`
    /// false: it is not, and its step count may stand still), and says what is wrong
    /// with its activity since the look before, if anything.
    pub(crate) fn judge(&mut self, t: &TaskContext, running: bool, now: Instant) -> Option<String> {
        let stats = t.stats();
        let before = self.by_name.get(t.name()).copied();
        let stepped_at = match before {
            Some(b) if running && b.running && b.steps == stats.steps => b.stepped_at,
            _ => now,
        };
        self.by_name.insert(
            t.name().to_string(),
            Look {
                at: now,
                unhealthy_ns: stats.unhealthy_ns,
                steps: stats.steps,
                stepped_at,
                running,
            },
        );
        if !running {
            return None;
        }
        let Some(before) = before else {
            return (!stats.healthy).then(|| overruns(t));
        };
        let window = now.saturating_duration_since(before.at);
        let unhealthy =
            Duration::from_nanos(stats.unhealthy_ns.saturating_sub(before.unhealthy_ns));
        if !unhealthy.is_zero() && unhealthy * 2 >= window {
            return Some(overruns(t));
        }
        let allowed = stall_allowed(&t.activity().current())?;
        (now.saturating_duration_since(stepped_at) > allowed).then(|| {
            format!(
                "{} ended no step for more than {} ms",
                t.name(),
                allowed.as_millis()
            )
        })
    }
}

fn overruns(t: &TaskContext) -> String {
    format!("{} overruns its period", t.name())
}

/// How long a periodic activity judged for its overruns (`max_overruns` set) may go without
/// ending a step: a period for each overrun it is allowed, and two more (two step ends of
/// an activity on time can be a period and a step apart: with no overrun allowed, one
/// period would find a stall in a look that falls between them). `None` for an activity
/// the watchdog does not judge.
fn stall_allowed(spec: &ActivitySpec) -> Option<Duration> {
    match spec {
        ActivitySpec::Periodic {
            period,
            max_overruns: Some(m),
            ..
        } => Some(period.saturating_mul(m.saturating_add(2))),
        _ => None,
    }
}
