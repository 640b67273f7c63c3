//! The driver conformance kit: checks that a device keeps the interface contract.
//!
//! Every driver crate runs these checks against its own devices in its tests (enable the
//! `conformance` feature in its dev-dependencies). Each check returns a [`Report`] that
//! names every [`Rule`] it ran and every violation it saw; `report.assert_complete()`
//! fails a test unless every rule of the interface ran and passed.
//!
//! Rules that need the inputs to change take a *stimulus*: a closure that makes the device
//! see an input value (inject into a simulator, send a CAN frame and wait for it, drive a
//! loopback). Without one, those rules are not run and the report says so.
//!
//! The checks write outputs. Run them on a test rig, never on a machine that moves; they
//! restore the outputs they found when they finish.
//!
//! ```
//! use device_interface::conformance::{self, Rule};
//! # use device_interface::{Device, DeviceError, DigitalOut, Health, Status, time::Timestamp};
//! # use device_interface::bits::{BitImage, BitSpan};
//! # struct Outputs(BitImage);
//! # impl Device for Outputs { fn health(&self) -> Health { Health { status: Status::Online, last_good: None, checked_at: Timestamp::ZERO, last_error: None } } }
//! # impl DigitalOut for Outputs {
//! #     fn output_count(&self) -> u32 { self.0.len() }
//! #     fn set_bit(&self, b: u32, v: bool) -> Result<(), DeviceError> { self.0.set(b, v).map(|_| ()) }
//! #     fn check_bit(&self, b: u32) -> Result<bool, DeviceError> { self.0.get(b) }
//! # }
//! let card = Outputs(BitImage::new(12));
//! let report = conformance::check_digital_out(&card);
//! report.assert_complete();
//! assert!(report.ran(Rule::DoSequence));
//! ```

mod axis;

pub use axis::{AxisRig, check_axis};

use crate::bits::BitSpan;
use crate::registry::Interface;
use crate::{AnalogIn, AnalogOut, DeviceError, DigitalIn, DigitalOut, Encoder, Scale};
use std::fmt;

/// One rule of the interface contract.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[non_exhaustive]
pub enum Rule {
    /// AnalogIn has at least one channel.
    AiChannels,
    /// AnalogIn methods refuse channels past the end with `ChannelOutOfRange`.
    AiOutOfRange,
    /// AnalogIn ranges are finite and ordered, and agree with the scale.
    AiRange,
    /// AnalogIn resolution is the physical span over the raw span.
    AiResolution,
    /// AnalogIn `read` is the scale's conversion of `read_raw` (within half a step: a
    /// device may read finer than its raw grid, `read_raw` then being the nearest code),
    /// within the raw range.
    AiConversion,
    /// AnalogIn reads exactly the raw values the stimulus sets, and `read` their
    /// conversion within half a step (needs a stimulus).
    AiStimulus,
    /// AnalogOut has at least one channel.
    AoChannels,
    /// AnalogOut methods refuse channels past the end with `ChannelOutOfRange`.
    AoOutOfRange,
    /// AnalogOut ranges are finite and ordered, and agree with the scale.
    AoRange,
    /// AnalogOut resolution is the physical span over the raw span.
    AoResolution,
    /// AnalogOut accepts both ends of its range exactly.
    AoEndpoints,
    /// AnalogOut reads back what was written, within half a step (raw: exactly).
    AoReadBack,
    /// AnalogOut refuses out-of-range, NaN and infinite values and keeps the old value.
    AoRefusal,
    /// DigitalIn has at least one bit.
    DiInputs,
    /// DigitalIn refuses bits and spans past the end, reversed spans and spans over 64 bits.
    DiOutOfRange,
    /// DigitalIn `is_on`/`is_off` agree with `read_bit`.
    DiOnOff,
    /// DigitalIn `read_sequence` puts bit `start` at bit 0, agreeing with `read_bit`.
    DiSequence,
    /// DigitalIn reads exactly the bit patterns the stimulus sets (needs a stimulus).
    DiStimulus,
    /// DigitalOut has at least one bit.
    DoOutputs,
    /// DigitalOut refuses bits and spans past the end and leaves outputs unchanged.
    DoOutOfRange,
    /// DigitalOut `check_bit` returns what `set_bit`/`switch_on`/`switch_off` set, and
    /// neighbours keep their state.
    DoSetCheck,
    /// DigitalOut `check_sequence` returns what `set_sequence` set, bit `start` at bit 0,
    /// agreeing with `check_bit`, with bits outside the span untouched.
    DoSequence,
    /// DigitalOut refuses sequence values wider than the span and leaves outputs unchanged.
    DoSequenceTooWide,
    /// Encoder resolution is not 0.
    EncResolution,
    /// Encoder `position` returns what `set_position` set; the turn is kept.
    EncPositionSetGet,
    /// Encoder `turn` returns what `set_turn` set; the position is kept.
    EncTurnSetGet,
    /// Encoder refuses positions outside the resolution's interval and keeps its state.
    EncPositionRejected,
    /// Encoder roll-over adds and removes turns as `upcounting` says (needs a stimulus).
    EncMotion,
    /// An axis starts disabled, standing still, its drive disabled.
    AxStartsDisabled,
    /// An axis its thread does not step refuses to be enabled; a disabled one refuses to
    /// move or home; each with `Refused`.
    AxRefusedDisabled,
    /// `enable` makes it ready at standstill, its drive enabled (its enable output on,
    /// where the rig can tell); `disable` undoes it.
    AxEnableDisable,
    /// `jog` moves it in the velocity's direction; `stop` stands it still, enabled.
    AxJog,
    /// `home` finds the home switch, latches it as the configured position and backs off,
    /// ending ready and homed within the tolerance (needs homing).
    AxHoming,
    /// A limit switch turning on while moving towards it disables the drive (its enable
    /// output off, where the rig can tell) and puts the axis in error with that limit as
    /// the fault; moves are refused until `reset`; after
    /// it the axis moves away from the limit but not into it (needs a limit stimulus).
    AxLimit,
}

impl Rule {
    /// Every rule for `interface`.
    pub fn for_interface(interface: Interface) -> &'static [Rule] {
        use Rule::*;
        match interface {
            Interface::AnalogIn => &[
                AiChannels,
                AiOutOfRange,
                AiRange,
                AiResolution,
                AiConversion,
                AiStimulus,
            ],
            Interface::AnalogOut => &[
                AoChannels,
                AoOutOfRange,
                AoRange,
                AoResolution,
                AoEndpoints,
                AoReadBack,
                AoRefusal,
            ],
            Interface::DigitalIn => &[DiInputs, DiOutOfRange, DiOnOff, DiSequence, DiStimulus],
            Interface::DigitalOut => &[
                DoOutputs,
                DoOutOfRange,
                DoSetCheck,
                DoSequence,
                DoSequenceTooWide,
            ],
            Interface::Encoder => &[
                EncResolution,
                EncPositionSetGet,
                EncTurnSetGet,
                EncPositionRejected,
                EncMotion,
            ],
            Interface::Axis => &[
                AxStartsDisabled,
                AxRefusedDisabled,
                AxEnableDisable,
                AxJog,
                AxHoming,
                AxLimit,
            ],
            Interface::Sensor | Interface::Drive => &[],
        }
    }
}

/// What happened to one rule.
#[derive(Debug, Clone)]
pub struct Outcome {
    /// The rule.
    pub rule: Rule,
    /// How many individual checks ran.
    pub checks: usize,
    /// What was wrong; empty when the rule held.
    pub failures: Vec<String>,
}

/// The result of checking one device against one interface.
#[derive(Debug, Clone)]
pub struct Report {
    interface: Interface,
    outcomes: Vec<Outcome>,
}

impl Report {
    fn new(interface: Interface) -> Self {
        Report {
            interface,
            outcomes: Vec::new(),
        }
    }

    /// The interface checked.
    pub fn interface(&self) -> Interface {
        self.interface
    }

    /// Every rule that ran, with its outcome.
    pub fn outcomes(&self) -> &[Outcome] {
        &self.outcomes
    }

    /// True when `rule` ran.
    pub fn ran(&self, rule: Rule) -> bool {
        self.outcomes.iter().any(|o| o.rule == rule)
    }

    /// Rules of the interface that did not run (for lack of a stimulus).
    pub fn not_run(&self) -> Vec<Rule> {
        Rule::for_interface(self.interface)
            .iter()
            .copied()
            .filter(|r| !self.ran(*r))
            .collect()
    }

    /// Rules that ran and failed.
    pub fn failed(&self) -> Vec<Rule> {
        self.outcomes
            .iter()
            .filter(|o| !o.failures.is_empty())
            .map(|o| o.rule)
            .collect()
    }

    /// True when every rule that ran held.
    pub fn passed(&self) -> bool {
        self.outcomes.iter().all(|o| o.failures.is_empty())
    }

    /// Panics, printing the report, unless every rule that ran held.
    pub fn assert_pass(&self) {
        assert!(self.passed(), "{self}");
    }

    /// Panics, printing the report, unless every rule of the interface ran and held.
    pub fn assert_complete(&self) {
        self.assert_pass();
        let missing = self.not_run();
        assert!(missing.is_empty(), "rules not run: {missing:?}\n{self}");
    }

    fn outcome(&mut self, rule: Rule) -> &mut Outcome {
        if let Some(i) = self.outcomes.iter().position(|o| o.rule == rule) {
            &mut self.outcomes[i]
        } else {
            self.outcomes.push(Outcome {
                rule,
                checks: 0,
                failures: Vec::new(),
            });
            let last = self.outcomes.len() - 1;
            &mut self.outcomes[last]
        }
    }

    /// Records one check of `rule`; `failure` is `None` when it held.
    fn check(&mut self, rule: Rule, failure: Option<String>) {
        let o = self.outcome(rule);
        o.checks += 1;
        // Keep the report readable when a device fails the same way on every channel.
        if let Some(f) = failure
            && o.failures.len() < 20
        {
            o.failures.push(f);
        }
    }

    fn expect(&mut self, rule: Rule, ok: bool, what: impl FnOnce() -> String) {
        self.check(rule, (!ok).then(what));
    }

    /// One check per (method, refused-correctly) pair for channel `c` past the end.
    fn expect_channel_oor(&mut self, rule: Rule, c: u32, count: u32, checks: &[(&str, bool)]) {
        for (method, ok) in checks {
            self.expect(rule, *ok, || {
                format!("{method}({c}) did not fail with ChannelOutOfRange {{ channel: {c}, count: {count} }}")
            });
        }
    }
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{} conformance:", self.interface)?;
        for o in &self.outcomes {
            let verdict = if o.failures.is_empty() {
                "ok"
            } else {
                "FAILED"
            };
            writeln!(f, "  {:?}: {verdict} ({} checks)", o.rule, o.checks)?;
            for failure in &o.failures {
                writeln!(f, "    - {failure}")?;
            }
        }
        for r in self.not_run() {
            writeln!(f, "  {r:?}: not run (no stimulus)")?;
        }
        Ok(())
    }
}

/// A stimulus for analog inputs: make `channel` read the raw value given.
pub type AnalogStimulus<'a> = &'a mut dyn FnMut(u32, i64);
/// A stimulus for digital inputs: make `bit` read the value given.
pub type DigitalStimulus<'a> = &'a mut dyn FnMut(u32, bool);
/// A stimulus for encoders: move by this many counts (positive: the positive direction).
pub type MotionStimulus<'a> = &'a mut dyn FnMut(i64);

fn is_channel_oor<T>(r: &Result<T, DeviceError>, channel: u32, count: u32) -> bool {
    matches!(r, Err(DeviceError::ChannelOutOfRange { channel: c, count: n }) if *c == channel && *n == count)
}

fn is_bit_oor<T>(r: &Result<T, DeviceError>, bit: u32, count: u32) -> bool {
    matches!(r, Err(DeviceError::BitOutOfRange { bit: b, count: n }) if *b == bit && *n == count)
}

fn is_span_oor<T>(r: &Result<T, DeviceError>) -> bool {
    matches!(r, Err(DeviceError::SpanOutOfRange { .. }))
}

/// Channels just past the end, the one most likely to be mishandled first.
fn channels_past(count: u32) -> Vec<u32> {
    let mut v = vec![count, count.saturating_add(1), u32::MAX];
    v.dedup();
    v
}

/// Raw values spread over a range: both ends, their neighbours and a few in between.
fn raw_samples(min: i64, max: i64) -> Vec<i64> {
    let span = i128::from(max) - i128::from(min);
    let mut v: Vec<i64> = [0i128, 1, span / 3, span / 2, span - 1, span]
        .iter()
        .map(|&d| (i128::from(min) + d.clamp(0, span)) as i64)
        .collect();
    v.sort_unstable();
    v.dedup();
    v
}

fn check_scale(
    report: &mut Report,
    rules: (Rule, Rule),
    channel: u32,
    scale: &Scale,
    ranges: Ranges,
) {
    let (range_rule, res_rule) = rules;
    let r = scale.range();
    report.expect(
        range_rule,
        r.lowest.is_finite() && r.highest.is_finite() && r.lowest < r.highest,
        || {
            format!(
                "channel {channel}: range [{}, {}] is not finite and ordered",
                r.lowest, r.highest
            )
        },
    );
    let raw = scale.raw_range();
    report.expect(range_rule, raw.min < raw.max, || {
        format!(
            "channel {channel}: raw range [{}, {}] is empty",
            raw.min, raw.max
        )
    });
    report.expect(range_rule, ranges.range == Some(r), || {
        format!(
            "channel {channel}: range() {:?} differs from scale().range() {r:?}",
            ranges.range
        )
    });
    report.expect(range_rule, ranges.raw == Some(raw), || {
        format!(
            "channel {channel}: raw_range() {:?} differs from scale().raw_range() {raw:?}",
            ranges.raw
        )
    });
    let expected = (r.highest - r.lowest) / (i128::from(raw.max) - i128::from(raw.min)) as f64;
    let ok = matches!(ranges.resolution, Some(res) if res > 0.0 && (res - expected).abs() <= expected * 1e-9);
    report.expect(res_rule, ok, || {
        format!(
            "channel {channel}: resolution {:?}, expected (highest - lowest) / (raw max - raw min) = {expected}",
            ranges.resolution
        )
    });
}

struct Ranges {
    range: Option<crate::AnalogRange>,
    raw: Option<crate::RawRange>,
    resolution: Option<f64>,
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

/// Checks an analog input device. With a `stimulus`, also checks exact reads of injected raw
/// values ([`Rule::AiStimulus`]); without one, inputs should hold still while it runs.
pub fn check_analog_in(dev: &dyn AnalogIn, mut stimulus: Option<AnalogStimulus<'_>>) -> Report {
    use Rule::*;
    let mut report = Report::new(Interface::AnalogIn);
    let count = dev.channel_count();
    report.expect(AiChannels, count >= 1, || "channel_count() is 0".into());

    for c in channels_past(count) {
        let checks = [
            ("read", is_channel_oor(&dev.read(c), c, count)),
            ("read_raw", is_channel_oor(&dev.read_raw(c), c, count)),
            ("scale", is_channel_oor(&dev.scale(c), c, count)),
            ("range", is_channel_oor(&dev.range(c), c, count)),
            ("raw_range", is_channel_oor(&dev.raw_range(c), c, count)),
            ("resolution", is_channel_oor(&dev.resolution(c), c, count)),
        ];
        report.expect_channel_oor(AiOutOfRange, c, count, &checks);
    }

    for c in 0..count {
        let scale = match dev.scale(c) {
            Ok(s) => s,
            Err(e) => {
                report.check(AiRange, Some(format!("scale({c}) failed: {e}")));
                continue;
            }
        };
        let ranges = Ranges {
            range: dev.range(c).ok(),
            raw: dev.raw_range(c).ok(),
            resolution: dev.resolution(c).ok(),
        };
        check_scale(&mut report, (AiRange, AiResolution), c, &scale, ranges);

        // read() may be finer than the raw grid (a float register carries its value
        // exactly); read_raw() is then its nearest code: half a step apart at most.
        let tol = scale.resolution() * (0.5 + 1e-6);
        match (dev.read_raw(c), dev.read(c)) {
            (Ok(raw), Ok(value)) => {
                report.expect(AiConversion, scale.raw_range().contains(raw), || {
                    format!(
                        "channel {c}: read_raw() = {raw} is outside the raw range {:?}",
                        scale.raw_range()
                    )
                });
                let want = scale.to_physical(raw);
                report.expect(AiConversion, close(value, want, tol), || {
                    format!(
                        "channel {c}: read() = {value}, but read_raw() = {raw} converts to {want}"
                    )
                });
            }
            (a, b) => report.check(
                AiConversion,
                Some(format!(
                    "channel {c}: reading failed: read_raw {a:?}, read {b:?}"
                )),
            ),
        }

        if let Some(stim) = stimulus.as_mut() {
            let raw_range = scale.raw_range();
            for raw in raw_samples(raw_range.min, raw_range.max) {
                stim(c, raw);
                let got_raw = dev.read_raw(c);
                report.expect(AiStimulus, matches!(got_raw, Ok(r) if r == raw), || {
                    format!("channel {c}: stimulus raw {raw}, read_raw() = {got_raw:?}")
                });
                let want = scale.to_physical(raw);
                let got = dev.read(c);
                report.expect(
                    AiStimulus,
                    matches!(got, Ok(v) if close(v, want, tol)),
                    || format!("channel {c}: stimulus raw {raw} is {want}, read() = {got:?}"),
                );
            }
        }
    }
    report
}

/// Checks an analog output device. Writes every channel; restores the values it found.
pub fn check_analog_out(dev: &dyn AnalogOut) -> Report {
    use Rule::*;
    let mut report = Report::new(Interface::AnalogOut);
    let count = dev.channel_count();
    report.expect(AoChannels, count >= 1, || "channel_count() is 0".into());

    for c in channels_past(count) {
        let checks = [
            ("write", is_channel_oor(&dev.write(c, 0.0), c, count)),
            ("write_raw", is_channel_oor(&dev.write_raw(c, 0), c, count)),
            ("read_back", is_channel_oor(&dev.read_back(c), c, count)),
            (
                "read_back_raw",
                is_channel_oor(&dev.read_back_raw(c), c, count),
            ),
            ("scale", is_channel_oor(&dev.scale(c), c, count)),
            ("range", is_channel_oor(&dev.range(c), c, count)),
            ("raw_range", is_channel_oor(&dev.raw_range(c), c, count)),
            ("resolution", is_channel_oor(&dev.resolution(c), c, count)),
        ];
        report.expect_channel_oor(AoOutOfRange, c, count, &checks);
    }

    for c in 0..count {
        let scale = match dev.scale(c) {
            Ok(s) => s,
            Err(e) => {
                report.check(AoRange, Some(format!("scale({c}) failed: {e}")));
                continue;
            }
        };
        let ranges = Ranges {
            range: dev.range(c).ok(),
            raw: dev.raw_range(c).ok(),
            resolution: dev.resolution(c).ok(),
        };
        check_scale(&mut report, (AoRange, AoResolution), c, &scale, ranges);
        let original = dev.read_back_raw(c);
        let (r, raw) = (scale.range(), scale.raw_range());

        // Endpoints, physical and raw.
        for (value, want_raw) in [
            (r.lowest, scale.to_raw(r.lowest)),
            (r.highest, scale.to_raw(r.highest)),
        ] {
            let w = dev.write(c, value);
            let back = dev.read_back(c);
            report.expect(AoEndpoints, w.is_ok() && matches!(back, Ok(b) if b == value), || {
                format!("channel {c}: write({value}) = {w:?}, read_back() = {back:?}, expected exactly {value}")
            });
            let back_raw = dev.read_back_raw(c);
            report.expect(AoEndpoints, back_raw.as_ref().ok() == want_raw.as_ref(), || {
                format!("channel {c}: after write({value}) read_back_raw() = {back_raw:?}, expected {want_raw:?}")
            });
        }

        // Physical values across the range read back within half a step.
        let tol = scale.resolution() * (0.5 + 1e-6);
        for i in 0..=10 {
            // (The fraction first: a double's span times 10 would overflow.)
            let value = r.lowest + (r.highest - r.lowest) * (f64::from(i) / 10.0);
            let w = dev.write(c, value);
            let back = dev.read_back(c);
            report.expect(AoReadBack, w.is_ok() && matches!(back, Ok(b) if close(b, value, tol)), || {
                format!("channel {c}: write({value}) = {w:?}, read_back() = {back:?}, expected within {tol}")
            });
            let back_raw = dev.read_back_raw(c);
            let want = scale.to_raw(value);
            report.expect(AoReadBack, back_raw.as_ref().ok() == want.as_ref(), || {
                format!("channel {c}: write({value}): read_back_raw() = {back_raw:?}, expected the nearest step {want:?}")
            });
        }
        for value in raw_samples(raw.min, raw.max) {
            let w = dev.write_raw(c, value);
            let back_raw = dev.read_back_raw(c);
            let back = dev.read_back(c);
            let want = scale.to_physical(value);
            report.expect(
                AoReadBack,
                w.is_ok() && matches!(back_raw, Ok(b) if b == value) && matches!(back, Ok(b) if close(b, want, scale.resolution() * 1e-6)),
                || format!("channel {c}: write_raw({value}) = {w:?}, read back raw {back_raw:?} / {back:?}, expected {value} / {want}"),
            );
        }

        // Refusals keep the previous value.
        let mid = raw.min + (raw.max - raw.min) / 2;
        let _ = dev.write_raw(c, mid);
        let span = r.highest - r.lowest;
        for value in [
            r.highest + span,
            r.lowest - span,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ] {
            let w = dev.write(c, value);
            let ok = matches!(w, Err(DeviceError::ValueOutOfRange { channel, .. }) if channel == c);
            report.expect(AoRefusal, ok, || {
                format!("channel {c}: write({value}) = {w:?}, expected ValueOutOfRange")
            });
            let back = dev.read_back_raw(c);
            report.expect(AoRefusal, matches!(back, Ok(b) if b == mid), || {
                format!("channel {c}: refused write({value}) changed the output: read_back_raw() = {back:?}, expected {mid}")
            });
        }
        for value in [raw.max.checked_add(1), raw.min.checked_sub(1)]
            .into_iter()
            .flatten()
        {
            let w = dev.write_raw(c, value);
            let ok = matches!(w, Err(DeviceError::RawOutOfRange { channel, .. }) if channel == c);
            report.expect(AoRefusal, ok, || {
                format!("channel {c}: write_raw({value}) = {w:?}, expected RawOutOfRange")
            });
            let back = dev.read_back_raw(c);
            report.expect(AoRefusal, matches!(back, Ok(b) if b == mid), || {
                format!("channel {c}: refused write_raw({value}) changed the output: read_back_raw() = {back:?}")
            });
        }

        if let Ok(o) = original {
            let _ = dev.write_raw(c, o);
        }
    }
    report
}

/// Spans worth checking on `count` bits: every single bit, the widest span from bit 0, the
/// widest span ending at the last bit, and a few interior spans.
fn spans(count: u32) -> Vec<BitSpan> {
    let mut v = Vec::new();
    for b in 0..count {
        v.extend(BitSpan::new(b, b, count));
    }
    let widest = count.min(64);
    if widest >= 1 {
        v.extend(BitSpan::new(0, widest - 1, count));
        v.extend(BitSpan::new(count - widest, count - 1, count));
    }
    for (start, width) in [(1, 3), (2, 5), (3, 8), (count / 3, 11), (count / 2, 17)] {
        if width >= 1 && start + width <= count {
            v.extend(BitSpan::new(start, start + width - 1, count));
        }
    }
    v.sort_by_key(|s| (s.start(), s.stop()));
    v.dedup();
    v
}

/// A named bit pattern: the state of each bit, as a function of the bit number.
type Pattern = (&'static str, fn(u32) -> bool);

/// Bit patterns the digital checks drive and expect.
const PATTERNS: [Pattern; 5] = [
    ("all off", |_| false),
    ("all on", |_| true),
    ("even bits on", |b| b % 2 == 0),
    ("odd bits on", |b| b % 2 == 1),
    ("every third on", |b| (b * 7 + 3) % 3 == 0),
];

fn expected_span(span: &BitSpan, pattern: impl Fn(u32) -> bool) -> u64 {
    span.bits()
        .fold(0u64, |acc, (bit, i)| acc | (u64::from(pattern(bit)) << i))
}

fn bad_spans(count: u32) -> Vec<(u32, u32)> {
    let mut v = vec![(count, count), (0, count), (count, count.saturating_add(5))];
    if count >= 2 {
        v.push((1, 0));
    }
    if count >= 65 {
        v.push((0, 64));
    }
    v
}

/// Checks a digital input device. With a `stimulus`, also checks exact reads of bit patterns
/// ([`Rule::DiStimulus`]); without one, inputs should hold still while it runs.
pub fn check_digital_in(dev: &dyn DigitalIn, mut stimulus: Option<DigitalStimulus<'_>>) -> Report {
    use Rule::*;
    let mut report = Report::new(Interface::DigitalIn);
    let count = dev.input_count();
    report.expect(DiInputs, count >= 1, || "input_count() is 0".into());

    for b in channels_past(count) {
        for (method, ok) in [
            ("read_bit", is_bit_oor(&dev.read_bit(b), b, count)),
            ("is_on", is_bit_oor(&dev.is_on(b), b, count)),
            ("is_off", is_bit_oor(&dev.is_off(b), b, count)),
        ] {
            report.expect(DiOutOfRange, ok, || {
                format!(
                    "{method}({b}) did not fail with BitOutOfRange {{ bit: {b}, count: {count} }}"
                )
            });
        }
    }
    for (start, stop) in bad_spans(count) {
        let r = dev.read_sequence(start, stop);
        report.expect(DiOutOfRange, is_span_oor(&r), || {
            format!("read_sequence({start}, {stop}) = {r:?}, expected SpanOutOfRange")
        });
    }

    let check_consistency = |report: &mut Report, rule: Rule, label: &str| {
        let bits: Vec<Result<bool, DeviceError>> = (0..count).map(|b| dev.read_bit(b)).collect();
        for (b, v) in bits.iter().enumerate() {
            let b = b as u32;
            let (on, off) = (dev.is_on(b), dev.is_off(b));
            let ok = matches!((v, &on, &off), (Ok(v), Ok(on), Ok(off)) if on == v && *off != *v);
            report.expect(DiOnOff, ok, || {
                format!("{label}bit {b}: read_bit {v:?}, is_on {on:?}, is_off {off:?}")
            });
        }
        for span in spans(count) {
            let want: Result<u64, String> = span.bits().try_fold(0u64, |acc, (bit, i)| match &bits
                [bit as usize]
            {
                Ok(v) => Ok(acc | (u64::from(*v) << i)),
                Err(e) => Err(e.to_string()),
            });
            let got = dev.read_sequence(span.start(), span.stop());
            report.expect(
                rule,
                matches!((&got, &want), (Ok(g), Ok(w)) if g == w),
                || {
                    format!(
                        "{label}read_sequence({}, {}) = {got:?}, but read_bit gives {want:?}",
                        span.start(),
                        span.stop()
                    )
                },
            );
        }
    };
    check_consistency(&mut report, DiSequence, "");

    if let Some(stim) = stimulus.as_mut() {
        for (name, pattern) in PATTERNS {
            for b in 0..count {
                stim(b, pattern(b));
            }
            for b in 0..count {
                let got = dev.read_bit(b);
                report.expect(DiStimulus, matches!(got, Ok(v) if v == pattern(b)), || {
                    format!(
                        "pattern {name}: read_bit({b}) = {got:?}, expected {}",
                        pattern(b)
                    )
                });
            }
            for span in spans(count) {
                let want = expected_span(&span, pattern);
                let got = dev.read_sequence(span.start(), span.stop());
                report.expect(DiStimulus, matches!(got, Ok(v) if v == want), || {
                    format!(
                        "pattern {name}: read_sequence({}, {}) = {got:?}, expected {want:#b}",
                        span.start(),
                        span.stop()
                    )
                });
            }
            check_consistency(&mut report, DiSequence, &format!("pattern {name}: "));
        }
    }
    report
}

fn snapshot(dev: &dyn DigitalOut) -> Vec<Option<bool>> {
    (0..dev.output_count())
        .map(|b| dev.check_bit(b).ok())
        .collect()
}

/// Checks a digital output device. Writes every bit; restores the states it found.
pub fn check_digital_out(dev: &dyn DigitalOut) -> Report {
    use Rule::*;
    let mut report = Report::new(Interface::DigitalOut);
    let count = dev.output_count();
    report.expect(DoOutputs, count >= 1, || "output_count() is 0".into());
    let original = snapshot(dev);

    // A known background, so a write that disturbs its neighbours shows.
    let set_pattern = |pattern: fn(u32) -> bool| {
        for b in 0..count {
            let _ = dev.set_bit(b, pattern(b));
        }
    };
    let unchanged = |report: &mut Report,
                     rule: Rule,
                     before: &[Option<bool>],
                     skip: Option<BitSpan>,
                     what: &str| {
        for (b, (was, now)) in before.iter().zip(snapshot(dev)).enumerate() {
            let b = b as u32;
            if skip.is_some_and(|s| (s.start()..=s.stop()).contains(&b)) {
                continue;
            }
            report.expect(rule, *was == now, || {
                format!("{what} changed bit {b} from {was:?} to {now:?}")
            });
        }
    };

    set_pattern(PATTERNS[2].1);
    let before = snapshot(dev);
    for b in channels_past(count) {
        for (method, ok) in [
            ("set_bit", is_bit_oor(&dev.set_bit(b, true), b, count)),
            ("switch_on", is_bit_oor(&dev.switch_on(b), b, count)),
            ("switch_off", is_bit_oor(&dev.switch_off(b), b, count)),
            ("check_bit", is_bit_oor(&dev.check_bit(b), b, count)),
        ] {
            report.expect(DoOutOfRange, ok, || {
                format!(
                    "{method}({b}) did not fail with BitOutOfRange {{ bit: {b}, count: {count} }}"
                )
            });
        }
    }
    for (start, stop) in bad_spans(count) {
        let w = dev.set_sequence(start, stop, 0);
        report.expect(DoOutOfRange, is_span_oor(&w), || {
            format!("set_sequence({start}, {stop}, 0) = {w:?}, expected SpanOutOfRange")
        });
        let r = dev.check_sequence(start, stop);
        report.expect(DoOutOfRange, is_span_oor(&r), || {
            format!("check_sequence({start}, {stop}) = {r:?}, expected SpanOutOfRange")
        });
    }
    unchanged(&mut report, DoOutOfRange, &before, None, "a refused call");

    for background in [PATTERNS[2].1, PATTERNS[3].1] {
        for b in 0..count {
            set_pattern(background);
            let only_b = BitSpan::new(b, b, count).ok();
            for (op, value) in [
                ("set_bit(true)", true),
                ("set_bit(false)", false),
                ("switch_on", true),
                ("switch_off", false),
            ] {
                let before = snapshot(dev);
                let w = match op {
                    "switch_on" => dev.switch_on(b),
                    "switch_off" => dev.switch_off(b),
                    _ => dev.set_bit(b, value),
                };
                let got = dev.check_bit(b);
                report.expect(
                    DoSetCheck,
                    w.is_ok() && matches!(got, Ok(v) if v == value),
                    || format!("{op} on bit {b} = {w:?}, then check_bit = {got:?}"),
                );
                unchanged(
                    &mut report,
                    DoSetCheck,
                    &before,
                    only_b,
                    &format!("{op} on bit {b}"),
                );
            }
        }
    }

    for span in spans(count) {
        for (name, pattern) in PATTERNS {
            set_pattern(PATTERNS[(span.start() as usize) % 2 + 2].1);
            let before = snapshot(dev);
            // The value's bit i drives device bit start+i.
            let value = (0..span.width()).fold(0u64, |acc, i| acc | (u64::from(pattern(i)) << i));
            let w = dev.set_sequence(span.start(), span.stop(), value);
            let got = dev.check_sequence(span.start(), span.stop());
            report.expect(DoSequence, w.is_ok() && matches!(got, Ok(v) if v == value), || {
                format!(
                    "set_sequence({}, {}, {value:#b}) ({name}) = {w:?}, then check_sequence = {got:?}",
                    span.start(),
                    span.stop()
                )
            });
            for (bit, i) in span.bits() {
                let got = dev.check_bit(bit);
                let want = value >> i & 1 == 1;
                report.expect(DoSequence, matches!(got, Ok(v) if v == want), || {
                    format!(
                        "after set_sequence({}, {}, {value:#b}): check_bit({bit}) = {got:?}, expected {want}",
                        span.start(),
                        span.stop()
                    )
                });
            }
            unchanged(
                &mut report,
                DoSequence,
                &before,
                Some(span),
                &format!("set_sequence({}, {}, ..)", span.start(), span.stop()),
            );
        }
        if span.width() < 64 {
            let before = snapshot(dev);
            let too_wide = 1u64 << span.width();
            let w = dev.set_sequence(span.start(), span.stop(), too_wide | 1);
            report.expect(
                DoSequenceTooWide,
                matches!(w, Err(DeviceError::SequenceValueTooWide { .. })),
                || {
                    format!(
                        "set_sequence({}, {}, {:#b}) = {w:?}, expected SequenceValueTooWide",
                        span.start(),
                        span.stop(),
                        too_wide | 1
                    )
                },
            );
            unchanged(
                &mut report,
                DoSequenceTooWide,
                &before,
                None,
                "a refused set_sequence",
            );
        }
    }

    for (b, v) in original.iter().enumerate() {
        if let Some(v) = v {
            let _ = dev.set_bit(b as u32, *v);
        }
    }
    report
}

/// Checks an encoder. With a `motion` stimulus, also checks roll-over ([`Rule::EncMotion`]).
/// Restores the position and turn it found.
pub fn check_encoder(dev: &dyn Encoder, mut motion: Option<MotionStimulus<'_>>) -> Report {
    use Rule::*;
    let mut report = Report::new(Interface::Encoder);
    let res = dev.resolution();
    report.expect(EncResolution, res != 0 && res != i64::MIN, || {
        format!("resolution() = {res}")
    });
    if res == 0 || res == i64::MIN {
        return report;
    }
    let original = (dev.position(), dev.turn());
    let sign = res.signum();
    let last = sign * (res.abs() - 1);
    let state = || (dev.position(), dev.turn());

    let turn_before = dev.turn();
    for p in [0, sign, last, sign * (res.abs() / 2)] {
        let w = dev.set_position(p);
        let got = dev.position();
        report.expect(
            EncPositionSetGet,
            w.is_ok() && matches!(got, Ok(v) if v == p),
            || format!("set_position({p}) = {w:?}, then position() = {got:?}"),
        );
        let t = dev.turn();
        report.expect(
            EncPositionSetGet,
            t.as_ref().ok() == turn_before.as_ref().ok(),
            || format!("set_position({p}) changed the turn from {turn_before:?} to {t:?}"),
        );
    }

    let _ = dev.set_position(last);
    for t in [0, 1, -1, 1000, -1000] {
        let w = dev.set_turn(t);
        let got = state();
        report.expect(
            EncTurnSetGet,
            w.is_ok() && matches!(got, (Ok(p), Ok(v)) if v == t && p == last),
            || {
                format!(
                    "set_turn({t}) = {w:?}, then (position, turn) = {got:?}, expected ({last}, {t})"
                )
            },
        );
    }

    let bad = if res > 0 {
        vec![res, -1, res.saturating_add(1), i64::MAX, i64::MIN]
    } else {
        vec![res, 1, res.saturating_sub(1), i64::MIN, i64::MAX]
    };
    let _ = dev.set_turn(3);
    let _ = dev.set_position(sign);
    for p in bad {
        let before = state();
        let w = dev.set_position(p);
        report.expect(
            EncPositionRejected,
            matches!(w, Err(DeviceError::PositionOutOfRange { position, .. }) if position == p),
            || format!("set_position({p}) = {w:?}, expected PositionOutOfRange (resolution {res})"),
        );
        let after = state();
        report.expect(EncPositionRejected, format!("{before:?}") == format!("{after:?}"), || {
            format!("refused set_position({p}) changed (position, turn) from {before:?} to {after:?}")
        });
    }

    if let Some(step) = motion.as_mut() {
        let up = dev.upcounting();
        // Up: last -> 0 adds a turn. Down: 0 -> last adds a turn.
        let (from, to) = if up { (last, 0) } else { (0, last) };
        let _ = dev.set_turn(0);
        let _ = dev.set_position(from);
        step(1);
        let got = state();
        report.expect(EncMotion, matches!(got, (Ok(p), Ok(1)) if p == to), || {
            format!("upcounting() = {up}: from ({from}, 0), one count forward gave {got:?}, expected ({to}, 1)")
        });
        step(-1);
        let got = state();
        report.expect(
            EncMotion,
            matches!(got, (Ok(p), Ok(0)) if p == from),
            || format!("upcounting() = {up}: one count back gave {got:?}, expected ({from}, 0)"),
        );
        step(res.abs());
        let got = state();
        report.expect(
            EncMotion,
            matches!(got, (Ok(p), Ok(1)) if p == from),
            || format!("one full turn forward gave {got:?}, expected ({from}, 1)"),
        );
    }

    if let (Ok(p), Ok(t)) = original {
        let _ = dev.set_turn(t);
        let _ = dev.set_position(p);
    }
    report
}
