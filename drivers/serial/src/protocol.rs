//! The Firmata protocol (version 2.x, as firmata.org documents it), spoken by hwgw itself:
//! a streaming [`Decoder`] for what a board sends and the encoders of what hwgw sends.
//!
//! Framing: a byte with the top bit set starts a message (its low nibble is a port, pin or
//! channel for the 0x90, 0xE0, 0xC0 and 0xD0 commands); data bytes carry 7 bits each; a
//! sysex message runs from `START_SYSEX` to `END_SYSEX`. The decoder never trusts the line:
//!
//! - data bytes outside a message are skipped until the next command byte (one *resync*
//!   per run of skipped bytes, each skipped byte a *framing error*);
//! - a command byte inside an unfinished message drops what came before it (a truncated
//!   message: a framing error and a resync), and starts anew;
//! - a command hwgw does not know, or a sysex too long for [`MAX_SYSEX`], is counted and
//!   skipped to the next command byte.
//!
//! Decoding allocates nothing: a frame borrows the decoder's sysex buffer, made once.

use serde::Serialize;

/// The longest sysex payload taken (a Mega's capability response is about 1.4 KB).
pub const MAX_SYSEX: usize = 4096;

/// DIGITAL_MESSAGE (| port): 8 pins of a port, two data bytes.
pub const DIGITAL_MESSAGE: u8 = 0x90;
/// ANALOG_MESSAGE (| pin or channel 0–15): a 14-bit value.
pub const ANALOG_MESSAGE: u8 = 0xE0;
/// REPORT_ANALOG (| channel): reporting on (1) or off (0).
pub const REPORT_ANALOG: u8 = 0xC0;
/// REPORT_DIGITAL (| port): reporting on (1) or off (0).
pub const REPORT_DIGITAL: u8 = 0xD0;
/// SET_PIN_MODE pin mode.
pub const SET_PIN_MODE: u8 = 0xF4;
/// SET_DIGITAL_PIN_VALUE pin value (protocol 2.5 and later).
pub const SET_DIGITAL_PIN_VALUE: u8 = 0xF5;
/// REPORT_VERSION: the protocol version (also the query for it).
pub const REPORT_VERSION: u8 = 0xF9;
/// SYSTEM_RESET.
pub const SYSTEM_RESET: u8 = 0xFF;
/// START_SYSEX.
pub const START_SYSEX: u8 = 0xF0;
/// END_SYSEX.
pub const END_SYSEX: u8 = 0xF7;

/// Sysex commands.
pub mod sysex {
    /// ENCODER_DATA (the encoder feature): attach, report, reset; positions back.
    pub const ENCODER_DATA: u8 = 0x61;
    /// ANALOG_MAPPING_QUERY.
    pub const ANALOG_MAPPING_QUERY: u8 = 0x69;
    /// ANALOG_MAPPING_RESPONSE: per pin, its analog channel or 127.
    pub const ANALOG_MAPPING_RESPONSE: u8 = 0x6A;
    /// CAPABILITY_QUERY.
    pub const CAPABILITY_QUERY: u8 = 0x6B;
    /// CAPABILITY_RESPONSE: per pin, (mode, resolution) pairs ended by 127.
    pub const CAPABILITY_RESPONSE: u8 = 0x6C;
    /// PIN_STATE_QUERY pin.
    pub const PIN_STATE_QUERY: u8 = 0x6D;
    /// PIN_STATE_RESPONSE pin mode state….
    pub const PIN_STATE_RESPONSE: u8 = 0x6E;
    /// EXTENDED_ANALOG pin value… (values wider than 14 bits, pins above 15).
    pub const EXTENDED_ANALOG: u8 = 0x6F;
    /// SERVO_CONFIG pin min-pulse max-pulse.
    pub const SERVO_CONFIG: u8 = 0x70;
    /// STRING_DATA: text from the board.
    pub const STRING_DATA: u8 = 0x71;
    /// REPORT_FIRMWARE: major minor name (also the query).
    pub const REPORT_FIRMWARE: u8 = 0x79;
    /// SAMPLING_INTERVAL ms.
    pub const SAMPLING_INTERVAL: u8 = 0x7A;
}

/// Encoder feature subcommands.
pub mod encoder {
    /// ENCODER_ATTACH index pin-a pin-b.
    pub const ATTACH: u8 = 0x00;
    /// ENCODER_RESET_POSITION index.
    pub const RESET_POSITION: u8 = 0x03;
    /// ENCODER_REPORT_AUTO enable.
    pub const REPORT_AUTO: u8 = 0x04;
    /// ENCODER_DETACH index.
    pub const DETACH: u8 = 0x05;
}

/// Pin modes as the capability response and SET_PIN_MODE number them.
pub mod mode {
    /// Digital input.
    pub const INPUT: u8 = 0x00;
    /// Digital output.
    pub const OUTPUT: u8 = 0x01;
    /// Analog input.
    pub const ANALOG: u8 = 0x02;
    /// PWM output.
    pub const PWM: u8 = 0x03;
    /// Servo output.
    pub const SERVO: u8 = 0x04;
    /// Quadrature encoder input (the encoder feature).
    pub const ENCODER: u8 = 0x09;
    /// Digital input with the pull-up on (protocol 2.5 and later).
    pub const PULLUP: u8 = 0x0B;

    /// A mode's name, for errors.
    pub fn name(mode: u8) -> &'static str {
        match mode {
            INPUT => "input",
            OUTPUT => "output",
            ANALOG => "analog",
            PWM => "pwm",
            SERVO => "servo",
            0x05 => "shift",
            0x06 => "i2c",
            0x07 => "onewire",
            0x08 => "stepper",
            ENCODER => "encoder",
            0x0A => "serial",
            PULLUP => "input_pullup",
            _ => "other",
        }
    }
}

/// One message from the board.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Frame<'a> {
    /// REPORT_VERSION: the protocol version.
    Version {
        /// Major.
        major: u8,
        /// Minor.
        minor: u8,
    },
    /// DIGITAL_MESSAGE: the 8 pins of `port`.
    Digital {
        /// The port (pins 8·port … 8·port+7).
        port: u8,
        /// Their levels, pin 8·port in bit 0.
        value: u8,
    },
    /// ANALOG_MESSAGE: a value of analog channel `channel`.
    Analog {
        /// The analog channel (A0 = 0).
        channel: u8,
        /// Its value (14 bits at most).
        value: u16,
    },
    /// A sysex message: its command and its payload's data bytes.
    Sysex {
        /// The sysex command.
        command: u8,
        /// The payload (data bytes, 7 bits each).
        data: &'a [u8],
    },
}

/// The decoder's counts.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct LineCounts {
    /// Bytes taken.
    pub bytes: u64,
    /// Whole messages decoded.
    pub messages: u64,
    /// Bytes that belong to no message, and messages cut short.
    pub framing_errors: u64,
    /// Commands and sysex commands the decoder does not know (skipped).
    pub unknown_commands: u64,
    /// Times the decoder dropped what it had and waited for the next command byte.
    pub resyncs: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// Waiting for a command byte.
    Idle,
    /// Skipping data bytes after an error (counted once).
    Skipping,
    /// A channel message: its command byte and data bytes so far.
    Channel { command: u8, have: u8, first: u8 },
    /// Inside a sysex: bytes in `buf`.
    Sysex,
    /// A sysex too long, skipped to its end.
    SysexOverflow,
}

/// A streaming Firmata decoder.
#[derive(Debug)]
pub struct Decoder {
    state: State,
    buf: Vec<u8>,
    counts: LineCounts,
}

impl Default for Decoder {
    fn default() -> Self {
        Decoder::new()
    }
}

/// Data bytes a channel command takes (None: a command hwgw does not take from a board).
fn data_len(command: u8) -> Option<u8> {
    match command & 0xF0 {
        DIGITAL_MESSAGE | ANALOG_MESSAGE => Some(2),
        0xF0 if command == REPORT_VERSION => Some(2),
        _ => None,
    }
}

impl Decoder {
    /// A decoder waiting for its first command byte.
    pub fn new() -> Decoder {
        Decoder {
            state: State::Idle,
            buf: Vec::with_capacity(MAX_SYSEX),
            counts: LineCounts::default(),
        }
    }

    /// The counts so far.
    pub fn counts(&self) -> LineCounts {
        self.counts
    }

    /// Forgets any partial message (a line reopened: what follows is a new stream).
    pub fn reset(&mut self) {
        self.state = State::Idle;
        self.buf.clear();
    }

    fn resync(&mut self, skipped_this_byte: bool) {
        self.counts.framing_errors += 1;
        self.counts.resyncs += 1;
        self.buf.clear();
        self.state = if skipped_this_byte {
            State::Skipping
        } else {
            State::Idle
        };
    }

    /// Takes one byte; returns the message it completes, if any.
    pub fn push(&mut self, byte: u8) -> Option<Frame<'_>> {
        self.counts.bytes += 1;
        if byte & 0x80 != 0 {
            return self.command_byte(byte);
        }
        match self.state {
            State::Idle => {
                self.resync(true);
                None
            }
            State::Skipping => {
                self.counts.framing_errors += 1;
                None
            }
            State::SysexOverflow => None,
            State::Sysex => {
                if self.buf.len() >= MAX_SYSEX {
                    self.counts.framing_errors += 1;
                    self.counts.resyncs += 1;
                    self.buf.clear();
                    self.state = State::SysexOverflow;
                } else {
                    self.buf.push(byte);
                }
                None
            }
            State::Channel {
                command,
                have,
                first,
            } => {
                let need = data_len(command).unwrap_or(0);
                if have + 1 < need {
                    self.state = State::Channel {
                        command,
                        have: have + 1,
                        first: byte,
                    };
                    return None;
                }
                self.state = State::Idle;
                self.counts.messages += 1;
                let low = command & 0x0F;
                Some(match command & 0xF0 {
                    DIGITAL_MESSAGE => Frame::Digital {
                        port: low,
                        value: first | ((byte & 1) << 7),
                    },
                    ANALOG_MESSAGE => Frame::Analog {
                        channel: low,
                        value: u16::from(first) | (u16::from(byte) << 7),
                    },
                    _ => Frame::Version {
                        major: first,
                        minor: byte,
                    },
                })
            }
        }
    }

    fn command_byte(&mut self, byte: u8) -> Option<Frame<'_>> {
        // What was under way is cut short by any command byte but a sysex's end.
        let cut = match self.state {
            State::Channel { .. } => true,
            State::Sysex | State::SysexOverflow => byte != END_SYSEX,
            State::Idle | State::Skipping => false,
        };
        if cut {
            self.resync(false);
        }
        if byte == END_SYSEX {
            if cut {
                // A channel message cut short by it: counted once, above.
                return None;
            }
            let was = std::mem::replace(&mut self.state, State::Idle);
            return match was {
                State::Sysex if !self.buf.is_empty() => {
                    let command = self.buf[0];
                    if !known_sysex(command) {
                        self.counts.unknown_commands += 1;
                        return None;
                    }
                    self.counts.messages += 1;
                    Some(Frame::Sysex {
                        command,
                        data: &self.buf[1..],
                    })
                }
                State::Sysex => {
                    // An empty sysex: nothing to decode, nothing lost.
                    self.counts.framing_errors += 1;
                    None
                }
                State::SysexOverflow => None,
                _ => {
                    // An end with no start.
                    self.counts.framing_errors += 1;
                    None
                }
            };
        }
        if byte == START_SYSEX {
            self.buf.clear();
            self.state = State::Sysex;
            return None;
        }
        if data_len(byte).is_some() {
            self.state = State::Channel {
                command: byte,
                have: 0,
                first: 0,
            };
        } else {
            // A command a board does not send (or none): skip its data.
            self.counts.unknown_commands += 1;
            self.counts.resyncs += 1;
            self.state = State::Skipping;
        }
        None
    }
}

/// Sysex replies hwgw reads.
fn known_sysex(command: u8) -> bool {
    matches!(
        command,
        sysex::ENCODER_DATA
            | sysex::ANALOG_MAPPING_RESPONSE
            | sysex::CAPABILITY_RESPONSE
            | sysex::PIN_STATE_RESPONSE
            | sysex::STRING_DATA
            | sysex::REPORT_FIRMWARE
    )
}

/// Text sent as 7-bit pairs (REPORT_FIRMWARE's name, STRING_DATA), LSB first; at most
/// `max` characters, non-ASCII as '?'.
pub fn two_byte_text(data: &[u8], max: usize) -> String {
    data.chunks(2)
        .take(max)
        .map(|c| {
            let v = u16::from(c[0]) | (u16::from(*c.get(1).unwrap_or(&0)) << 7);
            match u8::try_from(v) {
                Ok(b) if b.is_ascii() && !b.is_ascii_control() => char::from(b),
                _ => '?',
            }
        })
        .collect()
}

/// Encoders of the messages hwgw sends, each appended to a buffer made once.
pub mod write {
    use super::*;

    fn lsb(v: u32) -> u8 {
        (v & 0x7F) as u8
    }
    fn msb(v: u32) -> u8 {
        ((v >> 7) & 0x7F) as u8
    }

    /// The protocol version query.
    pub fn version_query(out: &mut Vec<u8>) {
        out.push(REPORT_VERSION);
    }
    /// A sysex query with no payload (firmware, capabilities, analog mapping).
    pub fn query(out: &mut Vec<u8>, command: u8) {
        out.extend_from_slice(&[START_SYSEX, command, END_SYSEX]);
    }
    /// PIN_STATE_QUERY: the pin's mode and state come back.
    pub fn query_pin(out: &mut Vec<u8>, pin: u8) {
        out.extend_from_slice(&[START_SYSEX, sysex::PIN_STATE_QUERY, pin & 0x7F, END_SYSEX]);
    }
    /// SET_PIN_MODE.
    pub fn pin_mode(out: &mut Vec<u8>, pin: u8, mode: u8) {
        out.extend_from_slice(&[SET_PIN_MODE, pin & 0x7F, mode & 0x7F]);
    }
    /// DIGITAL_MESSAGE for `port` (< 16): its 8 pins' levels, pin 8·port in bit 0.
    pub fn digital_port(out: &mut Vec<u8>, port: u8, value: u8) {
        out.extend_from_slice(&[DIGITAL_MESSAGE | (port & 0x0F), value & 0x7F, value >> 7]);
    }
    /// SET_DIGITAL_PIN_VALUE (protocol 2.5 and later).
    pub fn digital_pin(out: &mut Vec<u8>, pin: u8, on: bool) {
        out.extend_from_slice(&[SET_DIGITAL_PIN_VALUE, pin & 0x7F, u8::from(on)]);
    }
    /// An analog (PWM, servo) value: ANALOG_MESSAGE for pins 0–15 and values of 14 bits,
    /// else EXTENDED_ANALOG.
    pub fn analog(out: &mut Vec<u8>, pin: u8, value: u32) {
        if pin < 16 && value < (1 << 14) {
            out.extend_from_slice(&[ANALOG_MESSAGE | pin, lsb(value), msb(value)]);
        } else {
            out.extend_from_slice(&[START_SYSEX, sysex::EXTENDED_ANALOG, pin & 0x7F]);
            let mut v = value;
            loop {
                out.push(lsb(v));
                v >>= 7;
                if v == 0 {
                    break;
                }
            }
            out.push(END_SYSEX);
        }
    }
    /// REPORT_ANALOG for channel (< 16).
    pub fn report_analog(out: &mut Vec<u8>, channel: u8, on: bool) {
        out.extend_from_slice(&[REPORT_ANALOG | (channel & 0x0F), u8::from(on)]);
    }
    /// REPORT_DIGITAL for port (< 16).
    pub fn report_digital(out: &mut Vec<u8>, port: u8, on: bool) {
        out.extend_from_slice(&[REPORT_DIGITAL | (port & 0x0F), u8::from(on)]);
    }
    /// SAMPLING_INTERVAL, ms (14 bits).
    pub fn sampling_interval(out: &mut Vec<u8>, ms: u16) {
        let ms = u32::from(ms.min(0x3FFF));
        out.extend_from_slice(&[
            START_SYSEX,
            sysex::SAMPLING_INTERVAL,
            lsb(ms),
            msb(ms),
            END_SYSEX,
        ]);
    }
    /// SERVO_CONFIG: a servo's pulse width range, µs (14 bits each).
    pub fn servo_config(out: &mut Vec<u8>, pin: u8, min_us: u16, max_us: u16) {
        let (a, b) = (u32::from(min_us), u32::from(max_us));
        out.extend_from_slice(&[
            START_SYSEX,
            sysex::SERVO_CONFIG,
            pin & 0x7F,
            lsb(a),
            msb(a),
            lsb(b),
            msb(b),
            END_SYSEX,
        ]);
    }
    /// An encoder feature subcommand with its arguments.
    pub fn encoder(out: &mut Vec<u8>, sub: u8, args: &[u8]) {
        out.extend_from_slice(&[START_SYSEX, sysex::ENCODER_DATA, sub]);
        out.extend(args.iter().map(|a| a & 0x7F));
        out.push(END_SYSEX);
    }
}

/// Encoder positions in an ENCODER_DATA reply: (index, position) per 5 bytes (index in
/// bits 0–5, sign in bit 6, then 28 bits of magnitude, 7 a byte, LSB first). A partial
/// group at the end is ignored (and said by the `bool`).
pub fn encoder_positions(data: &[u8]) -> (impl Iterator<Item = (u8, i64)> + '_, bool) {
    let whole = data.len() - data.len() % 5;
    let it = data[..whole].chunks_exact(5).map(|c| {
        let magnitude = c[1..]
            .iter()
            .rev()
            .fold(0i64, |acc, b| (acc << 7) | i64::from(*b));
        let sign = if c[0] & 0x40 != 0 { -1 } else { 1 };
        (c[0] & 0x3F, sign * magnitude)
    });
    (it, whole == data.len())
}
