//! The link as sysfs tells it: whether an interface is there, up and carrying, which
//! interface it is now (a new one of the same name has a new index), and which CAN
//! interfaces the host has.

/// ARPHRD_CAN, the link type of CAN interfaces in /sys/class/net/IF/type.
pub const ARPHRD_CAN: u32 = 280;
/// `/sys/class/net/IF/FILE`, trimmed.
fn sys(iface: &str, file: &str) -> Option<String> {
    std::fs::read_to_string(format!("/sys/class/net/{iface}/{file}"))
        .ok()
        .map(|s| s.trim().to_string())
}

/// A number from `/sys/class/net/IF/FILE` (decimal or 0x-hex).
pub fn sys_u32(iface: &str, file: &str) -> Option<u32> {
    let s = sys(iface, file)?;
    match s.strip_prefix("0x") {
        Some(hex) => u32::from_str_radix(hex, 16).ok(),
        None => s.parse().ok(),
    }
}

/// The CAN interfaces of this host.
pub fn can_interfaces() -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir("/sys/class/net")
        .map(|d| {
            d.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| sys_u32(n, "type") == Some(ARPHRD_CAN))
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// Whether an interface is up (administratively, with its carrier) and its index, from
/// sysfs; None when there is no such interface.
pub fn link(iface: &str) -> Option<(bool, u32)> {
    let flags = sys_u32(iface, "flags")?;
    let index = sys_u32(iface, "ifindex")?;
    // Administratively up (IFF_UP) with the carrier on: a CAN controller drops its carrier
    // at bus-off; `carrier` cannot be read while the interface is down.
    let up = flags & 0x1 != 0 && sys(iface, "carrier").as_deref() == Some("1");
    Some((up, index))
}
