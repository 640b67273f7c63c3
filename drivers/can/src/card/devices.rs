//! The device interfaces of a CAN card: its channels read from and written to the images
//! the bus side fills and empties, each checked against its own frame's (or multiplexed
//! signal's) freshness and the link.

use super::{BusState, CanCard};
use crate::signal::Signal;
use device_interface::bits::{BitImage, BitSpan};
use device_interface::time::Timestamp;
use device_interface::{AnalogIn, AnalogOut, Device, DeviceError, Health, Scale, Status};
use std::sync::atomic::Ordering;

/// The card as a whole: online while the link is up and any received message is fresh;
/// stale when every one is; offline when the link is down or the controller off the bus.
/// Each registered device judges by its own messages instead (see [`super::CanDigitalIn`]
/// and its siblings).
impl Device for CanCard {
    fn health(&self) -> Health {
        self.health_of(Feeds::Frames(&self.feeds.all))
    }
}

/// What a device's health is judged by.
#[derive(Clone, Copy)]
pub(super) enum Feeds<'a> {
    /// The received frames its channels come from: fresh while any of them is.
    Frames(&'a [usize]),
    /// Nothing received: outputs, which only need the link.
    Link,
}

impl CanCard {
    /// Health judged by `feeds`: offline when the link is down or the controller off the
    /// bus; else online while any frame of `feeds` is fresh (or it has none), stale when
    /// none is. `last_good` is the newest frame's receive time.
    pub(super) fn health_of(&self, feeds: Feeds<'_>) -> Health {
        let now = self.clock.now();
        let rx = self.map.rx();
        let fresh = match feeds {
            Feeds::Link => true,
            Feeds::Frames(frames) => {
                frames.is_empty()
                    || frames.iter().any(|&f| {
                        rx.get(f)
                            .is_some_and(|frame| self.frame_age_error(f, frame, now).is_none())
                    })
            }
        };
        let newest = match feeds {
            Feeds::Link => &self.feeds.all[..],
            Feeds::Frames(frames) => frames,
        }
        .iter()
        .filter_map(|&f| self.rx.get(f))
        .map(|r| r.last.load(Ordering::Acquire))
        .max()
        .unwrap_or(0);
        let status = if !self.link_up() || self.bus_state() == BusState::BusOff {
            Status::Offline
        } else if fresh {
            Status::Online
        } else {
            Status::Stale
        };
        Health {
            status,
            last_good: (newest != 0).then(|| Timestamp::from_nanos(newest - 1)),
            checked_at: now,
            last_error: self.last_error.load().as_deref().cloned(),
        }
    }

    /// Analog input `channel`'s raw bits, its signal fresh.
    fn input_bits(&self, channel: u32) -> Result<(i64, &Signal), DeviceError> {
        let at = self.analog_at(false, channel)?;
        self.check_signal(at)?;
        let bits = self.ai[channel as usize].load(Ordering::Acquire);
        Ok((bits, self.signal_at(false, at)))
    }
}

impl AnalogIn for CanCard {
    fn channel_count(&self) -> u32 {
        self.map.counts()[0]
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.scale_of(false, channel)
    }

    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let (bits, signal) = self.input_bits(channel)?;
        signal.channel_raw(channel, bits)
    }

    fn read(&self, channel: u32) -> Result<f64, DeviceError> {
        let (bits, signal) = self.input_bits(channel)?;
        signal.channel_value(channel, bits)
    }
}

impl AnalogOut for CanCard {
    fn channel_count(&self) -> u32 {
        self.map.counts()[1]
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.scale_of(true, channel)
    }

    fn write(&self, channel: u32, value: f64) -> Result<(), DeviceError> {
        let signal = self.signal_at(true, self.analog_at(true, channel)?);
        self.store_output(channel, signal.channel_bits_of_value(channel, value)?)
    }

    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        // A float's raw value is a step of its scale: sent as the float it stands for.
        let signal = self.signal_at(true, self.analog_at(true, channel)?);
        self.store_output(channel, signal.channel_bits_of_raw(channel, raw)?)
    }

    fn read_back(&self, channel: u32) -> Result<f64, DeviceError> {
        let signal = self.signal_at(true, self.analog_at(true, channel)?);
        signal.channel_value(channel, self.ao[channel as usize].load(Ordering::Acquire))
    }

    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let signal = self.signal_at(true, self.analog_at(true, channel)?);
        signal.channel_raw(channel, self.ao[channel as usize].load(Ordering::Acquire))
    }
}

impl device_interface::bits::DigitalInputImage for CanCard {
    fn inputs(&self) -> &BitImage {
        &self.di
    }

    fn check_inputs(&self, span: BitSpan) -> Result<(), DeviceError> {
        // Each bit is as fresh as the frame it came in.
        for b in span.start()..=span.stop() {
            self.check_signal(self.di_at[b as usize])?;
        }
        Ok(())
    }
}

impl device_interface::bits::DigitalOutputImage for CanCard {
    fn outputs(&self) -> &BitImage {
        &self.dout
    }

    fn check_outputs_writable(&self) -> Result<(), DeviceError> {
        self.check_link()?;
        self.check_digital_sendable()
    }

    fn outputs_written(&self, written: device_interface::bits::Written) {
        use device_interface::bits::Written;
        let (start, stop) = match written {
            Written::Bit { bit, .. } => (bit, bit),
            Written::Span { span, .. } => (span.start(), span.stop()),
        };
        let mut last = None;
        for b in start..=stop {
            let f = self.do_frame[b as usize];
            if last != Some(f) {
                self.output(f);
                last = Some(f);
            }
        }
    }
}

/// One position-counter signal of a [`CanCard`], as a device of its own.
pub type CanEncoder = device_interface::encoder::CardEncoder<CanCard>;

impl device_interface::encoder::EncoderHost for CanCard {
    fn encoder_health(&self, index: usize) -> Health {
        match self.enc_at.get(index) {
            Some(&(f, _)) => self.health_of(Feeds::Frames(&[f as usize])),
            None => self.health(),
        }
    }

    fn encoder_counter(&self, index: usize) -> &device_interface::encoder::EncoderCounter {
        self.encoders[index].counter()
    }

    fn check_encoder(&self, index: usize) -> Result<(), DeviceError> {
        self.check_signal(self.enc_at[index])
    }

    fn check_writable(&self) -> Result<(), DeviceError> {
        self.check_link()
    }
}
