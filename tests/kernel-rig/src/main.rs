//! `kernel-rig`: the rig by hand.
//!
//! ```text
//! cargo run -p kernel-rig -- prepare            # install packages, fetch the kernel
//! cargo run -p kernel-rig -- shell [MODULE…]    # a root shell in the guest
//! cargo run -p kernel-rig -- run [MODULE…] -- CMD [ARG…]
//! cargo run -p kernel-rig -- run --systemd vcan -- systemctl status  # systemd as PID 1
//! cargo run -p kernel-rig -- run --gpio-sim -- gpiodetect             # gpio-sim loaded
//! cargo run -p kernel-rig -- shell --comedi     # comedi_test, comedi_parport, a parallel port
//! ```

use kernel_rig::Rig;
use std::process::ExitCode;

fn usage() -> ExitCode {
    eprintln!(
        "usage: kernel-rig prepare | shell [MODULE...] | run [MODULE...] -- COMMAND [ARG...]\n\
         (add --kvaser for two kvaser_pci CAN controllers on one emulated bus, --systemd for\n\
         systemd as the guest's PID 1, --gpio-sim for the kernel's GPIO simulator, --comedi for\n\
         comedi_test and comedi_parport on an emulated parallel port)"
    );
    ExitCode::from(2)
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some((verb, rest)) = args.split_first() else {
        return usage();
    };
    let (opts, command) = match rest.iter().position(|a| a == "--") {
        Some(i) => (&rest[..i], &rest[i + 1..]),
        None => (rest, &[][..]),
    };
    let mut rig = Rig::new();
    for o in opts {
        rig = match o.as_str() {
            "--kvaser" => rig.qemu_args(&kernel_rig::KVASER_PAIR),
            "--systemd" => rig.systemd(),
            "--gpio-sim" => rig.gpio_sim(),
            "--comedi" => rig.comedi(),
            m => rig.module(m),
        };
    }
    let result = match verb.as_str() {
        "prepare" => kernel_rig::prepare::kernel(&kernel_rig::rig_dir(), &[]).map(|k| {
            println!("guest kernel {} ready: {}", k.version, k.vmlinuz.display());
            0
        }),
        "shell" => rig.shell().map(|()| 0),
        "run" if !command.is_empty() => {
            let args: Vec<std::ffi::OsString> = command[1..].iter().map(Into::into).collect();
            rig.run(std::path::Path::new(&command[0]), &args)
        }
        _ => return usage(),
    };
    match result {
        Ok(rc) => ExitCode::from(u8::try_from(rc).unwrap_or(1)),
        Err(e) => {
            eprintln!("kernel-rig: {e}");
            ExitCode::FAILURE
        }
    }
}
