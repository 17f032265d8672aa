//! Rewrites a data set whose elements were stored with VR UN (as some PACS and toolkits
//! re-encode everything) into plain Explicit VR Little Endian with the dictionary's VRs, as
//! pydicom and DCMTK read such files; dicom-rs would keep the values as raw bytes.

use dicom_core::{Tag, VR};
use dicom_dictionary_std::tags;

use super::walk::{dictionary_vr, has_short_length, Event, Visitor};

/// Length field of a sequence or item closed by a delimiter.
const UNDEFINED_LENGTH: u32 = 0xFFFF_FFFF;

/// Re-encodes the walked events as Explicit VR Little Endian. Every sequence and item gets
/// an undefined length and its delimiter, since the re-encoded content changes size.
pub(super) struct ExplicitLittleWriter {
    /// The re-encoded data set.
    pub out: Vec<u8>,
    /// Sequences open around the current event (0: the top-level data set).
    depth: usize,
    /// PixelRepresentation (0028,0103) of the data set: US or SS for pixel-valued tags.
    pixel_representation: Option<u16>,
    /// BitsAllocated (0028,0100) of the data set: OB or OW for Pixel Data.
    bits_allocated: Option<u16>,
    /// Elements whose VR UN was replaced.
    pub replaced: usize,
}

impl ExplicitLittleWriter {
    /// A writer with room for about `capacity` bytes.
    pub(super) fn with_capacity(capacity: usize) -> Self {
        ExplicitLittleWriter {
            out: Vec::with_capacity(capacity),
            depth: 0,
            pixel_representation: None,
            bits_allocated: None,
            replaced: 0,
        }
    }

    fn tag(&mut self, tag: Tag) {
        self.out.extend_from_slice(&tag.0.to_le_bytes());
        self.out.extend_from_slice(&tag.1.to_le_bytes());
    }

    /// An element header in explicit VR little endian.
    fn header(&mut self, tag: Tag, vr: VR, length: u32) {
        self.tag(tag);
        self.out.extend_from_slice(vr.to_string().as_bytes());
        if has_short_length(vr) {
            self.out.extend_from_slice(&(length as u16).to_le_bytes());
        } else {
            self.out.extend_from_slice(&[0, 0]);
            self.out.extend_from_slice(&length.to_le_bytes());
        }
    }

    /// An item-level header (tag and 32-bit length, no VR).
    fn item(&mut self, element: u16, length: u32) {
        self.tag(Tag(0xFFFE, element));
        self.out.extend_from_slice(&length.to_le_bytes());
    }

    /// The VR to write for an element stored as `vr`: kept when written and not UN,
    /// otherwise the dictionary's, resolved by the pixel format where it depends on it.
    fn vr_for(&mut self, tag: Tag, vr: VR, declared: bool) -> VR {
        if declared && vr != VR::UN {
            return vr;
        }
        let resolved = match tag {
            t if t == tags::PIXEL_DATA => match self.bits_allocated {
                Some(bits) if bits <= 8 => VR::OB,
                _ => VR::OW,
            },
            tags::SMALLEST_IMAGE_PIXEL_VALUE
            | tags::LARGEST_IMAGE_PIXEL_VALUE
            | tags::SMALLEST_PIXEL_VALUE_IN_SERIES
            | tags::LARGEST_PIXEL_VALUE_IN_SERIES
            | tags::PIXEL_PADDING_VALUE
            | tags::PIXEL_PADDING_RANGE_LIMIT => match self.pixel_representation {
                Some(1) => VR::SS,
                _ => VR::US,
            },
            _ => dictionary_vr(tag),
        };
        if declared && resolved != VR::UN {
            self.replaced += 1;
        }
        resolved
    }

    /// Remembers the pixel format of the top-level data set.
    fn note_pixel_format(&mut self, tag: Tag, value: &[u8]) {
        if self.depth != 0 || value.len() < 2 {
            return;
        }
        let number = u16::from_le_bytes([value[0], value[1]]);
        if tag == tags::BITS_ALLOCATED {
            self.bits_allocated = Some(number);
        } else if tag == tags::PIXEL_REPRESENTATION {
            self.pixel_representation = Some(number);
        }
    }
}

impl Visitor for ExplicitLittleWriter {
    fn visit(&mut self, event: Event<'_>) -> Result<(), String> {
        match event {
            Event::Element {
                tag,
                vr,
                declared,
                value,
            } => {
                let mut vr = self.vr_for(tag, vr, declared);
                if has_short_length(vr) && value.len() > usize::from(u16::MAX) {
                    // Too long for this VR's 16-bit length field: left as bytes.
                    vr = VR::UN;
                }
                self.note_pixel_format(tag, value);
                self.header(tag, vr, value.len() as u32);
                self.out.extend_from_slice(value);
            }
            Event::SequenceStart { tag } => {
                self.header(tag, VR::SQ, UNDEFINED_LENGTH);
                self.depth += 1;
            }
            Event::PixelSequenceStart { tag, vr } => {
                let vr = if vr == VR::OW { VR::OW } else { VR::OB };
                self.header(tag, vr, UNDEFINED_LENGTH);
                self.depth += 1;
            }
            Event::ItemStart => self.item(0xE000, UNDEFINED_LENGTH),
            Event::Fragment(value) => {
                self.item(0xE000, value.len() as u32);
                self.out.extend_from_slice(value);
            }
            Event::ItemEnd => self.item(0xE00D, 0),
            Event::SequenceEnd => {
                self.item(0xE0DD, 0);
                self.depth = self.depth.saturating_sub(1);
            }
        }
        Ok(())
    }
}
