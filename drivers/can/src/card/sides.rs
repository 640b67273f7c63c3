//! The devices a CAN card registers: one view of the card per device interface, each
//! judging its health by what it reads. An input device is online while any message its
//! channels come from is fresh (a card whose digital inputs all come from one silent
//! message shows its `digital_in` stale while its analog inputs, from other messages, stay
//! online); an output device needs only the link (a silent sensor message does not make
//! the card's outputs look unusable). Every other call goes to the card.

use super::CanCard;
use super::devices::Feeds;
use device_interface::bits::{BitImage, BitSpan, DigitalInputImage, DigitalOutputImage, Written};
use device_interface::{AnalogIn, AnalogOut, Device, DeviceError, Health, Scale};
use std::sync::Arc;

/// The received frames (indices into the map's rx list) the whole card, its analog inputs
/// and its digital inputs come from: each list sorted, each frame once.
pub(super) struct Feeding {
    pub(super) all: Box<[usize]>,
    ai: Box<[usize]>,
    di: Box<[usize]>,
}

impl Feeding {
    /// From the (rx frame, signal) of each analog input and digital input bit.
    pub(super) fn new(rx_frames: usize, ai_at: &[(u32, u32)], di_at: &[(u32, u32)]) -> Self {
        fn frames(at: &[(u32, u32)]) -> Box<[usize]> {
            let mut f: Vec<usize> = at.iter().map(|&(f, _)| f as usize).collect();
            f.sort_unstable();
            f.dedup();
            f.into()
        }
        Feeding {
            all: (0..rx_frames).collect(),
            ai: frames(ai_at),
            di: frames(di_at),
        }
    }
}

macro_rules! side {
    ($(#[$doc:meta])* $name:ident, $feeds:expr) => {
        $(#[$doc])*
        pub struct $name(Arc<CanCard>);

        impl $name {
            /// The view of `card`.
            pub fn new(card: &Arc<CanCard>) -> Self {
                $name(card.clone())
            }

            /// The card behind it.
            pub fn card(&self) -> &Arc<CanCard> {
                &self.0
            }
        }

        impl Device for $name {
            fn health(&self) -> Health {
                let feeds: fn(&CanCard) -> Feeds<'_> = $feeds;
                self.0.health_of(feeds(&self.0))
            }
        }
    };
}

side!(
    /// A CAN card's analog inputs, online while a message they come from is fresh.
    CanAnalogIn,
    |c| Feeds::Frames(&c.feeds.ai)
);
side!(
    /// A CAN card's analog outputs, online while the link is up.
    CanAnalogOut,
    |_| Feeds::Link
);
side!(
    /// A CAN card's digital inputs, online while a message they come from is fresh.
    CanDigitalIn,
    |c| Feeds::Frames(&c.feeds.di)
);
side!(
    /// A CAN card's digital outputs, online while the link is up.
    CanDigitalOut,
    |_| Feeds::Link
);

impl AnalogIn for CanAnalogIn {
    fn channel_count(&self) -> u32 {
        AnalogIn::channel_count(&*self.0)
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        AnalogIn::scale(&*self.0, channel)
    }

    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.0.read_raw(channel)
    }

    fn read(&self, channel: u32) -> Result<f64, DeviceError> {
        self.0.read(channel)
    }
}

impl AnalogOut for CanAnalogOut {
    fn channel_count(&self) -> u32 {
        AnalogOut::channel_count(&*self.0)
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        AnalogOut::scale(&*self.0, channel)
    }

    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        self.0.write_raw(channel, raw)
    }

    fn write(&self, channel: u32, value: f64) -> Result<(), DeviceError> {
        self.0.write(channel, value)
    }

    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.0.read_back_raw(channel)
    }

    fn read_back(&self, channel: u32) -> Result<f64, DeviceError> {
        self.0.read_back(channel)
    }
}

impl DigitalInputImage for CanDigitalIn {
    fn inputs(&self) -> &BitImage {
        self.0.inputs()
    }

    fn check_inputs(&self, span: BitSpan) -> Result<(), DeviceError> {
        self.0.check_inputs(span)
    }
}

impl DigitalOutputImage for CanDigitalOut {
    fn outputs(&self) -> &BitImage {
        self.0.outputs()
    }

    fn check_outputs_writable(&self) -> Result<(), DeviceError> {
        self.0.check_outputs_writable()
    }

    fn outputs_written(&self, written: Written) {
        self.0.outputs_written(written)
    }
}
