//! The SDO client (CiA 301 §7.2.4.3): reading (upload) and writing (download) one entry of
//! a node's object dictionary, expedited (up to 4 bytes in one frame) or segmented (7
//! bytes a frame, the toggle bit alternating), as a state machine without I/O: it makes
//! the request frames and takes the response frames; the caller sends them on
//! COB-ID 0x600 + node and feeds back what comes on 0x580 + node, and bounds the wait.
//!
//! A server's abort is an error naming the object and the abort code's meaning
//! ([`abort_meaning`]). A response that does not fit the transfer (another command, the
//! wrong object, the toggle bit not alternated, more data than announced) ends it with an
//! error, and [`SdoError::abort_frame`] gives the abort to send the server. An upload
//! larger than [`MAX_UPLOAD`] is aborted: a hostile node cannot make the client grow
//! without bound.
//!
//! ```
//! use driver_canopen::sdo::{Step, Upload};
//!
//! // Read 0x1017 sub 0; the node answers expedited, two bytes: 500.
//! let (mut up, request) = Upload::start(0x1017, 0);
//! assert_eq!(request, [0x40, 0x17, 0x10, 0, 0, 0, 0, 0]);
//! let step = up.on_response(&[0x4B, 0x17, 0x10, 0, 0xF4, 0x01, 0, 0])?;
//! assert_eq!(step, Step::Done(vec![0xF4, 0x01]));
//! # Ok::<(), driver_canopen::sdo::SdoError>(())
//! ```

/// The most bytes an upload takes (a domain larger than this is aborted).
pub const MAX_UPLOAD: usize = 1 << 20;

/// What to do next.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Step {
    /// Send this request and feed the response back.
    Send([u8; 8]),
    /// The transfer is done: the data read (empty for a download).
    Done(Vec<u8>),
}

/// Why a transfer failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SdoError {
    /// The server aborted it.
    #[error("SDO {index:#06x} sub {sub}: the node aborted with {code:#010x}: {}", abort_meaning(*code))]
    Aborted {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The abort code.
        code: u32,
    },
    /// The server's response does not fit the transfer; the client aborts with `code`.
    #[error("SDO {index:#06x} sub {sub}: {why} (the client aborts with {code:#010x}: {})", abort_meaning(*code))]
    Protocol {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// What was wrong.
        why: String,
        /// The abort code the client sends.
        code: u32,
    },
}

impl SdoError {
    /// The abort frame the client sends the server for this error (none when the server
    /// aborted).
    pub fn abort_frame(&self) -> Option<[u8; 8]> {
        match self {
            SdoError::Aborted { .. } => None,
            SdoError::Protocol {
                index, sub, code, ..
            } => Some(abort(*index, *sub, *code)),
        }
    }
}

/// Abort codes the client sends.
pub mod code {
    /// Toggle bit not alternated.
    pub const TOGGLE: u32 = 0x0503_0000;
    /// SDO protocol timed out.
    pub const TIMEOUT: u32 = 0x0504_0000;
    /// Client/server command specifier not valid or unknown.
    pub const COMMAND: u32 = 0x0504_0001;
    /// Out of memory.
    pub const MEMORY: u32 = 0x0504_0005;
    /// General error.
    pub const GENERAL: u32 = 0x0800_0000;
    /// Data type does not match, length of service parameter does not match.
    pub const LENGTH: u32 = 0x0607_0010;
}

/// The meaning of an SDO abort code (CiA 301 Table 22).
pub fn abort_meaning(code: u32) -> &'static str {
    match code {
        0x0503_0000 => "toggle bit not alternated",
        0x0504_0000 => "SDO protocol timed out",
        0x0504_0001 => "client/server command specifier not valid or unknown",
        0x0504_0002 => "invalid block size",
        0x0504_0003 => "invalid sequence number",
        0x0504_0004 => "CRC error",
        0x0504_0005 => "out of memory",
        0x0601_0000 => "unsupported access to an object",
        0x0601_0001 => "attempt to read a write only object",
        0x0601_0002 => "attempt to write a read only object",
        0x0602_0000 => "object does not exist in the object dictionary",
        0x0604_0041 => "object cannot be mapped to the PDO",
        0x0604_0042 => {
            "the number and length of the objects to be mapped would exceed the PDO length"
        }
        0x0604_0043 => "general parameter incompatibility",
        0x0604_0047 => "general internal incompatibility in the device",
        0x0606_0000 => "access failed due to a hardware error",
        0x0607_0010 => "data type does not match, length of service parameter does not match",
        0x0607_0012 => "data type does not match, length of service parameter too high",
        0x0607_0013 => "data type does not match, length of service parameter too low",
        0x0609_0011 => "sub-index does not exist",
        0x0609_0030 => "invalid value for parameter (download only)",
        0x0609_0031 => "value of parameter written too high (download only)",
        0x0609_0032 => "value of parameter written too low (download only)",
        0x0609_0036 => "maximum value is less than minimum value",
        0x060A_0023 => "resource not available: SDO connection",
        0x0800_0000 => "general error",
        0x0800_0020 => "data cannot be transferred or stored to the application",
        0x0800_0021 => {
            "data cannot be transferred or stored to the application because of local control"
        }
        0x0800_0022 => {
            "data cannot be transferred or stored to the application because of the present device state"
        }
        0x0800_0023 => {
            "object dictionary dynamic generation fails or no object dictionary is present"
        }
        0x0800_0024 => "no data available",
        _ => "an abort code CiA 301 does not list",
    }
}

/// An abort frame for `index`, `sub` with `code`.
pub fn abort(index: u16, sub: u8, code: u32) -> [u8; 8] {
    let mut f = [0x80, 0, 0, sub, 0, 0, 0, 0];
    f[1..3].copy_from_slice(&index.to_le_bytes());
    f[4..8].copy_from_slice(&code.to_le_bytes());
    f
}

/// A request frame with command byte `cmd` for `index`, `sub`, and `data` (4 bytes).
fn frame(cmd: u8, index: u16, sub: u8, data: [u8; 4]) -> [u8; 8] {
    let i = index.to_le_bytes();
    [cmd, i[0], i[1], sub, data[0], data[1], data[2], data[3]]
}

/// What the transfers share: the object, and the checks of a response.
#[derive(Debug, Clone, Copy)]
struct Object {
    index: u16,
    sub: u8,
}

impl Object {
    fn fail(self, why: impl Into<String>, code: u32) -> SdoError {
        SdoError::Protocol {
            index: self.index,
            sub: self.sub,
            why: why.into(),
            code,
        }
    }

    /// The response as 8 bytes, or the server's abort as an error.
    fn response(self, r: &[u8]) -> Result<[u8; 8], SdoError> {
        let r: [u8; 8] = r.try_into().map_err(|_| {
            self.fail(
                format!("a response of {} bytes, not 8", r.len()),
                code::GENERAL,
            )
        })?;
        if r[0] == 0x80 {
            return Err(SdoError::Aborted {
                index: self.index,
                sub: self.sub,
                code: u32::from_le_bytes([r[4], r[5], r[6], r[7]]),
            });
        }
        Ok(r)
    }

    /// Checks an initiate response's object.
    fn echoed(self, r: &[u8; 8]) -> Result<(), SdoError> {
        let (index, sub) = (u16::from_le_bytes([r[1], r[2]]), r[3]);
        if (index, sub) != (self.index, self.sub) {
            return Err(self.fail(
                format!("the response is for {index:#06x} sub {sub}"),
                code::GENERAL,
            ));
        }
        Ok(())
    }
}

/// Reading one entry.
#[derive(Debug, Clone)]
pub struct Upload {
    object: Object,
    /// Segments come (after the initiate response).
    segmented: bool,
    toggle: bool,
    /// The size the server announced, if it did.
    size: Option<usize>,
    data: Vec<u8>,
}

impl Upload {
    /// Starts reading `index`, `sub`: the transfer and its first request.
    pub fn start(index: u16, sub: u8) -> (Upload, [u8; 8]) {
        let up = Upload {
            object: Object { index, sub },
            segmented: false,
            toggle: false,
            size: None,
            data: Vec::new(),
        };
        (up, frame(0x40, index, sub, [0; 4]))
    }

    /// Takes the server's response: the next request, or the data read.
    pub fn on_response(&mut self, response: &[u8]) -> Result<Step, SdoError> {
        let o = self.object;
        let r = o.response(response)?;
        if !self.segmented {
            if r[0] >> 5 != 2 {
                return Err(o.fail(
                    format!("command {:#04x} answering an upload", r[0]),
                    code::COMMAND,
                ));
            }
            o.echoed(&r)?;
            let (e, s) = (r[0] & 0x02 != 0, r[0] & 0x01 != 0);
            if e {
                // Expedited: the data in the frame (all four bytes when no size is given).
                let n = if s {
                    4 - usize::from((r[0] >> 2) & 0x03)
                } else {
                    4
                };
                return Ok(Step::Done(r[4..4 + n].to_vec()));
            }
            if s {
                let size = u32::from_le_bytes([r[4], r[5], r[6], r[7]]) as usize;
                if size > MAX_UPLOAD {
                    return Err(o.fail(
                        format!("{size} bytes announced: at most {MAX_UPLOAD} are read"),
                        code::MEMORY,
                    ));
                }
                self.size = Some(size);
                self.data.reserve(size);
            }
            self.segmented = true;
            return Ok(Step::Send(self.segment_request()));
        }
        if r[0] >> 5 != 0 {
            return Err(o.fail(
                format!("command {:#04x} answering an upload segment", r[0]),
                code::COMMAND,
            ));
        }
        if (r[0] & 0x10 != 0) != self.toggle {
            return Err(o.fail("the toggle bit did not alternate", code::TOGGLE));
        }
        let n = 7 - usize::from((r[0] >> 1) & 0x07);
        self.data.extend_from_slice(&r[1..1 + n]);
        if self.data.len() > self.size.unwrap_or(MAX_UPLOAD) {
            return Err(o.fail(
                format!(
                    "{} bytes sent: more than the {} announced",
                    self.data.len(),
                    self.size.unwrap_or(MAX_UPLOAD)
                ),
                if self.size.is_some() {
                    code::LENGTH
                } else {
                    code::MEMORY
                },
            ));
        }
        if r[0] & 0x01 != 0 {
            if let Some(size) = self.size
                && size != self.data.len()
            {
                return Err(o.fail(
                    format!("{} bytes sent, {size} announced", self.data.len()),
                    code::LENGTH,
                ));
            }
            return Ok(Step::Done(std::mem::take(&mut self.data)));
        }
        self.toggle = !self.toggle;
        Ok(Step::Send(self.segment_request()))
    }

    fn segment_request(&self) -> [u8; 8] {
        [0x60 | (u8::from(self.toggle) << 4), 0, 0, 0, 0, 0, 0, 0]
    }
}

/// Writing one entry.
#[derive(Debug, Clone)]
pub struct Download {
    object: Object,
    data: Vec<u8>,
    /// Bytes sent so far (segmented).
    sent: usize,
    toggle: bool,
    /// The initiate request is answered.
    initiated: bool,
    expedited: bool,
}

impl Download {
    /// Starts writing `data` to `index`, `sub` (expedited up to 4 bytes, else segmented
    /// with the size given): the transfer and its first request.
    pub fn start(index: u16, sub: u8, data: &[u8]) -> (Download, [u8; 8]) {
        let expedited = (1..=4).contains(&data.len());
        let request = if expedited {
            let mut d = [0u8; 4];
            d[..data.len()].copy_from_slice(data);
            let n = (4 - data.len()) as u8;
            frame(0x20 | (n << 2) | 0x03, index, sub, d)
        } else {
            frame(0x21, index, sub, (data.len() as u32).to_le_bytes())
        };
        let down = Download {
            object: Object { index, sub },
            data: data.to_vec(),
            sent: 0,
            toggle: false,
            initiated: false,
            expedited,
        };
        (down, request)
    }

    /// Takes the server's response: the next request, or done.
    pub fn on_response(&mut self, response: &[u8]) -> Result<Step, SdoError> {
        let o = self.object;
        let r = o.response(response)?;
        if !self.initiated {
            if r[0] != 0x60 {
                return Err(o.fail(
                    format!("command {:#04x} answering a download", r[0]),
                    code::COMMAND,
                ));
            }
            o.echoed(&r)?;
            self.initiated = true;
            if self.expedited {
                return Ok(Step::Done(Vec::new()));
            }
        } else {
            if r[0] & 0xE0 != 0x20 {
                return Err(o.fail(
                    format!("command {:#04x} answering a download segment", r[0]),
                    code::COMMAND,
                ));
            }
            if (r[0] & 0x10 != 0) != self.toggle {
                return Err(o.fail("the toggle bit did not alternate", code::TOGGLE));
            }
            self.toggle = !self.toggle;
            if self.sent == self.data.len() {
                return Ok(Step::Done(Vec::new()));
            }
        }
        Ok(Step::Send(self.next_segment()))
    }

    fn next_segment(&mut self) -> [u8; 8] {
        let rest = &self.data[self.sent..];
        let n = rest.len().min(7);
        let last = self.sent + n == self.data.len();
        let mut f = [0u8; 8];
        f[0] = (u8::from(self.toggle) << 4) | (((7 - n) as u8) << 1) | u8::from(last);
        f[1..1 + n].copy_from_slice(&rest[..n]);
        self.sent += n;
        f
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    #[test]
    fn a_segmented_upload_of_a_name() {
        // "hwgw IO401" (10 bytes) from 0x1008: size announced, two segments.
        let (mut up, req) = Upload::start(0x1008, 0);
        assert_eq!(req, [0x40, 0x08, 0x10, 0, 0, 0, 0, 0]);
        let s = up.on_response(&[0x41, 0x08, 0x10, 0, 10, 0, 0, 0]).unwrap();
        assert_eq!(s, Step::Send([0x60, 0, 0, 0, 0, 0, 0, 0]));
        let s = up
            .on_response(&[0x00, b'h', b'w', b'g', b'w', b' ', b'I', b'O'])
            .unwrap();
        assert_eq!(s, Step::Send([0x70, 0, 0, 0, 0, 0, 0, 0]));
        // Last: 3 bytes, n = 4 unused, c = 1, toggle 1.
        let s = up
            .on_response(&[0x10 | (4 << 1) | 1, b'4', b'0', b'1', 0, 0, 0, 0])
            .unwrap();
        assert_eq!(s, Step::Done(b"hwgw IO401".to_vec()));
    }

    #[test]
    fn a_segmented_download_and_an_expedited_one() {
        let data: Vec<u8> = (1..=9).collect();
        let (mut d, req) = Download::start(0x2002, 0, &data);
        assert_eq!(req, [0x21, 0x02, 0x20, 0, 9, 0, 0, 0]);
        let s = d.on_response(&[0x60, 0x02, 0x20, 0, 0, 0, 0, 0]).unwrap();
        assert_eq!(s, Step::Send([0x00, 1, 2, 3, 4, 5, 6, 7]));
        let s = d.on_response(&[0x20, 0, 0, 0, 0, 0, 0, 0]).unwrap();
        assert_eq!(s, Step::Send([0x10 | (5 << 1) | 1, 8, 9, 0, 0, 0, 0, 0]));
        let s = d.on_response(&[0x30, 0, 0, 0, 0, 0, 0, 0]).unwrap();
        assert_eq!(s, Step::Done(Vec::new()));
        // 0x1017 = 500 (two bytes): n = 2, e = s = 1.
        let (mut d, req) = Download::start(0x1017, 0, &500u16.to_le_bytes());
        assert_eq!(req, [0x2B, 0x17, 0x10, 0, 0xF4, 0x01, 0, 0]);
        let s = d.on_response(&[0x60, 0x17, 0x10, 0, 0, 0, 0, 0]).unwrap();
        assert_eq!(s, Step::Done(Vec::new()));
    }

    #[test]
    fn aborts_and_broken_responses_are_errors_that_name_the_object() {
        let (mut up, _) = Upload::start(0x6000, 3);
        let e = up.on_response(&abort(0x6000, 3, 0x0609_0011)).unwrap_err();
        assert_eq!(
            e.to_string(),
            "SDO 0x6000 sub 3: the node aborted with 0x06090011: sub-index does not exist"
        );
        assert_eq!(e.abort_frame(), None);
        // The toggle bit not alternated: the client aborts 0x05030000.
        let (mut up, _) = Upload::start(0x1008, 0);
        up.on_response(&[0x41, 0x08, 0x10, 0, 20, 0, 0, 0]).unwrap();
        up.on_response(&[0x00, 1, 2, 3, 4, 5, 6, 7]).unwrap();
        let e = up.on_response(&[0x00, 1, 2, 3, 4, 5, 6, 7]).unwrap_err();
        assert_eq!(e.abort_frame(), Some(abort(0x1008, 0, code::TOGGLE)));
        // Another object, a short frame, too much data announced.
        let (mut up, _) = Upload::start(0x1008, 0);
        assert!(up.on_response(&[0x43, 0x09, 0x10, 0, 1, 2, 3, 4]).is_err());
        let (mut up, _) = Upload::start(0x1008, 0);
        assert!(up.on_response(&[0x43, 0x08]).is_err());
        let (mut up, _) = Upload::start(0x1008, 0);
        let e = up
            .on_response(&[0x41, 0x08, 0x10, 0, 0xFF, 0xFF, 0xFF, 0xFF])
            .unwrap_err();
        assert_eq!(e.abort_frame(), Some(abort(0x1008, 0, code::MEMORY)));
    }

    #[test]
    fn a_server_sending_more_than_it_announced_is_cut_off() {
        let (mut up, _) = Upload::start(0x1008, 0);
        up.on_response(&[0x41, 0x08, 0x10, 0, 8, 0, 0, 0]).unwrap();
        up.on_response(&[0x00, 1, 2, 3, 4, 5, 6, 7]).unwrap();
        let e = up.on_response(&[0x10, 1, 2, 3, 4, 5, 6, 7]).unwrap_err();
        assert_eq!(e.abort_frame(), Some(abort(0x1008, 0, code::LENGTH)));
        // Without a size, no more than MAX_UPLOAD.
        let (mut up, _) = Upload::start(0x1008, 0);
        up.on_response(&[0x40, 0x08, 0x10, 0, 0, 0, 0, 0]).unwrap();
        let mut toggle = false;
        let mut failed = None;
        for _ in 0..=MAX_UPLOAD / 7 + 1 {
            let cmd = u8::from(toggle) << 4;
            match up.on_response(&[cmd, 0, 0, 0, 0, 0, 0, 0]) {
                Ok(_) => toggle = !toggle,
                Err(e) => {
                    failed = Some(e);
                    break;
                }
            }
        }
        assert_eq!(
            failed.unwrap().abort_frame(),
            Some(abort(0x1008, 0, code::MEMORY))
        );
    }
}
