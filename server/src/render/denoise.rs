//! Denoised finals: Intel Open Image Denoise over the frame's denoiser input.
//!
//! `image.exr?denoise=oidn` (or a frame created with `"denoise": "oidn"`) adds the layer
//! `denoised`. What OIDN is handed is the estimator's business
//! ([`splatd_estimator::denoise::DenoisePlan`]: the images to denoise and how their outputs
//! make the final); this module runs OIDN over each of them with the same guides and says in
//! the header how the layer was made ([`DenoiseRun::attributes`]).
//!
//! OIDN is loaded at start ([`Denoiser::load`]), at run time (`splatd-denoise`), from
//! `--oidn-lib` / `SPLATD_OIDN_LIB` or the dynamic loader's search path. A server without it runs
//! as ever; a denoise request is refused with [`DenoiseError::Unavailable`], saying why.
//!
//! **Guides.** OIDN's `RT` filter takes an albedo, or an albedo and a normal, beside the colour.
//! They come from the frame's AOVs (plain per-pixel means, see PROTOCOL.md, "AOVs"), chosen at
//! creation ([`Guides::choose`]): exactly the AOVs `denoise_guides` names, or else by name. The
//! AOV means are noisy at low sample counts, so OIDN is told they are not clean (`cleanAux`
//! off), as its documentation asks for noisy guides.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use splatd_denoise::{DenoiseInput, Oidn, Quality};
use splatd_estimator::denoise::{DenoisePlan, DEFAULT_DENOISE_DESIGN};
use splatd_estimator::ParamError;
use splatd_proto::api::{AovSpec, DenoiseGuides, DenoiseQuality};

use splatd_formats::exr::HeaderValue;

use crate::work::{Reservation, WorkBudget};

/// How an operator gives a server OIDN, for the messages of [`DenoiseError::Unavailable`].
pub const HOW: &str = "start the server with --oidn-lib PATH or SPLATD_OIDN_LIB naming \
    libOpenImageDenoise.so.2 of OIDN 2.x; `bash tests/setup/oidn.sh` installs one and prints \
    its path";

/// The layer of `image.exr` that holds the denoised final.
pub const DENOISED_LAYER: &str = "denoised";

/// Why a frame was not denoised.
#[derive(Debug, thiserror::Error)]
pub enum DenoiseError {
    /// The server has no usable OIDN (not found, not 2.x, or it failed to start a device).
    #[error("this server cannot denoise: {reason}")]
    Unavailable {
        /// Why the library could not be used, naming the path tried.
        reason: String,
    },
    /// OIDN failed on this frame.
    #[error("denoising frame {frame:?} failed: {source}")]
    Failed {
        /// The frame.
        frame: String,
        /// What OIDN said.
        source: splatd_denoise::DenoiseError,
    },
}

/// The server's denoiser: OIDN when it loaded, or why it did not, and the memory a denoise may
/// use inside it.
#[derive(Debug, Clone)]
pub struct Denoiser {
    oidn: Result<Arc<Oidn>, String>,
    memory: OidnMemory,
}

impl Denoiser {
    /// A denoiser that refuses every request, saying `reason`.
    pub fn unavailable(reason: impl Into<String>) -> Denoiser {
        Denoiser {
            oidn: Err(reason.into()),
            memory: OidnMemory::default(),
        }
    }

    /// Loads OIDN from `path`, or else from the dynamic loader's search path
    /// (`libOpenImageDenoise.so.2`), to denoise within `memory`. Never fails: a library that
    /// cannot be used makes a denoiser that refuses, saying why.
    ///
    /// The library is loaded on a thread at the renders' lower priority
    /// ([`crate::render::RENDER_NICE`]), so that the worker threads OIDN's thread pool starts,
    /// which inherit their creator's nice value, take only the cores ingest leaves idle.
    pub fn load(path: Option<&Path>, memory: OidnMemory) -> Denoiser {
        let path: PathBuf = path.map_or_else(
            || PathBuf::from(splatd_denoise::DEFAULT_LIB),
            Path::to_path_buf,
        );
        let loaded = std::thread::Builder::new()
            .name("splatd-oidn-load".into())
            .spawn(move || {
                crate::priority::lower_priority();
                Oidn::load_from(&path)
            })
            .expect("spawning a thread")
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        match loaded {
            Ok(oidn) => Denoiser {
                oidn: Ok(Arc::new(oidn)),
                memory,
            },
            Err(e @ splatd_denoise::DenoiseError::Load { .. }) => {
                Denoiser::unavailable(e.to_string())
            }
            Err(e) => Denoiser::unavailable(format!("{e} ({HOW})")),
        }
    }

    /// OIDN, or why there is none.
    pub fn oidn(&self) -> Result<&Arc<Oidn>, DenoiseError> {
        self.oidn
            .as_ref()
            .map_err(|reason| DenoiseError::Unavailable {
                reason: reason.clone(),
            })
    }

    /// The memory a denoise may use inside OIDN.
    pub fn memory(&self) -> OidnMemory {
        self.memory
    }
}

/// Bytes a pixel of a denoise may take inside OIDN untiled: OIDN 2.5.1 was measured at 582
/// (1920x1080, `high`: 1.21 GB) and 556 (640x480), rounded up to 640.
pub const OIDN_BYTES_PER_PIXEL: u64 = 640;

/// What a denoise may use inside OIDN (its filters' `maxMemoryMB`), from the working memory.
///
/// Every denoise reserves [`OidnMemory::reserved_bytes`] before it starts, with its images: at
/// most `least_mib`. When OIDN is about to run, [`OidnMemory::grant`] adds what the working
/// memory has free then, without waiting, up to what the image needs untiled (and at most
/// `most_mib`). Short of that, OIDN denoises in overlapping tiles: the same output, bit for
/// bit, but slower (a 1920x1080 `high` denoise took 5.2 s in 2x2 tiles, 3.9 s in 2x1 and 3.3 s
/// untiled on the 2-core machine it was measured on).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OidnMemory {
    /// MiB every denoise is sure of (`--oidn-min-memory-mib`).
    pub least_mib: u32,
    /// The most MiB one denoise may use (`--oidn-max-memory-mib`), or `None` for as much as
    /// the image needs untiled.
    pub most_mib: Option<u32>,
}

/// MiB every denoise reserves for OIDN unless set (`--oidn-min-memory-mib`).
pub const DEFAULT_LEAST_MIB: u32 = 512;

impl Default for OidnMemory {
    fn default() -> OidnMemory {
        OidnMemory {
            least_mib: DEFAULT_LEAST_MIB,
            most_mib: None,
        }
    }
}

/// What OIDN may use for one denoise: its filters' `maxMemoryMB`, and the working memory
/// reserved for it beyond [`OidnMemory::reserved_bytes`], given back when dropped.
#[derive(Debug)]
pub struct OidnGrant {
    /// OIDN's `maxMemoryMB`.
    pub max_memory_mib: u32,
    /// The denoise gets what the image needs untiled.
    pub untiled: bool,
    _more: Option<Reservation>,
}

impl OidnMemory {
    /// The floor in bytes: `least_mib`, or `most_mib` when that is lower.
    fn least_bytes(&self) -> u64 {
        u64::from(
            self.most_mib
                .map_or(self.least_mib, |m| m.min(self.least_mib)),
        ) << 20
    }

    /// Bytes a denoise of `pixels` pixels reserves for OIDN before it starts: what it needs
    /// untiled, or the floor when that is less.
    pub fn reserved_bytes(&self, pixels: u64) -> u64 {
        untiled_bytes(pixels).min(self.least_bytes())
    }

    /// OIDN's memory for a denoise of `pixels` pixels that holds [`Self::reserved_bytes`]:
    /// what it needs untiled (at most `most_mib`) when `budget` has the rest free now, else
    /// the most of half that, a quarter, and so on that is free, else the floor. Never waits:
    /// a denoise is not held back for speed, only made slower.
    pub fn grant(&self, pixels: u64, budget: &Arc<WorkBudget>) -> OidnGrant {
        let need = untiled_bytes(pixels);
        let least = self.least_bytes();
        let most = self.most_mib.map_or(u64::MAX, |m| u64::from(m) << 20);
        let mut want = need.min(most);
        while want > least {
            if let Some(more) = budget.try_reserve(want - least) {
                return OidnGrant {
                    max_memory_mib: mib_rounded_up(want),
                    untiled: want == need,
                    _more: Some(more),
                };
            }
            want /= 2;
        }
        // OIDN is told the floor even when the image needs less: it then takes what it needs.
        OidnGrant {
            max_memory_mib: mib_rounded_up(least),
            untiled: need <= least,
            _more: None,
        }
    }
}

/// Bytes a denoise of `pixels` pixels may take inside OIDN untiled.
pub fn untiled_bytes(pixels: u64) -> u64 {
    pixels.saturating_mul(OIDN_BYTES_PER_PIXEL)
}

fn mib_rounded_up(bytes: u64) -> u32 {
    u32::try_from(bytes.div_ceil(1 << 20)).unwrap_or(u32::MAX)
}

/// One guide: a declared AOV with three channels.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Guide {
    /// The AOV's name.
    pub name: String,
    /// Index of its first channel among all the frame's AOV channels (declaration order).
    pub first_channel: usize,
}

/// The guides of a frame's denoised images.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Guides {
    /// The albedo, if any.
    pub albedo: Option<Guide>,
    /// The normal, if any (only with an albedo).
    pub normal: Option<Guide>,
}

/// Last name components taken as an albedo when guides are chosen by name (case ignored).
pub const ALBEDO_NAMES: [&str; 4] = ["diffcol", "diffuse color", "albedo", "denoising albedo"];
/// Last name components taken as a normal when guides are chosen by name (case ignored).
pub const NORMAL_NAMES: [&str; 3] = ["normal", "n", "denoising normal"];

impl Guides {
    /// The guides of a frame declaring `aovs`: exactly those `explicit` names (each a declared
    /// AOV with three channels; a normal only with an albedo), or, without `explicit`, the first
    /// AOV with three channels whose last dot-separated name component is one of
    /// [`ALBEDO_NAMES`] (and likewise [`NORMAL_NAMES`]); a normal found without an albedo is
    /// left out, since OIDN takes a normal only beside an albedo.
    pub fn choose(
        aovs: &[AovSpec],
        explicit: Option<&DenoiseGuides>,
    ) -> Result<Guides, ParamError> {
        let first_channels: Vec<usize> = aovs
            .iter()
            .scan(0, |at, a| {
                let first = *at;
                *at += a.channels.len();
                Some(first)
            })
            .collect();
        let guide = |i: usize| Guide {
            name: aovs[i].name.clone(),
            first_channel: first_channels[i],
        };
        let Some(explicit) = explicit else {
            let by_name = |names: &[&str]| {
                aovs.iter().position(|a| {
                    let last = a.name.rsplit('.').next().unwrap_or(&a.name);
                    a.channels.len() == 3 && names.contains(&last.to_lowercase().as_str())
                })
            };
            let albedo = by_name(&ALBEDO_NAMES).map(guide);
            let normal = albedo
                .as_ref()
                .and_then(|_| by_name(&NORMAL_NAMES))
                .map(guide);
            return Ok(Guides { albedo, normal });
        };
        let named = |role: &str, name: &Option<String>| -> Result<Option<Guide>, ParamError> {
            let Some(name) = name else { return Ok(None) };
            let i = aovs.iter().position(|a| a.name == *name).ok_or_else(|| {
                ParamError::new(
                    "denoise_guides",
                    format!(
                        "{role} {name:?} is not one of the frame's AOVs ({})",
                        splatd_formats::names::describe_aovs(aovs)
                    ),
                )
            })?;
            if aovs[i].channels.len() != 3 {
                return Err(ParamError::new(
                    "denoise_guides",
                    format!(
                        "{role} {name:?} has {} channels; a guide has three",
                        aovs[i].channels.len()
                    ),
                ));
            }
            Ok(Some(guide(i)))
        };
        let albedo = named("albedo", &explicit.albedo)?;
        let normal = named("normal", &explicit.normal)?;
        if normal.is_some() && albedo.is_none() {
            return Err(ParamError::new(
                "denoise_guides",
                "a normal guide needs an albedo guide (OIDN takes a normal only beside an albedo)",
            ));
        }
        Ok(Guides { albedo, normal })
    }

    /// As the API shows them ([`splatd_proto::api::FrameInfo::denoise_guides`]).
    pub fn to_api(&self) -> DenoiseGuides {
        DenoiseGuides {
            albedo: self.albedo.as_ref().map(|g| g.name.clone()),
            normal: self.normal.as_ref().map(|g| g.name.clone()),
        }
    }
}

/// OIDN's quality from the API's.
pub fn quality(q: DenoiseQuality) -> Quality {
    match q {
        DenoiseQuality::Default => Quality::Default,
        DenoiseQuality::Balanced => Quality::Balanced,
        DenoiseQuality::High => Quality::High,
        DenoiseQuality::Fast => Quality::Fast,
    }
}

/// A denoised final and how it was made.
#[derive(Debug, Clone)]
pub struct DenoiseRun {
    /// The final, row-major RGB.
    pub rgb: Vec<[f32; 3]>,
    /// OIDN's version.
    pub version: String,
    /// The quality mode.
    pub quality: DenoiseQuality,
    /// The denoiser input's design ([`DenoisePlan::name`]).
    pub input: &'static str,
    /// How many images OIDN denoised for it.
    pub images: usize,
    /// The guides used.
    pub guides: Guides,
}

impl DenoiseRun {
    /// The EXR header attributes that say how the `denoised` layer was made.
    pub fn attributes(&self) -> Vec<(&'static str, HeaderValue)> {
        use HeaderValue as V;
        let name = |g: &Option<Guide>| V::Text(g.as_ref().map_or("none", |g| &g.name).to_owned());
        vec![
            ("splatd:denoiseAlbedo", name(&self.guides.albedo)),
            ("splatd:denoiseInput", V::Text(self.input.to_owned())),
            (
                "splatd:denoiseInputImages",
                V::Int(i32::try_from(self.images).unwrap_or(i32::MAX)),
            ),
            ("splatd:denoiseNormal", name(&self.guides.normal)),
            (
                "splatd:denoiseQuality",
                V::Text(self.quality.as_str().to_owned()),
            ),
            ("splatd:denoiser", V::Text("oidn".to_owned())),
            ("splatd:denoiserVersion", V::Text(self.version.clone())),
        ]
    }
}

/// Bytes a denoise of `pixels` pixels holds beside OIDN's own ([`OidnMemory`]): the plan's
/// resolve (three RGB layers and the sample counts, 44 bytes a pixel), and at 12 bytes a pixel
/// each its inputs (as many as [`DEFAULT_DENOISE_DESIGN`] makes), the two guides, one output per
/// input and the final. All are reserved before the denoise starts: a request reserving more
/// later could be refused by its own first reservation (a 3840x2160 frame, larger than the
/// default working memory, runs alone, and was then refused its second image, every time).
pub fn image_bytes(pixels: u64) -> u64 {
    let inputs = DEFAULT_DENOISE_DESIGN.images() as u64;
    pixels * (44 + 12 * (2 * inputs + 3))
}

/// Runs OIDN over `plan`'s inputs, one after the other, each with the same guides, taken from
/// the frame's AOV channel means `aov_planes` (every channel in declaration order; empty when
/// the frame has none), within the memory of `grant`, and combines the outputs into the final.
#[allow(clippy::too_many_arguments)]
pub fn run(
    oidn: &Oidn,
    frame: &str,
    plan: DenoisePlan,
    guides: &Guides,
    aov_planes: &[&[f32]],
    quality_mode: DenoiseQuality,
    grant: &OidnGrant,
) -> Result<DenoiseRun, DenoiseError> {
    let (w, h) = (plan.width(), plan.height());
    let guide_image = |g: &Option<Guide>| -> Option<Vec<[f32; 3]>> {
        let g = g.as_ref()?;
        let planes = aov_planes.get(g.first_channel..g.first_channel + 3)?;
        Some(
            (0..w * h)
                .map(|i| [planes[0][i], planes[1][i], planes[2][i]])
                .collect(),
        )
    };
    let albedo = guide_image(&guides.albedo);
    let normal = albedo.as_ref().and_then(|_| guide_image(&guides.normal));
    let used = Guides {
        albedo: albedo.as_ref().and(guides.albedo.clone()),
        normal: normal.as_ref().and(guides.normal.clone()),
    };
    let _ = crate::failpoint::hit("denoise:before_oidn");
    let started = std::time::Instant::now();
    let mut outputs = Vec::with_capacity(plan.inputs().len());
    for color in plan.inputs() {
        let input = DenoiseInput {
            width: w,
            height: h,
            color,
            albedo: albedo.as_deref(),
            normal: normal.as_deref(),
            hdr: true,
            quality: quality(quality_mode),
            clean_aux: false,
            max_memory_mib: Some(grant.max_memory_mib),
        };
        let out = oidn
            .denoise(&input)
            .map_err(|source| DenoiseError::Failed {
                frame: frame.to_owned(),
                source,
            })?;
        outputs.push(out);
    }
    let seconds = started.elapsed().as_secs_f64();
    metrics::histogram!(crate::meters::DENOISE_SECONDS).record(seconds);
    let memory = if grant.untiled { "untiled" } else { "tiled" };
    metrics::counter!(crate::meters::DENOISED_IMAGES, "memory" => memory)
        .increment(outputs.len() as u64);
    tracing::debug!(
        frame,
        images = outputs.len(),
        max_memory_mib = grant.max_memory_mib,
        memory,
        seconds,
        "denoised"
    );
    drop((albedo, normal));
    let input = plan.name();
    let images = plan.inputs().len();
    Ok(DenoiseRun {
        rgb: plan.combine(outputs),
        version: oidn.version(),
        quality: quality_mode,
        input,
        images,
        guides: used,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIB: u64 = 1 << 20;

    /// OIDN gets what an image needs untiled when the working memory has it free, else the most
    /// of a half, a quarter, ... of it that is free, else the floor; never more than the cap,
    /// and what it took beyond the floor goes back to the budget with the grant.
    #[test]
    fn oidn_gets_the_free_working_memory_up_to_what_the_image_needs() {
        let memory = OidnMemory::default();
        let hd = 1920 * 1080;
        // 1920x1080 needs 1 327 104 000 bytes untiled: 1266 MiB, rounded up.
        assert_eq!(untiled_bytes(hd), 1_327_104_000);
        assert_eq!(memory.reserved_bytes(hd), 512 * MIB, "the floor");
        assert_eq!(
            memory.reserved_bytes(64 * 48),
            64 * 48 * 640,
            "a small image's need"
        );

        // The grant for 1920x1080 in a budget of `capacity` bytes of which others hold `held`:
        // OIDN's cap, whether that is untiled, and the bytes it took from the budget.
        let grant = |memory: OidnMemory, capacity: u64, held: u64| -> (u32, bool, u64) {
            let budget = WorkBudget::new(capacity, std::time::Duration::ZERO);
            let _held = budget.try_reserve(held).unwrap();
            let grant = memory.grant(hd, &budget);
            let taken = budget.used() - held;
            let got = (grant.max_memory_mib, grant.untiled, taken);
            drop(grant);
            assert_eq!(budget.used(), held, "the grant gave its memory back");
            got
        };
        let held = 1000 * MIB;
        let need = untiled_bytes(hd);
        // Room for all of it: untiled.
        assert_eq!(
            grant(memory, 2400 * MIB, held),
            (1266, true, need - 512 * MIB)
        );
        // Room for half of it only: 633 MiB, tiled.
        let half = need / 2;
        assert_eq!(
            grant(memory, held + half - 512 * MIB, held),
            (633, false, half - 512 * MIB)
        );
        // No room: the floor, nothing more taken.
        assert_eq!(grant(memory, held, held), (512, false, 0));
        assert_eq!(grant(memory, held + 100 * MIB, held), (512, false, 0));
        // A cap below the need: at most the cap, even with room.
        let capped = OidnMemory {
            least_mib: 512,
            most_mib: Some(1024),
        };
        assert_eq!(grant(capped, 4096 * MIB, held), (1024, false, 512 * MIB));
        // A cap below the floor lowers the floor.
        let low = OidnMemory {
            least_mib: 512,
            most_mib: Some(256),
        };
        assert_eq!(low.reserved_bytes(hd), 256 * MIB);
        assert_eq!(grant(low, 4096 * MIB, held), (256, false, 0));
        // A small image is untiled within the floor, and OIDN is told the floor.
        let budget = WorkBudget::new(MIB, std::time::Duration::ZERO);
        let small = memory.grant(64 * 48, &budget);
        assert_eq!(
            (small.max_memory_mib, small.untiled, budget.used()),
            (512, true, 0)
        );
    }

    fn aov(name: &str, channels: &[&str]) -> AovSpec {
        AovSpec::new(name, channels)
    }

    #[test]
    fn guides_are_chosen_by_name_or_exactly_as_given() {
        let aovs = [
            aov("ViewLayer.Depth", &["Z"]),
            aov("ViewLayer.Normal", &["X", "Y", "Z"]),
            aov("ViewLayer.DiffCol", &["R", "G", "B"]),
            aov("albedo", &["R", "G", "B"]),
        ];
        let by_name = Guides::choose(&aovs, None).unwrap();
        assert_eq!(
            by_name.albedo,
            Some(Guide {
                name: "ViewLayer.DiffCol".into(),
                first_channel: 4
            }),
            "the first declared albedo"
        );
        assert_eq!(by_name.normal.as_ref().unwrap().first_channel, 1);

        let explicit = DenoiseGuides {
            albedo: Some("albedo".into()),
            normal: None,
        };
        let chosen = Guides::choose(&aovs, Some(&explicit)).unwrap();
        assert_eq!(chosen.albedo.unwrap().first_channel, 7);
        assert_eq!(chosen.normal, None, "exactly what was given");
        assert_eq!(
            Guides::choose(&aovs, Some(&DenoiseGuides::default())).unwrap(),
            Guides::default(),
            "{{}} is unguided"
        );

        // A normal alone is no guide by name, and refused when named.
        let normal_only = [aov("N", &["X", "Y", "Z"])];
        assert_eq!(
            Guides::choose(&normal_only, None).unwrap(),
            Guides::default()
        );
        let err = Guides::choose(
            &normal_only,
            Some(&DenoiseGuides {
                albedo: None,
                normal: Some("N".into()),
            }),
        )
        .unwrap_err();
        assert!(err.reason.contains("needs an albedo"), "{}", err.reason);

        for (name, want) in [
            ("nope", "not one of the frame's AOVs"),
            ("ViewLayer.Depth", "has 1 channels"),
        ] {
            let err = Guides::choose(
                &aovs,
                Some(&DenoiseGuides {
                    albedo: Some(name.into()),
                    normal: None,
                }),
            )
            .unwrap_err();
            assert!(err.reason.contains(want), "{}", err.reason);
            assert_eq!(err.name, "denoise_guides");
        }

        // Names by their last component, case ignored; a one-channel "albedo" is no guide.
        let blender = [
            aov("ViewLayer.Denoising Albedo", &["R", "G", "B"]),
            aov("ViewLayer.Denoising Normal", &["X", "Y", "Z"]),
        ];
        let g = Guides::choose(&blender, None).unwrap();
        assert!(g.albedo.is_some() && g.normal.is_some());
        assert_eq!(
            Guides::choose(&[aov("albedo", &["Y"])], None).unwrap(),
            Guides::default()
        );
    }
}
