//! Times one OIDN denoise of a synthetic noisy frame and prints the process's peak memory:
//! `cargo run --release -p splatd-denoise --example time_denoise -- [WIDTH HEIGHT [QUALITY [MAX_MEMORY_MIB]]]`
//! (1920x1080, `high` by default; OIDN from SPLATD_OIDN_LIB, see tests/setup/oidn.sh).

use std::time::Instant;

use splatd_denoise::{DenoiseInput, Oidn, Quality};

fn peak_rss_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let width: usize = args.first().map_or(1920, |a| a.parse().expect("WIDTH"));
    let height: usize = args.get(1).map_or(1080, |a| a.parse().expect("HEIGHT"));
    let quality: Quality = args
        .get(2)
        .map_or(Quality::High, |a| a.parse().expect("QUALITY"));
    let max_mib: Option<u32> = args.get(3).map(|a| a.parse().expect("MAX_MEMORY_MIB"));
    let oidn = Oidn::load().unwrap_or_else(|e| panic!("{e}"));
    let mut seed = 1u32;
    let mut noise = move || {
        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (seed >> 8) as f32 / (1u32 << 24) as f32
    };
    let n = width * height;
    let color: Vec<[f32; 3]> = (0..n)
        .map(|_| [noise() * 2.0, noise(), noise() * 0.5])
        .collect();
    let albedo = vec![[0.5f32; 3]; n];
    let normal = vec![[0.0f32, 0.0, 1.0]; n];
    let before = peak_rss_mib();
    for guided in [false, true] {
        let input = DenoiseInput {
            width,
            height,
            color: &color,
            albedo: guided.then_some(&albedo[..]),
            normal: guided.then_some(&normal[..]),
            hdr: true,
            quality,
            clean_aux: false,
            max_memory_mib: max_mib,
        };
        let started = Instant::now();
        let out = oidn.denoise(&input).unwrap_or_else(|e| panic!("{e}"));
        println!(
            "OIDN {} {width}x{height} {quality} maxMemoryMB={max_mib:?} guided={guided}: {:.2} s, peak RSS {:.0} MiB (inputs {:.0} MiB before)",
            oidn.version(),
            started.elapsed().as_secs_f64(),
            peak_rss_mib(),
            before,
        );
        assert_eq!(out.len(), n);
    }
}
