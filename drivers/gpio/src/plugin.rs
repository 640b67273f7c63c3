//! The GPIO card as an hwgw driver plug-in (`driver = "gpio"`, section [`GpioConfig`]).
//!
//! Building finds every line (a chip by path, name or label; a line by offset or name)
//! and refuses a line given twice or held by another consumer, without requesting
//! anything: `hwgw check` drives no output. The bus side is the [`GpioIo`] component named
//! after the card; it requests the lines when it starts.

use crate::bus::GpioBus;
use crate::card::{ChipLines, Enc, GpioCard, Line, Setup, Slot};
use crate::chips::LineId;
use crate::component::GpioIo;
use crate::config::GpioConfig;
use device_interface::CardDevices;
use device_interface::encoder::EncoderCounter;
use driver_api::{
    BuiltCard, BusSide, Card, CardContext, CardError, CardStatus, ChannelNames, ReadBack,
    is_port_name,
};
use std::sync::atomic::{AtomicBool, AtomicU64};
use std::sync::{Arc, Mutex};

/// A GPIO card of a deployment.
struct GpioPlugin {
    card: Arc<GpioCard>,
}

/// Builds the card a section describes, without requesting its lines; its bus side is
/// the [`GpioIo`] component, which requests them when it starts.
pub fn build(config: &GpioConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
    let card = card(config, ctx.clock())?;
    let bus = GpioBus::new(card.clone());
    let bus =
        BusSide::one(move |ctx| GpioIo::add(ctx.runtime(), ctx.name(), bus, ctx.thread().clone()));
    Ok(BuiltCard::new(GpioPlugin { card }, bus))
}

/// The card of a section: lines found and checked, nothing requested.
pub fn card(
    config: &GpioConfig,
    clock: Arc<dyn device_interface::time::Clock>,
) -> Result<Arc<GpioCard>, CardError> {
    config
        .check()
        .map_err(|e| CardError::at(e.key, e.message))?;
    let mut chips: Vec<ChipLines> = Vec::new();
    let mut keys: Vec<Vec<String>> = Vec::new();
    let mut place = |key: &str, id: LineId, setup: Setup| -> Result<Slot, CardError> {
        if let Some(who) = id.used_by.as_deref().filter(|w| *w != config.consumer) {
            return Err(CardError::at(key, format!("{id} is used by {who:?}")));
        }
        let chip = match chips
            .iter()
            .position(|c| c.lines[0].id.chip.path == id.chip.path)
        {
            Some(i) => i,
            None => {
                chips.push(ChipLines { lines: Vec::new() });
                keys.push(Vec::new());
                chips.len() - 1
            }
        };
        if let Some(b) = chips[chip]
            .lines
            .iter()
            .position(|l| l.id.offset == id.offset)
        {
            return Err(CardError::at(
                key,
                format!("{id} is already {}", keys[chip][b]),
            ));
        }
        let offset = id.offset;
        chips[chip].lines.push(Line { id, setup });
        keys[chip].push(key.to_string());
        // For now the offset: `in_request_order` makes it the index in the request.
        Ok(Slot { chip, bit: offset })
    };
    let find = |key: &str, chip: Option<&str>, line| {
        crate::chips::line(chip.or(config.chip.as_deref()), line).map_err(|e| CardError::at(key, e))
    };
    let mut inputs = Vec::new();
    for (i, l) in config.input.iter().enumerate() {
        let key = format!("input[{i}].line");
        let id = find(&key, l.chip.as_deref(), &l.line)?;
        let setup = Setup::Input {
            bias: l.bias,
            active_low: l.active_low,
            debounce_us: l.debounce_us,
            edges: l.edges,
        };
        inputs.push((place(&key, id, setup)?, l.edges));
    }
    let mut outputs = Vec::new();
    let mut image = Vec::new();
    for (i, l) in config.output.iter().enumerate() {
        let key = format!("output[{i}].line");
        let id = find(&key, l.chip.as_deref(), &l.line)?;
        let setup = Setup::Output {
            drive: l.drive,
            bias: l.bias,
            active_low: l.active_low,
            initial: l.initial,
        };
        outputs.push(place(&key, id, setup)?);
        image.push(AtomicBool::new(l.initial));
    }
    let mut encoders = Vec::new();
    for (i, e) in config.encoder.iter().enumerate() {
        let setup = Setup::Input {
            bias: e.bias,
            active_low: e.active_low,
            debounce_us: e.debounce_us,
            edges: crate::config::Edges::Both,
        };
        let mut slot = |what: &str, line| -> Result<Slot, CardError> {
            let key = format!("encoder[{i}].{what}");
            let id = find(&key, e.chip.as_deref(), line)?;
            place(&key, id, setup)
        };
        let a = slot("a", &e.a)?;
        let b = slot("b", &e.b)?;
        let index = e.index.as_ref().map(|x| slot("index", x)).transpose()?;
        let counter = EncoderCounter::new(e.resolution, e.upcounting)
            .map_err(|err| CardError::at(format!("encoder[{i}].resolution"), err))?;
        encoders.push(Enc {
            a,
            b,
            index,
            counter,
        });
    }
    in_request_order(&mut chips, &mut inputs, &mut outputs, &mut encoders);
    let opened = chips.iter().map(|_| Mutex::new(None)).collect();
    Ok(Arc::new(GpioCard {
        consumer: config.consumer.clone(),
        event_buffer: config.event_buffer,
        input_state: inputs.iter().map(|_| AtomicBool::new(false)).collect(),
        inputs,
        outputs,
        output_image: image,
        encoders,
        chips,
        opened,
        online: AtomicBool::new(false),
        last_event: AtomicU64::new(0),
        counters: Default::default(),
        clock,
    }))
}

/// Puts each chip's lines in the order the request has them (by offset: gpiocdev sorts
/// them), and turns the slots' offsets into indices in it (bits of the line values).
fn in_request_order(
    chips: &mut [ChipLines],
    inputs: &mut [(Slot, crate::config::Edges)],
    outputs: &mut [Slot],
    encoders: &mut [Enc],
) {
    for c in chips.iter_mut() {
        c.lines.sort_by_key(|l| l.id.offset);
    }
    let index = |s: &mut Slot| {
        if let Some(i) = chips[s.chip]
            .lines
            .iter()
            .position(|l| l.id.offset == s.bit)
        {
            s.bit = i as u32;
        }
    };
    inputs.iter_mut().for_each(|(s, _)| index(s));
    outputs.iter_mut().for_each(index);
    for e in encoders.iter_mut() {
        index(&mut e.a);
        index(&mut e.b);
        if let Some(x) = e.index.as_mut() {
            index(x);
        }
    }
}

/// The kernel's names of `lines`, when every one has a distinct port name; else none.
fn line_names<'a>(lines: impl Iterator<Item = Option<&'a Line>>) -> Vec<String> {
    let names: Vec<String> = lines
        .map(|l| l.map(|l| l.id.name.clone()).unwrap_or_default())
        .collect();
    let mut unique = names.clone();
    unique.sort();
    unique.dedup();
    if unique.len() == names.len() && names.iter().all(|n| is_port_name(n)) {
        names
    } else {
        Vec::new()
    }
}

impl Card for GpioPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn channel_names(&self) -> ChannelNames {
        let c = &self.card;
        ChannelNames {
            digital_in: line_names((0..c.inputs.len() as u32).map(|b| c.input_line(b))),
            digital_out: line_names((0..c.outputs.len() as u32).map(|b| c.output_line(b))),
            ..ChannelNames::default()
        }
    }

    fn summary(&self) -> String {
        let c = &self.card;
        let chips: Vec<String> = c
            .chips
            .iter()
            .map(|ch| {
                let id = &ch.lines[0].id.chip;
                format!(
                    "{} ({}) lines {:?}",
                    id.name,
                    id.label,
                    ch.lines.iter().map(|l| l.id.offset).collect::<Vec<_>>()
                )
            })
            .collect();
        format!(
            "{}: {} inputs, {} outputs, {} encoders, as consumer {:?}",
            chips.join(", "),
            c.inputs.len(),
            c.outputs.len(),
            c.encoders.len(),
            c.consumer
        )
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(self.card.chip_names().join(", "), &self.card.counters())
    }

    fn read_back(&self) -> ReadBack {
        // An output's image is the level the kernel drives it at, from the request on.
        ReadBack::Device
    }
}
