//! Generates the Sparkplug B payload types from `proto/sparkplug_b.proto` (written for
//! hwgw from the Sparkplug 3.0 specification's schema) with prost; protox compiles the
//! file in Rust, so the build needs no `protoc`.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let proto = "proto/sparkplug_b.proto";
    println!("cargo:rerun-if-changed={proto}");
    let descriptors = protox::compile([proto], ["proto"])?;
    prost_build::Config::new().compile_fds(descriptors)?;
    Ok(())
}
