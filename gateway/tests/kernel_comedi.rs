//! `hwgw` with comedi cards, in the kernel rig: the real binary on `config/comedi.toml`
//! over comedi_test (analog outputs looped back to its inputs) and comedi_parport (the
//! data lines showing ThreadScope), the CLI in between; comedilib read directly and qemu's
//! record of the parallel port's writes as the independent read-backs.
#![allow(clippy::unwrap_used, reason = "test code")]

use driver_comedi::board::{Board, Daq, comedilib_to_phys};
use kernel_rig::{Failed, Trial};
use testkit::wait::wait_ok;
use testkit::{ComediBoard, PortTrace, Service};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/comedi.toml");

/// Raw code of `value` on channel `ch` as comedilib reads the loop-back, and hwgw's `get`
/// of the input, both after `hwgw set` of the output.
fn set_and_get(
    gw: &Service,
    bare: &mut Board,
    ch: u32,
    range: u32,
    value: f64,
) -> Result<(u32, f64), Failed> {
    gw.out(&["set", "daq.ao", &format!("out{ch}"), &value.to_string()])?;
    let raw = bare.data_read(0, ch, range, 0)?;
    let mut got = f64::NAN;
    wait_ok("hwgw get to read the new value", || {
        got = gw
            .out(&["get", "daq.ai", &format!("in{ch}")])?
            .parse::<f64>()
            .map_err(|e| e.to_string())?;
        // A sample taken before the write shows the old value: wait for one after.
        Ok(
            bare.data_read(0, ch, range, 0).map_err(|e| e.to_string())? == raw
                && (got - value).abs() <= 20.0 / 65535.0,
        )
    })?;
    Ok((raw, got))
}

fn hwgw_sets_gets_scopes_and_leaves_the_outputs_safe() -> Result<(), Failed> {
    let _daq = ComediBoard::comedi_test("/dev/comedi0")?;
    let _lpt = ComediBoard::parport("/dev/comedi1")?;
    let trace = PortTrace::open()?;
    let from = trace.data_writes()?.len();
    let gw = Service::start(HWGW, "comedi", &[CONFIG], &[])?;
    let mut status = String::new();
    let online = wait_ok("both boards online", || {
        status = gw.out(&["status", "--json"])?;
        Ok(status.matches("\"online\": true").count() >= 2)
    });
    if let Err(e) = online {
        return Err(format!("{e:?}: {status}\n{}", gw.terminate().log).into());
    }
    let mut bare = Board::open("/dev/comedi0")?;
    let desc = bare.describe()?;
    // Both ranges, at their ends and between: what hwgw gets is comedi_to_phys of the
    // code comedilib reads back, exactly.
    for (ch, range, values) in [
        (0u32, 0u32, [-10.0, 10.0, 0.0, 3.3]),
        (4, 1, [-5.0, 5.0, 0.0, -1.25]),
    ] {
        let table = desc.subdevices[0].channels[ch as usize].ranges[range as usize];
        for value in values {
            let (raw, got) = set_and_get(&gw, &mut bare, ch, range, value)?;
            let theirs = comedilib_to_phys(raw, &table, 65535);
            assert_eq!(got, theirs, "out{ch} = {value}: raw {raw}");
            if value.abs() == table.max {
                assert_eq!(got, value, "a range end is exact");
            }
        }
    }
    // ThreadScope on the data lines, read back from qemu: runtime threads pulse their
    // lines, each write one line's edge.
    wait_ok("20 pulses on three lines", || {
        let writes = trace.data_writes().map_err(|e| e.to_string())?;
        let busy = (0..8)
            .filter(|b| {
                writes[from..]
                    .iter()
                    .filter(|w| w.value >> b & 1 == 1)
                    .count()
                    >= 20
            })
            .count();
        Ok(busy >= 3)
    })?;
    // SIGTERM: the outputs to their safe value (0 V), the data lines all low.
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(stopped.log.contains("ThreadScope"), "{}", stopped.log);
    let zero = |range: u32| -> Result<u32, Failed> {
        let r = desc.subdevices[1].channels[0].ranges[range as usize];
        Ok(((0.0 - r.min) / (r.max - r.min) * 65535.0).round() as u32)
    };
    for ch in 0..8 {
        let range = if ch < 4 { 0 } else { 1 };
        assert_eq!(
            bare.data_read(0, ch, range, 0)?,
            zero(range)?,
            "out{ch} after stop: {}",
            stopped.log
        );
    }
    let writes = trace.data_writes()?;
    let mut prev = 0u8;
    for w in &writes[from..] {
        assert!(
            (w.value ^ prev).count_ones() <= 1,
            "{prev:#04x} → {:#04x}",
            w.value
        );
        prev = w.value;
    }
    assert_eq!(prev, 0, "a data line left high");
    Ok(())
}

fn hwgw_check_names_a_board_that_is_not_there() -> Result<(), Failed> {
    // No board attached: the deployment is refused, naming the device and key.
    let out = std::process::Command::new(HWGW)
        .args(["check", CONFIG])
        .output()?;
    let text =
        String::from_utf8_lossy(&out.stderr).into_owned() + &String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success(), "{text}");
    // The device files are there (comedi's legacy minors), the board is not.
    assert!(
        text.contains(
            "card[0].comedi.device: card \"daq\": comedi_open on /dev/comedi0: No such device (errno 19); \
             comedi devices here: /dev/comedi0, /dev/comedi1, /dev/comedi2, /dev/comedi3"
        ),
        "{text}"
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    kernel_rig::harness(
        &testkit::rig::comedi(),
        vec![
            Trial::test(
                "hwgw_sets_gets_scopes_and_leaves_the_outputs_safe",
                hwgw_sets_gets_scopes_and_leaves_the_outputs_safe,
            ),
            Trial::test(
                "hwgw_check_names_a_board_that_is_not_there",
                hwgw_check_names_a_board_that_is_not_there,
            ),
        ],
    )
}
