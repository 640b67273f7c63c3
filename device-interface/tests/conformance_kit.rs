//! The conformance kit must pass a correct device and reject broken ones.
//!
//! `Double` is an in-memory device built from the crate's own building blocks; a `Bug` makes
//! it break one part of the contract. Each broken double must fail exactly the rule that
//! covers its bug — proof that the kit can fail, and that it blames the right rule.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::bits::{BitImage, BitSpan};
use device_interface::conformance::{self, Report, Rule};
use device_interface::encoder::EncoderCounter;
use device_interface::time::Timestamp;
use device_interface::{
    AnalogIn, AnalogOut, Device, DeviceError, DigitalIn, DigitalOut, Encoder, Health, Interface,
    RawRange, Scale, Status, Unit,
};
use std::sync::atomic::{AtomicI64, Ordering};

#[derive(Clone, Copy, PartialEq, Debug)]
enum Bug {
    None,
    // AnalogIn
    AiNoChannels,
    AiOutOfRangeReadsZero,
    AiRangeDisagreesWithScale,
    AiResolutionPerStepCount,
    AiReadOffset,
    AiStimulusIgnored,
    // AnalogOut
    AoNoChannels,
    AoRawRangeDisagreesWithScale,
    AoResolutionZero,
    AoScaleAcceptsAnyChannel,
    AoLowestOffByOne,
    AoTruncates,
    AoClamps,
    // DigitalIn
    DiNoInputs,
    DiOutOfRangeReadsFalse,
    DiIsOffSameAsIsOn,
    DiSequenceReversed,
    DiStimulusIgnored,
    // DigitalOut
    DoNoOutputs,
    DoOutOfRangeAccepted,
    DoSetClobbersNeighbour,
    DoSequenceIgnoresStart,
    DoSequenceTruncates,
    // Encoder
    EncZeroResolution,
    EncSetPositionOffByOne,
    EncSetTurnResetsPosition,
    EncAcceptsResolution,
    EncWrongDirection,
}

struct Double {
    bug: Bug,
    ai_scale: Scale,
    ai: Vec<AtomicI64>,
    ao_scale: Scale,
    ao: Vec<AtomicI64>,
    di: BitImage,
    dout: BitImage,
    enc: EncoderCounter,
}

impl Double {
    fn new(bug: Bug) -> Self {
        let unit = Unit::new("V").unwrap();
        Double {
            bug,
            ai_scale: Scale::linear(RawRange::unsigned_bits(12).unwrap(), -10.0, 10.0, unit)
                .unwrap(),
            ai: (0..3).map(|_| AtomicI64::new(1234)).collect(),
            ao_scale: Scale::linear(RawRange::signed_bits(10).unwrap(), 0.0, 5.0, unit).unwrap(),
            ao: (0..2).map(|_| AtomicI64::new(0)).collect(),
            di: BitImage::new(70),
            dout: BitImage::new(70),
            enc: EncoderCounter::new(-500, false).unwrap(),
        }
    }

    fn ai_chan(&self, c: u32) -> Result<usize, DeviceError> {
        let count = AnalogIn::channel_count(self);
        if c < count {
            Ok(c as usize)
        } else {
            Err(DeviceError::ChannelOutOfRange { channel: c, count })
        }
    }

    fn ao_chan(&self, c: u32) -> Result<usize, DeviceError> {
        let count = AnalogOut::channel_count(self);
        if c < count {
            Ok(c as usize)
        } else {
            Err(DeviceError::ChannelOutOfRange { channel: c, count })
        }
    }

    fn report(bug: Bug, interface: Interface) -> Report {
        let d = Double::new(bug);
        match interface {
            Interface::AnalogIn => {
                let mut stim = |c: u32, raw: i64| {
                    if bug != Bug::AiStimulusIgnored {
                        d.ai[c as usize].store(raw, Ordering::SeqCst);
                    }
                };
                conformance::check_analog_in(&d, Some(&mut stim))
            }
            Interface::AnalogOut => conformance::check_analog_out(&d),
            Interface::DigitalIn => {
                let mut stim = |b: u32, v: bool| {
                    if bug != Bug::DiStimulusIgnored {
                        d.di.set(b, v).unwrap();
                    }
                };
                conformance::check_digital_in(&d, Some(&mut stim))
            }
            Interface::DigitalOut => conformance::check_digital_out(&d),
            Interface::Encoder => {
                let mut motion = |n: i64| d.enc.advance(n);
                conformance::check_encoder(&d, Some(&mut motion))
            }
            // The axis check runs on a rig that moves: drivers/sim/tests/axis.rs.
            Interface::Sensor | Interface::Drive | Interface::Axis => {
                panic!("no physical double for {interface}")
            }
        }
    }
}

impl Device for Double {
    fn health(&self) -> Health {
        Health {
            status: Status::Online,
            last_good: Some(Timestamp::ZERO),
            checked_at: Timestamp::ZERO,
            last_error: None,
        }
    }
}

impl AnalogIn for Double {
    fn channel_count(&self) -> u32 {
        if self.bug == Bug::AiNoChannels {
            0
        } else {
            self.ai.len() as u32
        }
    }

    fn scale(&self, c: u32) -> Result<Scale, DeviceError> {
        self.ai_chan(c).map(|_| self.ai_scale)
    }

    fn read_raw(&self, c: u32) -> Result<i64, DeviceError> {
        if self.bug == Bug::AiOutOfRangeReadsZero && c >= self.ai.len() as u32 {
            return Ok(0);
        }
        Ok(self.ai[self.ai_chan(c)?].load(Ordering::SeqCst))
    }

    fn read(&self, c: u32) -> Result<f64, DeviceError> {
        let v = self.ai_scale.to_physical(self.read_raw(c)?);
        Ok(if self.bug == Bug::AiReadOffset {
            v + 0.5
        } else {
            v
        })
    }

    fn range(&self, c: u32) -> Result<device_interface::AnalogRange, DeviceError> {
        let mut r = AnalogIn::scale(self, c)?.range();
        if self.bug == Bug::AiRangeDisagreesWithScale {
            r.highest = 5.0;
        }
        Ok(r)
    }

    fn resolution(&self, c: u32) -> Result<f64, DeviceError> {
        let s = AnalogIn::scale(self, c)?;
        Ok(if self.bug == Bug::AiResolutionPerStepCount {
            // A classic mistake: dividing by the number of codes, not of steps.
            20.0 / 4096.0
        } else {
            s.resolution()
        })
    }
}

impl AnalogOut for Double {
    fn channel_count(&self) -> u32 {
        if self.bug == Bug::AoNoChannels {
            0
        } else {
            self.ao.len() as u32
        }
    }

    fn raw_range(&self, c: u32) -> Result<RawRange, DeviceError> {
        let r = AnalogOut::scale(self, c)?.raw_range();
        Ok(if self.bug == Bug::AoRawRangeDisagreesWithScale {
            RawRange { min: 0, max: r.max }
        } else {
            r
        })
    }

    fn resolution(&self, c: u32) -> Result<f64, DeviceError> {
        let r = AnalogOut::scale(self, c)?.resolution();
        Ok(if self.bug == Bug::AoResolutionZero {
            0.0
        } else {
            r
        })
    }

    fn scale(&self, c: u32) -> Result<Scale, DeviceError> {
        if self.bug == Bug::AoScaleAcceptsAnyChannel {
            return Ok(self.ao_scale);
        }
        self.ao_chan(c).map(|_| self.ao_scale)
    }

    fn write_raw(&self, c: u32, raw: i64) -> Result<(), DeviceError> {
        let i = self.ao_chan(c)?;
        let r = self.ao_scale.raw_range();
        let raw = if self.bug == Bug::AoClamps {
            r.clamp(raw)
        } else if !r.contains(raw) {
            return Err(DeviceError::RawOutOfRange {
                channel: c,
                raw,
                min: r.min,
                max: r.max,
            });
        } else {
            raw
        };
        self.ao[i].store(raw, Ordering::SeqCst);
        Ok(())
    }

    fn write(&self, c: u32, value: f64) -> Result<(), DeviceError> {
        let s = AnalogOut::scale(self, c)?;
        let range = s.range();
        match self.bug {
            Bug::AoClamps => self.write_raw(c, s.to_raw_saturating(value)),
            Bug::AoTruncates if (range.lowest..=range.highest).contains(&value) => {
                let steps = (value - range.lowest) / s.resolution();
                self.write_raw(c, s.raw_range().min + steps.trunc() as i64)
            }
            Bug::AoLowestOffByOne if value == range.lowest => {
                self.write_raw(c, s.raw_range().min + 1)
            }
            _ => {
                let raw = s.to_raw(value).ok_or(DeviceError::ValueOutOfRange {
                    channel: c,
                    value,
                    lowest: range.lowest,
                    highest: range.highest,
                })?;
                self.write_raw(c, raw)
            }
        }
    }

    fn read_back_raw(&self, c: u32) -> Result<i64, DeviceError> {
        Ok(self.ao[self.ao_chan(c)?].load(Ordering::SeqCst))
    }
}

impl DigitalIn for Double {
    fn input_count(&self) -> u32 {
        if self.bug == Bug::DiNoInputs {
            0
        } else {
            self.di.len()
        }
    }

    fn read_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        if self.bug == Bug::DiOutOfRangeReadsFalse && bit >= self.di.len() {
            return Ok(false);
        }
        self.di.get(bit)
    }

    fn is_off(&self, bit: u32) -> Result<bool, DeviceError> {
        if self.bug == Bug::DiIsOffSameAsIsOn {
            return self.read_bit(bit);
        }
        self.read_bit(bit).map(|v| !v)
    }

    fn read_sequence(&self, start: u32, stop: u32) -> Result<u64, DeviceError> {
        let span = BitSpan::new(start, stop, self.di.len())?;
        let v = self.di.read_span(span);
        Ok(if self.bug == Bug::DiSequenceReversed {
            v.reverse_bits() >> (64 - span.width())
        } else {
            v
        })
    }
}

impl DigitalOut for Double {
    fn output_count(&self) -> u32 {
        if self.bug == Bug::DoNoOutputs {
            0
        } else {
            self.dout.len()
        }
    }

    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        if self.bug == Bug::DoOutOfRangeAccepted && bit >= self.dout.len() {
            return Ok(());
        }
        self.dout.set(bit, value)?;
        if self.bug == Bug::DoSetClobbersNeighbour && bit + 1 < self.dout.len() {
            self.dout.set(bit + 1, false)?;
        }
        Ok(())
    }

    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.dout.get(bit)
    }

    fn set_sequence(&self, start: u32, stop: u32, value: u64) -> Result<(), DeviceError> {
        let span = BitSpan::new(start, stop, self.dout.len())?;
        match self.bug {
            Bug::DoSequenceIgnoresStart => {
                let from0 = BitSpan::new(0, span.width() - 1, self.dout.len())?;
                self.dout.write_span(from0, value)
            }
            Bug::DoSequenceTruncates => self.dout.write_span(span, value & span.mask()),
            _ => self.dout.write_span(span, value),
        }
    }

    fn check_sequence(&self, start: u32, stop: u32) -> Result<u64, DeviceError> {
        Ok(self
            .dout
            .read_span(BitSpan::new(start, stop, self.dout.len())?))
    }
}

impl Encoder for Double {
    fn position(&self) -> Result<i64, DeviceError> {
        Ok(self.enc.position())
    }

    fn turn(&self) -> Result<i64, DeviceError> {
        Ok(self.enc.turn())
    }

    fn set_position(&self, p: i64) -> Result<(), DeviceError> {
        match self.bug {
            Bug::EncSetPositionOffByOne => self.enc.set_position(p / 2),
            Bug::EncAcceptsResolution if p == Encoder::resolution(self) => self.enc.set_position(0),
            _ => self.enc.set_position(p),
        }
    }

    fn set_turn(&self, t: i64) -> Result<(), DeviceError> {
        if self.bug == Bug::EncSetTurnResetsPosition {
            self.enc.set_position(0)?;
        }
        self.enc.set_turn(t)
    }

    fn resolution(&self) -> i64 {
        if self.bug == Bug::EncZeroResolution {
            0
        } else {
            self.enc.geometry().resolution()
        }
    }

    fn upcounting(&self) -> bool {
        self.enc.geometry().upcounting() != (self.bug == Bug::EncWrongDirection)
    }
}

#[test]
fn a_correct_device_passes_every_rule() {
    for interface in Interface::ALL {
        let report = Double::report(Bug::None, interface);
        report.assert_complete();
        for o in report.outcomes() {
            assert!(o.checks > 0, "{:?} ran no checks", o.rule);
        }
    }
}

#[test]
fn without_a_stimulus_the_stimulus_rules_are_reported_not_run() {
    let d = Double::new(Bug::None);
    let r = conformance::check_analog_in(&d, None);
    r.assert_pass();
    assert_eq!(r.not_run(), vec![Rule::AiStimulus]);
    assert_eq!(
        conformance::check_digital_in(&d, None).not_run(),
        vec![Rule::DiStimulus]
    );
    assert_eq!(
        conformance::check_encoder(&d, None).not_run(),
        vec![Rule::EncMotion]
    );
    let text = r.to_string();
    assert!(text.contains("AiStimulus: not run (no stimulus)"), "{text}");
}

#[test]
fn every_broken_double_is_rejected_for_the_right_rule() {
    use Bug::*;
    use Interface as I;
    // (bug, interface checked, the rule that must fail, other rules allowed to fail too)
    let cases: &[(Bug, Interface, Rule, &[Rule])] = &[
        (AiNoChannels, I::AnalogIn, Rule::AiChannels, &[]),
        (AiOutOfRangeReadsZero, I::AnalogIn, Rule::AiOutOfRange, &[]),
        (AiRangeDisagreesWithScale, I::AnalogIn, Rule::AiRange, &[]),
        (
            AiResolutionPerStepCount,
            I::AnalogIn,
            Rule::AiResolution,
            &[],
        ),
        (
            AiReadOffset,
            I::AnalogIn,
            Rule::AiConversion,
            &[Rule::AiStimulus],
        ),
        (AiStimulusIgnored, I::AnalogIn, Rule::AiStimulus, &[]),
        (AoNoChannels, I::AnalogOut, Rule::AoChannels, &[]),
        (
            AoRawRangeDisagreesWithScale,
            I::AnalogOut,
            Rule::AoRange,
            &[],
        ),
        (AoResolutionZero, I::AnalogOut, Rule::AoResolution, &[]),
        (
            AoScaleAcceptsAnyChannel,
            I::AnalogOut,
            Rule::AoOutOfRange,
            &[],
        ),
        (
            AoLowestOffByOne,
            I::AnalogOut,
            Rule::AoEndpoints,
            &[Rule::AoReadBack],
        ),
        (
            AoTruncates,
            I::AnalogOut,
            Rule::AoReadBack,
            &[Rule::AoEndpoints],
        ),
        (AoClamps, I::AnalogOut, Rule::AoRefusal, &[]),
        (
            DiNoInputs,
            I::DigitalIn,
            Rule::DiInputs,
            &[Rule::DiOutOfRange],
        ),
        (
            DiOutOfRangeReadsFalse,
            I::DigitalIn,
            Rule::DiOutOfRange,
            &[],
        ),
        (DiIsOffSameAsIsOn, I::DigitalIn, Rule::DiOnOff, &[]),
        (
            DiSequenceReversed,
            I::DigitalIn,
            Rule::DiSequence,
            &[Rule::DiStimulus],
        ),
        (DiStimulusIgnored, I::DigitalIn, Rule::DiStimulus, &[]),
        (
            DoNoOutputs,
            I::DigitalOut,
            Rule::DoOutputs,
            &[Rule::DoOutOfRange],
        ),
        (DoOutOfRangeAccepted, I::DigitalOut, Rule::DoOutOfRange, &[]),
        (DoSetClobbersNeighbour, I::DigitalOut, Rule::DoSetCheck, &[]),
        (DoSequenceIgnoresStart, I::DigitalOut, Rule::DoSequence, &[]),
        (
            DoSequenceTruncates,
            I::DigitalOut,
            Rule::DoSequenceTooWide,
            &[],
        ),
        (EncZeroResolution, I::Encoder, Rule::EncResolution, &[]),
        (
            EncSetPositionOffByOne,
            I::Encoder,
            Rule::EncPositionSetGet,
            &[
                Rule::EncTurnSetGet,
                Rule::EncMotion,
                Rule::EncPositionRejected,
            ],
        ),
        (
            EncSetTurnResetsPosition,
            I::Encoder,
            Rule::EncTurnSetGet,
            &[Rule::EncMotion],
        ),
        (
            EncAcceptsResolution,
            I::Encoder,
            Rule::EncPositionRejected,
            &[],
        ),
        (EncWrongDirection, I::Encoder, Rule::EncMotion, &[]),
    ];
    for &(bug, interface, rule, also) in cases {
        let report = Double::report(bug, interface);
        let failed = report.failed();
        assert!(
            failed.contains(&rule),
            "{bug:?}: {rule:?} should fail\n{report}"
        );
        for f in &failed {
            assert!(
                *f == rule || also.contains(f),
                "{bug:?}: unexpected failure of {f:?}\n{report}"
            );
        }
    }
    // Every rule of every interface is covered by at least one broken double.
    for interface in Interface::ALL {
        for rule in Rule::for_interface(interface) {
            assert!(
                cases.iter().any(|c| c.2 == *rule),
                "no broken double for {rule:?}"
            );
        }
    }
}
