//! The link as sysfs and netlink tell it: whether the interface is there, up and carrying,
//! which interface it is now (a new one of the same name has a new index), and a real
//! controller's state.

use super::CanBus;
use device_interface::DeviceError;

/// ARPHRD_CAN, the link type of CAN interfaces in /sys/class/net/IF/type.
pub(super) const ARPHRD_CAN: u32 = 280;
fn sys(iface: &str, file: &str) -> Option<String> {
    std::fs::read_to_string(format!("/sys/class/net/{iface}/{file}"))
        .ok()
        .map(|s| s.trim().to_string())
}

pub(super) fn sys_u32(iface: &str, file: &str) -> Option<u32> {
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

/// The link state and identity of an interface, from sysfs.
pub(super) fn link(iface: &str) -> Option<(bool, u32)> {
    let flags = sys_u32(iface, "flags")?;
    let index = sys_u32(iface, "ifindex")?;
    // Administratively up (IFF_UP) with the carrier on: a CAN controller drops its carrier
    // at bus-off; `carrier` cannot be read while the interface is down.
    let up = flags & 0x1 != 0 && sys(iface, "carrier").as_deref() == Some("1");
    Some((up, index))
}

impl CanBus {
    pub(super) fn link_lost(&self, e: nix::Error) {
        if self.card.link_up() {
            tracing::warn!(interface = %self.card.map().interface(), "link down: {e}");
        }
        self.card
            .set_link(false, Some(DeviceError::bus(std::io::Error::from(e))));
    }

    pub(super) fn check_link(&mut self) {
        let card = self.card.clone();
        let name = card.map().interface();
        match link(name) {
            None => {
                if self.card.link_up() {
                    tracing::warn!(interface = %name, "interface gone");
                }
                self.card.set_link(
                    false,
                    Some(DeviceError::bus(std::io::Error::from(nix::Error::ENODEV))),
                );
            }
            Some((up, index)) => {
                if index != self.ifindex || self.socket.is_none() {
                    // A new interface of the same name: the old socket is bound to the
                    // old index.
                    self.ifindex = index;
                    self.controller = None;
                    if let Err(e) = self.open_socket() {
                        tracing::warn!(interface = %name, "cannot reopen: {e}");
                        self.card.set_link(false, Some(DeviceError::bus(e)));
                        return;
                    }
                }
                if up != self.card.link_up() {
                    if up {
                        tracing::info!(interface = %name, "link up");
                    } else {
                        tracing::warn!(interface = %name, "link down");
                    }
                }
                self.card.set_link(
                    up,
                    (!up).then(|| DeviceError::bus(std::io::Error::from(nix::Error::ENETDOWN))),
                );
                self.ask_controller();
            }
        }
    }

    /// Asks netlink for the controller's state, unless the interface is virtual (once
    /// asked, a vcan is not asked again). A failing query is said once and counted as an
    /// unknown state.
    fn ask_controller(&mut self) {
        if self.controller == Some(false) {
            return;
        }
        match crate::netlink::query(self.ifindex) {
            Ok(c) => {
                self.controller = Some(c.is_some());
                self.card.set_controller(c);
            }
            Err(e) => {
                if self.controller.is_none() {
                    tracing::warn!(interface = %self.card.map().interface(), "controller state not readable: {e}");
                    self.controller = Some(true);
                }
                self.card.set_controller(None);
            }
        }
    }
}
