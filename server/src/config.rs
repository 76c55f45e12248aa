//! A server's configuration: one struct, from which `splatd serve` derives its flags, so every
//! default and limit is written once, here.
//!
//! [`Config::default`] parses an empty command line through the same definitions, so a server
//! built in code (the demo, in-process tests) gets exactly the defaults `splatd serve` documents.

use std::path::PathBuf;
use std::time::Duration;

use clap::Parser;

use crate::Limits;

/// Everything `splatd serve` can be told.
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct Config {
    /// Address to listen on (port 0 picks a free port; the address is printed).
    #[arg(long, default_value = "127.0.0.1:7878")]
    pub addr: String,
    /// Most records in one batch.
    #[arg(long, default_value_t = splatd_proto::batch::DEFAULT_MAX_RECORDS)]
    pub max_records: usize,
    /// Most frames held at once.
    #[arg(long, default_value_t = 64)]
    pub max_frames: usize,
    /// Most pixels in one frame.
    #[arg(long, default_value_t = 8192 * 8192)]
    pub max_pixels: u64,
    /// Most cascades in one frame.
    #[arg(long, default_value_t = splatd_estimator::MAX_CASCADES)]
    pub max_cascades: u32,
    /// Most MiB of cascades over all frames.
    #[arg(long, default_value_t = 8192)]
    pub max_memory_mib: u64,
    /// Longest a request may take, body included, in seconds.
    #[arg(long, default_value_t = 120)]
    pub request_timeout: u64,
    /// Longest a keep-alive connection may wait between two requests, in seconds.
    #[arg(long, default_value_t = 60)]
    pub idle_timeout: u64,
    /// Longest from accept (or from the first byte of a later request on the connection) to a
    /// complete request head, in seconds; a silent or trickling socket is closed.
    #[arg(long, default_value_t = 10)]
    pub head_timeout: u64,
    /// Longest from the first byte of a response to its last, in seconds; a client that reads
    /// slower is disconnected and the response's memory freed.
    #[arg(long, default_value_t = 300)]
    pub response_timeout: u64,
    /// Most connections open at once (lowered at start to leave a quarter of the open-file limit
    /// for other files). At the cap a new connection replaces the oldest one without a request
    /// in progress, or is closed at once if every connection is serving one.
    #[arg(long, default_value_t = 4096)]
    pub max_connections: usize,
    /// MiB that requests may hold at once beyond the frames: state copies being resolved or
    /// exported, encoded images. A request that cannot get its share within
    /// --work-wait-secs is answered 503 with Retry-After.
    #[arg(long, default_value_t = 2048)]
    pub work_memory_mib: u64,
    /// Longest a request waits for working memory, in seconds.
    #[arg(long, default_value_t = 10)]
    pub work_wait_secs: u64,
    /// Most of the wall time a frame that workers keep changing spends rendering (images,
    /// previews, figures), in (0, 1]: watchers then wait for its next render instead of
    /// slowing its ingest. 1 renders it back to back.
    #[arg(long, default_value_t = crate::render::pace::DEFAULT_SHARE, value_parser = parse_share)]
    pub render_share: f64,
    /// Keep frames on disk here so they survive restarts and crashes (see PROTOCOL.md,
    /// "Exactly-once and durability"). Without it frames live in memory only.
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// How often changed frames are snapshotted to the data directory, in milliseconds.
    #[arg(long, default_value_t = 1000)]
    pub snapshot_interval_ms: u64,
    /// Bearer tokens with roles, one `<roles> <token>` per line (roles: read, write, admin).
    /// Entries in the SPLATD_TOKENS environment variable (separated by `;` or newlines) are
    /// added. Without any token the server is open to everyone.
    #[arg(long)]
    pub tokens_file: Option<PathBuf>,
    /// Let requests without a token read (list frames, fetch images and previews).
    #[arg(long)]
    pub public_read: bool,
    /// Push resolved frames to the tev viewer listening at HOST:PORT as samples arrive.
    #[arg(long, value_name = "HOST:PORT")]
    pub tev: Option<String>,
    /// How often changed frames are pushed to tev, in milliseconds.
    #[arg(long, default_value_t = 1000)]
    pub tev_interval_ms: u64,
    /// Push mode: send what this node accumulates to the splatd at this URL
    /// (e.g. `http://render-head:7878`) as exact deltas, each applied there once.
    /// Not with `--data-dir`: what was pushed is not part of a snapshot, so a restarted node
    /// would push its restored frames again and count them twice upstream.
    #[arg(long, conflicts_with = "data_dir")]
    pub upstream: Option<String>,
    /// This node's id in its pushed deltas. Must not be reused by another process, including
    /// this node after a restart (default: 64 random bits).
    #[arg(long, requires = "upstream")]
    pub node_id: Option<String>,
    /// Milliseconds between two push rounds.
    #[arg(long, default_value_t = 1000, requires = "upstream")]
    pub push_interval_ms: u64,
    /// Bearer token sent to the upstream.
    #[arg(long, requires = "upstream")]
    pub upstream_token: Option<String>,
    /// Intel Open Image Denoise 2.x library (the path of libOpenImageDenoise.so.2) that
    /// `image.exr?denoise=oidn` runs, loaded at start; without it the dynamic loader's search
    /// path is tried. A server without a usable one runs, and answers denoise requests 501
    /// `denoiser_unavailable`. `bash tests/setup/oidn.sh` installs OIDN and prints the path.
    #[arg(long, env = "SPLATD_OIDN_LIB", value_name = "PATH")]
    pub oidn_lib: Option<PathBuf>,
    /// MiB every denoise reserves for OIDN from --work-memory-mib, with its images, before it
    /// starts. When OIDN runs it also gets what the working memory has free then, up to what
    /// the image needs untiled (about 640 bytes a pixel); short of that it denoises in tiles
    /// (the same output, slower).
    #[arg(long, default_value_t = crate::render::denoise::DEFAULT_LEAST_MIB)]
    pub oidn_min_memory_mib: u32,
    /// Most MiB one denoise may use inside OIDN (its maxMemoryMB: it denoises in tiles to stay
    /// below). Without it, as much as the image needs untiled, when the working memory has it.
    #[arg(long)]
    pub oidn_max_memory_mib: Option<u32>,
}

/// `Config` as a whole command line, only to parse the defaults.
#[derive(Parser)]
struct Defaults {
    #[command(flatten)]
    config: Config,
}

/// A share of the wall time: a number in (0, 1].
fn parse_share(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(share) if share > 0.0 && share <= 1.0 => Ok(share),
        _ => Err(format!(
            "a share of the time is a number in (0, 1], not {s:?}"
        )),
    }
}

impl Default for Config {
    fn default() -> Config {
        Defaults::try_parse_from(["splatd"])
            .expect("the defaults parse")
            .config
    }
}

impl Config {
    /// What the server refuses, from these settings.
    pub fn limits(&self) -> Limits {
        Limits {
            max_records: self.max_records,
            max_frames: self.max_frames,
            max_pixels: self.max_pixels,
            max_cascades: self.max_cascades,
            max_memory_bytes: self.max_memory_mib << 20,
            request_timeout: Duration::from_secs(self.request_timeout),
            idle_timeout: Duration::from_secs(self.idle_timeout),
            head_timeout: Duration::from_secs(self.head_timeout),
            response_timeout: Duration::from_secs(self.response_timeout),
            max_connections: self.max_connections,
            work_memory_bytes: self.work_memory_mib << 20,
            work_wait: Duration::from_secs(self.work_wait_secs),
            render_share: self.render_share,
        }
    }

    /// What a denoise may use inside OIDN.
    pub fn oidn_memory(&self) -> crate::render::denoise::OidnMemory {
        crate::render::denoise::OidnMemory {
            least_mib: self.oidn_min_memory_mib,
            most_mib: self.oidn_max_memory_mib,
        }
    }

    /// Time between two snapshot rounds.
    pub fn snapshot_interval(&self) -> Duration {
        Duration::from_millis(self.snapshot_interval_ms.max(1))
    }

    /// Time between two pushes to tev.
    pub fn tev_interval(&self) -> Duration {
        Duration::from_millis(self.tev_interval_ms.max(1))
    }

    /// Time between two push rounds.
    pub fn push_interval(&self) -> Duration {
        Duration::from_millis(self.push_interval_ms.max(1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_flags_defaults() {
        let c = Config::default();
        assert_eq!(c.addr, "127.0.0.1:7878");
        assert_eq!(c.max_records, splatd_proto::batch::DEFAULT_MAX_RECORDS);
        assert_eq!(c.limits().request_timeout, Duration::from_secs(120));
        assert_eq!(c.data_dir, None);
        let parsed = Defaults::try_parse_from(["splatd", "--max-frames", "3", "--public-read"])
            .unwrap()
            .config;
        assert_eq!((parsed.max_frames, parsed.public_read), (3, true));
        assert_eq!(c.limits().render_share, 0.2);
        for bad in ["0", "1.5", "-1", "NaN", "half"] {
            assert!(
                Defaults::try_parse_from(["splatd", "--render-share", bad]).is_err(),
                "--render-share {bad}"
            );
        }
        assert!(
            Defaults::try_parse_from(["splatd", "--upstream", "http://x", "--data-dir", "d"])
                .is_err(),
            "push mode and a data directory exclude each other"
        );
    }
}
