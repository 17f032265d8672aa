//! Stored samples of any supported type and byte order → caller values, in parallel.

use rayon::prelude::*;

use super::header::DataType;
use super::image::Image;
use super::CHUNK_VOXELS;

/// A stored sample type: its width and its value as f64.
trait RawSample {
    const BYTES: usize;
    fn value(bytes: &[u8], big_endian: bool) -> f64;
}

macro_rules! raw_sample {
    ($($t:ty),*) => {$(
        impl RawSample for $t {
            const BYTES: usize = std::mem::size_of::<$t>();
            #[inline]
            fn value(bytes: &[u8], big_endian: bool) -> f64 {
                let mut a = [0u8; std::mem::size_of::<$t>()];
                a.copy_from_slice(bytes);
                (if big_endian { <$t>::from_be_bytes(a) } else { <$t>::from_le_bytes(a) }) as f64
            }
        }
    )*};
}
raw_sample!(u8, i8, i16, u16, i32, u32, i64, u64, f32, f64);

/// Converts every stored sample of `image` through `convert` into `out` (same length).
pub(super) fn decode_samples<T: Send, F: Fn(f64) -> T + Sync>(
    image: &Image,
    out: &mut [T],
    convert: F,
) {
    decode_typed_dispatch(
        image.datatype,
        &image.voxels,
        image.big_endian,
        out,
        convert,
    );
}

/// Picks the sample type of `datatype` for [`decode_typed`].
pub(super) fn decode_typed_dispatch<T: Send, F: Fn(f64) -> T + Sync>(
    datatype: DataType,
    raw: &[u8],
    big_endian: bool,
    out: &mut [T],
    convert: F,
) {
    match datatype {
        DataType::U8 => decode_typed::<u8, _, _>(raw, big_endian, out, convert),
        DataType::I8 => decode_typed::<i8, _, _>(raw, big_endian, out, convert),
        DataType::I16 => decode_typed::<i16, _, _>(raw, big_endian, out, convert),
        DataType::U16 => decode_typed::<u16, _, _>(raw, big_endian, out, convert),
        DataType::I32 => decode_typed::<i32, _, _>(raw, big_endian, out, convert),
        DataType::U32 => decode_typed::<u32, _, _>(raw, big_endian, out, convert),
        DataType::I64 => decode_typed::<i64, _, _>(raw, big_endian, out, convert),
        DataType::U64 => decode_typed::<u64, _, _>(raw, big_endian, out, convert),
        DataType::F32 => decode_typed::<f32, _, _>(raw, big_endian, out, convert),
        DataType::F64 => decode_typed::<f64, _, _>(raw, big_endian, out, convert),
    }
}

/// Converts `raw` samples of type `S` in parallel chunks.
fn decode_typed<S: RawSample, T: Send, F: Fn(f64) -> T + Sync>(
    raw: &[u8],
    big_endian: bool,
    out: &mut [T],
    convert: F,
) {
    out.par_chunks_mut(CHUNK_VOXELS)
        .zip(raw.par_chunks(CHUNK_VOXELS * S::BYTES))
        .for_each(|(dst, src)| {
            for (d, s) in dst.iter_mut().zip(src.chunks_exact(S::BYTES)) {
                *d = convert(S::value(s, big_endian));
            }
        });
}
