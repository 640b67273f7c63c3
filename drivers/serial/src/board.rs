//! What a Firmata board says it is: protocol and firmware versions, each pin's modes and
//! resolutions (the capability response) and which pins are analog channels (the analog
//! mapping), parsed from its replies and described for errors.

use crate::protocol::{mode, two_byte_text};
use serde::Serialize;

/// The most pins a board may describe (Firmata numbers pins in 7 bits).
pub const MAX_PINS: usize = 128;

/// A board as its replies describe it.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct BoardInfo {
    /// The protocol version (REPORT_VERSION).
    pub protocol: (u8, u8),
    /// The firmware's name and version (REPORT_FIRMWARE), once known.
    pub firmware: Option<(String, u8, u8)>,
    /// Per pin, its (mode, resolution) pairs.
    pub pins: Vec<Vec<(u8, u8)>>,
    /// Per pin, its analog channel.
    pub analog: Vec<Option<u8>>,
}

/// Why a reply could not be read as a board description.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BoardError {
    /// A capability response that is cut short or describes more than [`MAX_PINS`].
    #[error("bad capability response: {0}")]
    Capabilities(&'static str),
    /// An analog mapping longer than [`MAX_PINS`].
    #[error("bad analog mapping response: more than {MAX_PINS} pins")]
    Mapping,
}

impl BoardInfo {
    /// Reads a CAPABILITY_RESPONSE payload: per pin, (mode, resolution) pairs ended by 127.
    pub fn set_capabilities(&mut self, data: &[u8]) -> Result<(), BoardError> {
        let mut pins = Vec::new();
        let mut modes = Vec::new();
        let mut i = 0;
        while i < data.len() {
            if data[i] == 0x7F {
                pins.push(std::mem::take(&mut modes));
                i += 1;
                continue;
            }
            let Some(res) = data.get(i + 1) else {
                return Err(BoardError::Capabilities("a mode without its resolution"));
            };
            modes.push((data[i], *res));
            i += 2;
        }
        if !modes.is_empty() {
            return Err(BoardError::Capabilities("the last pin is not ended by 127"));
        }
        if pins.len() > MAX_PINS {
            return Err(BoardError::Capabilities("more than 128 pins"));
        }
        self.pins = pins;
        Ok(())
    }

    /// Reads an ANALOG_MAPPING_RESPONSE payload: per pin, its channel or 127.
    pub fn set_mapping(&mut self, data: &[u8]) -> Result<(), BoardError> {
        if data.len() > MAX_PINS {
            return Err(BoardError::Mapping);
        }
        self.analog = data.iter().map(|&c| (c != 0x7F).then_some(c)).collect();
        Ok(())
    }

    /// Reads a REPORT_FIRMWARE payload: major, minor, name.
    pub fn set_firmware(&mut self, data: &[u8]) {
        if let [major, minor, name @ ..] = data {
            self.firmware = Some((two_byte_text(name, 64), *major, *minor));
        }
    }

    /// The resolution of `pin` in `mode`, if it has that mode.
    pub fn resolution(&self, pin: u8, mode: u8) -> Option<u8> {
        self.pins
            .get(usize::from(pin))?
            .iter()
            .find(|(m, _)| *m == mode)
            .map(|(_, r)| *r)
    }

    /// The pin analog channel `channel` is on.
    pub fn analog_pin(&self, channel: u8) -> Option<u8> {
        self.analog
            .iter()
            .position(|c| *c == Some(channel))
            .and_then(|p| u8::try_from(p).ok())
    }

    /// True when the protocol is at least `major.minor`.
    pub fn protocol_at_least(&self, major: u8, minor: u8) -> bool {
        self.protocol >= (major, minor)
    }

    /// "StandardFirmata.ino 2.4 (protocol 2.4), 20 pins".
    pub fn describe(&self) -> String {
        let fw = match &self.firmware {
            Some((name, a, b)) => format!("{name} {a}.{b}"),
            None => "firmware unknown".into(),
        };
        format!(
            "{fw} (protocol {}.{}), {} pins",
            self.protocol.0,
            self.protocol.1,
            self.pins.len()
        )
    }

    /// A pin's modes, for errors: "input, output, servo".
    pub fn modes_of(&self, pin: u8) -> String {
        match self.pins.get(usize::from(pin)) {
            None => format!(
                "none: the board has pins 0-{}",
                self.pins.len().saturating_sub(1)
            ),
            Some(m) if m.is_empty() => {
                "none (a pin the firmware keeps, e.g. its serial line)".into()
            }
            Some(m) => m
                .iter()
                .map(|(md, _)| mode::name(*md))
                .collect::<Vec<_>>()
                .join(", "),
        }
    }

    /// The pins that have `mode`, for errors: "3, 5, 6, 9, 10, 11".
    pub fn pins_with(&self, mode: u8) -> String {
        let list: Vec<String> = (0..self.pins.len())
            .filter(|&p| self.pins[p].iter().any(|(m, _)| *m == mode))
            .map(|p| p.to_string())
            .collect();
        if list.is_empty() {
            "none".into()
        } else {
            list.join(", ")
        }
    }

    /// The analog channels and their pins, for errors: "A0 (pin 14), A1 (pin 15)".
    pub fn channels(&self) -> String {
        let list: Vec<String> = self
            .analog
            .iter()
            .enumerate()
            .filter_map(|(p, c)| c.map(|c| format!("A{c} (pin {p})")))
            .collect();
        if list.is_empty() {
            "none".into()
        } else {
            list.join(", ")
        }
    }
}
