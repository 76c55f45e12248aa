//! Intel Open Image Denoise (OIDN) 2.x, loaded at run time.
//!
//! The library is opened with `dlopen` ([`libloading`]) when [`Oidn::load`] or
//! [`Oidn::load_from`] is called, never linked: Debian has no OIDN package, and both of the
//! project's commands (`cargo run --release -- demo`, `bash tests/run.sh`) must build and run on
//! a fresh clone with only the Rust toolchain. A process without the library still runs; asking
//! it to denoise gives a [`DenoiseError`] that names the path it tried. `tests/setup/oidn.sh`
//! installs OIDN 2.5.1 from PyPI's `pyoidn` wheel and prints the library's path.
//!
//! The FFI below is this crate's own, written from OIDN's C API (`OpenImageDenoise/oidn.h`) and
//! its documentation (`doc/api.md`): one CPU device per [`Oidn`], committed once, and one `RT`
//! filter per [`Oidn::denoise`] call, with the images shared (no copies into OIDN buffers).
//! OIDN's API is thread-safe; calls on one device are serialized by OIDN, and each thread reads
//! its own error state (`oidnGetDeviceError` is per thread and device), so `Oidn` is `Send` and
//! `Sync` and every error is read on the thread that caused it.

use std::ffi::{c_char, c_int, c_void, CStr};
use std::fmt;
use std::path::{Path, PathBuf};

/// The environment variable that names the library [`Oidn::load`] opens.
pub const LIB_ENV: &str = "SPLATD_OIDN_LIB";

/// The file name [`Oidn::load`] asks the dynamic loader for when [`LIB_ENV`] is not set.
pub const DEFAULT_LIB: &str = "libOpenImageDenoise.so.2";

/// Why OIDN could not be loaded or could not denoise.
#[derive(Debug, thiserror::Error)]
pub enum DenoiseError {
    /// The library could not be opened (missing file, wrong architecture, missing dependency).
    #[error("cannot load Open Image Denoise from {path}: {reason} (set {LIB_ENV} or --oidn-lib to the path of libOpenImageDenoise.so.2; `bash tests/setup/oidn.sh` installs it and prints the path)")]
    Load {
        /// What was opened: a path, or the bare file name given to the dynamic loader.
        path: PathBuf,
        /// The loader's message.
        reason: String,
    },
    /// The library opened but lacks a function of OIDN 2's C API.
    #[error("{path} is not Open Image Denoise 2.x: it has no {symbol} ({reason})")]
    Symbol {
        /// The library opened.
        path: PathBuf,
        /// The missing function.
        symbol: &'static str,
        /// The loader's message.
        reason: String,
    },
    /// The library is OIDN, but not a major version this crate speaks.
    #[error("{path} is Open Image Denoise {version}; splatd needs 2.x")]
    Version {
        /// The library opened.
        path: PathBuf,
        /// The version it reports.
        version: String,
    },
    /// OIDN reported an error (device creation, filter setup or execution).
    #[error("Open Image Denoise ({path}) failed to {during}: {code}: {message}")]
    Oidn {
        /// The library opened.
        path: PathBuf,
        /// What was being done.
        during: &'static str,
        /// OIDN's error code, by name.
        code: &'static str,
        /// OIDN's message.
        message: String,
    },
    /// The images handed to [`Oidn::denoise`] do not fit together.
    #[error("invalid denoiser input: {0}")]
    InvalidInput(String),
}

/// OIDN's quality modes for the `RT` filter (`OIDNQuality`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Quality {
    /// OIDN's default (which is `High` in OIDN 2.x).
    #[default]
    Default,
    /// Balanced quality and performance (interactive rendering).
    Balanced,
    /// Highest quality (final frames).
    High,
    /// Fastest (previews).
    Fast,
}

impl Quality {
    /// Every mode, in declaration order.
    pub const ALL: [Quality; 4] = [
        Quality::Default,
        Quality::Balanced,
        Quality::High,
        Quality::Fast,
    ];

    /// OIDN's `OIDNQuality` value.
    fn raw(self) -> c_int {
        match self {
            Quality::Default => 0,
            Quality::Fast => 4,
            Quality::Balanced => 5,
            Quality::High => 6,
        }
    }

    /// The lower-case name (`default`, `balanced`, `high`, `fast`), as `oidnDenoise -q` takes it.
    pub fn as_str(self) -> &'static str {
        match self {
            Quality::Default => "default",
            Quality::Balanced => "balanced",
            Quality::High => "high",
            Quality::Fast => "fast",
        }
    }
}

impl fmt::Display for Quality {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Quality {
    type Err = String;

    fn from_str(s: &str) -> Result<Quality, String> {
        Quality::ALL
            .into_iter()
            .find(|q| q.as_str() == s)
            .ok_or_else(|| format!("unknown OIDN quality {s:?}: default, balanced, high or fast"))
    }
}

/// One image to denoise with its optional guides: every image is `width * height` RGB pixels,
/// row-major, top row first.
#[derive(Debug, Clone, Copy)]
pub struct DenoiseInput<'a> {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// The noisy beauty (linear; HDR when `hdr`).
    pub color: &'a [[f32; 3]],
    /// Albedo guide, values in [0, 1].
    pub albedo: Option<&'a [[f32; 3]]>,
    /// Shading normal guide, values in [-1, 1]; OIDN takes it only with an albedo.
    pub normal: Option<&'a [[f32; 3]]>,
    /// The beauty is high dynamic range (OIDN's `hdr`).
    pub hdr: bool,
    /// OIDN's quality mode.
    pub quality: Quality,
    /// The guides are noise-free (OIDN's `cleanAux`); leave it off for guides averaged over few
    /// samples, or their noise stays in the output.
    pub clean_aux: bool,
    /// The most memory the filter may use, in MiB (OIDN's `maxMemoryMB`, which it meets by
    /// denoising in overlapping tiles, a little slower), or `None` for OIDN's own limit. OIDN
    /// says its actual use "may be higher"; untiled, a 1920x1080 `high` denoise used 1.21 GB
    /// (582 bytes a pixel) here, and a cap of 1266 MiB left it untiled.
    pub max_memory_mib: Option<u32>,
}

impl DenoiseInput<'_> {
    fn check(&self) -> Result<(), DenoiseError> {
        let bad = |what: String| Err(DenoiseError::InvalidInput(what));
        if self.width == 0 || self.height == 0 {
            return bad(format!("empty image ({}x{})", self.width, self.height));
        }
        let Some(pixels) = self.width.checked_mul(self.height) else {
            return bad(format!("{}x{} is too large", self.width, self.height));
        };
        let images = [
            ("color", Some(self.color)),
            ("albedo", self.albedo),
            ("normal", self.normal),
        ];
        for (name, image) in images {
            if let Some(image) = image {
                if image.len() != pixels {
                    return bad(format!(
                        "{name} has {} pixels, {}x{} needs {pixels}",
                        image.len(),
                        self.width,
                        self.height
                    ));
                }
            }
        }
        if self.normal.is_some() && self.albedo.is_none() {
            return bad(
                "a normal guide needs an albedo guide (OIDN's RT filter takes color, \
                 color + albedo, or color + albedo + normal)"
                    .into(),
            );
        }
        Ok(())
    }
}

type Device = *mut c_void;
type Filter = *mut c_void;

/// OIDN's functions, resolved from the library. Valid while `Oidn::_lib` is loaded.
struct Api {
    new_device: unsafe extern "C" fn(c_int) -> Device,
    commit_device: unsafe extern "C" fn(Device),
    release_device: unsafe extern "C" fn(Device),
    set_device_bool: unsafe extern "C" fn(Device, *const c_char, bool),
    get_device_int: unsafe extern "C" fn(Device, *const c_char) -> c_int,
    get_device_error: unsafe extern "C" fn(Device, *mut *const c_char) -> c_int,
    new_filter: unsafe extern "C" fn(Device, *const c_char) -> Filter,
    release_filter: unsafe extern "C" fn(Filter),
    #[allow(clippy::type_complexity)]
    set_shared_filter_image: unsafe extern "C" fn(
        Filter,
        *const c_char,
        *mut c_void,
        c_int,
        usize,
        usize,
        usize,
        usize,
        usize,
    ),
    set_filter_bool: unsafe extern "C" fn(Filter, *const c_char, bool),
    set_filter_int: unsafe extern "C" fn(Filter, *const c_char, c_int),
    commit_filter: unsafe extern "C" fn(Filter),
    execute_filter: unsafe extern "C" fn(Filter),
}

/// `OIDN_DEVICE_TYPE_CPU`
const DEVICE_TYPE_CPU: c_int = 1;
/// `OIDN_FORMAT_FLOAT3`
const FORMAT_FLOAT3: c_int = 3;

/// `OIDNError` by name.
fn error_name(code: c_int) -> &'static str {
    match code {
        0 => "OIDN_ERROR_NONE",
        1 => "OIDN_ERROR_UNKNOWN",
        2 => "OIDN_ERROR_INVALID_ARGUMENT",
        3 => "OIDN_ERROR_INVALID_OPERATION",
        4 => "OIDN_ERROR_OUT_OF_MEMORY",
        5 => "OIDN_ERROR_UNSUPPORTED_HARDWARE",
        6 => "OIDN_ERROR_CANCELLED",
        _ => "unknown OIDN error code",
    }
}

/// A loaded OIDN library with one committed CPU device. Filters are made per call.
pub struct Oidn {
    api: Api,
    device: Device,
    path: PathBuf,
    version: String,
    // Dropped last (fields drop in order, after `Drop::drop` released the device): the
    // function pointers in `api` point into it.
    _lib: libloading::Library,
}

// SAFETY: OIDN's API is thread-safe (doc/api.md: "All API calls are thread-safe, but operations
// that use the same device will be serialized"); the device handle is only passed to it, and
// errors are read per thread.
unsafe impl Send for Oidn {}
// SAFETY: as for `Send`: `&Oidn` only calls OIDN's thread-safe functions.
unsafe impl Sync for Oidn {}

impl fmt::Debug for Oidn {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Oidn")
            .field("path", &self.path)
            .field("version", &self.version)
            .finish()
    }
}

impl Oidn {
    /// Loads the library named by `SPLATD_OIDN_LIB` (a path to `libOpenImageDenoise.so.2`), or
    /// else `libOpenImageDenoise.so.2` from the dynamic loader's search path.
    pub fn load() -> Result<Oidn, DenoiseError> {
        match std::env::var_os(LIB_ENV) {
            Some(path) if !path.is_empty() => Oidn::load_from(Path::new(&path)),
            _ => Oidn::load_from(Path::new(DEFAULT_LIB)),
        }
    }

    /// Loads the library at `path` (a bare file name goes to the dynamic loader's search path),
    /// creates and commits a CPU device, and checks that it is OIDN 2.x.
    pub fn load_from(path: &Path) -> Result<Oidn, DenoiseError> {
        let path = path.to_path_buf();
        // SAFETY: loading OIDN runs its initializers, which are sound (a C++ library with static
        // constructors); a library that is not OIDN is caught by the symbol and version checks.
        let lib = unsafe { libloading::Library::new(&path) }.map_err(|e| DenoiseError::Load {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        macro_rules! sym {
            ($name:literal) => {{
                // SAFETY: the type is the function's signature in OIDN 2's oidn.h; the pointer
                // is used only while `lib` is loaded (it is kept in the returned `Oidn`).
                let f = unsafe { lib.get(concat!($name, "\0").as_bytes()) }.map_err(|e| {
                    DenoiseError::Symbol {
                        path: path.clone(),
                        symbol: $name,
                        reason: e.to_string(),
                    }
                })?;
                *f
            }};
        }
        let api = Api {
            new_device: sym!("oidnNewDevice"),
            commit_device: sym!("oidnCommitDevice"),
            release_device: sym!("oidnReleaseDevice"),
            set_device_bool: sym!("oidnSetDeviceBool"),
            get_device_int: sym!("oidnGetDeviceInt"),
            get_device_error: sym!("oidnGetDeviceError"),
            new_filter: sym!("oidnNewFilter"),
            release_filter: sym!("oidnReleaseFilter"),
            set_shared_filter_image: sym!("oidnSetSharedFilterImage"),
            set_filter_bool: sym!("oidnSetFilterBool"),
            set_filter_int: sym!("oidnSetFilterInt"),
            commit_filter: sym!("oidnCommitFilter"),
            execute_filter: sym!("oidnExecuteFilter"),
        };
        // SAFETY: OIDN's API as documented; a null device is allowed in oidnGetDeviceError.
        let device = unsafe { (api.new_device)(DEVICE_TYPE_CPU) };
        if device.is_null() {
            let (code, message) = take_error(&api, std::ptr::null_mut());
            return Err(DenoiseError::Oidn {
                path,
                during: "create a CPU device",
                code: error_name(code),
                message,
            });
        }
        let mut oidn = Oidn {
            api,
            device,
            path,
            version: String::new(),
            _lib: lib,
        };
        // A server shares its cores with its own threads: OIDN's default pins its worker threads
        // to cores, which would fight the scheduler there.
        // SAFETY: a valid device and a NUL-terminated parameter name.
        unsafe { (oidn.api.set_device_bool)(oidn.device, c"setAffinity".as_ptr(), false) };
        // SAFETY: a valid device.
        unsafe { (oidn.api.commit_device)(oidn.device) };
        oidn.check("commit the CPU device")?;
        // SAFETY: a valid, committed device; `version` is a documented constant parameter.
        let raw = unsafe { (oidn.api.get_device_int)(oidn.device, c"version".as_ptr()) };
        oidn.check("read the device's version")?;
        oidn.version = format!("{}.{}.{}", raw / 10000, raw / 100 % 100, raw % 100);
        if raw / 10000 != 2 {
            return Err(DenoiseError::Version {
                path: oidn.path.clone(),
                version: oidn.version.clone(),
            });
        }
        Ok(oidn)
    }

    /// OIDN's version, e.g. `2.5.1` (the device's `version` parameter).
    pub fn version(&self) -> String {
        self.version.clone()
    }

    /// The library this was loaded from, as given.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Denoises `input.color` with OIDN's `RT` filter, guided by the albedo and normal when
    /// given; returns the denoised RGB image, row-major.
    pub fn denoise(&self, input: &DenoiseInput<'_>) -> Result<Vec<[f32; 3]>, DenoiseError> {
        input.check()?;
        let (w, h) = (input.width, input.height);
        let mut output = vec![[0f32; 3]; w * h];
        // SAFETY: a valid device and filter type name.
        let filter = unsafe { (self.api.new_filter)(self.device, c"RT".as_ptr()) };
        if filter.is_null() {
            self.check("create an RT filter")?;
            return Err(self.oidn_error("create an RT filter", 1, "no filter".into()));
        }
        // Released on every path out, errors included.
        struct Release<'a>(&'a Api, Filter);
        impl Drop for Release<'_> {
            fn drop(&mut self) {
                // SAFETY: the filter was created by this API and is released once.
                unsafe { (self.0.release_filter)(self.1) };
            }
        }
        let _release = Release(&self.api, filter);
        let set_image = |name: &CStr, data: *mut c_void| {
            // SAFETY: `data` points at `w * h` float triples (checked above) that outlive the
            // filter's execution below; strides 0 mean tightly packed.
            unsafe {
                (self.api.set_shared_filter_image)(
                    filter,
                    name.as_ptr(),
                    data,
                    FORMAT_FLOAT3,
                    w,
                    h,
                    0,
                    0,
                    0,
                )
            }
        };
        // OIDN only reads the inputs (the output is a separate image): casting away const is
        // what its C signature asks for, not a licence to write.
        set_image(c"color", input.color.as_ptr() as *mut c_void);
        if let Some(albedo) = input.albedo {
            set_image(c"albedo", albedo.as_ptr() as *mut c_void);
        }
        if let Some(normal) = input.normal {
            set_image(c"normal", normal.as_ptr() as *mut c_void);
        }
        set_image(c"output", output.as_mut_ptr() as *mut c_void);
        // SAFETY: a valid filter and NUL-terminated documented parameter names.
        unsafe {
            (self.api.set_filter_bool)(filter, c"hdr".as_ptr(), input.hdr);
            (self.api.set_filter_bool)(filter, c"cleanAux".as_ptr(), input.clean_aux);
            (self.api.set_filter_int)(filter, c"quality".as_ptr(), input.quality.raw());
            if let Some(mib) = input.max_memory_mib {
                let mib = c_int::try_from(mib).unwrap_or(c_int::MAX);
                (self.api.set_filter_int)(filter, c"maxMemoryMB".as_ptr(), mib);
            }
        }
        self.check("set the RT filter's images and parameters")?;
        // SAFETY: a valid filter whose images are set.
        unsafe { (self.api.commit_filter)(filter) };
        self.check("commit the RT filter")?;
        // SAFETY: as above; synchronous, so the shared images are not used after it returns.
        unsafe { (self.api.execute_filter)(filter) };
        self.check("execute the RT filter")?;
        Ok(output)
    }

    /// The first error this thread left on the device since the last check, if any.
    fn check(&self, during: &'static str) -> Result<(), DenoiseError> {
        let (code, message) = take_error(&self.api, self.device);
        if code == 0 {
            Ok(())
        } else {
            Err(self.oidn_error(during, code, message))
        }
    }

    fn oidn_error(&self, during: &'static str, code: c_int, message: String) -> DenoiseError {
        DenoiseError::Oidn {
            path: self.path.clone(),
            during,
            code: error_name(code),
            message,
        }
    }
}

/// `oidnGetDeviceError` for this thread: the code and a copy of the message.
fn take_error(api: &Api, device: Device) -> (c_int, String) {
    let mut message: *const c_char = std::ptr::null();
    // SAFETY: `device` is valid or null (allowed); `message` receives a C string valid until the
    // next call on this thread, copied at once.
    let code = unsafe { (api.get_device_error)(device, &mut message) };
    let text = if message.is_null() {
        String::new()
    } else {
        // SAFETY: a NUL-terminated string from OIDN, see above.
        unsafe { CStr::from_ptr(message) }
            .to_string_lossy()
            .into_owned()
    };
    (code, text)
}

impl Drop for Oidn {
    fn drop(&mut self) {
        // SAFETY: the device was created by this library, which is still loaded.
        unsafe { (self.api.release_device)(self.device) };
    }
}
