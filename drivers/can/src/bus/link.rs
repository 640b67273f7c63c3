//! The card's view of its link: gone, down, replaced by a new interface of the same name,
//! and a real controller's state (the sysfs and netlink reading is `can_socket`'s).

use super::CanBus;
use device_interface::DeviceError;
use rtt::log::Arg;
use rtt::rt_log;

impl CanBus {
    /// A socket said the interface went down or away.
    pub(super) fn link_lost(&mut self, e: nix::Error) {
        self.interface_down();
        if self.card.link_up() {
            rt_log!(
                self.card.log(),
                Warn,
                "link {} down: {}",
                Arg::text(self.card.map().interface()),
                Arg::Errno(e as i32)
            );
        }
        self.card
            .set_link(false, Some(DeviceError::bus(std::io::Error::from(e))));
    }

    pub(super) fn check_link(&mut self) {
        let card = self.card.clone();
        let name = card.map().interface();
        match self.link.read() {
            None => {
                if self.card.link_up() {
                    rt_log!(self.card.log(), Warn, "interface {} gone", Arg::text(name));
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
                        rt_log!(
                            self.card.log(),
                            Warn,
                            "cannot reopen {}: {}",
                            Arg::text(name),
                            Arg::io(&e)
                        );
                        self.card.set_link(false, Some(DeviceError::bus(e)));
                        return;
                    }
                }
                if up != self.card.link_up() {
                    if up {
                        rt_log!(self.card.log(), Info, "link {} up", Arg::text(name));
                    } else {
                        rt_log!(self.card.log(), Warn, "link {} down", Arg::text(name));
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
                    rt_log!(
                        self.card.log(),
                        Warn,
                        "{}: controller state not readable: {}",
                        Arg::text(self.card.map().interface()),
                        Arg::display(&e)
                    );
                    self.controller = Some(true);
                }
                self.card.set_controller(None);
            }
        }
    }
}
