//! Base64 as VTK's binary DataArrays use it: a streaming encoder and a strict decoder.

/// The standard base64 alphabet (RFC 4648), as VTK uses it.
const BASE64: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

/// Streams bytes into base64 text, so arrays are encoded without an intermediate buffer.
pub(super) struct Base64Writer<'a> {
    out: &'a mut String,
    pending: [u8; 3],
    n_pending: usize,
}

impl<'a> Base64Writer<'a> {
    pub fn new(out: &'a mut String) -> Self {
        Base64Writer {
            out,
            pending: [0; 3],
            n_pending: 0,
        }
    }

    pub fn push(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.pending[self.n_pending] = b;
            self.n_pending += 1;
            if self.n_pending == 3 {
                self.emit();
            }
        }
    }

    fn emit(&mut self) {
        let [a, b, c] = self.pending;
        let chars = [
            a >> 2,
            ((a & 3) << 4) | (b >> 4),
            ((b & 15) << 2) | (c >> 6),
            c & 63,
        ];
        for (i, &s) in chars.iter().enumerate() {
            // A partial group keeps n+1 characters and pads the rest.
            if i <= self.n_pending {
                self.out.push(BASE64[s as usize] as char);
            } else {
                self.out.push('=');
            }
        }
        self.pending = [0; 3];
        self.n_pending = 0;
    }

    pub fn finish(mut self) {
        if self.n_pending > 0 {
            self.emit();
        }
    }
}

/// Decodes base64 text (padding allowed only at the end); `None` if it is not base64.
pub(super) fn base64_decode(text: &[u8]) -> Option<Vec<u8>> {
    if !text.len().is_multiple_of(4) {
        return None;
    }
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let value = |c: u8| -> Option<u8> {
        match c {
            b'A'..=b'Z' => Some(c - b'A'),
            b'a'..=b'z' => Some(c - b'a' + 26),
            b'0'..=b'9' => Some(c - b'0' + 52),
            b'+' => Some(62),
            b'/' => Some(63),
            _ => None,
        }
    };
    let groups = text.len() / 4;
    for (g, quad) in text.chunks_exact(4).enumerate() {
        let pad = quad.iter().rev().take_while(|&&c| c == b'=').count();
        if pad > 2 || (pad > 0 && g + 1 != groups) {
            return None;
        }
        let mut v = [0u8; 4];
        for (i, &c) in quad[..4 - pad].iter().enumerate() {
            v[i] = value(c)?;
        }
        let bytes = [
            (v[0] << 2) | (v[1] >> 4),
            (v[1] << 4) | (v[2] >> 2),
            (v[2] << 6) | v[3],
        ];
        out.extend_from_slice(&bytes[..3 - pad]);
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc4648_vectors() {
        let cases: [(&[u8], &str); 4] = [
            (b"", ""),
            (b"f", "Zg=="),
            (b"fo", "Zm8="),
            (b"foobar", "Zm9vYmFy"),
        ];
        for (raw, text) in cases {
            let mut s = String::new();
            let mut w = Base64Writer::new(&mut s);
            w.push(raw);
            w.finish();
            assert_eq!(s, text);
            assert_eq!(base64_decode(text.as_bytes()).unwrap(), raw);
        }
        assert!(base64_decode(b"Zg==Zg==").is_none());
        assert!(base64_decode(b"Z!==").is_none());
    }
}
