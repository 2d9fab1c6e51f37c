// Bakes the libtorch library folder into the binaries as an rpath, so
// `lcrl` runs without LD_LIBRARY_PATH. torch-sys reports the folder it
// linked against (DEP_TCH_LIBTORCH_LIB, from LIBTORCH set in
// .cargo/config.toml); it is canonicalized because libtorch finds its CUDA
// companions relative to its own real location ($ORIGIN).
//
// With a CUDA build of libtorch whose CUDA runtime headers lie beside it
// (PyPI's wheels: site-packages/nvidia/*/include), it also compiles
// cuda/graph_shim.cpp into a small shared library that src/device/cuda_graph.rs
// embeds and loads at run time (CUDA graphs; tch binds none). Without
// them, or if the compiler fails, the learner builds without graphs and
// says so (a cargo warning here, `lcrl doctor` there).
use std::path::{Path, PathBuf};
use std::process::Command;

fn main() {
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    println!("cargo:rerun-if-changed=cuda/graph_shim.cpp");
    println!("cargo:rustc-check-cfg=cfg(lcrl_cuda_graphs)");
    let Ok(dir) = std::env::var("DEP_TCH_LIBTORCH_LIB") else { return };
    let dir = std::fs::canonicalize(&dir).map(|p| p.display().to_string()).unwrap_or(dir);
    println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
    // Where src/device/torch.rs finds libtorch_cuda.so to load at run time.
    println!("cargo:rustc-env=LCRL_LIBTORCH_LIB={dir}");
    match build_graph_shim(Path::new(&dir)) {
        Ok(Some(shim)) => {
            println!("cargo:rustc-cfg=lcrl_cuda_graphs");
            println!("cargo:rustc-env=LCRL_CUDA_GRAPH_SHIM={}", shim.display());
        }
        Ok(None) => {}
        Err(why) => println!("cargo:warning=CUDA graphs left out: {why}"),
    }
}

/// The shim library in OUT_DIR, or None where libtorch has no CUDA build
/// or its CUDA headers are absent.
fn build_graph_shim(lib: &Path) -> Result<Option<PathBuf>, String> {
    if !lib.join("libtorch_cuda.so").is_file() {
        return Ok(None);
    }
    let torch = lib.parent().ok_or("libtorch's lib folder has no parent")?;
    let Some(cuda) = cuda_runtime_dir(torch) else { return Ok(None) };
    let out = PathBuf::from(std::env::var("OUT_DIR").map_err(|e| e.to_string())?).join("liblcrl_cuda_graph.so");
    let cxx = std::env::var("CXX").unwrap_or_else(|_| "c++".into());
    // The runtime wheel's headers include crt/host_config.h, which only
    // the compiler's wheel ships; triton's copy of the headers has it.
    let crt = torch.parent().map(|site| site.join("triton/backends/nvidia/include")).filter(|d| d.join("crt/host_config.h").is_file());
    let includes = [Some(torch.join("include")), Some(cuda.join("include")), crt];
    let status = Command::new(&cxx)
        .args(["-std=c++17", "-O2", "-fPIC", "-shared", "-D_GLIBCXX_USE_CXX11_ABI=1", "-w"])
        .args(includes.iter().flatten().map(|dir| format!("-I{}", dir.display())))
        .arg("cuda/graph_shim.cpp")
        .arg("-o")
        .arg(&out)
        .arg(format!("-L{}", lib.display()))
        .arg(format!("-L{}", cuda.join("lib").display()))
        // Resolved at load time against the libraries libtorch_cuda.so
        // already brought in (same sonames), so no rpath is needed.
        .args(["-ltorch_cuda", "-ltorch_cpu", "-lc10_cuda", "-lc10"])
        .status()
        .map_err(|e| format!("running {cxx}: {e}"))?;
    if !status.success() {
        return Err(format!("{cxx} failed to compile cuda/graph_shim.cpp ({status})"));
    }
    Ok(Some(out))
}

/// site-packages/nvidia/<cu13 or cuda_runtime>, the folder with
/// include/cuda_runtime_api.h, beside the torch package.
fn cuda_runtime_dir(torch: &Path) -> Option<PathBuf> {
    let nvidia = torch.parent()?.join("nvidia");
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(nvidia).ok()?.filter_map(|e| e.ok().map(|e| e.path())).collect();
    dirs.sort();
    dirs.into_iter().find(|d| d.join("include/cuda_runtime_api.h").is_file())
}
