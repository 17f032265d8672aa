//! Vector aliases shared by the mechanical core and its callers.

use nalgebra::Vector3;

/// A 3-vector of `f64`; the unit and frame (metres or millimetres, LPS) are the caller's and
/// are named on the value (`_m`, `_mm`).
pub type V3 = Vector3<f64>;

/// Median of `values` sorted in place (`total_cmp` order): the middle value, or the mean of
/// the middle two for an even count; `None` for no values.
pub fn median_sorting(values: &mut [f64]) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(values[n / 2]),
        _ => Some(0.5 * (values[n / 2 - 1] + values[n / 2])),
    }
}

#[cfg(test)]
mod tests {
    use super::median_sorting;

    #[test]
    fn median_of_odd_even_and_no_values() {
        assert_eq!(median_sorting(&mut [3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median_sorting(&mut [4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(median_sorting(&mut []), None);
    }
}
