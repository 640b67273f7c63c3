//! Position switches: digital inputs an encoder's travel turns on, as a home or limit
//! switch on a real axis is hit by the carriage (`[[card.sim.switch]]`).
//!
//! A switch is on while the encoder's *travel* — every count it moved since the card was
//! built, whatever the encoder's position was set to since — lies in `from..=to`. Setting
//! the encoder's position (homing) moves no carriage, so it moves no switch.

use device_interface::bits::BitImage;
use serde::Deserialize;

/// A digital input switched by an encoder's travel.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SwitchConfig {
    /// The digital input it drives (not one a loopback drives).
    pub digital_in: u32,
    /// The encoder whose travel switches it.
    pub encoder: u32,
    /// Lowest travel (counts) at which it is on.
    pub from: i64,
    /// Highest travel (counts) at which it is on.
    pub to: i64,
}

/// The switches of a card, checked.
pub(crate) struct Switches(Box<[SwitchConfig]>);

impl Switches {
    /// Checks `config` against a card with `inputs` digital inputs (those in `looped`
    /// driven by a loopback) and `encoders` encoders. Errors: the key path and the
    /// problem.
    pub(crate) fn new(
        config: &[SwitchConfig],
        inputs: u32,
        looped: &BitImage,
        encoders: usize,
    ) -> Result<Switches, (String, String)> {
        for (i, s) in config.iter().enumerate() {
            let invalid = |key: &str, problem: String| (format!("switch[{i}].{key}"), problem);
            if s.digital_in >= inputs {
                return Err(invalid(
                    "digital_in",
                    format!(
                        "digital input {} does not exist (the card has {inputs})",
                        s.digital_in
                    ),
                ));
            }
            if looped.get(s.digital_in).unwrap_or(false) {
                return Err(invalid(
                    "digital_in",
                    format!(
                        "digital input {} is driven by digital_loopback; a switch needs an \
                         input no loopback drives",
                        s.digital_in
                    ),
                ));
            }
            if let Some(first) = config[..i]
                .iter()
                .position(|o| o.digital_in == s.digital_in)
            {
                return Err(invalid(
                    "digital_in",
                    format!(
                        "digital input {} is switched by switch[{first}] already",
                        s.digital_in
                    ),
                ));
            }
            if s.encoder as usize >= encoders {
                return Err(invalid(
                    "encoder",
                    format!(
                        "encoder {} does not exist (the card has {encoders})",
                        s.encoder
                    ),
                ));
            }
            if s.from > s.to {
                return Err(invalid(
                    "to",
                    format!("{} is below from = {}", s.to, s.from),
                ));
            }
        }
        Ok(Switches(config.into()))
    }

    /// Sets each switch's input from its encoder's `travel`, except inputs in `held`.
    pub(crate) fn apply(&self, travel: impl Fn(usize) -> i64, di: &BitImage, held: &BitImage) {
        for s in self.0.iter() {
            if held.get(s.digital_in).unwrap_or(false) {
                continue;
            }
            let t = travel(s.encoder as usize);
            // Checked against the card's inputs when built.
            let _ = di.set(s.digital_in, (s.from..=s.to).contains(&t));
        }
    }
}
