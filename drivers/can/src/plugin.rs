//! The SocketCAN card as an hwgw driver plug-in (`driver = "socketcan"`, section
//! [`CanConfig`]).
//!
//! Building opens the interface; one that is not there is a warning in the card's summary
//! (`hwgw check` validates a deployment before it is installed) and the bus component's
//! start opens it, failing `hwgw run` with its name when it is still missing. The bus side
//! is the [`CanIo`] component named after the card. Channels take their signals'
//! names as port names. At stop the card sends every tx frame once more, carrying the safe
//! values, before its bus component stops.

use crate::bus::CanBus;
use crate::card::CanCard;
use crate::component::CanIo;
use crate::map::{CanConfig, MappedFrame, SignalRole};
use crate::signal::ValueKind;
use device_interface::CardDevices;
use driver_api::{
    BuiltCard, BusSide, Card, CardContext, CardError, CardStatus, ChannelDetail, ChannelDetails,
    ChannelNames, ReadBack, SettleError, is_port_name, wait_while,
};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A CAN card of a deployment.
struct CanPlugin {
    card: Arc<CanCard>,
    /// The interface was not there at build: why (the bus component's start opens it).
    missing: Option<String>,
}

/// Builds a CAN card from its section: the map (DBC files relative to the deployment),
/// the card, and its interface opened; its bus side is the [`CanIo`] component, over the
/// opened interface (or opening it at its start).
pub fn build(config: &CanConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
    let map = crate::map::CanMap::new(config, ctx.base()).map_err(keyed)?;
    let card = CanCard::with_log(map, ctx.clock(), rtt::log::Area::named(ctx.name()));
    // An interface that is not here is for the start to find (`hwgw check` validates a
    // deployment before it is installed); one that is here must be a CAN interface that
    // can carry what is mapped.
    let (bus, missing) = match CanBus::open(card.clone()) {
        Ok(bus) => (Some(bus), None),
        Err(e @ crate::bus::BusError::NoInterface { .. }) => {
            let why = format!("{e}; the bus component's start needs it (hwgw run)");
            tracing::warn!(card = ctx.name(), "{why}");
            (None, Some(why))
        }
        Err(e) => return Err(CardError::at("interface", e)),
    };
    let unopened = card.clone();
    let bus_side = BusSide::one(move |ctx| {
        let thread = ctx.thread().clone();
        match bus {
            Some(bus) => CanIo::add(ctx.runtime(), ctx.name(), bus, thread),
            None => CanIo::add_unopened(ctx.runtime(), ctx.name(), unopened, thread),
        }
    });
    Ok(BuiltCard::new(CanPlugin { card, missing }, bus_side))
}

/// A map error as the key it is about and what is wrong: `rx[0].signal[2] (Speed)` is
/// key `rx[0].signal[2]`, the signal's name going with the message.
fn keyed(e: crate::map::MapError) -> CardError {
    match e {
        crate::map::MapError::Setting { path, message } => match path.split_once(" (") {
            Some((key, name)) => {
                let name = name.trim_end_matches(')');
                CardError::at(key, format!("signal {name}: {message}"))
            }
            None => CardError::at(path, message),
        },
        crate::map::MapError::Dbc(e) => CardError::at("dbc", e),
    }
}

/// The port names of one role's signals in `frames` (`signal`, or `signal_k` for bit k of
/// a multi-bit digital signal); none when they would not all be distinct port names.
fn signal_names(frames: &[MappedFrame], role: SignalRole) -> Vec<String> {
    let mut all = Vec::new();
    for s in frames
        .iter()
        .flat_map(|f| &f.signals)
        .filter(|s| s.role == role)
    {
        match s.width() {
            1 => all.push(s.port.clone()),
            w => all.extend((0..w).map(|k| format!("{}_{k}", s.port))),
        }
    }
    let mut unique = all.clone();
    unique.sort();
    unique.dedup();
    if unique.len() == all.len() && all.iter().all(|n| is_port_name(n)) {
        all
    } else {
        Vec::new()
    }
}

/// What the DBC file says of one role's signals in `frames`, channel by channel: the
/// signal's comment, and its value descriptions as physical values (bit by bit for a
/// multi-bit digital signal, which then has no named values).
fn signal_details(frames: &[MappedFrame], role: SignalRole) -> Vec<ChannelDetail> {
    let mut out = Vec::new();
    for s in frames
        .iter()
        .flat_map(|f| &f.signals)
        .filter(|s| s.role == role)
    {
        // A port's doc is one line: a comment's line breaks (CR LF from Windows tools)
        // and runs of white space become single spaces.
        let comment = s
            .comment
            .as_deref()
            .map(|c| c.split_whitespace().collect::<Vec<_>>().join(" "));
        // A VAL_ key is the raw integer value (for a float signal too, as cantools reads
        // it: the number, not the float's bits); a digital channel's value is its bit.
        let values: Vec<(f64, String)> = s
            .values
            .iter()
            .map(|(raw, name)| {
                let v = match (s.role, s.signal.kind()) {
                    (SignalRole::Digital, _) => *raw as f64,
                    (_, ValueKind::Integer) => s.signal.physical(*raw),
                    _ => {
                        let (factor, offset) = s.signal.factor_offset();
                        *raw as f64 * factor + offset
                    }
                };
                (v, name.clone())
            })
            .collect();
        match s.width() {
            1 => out.push(ChannelDetail {
                doc: comment,
                values,
            }),
            w => out.extend((0..w).map(|k| ChannelDetail {
                doc: Some(match &comment {
                    Some(c) => format!("bit {k} of {}: {c}", s.name),
                    None => format!("bit {k} of {}", s.name),
                }),
                values: Vec::new(),
            })),
        }
    }
    out
}

fn frame_list(frames: &[MappedFrame]) -> String {
    if frames.is_empty() {
        return "nothing".into();
    }
    frames
        .iter()
        .map(|f| {
            let when = match (f.cycle, f.on_change) {
                (Some(c), true) => format!("every {c:?} and on change"),
                (Some(c), false) => format!("every {c:?}"),
                (None, _) => "on change".to_string(),
            };
            let by = match f.j1939 {
                Some(j) => match j.source {
                    Some(s) => format!("PGN {} from {s:#x}", j.pgn),
                    None => format!("PGN {}", j.pgn),
                },
                None => format!("id {:#x}", f.id),
            };
            format!("{} ({by}, {} signals, {when})", f.name, f.signals.len())
        })
        .collect::<Vec<_>>()
        .join(", ")
}

impl Card for CanPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn channel_names(&self) -> ChannelNames {
        let map = self.card.map();
        ChannelNames {
            analog_in: signal_names(map.rx(), SignalRole::Analog),
            digital_in: signal_names(map.rx(), SignalRole::Digital),
            analog_out: signal_names(map.tx(), SignalRole::Analog),
            digital_out: signal_names(map.tx(), SignalRole::Digital),
        }
    }

    fn channel_details(&self) -> ChannelDetails {
        let map = self.card.map();
        ChannelDetails {
            analog_in: signal_details(map.rx(), SignalRole::Analog),
            digital_in: signal_details(map.rx(), SignalRole::Digital),
            analog_out: signal_details(map.tx(), SignalRole::Analog),
            digital_out: signal_details(map.tx(), SignalRole::Digital),
        }
    }

    fn summary(&self) -> String {
        let map = self.card.map();
        let renamed: Vec<String> = map
            .rx()
            .iter()
            .chain(map.tx())
            .flat_map(|f| &f.signals)
            .filter(|s| s.port != s.name)
            .map(|s| s.port.clone())
            .collect();
        format!(
            "{}: receives {}; sends {}{}{}",
            map.interface(),
            frame_list(map.rx()),
            frame_list(map.tx()),
            match &self.missing {
                Some(why) => format!("; WARNING: {why}"),
                None => String::new(),
            },
            if renamed.is_empty() {
                String::new()
            } else {
                format!(
                    "; signals whose name two messages share are Message__Signal: {}",
                    renamed.join(", ")
                )
            }
        )
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(self.card.map().interface(), &self.card.counters())
    }

    fn read_back(&self) -> ReadBack {
        // The outputs are the signals of hwgw's own frames: before hwgw first writes one
        // it holds its start value (the section's `initial`, the DBC's GenSigStartValue,
        // else 0) — what a cyclic frame carried until then — so "initial" puts it back.
        ReadBack::Device
    }

    fn settle(&self, deadline: Instant, bus_running: bool) -> Result<(), SettleError> {
        // Every tx frame goes out once more, with the safe values in it.
        self.card.flush();
        wait_while(deadline, Duration::from_millis(2), || {
            bus_running && self.card.link_up() && self.card.sends_pending()
        });
        if !self.card.link_up() {
            let link = format!("{} (link down)", self.card.map().interface());
            return Err(SettleError::Offline(link));
        }
        if self.card.sends_pending() {
            return Err(SettleError::pending(bus_running, "safe values sent"));
        }
        if let Some(e) = self.card.unsendable() {
            return Err(SettleError::Unsent(vec![format!(
                "{}'s J1939 groups: {e}",
                self.card.map().interface()
            )]));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    #[test]
    fn value_names_are_the_channels_values() {
        // A VAL_ key is the raw number: scaled for an integer, the number itself (not its
        // bits) for a float, the bit for a digital channel whatever its factor and offset.
        let dir = std::env::temp_dir().join(format!("hwgw-can-vals-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(
            dir.join("v.dbc"),
            "BO_ 1 M: 8 X\n SG_ Gear : 0|8@1+ (2,1) [0|0] \"\" Y\n \
             SG_ F : 8|32@1+ (1,0) [0|0] \"\" Y\n SG_ Lamp : 40|1@1+ (1,1) [0|0] \"\" Y\n\
             VAL_ 1 Gear 0 \"P\" 3 \"D\" ;\nVAL_ 1 F 1 \"One\" ;\nVAL_ 1 Lamp 0 \"off\" 1 \"on\" ;\n\
             SIG_VALTYPE_ 1 F : 1;\nCM_ SG_ 1 Gear \"the\r\n  gear\";\n",
        )
        .unwrap();
        let config: CanConfig =
            toml::from_str("interface = \"vcan0\"\ndbc = \"v.dbc\"\n[[rx]]\nmessage = \"M\"\n")
                .unwrap();
        let map = crate::map::CanMap::new(&config, &dir).unwrap();
        let analog = signal_details(map.rx(), SignalRole::Analog);
        assert_eq!(analog[0].values, [(1.0, "P".into()), (7.0, "D".into())]);
        assert_eq!(analog[0].doc.as_deref(), Some("the gear"));
        assert_eq!(analog[1].values, [(1.0, "One".into())]);
        let digital = signal_details(map.rx(), SignalRole::Digital);
        assert_eq!(digital[0].values, [(0.0, "off".into()), (1.0, "on".into())]);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
