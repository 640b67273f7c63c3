//! What a recording reads from the runtime: a stamped buffer connection on each chosen
//! output port and a tap on each chosen activity's steps, drained off the real-time
//! threads into [`recording::Item`]s.
//!
//! The ports' components write into their connection's pre-allocated buffer (lock- and
//! allocation-free; a sample takes the start time of the step that wrote it, so no clock
//! is read per write); a full buffer drops the sample and counts it, and the counts end
//! up in the recording's metadata. Times are on the monotonic clock, as the steps' are.

use recording::{Closing, Item, PortSpec, Step};
use rtt::TaskContext;
use rtt::activity::{StepRecord, StepTap};
use rtt::component::DynReader;
use rtt::info::Direction;
use rtt::port::{ConnPolicy, FlowStatus};
use rtt::time::{Clock, MonotonicClock};

/// The most samples a port's recording buffer holds (each a copy of the port's sample).
pub const MAX_BUFFER: usize = 1 << 16;

/// The most samples all of one recording's buffers hold together: a recording of many
/// ports gets smaller buffers (each at least 64), so one `record` stream allocates at most
/// this many samples however many ports it names.
pub const MAX_TOTAL_BUFFER: usize = 1 << 20;

/// The ports and activities being recorded.
pub struct Taps {
    ports: Vec<PortSpec>,
    readers: Vec<Box<dyn DynReader>>,
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
        let mut readers = Vec::with_capacity(ports.len());
        for p in &ports {
            let Some((comp, port)) = crate::config::split_port(&p.name) else {
                return Err(format!("{:?}: expected \"component.port\"", p.name));
            };
            let reader = peer(comp)
                .and_then(|t| {
                    t.port(port)
                        .and_then(|port| port.stamped_reader(ConnPolicy::buffer(buffer)))
                        .map_err(|e| e.to_string())
                })
                .map_err(|e| format!("{}: {e}", p.name))?;
            readers.push(reader);
        }
        let mut steps = Vec::with_capacity(activities.len());
        for a in activities {
            let t = peer(a).map_err(|e| format!("activity {a:?}: {e}"))?;
            steps.push(t.activity().tap_steps(buffer.max(1024)));
        }
        Ok(Taps {
            ports,
            readers,
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

    /// Moves what came since the last call into `out`: at most one buffer's worth per
    /// port, so a port written faster than it is drained cannot hold the others up.
    pub fn drain(&mut self, out: &mut Vec<Item>) {
        for (i, r) in self.readers.iter_mut().enumerate() {
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
            ports_lost: self.readers.iter().map(|r| r.dropped()).collect(),
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
