//! What a recording reads from the runtime: a journal per component that its chosen
//! one-word output ports append to, a stamped buffer connection on each other chosen port,
//! and a tap on each chosen activity's steps, drained off the real-time threads into
//! [`recording::Item`]s.
//!
//! The ports' components write into pre-allocated memory, lock- and allocation-free: a
//! number, flag or character as an entry of its component's journal
//! ([`rtt::port::journal`]: the ports of a step write side by side, so a recorded write
//! costs about a store), any other sample into its connection's buffer. A sample takes the
//! start time of the step that wrote it, so no clock is read per write. A full journal or
//! buffer drops the sample and counts it against its port, and the counts end up in the
//! recording's metadata. Times are on the monotonic clock, as the steps' are.

use recording::{Closing, Item, PortSpec, Step};
use rtt::TaskContext;
use rtt::activity::{StepRecord, StepTap};
use rtt::component::{DynPort, DynReader, WordValue};
use rtt::info::Direction;
use rtt::port::journal::{Entry, Journal, MAX_ENTRIES, Tap};
use rtt::port::{ConnPolicy, FlowStatus};
use rtt::time::{Clock, MonotonicClock};
use std::sync::Arc;

/// The most samples a port's recording buffer holds (each a copy of the port's sample).
pub const MAX_BUFFER: usize = 1 << 16;

/// The most samples all of one recording's buffers hold together: a recording of many
/// ports gets smaller buffers (each at least 64), so one `record` stream allocates at most
/// this many samples however many ports it names.
pub const MAX_TOTAL_BUFFER: usize = 1 << 20;

/// How one recorded port's samples come.
enum Source {
    /// Through its component's journal (entries tagged with the port's index).
    Journal(Tap),
    /// Through a stamped buffer connection of its own.
    Reader(Box<dyn DynReader>),
}

/// The ports and activities being recorded.
pub struct Taps {
    ports: Vec<PortSpec>,
    sources: Vec<Source>,
    /// Per port: what turns a journal entry's word back into its value (journal ports).
    values: Vec<Option<WordValue>>,
    journals: Vec<Arc<Journal>>,
    /// A journal's entries as drained, and their order port after port (reused).
    entries: Vec<Entry>,
    counts: Vec<usize>,
    starts: Vec<usize>,
    order: Vec<usize>,
    activities: Vec<String>,
    steps: Vec<StepTap>,
    scratch: Vec<StepRecord>,
    buffer: usize,
    /// Samples whose value could not be serialised (counted, not written).
    unserialisable: u64,
}

/// Output ports chosen by `selectors`: `component.port` names one; a bare `component`
/// names each of its output ports. Errors name what exists.
pub fn resolve(
    peer: &dyn Fn(&str) -> Result<TaskContext, String>,
    selectors: &[String],
) -> Result<Vec<PortSpec>, String> {
    let mut out: Vec<PortSpec> = Vec::new();
    for sel in selectors {
        let found = match peer(sel) {
            Ok(t) => outputs(&t),
            Err(whole) => {
                let Some((comp, port)) = crate::config::split_port(sel) else {
                    return Err(format!("{sel:?}: {whole}"));
                };
                let t = peer(comp).map_err(|e| format!("{sel:?}: {e}"))?;
                let info = t.port(port).map_err(|e| format!("{sel:?}: {e}"))?.info();
                if info.direction != Direction::Output {
                    return Err(format!(
                        "{sel:?} is an input port: a recording takes output ports (outputs of {comp}: {})",
                        names(&outputs(&t))
                    ));
                }
                vec![PortSpec {
                    name: sel.clone(),
                    type_name: info.type_name,
                }]
            }
        };
        for p in found {
            if !out.iter().any(|o| o.name == p.name) {
                out.push(p);
            }
        }
    }
    Ok(out)
}

fn outputs(t: &TaskContext) -> Vec<PortSpec> {
    t.ports()
        .into_iter()
        .filter(|p| p.direction == Direction::Output)
        .map(|p| PortSpec {
            name: format!("{}.{}", t.name(), p.name),
            type_name: p.type_name,
        })
        .collect()
}

fn names(ports: &[PortSpec]) -> String {
    let v: Vec<&str> = ports.iter().map(|p| p.name.as_str()).collect();
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

impl Taps {
    /// Connects to `ports` (from [`resolve`]) with stamped buffers of `buffer` samples
    /// (clamped to 1..=[`MAX_BUFFER`], and so that all hold at most [`MAX_TOTAL_BUFFER`]),
    /// and taps the steps of `activities` (component names).
    pub fn open(
        peer: &dyn Fn(&str) -> Result<TaskContext, String>,
        ports: Vec<PortSpec>,
        activities: &[String],
        buffer: usize,
    ) -> Result<Taps, String> {
        let share = (MAX_TOTAL_BUFFER / ports.len().max(1)).max(64);
        let buffer = buffer.clamp(1, MAX_BUFFER).min(share);
        let mut found: Vec<(&str, Arc<dyn DynPort>)> = Vec::with_capacity(ports.len());
        for p in &ports {
            let Some((comp, port)) = crate::config::split_port(&p.name) else {
                return Err(format!("{:?}: expected \"component.port\"", p.name));
            };
            let port = peer(comp)
                .and_then(|t| t.port(port).map_err(|e| e.to_string()))
                .map_err(|e| format!("{}: {e}", p.name))?;
            found.push((comp, port));
        }
        let mut sources = Vec::with_capacity(ports.len());
        let mut values = Vec::with_capacity(ports.len());
        let mut journals: Vec<(&str, Arc<Journal>)> = Vec::new();
        for (i, (comp, port)) in found.iter().enumerate() {
            // One journal a component, room for `buffer` samples of each of its ports.
            let journal = match journals.iter().find(|(c, _)| c == comp) {
                Some((_, j)) => j.clone(),
                None => {
                    let n = found.iter().filter(|(c, _)| c == comp).count();
                    let j = Arc::new(Journal::new(buffer.saturating_mul(n).min(MAX_ENTRIES)));
                    journals.push((comp, j.clone()));
                    j
                }
            };
            let index = u32::try_from(i).map_err(|_| "too many ports to record".to_string())?;
            match port.tap(&journal, index, "recording") {
                Ok((tap, value)) => {
                    sources.push(Source::Journal(tap));
                    values.push(Some(value));
                }
                Err(_) => {
                    let reader = port
                        .stamped_reader(ConnPolicy::buffer(buffer))
                        .map_err(|e| format!("{}: {e}", ports[i].name))?;
                    sources.push(Source::Reader(reader));
                    values.push(None);
                }
            }
        }
        let journals = journals.into_iter().map(|(_, j)| j).collect();
        let mut steps = Vec::with_capacity(activities.len());
        for a in activities {
            let t = peer(a).map_err(|e| format!("activity {a:?}: {e}"))?;
            steps.push(t.activity().tap_steps(buffer.max(1024)));
        }
        Ok(Taps {
            ports,
            sources,
            values,
            journals,
            entries: Vec::new(),
            counts: Vec::new(),
            starts: Vec::new(),
            order: Vec::new(),
            activities: activities.to_vec(),
            steps,
            scratch: Vec::new(),
            buffer,
            unserialisable: 0,
        })
    }

    /// The ports recorded.
    pub fn ports(&self) -> &[PortSpec] {
        &self.ports
    }

    /// The activities recorded.
    pub fn activities(&self) -> &[String] {
        &self.activities
    }

    /// Moves what came since the last call into `out`: at most one journal's or buffer's
    /// worth from each, so a port written faster than it is drained cannot hold the others
    /// up.
    pub fn drain(&mut self, out: &mut Vec<Item>) {
        for journal in &self.journals {
            self.entries.clear();
            let ports = self.ports.len();
            let entries = &mut self.entries;
            let unserialisable = &mut self.unserialisable;
            // At most a lane's worth from each lane; an entry of no port (none is made) is
            // counted, not indexed.
            journal.drain(journal.capacity(), |e| {
                if (e.tap as usize) < ports {
                    entries.push(e);
                } else {
                    *unserialisable += 1;
                }
            });
            // Port after port, as the buffers give them: the file's writer takes a run of
            // one channel's messages faster than the same messages interleaved.
            self.counts.clear();
            self.counts.resize(self.ports.len() + 1, 0);
            for e in &self.entries {
                self.counts[e.tap as usize + 1] += 1;
            }
            for (source, &n) in self.sources.iter().zip(&self.counts[1..]) {
                if let (Source::Journal(tap), 1..) = (source, n) {
                    tap.taken(n as u64);
                }
            }
            for i in 1..self.counts.len() {
                self.counts[i] += self.counts[i - 1];
            }
            // Where each port's run starts (before the placing below moves the counts on).
            self.starts.clear();
            self.starts
                .extend_from_slice(&self.counts[..self.ports.len()]);
            self.order.clear();
            self.order.resize(self.entries.len(), 0);
            for (k, e) in self.entries.iter().enumerate() {
                let at = &mut self.counts[e.tap as usize];
                self.order[*at] = k;
                *at += 1;
            }
            // A port written by more than one writer (lanes one after the other) is put
            // back in time order; a run from one lane is in order already (a linear pass).
            for (p, &start) in self.starts.iter().enumerate() {
                let end = self.counts[p];
                let entries = &self.entries;
                self.order[start..end].sort_by_key(|&k| entries[k].at);
            }
            for &k in &self.order {
                let e = self.entries[k];
                let value = self
                    .values
                    .get(e.tap as usize)
                    .and_then(Option::as_ref)
                    .and_then(|v| v(e.word));
                match value {
                    Some(value) => out.push(Item::Sample {
                        port: e.tap,
                        at_ns: e.at,
                        value,
                    }),
                    None => self.unserialisable += 1,
                }
            }
        }
        for (i, source) in self.sources.iter_mut().enumerate() {
            let Source::Reader(r) = source else { continue };
            for _ in 0..self.buffer {
                match r.read_at() {
                    (FlowStatus::NewData, Some(value), at_ns) => out.push(Item::Sample {
                        port: i as u32,
                        at_ns,
                        value,
                    }),
                    (FlowStatus::NewData, None, _) => self.unserialisable += 1,
                    _ => break,
                }
            }
        }
        for (i, tap) in self.steps.iter().enumerate() {
            self.scratch.clear();
            tap.drain(&mut self.scratch);
            out.extend(self.scratch.iter().map(|s| Item::Step {
                activity: i as u32,
                step: Step {
                    scheduled_ns: s.scheduled,
                    started_ns: s.started,
                    ended_ns: s.ended,
                },
            }));
        }
    }

    /// What was lost so far: each port's and each activity's dropped count.
    pub fn losses(&self) -> Closing {
        Closing {
            ports_lost: self
                .sources
                .iter()
                .map(|s| match s {
                    Source::Journal(tap) => tap.info().map_or(0, |i| i.dropped),
                    Source::Reader(r) => r.dropped(),
                })
                .collect(),
            steps_lost: self.steps.iter().map(StepTap::dropped).collect(),
            unserialisable: self.unserialisable,
            notes: Default::default(),
        }
    }
}

/// UNIX time minus the monotonic clock's, ns: what turns a recording's times into UNIX
/// times.
pub fn wall_offset() -> i128 {
    let unix = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as i128);
    unix - i128::from(MonotonicClock.now().as_nanos())
}

/// The monotonic clock now, ns (the recordings' clock).
pub fn now_ns() -> u64 {
    MonotonicClock.now().as_nanos()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rtt::port::OutputPort;

    /// Each step writes `per_step` values to `x` (f64), one to `on` (bool) and one to `v`
    /// (a Vec: not one word).
    struct Mixed {
        x: OutputPort<f64>,
        on: OutputPort<bool>,
        v: OutputPort<Vec<f64>>,
        per_step: u32,
        n: f64,
    }

    impl rtt::Component for Mixed {
        fn update_hook(&mut self, _: &mut rtt::Context<'_>) -> rtt::HookResult {
            for _ in 0..self.per_step {
                self.n += 0.1;
                self.x.write(&self.n);
            }
            self.on.write(&(self.n > 0.5));
            self.v.write(&vec![self.n; 3]);
            Ok(())
        }
    }

    fn mixed(rt: &rtt::Runtime, name: &str, per_step: u32) -> rtt::TaskContext {
        rt.add(
            name,
            rtt::ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            move |i| {
                Ok(Mixed {
                    x: i.output("x", "numbers")?,
                    on: i.output("on", "a flag")?,
                    v: i.output("v", "a vector")?,
                    per_step,
                    n: 0.0,
                })
            },
        )
        .unwrap()
    }

    /// Numbers and flags of two components go through their components' journals, a
    /// vector through a connection of its own; every value comes back exact and in order,
    /// and what a full journal drops is counted against the port that wrote it.
    #[test]
    fn journals_and_buffers_give_back_every_value_and_count_losses_per_port() {
        let rt = rtt::Runtime::new(
            Arc::new(device_interface::Registry::new()),
            rtt::RuntimeOptions::default(),
        )
        .unwrap();
        let (a, b) = (mixed(&rt, "a", 1), mixed(&rt, "b", 10));
        a.start().unwrap();
        b.start().unwrap();
        let peer = |n: &str| rt.component(n).map_err(|e| e.to_string());
        let ports = resolve(&peer, &["a".to_string(), "b.x".to_string()]).unwrap();
        let names: Vec<&str> = ports.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, ["a.x", "a.on", "a.v", "b.x"]);
        // Room for 4 samples a port: a's journal holds 12, b's 4.
        let mut taps = Taps::open(&peer, ports, &[], 4).unwrap();
        a.step().unwrap();
        a.step().unwrap();
        b.step().unwrap();
        let mut items = Vec::new();
        taps.drain(&mut items);
        let of = |port: u32| -> Vec<serde_json::Value> {
            items
                .iter()
                .filter_map(|i| match i {
                    Item::Sample { port: p, value, .. } if *p == port => Some(value.clone()),
                    _ => None,
                })
                .collect()
        };
        let x = [0.1f64, 0.1 + 0.1];
        assert_eq!(of(0), x.map(|v| serde_json::json!(v)));
        assert_eq!(of(1), [serde_json::json!(false), serde_json::json!(false)]);
        assert_eq!(of(2), x.map(|v| serde_json::json!([v, v, v])));
        let mut n = 0.0f64;
        let b_x: Vec<serde_json::Value> = (0..4)
            .map(|_| {
                n += 0.1;
                serde_json::json!(n)
            })
            .collect();
        assert_eq!(of(3), b_x, "b's first four, exact");
        assert_eq!(taps.losses().ports_lost, [0, 0, 0, 6]);
        let counted = |port: &str| {
            rt.component(port.split('.').next().unwrap())
                .unwrap()
                .port(port.split('.').nth(1).unwrap())
                .unwrap()
                .connections()
                .iter()
                .map(|c| (c.written, c.read, c.dropped))
                .collect::<Vec<_>>()
        };
        assert_eq!(
            counted("a.x"),
            [(2, 2, 0)],
            "a tap's entries counted as taken"
        );
        assert_eq!(counted("b.x"), [(4, 4, 6)]);
        let order: Vec<u32> = items
            .iter()
            .filter_map(|i| match i {
                Item::Sample { port, .. } => Some(*port),
                _ => None,
            })
            .collect();
        assert_eq!(
            order,
            [0, 0, 1, 1, 3, 3, 3, 3, 2, 2],
            "each journal's samples port after port, then the buffers'"
        );
        assert!(
            items.iter().all(|i| i.time_ns() > 0),
            "every sample stamped"
        );
    }
}
