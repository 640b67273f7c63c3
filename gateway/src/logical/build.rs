//! Builds the `[[logical]]` devices over the registry's devices, registers them, checks the
//! drives' outputs against their cards' output policies, and builds their IO components.

use super::{AxisConfig, BitRef, ChannelRef, DriveConfig, LogicalConfig, SensorConfig, io};
use crate::deploy::CardRt;
use crate::outputs::Policy;
use crate::problems::{KeyPath, Problems};
use device_interface::channel::{AnalogInput, AnalogOutput, DigitalInput, DigitalOutput};
use device_interface::logical::{
    AnalogDrive, AnalogDriveParts, AnalogSensor, Axis, Drive, EncoderSensor, HomingConfig, Sensor,
    ServoAxis, ServoAxisParts,
};
use device_interface::{Registry, RegistryError};
use rtt::{Runtime, TaskContext};
use std::sync::Arc;

/// One build's view: where problems go and what the cards are.
struct Ctx<'p, 's, 'a, 'c> {
    problems: &'p mut Problems<'s, 'a>,
    registry: &'c Registry,
    cards: &'c [CardRt],
    /// (card, port, writer): the drives' outputs and who writes them.
    writers: Vec<(String, String, String)>,
    /// The drives axes command, by name, as built (the registry serves them read-only).
    owned: Vec<(String, Arc<dyn Drive>)>,
    /// (axis, drive) of the axes built so far.
    axes: Vec<(String, String)>,
}

/// What [`build`] made: the IO components in start order, and who writes which card
/// output (card, port, writer component), for the output watchdog.
pub(crate) struct Built {
    pub(crate) tasks: Vec<TaskContext>,
    pub(crate) writers: Vec<(String, String, String)>,
}

/// Builds every `[[logical]]` entry of `list` into `runtime`: drives and sensors first,
/// then the axes over them.
pub(crate) fn build(
    list: &[LogicalConfig],
    runtime: &Runtime,
    cards: &[CardRt],
    problems: &mut Problems<'_, '_>,
) -> Built {
    let registry = runtime.registry().clone();
    let mut cx = Ctx {
        problems,
        registry: &registry,
        cards,
        writers: Vec::new(),
        owned: Vec::new(),
        axes: Vec::new(),
    };
    let mut tasks = Vec::new();
    let mut failed: Vec<&str> = Vec::new();
    let axes_last = list
        .iter()
        .enumerate()
        .filter(|(_, l)| !matches!(l, LogicalConfig::Axis(_)))
        .chain(
            list.iter()
                .enumerate()
                .filter(|(_, l)| matches!(l, LogicalConfig::Axis(_))),
        );
    for (i, l) in axes_last {
        let at = KeyPath::top("logical").index(i);
        if let Some(first) = list[..i].iter().position(|o| o.name() == l.name()) {
            let msg = format!("{:?} is logical[{first}]'s name already", l.name());
            cx.problems.at(&at.key("name"), msg);
            continue;
        }
        if let LogicalConfig::Axis(a) = l
            && failed.contains(&a.drive.as_str())
        {
            // Its drive was refused above; that problem says why.
            continue;
        }
        if let Some(c) = cards.iter().find(|c| c.name == l.name()) {
            let msg = format!(
                "{:?} is the name of card[{}] already; a logical device needs a name of its own",
                l.name(),
                c.index
            );
            cx.problems.at(&at.key("name"), msg);
            continue;
        }
        let made = match l {
            LogicalConfig::Sensor(s) => cx.sensor(&at, s).and_then(|d| {
                let task = io::sensor(
                    runtime,
                    &s.name,
                    d.clone(),
                    crate::config::millis(s.sample_period_ms),
                );
                cx.register(&at, |r| r.sensor().register(&s.name, &s.name, d))
                    .then_some(task)
            }),
            LogicalConfig::Drive(dc) => cx.drive(&at, dc).and_then(|d| {
                let owned = claimed(list, &dc.name);
                let task = io::drive(runtime, &dc.name, d.clone(), owned);
                // Everyone else gets a drive that takes no command: its axis' is the real one.
                let served: Arc<dyn Drive> = if owned {
                    cx.owned.push((dc.name.clone(), d.clone()));
                    Arc::new(super::claimed::ClaimedDrive(d))
                } else {
                    d
                };
                cx.register(&at, |r| r.drive().register(&dc.name, &dc.name, served))
                    .then_some(task)
            }),
            LogicalConfig::Axis(a) => cx.axis(&at, a).and_then(|d| {
                let period = crate::config::millis(a.period_ms);
                let task = io::axis(runtime, &a.name, d.clone(), period, a.thread.clone());
                cx.register(&at, |r| r.axis().register(&a.name, &a.name, d))
                    .then_some(task)
            }),
        };
        match made {
            Some(Ok(task)) => {
                tasks.push(task);
                // The drive's outputs are written by its axis if it has one, else by its
                // own component.
                let drive = match l {
                    LogicalConfig::Drive(dc) if !claimed(list, &dc.name) => Some(dc),
                    LogicalConfig::Axis(a) => list.iter().find_map(|o| match o {
                        LogicalConfig::Drive(dc) if dc.name == a.drive => Some(dc),
                        _ => None,
                    }),
                    _ => None,
                };
                if let Some(dc) = drive {
                    cx.note_writers(dc, l.name());
                }
            }
            Some(Err(e)) => {
                cx.problems.at(&at, e);
                failed.push(l.name());
            }
            None => failed.push(l.name()),
        }
    }
    Built {
        tasks,
        writers: cx.writers,
    }
}

/// What the default output policy does at stop, said of a drive's output.
const INITIAL: &str = "puts it back to its value before hwgw first wrote it (\"initial\": \
    a value hwgw does not know, or the last one written where the card cannot tell)";

/// True when an axis of `list` uses drive `name`.
fn claimed(list: &[LogicalConfig], name: &str) -> bool {
    list.iter()
        .any(|o| matches!(o, LogicalConfig::Axis(a) if a.drive == name))
}

impl Ctx<'_, '_, '_, '_> {
    /// Registers a device with `f`; false (the problem at `at.name`) when refused.
    fn register(
        &mut self,
        at: &KeyPath,
        f: impl FnOnce(&Registry) -> Result<(), RegistryError>,
    ) -> bool {
        match f(self.registry) {
            Ok(()) => true,
            Err(e) => {
                self.problems.at(&at.key("name"), e);
                false
            }
        }
    }

    /// `Some` when `r` is `Ok`; otherwise the problem at `at`.
    fn ok<T, E: std::fmt::Display>(&mut self, at: &KeyPath, r: Result<T, E>) -> Option<T> {
        r.map_err(|e| self.problems.at(at, e)).ok()
    }

    fn period(&mut self, at: &KeyPath, ms: f64) -> Option<()> {
        let r = crate::checks::period(ms).map(|_| ());
        self.ok(at, r)
    }

    fn analog_in(&mut self, at: &KeyPath, c: &ChannelRef) -> Option<AnalogInput> {
        let d = self.ok(
            &at.key("device"),
            self.registry.analog_in().lookup(&c.device),
        )?;
        self.ok(&at.key("channel"), AnalogInput::new(d, c.channel))
    }

    fn analog_out(&mut self, at: &KeyPath, c: &ChannelRef) -> Option<AnalogOutput> {
        let d = self.ok(
            &at.key("device"),
            self.registry.analog_out().lookup(&c.device),
        )?;
        self.ok(&at.key("channel"), AnalogOutput::new(d, c.channel))
    }

    fn digital_in(&mut self, at: &KeyPath, b: &BitRef) -> Option<DigitalInput> {
        let d = self.ok(
            &at.key("device"),
            self.registry.digital_in().lookup(&b.device),
        )?;
        self.ok(&at.key("bit"), DigitalInput::new(d, b.bit, b.invert))
    }

    fn digital_out(&mut self, at: &KeyPath, b: &BitRef) -> Option<DigitalOutput> {
        let d = self.ok(
            &at.key("device"),
            self.registry.digital_out().lookup(&b.device),
        )?;
        self.ok(&at.key("bit"), DigitalOutput::new(d, b.bit, b.invert))
    }

    /// `Some(input)` for an optional input, `None` inside when absent; `None` outside on a
    /// problem.
    fn optional_in(&mut self, at: &KeyPath, b: &Option<BitRef>) -> Option<Option<DigitalInput>> {
        match b {
            None => Some(None),
            Some(b) => self.digital_in(at, b).map(Some),
        }
    }

    fn sensor(&mut self, at: &KeyPath, s: &SensorConfig) -> Option<Arc<dyn Sensor<f64>>> {
        self.period(&at.key("sample_period_ms"), s.sample_period_ms)?;
        if let Some(why) = device_interface::text::non_finite(s.offset) {
            self.problems
                .at(&at.key("offset"), format!("{why}: give a finite number"));
            return None;
        }
        match (&s.analog_in, &s.encoder) {
            (Some(c), None) => {
                if s.counts_per_unit.is_some() {
                    self.problems.at(
                        &at.key("counts_per_unit"),
                        "counts_per_unit is for an encoder sensor; one over analog_in has gain",
                    );
                    return None;
                }
                let input = self.analog_in(&at.key("analog_in"), c)?;
                let r = AnalogSensor::new(input, s.gain.unwrap_or(1.0), s.offset, &s.unit);
                let d = self.ok(&at.key("gain"), r)?;
                Some(Arc::new(d))
            }
            (None, Some(e)) => {
                if s.gain.is_some() {
                    self.problems.at(
                        &at.key("gain"),
                        "gain is for a sensor over analog_in; an encoder sensor has counts_per_unit",
                    );
                    return None;
                }
                let Some(cpu) = s.counts_per_unit else {
                    self.problems
                        .at(at, "a sensor over an encoder needs counts_per_unit");
                    return None;
                };
                let enc = self.ok(&at.key("encoder"), self.registry.encoder().lookup(e))?;
                let r = EncoderSensor::new(enc, cpu, s.offset, &s.unit);
                let d = self.ok(&at.key("counts_per_unit"), r)?;
                Some(Arc::new(d))
            }
            _ => {
                self.problems.at(
                    at,
                    "a sensor reads either analog_in or encoder: give exactly one",
                );
                None
            }
        }
    }

    fn drive(&mut self, at: &KeyPath, c: &DriveConfig) -> Option<Arc<dyn Drive>> {
        let setpoint = self.analog_out(&at.key("setpoint"), &c.setpoint)?;
        let enable = match &c.enable {
            None => None,
            Some(b) => Some(self.digital_out(&at.key("enable"), b)?),
        };
        let fault = self.optional_in(&at.key("fault"), &c.fault)?;
        let parts = AnalogDriveParts {
            setpoint,
            volts_per_unit: c.volts_per_unit,
            offset: c.offset,
            enable,
            fault,
            unit: c.unit.clone(),
        };
        let key = if c.volts_per_unit.is_finite() && c.volts_per_unit != 0.0 {
            "offset"
        } else {
            "volts_per_unit"
        };
        let drive = self.ok(&at.key(key), AnalogDrive::new(parts))?;
        self.safe_at_stop(at, c, &drive)?;
        Some(Arc::new(drive))
    }

    /// The card, output policy and port name of `device` output `channel` (`analog`), if
    /// `device` is a card's (or an alias of one).
    fn output(
        &self,
        device: &str,
        analog: bool,
        channel: u32,
    ) -> Option<(&CardRt, Policy, String)> {
        let server = if analog {
            self.registry.analog_out().names()
        } else {
            self.registry.digital_out().names()
        };
        let info = server.into_iter().find(|n| n.name == device)?;
        let card = info.alias_of.unwrap_or(info.name);
        let c = self.cards.iter().find(|c| c.name == card)?;
        let (policy, port) = c.outputs.policy(analog, channel)?;
        let port = port.to_string();
        Some((c, policy, port))
    }

    /// Notes `writer` as the writer of drive `c`'s outputs: the output watchdog drives them
    /// to their safe values when it fails (Exception, FatalError), as for a connection.
    fn note_writers(&mut self, c: &DriveConfig, writer: &str) {
        let mut outputs = vec![(c.setpoint.device.as_str(), true, c.setpoint.channel)];
        outputs.extend(c.enable.iter().map(|b| (b.device.as_str(), false, b.bit)));
        for (device, analog, channel) in outputs {
            if let Some((card, _, port)) = self.output(device, analog, channel) {
                card.outputs.add_writer(&port, writer);
                self.writers
                    .push((card.name.clone(), port, writer.to_string()));
            }
        }
    }

    /// Refuses a drive its cards would leave enabled or moving at stop.
    fn safe_at_stop(&mut self, at: &KeyPath, c: &DriveConfig, drive: &AnalogDrive) -> Option<()> {
        let mut ok = true;
        let setpoint = self
            .output(&c.setpoint.device, true, c.setpoint.channel)
            .map(|(card, p, port)| (card.name.clone(), p, port));
        if let Some((card, p, port)) = setpoint {
            let step = drive
                .setpoint()
                .device()
                .resolution(c.setpoint.channel)
                .unwrap_or(0.0);
            // As TOML writes a float (`0.0`, not `0`).
            let zero = format!("{:?}", drive.zero_output());
            let bad = match p {
                Policy::Keep => Some("keeps it as it is".to_string()),
                Policy::Initial => Some(INITIAL.to_string()),
                Policy::Safe(v) if (v - drive.zero_output()).abs() > step => Some(format!(
                    "drives it to {}, not to zero velocity",
                    device_interface::text::Number(v),
                )),
                Policy::Safe(_) => None,
            };
            if let Some(what) = bad {
                ok = false;
                let msg = format!(
                    "the setpoint {card}.{port}: at stop the card {what}; a drive's setpoint \
                     needs its zero-velocity value as its safe value ([card.outputs] safe = \
                     {{ {port} = {zero} }})"
                );
                self.problems.at(&at.key("setpoint"), msg);
            }
        }
        let enable = c.enable.as_ref().and_then(|b| {
            self.output(&b.device, false, b.bit)
                .map(|(card, p, port)| (b, card.name.clone(), p, port))
        });
        if let Some((b, card, p, port)) = enable {
            let on = f64::from(u8::from(!b.invert));
            let bad = match p {
                Policy::Keep => Some("keeps it as it is"),
                Policy::Initial => Some(INITIAL),
                Policy::Safe(v) if v == on => Some("switches the drive on"),
                Policy::Safe(_) => None,
            };
            if let Some(what) = bad {
                ok = false;
                let msg = format!(
                    "the enable output {card}.{port}: at stop the card {what}; a drive's enable \
                     needs its off value as its safe value ([card.outputs] safe = \
                     {{ {port} = {} }})",
                    b.invert
                );
                self.problems.at(&at.key("enable"), msg);
            }
        }
        ok.then_some(())
    }

    fn axis(&mut self, at: &KeyPath, a: &AxisConfig) -> Option<Arc<dyn Axis>> {
        self.period(&at.key("period_ms"), a.period_ms)?;
        if let Err(e) = a.thread.check() {
            self.problems.at(&at.key("thread"), e);
            return None;
        }
        if let Some(first) = self.axes.iter().find(|(_, d)| *d == a.drive) {
            let msg = format!(
                "drive {:?} is commanded by axis {:?} already",
                a.drive, first.0
            );
            self.problems.at(&at.key("drive"), msg);
            return None;
        }
        self.axes.push((a.name.clone(), a.drive.clone()));
        let drive = match self.owned.iter().find(|(n, _)| *n == a.drive) {
            Some((_, d)) => d.clone(),
            None => {
                // A card's drive (a CANopen CiA 402 node) has its own drive component,
                // whose commands would race the axis'.
                let card = self.registry.entries().into_iter().find(|e| {
                    e.interface == device_interface::Interface::Drive
                        && e.info.name == a.drive
                        && e.info.owner != a.drive
                });
                if let Some(e) = card {
                    let msg = format!(
                        "drive {:?} is card {:?}'s: an axis does not yet take a card's drive",
                        a.drive, e.info.owner
                    );
                    self.problems.at(&at.key("drive"), msg);
                    return None;
                }
                self.ok(&at.key("drive"), self.registry.drive().lookup(&a.drive))?
            }
        };
        let enc = self.ok(
            &at.key("encoder"),
            self.registry.encoder().lookup(&a.encoder),
        )?;
        let encoder = self.ok(
            &at.key("counts_per_unit"),
            EncoderSensor::new(enc, a.counts_per_unit, 0.0, &a.unit),
        )?;
        let limit_min = self.optional_in(&at.key("limit_min"), &a.limit_min)?;
        let limit_max = self.optional_in(&at.key("limit_max"), &a.limit_max)?;
        let home = self.optional_in(&at.key("home"), &a.home)?;
        let homing = a.homing.map(|h| HomingConfig {
            velocity: h.velocity,
            position: h.position,
            back_off: h.back_off,
            max_travel: h.max_travel,
        });
        let parts = ServoAxisParts {
            drive,
            encoder,
            limit_min,
            limit_max,
            home,
            homing,
        };
        let axis = self.ok(&at.key("homing"), ServoAxis::new(parts))?;
        Some(Arc::new(axis))
    }
}
