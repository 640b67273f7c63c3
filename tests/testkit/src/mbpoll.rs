//! mbpoll, a libmodbus master: the independent check that a Modbus server (ours, or one
//! our client talks to) holds what it should.

use crate::peers::{MBPOLL, ensure};
use std::process::Command;

/// One mbpoll transaction against unit 1 (or another: [`Mbpoll::run_unit`]) on
/// 127.0.0.1:`port`.
#[derive(Debug, Clone, Copy)]
pub struct Mbpoll<'a> {
    /// TCP port.
    pub port: u16,
    /// mbpoll's table: 0 coils, 1 discrete inputs, 3 input registers, 4 holding registers.
    pub table: &'a str,
    /// First address, 0-based.
    pub address: u16,
    /// Items to read (mbpoll's default, 1, when `None`).
    pub count: Option<u16>,
    /// Values to write (a read when empty).
    pub write: &'a [&'a str],
}

impl Mbpoll<'_> {
    /// Runs it once (`-1`, 0-based addresses `-0`); returns its standard output followed by
    /// its standard error. Fails the test when mbpoll cannot be had.
    pub fn run(&self) -> String {
        self.run_unit(1)
    }

    /// The same, to unit `unit`.
    pub fn run_unit(&self, unit: u8) -> String {
        ensure(&MBPOLL);
        let mut cmd = Command::new("mbpoll");
        cmd.args([
            "-m",
            "tcp",
            "-p",
            &self.port.to_string(),
            "-a",
            &unit.to_string(),
        ])
        .args(["-t", self.table, "-r", &self.address.to_string()]);
        if let Some(n) = self.count {
            cmd.args(["-c", &n.to_string()]);
        }
        let out = cmd
            .args(["-0", "-1", "127.0.0.1"])
            .args(self.write)
            .output()
            .unwrap_or_else(|e| panic!("cannot run mbpoll: {e}"));
        text(&out)
    }
}

/// One mbpoll transaction over RTU (`baud`, `parity` none, even or odd, one stop bit) on
/// serial port `device` to `unit`: `table` as in [`Mbpoll`], 0-based
/// `address`, `count` items to read, or `write` values (a read when empty; `count` is not
/// given to a write: mbpoll writes as many as there are values). Returns standard output
/// followed by standard error.
pub fn rtu(
    device: &std::path::Path,
    (baud, parity): (u32, &str),
    unit: u8,
    (table, address, count): (&str, u16, u16),
    write: &[&str],
) -> String {
    ensure(&MBPOLL);
    let mut cmd = Command::new("mbpoll");
    cmd.args([
        "-m",
        "rtu",
        "-b",
        &baud.to_string(),
        "-P",
        parity,
        "-s",
        "1",
    ])
    .args([
        "-a",
        &unit.to_string(),
        "-t",
        table,
        "-r",
        &address.to_string(),
    ]);
    if write.is_empty() {
        cmd.args(["-c", &count.to_string()]);
    }
    let out = cmd
        .args(["-0", "-1", "-o", "2"])
        .arg(device)
        .args(write)
        .output()
        .unwrap_or_else(|e| panic!("cannot run mbpoll: {e}"));
    text(&out)
}

/// mbpoll's standard output followed by its standard error.
fn text(out: &std::process::Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}
