//! The planning CT's patient, study and frame of reference, carried from the series read to
//! the DICOM objects derived from it (virtual 4D-CT phases, RTSTRUCT, spatial registrations)
//! so that a PACS files them beside the CT and a planning system overlays them on it.

use std::fmt;

/// Identity of the CT a run read, for the DICOM objects it writes. It holds identifying data
/// (patient name, ID, birth date): it is never serialized into `summary.json`, logged, or
/// shown in `Debug` output beyond its UIDs.
#[derive(Clone, PartialEq, Eq)]
pub struct DicomStudyContext {
    /// PatientName (0010,0010), as stored.
    pub patient_name: String,
    /// PatientID (0010,0020).
    pub patient_id: String,
    /// PatientBirthDate (0010,0030), may be empty.
    pub patient_birth_date: String,
    /// PatientSex (0010,0040), may be empty.
    pub patient_sex: String,
    /// StudyInstanceUID (0020,000D).
    pub study_instance_uid: String,
    /// StudyDate (0008,0020), may be empty.
    pub study_date: String,
    /// StudyTime (0008,0030), may be empty.
    pub study_time: String,
    /// StudyID (0020,0010), may be empty.
    pub study_id: String,
    /// AccessionNumber (0008,0050), may be empty.
    pub accession_number: String,
    /// ReferringPhysicianName (0008,0090), may be empty.
    pub referring_physician_name: String,
    /// StudyDescription (0008,1030), may be empty.
    pub study_description: String,
    /// FrameOfReferenceUID (0020,0052) of the CT: the derived objects share it.
    pub frame_of_reference_uid: String,
    /// SeriesInstanceUID (0020,000E) of the CT.
    pub series_instance_uid: String,
    /// PatientPosition (0018,5100), e.g. "HFS"; may be empty.
    pub patient_position: String,
    /// The image each volume slice k came from, in k order (RTSTRUCT contours reference them).
    pub slices: Vec<SliceReference>,
    /// Whether these identifiers came from the input's DICOM (false: generated for a NIfTI or
    /// NRRD input, which carries no study; derived objects then start a new study).
    pub from_input: bool,
}

/// The DICOM instance a volume slice was read from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SliceReference {
    /// SOPClassUID (0008,0016): CT Image Storage, or Enhanced CT for a multi-frame file.
    pub sop_class_uid: String,
    /// SOPInstanceUID (0008,0018).
    pub sop_instance_uid: String,
    /// Frame number (1-based) in a multi-frame instance.
    pub frame_number: Option<u32>,
}

impl fmt::Debug for DicomStudyContext {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // The patient's name, ID and birth date stay out of logs and panics.
        f.debug_struct("DicomStudyContext")
            .field("study_instance_uid", &self.study_instance_uid)
            .field("frame_of_reference_uid", &self.frame_of_reference_uid)
            .field("series_instance_uid", &self.series_instance_uid)
            .field("slices", &self.slices.len())
            .field("from_input", &self.from_input)
            .finish_non_exhaustive()
    }
}

impl DicomStudyContext {
    /// A new study for a CT that came without one (NIfTI, NRRD): fictitious patient, UIDs
    /// derived from `key` (a fingerprint of the CT) so a rerun gives the same UIDs, and
    /// no slice references.
    pub fn generated(key: u64) -> Self {
        DicomStudyContext {
            patient_name: "ANONYMOUS".into(),
            patient_id: format!("LUNGMOTION-{key:016X}"),
            patient_birth_date: String::new(),
            patient_sex: String::new(),
            study_instance_uid: derived_uid(key, 1, 0),
            study_date: String::new(),
            study_time: String::new(),
            study_id: "1".into(),
            accession_number: String::new(),
            referring_physician_name: String::new(),
            study_description: "lungmotion".into(),
            frame_of_reference_uid: derived_uid(key, 3, 0),
            series_instance_uid: derived_uid(key, 2, 0),
            patient_position: String::new(),
            slices: Vec::new(),
            from_input: false,
        }
    }

    /// A new UID for an object derived from this study: deterministic in the CT's series
    /// UID, `kind` (which object) and `index` (which phase, slice, …), in the 2.25 arc (a
    /// UUID-derived root needs no registered organisation root).
    pub fn derived_uid(&self, kind: u64, index: u64) -> String {
        derived_uid(fnv1a(self.series_instance_uid.as_bytes()), kind, index)
    }

    /// [`DicomStudyContext::derived_uid`] of an object whose content hashes to
    /// `content_key`: a rerun with the same result gets the same UIDs (a PACS holding them
    /// is sent nothing twice), a run with other settings gets new ones (and is stored).
    pub fn content_uid(&self, kind: u64, index: u64, content_key: u64) -> String {
        let key = fnv1a(self.series_instance_uid.as_bytes()) ^ splitmix64(content_key);
        derived_uid(key, kind, index)
    }
}

/// Folds 64-bit words into a content key (FNV-1a over words): for hashing what an object
/// shows, e.g. its vectors' bits.
#[derive(Debug, Clone, Copy)]
pub struct ContentKey(u64);

impl Default for ContentKey {
    fn default() -> Self {
        ContentKey(0xcbf2_9ce4_8422_2325)
    }
}

impl ContentKey {
    /// Folds `word` in.
    pub fn mix(&mut self, word: u64) {
        self.0 ^= word;
        self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
    }

    /// Folds the bytes of `text` in, then its length (so "ab"+"c" differs from "a"+"bc").
    pub fn mix_str(&mut self, text: &str) {
        text.bytes().for_each(|b| self.mix(u64::from(b)));
        self.mix(text.len() as u64);
    }

    /// The key.
    pub fn finish(self) -> u64 {
        self.0
    }
}

/// FNV-1a of `bytes`.
pub(crate) fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// `2.25.<128-bit number>` mixed from `key`, `kind` and `index`.
pub(crate) fn derived_uid(key: u64, kind: u64, index: u64) -> String {
    let a = splitmix64(key ^ splitmix64(kind.wrapping_mul(0x9e37_79b9) ^ index));
    let b = splitmix64(a ^ index.rotate_left(17) ^ kind);
    let n = (u128::from(a) << 64 | u128::from(b)).max(1);
    format!("2.25.{n}")
}

/// One round of SplitMix64.
pub(crate) fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derived_uids_are_valid_distinct_and_repeatable() {
        let ctx = DicomStudyContext::generated(42);
        let a = ctx.derived_uid(10, 1);
        assert_eq!(a, ctx.derived_uid(10, 1));
        assert_ne!(a, ctx.derived_uid(10, 2));
        assert_ne!(a, ctx.derived_uid(11, 1));
        // PS3.5 §9.1: at most 64 characters, digits and dots, no leading zero in a component.
        for uid in [&a, &ctx.study_instance_uid, &ctx.frame_of_reference_uid] {
            assert!(uid.len() <= 64, "{uid}");
            assert!(uid.split('.').all(|c| !c.is_empty()
                && c.bytes().all(|b| b.is_ascii_digit())
                && (c == "0" || !c.starts_with('0'))));
        }
    }

    #[test]
    fn content_uids_follow_the_content_and_stay_valid() {
        let ctx = DicomStudyContext::generated(7);
        let a = ctx.content_uid(10, 1, 99);
        assert_eq!(a, ctx.content_uid(10, 1, 99));
        assert_ne!(a, ctx.content_uid(10, 1, 100));
        assert_ne!(a, ctx.derived_uid(10, 1));
        let mut other = ctx.clone();
        other.series_instance_uid = "1.2.3".into();
        assert_ne!(a, other.content_uid(10, 1, 99));
        assert!(a.len() <= 64 && a.starts_with("2.25."), "{a}");
        let key = |parts: &[&str]| {
            let mut k = ContentKey::default();
            parts.iter().for_each(|p| k.mix_str(p));
            k.finish()
        };
        assert_ne!(key(&["ab", "c"]), key(&["a", "bc"]));
        assert_eq!(key(&["ab", "c"]), key(&["ab", "c"]));
    }

    #[test]
    fn debug_output_leaves_the_patient_out() {
        let mut ctx = DicomStudyContext::generated(1);
        ctx.patient_name = "DOE^JANE".into();
        ctx.patient_id = "MRN-12345".into();
        let shown = format!("{ctx:?}");
        assert!(
            !shown.contains("DOE") && !shown.contains("12345"),
            "{shown}"
        );
        assert!(shown.contains(&ctx.study_instance_uid));
    }
}
