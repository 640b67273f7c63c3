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
    parse_number(&sys(iface, file)?)
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
    LinkReader::new(iface).read()
}

/// The sysfs attributes [`LinkReader`] reads: `flags`, `ifindex`, `carrier`.
const LINK_FILES: [&str; 3] = ["flags", "ifindex", "carrier"];

/// [`link`] of one interface, asked again and again (a bus thread's link check, several
/// times a second, on a real-time thread) without opening a file or allocating: the three
/// attributes stay open and each check reads them with one `pread` at offset 0 apiece
/// (sysfs gives the value afresh at each read). A file of an interface that went away
/// answers ENODEV (any error but EINVAL, which `carrier` answers while the interface is
/// down) and is opened again by name, which finds a new interface of that name;
/// one that cannot be opened is tried again at the next read. An interface renamed, or
/// moved to another network namespace, while its files are open is still the one read
/// until it goes: a new interface given the name meanwhile is not seen before then.
#[derive(Debug)]
pub struct LinkReader {
    iface: String,
    files: [Option<std::fs::File>; 3],
    /// Files opened so far.
    opened: u64,
}

impl LinkReader {
    /// A reader of `iface`'s link; nothing is opened until the first read.
    pub fn new(iface: &str) -> LinkReader {
        LinkReader {
            iface: iface.to_string(),
            files: [None, None, None],
            opened: 0,
        }
    }

    /// Whether the interface is up (administratively, with its carrier) and its index;
    /// None when there is no such interface.
    pub fn read(&mut self) -> Option<(bool, u32)> {
        let flags = self.number(0)?;
        let index = self.number(1)?;
        // Administratively up (IFF_UP) with the carrier on: a CAN controller drops its
        // carrier at bus-off; `carrier` cannot be read while the interface is down.
        let up = flags & 0x1 != 0 && self.number(2) == Some(1);
        Some((up, index))
    }

    /// Attribute `k`'s number, read from its open file (opened first if it is not).
    fn number(&mut self, k: usize) -> Option<u32> {
        use std::os::unix::fs::FileExt;
        let mut buf = [0u8; 32];
        for _ in 0..2 {
            if self.files[k].is_none() {
                let path = format!("/sys/class/net/{}/{}", self.iface, LINK_FILES[k]);
                self.files[k] = Some(std::fs::File::open(path).ok()?);
                self.opened += 1;
            }
            match self.files[k].as_ref()?.read_at(&mut buf, 0) {
                Ok(n) => return parse_number(std::str::from_utf8(&buf[..n]).ok()?),
                // No carrier to tell: the interface is down.
                Err(e) if e.raw_os_error() == Some(libc::EINVAL) => return None,
                // The interface went (ENODEV): its name may be another's now.
                Err(_) => self.files[k] = None,
            }
        }
        None
    }
}

/// A sysfs number, decimal or 0x-hex, surrounded by white space.
fn parse_number(s: &str) -> Option<u32> {
    let s = s.trim();
    match s.strip_prefix("0x") {
        Some(hex) => u32::from_str_radix(hex, 16).ok(),
        None => s.parse().ok(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_reader_reads_what_link_reads_from_files_it_keeps_open() {
        // Every Linux host has its loopback interface.
        let mut r = LinkReader::new("lo");
        let first = r.read();
        assert!(first.is_some(), "lo has a link state");
        assert_eq!(first, link("lo"));
        assert!(r.files.iter().all(Option::is_some), "{r:?}");
        assert_eq!(r.opened, 3);
        for _ in 0..10 {
            assert_eq!(r.read(), first);
        }
        assert_eq!(r.opened, 3, "no file opened again");
    }

    #[test]
    fn a_missing_interface_has_no_link_and_is_looked_for_again() {
        let mut r = LinkReader::new("nosuch-if0");
        assert_eq!(r.read(), None);
        assert_eq!(r.read(), None);
        assert!(r.files.iter().all(Option::is_none));
        assert_eq!(parse_number(" 0x1003\n"), Some(0x1003));
        assert_eq!(parse_number("7\n"), Some(7));
        assert_eq!(parse_number("x"), None);
    }
}
