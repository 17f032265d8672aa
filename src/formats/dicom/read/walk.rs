//! Walks the element structure of a DICOM data set without allocating: every declared
//! length is checked against the bytes left in its file or enclosing item, and sequences may
//! nest only so deep. It reads as dicom-rs does, except that a VR UN value of undefined
//! length holds Implicit VR Little Endian items (PS3.5 6.2.2), which the caller rewrites.

use dicom_core::dictionary::{DataDictionary, DataDictionaryEntry};
use dicom_core::{Tag, VR};
use dicom_dictionary_std::{tags, StandardDataDictionary};

/// Sequences nested deeper than this are refused: real objects (Enhanced CT functional
/// groups, structured reports) stay under ten, and dicom-rs recurses once per level.
pub(super) const MAX_SEQUENCE_DEPTH: usize = 32;

/// Value of a length field meaning "undefined, ends at a delimiter".
const UNDEFINED_LENGTH: u32 = 0xFFFF_FFFF;

/// Byte order and VR style of a stretch of the data set.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(super) enum Encoding {
    /// Explicit VR Little Endian (and every compressed syntax).
    ExplicitLittle,
    /// Implicit VR Little Endian: VRs come from the dictionary.
    ImplicitLittle,
    /// Explicit VR Big Endian (retired, still sent by old scanners).
    ExplicitBig,
}

/// What the walk found at one place in the data set, in file order.
pub(super) enum Event<'a> {
    /// A value of defined length; `vr` as written (`declared`) or from the dictionary.
    Element {
        tag: Tag,
        vr: VR,
        declared: bool,
        value: &'a [u8],
    },
    /// A sequence of items opens.
    SequenceStart { tag: Tag },
    /// Encapsulated (compressed) pixel data opens: fragments follow.
    PixelSequenceStart { tag: Tag, vr: VR },
    /// An item of a sequence opens.
    ItemStart,
    /// One fragment of encapsulated pixel data (the offset table included).
    Fragment(&'a [u8]),
    /// The current item closes.
    ItemEnd,
    /// The current sequence (or pixel sequence) closes.
    SequenceEnd,
}

/// Receives the walk's events; an `Err` stops the walk with that reason.
pub(super) trait Visitor {
    /// Handles one event.
    fn visit(&mut self, event: Event<'_>) -> Result<(), String>;
}

/// What a walk found besides its events.
#[derive(Debug, Default, Clone, Copy)]
pub(super) struct WalkSummary {
    /// Elements written with VR UN that dicom-rs would read differently from the standard:
    /// a tag the dictionary knows, or an undefined length (Implicit VR items inside).
    pub un_to_repair: usize,
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Kind {
    Dataset,
    Sequence,
    PixelSequence,
    Item,
}

/// An open sequence or item: where it ends (`end`, if its length is defined) and the last
/// byte anything inside may reach (`limit`, its own or its parent's end).
struct Container {
    kind: Kind,
    tag: Tag,
    end: Option<usize>,
    limit: usize,
    encoding: Encoding,
}

/// "PixelData (7FE0,0010)": the keyword when the dictionary knows the tag.
pub(super) fn tag_name(tag: Tag) -> String {
    match StandardDataDictionary.by_tag(tag) {
        Some(entry) => format!("{} ({:04X},{:04X})", entry.alias(), tag.0, tag.1),
        None => format!("({:04X},{:04X})", tag.0, tag.1),
    }
}

/// The dictionary's VR of `tag` as dicom-rs resolves it for Implicit VR, UN if unknown.
pub(super) fn dictionary_vr(tag: Tag) -> VR {
    if tag == tags::PIXEL_DATA {
        return VR::OW;
    }
    StandardDataDictionary
        .by_tag(tag)
        .map(|entry| entry.vr().relaxed())
        .unwrap_or(VR::UN)
}

/// Whether the dictionary knows `tag` (so a VR UN on it can be replaced).
pub(super) fn is_known(tag: Tag) -> bool {
    StandardDataDictionary.by_tag(tag).is_some()
}

/// VRs whose explicit length field is 16 bits (PS3.5 7.1.2); every other VR, and an
/// unknown one (read as UN), has 2 reserved bytes and a 32-bit length.
pub(super) fn has_short_length(vr: VR) -> bool {
    use VR::*;
    matches!(
        vr,
        AE | AS
            | AT
            | CS
            | DA
            | DS
            | DT
            | FL
            | FD
            | IS
            | LO
            | LT
            | PN
            | SH
            | SL
            | SS
            | ST
            | TM
            | UI
            | UL
            | US
    )
}

/// Bytes of one value of a binary VR (PS3.5 6.2), 1 for text and byte strings.
fn value_unit_bytes(vr: VR) -> usize {
    use VR::*;
    match vr {
        US | SS | OW => 2,
        UL | SL | FL | AT | OF | OL => 4,
        FD | OD | OV | SV | UV => 8,
        _ => 1,
    }
}

fn u16_at(data: &[u8], pos: usize, encoding: Encoding) -> u16 {
    let b = [data[pos], data[pos + 1]];
    match encoding {
        Encoding::ExplicitBig => u16::from_be_bytes(b),
        _ => u16::from_le_bytes(b),
    }
}

fn u32_at(data: &[u8], pos: usize, encoding: Encoding) -> u32 {
    let b = [data[pos], data[pos + 1], data[pos + 2], data[pos + 3]];
    match encoding {
        Encoding::ExplicitBig => u32::from_be_bytes(b),
        _ => u32::from_le_bytes(b),
    }
}

fn tag_at(data: &[u8], pos: usize, encoding: Encoding) -> Tag {
    Tag(u16_at(data, pos, encoding), u16_at(data, pos + 2, encoding))
}

/// Walks the data set `data` (everything after the file meta information) in `encoding`,
/// reporting each element to `visitor`. Linear in `data.len()`, no recursion.
pub(super) fn walk(
    data: &[u8],
    encoding: Encoding,
    visitor: &mut impl Visitor,
) -> Result<WalkSummary, String> {
    let mut walker = Walker {
        data,
        pos: 0,
        stack: vec![Container {
            kind: Kind::Dataset,
            tag: Tag(0, 0),
            end: Some(data.len()),
            limit: data.len(),
            encoding,
        }],
        summary: WalkSummary::default(),
    };
    while !walker.stack.is_empty() {
        walker.step(visitor)?;
    }
    Ok(walker.summary)
}

struct Walker<'a> {
    data: &'a [u8],
    pos: usize,
    stack: Vec<Container>,
    summary: WalkSummary,
}

impl<'a> Walker<'a> {
    fn top(&self) -> &Container {
        &self.stack[self.stack.len() - 1]
    }

    /// Where the innermost container is, for messages.
    fn place(&self) -> String {
        let open: Vec<&Container> = self
            .stack
            .iter()
            .filter(|c| c.kind == Kind::Sequence || c.kind == Kind::PixelSequence)
            .collect();
        match open.last() {
            Some(c) => format!("at byte {} (inside {})", self.pos, tag_name(c.tag)),
            None => format!("at byte {}", self.pos),
        }
    }

    /// One step: closes a container that has ended, or reads one header.
    fn step(&mut self, visitor: &mut impl Visitor) -> Result<(), String> {
        let top = self.top();
        let (kind, end, limit) = (top.kind, top.end, top.limit);
        if end == Some(self.pos) {
            self.stack.pop();
            return match kind {
                Kind::Dataset => Ok(()),
                Kind::Item => visitor.visit(Event::ItemEnd),
                Kind::Sequence | Kind::PixelSequence => visitor.visit(Event::SequenceEnd),
            };
        }
        let left = limit - self.pos;
        if left < 8 {
            return self.short_header(kind, end, limit, visitor);
        }
        match kind {
            Kind::Sequence | Kind::PixelSequence => self.item_header(kind, end, limit, visitor),
            Kind::Dataset | Kind::Item => self.element(limit, visitor),
        }
    }

    /// Fewer than 8 bytes left in a container: tolerated only as trailing bytes of the
    /// file (dicom-rs stops there) and at the end of a file cut inside encapsulated pixels.
    fn short_header(
        &mut self,
        kind: Kind,
        end: Option<usize>,
        limit: usize,
        visitor: &mut impl Visitor,
    ) -> Result<(), String> {
        let at_file_end = limit == self.data.len();
        let pixels_open = self.stack.iter().any(|c| c.kind == Kind::PixelSequence);
        if at_file_end && (kind == Kind::Dataset || pixels_open) {
            // dicom-rs ends the object gracefully here; close everything.
            while let Some(c) = self.stack.pop() {
                match c.kind {
                    Kind::Dataset => {}
                    Kind::Item => visitor.visit(Event::ItemEnd)?,
                    _ => visitor.visit(Event::SequenceEnd)?,
                }
            }
            self.pos = self.data.len();
            return Ok(());
        }
        let what = match (kind, end) {
            (Kind::Item, None) | (Kind::Sequence, None) | (Kind::PixelSequence, None) => {
                "is not closed by its delimiter"
            }
            _ => "ends inside an element header",
        };
        let container = if kind == Kind::Item {
            "item"
        } else {
            "sequence"
        };
        Err(format!(
            "a {container} {} {what} before {} (file truncated or corrupt)",
            self.place(),
            if at_file_end {
                "the end of the file".to_string()
            } else {
                format!("its enclosing item ends at byte {limit}")
            }
        ))
    }

    /// Inside a sequence: an item, or the sequence's delimiter.
    fn item_header(
        &mut self,
        kind: Kind,
        end: Option<usize>,
        limit: usize,
        visitor: &mut impl Visitor,
    ) -> Result<(), String> {
        let encoding = self.top().encoding;
        let tag = tag_at(self.data, self.pos, encoding);
        let length = u32_at(self.data, self.pos + 4, encoding);
        let start = self.pos;
        self.pos += 8;
        match (tag, kind) {
            (Tag(0xFFFE, 0xE0DD), _) if end.is_none() => {
                self.stack.pop();
                visitor.visit(Event::SequenceEnd)
            }
            (Tag(0xFFFE, 0xE000), Kind::PixelSequence) => {
                if length == UNDEFINED_LENGTH {
                    return Err(format!(
                        "a pixel data fragment at byte {start} has an undefined length"
                    ));
                }
                let value = self.value(length, limit, start, "a pixel data fragment")?;
                visitor.visit(Event::Fragment(value))
            }
            (Tag(0xFFFE, 0xE000), _) => {
                let item_end = if length == UNDEFINED_LENGTH {
                    None
                } else {
                    self.check_fits(length, limit, start, "an item")?;
                    Some(self.pos + length as usize)
                };
                self.stack.push(Container {
                    kind: Kind::Item,
                    tag,
                    end: item_end,
                    limit: item_end.unwrap_or(limit),
                    encoding,
                });
                visitor.visit(Event::ItemStart)
            }
            _ => {
                self.pos = start;
                Err(format!(
                    "{} where an item (FFFE,E000) was expected {}",
                    tag_name(tag),
                    self.place()
                ))
            }
        }
    }

    /// Checks that `length` bytes from the current position fit before `limit`.
    fn check_fits(
        &self,
        length: u32,
        limit: usize,
        start: usize,
        what: &str,
    ) -> Result<(), String> {
        let left = limit - self.pos;
        if length as usize > left {
            let within = if limit == self.data.len() {
                "the file".to_string()
            } else {
                format!("its enclosing item (ends at byte {limit})")
            };
            return Err(format!(
                "{what} at byte {start} declares {length} bytes but only {left} remain in \
                 {within} (truncated or corrupt file)"
            ));
        }
        Ok(())
    }

    /// Takes a value of `length` bytes after checking it fits.
    fn value(
        &mut self,
        length: u32,
        limit: usize,
        start: usize,
        what: &str,
    ) -> Result<&'a [u8], String> {
        self.check_fits(length, limit, start, what)?;
        let value = &self.data[self.pos..self.pos + length as usize];
        self.pos += length as usize;
        Ok(value)
    }

    fn push_sequence(
        &mut self,
        kind: Kind,
        tag: Tag,
        length: u32,
        encoding: Encoding,
    ) -> Result<(), String> {
        let depth = self
            .stack
            .iter()
            .filter(|c| c.kind == Kind::Sequence || c.kind == Kind::PixelSequence)
            .count();
        if depth >= MAX_SEQUENCE_DEPTH {
            return Err(format!(
                "sequences nested more than {MAX_SEQUENCE_DEPTH} deep ({} at byte {}): refused \
                 as corrupt or hostile",
                tag_name(tag),
                self.pos
            ));
        }
        let parent_limit = self.top().limit;
        let end = (length != UNDEFINED_LENGTH).then(|| self.pos + length as usize);
        self.stack.push(Container {
            kind,
            tag,
            end,
            limit: end.unwrap_or(parent_limit),
            encoding,
        });
        Ok(())
    }

    /// Inside a data set or item: one element header, then its value or its sequence.
    fn element(&mut self, limit: usize, visitor: &mut impl Visitor) -> Result<(), String> {
        let encoding = self.top().encoding;
        let start = self.pos;
        let tag = tag_at(self.data, start, encoding);
        if tag.0 == 0xFFFE {
            return self.delimiter_in_item(tag, visitor);
        }
        let (vr, declared, length) = match encoding {
            Encoding::ImplicitLittle => {
                self.pos += 8;
                (
                    dictionary_vr(tag),
                    false,
                    u32_at(self.data, start + 4, encoding),
                )
            }
            Encoding::ExplicitLittle | Encoding::ExplicitBig => {
                let vr =
                    VR::from_binary([self.data[start + 4], self.data[start + 5]]).unwrap_or(VR::UN);
                if has_short_length(vr) {
                    self.pos += 8;
                    (vr, true, u32::from(u16_at(self.data, start + 6, encoding)))
                } else {
                    if limit - start < 12 {
                        return Err(format!(
                            "{} at byte {start}: its header is cut short (truncated file)",
                            tag_name(tag)
                        ));
                    }
                    self.pos += 12;
                    (vr, true, u32_at(self.data, start + 8, encoding))
                }
            }
        };
        let un = declared && vr == VR::UN;
        if length == UNDEFINED_LENGTH {
            if tag == tags::PIXEL_DATA {
                self.push_sequence(Kind::PixelSequence, tag, length, encoding)?;
                return visitor.visit(Event::PixelSequenceStart { tag, vr });
            }
            let content = if un {
                if encoding == Encoding::ExplicitBig {
                    return Err(format!(
                        "{} at byte {start} is VR UN of undefined length in a big endian file: \
                         not supported",
                        tag_name(tag)
                    ));
                }
                self.summary.un_to_repair += 1;
                Encoding::ImplicitLittle
            } else {
                // dicom-rs reads any other undefined length as a sequence in the same encoding.
                encoding
            };
            self.push_sequence(Kind::Sequence, tag, length, content)?;
            return visitor.visit(Event::SequenceStart { tag });
        }
        self.check_fits(length, limit, start, &tag_name(tag))?;
        if vr == VR::SQ {
            self.push_sequence(Kind::Sequence, tag, length, encoding)?;
            return visitor.visit(Event::SequenceStart { tag });
        }
        if un && encoding == Encoding::ExplicitLittle && is_known(tag) {
            self.summary.un_to_repair += 1;
            if dictionary_vr(tag) == VR::SQ {
                self.push_sequence(Kind::Sequence, tag, length, Encoding::ImplicitLittle)?;
                return visitor.visit(Event::SequenceStart { tag });
            }
        }
        // dicom-rs reads whole values only and goes on from there, one byte short of where
        // this walk would: the two would then disagree on every later header (a fuzzer found
        // dicom-rs reading pixel bytes as a 4 GB length that way).
        let unit = value_unit_bytes(vr);
        if !(length as usize).is_multiple_of(unit) {
            return Err(format!(
                "{} at byte {start} declares {length} bytes, not a whole number of its VR {}'s \
                 {unit}-byte values (corrupt file)",
                tag_name(tag),
                vr.to_string()
            ));
        }
        let value = &self.data[self.pos..self.pos + length as usize];
        self.pos += length as usize;
        visitor.visit(Event::Element {
            tag,
            vr,
            declared,
            value,
        })
    }

    /// An item delimiter closes an item of undefined length; dicom-rs ignores one in the
    /// top-level data set. Anything else of group FFFE here is corrupt.
    fn delimiter_in_item(&mut self, tag: Tag, visitor: &mut impl Visitor) -> Result<(), String> {
        let (kind, end) = (self.top().kind, self.top().end);
        let start = self.pos;
        self.pos += 8;
        match (tag, kind, end) {
            (Tag(0xFFFE, 0xE00D), Kind::Item, None) => {
                self.stack.pop();
                visitor.visit(Event::ItemEnd)
            }
            (Tag(0xFFFE, 0xE00D), Kind::Dataset, _) => Ok(()),
            _ => {
                self.pos = start;
                Err(format!(
                    "unexpected {} {} inside {}",
                    tag_name(tag),
                    self.place(),
                    if kind == Kind::Item {
                        "an item"
                    } else {
                        "the data set"
                    }
                ))
            }
        }
    }
}
