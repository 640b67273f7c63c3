//! A pty pair made by socat (installed by the tests when missing): two serial ports joined
//! back to back, `line` (the master's end) and `unit` (the slave's end), as links in a
//! directory of their own.

use crate::peers::{SOCAT, ensure};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

/// A running pty pair; socat killed and the directory removed when dropped.
pub struct PtyPair {
    child: Child,
    /// The directory of the links `line` and `unit`.
    pub dir: PathBuf,
}

impl PtyPair {
    /// A pair whose links live in a temporary directory named after `tag` and the process,
    /// once both exist.
    pub fn new(tag: &str) -> PtyPair {
        ensure(&SOCAT);
        let dir = std::env::temp_dir().join(format!("hwgw-pty-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir)
            .unwrap_or_else(|e| panic!("cannot make {}: {e}", dir.display()));
        let child = Command::new("socat")
            .arg(format!(
                "pty,raw,echo=0,link={}",
                dir.join("line").display()
            ))
            .arg(format!(
                "pty,raw,echo=0,link={}",
                dir.join("unit").display()
            ))
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run socat: {e}"));
        let pair = PtyPair { child, dir };
        crate::wait_until("socat's ptys", || {
            pair.line().exists() && pair.unit().exists()
        });
        pair
    }

    /// The master's end.
    pub fn line(&self) -> PathBuf {
        self.dir.join("line")
    }

    /// The slave's end.
    pub fn unit(&self) -> PathBuf {
        self.dir.join("unit")
    }
}

impl Drop for PtyPair {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}
