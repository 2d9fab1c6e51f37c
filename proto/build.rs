// Generates the lcrl.v1 types and stubs. protoc comes from the
// protoc-bin-vendored crate so a fresh machine needs no system protoc.
fn main() -> Result<(), Box<dyn std::error::Error>> {
    if std::env::var_os("PROTOC").is_none() {
        std::env::set_var("PROTOC", protoc_bin_vendored::protoc_bin_path()?);
    }
    let out_dir = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    tonic_prost_build::configure()
        .file_descriptor_set_path(out_dir.join("lcrl_descriptor.bin"))
        // prost's codec with a check of repeated entries before decoding
        // (src/codec.rs): what a peer sends cannot decode to 60× its size.
        .codec_path("crate::codec::BoundedCodec")
        // A policy's weights are shared, not copied, by every WatchPolicy
        // stream, GetPolicy reply and queued version: a clone is a count.
        .bytes(".lcrl.v1.PolicySnapshot.weights")
        .compile_protos(&["lcrl.proto"], &["."])?;
    println!("cargo:rerun-if-changed=lcrl.proto");
    Ok(())
}
