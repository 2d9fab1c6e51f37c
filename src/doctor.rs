//! `lcrl doctor`: proves libtorch is installed, found (rpath) and computing.

use anyhow::ensure;

/// Multiplies a small tensor and checks the answer, then prints versions.
pub fn run() -> anyhow::Result<()> {
    let sum = tensor_smoke_check()?;
    println!("libtorch: ok (2 · [1, 2, 3] sums to {sum})");
    println!("torch threads: {}", tch::get_num_threads());
    println!("cuda available: {}", tch::Cuda::is_available());
    Ok(())
}

/// Creates a tensor, computes with it and reads the result back.
pub fn tensor_smoke_check() -> anyhow::Result<f64> {
    let t = tch::Tensor::from_slice(&[1.0f32, 2.0, 3.0]);
    let sum = (t * 2.0).sum(tch::Kind::Float).double_value(&[]);
    ensure!(sum == 12.0, "libtorch computed 2·[1,2,3] summed as {sum}, expected 12");
    Ok(sum)
}

#[cfg(test)]
mod tests {
    #[test]
    fn libtorch_creates_and_computes_a_tensor() {
        assert_eq!(super::tensor_smoke_check().unwrap(), 12.0);
    }
}
