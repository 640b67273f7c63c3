//! A Firmata card's set-up and settle check, on its bus side: the pin modes, outputs,
//! sampling interval and reports sent once the board has described itself and passed the
//! section's check; and at stop, each output pin's state asked of the board.

use super::{FirmataBus, Link, MAX_BACKOFF, Phase, REPORT_WAIT, after};
use crate::card::{CHECK_ASKED, CHECK_FAILED, CHECK_OK, CHECK_QUERYING, FirmataCard};
use crate::line::send;
use crate::protocol::{mode, write};
use device_interface::time::Timestamp;
use std::sync::PoisonError;
use std::sync::atomic::Ordering;

impl FirmataBus {
    /// Checks the board and sends the set-up.
    pub(super) fn set_up(&mut self, now: Timestamp) -> Result<(), String> {
        let Link::Handshake {
            line,
            phase,
            deadline,
            board,
            ..
        } = &mut self.link
        else {
            return Ok(());
        };
        if let Err(e) = self.card.config.check_board(board) {
            let key = e.key.map(|k| format!("firmata.{k}: ")).unwrap_or_default();
            let why = format!("{}: {key}{}", self.card.config.port, e.message);
            self.refused = Some(why.clone());
            self.card
                .shared
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .board = Some(board.clone());
            self.close(Some(why));
            // Opening again resets an Uno (DTR): not until the port is another device.
            self.refused_port = crate::line::identity(&self.card.config.port);
            self.backoff = MAX_BACKOFF;
            return Ok(());
        }
        self.refused = None;
        self.refused_port = None;
        let c = &self.card.config;
        let new_pullup = board.protocol_at_least(2, 5);
        self.pin_writes = new_pullup;
        let tx = &mut self.tx;
        tx.clear();
        for p in &c.digital_in {
            let m = if p.pullup && new_pullup && board.resolution(p.pin, mode::PULLUP).is_some() {
                mode::PULLUP
            } else {
                mode::INPUT
            };
            write::pin_mode(tx, p.pin, m);
        }
        for p in &c.digital_out {
            write::pin_mode(tx, p.pin, mode::OUTPUT);
        }
        for p in &c.servo {
            write::servo_config(tx, p.pin, p.min_us, p.max_us);
        }
        for a in &self.card.ao {
            write::pin_mode(tx, a.pin, if a.servo { mode::SERVO } else { mode::PWM });
        }
        for ch in &c.analog_in {
            if let Some(pin) = board.analog_pin(ch.channel) {
                write::pin_mode(tx, pin, mode::ANALOG);
            }
        }
        for (i, e) in c.encoder.iter().enumerate() {
            write::encoder(tx, crate::protocol::encoder::ATTACH, &[i as u8, e.a, e.b]);
        }
        if !c.encoder.is_empty() {
            write::encoder(tx, crate::protocol::encoder::REPORT_AUTO, &[1]);
        }
        write::sampling_interval(tx, c.sampling_ms);
        // Every output as the card holds it, whatever was marked: pin by pin from protocol
        // 2.5 on; before, port by port, with the ports of the pull-up inputs too (a 1
        // written to an input is its pull-up then).
        let written = self.card.written.load(Ordering::Acquire);
        self.card.dirty_ports.store(0, Ordering::Release);
        if self.pin_writes {
            for (i, p) in c.digital_out.iter().enumerate() {
                write::digital_pin(tx, p.pin, self.card.output(i));
            }
        } else {
            let outputs = c.digital_out.iter().map(|p| p.pin);
            let pullups = c.digital_in.iter().filter(|p| p.pullup).map(|p| p.pin);
            let ports = outputs
                .chain(pullups)
                .fold(0u32, |m, pin| m | 1 << (pin / 8));
            for port in 0..16 {
                if ports & 1 << port != 0 {
                    write::digital_port(tx, port, port_value(&self.card, port));
                }
            }
        }
        for a in &self.card.ao {
            a.dirty.store(false, Ordering::Release);
            write::analog(tx, a.pin, a.raw.load(Ordering::Acquire));
        }
        for ch in &c.analog_in {
            write::report_analog(tx, ch.channel, true);
        }
        let inputs = c
            .digital_in
            .iter()
            .map(|p| p.pin / 8)
            .fold(0u32, |m, p| m | 1 << p);
        for port in 0..16 {
            if inputs & 1 << port != 0 {
                write::report_digital(tx, port, true);
            }
        }
        send(line.as_mut(), tx, &self.card.bytes_sent)?;
        self.card.sent.store(written, Ordering::Release);
        self.card
            .shared
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .board = Some(board.clone());
        *phase = Phase::Reports(inputs);
        *deadline = after(now, REPORT_WAIT);
        if inputs == 0 {
            self.go_online(now);
        }
        Ok(())
    }

    /// Asked by settle: queries the state of every output pin (everything marked was sent
    /// just before, on this same step).
    pub(super) fn query_states(&mut self) -> Result<(), String> {
        let Link::Online { line, .. } = &mut self.link else {
            return Ok(());
        };
        if self.card.check.load(Ordering::Acquire) != CHECK_ASKED {
            return Ok(());
        }
        self.card.expected_states(&mut self.checks);
        self.tx.clear();
        for (pin, _) in &self.checks {
            write::query_pin(&mut self.tx, *pin);
        }
        send(line.as_mut(), &self.tx, &self.card.bytes_sent)?;
        self.card.check.store(CHECK_QUERYING, Ordering::Release);
        Ok(())
    }

    /// A PIN_STATE_RESPONSE (pin, mode, state in 7-bit groups): one output confirmed, or
    /// the check failed.
    pub(super) fn pin_state(&mut self) {
        if self.card.check.load(Ordering::Acquire) != CHECK_QUERYING {
            return;
        }
        let [pin, _mode, state @ ..] = self.sysex.as_slice() else {
            return;
        };
        let value = state
            .iter()
            .take(5)
            .rev()
            .fold(0u32, |acc, b| (acc << 7) | u32::from(*b));
        let Some(i) = self.checks.iter().position(|(p, _)| p == pin) else {
            return;
        };
        let (pin, expected) = self.checks.swap_remove(i);
        if value != expected {
            let why = format!(
                "{}: pin {pin} is {value} on the board, not {expected} as written",
                self.card.config.port
            );
            self.card
                .shared
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .check_error = Some(why);
            self.card.check.store(CHECK_FAILED, Ordering::Release);
        } else if self.checks.is_empty() {
            self.card.check.store(CHECK_OK, Ordering::Release);
        }
    }
}

/// A port's DIGITAL_MESSAGE value: its outputs' bits, and its inputs' pull-ups (a 1 written
/// to an input turns its pull-up on, the protocol's way before INPUT_PULLUP).
pub(super) fn port_value(card: &FirmataCard, port: u8) -> u8 {
    let c = card.config();
    let mut v = 0u8;
    for (i, p) in c.digital_out.iter().enumerate() {
        if p.pin / 8 == port && card.output(i) {
            v |= 1 << (p.pin % 8);
        }
    }
    for p in &c.digital_in {
        if p.pin / 8 == port && p.pullup {
            v |= 1 << (p.pin % 8);
        }
    }
    v
}
