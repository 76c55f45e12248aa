//! `/metrics` of a real server in the Prometheus text format, counting what happened.

use std::time::{Duration, Instant};

use crate::common::{parse_metrics, runtime, scrape_metrics, Server};
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{Batch, Client, Record};

/// Batches of worker 1 numbered `seqs` to frame `m`, each 10 samples at pixel (1, 2).
async fn post_tens(client: &Client, seqs: std::ops::Range<u64>) {
    for seq in seqs {
        let records = vec![Record::new(1, 2, [1.0; 3]); 10];
        client
            .post_batch(&Batch::new("m", 1, seq, records).unwrap())
            .await
            .unwrap();
    }
}

#[test]
fn metrics_count_ingest_rejections_frames_and_resolves() {
    let server = Server::start(&[]);
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    rt.block_on(async {
        client
            .create_frame(&CreateFrame::new("m", 8, 8))
            .await
            .unwrap();
        post_tens(&client, 0..3).await;
        // A duplicate and a refused batch.
        let records = vec![Record::new(1, 2, [1.0; 3]); 10];
        client
            .post_batch(&Batch::new("m", 1, 0, records).unwrap())
            .await
            .unwrap();
        let bad = vec![Record::new(9, 2, [1.0; 3])];
        assert!(client
            .post_batch(&Batch::new("m", 1, 3, bad).unwrap())
            .await
            .is_err());
        client.image("m", &ImageQuery::default()).await.unwrap();
        client.image("m", &ImageQuery::default()).await.unwrap();
    });
    // The first scrape renders the frame's first convergence point, at a time within it.
    let first_scrape = Instant::now();
    let text = scrape_metrics(&server.url);
    let first_scraped = Instant::now();
    let m = parse_metrics(&text);
    let get = |k: &str| *m.get(k).unwrap_or_else(|| panic!("no {k} in:\n{text}"));
    assert_eq!(get("splatd_samples_ingested_total"), 30.0);
    assert_eq!(get("splatd_batches_ingested_total"), 3.0);
    assert_eq!(get("splatd_batches_duplicate_total"), 1.0);
    assert_eq!(
        get("splatd_batches_rejected_total{reason=\"samples\"}"),
        1.0
    );
    assert_eq!(get("splatd_samples_rejected_total"), 1.0);
    assert_eq!(get("splatd_frames"), 1.0);
    assert_eq!(get("splatd_resolve_seconds_count"), 2.0);
    // Two images of one version: one resolve, the first.
    assert_eq!(get("splatd_resolves_total{made=\"whole\"}"), 1.0);
    assert!(get("splatd_resolve_seconds_bucket{le=\"+Inf\"}") == 2.0);
    assert!(get("splatd_ingest_bytes_total") > 5.0 * 200.0);
    assert!(
        text.contains("# TYPE splatd_resolve_seconds histogram"),
        "{text}"
    );
    // The frame's convergence: 30 samples, all in pixel (1, 2) of 64.
    let frame = |name: &str| get(&format!("{name}{{frame=\"m\"}}"));
    assert_eq!(frame("splatd_frame_spp_min"), 0.0);
    assert_eq!(frame("splatd_frame_spp_mean"), 30.0 / 64.0);
    assert_eq!(frame("splatd_frame_spp_max"), 30.0);
    assert_eq!(
        frame("splatd_frame_converged"),
        0.0,
        "63 pixels have no samples"
    );
    assert_eq!(frame("splatd_frame_converged_below"), 0.01);
    // 30 identical samples of one pixel: fully supported, nothing removed.
    assert_eq!(frame("splatd_frame_removed_fraction"), 0.0);
    // The rate is measured from that one point: no samples came after it.
    assert_eq!(frame("splatd_frame_samples_per_second"), 0.0);
    assert!(
        text.contains("# TYPE splatd_frame_removed_fraction gauge"),
        "{text}"
    );

    // 100 samples more, then a second scrape: a second point, and the rate over the time from
    // the first point (the newest at least a second old, or else the oldest) to this scrape:
    // 100 samples over a time that lies between the two scrapes' ends (which the first point and
    // this scrape's rate each lie within), so within bounds measured here. If this scrape itself
    // took a second or more, its own new point may be the one the rate starts from: then 0.
    // A second between the scrapes, so that their own durations leave the bounds tight.
    std::thread::sleep(Duration::from_secs(1));
    rt.block_on(async {
        post_tens(&client, 10..20).await;
    });
    let second_scrape = Instant::now();
    let text = scrape_metrics(&server.url);
    let second_scraped = Instant::now();
    let m = parse_metrics(&text);
    let rate = *m
        .get("splatd_frame_samples_per_second{frame=\"m\"}")
        .unwrap_or_else(|| panic!("no rate in:\n{text}"));
    assert_eq!(m["splatd_frame_spp_max{frame=\"m\"}"], 130.0);
    let longest = (second_scraped - first_scrape).as_secs_f64();
    let shortest = (second_scrape - first_scraped).as_secs_f64();
    let (low, high) = (100.0 / longest, 100.0 / shortest);
    let slow_scrape = second_scraped - second_scrape >= Duration::from_secs(1);
    assert!(
        (low * (1.0 - 1e-9)..=high * (1.0 + 1e-9)).contains(&rate) || (slow_scrape && rate == 0.0),
        "{rate} samples/s, not 100 samples over {shortest}..{longest} s"
    );
    // The first scrape's figures took the images' resolve as it was; the second's patched it
    // where the batches changed the frame.
    let text = scrape_metrics(&server.url);
    let m = parse_metrics(&text);
    for (made, resolves) in [("whole", 1.0), ("patched", 1.0)] {
        let key = format!("splatd_resolves_total{{made=\"{made}\"}}");
        assert_eq!(m.get(&key), Some(&resolves), "{key} in:\n{text}");
    }
}
