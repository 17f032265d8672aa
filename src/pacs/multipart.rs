//! `multipart/related` bodies of DICOMweb: the boundary of a WADO-RS answer (its parts are
//! read by `multer`), and STOW-RS request bodies.

use crate::{Error, Result};

/// The `boundary` parameter of a `multipart/related` Content-Type.
pub(super) fn boundary_of(content_type: &str, url: &str) -> Result<String> {
    let unusable = |reason: String| Error::Pacs {
        url: url.to_string(),
        status: Some(200),
        reason,
    };
    let lower = content_type.to_ascii_lowercase();
    if !lower.starts_with("multipart/related") {
        return Err(unusable(format!(
            "the answer is '{content_type}', not multipart/related DICOM (is this a DICOMweb \
             root?)"
        )));
    }
    content_type
        .split(';')
        .filter_map(|p| p.trim().split_once('='))
        .find(|(k, _)| k.trim().eq_ignore_ascii_case("boundary"))
        .map(|(_, v)| v.trim().trim_matches('"').to_string())
        .filter(|b| !b.is_empty() && b.len() <= 200)
        .ok_or_else(|| unusable(format!("'{content_type}' has no usable boundary")))
}

/// A STOW-RS body holding `parts` (each a DICOM file), and its Content-Type.
pub(super) fn stow_body(parts: &[Vec<u8>], boundary: &str) -> (Vec<u8>, String) {
    let size: usize = parts.iter().map(|p| p.len() + boundary.len() + 48).sum();
    let mut body = Vec::with_capacity(size + boundary.len() + 8);
    for part in parts {
        body.extend_from_slice(b"--");
        body.extend_from_slice(boundary.as_bytes());
        body.extend_from_slice(b"\r\nContent-Type: application/dicom\r\n\r\n");
        body.extend_from_slice(part);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(b"--");
    body.extend_from_slice(boundary.as_bytes());
    body.extend_from_slice(b"--\r\n");
    let content_type =
        format!("multipart/related; type=\"application/dicom\"; boundary={boundary}");
    (body, content_type)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn boundaries_are_read_quoted_or_not_and_other_answers_refused() {
        let ct = "multipart/related; type=\"application/dicom\"; boundary=\"abc 1\"";
        assert_eq!(boundary_of(ct, "u").unwrap(), "abc 1");
        assert_eq!(
            boundary_of("multipart/related;boundary=xyz", "u").unwrap(),
            "xyz"
        );
        let e = boundary_of("text/html", "u").unwrap_err().to_string();
        assert!(e.contains("not multipart/related"), "{e}");
        let e = boundary_of("multipart/related; type=x", "u")
            .unwrap_err()
            .to_string();
        assert!(e.contains("no usable boundary"), "{e}");
    }

    #[test]
    fn stow_bodies_delimit_each_part() {
        let (body, ct) = stow_body(&[b"AB".to_vec(), b"C".to_vec()], "b0");
        assert_eq!(
            body,
            b"--b0\r\nContent-Type: application/dicom\r\n\r\nAB\r\n--b0\r\nContent-Type: \
              application/dicom\r\n\r\nC\r\n--b0--\r\n"
        );
        assert!(ct.ends_with("boundary=b0"));
    }
}
