//! Signal layout, extraction, insertion and scaling against worked examples and a
//! bit-by-bit reference.

use super::*;

fn sig(start: u32, len: u32, order: ByteOrder, signed: bool) -> Signal {
    Signal::new(start, len, order, signed, 1.0, 0.0, "").unwrap()
}

#[test]
fn intel_bits() {
    assert_eq!(
        sig(0, 16, ByteOrder::Intel, false)
            .extract(&[0x34, 0x12])
            .unwrap(),
        0x1234
    );
    // 12 bits from bit 4: the high nibble of byte 0 and all of byte 1.
    assert_eq!(
        sig(4, 12, ByteOrder::Intel, false)
            .extract(&[0xA0, 0xBC])
            .unwrap(),
        0xBCA
    );
    assert_eq!(
        sig(8, 12, ByteOrder::Intel, true)
            .extract(&[0x00, 0xFF, 0x0F])
            .unwrap(),
        -1
    );
    assert_eq!(
        sig(0, 64, ByteOrder::Intel, false)
            .extract(&[1, 0, 0, 0, 0, 0, 0, 0x80])
            .unwrap(),
        i64::MIN + 1,
        "all 64 bits"
    );
}

#[test]
fn motorola_bits() {
    assert_eq!(
        sig(7, 16, ByteOrder::Motorola, false)
            .extract(&[0x12, 0x34])
            .unwrap(),
        0x1234
    );
    // MSB at bit 4 of byte 0: five bits of byte 0, then bits 7..5 of byte 1.
    assert_eq!(
        sig(4, 8, ByteOrder::Motorola, false)
            .extract(&[0x1F, 0xE0])
            .unwrap(),
        0xFF
    );
    assert_eq!(
        sig(4, 8, ByteOrder::Motorola, false)
            .extract(&[0x10, 0x00])
            .unwrap(),
        0x80
    );
    assert_eq!(
        sig(23, 12, ByteOrder::Motorola, true)
            .extract(&[0, 0, 0x80, 0x00])
            .unwrap(),
        -2048
    );
    assert_eq!(sig(7, 8, ByteOrder::Motorola, false).bytes_needed(), 1);
    assert_eq!(sig(4, 8, ByteOrder::Motorola, false).bytes_needed(), 2);
}

#[test]
fn physical_values_use_factor_and_offset() {
    let rpm = Signal::new(24, 16, ByteOrder::Intel, false, 0.25, 0.0, "rpm").unwrap();
    assert_eq!(rpm.decode(&[0, 0, 0, 0x40, 0x1F, 0, 0, 0]).unwrap(), 2000.0);
    let temp = Signal::new(0, 8, ByteOrder::Intel, true, 0.5, -10.0, "degC").unwrap();
    assert_eq!(temp.decode(&[0xF6]).unwrap(), -15.0, "raw -10");
    assert_eq!(temp.scale().range().unit.as_str(), "degC");
}

#[test]
fn insert_is_extracts_inverse_and_leaves_other_bits() {
    let mut seed = 0x9E37_79B9_u64;
    let mut next = |m: u64| {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 33) % m
    };
    for _ in 0..2000 {
        let order = if next(2) == 0 {
            ByteOrder::Intel
        } else {
            ByteOrder::Motorola
        };
        let length = 1 + next(64) as u32;
        let signed = next(2) == 0 && length > 1;
        let start = next(64) as u32;
        let Ok(s) = Signal::new(start, length, order, signed, 1.0, 0.0, "") else {
            continue;
        };
        let mut payload = vec![0u8; s.bytes_needed()];
        for b in payload.iter_mut() {
            *b = next(256) as u8;
        }
        let before = payload.clone();
        let r = s.scale().raw_range();
        let span = (r.max as i128 - r.min as i128 + 1).min(1 << 62) as u64;
        let raw = (r.min as i128 + i128::from(next(span))) as i64;
        s.insert(&mut payload, raw).unwrap();
        assert_eq!(
            s.extract(&payload).unwrap(),
            raw,
            "{order:?} start {start} len {length} signed {signed}"
        );
        for (i, (a, b)) in before.iter().zip(&payload).enumerate() {
            let mine: u8 = s
                .bits
                .iter()
                .filter(|&&bit| (bit / 8) as usize == i)
                .fold(0, |m, bit| m | 1 << (bit % 8));
            assert_eq!(a & !mine, b & !mine, "other bits of byte {i} untouched");
        }
    }
}

#[test]
fn limits_narrow_the_raw_range() {
    let s = Signal::new(0, 16, ByteOrder::Intel, true, 0.1, 0.0, "Nm").unwrap();
    let l = s.clone().with_limits(-100.0, 250.5).unwrap();
    assert_eq!(
        l.scale().raw_range(),
        RawRange {
            min: -1000,
            max: 2505
        }
    );
    // Negative factor: the limits swap ends in raw.
    let n = Signal::new(0, 8, ByteOrder::Intel, false, -0.5, 100.0, "").unwrap();
    let n = n.with_limits(0.0, 50.0).unwrap();
    assert_eq!(n.scale().raw_range(), RawRange { min: 100, max: 200 });
    // 0|0 is "no limits"; limits past the raw range keep it.
    assert_eq!(s.clone().with_limits(0.0, 0.0).unwrap(), s);
    let w = s.clone().with_limits(-1e9, 1e9).unwrap();
    assert_eq!(w.scale().raw_range(), s.scale().raw_range());
    assert!(matches!(
        s.clone().with_limits(5.0, 1.0),
        Err(SignalError::Limits { .. })
    ));
    assert!(matches!(
        s.clone().with_limits(1e9, 2e9),
        Err(SignalError::Limits { .. })
    ));
    // One raw value in range (a constant signal, [5|5]): taken, and checked.
    let one = sig(0, 8, ByteOrder::Intel, false)
        .with_limits(5.0, 5.0)
        .unwrap();
    assert!(one.in_range(5));
    assert!(!one.in_range(6));
    assert_eq!(one.raw_of(5.0), Some(5));
    assert_eq!(one.raw_of(6.0), None);
}

#[test]
fn bad_signals_and_short_frames() {
    assert_eq!(
        Signal::new(0, 0, ByteOrder::Intel, false, 1.0, 0.0, "").unwrap_err(),
        SignalError::Length(0)
    );
    assert_eq!(
        Signal::new(0, 65, ByteOrder::Intel, false, 1.0, 0.0, "").unwrap_err(),
        SignalError::Length(65)
    );
    assert!(
        Signal::new(0, 8, ByteOrder::Intel, false, 0.0, 0.0, "").is_err(),
        "zero factor"
    );
    let s = sig(60, 8, ByteOrder::Intel, false);
    assert_eq!(
        s.extract(&[0; 8]).unwrap_err().to_string(),
        "the signal needs 9 bytes of payload, the frame has 8"
    );
    let mut p = [0u8; 2];
    assert_eq!(
        sig(0, 4, ByteOrder::Intel, false)
            .insert(&mut p, 16)
            .unwrap_err()
            .to_string(),
        "raw value 16 does not fit 4 unsigned bits"
    );
    assert!(sig(0, 4, ByteOrder::Intel, true).insert(&mut p, -8).is_ok());
    assert!(sig(0, 4, ByteOrder::Intel, true).insert(&mut p, 8).is_err());
}

/// The value of `s` in `payload` bit by bit, from the bit list: the reference the
/// byte-window reading is checked against.
fn extract_bitwise(s: &Signal, payload: &[u8]) -> u64 {
    s.bits.iter().fold(0u64, |v, &b| {
        (v << 1) | u64::from(payload[(b / 8) as usize] >> (b % 8) & 1)
    })
}

#[test]
fn byte_windows_read_and_write_as_the_bits_say() {
    // Every start and length in a 64-byte FD payload, both byte orders, random payloads:
    // extraction equals the bit-by-bit reading; insertion changes exactly the signal's bits.
    let mut seed = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    };
    let mut checked = 0;
    for order in [ByteOrder::Intel, ByteOrder::Motorola] {
        for start in 0..512 {
            for length in 1..=64 {
                let Ok(s) = Signal::new(start, length, order, false, 1.0, 0.0, "") else {
                    continue;
                };
                if s.bytes_needed() > 64 {
                    continue;
                }
                let mut payload = [0u8; 64];
                payload.iter_mut().for_each(|b| *b = next() as u8);
                let raw = s.extract(&payload).unwrap() as u64;
                assert_eq!(
                    raw,
                    extract_bitwise(&s, &payload),
                    "{order:?} {start}|{length}"
                );
                let before = payload;
                let v = next() & (u64::MAX >> (64 - length));
                let v = if length == 64 {
                    v & (i64::MAX as u64)
                } else {
                    v
                };
                s.insert(&mut payload, v as i64).unwrap();
                assert_eq!(
                    extract_bitwise(&s, &payload),
                    v,
                    "{order:?} {start}|{length}"
                );
                let mut mine = [false; 512];
                s.bits.iter().for_each(|&b| mine[b as usize] = true);
                for bit in 0..512u32 {
                    if !mine[bit as usize] {
                        let (byte, k) = ((bit / 8) as usize, bit % 8);
                        assert_eq!(
                            payload[byte] >> k & 1,
                            before[byte] >> k & 1,
                            "{order:?} {start}|{length}: bit {bit} changed"
                        );
                    }
                }
                checked += 1;
            }
        }
    }
    assert!(checked > 40_000, "{checked}");
}

#[test]
fn values_at_the_ends_of_their_types_are_written_and_read_back() {
    // An unsigned 64-bit counter above 2^63 − 1, and with an integral offset: exact.
    let total = Signal::new(0, 64, ByteOrder::Intel, false, 1.0, 0.0, "m").unwrap();
    let top = 1.8e19;
    let bits = total.raw_of(top).unwrap();
    assert_eq!(bits as u64, 18_000_000_000_000_000_000);
    assert_eq!(total.physical(bits), top);
    assert_eq!(total.raw_of(2f64.powi(64)), None, "beyond 2^64 − 1");
    let shifted = Signal::new(0, 64, ByteOrder::Intel, true, 1.0, 100.0, "").unwrap();
    assert_eq!(
        shifted.physical(-5_739_657_946_639_245_890),
        -5_739_657_946_639_245_790f64,
        "signed: raw + 100 exactly, then rounded once"
    );
    // Floats: any finite value of the type, scaled.
    let f = Signal::new(0, 32, ByteOrder::Intel, false, 2.0, 0.0, "")
        .unwrap()
        .with_kind(ValueKind::Float32)
        .unwrap();
    let big = f64::from(f32::MAX) * 2.0;
    assert_eq!(f.physical(f.raw_of(big).unwrap()), big);
    assert_eq!(f.raw_of(big * 1.01), None, "beyond the float's range");
    let d = Signal::new(0, 64, ByteOrder::Intel, false, 1.0, 0.0, "")
        .unwrap()
        .with_kind(ValueKind::Float64)
        .unwrap();
    let half = 2f64.powi(1023) * (1.0 - f64::EPSILON);
    assert_eq!(d.physical(d.raw_of(half).unwrap()), half);
    assert_eq!(d.raw_of(f64::MAX), None, "a double's scale ends at 2^1023");
    assert_eq!(d.raw_of(f64::NAN), None);
    assert_eq!(d.physical(i64::MIN), -0.0, "-0.0 is the float itself");
    assert!(d.physical(i64::MIN).is_sign_negative());
}

#[test]
fn the_ends_of_the_advertised_ranges_are_writable() {
    for (kind, length) in [(ValueKind::Float32, 32), (ValueKind::Float64, 64)] {
        for (factor, offset) in [(1.0, 0.0), (2.0, 0.0), (0.5, -40.0), (1e-3, 1e6)] {
            let s = Signal::new(0, length, ByteOrder::Intel, false, factor, offset, "")
                .unwrap()
                .with_kind(kind)
                .unwrap();
            let r = s.scale().range();
            let raw = s.scale().raw_range();
            for v in [
                r.lowest,
                r.highest,
                s.scale().to_physical(raw.min),
                s.scale().to_physical(raw.max),
            ] {
                assert!(
                    s.raw_of(v).is_some(),
                    "{kind:?} factor {factor} offset {offset}: {v} is in [{}, {}]",
                    r.lowest,
                    r.highest
                );
            }
        }
    }
    // The unsigned 64-bit boundary: 2^63 is the unsigned value's bits, not i64::MAX.
    let u = Signal::new(0, 64, ByteOrder::Intel, false, 1.0, 0.0, "").unwrap();
    assert_eq!(u.raw_of(2f64.powi(63)).map(|b| b as u64), Some(1 << 63));
    let u2 = Signal::new(0, 64, ByteOrder::Intel, false, 2.0, 0.0, "").unwrap();
    assert_eq!(u2.raw_of(2f64.powi(64)).map(|b| b as u64), Some(1 << 63));
}

#[test]
fn the_physical_value_is_the_scales() {
    // Beyond 2^53, where one rounding and two differ: read() and scale() agree.
    let s = Signal::new(0, 64, ByteOrder::Intel, true, 1.0, 259.0, "").unwrap();
    for raw in [-3_074_457_345_618_258_603, i64::MIN, i64::MAX, 0, 1 << 60] {
        assert_eq!(s.physical(raw), s.scale().to_physical(raw), "raw {raw}");
    }
    let t = Signal::new(0, 64, ByteOrder::Intel, true, 3.0, 0.5, "").unwrap();
    for raw in [i64::MIN / 3, (1 << 55) + 1] {
        assert_eq!(t.physical(raw), t.scale().to_physical(raw), "raw {raw}");
    }
}
