//! The kernels a test of the estimator checks, shared by its unit tests (`resolve`'s
//! `matches_reference`) and its integration tests (`fast_paths`): each includes this file as a
//! module, beside its own `Kernel` in scope.

use super::Kernel;

/// Every kernel this CPU runs. Which ones is said once per test binary on standard error, past
/// the test harness's capture, and loudly when the AVX2 kernel is left out, so that a run on a
/// CPU without AVX2 cannot pass for one that checked it. Fails when a kernel's availability
/// disagrees with the CPU's features (by `is_x86_feature_detected!`), and on CI (`CI=true`) on
/// an x86-64 CPU without AVX2: there it must be checked. A CPU without AVX-512 (many have none,
/// and older ones do not use it) leaves the AVX-512 kernel out, and says so.
pub fn kernels() -> Vec<Kernel> {
    #[cfg(target_arch = "x86_64")]
    let (cpu_avx2, cpu_avx512) = {
        use std::arch::is_x86_feature_detected as has;
        let avx2 = has!("avx2");
        let avx512 = has!("avx512f") && has!("avx512dq") && has!("avx512vl") && has!("avx512bw");
        // VBMI2: the generations where the kernel is used (see `Kernel::detect`).
        (avx2, avx2 && avx512 && has!("avx512vbmi2"))
    };
    #[cfg(not(target_arch = "x86_64"))]
    let (cpu_avx2, cpu_avx512) = (false, false);
    assert_eq!(
        Kernel::Avx2.available(),
        cpu_avx2,
        "the AVX2 kernel's availability disagrees with the CPU's AVX2"
    );
    assert_eq!(
        Kernel::Avx512.available(),
        cpu_avx512,
        "the AVX-512 kernel's availability disagrees with the CPU's AVX-512"
    );
    let on_ci = std::env::var("CI").is_ok_and(|v| v == "true");
    assert!(
        cpu_avx2 || !on_ci || !cfg!(target_arch = "x86_64"),
        "this x86-64 CPU has no AVX2: the AVX2 kernel cannot be checked, and CI must check it"
    );
    static SAID: std::sync::Once = std::sync::Once::new();
    SAID.call_once(|| {
        use std::io::Write;
        let line = if cpu_avx512 {
            "kernels checked: portable, avx2, avx512\n"
        } else if cpu_avx2 {
            "kernels checked: portable, avx2 (not avx512: this CPU does not run it)\n"
        } else if cfg!(target_arch = "x86_64") {
            "\n!!!!!!!!!! kernels checked: portable only: THE AVX2 KERNEL WAS NOT CHECKED (this CPU has no AVX2)\n\n"
        } else {
            "kernels checked: portable only (the AVX2 and AVX-512 kernels are x86-64's)\n"
        };
        let _ = std::io::stderr().write_all(line.as_bytes());
    });
    [Kernel::Portable, Kernel::Avx2, Kernel::Avx512]
        .into_iter()
        .filter(|k| k.available())
        .collect()
}
