//! Text drawn into [`RgbImage`]s with an embedded 5×7 bitmap font (plus one row for the
//! descenders of g, j, p, q, y), so plots carry labels on machines without any system font
//! (hospital servers, containers).
//!
//! Convention: the font covers printable ASCII (32–126); any other character is drawn as a
//! hollow box so a missing glyph is visible rather than silently dropped. A glyph cell is 5
//! pixels wide and 8 high (capitals and digits fill the top 7 rows, the 8th holds
//! descenders), advanced by 6 pixels (one pixel of spacing); `scale` repeats every font
//! pixel as a `scale × scale` block. Positions are the top-left corner of the text box, in
//! image pixels (column from the left, row from the top); pixels outside the image are
//! clipped.

use crate::outputs::quicklook::RgbImage;

/// Width of a glyph in font pixels.
pub const GLYPH_WIDTH: usize = 5;
/// Height of a glyph cell in font pixels (7 rows and a descender row).
pub const GLYPH_HEIGHT: usize = 8;
/// Horizontal distance between successive glyphs in font pixels.
pub const GLYPH_ADVANCE: usize = GLYPH_WIDTH + 1;

/// Columns of each glyph from ASCII 32 to 126, left to right; bit 0 is the top row, bit 7
/// the descender row. The classic 5×7 LCD font, public domain.
const FONT_5X7: [[u8; 5]; 95] = [
    [0x00, 0x00, 0x00, 0x00, 0x00], // ' '
    [0x00, 0x00, 0x5F, 0x00, 0x00], // !
    [0x00, 0x07, 0x00, 0x07, 0x00], // "
    [0x14, 0x7F, 0x14, 0x7F, 0x14], // #
    [0x24, 0x2A, 0x7F, 0x2A, 0x12], // $
    [0x23, 0x13, 0x08, 0x64, 0x62], // %
    [0x36, 0x49, 0x55, 0x22, 0x50], // &
    [0x00, 0x05, 0x03, 0x00, 0x00], // '
    [0x00, 0x1C, 0x22, 0x41, 0x00], // (
    [0x00, 0x41, 0x22, 0x1C, 0x00], // )
    [0x14, 0x08, 0x3E, 0x08, 0x14], // *
    [0x08, 0x08, 0x3E, 0x08, 0x08], // +
    [0x00, 0x50, 0x30, 0x00, 0x00], // ,
    [0x08, 0x08, 0x08, 0x08, 0x08], // -
    [0x00, 0x60, 0x60, 0x00, 0x00], // .
    [0x20, 0x10, 0x08, 0x04, 0x02], // /
    [0x3E, 0x51, 0x49, 0x45, 0x3E], // 0
    [0x00, 0x42, 0x7F, 0x40, 0x00], // 1
    [0x42, 0x61, 0x51, 0x49, 0x46], // 2
    [0x21, 0x41, 0x45, 0x4B, 0x31], // 3
    [0x18, 0x14, 0x12, 0x7F, 0x10], // 4
    [0x27, 0x45, 0x45, 0x45, 0x39], // 5
    [0x3C, 0x4A, 0x49, 0x49, 0x30], // 6
    [0x01, 0x71, 0x09, 0x05, 0x03], // 7
    [0x36, 0x49, 0x49, 0x49, 0x36], // 8
    [0x06, 0x49, 0x49, 0x29, 0x1E], // 9
    [0x00, 0x36, 0x36, 0x00, 0x00], // :
    [0x00, 0x56, 0x36, 0x00, 0x00], // ;
    [0x08, 0x14, 0x22, 0x41, 0x00], // <
    [0x14, 0x14, 0x14, 0x14, 0x14], // =
    [0x00, 0x41, 0x22, 0x14, 0x08], // >
    [0x02, 0x01, 0x51, 0x09, 0x06], // ?
    [0x32, 0x49, 0x79, 0x41, 0x3E], // @
    [0x7E, 0x11, 0x11, 0x11, 0x7E], // A
    [0x7F, 0x49, 0x49, 0x49, 0x36], // B
    [0x3E, 0x41, 0x41, 0x41, 0x22], // C
    [0x7F, 0x41, 0x41, 0x22, 0x1C], // D
    [0x7F, 0x49, 0x49, 0x49, 0x41], // E
    [0x7F, 0x09, 0x09, 0x09, 0x01], // F
    [0x3E, 0x41, 0x49, 0x49, 0x7A], // G
    [0x7F, 0x08, 0x08, 0x08, 0x7F], // H
    [0x00, 0x41, 0x7F, 0x41, 0x00], // I
    [0x20, 0x40, 0x41, 0x3F, 0x01], // J
    [0x7F, 0x08, 0x14, 0x22, 0x41], // K
    [0x7F, 0x40, 0x40, 0x40, 0x40], // L
    [0x7F, 0x02, 0x0C, 0x02, 0x7F], // M
    [0x7F, 0x04, 0x08, 0x10, 0x7F], // N
    [0x3E, 0x41, 0x41, 0x41, 0x3E], // O
    [0x7F, 0x09, 0x09, 0x09, 0x06], // P
    [0x3E, 0x41, 0x51, 0x21, 0x5E], // Q
    [0x7F, 0x09, 0x19, 0x29, 0x46], // R
    [0x46, 0x49, 0x49, 0x49, 0x31], // S
    [0x01, 0x01, 0x7F, 0x01, 0x01], // T
    [0x3F, 0x40, 0x40, 0x40, 0x3F], // U
    [0x1F, 0x20, 0x40, 0x20, 0x1F], // V
    [0x3F, 0x40, 0x38, 0x40, 0x3F], // W
    [0x63, 0x14, 0x08, 0x14, 0x63], // X
    [0x07, 0x08, 0x70, 0x08, 0x07], // Y
    [0x61, 0x51, 0x49, 0x45, 0x43], // Z
    [0x00, 0x7F, 0x41, 0x41, 0x00], // [
    [0x02, 0x04, 0x08, 0x10, 0x20], // backslash
    [0x00, 0x41, 0x41, 0x7F, 0x00], // ]
    [0x04, 0x02, 0x01, 0x02, 0x04], // ^
    [0x40, 0x40, 0x40, 0x40, 0x40], // _
    [0x00, 0x01, 0x02, 0x04, 0x00], // `
    [0x20, 0x54, 0x54, 0x54, 0x78], // a
    [0x7F, 0x48, 0x44, 0x44, 0x38], // b
    [0x38, 0x44, 0x44, 0x44, 0x20], // c
    [0x38, 0x44, 0x44, 0x48, 0x7F], // d
    [0x38, 0x54, 0x54, 0x54, 0x18], // e
    [0x08, 0x7E, 0x09, 0x01, 0x02], // f
    [0x18, 0xA4, 0xA4, 0xA4, 0x7C], // g
    [0x7F, 0x08, 0x04, 0x04, 0x78], // h
    [0x00, 0x44, 0x7D, 0x40, 0x00], // i
    [0x40, 0x80, 0x84, 0x7D, 0x00], // j
    [0x7F, 0x10, 0x28, 0x44, 0x00], // k
    [0x00, 0x41, 0x7F, 0x40, 0x00], // l
    [0x7C, 0x04, 0x18, 0x04, 0x78], // m
    [0x7C, 0x08, 0x04, 0x04, 0x78], // n
    [0x38, 0x44, 0x44, 0x44, 0x38], // o
    [0xFC, 0x24, 0x24, 0x24, 0x18], // p
    [0x18, 0x24, 0x24, 0x24, 0xFC], // q
    [0x7C, 0x08, 0x04, 0x04, 0x08], // r
    [0x48, 0x54, 0x54, 0x54, 0x20], // s
    [0x04, 0x3F, 0x44, 0x40, 0x20], // t
    [0x3C, 0x40, 0x40, 0x20, 0x7C], // u
    [0x1C, 0x20, 0x40, 0x20, 0x1C], // v
    [0x3C, 0x40, 0x30, 0x40, 0x3C], // w
    [0x44, 0x28, 0x10, 0x28, 0x44], // x
    [0x1C, 0xA0, 0xA0, 0xA0, 0x7C], // y
    [0x44, 0x64, 0x54, 0x4C, 0x44], // z
    [0x00, 0x08, 0x36, 0x41, 0x00], // {
    [0x00, 0x00, 0x7F, 0x00, 0x00], // |
    [0x00, 0x41, 0x36, 0x08, 0x00], // }
    [0x08, 0x04, 0x08, 0x10, 0x08], // ~
];

/// Drawn for characters outside printable ASCII: a hollow box.
const MISSING_GLYPH: [u8; 5] = [0x7F, 0x41, 0x41, 0x41, 0x7F];

/// The five font columns of `c` (bit 0 the top row).
pub fn glyph_columns(c: char) -> [u8; 5] {
    match c {
        ' '..='~' => FONT_5X7[c as usize - 32],
        _ => MISSING_GLYPH,
    }
}

/// Width in image pixels of `text` drawn at `scale` (no trailing spacing).
pub fn text_width_px(text: &str, scale: usize) -> usize {
    let n = text.chars().count();
    if n == 0 {
        0
    } else {
        (n * GLYPH_ADVANCE - 1) * scale
    }
}

/// Height in image pixels of one line of text at `scale`.
pub fn text_height_px(scale: usize) -> usize {
    GLYPH_HEIGHT * scale
}

/// Draws `text` with its top-left corner at (`left`, `top`) image pixels (which may lie off
/// the image: the text is clipped); `scale` ≥ 1 magnifies every font pixel.
pub fn draw_text(
    image: &mut RgbImage,
    text: &str,
    left: i64,
    top: i64,
    scale: usize,
    colour: [u8; 3],
) {
    let s = scale.max(1) as i64;
    for_each_font_pixel(text, |along, down| {
        fill_block(image, left + along * s, top + down * s, s, colour);
    });
}

/// Draws `text` turned a quarter turn anticlockwise so it reads upwards (a y-axis label),
/// the bottom-left corner of its box at (`left`, `bottom`) image pixels; clipped like
/// [`draw_text`].
pub fn draw_text_up(
    image: &mut RgbImage,
    text: &str,
    left: i64,
    bottom: i64,
    scale: usize,
    colour: [u8; 3],
) {
    let s = scale.max(1) as i64;
    for_each_font_pixel(text, |along, down| {
        fill_block(image, left + down * s, bottom - (along + 1) * s, s, colour);
    });
}

/// Calls `set(along, down)` for every lit font pixel of `text`, in font pixels from the
/// top-left of the unrotated text box.
fn for_each_font_pixel(text: &str, mut set: impl FnMut(i64, i64)) {
    for (n, c) in text.chars().enumerate() {
        for (gx, bits) in glyph_columns(c).iter().enumerate() {
            for gy in 0..GLYPH_HEIGHT {
                if bits >> gy & 1 == 1 {
                    set((n * GLYPH_ADVANCE + gx) as i64, gy as i64);
                }
            }
        }
    }
}

/// Fills the `side × side` block at (`x0`, `y0`), clipped to the image.
fn fill_block(image: &mut RgbImage, x0: i64, y0: i64, side: i64, colour: [u8; 3]) {
    let (width, height) = (image.width as i64, image.height as i64);
    for y in y0.max(0)..(y0 + side).min(height) {
        for x in x0.max(0)..(x0 + side).min(width) {
            let o = 3 * (y as usize * image.width + x as usize);
            image.pixels[o..o + 3].copy_from_slice(&colour);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blank(width: usize, height: usize) -> RgbImage {
        RgbImage {
            width,
            height,
            pixels: vec![0; 3 * width * height],
        }
    }

    /// Font pixels set in the image, read back as 5 columns of 7 bits from (left, top).
    fn read_glyph(image: &RgbImage, left: usize, top: usize, scale: usize) -> [u8; 5] {
        let mut cols = [0u8; 5];
        for (gx, col) in cols.iter_mut().enumerate() {
            for gy in 0..GLYPH_HEIGHT {
                if image.pixel(left + gx * scale, top + gy * scale)[0] == 255 {
                    *col |= 1 << gy;
                }
            }
        }
        cols
    }

    #[test]
    fn every_printable_glyph_is_distinct_and_fits_its_box() {
        for a in ' '..='~' {
            let g = glyph_columns(a);
            let descends = g.iter().any(|c| c & 0x80 != 0);
            assert_eq!(descends, "gjpqy".contains(a), "{a:?} descender");
            for b in ' '..='~' {
                if a != b {
                    assert_ne!(g, glyph_columns(b), "{a:?} and {b:?} look the same");
                }
            }
        }
        assert_eq!(glyph_columns('µ'), MISSING_GLYPH);
    }

    #[test]
    fn scaled_text_reproduces_the_glyphs_at_their_advance() {
        let mut image = blank(80, 30);
        draw_text(&mut image, "R5", 3, 4, 2, [255, 255, 255]);
        assert_eq!(read_glyph(&image, 3, 4, 2), glyph_columns('R'));
        assert_eq!(
            read_glyph(&image, 3 + 2 * GLYPH_ADVANCE, 4, 2),
            glyph_columns('5')
        );
        let lit = image.pixels.chunks_exact(3).filter(|p| p[0] == 255).count();
        let bits: u32 = ['R', '5']
            .iter()
            .flat_map(|&c| glyph_columns(c))
            .map(|c| c.count_ones())
            .sum();
        assert_eq!(lit, 4 * bits as usize, "each font pixel is a 2×2 block");
        assert_eq!(text_width_px("R5", 2), 22);
    }

    #[test]
    fn text_off_the_image_is_clipped_not_a_panic() {
        let mut image = blank(10, 5);
        draw_text(&mut image, "clipped text", -7, -3, 3, [255, 0, 0]);
        draw_text(&mut image, "x", 9, 4, 1, [255, 0, 0]);
        assert!(image.pixels.chunks_exact(3).any(|p| p[0] == 255));
    }

    #[test]
    fn upward_text_is_the_horizontal_text_turned_anticlockwise() {
        let mut flat = blank(40, 12);
        let mut up = blank(12, 40);
        draw_text(&mut flat, "mL", 0, 0, 1, [255, 255, 255]);
        draw_text_up(&mut up, "mL", 0, 40, 1, [255, 255, 255]);
        for row in 0..12 {
            for col in 0..40 {
                // (col, row) of the flat text lands at (row, 39 − col) once turned.
                assert_eq!(
                    flat.pixel(col, row),
                    up.pixel(row, 39 - col),
                    "({col}, {row})"
                );
            }
        }
        assert!(flat.pixels.contains(&255));
    }
}
