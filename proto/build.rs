//! Compiles hypertexture.proto with protox (pure Rust): no system protoc needed.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=hypertexture.proto");
    let descriptors = protox::compile(["hypertexture.proto"], ["."])?;
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        // Tiles as `Bytes`: decoding takes a slice of the received buffer, no copy.
        .bytes(".hypertexture.v1.SubmitTileParams.pixels")
        .compile_fds(descriptors)?;
    Ok(())
}
