//! `lcrl doctor`: proves libtorch is installed, found (rpath) and computing.

use anyhow::ensure;

/// Multiplies a small tensor and checks the answer, then prints versions.
pub fn run() -> anyhow::Result<()> {
    // Before any CUDA query: libtorch registers its CUDA backend only once
    // libtorch_cuda.so is loaded (learner/src/device/torch.rs says why).
    let cuda_library = lcrl_learner::device::torch::load_cuda();
    let sum = tensor_smoke_check()?;
    println!("libtorch: ok (2 · [1, 2, 3] sums to {sum})");
    println!("cores: {}", lcrl_learner::device::torch::available_cores());
    println!("torch threads: {} (libtorch's own default; run.threads = 0 uses the cores, or what the actors leave over, at most 4)", tch::get_num_threads());
    println!("libtorch_cuda: {cuda_library}");
    let available = tch::Cuda::is_available();
    println!("cuda available: {available}");
    if available {
        println!("cuda devices: {} (cudnn: {})", tch::Cuda::device_count(), tch::Cuda::cudnn_is_available());
        // A computation on the GPU, read back: the device works, not only exists.
        let t = tch::Tensor::from_slice(&[1.0f32, 2.0, 3.0]).to_device(tch::Device::Cuda(0));
        let sum = (t * 2.0).sum(tch::Kind::Float).double_value(&[]);
        ensure!(sum == 12.0, "CUDA computed 2·[1,2,3] summed as {sum}, expected 12");
        println!("cuda: ok (2 · [1, 2, 3] sums to {sum} on cuda:0)");
    }
    // Whether a GPU learner's DDPG updates can run as CUDA graphs
    // (`run.cuda_graphs`, learner/src/device/cuda_graph.rs).
    match lcrl_learner::device::cuda_graph::availability() {
        Ok(()) => println!("cuda graphs: available"),
        Err(why) => println!("cuda graphs: unavailable ({why})"),
    }
    Ok(())
}

/// Creates a tensor, computes with it and reads the result back.
pub fn tensor_smoke_check() -> anyhow::Result<f64> {
    let t = tch::Tensor::from_slice(&[1.0f32, 2.0, 3.0]);
    let sum = (t * 2.0).sum(tch::Kind::Float).double_value(&[]);
    ensure!(sum == 12.0, "libtorch computed 2·[1,2,3] summed as {sum}, expected 12");
    Ok(sum)
}
