//! A section resolved against its board's description: which subdevice and channel each
//! device channel is, with its range table turned into scales. Done once, at build, so
//! every channel a device reports exists on the board.

use crate::board::{BoardDesc, Kind, Range, RangeUnit, SubdeviceDesc};
use crate::config::{AnalogGroup, Aref, ComediConfig, MAX_CHANNELS};
use device_interface::{RawRange, Scale, ScaleError, Unit};
use driver_api::CardError;

/// An analog channel: where it is and its range table as scales.
#[derive(Debug, Clone)]
pub struct AnalogChan {
    /// Its subdevice.
    pub subdevice: u32,
    /// Its channel there.
    pub channel: u32,
    /// Its largest raw value.
    pub maxdata: u32,
    /// Its ranges, as comedi gives them and as scales (raw 0..=maxdata).
    pub ranges: Vec<(Range, Scale)>,
    /// The range it starts in.
    pub range: u32,
    /// The reference it starts with.
    pub aref: Aref,
    /// The references its subdevice takes (`SDF_GROUND` …).
    pub flags: u32,
    /// An output's value to write at start, raw.
    pub initial: Option<u32>,
}

/// A digital channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BitChan {
    /// Its subdevice.
    pub subdevice: u32,
    /// Its channel there.
    pub channel: u32,
    /// On a DIO subdevice (its direction is set at open).
    pub dio: bool,
    /// An output's level to write at start.
    pub initial: Option<bool>,
}

/// A counter channel.
#[derive(Debug, Clone, Copy)]
pub struct CounterChan {
    /// Its subdevice.
    pub subdevice: u32,
    /// Its channel there.
    pub channel: u32,
    /// Its largest value (it wraps after it).
    pub maxdata: u32,
    /// Counts per turn.
    pub resolution: i64,
    /// Counting direction.
    pub upcounting: bool,
}

/// A section resolved.
#[derive(Debug, Clone, Default)]
pub struct Layout {
    /// AnalogIn channels.
    pub analog_in: Vec<AnalogChan>,
    /// AnalogOut channels.
    pub analog_out: Vec<AnalogChan>,
    /// DigitalIn bits.
    pub input: Vec<BitChan>,
    /// DigitalOut bits.
    pub output: Vec<BitChan>,
    /// Encoders.
    pub counters: Vec<CounterChan>,
}

fn err(key: impl Into<String>, message: impl std::fmt::Display) -> CardError {
    CardError::at(key, message)
}

/// The board's subdevices as one line: `0 AI (8 channels), 1 AO (8 channels)`.
pub fn listing(desc: &BoardDesc) -> String {
    let list: Vec<String> = desc
        .subdevices
        .iter()
        .enumerate()
        .map(|(i, s)| format!("{i} {} ({} channels)", s.kind, s.channels.len()))
        .collect();
    if list.is_empty() {
        "none".into()
    } else {
        list.join(", ")
    }
}

/// The scale of `range` over raw `0..=maxdata`, computing as comedilib's `comedi_to_phys`.
pub fn scale(range: &Range, maxdata: u32) -> Result<Scale, ScaleError> {
    let unit = match range.unit {
        RangeUnit::Volt => "V",
        RangeUnit::MilliAmpere => "mA",
        RangeUnit::None => "",
    };
    let unit = Unit::new(unit)?;
    let raw = RawRange::new(0, i64::from(maxdata))?;
    Scale::fraction(raw, range.min, range.max, unit)
}

/// Finds the subdevice a group names, or the first of `kinds`.
fn subdevice<'a>(
    desc: &'a BoardDesc,
    key: &str,
    given: Option<u32>,
    kinds: &[Kind],
) -> Result<(u32, &'a SubdeviceDesc), CardError> {
    let names: Vec<String> = kinds.iter().map(|k| k.to_string()).collect();
    let names = names.join(" or ");
    match given {
        Some(n) => {
            let s = desc.subdevices.get(n as usize).ok_or_else(|| {
                err(
                    format!("{key}.subdevice"),
                    format!(
                        "{} has no subdevice {n} (it has: {})",
                        desc.board,
                        listing(desc)
                    ),
                )
            })?;
            if !kinds.contains(&s.kind) {
                return Err(err(
                    format!("{key}.subdevice"),
                    format!(
                        "subdevice {n} is {}, not {names} (the board has: {})",
                        s.kind,
                        listing(desc)
                    ),
                ));
            }
            Ok((n, s))
        }
        None => kinds
            .iter()
            .find_map(|k| {
                desc.subdevices
                    .iter()
                    .enumerate()
                    .find(|(_, s)| s.kind == *k)
                    .map(|(i, s)| (i as u32, s))
            })
            .ok_or_else(|| {
                err(
                    key,
                    format!(
                        "{} has no {names} subdevice (it has: {})",
                        desc.board,
                        listing(desc)
                    ),
                )
            }),
    }
}

/// The channels a group names (all when none), each checked to exist.
fn channels(
    key: &str,
    given: &Option<Vec<u32>>,
    n: u32,
    s: &SubdeviceDesc,
) -> Result<Vec<u32>, CardError> {
    let count = s.channels.len() as u32;
    let list = given.clone().unwrap_or_else(|| (0..count).collect());
    for c in &list {
        if *c >= count {
            return Err(err(
                format!("{key}.channels"),
                format!(
                    "subdevice {n} ({}) has no channel {c} (it has {})",
                    s.kind,
                    if count == 0 {
                        "none".to_string()
                    } else {
                        format!("0..={}", count - 1)
                    }
                ),
            ));
        }
    }
    Ok(list)
}

fn analog(
    desc: &BoardDesc,
    key: &str,
    spec: &AnalogGroup,
    kind: Kind,
) -> Result<Vec<AnalogChan>, CardError> {
    let (n, s) = subdevice(desc, key, spec.subdevice, &[kind])?;
    if s.flags & spec.aref.flag() == 0 {
        return Err(err(
            format!("{key}.aref"),
            format!("subdevice {n} does not take aref {:?}", spec.aref.name()),
        ));
    }
    let mut out = Vec::new();
    for c in channels(key, &spec.channels, n, s)? {
        let ch = &s.channels[c as usize];
        let mut ranges = Vec::new();
        for (i, r) in ch.ranges.iter().enumerate() {
            let sc = scale(r, ch.maxdata).map_err(|e| {
                err(
                    key,
                    format!(
                        "subdevice {n} channel {c} range {i} [{}, {}]: {e}",
                        r.min, r.max
                    ),
                )
            })?;
            ranges.push((*r, sc));
        }
        let Some((_, sc)) = ranges.get(spec.range as usize) else {
            return Err(err(
                format!("{key}.range"),
                format!(
                    "subdevice {n} channel {c} has no range {} (its ranges: {})",
                    spec.range,
                    ranges
                        .iter()
                        .enumerate()
                        .map(|(i, (r, sc))| format!("{i} [{}, {}] {}", r.min, r.max, sc.unit()))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            ));
        };
        let initial = match spec.initial {
            Some(v) => Some(sc.to_raw(v).ok_or_else(|| {
                let r = sc.range();
                err(
                    format!("{key}.initial"),
                    format!(
                        "{v} is outside range {} [{}, {}]",
                        spec.range, r.lowest, r.highest
                    ),
                )
            })? as u32),
            None => None,
        };
        out.push(AnalogChan {
            subdevice: n,
            channel: c,
            maxdata: ch.maxdata,
            ranges,
            range: spec.range,
            aref: spec.aref,
            flags: s.flags,
            initial,
        });
    }
    Ok(out)
}

fn bits(
    desc: &BoardDesc,
    key: &str,
    given: Option<u32>,
    channel_list: &Option<Vec<u32>>,
    kinds: &[Kind],
    initial: Option<bool>,
) -> Result<Vec<BitChan>, CardError> {
    let (n, s) = subdevice(desc, key, given, kinds)?;
    Ok(channels(key, channel_list, n, s)?
        .into_iter()
        .map(|c| BitChan {
            subdevice: n,
            channel: c,
            dio: s.kind == Kind::Dio,
            initial,
        })
        .collect())
}

/// Refuses a list past [`MAX_CHANNELS`] as soon as a group takes it there.
fn bound(key: &str, len: usize) -> Result<(), CardError> {
    if len > MAX_CHANNELS {
        return Err(err(
            key,
            format!("takes its list past {MAX_CHANNELS} channels"),
        ));
    }
    Ok(())
}

/// Resolves `config` against the board `desc` describes.
pub fn resolve(config: &ComediConfig, desc: &BoardDesc) -> Result<Layout, CardError> {
    let mut layout = Layout::default();
    for (i, g) in config.analog_in.iter().enumerate() {
        let key = format!("analog_in[{i}]");
        layout.analog_in.extend(analog(desc, &key, g, Kind::Ai)?);
        bound(&key, layout.analog_in.len())?;
    }
    for (i, g) in config.analog_out.iter().enumerate() {
        let key = format!("analog_out[{i}]");
        layout.analog_out.extend(analog(desc, &key, g, Kind::Ao)?);
        bound(&key, layout.analog_out.len())?;
    }
    for (i, g) in config.input.iter().enumerate() {
        let key = format!("input[{i}]");
        layout.input.extend(bits(
            desc,
            &key,
            g.subdevice,
            &g.channels,
            &[Kind::Di, Kind::Dio],
            None,
        )?);
        bound(&key, layout.input.len())?;
    }
    for (i, g) in config.output.iter().enumerate() {
        let key = format!("output[{i}]");
        layout.output.extend(bits(
            desc,
            &key,
            g.subdevice,
            &g.channels,
            &[Kind::Do, Kind::Dio],
            g.initial,
        )?);
        bound(&key, layout.output.len())?;
    }
    for (i, e) in config.encoder.iter().enumerate() {
        let key = format!("encoder[{i}]");
        let (n, s) = subdevice(desc, &key, e.subdevice, &[Kind::Counter])?;
        let c = e.channel;
        channels(&key, &Some(vec![c]), n, s)?;
        layout.counters.push(CounterChan {
            subdevice: n,
            channel: c,
            maxdata: s.channels[c as usize].maxdata,
            resolution: e.resolution,
            upcounting: e.upcounting,
        });
    }
    check_unique(&layout)?;
    Ok(layout)
}

/// Refuses a channel mapped twice in one list, or a DIO channel both input and output.
fn check_unique(layout: &Layout) -> Result<(), CardError> {
    fn once(list: &str, places: impl Iterator<Item = (u32, u32)>) -> Result<(), CardError> {
        let mut seen = std::collections::HashSet::new();
        for (s, c) in places {
            if !seen.insert((s, c)) {
                return Err(err(
                    list,
                    format!("subdevice {s} channel {c} is mapped twice"),
                ));
            }
        }
        Ok(())
    }
    once(
        "analog_in",
        layout.analog_in.iter().map(|a| (a.subdevice, a.channel)),
    )?;
    once(
        "analog_out",
        layout.analog_out.iter().map(|a| (a.subdevice, a.channel)),
    )?;
    once(
        "input",
        layout.input.iter().map(|b| (b.subdevice, b.channel)),
    )?;
    once(
        "output",
        layout.output.iter().map(|b| (b.subdevice, b.channel)),
    )?;
    once(
        "encoder",
        layout.counters.iter().map(|b| (b.subdevice, b.channel)),
    )?;
    for b in layout.output.iter().filter(|b| b.dio) {
        if layout
            .input
            .iter()
            .any(|i| i.subdevice == b.subdevice && i.channel == b.channel)
        {
            return Err(err(
                "output",
                format!(
                    "DIO subdevice {} channel {} is an input too",
                    b.subdevice, b.channel
                ),
            ));
        }
    }
    Ok(())
}
