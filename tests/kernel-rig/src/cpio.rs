//! The initramfs archive: the "newc" cpio format the kernel unpacks at boot.
//!
//! Only what an initramfs needs: directories and regular files, owned by root, in the
//! order given (a directory before what is inside it).
//!
//! ```
//! let mut a = kernel_rig::cpio::Archive::default();
//! a.dir("bin");
//! a.file("init", 0o755, b"#!/bin/sh\n");
//! let bytes = a.finish();
//! assert!(bytes.starts_with(b"070701"));
//! ```

/// An archive being written.
#[derive(Default)]
pub struct Archive {
    out: Vec<u8>,
    inode: u32,
}

impl Archive {
    /// Adds a directory (mode 0755).
    pub fn dir(&mut self, name: &str) {
        self.entry(name, 0o040_755, &[]);
    }

    /// Adds a regular file with permission bits `perm`.
    pub fn file(&mut self, name: &str, perm: u32, data: &[u8]) {
        self.entry(name, 0o100_000 | (perm & 0o7777), data);
    }

    fn entry(&mut self, name: &str, mode: u32, data: &[u8]) {
        self.inode += 1;
        let nlink = if mode & 0o040_000 != 0 { 2 } else { 1 };
        // Fields: ino mode uid gid nlink mtime filesize devmajor devminor rdevmajor
        // rdevminor namesize check; the name counts its terminating NUL.
        let fields = [
            self.inode,
            mode,
            0,
            0,
            nlink,
            0,
            data.len() as u32,
            0,
            0,
            0,
            0,
            name.len() as u32 + 1,
            0,
        ];
        self.out.extend_from_slice(b"070701");
        for f in fields {
            self.out.extend_from_slice(format!("{f:08x}").as_bytes());
        }
        self.out.extend_from_slice(name.as_bytes());
        self.out.push(0);
        self.pad();
        self.out.extend_from_slice(data);
        self.pad();
    }

    fn pad(&mut self) {
        while !self.out.len().is_multiple_of(4) {
            self.out.push(0);
        }
    }

    /// Closes the archive and returns its bytes.
    pub fn finish(mut self) -> Vec<u8> {
        self.entry("TRAILER!!!", 0, &[]);
        self.out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn headers_are_aligned_and_sized() {
        let mut a = Archive::default();
        a.file("ab", 0o644, b"xyz");
        let b = a.finish();
        // 110-byte header + "ab\0" = 113, padded to 116; data 3 padded to 4.
        assert_eq!(&b[..6], b"070701");
        assert_eq!(&b[54..62], b"00000003", "file size field");
        assert_eq!(&b[94..102], b"00000003", "name size field");
        assert_eq!(&b[110..113], b"ab\0");
        assert_eq!(&b[116..119], b"xyz");
        assert_eq!(&b[120..126], b"070701", "trailer header starts aligned");
        assert!(b.len().is_multiple_of(4));
    }
}
