//! Getting a machine ready to boot the rig: host packages, the guest kernel, the
//! initramfs. Everything lands under the rig directory (`target/kernel-rig/`), nothing
//! outside the checkout but the Debian packages themselves.
//!
//! ```no_run
//! let dir = kernel_rig::rig_dir();
//! let kernel = kernel_rig::prepare::kernel(&dir, &[("candump", "can-utils")])?;
//! println!("guest kernel {} at {}", kernel.version, kernel.vmlinuz.display());
//! # Ok::<(), kernel_rig::RigError>(())
//! ```

use crate::RigError;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Commands the rig itself needs on the host, with the Debian package of each.
pub const HOST_TOOLS: &[(&str, &str)] = &[
    ("qemu-system-x86_64", "qemu-system-x86"),
    ("depmod", "kmod"),
    ("modprobe", "kmod"),
    ("modinfo", "kmod"),
    ("ip", "iproute2"),
    ("dpkg-deb", "dpkg"),
];

/// The statically linked busybox the initramfs runs.
const BUSYBOX: &str = "/bin/busybox";

/// The modules the initramfs loads to mount the host's root (in dependency order).
const BOOT_MODULES: &[&str] = &["netfs", "9pnet", "9pnet_virtio", "9p", "overlay"];

/// A guest kernel ready to boot.
#[derive(Debug, Clone)]
pub struct Kernel {
    /// `uname -r` of the guest.
    pub version: String,
    /// The kernel image.
    pub vmlinuz: PathBuf,
    /// The tree whose `lib/modules/VERSION` holds its modules (with `modules.dep`).
    pub root: PathBuf,
    /// The initramfs.
    pub initramfs: PathBuf,
}

/// True when `cmd` is on the PATH (or in /usr/sbin, /sbin).
pub fn which(cmd: &str) -> bool {
    std::env::var_os("PATH")
        .map(|p| std::env::split_paths(&p).any(|d| d.join(cmd).is_file()))
        .unwrap_or(false)
        || Path::new("/usr/sbin").join(cmd).is_file()
        || Path::new("/sbin").join(cmd).is_file()
}

fn busybox_is_static() -> bool {
    // A static ELF has no PT_INTERP program header: look for the interpreter path.
    std::fs::read(BUSYBOX)
        .map(|b| {
            !b.windows(b"ld-linux".len())
                .take(8192)
                .any(|w| w == b"ld-linux")
        })
        .unwrap_or(false)
}

fn run(cmd: &mut Command) -> Result<String, RigError> {
    let what = format!("{cmd:?}");
    let out = cmd.output().map_err(|e| RigError::Command {
        command: what.clone(),
        problem: e.to_string(),
    })?;
    if !out.status.success() {
        return Err(RigError::Command {
            command: what,
            problem: format!(
                "{}: {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

fn is_root() -> bool {
    nix::unistd::geteuid().is_root()
}

/// Installs the Debian `packages` (as root, with apt; `--no-install-recommends`, so name
/// every package needed). Installs from concurrent test processes take turns (a lock file
/// under the temporary directory); a failed install is tried once more after
/// `apt-get update`.
pub fn apt_install(packages: &[&str]) -> Result<(), RigError> {
    if !is_root() || !which("apt-get") {
        return Err(RigError::Missing(format!(
            "the Debian packages {} are needed (install them as root: apt-get install {})",
            packages.join(", "),
            packages.join(" ")
        )));
    }
    let lock_path = std::env::temp_dir().join("hwgw-apt.lock");
    let lock = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&lock_path)
        .map_err(|e| RigError::io(&lock_path, e))?;
    lock.lock().map_err(|e| RigError::io(&lock_path, e))?;
    eprintln!("installing {}", packages.join(" "));
    let install = || {
        run(Command::new("apt-get")
            .args(["install", "-y", "-q", "--no-install-recommends"])
            .args(packages)
            .env("DEBIAN_FRONTEND", "noninteractive"))
    };
    if install().is_err() {
        run(Command::new("apt-get").args(["update", "-q"]))?;
        install()?;
    }
    Ok(())
}

/// Installs what is missing of the rig's own tools and of `extra` (command, package).
pub fn host_tools(extra: &[(&str, &str)]) -> Result<(), RigError> {
    let mut missing: Vec<&str> = HOST_TOOLS
        .iter()
        .chain(extra)
        .filter(|(cmd, _)| !which(cmd))
        .map(|(_, pkg)| *pkg)
        .collect();
    if !busybox_is_static() {
        missing.push("busybox-static");
    }
    missing.sort_unstable();
    missing.dedup();
    if missing.is_empty() {
        return Ok(());
    }
    apt_install(&missing)
}

/// The newest Debian 6.12 kernel package, as `(package, version)`.
fn kernel_package() -> Result<String, RigError> {
    if let Ok(p) = std::env::var("HWGW_RIG_KERNEL_PACKAGE") {
        return Ok(p);
    }
    let search = || {
        run(Command::new("apt-cache").args([
            "search",
            "--names-only",
            r"^linux-image-6\.12\.[0-9]+\+deb[0-9]+-amd64-unsigned$",
        ]))
    };
    let mut found = search()?;
    if found.trim().is_empty() && is_root() {
        run(Command::new("apt-get").args(["update", "-q"]))?;
        found = search()?;
    }
    let mut names: Vec<(u32, String)> = found
        .lines()
        .filter_map(|l| l.split_whitespace().next())
        .filter_map(|n| {
            let patch = n.strip_prefix("linux-image-6.12.")?.split('+').next()?;
            Some((patch.parse().ok()?, n.to_string()))
        })
        .collect();
    names.sort();
    names.pop().map(|(_, n)| n).ok_or_else(|| {
        RigError::Missing(
            "no linux-image-6.12.*-amd64-unsigned package in the apt lists (apt-get update?)"
                .into(),
        )
    })
}

/// The guest kernel and initramfs under `dir`, downloaded and built the first time.
/// `extra` are host commands the caller's tests need (command, Debian package).
pub fn kernel(dir: &Path, extra: &[(&str, &str)]) -> Result<Kernel, RigError> {
    host_tools(extra)?;
    std::fs::create_dir_all(dir).map_err(|e| RigError::io(dir, e))?;
    // One preparer at a time (test binaries may run in parallel under nextest).
    let lock_path = dir.join("prepare.lock");
    let lock = std::fs::File::create(&lock_path).map_err(|e| RigError::io(&lock_path, e))?;
    lock.lock().map_err(|e| RigError::io(&lock_path, e))?;

    let root = dir.join("kernel");
    let stamp = root.join("version");
    if !stamp.is_file() {
        let package = kernel_package()?;
        eprintln!(
            "kernel-rig: fetching {package} (once; kept in {})",
            dir.display()
        );
        let dl = dir.join("download");
        let _ = std::fs::remove_dir_all(&dl);
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(&dl).map_err(|e| RigError::io(&dl, e))?;
        run(Command::new("apt-get")
            .args(["download", "-q", &package])
            .current_dir(&dl))?;
        let deb = std::fs::read_dir(&dl)
            .map_err(|e| RigError::io(&dl, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .find(|p| p.extension().is_some_and(|x| x == "deb"))
            .ok_or_else(|| RigError::Missing(format!("apt-get download {package}: no .deb")))?;
        run(Command::new("dpkg-deb").arg("-x").arg(&deb).arg(&root))?;
        let version = only_entry(&root.join("lib/modules"))?;
        run(Command::new("depmod").arg("-b").arg(&root).arg(&version))?;
        let _ = std::fs::remove_dir_all(&dl);
        std::fs::write(&stamp, &version).map_err(|e| RigError::io(&stamp, e))?;
    }
    let version = std::fs::read_to_string(&stamp)
        .map_err(|e| RigError::io(&stamp, e))?
        .trim()
        .to_string();
    let vmlinuz = root.join(format!("boot/vmlinuz-{version}"));
    // Named by what goes in, so a changed init script builds a new one.
    let initramfs = dir.join(format!("initramfs-{:016x}.cpio", {
        use std::hash::{Hash, Hasher};
        let mut h = std::collections::hash_map::DefaultHasher::new();
        (
            include_bytes!("../guest/init").as_slice(),
            &version,
            BOOT_MODULES,
        )
            .hash(&mut h);
        h.finish()
    }));
    if !initramfs.is_file() {
        build_initramfs(&root, &version, &initramfs)?;
    }
    Ok(Kernel {
        version,
        vmlinuz,
        root,
        initramfs,
    })
}

fn only_entry(dir: &Path) -> Result<String, RigError> {
    std::fs::read_dir(dir)
        .map_err(|e| RigError::io(dir, e))?
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .next()
        .ok_or_else(|| RigError::Missing(format!("{}: no kernel version inside", dir.display())))
}

fn build_initramfs(root: &Path, version: &str, out: &Path) -> Result<(), RigError> {
    let mut a = crate::cpio::Archive::default();
    for d in [
        "bin", "lib", "lib/mods", "proc", "sys", "dev", "lower", "rw", "root",
    ] {
        a.dir(d);
    }
    let busybox = std::fs::read(BUSYBOX).map_err(|e| RigError::io(Path::new(BUSYBOX), e))?;
    a.file("bin/busybox", 0o755, &busybox);
    a.file("init", 0o755, include_bytes!("../guest/init"));
    for m in BOOT_MODULES {
        let path = run(Command::new("modinfo")
            .arg("-b")
            .arg(root)
            .args(["-k", version, "-n", m]))?;
        let path = path.trim();
        // busybox insmod wants the plain module; Debian ships them xz-compressed.
        let plain = if path.ends_with(".xz") {
            let out = Command::new(BUSYBOX)
                .args(["xz", "-dc", path])
                .output()
                .map_err(|e| RigError::io(Path::new(path), e))?;
            if !out.status.success() {
                return Err(RigError::Command {
                    command: format!("busybox xz -dc {path}"),
                    problem: String::from_utf8_lossy(&out.stderr).into_owned(),
                });
            }
            out.stdout
        } else {
            std::fs::read(path).map_err(|e| RigError::io(Path::new(path), e))?
        };
        a.file(&format!("lib/mods/{m}.ko"), 0o644, &plain);
    }
    let tmp = out.with_extension("tmp");
    std::fs::write(&tmp, a.finish()).map_err(|e| RigError::io(&tmp, e))?;
    std::fs::rename(&tmp, out).map_err(|e| RigError::io(out, e))
}
