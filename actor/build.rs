// Bakes the libtorch library folder into the binaries as an rpath, so
// `lcrl` runs without LD_LIBRARY_PATH. torch-sys reports the folder it
// linked against (DEP_TCH_LIBTORCH_LIB, from LIBTORCH set in
// .cargo/config.toml); it is canonicalized because libtorch finds its CUDA
// companions relative to its own real location ($ORIGIN).
fn main() {
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    if let Ok(dir) = std::env::var("DEP_TCH_LIBTORCH_LIB") {
        let dir = std::fs::canonicalize(&dir).map(|p| p.display().to_string()).unwrap_or(dir);
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
    }
}
