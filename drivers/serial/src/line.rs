//! The serial line under a Firmata card: what the bus side needs of it (non-blocking reads
//! and writes, a descriptor to wait on), the real port opened through tokio-serial's
//! builder as mio-serial's non-blocking stream, and writing a whole message.

use std::io::{self, Read, Write};
use std::os::fd::BorrowedFd;

/// An open serial line: non-blocking reads and writes, and the descriptor to wait on.
pub trait Line: Send {
    /// Reads what is there (`WouldBlock` when nothing).
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize>;
    /// Writes what it can (`WouldBlock` when the line's buffer is full).
    fn write(&mut self, data: &[u8]) -> io::Result<usize>;
    /// The descriptor that becomes readable.
    fn fd(&self) -> BorrowedFd<'_>;
}

impl Line for mio_serial::SerialStream {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        Read::read(self, buf)
    }
    fn write(&mut self, data: &[u8]) -> io::Result<usize> {
        Write::write(self, data)
    }
    // mio-serial gives its descriptor only as a raw one.
    #[allow(
        unsafe_code,
        reason = "borrowing the stream's own descriptor for its lifetime"
    )]
    fn fd(&self) -> BorrowedFd<'_> {
        // SAFETY: the stream owns this descriptor and keeps it open while borrowed: the
        // borrow cannot outlive `&self`.
        unsafe { BorrowedFd::borrow_raw(std::os::fd::AsRawFd::as_raw_fd(self)) }
    }
}

/// Opens a line: the port's path and baud rate.
pub type Opener = Box<dyn FnMut(&str, u32) -> io::Result<Box<dyn Line>> + Send>;

/// Opens a real serial port (8N1, no flow control, exclusive: a second program cannot open
/// it while hwgw has it).
pub fn open_port(path: &str, baud: u32) -> io::Result<Box<dyn Line>> {
    let builder = tokio_serial::new(path, baud)
        .data_bits(tokio_serial::DataBits::Eight)
        .parity(tokio_serial::Parity::None)
        .stop_bits(tokio_serial::StopBits::One)
        .flow_control(tokio_serial::FlowControl::None);
    let stream = mio_serial::SerialStream::open(&builder).map_err(io::Error::from)?;
    Ok(Box::new(stream))
}

/// Writes all of `data`; a line whose buffer stays full is stuck.
pub fn send(line: &mut dyn Line, data: &[u8]) -> Result<(), String> {
    let mut rest = data;
    let mut waits = 0;
    while !rest.is_empty() {
        match line.write(rest) {
            Ok(0) => return Err("write: the port took nothing".into()),
            Ok(n) => rest = &rest[n..],
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) if e.kind() == io::ErrorKind::WouldBlock && waits < 100 => {
                // The line's buffer is full (a slow baud rate): wait for room, 1 s at most.
                waits += 1;
                let fd = line.fd();
                let mut p = [nix::poll::PollFd::new(fd, nix::poll::PollFlags::POLLOUT)];
                let _ = nix::poll::poll(&mut p, nix::poll::PollTimeout::from(10u8));
            }
            Err(e) => return Err(format!("write: {e}")),
        }
    }
    Ok(())
}
