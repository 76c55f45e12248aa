//! The kernels a test of the estimator checks, shared by its unit tests (`resolve`'s
//! `matches_reference`) and its integration tests (`fast_paths`): each includes this file as a
//! module, beside its own `Kernel` in scope.

use super::Kernel;

/// Every kernel this CPU runs. Which ones is said once per test binary on standard error, past
/// the test harness's capture, and loudly when the AVX2 kernel is left out, so that a run on a
/// CPU without AVX2 cannot pass for one that checked it. Fails when the CPU has AVX2 (by
/// `is_x86_feature_detected!`) but the kernel says it is unavailable, and on CI (`CI=true`) on
/// an x86-64 CPU without AVX2: there it must be checked.
pub fn kernels() -> Vec<Kernel> {
    #[cfg(target_arch = "x86_64")]
    let cpu_avx2 = std::arch::is_x86_feature_detected!("avx2");
    #[cfg(not(target_arch = "x86_64"))]
    let cpu_avx2 = false;
    assert_eq!(
        Kernel::Avx2.available(),
        cpu_avx2,
        "the AVX2 kernel's availability disagrees with the CPU's AVX2"
    );
    let on_ci = std::env::var("CI").is_ok_and(|v| v == "true");
    assert!(
        cpu_avx2 || !on_ci || !cfg!(target_arch = "x86_64"),
        "this x86-64 CPU has no AVX2: the AVX2 kernel cannot be checked, and CI must check it"
    );
    static SAID: std::sync::Once = std::sync::Once::new();
    SAID.call_once(|| {
        use std::io::Write;
        let line = if cpu_avx2 {
            "kernels checked: portable, avx2\n"
        } else if cfg!(target_arch = "x86_64") {
            "\n!!!!!!!!!! kernels checked: portable only: THE AVX2 KERNEL WAS NOT CHECKED (this CPU has no AVX2)\n\n"
        } else {
            "kernels checked: portable only (the AVX2 kernel is x86-64's)\n"
        };
        let _ = std::io::stderr().write_all(line.as_bytes());
    });
    if cpu_avx2 {
        vec![Kernel::Portable, Kernel::Avx2]
    } else {
        vec![Kernel::Portable]
    }
}
