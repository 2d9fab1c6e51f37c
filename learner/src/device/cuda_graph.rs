//! CUDA graphs: work captured once and replayed as one launch, through the
//! small C shim over libtorch's `at::cuda::CUDAGraph` (learner/cuda/
//! graph_shim.cpp; tch binds no graph API).
//!
//! Why: a DDPG update at peg sizes is a few hundred small kernels, and what
//! it costs on a GPU is libtorch's host-side dispatch of each, not the
//! arithmetic (docs/scaling.md, "On a GPU and 16 cores"). A replay skips
//! the dispatch.
//!
//! How it is built and found: learner/build.rs compiles the shim when
//! libtorch is a CUDA build with the CUDA headers beside it; the library is
//! embedded in the binary, written to the temporary folder and loaded at
//! run time after `libtorch_cuda.so` (torch.rs), so no binary links the
//! CUDA libraries and CPU machines never load it.
//!
//! The rules a captured piece of work must keep (as PyTorch's
//! `torch.cuda.graph`): it reads its inputs from tensors allocated before
//! the capture, which the host refills before each replay; it does not
//! read values back to the host or branch on them; host numbers it uses are
//! baked into the graph, so anything that changes between updates comes
//! from a device tensor instead.

use std::ffi::{c_char, c_int, c_void, CStr};
use std::panic::AssertUnwindSafe;
use std::sync::OnceLock;

#[cfg(lcrl_cuda_graphs)]
const SHIM: Option<&[u8]> = Some(include_bytes!(env!("LCRL_CUDA_GRAPH_SHIM")));
#[cfg(not(lcrl_cuda_graphs))]
const SHIM: Option<&[u8]> = None;

type Handle = *mut c_void;

/// The shim's functions (see graph_shim.cpp).
struct Api {
    new: unsafe extern "C" fn() -> Handle,
    free: unsafe extern "C" fn(Handle),
    error: unsafe extern "C" fn(Handle) -> *const c_char,
    enter_side_stream: unsafe extern "C" fn(Handle) -> c_int,
    capture_begin: unsafe extern "C" fn(Handle) -> c_int,
    capture_end: unsafe extern "C" fn(Handle) -> c_int,
    leave_side_stream: unsafe extern "C" fn(Handle) -> c_int,
    replay: unsafe extern "C" fn(Handle) -> c_int,
}

/// The shim, loaded once per process (after libtorch's CUDA backend), or
/// why it is not there.
fn api() -> Result<&'static Api, String> {
    static API: OnceLock<Result<Api, String>> = OnceLock::new();
    API.get_or_init(load).as_ref().map_err(Clone::clone)
}

/// Whether this build carries the shim and it loads here: `lcrl doctor`'s
/// line and the reason graphs are off where they are.
pub fn availability() -> Result<(), String> {
    api().map(|_| ())
}

fn load() -> Result<Api, String> {
    let bytes = SHIM.ok_or("this build has no CUDA graph shim (libtorch without CUDA, or its CUDA headers were not found at build time)")?;
    // The shim's libraries resolve against the libtorch_cuda.so in this
    // process: loaded here from beside libtorch, or already there (a
    // machine whose libtorch lies elsewhere preloads it: docs/scaling.md,
    // "Measuring on a GPU machine"); otherwise loading says what is missing.
    crate::device::torch::load_cuda();
    let path = write_shim(bytes)?;
    let flags = libloading::os::unix::RTLD_NOW | libloading::os::unix::RTLD_LOCAL;
    // SAFETY: the shim only calls libtorch, already loaded with its CUDA
    // backend; it is never unloaded (leaked below), so the function
    // pointers taken from it stay valid.
    let library = unsafe { libloading::os::unix::Library::open(Some(&path), flags) }.map_err(|e| format!("loading {}: {e}", path.display()))?;
    macro_rules! symbol {
        ($name:literal) => {
            // SAFETY: the signatures match graph_shim.cpp's extern "C" ones.
            *unsafe { library.get(concat!($name, "\0").as_bytes()) }.map_err(|e| format!("{}: {e}", $name))?
        };
    }
    let api = Api {
        new: symbol!("lcrl_graph_new"),
        free: symbol!("lcrl_graph_free"),
        error: symbol!("lcrl_graph_error"),
        enter_side_stream: symbol!("lcrl_graph_enter_side_stream"),
        capture_begin: symbol!("lcrl_graph_capture_begin"),
        capture_end: symbol!("lcrl_graph_capture_end"),
        leave_side_stream: symbol!("lcrl_graph_leave_side_stream"),
        replay: symbol!("lcrl_graph_replay"),
    };
    std::mem::forget(library);
    Ok(api)
}

/// Writes the embedded library once per content (processes share the file;
/// a new name per content, so a newer binary never loads an older shim).
fn write_shim(bytes: &[u8]) -> Result<std::path::PathBuf, String> {
    use std::hash::{Hash, Hasher};
    let mut hasher = std::collections::hash_map::DefaultHasher::new();
    bytes.hash(&mut hasher);
    let path = std::env::temp_dir().join(format!("lcrl-cuda-graph-{:016x}.so", hasher.finish()));
    if std::fs::read(&path).is_ok_and(|existing| existing == bytes) {
        return Ok(path);
    }
    // Written beside and renamed: a concurrent process never loads half a file.
    let partial = path.with_extension(format!("{}.partial", std::process::id()));
    std::fs::write(&partial, bytes).and_then(|()| std::fs::rename(&partial, &path)).map_err(|e| format!("writing {}: {e}", path.display()))?;
    Ok(path)
}

/// A captured CUDA graph, replayed on the current stream.
pub struct CudaGraph {
    handle: Handle,
    api: &'static Api,
}

// SAFETY: the graph is used from one thread at a time (it is owned by the
// agent, which the learner's update thread owns); libtorch's CUDAGraph has
// no thread affinity.
unsafe impl Send for CudaGraph {}

impl CudaGraph {
    fn call(&self, f: unsafe extern "C" fn(Handle) -> c_int, what: &str) -> Result<(), String> {
        // SAFETY: `handle` is live until drop; the shim catches every C++
        // exception and keeps its message.
        if unsafe { f(self.handle) } == 0 {
            return Ok(());
        }
        // SAFETY: the shim returns a NUL-terminated string it owns.
        let message = unsafe { CStr::from_ptr((self.api.error)(self.handle)) }.to_string_lossy().into_owned();
        Err(format!("{what}: {message}"))
    }

    /// Runs `work` once for real on a side stream (the warm-up PyTorch asks
    /// for: lazy per-stream set-up happens outside the capture), then
    /// captures a second call of it, which is not run. Returns the graph,
    /// or why capturing failed; either way `work` ran exactly once for
    /// real if it got to run at all (`ran` says whether).
    pub fn capture(mut work: impl FnMut()) -> (Result<CudaGraph, String>, bool) {
        let api = match api() {
            Ok(api) => api,
            Err(e) => return (Err(e), false),
        };
        // SAFETY: plain constructor; null on failure.
        let handle = unsafe { (api.new)() };
        if handle.is_null() {
            return (Err("could not create a CUDA graph".into()), false);
        }
        let graph = CudaGraph { handle, api };
        if let Err(e) = graph.call(api.enter_side_stream, "switching to a side stream") {
            return (Err(e), false);
        }
        work();
        let captured = graph.call(api.capture_begin, "beginning the capture").and_then(|()| {
            let recorded = std::panic::catch_unwind(AssertUnwindSafe(&mut work)).map_err(|_| "an operation failed during the capture".to_string());
            // End the capture even after a failure, so the stream leaves
            // capture mode; the first error is the one reported.
            let ended = graph.call(api.capture_end, "ending the capture");
            recorded.and(ended)
        });
        let left = graph.call(api.leave_side_stream, "returning from the side stream");
        (captured.and(left).map(|()| graph), true)
    }

    /// Launches the captured work after what is queued on the current stream.
    pub fn replay(&self) -> Result<(), String> {
        self.call(self.api.replay, "replaying the CUDA graph")
    }
}

impl Drop for CudaGraph {
    fn drop(&mut self) {
        // SAFETY: created by `new`, freed once.
        unsafe { (self.api.free)(self.handle) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Where the build carries the shim (a CUDA build of libtorch with its
    /// headers), it loads on any machine, GPU or not: every symbol resolves
    /// against the libtorch_cuda.so this process loaded. (Capturing and
    /// replaying need a GPU: `cuda_updates_equal_cpu_updates`.)
    #[test]
    fn the_shim_loads_where_the_build_carries_it() {
        match SHIM {
            Some(_) => assert_eq!(availability(), Ok(())),
            None => assert!(availability().is_err_and(|e| e.contains("no CUDA graph shim"))),
        }
    }
}
