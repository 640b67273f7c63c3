//! The I2C rig's facts, checked where the I2C driver will rely on them: i2c-stub in the
//! guest found by its adapter's name, its chips' registers set and read back with
//! i2c-tools, a word register apart from the byte registers after it, an absent address
//! refused, and a reload with
//! other addresses (how a test brings a dead chip back).
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Trial};
use testkit::I2cStub;

fn registers_round_trip_through_i2c_tools() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x20, 0x48])?;
    assert!(stub.path().exists(), "{}", stub.path().display());
    stub.set_byte(0x20, 0x12, 0x5a)?;
    assert_eq!(stub.get_byte(0x20, 0x12)?, 0x5a);
    // i2c-stub keeps one 16-bit word per register: a byte access reaches its low byte,
    // and the next register is not its high byte (as it would be on a chip of byte
    // registers). A chip model must use the transfer size the real chip uses.
    stub.set_word(0x48, 0x00, 0x1234)?;
    assert_eq!(stub.get_word(0x48, 0x00)?, 0x1234);
    assert_eq!(
        (stub.get_byte(0x48, 0x00)?, stub.get_byte(0x48, 0x01)?),
        (0x34, 0x00)
    );
    // Nothing at 0x21: refused (NAK), not answered with zeros.
    let e = stub.get_byte(0x21, 0x00).err().ok_or("0x21 answered")?;
    assert!(e.to_string().contains("0x21"), "{e}");
    Ok(())
}

fn a_reload_brings_another_set_of_chips() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x20])?;
    assert!(stub.get_byte(0x36, 0x0c).is_err());
    drop(stub);
    let stub = I2cStub::load(&[0x20, 0x36])?;
    stub.set_byte(0x36, 0x0c, 0x0f)?;
    assert_eq!(stub.get_byte(0x36, 0x0c)?, 0x0f);
    Ok(())
}

fn main() -> std::process::ExitCode {
    kernel_rig::harness(
        &testkit::rig::i2c_stub(),
        vec![
            Trial::test(
                "registers_round_trip_through_i2c_tools",
                registers_round_trip_through_i2c_tools,
            ),
            Trial::test(
                "a_reload_brings_another_set_of_chips",
                a_reload_brings_another_set_of_chips,
            ),
        ],
    )
}
