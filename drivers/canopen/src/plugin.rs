//! The CANopen manager as an hwgw driver plug-in (`driver = "canopen"`, section
//! [`CanopenConfig`]).
//!
//! Building reads every node's EDS and resolves the PDOs and channels (errors name the
//! key), and opens the interface (a missing one fails the build with the CAN interfaces
//! there are). The bus side is the [`CanopenIo`] component named after the card. At stop
//! the gateway writes the safe values; settling sends every RPDO once more with them;
//! the bus component's stop then leaves the nodes as `at_stop` says.

use crate::bus::CanopenBus;
use crate::card::CanopenCard;
use crate::component::CanopenIo;
use crate::map::{CanopenMap, Channel};
use crate::node::NodeRun;
use crate::section::CanopenConfig;
use can_socket::socket::InterfaceError;
use device_interface::{AnalogIn, AnalogOut, CardDevices, DigitalIn, DigitalOut};
use driver_api::{
    BuiltCard, BusSide, Card, CardContext, CardError, CardStatus, ChannelDetail, ChannelDetails,
    ChannelNames, ReadBack, SettleError, wait_while,
};
use std::sync::Arc;
use std::time::{Duration, Instant};

struct CanopenPlugin {
    card: Arc<CanopenCard>,
    /// The interface was not there at build: why (the bus component's start opens it).
    missing: Option<String>,
}

/// Builds a CANopen card from its section.
pub fn build(config: &CanopenConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
    let map = CanopenMap::new(config, ctx.base()).map_err(|e| CardError::at(e.key, e.message))?;
    let runs: Vec<NodeRun> = map
        .nodes
        .iter()
        .map(|n| NodeRun::new(n.clone(), map.sdo_timeout))
        .collect();
    let statuses = runs.iter().map(|r| r.status().clone()).collect();
    let card = CanopenCard::new(map, ctx.clock(), statuses);
    // An interface that is not here is for the start to find (`hwgw check` validates a
    // deployment before it is installed); one that is here must be a CAN interface.
    let (bus, missing) = match CanopenBus::open(card.clone(), runs) {
        Ok(bus) => (Ok(bus), None),
        Err((e @ InterfaceError::NoInterface { .. }, runs)) => {
            let why = format!("{e}; the bus component's start needs it (hwgw run)");
            tracing::warn!(card = ctx.name(), "{why}");
            (Err(runs), Some(why))
        }
        Err((e, _)) => return Err(CardError::at("interface", e)),
    };
    let unopened = card.clone();
    let bus_side = BusSide::one(move |ctx| {
        let thread = ctx.thread().clone();
        match bus {
            Ok(bus) => CanopenIo::add(ctx.runtime(), ctx.name(), bus, thread),
            Err(runs) => CanopenIo::add_unopened(ctx.runtime(), ctx.name(), unopened, runs, thread),
        }
    });
    Ok(BuiltCard::new(CanopenPlugin { card, missing }, bus_side))
}

fn names(list: &[Channel]) -> Vec<String> {
    list.iter().map(|c| c.name.clone()).collect()
}

fn details(list: &[Channel]) -> Vec<ChannelDetail> {
    list.iter()
        .map(|c| ChannelDetail {
            doc: Some(format!(
                "object {:#06x} sub {}{}",
                c.object.0,
                c.object.1,
                if c.signal.layout().1 > 1 && c.name.ends_with(&format!("_{}", c.bit)) {
                    format!(", bit {}", c.bit)
                } else {
                    String::new()
                }
            )),
            values: Vec::new(),
        })
        .collect()
}

impl Card for CanopenPlugin {
    fn devices(&self) -> CardDevices {
        let map = self.card.map();
        let c = &self.card;
        CardDevices {
            analog_in: (!map.analog_in.is_empty()).then(|| c.clone() as Arc<dyn AnalogIn>),
            analog_out: (!map.analog_out.is_empty()).then(|| c.clone() as Arc<dyn AnalogOut>),
            digital_in: (!map.digital_in.is_empty()).then(|| c.clone() as Arc<dyn DigitalIn>),
            digital_out: (!map.digital_out.is_empty()).then(|| c.clone() as Arc<dyn DigitalOut>),
            encoders: Vec::new(),
            drives: (0..map.drives.len())
                .map(|d| {
                    let drive = crate::drive::Cia402Drive::new(c.clone(), d);
                    (
                        map.drives[d].name.clone(),
                        Arc::new(drive) as Arc<dyn device_interface::logical::Drive>,
                    )
                })
                .collect(),
        }
    }

    fn channel_names(&self) -> ChannelNames {
        let map = self.card.map();
        ChannelNames {
            analog_in: names(&map.analog_in),
            digital_in: names(&map.digital_in),
            analog_out: names(&map.analog_out),
            digital_out: names(&map.digital_out),
        }
    }

    fn channel_details(&self) -> ChannelDetails {
        let map = self.card.map();
        ChannelDetails {
            analog_in: details(&map.analog_in),
            digital_in: details(&map.digital_in),
            analog_out: details(&map.analog_out),
            digital_out: details(&map.digital_out),
        }
    }

    fn summary(&self) -> String {
        let map = self.card.map();
        let nodes: Vec<String> = map
            .nodes
            .iter()
            .map(|n| format!("node {} ({})", n.id, n.name))
            .collect();
        format!(
            "{}: {}; {} TPDOs, {} RPDOs; SYNC {}{}",
            map.interface,
            if nodes.is_empty() {
                "no nodes".into()
            } else {
                nodes.join(", ")
            },
            map.tpdos.len(),
            map.rpdos.len(),
            match map.sync {
                Some(p) => format!("every {p:?}"),
                None => "not sent".into(),
            },
            match &self.missing {
                Some(why) => format!("; WARNING: {why}"),
                None => String::new(),
            }
        )
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(&self.card.map().interface, &self.card.snapshot())
    }

    fn read_back(&self) -> ReadBack {
        // The outputs are hwgw's own RPDO values: before hwgw writes one it holds what the
        // node had when it was started (read at its configuration).
        ReadBack::Device
    }

    fn settle(&self, deadline: Instant, bus_running: bool) -> Result<(), SettleError> {
        // The drives disabled (zero velocity, shutdown), then every RPDO once more; twice,
        // so that a bus step that ran while the drives were told is followed by one that
        // saw it.
        for d in 0..self.card.map().drives.len() {
            use device_interface::logical::Drive;
            let _ = crate::drive::Cia402Drive::new(self.card.clone(), d).disable();
        }
        for _ in 0..2 {
            self.card.flush();
            wait_while(deadline, Duration::from_millis(2), || {
                bus_running && self.card.link_up() && self.card.sends_pending()
            });
        }
        if !self.card.link_up() {
            return Err(SettleError::Offline(format!(
                "{} (link down)",
                self.card.map().interface
            )));
        }
        let unreachable = self.card.outputs_unreachable();
        if !unreachable.is_empty() {
            let ids: Vec<String> = unreachable.iter().map(u8::to_string).collect();
            return Err(SettleError::Offline(format!(
                "{} node(s) {} (not operational: their outputs could not be sent)",
                self.card.map().interface,
                ids.join(", ")
            )));
        }
        if self.card.sends_pending() {
            return Err(SettleError::pending(
                bus_running,
                "safe values sent in RPDOs",
            ));
        }
        Ok(())
    }
}
