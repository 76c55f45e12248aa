//! Watching is free: reading the figures of frames that did not change renders nothing,
//! however many frames the server holds (more than the renders' cache keeps), and a change
//! costs one render of the frame that changed.

use axum::body::Body;
use axum::http::{Request, StatusCode};
use splatd_proto::{Batch, Record};

use crate::{testing, AppState, Limits};

/// More frames than the renders' cache holds (16).
const FRAMES: usize = 20;

async fn info(app: &AppState, id: &str) -> serde_json::Value {
    let request = Request::get(format!("/v1/frames/{id}"))
        .body(Body::empty())
        .unwrap();
    let reply = testing::send(app, request).await;
    assert_eq!(reply.status, StatusCode::OK);
    reply.json()
}

async fn list(app: &AppState) -> serde_json::Value {
    let request = Request::get("/v1/frames").body(Body::empty()).unwrap();
    let reply = testing::send(app, request).await;
    assert_eq!(reply.status, StatusCode::OK);
    reply.json()
}

fn post(app: &AppState, id: &str, seq: u64) {
    let records = (0..16)
        .map(|i| Record::new(i % 8, i / 8, [1.0 + seq as f32, 2.0, 3.0]))
        .collect();
    let batch = Batch::new(id, 1, seq, records).unwrap();
    app.store.get(id).unwrap().ingest(&batch).unwrap();
}

#[tokio::test]
async fn polling_unchanged_frames_renders_nothing() {
    let mut app = AppState::new(Limits::default(), None, None);
    let ids: Vec<String> = (0..FRAMES).map(|i| format!("f{i}")).collect();
    for id in &ids {
        app = testing::with_frame(app, id, 8, 8);
        post(&app, id, 0);
    }
    for id in &ids {
        let c = &info(&app, id).await["convergence"];
        assert_eq!(c["samples"], 16, "{id}: {c}");
    }
    assert_eq!(
        app.renders.rendered(),
        FRAMES as u64,
        "one render per frame"
    );

    // A dashboard polling every frame, round after round: nothing changed, nothing renders.
    for _ in 0..3 {
        for id in &ids {
            info(&app, id).await;
        }
        for frame in app.store.list() {
            crate::render::figures::convergence(&app, &frame)
                .await
                .unwrap();
        }
    }
    assert_eq!(
        app.renders.rendered(),
        FRAMES as u64,
        "unchanged frames render nothing"
    );

    // One frame changes: the next round renders it, once.
    post(&app, "f7", 1);
    for _ in 0..2 {
        for id in &ids {
            info(&app, id).await;
        }
    }
    assert_eq!(app.renders.rendered(), FRAMES as u64 + 1);
    assert_eq!(info(&app, "f7").await["convergence"]["samples"], 32);
}

/// The figures asked for after an image of the same version come from the image's resolve: a
/// need map, no second resolve.
#[tokio::test]
async fn figures_after_an_image_reuse_its_resolve() {
    let app = testing::with_frame(AppState::new(Limits::default(), None, None), "i", 8, 8);
    post(&app, "i", 0);
    let request = Request::get("/v1/frames/i/image.exr")
        .body(Body::empty())
        .unwrap();
    assert_eq!(testing::send(&app, request).await.status, StatusCode::OK);
    let shown = info(&app, "i").await;
    assert_eq!(shown["convergence"]["samples"], 16);
    let kept = app.renders.kept();
    assert_eq!(
        (kept.whole(), kept.patched()),
        (1, 0),
        "one resolve for both"
    );
    // Its samples per pixel are the render's, and they are what counting the cells gives.
    post(&app, "i", 1);
    let (shown, listed) = (info(&app, "i").await, list(&app).await);
    let counted = app.store.get("i").unwrap().info();
    let spp = |v: &serde_json::Value| {
        (
            v["spp_min"].clone(),
            v["spp_mean"].clone(),
            v["spp_max"].clone(),
        )
    };
    let want = (
        counted.spp_min.into(),
        counted.spp_mean.into(),
        counted.spp_max.into(),
    );
    assert_eq!(spp(&shown), want);
    assert_eq!(spp(&listed["frames"][0]), want);
    // Two posts of a sample in each of 16 pixels of 64.
    assert_eq!(want, (0.into(), 0.5.into(), 2.into()));
}

/// The frame list (the live page asks for it every second) gives each frame's newest samples
/// per pixel without counting its cells again while workers change it; a frame with none yet
/// is counted.
#[tokio::test]
async fn listing_frames_never_counts_a_changed_frame_again() {
    let app = testing::with_frame(AppState::new(Limits::default(), None, None), "l", 8, 8);
    let listed = |list: &serde_json::Value, id: &str| {
        let frames = list["frames"].as_array().expect("frames");
        let f = frames.iter().find(|f| f["id"] == id).expect("listed");
        (f["samples"].clone(), f["spp_mean"].clone())
    };
    // Never counted nor rendered: counted for the list.
    post(&app, "l", 0);
    assert_eq!(listed(&list(&app).await, "l"), (16.into(), 0.25.into()));
    // Changed: the list keeps the count it has, beside the frame's samples now.
    post(&app, "l", 1);
    assert_eq!(listed(&list(&app).await, "l"), (32.into(), 0.25.into()));
    // A render of its figures (`GET /v1/frames/l`) read the frame as it is: the list takes its.
    assert_eq!(info(&app, "l").await["spp_mean"], 0.5);
    assert_eq!(listed(&list(&app).await, "l"), (32.into(), 0.5.into()));
    // A count newer than the render (`convergence=none` counts the cells) is the newest.
    post(&app, "l", 2);
    let request = Request::get("/v1/frames/l?convergence=none")
        .body(Body::empty())
        .unwrap();
    assert_eq!(testing::send(&app, request).await.json()["spp_mean"], 0.75);
    assert_eq!(listed(&list(&app).await, "l"), (48.into(), 0.75.into()));
}

/// A writer that posts to each of `ids` now and every 10 ms (on tokio's clock), until aborted.
fn keep_writing(app: &AppState, ids: &[&str]) -> tokio::task::JoinHandle<()> {
    let (app, ids) = (
        app.clone(),
        ids.iter().map(|s| s.to_string()).collect::<Vec<_>>(),
    );
    for id in &ids {
        post(&app, id, 1);
    }
    tokio::spawn(async move {
        for seq in 2..1_000_000 {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
            for id in &ids {
                post(&app, id, seq);
            }
        }
    })
}

/// A server with a metrics recorder and 8x8 frames `ids`, one batch in each.
fn scraped_frames(ids: &[&str]) -> AppState {
    let handle = metrics_exporter_prometheus::PrometheusBuilder::new()
        .build_recorder()
        .handle();
    let mut app = AppState::new(Limits::default(), Some(handle), None);
    for id in ids {
        app = testing::with_frame(app, id, 8, 8);
        post(&app, id, 0);
    }
    app
}

/// The text of a `/metrics` scrape, asserted to be 200, with Prometheus' timeout header if
/// `timeout` is given.
async fn scrape(app: &AppState, timeout: Option<&str>) -> String {
    let mut request = Request::get("/metrics");
    if let Some(seconds) = timeout {
        request = request.header(super::operations::SCRAPE_TIMEOUT_HEADER, seconds);
    }
    let reply = testing::send(app, request.body(Body::empty()).unwrap()).await;
    assert_eq!(reply.status, StatusCode::OK);
    String::from_utf8(reply.body.to_vec()).unwrap()
}

/// As if every frame's last render had taken 100 s (a saturated head): at the default share of
/// 0.2, their next renders wait 400 s while writers keep changing them.
fn renders_took_100_s(app: &AppState) {
    let (paces, ended) = (app.renders.paces(), tokio::time::Instant::now());
    let took = std::time::Duration::from_secs(100);
    for frame in app.store.list() {
        paces.rendered(&frame, frame.version(), ended, took);
    }
}

/// A frame that workers keep changing renders at its pace, which on a busy head can outlast
/// Prometheus' scrape timeout: a scrape waits `SCRAPE_WAIT` at most, for all frames at once,
/// then reports the latest figures; the render it started goes on, and the next scrape waits
/// for that one instead of starting another. On tokio's paused clock, so the waits are exact.
#[tokio::test(start_paused = true)]
async fn a_scrape_of_frames_that_keep_changing_waits_its_bound_once() {
    use crate::render::figures::{latest_convergence, SCRAPE_WAIT};
    use std::time::Duration;
    let app = scraped_frames(&["a", "b"]);
    let text = scrape(&app, None).await;
    assert!(
        text.contains("splatd_frame_spp_max{frame=\"a\"} 1\n"),
        "{text}"
    );
    assert_eq!(app.renders.rendered(), 2, "one render per frame");

    renders_took_100_s(&app);
    let writer = keep_writing(&app, &["a", "b"]);
    let ms = Duration::from_millis(1);
    for _ in 0..2 {
        let started = tokio::time::Instant::now();
        let text = scrape(&app, None).await;
        let took = started.elapsed();
        assert!(
            took >= SCRAPE_WAIT && took <= SCRAPE_WAIT + ms,
            "two frames waited for together: {took:?}"
        );
        for id in ["a", "b"] {
            let line = format!("splatd_frame_spp_max{{frame=\"{id}\"}} 1\n");
            assert!(text.contains(&line), "the latest figures of {id}:\n{text}");
        }
        assert!(text.contains("splatd_frame_figures_age_seconds{frame=\"a\"} "));
    }
    assert_eq!(
        app.renders.rendered(),
        2,
        "both renders still wait their pace"
    );

    // The writer stops: after one quiet spell each frame renders once, for both scrapes and
    // for the wait below, which joins the render running.
    writer.abort();
    let frame = app.store.get("a").unwrap();
    let far = tokio::time::Instant::now() + Duration::from_secs(60);
    let (c, _) = latest_convergence(&app, &frame, far).await.unwrap();
    assert_eq!(
        c.samples,
        frame.samples(),
        "the figures of the frame as it is"
    );
    assert!(c.samples > 16);
    let b = app.store.get("b").unwrap();
    latest_convergence(&app, &b, far).await.unwrap();
    assert_eq!(app.renders.rendered(), 4, "one more render per frame");
}

/// A scrape waits half the timeout its scraper says it has (Prometheus sends it with every
/// scrape), at most `SCRAPE_WAIT`; a header that is not a positive number of seconds is ignored.
/// Two frames that keep changing, whose renders wait 400 s for their pace, on tokio's paused
/// clock, so the waits are exact.
#[tokio::test(start_paused = true)]
async fn a_scrape_waits_half_the_timeout_its_scraper_gives_it() {
    use crate::render::figures::SCRAPE_WAIT;
    use std::time::Duration;
    let app = scraped_frames(&["a", "b"]);
    scrape(&app, None).await;
    renders_took_100_s(&app);
    let writer = keep_writing(&app, &["a", "b"]);
    let ms = Duration::from_millis(1);
    for (header, waits) in [
        (Some("5"), Duration::from_millis(2500)),
        (Some("0.5"), Duration::from_millis(250)),
        (Some(" 2.000 "), Duration::from_secs(1)),
        (Some("60"), SCRAPE_WAIT),
        (None, SCRAPE_WAIT),
        (Some("soon"), SCRAPE_WAIT),
        (Some("-3"), SCRAPE_WAIT),
        (Some("0"), SCRAPE_WAIT),
        (Some("NaN"), SCRAPE_WAIT),
        (Some("1e300"), SCRAPE_WAIT),
    ] {
        let started = tokio::time::Instant::now();
        let text = scrape(&app, header).await;
        let took = started.elapsed();
        assert!(
            text.contains("splatd_frame_spp_max{frame=\"b\"} "),
            "{text}"
        );
        assert!(
            took >= waits && took <= waits + ms,
            "{header:?}: waited {took:?}, not {waits:?}"
        );
    }
    writer.abort();
}

/// The JSON answer to `GET path`, asserted to be 200 and to come at once (no time passes on
/// tokio's paused clock: it waited for no render).
async fn at_once(app: &AppState, path: &str) -> serde_json::Value {
    let started = tokio::time::Instant::now();
    let request = Request::get(path).body(Body::empty()).unwrap();
    let reply = testing::send(app, request).await;
    assert_eq!(
        started.elapsed(),
        std::time::Duration::ZERO,
        "{path} waited for a render"
    );
    assert_eq!(reply.status, StatusCode::OK, "{path}");
    reply.json()
}

/// `GET /v1/frames/{id}?convergence=none` answers the counts of a frame that workers keep changing
/// at once, while its renders wait their pace (a worker reporting the frame's spp after each
/// pass must not wait on it), renders nothing, and counts every sample acknowledged before it.
/// A value other than fresh, latest or none is refused, naming it. On tokio's paused clock.
#[tokio::test(start_paused = true)]
async fn counts_alone_never_wait_for_a_busy_frames_render() {
    use std::time::Duration;
    let app = testing::with_frame(AppState::new(Limits::default(), None, None), "c", 8, 8);
    post(&app, "c", 0);
    info(&app, "c").await;
    assert_eq!(app.renders.rendered(), 1);
    let frame = app.store.get("c").unwrap();
    renders_took_100_s(&app);
    let writer = keep_writing(&app, &["c"]);
    for _ in 0..3 {
        tokio::time::sleep(Duration::from_millis(25)).await;
        // The writer's timer may fall due at this instant too, and it may post while the
        // answer is being made: the answer counts every sample acknowledged before the request
        // and none that was not acknowledged by its end.
        let before = frame.samples();
        let shown = at_once(&app, "/v1/frames/c?convergence=none").await;
        let after = frame.samples();
        assert!(before > 16, "the writer wrote before the request");
        assert!(shown.get("convergence").is_none(), "{shown}");
        let within = |key: &str, per: u64| {
            let value = shown[key].as_f64().unwrap();
            assert!(
                (before as f64 / per as f64..=after as f64 / per as f64).contains(&value),
                "{key} {value} outside {before} .. {after} samples / {per}: {shown}"
            );
        };
        // The writer posts 16 samples at a time, one in each of the first 16 pixels of 64.
        within("samples", 1);
        within("spp_max", 16);
        within("spp_mean", 64);
        assert_eq!(shown["spp_min"], 0);
    }
    writer.abort();
    assert_eq!(app.renders.rendered(), 1, "the counts rendered nothing");

    let request = Request::get("/v1/frames/c?convergence=soon")
        .body(Body::empty())
        .unwrap();
    let reply = testing::send(&app, request).await;
    assert_eq!(reply.status, StatusCode::BAD_REQUEST);
    let error: serde_json::Value = reply.json();
    assert_eq!(error["error"], "bad_query", "{error}");
    assert!(
        error["message"]
            .as_str()
            .unwrap()
            .contains("unknown variant `soon`"),
        "{error}"
    );
}

/// `GET /v1/frames/{id}?convergence=latest` answers at once with the latest figures while a
/// busy frame's renders wait their pace (a page polling every second must not wait on it): the
/// figures and their spp say what they saw, the counts are the frame's now, and
/// the render it started gives the next request the frame's figures once the writers stop. On
/// tokio's paused clock.
#[tokio::test(start_paused = true)]
async fn the_latest_figures_never_wait_for_a_busy_frames_render() {
    use crate::render::figures::latest_convergence;
    use std::time::Duration;
    let app = testing::with_frame(AppState::new(Limits::default(), None, None), "l", 8, 8);
    post(&app, "l", 0);
    let latest =
        |app: AppState| async move { at_once(&app, "/v1/frames/l?convergence=latest").await };
    // No figures yet: none, and a render of them is started.
    let first = latest(app.clone()).await;
    assert!(first.get("convergence").is_none(), "{first}");
    assert_eq!(first["samples"], 16);
    let frame = app.store.get("l").unwrap();
    let far = tokio::time::Instant::now() + Duration::from_secs(60);
    latest_convergence(&app, &frame, far).await.unwrap();
    assert_eq!(
        app.renders.rendered(),
        1,
        "the render the first request started"
    );
    assert_eq!(latest(app.clone()).await["convergence"]["samples"], 16);

    // The frame turns busy, and its next render waits a 400 s pace.
    renders_took_100_s(&app);
    let writer = keep_writing(&app, &["l"]);
    for _ in 0..3 {
        tokio::time::sleep(Duration::from_millis(25)).await;
        let shown = latest(app.clone()).await;
        let c = &shown["convergence"];
        assert_eq!(
            (&c["samples"], &c["spp_max"]),
            (&16.into(), &1.into()),
            "{c}"
        );
        assert_eq!(
            shown["spp_max"], 1,
            "the spp of the render the figures come from"
        );
        assert!(
            shown["samples"].as_u64().unwrap() > 16,
            "the counts are the frame's now"
        );
        assert_eq!(c["converged"], false);
    }
    assert_eq!(
        app.renders.rendered(),
        1,
        "the figures' render waits its pace"
    );

    // The writers stop: after one quiet spell the render started runs, and the latest figures
    // are the frame's.
    writer.abort();
    latest_convergence(&app, &frame, far).await.unwrap();
    assert_eq!(app.renders.rendered(), 2);
    let shown = latest(app.clone()).await;
    assert_eq!(shown["convergence"]["samples"], frame.samples());
    assert_eq!(shown["samples"], frame.samples());
}
