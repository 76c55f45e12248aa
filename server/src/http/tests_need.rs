//! Need maps and convergence in process: `GET /v1/frames/{id}/need` and the convergence in
//! `GET /v1/frames/{id}` equal figures worked out by hand for the samples posted (from the
//! definitions in docs/ALGORITHM.md, not with the estimator's code), come from one shared render
//! per version, and bad queries change nothing.

use axum::body::Body;
use axum::http::{header, Method, Request, StatusCode};
use serde_json::{json, Value};
use splatd_estimator::{DEFAULT_KAPPA, DEFAULT_KAPPA_EXPONENT, DEFAULT_KAPPA_MIN};
use splatd_proto::api;
use splatd_proto::{Batch, Record};

use crate::{testing, AppState, Limits};
use splatd_formats::exr::decode_exr_channels;

const W: u32 = 40;
const H: u32 = 20;
/// The one firefly: a sample of grey [`FIREFLY`] in this pixel.
const FIREFLY_AT: (u32, u32) = (20, 5);
/// The top cascade's scale with the default layout (`0.125 * 8^5`): the firefly lies wholly in
/// it, as every smooth sample (grey 1, cascade 1's scale) lies wholly in cascade 1.
const FIREFLY: f32 = 4096.0;

/// Pixels that get no samples: the right half of the top right tile (16-pixel tiles) and the
/// whole bottom middle tile.
fn empty(x: u32, y: u32) -> bool {
    (x >= 36 && y < 16) || ((16..32).contains(&x) && y >= 16)
}

/// A server with frame `f` and no samples.
fn app() -> AppState {
    testing::with_frame(AppState::new(Limits::default(), None, None), "f", W, H)
}

/// Posts passes `passes` to `f`: each gives every pixel but the [`empty`] ones one sample of
/// grey 1; pass 0 also carries the firefly.
fn post(app: &AppState, passes: std::ops::Range<u64>) {
    for pass in passes {
        let mut records: Vec<Record> = (0..H)
            .flat_map(|y| (0..W).map(move |x| (x, y)))
            .filter(|&(x, y)| !empty(x, y))
            .map(|(x, y)| Record::new(x, y, [1.0; 3]))
            .collect();
        if pass == 0 {
            records.push(Record::new(FIREFLY_AT.0, FIREFLY_AT.1, [FIREFLY; 3]));
        }
        let batch = Batch::new("f", 1, pass, records).unwrap();
        app.store.get("f").unwrap().ingest(&batch).unwrap();
    }
}

/// One pixel's figures by hand, in units of grey luminance (only their ratios are compared), for
/// `smooth` samples of grey 1 and, if `firefly`, the firefly. From docs/ALGORITHM.md:
///
/// * cascade 1 holds the `smooth` samples; with 8 or more its count term
///   `(n - kappa_min) / kappa(N)` is at least 1: full weight, nothing removed, no deficit;
/// * the top cascade holds the firefly, supported by that one sample alone (in the pixel and in
///   its 3x3 pool): count term `(1 - kappa_min) / kappa(N) = 0`, value term
///   `L(F) / (kappa(N) * 4096)` with `F` the `smooth` samples' sum, so the weight is the value
///   term; `(1 - w) 4096 / N` is removed, and its deficit is all of it, `4096 / N` (`u = 1`).
///   The default `spread` variant gives none of it back: one sample of the band in the whole
///   frame is below its `spread_support`.
#[derive(Debug, Clone, Copy, Default)]
struct Pixel {
    samples: u64,
    mean: f64,
    removed: f64,
    deficit: f64,
}

fn pixel(smooth: u64, firefly: bool) -> Pixel {
    if smooth == 0 {
        return Pixel::default();
    }
    let n = smooth + u64::from(firefly);
    let nf = n as f64;
    let kappa = DEFAULT_KAPPA * nf.powf(DEFAULT_KAPPA_EXPONENT);
    assert!(
        (smooth as f64 - DEFAULT_KAPPA_MIN) / kappa >= 1.0,
        "cascade 1 fully supported"
    );
    if !firefly {
        return Pixel {
            samples: n,
            mean: 1.0,
            ..Pixel::default()
        };
    }
    let top = f64::from(FIREFLY);
    let count_term = (1.0 - DEFAULT_KAPPA_MIN) / kappa;
    let value_term = smooth as f64 / (kappa * top);
    let w = count_term.max(value_term).clamp(0.0, 1.0);
    Pixel {
        samples: n,
        mean: (smooth as f64 + top) / nf,
        removed: (1.0 - w) * top / nf,
        deficit: top / nf,
    }
}

/// The pixels of the frame after `passes` passes, row-major.
fn pixels(passes: u64) -> Vec<Pixel> {
    (0..H)
        .flat_map(|y| (0..W).map(move |x| (x, y)))
        .map(|(x, y)| {
            let smooth = if empty(x, y) { 0 } else { passes };
            pixel(smooth, (x, y) == FIREFLY_AT)
        })
        .collect()
}

/// A tile's or the frame's figures by hand (docs/ALGORITHM.md, "Need map").
#[derive(Debug)]
struct Figures {
    samples: u64,
    spp_min: u64,
    spp_mean: f64,
    removed_fraction: f64,
    deficit_fraction: f64,
    need: f64,
}

fn figures<'a>(pixels: impl IntoIterator<Item = &'a Pixel>) -> Figures {
    let (mut count, mut empty, mut samples, mut spp_min) = (0u64, 0u64, 0u64, u64::MAX);
    let (mut mean, mut removed, mut deficit) = (0.0, 0.0, 0.0);
    for p in pixels {
        count += 1;
        empty += u64::from(p.samples == 0);
        samples += p.samples;
        spp_min = spp_min.min(p.samples);
        mean += p.mean;
        removed += p.removed;
        deficit += p.deficit;
    }
    let share = |part: f64| if mean > 0.0 { part / mean } else { 0.0 };
    let spp_mean = samples as f64 / count as f64;
    let (removed_fraction, deficit_fraction) = (share(removed), share(deficit));
    Figures {
        samples,
        spp_min,
        spp_mean,
        removed_fraction,
        deficit_fraction,
        need: (removed_fraction + deficit_fraction + empty as f64 / count as f64)
            / (spp_mean + 1.0),
    }
}

/// The frame's tiles of `tile` pixels after `passes` passes, row-major.
fn tiles(passes: u64, tile: u32) -> Vec<Figures> {
    let all = pixels(passes);
    let mut out = Vec::new();
    for ty in 0..H.div_ceil(tile) {
        for tx in 0..W.div_ceil(tile) {
            let inside = (ty * tile..H.min((ty + 1) * tile)).flat_map(|y| {
                (tx * tile..W.min((tx + 1) * tile)).map(move |x| (y * W + x) as usize)
            });
            out.push(figures(inside.map(|i| &all[i])));
        }
    }
    out
}

/// Equal within the `f32` rounding of the resolved layers the server sums.
fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-6 * b.abs()
}

fn all_close(got: &[f64], want: &[f64]) -> bool {
    got.len() == want.len() && got.iter().zip(want).all(|(&a, &b)| close(a, b))
}

async fn get(app: &AppState, path: &str) -> (StatusCode, Vec<u8>) {
    let reply = testing::send(app, Request::get(path).body(Body::empty()).unwrap()).await;
    (reply.status, reply.body.to_vec())
}

async fn get_json(app: &AppState, path: &str) -> (StatusCode, Value) {
    let (status, bytes) = get(app, path).await;
    (status, serde_json::from_slice(&bytes).expect("a JSON body"))
}

#[tokio::test]
async fn the_need_map_is_the_one_worked_out_by_hand_for_the_samples() {
    let app = app();
    post(&app, 0..8);
    let (status, body) = get_json(&app, "/v1/frames/f/need?tile=16").await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let map: api::NeedMap = serde_json::from_value(body).unwrap();
    let want = tiles(8, 16);
    assert_eq!((map.tile, map.tiles_x, map.tiles_y), (16, 3, 2));
    let total: u64 = want.iter().map(|t| t.samples).sum();
    assert_eq!(total, 8 * (800 - 64 - 64) + 1);
    assert_eq!(map.samples, total);
    let field = |f: fn(&Figures) -> f64| want.iter().map(f).collect::<Vec<_>>();
    let need = field(|t| t.need);
    // Smooth tiles need nothing; the half-empty one (8 spp on half its pixels) needs
    // `0.5 / (4 + 1)`; the empty one `1 / (0 + 1)`; the firefly's tile its doubt.
    assert_eq!(&need[2..], [0.1, 0.0, 1.0, 0.0]);
    assert_eq!(need[0], 0.0);
    assert!(need[1] > 0.0, "{need:?}");
    assert!(all_close(&map.need, &need), "{:?} vs {need:?}", map.need);
    let removed = field(|t| t.removed_fraction);
    assert!(
        all_close(&map.removed_fraction, &removed),
        "{:?} vs {removed:?}",
        map.removed_fraction
    );
    let deficit = field(|t| t.deficit_fraction);
    assert!(
        all_close(&map.deficit_fraction, &deficit),
        "{:?} vs {deficit:?}",
        map.deficit_fraction
    );
    assert_eq!(map.spp_mean, field(|t| t.spp_mean));
    assert_eq!(
        map.spp_min,
        want.iter().map(|t| t.spp_min).collect::<Vec<_>>()
    );
    assert_eq!(map.spp_min, [8, 8, 0, 8, 0, 8]);

    // The default tile size, and the EXR form of the same map, one pixel per tile.
    let (_, body) = get_json(&app, "/v1/frames/f/need").await;
    assert_eq!(body["tile"], json!(api::DEFAULT_NEED_TILE));
    let (status, exr) = get(&app, "/v1/frames/f/need?tile=16&format=exr").await;
    assert_eq!(status, StatusCode::OK);
    let channels = decode_exr_channels(&exr).expect("an EXR");
    let channel = |name: &str| {
        channels
            .iter()
            .find(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("no {name}"))
            .1
            .iter()
            .map(|&v| f64::from(v))
            .collect::<Vec<_>>()
    };
    assert!(
        all_close(&channel("need.Y"), &need),
        "{:?}",
        channel("need.Y")
    );
    assert!(all_close(&channel("removed.Y"), &removed));
    assert_eq!(channel("spp_min.Y"), [8.0, 8.0, 0.0, 8.0, 0.0, 8.0]);
}

#[tokio::test]
async fn bad_need_queries_are_refused_by_name() {
    let app = app();
    for (path, status, code) in [
        ("/v1/frames/f/need?tile=0", 400, "invalid_parameters"),
        ("/v1/frames/f/need?tile=100000", 400, "invalid_parameters"),
        ("/v1/frames/f/need?tile=big", 400, "bad_query"),
        ("/v1/frames/f/need?format=png", 400, "bad_query"),
        ("/v1/frames/f/need?tiles=8", 400, "bad_query"),
        ("/v1/frames/nope/need", 404, "unknown_frame"),
    ] {
        let (got, body) = get_json(&app, path).await;
        assert_eq!(
            (got.as_u16(), body["error"].as_str()),
            (status, Some(code)),
            "{path}"
        );
    }
    assert_eq!(app.renders.rendered(), 0, "nothing was resolved for them");
}

#[tokio::test]
async fn frame_info_shows_convergence_from_one_shared_render_per_version() {
    let app = app();
    post(&app, 0..8);
    let (status, info) = get_json(&app, "/v1/frames/f").await;
    assert_eq!(status, StatusCode::OK);
    let c: api::Convergence = serde_json::from_value(info["convergence"].clone()).unwrap();
    let want = figures(&pixels(8));
    assert_eq!((c.samples, c.spp_min, c.spp_max), (want.samples, 0, 9));
    assert!(
        close(c.removed_fraction, want.removed_fraction),
        "{c:?} vs {want:?}"
    );
    assert!(
        close(c.deficit_fraction, want.deficit_fraction),
        "{c:?} vs {want:?}"
    );
    assert_eq!(c.converged_below, api::DEFAULT_CONVERGED_BELOW);
    assert!(
        !c.converged,
        "empty pixels and a firefly are not converged: {c:?}"
    );
    assert_eq!(c.history.len(), 1);
    assert_eq!(app.renders.rendered(), 1);

    // Asking again, or for the need map at the default tile, shares that render.
    get_json(&app, "/v1/frames/f").await;
    get_json(&app, "/v1/frames/f/need").await;
    assert_eq!(app.renders.rendered(), 1);

    // More samples: a new render, a new point, and less energy removed.
    post(&app, 8..64);
    let (_, info) = get_json(&app, "/v1/frames/f").await;
    let later: api::Convergence = serde_json::from_value(info["convergence"].clone()).unwrap();
    let want_later = figures(&pixels(64));
    assert_eq!(app.renders.rendered(), 2);
    assert_eq!(later.history.len(), 2);
    assert_eq!(later.history[1].spp_mean, want_later.spp_mean);
    assert!(
        later.removed_fraction < c.removed_fraction,
        "{} then {}",
        c.removed_fraction,
        later.removed_fraction
    );
    assert!(
        close(later.removed_fraction, want_later.removed_fraction),
        "{later:?} vs {want_later:?}"
    );
    // The list stays cheap: no convergence there.
    let (_, list) = get_json(&app, "/v1/frames").await;
    assert!(list["frames"][0].get("convergence").is_none());
    assert_eq!(app.renders.rendered(), 2);
}

#[tokio::test]
async fn the_threshold_is_set_at_creation_and_validated() {
    let app = AppState::new(Limits::default(), None, None);
    let create = |body: Value| {
        let app = app.clone();
        async move {
            let request = Request::builder()
                .method(Method::POST)
                .uri("/v1/frames")
                .header(header::CONTENT_TYPE, "application/json")
                .body(Body::from(body.to_string()))
                .unwrap();
            let reply = testing::send(&app, request).await;
            (reply.status, reply.json())
        }
    };
    for bad in [json!(0.0), json!(-0.1), json!(1.5)] {
        let (status, body) =
            create(json!({"id": "bad", "width": 2, "height": 2, "converged_below": bad})).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{bad}");
        assert_eq!(body["error"], "invalid_parameters");
        assert!(
            body["message"]
                .as_str()
                .unwrap()
                .contains("converged_below"),
            "{body}"
        );
    }
    assert!(app.store.list().is_empty(), "nothing was created");

    // A smooth 2x2 frame at 8 spp removes nothing: converged at any threshold.
    let (status, _) =
        create(json!({"id": "g", "width": 2, "height": 2, "converged_below": 0.001})).await;
    assert_eq!(status, StatusCode::CREATED);
    let records = (0..32)
        .map(|i| Record::new(i % 2, (i / 2) % 2, [0.5; 3]))
        .collect();
    let batch = Batch::new("g", 1, 0, records).unwrap();
    app.store.get("g").unwrap().ingest(&batch).unwrap();
    let (_, info) = get_json(&app, "/v1/frames/g").await;
    assert_eq!(info["convergence"]["converged_below"], json!(0.001));
    assert_eq!(info["convergence"]["removed_fraction"], json!(0.0));
    assert_eq!(info["convergence"]["own_count_from"], json!(16));
    assert_eq!(info["convergence"]["converged"], json!(true));
    assert_eq!(info["convergence"]["waiting_on"], json!(null));

    // Until then, what the frame waits on: pixels without samples, then, at one sample a
    // pixel, each pixel's own samples, then (from 16) a firefly's removed energy.
    let (status, _) = create(json!({"id": "w", "width": 2, "height": 2})).await;
    assert_eq!(status, StatusCode::CREATED);
    let frame = app.store.get("w").unwrap();
    let mut seq = 0;
    let mut post = |records: Vec<Record>| {
        seq += 1;
        frame
            .ingest(&Batch::new("w", 1, seq, records).unwrap())
            .unwrap();
    };
    let waiting_on = |app: AppState| async move {
        let (_, info) = get_json(&app, "/v1/frames/w").await;
        let c = &info["convergence"];
        assert_eq!(c["converged"], json!(c["waiting_on"].is_null()), "{c}");
        c["waiting_on"].clone()
    };
    post(
        (0..3)
            .map(|i| Record::new(i % 2, i / 2, [0.5; 3]))
            .collect(),
    );
    assert_eq!(
        waiting_on(app.clone()).await,
        json!("pixels_without_samples")
    );
    post(vec![Record::new(1, 1, [0.5; 3])]);
    assert_eq!(waiting_on(app.clone()).await, json!("own_samples"));
    post(
        (0..60)
            .map(|i| Record::new(i % 2, (i / 2) % 2, [0.5; 3]))
            .collect(),
    );
    post(vec![Record::new(0, 0, [5000.0; 3])]);
    assert_eq!(waiting_on(app.clone()).await, json!("removed_energy"));
}

#[test]
fn convergence_metrics_are_prometheus_gauges_per_frame() {
    let c = api::Convergence {
        samples: 100,
        spp_min: 1,
        spp_mean: 2.5,
        spp_max: 4,
        removed_fraction: 0.125,
        deficit_fraction: 0.25,
        samples_per_second: 50.0,
        converged_below: 0.01,
        own_count_from: 16,
        converged: false,
        waiting_on: Some(api::WaitingOn::RemovedEnergy),
        history: Vec::new(),
    };
    let figures = super::operations::FrameFigures {
        id: "shot\"1".into(),
        c,
        age: 2.5,
    };
    let text = super::operations::convergence_metrics(&[figures]);
    for line in [
        "# TYPE splatd_frame_removed_fraction gauge",
        "splatd_frame_removed_fraction{frame=\"shot\\\"1\"} 0.125",
        "splatd_frame_spp_min{frame=\"shot\\\"1\"} 1",
        "splatd_frame_spp_mean{frame=\"shot\\\"1\"} 2.5",
        "splatd_frame_spp_max{frame=\"shot\\\"1\"} 4",
        "splatd_frame_samples_per_second{frame=\"shot\\\"1\"} 50",
        "splatd_frame_converged{frame=\"shot\\\"1\"} 0",
        "splatd_frame_converged_below{frame=\"shot\\\"1\"} 0.01",
        "splatd_frame_figures_age_seconds{frame=\"shot\\\"1\"} 2.5",
    ] {
        assert!(
            text.lines().any(|l| l == line),
            "{line:?} missing from\n{text}"
        );
    }
    assert_eq!(super::operations::convergence_metrics(&[]), "");
}
