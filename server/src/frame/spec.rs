//! A frame's parameters: the create request checked and turned into the core's types.

use splatd_proto::api::{AovSpec, CreateFrame};

use splatd_estimator::{
    self as estimator, aov_words, cell_len, AovSums, CascadeLayout, ParamError,
};

use splatd_formats::names::{check_exr_name, MAX_EXR_NAME_BYTES};

/// A frame's parameters, checked and turned into the core's types.
#[derive(Debug, Clone)]
pub struct FrameSpec {
    /// The request as the frame was created (after defaults were filled in).
    pub request: CreateFrame,
    /// The cascade layout.
    pub layout: CascadeLayout,
    /// The default resolve parameters.
    pub resolve: estimator::ResolveParams,
    /// The AOVs that guide its denoised images (see [`crate::render::denoise::Guides::choose`]).
    pub guides: crate::render::denoise::Guides,
}

impl FrameSpec {
    /// Checks a create request. Size limits are the store's business, not this one's.
    pub fn new(request: CreateFrame) -> Result<FrameSpec, ParamError> {
        splatd_proto::validate_frame_id(&request.id)
            .map_err(|e| ParamError::new("id", e.to_string()))?;
        if request.width == 0 || request.height == 0 {
            return Err(ParamError::new(
                "width/height",
                format!(
                    "a frame needs at least one pixel, got {}x{}",
                    request.width, request.height
                ),
            ));
        }
        let c = &request.cascades;
        let layout = CascadeLayout::new(c.base, c.cascades, c.lowest_scale, c.luminance)?;
        let resolve = core_resolve_params(&request.resolve)?;
        estimator::check_converged_below(request.converged_below)?;
        check_aovs(&request.aovs)?;
        let guides =
            crate::render::denoise::Guides::choose(&request.aovs, request.denoise_guides.as_ref())?;
        Ok(FrameSpec {
            request,
            layout,
            resolve,
            guides,
        })
    }

    /// Bytes of cascade and AOV memory a frame of this spec holds.
    pub fn memory_bytes(&self) -> u64 {
        let aovs = match self.aov_channels() {
            0 => 0,
            c => aov_words(c),
        };
        self.request.width as u64
            * self.request.height as u64
            * (cell_len(self.layout.cascades()) + aovs) as u64
            * 8
    }

    /// Channels of all the frame's AOVs together (0: the frame has no AOVs).
    pub fn aov_channels(&self) -> usize {
        self.request.aovs.iter().map(|a| a.channels.len()).sum()
    }

    /// Empty AOV sums for the whole frame, if it has AOVs.
    pub fn empty_aovs(&self) -> Option<AovSums> {
        self.empty_aovs_in(|_| Vec::new())
    }

    /// [`FrameSpec::empty_aovs`] in the memory `words(len)` gives for their `len` words
    /// ([`AovSums::new_in`]).
    pub fn empty_aovs_in(&self, words: impl FnOnce(usize) -> Vec<u64>) -> Option<AovSums> {
        let c = self.aov_channels();
        let (w, h) = (self.request.width, self.request.height);
        (c > 0).then(|| AovSums::new_in(w, 0..h, c, words))
    }
}

/// Most AOV channels a frame may declare (each costs 16 bytes per pixel).
pub const MAX_AOV_CHANNELS: usize = 64;

/// Layer names of `image.exr` that an AOV may not take.
const RESERVED_LAYERS: [&str; 4] = [
    "mean",
    "removed",
    "spp",
    crate::render::denoise::DENOISED_LAYER,
];

/// Checks a frame's AOV declarations: named, each name once and not one of the served layers'
/// (`mean`, `removed`, `spp`, `cascadeN`, the unnamed beauty), channels named, each once, and
/// every name one that can be written into a valid EXR ([`check_exr_name`]).
fn check_aovs(aovs: &[AovSpec]) -> Result<(), ParamError> {
    let bad = |m: String| Err(ParamError::new("aovs", m));
    let total: usize = aovs.iter().map(|a| a.channels.len()).sum();
    if total > MAX_AOV_CHANNELS {
        return bad(format!(
            "{total} AOV channels declared, at most {MAX_AOV_CHANNELS} are allowed"
        ));
    }
    for (i, aov) in aovs.iter().enumerate() {
        let name = shown(&aov.name);
        // Before anything else quotes it (`{:?}` escapes a NUL or a control character).
        check_exr_name(&aov.name)
            .map_err(|rule| ParamError::new("aovs", format!("AOV name {name}: {rule}")))?;
        let cascade = aov
            .name
            .strip_prefix("cascade")
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        if aov.name.is_empty() || RESERVED_LAYERS.contains(&aov.name.as_str()) || cascade {
            return bad(format!(
                "AOV name {name} is empty or taken by a layer image.exr serves (mean, removed, \
                 spp, denoised, cascadeN)"
            ));
        }
        if aovs[..i].iter().any(|a| a.name == aov.name) {
            return bad(format!("AOV {name} is declared twice"));
        }
        if aov.channels.is_empty() {
            return bad(format!("AOV {name} has no channels"));
        }
        for (j, c) in aov.channels.iter().enumerate() {
            check_exr_name(c).map_err(|rule| {
                ParamError::new(
                    "aovs",
                    format!("AOV {name}: channel name {}: {rule}", shown(c)),
                )
            })?;
            if c.is_empty() || c.contains('.') || aov.channels[..j].contains(c) {
                return bad(format!(
                    "AOV {name}: channel {c:?} is empty, has a dot or is named twice"
                ));
            }
            // What image.exr writes: `<name>.<channel>`, with no other prefix.
            let full = aov.name.len() + 1 + c.len();
            if full > MAX_EXR_NAME_BYTES {
                return bad(format!(
                    "AOV {name}: channel {}: length rule: the EXR channel name \
                     \"<name>.<channel>\" would be {full} bytes, and OpenEXR names are at \
                     most {MAX_EXR_NAME_BYTES} bytes",
                    shown(c)
                ));
            }
        }
    }
    Ok(())
}

/// A name quoted for a message, cut short when long (a refused name may be 30,000 bytes).
fn shown(name: &str) -> String {
    const SHOWN: usize = 40;
    if name.chars().count() <= SHOWN {
        return format!("{name:?}");
    }
    let head: String = name.chars().take(SHOWN).collect();
    format!("{head:?}... ({} bytes)", name.len())
}

/// The core's resolve parameters from the API's.
pub fn core_resolve_params(
    p: &splatd_proto::api::ResolveParams,
) -> Result<estimator::ResolveParams, ParamError> {
    estimator::ResolveParams::new(
        p.variant.to_estimator(),
        p.kappa,
        p.kappa_min,
        p.kappa_exponent,
    )
}
