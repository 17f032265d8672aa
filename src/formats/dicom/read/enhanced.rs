//! Multi-frame files (Enhanced CT Image Storage, PS3.3 A.38): one slice a frame, each frame's
//! position and orientation in its functional groups.

use dicom_dictionary_std::{tags, uids};
use dicom_object::InMemDicomObject;

use super::attributes::AttributeScope;
use super::{text, ParsedFile, SeriesLabel};
use crate::Result;

/// One slice to read: a single-frame file, or one frame of a multi-frame file.
pub(super) struct FrameRef<'a> {
    /// The file it is in.
    pub file: &'a ParsedFile,
    /// Frame index (0-based) in a multi-frame file; `None` for a single-frame file.
    pub frame: Option<usize>,
    /// Frames in the file.
    pub frame_count: usize,
    /// The file's name, with the frame's number for a multi-frame file.
    pub name: String,
    /// Where its attributes are.
    pub scope: AttributeScope<'a>,
}

/// Every slice of the series' files: each frame of an Enhanced CT file, each single-frame
/// file as is.
pub(super) fn expand_frames<'a>(
    files: &'a [ParsedFile],
    label: &SeriesLabel,
) -> Result<Vec<FrameRef<'a>>> {
    let mut slices = Vec::with_capacity(files.len());
    for file in files {
        let top: &InMemDicomObject = &file.object;
        let frames = match file.object.get(tags::NUMBER_OF_FRAMES) {
            None => 1,
            Some(e) => e.to_int::<u32>().map_err(|_| {
                label.error(format!(
                    "{}: NumberOfFrames (0028,0008) is not a positive integer",
                    file.name
                ))
            })? as usize,
        };
        let sop_class = text(&file.object, tags::SOP_CLASS_UID).unwrap_or_default();
        let enhanced = sop_class == uids::ENHANCED_CT_IMAGE_STORAGE
            || sop_class == uids::LEGACY_CONVERTED_ENHANCED_CT_IMAGE_STORAGE;
        if frames <= 1 && !enhanced {
            slices.push(FrameRef {
                file,
                frame: None,
                frame_count: 1,
                name: file.name.clone(),
                scope: AttributeScope::single_frame(top),
            });
            continue;
        }
        let items = |tag| top.get(tag).and_then(|e| e.items());
        let Some(per_frame) = items(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE) else {
            return Err(label.error(format!(
                "{} is a multi-frame image ({frames} frames) without a \
                 PerFrameFunctionalGroupsSequence (5200,9230): the position of each frame is \
                 unknown; export the series as single-frame CT images or as Enhanced CT",
                file.name
            )));
        };
        // The sequence's parsed items bound the frame count, not the declared number.
        if per_frame.len() != frames.max(1) {
            return Err(label.error(format!(
                "{}: PerFrameFunctionalGroupsSequence (5200,9230) has {} items for \
                 NumberOfFrames {frames}",
                file.name,
                per_frame.len()
            )));
        }
        let shared = items(tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE).and_then(|i| i.first());
        for (k, item) in per_frame.iter().enumerate() {
            slices.push(FrameRef {
                file,
                frame: (per_frame.len() > 1).then_some(k),
                frame_count: per_frame.len(),
                name: format!("{} frame {} of {}", file.name, k + 1, per_frame.len()),
                scope: AttributeScope {
                    per_frame: Some(item),
                    shared,
                    top,
                },
            });
        }
    }
    if slices.len() < 2 {
        return Err(label.error(format!(
            "only {} slice ({}): a volume needs at least 2",
            slices.len(),
            files[0].name
        )));
    }
    Ok(slices)
}
