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
use driver_api::{Card, CardContext, CardError, CardStatus};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};

/// The ports the deployment's Firmata cards use: port (resolved where it exists) → card.
#[derive(Default)]
struct Claimed(HashMap<String, String>);

struct FirmataPlugin {
    card: Arc<FirmataCard>,
    /// Taken by `add_bus` (once).
    bus: Mutex<Option<FirmataBus>>,
    thread: rtt::ThreadOptions,
}

/// Builds the card a section describes.
pub fn build(
    config: &FirmataConfig,
    ctx: &mut CardContext<'_>,
) -> Result<Box<dyn Card>, CardError> {
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
    Ok(Box::new(FirmataPlugin {
        bus: Mutex::new(Some(FirmataBus::new(card.clone()))),
        card,
        thread: ctx.thread().clone(),
    }))
}

impl Card for FirmataPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn add_bus(
        &self,
        runtime: &rtt::Runtime,
        name: &str,
    ) -> Result<Vec<rtt::TaskContext>, rtt::RuntimeError> {
        let Some(bus) = self
            .bus
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take()
        else {
            return Ok(Vec::new());
        };
        Ok(vec![FirmataIo::add(
            runtime,
            name,
            bus,
            self.thread.clone(),
        )?])
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
    /// state (PIN_STATE_QUERY), then refuses further writes.
    fn settle(&self, deadline: std::time::Instant) -> Result<(), String> {
        self.card.settle(deadline)
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(self.card.config().port.clone(), &self.card.counters())
    }
}
