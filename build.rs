//! Compiles proto/prac/v1/prac.proto and the dm_env_rpc protocol (proto/dm_env_rpc); protoc comes from `protoc-bin-vendored` unless PROTOC is set,
//! because a fresh machine has no protoc.
fn main() -> Result<(), Box<dyn std::error::Error>> {
    if std::env::var_os("PROTOC").is_none() {
        // SAFETY: build scripts are single-threaded at this point.
        unsafe { std::env::set_var("PROTOC", protoc_bin_vendored::protoc_bin_path()?) };
    }
    let out_dir = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    tonic_prost_build::configure()
        .file_descriptor_set_path(out_dir.join("prac_descriptor.bin"))
        // Small first buffers per call (src/proto/codec.rs).
        .codec_path("crate::proto::codec::LeanCodec")
        .compile_protos(&["proto/prac/v1/prac.proto"], &["proto"])?;
    tonic_prost_build::configure()
        .compile_protos(&["proto/dm_env_rpc/v1/dm_env_rpc.proto"], &["proto"])?;
    println!("cargo:rerun-if-changed=proto");
    Ok(())
}
