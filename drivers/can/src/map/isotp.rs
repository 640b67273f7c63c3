//! A card's `[[isotp]]` address pairs checked: names unique and usable as operation
//! arguments, ids that fit their format and differ, a timeout and a separation time
//! ISO 15765-2 can code.

use super::{MapError, bad};
use crate::section::IsoTpConfig;
use can_socket::isotp::IsoTp;
use std::time::Duration;

/// The STmin code of `us` microseconds: 0-127 ms as 0x00-0x7F, 100-900 µs as 0xF1-0xF9.
fn st_min(path: &str, us: u32) -> Result<u8, MapError> {
    match us {
        0 => Ok(0),
        100..=900 if us.is_multiple_of(100) => Ok(0xF0 + (us / 100) as u8),
        1000..=127_000 if us.is_multiple_of(1000) => Ok((us / 1000) as u8),
        _ => Err(bad(
            path,
            format!("{us} µs: ISO 15765-2 codes 100 to 900 µs in steps of 100, or 1 to 127 ms"),
        )),
    }
}

/// The checked address pairs, by name.
pub(super) fn resolve(list: &[IsoTpConfig]) -> Result<Vec<(String, IsoTp)>, MapError> {
    let mut out: Vec<(String, IsoTp)> = Vec::new();
    for (i, c) in list.iter().enumerate() {
        let path = format!("isotp[{i}]");
        if !driver_api::is_port_name(&c.name) {
            return Err(bad(
                format!("{path}.name"),
                format!("{:?}: a name has no dots or spaces", c.name),
            ));
        }
        if let Some(j) = out.iter().position(|(n, _)| *n == c.name) {
            return Err(bad(
                format!("{path}.name"),
                format!("{:?} is isotp[{j}]'s name already", c.name),
            ));
        }
        let max = if c.extended { 0x1FFF_FFFF } else { 0x7FF };
        for (key, id) in [("tx_id", c.tx_id), ("rx_id", c.rx_id)] {
            if id > max {
                return Err(bad(
                    format!("{path}.{key}"),
                    format!(
                        "{id:#x} does not fit a {} id",
                        if c.extended { "29-bit" } else { "11-bit" }
                    ),
                ));
            }
        }
        if c.tx_id == c.rx_id {
            return Err(bad(
                format!("{path}.rx_id"),
                "the response id must differ from the request id",
            ));
        }
        if c.timeout_ms == 0 {
            return Err(bad(format!("{path}.timeout_ms"), "at least 1 ms"));
        }
        out.push((
            c.name.clone(),
            IsoTp {
                tx_id: c.tx_id,
                rx_id: c.rx_id,
                extended: c.extended,
                block_size: c.block_size,
                st_min: st_min(&format!("{path}.st_min_us"), c.st_min_us)?,
                padding: c.padding,
                timeout: Duration::from_millis(c.timeout_ms.into()),
            },
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    #[test]
    fn separation_times_as_iso_15765_codes_them() {
        assert_eq!(st_min("s", 0).unwrap(), 0);
        assert_eq!(st_min("s", 300).unwrap(), 0xF3);
        assert_eq!(st_min("s", 5000).unwrap(), 5);
        assert_eq!(st_min("s", 127_000).unwrap(), 0x7F);
        assert!(st_min("s", 150).is_err());
        assert!(st_min("s", 128_000).is_err());
    }
}
