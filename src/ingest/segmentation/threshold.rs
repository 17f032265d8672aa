//! Otsu's air/tissue threshold of the HU histogram inside the body.

use rayon::prelude::*;

/// Otsu's threshold of the HU histogram (1 HU bins, −1024…+1023) of the body voxels.
pub(super) fn otsu_threshold_hu(hu: &[f32], body: &[u8]) -> f32 {
    const LO: f32 = -1024.0;
    const BINS: usize = 2048;
    let hist = hu
        .par_chunks(1 << 16)
        .zip(body.par_chunks(1 << 16))
        .fold(
            || vec![0u64; BINS],
            |mut h, (c, b)| {
                for (&v, &m) in c.iter().zip(b) {
                    if m != 0 && v.is_finite() {
                        h[((v - LO).clamp(0.0, (BINS - 1) as f32)) as usize] += 1;
                    }
                }
                h
            },
        )
        .reduce(
            || vec![0u64; BINS],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                a
            },
        );
    let total: f64 = hist.iter().sum::<u64>() as f64;
    let sum_all: f64 = hist
        .iter()
        .enumerate()
        .map(|(i, &n)| i as f64 * n as f64)
        .sum();
    // Ties (an empty gap between two modes, as in synthetic images) resolve to the middle
    // of the gap rather than its first bin.
    let (mut w0, mut sum0, mut best, mut best_t, mut best_last) = (0.0, 0.0, -1.0, 0usize, 0usize);
    for (t, &n) in hist.iter().enumerate() {
        w0 += n as f64;
        sum0 += t as f64 * n as f64;
        let w1 = total - w0;
        if w0 == 0.0 || w1 == 0.0 {
            continue;
        }
        let (m0, m1) = (sum0 / w0, (sum_all - sum0) / w1);
        let between = w0 * w1 * (m0 - m1) * (m0 - m1);
        if between > best * (1.0 + 1e-12) {
            best = between;
            best_t = t;
            best_last = t;
        } else if between >= best * (1.0 - 1e-12) {
            best_last = t;
        }
    }
    LO + 0.5 * (best_t + best_last) as f32 + 1.0
}
