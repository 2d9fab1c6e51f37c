use super::common::{lcrl, stdout};

/// libtorch is found through the rpath (no LD_LIBRARY_PATH) and computes.
#[test]
fn doctor_runs_libtorch_without_ld_library_path() {
    let out = lcrl().arg("doctor").env_remove("LD_LIBRARY_PATH").output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout(&out).contains("libtorch: ok"), "{}", stdout(&out));
}
