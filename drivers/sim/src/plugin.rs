//! The simulated card as an hwgw driver plug-in (`driver = "sim"`, section [`SimConfig`]):
//! its bus side is a periodic cycle component ([`driver_api::periodic_bus`]), named after
//! the card, that steps the simulation at the card's period.

use crate::card::SimCard;
use crate::config::SimConfig;
use device_interface::{AnalogIn, AnalogOut, CardDevices, DigitalIn, DigitalOut};
use driver_api::{Card, CardContext, CardError, ReadBack};
use std::sync::Arc;
use std::time::Duration;

/// A sim card of a deployment.
struct SimPlugin {
    card: Arc<SimCard>,
    period: Duration,
    thread: rtt::ThreadOptions,
}

/// Builds a sim card from its section.
pub fn build(config: &SimConfig, ctx: &mut CardContext<'_>) -> Result<Box<dyn Card>, CardError> {
    let card = SimCard::new(config, ctx.clock()).map_err(|e| {
        let (key, message) = e.at();
        CardError::at(key, message)
    })?;
    Ok(Box::new(SimPlugin {
        card,
        period: ctx.period(),
        thread: ctx.thread().clone(),
    }))
}

impl Card for SimPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn add_bus(
        &self,
        runtime: &rtt::Runtime,
        name: &str,
    ) -> Result<Vec<rtt::TaskContext>, rtt::RuntimeError> {
        let card = self.card.clone();
        let step = move || card.step();
        driver_api::periodic_bus(runtime, name, self.period, self.thread.clone(), step)
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
        driver_api::CardStatus {
            bus: "simulated".into(),
            counters: Default::default(),
        }
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
            &thread,
            std::path::Path::new("."),
            Arc::new(device_interface::time::MonotonicClock),
            &mut shared,
        );
        let card = build(&config, &mut ctx).unwrap();
        let devices = card.devices();
        let rt = rtt::Runtime::new(
            Arc::new(device_interface::Registry::new()),
            Default::default(),
        )
        .unwrap();
        let bus = card.add_bus(&rt, "s").unwrap();
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
