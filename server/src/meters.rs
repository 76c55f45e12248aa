//! Every metric the server exports, named once: handlers, durability, the transport and the
//! per-frame gauges use these names, and a test holds the README's list of metrics to them.
//!
//! Counters end in `_total`; labels are noted beside their metric.

/// Samples of applied batches and passes.
pub const SAMPLES_INGESTED: &str = "splatd_samples_ingested_total";
/// Applied batches and passes.
pub const BATCHES_INGESTED: &str = "splatd_batches_ingested_total";
/// Batches recognised as applied before (retries), applied nothing.
pub const BATCHES_DUPLICATE: &str = "splatd_batches_duplicate_total";
/// Refused batches, label `reason`.
pub const BATCHES_REJECTED: &str = "splatd_batches_rejected_total";
/// Samples of refused batches.
pub const SAMPLES_REJECTED: &str = "splatd_samples_rejected_total";
/// Bytes of batch and pass bodies received.
pub const INGEST_BYTES: &str = "splatd_ingest_bytes_total";
/// Frames held (gauge).
pub const FRAMES: &str = "splatd_frames";
/// Bytes of deleted frames' cells kept for new frames (gauge; see `memory::CellPool`).
pub const IDLE_CELL_BYTES: &str = "splatd_idle_cell_bytes";
/// Seconds an `image.exr` took (histogram).
pub const RESOLVE_SECONDS: &str = "splatd_resolve_seconds";
/// Renders run for images, previews, need maps, convergence figures and the tev feed;
/// requests that shared one count once (a dashboard of unchanged frames adds none).
pub const RENDERS: &str = "splatd_renders_total";
/// Resolves renders ran, label `made`: `whole` (a whole frame resolved) or `patched` (a kept
/// resolve brought up to date where the frame changed). Renders that took a kept resolve as it
/// was add none.
pub const RESOLVES: &str = "splatd_resolves_total";
/// Seconds a request waited for a changing frame's render pace (`--render-share`), when it
/// waited (histogram).
pub const RENDER_PACE_SECONDS: &str = "splatd_render_pace_seconds";
/// Seconds OIDN took for a denoised image (histogram).
pub const DENOISE_SECONDS: &str = "splatd_denoise_seconds";
/// Images OIDN denoised, label `memory`: `untiled` when it had what the image needs untiled,
/// `tiled` when the working memory was short and it denoised in tiles (the same output, slower).
pub const DENOISED_IMAGES: &str = "splatd_denoised_images_total";
/// Imported states, label `result` (`applied`, `duplicate`).
pub const IMPORTS: &str = "splatd_imports_total";
/// Exported states.
pub const EXPORTS: &str = "splatd_exports_total";
/// Deltas pushed upstream, label `result`.
pub const PUSHES: &str = "splatd_pushes_total";
/// Snapshots written.
pub const SNAPSHOTS: &str = "splatd_snapshots_total";
/// Snapshots that failed.
pub const SNAPSHOT_FAILURES: &str = "splatd_snapshot_failures_total";
/// Frames whose latest snapshot failed (gauge).
pub const FRAMES_SNAPSHOT_FAILING: &str = "splatd_frames_snapshot_failing";
/// Frames set aside as damaged at start (gauge).
pub const FRAMES_QUARANTINED: &str = "splatd_frames_quarantined";
/// Log lines that could not be written (the `splatd` command's log sink counts them).
pub const LOG_LINES_DROPPED: &str = "splatd_log_lines_dropped_total";
/// Requests refused by the bearer-token check, label `status`.
pub const AUTH_REFUSED: &str = "splatd_auth_refused_total";
/// Connections the server closed, label `reason` (`evicted`, `full`, `head_timeout`, `idle`,
/// `slow_reader`).
pub const CONNECTIONS_CLOSED: &str = "splatd_connections_closed_total";
/// Frames pushed to tev.
pub const TEV_UPDATES: &str = "splatd_tev_updates_total";

/// Per-frame gauge (label `frame`): luminance the resolve removes, as a fraction of the mean's.
pub const FRAME_REMOVED_FRACTION: &str = "splatd_frame_removed_fraction";
/// Per-frame gauge: fewest samples of any pixel.
pub const FRAME_SPP_MIN: &str = "splatd_frame_spp_min";
/// Per-frame gauge: mean samples per pixel.
pub const FRAME_SPP_MEAN: &str = "splatd_frame_spp_mean";
/// Per-frame gauge: most samples of any pixel.
pub const FRAME_SPP_MAX: &str = "splatd_frame_spp_max";
/// Per-frame gauge: samples accepted per second lately.
pub const FRAME_SAMPLES_PER_SECOND: &str = "splatd_frame_samples_per_second";
/// Per-frame gauge: 1 when the frame is converged at its threshold, else 0.
pub const FRAME_CONVERGED: &str = "splatd_frame_converged";
/// Per-frame gauge: the frame's convergence threshold.
pub const FRAME_CONVERGED_BELOW: &str = "splatd_frame_converged_below";
/// Gauge per frame: seconds since the render its figures come from.
pub const FRAME_FIGURES_AGE: &str = "splatd_frame_figures_age_seconds";

/// Every name above.
pub const ALL: [&str; 33] = [
    SAMPLES_INGESTED,
    BATCHES_INGESTED,
    BATCHES_DUPLICATE,
    BATCHES_REJECTED,
    SAMPLES_REJECTED,
    INGEST_BYTES,
    FRAMES,
    IDLE_CELL_BYTES,
    RESOLVE_SECONDS,
    RENDERS,
    RESOLVES,
    RENDER_PACE_SECONDS,
    DENOISE_SECONDS,
    DENOISED_IMAGES,
    IMPORTS,
    EXPORTS,
    PUSHES,
    SNAPSHOTS,
    SNAPSHOT_FAILURES,
    FRAMES_SNAPSHOT_FAILING,
    FRAMES_QUARANTINED,
    LOG_LINES_DROPPED,
    AUTH_REFUSED,
    CONNECTIONS_CLOSED,
    TEV_UPDATES,
    FRAME_REMOVED_FRACTION,
    FRAME_SPP_MIN,
    FRAME_SPP_MEAN,
    FRAME_SPP_MAX,
    FRAME_SAMPLES_PER_SECOND,
    FRAME_CONVERGED,
    FRAME_CONVERGED_BELOW,
    FRAME_FIGURES_AGE,
];

#[cfg(test)]
mod tests {
    /// The README's list of metrics names every metric, and no metric that is not here.
    #[test]
    fn the_readme_lists_every_metric() {
        let readme = include_str!("../../README.md");
        for name in super::ALL {
            assert!(readme.contains(&format!("`{name}")), "README lacks {name}");
        }
        let mut listed: Vec<&str> = readme
            .split('`')
            .filter(|w| {
                w.starts_with("splatd_")
                    && w.chars()
                        .all(|c| c.is_ascii_lowercase() || c == '_' || c == '{' || c == '}')
            })
            .map(|w| w.split('{').next().unwrap())
            .collect();
        listed.sort();
        listed.dedup();
        for name in listed {
            assert!(
                super::ALL.contains(&name),
                "README lists {name}, which is not a metric"
            );
        }
    }
}
