//! Generates the gRPC code from saver.proto with protox (pure Rust): no system protoc.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=saver.proto");
    let fds = protox::compile(["saver.proto"], ["."])?;
    tonic_prost_build::configure()
        .bytes(".saver.v1.Weights.safetensors")
        .bytes(".saver.v1.PcpnChunk.data")
        .compile_fds(fds)?;
    Ok(())
}
