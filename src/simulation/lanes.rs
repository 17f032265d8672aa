//! Four elements per SIMD lane: the lane type and element batching shared by the force kernel
//! and the multigrid operator products.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// Elements evaluated together, one per SIMD lane (4 × f64 fills an AVX2 register).
pub const LANES: usize = 4;

/// One f64 per lane; plain arrays so that LLVM vectorises every operation.
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C, align(32))]
pub(crate) struct Lanes(pub(crate) [f64; LANES]);

impl Lanes {
    pub(crate) const ZERO: Lanes = Lanes([0.0; LANES]);

    #[inline(always)]
    pub(crate) fn splat(v: f64) -> Self {
        Lanes([v; LANES])
    }

    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        let mut r = self;
        for v in &mut r.0 {
            *v = v.sqrt();
        }
        r
    }
}

macro_rules! lane_op {
    ($trait:ident, $method:ident, $op:tt) => {
        impl $trait for Lanes {
            type Output = Lanes;
            #[inline(always)]
            fn $method(self, rhs: Lanes) -> Lanes {
                let mut r = self;
                for i in 0..LANES {
                    r.0[i] = self.0[i] $op rhs.0[i];
                }
                r
            }
        }
    };
}
lane_op!(Add, add, +);
lane_op!(Sub, sub, -);
lane_op!(Mul, mul, *);
lane_op!(Div, div, /);

impl Neg for Lanes {
    type Output = Lanes;
    #[inline(always)]
    fn neg(self) -> Lanes {
        let mut r = self;
        for v in &mut r.0 {
            *v = -*v;
        }
        r
    }
}

/// A 3-vector per lane.
pub(crate) type LaneV3 = [Lanes; 3];

#[inline(always)]
pub(crate) fn sub3(a: &LaneV3, b: &LaneV3) -> LaneV3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline(always)]
pub(crate) fn add3(a: &LaneV3, b: &LaneV3) -> LaneV3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

#[inline(always)]
pub(crate) fn scale3(a: &LaneV3, s: Lanes) -> LaneV3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

#[inline(always)]
pub(crate) fn dot3(a: &LaneV3, b: &LaneV3) -> Lanes {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a × b`, component by component as nalgebra's `cross` computes it.
#[inline(always)]
pub(crate) fn cross3(a: &LaneV3, b: &LaneV3) -> LaneV3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `a / |a|` as nalgebra's `normalize` computes it (norm, then one division per component).
#[inline(always)]
pub(crate) fn normalize3(a: &LaneV3) -> LaneV3 {
    let n = dot3(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

/// A source of element indices handed out [`LANES`] at a time.
pub(crate) trait ElementSource {
    /// Fills `ids` with the next batch (the last one padded by repeating its last element)
    /// and returns how many are real, or `None` when exhausted.
    fn next_batch(&mut self, ids: &mut [u32; LANES]) -> Option<usize>;
}

impl ElementSource for std::ops::Range<u32> {
    #[inline(always)]
    fn next_batch(&mut self, ids: &mut [u32; LANES]) -> Option<usize> {
        if self.start >= self.end {
            return None;
        }
        let count = ((self.end - self.start) as usize).min(LANES);
        for (l, id) in ids.iter_mut().enumerate() {
            *id = self.start + l.min(count - 1) as u32;
        }
        self.start += count as u32;
        Some(count)
    }
}

impl ElementSource for std::slice::Iter<'_, u32> {
    #[inline(always)]
    fn next_batch(&mut self, ids: &mut [u32; LANES]) -> Option<usize> {
        let rest = self.as_slice();
        if rest.is_empty() {
            return None;
        }
        let count = rest.len().min(LANES);
        for (l, id) in ids.iter_mut().enumerate() {
            *id = rest[l.min(count - 1)];
        }
        *self = rest[count..].iter();
        Some(count)
    }
}
