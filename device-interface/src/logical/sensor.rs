//! `Sensor<T>`: a reading in its unit (RTT's SensorInterface: readSensor, minMeasurement,
//! maxMeasurement), and the two sensors built over physical devices.

use crate::channel::AnalogInput;
use crate::encoder::EncoderGeometry;
use crate::{Device, DeviceError, Encoder, Health};
use std::sync::Arc;

/// A sensor reading values of type `T`.
///
/// Real-time contract as the physical interfaces: non-blocking, bounded, allocation-free.
pub trait Sensor<T>: Device {
    /// The latest reading. Errors as the device underneath: offline, stale, bus.
    fn read(&self) -> Result<T, DeviceError>;

    /// The lowest and highest reading the sensor can give.
    fn measurement_range(&self) -> (T, T);

    /// The unit of the readings ("bar", "mm"); empty for none.
    fn unit(&self) -> &str;
}

/// An analog input channel read as `gain × value + offset` in a unit of its own (a
/// 0–10 V pressure transmitter read in bar).
pub struct AnalogSensor {
    input: AnalogInput,
    gain: f64,
    offset: f64,
    unit: String,
    range: (f64, f64),
}

impl AnalogSensor {
    /// Channel `input` read as `gain × value + offset` in `unit`. Fails for a gain that is
    /// 0 or not finite, an offset that is not finite, or a channel whose range cannot be
    /// read.
    pub fn new(
        input: AnalogInput,
        gain: f64,
        offset: f64,
        unit: &str,
    ) -> Result<AnalogSensor, DeviceError> {
        if !gain.is_finite() || gain == 0.0 || !offset.is_finite() {
            return Err(DeviceError::Refused {
                reason: "the gain must be finite and not 0, the offset finite",
            });
        }
        let r = input.range()?;
        let (a, b) = (gain * r.lowest + offset, gain * r.highest + offset);
        Ok(AnalogSensor {
            input,
            gain,
            offset,
            unit: unit.to_string(),
            range: (a.min(b), a.max(b)),
        })
    }
}

impl Device for AnalogSensor {
    fn health(&self) -> Health {
        self.input.device().health()
    }
}

impl Sensor<f64> for AnalogSensor {
    fn read(&self) -> Result<f64, DeviceError> {
        Ok(self.gain * self.input.read()? + self.offset)
    }

    fn measurement_range(&self) -> (f64, f64) {
        self.range
    }

    fn unit(&self) -> &str {
        &self.unit
    }
}

/// An encoder's whole count (turns and position) read as a position in a unit:
/// `count / counts_per_unit + offset`.
pub struct EncoderSensor {
    encoder: Arc<dyn Encoder>,
    geometry: EncoderGeometry,
    counts_per_unit: f64,
    offset: f64,
    unit: String,
}

impl EncoderSensor {
    /// `encoder` read in `unit`, `counts_per_unit` counts to a unit (negative: the unit
    /// grows as the count falls). Fails for a `counts_per_unit` that is 0 or not finite.
    pub fn new(
        encoder: Arc<dyn Encoder>,
        counts_per_unit: f64,
        offset: f64,
        unit: &str,
    ) -> Result<EncoderSensor, DeviceError> {
        if !counts_per_unit.is_finite() || counts_per_unit == 0.0 || !offset.is_finite() {
            return Err(DeviceError::Refused {
                reason: "counts_per_unit must be finite and not 0, the offset finite",
            });
        }
        let geometry = EncoderGeometry::new(encoder.resolution(), encoder.upcounting())?;
        Ok(EncoderSensor {
            encoder,
            geometry,
            counts_per_unit,
            offset,
            unit: unit.to_string(),
        })
    }

    /// The encoder's whole count now: turns × |resolution| + position, in the positive
    /// direction.
    ///
    /// Position and turn are two reads: a roll-over between them would be a turn off, so
    /// the turn is read before and after and the three reads made again (at most four
    /// times) until it did not change. An encoder turning over on every try is
    /// [`Stale`](DeviceError::Stale).
    pub fn count(&self) -> Result<i64, DeviceError> {
        for _ in 0..4 {
            let before = self.encoder.turn()?;
            let p = self.encoder.position()?;
            if self.encoder.turn()? == before {
                return self.geometry.join(p, before);
            }
        }
        Err(DeviceError::Stale { age: None })
    }

    /// Counts per unit.
    pub fn counts_per_unit(&self) -> f64 {
        self.counts_per_unit
    }
}

impl Device for EncoderSensor {
    fn health(&self) -> Health {
        self.encoder.health()
    }
}

impl Sensor<f64> for EncoderSensor {
    fn read(&self) -> Result<f64, DeviceError> {
        Ok(self.count()? as f64 / self.counts_per_unit + self.offset)
    }

    fn measurement_range(&self) -> (f64, f64) {
        let span = i64::MAX as f64 / self.counts_per_unit.abs();
        (self.offset - span, self.offset + span)
    }

    fn unit(&self) -> &str {
        &self.unit
    }
}
