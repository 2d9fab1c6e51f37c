//! Where the learner computes: the libtorch device (`run.device`) and the
//! intra-op thread count (`run.threads`).
//!
//! **Why CUDA needs loading.** tch's binaries link `libtorch_cpu` and
//! `libtorch`, but no symbol of `libtorch_cuda.so` is referenced, so the
//! linker's `--as-needed` drops it, its static initializers never run, and
//! libtorch never registers its CUDA backend: `Cuda::is_available()` stays
//! false on a GPU machine. Linking it into every binary would cost every
//! actor ~0.4 s of start-up and ~400 MB of mapped CUDA libraries for
//! nothing (actors stay on the CPU), so it is loaded here instead, once, at
//! run time, before the first CUDA query: by `resolve_device("cuda")` and
//! by `lcrl doctor`.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use tch::Tensor;

use crate::LearnerError;

/// The libtorch library folder the binaries were linked against (their
/// rpath), from build.rs.
const LIBTORCH_LIB: Option<&str> = option_env!("LCRL_LIBTORCH_LIB");

// The most intra-op threads `run.threads` accepts: the configuration's bound.
pub use crate::config::MAX_THREADS;

/// What loading `libtorch_cuda.so` found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CudaLibrary {
    /// Loaded from this path: libtorch's CUDA backend is registered.
    Loaded(PathBuf),
    /// Already in the process before lcrl looked (LD_PRELOAD, or release
    /// binaries run beside another libtorch), from this path.
    Preloaded(PathBuf),
    /// This libtorch is a CPU-only build (no `libtorch_cuda.so` beside it).
    CpuOnlyBuild,
    /// The file is there but would not load (a missing CUDA runtime
    /// library, for example); the loader's message.
    Failed(String),
}

impl std::fmt::Display for CudaLibrary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CudaLibrary::Loaded(path) => write!(f, "loaded ({})", path.display()),
            CudaLibrary::Preloaded(path) => write!(f, "loaded (already in the process: {})", path.display()),
            CudaLibrary::CpuOnlyBuild => write!(f, "absent: this libtorch is a CPU-only build"),
            CudaLibrary::Failed(why) => write!(f, "present but failed to load: {why}"),
        }
    }
}

/// Loads `libtorch_cuda.so` (once per process; later calls return the first
/// answer). Call it before anything asks libtorch about CUDA.
pub fn load_cuda() -> &'static CudaLibrary {
    static LOADED: OnceLock<CudaLibrary> = OnceLock::new();
    LOADED.get_or_init(|| {
        // Loaded already (a preload): that one is the backend, whatever
        // the libtorch this was built against holds.
        if let Some(path) = mapped("libtorch_cuda.so") {
            return CudaLibrary::Preloaded(path);
        }
        let Some(dir) = LIBTORCH_LIB else { return CudaLibrary::CpuOnlyBuild };
        let path = PathBuf::from(dir).join("libtorch_cuda.so");
        if !path.is_file() {
            return CudaLibrary::CpuOnlyBuild;
        }
        // RTLD_GLOBAL: libtorch resolves the backend's symbols across
        // libraries, as when Python's torch loads it.
        let flags = libloading::os::unix::RTLD_NOW | libloading::os::unix::RTLD_GLOBAL;
        // SAFETY: libtorch_cuda.so's initializers register the CUDA backend
        // with the libtorch already loaded; it is never unloaded (leaked
        // below), so no symbol outlives its library.
        match unsafe { libloading::os::unix::Library::open(Some(&path), flags) } {
            Ok(library) => {
                std::mem::forget(library);
                CudaLibrary::Loaded(path)
            }
            Err(e) => CudaLibrary::Failed(e.to_string()),
        }
    })
}

/// The path of a shared library this process has mapped whose file name
/// is `name` (Linux: /proc/self/maps), if any.
fn mapped(name: &str) -> Option<PathBuf> {
    let maps = std::fs::read_to_string("/proc/self/maps").ok()?;
    maps.lines().filter_map(|line| line.split_whitespace().nth(5)).find(|path| Path::new(path).file_name().is_some_and(|f| f == name)).map(PathBuf::from)
}

/// Whether libtorch sees a CUDA device (after loading its CUDA backend).
pub fn cuda_available() -> bool {
    load_cuda();
    tch::Cuda::is_available()
}

/// The libtorch device for `run.device` ("cpu" or "cuda"; validated in the
/// config). "cuda" without a usable GPU is an error that says why.
pub fn resolve_device(name: &str) -> Result<tch::Device, LearnerError> {
    match name {
        "cpu" => Ok(tch::Device::Cpu),
        "cuda" => {
            let library = load_cuda();
            if tch::Cuda::is_available() {
                return Ok(tch::Device::Cuda(0));
            }
            let why = match library {
                CudaLibrary::Loaded(_) | CudaLibrary::Preloaded(_) => "libtorch's CUDA backend loaded, but it sees no CUDA device (no NVIDIA GPU or driver here)".to_string(),
                other => format!("libtorch_cuda.so: {other}"),
            };
            Err(LearnerError::Config(format!("device \"cuda\" asked for, but CUDA is not available: {why}; use device \"cpu\" (`lcrl doctor` shows what libtorch sees)")))
        }
        other => Err(LearnerError::Config(format!("device must be \"cpu\" or \"cuda\", got {other:?}"))),
    }
}

/// A host tensor on `device`. To a GPU it goes through page-locked memory
/// without waiting: a copy from ordinary (pageable) memory makes the host
/// wait until the GPU's queue has drained, which in the update path would
/// stall every update on the one before it. libtorch's pinned-memory
/// allocator keeps the staging block until the copy has finished.
pub fn to_device_async(host: Tensor, device: tch::Device) -> Tensor {
    match device {
        tch::Device::Cuda(_) => host.internal_pin_memory(device).to_device_(device, host.kind(), true, false),
        _ => host.to_device(device),
    }
}

/// The cores of this machine (or of this container's CPU quota).
pub fn available_cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// The most threads the automatic setting gives one learner. An update at
/// these sizes (batch 256, 256-wide layers) is a few dozen small matrix
/// products, and every thread adds its synchronization to each: on a
/// 16-core machine the global DDPG update took 5.4, 3.3, 3.0, 3.3 and
/// 5.4 ms on 1, 2, 4, 8 and 16 threads, and `lcrl scale` ran 2.0–2.3× the
/// environment steps/s with 4 learner threads than with all the cores the
/// actors left over (docs/scaling.md, "The learner's device and threads").
pub const AUTO_MAX_THREADS: usize = 4;

/// libtorch intra-op threads for `run.threads`: the number itself, or with
/// 0 ("auto") the cores left over after `reserved` cores that other
/// processes of the run on this machine use (its actors), at least 1 and
/// at most [`AUTO_MAX_THREADS`].
pub fn resolve_threads(configured: usize, reserved: usize) -> usize {
    match configured {
        0 => auto_threads(available_cores(), reserved),
        n => n,
    }
}

fn auto_threads(cores: usize, reserved: usize) -> usize {
    cores.saturating_sub(reserved).clamp(1, AUTO_MAX_THREADS)
}

/// Sets libtorch's intra-op threads for `run.threads` (see
/// [`resolve_threads`]) and returns the count used.
pub fn apply_threads(configured: usize, reserved: usize) -> usize {
    let threads = resolve_threads(configured, reserved);
    tch::set_num_threads(threads as i32);
    threads
}

/// Sets `threads` libtorch threads on the calling thread: OpenMP (and
/// MKL's local count) keep their thread count per thread, so a thread that
/// computes must set it itself; a new thread starts with OpenMP's default
/// team, one thread per core. Returns what OpenMP then says.
pub fn set_threads_here(threads: usize) -> Option<usize> {
    tch::set_num_threads(threads.max(1) as i32);
    openmp_threads_here()
}

/// OpenMP's thread count for the calling thread (`omp_get_max_threads`,
/// looked up in the process: libtorch loads libgomp), read without
/// libtorch's lazy per-thread set-up, which would set it as it reads.
/// None where no OpenMP runtime is loaded.
pub fn openmp_threads_here() -> Option<usize> {
    // SAFETY: dlsym with RTLD_DEFAULT and a NUL-terminated name only looks
    // the symbol up; omp_get_max_threads takes no argument and returns int.
    unsafe {
        let symbol = libc::dlsym(libc::RTLD_DEFAULT, c"omp_get_max_threads".as_ptr());
        if symbol.is_null() {
            return None;
        }
        let get: extern "C" fn() -> libc::c_int = std::mem::transmute(symbol);
        usize::try_from(get()).ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_threads_leave_the_reserved_cores_and_never_drop_to_zero() {
        assert_eq!(resolve_threads(3, 100), 3, "an explicit count is kept");
        assert_eq!(resolve_threads(0, 1), auto_threads(available_cores(), 1));
        // (cores, reserved) → threads: what is left, capped, at least one.
        for ((cores, reserved), threads) in [((2, 0), 2), ((2, 1), 1), ((2, 5), 1), ((16, 0), 4), ((16, 14), 2), ((16, 15), 1), ((64, 8), 4)] {
            assert_eq!(auto_threads(cores, reserved), threads, "{cores} cores, {reserved} reserved");
        }
    }

    #[test]
    fn cpu_resolves_and_unknown_devices_are_refused() {
        assert_eq!(resolve_device("cpu").expect("cpu"), tch::Device::Cpu);
        let err = resolve_device("tpu").expect_err("tpu").to_string();
        assert!(err.contains("\"cpu\" or \"cuda\""), "{err}");
    }

    /// A library already in the process is found by its file name (how a
    /// preloaded libtorch_cuda.so is told apart from a CPU-only build).
    #[test]
    fn mapped_libraries_are_found_by_file_name() {
        let _ = tch::Tensor::from_slice(&[1.0f32]);
        let cpu = mapped("libtorch_cpu.so").expect("libtorch_cpu.so is mapped in a process that computed with libtorch");
        assert!(cpu.is_absolute() && cpu.ends_with("libtorch_cpu.so"), "{}", cpu.display());
        assert_eq!(mapped("libtorch_cpu"), None, "whole file names only");
        assert_eq!(mapped("no-such-library.so"), None);
    }

    /// The mechanism itself, GPU or not: with a CUDA build of libtorch the
    /// backend library is really mapped into this process afterwards.
    #[test]
    fn the_cuda_backend_library_is_loaded_when_libtorch_has_one() {
        let has_cuda_build = LIBTORCH_LIB.is_some_and(|dir| PathBuf::from(dir).join("libtorch_cuda.so").is_file());
        let status = load_cuda();
        let maps = std::fs::read_to_string("/proc/self/maps").unwrap_or_default();
        if has_cuda_build {
            assert!(matches!(status, CudaLibrary::Loaded(_) | CudaLibrary::Preloaded(_)), "{status}");
            assert!(maps.contains("libtorch_cuda.so"), "libtorch_cuda.so is not mapped after load_cuda");
        } else {
            assert_eq!(*status, CudaLibrary::CpuOnlyBuild);
        }
    }

    /// On a machine without a GPU, "cuda" fails with a message that says so
    /// and what to do; with one, it resolves.
    #[test]
    fn cuda_resolves_exactly_when_a_device_is_there() {
        match resolve_device("cuda") {
            Ok(device) => assert!(cuda_available() && device == tch::Device::Cuda(0)),
            Err(e) => {
                assert!(!cuda_available());
                let text = e.to_string();
                assert!(text.contains("CUDA is not available") && text.contains("use device \"cpu\""), "{text}");
            }
        }
    }
}
