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

/// Host commands building an out-of-tree module takes, with their Debian packages.
pub const MODULE_BUILD_TOOLS: &[(&str, &str)] = &[
    ("make", "make"),
    ("gcc", "gcc"),
    ("pahole", "dwarves"),
    ("xz", "xz-utils"),
    ("tar", "tar"),
];

/// Where [`gpio_sim`] puts the module in the guest kernel's tree.
fn gpio_sim_path(kernel: &Kernel) -> PathBuf {
    kernel
        .root
        .join("lib/modules")
        .join(&kernel.version)
        .join("extra/gpio-sim.ko")
}

/// Builds the kernel's gpio-sim module for the guest kernel, once (Debian's kernel has
/// gpiolib and the character device but not gpio-sim, nor the irq_sim it needs): fetches
/// the kernel's headers, kbuild and source packages of the same version, builds
/// `drivers/gpio/gpio-sim.c` with `kernel/irq/irq_sim.c` into one module (irq_sim
/// changed to use an exported call), installs it under `extra/` and runs depmod, so
/// `modprobe gpio-sim` loads it in the guest. About 170 MB of downloads and half a minute.
pub fn gpio_sim(dir: &Path, kernel: &Kernel) -> Result<(), RigError> {
    let ko = gpio_sim_path(kernel);
    if ko.is_file() {
        return Ok(());
    }
    host_tools(MODULE_BUILD_TOOLS)?;
    let lock_path = dir.join("prepare.lock");
    let lock = std::fs::File::create(&lock_path).map_err(|e| RigError::io(&lock_path, e))?;
    lock.lock().map_err(|e| RigError::io(&lock_path, e))?;
    if ko.is_file() {
        return Ok(());
    }
    eprintln!(
        "kernel-rig: building gpio-sim for {} (once; kept in {})",
        kernel.version,
        dir.display()
    );
    let work = dir.join("gpio-sim-build");
    let _ = std::fs::remove_dir_all(&work);
    let x = work.join("x");
    let mods = work.join("mod");
    for d in [&work, &x, &mods] {
        std::fs::create_dir_all(d).map_err(|e| RigError::io(d, e))?;
    }
    let result = build_gpio_sim(kernel, &work, &x, &mods, &ko);
    let _ = std::fs::remove_dir_all(&work);
    result
}

fn build_gpio_sim(
    kernel: &Kernel,
    work: &Path,
    x: &Path,
    mods: &Path,
    ko: &Path,
) -> Result<(), RigError> {
    let version = &kernel.version;
    let abi = version.strip_suffix("-amd64").ok_or_else(|| {
        RigError::Missing(format!(
            "{version}: not an -amd64 kernel; cannot name its headers"
        ))
    })?;
    let headers = format!("linux-headers-{version}");
    run(Command::new("apt-get")
        .args([
            "download",
            "-q",
            &headers,
            &format!("linux-headers-{abi}-common"),
        ])
        .arg(format!("linux-kbuild-{abi}"))
        .current_dir(work))?;
    let debs = |w: &Path| -> Result<Vec<PathBuf>, RigError> {
        Ok(std::fs::read_dir(w)
            .map_err(|e| RigError::io(w, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "deb"))
            .collect())
    };
    let header_deb = debs(work)?
        .into_iter()
        .find(|p| p.to_string_lossy().contains(&format!("/{headers}_")))
        .ok_or_else(|| RigError::Missing(format!("apt-get download {headers}: no .deb")))?;
    // The source package of the same Debian version as the headers.
    let deb_version = run(Command::new("dpkg-deb")
        .args(["-f"])
        .arg(&header_deb)
        .arg("Version"))?;
    run(Command::new("apt-get")
        .args(["download", "-q"])
        .arg(format!("linux-source-6.12={}", deb_version.trim()))
        .current_dir(work))?;
    let mut needed = Vec::new();
    for deb in debs(work)? {
        run(Command::new("dpkg-deb").arg("-x").arg(&deb).arg(x))?;
        let depends = run(Command::new("dpkg-deb").arg("-f").arg(&deb).arg("Depends"))?;
        needed.extend(libraries_needed(&depends));
    }
    // What the kbuild tools link to and the compiler the headers name (not the kernel
    // packages themselves: those stay extracted here, never installed).
    needed.sort();
    needed.dedup();
    let missing: Vec<&str> = needed
        .iter()
        .map(String::as_str)
        .filter(|p| !installed(p))
        .collect();
    if !missing.is_empty() {
        apt_install(&missing)?;
    }
    // The headers' Makefile includes the -common tree by its installed path.
    let hdir = x.join("usr/src").join(&headers);
    let makefile = hdir.join("Makefile");
    let text = std::fs::read_to_string(&makefile).map_err(|e| RigError::io(&makefile, e))?;
    let text = text.replace(
        "include /usr/src/",
        &format!("include {}/usr/src/", x.display()),
    );
    std::fs::write(&makefile, text).map_err(|e| RigError::io(&makefile, e))?;
    let tarball = x.join("usr/src/linux-source-6.12.tar.xz");
    run(Command::new("tar")
        .arg("-xJf")
        .arg(&tarball)
        .args([
            "linux-source-6.12/drivers/gpio/gpio-sim.c",
            "linux-source-6.12/kernel/irq/irq_sim.c",
        ])
        .current_dir(work))?;
    let src = work.join("linux-source-6.12");
    let read = |from: &str| -> Result<String, RigError> {
        let p = src.join(from);
        std::fs::read_to_string(&p).map_err(|e| RigError::io(&p, e))
    };
    let main = read("drivers/gpio/gpio-sim.c")?;
    let irq = read("kernel/irq/irq_sim.c")?;
    // irq_to_desc is not exported to modules: handle the interrupt by domain instead.
    let old = "irqnum = irq_find_mapping(work_ctx->domain, offset);\n\t\thandle_simple_irq(irq_to_desc(irqnum));";
    if !irq.contains(old) {
        return Err(RigError::Missing(format!(
            "{}: the irq_sim.c of this kernel source differs from the one the rig knows \
             (no irq_find_mapping + handle_simple_irq(irq_to_desc(...)) to replace)",
            src.display()
        )));
    }
    let irq = irq
        .replace(old, "generic_handle_domain_irq(work_ctx->domain, offset);")
        .replace(
            "\tunsigned int offset = 0;\n\tint irqnum;\n",
            "\tunsigned int offset = 0;\n",
        );
    for (name, text) in [
        ("gpio-sim-main.c", main.as_str()),
        ("irq_sim.c", irq.as_str()),
        (
            "Kbuild",
            "obj-m := gpio-sim.o\ngpio-sim-y := gpio-sim-main.o irq_sim.o\n",
        ),
    ] {
        let p = mods.join(name);
        std::fs::write(&p, text).map_err(|e| RigError::io(&p, e))?;
    }
    run(Command::new("make")
        .arg("-C")
        .arg(&hdir)
        .arg(format!("M={}", mods.display()))
        .arg("modules"))?;
    let built = mods.join("gpio-sim.ko");
    let dir = ko.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| RigError::io(dir, e))?;
    let tmp = ko.with_extension("tmp");
    std::fs::copy(&built, &tmp).map_err(|e| RigError::io(&built, e))?;
    std::fs::rename(&tmp, ko).map_err(|e| RigError::io(ko, e))?;
    run(Command::new("depmod")
        .arg("-b")
        .arg(&kernel.root)
        .arg(version))?;
    Ok(())
}

/// The packages of a Depends field (first of each alternative, no versions), but the
/// kernel's own packages.
fn libraries_needed(depends: &str) -> Vec<String> {
    depends
        .split(',')
        .filter_map(|d| d.split('|').next())
        .filter_map(|d| d.split_whitespace().next())
        .filter(|p| !p.is_empty() && !p.starts_with("linux-"))
        .map(str::to_string)
        .collect()
}

/// True when Debian package `package` is installed.
fn installed(package: &str) -> bool {
    Command::new("dpkg-query")
        .args(["-W", "-f=${Status}", package])
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).contains("install ok installed"))
}
