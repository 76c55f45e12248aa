//! Need maps and convergence in process: `GET /v1/frames/{id}/need` and the convergence in
//! `GET /v1/frames/{id}` equal the estimator's figures for the same samples computed here
//! independently, come from one shared render per version, and bad queries change nothing.

use axum::body::Body;
use axum::http::{header, Method, Request, StatusCode};
use serde_json::{json, Value};
use splatd_estimator::{CascadeLayout, FrameState, NeedMap, ResolveParams};
use splatd_proto::api::{self, CreateFrame};
use splatd_proto::{Batch, Record};
use splatd_scenes::synth::FireflyScene;
use tower::ServiceExt;

use super::router;
use crate::{AppState, Limits};
use splatd_formats::exr::decode_exr_channels;

const W: u32 = 40;
const H: u32 = 20;

/// A server with frame `f`, and the same samples splatted into a state of our own.
fn app() -> (AppState, FrameState) {
    let app = AppState::new(Limits::default(), None, None);
    let spec = app.store.check(CreateFrame::new("f", W, H)).unwrap();
    app.store.create(spec).unwrap();
    let state = FrameState::new(W, H, CascadeLayout::with_defaults());
    (app, state)
}

/// Posts passes `passes` of the synthetic scene to `f` and splats them into `state`.
fn post(app: &AppState, state: &mut FrameState, passes: std::ops::Range<u64>) {
    let scene = FireflyScene::new(W, H, 11);
    for pass in passes {
        let records: Vec<Record> = scene
            .pass(pass)
            .map(|(x, y, rgb)| Record::new(x, y, rgb))
            .collect();
        state.splat_all(scene.pass(pass));
        let batch = Batch::new("f", 1, pass, records).unwrap();
        app.store.get("f").unwrap().ingest(&batch).unwrap();
    }
}

async fn get(app: &AppState, path: &str) -> (StatusCode, Vec<u8>) {
    let request = Request::get(path).body(Body::empty()).unwrap();
    let response = router(app.clone()).oneshot(request).await.unwrap();
    let status = response.status();
    let bytes = axum::body::to_bytes(response.into_body(), usize::MAX)
        .await
        .unwrap();
    (status, bytes.to_vec())
}

async fn get_json(app: &AppState, path: &str) -> (StatusCode, Value) {
    let (status, bytes) = get(app, path).await;
    (status, serde_json::from_slice(&bytes).expect("a JSON body"))
}

fn expected(state: &FrameState, tile: u32) -> NeedMap {
    let params = ResolveParams::with_defaults();
    NeedMap::build(&[state], &state.resolve(&params), &params, tile).unwrap()
}

#[tokio::test]
async fn the_need_map_is_the_estimators_for_the_same_samples() {
    let (app, mut state) = app();
    post(&app, &mut state, 0..6);
    let (status, body) = get_json(&app, "/v1/frames/f/need?tile=16").await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let map: api::NeedMap = serde_json::from_value(body).unwrap();
    let want = expected(&state, 16);
    assert_eq!((map.tile, map.tiles_x, map.tiles_y), (16, 3, 2));
    assert_eq!(map.samples, u64::from(W * H) * 6);
    let need: Vec<f64> = want.tiles.iter().map(|t| t.need).collect();
    let removed: Vec<f64> = want.tiles.iter().map(|t| t.removed_fraction()).collect();
    let spp: Vec<f64> = want.tiles.iter().map(|t| t.spp_mean()).collect();
    // JSON carries f64s to within an ulp or so.
    let same = |a: &[f64], b: &[f64]| {
        a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|(x, y)| (x - y).abs() <= 1e-12 * y.abs())
    };
    assert!(same(&map.need, &need), "{:?} vs {need:?}", map.need);
    assert!(same(&map.removed_fraction, &removed));
    assert_eq!(map.spp_mean, spp);
    assert!(
        map.need.iter().all(|&n| n > 0.0),
        "6 spp of fireflies: every tile needs more"
    );

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
            .clone()
    };
    assert_eq!(
        channel("need.Y"),
        need.iter().map(|&n| n as f32).collect::<Vec<_>>()
    );
    assert_eq!(channel("spp_min.Y"), vec![6.0; 6]);
    assert_eq!(channel("removed.Y").len(), 6);
}

#[tokio::test]
async fn bad_need_queries_are_refused_by_name() {
    let (app, _) = app();
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
    let (app, mut state) = app();
    post(&app, &mut state, 0..4);
    let (status, info) = get_json(&app, "/v1/frames/f").await;
    assert_eq!(status, StatusCode::OK);
    let c: api::Convergence = serde_json::from_value(info["convergence"].clone()).unwrap();
    let want = expected(&state, api::DEFAULT_NEED_TILE).convergence();
    assert_eq!((c.samples, c.spp_min, c.spp_max), (want.samples, 4, 4));
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * b.abs();
    assert!(close(c.removed_fraction, want.removed_fraction));
    assert!(close(c.deficit_fraction, want.deficit_fraction));
    assert_eq!(c.converged_below, api::DEFAULT_CONVERGED_BELOW);
    assert!(!c.converged, "4 spp of fireflies is not converged: {c:?}");
    assert_eq!(c.history.len(), 1);
    assert_eq!(app.renders.rendered(), 1);

    // Asking again, or for the need map at the default tile, shares that render.
    get_json(&app, "/v1/frames/f").await;
    get_json(&app, "/v1/frames/f/need").await;
    assert_eq!(app.renders.rendered(), 1);

    // More samples: a new render, a new point, and less energy removed.
    post(&app, &mut state, 4..64);
    let (_, info) = get_json(&app, "/v1/frames/f").await;
    let later: api::Convergence = serde_json::from_value(info["convergence"].clone()).unwrap();
    assert_eq!(app.renders.rendered(), 2);
    assert_eq!(later.history.len(), 2);
    assert_eq!(later.history[1].spp_mean, 64.0);
    assert!(
        later.removed_fraction < c.removed_fraction,
        "{} then {}",
        c.removed_fraction,
        later.removed_fraction
    );
    assert!(close(
        later.removed_fraction,
        expected(&state, 16).convergence().removed_fraction
    ));
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
            let response = router(app).oneshot(request).await.unwrap();
            let status = response.status();
            let bytes = axum::body::to_bytes(response.into_body(), usize::MAX)
                .await
                .unwrap();
            (status, serde_json::from_slice::<Value>(&bytes).unwrap())
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
    assert_eq!(info["convergence"]["converged"], json!(true));
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
        converged: false,
        history: Vec::new(),
    };
    let text = super::operations::convergence_metrics(&[("shot\"1".into(), c)]);
    for line in [
        "# TYPE splatd_frame_removed_fraction gauge",
        "splatd_frame_removed_fraction{frame=\"shot\\\"1\"} 0.125",
        "splatd_frame_spp_min{frame=\"shot\\\"1\"} 1",
        "splatd_frame_spp_mean{frame=\"shot\\\"1\"} 2.5",
        "splatd_frame_spp_max{frame=\"shot\\\"1\"} 4",
        "splatd_frame_samples_per_second{frame=\"shot\\\"1\"} 50",
        "splatd_frame_converged{frame=\"shot\\\"1\"} 0",
        "splatd_frame_converged_below{frame=\"shot\\\"1\"} 0.01",
    ] {
        assert!(
            text.lines().any(|l| l == line),
            "{line:?} missing from\n{text}"
        );
    }
    assert_eq!(super::operations::convergence_metrics(&[]), "");
}
