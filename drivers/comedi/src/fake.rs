//! A board in memory for the unit tests: a [`Daq`] whose state the test sets and reads,
//! that logs every call that changes the board, can be made to fail or go away, and can
//! set the direction of a DIO subdevice's channels together (as the parallel port does).

use crate::board::{
    BoardDesc, ChannelDesc, ComediError, Daq, Kind, Range, RangeUnit, SubdeviceDesc,
};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// The fake board's state.
#[derive(Debug, Default)]
pub struct State {
    pub desc: Option<BoardDesc>,
    /// Samples by (subdevice, channel).
    pub data: HashMap<(u32, u32), u32>,
    /// Digital levels by subdevice (bit = channel).
    pub bits: HashMap<u32, u64>,
    /// DIO outputs by subdevice (bit = channel).
    pub dirs: HashMap<u32, u64>,
    /// The levels on a DIO subdevice's pins from outside (what its inputs read).
    pub pins: HashMap<u32, u64>,
    /// DIO subdevices whose channels share one direction.
    pub ganged: Vec<u32>,
    /// Calls that changed the board, in order.
    pub log: Vec<String>,
    /// The board is gone: every call fails with ENODEV.
    pub gone: bool,
    /// The next this many calls fail with EAGAIN.
    pub fail: u32,
    /// Calls made.
    pub calls: u64,
}

/// A handle on the fake board (the test keeps one, the card opens others).
#[derive(Debug, Clone, Default)]
pub struct Fake(pub Arc<Mutex<State>>);

pub fn range(min: f64, max: f64) -> Range {
    Range {
        min,
        max,
        unit: RangeUnit::Volt,
    }
}

fn sub(kind: Kind, flags: u32, n: usize, maxdata: u32, ranges: &[Range]) -> SubdeviceDesc {
    SubdeviceDesc {
        kind,
        flags,
        channels: (0..n)
            .map(|_| ChannelDesc {
                maxdata,
                ranges: ranges.to_vec(),
            })
            .collect(),
    }
}

/// 0: AI, 4 channels, 12 bit, ±10 V and 0–5 V, ground and diff; 1: AO, 2 channels, 12 bit,
/// 0–10 V and ±10 V; 2: DIO, 8 channels; 3: DI, 4 channels; 4: COUNTER, 2 channels, 24 bit;
/// 5: DO and 6: DI, 48 channels each (two windows of 32 for a bit-field call).
pub fn desc() -> BoardDesc {
    use comedi_sys::{SDF_DIFF, SDF_GROUND};
    BoardDesc {
        driver: "fake".into(),
        board: "fake board".into(),
        subdevices: vec![
            sub(
                Kind::Ai,
                SDF_GROUND | SDF_DIFF,
                4,
                4095,
                &[range(-10.0, 10.0), range(0.0, 5.0)],
            ),
            sub(
                Kind::Ao,
                SDF_GROUND,
                2,
                4095,
                &[range(0.0, 10.0), range(-10.0, 10.0)],
            ),
            sub(Kind::Dio, 0, 8, 1, &[]),
            sub(Kind::Di, 0, 4, 1, &[]),
            sub(Kind::Counter, 0, 2, 0xff_ffff, &[]),
            sub(Kind::Do, 0, 48, 1, &[]),
            sub(Kind::Di, 0, 48, 1, &[]),
        ],
    }
}

impl Fake {
    pub fn new() -> Fake {
        let f = Fake::default();
        f.state().desc = Some(desc());
        f
    }

    pub fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// An opener for the card's bus side.
    pub fn opener(&self) -> crate::bus::Opener {
        let f = self.clone();
        Box::new(move |path| {
            let s = f.state();
            if s.gone {
                return Err(error("comedi_open", path, 19));
            }
            Ok(Box::new(f.clone()) as Box<dyn Daq>)
        })
    }

    fn enter(&self, call: &'static str) -> Result<std::sync::MutexGuard<'_, State>, ComediError> {
        let mut s = self.state();
        s.calls += 1;
        if s.gone {
            return Err(error(call, "fake", 19));
        }
        if s.fail > 0 {
            s.fail -= 1;
            return Err(error(call, "fake", 11));
        }
        Ok(s)
    }
}

fn error(call: &'static str, path: &str, code: i32) -> ComediError {
    ComediError {
        call,
        path: path.into(),
        code,
        message: if code == 19 {
            "No such device".into()
        } else {
            "Try again".into()
        },
    }
}

impl Daq for Fake {
    fn describe(&mut self) -> Result<BoardDesc, ComediError> {
        let s = self.enter("describe")?;
        Ok(s.desc.clone().unwrap_or_else(desc))
    }

    fn data_read(
        &mut self,
        subdevice: u32,
        channel: u32,
        _range: u32,
        _aref: u32,
    ) -> Result<u32, ComediError> {
        let s = self.enter("comedi_data_read")?;
        Ok(s.data.get(&(subdevice, channel)).copied().unwrap_or(0))
    }

    fn data_write(
        &mut self,
        subdevice: u32,
        channel: u32,
        range: u32,
        _aref: u32,
        data: u32,
    ) -> Result<(), ComediError> {
        let mut s = self.enter("comedi_data_write")?;
        s.data.insert((subdevice, channel), data);
        s.log.push(format!(
            "write {subdevice}/{channel} range {range} = {data}"
        ));
        Ok(())
    }

    fn dio_config(
        &mut self,
        subdevice: u32,
        channel: u32,
        output: bool,
    ) -> Result<(), ComediError> {
        let mut s = self.enter("comedi_dio_config")?;
        let mask = if s.ganged.contains(&subdevice) {
            u64::MAX
        } else {
            1u64 << channel
        };
        let d = s.dirs.entry(subdevice).or_default();
        if output {
            *d |= mask
        } else {
            *d &= !mask
        }
        s.log.push(format!(
            "config {subdevice}/{channel} {}",
            if output { "out" } else { "in" }
        ));
        Ok(())
    }

    fn dio_get_config(&mut self, subdevice: u32, channel: u32) -> Result<bool, ComediError> {
        let s = self.enter("comedi_dio_get_config")?;
        Ok(s.dirs.get(&subdevice).copied().unwrap_or(0) >> channel & 1 == 1)
    }

    fn bitfield(
        &mut self,
        subdevice: u32,
        base: u32,
        mask: u32,
        bits: u32,
    ) -> Result<u32, ComediError> {
        let mut s = self.enter("comedi_dio_bitfield2")?;
        let dio = s
            .desc
            .as_ref()
            .and_then(|d| d.subdevices.get(subdevice as usize))
            .is_some_and(|d| d.kind == Kind::Dio);
        // Up to 64 channels a subdevice; `base` picks the 32 a call sees.
        let (mask64, bits64) = (u64::from(mask) << base, u64::from(bits & mask) << base);
        let word = s.bits.entry(subdevice).or_default();
        *word = (*word & !mask64) | bits64;
        let latch = *word;
        // A DIO channel reads its latch as an output, its pin as an input.
        let now = if dio {
            let dirs = s.dirs.get(&subdevice).copied().unwrap_or(0);
            let pins = s.pins.get(&subdevice).copied().unwrap_or(0);
            (latch & dirs) | (pins & !dirs)
        } else {
            latch
        };
        let now = (now >> base) as u32;
        if mask != 0 {
            let at = if base == 0 {
                String::new()
            } else {
                format!(" base {base}")
            };
            s.log.push(format!(
                "bits {subdevice}{at} mask {mask:#x} = {:#x}",
                bits & mask
            ));
        }
        Ok(now)
    }
}
