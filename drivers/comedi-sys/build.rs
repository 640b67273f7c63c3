//! Generates the comedilib bindings with bindgen from the system's `comedilib.h` and links
//! libcomedi (pkg-config `comedilib`, which also adds `-lm`).
//!
//! Both need Debian's `libcomedi-dev` (the header, the library, the .pc file) and
//! `libclang-dev` (bindgen parses the header with libclang). When either is missing and
//! the build runs as root on a host with apt-get, it installs them (as the tests install
//! their peers; `HWGW_NO_APT=1` forbids it); otherwise the build fails naming them.

use std::path::{Path, PathBuf};
use std::process::Command;

const PACKAGES: [&str; 2] = ["libcomedi-dev", "libclang-dev"];

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=HWGW_NO_APT");
    let lib = match probe() {
        Ok(lib) if libclang_present() => lib,
        first => {
            install();
            match (probe(), libclang_present()) {
                (Ok(lib), true) => lib,
                (Err(e), _) => fail(&format!(
                    "comedilib was not found by pkg-config ({e}); first attempt: {}",
                    first.err().unwrap_or_default()
                )),
                (Ok(_), false) => fail("libclang (for bindgen) was not found"),
            }
        }
    };
    let header = lib
        .include_paths
        .iter()
        .map(|p| p.join("comedilib.h"))
        .find(|p| p.exists())
        .unwrap_or_else(|| PathBuf::from("/usr/include/comedilib.h"));
    println!("cargo:rerun-if-changed={}", header.display());
    let bindings = bindgen::Builder::default()
        .header(header.to_string_lossy())
        .clang_args(lib.include_paths.iter().map(|p| format!("-I{}", p.display())))
        .rust_edition(bindgen::RustEdition::Edition2024)
        .allowlist_function(
            "comedi_(open|close|get_n_subdevices|get_subdevice_type|get_subdevice_flags|\
             get_n_channels|get_maxdata|get_n_ranges|get_range|data_read|data_write|\
             dio_config|dio_get_config|dio_bitfield2|to_phys|from_phys|\
             set_global_oor_behavior|errno|strerror|get_board_name|get_driver_name|loglevel)",
        )
        .allowlist_type(
            "comedi_t|comedi_range|lsampl_t|comedi_subdevice_type|comedi_oor_behavior|comedi_io_direction",
        )
        .allowlist_var("AREF_.*|COMEDI_INPUT|COMEDI_OUTPUT|SDF_.*|UNIT_.*|COMEDI_SUBD_.*|COMEDI_OOR_.*")
        .prepend_enum_name(false)
        .layout_tests(false)
        .generate_comments(false)
        .generate()
        .unwrap_or_else(|e| fail(&format!("bindgen could not read {}: {e}", header.display())));
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap_or_else(|_| fail("OUT_DIR unset")));
    bindings
        .write_to_file(out.join("comedilib.rs"))
        .unwrap_or_else(|e| fail(&format!("writing the bindings: {e}")));
}

fn probe() -> Result<pkg_config::Library, String> {
    pkg_config::Config::new()
        .atleast_version("0.10")
        .probe("comedilib")
        .map_err(|e| e.to_string())
}

/// Whether a libclang bindgen can load is installed (Debian's `libclang-dev` gives
/// `libclang.so` under /usr/lib/llvm-N/lib; `LIBCLANG_PATH` points elsewhere).
fn libclang_present() -> bool {
    if let Some(dir) = std::env::var_os("LIBCLANG_PATH") {
        return Path::new(&dir).exists();
    }
    let Ok(entries) = std::fs::read_dir("/usr/lib") else {
        return false;
    };
    entries.flatten().any(|e| {
        e.file_name().to_string_lossy().starts_with("llvm-")
            && e.path().join("lib/libclang.so").exists()
    })
}

/// Installs the packages as root with apt-get, unless forbidden or impossible.
fn install() {
    let root = Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0");
    if std::env::var_os("HWGW_NO_APT").is_some_and(|v| v != "0") || !root {
        return;
    }
    if Command::new("apt-get").arg("--version").output().is_err() {
        return;
    }
    println!(
        "cargo:warning=installing {} with apt-get (what comedi-sys builds against)",
        PACKAGES.join(" ")
    );
    let update = Command::new("apt-get")
        .args(["update", "-qq"])
        .env("DEBIAN_FRONTEND", "noninteractive")
        .status();
    let install = Command::new("apt-get")
        .args(["install", "-y", "-qq", "--no-install-recommends"])
        .args(PACKAGES)
        .env("DEBIAN_FRONTEND", "noninteractive")
        .status();
    if !matches!((update, install), (Ok(u), Ok(i)) if u.success() && i.success()) {
        println!(
            "cargo:warning=apt-get could not install {}",
            PACKAGES.join(" ")
        );
    }
}

fn fail(why: &str) -> ! {
    panic!(
        "comedi-sys: {why}.\n  It builds against Debian's {} (as root: apt-get install {}; \
         .ci/run installs them).",
        PACKAGES.join(" and "),
        PACKAGES.join(" ")
    )
}
