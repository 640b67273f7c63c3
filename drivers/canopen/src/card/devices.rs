//! The card's devices: AnalogIn and AnalogOut over its PDO images (an object's bits, its
//! scale, float objects as their values), DigitalIn and DigitalOut as bit images, each
//! read or write refused while the channel's node is not operational.

use super::CanopenCard;
use device_interface::bits::{BitImage, BitSpan, Written};
use device_interface::time::Timestamp;
use device_interface::{AnalogIn, AnalogOut, Device, DeviceError, Health, Scale, Status};
use std::sync::atomic::Ordering;

impl Device for CanopenCard {
    fn health(&self) -> Health {
        let now = self.clock.now();
        let newest = self
            .rx
            .iter()
            .map(|r| r.at.load(Ordering::Acquire))
            .max()
            .unwrap_or(0);
        let down: Vec<u8> = self
            .map
            .nodes
            .iter()
            .enumerate()
            .filter(|(n, _)| !self.node_operational(*n))
            .map(|(_, node)| node.id)
            .collect();
        let status = if self.link_up() && down.is_empty() {
            Status::Online
        } else {
            Status::Offline
        };
        Health {
            status,
            last_good: (newest != 0).then(|| Timestamp::from_nanos(newest - 1)),
            checked_at: now,
            last_error: (status != Status::Online).then_some(DeviceError::Offline),
        }
    }
}

impl AnalogIn for CanopenCard {
    fn channel_count(&self) -> u32 {
        self.map.analog_in.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        Ok(*Self::channel(&self.map.analog_in, channel)?.signal.scale())
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

impl AnalogOut for CanopenCard {
    fn channel_count(&self) -> u32 {
        self.map.analog_out.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        Ok(*Self::channel(&self.map.analog_out, channel)?.signal.scale())
    }

    fn write(&self, channel: u32, value: f64) -> Result<(), DeviceError> {
        let c = Self::channel(&self.map.analog_out, channel)?;
        self.store(
            channel,
            c.pdo,
            c.signal.channel_bits_of_value(channel, value)?,
        )
    }

    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        let c = Self::channel(&self.map.analog_out, channel)?;
        self.store(channel, c.pdo, c.signal.channel_bits_of_raw(channel, raw)?)
    }

    fn read_back(&self, channel: u32) -> Result<f64, DeviceError> {
        let c = Self::channel(&self.map.analog_out, channel)?;
        c.signal
            .channel_value(channel, self.ao[channel as usize].load(Ordering::Acquire))
    }

    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let c = Self::channel(&self.map.analog_out, channel)?;
        c.signal
            .channel_raw(channel, self.ao[channel as usize].load(Ordering::Acquire))
    }
}

impl CanopenCard {
    /// Stores analog output `channel`'s bits and marks its RPDO (refused while its node is
    /// not operational: the write could not reach it).
    fn store(&self, channel: u32, pdo: usize, bits: i64) -> Result<(), DeviceError> {
        self.check_output(pdo)?;
        self.ao[channel as usize].store(bits, Ordering::Release);
        self.dirty[pdo].store(true, Ordering::Release);
        self.wake();
        Ok(())
    }
}

impl device_interface::bits::DigitalInputImage for CanopenCard {
    fn inputs(&self) -> &BitImage {
        &self.di
    }

    fn check_inputs(&self, span: BitSpan) -> Result<(), DeviceError> {
        for b in span.start()..=span.stop() {
            self.input(Self::channel(&self.map.digital_in, b)?)?;
        }
        Ok(())
    }
}

impl device_interface::bits::DigitalOutputImage for CanopenCard {
    fn outputs(&self) -> &BitImage {
        &self.dout
    }

    fn check_outputs_writable(&self) -> Result<(), DeviceError> {
        if self.link_up() {
            Ok(())
        } else {
            Err(DeviceError::Offline)
        }
    }

    fn check_span_writable(&self, span: BitSpan) -> Result<(), DeviceError> {
        // Each bit's node must be operational: a write to a node being configured or
        // offline could not reach it (its outputs are read from it when it starts).
        for b in span.start()..=span.stop() {
            self.check_output(Self::channel(&self.map.digital_out, b)?.pdo)?;
        }
        Ok(())
    }

    fn outputs_written(&self, written: Written) {
        let (start, stop) = match written {
            Written::Bit { bit, .. } => (bit, bit),
            Written::Span { span, .. } => (span.start(), span.stop()),
        };
        for b in start..=stop {
            if let Some(c) = self.map.digital_out.get(b as usize) {
                self.dirty[c.pdo].store(true, Ordering::Release);
            }
        }
        self.wake();
    }
}
