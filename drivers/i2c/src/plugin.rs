//! The I2C card as an hwgw driver plug-in (`driver = "i2c"`, section
//! [`I2cConfig`]).
//!
//! Building finds the bus (a path, or an adapter's name) and makes each chip's model;
//! nothing is sent until the bus component starts, so `hwgw check` touches no chip.

use crate::bus::I2cBus;
use crate::card::{ChipPlace, I2cCard};
use crate::chips::{self, ChipModel};
use crate::component::I2cIo;
use crate::config::I2cConfig;
use crate::smbus::find_bus;
use device_interface::CardDevices;
use device_interface::time::Clock;
use driver_api::{BuiltCard, BusSide, Card, CardContext, CardError, CardStatus, SettleError};
use std::path::PathBuf;
use std::sync::Arc;

/// A section built: the card, its chips' models and the bus they are on.
pub struct Built {
    /// The card (its chips offline until polled).
    pub card: Arc<I2cCard>,
    /// The chips' models, in the card's chip order.
    pub models: Vec<Box<dyn ChipModel>>,
    /// The bus's character device, as found now.
    pub path: PathBuf,
    /// The bus as the section names it (found again at each open).
    pub bus: String,
}

impl Built {
    /// Its bus side.
    pub fn bus(self) -> I2cBus {
        I2cBus::new(self.card, self.models, self.bus)
    }
}

/// The card of a section and its chips' models (the bus found, nothing sent).
pub fn card(config: &I2cConfig, clock: Arc<dyn Clock>) -> Result<Built, CardError> {
    config
        .check()
        .map_err(|e| CardError::at(e.key, e.message))?;
    let path = find_bus(&config.bus).map_err(|e| CardError::at("bus", e))?;
    let models: Vec<Box<dyn ChipModel>> = config.chip.iter().map(chips::model).collect();
    let places: Vec<ChipPlace> = config
        .chip
        .iter()
        .zip(&models)
        .map(|(c, m)| chips::place(c, m.as_ref()))
        .collect();
    let card = Arc::new(I2cCard::new(&places, clock).map_err(|e| CardError::at("chip", e))?);
    Ok(Built {
        card,
        models,
        path,
        bus: config.bus.clone(),
    })
}

/// The chips the deployment's I2C cards poll: (bus device, address) → the card and its
/// chip key. Two cards polling one chip would each send it their own outputs.
#[derive(Default)]
struct Claimed(std::collections::HashMap<(PathBuf, u16), String>);

/// Claims every chip of `config` on `path` for card `name`; refuses one another card has.
fn claim(
    claimed: &mut Claimed,
    name: &str,
    path: &std::path::Path,
    config: &I2cConfig,
) -> Result<(), CardError> {
    // The same bus under another name (a udev symlink) is the same bus.
    let path = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    for (i, c) in config.chip.iter().enumerate() {
        if let Some(other) = claimed.0.get(&(path.clone(), c.address())) {
            return Err(CardError::at(
                format!("chip[{i}].address"),
                format!(
                    "{:#04x} on {} is card {other} already",
                    c.address(),
                    path.display()
                ),
            ));
        }
    }
    for (i, c) in config.chip.iter().enumerate() {
        claimed
            .0
            .insert((path.clone(), c.address()), format!("{name:?}'s chip[{i}]"));
    }
    Ok(())
}

struct I2cPlugin {
    card: Arc<I2cCard>,
    path: PathBuf,
}

/// Builds the card a section describes; its bus side (the chips' models on the bus) is
/// the [`I2cIo`] component named after the card.
pub fn build(config: &I2cConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
    let built = card(config, ctx.clock())?;
    let name = ctx.name().to_string();
    claim(ctx.shared(), &name, &built.path, config)?;
    let plugin = I2cPlugin {
        card: built.card.clone(),
        path: built.path.clone(),
    };
    let bus = built.bus();
    let bus =
        BusSide::one(move |ctx| I2cIo::add(ctx.runtime(), ctx.name(), bus, ctx.thread().clone()));
    Ok(BuiltCard::new(plugin, bus))
}

impl Card for I2cPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn summary(&self) -> String {
        let chips: Vec<String> = self
            .card
            .chips()
            .iter()
            .map(|c| format!("{} at {:#04x} every {} ms", c.model, c.address, c.poll_ms))
            .collect();
        format!("{}: {}", self.path.display(), chips.join(", "))
    }

    fn settle(&self, deadline: std::time::Instant, bus_running: bool) -> Result<(), SettleError> {
        if !bus_running {
            // Nothing will send them: no wait, and an error only for chips with outputs.
            let now = std::time::Instant::now();
            return self
                .card
                .settle(now)
                .map_err(|_| SettleError::BusNotRunning);
        }
        self.card.settle(deadline)
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(self.path.display().to_string(), &self.card.counters())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;
    use device_interface::time::MonotonicClock;
    use std::collections::HashMap;
    use std::path::Path;
    use std::time::Duration;

    #[test]
    fn a_chip_belongs_to_one_card() {
        let section = |bus: &str, first: u16, second: u16| -> I2cConfig {
            toml::from_str(&format!(
                "bus = {bus:?}\n[[chip]]\nmodel = \"mcp4725\"\naddress = {first}\nvref_v = 5.0\n\
                 [[chip]]\nmodel = \"mcp4725\"\naddress = {second}\nvref_v = 5.0"
            ))
            .unwrap()
        };
        let mut shared = HashMap::new();
        let mut ctx = CardContext::new(
            "n",
            Duration::from_millis(10),
            Path::new("/"),
            Arc::new(MonotonicClock),
            &mut shared,
        );
        // /dev/null is no I2C bus: refused from its device number, never opened.
        let Err(e) = build(&section("/dev/null", 0x60, 0x61), &mut ctx) else {
            panic!("/dev/null taken for a bus");
        };
        assert_eq!(e.key.as_deref(), Some("bus"));
        assert!(
            e.message.starts_with("/dev/null is not an I2C bus"),
            "{}",
            e.message
        );
        // The claims, as `build` makes them once the bus is found: /dev/null stands in for
        // one here.
        let mut claimed = Claimed::default();
        let mut build_as = |name: &str, config: &I2cConfig| {
            claim(&mut claimed, name, Path::new(&config.bus), config)
        };
        build_as("a", &section("/dev/null", 0x60, 0x61)).unwrap();
        // The same bus by another path.
        let Err(e) = build_as("b", &section("/dev/../dev/null", 0x62, 0x61)) else {
            panic!("a second card on chip 0x61");
        };
        assert_eq!(e.key.as_deref(), Some("chip[1].address"));
        assert!(
            e.message
                .contains("0x61 on /dev/null is card \"a\"'s chip[1] already"),
            "{}",
            e.message
        );
        // The refused card claimed nothing: 0x62 is free.
        build_as("c", &section("/dev/null", 0x62, 0x63)).unwrap();
    }
}
