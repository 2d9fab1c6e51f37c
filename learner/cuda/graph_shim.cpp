// A C interface to libtorch's CUDA graphs (at::cuda::CUDAGraph), which tch
// does not bind. learner/build.rs compiles it into a small shared library
// when libtorch is a CUDA build with the CUDA runtime's headers beside it;
// learner/src/device/cuda_graph.rs loads it at run time, after libtorch_cuda.so
// (device.rs), so no binary links the CUDA libraries.
//
// Why graphs (docs/scaling.md, "On a GPU and 16 cores"): a DDPG update at
// peg sizes is a few hundred small kernels, and libtorch's host-side
// dispatch of each, not the GPU's arithmetic, is what an update costs.
// Captured once and replayed, the whole update is one launch.
//
// Every function returns 0 on success; on failure, 1, with the message
// kept for lcrl_graph_error.
#include <ATen/cuda/CUDAGraph.h>
#include <c10/cuda/CUDAFunctions.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <exception>
#include <optional>
#include <string>

struct LcrlGraph {
  at::cuda::CUDAGraph graph;
  // A stream of libtorch's pool: capture cannot happen on the default
  // stream, and the warm-up runs there too (lazy per-stream set-up, such
  // as cuBLAS's workspace, happens outside the capture).
  std::optional<c10::cuda::CUDAStreamGuard> guard;
  std::string error;
};

template <typename F>
static int guarded(LcrlGraph* g, F&& body) {
  try {
    body();
    return 0;
  } catch (const std::exception& e) {
    g->error = e.what();
  } catch (...) {
    g->error = "unknown C++ exception";
  }
  return 1;
}

extern "C" {

LcrlGraph* lcrl_graph_new() {
  try {
    return new LcrlGraph();
  } catch (...) {
    return nullptr;
  }
}

void lcrl_graph_free(LcrlGraph* g) { delete g; }

const char* lcrl_graph_error(LcrlGraph* g) { return g->error.c_str(); }

// Waits for all queued work, then makes a side stream current on this
// thread: what runs next (the warm-up, then the capture) runs there.
int lcrl_graph_enter_side_stream(LcrlGraph* g) {
  return guarded(g, [&] {
    c10::cuda::device_synchronize();
    g->guard.emplace(c10::cuda::getStreamFromPool());
  });
}

// Begins capturing this thread's work on the side stream. Thread-local
// mode: other threads of the learner (serving, validation) may keep using
// the CUDA runtime meanwhile.
int lcrl_graph_capture_begin(LcrlGraph* g) {
  return guarded(g, [&] { g->graph.capture_begin({0, 0}, cudaStreamCaptureModeThreadLocal); });
}

int lcrl_graph_capture_end(LcrlGraph* g) {
  return guarded(g, [&] { g->graph.capture_end(); });
}

// Back to the previous stream, after the side stream's work has finished.
int lcrl_graph_leave_side_stream(LcrlGraph* g) {
  return guarded(g, [&] {
    c10::cuda::device_synchronize();
    g->guard.reset();
  });
}

// Launches the captured work on the current stream, after what is queued
// there (the staged inputs).
int lcrl_graph_replay(LcrlGraph* g) {
  return guarded(g, [&] { g->graph.replay(); });
}

}  // extern "C"
