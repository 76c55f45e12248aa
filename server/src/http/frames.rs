//! Frames as resources: create, list, inspect, delete.

use axum::extract::{Path, State};
use axum::http::StatusCode;
use splatd_proto::api::{
    CreateFrame, FrameInfo, FrameList, InfoConvergence, InfoQuery, PutFrame, QuarantinedFrame,
};

use crate::http::blocking::blocking;
use crate::http::error::ApiError;
use crate::http::extract::{Frame, Json, Query};
use crate::render::figures::FiguresError;
use crate::store::Created;
use crate::AppState;

/// `POST /v1/frames`: creates a frame (201), or finds the one a retried create made (200).
pub async fn create(
    State(app): State<AppState>,
    Json(request): Json<CreateFrame>,
) -> Result<(StatusCode, Json<FrameInfo>), ApiError> {
    create_or_get(&app, request).await
}

/// `PUT /v1/frames/{id}`: creates the frame (201), or answers the one there (200) when it has
/// exactly these parameters; 409 `frame_exists` naming the parameters that differ otherwise.
/// The same as `POST /v1/frames` with the id in the path, and allowed to `write` tokens, so a
/// render worker needs no token that can delete frames.
pub async fn put(
    State(app): State<AppState>,
    Path(id): Path<String>,
    Json(body): Json<PutFrame>,
) -> Result<(StatusCode, Json<FrameInfo>), ApiError> {
    if let Some(named) = body.id.as_deref().filter(|named| *named != id) {
        return Err(ApiError::bad_request(
            "frame_mismatch",
            format!("the body names frame {named:?} but the path frame {id:?}"),
        ));
    }
    create_or_get(&app, body.into_create(id)).await
}

/// Creates the frame `request` describes (201), or answers the existing one with the same
/// parameters (200).
async fn create_or_get(
    app: &AppState,
    request: CreateFrame,
) -> Result<(StatusCode, Json<FrameInfo>), ApiError> {
    let spec = app.store.check(request)?;
    let shared = app.clone();
    let created = blocking("create frame", move || Ok(shared.store.create(spec)?)).await?;
    let (status, frame) = match created {
        Created::New(frame) => {
            if let Err(e) = app.on_created(&frame).await {
                // Not durable: take it back, so the client's retry creates it properly.
                app.store.remove_frame(&frame);
                return Err(e.into());
            }
            tracing::info!(frame = frame.id(), "frame created");
            (StatusCode::CREATED, frame)
        }
        Created::Existing(frame) => (StatusCode::OK, frame),
    };
    set_frames_gauge(app);
    Ok((status, Json(frame.info())))
}

/// `GET /v1/frames`: every frame, ordered by id.
pub async fn list(State(app): State<AppState>) -> Result<Json<FrameList>, ApiError> {
    let frames = app.store.list();
    let frames = blocking("frame list", move || {
        Ok(frames.iter().map(|f| f.listed()).collect())
    })
    .await?;
    let quarantined = app
        .durable
        .as_ref()
        .map(|d| d.quarantined())
        .unwrap_or_default()
        .into_iter()
        .map(|q| QuarantinedFrame {
            id: q.frame,
            reason: q.reason,
            moved_to: q.moved_to.display().to_string(),
        })
        .collect();
    Ok(Json(FrameList {
        frames,
        quarantined,
    }))
}

/// `GET /v1/frames/{id}`, with the frame's convergence figures as the query asks
/// ([`InfoConvergence`]): from a render of the frame as it is (`fresh`, rendered now if the
/// frame changed since; without them when the working memory stayed busy), the latest at once
/// (`latest`), or none (`none`: the counts alone, which never wait for a render).
pub async fn info(
    State(app): State<AppState>,
    Query(query): Query<InfoQuery>,
    Frame(frame): Frame,
) -> Result<Json<FrameInfo>, ApiError> {
    let convergence = match query.convergence {
        InfoConvergence::None => None,
        InfoConvergence::Latest => {
            let now = tokio::time::Instant::now();
            crate::render::figures::latest_convergence(&app, &frame, now)
                .await
                .map(|(c, _age)| c)
        }
        InfoConvergence::Fresh => match crate::render::figures::convergence(&app, &frame).await {
            Ok(c) => Some(c),
            Err(FiguresError::Busy(busy)) => {
                tracing::warn!(frame = frame.id(), "frame info without convergence: {busy}");
                None
            }
            Err(e) => return Err(e.into()),
        },
    };
    let mut info = match &convergence {
        Some(c) => frame.info_rendered(c),
        None => blocking("frame info", move || Ok(frame.info())).await?,
    };
    info.convergence = convergence;
    Ok(Json(info))
}

/// `DELETE /v1/frames/{id}`: answered once the frame is gone, from disk too (see
/// [`AppState::delete_frame`] for the order that keeps every acknowledgement honest).
pub async fn delete(
    State(app): State<AppState>,
    Frame(frame): Frame,
) -> Result<StatusCode, ApiError> {
    app.delete_frame(&frame).await?;
    set_frames_gauge(&app);
    tracing::info!(frame = frame.id(), "frame deleted");
    Ok(StatusCode::NO_CONTENT)
}

fn set_frames_gauge(app: &AppState) {
    metrics::gauge!(crate::meters::FRAMES).set(app.store.list().len() as f64);
}
