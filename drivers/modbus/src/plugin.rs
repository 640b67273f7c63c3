//! The Modbus card as an hwgw driver plug-in (`driver = "modbus"`, section
//! [`ModbusConfig`]).
//!
//! Every card is one unit. Cards whose transports are equal share one line: one
//! [`LineIo`] component, named after the first card on it, polls all their units with one
//! request outstanding. At stop a card settles once its unit has taken the safe values and
//! answered a full poll after them.

use crate::card::ModbusCard;
use crate::component::LineIo;
use crate::config::ModbusConfig;
use crate::line::{LineUnit, Transport, UnitCounters, UnitStats, UnitTiming};
use device_interface::CardDevices;
use driver_api::{Card, CardContext, CardError, CardStatus};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// One line of a deployment: its transport, the units that share it, its component.
struct SharedLine {
    transport: Transport,
    thread: rtt::ThreadOptions,
    /// The units, until the line's component takes them.
    units: Mutex<Vec<LineUnit>>,
    /// The line's component, once added.
    task: Mutex<Option<rtt::TaskContext>>,
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
    /// The first card on its line adds the line's component.
    first: bool,
}

/// Builds a Modbus card from its section: the unit's map and timing, on the line of its
/// transport (shared with the cards before it on the same transport).
pub fn build(config: &ModbusConfig, ctx: &mut CardContext<'_>) -> Result<Box<dyn Card>, CardError> {
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
    if matches!(transport, crate::line::Transport::Rtu(_))
        && timing.unit == 0
        && !card.map().reads().is_empty()
    {
        return Err(CardError::at(
            "unit",
            "unit 0 is the broadcast address on RTU: every unit takes its writes and none answers, so it can have outputs only (no inputs, no read_back)",
        ));
    }
    let stats = Arc::new(UnitStats::default());
    let thread = ctx.thread().clone();
    let unit = LineUnit {
        card: card.clone(),
        timing,
        stats: stats.clone(),
    };
    let lines: &mut Lines = ctx.shared();
    if let Some(other) = lines
        .0
        .iter()
        .find(|l| l.transport.same_place(&transport) && l.transport != transport)
    {
        return Err(CardError::at(
            "transport",
            format!(
                "{} is a line already, with other settings ({}); every unit on one port shares its baud rate, parity, stop bits and turnaround",
                transport.describe(),
                other.transport.settings()
            ),
        ));
    }
    let (line, first) = match lines.0.iter().find(|l| l.transport == transport) {
        Some(l) => (l.clone(), false),
        None => {
            let l = Arc::new(SharedLine {
                transport,
                thread,
                units: Mutex::new(Vec::new()),
                task: Mutex::new(None),
            });
            lines.0.push(l.clone());
            (l, true)
        }
    };
    rtt::lock(&line.units).push(unit);
    Ok(Box::new(ModbusPlugin {
        card,
        timing,
        stats,
        line,
        first,
    }))
}

impl ModbusPlugin {
    fn line_running(&self) -> bool {
        rtt::lock(&self.line.task)
            .as_ref()
            .is_some_and(|t| t.state() == rtt::TaskState::Running)
    }
}

impl Card for ModbusPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn add_bus(
        &self,
        runtime: &rtt::Runtime,
        name: &str,
    ) -> Result<Vec<rtt::TaskContext>, rtt::RuntimeError> {
        if !self.first {
            return Ok(Vec::new());
        }
        let units = std::mem::take(&mut *rtt::lock(&self.line.units));
        let task = LineIo::add(
            runtime,
            name,
            self.line.transport.clone(),
            units,
            self.line.thread.clone(),
        )?;
        *rtt::lock(&self.line.task) = Some(task.clone());
        Ok(vec![task])
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

    fn settle(&self, deadline: Instant) -> Result<(), String> {
        // Confirmed once the unit took the writes and a whole poll after them succeeded.
        let polls = self.stats.polls.load(Ordering::Relaxed);
        let pending = || self.card.writes_pending() || self.card.deliveries_pending();
        while (pending() || self.stats.polls.load(Ordering::Relaxed) <= polls)
            && Instant::now() < deadline
            && self.line_running()
        {
            std::thread::sleep(Duration::from_millis(5));
        }
        if pending() {
            return Err("safe values not confirmed by the unit before stopping".into());
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
                .collect::<Vec<_>>()
                .join("; ");
            return Err(format!("safe values not confirmed by the unit: {list}"));
        }
        Ok(())
    }
}
