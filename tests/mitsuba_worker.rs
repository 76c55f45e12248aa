//! The Mitsuba worker's need-guided mode end to end: Mitsuba 3 (from PyPI, installed by
//! `tests/setup/mitsuba.sh`) renders the worker's built-in scene at 32x32 and the worker posts
//! with the installed Python client to a real server.
//!
//! After a uniform warm-up the test fetches the need map itself; one guided round then lands
//! exactly where that map points: every tile gains the samples per pixel that the estimator's
//! own `NeedMap::plan` gives the map's scores plus the worker's base doubt (the worker plans in
//! Python), so the neediest tile gains the most and spp becomes uneven, and nothing lands
//! elsewhere. A second run with the default
//! policy (warm-up, several rounds with uniform passes mixed in, a budget that no tile divides)
//! posts exactly its budget. The frame's totals are what the worker posted.

use std::path::Path;
use std::process::Command;

use crate::common::{python_package_venv, run_setup, runtime, venv_site_packages, Server};
use splatd_estimator::{NeedMap, TileNeed};
use splatd_proto::api::NeedMap as ApiNeedMap;
use splatd_proto::Client;

const RES: u32 = 32;
const TILE: u32 = 8;
const WARM_PASSES: u64 = 4;
const BASE_DOUBT: f64 = 0.2;

/// The estimator's map with the scores the worker plans with: the server's need plus the base
/// doubt per sample of each tile (all `plan` reads).
fn estimator_map(map: &ApiNeedMap) -> NeedMap {
    let tiles = (0..map.tiles_x * map.tiles_y)
        .map(|i| {
            let (x, y) = ((i % map.tiles_x) * map.tile, (i / map.tiles_x) * map.tile);
            TileNeed {
                x,
                y,
                width: map.tile.min(map.width - x),
                height: map.tile.min(map.height - y),
                need: map.need[i as usize] + BASE_DOUBT / (map.spp_mean[i as usize] + 1.0),
                ..TileNeed::default()
            }
        })
        .collect();
    NeedMap {
        width: map.width,
        height: map.height,
        tile: map.tile,
        tiles_x: map.tiles_x,
        tiles_y: map.tiles_y,
        tiles,
    }
}

#[test]
fn guided_mitsuba_renders_land_where_the_need_map_points() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let python =
        run_setup("mitsuba.sh").unwrap_or_else(|e| panic!("tests/setup/mitsuba.sh failed: {e}"));
    let dir = tempfile::tempdir().unwrap();
    // The client package as pip installs it; Mitsuba from python3's own site-packages.
    let venv_python = python_package_venv(dir.path());
    let site = venv_site_packages(&venv_python);

    let server = Server::start(&[]);
    let worker = |args: &[&str], what: &str| -> String {
        let out = Command::new(&python)
            .arg(root.join("proto/python/mitsuba_worker.py"))
            .args(["--url", &server.url, "--res", &RES.to_string()])
            .args(args)
            .env("PYTHONPATH", &site)
            .current_dir(dir.path())
            .output()
            .unwrap_or_else(|e| panic!("{what}: {e}"));
        let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success(),
            "{what} failed:\n{stdout}{}",
            String::from_utf8_lossy(&out.stderr)
        );
        stdout
    };
    let pixels = u64::from(RES * RES);
    let client = Client::new(&server.url).unwrap();
    let rt = runtime();

    // The uniform warm-up: every pixel has WARM_PASSES samples.
    worker(
        &[
            "--frame",
            "m",
            "--passes",
            &WARM_PASSES.to_string(),
            "--worker",
            "7",
        ],
        "the uniform passes",
    );
    let before = rt.block_on(client.need("m", Some(TILE))).unwrap();
    assert_eq!(before.samples, WARM_PASSES * pixels);
    assert!(before.spp_min.iter().all(|&n| n == WARM_PASSES));

    // One guided round of 4 passes' worth, nothing uniform: the worker asks for the map the test
    // just fetched (nothing changed in between) and plans with it.
    let budget = 4 * pixels;
    let expected = estimator_map(&before).plan(budget);
    let tiles = (before.tiles_x * before.tiles_y) as usize;
    let out = worker(
        &[
            "--frame",
            "m",
            "--guided",
            "--samples",
            &budget.to_string(),
            "--warmup",
            "0",
            "--rounds",
            "1",
            "--uniform-share",
            "0",
            "--base-doubt",
            &BASE_DOUBT.to_string(),
            "--tile",
            &TILE.to_string(),
            "--worker",
            "8",
            "--first-pass",
            "100",
        ],
        "the guided round",
    );
    assert!(
        out.contains(&format!("done: {budget} samples")),
        "the worker's report: {out}"
    );
    assert!(
        out.contains(&format!(
            "round 0: need map at {} samples",
            WARM_PASSES * pixels
        )),
        "{out}"
    );
    let after = rt.block_on(client.need("m", Some(TILE))).unwrap();
    let info = rt.block_on(client.frame_info("m")).unwrap();
    assert_eq!(info.samples, WARM_PASSES * pixels + budget);
    assert_eq!(after.samples, info.samples);
    let gained: Vec<u64> = (0..tiles)
        .map(|t| {
            // Every pixel of a tile gained the same: its fewest samples rose with its mean.
            let gain = after.spp_mean[t] - before.spp_mean[t];
            assert_eq!(
                after.spp_min[t] - before.spp_min[t],
                gain as u64,
                "tile {t}"
            );
            gain as u64
        })
        .collect();
    assert_eq!(gained, expected, "spp gained per tile against the plan");
    assert_eq!(
        gained.iter().sum::<u64>() * u64::from(TILE * TILE),
        budget,
        "all of the budget landed in whole tiles"
    );
    let neediest = (0..tiles)
        .max_by(|&a, &b| before.need[a].total_cmp(&before.need[b]).then(b.cmp(&a)))
        .unwrap();
    let least = (0..tiles)
        .min_by(|&a, &b| before.need[a].total_cmp(&before.need[b]))
        .unwrap();
    assert_eq!(
        gained[neediest],
        *gained.iter().max().unwrap(),
        "the neediest tile gained the most: {gained:?}, need {:?}",
        before.need
    );
    assert!(
        gained[neediest] >= 2 * gained[least].max(1),
        "spp is uneven: {gained:?}, need {:?}",
        before.need
    );
    // More need never gets fewer samples (up to the one pass a remainder adds).
    for a in 0..tiles {
        for b in 0..tiles {
            if before.need[a] > before.need[b] {
                assert!(gained[a] + 1 >= gained[b], "{a} vs {b}: {gained:?}");
            }
        }
    }

    // The default policy on a fresh frame, with a budget no tile divides: exactly it is posted.
    let odd = 12 * pixels + 37;
    let out = worker(
        &[
            "--frame",
            "d",
            "--guided",
            "--samples",
            &odd.to_string(),
            "--uniform-share",
            "0.5",
            "--rounds",
            "3",
        ],
        "the guided worker's default policy",
    );
    assert!(out.contains(&format!("done: {odd} samples")), "{out}");
    assert_eq!(out.matches("round ").count(), 3, "{out}");
    let info = rt.block_on(client.frame_info("d")).unwrap();
    assert_eq!(info.samples, odd);
    assert_eq!(info.rejected_samples, 0);
    // The warm-up's quarter is uniform passes, and every round adds half its share as uniform
    // passes (a whole one here) before the guided part: no pixel starves.
    let warm = (odd / 4) / pixels;
    let per_round = (odd - warm * pixels) / 3;
    assert_eq!((warm, per_round / 2 / pixels), (3, 1));
    assert!(info.spp_min >= warm + 3, "{info:?}");
    assert!(info.spp_max > info.spp_min + 1, "{info:?}");
}
