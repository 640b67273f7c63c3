//! The Modbus card as an hwgw driver plug-in (`driver = "modbus"`, section
//! [`ModbusConfig`]).
//!
//! Every card is one unit. Cards whose transports are equal share one line: one
//! [`LineIo`] component, the bus side of the first card on it and named after it, polls
//! all their units with one request outstanding (the other cards have no bus side of their
//! own). At stop a card settles once its unit has taken the safe values and answered a
//! full poll after them, while its line runs.

use crate::card::ModbusCard;
use crate::component::LineIo;
use crate::config::ModbusConfig;
use crate::line::{LineUnit, Transport, UnitCounters, UnitStats, UnitTiming};
use device_interface::CardDevices;
use driver_api::{
    BuiltCard, BusSide, Card, CardContext, CardError, CardStatus, SettleError, wait_while,
};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

/// One line of a deployment: its transport, the units that share it, its component.
struct SharedLine {
    transport: Transport,
    /// The units, in build order: each card built on the line adds its own.
    units: Mutex<Vec<LineUnit>>,
    /// The line's component, reported by the bus side when it adds it: how every card on
    /// the line, the first or not, knows whether its line runs.
    task: OnceLock<rtt::TaskContext>,
}

impl SharedLine {
    /// The line's bus side: its component over every unit built on it by the time the
    /// gateway adds it (after the whole deployment is built).
    fn bus(line: Arc<SharedLine>) -> BusSide {
        BusSide::one(move |ctx| {
            let units = rtt::lock(&line.units)
                .iter()
                .map(|u| LineUnit {
                    card: u.card.clone(),
                    timing: u.timing,
                    stats: u.stats.clone(),
                })
                .collect();
            let task = LineIo::add(
                ctx.runtime(),
                ctx.name(),
                line.transport.clone(),
                units,
                ctx.thread().clone(),
            )?;
            // Set once: this bus side is consumed by adding it.
            let _ = line.task.set(task.clone());
            Ok(task)
        })
    }

    /// True while the line's component runs (not once it stopped or failed).
    fn running(&self) -> bool {
        self.task.get().is_some_and(|t| {
            matches!(
                t.state(),
                rtt::TaskState::Running | rtt::TaskState::RunTimeError
            )
        })
    }
}

/// The lines of one deployment, kept in the build context's shared state.
#[derive(Default)]
struct Lines(Vec<Arc<SharedLine>>);

/// A Modbus unit as a card.
struct ModbusPlugin {
    card: Arc<ModbusCard>,
    timing: UnitTiming,
    stats: Arc<UnitStats>,
    line: Arc<SharedLine>,
}

/// Builds a Modbus card from its section: the unit's map and timing, on the line of its
/// transport (shared with the cards before it on the same transport). The first card on a
/// line has the line's component as its bus side; the others none.
pub fn build(config: &ModbusConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
    let transport = config.transport()?;
    let timing = config.timing()?;
    let card = config.card(ctx.clock()).map_err(|e| match &e {
        crate::map::MapError::Point {
            point,
            key,
            problem,
        } => CardError::at(format!("point[{point}].{key}"), problem),
        _ => CardError::new(e),
    })?;
    if transport.rtu_framed() && timing.unit == 0 && !card.map().reads().is_empty() {
        return Err(CardError::at(
            "unit",
            "unit 0 is the broadcast address on RTU: every unit takes its writes and none answers, so it can have outputs only (no inputs, no read_back)",
        ));
    }
    let stats = Arc::new(UnitStats::default());
    let unit = LineUnit {
        card: card.clone(),
        timing,
        stats: stats.clone(),
    };
    ctx.shares_bus(transport.describe());
    let lines: &mut Lines = ctx.shared();
    if let Some(other) = lines
        .0
        .iter()
        .find(|l| l.transport.same_place(&transport) && l.transport != transport)
    {
        return Err(CardError::at(
            "transport",
            format!(
                "{} is a line already, with other settings ({}); {}",
                transport.describe(),
                other.transport.settings(),
                if matches!(transport, Transport::Rtu(_)) {
                    "every unit on one port shares its baud rate, parity, stop bits and turnaround"
                } else {
                    "every unit behind one address shares its framing (tcp or rtu_over_tcp) and turnaround"
                }
            ),
        ));
    }
    let (line, first) = match lines.0.iter().find(|l| l.transport == transport) {
        Some(l) => (l.clone(), false),
        None => {
            let l = Arc::new(SharedLine {
                transport,
                units: Mutex::new(Vec::new()),
                task: OnceLock::new(),
            });
            lines.0.push(l.clone());
            (l, true)
        }
    };
    rtt::lock(&line.units).push(unit);
    let bus = first.then(|| SharedLine::bus(line.clone()));
    let card = Box::new(ModbusPlugin {
        card,
        timing,
        stats,
        line,
    });
    Ok(BuiltCard { card, bus })
}

impl Card for ModbusPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn read_back(&self) -> driver_api::ReadBack {
        // With `read_back` the outputs are polled: after a good poll their images are the
        // unit's registers. Without, they only hold what hwgw wrote.
        if self.card.map().reads_outputs() {
            let card = self.card.clone();
            driver_api::ReadBack::DeviceWhen(Arc::new(move || card.polled()))
        } else {
            driver_api::ReadBack::Written
        }
    }

    fn summary(&self) -> String {
        let reads = self.card.map().reads();
        format!(
            "{:?} unit {}, {} reads per poll: {}",
            self.line.transport,
            self.timing.unit,
            reads.len(),
            reads
                .iter()
                .map(|r| r.to_string())
                .collect::<Vec<_>>()
                .join("; ")
        )
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(
            format!("{:?} unit {}", self.line.transport, self.timing.unit),
            &UnitCounters::from_stats(self.timing.unit, &self.stats),
        )
    }

    fn settle(&self, deadline: Instant, bus_running: bool) -> Result<(), SettleError> {
        // Confirmed once the unit took the writes and a whole poll after them succeeded.
        // The line is this card's bus side or another card's: it must run.
        let line_running = || bus_running && self.line.running();
        let polls = self.stats.polls.load(Ordering::Relaxed);
        let pending = || self.card.writes_pending() || self.card.deliveries_pending();
        wait_while(deadline, Duration::from_millis(5), || {
            (pending() || self.stats.polls.load(Ordering::Relaxed) <= polls) && line_running()
        });
        if pending() {
            return Err(SettleError::pending(
                line_running(),
                "safe values confirmed by the unit",
            ));
        }
        // A write the unit refused is not sent again: that output does not hold its value.
        let failed = self.card.failed_outputs();
        if !failed.is_empty() {
            let list = failed
                .iter()
                .map(|(role, ch, why)| {
                    let what = if *role == crate::map::Role::DigitalOut {
                        "digital"
                    } else {
                        "analog"
                    };
                    format!("{what} output {ch}: {why}")
                })
                .collect();
            return Err(SettleError::Refused(list));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;
    use device_interface::time::MonotonicClock;
    use std::collections::HashMap;

    fn unit(n: u8) -> ModbusConfig {
        toml::from_str(&format!(
            "transport = {{ type = \"tcp\", address = \"127.0.0.1:1\" }}\nunit = {n}\n\
             [[point]]\ntable = \"coils\"\naddress = 0\n"
        ))
        .unwrap()
    }

    #[test]
    fn the_first_card_on_a_line_has_its_bus_side_and_no_card_waits_for_a_line_not_running() {
        let mut shared = HashMap::new();
        let mut built: Vec<BuiltCard> = Vec::new();
        for (name, n) in [("a", 1), ("b", 2)] {
            let mut ctx = CardContext::new(
                name,
                Duration::from_millis(10),
                std::path::Path::new("."),
                Arc::new(MonotonicClock),
                &mut shared,
            );
            built.push(build(&unit(n), &mut ctx).unwrap());
        }
        // One line, one component: the first card's bus side; the second has none.
        assert!(built[0].bus.is_some());
        assert!(built[1].bus.is_none());
        // Its line never started, no card waits for a poll that will not come.
        let settles_at_once = |card: &dyn Card| {
            let t0 = Instant::now();
            assert_eq!(card.settle(t0 + Duration::from_secs(3), true), Ok(()));
            assert!(t0.elapsed() < Duration::from_secs(1), "{:?}", t0.elapsed());
        };
        settles_at_once(built[0].card.as_ref());
        settles_at_once(built[1].card.as_ref());
        // Added (not started), the line's component is the first card's, named after it.
        let registry = Arc::new(device_interface::Registry::new());
        let rt = rtt::Runtime::new(registry, Default::default()).unwrap();
        let thread = rtt::ThreadOptions::default();
        let BuiltCard { bus, .. } = built.remove(0);
        let tasks = bus
            .unwrap()
            .add_to(&driver_api::BusContext::new(&rt, "a", &thread))
            .unwrap();
        assert_eq!(tasks.len(), 1);
        assert_eq!(tasks[0].name(), "a");
        settles_at_once(built[0].card.as_ref());
    }
}
