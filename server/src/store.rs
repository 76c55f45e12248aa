//! The frames a server holds, and the limits on how many and how large.

use std::collections::BTreeMap;
use std::sync::{Arc, RwLock};

use axum::http::StatusCode;
use splatd_proto::api::CreateFrame;

use super::frame::{FrameSpec, ShardedFrame};
use super::Limits;
use crate::http::error::ApiError;

/// What `POST /v1/frames` did.
#[derive(Debug, Clone)]
pub enum Created {
    /// A new, empty frame.
    New(Arc<ShardedFrame>),
    /// A frame with this id and exactly these parameters existed (a retried create).
    Existing(Arc<ShardedFrame>),
}

/// All frames of a server, by id.
#[derive(Debug)]
pub struct FrameStore {
    frames: RwLock<BTreeMap<String, Arc<ShardedFrame>>>,
    limits: Limits,
}

impl FrameStore {
    /// An empty store enforcing `limits`.
    pub fn new(limits: Limits) -> FrameStore {
        FrameStore {
            frames: RwLock::new(BTreeMap::new()),
            limits,
        }
    }

    /// The limits in force.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Checks a create request against the parameters' own rules and this server's limits.
    pub fn check(&self, request: CreateFrame) -> Result<FrameSpec, ApiError> {
        let spec = FrameSpec::new(request)
            .map_err(|e| ApiError::bad_request("invalid_parameters", e.to_string()))?;
        let r = &spec.request;
        let pixels = r.width as u64 * r.height as u64;
        let too_large =
            |what: String| ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, "frame_too_large", what);
        if pixels > self.limits.max_pixels {
            return Err(too_large(format!(
                "a {}x{} frame has {pixels} pixels; this server allows at most {}",
                r.width, r.height, self.limits.max_pixels
            )));
        }
        if r.cascades.cascades > self.limits.max_cascades {
            return Err(too_large(format!(
                "{} cascades requested; this server allows at most {}",
                r.cascades.cascades, self.limits.max_cascades
            )));
        }
        Ok(spec)
    }

    /// Creates a frame, or returns the existing one if it has exactly the same parameters.
    pub fn create(&self, spec: FrameSpec) -> Result<Created, ApiError> {
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        if let Some(existing) = frames.get(&spec.request.id) {
            if existing.spec().request == spec.request {
                return Ok(Created::Existing(existing.clone()));
            }
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "frame_exists",
                format!(
                    "frame {:?} exists with different parameters ({})",
                    spec.request.id,
                    describe_difference(&existing.spec().request, &spec.request)
                ),
            ));
        }
        self.admit(&frames, &spec)?;
        let frame = Arc::new(ShardedFrame::new(spec));
        frames.insert(frame.id().to_owned(), frame.clone());
        Ok(Created::New(frame))
    }

    /// Removes `frame` (this very frame, not another of the same id).
    pub fn remove_frame(&self, frame: &Arc<ShardedFrame>) {
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        if frames
            .get(frame.id())
            .is_some_and(|f| Arc::ptr_eq(f, frame))
        {
            frames.remove(frame.id());
        }
    }

    /// Puts back a frame whose deletion failed; false if its id was taken meanwhile.
    pub fn reinsert(&self, frame: Arc<ShardedFrame>) -> bool {
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        if frames.contains_key(frame.id()) {
            return false;
        }
        frames.insert(frame.id().to_owned(), frame);
        true
    }

    /// Puts a frame restored from disk back (no limits: it was admitted before).
    pub fn insert_restored(&self, frame: ShardedFrame) {
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        frames.insert(frame.id().to_owned(), Arc::new(frame));
    }

    fn admit(
        &self,
        frames: &BTreeMap<String, Arc<ShardedFrame>>,
        spec: &FrameSpec,
    ) -> Result<(), ApiError> {
        if frames.len() >= self.limits.max_frames {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "too_many_frames",
                format!(
                    "this server holds {} frames, its limit; delete one first",
                    frames.len()
                ),
            ));
        }
        let used: u64 = frames.values().map(|f| f.spec().memory_bytes()).sum();
        let wanted = spec.memory_bytes();
        if used + wanted > self.limits.max_memory_bytes {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                "memory_limit",
                format!(
                    "frame {:?} needs {} MiB of cascades; {} MiB of this server's {} MiB are in use",
                    spec.request.id,
                    wanted.div_ceil(1 << 20),
                    used.div_ceil(1 << 20),
                    self.limits.max_memory_bytes >> 20
                ),
            ));
        }
        Ok(())
    }

    /// The frame `id`.
    pub fn get(&self, id: &str) -> Result<Arc<ShardedFrame>, ApiError> {
        let frames = self.frames.read().unwrap_or_else(|e| e.into_inner());
        frames
            .get(id)
            .cloned()
            .ok_or_else(|| ApiError::unknown_frame(id))
    }

    /// Every frame, ordered by id.
    pub fn list(&self) -> Vec<Arc<ShardedFrame>> {
        let frames = self.frames.read().unwrap_or_else(|e| e.into_inner());
        frames.values().cloned().collect()
    }

    /// Removes frame `id`.
    pub fn remove(&self, id: &str) -> Result<Arc<ShardedFrame>, ApiError> {
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        frames.remove(id).ok_or_else(|| ApiError::unknown_frame(id))
    }
}

/// Names the first parameters that differ between two create requests.
fn describe_difference(ours: &CreateFrame, theirs: &CreateFrame) -> String {
    let mut diffs = Vec::new();
    if (ours.width, ours.height) != (theirs.width, theirs.height) {
        diffs.push(format!(
            "size {}x{} here, {}x{} requested",
            ours.width, ours.height, theirs.width, theirs.height
        ));
    }
    if ours.cascades != theirs.cascades {
        diffs.push(format!(
            "cascades {:?} here, {:?} requested",
            ours.cascades, theirs.cascades
        ));
    }
    if ours.resolve != theirs.resolve {
        diffs.push(format!(
            "resolve {:?} here, {:?} requested",
            ours.resolve, theirs.resolve
        ));
    }
    diffs.join("; ")
}
