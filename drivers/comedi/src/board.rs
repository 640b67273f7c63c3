//! The safe wrapper over comedilib: a board opened by path, described once, and the
//! single-sample and bit-field calls the card makes.
//!
//! This module holds the crate's only `unsafe` code: each block calls one comedilib
//! function on the handle this [`Board`] owns, with a SAFETY note. A [`Board`] is `Send`
//! but not `Sync`: comedilib's handle may move between threads but is used by one at a
//! time (the card keeps it behind a mutex).
//!
//! Real-time: [`Daq`]'s calls are one `ioctl` each (`COMEDI_INSN`), allocation-free but
//! on an error path (the message); describing and opening allocate.

#![allow(
    unsafe_code,
    reason = "the FFI boundary to comedilib; every block has its SAFETY note"
)]

use comedi_sys as sys;
use std::ffi::{CStr, CString};
use std::os::raw::c_uint;
use std::ptr::NonNull;

/// What kind of subdevice (comedi's `COMEDI_SUBD_*`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    /// Analog input.
    Ai,
    /// Analog output.
    Ao,
    /// Digital input.
    Di,
    /// Digital output.
    Do,
    /// Digital input/output, direction per channel.
    Dio,
    /// Counter.
    Counter,
    /// Anything else (timer, memory, calibration, serial, PWM, unused), by comedi's number.
    Other(i32),
}

impl Kind {
    fn from_raw(t: i32) -> Kind {
        match t as c_uint {
            sys::COMEDI_SUBD_AI => Kind::Ai,
            sys::COMEDI_SUBD_AO => Kind::Ao,
            sys::COMEDI_SUBD_DI => Kind::Di,
            sys::COMEDI_SUBD_DO => Kind::Do,
            sys::COMEDI_SUBD_DIO => Kind::Dio,
            sys::COMEDI_SUBD_COUNTER => Kind::Counter,
            _ => Kind::Other(t),
        }
    }
}

impl std::fmt::Display for Kind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Kind::Ai => f.write_str("AI"),
            Kind::Ao => f.write_str("AO"),
            Kind::Di => f.write_str("DI"),
            Kind::Do => f.write_str("DO"),
            Kind::Dio => f.write_str("DIO"),
            Kind::Counter => f.write_str("COUNTER"),
            Kind::Other(n) => write!(f, "type {n}"),
        }
    }
}

/// A physical unit of a range (comedi's `UNIT_*`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RangeUnit {
    /// Volts.
    Volt,
    /// Milliamperes.
    MilliAmpere,
    /// None (a fraction of full scale, or a driver-specific unit).
    None,
}

/// One entry of a channel's range table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Range {
    /// Physical value at raw 0.
    pub min: f64,
    /// Physical value at raw `maxdata`.
    pub max: f64,
    /// Its unit.
    pub unit: RangeUnit,
}

/// One channel as the board describes it.
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelDesc {
    /// The largest raw value.
    pub maxdata: u32,
    /// Its range table.
    pub ranges: Vec<Range>,
}

/// One subdevice as the board describes it.
#[derive(Debug, Clone, PartialEq)]
pub struct SubdeviceDesc {
    /// Its kind.
    pub kind: Kind,
    /// comedi's `SDF_*` flags.
    pub flags: u32,
    /// Its channels.
    pub channels: Vec<ChannelDesc>,
}

/// A board as comedilib describes it.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardDesc {
    /// The kernel driver's name (`comedi_test`).
    pub driver: String,
    /// The board's name.
    pub board: String,
    /// Its subdevices, by number.
    pub subdevices: Vec<SubdeviceDesc>,
}

/// The most channels of one subdevice, and ranges of one channel, a description takes
/// (comedi's own channel field is 16 bits wide; real boards have at most a few hundred
/// channels and a few dozen ranges).
pub const MAX_DESCRIBED: usize = 4096;

/// A comedilib call that failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{call} on {path}: {message} (errno {code})")]
pub struct ComediError {
    /// The comedilib function.
    pub call: &'static str,
    /// The board's path.
    pub path: String,
    /// comedilib's error number (an errno, or one of comedilib's own from 0x1000 on).
    pub code: i32,
    /// comedilib's text for it.
    pub message: String,
}

impl ComediError {
    /// True when the board is gone (detached with `comedi_config -r`, unplugged, its
    /// driver unloaded): the card goes offline and opens it again later.
    pub fn gone(&self) -> bool {
        [
            libc_errno::ENODEV,
            libc_errno::ENXIO,
            libc_errno::EBADF,
            libc_errno::EIO,
        ]
        .contains(&self.code)
    }
}

/// The errno values [`ComediError::gone`] tells a board gone by.
mod libc_errno {
    pub const EIO: i32 = 5;
    pub const ENXIO: i32 = 6;
    pub const EBADF: i32 = 9;
    pub const ENODEV: i32 = 19;
}

/// A board's single-sample calls, as the card makes them: [`Board`], or a test's
/// stand-in. Real-time: each call is one bounded system call on a real board.
pub trait Daq: Send {
    /// The board's description.
    fn describe(&mut self) -> Result<BoardDesc, ComediError>;
    /// One sample of `channel` of `subdevice`, in `range` against `aref`.
    fn data_read(
        &mut self,
        subdevice: u32,
        channel: u32,
        range: u32,
        aref: u32,
    ) -> Result<u32, ComediError>;
    /// Writes one sample.
    fn data_write(
        &mut self,
        subdevice: u32,
        channel: u32,
        range: u32,
        aref: u32,
        data: u32,
    ) -> Result<(), ComediError>;
    /// Makes a DIO channel an output (`true`) or input.
    fn dio_config(&mut self, subdevice: u32, channel: u32, output: bool)
    -> Result<(), ComediError>;
    /// Whether a DIO channel is an output now.
    fn dio_get_config(&mut self, subdevice: u32, channel: u32) -> Result<bool, ComediError>;
    /// Writes the channels `base + i` whose bit `i` is in `mask` to that bit of `bits`
    /// (none when `mask` is 0), then reads all 32 from `base` on, in one call.
    fn bitfield(
        &mut self,
        subdevice: u32,
        base: u32,
        mask: u32,
        bits: u32,
    ) -> Result<u32, ComediError>;
}

/// A comedi board, opened.
pub struct Board {
    handle: NonNull<sys::comedi_t>,
    path: String,
}

// SAFETY: comedilib's handle is a heap struct with the device's file descriptor and its
// cached description; it has no thread affinity. `Board` is not `Sync` (the raw pointer),
// so only one thread at a time reaches it.
unsafe impl Send for Board {}

impl Board {
    /// Opens the board at `path` (`/dev/comedi0`). Fails when the file is absent or the
    /// board is not configured (`comedi_config`).
    ///
    /// The path must be a character device of the comedi driver (its major number in
    /// `/proc/devices`): comedilib opens it read-write and sends it comedi's ioctls, which
    /// another device (a watchdog, a serial port waiting for carrier) must never get.
    pub fn open(path: &str) -> Result<Board, ComediError> {
        check_device(path)?;
        let c = CString::new(path).map_err(|_| ComediError {
            call: "comedi_open",
            path: path.escape_debug().to_string(),
            code: 0,
            message: "the path has a NUL byte".into(),
        })?;
        quiet();
        clear_errno();
        // SAFETY: `c` is a NUL-terminated string that outlives the call; comedi_open
        // returns NULL or a handle this Board then owns.
        let handle = unsafe { sys::comedi_open(c.as_ptr()) };
        match NonNull::new(handle) {
            Some(handle) => Ok(Board {
                handle,
                path: path.to_string(),
            }),
            None => Err(error("comedi_open", path)),
        }
    }

    /// Its path.
    pub fn path(&self) -> &str {
        &self.path
    }

    fn ptr(&self) -> *mut sys::comedi_t {
        self.handle.as_ptr()
    }

    fn err(&self, call: &'static str) -> ComediError {
        error(call, &self.path)
    }

    fn check(&self, call: &'static str, rc: i32) -> Result<i32, ComediError> {
        if rc < 0 { Err(self.err(call)) } else { Ok(rc) }
    }

    fn name(
        &self,
        call: &'static str,
        p: *const std::os::raw::c_char,
    ) -> Result<String, ComediError> {
        if p.is_null() {
            return Err(self.err(call));
        }
        // SAFETY: non-null, a NUL-terminated string in the handle's cached device info,
        // valid while the handle is open; copied out at once.
        Ok(unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned())
    }
}

impl Drop for Board {
    fn drop(&mut self) {
        // SAFETY: the handle is open and owned; nothing uses it after this.
        unsafe { sys::comedi_close(self.ptr()) };
    }
}

impl Daq for Board {
    fn describe(&mut self) -> Result<BoardDesc, ComediError> {
        // SAFETY (this and the calls below): the handle is open; each call reads the
        // description comedilib cached at open, for indices checked against its counts.
        let driver = self.name("comedi_get_driver_name", unsafe {
            sys::comedi_get_driver_name(self.ptr())
        })?;
        let board = self.name("comedi_get_board_name", unsafe {
            sys::comedi_get_board_name(self.ptr())
        })?;
        let n = self.check("comedi_get_n_subdevices", unsafe {
            sys::comedi_get_n_subdevices(self.ptr())
        })?;
        let mut subdevices = Vec::new();
        for s in 0..n as c_uint {
            let kind = self.check("comedi_get_subdevice_type", unsafe {
                sys::comedi_get_subdevice_type(self.ptr(), s)
            })?;
            let kind = Kind::from_raw(kind);
            let flags = match kind {
                Kind::Other(_) => 0,
                _ => self.check("comedi_get_subdevice_flags", unsafe {
                    sys::comedi_get_subdevice_flags(self.ptr(), s)
                })? as u32,
            };
            let count = match kind {
                Kind::Other(_) => 0,
                _ => self.check("comedi_get_n_channels", unsafe {
                    sys::comedi_get_n_channels(self.ptr(), s)
                })?,
            };
            let mut channels = Vec::new();
            for ch in 0..(count as usize).min(MAX_DESCRIBED) as c_uint {
                let maxdata = unsafe { sys::comedi_get_maxdata(self.ptr(), s, ch) };
                let mut ranges = Vec::new();
                if matches!(kind, Kind::Ai | Kind::Ao) {
                    let n = self.check("comedi_get_n_ranges", unsafe {
                        sys::comedi_get_n_ranges(self.ptr(), s, ch)
                    })?;
                    for r in 0..(n as usize).min(MAX_DESCRIBED) as c_uint {
                        let p = unsafe { sys::comedi_get_range(self.ptr(), s, ch, r) };
                        if p.is_null() {
                            return Err(self.err("comedi_get_range"));
                        }
                        // SAFETY: non-null, a range in the cached description.
                        let range = unsafe { *p };
                        ranges.push(Range {
                            min: range.min,
                            max: range.max,
                            unit: match range.unit {
                                sys::UNIT_volt => RangeUnit::Volt,
                                sys::UNIT_mA => RangeUnit::MilliAmpere,
                                _ => RangeUnit::None,
                            },
                        });
                    }
                }
                channels.push(ChannelDesc { maxdata, ranges });
            }
            subdevices.push(SubdeviceDesc {
                kind,
                flags,
                channels,
            });
        }
        Ok(BoardDesc {
            driver,
            board,
            subdevices,
        })
    }

    fn data_read(
        &mut self,
        subdevice: u32,
        channel: u32,
        range: u32,
        aref: u32,
    ) -> Result<u32, ComediError> {
        let mut data: sys::lsampl_t = 0;
        clear_errno();
        // SAFETY: the handle is open; `data` is a valid place for one sample.
        let rc = unsafe {
            sys::comedi_data_read(self.ptr(), subdevice, channel, range, aref, &mut data)
        };
        self.check("comedi_data_read", rc).map(|_| data)
    }

    fn data_write(
        &mut self,
        subdevice: u32,
        channel: u32,
        range: u32,
        aref: u32,
        data: u32,
    ) -> Result<(), ComediError> {
        clear_errno();
        // SAFETY: the handle is open; the sample is passed by value.
        let rc =
            unsafe { sys::comedi_data_write(self.ptr(), subdevice, channel, range, aref, data) };
        self.check("comedi_data_write", rc).map(|_| ())
    }

    fn dio_config(
        &mut self,
        subdevice: u32,
        channel: u32,
        output: bool,
    ) -> Result<(), ComediError> {
        let dir = if output {
            sys::COMEDI_OUTPUT
        } else {
            sys::COMEDI_INPUT
        };
        clear_errno();
        // SAFETY: the handle is open; plain values.
        let rc = unsafe { sys::comedi_dio_config(self.ptr(), subdevice, channel, dir) };
        self.check("comedi_dio_config", rc).map(|_| ())
    }

    fn dio_get_config(&mut self, subdevice: u32, channel: u32) -> Result<bool, ComediError> {
        let mut dir: c_uint = 0;
        clear_errno();
        // SAFETY: the handle is open; `dir` is a valid place for the answer.
        let rc = unsafe { sys::comedi_dio_get_config(self.ptr(), subdevice, channel, &mut dir) };
        self.check("comedi_dio_get_config", rc)
            .map(|_| dir == sys::COMEDI_OUTPUT)
    }

    fn bitfield(
        &mut self,
        subdevice: u32,
        base: u32,
        mask: u32,
        bits: u32,
    ) -> Result<u32, ComediError> {
        let mut bits = bits;
        clear_errno();
        // SAFETY: the handle is open; `bits` is a valid place for the bits read back.
        let rc = unsafe { sys::comedi_dio_bitfield2(self.ptr(), subdevice, mask, &mut bits, base) };
        self.check("comedi_dio_bitfield2", rc).map(|_| bits)
    }
}

/// comedi's character-device major number in the kernel (`COMEDI_MAJOR`), for when the
/// module is not loaded to say so in `/proc/devices`.
pub const COMEDI_MAJOR: u64 = 98;

/// Checks that `path` is a comedi character device, from `stat` (nothing opened): the
/// wrong kind of file is named as such whether or not comedi is loaded.
fn check_device(path: &str) -> Result<(), ComediError> {
    use driver_api::node::Node;
    let refuse = |code: i32, message: String| ComediError {
        call: "comedi_open",
        path: path.escape_debug().to_string(),
        code,
        message,
    };
    let node = Node::of(std::path::Path::new(path)).map_err(|e| {
        let text = e.to_string();
        let text = text
            .split(" (os error")
            .next()
            .unwrap_or_default()
            .to_string();
        refuse(e.raw_os_error().unwrap_or(0), text)
    })?;
    let loaded = comedi_major();
    let comedi = loaded.unwrap_or(COMEDI_MAJOR);
    match node {
        Node::Char { major, .. } if major == comedi => {}
        other => {
            return Err(refuse(
                libc_errno::ENODEV,
                format!(
                    "not a comedi device: it is {other} (comedi's are character devices of \
                     major {comedi}, /dev/comediN)"
                ),
            ));
        }
    }
    if loaded.is_none() {
        return Err(refuse(
            libc_errno::ENODEV,
            "the comedi driver is not loaded (no comedi in /proc/devices)".into(),
        ));
    }
    Ok(())
}

/// comedi's character-device major number, from `/proc/devices`.
fn comedi_major() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/devices").ok()?;
    text.lines()
        .skip_while(|l| !l.starts_with("Character devices"))
        .take_while(|l| !l.is_empty())
        .find_map(|l| {
            let (n, name) = l.trim().split_once(' ')?;
            (name.trim() == "comedi").then(|| n.parse().ok()).flatten()
        })
}

/// Turns off comedilib's own error printing (hwgw reports its errors itself); once.
fn quiet() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // SAFETY: sets a global of comedilib's; no handle involved.
        unsafe { sys::comedi_loglevel(0) };
    });
}

/// Where comedilib's own error numbers start (`COMEDI_NOERROR`); below are errno values.
const COMEDI_OWN_ERRORS: i32 = 0x1000;

/// Clears the thread's errno before a comedilib call, so [`error`] reads this call's.
fn clear_errno() {
    // SAFETY: `__errno_location` returns the calling thread's errno, valid for the
    // thread's life; writing 0 there is what C code does before a call it checks.
    unsafe { *libc::__errno_location() = 0 };
}

/// The error of the comedilib call that just failed on this thread.
fn error(call: &'static str, path: &str) -> ComediError {
    // The system's error number, cleared before the call: the kernel's answer when the
    // call failed in a system call. Else comedilib's own (0x1000 on), which it does not
    // clear: an errno-range value there is an earlier call's, not this one's.
    let os = std::io::Error::last_os_error().raw_os_error().unwrap_or(0);
    // SAFETY: reads comedilib's last error number.
    let lib = unsafe { sys::comedi_errno() };
    let code = if os != 0 {
        os
    } else if lib >= COMEDI_OWN_ERRORS {
        lib
    } else {
        return ComediError {
            call,
            path: path.to_string(),
            code: 0,
            message: "comedilib failed without saying why".into(),
        };
    };
    // SAFETY: comedi_strerror returns a pointer to a static string (or NULL).
    let text = unsafe { sys::comedi_strerror(code) };
    let message = if text.is_null() {
        format!("error {code}")
    } else {
        // SAFETY: non-null, NUL-terminated, static.
        unsafe { CStr::from_ptr(text) }
            .to_string_lossy()
            .into_owned()
    };
    ComediError {
        call,
        path: path.to_string(),
        code,
        message,
    }
}

/// comedilib's own `comedi_to_phys` of `data` in `range` (out-of-range ends as numbers,
/// not NaN): the reference hwgw's scales are checked against.
pub fn comedilib_to_phys(data: u32, range: &Range, maxdata: u32) -> f64 {
    let mut r = sys::comedi_range {
        min: range.min,
        max: range.max,
        unit: match range.unit {
            RangeUnit::Volt => sys::UNIT_volt,
            RangeUnit::MilliAmpere => sys::UNIT_mA,
            RangeUnit::None => sys::UNIT_none,
        },
    };
    // SAFETY: sets a global of comedilib's, then converts with `r`, a valid range that
    // outlives the call.
    unsafe {
        sys::comedi_set_global_oor_behavior(sys::COMEDI_OOR_NUMBER);
        sys::comedi_to_phys(data, &mut r, maxdata)
    }
}
