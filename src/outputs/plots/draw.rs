//! Raster primitives of the plots: rectangles, anti-alias-free segments, arrows, disks and
//! rings on an [`RgbImage`], clipped to the image.

use crate::outputs::quicklook::RgbImage;

/// A `width` × `height` image filled with `colour`.
pub(super) fn canvas(width: usize, height: usize, colour: [u8; 3]) -> RgbImage {
    RgbImage {
        width,
        height,
        pixels: colour.repeat(width * height),
    }
}

/// Fills the `w` × `h` rectangle at (`left`, `top`), clipped to the image.
pub(super) fn fill_rect(
    image: &mut RgbImage,
    left: i64,
    top: i64,
    w: i64,
    h: i64,
    colour: [u8; 3],
) {
    let x0 = left.max(0);
    let x1 = (left + w).min(image.width as i64);
    for y in top.max(0)..(top + h).min(image.height as i64) {
        for x in x0..x1 {
            put(image, x, y, colour);
        }
    }
}

/// The one-pixel border of the `w` × `h` rectangle at (`left`, `top`).
pub(super) fn outline_rect(
    image: &mut RgbImage,
    left: i64,
    top: i64,
    w: i64,
    h: i64,
    colour: [u8; 3],
) {
    fill_rect(image, left, top, w, 1, colour);
    fill_rect(image, left, top + h - 1, w, 1, colour);
    fill_rect(image, left, top, 1, h, colour);
    fill_rect(image, left + w - 1, top, 1, h, colour);
}

/// Sets one pixel; nothing outside the image.
#[inline]
fn put(image: &mut RgbImage, x: i64, y: i64, colour: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as usize) < image.width && (y as usize) < image.height {
        let o = 3 * (y as usize * image.width + x as usize);
        image.pixels[o..o + 3].copy_from_slice(&colour);
    }
}

/// Pixels whose centre lies within `radius` of the segment a–b.
pub(super) fn draw_segment(
    image: &mut RgbImage,
    a: [f64; 2],
    b: [f64; 2],
    radius: f64,
    colour: [u8; 3],
) {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len2 = dx * dx + dy * dy;
    let x0 = (a[0].min(b[0]) - radius).floor() as i64;
    let x1 = (a[0].max(b[0]) + radius).ceil() as i64;
    let y0 = (a[1].min(b[1]) - radius).floor() as i64;
    let y1 = (a[1].max(b[1]) + radius).ceil() as i64;
    let x0 = x0.max(0);
    let y0 = y0.max(0);
    let x1 = x1.min(image.width as i64 - 1);
    let y1 = y1.min(image.height as i64 - 1);
    for y in y0..=y1 {
        for x in x0..=x1 {
            let (px, py) = (x as f64 - a[0], y as f64 - a[1]);
            let t = if len2 > 0.0 {
                ((px * dx + py * dy) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let (ex, ey) = (px - t * dx, py - t * dy);
            if ex * ex + ey * ey <= radius * radius {
                put(image, x, y, colour);
            }
        }
    }
}

/// Segments between consecutive points, `radius` thick.
pub(super) fn draw_polyline(
    image: &mut RgbImage,
    points: &[[f64; 2]],
    radius: f64,
    colour: [u8; 3],
) {
    for w in points.windows(2) {
        draw_segment(image, w[0], w[1], radius, colour);
    }
}

/// Shaft from tail to head and two barbs at the head, all `radius` thick.
pub(super) fn draw_arrow(
    image: &mut RgbImage,
    tail: [f64; 2],
    head: [f64; 2],
    radius: f64,
    colour: [u8; 3],
) {
    let (dx, dy) = (head[0] - tail[0], head[1] - tail[1]);
    let len = dx.hypot(dy);
    if len == 0.0 {
        return;
    }
    let (ux, uy) = (dx / len, dy / len);
    let barb = (0.35 * len).clamp(3.0, 8.0);
    let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
    draw_segment(image, tail, head, radius, colour);
    for side in [-1.0, 1.0] {
        // The reversed direction turned by ±30°.
        let bx = -(ux * c - side * uy * s);
        let by = -(uy * c + side * ux * s);
        draw_segment(
            image,
            head,
            [head[0] + barb * bx, head[1] + barb * by],
            radius,
            colour,
        );
    }
}

/// Pixels whose centre is within `radius` of (cx, cy).
pub(super) fn fill_disk(image: &mut RgbImage, cx: f64, cy: f64, radius: f64, colour: [u8; 3]) {
    fill_ring(image, cx, cy, radius, -1.0, colour);
}

/// Pixels whose centre is within `outer` of (cx, cy) and farther than `inner`.
pub(super) fn fill_ring(
    image: &mut RgbImage,
    cx: f64,
    cy: f64,
    outer: f64,
    inner: f64,
    colour: [u8; 3],
) {
    let inner2 = if inner > 0.0 { inner * inner } else { -1.0 };
    for y in (cy - outer).floor() as i64..=(cy + outer).ceil() as i64 {
        for x in (cx - outer).floor() as i64..=(cx + outer).ceil() as i64 {
            let r2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
            if r2 <= outer * outer && r2 > inner2 {
                put(image, x, y, colour);
            }
        }
    }
}
