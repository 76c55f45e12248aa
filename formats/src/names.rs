//! Names in splatd's formats: which AOV and channel names an OpenEXR file can hold, and how
//! a frame's AOVs are described in messages.

use splatd_proto::api::AovSpec;

/// Longest EXR channel name: OpenEXR reads and writes names (attribute names, type names and
/// channel names) of at most 255 bytes, with the header's long-names flag set for those over 31.
pub const MAX_EXR_NAME_BYTES: usize = 255;

/// Why `name` (an AOV or channel name) cannot be written into an EXR as it is, if it cannot:
/// names are printable ASCII, bytes 0x20 (space) to 0x7E (`~`).
///
/// OpenEXR stores names as NUL-terminated bytes, so a NUL (or any control character) cuts or
/// garbles the header. Bytes above 0x7E have no one meaning: the `exr` crate that writes
/// `image.exr` and reads passes takes them as Latin-1 characters, while OpenEXR's own tools
/// (and Blender) read and write UTF-8, so a name such as `été` would be written in one encoding
/// and looked for in the other. Such a name is refused rather than served as an unreadable file
/// or matched against no layer of the passes.
pub fn check_exr_name(name: &str) -> Result<(), String> {
    if let Some((at, c)) = name.char_indices().find(|(_, c)| !c.is_ascii()) {
        return Err(format!(
            "encoding rule: names are printable ASCII (0x20 to 0x7E), but {c:?} (U+{:04X}) at \
             byte {at} is not ASCII",
            c as u32
        ));
    }
    if let Some(at) = name.bytes().position(|b| !(0x20..=0x7E).contains(&b)) {
        return Err(format!(
            "characters rule: names are printable ASCII (0x20 to 0x7E), but byte {at} is the \
             control character 0x{:02X}",
            name.as_bytes()[at]
        ));
    }
    if name.len() > MAX_EXR_NAME_BYTES {
        return Err(format!(
            "length rule: {} bytes, and OpenEXR names are at most {MAX_EXR_NAME_BYTES} bytes",
            name.len()
        ));
    }
    Ok(())
}

/// AOV declarations for a message: `"albedo" (R, G, B), "depth" (Z)`, or `none`.
pub fn describe_aovs(aovs: &[AovSpec]) -> String {
    if aovs.is_empty() {
        return "none".into();
    }
    let all: Vec<String> = aovs
        .iter()
        .map(|a| format!("{:?} ({})", a.name, a.channels.join(", ")))
        .collect();
    all.join(", ")
}
