//! The simulated card as an hwgw driver plug-in (`driver = "sim"`, section [`SimConfig`]):
//! its bus side is a periodic cycle component ([`driver_api::BusSide::periodic`]), named
//! after the card, that steps the simulation at the card's period.

use crate::card::SimCard;
use crate::config::SimConfig;
use device_interface::{AnalogIn, AnalogOut, CardDevices, DigitalIn, DigitalOut};
use driver_api::{BuiltCard, BusSide, Card, CardContext, CardError, ReadBack};
use std::sync::Arc;
use std::time::Duration;

/// A sim card of a deployment.
struct SimPlugin {
    card: Arc<SimCard>,
    period: Duration,
}

/// Builds a sim card from its section; its bus side steps the simulation.
pub fn build(config: &SimConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
    let card = SimCard::new(config, ctx.clock()).map_err(|e| {
        let (key, message) = e.at();
        CardError::at(key, message)
    })?;
    let stepped = card.clone();
    let bus = BusSide::periodic(ctx.period(), move || stepped.step());
    Ok(BuiltCard::new(
        SimPlugin {
            card,
            period: ctx.period(),
        },
        bus,
    ))
}

impl Card for SimPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn read_back(&self) -> ReadBack {
        // The simulation's outputs are its state.
        ReadBack::Device
    }

    fn summary(&self) -> String {
        let c = &*self.card;
        format!(
            "{} analog in, {} analog out, {} digital in, {} digital out, {} encoders, stepped every {:?}",
            AnalogIn::channel_count(c),
            AnalogOut::channel_count(c),
            c.input_count(),
            DigitalOut::output_count(c),
            c.encoder_count(),
            self.period
        )
    }

    fn status(&self) -> driver_api::CardStatus {
        /// The simulation's counters.
        #[derive(serde::Serialize)]
        struct Counters {
            /// Output writes the card recorded (with `record_capacity` > 0).
            output_writes: u64,
        }
        driver_api::CardStatus::new(
            "simulated",
            &Counters {
                output_writes: self.card.output_writes(),
            },
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sim_card_steps_on_its_cycle_component() {
        let config: SimConfig =
            toml::from_str("digital_outputs = 2\ndigital_inputs = 2\ndigital_loopback = true\n")
                .unwrap();
        let thread = rtt::ThreadOptions::default();
        let mut shared = Default::default();
        let mut ctx = CardContext::new(
            "s",
            Duration::from_millis(1),
            std::path::Path::new("."),
            Arc::new(device_interface::time::MonotonicClock),
            &mut shared,
        );
        let BuiltCard { card, bus } = build(&config, &mut ctx).unwrap();
        let devices = card.devices();
        let rt = rtt::Runtime::new(
            Arc::new(device_interface::Registry::new()),
            Default::default(),
        )
        .unwrap();
        let bus = bus
            .unwrap()
            .add_to(&driver_api::BusContext::new(&rt, "s", &thread))
            .unwrap();
        assert_eq!(bus.len(), 1);
        devices
            .digital_out
            .as_ref()
            .unwrap()
            .set_bit(1, true)
            .unwrap();
        bus[0].start().unwrap();
        let di = devices.digital_in.unwrap();
        let deadline = std::time::Instant::now() + Duration::from_secs(5);
        while !di.read_bit(1).unwrap() {
            assert!(
                std::time::Instant::now() < deadline,
                "the cycle never stepped"
            );
            std::thread::sleep(Duration::from_millis(1));
        }
        assert!(
            card.summary()
                .starts_with("0 analog in, 0 analog out, 2 digital in, 2 digital out")
        );
    }
}
