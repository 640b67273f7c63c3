//! The Firmata card as an hwgw driver plug-in (`driver = "firmata"`, section
//! [`FirmataConfig`]).
//!
//! Building checks the section and makes the devices from it; nothing is opened: the port
//! is opened (and an Uno reset) only when the bus side starts, so `hwgw check` touches no
//! board. The board's capabilities are checked against the section at that start. One
//! card per port: a second card on the same port is refused. Outputs read back only what
//! hwgw wrote (a Firmata board is not asked what its pins are).

use crate::bus::FirmataBus;
use crate::card::FirmataCard;
use crate::component::FirmataIo;
use crate::config::FirmataConfig;
use device_interface::CardDevices;
use driver_api::{BuiltCard, BusSide, Card, CardContext, CardError, CardStatus, SettleError};
use std::collections::HashMap;
use std::sync::Arc;

/// The ports the deployment's Firmata cards use: port (resolved where it exists) → card.
#[derive(Default)]
struct Claimed(HashMap<String, String>);

struct FirmataPlugin {
    card: Arc<FirmataCard>,
}

/// Builds the card a section describes; its bus side is the [`FirmataIo`] component named
/// after the card.
pub fn build(config: &FirmataConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
    config.check()?;
    crate::line::check_port(&config.port).map_err(|e| CardError::at("port", e.to_string()))?;
    let card = Arc::new(FirmataCard::new(config, ctx.clock()).map_err(CardError::new)?);
    let port = std::fs::canonicalize(&config.port)
        .map(|p| p.to_string_lossy().into_owned())
        .unwrap_or_else(|_| config.port.clone());
    let name = ctx.name().to_string();
    let claimed = ctx.shared::<Claimed>();
    if let Some(other) = claimed.0.get(&port) {
        return Err(CardError::at(
            "port",
            format!("{port} is card {other:?}'s already"),
        ));
    }
    claimed.0.insert(port, name);
    let bus = FirmataBus::new(card.clone());
    let bus = BusSide::one(move |ctx| {
        FirmataIo::add(ctx.runtime(), ctx.name(), bus, ctx.thread().clone())
    });
    Ok(BuiltCard::new(FirmataPlugin { card }, bus))
}

impl Card for FirmataPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn summary(&self) -> String {
        let c = self.card.config();
        format!(
            "Firmata board on {} at {} baud: {} digital in, {} digital out, {} analog in, {} pwm, {} servo, {} encoders",
            c.port,
            c.baud,
            c.digital_in.len(),
            c.digital_out.len(),
            c.analog_in.len(),
            c.pwm.len(),
            c.servo.len(),
            c.encoder.len()
        )
    }

    /// Waits until every output written was sent and the board confirmed each output pin's
    /// state (PIN_STATE_QUERY), then refuses further writes. With its bus side not
    /// running, does not wait: nothing sends or asks.
    fn settle(&self, deadline: std::time::Instant, bus_running: bool) -> Result<(), SettleError> {
        if !bus_running {
            let now = std::time::Instant::now();
            return self
                .card
                .settle(now)
                .map_err(|_| SettleError::BusNotRunning);
        }
        self.card.settle(deadline)
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(self.card.config().port.clone(), &self.card.counters())
    }
}
