//! The request side of Modbus as hwgw's server reads it: a request PDU checked field by
//! field against the Modbus Application Protocol specification (v1.1b3, §6) before
//! anything acts on it, and the reply PDU encoded. No third-party decoder sees a client's
//! bytes, so no request can panic the server (tokio-modbus 0.17's server decoder indexes
//! out of bounds on FC15 with a quantity above 8 × its byte count, and overflows on FC16
//! with a quantity of 0x8000 or more).
//!
//! | function | checked | exception |
//! |---|---|---|
//! | 1, 2 read bits | 1 ≤ quantity ≤ 2000; address + quantity ≤ 65536 | 03; 02 |
//! | 3, 4 read registers | 1 ≤ quantity ≤ 125; address + quantity ≤ 65536 | 03; 02 |
//! | 5 write coil | value 0x0000 or 0xFF00 | 03 |
//! | 6 write register | — | — |
//! | 15 write coils | 1 ≤ quantity ≤ 1968; byte count = ⌈quantity / 8⌉ = bytes present | 03 |
//! | 16 write registers | 1 ≤ quantity ≤ 123; byte count = 2 × quantity = bytes present | 03 |
//! | any other | — | 01 |
//!
//! A PDU of the wrong length for its function is answered 03 (illegal data value).

/// The most coils one FC15 request writes (its byte count is one byte: 246 bytes of data
/// fit the 253-byte PDU).
pub const MAX_WRITE_COILS: u16 = 1968;
/// The most registers one FC16 request writes.
pub const MAX_WRITE_REGISTERS: u16 = 123;

/// Exception codes hwgw answers with.
pub mod exception {
    /// The function is not served.
    pub const ILLEGAL_FUNCTION: u8 = 0x01;
    /// An address the table does not have (or part of a multi-register value).
    pub const ILLEGAL_DATA_ADDRESS: u8 = 0x02;
    /// A quantity, byte count or value the request may not have; a value the device
    /// refuses.
    pub const ILLEGAL_DATA_VALUE: u8 = 0x03;
    /// The device behind the address is offline or stale, or failed; a write it took
    /// was refused on its way.
    pub const SERVER_DEVICE_FAILURE: u8 = 0x04;
    /// The server has no path to the unit the request is for (a gateway's unit not
    /// configured, or its line's queue full).
    pub const GATEWAY_PATH_UNAVAILABLE: u8 = 0x0A;
    /// A write taken by a device that a bus carries later (a Modbus unit behind hwgw's
    /// client, another gateway's output) got no answer from its target: the target is
    /// offline, or the write was still on its way when the server stopped waiting.
    pub const GATEWAY_TARGET_FAILED_TO_RESPOND: u8 = 0x0B;
}

/// A checked request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Req {
    /// FC1 or FC2: `count` bits from `start` of the coils or discrete inputs.
    ReadBits {
        /// 1 (coils) or 2 (discrete inputs).
        function: u8,
        /// First address.
        start: u16,
        /// 1–2000.
        count: u16,
    },
    /// FC3 or FC4: `count` registers from `start`.
    ReadRegisters {
        /// 3 (holding) or 4 (input).
        function: u8,
        /// First address.
        start: u16,
        /// 1–125.
        count: u16,
    },
    /// FC5.
    WriteCoil {
        /// The coil.
        address: u16,
        /// On (0xFF00) or off (0x0000).
        on: bool,
    },
    /// FC6.
    WriteRegister {
        /// The register.
        address: u16,
        /// Its value.
        value: u16,
    },
    /// FC15.
    WriteCoils {
        /// First coil.
        start: u16,
        /// Their values (1–1968).
        values: Vec<bool>,
    },
    /// FC16.
    WriteRegisters {
        /// First register.
        start: u16,
        /// Their values (1–123).
        values: Vec<u16>,
    },
}

/// A reply.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Resp {
    /// To FC1/FC2: the bits.
    Bits(u8, Vec<bool>),
    /// To FC3/FC4: the registers.
    Registers(u8, Vec<u16>),
    /// To FC5/FC6: the request echoed (function, address, value as sent).
    Echo(u8, u16, u16),
    /// To FC15/FC16: function, start, quantity.
    Written(u8, u16, u16),
}

/// A refusal: the function and the exception code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Refusal {
    /// The request's function code.
    pub function: u8,
    /// The exception code.
    pub code: u8,
}

fn word(b: &[u8], at: usize) -> u16 {
    u16::from_be_bytes([b[at], b[at + 1]])
}

/// Checks and reads a request PDU (function code first).
pub fn parse(pdu: &[u8]) -> Result<Req, Refusal> {
    let Some(&function) = pdu.first() else {
        return Err(Refusal {
            function: 0,
            code: exception::ILLEGAL_FUNCTION,
        });
    };
    let refuse = |code| Refusal { function, code };
    let value = || refuse(exception::ILLEGAL_DATA_VALUE);
    let fixed = |len: usize| {
        if pdu.len() == len {
            Ok(())
        } else {
            Err(value())
        }
    };
    match function {
        1..=4 => {
            fixed(5)?;
            let (start, count) = (word(pdu, 1), word(pdu, 3));
            let max = if function <= 2 { 2000 } else { 125 };
            if count == 0 || count > max {
                return Err(value());
            }
            if u32::from(start) + u32::from(count) > 65536 {
                return Err(refuse(exception::ILLEGAL_DATA_ADDRESS));
            }
            Ok(if function <= 2 {
                Req::ReadBits {
                    function,
                    start,
                    count,
                }
            } else {
                Req::ReadRegisters {
                    function,
                    start,
                    count,
                }
            })
        }
        5 => {
            fixed(5)?;
            match word(pdu, 3) {
                0xFF00 => Ok(Req::WriteCoil {
                    address: word(pdu, 1),
                    on: true,
                }),
                0x0000 => Ok(Req::WriteCoil {
                    address: word(pdu, 1),
                    on: false,
                }),
                _ => Err(value()),
            }
        }
        6 => {
            fixed(5)?;
            Ok(Req::WriteRegister {
                address: word(pdu, 1),
                value: word(pdu, 3),
            })
        }
        15 | 16 => {
            if pdu.len() < 6 {
                return Err(value());
            }
            let (start, count, bytes) = (word(pdu, 1), word(pdu, 3), usize::from(pdu[5]));
            let (max, need) = if function == 15 {
                (MAX_WRITE_COILS, usize::from(count).div_ceil(8))
            } else {
                (MAX_WRITE_REGISTERS, 2 * usize::from(count))
            };
            if count == 0 || count > max || bytes != need || pdu.len() != 6 + bytes {
                return Err(value());
            }
            if u32::from(start) + u32::from(count) > 65536 {
                return Err(refuse(exception::ILLEGAL_DATA_ADDRESS));
            }
            let data = &pdu[6..];
            Ok(if function == 15 {
                Req::WriteCoils {
                    start,
                    values: (0..usize::from(count))
                        .map(|i| data[i / 8] >> (i % 8) & 1 == 1)
                        .collect(),
                }
            } else {
                Req::WriteRegisters {
                    start,
                    values: (0..usize::from(count)).map(|i| word(data, 2 * i)).collect(),
                }
            })
        }
        _ => Err(refuse(exception::ILLEGAL_FUNCTION)),
    }
}

/// Appends the reply PDU of `resp` to `out`.
pub fn encode(resp: &Resp, out: &mut Vec<u8>) {
    match resp {
        Resp::Bits(f, bits) => {
            let bytes = bits.len().div_ceil(8);
            out.push(*f);
            out.push(bytes as u8);
            let at = out.len();
            out.resize(at + bytes, 0);
            for (i, b) in bits.iter().enumerate() {
                out[at + i / 8] |= u8::from(*b) << (i % 8);
            }
        }
        Resp::Registers(f, regs) => {
            out.push(*f);
            out.push((2 * regs.len()) as u8);
            for r in regs {
                out.extend_from_slice(&r.to_be_bytes());
            }
        }
        Resp::Echo(f, a, v) | Resp::Written(f, a, v) => {
            out.push(*f);
            out.extend_from_slice(&a.to_be_bytes());
            out.extend_from_slice(&v.to_be_bytes());
        }
    }
}

/// Appends the exception PDU of `r` to `out`.
pub fn encode_refusal(r: Refusal, out: &mut Vec<u8>) {
    out.push(r.function | 0x80);
    out.push(r.code);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn code(pdu: &[u8]) -> u8 {
        parse(pdu).unwrap_err().code
    }

    #[test]
    fn requests_are_checked_as_the_specification_says() {
        // The two that panic tokio-modbus 0.17's decoder.
        assert_eq!(
            code(&[15, 0, 0, 0, 100, 1, 0xFF]),
            3,
            "FC15 quantity over 8 × bytes"
        );
        assert_eq!(code(&[16, 0, 0, 0x80, 0, 0]), 3, "FC16 quantity 0x8000");
        assert_eq!(code(&[3, 0, 0, 0, 0]), 3, "quantity 0");
        assert_eq!(code(&[3, 0, 0, 0, 126]), 3, "126 registers");
        assert_eq!(code(&[1, 0, 0, 0x07, 0xD1]), 3, "2001 bits");
        assert_eq!(code(&[5, 0, 1, 0x12, 0x34]), 3, "FC5 value");
        assert_eq!(code(&[4, 0xFF, 0xFF, 0, 2]), 2, "past 65535");
        assert_eq!(
            code(&[16, 0, 0, 0, 2, 4, 0, 1]),
            3,
            "fewer bytes than the count"
        );
        assert_eq!(code(&[3, 0, 0]), 3, "short");
        assert_eq!(code(&[43, 14, 1, 0]), 1, "function 43 not served");
        assert_eq!(code(&[]), 1);
        assert_eq!(
            parse(&[15, 0, 2, 0, 10, 2, 0b0000_0101, 0b10]).unwrap(),
            Req::WriteCoils {
                start: 2,
                values: vec![
                    true, false, true, false, false, false, false, false, false, true
                ]
            }
        );
        assert_eq!(
            parse(&[16, 0, 7, 0, 2, 4, 0x12, 0x34, 0xAB, 0xCD]).unwrap(),
            Req::WriteRegisters {
                start: 7,
                values: vec![0x1234, 0xABCD]
            }
        );
        assert_eq!(
            parse(&[3, 0xFF, 0x83, 0, 125]).unwrap(),
            Req::ReadRegisters {
                function: 3,
                start: 65411,
                count: 125
            }
        );
    }

    #[test]
    fn replies_encode() {
        let mut out = Vec::new();
        encode(
            &Resp::Bits(
                1,
                vec![true, false, true, true, false, false, false, false, true],
            ),
            &mut out,
        );
        assert_eq!(out, [1, 2, 0b0000_1101, 1]);
        out.clear();
        encode(&Resp::Registers(4, vec![0x1234, 7]), &mut out);
        assert_eq!(out, [4, 4, 0x12, 0x34, 0, 7]);
        out.clear();
        encode_refusal(
            Refusal {
                function: 3,
                code: 2,
            },
            &mut out,
        );
        assert_eq!(out, [0x83, 2]);
    }
}
