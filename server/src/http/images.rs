//! Images out: the resolved OpenEXR (`image.exr`) and the live page's PNG preview.

use std::sync::Arc;
use std::time::Instant;

use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;
use bytes::Bytes;
use serde::{Deserialize, Deserializer};
use splatd_estimator::denoise::DenoisePlan;
use splatd_estimator::ResolveParams;
use splatd_proto::api::{Denoise, DenoiseQuality, ImageQuery};

use crate::frame::{core_resolve_params, FrameCut, ShardedFrame};
use crate::http::error::ApiError;
use crate::http::extract::{Frame, Query};
use crate::render::denoise;
use crate::work::{Reservation, WorkBudget};
use crate::AppState;
use splatd_formats::exr::{cascade_layers, encode_exr_in, ExtraLayer, Provenance};

/// `GET /v1/frames/{id}/image.exr`: resolves the frame as it is now, and denoises it when the
/// query or the frame asks for it (`denoise=oidn`: the layer `denoised`).
pub async fn get_image(
    State(app): State<AppState>,
    Query(mut query): Query<ImageQuery>,
    Frame(frame): Frame,
) -> Result<impl IntoResponse, ApiError> {
    let params = core_resolve_params(&query.apply(&frame.spec().request.resolve))?;
    let threads = app.resolve_threads;
    let started = Instant::now();
    // The query in its canonical form (the render's key): what is run, not how it was said.
    let denoise = query.denoise.unwrap_or(frame.spec().request.denoise);
    query.denoise = Some(denoise);
    query.denoise_quality = match denoise {
        Denoise::Oidn => Some(query.denoise_quality.unwrap_or_default()),
        Denoise::None => None,
    };
    // Refused before any memory is reserved or anything resolved.
    let oidn = match denoise {
        Denoise::Oidn => Some(app.denoiser.oidn()?.clone()),
        Denoise::None => None,
    };
    let extra_layers = if query.cascades {
        frame.spec().layout.cascades() as u64
    } else {
        0
    };
    let px = pixels(&frame);
    // The copy of the state, three resolved layers and the EXR holding them (and the raw
    // cascades when asked for), at 12 bytes per pixel and layer.
    // AOV means: two copies (planes and channels) of 4 bytes per channel and pixel.
    let aov_bytes = px * 8 * frame.spec().aov_channels() as u64;
    // A denoise (`denoise_bytes`), the copy of the resolve the EXR is encoded from once the
    // kept one is let go (three RGB layers and the counts, 44 bytes a pixel) and the `denoised`
    // layer in the EXR. The state copy's share is given back before OIDN runs.
    let denoise_bytes = match oidn {
        Some(_) => denoise_bytes(app.denoiser.memory(), px) + px * 44 + px * 12 * 2,
        None => 0,
    };
    let cost =
        frame.spec().memory_bytes() + px * 12 * (6 + 2 * extra_layers) + aov_bytes + denoise_bytes;
    let key = format!("exr {params:?} {query:?}");
    let budget = app.renders.budget().clone();
    let kept = app.renders.kept().clone();
    let scratches = app.clone();
    let exr = app
        .renders
        .get_or_render(&frame, key, cost, move |frame, wanted, reservation| {
            let provenance = Provenance {
                layout: &frame.spec().layout,
                params: &params,
            };
            let encode = |resolved: &splatd_estimator::Resolved,
                          extra: &[ExtraLayer],
                          aovs: &[(String, Vec<f32>)],
                          more_attributes| {
                // In buffers kept from the last image, given back whatever the outcome.
                let mut scratch = scratches.exr_scratch.take();
                let encoded = encode_exr_in(
                    resolved,
                    extra,
                    aovs,
                    &provenance,
                    more_attributes,
                    &mut scratch,
                );
                scratches.exr_scratch.give(scratch);
                encoded
                    .map(Bytes::from)
                    .map_err(|e| ApiError::internal("EXR encoding", e))
            };
            // Without cascades, AOVs or a denoise the image needs the resolved layers only: a
            // render of another kind that started with this one may just have made them.
            if !query.cascades && oidn.is_none() && frame.spec().request.aovs.is_empty() {
                return kept.with_resolved_since(frame, &params, threads, wanted, |resolved, _| {
                    encode(resolved, &[], &[], Vec::new())
                });
            }
            let denoising = oidn.as_deref().map(|oidn| Denoising {
                oidn,
                memory: scratches.denoiser.memory(),
                budget: &budget,
                quality: query.denoise_quality.unwrap_or_default(),
            });
            let image = kept.with_resolved(frame, &params, threads, |resolved, cut, _| {
                let extra = if query.cascades {
                    cascade_layers(cut.cascade_means())
                } else {
                    Vec::new()
                };
                let aovs = cut
                    .aovs
                    .as_ref()
                    .map(|sums| splatd_formats::exr::aov_planes(&frame.spec().request.aovs, sums))
                    .unwrap_or_default();
                let Some(denoising) = denoising else {
                    // The encoding needs nothing of the state.
                    give_back_cut(frame, cut, reservation);
                    return encode(resolved, &extra, &aovs, Vec::new()).map(Image::Encoded);
                };
                let plan = denoising.plan(frame, cut, reservation, &params, threads);
                Ok(Image::ToDenoise(Box::new(ToDenoise {
                    denoising,
                    resolved: resolved.clone(),
                    extra,
                    aovs,
                    plan,
                })))
            })?;
            // OIDN runs with the kept resolve free for other renders of the frame.
            let ToDenoise {
                denoising,
                resolved,
                mut extra,
                aovs,
                plan,
            } = match image {
                Image::Encoded(bytes) => return Ok(bytes),
                Image::ToDenoise(to_denoise) => *to_denoise,
            };
            let planes: Vec<&[f32]> = aovs.iter().map(|(_, p)| p.as_slice()).collect();
            let run = denoising.run(frame, plan, &planes)?;
            let attributes = run.attributes();
            extra.push(ExtraLayer {
                name: denoise::DENOISED_LAYER.to_owned(),
                rgb: run.rgb,
            });
            encode(&resolved, &extra, &aovs, attributes)
        })
        .await?;
    metrics::histogram!(crate::meters::RESOLVE_SECONDS).record(started.elapsed().as_secs_f64());
    Ok(([(header::CONTENT_TYPE, "image/x-exr")], exr))
}

/// Pixels of a frame.
fn pixels(frame: &ShardedFrame) -> u64 {
    let r = &frame.spec().request;
    u64::from(r.width) * u64::from(r.height)
}

/// Which layer a preview shows.
#[derive(Debug, Clone, Copy, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PreviewLayer {
    /// The reweighted image.
    #[default]
    Reweighted,
    /// The plain mean.
    Mean,
    /// The energy removed as fireflies.
    Removed,
    /// The denoised final (as `image.exr?denoise=oidn` has it, quality `high`); 501
    /// `denoiser_unavailable` on a server without OIDN.
    Denoised,
}

/// Query of `GET /v1/frames/{id}/preview.png`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PreviewQuery {
    /// The layer (default reweighted).
    #[serde(default)]
    pub layer: PreviewLayer,
    /// Exposure multiplier; by default chosen from the reweighted image, so that every layer
    /// of a frame is shown with the same exposure and compares fairly. Must be positive.
    #[serde(default, deserialize_with = "positive_exposure")]
    pub exposure: Option<f32>,
    /// Stops added to the exposure (the given one or the automatic one): the live page's
    /// exposure slider. In `[-20, 20]`, default 0.
    #[serde(default, deserialize_with = "bounded_stops")]
    pub stops: f32,
    /// Ignored: lets pages defeat caches by naming the sample count they expect.
    pub samples: Option<u64>,
}

/// Refuses an exposure that would give a black or meaningless image, as part of parsing the
/// query, so that it is refused (400 `bad_query`) before the frame is even looked up.
fn positive_exposure<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f32>, D::Error> {
    let exposure = Option::<f32>::deserialize(d)?;
    match exposure {
        Some(e) if !(e.is_finite() && e > 0.0) => Err(serde::de::Error::custom(format!(
            "exposure must be a positive number, got {e}"
        ))),
        _ => Ok(exposure),
    }
}

/// Refuses exposure stops outside `[-20, 20]` (or not a number) while parsing the query.
fn bounded_stops<'de, D: Deserializer<'de>>(d: D) -> Result<f32, D::Error> {
    let stops = f32::deserialize(d)?;
    if (-20.0..=20.0).contains(&stops) {
        Ok(stops)
    } else {
        Err(serde::de::Error::custom(format!(
            "stops must be a number in [-20, 20], got {stops}"
        )))
    }
}

/// `GET /v1/frames/{id}/preview.png`: a tone-mapped 8-bit view of a layer, for the live page.
pub async fn get_preview(
    State(app): State<AppState>,
    Query(query): Query<PreviewQuery>,
    Frame(frame): Frame,
) -> Result<impl IntoResponse, ApiError> {
    let params = frame.spec().resolve;
    let threads = app.resolve_threads;
    let shown = match query.layer {
        PreviewLayer::Reweighted => Shown::Layer(|r| &r.reweighted),
        PreviewLayer::Mean => Shown::Layer(|r| &r.mean),
        PreviewLayer::Removed => Shown::Layer(|r| &r.removed),
        PreviewLayer::Denoised => Shown::Denoised(app.denoiser.oidn()?.clone()),
    };
    let px = pixels(&frame);
    // The copy of the state, three resolved layers, the tone-mapped bytes and the PNG; for the
    // denoised layer, a denoise (`denoise_bytes`) and the AOV means.
    let denoise_bytes = match shown {
        Shown::Denoised(_) => {
            denoise_bytes(app.denoiser.memory(), px) + px * 4 * frame.spec().aov_channels() as u64
        }
        Shown::Layer(_) => 0,
    };
    let cost = frame.spec().memory_bytes() + px * (36 + 6) + denoise_bytes;
    let key = format!("png {:?} {:?} {}", query.layer, query.exposure, query.stops);
    let budget = app.renders.budget().clone();
    let kept = app.renders.kept().clone();
    let memory = app.denoiser.memory();
    let png = app
        .renders
        .get_or_render(&frame, key, cost, move |frame, wanted, reservation| {
            // Every layer is shown at the exposure of the reweighted one (unless the query sets
            // it), so that switching layers compares them.
            let exposure = |resolved: &splatd_estimator::Resolved| {
                query
                    .exposure
                    .unwrap_or_else(|| splatd_formats::preview::auto_exposure(&resolved.reweighted))
                    * query.stops.exp2()
            };
            let encode = |width: u32, height: u32, layer: &[[f32; 3]], exposure: f32| {
                let pixels = splatd_formats::preview::tonemap(layer, exposure);
                splatd_formats::preview::encode_png(width, height, &pixels)
                    .map(Bytes::from)
                    .map_err(|e| ApiError::internal("PNG encoding", e))
            };
            let oidn = match &shown {
                // A layer that needs nothing of the state is answered by a resolve of the
                // version read before this render began or a later one, kept by a render of
                // another kind.
                Shown::Layer(layer) => {
                    return kept.with_resolved_since(frame, &params, threads, wanted, |r, _| {
                        encode(r.width, r.height, layer(r), exposure(r))
                    });
                }
                Shown::Denoised(oidn) => oidn,
            };
            let denoising = Denoising {
                oidn,
                memory,
                budget: &budget,
                quality: DenoiseQuality::High,
            };
            // Of the kept resolve the denoised layer needs only its size and exposure (OIDN's
            // input is in the plan): nothing of it is copied.
            let (size, exposure, aovs, plan) =
                kept.with_resolved(frame, &params, threads, |resolved, cut, _| {
                    let aovs = cut
                        .aovs
                        .as_ref()
                        .map(|sums| sums.means())
                        .unwrap_or_default();
                    let plan = denoising.plan(frame, cut, reservation, &params, threads);
                    let size = (resolved.width, resolved.height);
                    (size, exposure(resolved), aovs, plan)
                });
            // OIDN runs with the kept resolve free for other renders of the frame.
            let planes: Vec<&[f32]> = aovs.iter().map(Vec::as_slice).collect();
            let denoised = denoising.run(frame, plan, &planes)?.rgb;
            encode(size.0, size.1, &denoised, exposure)
        })
        .await?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        png,
    ))
}

/// What a preview shows: a layer of the resolve, or the denoised final (made with this OIDN).
enum Shown {
    Layer(fn(&splatd_estimator::Resolved) -> &[[f32; 3]]),
    Denoised(Arc<splatd_denoise::Oidn>),
}

/// Bytes a render that denoises `px` pixels reserves for the denoise: OIDN's floor (more is
/// taken when OIDN runs, if free) and the plan's images.
fn denoise_bytes(memory: denoise::OidnMemory, px: u64) -> u64 {
    memory.reserved_bytes(px) + denoise::image_bytes(px)
}

/// Drops `cut`, a copy of `frame`'s state, and gives its share of the render's working memory
/// back.
fn give_back_cut(frame: &ShardedFrame, cut: FrameCut, reservation: &mut Reservation) {
    drop(cut);
    reservation.shrink_to(
        reservation
            .bytes()
            .saturating_sub(frame.spec().memory_bytes()),
    );
}

/// A denoise to run: OIDN, the memory it may use, and its quality.
struct Denoising<'a> {
    oidn: &'a splatd_denoise::Oidn,
    memory: denoise::OidnMemory,
    budget: &'a Arc<WorkBudget>,
    quality: DenoiseQuality,
}

impl Denoising<'_> {
    /// The denoiser input of `cut`, a copy of `frame` resolved at `params` on `threads`. The
    /// cut is dropped, and its share of the render's `reservation` given back, once it is made.
    fn plan(
        &self,
        frame: &ShardedFrame,
        cut: FrameCut,
        reservation: &mut Reservation,
        params: &ResolveParams,
        threads: usize,
    ) -> DenoisePlan {
        let bands = cut.band_refs();
        let plan = DenoisePlan::new(&bands, params, threads);
        drop(bands);
        give_back_cut(frame, cut, reservation);
        plan
    }

    /// The denoised final of `plan`, guided by the frame's guides among `aov_planes` (all its
    /// AOV channel means), OIDN getting what memory is free ([`denoise::OidnMemory::grant`]).
    fn run(
        &self,
        frame: &ShardedFrame,
        plan: DenoisePlan,
        aov_planes: &[&[f32]],
    ) -> Result<denoise::DenoiseRun, ApiError> {
        let px = plan.width() as u64 * plan.height() as u64;
        let grant = self.memory.grant(px, self.budget);
        Ok(denoise::run(
            self.oidn,
            frame.id(),
            plan,
            &frame.spec().guides,
            aov_planes,
            self.quality,
            &grant,
        )?)
    }
}

/// What a render of `image.exr` made with the frame's kept resolve: the file, or, for a denoise,
/// everything but OIDN's output, taken out so that OIDN runs with the kept resolve free.
enum Image<'a> {
    Encoded(Bytes),
    ToDenoise(Box<ToDenoise<'a>>),
}

/// A denoised `image.exr` before OIDN: a copy of the resolve, the other extra layers, the AOV
/// means and the denoiser input.
struct ToDenoise<'a> {
    denoising: Denoising<'a>,
    resolved: splatd_estimator::Resolved,
    extra: Vec<ExtraLayer>,
    aovs: Vec<(String, Vec<f32>)>,
    plan: DenoisePlan,
}
