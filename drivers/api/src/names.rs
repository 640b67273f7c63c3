//! Port names for a card's channels (`[card.names]`), given by the deployment or by the
//! driver.

use serde::{Deserialize, Serialize};

/// Port names for a card's channels, in channel order: the IO components' ports are called
/// by them (unnamed channels keep `ch0…`/`bit0…`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelNames {
    /// Analog inputs.
    #[serde(default)]
    pub analog_in: Vec<String>,
    /// Analog outputs.
    #[serde(default)]
    pub analog_out: Vec<String>,
    /// Digital inputs.
    #[serde(default)]
    pub digital_in: Vec<String>,
    /// Digital outputs.
    #[serde(default)]
    pub digital_out: Vec<String>,
}

/// A name list that does not fit the card: the key under `names` and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct NamesError {
    /// The key path under `names`, e.g. `digital_out[1]`.
    pub key: String,
    /// What is wrong.
    pub message: String,
}

/// True when `name` can be a port name: not empty, no dots (they separate component and
/// port), no white space.
pub fn is_port_name(name: &str) -> bool {
    !name.is_empty() && !name.contains('.') && !name.chars().any(char::is_whitespace)
}

impl ChannelNames {
    /// The port name of channel `i` of a list: its given name, else `prefix{i}`.
    pub fn port(names: &[String], prefix: &str, i: u32) -> String {
        names
            .get(i as usize)
            .cloned()
            .unwrap_or_else(|| format!("{prefix}{i}"))
    }

    /// The lists with their keys, in a fixed order.
    fn lists(&self) -> [(&'static str, &Vec<String>); 4] {
        [
            ("analog_in", &self.analog_in),
            ("analog_out", &self.analog_out),
            ("digital_in", &self.digital_in),
            ("digital_out", &self.digital_out),
        ]
    }

    /// Each list given here, else the one in `fallback` (the driver's names fill what the
    /// deployment leaves out, list by list).
    pub fn or(mut self, fallback: ChannelNames) -> ChannelNames {
        let take = |mine: &mut Vec<String>, theirs: Vec<String>| {
            if mine.is_empty() {
                *mine = theirs;
            }
        };
        take(&mut self.analog_in, fallback.analog_in);
        take(&mut self.analog_out, fallback.analog_out);
        take(&mut self.digital_in, fallback.digital_in);
        take(&mut self.digital_out, fallback.digital_out);
        self
    }

    /// Checks the names against the card's channel counts (analog in, analog out, digital
    /// in, digital out): not more names than channels, each a port name, no duplicates.
    pub fn check(&self, counts: [u32; 4]) -> Result<(), NamesError> {
        for ((key, names), count) in self.lists().into_iter().zip(counts) {
            if names.len() > count as usize {
                return Err(NamesError {
                    key: key.to_string(),
                    message: format!("{} names for {count} channels", names.len()),
                });
            }
            let mut seen = std::collections::HashSet::new();
            for (i, n) in names.iter().enumerate() {
                if !is_port_name(n) {
                    return Err(NamesError {
                        key: format!("{key}[{i}]"),
                        message: format!(
                            "{n:?} is not a port name (no dots, no spaces, not empty)"
                        ),
                    });
                }
                if !seen.insert(n.as_str()) {
                    return Err(NamesError {
                        key: format!("{key}[{i}]"),
                        message: format!("{n:?} is used twice"),
                    });
                }
            }
        }
        Ok(())
    }
}

/// What a driver knows of one channel beyond its name.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ChannelDetail {
    /// What the channel is (a DBC comment): its port's documentation.
    pub doc: Option<String>,
    /// Values with names (a DBC value description, in the port's units): `describe` lists
    /// them and `set` takes a name for its value. A digital channel's are 0 and 1.
    pub values: Vec<(f64, String)>,
}

/// [`ChannelDetail`]s for a card's channels, in channel order, as [`ChannelNames`] lists
/// names (a list shorter than the channels leaves the rest without details).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ChannelDetails {
    /// Analog inputs.
    pub analog_in: Vec<ChannelDetail>,
    /// Analog outputs.
    pub analog_out: Vec<ChannelDetail>,
    /// Digital inputs.
    pub digital_in: Vec<ChannelDetail>,
    /// Digital outputs.
    pub digital_out: Vec<ChannelDetail>,
}
