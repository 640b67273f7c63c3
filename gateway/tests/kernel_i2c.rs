//! `hwgw` with an I2C card, in the kernel rig: the real binary on `config/i2c.toml` over
//! the kernel's i2c-stub, the MCP23017's input register set and its output latch read
//! with i2c-tools, the CLI in between.
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Trial};
use testkit::wait::wait_ok;
use testkit::{I2cStub, Service};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/i2c.toml");

fn hwgw_gets_sets_and_leaves_the_outputs_safe() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x20, 0x36, 0x40, 0x41, 0x48, 0x60])?;
    // The INA219: shunt 1000 counts, bus 3000 counts (bits 15..3) with a conversion ready
    // (CNVR, bit 1), current 2000 counts, big-endian.
    stub.set_word(0x40, 0x01, 1000u16.swap_bytes())?;
    stub.set_word(0x40, 0x02, (3000u16 << 3 | 2).swap_bytes())?;
    stub.set_word(0x40, 0x04, 2000u16.swap_bytes())?;
    // The AS5600 sees a magnet, at 1000 counts (RAW ANGLE MSB first on the wire).
    stub.set_byte(0x36, 0x0b, 0x20)?;
    stub.set_word(0x36, 0x0c, 1000u16.swap_bytes())?;
    // The ADS1115's conversion: 0x4000, MSB first on the wire.
    stub.set_word(0x48, 0x00, 0x0040)?;
    let gw = Service::start(HWGW, "i2c", &[CONFIG], &[])?;
    let get = |name: &str| gw.out(&["get", "i2c.di", name]).map_err(Failed::from);
    wait_ok("the chip online", || {
        Ok(gw
            .out(&["call", "i2c", "counters"])?
            .contains("\"online\": \"6/6\""))
    })?;
    // Configured as config/i2c.toml says.
    assert_eq!(
        stub.get_word(0x20, 0x00)?,
        0xfffc,
        "IODIR: GPA0, GPA1 outputs"
    );
    assert_eq!(stub.get_word(0x20, 0x0c)?, 0x0300, "GPPU: GPB0, GPB1");
    assert_eq!(stub.get_word(0x20, 0x02)?, 0x0200, "IPOL: GPB1");
    // Inputs as the GPIO register has them.
    stub.set_word(0x20, 0x12, 0x0100)?;
    wait_ok("button on, limit off", || {
        Ok(get("button")? == "true" && get("limit")? == "false")
    })?;
    stub.set_word(0x20, 0x12, 0x0200)?;
    wait_ok("button off, limit on", || {
        Ok(get("button")? == "false" && get("limit")? == "true")
    })?;
    // Analog inputs with each channel's range: 16384 × 4.096 / 32768, × 0.256 / 32768.
    wait_ok("both channels converted", || {
        Ok(gw.out(&["get", "i2c.ai", "supply"])? == "2.048"
            && gw.out(&["get", "i2c.ai", "bridge"])? == "0.128")
    })?;
    // Outputs: hwgw set, read back from the latch byte for byte.
    gw.out(&["set", "i2c.do", "lamp", "true"])?;
    gw.out(&["set", "i2c.do", "valve", "true"])?;
    wait_ok("OLAT 0x0003", || Ok(stub.get_word(0x20, 0x14)? == 0x0003))?;
    // The DAC: code 2703 (3.3 V × 4096 / 5 V = 0xa8f), "register" 0x0a, data 0x8f.
    gw.out(&["set", "i2c.ao", "setpoint", "3.3"])?;
    wait_ok("the DAC code sent", || {
        Ok(stub.get_byte(0x60, 0x0a)? == 0x8f)
    })?;
    // The shaft: its angle as the position, then forwards across the wrap.
    wait_ok("the angle", || {
        Ok(gw.out(&["get", "i2c.encoder0", "position"])? == "1000")
    })?;
    stub.set_word(0x36, 0x0c, 3000u16.swap_bytes())?;
    wait_ok("3000", || {
        Ok(gw.out(&["get", "i2c.encoder0", "position"])? == "3000")
    })?;
    stub.set_word(0x36, 0x0c, 500u16.swap_bytes())?;
    wait_ok("one turn on", || {
        Ok(gw.out(&["get", "i2c.encoder0", "position"])? == "500"
            && gw.out(&["get", "i2c.encoder0", "turn"])? == "1")
    })?;
    // The INA219 with its LSBs: 1000 × 10 µV, 3000 × 4 mV, and 2000 counts of the current
    // LSB its calibration gives (0.04096 / (4194 × 0.1 Ω) A).
    wait_ok("the monitor's channels", || {
        Ok(gw
            .out(&["get", "i2c.ai", "shunt"])?
            .parse::<f64>()
            .is_ok_and(|v| (v - 0.01).abs() < 1e-12)
            && gw.out(&["get", "i2c.ai", "bus"])? == "12.0"
            && gw
                .out(&["get", "i2c.ai", "current"])?
                .parse::<f64>()
                .is_ok_and(|v| (v - 2000.0 * 0.04096 / (4194.0 * 0.1)).abs() < 1e-12))
    })?;
    // The INA219 browns out (its calibration back at 0): counted, set up again, and its
    // current reads as before.
    stub.set_word(0x40, 0x05, 0x0000)?;
    wait_ok("the INA219's reset counted", || {
        let counters = gw.out(&["call", "i2c", "counters"])?;
        Ok(counters.contains("\"last_reset\": \"calibration reads 0x0000, not 0x1062\""))
    })?;
    wait_ok("its calibration written again", || {
        Ok(stub.get_word(0x40, 0x05)? == 0x1062u16.swap_bytes())
    })?;
    wait_ok("its current as before", || {
        Ok(gw
            .out(&["get", "i2c.ai", "current"])?
            .parse::<f64>()
            .is_ok_and(|v| (v - 2000.0 * 0.04096 / (4194.0 * 0.1)).abs() < 1e-12))
    })?;
    // A component's writes: fan_control drives the fan at a quarter of the supply's
    // volts, 2.048 × 0.25 = 0.512 of the period: LED0_OFF = round(0.512 × 4096) = 2097.
    wait_ok("the fan's duty", || Ok(stub.get_word(0x41, 0x08)? == 2097))?;
    assert_eq!(
        stub.get_byte(0x41, 0xfe)?,
        5,
        "1000 Hz: round(25 MHz / 4096 / 1000) - 1"
    );
    let status = gw.out(&["status"])?;
    assert!(status.contains("mcp23017"), "{status}");
    // SIGTERM: every output to its safe value (off), sent before the bus side stops. The
    // DAC's safe code is 0 ("register" 0x00, data 0x00): a marker there first shows it
    // written.
    stub.set_byte(0x60, 0x00, 0xaa)?;
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert_eq!(
        stub.get_word(0x20, 0x14)?,
        0x0000,
        "the latch after stop: {}",
        stopped.log
    );
    assert_eq!(
        stub.get_word(0x41, 0x08)?,
        0x1000,
        "the fan full off after stop"
    );
    assert_eq!(
        stub.get_byte(0x60, 0x00)?,
        0x00,
        "the DAC at code 0 after stop"
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    kernel_rig::harness(
        &testkit::rig::i2c_stub(),
        vec![Trial::test(
            "hwgw_gets_sets_and_leaves_the_outputs_safe",
            hwgw_gets_sets_and_leaves_the_outputs_safe,
        )],
    )
}
